"""Safe loading: every kind of bad file becomes one DataProblem line naming the file and reason."""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from hypothesis import given, settings
from hypothesis import strategies as st

from embody_layout import manifest_entries, write_manifest, write_sequence
from sarah_data.constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME
from sarah_data.embody3d import PairRecord, load_person, read_corpus
from sarah_data.loading import DataProblem, format_frames, load_mask, load_npy, load_wav

T = 8  # frames of the test sequence
N = T * SAMPLES_PER_FRAME
SEQUENCE = ("c--20250321--1019--WBM368--BVO565--pilot--MotionPrior2--AIAGENT_scene_009"
            "--000100-000107")
PERSON = "BVO565"


@pytest.fixture
def pair(tmp_path) -> PairRecord:
    folder = tmp_path / "aiagent"
    write_manifest(folder, {SEQUENCE: manifest_entries(SEQUENCE, T)})
    write_sequence(folder, SEQUENCE, seed=3)
    corpus = read_corpus(folder)
    assert corpus.skipped == [] and corpus.problems == []
    return corpus.pairs[0]


def param(pair: PairRecord, folder: str = "smplx_mesh_body_pose") -> Path:
    return pair.files[PERSON].params[folder]


def mask(pair: PairRecord) -> Path:
    return pair.files[PERSON].missing


def audio(pair: PairRecord) -> Path:
    return pair.files[PERSON].audio


def wave(n: int, channels: int = 1) -> np.ndarray:
    x = 0.05 * np.sin(np.arange(n) * 0.01, dtype=np.float32)
    return np.stack([x] * channels, axis=1) if channels > 1 else x


def nan_frames(path: Path, frames=(2, 3, 6), value=np.nan, width=63):
    x = np.zeros((T, width), np.float32)
    x[list(frames), width - 1] = value
    np.save(path, x)


# Each case: (what it breaks, how, which file the problem must name, reason regex).
CASES = [
    ("missing param file", lambda p: param(p).unlink(), param, r"missing file"),
    ("truncated npy", lambda p: param(p).write_bytes(param(p).read_bytes()[:-40]), param,
     r"truncated: header promises 2016 bytes of data, file holds 1976"),
    ("not an npy", lambda p: param(p).write_bytes(b"hello, world"), param,
     r"not a readable \.npy file"),
    ("broken header", lambda p: param(p).write_bytes(_broken_header()), param,
     r"not a readable \.npy file \(TokenError"),
    ("empty file", lambda p: param(p).write_bytes(b""), param, r"not a readable \.npy file"),
    ("object array", lambda p: np.save(param(p), np.array([{}] * T, dtype=object),
                                       allow_pickle=True), param,
     r"contains Python objects \(pickled\); refusing to load"),
    ("raw pickle", lambda p: param(p).write_bytes(pickle.dumps(np.zeros((T, 63)))), param,
     r"is a Python pickle, not a \.npy array; refusing to load"),
    ("npz archive", lambda p: param(p).write_bytes(_npz_bytes(p)), param, r"zip / \.npz"),
    ("int params", lambda p: np.save(param(p), np.zeros((T, 63), np.int64)), param,
     r"dtype int64 \(signed int\); expected float"),
    ("string params", lambda p: np.save(param(p), np.full((T, 63), "a")), param,
     r"dtype <U1 \(str\); expected float"),
    ("wrong width", lambda p: np.save(param(p), np.zeros((T, 62), np.float32)), param,
     r"shape \(8, 62\); expected \(T, 63\)"),
    ("wrong ndim", lambda p: np.save(param(p), np.zeros((T, 63, 1), np.float32)), param,
     r"is 3-D, shape \(8, 63, 1\); expected \(T, 63\)"),
    ("betas width", lambda p: np.save(param(p, "smplx_mesh_betas"), np.zeros((T, 10))),
     lambda p: param(p, "smplx_mesh_betas"), r"shape \(8, 10\); expected \(T, 300\)"),
    ("too short", lambda p: np.save(param(p), np.zeros((T - 1, 63), np.float32)), param,
     r"has 7 frames, expected 8 \(shorter than the sequence\)"),
    ("too long", lambda p: np.save(param(p), np.zeros((T + 1, 63), np.float32)), param,
     r"has 9 frames, expected 8 \(longer than the sequence\)"),
    ("zero length", lambda p: np.save(param(p), np.zeros((0, 63), np.float32)), param,
     r"zero-length array \(0 frames\)"),
    ("missing mask", lambda p: mask(p).unlink(), mask, r"missing file"),
    ("mask value 2", lambda p: np.save(mask(p), np.array([1, 1, 0, 1, 1, 2, 1, 1.0])), mask,
     r"mask values other than 0/1 \(2\.0\) in frames 5 \(1 frame\)"),
    ("mask NaN", lambda p: np.save(mask(p), np.array([1, np.nan, 1, 1, 1, 1, 1, 1.0])), mask,
     r"mask values other than 0/1 \(nan\) in frames 1 \(1 frame\)"),
    ("mask 2-D", lambda p: np.save(mask(p), np.ones((T, 1))), mask,
     r"is 2-D, shape \(8, 1\); expected \(T\)"),
    ("mask strings", lambda p: np.save(mask(p), np.array(["1"] * T)), mask,
     r"dtype <U1 \(str\); expected bool or signed int or unsigned int or float"),
    ("missing wav", lambda p: audio(p).unlink(), audio,
     r"missing file \(also looked in separated_audio/\)"),
    ("garbage wav", lambda p: audio(p).write_bytes(bytes(range(256)) * 4), audio,
     r"unreadable audio \(.+\)"),
    ("headerless wav", lambda p: audio(p).write_bytes(audio(p).read_bytes()[:30]), audio,
     r"unreadable audio \(.+\)"),
    ("truncated wav", lambda p: audio(p).write_bytes(audio(p).read_bytes()[:N * 2]), audio,
     r"audio has \d+ samples, expected 12800; shorter by \d+ samples"),
    ("empty wav", lambda p: sf.write(audio(p), np.zeros(0, np.float32), AUDIO_SAMPLE_RATE),
     audio, r"empty audio \(0 samples\)"),
    ("stereo", lambda p: sf.write(audio(p), wave(N, 2), AUDIO_SAMPLE_RATE), audio,
     r"has 2 channels; expected a mono track"),
    ("4 kHz", lambda p: sf.write(audio(p), wave(N // 12), 4000), audio,
     r"sample rate 4000 Hz; expected 48000 Hz and cannot resample from 4000 Hz"),
    ("odd rate", lambda p: sf.write(audio(p), wave(N), 47_999), audio,
     r"sample rate 47999 Hz; expected 48000 Hz and cannot resample"),
    ("short audio", lambda p: sf.write(audio(p), wave(N - SAMPLES_PER_FRAME - 1),
                                       AUDIO_SAMPLE_RATE), audio,
     r"audio has 11199 samples, expected 12800; shorter by 1601 samples \(more than the 1600"),
    ("long audio", lambda p: sf.write(audio(p), wave(N + 2 * SAMPLES_PER_FRAME),
                                      AUDIO_SAMPLE_RATE), audio,
     r"audio has 16000 samples, expected 12800; longer by 3200 samples"),
    ("NaN audio", lambda p: sf.write(audio(p), np.where(np.arange(N) == 9, np.nan, wave(N)),
                                     AUDIO_SAMPLE_RATE, subtype="FLOAT"), audio,
     r"NaN/inf audio samples \(1, first at sample 9\)"),
]


def _broken_header() -> bytes:
    """A version 1.0 header whose dict stops mid-way but whose length field is consistent."""
    text = b"{'descr': '<f4', 'fortran_order': False, 'shape': (8, ".ljust(63) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text


def _npz_bytes(pair: PairRecord) -> bytes:
    out = pair.folder / "x.npz"
    np.savez(out, a=np.zeros((T, 63)))
    return out.read_bytes()


@pytest.mark.parametrize("name, breaks, culprit, reason", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_clear_data_problem(pair, name, breaks, culprit, reason):
    breaks(pair)
    path = culprit(pair)
    with pytest.raises(DataProblem) as info:  # any other exception type fails the test
        load_person(pair, PERSON)
    problem = info.value
    assert problem.path == path
    assert str(problem) == f"{path}: {problem.reason}"
    assert "\n" not in str(problem)
    assert re.search(reason, problem.reason), problem.reason
    # The partner's files are untouched and still load.
    assert load_person(pair, "WBM368").length == T


def test_nonfinite_parameters_mark_tracked_frames_untracked(pair):
    """NaN/inf in tracked frames: those frames become untracked, with a warning naming the file
    and frames; in untracked frames: allowed. Both are filled, so every array is finite."""
    nan_frames(param(pair), (2, 3, 6))
    nan_frames(param(pair, "smplx_mesh_transl"), (7,), -np.inf, 3)
    before = load_person(pair, "WBM368")  # the partner, untouched
    valid = np.ones(T, np.uint8)
    valid[6] = 0
    np.save(mask(pair), valid)
    arrays = load_person(pair, PERSON)
    assert list(np.flatnonzero(~arrays.valid)) == [2, 3, 6, 7]
    assert arrays.nonfinite == {"tracked": 3, "untracked": 1}
    assert any(str(param(pair)) in w and "frames 2-3 (2 frames)" in w for w in arrays.warnings)
    assert any("smplx_mesh_transl" in w and "frames 7 (1 frame)" in w for w in arrays.warnings)
    assert all(np.isfinite(v).all() for v in arrays.params.values())
    assert before.length == T


def test_good_sequence_loads_read_only(pair):
    arrays = load_person(pair, PERSON)
    assert arrays.warnings == []
    assert not arrays.params["betas"].flags.writeable  # memory-mapped, read-only


def test_big_endian_params_come_back_native(pair):
    x = np.linspace(-1, 1, T * 63).reshape(T, 63).astype(">f8")
    np.save(param(pair), x)
    body_pose = load_person(pair, PERSON).params["body_pose"]
    assert body_pose.dtype == np.float64 and body_pose.dtype.isnative
    np.testing.assert_array_equal(body_pose, x)


@pytest.mark.parametrize("stored", [
    np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=bool),
    np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=np.int8),
    np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=np.uint8),
    np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=np.float64),
    np.array([1, 0, 1, 1, 0, 1, 1, 1], dtype=">f4"),  # big-endian storage
])
def test_mask_storage_forms(pair, stored):
    np.save(mask(pair), stored)
    valid = load_person(pair, PERSON).valid
    assert valid.dtype == bool
    np.testing.assert_array_equal(valid, stored.astype(bool))


@pytest.mark.parametrize("n, note", [(N - 100, "100 samples short; zero-padded to 12800"),
                                     (N - SAMPLES_PER_FRAME, "1600 samples short"),
                                     (N + 100, "100 samples long; trimmed to 12800")])
def test_audio_within_one_frame_is_fitted_with_a_warning(pair, n, note):
    x = wave(n)
    sf.write(audio(pair), x, AUDIO_SAMPLE_RATE, subtype="FLOAT")
    arrays = load_person(pair, PERSON)
    assert arrays.audio.shape == (N,) and arrays.audio.dtype == np.float32
    keep = min(n, N)
    np.testing.assert_array_equal(arrays.audio[:keep], x[:keep])
    assert not arrays.audio[keep:].any()
    warning, = arrays.warnings
    assert warning.startswith(str(audio(pair))) and note in warning


def test_plausible_rate_is_resampled_with_a_warning(pair):
    seconds = N / AUDIO_SAMPLE_RATE
    t = np.arange(round(seconds * 44_100)) / 44_100
    sf.write(audio(pair), 0.3 * np.sin(2 * np.pi * 440 * t), 44_100, subtype="FLOAT")
    arrays = load_person(pair, PERSON)
    assert arrays.audio.shape == (N,)
    assert "resampled from 44100 Hz to 48000 Hz" in arrays.warnings[0]
    # The 440 Hz tone survives: compare away from the edges, where the filter has support.
    want = 0.3 * np.sin(2 * np.pi * 440 * np.arange(N) / AUDIO_SAMPLE_RATE)
    np.testing.assert_allclose(arrays.audio[500:-500], want[500:-500], atol=2e-3)


# ----------------------------------------------------------------------------- generic loaders

def test_load_npy_without_length_and_without_mmap(tmp_path):
    path = tmp_path / "x.npy"
    np.save(path, np.arange(12, dtype=np.float64).reshape(4, 3))
    a = load_npy(path, (3,), "f", mmap=False)
    assert a.flags.writeable and a.shape == (4, 3)
    with pytest.raises(DataProblem, match="not a regular file"):
        load_npy(tmp_path, (3,), "f")


def test_load_wav_without_expected_length(tmp_path):
    path = tmp_path / "x.wav"
    sf.write(path, wave(1000), 16_000, subtype="PCM_16")
    x, warnings = load_wav(path, AUDIO_SAMPLE_RATE)
    assert x.shape == (3000,) and x.dtype == np.float32
    assert len(warnings) == 1


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_nonfinite_frames_are_named_exactly(data):
    import tempfile

    length = data.draw(st.integers(1, 300))
    bad = data.draw(st.sets(st.integers(0, length - 1), max_size=length))
    x = np.zeros((length, 4), np.float32)
    for f in bad:
        x[f, data.draw(st.integers(0, 3))] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.npy"
        np.save(path, x)
        if not bad:
            assert load_npy(path, (4,), "f", length).shape == (length, 4)
            return
        with pytest.raises(DataProblem) as info:
            load_npy(path, (4,), "f", length)
    assert info.value.reason == f"NaN/inf values in frames {format_frames(np.array(sorted(bad)))}"


@settings(max_examples=100, deadline=None)
@given(st.sets(st.integers(0, 10_000), min_size=1, max_size=200))
def test_format_frames_lists_exactly_the_frames(frames):
    text = format_frames(np.array(sorted(frames)), limit=10**6)
    ranges, count = re.fullmatch(r"(.*) \((\d+) frames?\)", text).groups()
    listed = set()
    for part in ranges.split(", "):
        a, _, b = part.partition("-")
        listed.update(range(int(a), int(b or a) + 1))
    assert listed == frames and int(count) == len(frames)


def test_mask_loader_direct(tmp_path):
    path = tmp_path / "m.npy"
    np.save(path, np.array([0, 1, 1], np.int32))
    np.testing.assert_array_equal(load_mask(path, 3), [False, True, True])
    np.save(path, np.array([0, -1, 1], np.int32))
    with pytest.raises(DataProblem, match=r"other than 0/1 \(-1\) in frames 1 \(1 frame\)"):
        load_mask(path, 3)


# ----------------------------------------------------------------------------- fuzzing

def _good_npy_bytes() -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.linspace(0, 1, T * 3, dtype=np.float32).reshape(T, 3))
    return buf.getvalue()


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_corrupted_npy_never_escapes_as_another_error(data):
    import tempfile

    raw = bytearray(_good_npy_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, 127))  # the header, where corruption is most confusing
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.npy"
        path.write_bytes(bytes(raw[:cut]))
        try:
            x = load_npy(path, (3,), "f", T)
        except DataProblem as problem:
            assert problem.path == path and "\n" not in str(problem)
        else:
            assert x.shape == (T, 3)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_corrupted_wav_never_escapes_as_another_error(data):
    import io
    import tempfile

    buf = io.BytesIO()
    sf.write(buf, wave(N), AUDIO_SAMPLE_RATE, format="WAV", subtype="PCM_16")
    raw = bytearray(buf.getvalue())
    for _ in range(data.draw(st.integers(1, 4))):
        raw[data.draw(st.integers(0, 63))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.wav"
        path.write_bytes(bytes(raw[:cut]))
        try:
            x, _ = load_wav(path, AUDIO_SAMPLE_RATE, N, tolerance=SAMPLES_PER_FRAME)
        except DataProblem as problem:
            assert problem.path == path and "\n" not in str(problem)
        else:
            assert x.shape == (N,) and x.dtype == np.float32


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([0.0, 1.5, np.nan, np.inf]), min_size=1, max_size=12))
def test_fill_nonfinite_frames_holds_the_nearest_earlier_finite_frame(values):
    from sarah_data.loading import fill_nonfinite_frames, nonfinite_frames

    array = np.stack([np.array(values), np.arange(len(values), dtype=float)], 1)
    bad = nonfinite_frames(array)
    filled = fill_nonfinite_frames(array, bad)
    assert np.isfinite(filled).all()
    good = np.setdiff1d(np.arange(len(values)), bad)
    np.testing.assert_array_equal(filled[good], array[good])  # finite frames untouched
    for frame in bad:
        earlier = good[good < frame]
        source = earlier[-1] if earlier.size else (good[0] if good.size else None)
        expected = array[source] if source is not None else np.zeros(2)
        np.testing.assert_array_equal(filled[frame], expected)
