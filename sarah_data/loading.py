"""Safe loading of per-frame arrays (.npy) and audio tracks (.wav).

Every failure is a `DataProblem(path, reason)`: one line naming the file and what is wrong with
it, so a bad file in a corpus of thousands is found without reading a traceback. Arrays are
checked against what the caller expects (shape, dtype kind, frame count, finiteness) before
anyone computes on them.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

FINITE_CHECK_CHUNK = 8192  # frames per chunk, bounds the temporary memory of the NaN scan
MIN_RESAMPLE_RATE = 8_000  # Hz; outside [MIN, MAX] a file's rate is not a real recording rate
MAX_RESAMPLE_RATE = 192_000
MAX_RESAMPLE_FACTOR = 1_000  # reduced up/down factors above this make the polyphase kernel huge

_DTYPE_KIND_NAMES = {"b": "bool", "i": "signed int", "u": "unsigned int", "f": "float",
                     "c": "complex", "O": "object", "S": "bytes", "U": "str", "V": "structured",
                     "M": "datetime", "m": "timedelta"}


class DataProblem(Exception):
    """A data file that cannot be used: `path` names the file, `reason` says why."""

    def __init__(self, path: Path | str, reason: str):
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


def format_frames(frames: np.ndarray, limit: int = 5) -> str:
    """Frame indices as compact ranges, e.g. ``3, 17-18, 40 (4 frames)``; long lists elided."""
    frames = np.unique(np.asarray(frames, dtype=np.int64))
    if frames.size == 0:
        return "no frames"
    breaks = np.flatnonzero(np.diff(frames) != 1) + 1
    runs = [(int(r[0]), int(r[-1])) for r in np.split(frames, breaks)]
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:limit])
    if len(runs) > limit:
        text += f", ... ({len(runs) - limit} more ranges)"
    noun = "frame" if frames.size == 1 else "frames"
    return f"{text} ({frames.size} {noun})"


def _read_npy_header(path: Path) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Shape, fortran order, dtype and data offset, without loading the data."""
    try:
        f = open(path, "rb")
    except OSError as err:
        raise DataProblem(path, f"unreadable ({err.strerror or err})") from None
    with f:
        head = f.read(8)
        f.seek(0)
        if head[:1] == b"\x80":
            raise DataProblem(path, "is a Python pickle, not a .npy array; refusing to load")
        if head[:2] == b"PK":
            raise DataProblem(path, "is a zip / .npz archive, not a .npy array")
        try:
            version = np.lib.format.read_magic(f)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(f)
        # numpy parses the header text with tokenize and ast, which raise many exception
        # types on corrupt input; all of them mean "not a readable .npy" here.
        except Exception as err:  # noqa: BLE001
            first_line = str(err).splitlines()[0] if str(err) else ""
            raise DataProblem(path, f"not a readable .npy file ({type(err).__name__}: "
                                    f"{first_line})") from None
        return tuple(shape), bool(fortran), dtype, f.tell()


def _kind_name(dtype: np.dtype) -> str:
    return f"{dtype} ({_DTYPE_KIND_NAMES.get(dtype.kind, dtype.kind)})"


def load_npy(path: Path | str, expected_shape_tail: tuple[int, ...], dtype_kind: str,
             length: int | None = None, *, check_finite: bool = True,
             mmap: bool = True) -> np.ndarray:
    """Load a per-frame array `(T, *expected_shape_tail)` after checking it is what we expect.

    `dtype_kind` lists the accepted numpy dtype kinds ("f" floats, "biuf" anything numeric);
    `length`, when given, is the required frame count T. Floating arrays are scanned for NaN/inf
    and the offending frames are named. The array is memory-mapped read-only when `mmap`
    (large per-frame files need not be read twice); pickled data is never loaded.
    """
    path = Path(path)
    if not path.is_file():
        raise DataProblem(path, "missing file" if not path.exists() else "not a regular file")
    shape, _, dtype, offset = _read_npy_header(path)
    if dtype.hasobject:
        raise DataProblem(path, "contains Python objects (pickled); refusing to load")
    if dtype.kind not in dtype_kind:
        wanted = " or ".join(_DTYPE_KIND_NAMES[k] for k in dtype_kind)
        raise DataProblem(path, f"dtype {_kind_name(dtype)}; expected {wanted}")
    want_ndim = 1 + len(expected_shape_tail)
    wanted_shape = "(T" + "".join(f", {w}" for w in expected_shape_tail) + ")"
    if len(shape) != want_ndim:
        raise DataProblem(path, f"is {len(shape)}-D, shape {shape}; expected {wanted_shape}")
    if tuple(shape[1:]) != tuple(expected_shape_tail):
        raise DataProblem(path, f"shape {shape}; expected {wanted_shape}")
    if shape[0] == 0:
        raise DataProblem(path, "zero-length array (0 frames)")
    if length is not None and shape[0] != length:
        relation = "shorter" if shape[0] < length else "longer"
        raise DataProblem(path, f"has {shape[0]} frames, expected {length} "
                                f"({relation} than the sequence)")
    data_bytes = math.prod(shape) * dtype.itemsize
    file_bytes = path.stat().st_size - offset
    if file_bytes < data_bytes:
        raise DataProblem(path, f"truncated: header promises {data_bytes} bytes of data, "
                                f"file holds {file_bytes}")
    try:
        array = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise DataProblem(path, f"unreadable .npy ({err})") from None
    if not array.dtype.isnative:  # torch and most kernels want native byte order
        array = array.astype(array.dtype.newbyteorder("="))
    if check_finite and dtype.kind in "fc":
        bad = nonfinite_frames(array)
        if bad.size:
            raise DataProblem(path, f"NaN/inf values in frames {format_frames(bad)}")
    return array


def nonfinite_frames(array: np.ndarray) -> np.ndarray:
    """Indices of the frames (first axis) holding any NaN or infinite value."""
    bad = []
    for start in range(0, array.shape[0], FINITE_CHECK_CHUNK):
        chunk = np.asarray(array[start:start + FINITE_CHECK_CHUNK])
        finite = np.isfinite(chunk).reshape(chunk.shape[0], -1).all(axis=1)
        bad.append(np.flatnonzero(~finite) + start)
    return np.concatenate(bad)


def load_mask(path: Path | str, length: int | None = None) -> np.ndarray:
    """A per-frame 0/1 mask `(T,)` (bool, int or float storage) as a bool array."""
    path = Path(path)
    raw = load_npy(path, (), "biuf", length, check_finite=False)
    if raw.dtype.kind == "b":
        return np.array(raw, dtype=bool)
    values = np.asarray(raw)
    bad = np.flatnonzero((values != 0) & (values != 1))  # NaN compares unequal to both
    if bad.size:
        shown = ", ".join(repr(v.item()) for v in np.unique(values[bad])[:3])
        raise DataProblem(path, f"mask values other than 0/1 ({shown}) in frames "
                                f"{format_frames(bad)}")
    return values == 1


def load_wav(path: Path | str, expected_rate: int, expected_samples: int | None = None,
             tolerance: int = 0) -> tuple[np.ndarray, list[str]]:
    """Load a mono track as float32 `(N,)` at `expected_rate`; returns `(audio, warnings)`.

    A plausible other sample rate (8-192 kHz) is resampled with a warning. With
    `expected_samples`, audio within `tolerance` samples of it is zero-padded or trimmed to
    exactly that many samples (with a warning); further off is a problem.
    """
    import soundfile as sf

    path = Path(path)
    if not path.is_file():
        raise DataProblem(path, "missing file" if not path.exists() else "not a regular file")
    try:
        info = sf.info(str(path))
    except (sf.LibsndfileError, RuntimeError, OSError) as err:
        raise DataProblem(path, f"unreadable audio ({_sndfile_message(err)})") from None
    if info.channels != 1:
        raise DataProblem(path, f"has {info.channels} channels; expected a mono track")
    if info.frames == 0:
        raise DataProblem(path, "empty audio (0 samples)")
    rate = int(info.samplerate)
    warnings: list[str] = []
    if rate != expected_rate and not _can_resample(rate, expected_rate):
        raise DataProblem(path, f"sample rate {rate} Hz; expected {expected_rate} Hz and "
                                f"cannot resample from {rate} Hz")
    try:
        audio, _ = sf.read(str(path), dtype="float32", always_2d=False)
    except (sf.LibsndfileError, RuntimeError, OSError) as err:
        raise DataProblem(path, f"corrupt audio data ({_sndfile_message(err)})") from None
    if audio.shape[0] != info.frames:
        raise DataProblem(path, f"corrupt audio data: header says {info.frames} samples, "
                                f"read {audio.shape[0]}")
    if not np.isfinite(audio).all():
        bad = np.flatnonzero(~np.isfinite(audio))
        raise DataProblem(path, f"NaN/inf audio samples ({bad.size}, first at sample {bad[0]})")
    if rate != expected_rate:
        audio = _resample(audio, rate, expected_rate)
        warnings.append(f"{path}: resampled from {rate} Hz to {expected_rate} Hz")
    if expected_samples is not None:
        audio = _fit_length(path, audio, expected_samples, tolerance, warnings)
    return np.ascontiguousarray(audio, dtype=np.float32), warnings


def _sndfile_message(err: Exception) -> str:
    """libsndfile's own words, without its copy of the path (ours leads the line)."""
    return str(getattr(err, "error_string", None) or err).strip()


def _can_resample(rate: int, target: int) -> bool:
    if not MIN_RESAMPLE_RATE <= rate <= MAX_RESAMPLE_RATE:
        return False
    g = math.gcd(rate, target)
    return max(rate // g, target // g) <= MAX_RESAMPLE_FACTOR


def _resample(audio: np.ndarray, rate: int, target: int) -> np.ndarray:
    import torch
    import torchaudio.functional as AF

    wave = torch.from_numpy(np.ascontiguousarray(audio))
    return AF.resample(wave, rate, target).numpy()


def _fit_length(path: Path, audio: np.ndarray, expected: int, tolerance: int,
                warnings: list[str]) -> np.ndarray:
    n = audio.shape[0]
    if n == expected:
        return audio
    diff = n - expected
    relation = "shorter" if diff < 0 else "longer"
    if abs(diff) > tolerance:
        raise DataProblem(path, f"audio has {n} samples, expected {expected}; {relation} by "
                                f"{abs(diff)} samples (more than the {tolerance} tolerated)")
    if diff < 0:
        audio = np.concatenate([audio, np.zeros(-diff, dtype=audio.dtype)])
        warnings.append(f"{path}: audio {-diff} samples short; zero-padded to {expected}")
    else:
        audio = audio[:expected]
        warnings.append(f"{path}: audio {diff} samples long; trimmed to {expected}")
    return audio


def fill_nonfinite_frames(array: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """A copy of ``array`` whose ``bad`` frames hold the nearest earlier finite frame (the first
    finite frame for a leading run; zeros when no frame is finite)."""
    out = np.array(array)
    good = np.setdiff1d(np.arange(len(out)), bad)
    if good.size == 0:
        out[...] = 0
        return out
    source = good[np.clip(np.searchsorted(good, bad, side="right") - 1, 0, None)]
    out[bad] = out[source]
    return out
