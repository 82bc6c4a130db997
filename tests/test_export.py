"""sarah-export and the shareable model file: ground truth survives SMPL-X (through the `smplx`
package), BVH (through bvhio and Blender's own importer) and glTF (through Blender's); generated
motion exports with its body, and Blender shows its joints where its rotations disagree with them;
bad input is one line and writes nothing; model.safetensors generates what flow.pt does."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from sarah_cli.export import main
from sarah_data import icosahedron
from sarah_data.constants import JOINT_NAMES, NUM_JOINTS
from sarah_data.export.smplx_params import Y_UP_TO_Z_UP
from sarah_data.shards import ShardSet

HERE = Path(__file__).parent
GLTF_VALIDATOR = HERE.parent / ".cache" / "npm" / "node_modules" / "gltf-validator"


@pytest.fixture(scope="module")
def shard_person(prepared_shards):
    """(sequence, person, world joints (T, 55, 3)) of one prepared ground-truth person."""
    shards = ShardSet(prepared_shards)
    sequence = shards.sequences("train")[0]
    group = shards.group(sequence)
    person = str(group.attrs["persons"][1])
    joints, _ = icosahedron.decode(group[person]["icosahedra"][()].astype(np.float64))
    shards.close()
    return sequence, person, joints


def export(tmp_path, *argv):
    out = tmp_path / "out"
    return main([*map(str, argv), "--out", str(out)]), out


def smplx_joints(params, body_model_path):
    """Joints (T, 55, 3) of the AMASS-layout parameters through the smplx package itself."""
    import smplx

    model = smplx.create(str(body_model_path), model_type="smplx", gender="neutral",
                         num_betas=int(params["num_betas"]), use_pca=False,
                         flat_hand_mean=bool(params["flat_hand_mean"]))
    frames = len(params["trans"])

    def t(key, cut=slice(None)):
        return torch.tensor(params[key][:, cut], dtype=torch.float32)

    out = model(betas=torch.tensor(params["betas"], dtype=torch.float32)[None].expand(frames, -1),
                global_orient=t("root_orient"), body_pose=t("pose_body"), jaw_pose=t("pose_jaw"),
                leye_pose=t("pose_eye", slice(0, 3)), reye_pose=t("pose_eye", slice(3, 6)),
                left_hand_pose=t("pose_hand", slice(0, 45)),
                right_hand_pose=t("pose_hand", slice(45, 90)),
                transl=t("trans"), expression=torch.zeros(frames, 10))
    return out.joints[:, :NUM_JOINTS].detach().double().numpy()


def blender_probe(probe: str, path: Path, tmp_path: Path) -> dict:
    """What Blender's own importer makes of ``path``, as the probe script ``probe`` reports it;
    skips where Blender (or the NumPy its glTF importer needs) is not installed."""
    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Blender is not installed (.ci/run installs Debian's blender package)")
    out = tmp_path / "blender.json"
    run = subprocess.run([blender, "-b", "--factory-startup", "--python", str(HERE / probe), "--",
                          str(path), str(out)], capture_output=True, text=True, timeout=300)
    if not out.is_file() and "No module named 'numpy'" in run.stdout + run.stderr:
        pytest.skip("Blender's Python has no NumPy, which its glTF importer needs (.ci/run "
                    "installs Debian's python3-numpy)")
    assert out.is_file(), run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads(out.read_text())


def test_shards_hold_each_persons_body(prepared_shards, prep_raw_dir):
    from sarah_data.body import BodyModel

    body = BodyModel.from_file(prep_raw_dir / "body_models" / "SMPLX_PROCEDURAL.npz", device="cpu")
    shards = ShardSet(prepared_shards)
    sequence = shards.sequences()[0]
    seq = shards.read_sequence(sequence)
    shards.close()
    for person in seq.persons:
        assert person.betas.shape == (body.num_betas,) and person.gender == "neutral"
        assert np.abs(person.betas[:10]).max() > 0  # the fixtures give people their own shapes
        np.testing.assert_allclose(person.rest_joints, body.rest_joints(person.betas), atol=1e-6)
    assert not np.allclose(seq.persons[0].rest_joints, seq.persons[1].rest_joints)


@pytest.mark.parametrize("up", ["y", "z"])
def test_ground_truth_round_trips_through_the_smplx_package(prepared_shards, prep_raw_dir,
                                                            shard_person, tmp_path, capsys, up):
    sequence, person, joints = shard_person
    code, out = export(tmp_path, "--shards", prepared_shards, "--sequence", sequence,
                       "--person", person, "--format", "smplx", "--up", up)
    assert code == 0
    line = capsys.readouterr().out
    assert "joint residual to the motion: mean 0.000 mm" in line
    params = dict(np.load(out / f"{sequence}_{person}.smplx.npz", allow_pickle=False))
    assert params["poses"].shape == (len(joints), 165) and params["trans"].shape == (len(joints), 3)
    assert str(params["surface_model_type"]) == "smplx" and float(params["mocap_frame_rate"]) == 30
    assert str(params["up_axis"]) == up
    np.testing.assert_array_equal(params["poses"][:, 66:69], params["pose_jaw"])
    np.testing.assert_array_equal(params["poses"][:, 75:], params["pose_hand"])
    back = smplx_joints(params, prep_raw_dir / "body_models" / "SMPLX_PROCEDURAL.npz")
    if up == "z":
        back = back @ Y_UP_TO_Z_UP  # z up -> ours: the inverse rotation (orthogonal)
    error = np.linalg.norm(back - joints, axis=-1)
    assert error.max() < 1e-3, f"worst joint {1000 * error.max():.3f} mm"


@pytest.mark.parametrize("units", ["m", "cm"])
def test_bvh_read_by_an_independent_parser(prepared_shards, shard_person, tmp_path, units):
    import bvhio

    sequence, person, joints = shard_person
    code, out = export(tmp_path, "--shards", prepared_shards, "--sequence", sequence, "--person",
                       person, "--format", "bvh", "--bvh-units", units, "--start", 30, "--frames", 200)
    assert code == 0
    path = out / f"{sequence}_{person}_30-230.bvh"
    root = bvhio.readAsHierarchy(str(path))
    named = {joint.Name: joint for joint, _, _ in root.layout()}
    assert set(named) == set(JOINT_NAMES)
    scale = {"m": 1.0, "cm": 100.0}[units]
    assert root.getKeyframeRange() == (0, 199)
    worst = 0.0
    for frame in range(0, 200, 7):
        root.loadPose(frame)
        read = np.array([named[name].PositionWorld for name in JOINT_NAMES]) / scale
        worst = max(worst, np.linalg.norm(read - joints[30 + frame], axis=-1).max())
    assert worst < 1e-3, f"worst joint {1000 * worst:.3f} mm"


def test_blender_imports_the_bvh(prepared_shards, shard_person, tmp_path):
    sequence, person, joints = shard_person
    code, out = export(tmp_path, "--shards", prepared_shards, "--sequence", sequence,
                       "--person", person, "--format", "bvh")
    assert code == 0
    data = blender_probe("blender_bvh_probe.py", out / f"{sequence}_{person}.bvh", tmp_path)
    assert data["frame_range"] == [1, len(joints)] and data["fps"] == 30
    wrist = JOINT_NAMES.index("left_wrist")
    for frame, heads in data["heads"].items():
        ours = joints[int(frame) - 1, wrist]
        in_blender = np.array([ours[0], -ours[2], ours[1]])  # Blender is z up: (x, y, z) -> (x, -z, y)
        assert np.linalg.norm(np.array(heads["left_wrist"]) - in_blender) < 0.01


def test_blender_imports_the_glb(prepared_shards, shard_person, tmp_path):
    """The glTF through Blender's own importer (what game engines read too): an armature of the 55
    joints with the stick figure skinned to it, every frame at 30 fps, every joint where the
    ground truth's is."""
    sequence, person, joints = shard_person
    code, out = export(tmp_path, "--shards", prepared_shards, "--sequence", sequence,
                       "--person", person, "--format", "glb")
    assert code == 0
    glb = (out / f"{sequence}_{person}.glb").read_bytes()
    magic, version, length = struct.unpack("<III", glb[:12])
    assert (magic, version, length) == (0x46546C67, 2, len(glb))
    data = blender_probe("blender_gltf_probe.py", out / f"{sequence}_{person}.glb", tmp_path)
    assert data["frame_range"] == [0, len(joints) - 1] and data["fps"] == 30
    assert data["bones"] == NUM_JOINTS and data["meshes"] == ["body"]
    for frame, heads in data["heads"].items():
        ours = joints[int(frame)]
        in_blender = np.stack([ours[:, 0], -ours[:, 2], ours[:, 1]], axis=1)  # Blender is z up
        theirs = np.array([heads[name] for name in JOINT_NAMES])
        assert np.linalg.norm(theirs - in_blender, axis=-1).max() < 1e-3, frame


def test_the_glb_passes_the_khronos_validator(generated, tmp_path):
    """The reference glTF validator (what engines' importers follow) finds nothing: no error,
    no warning, no note."""
    node = shutil.which("node")
    if node is None or not GLTF_VALIDATOR.is_dir():
        pytest.skip(f"the Khronos glTF validator is not installed ({GLTF_VALIDATOR}: .ci/run "
                    f"installs it with npm)")
    code, out = export(tmp_path, generated, "--format", "glb")
    assert code == 0
    run = subprocess.run([node, str(HERE / "gltf_validate.js"), str(GLTF_VALIDATOR),
                          str(out / "gen.glb")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads(run.stdout)
    assert (report["errors"], report["warnings"], report["infos"]) == (0, 0, 0), report["messages"][:10]


def test_glb_quaternions_never_turn_the_long_way_between_frames():
    """q and -q are one rotation; an engine interpolating between two keys must not go round."""
    from scipy.spatial.transform import Rotation

    from sarah_data.export.gltf import continuous

    steps = Rotation.from_rotvec(np.random.default_rng(0).normal(scale=0.05, size=(200 * 3, 3)))
    path = Rotation.random(3, random_state=0)
    frames = [path]
    for t in range(1, 200):
        frames.append(steps[3 * t: 3 * t + 3] * frames[-1])
    raw = np.stack([f.as_quat() for f in frames])  # (200, 3, 4)
    raw[1::2] *= -1.0  # the same rotations, every other frame written the other way round
    smooth = continuous(raw)
    assert (np.sum(smooth[1:] * smooth[:-1], axis=-1) > 0.9).all()
    np.testing.assert_allclose(np.abs(np.sum(smooth * raw, axis=-1)), 1.0)


def test_blender_shows_the_joints_of_a_motion_whose_rotations_disagree(prepared_shards, generated,
                                                                        tmp_path):
    """A motion.npz as the decoding chain leaves it, joints moved and rotations not (here: ground
    truth with every rotation turned up to 20 degrees): in Blender the ankles and wrists stand
    where the motion's do."""
    from test_export_pose import person_motion, turned

    joints, rotations, rest_joints, betas = person_motion(prepared_shards, 60)
    motion = dict(np.load(generated, allow_pickle=False))
    motion.update(joint_positions=joints, joint_rotations=turned(rotations, 20.0, 0),
                  rest_joints=rest_joints, betas=betas)
    path = tmp_path / "turned" / "motion.npz"
    path.parent.mkdir()
    np.savez(path, **{k: v for k, v in motion.items() if k not in ("icosahedra", "shell")})
    code, out = export(tmp_path, path, "--format", "bvh")
    assert code == 0
    data = blender_probe("blender_bvh_probe.py", out / "turned.bvh", tmp_path)
    for frame, heads in data["heads"].items():
        for name in ("left_ankle", "right_ankle", "left_wrist", "right_wrist"):
            ours = joints[int(frame) - 1, JOINT_NAMES.index(name)]
            in_blender = np.array([ours[0], -ours[2], ours[1]])  # Blender is z up
            assert np.linalg.norm(np.array(heads[name]) - in_blender) < 1e-3, (frame, name)


@pytest.fixture(scope="module")
def generated(prepared_shards, tmp_path_factory):
    """motion.npz of a tiny random-weight run on a prepared shard window."""
    from sarah_cli.generate import main as generate
    from test_generate import save_run

    shards = ShardSet(prepared_shards)
    shell = len(shards.attrs.shell_vertex_ids)
    shards.close()
    root = tmp_path_factory.mktemp("generated")
    run = save_run(root / "run", shell_points=shell)
    assert generate(["--run", str(run), "--shards", str(prepared_shards), "--split", "test",
                     "--frames", "24", "--out", str(root / "gen"), "--no-animation"]) == 0
    return root / "gen" / "motion.npz"


def test_generated_motion_exports_with_the_agents_body(generated, tmp_path, capsys):
    import bvhio

    data = np.load(generated, allow_pickle=False)
    assert data["rest_joints"].shape == (NUM_JOINTS, 3) and "agent" in str(data["body_shape_source"])
    code, out = export(tmp_path, generated)
    assert code == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and all("joint residual to the motion" in line for line in lines)
    assert (out / "gen.glb").is_file()
    params = np.load(out / "gen.smplx.npz", allow_pickle=False)
    np.testing.assert_allclose(params["betas"], data["betas"])
    # The exported body keeps the agent's bone lengths whatever the generated joints did.
    root = bvhio.readAsHierarchy(str(out / "gen.bvh"))
    named = {joint.Name: joint for joint, _, _ in root.layout()}
    root.loadPose(5)
    knee, ankle = (np.array(named[n].PositionWorld) for n in ("left_knee", "left_ankle"))
    rest = data["rest_joints"]
    bone = np.linalg.norm(rest[JOINT_NAMES.index("left_ankle")] - rest[JOINT_NAMES.index("left_knee")])
    assert abs(np.linalg.norm(ankle - knee) - bone) < 1e-5


def test_generated_motion_exports_on_its_joints_through_the_smplx_package(generated, prep_raw_dir,
                                                                          tmp_path, capsys):
    """The body the smplx package builds from the file is the one the export line reports, and
    posed from the joints it is nearer the motion than posed from the decoded rotations."""
    motion = np.load(generated, allow_pickle=False)["joint_positions"]
    means = {}
    for pose_from in ("joints", "rotations"):
        code, out = export(tmp_path / pose_from, generated, "--format", "smplx", "--pose-from", pose_from)
        line = capsys.readouterr().out
        assert code == 0 and f"posed from its {pose_from}" in line
        reported = float(line.split("joint residual to the motion: mean ")[1].split(" mm")[0])
        params = dict(np.load(out / "gen.smplx.npz", allow_pickle=False))
        back = smplx_joints(params, prep_raw_dir / "body_models" / "SMPLX_PROCEDURAL.npz")
        means[pose_from] = 1000 * np.linalg.norm(back - motion, axis=-1).mean()
        assert abs(means[pose_from] - reported) < 0.5, (pose_from, means[pose_from], reported)
    assert means["joints"] < means["rotations"]


def test_motion_without_a_body_needs_a_body_model_for_smplx(generated, prep_raw_dir, tmp_path, capsys):
    data = dict(np.load(generated, allow_pickle=False))
    del data["rest_joints"]  # what a raw-input generation writes
    raw = tmp_path / "raw_motion.npz"
    np.savez(raw, **data)
    code, out = export(tmp_path, raw)
    assert code == 1 and not out.exists()
    err = capsys.readouterr().err
    assert "raw_motion.npz" in err and "--body-model" in err
    code, out = export(tmp_path, raw, "--format", "bvh")  # BVH fits a skeleton to the motion
    assert code == 0 and (out / "raw_motion.bvh").is_file()
    code, out = export(tmp_path, raw, "--body-model", prep_raw_dir / "body_models" / "SMPLX_PROCEDURAL.npz")
    assert code == 0
    params = np.load(out / "raw_motion.smplx.npz", allow_pickle=False)
    assert not params["betas"].any() and "neutral zero betas" in str(params["body_shape_source"])


def test_bad_input_is_one_line_and_writes_nothing(generated, prepared_shards, tmp_path, capsys):
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, poses=np.zeros((3, 165)))
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(generated.read_bytes()[:2000])
    not_zip = tmp_path / "text.npz"
    not_zip.write_text("hello")
    for path, words in ((foreign, "not a sarah-generate motion.npz"), (truncated, "unreadable npz"),
                        (not_zip, "unreadable npz"), (tmp_path / "missing.npz", "no such file")):
        code, out = export(tmp_path, path)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and not out.exists()
        assert str(path) in err[0] and words in err[0] and "Traceback" not in "".join(err)
    code, out = export(tmp_path, "--shards", prepared_shards, "--sequence", "no-such-sequence")
    err = capsys.readouterr().err
    assert code == 1 and "no sequence 'no-such-sequence'" in err and not out.exists()
    # One bad file among good ones: the good one is exported, the bad one reported.
    code, out = export(tmp_path, foreign, generated)
    assert code == 1 and (out / "gen.bvh").is_file() and not (out / "foreign.bvh").exists()
    assert "1 of 2 sources not exported" in capsys.readouterr().err


def test_arguments_are_checked_before_any_work(generated, tmp_path, capsys):
    for argv, words in (([generated, "--format", "fbx"], "--format"),
                        (["--sequence", "x"], "one of the two"),
                        ([generated, "--frames", "0"], "must be >= 1"),
                        ([generated, "--body-model", tmp_path / "none.npz"], "no such file"),
                        ([generated, "--pose-from", "icosahedra"], "--pose-from")):
        with pytest.raises(SystemExit) as exit_:
            export(tmp_path, *argv)
        assert exit_.value.code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_run_folder_reads_its_model_file_first(tmp_path):
    """A folder whose model file was written again with other decoding settings (sarah-train
    --stage model --out FOLDER) generates, serves and is evaluated as that model file, not as
    flow.pt's training config; --checkpoint flow.pt still asks for the checkpoint, and a folder
    without a model file reads flow.pt."""
    from sarah_models.evaluation.runner import EvalConfig, _load_model
    from sarah_models.generation.run import load_run
    from sarah_models.training.model_file import MODEL_FILE, write_model_file
    from test_generate import save_run

    run = save_run(tmp_path / "run")
    models, path = load_run(run)
    assert path == run / "flow.pt" and models.vae.config.boundary_inertia == 0.0
    write_model_file(run / "flow.pt", run / MODEL_FILE, ["vae.boundary_inertia=0.5"])
    models, path = load_run(run)
    assert path == run / MODEL_FILE and models.vae.config.boundary_inertia == 0.5
    models, path = load_run(run, "flow.pt")
    assert path == run / "flow.pt" and models.vae.config.boundary_inertia == 0.0
    for method in ("model", "vae", "decoded"):  # sarah-eval's rows of the same folder
        assert _load_model(run, EvalConfig(device="cpu"), method).vae.config.boundary_inertia == 0.5


def test_model_file_generates_what_the_checkpoint_does(tmp_path, monkeypatch):
    """model.safetensors alone in a run folder: the same motion as flow.pt, and no unpickling;
    the same checkpoint written twice gives the same bytes."""
    import pickle

    from sarah_cli.generate import main as generate
    from sarah_models.training.model_file import MODEL_FILE, load_model_file, write_model_file
    from test_generate import save_run, write_wav

    run = save_run(tmp_path / "run")
    shared = tmp_path / "shared"
    shared.mkdir()
    write_model_file(run / "flow.pt", shared / MODEL_FILE)
    write_model_file(run / "flow.pt", tmp_path / "again.safetensors")
    assert (tmp_path / "again.safetensors").read_bytes() == (shared / MODEL_FILE).read_bytes()
    raw = tmp_path / "raw"
    raw.mkdir()
    write_wav(raw / "agent.wav", 1.0, 48_000, 220.0)
    write_wav(raw / "user.wav", 1.0, 48_000, 330.0, seed=1)
    np.savetxt(raw / "traj.csv", np.stack([np.linspace(1, 2, 30), np.full(30, 1.5)], 1),
               delimiter=",", header="x,z", comments="")
    argv = ["--user-trajectory", str(raw / "traj.csv"), "--agent-audio", str(raw / "agent.wav"),
            "--user-audio", str(raw / "user.wav"), "--no-animation", "--seed", "3",
            "--threads", "1"]
    assert generate(["--run", str(run), "--out", str(tmp_path / "a"), *argv]) == 0

    def refuse(*args, **kwargs):
        raise AssertionError("the model file must load without unpickling")

    monkeypatch.setattr(torch, "load", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    assert generate(["--run", str(shared), "--out", str(tmp_path / "b"), *argv]) == 0
    a, b = (np.load(tmp_path / name / "motion.npz", allow_pickle=False) for name in "ab")
    np.testing.assert_array_equal(a["icosahedra"], b["icosahedra"])
    np.testing.assert_array_equal(a["joint_rotations"], b["joint_rotations"])
    monkeypatch.undo()
    not_ours = tmp_path / "other.safetensors"
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, str(not_ours))
    with pytest.raises(ValueError, match="not a SARAH model file"):
        load_model_file(not_ours)
