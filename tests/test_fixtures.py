"""Generated fixture dyads: the exact Embody 3D layout, determinism, the CLI, and the behaviour the
truth file promises, measured through the project's own reader and body model."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from hypothesis import given, settings, strategies as st

from sarah_cli.fixtures import main as fixtures_main
from conftest import FIXTURE_RAW_ARGS
from sarah_data.constants import (AUDIO_SAMPLE_RATE, FPS, JOINT, NUM_BETAS, SAMPLES_PER_FRAME,
                                  SMPLX_PARAM_WIDTHS)
from sarah_data.fixtures import layout
from sarah_data.fixtures.dyads import make_fixtures
from sarah_data.fixtures.motion import (MotionConfig, ModelGeometry, gaze_offsets,
                                        gesture_intervals, intervals_of)

REAL_MANIFEST = Path("/work/shared/embody3d/aiagent_dataset.json")
SEQUENCE_RE = re.compile(r"^(c--\d{8}--\d{4})--([A-Z]{3}\d{3})--([A-Z]{3}\d{3})--pilot--MotionPrior\d*"
                         r"--AIAGENT_scene_\d{3}--(\d{6})-(\d{6})$")
ENTRY_KEYS = ["length", "id", "text", "multiperson", "audio"]
PERSON_FOLDERS = set(SMPLX_PARAM_WIDTHS) | {"missing", "audio_separated"}


def _manifest(raw: Path) -> dict:
    return json.loads((raw / "aiagent" / "dataset.json").read_text())


def _truth(raw: Path) -> tuple[dict, np.lib.npyio.NpzFile]:
    return (json.loads((raw / layout.TRUTH_FILE).read_text()),
            np.load(raw / layout.TRUTH_ARRAYS_FILE, allow_pickle=False))


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- layout

def _shape(sequence: str) -> str:
    """A name with digits -> N and subject letters -> A: what two names of one format share."""
    parts = re.sub(r"\d", "N", sequence).split("--")
    parts[3:5] = [re.sub(r"[A-Z]", "A", p) for p in parts[3:5]]
    return "--".join(parts)


def test_sequence_names_have_a_real_format(fixture_raw_dir):
    real = json.loads(REAL_MANIFEST.read_text())
    real_shapes = {_shape(s) for entries in real.values() for s in entries}
    ours = {s for entries in _manifest(fixture_raw_dir).values() for s in entries}
    assert ours and all(_shape(s) in real_shapes and SEQUENCE_RE.match(s) for s in ours)


def test_manifest_has_upstream_structure(fixture_raw_dir):
    manifest = _manifest(fixture_raw_dir)
    real = json.loads(REAL_MANIFEST.read_text())
    real_keys = list(next(iter(next(iter(real.values())).values())))
    assert real_keys == ENTRY_KEYS
    sequences = {s for entries in manifest.values() for s in entries}
    expected = FIXTURE_RAW_ARGS["sessions"] * FIXTURE_RAW_ARGS["sequences_per_session"]
    assert len(sequences) == expected
    sessions = {SEQUENCE_RE.match(s).group(1) for s in sequences}
    assert len(sessions) == FIXTURE_RAW_ARGS["sessions"]
    ids = []
    for subject, entries in manifest.items():
        assert re.fullmatch(r"[A-Z]{3}\d{3}", subject)
        for sequence, entry in entries.items():
            session, a, b, start, end = SEQUENCE_RE.match(sequence).groups()
            assert list(entry) == ENTRY_KEYS and entry["text"] is None
            assert subject in (a, b) and entry["multiperson"] == [b if subject == a else a]
            partner = manifest[entry["multiperson"][0]][sequence]
            assert partner["multiperson"] == [subject] and partner["length"] == entry["length"]
            assert entry["length"] == int(end) - int(start) + 1 == round(FIXTURE_RAW_ARGS["seconds"] * FPS)
            assert (entry["audio"] is None) == (partner["audio"] is None)
            if entry["audio"] is not None:  # an absolute path on the producer's machine
                assert entry["audio"] == (f"/social_ai/datasets/opensource_v5/aiagent/{sequence}/"
                                          f"{subject}/audio_separated/{sequence}.wav")
                assert not Path(entry["audio"]).exists()
            ids.append(entry["id"])
    assert sorted(ids) == list(range(2 * expected))
    without_audio = {s for entries in manifest.values() for s, e in entries.items() if e["audio"] is None}
    assert len(without_audio) >= 1  # 4 sequences: every 6th from the 4th has no audio


def test_person_files_have_embody_shapes_and_dtypes(fixture_raw_dir):
    manifest = _manifest(fixture_raw_dir)
    saw_untracked = False
    for subject, entries in manifest.items():
        for sequence, entry in entries.items():
            base = fixture_raw_dir / "aiagent" / sequence / subject
            T = entry["length"]
            folders = {p.name for p in base.iterdir()}
            assert folders == (PERSON_FOLDERS if entry["audio"] else PERSON_FOLDERS - {"audio_separated"})
            for folder, width in SMPLX_PARAM_WIDTHS.items():
                files = list((base / folder).iterdir())
                assert [f.name for f in files] == [f"{sequence}.npy"]
                array = np.load(files[0], allow_pickle=False)
                assert array.shape == (T, width) and array.dtype == np.float32
                assert np.isfinite(array).all()
            betas = np.load(base / "smplx_mesh_betas" / f"{sequence}.npy")
            assert np.all(betas == betas[0]) and 0 < np.abs(betas[0]).max() < 3
            mask = np.load(base / "missing" / f"{sequence}.npy", allow_pickle=False)
            assert mask.shape == (T,) and mask.dtype == np.float32 and set(np.unique(mask)) <= {0.0, 1.0}
            assert mask[0] == 1 and mask.mean() > 0.8
            saw_untracked |= bool((mask == 0).any())
            if entry["audio"]:
                wave, rate = sf.read(base / "audio_separated" / f"{sequence}.wav")
                info = sf.info(base / "audio_separated" / f"{sequence}.wav")
                assert rate == AUDIO_SAMPLE_RATE and info.channels == 1
                assert wave.shape == (T * SAMPLES_PER_FRAME,) and np.abs(wave).max() > 0.01
    assert saw_untracked


def test_body_model_and_truth_files(fixture_raw_dir):
    assert [p.name for p in (fixture_raw_dir / "body_models").iterdir()] == [layout.BODY_MODEL_FILE]
    assert {p.name for p in fixture_raw_dir.iterdir()} == {
        "aiagent", "body_models", layout.TRUTH_FILE, layout.TRUTH_ARRAYS_FILE}
    truth, arrays = _truth(fixture_raw_dir)
    manifest = _manifest(fixture_raw_dir)
    assert set(truth["sequences"]) == {s for e in manifest.values() for s in e}
    for sequence, entry in truth["sequences"].items():
        T = entry["num_frames"]
        assert {entry["agent"], entry["user"]} == set(entry["persons"])
        assert 0.0 <= entry["gaze_propensity"] <= 1.0
        assert entry["has_audio"] == (manifest[entry["agent"]][sequence]["audio"] is not None)
        for subject, person in entry["persons"].items():
            assert person["role"] == ("agent" if subject == entry["agent"] else "user")
            for key, shape in {"head_yaw": (T,), "head_xz": (T, 2), "root_xz": (T, 2),
                               "root_yaw": (T,), "gaze_cos": (T,), "speaking": (T,)}.items():
                assert arrays[f"{sequence}/{subject}/{key}"].shape == shape
            speaking = arrays[f"{sequence}/{subject}/speaking"]
            assert intervals_of(speaking) == [tuple(p) for p in person["speaking_intervals"]]
            for start, end in person["gesture_intervals"]:  # gestures happen while speaking
                assert speaking[start:end].mean() > 0.7
            mask = np.load(fixture_raw_dir / "aiagent" / sequence / subject / "missing" / f"{sequence}.npy")
            assert intervals_of(mask == 0) == [tuple(p) for p in person["untracked_intervals"]]
            assert all(0 <= s < e <= T for s, e in person["step_intervals"])


def test_read_by_the_project_reader(fixture_raw_dir):
    from sarah_data.embody3d import check_files, load_person, read_corpus

    corpus = read_corpus(fixture_raw_dir / "aiagent", require_audio=False)
    assert not corpus.problems and not corpus.skipped and len(corpus.pairs) == 4
    assert not check_files(corpus)
    pair = corpus.pairs[0]
    person = load_person(pair, pair.persons[0])
    stored = np.load(fixture_raw_dir / "aiagent" / pair.sequence / pair.persons[0] /
                     "smplx_mesh_body_pose" / f"{pair.sequence}.npy")
    np.testing.assert_array_equal(person.params["body_pose"], stored)
    strict = read_corpus(fixture_raw_dir / "aiagent")
    assert len(strict.pairs) == 3 and [s.sequence for s in strict.skipped] == \
        [p.sequence for p in corpus.pairs if not p.has_audio]


# ----------------------------------------------------------------------------- determinism, CLI

def test_same_arguments_give_byte_identical_files(fixture_raw_dir, tmp_path):
    model = fixture_raw_dir / "body_models" / layout.BODY_MODEL_FILE
    make_fixtures(tmp_path, **FIXTURE_RAW_ARGS, body_model=model)
    first, second = _tree_bytes(fixture_raw_dir), _tree_bytes(tmp_path)
    assert first.keys() == second.keys()
    assert [k for k in first if first[k] != second[k]] == []
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]


def test_cli_writes_a_tree_and_prints_one_line(fixture_raw_dir, tmp_path, capsys):
    model = fixture_raw_dir / "body_models" / layout.BODY_MODEL_FILE
    code = fixtures_main([str(tmp_path / "raw"), "--sessions", "1", "--sequences-per-session", "3",
                          "--seconds", "3", "--seed", "5", "--body-model", str(model), "--quiet"])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 0 and len(out) == 1 and "3 dyad sequences" in out[0] and "1 sessions" in out[0]
    manifest = _manifest(tmp_path / "raw")
    sequences = {s for e in manifest.values() for s in e}
    assert len(manifest) == 2 and len(sequences) == 3
    assert not sequences & {s for e in _manifest(fixture_raw_dir).values() for s in e}


def test_cli_rejects_bad_arguments(tmp_path, capsys):
    assert fixtures_main([str(tmp_path), "--seconds", "0.5", "--quiet"]) == 2
    assert "seconds" in capsys.readouterr().err


def test_cli_help_runs_as_a_module():
    result = subprocess.run([sys.executable, "-m", "sarah_cli.fixtures", "--help"], capture_output=True,
                            text=True, cwd=Path(__file__).resolve().parents[1], timeout=60)
    assert result.returncode == 0
    assert "--sessions" in result.stdout and "(default: 4)" in result.stdout


def test_bad_body_model_file_is_named(tmp_path):
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="broken.npz"):
        ModelGeometry.from_file(bad)


# ----------------------------------------------------------------------------- behaviour

@settings(max_examples=25, deadline=None)
@given(p=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_gaze_propensity_sets_the_share_of_eye_contact(p, seed):
    cfg = MotionConfig()
    offsets = gaze_offsets(60 * 60 * FPS, p, np.random.default_rng(seed), cfg)
    averted = np.abs(offsets) > math.radians(20.0)
    assert abs(averted.mean() - (1.0 - p)) < 0.2
    if averted.any():  # aversion turns the head well away, further for low propensity
        low, high = cfg.aversion_degrees
        assert np.median(np.abs(offsets[averted])) > math.radians(0.5 * (low + high * (1 - p)))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=300))
def test_gestures_cover_long_speaking_runs_and_bridge_only_short_pauses(flags):
    speaking = np.array(flags)
    cfg = MotionConfig()
    covered = np.zeros(len(speaking), dtype=bool)
    for start, end in gesture_intervals(speaking, cfg):
        assert speaking[start] and speaking[end - 1] and end - start >= cfg.gesture_min_seconds * FPS
        assert all(e - s < cfg.gesture_merge_seconds * FPS for s, e in intervals_of(~speaking[start:end]))
        covered[start:end] = True
    for start, end in intervals_of(speaking):
        if end - start >= cfg.gesture_min_seconds * FPS:
            assert covered[start:end].all()


def test_partners_stay_one_to_three_metres_apart(fixture_raw_dir):
    truth, arrays = _truth(fixture_raw_dir)
    for sequence, entry in truth["sequences"].items():
        agent = arrays[f"{sequence}/{entry['agent']}/root_xz"]
        user = arrays[f"{sequence}/{entry['user']}/root_xz"]
        distance = np.linalg.norm(agent - user, axis=1)
        assert 1.0 <= distance.min() and distance.max() <= 3.0


@pytest.fixture(scope="module")
def bodies(fixture_raw_dir):
    """BodyModel frames of every person, through the project's reader: {(sequence, subject): ...}."""
    from sarah_data.body.model import BodyModel
    from sarah_data.embody3d import load_person, read_corpus

    model = BodyModel.from_file(fixture_raw_dir / "body_models" / layout.BODY_MODEL_FILE, device="cpu")
    out = {}
    for pair in read_corpus(fixture_raw_dir / "aiagent", require_audio=False).pairs:
        for subject in pair.persons:
            person = load_person(pair, subject)
            out[pair.sequence, subject] = (model.forward(person.params), np.asarray(person.valid, bool))
    return out


def test_soles_touch_the_floor(fixture_raw_dir, bodies):
    import smplx
    import torch

    full = smplx.SMPLX(model_path=str(fixture_raw_dir / "body_models" / layout.BODY_MODEL_FILE),
                       num_betas=NUM_BETAS, use_pca=False, flat_hand_mean=True, ext="npz")
    for (sequence, subject), (frames, valid) in bodies.items():
        base = fixture_raw_dir / "aiagent" / sequence / subject
        keep = np.flatnonzero(valid)[::7]
        p = {k: torch.from_numpy(np.load(base / f"smplx_mesh_{k}" / f"{sequence}.npy")[keep])
             for k in ("betas", "body_pose", "global_orient", "transl", "left_hand_pose", "right_hand_pose")}
        face = {k: torch.zeros(len(keep), 3) for k in ("jaw_pose", "leye_pose", "reye_pose")}
        with torch.no_grad():
            vertices = full(**p, **face, expression=torch.zeros(len(keep), full.num_expression_coeffs),
                            return_verts=True).vertices.numpy()
        lowest = vertices[..., 1].min(axis=1)  # one foot is always planted, even mid-step
        assert np.abs(lowest).max() < 0.02, (sequence, subject, lowest.min(), lowest.max())


def test_feet_do_not_slide_outside_steps(fixture_raw_dir, bodies):
    truth, _ = _truth(fixture_raw_dir)
    feet = [JOINT[n] for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]
    stepping_total = 0
    for (sequence, subject), (frames, valid) in bodies.items():
        stepping = np.zeros(len(valid), dtype=bool)
        for start, end in truth["sequences"][sequence]["persons"][subject]["step_intervals"]:
            stepping[start:end] = True
        stepping_total += stepping.sum()
        speed = np.linalg.norm(np.diff(frames.joints[:, feet][..., [0, 2]], axis=0), axis=-1).max(-1) * FPS
        still = ~stepping[1:] & ~stepping[:-1] & valid[1:] & valid[:-1]
        assert still.sum() > 0.3 * len(valid)
        assert speed[still].max() < 0.03, (sequence, subject)
    assert stepping_total > 0


def test_a_standing_foot_stays_planted_during_steps(fixture_raw_dir, bodies):
    """The ground truth does not skate: the paper's metric on it is near its real-data 0.01."""
    from sarah_models.evaluation.metrics import foot_slide

    truth, _ = _truth(fixture_raw_dir)
    feet = [[JOINT[f"{side}_ankle"], JOINT[f"{side}_foot"]] for side in ("left", "right")]
    lifted = 0
    for (sequence, subject), (frames, valid) in bodies.items():
        assert foot_slide(frames.joints[valid]) < 0.005, (sequence, subject)
        for start, end in truth["sequences"][sequence]["persons"][subject]["step_intervals"]:
            if not valid[start:end].all():
                continue
            last = end - start - 1  # the step's progress is k / last at its frame start + k
            for half in (frames.joints[start:start + last // 2 + 1], frames.joints[start + (last + 1) // 2:end]):
                # One leg swings in each half while the other foot stands still.
                moved = [np.linalg.norm(half[:, f] - half[:1, f], axis=-1).max() for f in feet]
                assert min(moved) < 0.003, (sequence, subject, start)
                lifted += max(half[:, f, 1].max() - half[0, f, 1].min() for f in feet) > 0.05
    assert lifted > 0


def test_leg_solver_reaches_its_targets():
    """Hip, knee and ankle rotations put the ankle on its target with the foot level and turned."""
    from scipy.spatial.transform import Rotation

    from sarah_data.fixtures.legs import LEGS, solve_legs
    from sarah_data.frames import rotation_about_y as yaw_matrix

    rng = np.random.default_rng(0)
    rest = np.zeros((55, 3))
    for side, sign in enumerate((1.0, -1.0)):
        hip, knee, ankle = (JOINT[n] for n in LEGS[side])
        rest[hip], rest[knee], rest[ankle] = (sign * 0.09, 0.88, 0.0), (sign * 0.1, 0.5, 0.015), (sign * 0.1, 0.085, -0.01)
    T = 64
    pelvis_yaw = rng.uniform(-np.pi, np.pi, T)
    hips = rng.normal(0.0, 1.0, (2, T, 3))
    heading = pelvis_yaw + rng.uniform(-0.6, 0.6, (2, T))
    horizontal = rng.uniform(-0.25, 0.25, (2, T, 2))  # reachable: under the 0.795 m rest leg
    gap = np.stack([horizontal[..., 0], -rng.uniform(0.45, 0.7, (2, T)), horizontal[..., 1]], axis=-1)
    rotations = solve_legs(hips, pelvis_yaw, hips + gap, heading, rest)
    for side, (hip, knee, ankle) in enumerate(LEGS):
        hip, knee, ankle = JOINT[hip], JOINT[knee], JOINT[ankle]
        hip_global = yaw_matrix(pelvis_yaw) @ Rotation.from_rotvec(rotations[side, 0]).as_matrix()
        knee_global = hip_global @ Rotation.from_rotvec(rotations[side, 1]).as_matrix()
        reached = hips[side] + hip_global @ (rest[knee] - rest[hip]) + knee_global @ (rest[ankle] - rest[knee])
        np.testing.assert_allclose(reached, hips[side] + gap[side], atol=1e-9)
        foot = knee_global @ Rotation.from_rotvec(rotations[side, 2]).as_matrix()
        np.testing.assert_allclose(foot, yaw_matrix(heading[side]), atol=1e-9)
        assert (rotations[side, 1, :, 0] >= 0).all()  # the knee only flexes


def test_head_facing_matches_truth(fixture_raw_dir, bodies):
    from sarah_data.frames import yaw_of
    from sarah_data.gaze import gaze_score, head_trajectory

    truth, arrays = _truth(fixture_raw_dir)
    for (sequence, subject), (frames, valid) in bodies.items():
        entry = truth["sequences"][sequence]
        yaw = yaw_of(frames.rotations[:, JOINT["head"]])
        error = np.abs((yaw - arrays[f"{sequence}/{subject}/head_yaw"] + np.pi) % (2 * np.pi) - np.pi)
        assert np.degrees(error[valid].mean()) < 3.0
        head_xz = frames.joints[:, JOINT["head"]][:, [0, 2]]
        assert np.abs(head_xz - arrays[f"{sequence}/{subject}/head_xz"])[valid].max() < 0.01
        partner = entry["user"] if subject == entry["agent"] else entry["agent"]
        partner_frames, partner_valid = bodies[sequence, partner]
        both = valid & partner_valid
        score = gaze_score(frames.head_front, frames.head_back, head_trajectory(partner_frames.eye_mid))
        assert np.abs(score - arrays[f"{sequence}/{subject}/gaze_cos"])[both].mean() < 0.05


def test_wrists_move_more_while_speaking(fixture_raw_dir, bodies):
    _, arrays = _truth(fixture_raw_dir)
    speaking_speed, silent_speed = [], []
    for (sequence, subject), (frames, valid) in bodies.items():
        wrists = frames.joints[:, [JOINT["left_wrist"], JOINT["right_wrist"]]] - frames.joints[:, [JOINT["pelvis"]]]
        speed = np.linalg.norm(np.diff(wrists, axis=0), axis=-1).mean(-1) * FPS
        speaking = arrays[f"{sequence}/{subject}/speaking"][1:]
        ok = valid[1:] & valid[:-1]
        speaking_speed.append(speed[ok & speaking])
        silent_speed.append(speed[ok & ~speaking])
        # Arms hang down while listening: wrists below the shoulders.
        below = frames.joints[:, JOINT["left_wrist"], 1] < frames.joints[:, JOINT["left_shoulder"], 1] - 0.3
        assert below[1:][ok & ~speaking].mean() > 0.8
    assert np.concatenate(speaking_speed).mean() > 1.5 * np.concatenate(silent_speed).mean()
