"""``sarah-serve``: a WebSocket server streaming the agent's motion, and the browser page at ``/``.

One ``LiveSession`` (a ``StreamingSession`` and its own generator state) per connection; the
models are loaded once and shared read-only. Compute runs in a small thread pool so the event
loop keeps serving other connections, in rounds: the chunks that arrived while a round ran are
generated together in the next one (``push_together``: one flow solve per round, each network
call serving every session's rows, so its fixed cost is paid once per round rather than once per
session; a session's motion is the same as alone). Each connection is handled in order (receive a chunk,
generate, send its frames), so nothing queues without bound: websockets stops reading a socket
whose ``max_queue`` messages are waiting, and a send to a client that stops reading waits at most
``send_timeout`` seconds before the connection is closed with a reason.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np

from sarah_data import icosahedron
from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, JOINT_NAMES, JOINT_PARENTS, SAMPLES_PER_FRAME
from sarah_data.skeleton import MotionLayout

from ..accel.threads import ThreadPolicy, stream_probe
from ..config import StreamConfig
from ..generation.inputs import agent_anchor, make_extractor
from ..generation.outputs import head_gaze
from ..sampling.decoding import body_bone_lengths
from ..sampling.stream import StreamingGenerator, StreamingSession, push_together
from .protocol import (AUDIO_FORMATS, MAX_CHUNK_FRAMES, VERSION, Chunk, OpenRequest, ProtocolError,
                       pack, parse_chunk, parse_gaze, parse_open, parse_text)

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
WEB_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
             "/index.html": ("index.html", "text/html; charset=utf-8"),
             "/app.js": ("app.js", "text/javascript; charset=utf-8")}


@dataclass
class ServeConfig:
    host: str = "127.0.0.1"
    port: int = 8765
    max_sessions: int = 16
    workers: int = 1  # compute threads; each step already uses every intra-op thread
    send_timeout: float = 10.0  # seconds a send may wait on a client that does not read
    max_message_bytes: int = 4 * 1024 * 1024  # a chunk of MAX_CHUNK_FRAMES f32 frames fits
    max_queue: int = 4  # messages read ahead per connection before its socket is left unread
    threads: int | None = None  # intra-op threads per compute thread (None: accel.ThreadPolicy)
    # How long a round waits for the other open sessions' chunks before it starts without them
    # (clients on one clock send together; the first to arrive must not leave alone).
    gather_ms: float = 5.0


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_HOSTS:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class LiveSession:
    """One client's stream: settings from its open message, the generator's state, counters."""

    def __init__(self, models, request: OpenRequest, defaults: StreamConfig, extractor,
                 body=None):
        config = replace(defaults,
                         gaze=request.gaze if request.gaze_given else defaults.gaze,
                         steps=request.steps or defaults.steps,
                         cfg_scale=defaults.cfg_scale if request.cfg_scale is None else request.cfg_scale,
                         seed=defaults.seed if request.seed is None else request.seed)
        self.config = config
        self.request = request
        # A server with a body (--body-model) animates that body: the motion is decoded on its
        # bones, the ones its SMPL-X parameters pose, whether or not this client asks for them.
        bones = None if body is None else body_bone_lengths(models.vae, body.rest_joints)
        generator = StreamingGenerator(models.vae, models.flow, models.normalizer, config,
                                       agent_anchor(request.agent_start), bones)
        self.stream = StreamingSession(generator, extractor, keep_features=False)
        self.layout = MotionLayout.from_width(generator.motion_dim)
        self.body = body  # sarah_data.export BodyShape for SMPL-X parameters, when requested
        self.expected_seq = 0
        self.frames_out = 0
        self._heads = np.zeros((0, 2), np.float32)  # user positions of frames not yet generated

    def push(self, chunk: Chunk) -> tuple[dict, list[np.ndarray]]:
        """Generate for one chunk; the frames message's header and arrays."""
        return self.frames_message(chunk, self.stream.push(*self.inputs(chunk)))

    @staticmethod
    def inputs(chunk: Chunk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What ``StreamingSession.push`` takes from a chunk."""
        return chunk.head, chunk.agent_audio, chunk.user_audio

    def frames_message(self, chunk: Chunk, motion: np.ndarray) -> tuple[dict, list[np.ndarray]]:
        """The frames message (header and arrays) for the motion generated from ``chunk``."""
        positions, rotations = icosahedron.decode(self.layout.split(motion)[0])
        pending = np.concatenate([self._heads, chunk.head])
        heads, self._heads = pending[:len(motion)], pending[len(motion):]
        gaze = head_gaze(positions, rotations, heads) if len(motion) else np.zeros(0, np.float32)
        parts = {"motion": motion.astype(np.float32),
                 "joint_positions": positions.astype(np.float32),
                 "joint_rotations": rotations.astype(np.float32)}
        if self.request.features:
            parts["agent_features"] = self.stream.last_features["agent"]
            parts["user_features"] = self.stream.last_features["user"]
        if self.request.smplx and len(motion):
            from sarah_data.export import ExportMotion, smplx_parameters

            live = ExportMotion("live", positions, rotations, self.body)
            params = smplx_parameters(live, live.fit())
            parts["smplx_poses"] = params["poses"].astype(np.float32)
            parts["smplx_trans"] = params["trans"].astype(np.float32)
        header = {"type": "frames", "seq": chunk.seq, "first_frame": self.frames_out,
                  "frames": int(len(motion)), "gaze_score": [float(g) for g in gaze],
                  "gaze_target": self.stream.generator.gaze,
                  "arrays": [{"name": k, "shape": list(v.shape), "dtype": "<f4"} for k, v in parts.items()]}
        self.frames_out += len(motion)
        return header, list(parts.values())


class LiveServer:
    def __init__(self, models, config: ServeConfig, defaults: StreamConfig = StreamConfig(),
                 body=None):
        self.models = models
        self.body = body  # BodyShape (neutral betas of --body-model) for SMPL-X output, or None
        self.config = config
        self.defaults = defaults
        self.executor = ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="sarah-serve")
        self.threads = None
        if next(models.flow.parameters()).device.type == "cpu":
            self.threads = ThreadPolicy(config.threads)
            # Timed where chunks will run: a compute thread's kernels, not this thread's.
            self.executor.submit(self.threads.calibrate, stream_probe(models, defaults)).result()
        self.sessions = 0
        self.stride = models.vae.stride
        # Chunks waiting for the next round, and rounds running (at most one per worker).
        self.waiting: list[tuple[LiveSession, Chunk, asyncio.Future]] = []
        self.rounds_running = 0
        self.open_streams = 0  # connections with an open session
        self.gathering: asyncio.TimerHandle | None = None  # a round waiting for more chunks
        self.rounds_run = self.chunks_run = 0  # how well rounds batch: chunks per round
        self.round_tasks: set[asyncio.Task] = set()  # referenced, so none is collected mid-round
        make_extractor(models.features)  # fail at start, not at the first connection

    def ready_message(self) -> str:
        flow = self.models.flow
        return json.dumps({
            "type": "ready", "version": VERSION, "fps": FPS, "stride": self.stride,
            "sample_rate": AUDIO_SAMPLE_RATE, "samples_per_frame": SAMPLES_PER_FRAME,
            "audio_formats": sorted(AUDIO_FORMATS), "max_chunk_frames": MAX_CHUNK_FRAMES,
            "motion_width": int(self.models.vae.motion_dim), "audio_dim": int(flow.audio_dim),
            "features": self.models.features, "joint_names": list(JOINT_NAMES),
            "joint_parents": list(JOINT_PARENTS),
            "smplx": None if self.body is None else {
                "betas": [float(b) for b in self.body.betas], "gender": self.body.gender,
                "source": self.body.source, "flat_hand_mean": True, "up_axis": "y"}})

    async def _send(self, ws, data) -> None:
        try:
            await asyncio.wait_for(ws.send(data), self.config.send_timeout)
        except asyncio.TimeoutError:
            await ws.close(1008, f"client not reading: a send waited {self.config.send_timeout:g} s")
            raise

    async def handler(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        if self.sessions >= self.config.max_sessions:
            await ws.close(1013, f"server full ({self.config.max_sessions} sessions); try again later")
            return
        self.sessions += 1
        session: LiveSession | None = None
        try:
            async for message in ws:
                try:
                    if isinstance(message, str):
                        request = parse_text(message)
                        kind = request["type"]
                        if kind == "open":
                            if session is not None:
                                raise ProtocolError("already_open", "this connection already has a session")
                            opened = parse_open(request)
                            if opened.smplx and self.body is None:
                                raise ProtocolError("bad_open", "smplx output needs the server started "
                                                                "with --body-model (a SMPL-X .npz)")
                            extractor = make_extractor(self.models.features)
                            session = LiveSession(self.models, opened, self.defaults, extractor, self.body)
                            self.open_streams += 1
                            await self._send(ws, self.ready_message())
                        elif kind == "gaze":
                            if session is None:
                                raise ProtocolError("not_open", "send an 'open' message first")
                            value = parse_gaze(request)
                            session.stream.generator.set_gaze(value)
                            await self._send(ws, json.dumps({"type": "gaze_set", "value": value,
                                                             "from_frame": session.frames_out}))
                        elif kind == "close":
                            await ws.close(1000, "closed by the client")
                            return
                        else:
                            raise ProtocolError("unknown_type", f"unknown message type {kind!r}; "
                                                                f"text messages are open, gaze, close")
                    else:
                        if session is None:
                            raise ProtocolError("not_open", "send an 'open' message first")
                        chunk = parse_chunk(message, session.request.audio_format, self.stride)
                        if chunk.seq != session.expected_seq:
                            raise ProtocolError("bad_seq", f"chunk seq {chunk.seq}, expected "
                                                           f"{session.expected_seq}", chunk.seq)
                        tick = time.perf_counter()
                        header, arrays = await self._generate(session, chunk)
                        session.expected_seq += 1
                        header["latency_ms"] = 1000.0 * (time.perf_counter() - tick)
                        await self._send(ws, pack(header, *arrays))
                except ProtocolError as error:
                    await self._send(ws, error.to_message())
        except (ConnectionClosed, asyncio.TimeoutError):
            pass
        finally:
            self.sessions -= 1
            if session is not None:
                self.open_streams -= 1
                self._start_rounds(wait_for_others=True)  # a round waiting for it need not

    async def _generate(self, session: LiveSession, chunk: Chunk) -> tuple[dict, list[np.ndarray]]:
        """The frames message for ``chunk``, generated in the next round with every other
        session's waiting chunk (a connection sends its next chunk only after this answer, so
        a round holds at most one chunk per session)."""
        future = asyncio.get_running_loop().create_future()
        self.waiting.append((session, chunk, future))
        self._start_rounds(wait_for_others=True)
        return await future

    def _start_rounds(self, wait_for_others: bool = False) -> None:
        """Start a round with the waiting chunks when a worker is free. A round that would
        start on an idle server (``wait_for_others``) waits until every open session has a
        chunk waiting, or ``gather_ms`` at most; one after a round starts at once (the
        sessions of the round that ended send again only on their next tick)."""
        if not self.waiting or self.rounds_running >= self.config.workers:
            return
        if wait_for_others and len(self.waiting) < self.open_streams and self.config.gather_ms > 0:
            if self.gathering is None:
                self.gathering = asyncio.get_running_loop().call_later(
                    self.config.gather_ms / 1000.0, self._gathered)
            return
        if self.gathering is not None:
            self.gathering.cancel()
            self.gathering = None
        while self.waiting and self.rounds_running < self.config.workers:
            batch, self.waiting = self.waiting, []
            self.rounds_running += 1
            self.rounds_run += 1
            self.chunks_run += len(batch)
            task = asyncio.get_running_loop().create_task(self._round(batch))
            self.round_tasks.add(task)
            task.add_done_callback(self.round_tasks.discard)

    def _gathered(self) -> None:
        self.gathering = None
        self._start_rounds()

    async def _round(self, batch: list[tuple[LiveSession, Chunk, asyncio.Future]]) -> None:
        try:
            results = await asyncio.get_running_loop().run_in_executor(
                self.executor, self._compute, [(session, chunk) for session, chunk, _ in batch])
        except Exception as error:  # a bug in the models: every session of the round hears it
            results = [error] * len(batch)
        finally:
            self.rounds_running -= 1
        for (_, _, future), result in zip(batch, results):
            if future.done():  # its connection went away meanwhile
                continue
            if isinstance(result, Exception):
                future.set_exception(result)
            else:
                future.set_result(result)
        self._start_rounds()

    def _compute(self, batch: list[tuple[LiveSession, Chunk]]) -> list:
        """One round on a compute thread, with the intra-op threads that the other processes
        leave free (set per compute thread: torch keeps the count per thread): every session's
        chunk generated together (``push_together``: one flow solve for the round), then each
        session's message, or the error that one session's message raised."""
        if self.threads is not None:
            self.threads.apply()
        motions = push_together([session.stream for session, _ in batch],
                                [LiveSession.inputs(chunk) for _, chunk in batch])
        results: list = []
        for (session, chunk), motion in zip(batch, motions):
            try:
                results.append(session.frames_message(chunk, motion))
            except Exception as error:
                results.append(error)
        return results

    def process_request(self, connection, request):
        """Plain HTTP GETs get the browser page; WebSocket upgrades go on to ``handler``."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        if request.headers.get("Upgrade", "").lower() == "websocket":
            return None
        path = request.path.split("?", 1)[0]
        if path not in WEB_FILES:
            return connection.respond(404, f"no page {path}; the page is at /\n")
        name, content_type = WEB_FILES[path]
        body = resources.files("sarah_models.serving").joinpath("web", name).read_bytes()
        headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                           ("Cache-Control", "no-store")])
        return Response(200, "OK", headers, body)

    async def serve(self, ready: asyncio.Future | None = None, stop: asyncio.Future | None = None) -> None:
        from websockets.asyncio.server import serve

        config = self.config
        async with serve(self.handler, config.host, config.port, process_request=self.process_request,
                         max_size=config.max_message_bytes, max_queue=config.max_queue,
                         close_timeout=2, compression=None) as server:
            port = server.sockets[0].getsockname()[1]
            if ready is not None:
                ready.set_result(port)
            await (stop if stop is not None else asyncio.get_running_loop().create_future())


def load_server_models(run: str | Path, checkpoint=None, device=None, speed: str = "fp32",
                       stream_config: StreamConfig = StreamConfig()):
    """The run's models as ``sarah-generate`` loads them (same checkpoint rules, same fast path)."""
    from ..accel import optimize_for_inference
    from ..generation.run import load_run

    models, path = load_run(run, checkpoint, device)
    if speed != "none":
        models = optimize_for_inference(models, mode=speed, stream_config=stream_config)
    return models, path
