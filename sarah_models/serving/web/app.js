// The sarah-serve browser page: streams the user's position and both voices to the server in
// chunks of 4 frames (protocol v1, docs/protocol.md) and draws the agent frames it answers with.
"use strict";

const state = {
  ws: null, ready: null, seq: 0, waiting: false, running: false,
  user: { x: 0.0, z: 1.6 },              // the user's floor position (metres)
  frames: [],                            // joint positions (55 x 3 Float32Array) to draw
  framesReceived: 0, framesDrawn: 0, latency: 0, gazeScore: NaN,
  agentWave: null, userWave: null, sampleOffset: 0, mic: null, micBuffer: [],
  keys: new Set(), started: 0, trail: [],
};
window.sarah = state; // for scripted checks (tests drive this page in headless Chromium)

const $ = (id) => document.getElementById(id);
const RATE = 48000;

async function decodeTo48k(file) {
  if (!file) return null;
  const ctx = new AudioContext();
  const decoded = await ctx.decodeAudioData(await file.arrayBuffer());
  const frames = Math.ceil(decoded.duration * RATE);
  const offline = new OfflineAudioContext(1, frames, RATE);
  const source = offline.createBufferSource();
  source.buffer = decoded;
  source.connect(offline.destination);
  source.start();
  const rendered = await offline.startRendering();
  ctx.close();
  return { samples: rendered.getChannelData(0), buffer: decoded };
}

function play(wave) {
  if (!wave) return;
  const ctx = new AudioContext();
  const source = ctx.createBufferSource();
  source.buffer = wave.buffer;
  source.connect(ctx.destination);
  source.start();
}

async function startMic() {
  const stream = await navigator.mediaDevices.getUserMedia({ audio: true });
  const ctx = new AudioContext({ sampleRate: RATE });
  const source = ctx.createMediaStreamSource(stream);
  const node = ctx.createScriptProcessor(4096, 1, 1);
  node.onaudioprocess = (e) => state.micBuffer.push(new Float32Array(e.inputBuffer.getChannelData(0)));
  source.connect(node);
  node.connect(ctx.destination);
  return { stream, ctx };
}

function takeMic(n) {
  const out = new Float32Array(n);
  let filled = 0;
  while (filled < n && state.micBuffer.length) {
    const head = state.micBuffer[0];
    const take = Math.min(n - filled, head.length);
    out.set(head.subarray(0, take), filled);
    filled += take;
    if (take === head.length) state.micBuffer.shift(); else state.micBuffer[0] = head.subarray(take);
  }
  return out;
}

function slice(wave, start, n) {
  const out = new Float32Array(n);
  if (wave) out.set(wave.samples.subarray(start, Math.min(start + n, wave.samples.length)));
  return out;
}

function packChunk(header, a, b) {
  const head = new TextEncoder().encode(JSON.stringify(header));
  const buf = new ArrayBuffer(4 + head.length + a.byteLength + b.byteLength);
  const view = new DataView(buf);
  view.setUint32(0, head.length, true);
  new Uint8Array(buf, 4, head.length).set(head);
  new Uint8Array(buf, 4 + head.length, a.byteLength).set(new Uint8Array(a.buffer));
  new Uint8Array(buf, 4 + head.length + a.byteLength).set(new Uint8Array(b.buffer));
  return buf;
}

function unpackFrames(buf) {
  const view = new DataView(buf);
  const size = view.getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, size)));
  let offset = 4 + size;
  const arrays = {};
  for (const spec of header.arrays) {
    const count = spec.shape.reduce((p, q) => p * q, 1);
    arrays[spec.name] = new Float32Array(buf.slice(offset, offset + 4 * count));
    offset += 4 * count;
  }
  return { header, arrays };
}

function sendChunk() {
  if (!state.running || state.waiting || !state.ready) return;
  // Real time: never ahead of the clock (4 frames = 133 ms of audio per chunk).
  const due = (performance.now() - state.started) / 1000 * 30;
  if (state.seq * 4 > due) return;
  const frames = 4, n = frames * state.ready.samples_per_frame;
  const head = [];
  for (let i = 0; i < frames; i++) head.push([state.user.x, state.user.z]);
  const a = slice(state.agentWave, state.sampleOffset, n);
  const b = state.mic ? takeMic(n) : slice(state.userWave, state.sampleOffset, n);
  state.sampleOffset += n;
  state.waiting = true;
  state.ws.send(packChunk({ type: "chunk", seq: state.seq++, frames, head }, a, b));
}

function onMessage(event) {
  if (typeof event.data === "string") {
    const msg = JSON.parse(event.data);
    if (msg.type === "ready") { state.ready = msg; state.started = performance.now(); }
    else if (msg.type === "error") { $("status").textContent = `server error ${msg.code}: ${msg.message}`; state.waiting = false; }
    return;
  }
  const { header, arrays } = unpackFrames(event.data);
  const pos = arrays.joint_positions;
  for (let f = 0; f < header.frames; f++) state.frames.push(pos.subarray(f * 165, (f + 1) * 165));
  if (state.frames.length > 30) state.frames.splice(0, state.frames.length - 30);
  state.framesReceived += header.frames;
  state.latency = header.latency_ms;
  if (header.gaze_score.length) state.gazeScore = header.gaze_score[header.gaze_score.length - 1];
  state.waiting = false;
}

async function start() {
  $("start").disabled = true;
  state.agentWave = await decodeTo48k($("agent-file").files[0]);
  state.userWave = await decodeTo48k($("user-file").files[0]);
  if ($("mic").checked) state.mic = await startMic();
  const url = `ws://${location.host}/`;
  state.ws = new WebSocket(url);
  state.ws.binaryType = "arraybuffer";
  state.ws.onmessage = onMessage;
  state.ws.onclose = (e) => { state.running = false; $("status").textContent = `closed (${e.code} ${e.reason})`; $("start").disabled = false; $("stop").disabled = true; };
  state.ws.onopen = () => {
    state.ws.send(JSON.stringify({ type: "open", version: 1, gaze: gazeValue(), audio_format: "f32le" }));
    state.running = true; state.seq = 0; state.sampleOffset = 0;
    play(state.agentWave); if (!state.mic) play(state.userWave);
    $("stop").disabled = false;
  };
}

function stop() {
  state.running = false;
  if (state.ws) state.ws.send(JSON.stringify({ type: "close" }));
}

function gazeValue() { return $("gaze-off").checked ? null : parseFloat($("gaze").value); }

function sendGaze() {
  $("gaze-value").textContent = $("gaze-off").checked ? "none" : parseFloat($("gaze").value).toFixed(2);
  if (state.ws && state.ws.readyState === 1 && state.ready) state.ws.send(JSON.stringify({ type: "gaze", value: gazeValue() }));
}

function moveUser(dt) {
  const speed = 1.2; // m/s, a walk
  let dx = 0, dz = 0;
  if (state.keys.has("a") || state.keys.has("arrowleft")) dx -= 1;
  if (state.keys.has("d") || state.keys.has("arrowright")) dx += 1;
  if (state.keys.has("w") || state.keys.has("arrowup")) dz += 1;
  if (state.keys.has("s") || state.keys.has("arrowdown")) dz -= 1;
  state.user.x += dx * speed * dt;
  state.user.z += dz * speed * dt;
}

function drawSkeleton(ctx, joints, project, color) {
  const parents = state.ready ? state.ready.joint_parents : [];
  ctx.strokeStyle = color; ctx.lineWidth = 2;
  for (let j = 1; j < parents.length; j++) {
    const p = parents[j];
    const [ax, ay] = project(joints, j), [bx, by] = project(joints, p);
    ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke();
  }
}

function draw() {
  const top = $("top").getContext("2d"), front = $("front").getContext("2d");
  const W = 520, H = 520, scale = 80;
  top.clearRect(0, 0, W, H); front.clearRect(0, 0, 360, H);
  const latest = state.frames.length ? state.frames[state.frames.length - 1] : null;
  const cx = latest ? latest[0] : 0, cz = latest ? latest[2] : 0;
  const toTop = (x, z) => [W / 2 + (x - cx) * scale, H / 2 - (z - cz) * scale];
  top.strokeStyle = "#eee";
  for (let g = -3; g <= 3; g++) {
    const [x0, y0] = toTop(Math.round(cx) + g, cz - 4), [x1, y1] = toTop(Math.round(cx) + g, cz + 4);
    top.beginPath(); top.moveTo(x0, y0); top.lineTo(x1, y1); top.stroke();
    const [u0, v0] = toTop(cx - 4, Math.round(cz) + g), [u1, v1] = toTop(cx + 4, Math.round(cz) + g);
    top.beginPath(); top.moveTo(u0, v0); top.lineTo(u1, v1); top.stroke();
  }
  const [ux, uy] = toTop(state.user.x, state.user.z);
  top.fillStyle = "#d33"; top.beginPath(); top.arc(ux, uy, 9, 0, 2 * Math.PI); top.fill();
  if (latest) {
    drawSkeleton(top, latest, (p, j) => toTop(p[3 * j], p[3 * j + 2]), "#246");
    const head = 15, nose = [latest[3 * head], latest[3 * head + 2]];
    const [hx, hy] = toTop(nose[0], nose[1]);
    top.fillStyle = "#246"; top.beginPath(); top.arc(hx, hy, 5, 0, 2 * Math.PI); top.fill();
    drawSkeleton(front, latest, (p, j) => [180 + (p[3 * j] - cx) * 160, 480 - p[3 * j + 1] * 160], "#246");
    state.framesDrawn += 1;
  }
  $("status").textContent =
    `${state.running ? "streaming" : "stopped"}  frames received ${state.framesReceived}  drawn ${state.framesDrawn}` +
    `  server latency ${state.latency.toFixed(1)} ms  gaze score ${isNaN(state.gazeScore) ? "-" : state.gazeScore.toFixed(2)}` +
    `  user (${state.user.x.toFixed(2)}, ${state.user.z.toFixed(2)})`;
}

let last = performance.now();
function tick(now) {
  moveUser((now - last) / 1000);
  last = now;
  sendChunk();
  draw();
  requestAnimationFrame(tick);
}

document.addEventListener("keydown", (e) => state.keys.add(e.key.toLowerCase()));
document.addEventListener("keyup", (e) => state.keys.delete(e.key.toLowerCase()));
$("top").addEventListener("click", (e) => {
  const r = e.target.getBoundingClientRect();
  const latest = state.frames.length ? state.frames[state.frames.length - 1] : null;
  const cx = latest ? latest[0] : 0, cz = latest ? latest[2] : 0;
  state.user.x = cx + (e.clientX - r.left - 260) / 80;
  state.user.z = cz - (e.clientY - r.top - 260) / 80;
});
$("start").addEventListener("click", start);
$("stop").addEventListener("click", stop);
$("gaze").addEventListener("input", sendGaze);
$("gaze-off").addEventListener("change", sendGaze);
requestAnimationFrame(tick);
