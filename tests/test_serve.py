"""sarah-serve: the same motion as sarah-generate through the wire, bad input over the wire
answered without harming other sessions, two server processes, and the browser page in a real
headless Chromium."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from sarah_cli.generate import main as generate
from sarah_cli.serve import main as serve_main
from sarah_data.constants import SAMPLES_PER_FRAME
from sarah_models.config import StreamConfig
from sarah_models.serving.client import read_frames
from sarah_models.serving.protocol import encode_pcm, pack
from sarah_models.serving.server import LiveServer, ServeConfig, load_server_models
from helpers import spinning_processes
from test_generate import save_run, write_wav

FRAMES = 60


class RunningServer:
    """A LiveServer on a free loopback port, in a thread with its own event loop."""

    def __init__(self, run: Path, body=None, defaults: StreamConfig = StreamConfig(), **config):
        models, _ = load_server_models(run, device="cpu")
        self.server = LiveServer(models, ServeConfig(port=0, **config), defaults, body=body)
        self.loop = asyncio.new_event_loop()
        self.ready = self.loop.create_future()
        self.stop_future = self.loop.create_future()
        self.thread = threading.Thread(target=self.loop.run_until_complete,
                                       args=(self.server.serve(self.ready, self.stop_future),), daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.ready.done():
            assert time.monotonic() < deadline, "server did not start"
            time.sleep(0.02)
        self.url = f"ws://127.0.0.1:{self.ready.result()}/"

    def stop(self):
        self.loop.call_soon_threadsafe(self.stop_future.set_result, None)
        self.thread.join(10)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A tiny random-weight run; SARAH_SERVE_RUN names a trained one instead (for the README's
    screenshot, taken with SARAH_SCREENSHOT)."""
    trained = os.environ.get("SARAH_SERVE_RUN")
    return Path(trained) if trained else save_run(tmp_path_factory.mktemp("serve") / "run")


@pytest.fixture(scope="module")
def server(run_dir, procedural_model_path):
    from sarah_data.export.motion import neutral_shape

    # One thread, as the sarah-generate runs it is compared with: thread counts round differently.
    running = RunningServer(run_dir, body=neutral_shape(procedural_model_path), send_timeout=1.0,
                            max_sessions=8, threads=1)
    yield running
    running.stop()


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    folder = tmp_path_factory.mktemp("serve_raw")
    write_wav(folder / "agent.wav", FRAMES / 30 + 0.2, 44_100, 220)
    write_wav(folder / "user.wav", FRAMES / 30 + 0.2, 16_000, 150, seed=1)
    angle = np.linspace(0, 1.2, FRAMES)
    np.savetxt(folder / "traj.csv", np.stack([2 * np.sin(angle), 2 * np.cos(angle)], 1),
               delimiter=",", header="x,z", comments="")
    return folder


def files(raw):
    return ["--user-trajectory", str(raw / "traj.csv"), "--agent-audio", str(raw / "agent.wav"),
            "--user-audio", str(raw / "user.wav")]


@pytest.mark.parametrize("gaze", ["0.8", "none"])
def test_streaming_through_the_server_is_sarah_generate(server, run_dir, raw, tmp_path, gaze):
    assert serve_main(["--client", server.url, *files(raw), "--out", str(tmp_path / "served"),
                       "--seed", "5", "--gaze", gaze]) == 0
    assert generate(["--run", str(run_dir), *files(raw), "--out", str(tmp_path / "direct"),
                     "--seed", "5", "--gaze", gaze, "--no-animation", "--device", "cpu",
                     "--threads", "1"]) == 0
    served, direct = (np.load(tmp_path / name / "motion.npz", allow_pickle=False)
                      for name in ("served", "direct"))
    assert served["icosahedra"].shape[0] == FRAMES
    for key in ("icosahedra", "shell", "joint_positions", "joint_rotations", "gaze_score",
                "agent_audio", "user_audio", "user_head", "agent_speaking", "anchor"):
        np.testing.assert_array_equal(served[key], direct[key], err_msg=key)


def test_a_server_streaming_with_trajectory_imputation_sends_the_offline_motion(run_dir, raw,
                                                                               tmp_path):
    """``sarah-serve --imputation trajectory``: every session streams what ``sarah-generate
    --offline`` writes for the same inputs and seed."""
    running = RunningServer(run_dir, defaults=StreamConfig(imputation="trajectory"), threads=1)
    try:
        assert serve_main(["--client", running.url, *files(raw), "--out", str(tmp_path / "served"),
                           "--seed", "5"]) == 0
    finally:
        running.stop()
    assert generate(["--run", str(run_dir), *files(raw), "--out", str(tmp_path / "offline"),
                     "--seed", "5", "--offline", "--no-animation", "--device", "cpu",
                     "--threads", "1"]) == 0
    served, offline = (np.load(tmp_path / name / "motion.npz", allow_pickle=False)
                       for name in ("served", "offline"))
    assert served["icosahedra"].shape[0] == FRAMES
    np.testing.assert_allclose(served["icosahedra"], offline["icosahedra"], atol=1e-4)


@contextmanager
def open_session(url, **fields):
    with connect(url, max_size=None, compression=None) as ws:
        ws.send(json.dumps({"type": "open", "version": 1, "audio_format": "s16le", **fields}))
        ready = json.loads(ws.recv(timeout=10))
        assert ready["type"] == "ready" and ready["version"] == 1
        yield ws, ready


def chunk(seq, frames=4, head=None, samples=None, fmt="s16le"):
    head = [[0.5, 1.5]] * frames if head is None else head
    n = frames * SAMPLES_PER_FRAME if samples is None else samples
    wave = 0.1 * np.sin(np.arange(n) / 20.0)
    return pack({"type": "chunk", "seq": seq, "frames": frames, "head": head}) + \
        encode_pcm(wave, fmt) + encode_pcm(wave, fmt)


def error_of(ws):
    message = json.loads(ws.recv(timeout=10))
    assert message["type"] == "error", message
    return message


def test_sessions_in_one_round_get_what_each_gets_alone(run_dir):
    """Three clients sending on one clock are generated in shared rounds (one flow solve per
    round), and each gets the motion it gets with the server to itself."""
    running = RunningServer(run_dir, threads=1, gather_ms=1000.0)  # rounds wait for all three

    def session(seed, out, barrier):
        with open_session(running.url, seed=seed, gaze=0.8 if seed else None) as (ws, _):
            frames = []
            for seq in range(5):
                barrier.wait()
                ws.send(chunk(seq, head=[[0.5 + 0.2 * seed, 1.5 - 0.1 * seq]] * 4))
                header, arrays = read_frames(ws.recv(timeout=30))
                assert header["seq"] == seq
                frames.append(arrays["motion"])
            out[seed] = np.concatenate(frames)

    try:
        together, barrier = {}, threading.Barrier(3)
        clients = [threading.Thread(target=session, args=(seed, together, barrier))
                   for seed in range(3)]
        for client in clients:
            client.start()
        for client in clients:
            client.join(120)
        assert (running.server.rounds_run, running.server.chunks_run) == (5, 15)
        alone = {}
        for seed in range(3):
            session(seed, alone, threading.Barrier(1))
        assert running.server.rounds_run == 5 + 15
    finally:
        running.stop()
    for seed in range(3):
        np.testing.assert_allclose(together[seed], alone[seed], atol=1e-5)
    assert not np.allclose(together[0], together[1])


def test_serve_bench_beside_a_busy_process(tmp_path, capsys):
    """``sarah-bench --serve --background-load 1``: levels of real client sessions against a
    sarah-serve process while a busy process of the bench's own runs, the capacity stated, and
    no busy process left behind."""
    from sarah_cli.bench import main as bench_main

    out = tmp_path / "serve.json"
    assert bench_main(["--serve", "--sizes", "tiny,fixture-tiny", "--serve-seconds", "1",
                       "--soak-seconds", "0", "--background-load", "1", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["config"]["background_load"] == 1
    for size in ("tiny", "fixture-tiny"):  # random weights, and the shipped model with its chain
        levels = [level for level in result["levels"] if level["size"] == size]
        assert [level["sessions"] for level in levels] == list(
            result["config"]["session_counts"][:len(levels)])
        assert all(level["chunks"] > 0 and level["lost"] == 0 for level in levels)
        assert result["capacity"][size] == max([0] + [level["sessions"] for level in levels
                                                      if level["holds"]])
    assert "beside 1 busy processes" in capsys.readouterr().out
    assert spinning_processes() == []


def test_bad_messages_get_an_error_and_the_session_goes_on(server):
    with open_session(server.url) as (ws, ready):
        ws.send(chunk(0, samples=1000))
        assert error_of(ws)["code"] == "bad_audio"
        ws.send(chunk(0, head=[[0.0, float("nan")]] * 4))
        assert "NaN" in error_of(ws)["message"]
        ws.send(json.dumps({"type": "dance"}))
        assert error_of(ws)["code"] == "unknown_type"
        ws.send("{not json")
        assert error_of(ws)["code"] == "bad_json"
        ws.send(chunk(3))
        assert error_of(ws)["code"] == "bad_seq"
        ws.send(json.dumps({"type": "gaze", "value": 7}))
        assert error_of(ws)["code"] == "bad_gaze"
        ws.send(chunk(0, frames=6))
        assert error_of(ws)["code"] == "bad_chunk"
        for seq in range(3):  # still usable: frames for every good chunk, in order
            ws.send(chunk(seq, frames=8))
            header, arrays = read_frames(ws.recv(timeout=30))
            assert header["seq"] == seq and header["first_frame"] == 8 * seq
            assert arrays["motion"].shape == (8, ready["motion_width"])
            assert arrays["joint_positions"].shape == (8, 55, 3) and np.isfinite(arrays["motion"]).all()
        ws.send(json.dumps({"type": "gaze", "value": None}))
        assert json.loads(ws.recv(timeout=10)) == {"type": "gaze_set", "value": None, "from_frame": 24}


def test_an_open_with_bad_fields_is_refused_by_name(server):
    with connect(server.url) as ws:
        ws.send(json.dumps({"type": "open", "version": 1, "gaze": 3}))
        assert "gaze" in error_of(ws)["message"]
        ws.send(json.dumps({"type": "open", "version": 9}))
        assert error_of(ws)["code"] == "bad_version"
        ws.send(chunk(0))
        assert error_of(ws)["code"] == "not_open"


def frames_ok(url):
    with open_session(url) as (ws, _):
        ws.send(chunk(0))
        header, _ = read_frames(ws.recv(timeout=30))
        return header["frames"] == 4


def test_oversized_slow_and_vanishing_clients_do_not_hurt_the_others(server):
    with open_session(server.url) as (bystander, _):
        # A 100 MB message: the connection is closed with "message too big" (1009).
        with open_session(server.url) as (big, _):
            with pytest.raises(ConnectionClosed) as closed:
                big.send(b"\0" * (100 * 1024 * 1024))
                big.recv(timeout=10)
            assert closed.value.rcvd is None or closed.value.rcvd.code == 1009
        # A client that sends chunks but never reads: closed after the send timeout (1 s here).
        with open_session(server.url) as (slow, _):
            with pytest.raises(ConnectionClosed):
                for seq in range(2000):
                    slow.send(chunk(seq))
        # A client that disconnects in the middle of a chunk's generation.
        with open_session(server.url) as (gone, _):
            gone.send(chunk(0, frames=40))
            gone.socket.close()
        # The bystander's session went on untouched.
        bystander.send(chunk(0))
        header, _ = read_frames(bystander.recv(timeout=30))
        assert header["seq"] == 0 and header["frames"] == 4
    deadline = time.monotonic() + 20
    while server.server.sessions and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.server.sessions == 0  # every disconnect freed its session
    assert frames_ok(server.url)


def test_loopback_by_default_and_arguments_checked(run_dir, capsys):
    with pytest.raises(SystemExit):
        serve_main(["--run", str(run_dir), "--host", "0.0.0.0"])
    assert "--public" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        serve_main(["--client", "ws://127.0.0.1:1/"])
    assert "--user-trajectory" in capsys.readouterr().err
    assert serve_main(["--run", str(run_dir / "missing")]) == 2
    assert "no such run folder or model file" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["run", "pretrained"])
def test_two_server_processes_share_nothing(run_dir, raw, tmp_path, model):
    """Scaling out is N servers behind a WebSocket-aware balancer: two processes here, each
    serving a client, give the same motion for the same inputs. Also with the shipped model,
    as `make serve` starts it."""
    procs, urls = [], []
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    choice = ["--run", str(run_dir)] if model == "run" else ["--pretrained", "fixture-tiny"]
    try:
        for _ in range(2):
            proc = subprocess.Popen([sys.executable, "-m", "sarah_cli.serve", *choice,
                                     "--port", "0", "--device", "cpu", "--threads", "1"],
                                    stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True, env=env)
            procs.append(proc)
        for proc in procs:
            line = proc.stdout.readline()
            match = re.search(r"ws://127\.0\.0\.1:(\d+)/", line)
            assert match, line
            urls.append(f"ws://127.0.0.1:{match.group(1)}/")
        assert len(set(urls)) == 2
        for i, url in enumerate(urls):
            assert serve_main(["--client", url, *files(raw), "--out", str(tmp_path / str(i))]) == 0
        a, b = (np.load(tmp_path / str(i) / "motion.npz", allow_pickle=False) for i in range(2))
        np.testing.assert_array_equal(a["icosahedra"], b["icosahedra"])
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(10)


def test_the_solver_flag_reaches_every_session(run_dir, raw, tmp_path):
    """``sarah-serve --solver euler``: a session streams what ``sarah-generate --solver euler``
    writes, which is not the midpoint method's motion; a solver it does not know stops the
    command before anything loads."""
    with pytest.raises(SystemExit):
        serve_main(["--run", str(run_dir), "--solver", "rk4"])
    proc = subprocess.Popen([sys.executable, "-m", "sarah_cli.serve", "--run", str(run_dir),
                             "--port", "0", "--device", "cpu", "--threads", "1",
                             "--solver", "euler"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        match = re.search(r"ws://127\.0\.0\.1:(\d+)/", line)
        assert match, line
        assert serve_main(["--client", f"ws://127.0.0.1:{match.group(1)}/", *files(raw),
                           "--out", str(tmp_path / "served"), "--seed", "5"]) == 0
    finally:
        proc.terminate()
        proc.wait(10)
    for solver in ("euler", "midpoint"):
        assert generate(["--run", str(run_dir), *files(raw), "--out", str(tmp_path / solver),
                         "--seed", "5", "--solver", solver, "--no-animation", "--device", "cpu",
                         "--threads", "1"]) == 0
    served, euler, midpoint = (np.load(tmp_path / name / "motion.npz", allow_pickle=False)["icosahedra"]
                               for name in ("served", "euler", "midpoint"))
    np.testing.assert_array_equal(served, euler)
    assert np.abs(served - midpoint).max() > 1e-3


def chromium_path():
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


def test_the_page_in_a_real_browser(server, tmp_path):
    """Headless Chromium opens the page, starts a session, walks the user with the keyboard and
    sees frames arrive and get drawn; the screenshot is the one the README shows."""
    browser_path = chromium_path()
    if browser_path is None:
        pytest.skip("Chromium is not installed (.ci/run installs Debian's chromium package)")
    from playwright.sync_api import sync_playwright

    page_url = server.url.replace("ws://", "http://")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=browser_path, headless=True,
                                    args=["--no-sandbox", "--autoplay-policy=no-user-gesture-required"])
        try:
            page = browser.new_page(viewport={"width": 960, "height": 700})
            page.goto(page_url)
            page.click("#start")
            page.wait_for_function("window.sarah.framesReceived >= 8", timeout=30_000)
            before = page.evaluate("[window.sarah.user.x, window.sarah.user.z]")
            page.keyboard.down("d")
            page.wait_for_timeout(600)
            page.keyboard.up("d")
            after = page.evaluate("[window.sarah.user.x, window.sarah.user.z]")
            assert after[0] > before[0] + 0.2  # the user walked to the right
            page.fill("#gaze", "0.2")
            page.dispatch_event("#gaze", "input")
            page.wait_for_function("window.sarah.framesReceived >= 40", timeout=30_000)
            state = page.evaluate("({r: window.sarah.framesReceived, d: window.sarah.framesDrawn})")
            assert state["d"] > 0 and state["r"] >= 40
            assert "frames received" in page.inner_text("#status")
            shot = tmp_path / "sarah-serve-page.png"
            page.screenshot(path=str(shot))
            assert shot.stat().st_size > 5000
            target = os.environ.get("SARAH_SCREENSHOT")
            if target:  # docs/images/ is refreshed with SARAH_SCREENSHOT=docs/images/sarah-serve-page.png
                shutil.copy(shot, target)
        finally:
            browser.close()


def test_smplx_parameters_on_request(server, procedural_model_path):
    """open {"smplx": true}: each frames message also carries SMPL-X poses and trans (the
    exporter's, on the server's --body-model with zero betas), which the smplx package turns
    back into the streamed body's joints."""
    import smplx
    import torch

    with open_session(server.url, smplx=True) as (ws, ready):
        assert ready["smplx"]["gender"] == "neutral" and not any(ready["smplx"]["betas"])
        ws.send(chunk(0, frames=8))
        header, arrays = read_frames(ws.recv(timeout=30))
    poses, trans = arrays["smplx_poses"], arrays["smplx_trans"]
    assert poses.shape == (8, 165) and trans.shape == (8, 3)
    model = smplx.SMPLX(model_path=str(procedural_model_path), ext="npz", gender="neutral",
                        use_pca=False, flat_hand_mean=True, num_betas=len(ready["smplx"]["betas"]))
    def t(array):
        return torch.tensor(np.array(array))

    out = model(global_orient=t(poses[:, :3]), body_pose=t(poses[:, 3:66]), jaw_pose=t(poses[:, 66:69]),
                leye_pose=t(poses[:, 69:72]), reye_pose=t(poses[:, 72:75]),
                left_hand_pose=t(poses[:, 75:120]), right_hand_pose=t(poses[:, 120:]), transl=t(trans),
                betas=torch.zeros(8, len(ready["smplx"]["betas"])), expression=torch.zeros(8, 10))
    joints = out.joints[:, :55].detach().numpy()
    # The rigid body keeps the model's bones: its pelvis is exactly the streamed one.
    np.testing.assert_allclose(joints[:, 0], arrays["joint_positions"][:, 0], atol=1e-4)



def test_a_server_with_a_body_animates_that_body(procedural_model_path):
    """--body-model: the live agent is that body, its motion decoded on its bones (those its
    SMPL-X parameters pose) for every session; without one, on the training data's. The shipped
    model, whose decoding keeps bone lengths, streamed one chunk of 8 frames each way."""
    from sarah_data.export.motion import neutral_shape
    from sarah_data.skeleton import MotionLayout, bone_lengths
    from sarah_models.generation.inputs import make_extractor
    from sarah_models.pretrained import model_path
    from sarah_models.serving.protocol import Chunk, OpenRequest
    from sarah_models.serving.server import LiveSession
    from sarah_models.training.model_file import load_model_file

    models = load_model_file(model_path("fixture-tiny"), device="cpu")
    body = neutral_shape(procedural_model_path)
    layout = MotionLayout()
    wave = (0.1 * np.sin(np.arange(8 * SAMPLES_PER_FRAME) / 20.0)).astype(np.float32)
    pushed = Chunk(0, np.tile(np.float32([[0.5, 1.5]]), (8, 1)), wave, wave)
    lengths = {}
    for name, given in (("body", body), ("none", None)):
        session = LiveSession(models, OpenRequest(smplx=given is not None), StreamConfig(),
                              make_extractor(models.features), given)
        header, arrays = session.push(pushed)
        joints = dict(zip((a["name"] for a in header["arrays"]), arrays))["joint_positions"]
        assert len(joints) == 8
        lengths[name] = bone_lengths(joints.astype(np.float64), layout.bones)
    np.testing.assert_allclose(lengths["body"], np.broadcast_to(
        layout.rest_bone_lengths(body.rest_joints), lengths["body"].shape), atol=1e-4)
    np.testing.assert_allclose(lengths["none"], np.broadcast_to(
        models.normalizer.bone_length_mean.double().numpy(), lengths["none"].shape), atol=1e-4)


def test_smplx_without_a_body_model_is_refused_by_name(run_dir):
    plain = RunningServer(run_dir)
    try:
        with connect(plain.url) as ws:
            ws.send(json.dumps({"type": "open", "version": 1, "smplx": True}))
            assert "--body-model" in error_of(ws)["message"]
    finally:
        plain.stop()
