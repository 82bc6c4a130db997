"""sarah-generate end to end: raw files and shard windows in, motion.npz + plots out, errors."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import soundfile as sf
from PIL import Image

from sarah_cli.generate import main
from sarah_data import icosahedron
from sarah_data.constants import JOINT_NAMES, NUM_JOINTS
from sarah_data.frames import rotation_about_y, window_transform
from sarah_data.shards import (MANIFEST_NAME, Manifest, ProcessedPerson, ProcessedSequence,
                               ShardAttrs, ShardWriter, write_manifest)
from sarah_models.training.checkpoint import save_checkpoint
from sarah_models.generation.outputs import head_gaze
from test_stream import SHELL, tiny_models

LOGMEL_DIM = 80
FRAMES = 16


def save_run(folder, audio_dim=LOGMEL_DIM, stage="flow", features="logmel", shell_points=SHELL):
    config, dims, vae, flow, normalizer = tiny_models(audio_dim=audio_dim, audio_mean=-8.0,
                                                      audio_std=4.0, shell_points=shell_points)
    folder.mkdir(parents=True, exist_ok=True)
    payload = {"stage": stage, "step": 3, "total_steps": 3, "config": config.to_dict(),
               "dims": dims, "features": features, "normalizer": normalizer.state_dict(),
               "vae": vae.state_dict()}
    if stage == "flow":
        payload["flow"] = flow.state_dict()
    save_checkpoint(folder / f"{stage}.pt", payload)
    return folder


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return save_run(tmp_path_factory.mktemp("runs") / "tiny")


def write_wav(path, seconds, rate, freq, channels=1, seed=0):
    t = np.arange(int(seconds * rate)) / rate
    wave = 0.3 * np.sin(2 * np.pi * freq * t) * (np.sin(2 * np.pi * 0.9 * t) > 0)
    wave += 0.01 * np.random.default_rng(seed).normal(size=t.size)
    sf.write(path, np.repeat(wave[:, None], channels, 1).astype(np.float32), rate)
    return path


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    folder = tmp_path_factory.mktemp("raw")
    angle = np.linspace(0, 1.5, 20)
    trajectory = np.stack([2 * np.sin(angle), 2 * np.cos(angle)], 1)
    np.savetxt(folder / "traj.csv", trajectory, delimiter=",", header="x,z", comments="")
    return {"traj": folder / "traj.csv", "trajectory": trajectory,
            "agent": write_wav(folder / "a.wav", 0.8, 16_000, 220, channels=2),
            "user": write_wav(folder / "b.wav", 0.8, 22_050, 150, seed=1),
            "short": write_wav(folder / "short.wav", 0.3, 16_000, 150)}


def raw_args(run, raw, out, *extra):
    return ["--run", str(run), "--user-trajectory", str(raw["traj"]), "--agent-audio",
            str(raw["agent"]), "--user-audio", str(raw["user"]), "--out", str(out),
            "--device", "cpu", "--frames", str(FRAMES), *extra]


def test_raw_files_end_to_end(run_dir, raw, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(raw_args(run_dir, raw, out, "--gaze", "0.8", "--seed", "0")) == 0
    printed = capsys.readouterr().out
    assert "frames/s" in printed and "p50" in printed and "p99" in printed
    assert "generated motion: gaze score" in printed and "ground truth" not in printed  # raw
    data = np.load(out / "motion.npz", allow_pickle=False)
    assert data["icosahedra"].shape == (FRAMES, NUM_JOINTS, 12, 3)
    assert data["shell"].shape == (FRAMES, SHELL, 3)
    assert int(data["fps"]) == 30 and float(data["gaze_target"]) == pytest.approx(0.8)
    np.testing.assert_allclose(data["user_head"], raw["trajectory"][:FRAMES], atol=1e-6)
    assert data["agent_audio"].shape == data["user_audio"].shape == (FRAMES, LOGMEL_DIM)
    positions, rotations = icosahedron.decode(data["icosahedra"])
    np.testing.assert_allclose(data["joint_positions"], positions, atol=1e-6)
    np.testing.assert_allclose(data["joint_rotations"], rotations, atol=1e-6)
    np.testing.assert_allclose(data["gaze_score"],
                               head_gaze(positions, rotations, data["user_head"]), atol=1e-6)
    assert data["agent_speaking"].shape == (FRAMES,) and data["agent_speaking"].dtype == bool
    settings = json.loads(str(data["settings"]))
    assert settings["stream"]["steps"] == 4 and settings["stream"]["cfg_scale"] == 1.3
    # Whose bones: this model's decoding keeps none (the paper's), and the line says so.
    assert settings["skeleton"].startswith("the decoder's own bones")
    assert f"skeleton: {settings['skeleton']}" in printed
    assert str(data["source_kind"]) == "raw"
    with Image.open(out / "topview.png") as png:
        assert png.format == "PNG" and png.size[0] > 100
    with Image.open(out / "skeleton.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames == math.ceil(FRAMES / 3)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_same_seed_same_motion_and_gaze_none(run_dir, raw, tmp_path):
    def motion(name, *extra):
        assert main(raw_args(run_dir, raw, tmp_path / name, "--no-animation", *extra)) == 0
        assert not (tmp_path / name / "skeleton.gif").exists()
        return np.load(tmp_path / name / "motion.npz")

    # Bit for bit needs one thread count (the automatic one can change with the load).
    a, b = motion("a", "--seed", "1", "--threads", "1"), motion("b", "--seed", "1", "--threads", "1")
    assert np.array_equal(a["icosahedra"], b["icosahedra"])
    assert not np.array_equal(a["icosahedra"], motion("c", "--seed", "2")["icosahedra"])
    none = motion("d", "--seed", "1", "--gaze", "none")
    assert math.isnan(float(none["gaze_target"]))
    assert not np.allclose(a["icosahedra"], none["icosahedra"], atol=1e-5)


def test_offline_equals_streaming_for_one_euler_step(run_dir, raw, tmp_path):
    exact = ["--no-animation", "--solver", "euler", "--steps", "1", "--history", "all"]
    assert main(raw_args(run_dir, raw, tmp_path / "s", *exact)) == 0
    assert main(raw_args(run_dir, raw, tmp_path / "o", *exact, "--offline")) == 0
    streamed, offline = (np.load(tmp_path / n / "motion.npz") for n in ("s", "o"))
    np.testing.assert_allclose(streamed["icosahedra"], offline["icosahedra"], atol=1e-4)
    np.testing.assert_allclose(streamed["agent_audio"], offline["agent_audio"], atol=1e-5)


def test_trajectory_imputation_streams_the_offline_motion(run_dir, raw, tmp_path):
    """With the paper's solver (4 midpoint steps), a stream with trajectory imputation writes
    the motion the offline protocol writes."""
    assert main(raw_args(run_dir, raw, tmp_path / "s", "--no-animation",
                         "--imputation", "trajectory")) == 0
    assert main(raw_args(run_dir, raw, tmp_path / "o", "--no-animation", "--offline")) == 0
    streamed, offline = (np.load(tmp_path / n / "motion.npz") for n in ("s", "o"))
    np.testing.assert_allclose(streamed["icosahedra"], offline["icosahedra"], atol=1e-4)


def test_guidance_interval_reaches_the_sampler(run_dir, raw, tmp_path):
    """--guidance-interval holding none of the solver's flow times is --cfg 1; one holding all
    of them is the whole guidance."""
    def motion(name, *extra):
        assert main(raw_args(run_dir, raw, tmp_path / name, "--no-animation", "--threads", "1",
                             "--gaze", "none", *extra)) == 0
        return np.load(tmp_path / name / "motion.npz")["icosahedra"]

    guided = motion("guided", "--cfg", "4")
    unguided = motion("unguided", "--cfg", "1")
    assert np.abs(guided - unguided).max() > 1e-4
    np.testing.assert_allclose(motion("none", "--cfg", "4", "--guidance-interval", "0.9,1"),
                               unguided, atol=1e-4)
    np.testing.assert_array_equal(motion("all", "--cfg", "4", "--guidance-interval", "0,0.9"),
                                  guided)


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("sarah-generate: error:")
    return err


def test_one_line_errors(run_dir, raw, tmp_path, capsys):
    out = tmp_path / "out"
    assert "no such run folder or model file" in _error(capsys, raw_args(tmp_path / "nope", raw, out))
    (tmp_path / "empty").mkdir()
    assert "no such checkpoint" in _error(capsys, raw_args(tmp_path / "empty", raw, out))
    vae_run = save_run(tmp_path / "vae_only", stage="vae")
    assert "flow stage" in _error(capsys, raw_args(vae_run, raw, out, "--checkpoint", "vae.pt"))
    for bad in ("1.5", "high", "nan"):
        assert "--gaze" in _error(capsys, raw_args(run_dir, raw, out, "--gaze", bad))
    short = dict(raw, user=raw["short"])
    assert "shorter than the trajectory" in _error(capsys, raw_args(run_dir, short, out))
    narrow = save_run(tmp_path / "narrow", audio_dim=8)
    assert "mismatched feature extractor" in _error(capsys, raw_args(narrow, raw, out))
    assert "--frames must be >= 1" in _error(capsys, raw_args(run_dir, raw, out, "--frames", "0"))
    assert "'gpu' is not a device" in _error(capsys, raw_args(run_dir, raw, out, "--device", "gpu"))
    for text, words in (("x,z\n1,2\n3,abc\n", "line 3: '3,abc' is not two numbers"),
                        ("", "has no rows"), ("x,z\n", "has no rows"),
                        ("1,2,3\n", "line 1: 3 values"), ("1,2\n3,nan\n", "first at frame 1")):
        bad = tmp_path / "bad.csv"
        bad.write_text(text)
        assert words in _error(capsys, raw_args(run_dir, dict(raw, traj=bad), out))
    with pytest.raises(SystemExit):
        main(raw_args(run_dir, raw, out, "--history", "abc"))
    assert "--history: expected a whole number, got 'abc' (or 'all', or 'window')" in capsys.readouterr().err
    assert not out.exists()


# --------------------------------------------------------------------------- shard input

def make_person(rng, name, frames, features):
    yaw = 0.3 + np.cumsum(rng.normal(0, 0.02, frames))
    root_rotation = rotation_about_y(yaw)
    root_position = np.stack([1.0 + 0.01 * np.arange(frames), np.full(frames, 0.9),
                              -0.5 + np.zeros(frames)], 1)
    positions = root_position[:, None] + rng.normal(0, 0.3, (frames, NUM_JOINTS, 3))
    rotations = np.broadcast_to(root_rotation[:, None], (frames, NUM_JOINTS, 3, 3))
    return ProcessedPerson(
        name=name, icosahedra=icosahedron.encode(positions, rotations).astype(np.float32),
        shell=(root_position[:, None] + rng.normal(0, 0.3, (frames, SHELL, 3))).astype(np.float32),
        head=(root_position[:, [0, 2]] + rng.normal(0, 0.05, (frames, 2))).astype(np.float32),
        gaze=rng.uniform(-1, 1, frames).astype(np.float32), speaking=rng.random(frames) < 0.5,
        valid=np.arange(frames) < frames - 4, root_position=root_position.astype(np.float32),
        root_rotation=root_rotation.astype(np.float32),
        audio={f: rng.normal(-8, 4, (frames, LOGMEL_DIM)).astype(np.float32) for f in features})


def write_shards(root, features=("logmel",), frames=40, tracked=None):
    """One test sequence "seq-one" (persons AAA111, BBB222; the last 4 frames untracked), or with
    ``tracked`` {name: (start, stop) tracked for both} one sequence per name, in that order."""
    rng = np.random.default_rng(0)
    attrs = ShardAttrs(toolkit_version="0.1.0", joint_names=JOINT_NAMES,
                       icosahedron_template=icosahedron.TEMPLATE,
                       icosahedron_radius=icosahedron.DEFAULT_RADIUS,
                       shell_vertex_ids=np.arange(SHELL), body_model_name="procedural",
                       body_model_sha256="0" * 64, extractors={f: {} for f in features})
    sequences = []
    for name, run in (tracked or {"seq-one": None}).items():
        persons = [make_person(rng, person, frames, features) for person in ("AAA111", "BBB222")]
        if run is not None:
            valid = (np.arange(frames) >= run[0]) & (np.arange(frames) < run[1])
            persons = [dataclasses.replace(p, valid=valid) for p in persons]
        sequences.append(ProcessedSequence(name=name, session="c--one", split="test",
                                           persons=tuple(persons)))
    with ShardWriter(root, "test", attrs) as writer:
        for seq in sequences:
            writer.add(seq)
    write_manifest(root / MANIFEST_NAME, Manifest(toolkit_version="0.1.0", config={},
                                                  splits={"test": ["c--one"]},
                                                  shards=writer.close(), sequences=writer.entries))
    return sequences[0]


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    return root, write_shards(root)


def shard_args(run, root, out, *extra):
    return ["--run", str(run), "--shards", str(root), "--split", "test", "--out", str(out),
            "--no-animation", *extra]


def test_shard_window_end_to_end(run_dir, shards, tmp_path, capsys):
    root, seq = shards
    agent, user = seq.persons[1], seq.persons[0]
    out = tmp_path / "out"
    assert main(shard_args(run_dir, root, out, "--sequence", "seq-one", "--agent", "BBB222",
                           "--start", "4", "--frames", "18")) == 0
    # The real agent of the same window is measured beside the generated one.
    line = next(line for line in capsys.readouterr().out.splitlines()
                if line.startswith("generated motion:"))
    for name in ("gaze score", "foot slide", "wrist speed", "pelvis speed", "user distance",
                 "radial speed", "bone length"):
        assert name in line
    assert line.count("(ground truth") == 7
    data = np.load(out / "motion.npz")
    assert data["icosahedra"].shape[0] == 16  # rounded down to whole blocks of 4
    np.testing.assert_array_equal(data["user_head"], user.head[4:20])
    np.testing.assert_array_equal(data["agent_audio"], agent.audio["logmel"][4:20])
    np.testing.assert_array_equal(data["agent_speaking"], agent.speaking[4:20])
    expected = window_transform(agent.root_position[4], agent.root_rotation[4]).as_array()
    np.testing.assert_allclose(data["anchor"], expected, atol=1e-6)
    assert str(data["source_sequence"]) == "seq-one" and str(data["source_agent"]) == "BBB222"
    np.testing.assert_array_equal(data["source_reference_gaze"], agent.gaze[4:20])
    # Defaults: the split's first sequence, its first person, 400 frames capped at the tracked end.
    assert main(shard_args(run_dir, root, tmp_path / "d", "--frames", "8")) == 0
    default = np.load(tmp_path / "d" / "motion.npz")
    assert str(default["source_agent"]) == "AAA111" and default["icosahedra"].shape[0] == 8


def test_shard_errors(run_dir, shards, tmp_path, capsys):
    root, _ = shards
    out = tmp_path / "out"
    assert "no sequence 'other'" in _error(capsys, shard_args(run_dir, root, out, "--sequence",
                                                              "other"))
    assert "no person 'ZZZ'" in _error(capsys, shard_args(run_dir, root, out, "--agent", "ZZZ"))
    assert "not tracked" in _error(capsys, shard_args(run_dir, root, out, "--start", "20"))
    assert "outside" in _error(capsys, shard_args(run_dir, root, out, "--start", "99"))
    hubert_only = tmp_path / "hubert"
    write_shards(hubert_only, features=("hubert-large",))
    assert "mismatched feature extractor" in _error(capsys, shard_args(run_dir, hubert_only, out))
    assert "no manifest" in _error(capsys, shard_args(run_dir, tmp_path, out))


def test_default_window_is_a_tracked_run(run_dir, tmp_path, capsys):
    """Without --start, generation starts where both persons are tracked for --frames frames,
    in the split's first sequence that has such a run; an explicit --start is taken as given."""
    root = tmp_path / "shards"
    write_shards(root, tracked={"seq-a": (10, 20), "seq-b": (5, 40)})

    def source(*extra):
        out = tmp_path / f"out{len(list(tmp_path.iterdir()))}"
        assert main(shard_args(run_dir, root, out, *extra)) == 0
        data = np.load(out / "motion.npz")
        return str(data["source_sequence"]), int(data["source_start"]), data["icosahedra"].shape[0]

    assert source("--frames", "16") == ("seq-b", 5, 16)  # seq-a's run of 10 is too short
    assert source("--frames", "8") == ("seq-a", 10, 8)
    assert source("--sequence", "seq-a", "--frames", "16") == ("seq-a", 10, 8)  # its longest run
    assert source("--agent", "BBB222", "--frames", "400") == ("seq-b", 5, 32)  # longest anywhere
    assert "not tracked" in _error(capsys, shard_args(run_dir, root, tmp_path / "x", "--start", "0"))


def test_prepared_fixture_shards(prepared_shards, tmp_path):
    """The demo's command on shards made by sarah-prep from fixture dyads (default sequence and
    agent of the test split)."""
    from sarah_data.shards import ShardSet

    shard_set = ShardSet(prepared_shards)
    shell_points = len(shard_set.attrs.shell_vertex_ids)
    shard_set.close()
    run = save_run(tmp_path / "run", shell_points=shell_points)
    out = tmp_path / "out"
    assert main(["--run", str(run), "--shards", str(prepared_shards), "--split", "test",
                 "--gaze", "0.8", "--frames", "12", "--out", str(out), "--no-animation"]) == 0
    data = np.load(out / "motion.npz")
    assert data["icosahedra"].shape == (12, NUM_JOINTS, 12, 3)
    assert data["shell"].shape == (12, shell_points, 3)
    assert np.isfinite(data["joint_positions"]).all()


def test_speed_paths_match_the_plain_models(run_dir, raw, tmp_path):
    """--speed fp32 (the default) is exact; int8 stays within the documented 1 mm."""
    motion = {}
    for speed in ("none", "fp32", "int8"):
        out = tmp_path / speed
        assert main(raw_args(run_dir, raw, out, "--gaze", "0.8", "--speed", speed, "--no-animation",
                             "--threads", "1")) == 0
        motion[speed] = np.load(out / "motion.npz", allow_pickle=False)["joint_positions"]
    np.testing.assert_array_equal(motion["fp32"], motion["none"])
    assert np.abs(motion["int8"] - motion["none"]).max() < 1e-3


def test_pad_and_mixed_stereo_warnings(run_dir, raw, tmp_path, capsys):
    """--pad pads short audio with silence (said so); a stereo file whose channels are two
    different signals is averaged with a warning; the GIF step says what it is doing."""
    short = dict(raw, user=raw["short"])
    assert main(raw_args(run_dir, short, tmp_path / "padded", "--pad")) == 0
    printed = capsys.readouterr().out
    assert "padded with silence" in printed and "drawing" in printed and "skeleton.gif" in printed
    rate = 16_000
    t = np.arange(rate) / rate
    two_voices = np.stack([np.sin(2 * np.pi * 180 * t), np.sign(np.sin(2 * np.pi * 3 * t)) *
                           np.random.default_rng(0).normal(size=t.size)], 1) * 0.2
    sf.write(tmp_path / "mixed.wav", two_voices.astype(np.float32), rate)
    mixed = dict(raw, agent=tmp_path / "mixed.wav")
    assert main(raw_args(run_dir, mixed, tmp_path / "mixed", "--no-animation")) == 0
    assert "channels differ a lot" in capsys.readouterr().out
