"""A scripted ``sarah-serve`` client: stream two audio files and a trajectory through a running
server and write the motion.npz that ``sarah-generate`` writes for the same inputs.

The files are read exactly as ``sarah-generate`` reads them (``raw_inputs``) and sent as f32le
PCM, so the server sees the same samples and, with the same seed and settings, generates the
same motion bit for bit.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sarah_data import icosahedron
from sarah_data.constants import SAMPLES_PER_FRAME
from sarah_data.skeleton import MotionLayout

from ..config import StreamConfig
from ..generation.inputs import raw_inputs
from ..generation.outputs import Result, head_gaze, write_motion
from .protocol import ProtocolError, encode_pcm, pack, unpack


class ServerError(RuntimeError):
    """The server answered with an error message or closed the connection."""


def read_frames(data: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A binary frames message -> its header and named arrays."""
    header, payload = unpack(data)
    arrays, offset = {}, 0
    for spec in header.get("arrays", []):
        count = int(np.prod(spec["shape"]))
        arrays[spec["name"]] = np.frombuffer(payload[offset:offset + 4 * count], dtype="<f4").reshape(spec["shape"])
        offset += 4 * count
    return header, arrays


def _expect(ws, kind: str):
    message = ws.recv()
    if isinstance(message, str):
        data = json.loads(message)
        if data.get("type") == "error":
            raise ServerError(f"server error {data['code']}: {data['message']}")
        if data.get("type") != kind:
            raise ServerError(f"expected a {kind!r} message, got {data.get('type')!r}")
        return data
    if kind != "frames":
        raise ServerError(f"expected a {kind!r} message, got binary frames")
    return read_frames(message)


def stream_files(url: str, trajectory, agent_audio, user_audio, out: str | Path, *,
                 gaze: float | None = 0.8, steps: int | None = None, seed: int | None = None,
                 cfg_scale: float | None = None, frames: int | None = None,
                 agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0), chunk_frames: int = 4,
                 echo: Callable[[str], None] = print) -> Path:
    """Stream the files through the server at ``url``; write ``out``/motion.npz; return its path."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    request = {"type": "open", "version": 1, "gaze": gaze, "agent_start": list(agent_start),
               "audio_format": "f32le", "features": True}
    for key, value in (("steps", steps), ("seed", seed), ("cfg", cfg_scale)):
        if value is not None:
            request[key] = value
    try:
        with connect(url, max_size=None, compression=None) as ws:
            ws.send(json.dumps(request))
            ready = _expect(ws, "ready")
            stride = ready["stride"]
            if chunk_frames <= 0 or chunk_frames % stride:
                raise ServerError(f"chunk_frames must be a positive multiple of {stride}")
            inputs = raw_inputs(trajectory, agent_audio, user_audio, stride, frames, agent_start)
            motion, agent_feats, user_feats, latencies = [], [], [], []
            seconds = 0.0
            for seq, start in enumerate(range(0, inputs.frames, chunk_frames)):
                stop = min(start + chunk_frames, inputs.frames)
                a, b = (w[start * SAMPLES_PER_FRAME: stop * SAMPLES_PER_FRAME]
                        for w in (inputs.agent_wave, inputs.user_wave))
                header = {"type": "chunk", "seq": seq, "frames": stop - start,
                          "head": inputs.user_head[start:stop].astype(float).tolist()}
                tick = time.perf_counter()
                ws.send(pack(header) + encode_pcm(a, "f32le") + encode_pcm(b, "f32le"))
                reply, arrays = _expect(ws, "frames")
                seconds += time.perf_counter() - tick
                if reply["seq"] != seq:
                    raise ServerError(f"frames for chunk {reply['seq']} arrived for chunk {seq}")
                motion.append(arrays["motion"])
                agent_feats.append(arrays["agent_features"])
                user_feats.append(arrays["user_features"])
                latencies.append(reply["latency_ms"] / 1000.0)
            ws.send(json.dumps({"type": "close"}))
    except ConnectionRefusedError:
        raise ServerError(f"{url}: connection refused: is sarah-serve running there?") from None
    except OSError as error:
        raise ServerError(f"{url}: cannot connect ({error.strerror or error})") from None
    except (ConnectionClosed, ProtocolError) as error:
        raise ServerError(f"{url}: {error}") from None
    result = Result(np.concatenate(motion), np.concatenate(agent_feats), np.concatenate(user_feats),
                    latencies, seconds)
    positions, rotations = icosahedron.decode(MotionLayout.from_width(result.motion.shape[-1])
                                              .split(result.motion)[0])
    scores = head_gaze(positions, rotations, inputs.user_head)
    config = StreamConfig(gaze=gaze)
    settings = {"server": url, "open": request, "ready": {k: ready[k] for k in ("version", "features")}}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = write_motion(out / "motion.npz", result, inputs, config, positions, rotations, scores, settings)
    echo(f"streamed {len(result.motion)} frames through {url} in {len(latencies)} chunks; server "
         f"latency p50 {1000 * np.median(latencies):.1f} ms, p99 {1000 * np.percentile(latencies, 99):.1f} ms; "
         f"wrote {path}")
    return path
