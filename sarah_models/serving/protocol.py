"""The sarah-serve wire protocol, version 1 (docs/protocol.md): message shapes and checks.

Control messages are JSON text; chunks and frames are binary: a little-endian uint32 header
length, the UTF-8 JSON header, then raw little-endian arrays in the order the header lists.
Every check here raises ``ProtocolError(code, message)``; the server answers it with an
``error`` message and the session goes on.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sarah_data.constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME

VERSION = 1
AUDIO_FORMATS = {"s16le": np.dtype("<i2"), "f32le": np.dtype("<f4")}
MAX_CHUNK_FRAMES = 120  # 4 s per chunk at most: what a client sends is real time, not a file
HEADER = struct.Struct("<I")
MAX_HEADER_BYTES = 64 * 1024


class ProtocolError(ValueError):
    def __init__(self, code: str, message: str, seq: int | None = None):
        super().__init__(message)
        self.code, self.message, self.seq = code, message, seq

    def to_message(self) -> str:
        return json.dumps({"type": "error", "code": self.code, "message": self.message,
                           "seq": self.seq})


@dataclass
class OpenRequest:
    """What a client may set for its session; None means the server's default (the paper's)."""

    gaze: float | None = None
    gaze_given: bool = False
    steps: int | None = None
    cfg_scale: float | None = None
    seed: int | None = None
    agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    audio_format: str = "s16le"
    features: bool = False  # also return the audio features the model used (for motion.npz)
    smplx: bool = False  # also return SMPL-X parameters (needs the server's --body-model)


@dataclass
class Chunk:
    seq: int
    head: np.ndarray  # (k, 2) float32 world floor (x, z) of the user's head per frame
    agent_audio: np.ndarray  # (k * 1600,) float32 in [-1, 1]
    user_audio: np.ndarray
    frames: int = field(init=False)

    def __post_init__(self) -> None:
        self.frames = int(self.head.shape[0])


def _number(value: Any, name: str, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError("bad_open", f"{name} must be a finite number, got {value!r}")
    if integer and int(value) != value:
        raise ProtocolError("bad_open", f"{name} must be a whole number, got {value!r}")
    return value


def parse_text(text: str) -> dict[str, Any]:
    try:
        message = json.loads(text)
    except json.JSONDecodeError as error:
        raise ProtocolError("bad_json", f"not JSON: {error}") from None
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise ProtocolError("bad_message", "a message is a JSON object with a string 'type'")
    return message


def parse_open(message: dict[str, Any]) -> OpenRequest:
    from sarah_models.config import check_gaze

    version = message.get("version", VERSION)
    if version != VERSION:
        raise ProtocolError("bad_version", f"protocol version {version!r}; this server speaks {VERSION}")
    known = {"type", "version", "gaze", "steps", "cfg", "seed", "agent_start", "audio_format",
             "features", "smplx"}
    unknown = sorted(set(message) - known)
    if unknown:
        raise ProtocolError("bad_open", f"unknown open fields {unknown}; known: {sorted(known)}")
    request = OpenRequest()
    if "gaze" in message:
        request.gaze_given = True
        request.gaze = None if message["gaze"] is None else float(_number(message["gaze"], "gaze"))
        try:
            check_gaze(request.gaze)
        except ValueError as error:
            raise ProtocolError("bad_open", str(error)) from None
    if "steps" in message:
        request.steps = int(_number(message["steps"], "steps", integer=True))
        if not 1 <= request.steps <= 64:
            raise ProtocolError("bad_open", f"steps must be in 1..64, got {request.steps}")
    if "cfg" in message:
        request.cfg_scale = float(_number(message["cfg"], "cfg"))
    if "seed" in message:
        request.seed = int(_number(message["seed"], "seed", integer=True))
    if "agent_start" in message:
        start = message["agent_start"]
        if not isinstance(start, list) or len(start) != 3:
            raise ProtocolError("bad_open", f"agent_start is [x, z, yaw_degrees], got {start!r}")
        request.agent_start = tuple(float(_number(v, "agent_start")) for v in start)
    if "audio_format" in message:
        if message["audio_format"] not in AUDIO_FORMATS:
            raise ProtocolError("bad_open", f"audio_format must be one of {sorted(AUDIO_FORMATS)}, "
                                            f"got {message['audio_format']!r}")
        request.audio_format = message["audio_format"]
    if "features" in message:
        request.features = bool(message["features"])
    if "smplx" in message:
        request.smplx = bool(message["smplx"])
    return request


def parse_gaze(message: dict[str, Any]) -> float | None:
    from sarah_models.config import check_gaze

    if "value" not in message:
        raise ProtocolError("bad_gaze", "a gaze message has 'value' (a number in [-1, 1] or null)")
    value = message["value"]
    if value is not None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ProtocolError("bad_gaze", f"gaze value must be a number or null, got {value!r}")
        value = float(value)
    try:
        check_gaze(value)
    except ValueError as error:
        raise ProtocolError("bad_gaze", str(error)) from None
    return value


def pack(header: dict[str, Any], *arrays: np.ndarray) -> bytes:
    """A binary message: header length, JSON header, then the arrays' little-endian bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return HEADER.pack(len(head)) + head + b"".join(
        np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<")).tobytes() for a in arrays)


def unpack(data: bytes) -> tuple[dict[str, Any], memoryview]:
    if len(data) < HEADER.size:
        raise ProtocolError("bad_binary", "a binary message starts with a 4-byte header length")
    (size,) = HEADER.unpack_from(data)
    if size > MAX_HEADER_BYTES or HEADER.size + size > len(data):
        raise ProtocolError("bad_binary", f"header length {size} does not fit the {len(data)}-byte message")
    try:
        header = json.loads(bytes(data[HEADER.size:HEADER.size + size]))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ProtocolError("bad_binary", f"header is not JSON: {error}") from None
    if not isinstance(header, dict):
        raise ProtocolError("bad_binary", "the header is a JSON object")
    return header, memoryview(data)[HEADER.size + size:]


def parse_chunk(data: bytes, audio_format: str, stride: int) -> Chunk:
    """A binary chunk: header {"type": "chunk", "seq", "frames", "head": [[x, z], ...]}, then the
    agent's and the user's PCM (frames * 1600 samples each, 48 kHz mono, ``audio_format``)."""
    header, payload = unpack(data)
    seq = header.get("seq")
    if header.get("type") != "chunk":
        raise ProtocolError("unknown_type", f"binary message of type {header.get('type')!r}; "
                                            f"clients send binary 'chunk' messages", None)
    if isinstance(seq, bool) or not isinstance(seq, int):
        raise ProtocolError("bad_chunk", f"seq must be an integer, got {seq!r}")
    frames = header.get("frames")
    if isinstance(frames, bool) or not isinstance(frames, int) or not 0 < frames <= MAX_CHUNK_FRAMES \
            or frames % stride:
        raise ProtocolError("bad_chunk", f"frames must be a positive multiple of {stride} up to "
                                         f"{MAX_CHUNK_FRAMES}, got {frames!r}", seq)
    try:
        head = np.asarray(header.get("head"), dtype=np.float64)
    except (TypeError, ValueError):
        raise ProtocolError("bad_chunk", "head must be [[x, z], ...] numbers", seq) from None
    if head.shape != (frames, 2):
        raise ProtocolError("bad_chunk", f"head has shape {head.shape}, expected ({frames}, 2)", seq)
    if not np.isfinite(head).all():
        raise ProtocolError("bad_chunk", "head positions contain NaN or infinite values", seq)
    dtype = AUDIO_FORMATS[audio_format]
    samples = frames * SAMPLES_PER_FRAME
    expected = 2 * samples * dtype.itemsize
    if len(payload) != expected:
        raise ProtocolError("bad_audio", f"{len(payload)} audio bytes; {frames} frames of two "
                                         f"{audio_format} tracks at {AUDIO_SAMPLE_RATE} Hz are "
                                         f"{expected} ({samples} samples each)", seq)
    audio = np.frombuffer(payload, dtype=dtype).reshape(2, samples)
    if dtype.kind == "i":
        audio = audio.astype(np.float32) / 32768.0
    else:
        audio = audio.astype(np.float32)
        if not np.isfinite(audio).all():
            raise ProtocolError("bad_audio", "audio samples contain NaN or infinite values", seq)
    return Chunk(seq, head.astype(np.float32), audio[0].copy(), audio[1].copy())


def encode_pcm(wave: np.ndarray, audio_format: str) -> bytes:
    """Float samples in [-1, 1] as the wire's PCM bytes."""
    wave = np.asarray(wave, dtype=np.float32)
    if audio_format == "s16le":
        return (np.clip(wave, -1.0, 32767 / 32768) * 32768.0).round().astype("<i2").tobytes()
    return wave.astype("<f4").tobytes()
