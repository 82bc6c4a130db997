import hashlib
import os

import numpy as np
import pytest
import smplx
import torch
import trimesh
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from sarah_data.body import (SOLE_Y, BodyModel, BodyModelError, farthest_point_sampling,
                             shell_vertex_ids, write_procedural_body_model)
from sarah_data.body.model import axis_angle_to_matrix
from sarah_data.body.procedural import procedural_body_arrays
from sarah_data.constants import (DEFAULT_SHELL_POINTS, JOINT, JOINT_NAMES, JOINT_PARENTS, NUM_BETAS,
                                  NUM_JOINTS, NUM_VERTICES)
from sarah_data.gaze import HEAD_HALF_DEPTH


@pytest.fixture(scope="module")
def arrays(procedural_model_path):
    with np.load(procedural_model_path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def smplx_reference(path, params):
    """The smplx package's own full forward pass: all vertices and the 55 joints."""
    frames = len(params["transl"])
    model = smplx.SMPLX(model_path=str(path), num_betas=NUM_BETAS, use_pca=False, flat_hand_mean=True,
                        gender="neutral", ext="npz", batch_size=frames)
    with torch.no_grad():
        out = model(**{k: torch.as_tensor(v, dtype=torch.float32) for k, v in params.items()},
                    return_verts=True)
    return out.vertices.numpy(), out.joints[:, :NUM_JOINTS].numpy()


def random_params(rng, frames, pose_scale=0.5):
    return {
        "betas": rng.normal(size=(frames, NUM_BETAS)),
        "body_pose": rng.normal(scale=pose_scale, size=(frames, 63)),
        "global_orient": rng.normal(size=(frames, 3)),
        "transl": rng.normal(size=(frames, 3)),
        "left_hand_pose": rng.normal(scale=pose_scale, size=(frames, 45)),
        "right_hand_pose": rng.normal(scale=pose_scale, size=(frames, 45)),
    }


def rest_params(frames=1, betas=None):
    params = {k: np.zeros((frames, w)) for k, w in
              [("body_pose", 63), ("global_orient", 3), ("transl", 3), ("left_hand_pose", 45),
               ("right_hand_pose", 45)]}
    params["betas"] = np.zeros((frames, NUM_BETAS)) if betas is None else betas
    return params


# ---- the procedural body model file ----

def test_procedural_file_has_the_smplx_layout(arrays):
    assert arrays["v_template"].shape == (NUM_VERTICES, 3)
    assert arrays["shapedirs"].shape == (NUM_VERTICES, 3, 400)
    assert arrays["posedirs"].shape == (NUM_VERTICES, 3, (NUM_JOINTS - 1) * 9)
    assert np.abs(arrays["posedirs"]).max() > 0  # correctives are exercised
    np.testing.assert_array_equal(arrays["kintree_table"][0], JOINT_PARENTS)
    J, W = arrays["J_regressor"], arrays["weights"]
    assert J.shape == (NUM_JOINTS, NUM_VERTICES) and W.shape == (NUM_VERTICES, NUM_JOINTS)
    assert J.min() >= 0 and W.min() >= 0
    np.testing.assert_allclose(J.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-12)
    for side in "lr":
        components = arrays[f"hands_components{side}"]
        np.testing.assert_allclose(components @ components.T, np.eye(45), atol=1e-10)
    assert arrays["lmk_faces_idx"].shape == (51,) and arrays["dynamic_lmk_faces_idx"].shape == (79, 17)
    np.testing.assert_allclose(arrays["lmk_bary_coords"].sum(1), 1.0, atol=1e-12)
    assert arrays["f"].min() >= 0 and arrays["f"].max() < NUM_VERTICES


def test_procedural_body_is_a_closed_humanlike_t_pose(arrays):
    v = arrays["v_template"]
    mesh = trimesh.Trimesh(v, arrays["f"], process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert 0.05 < mesh.volume < 0.09  # m^3: an adult's volume
    assert v[:, 1].min() == pytest.approx(SOLE_Y, abs=1e-12)
    assert 1.6 < v[:, 1].max() - v[:, 1].min() < 1.8
    J = arrays["J_regressor"] @ v
    assert J[JOINT["left_hip"], 0] > 0 > J[JOINT["right_hip"], 0]  # left side at +x
    wrist, shoulder = J[JOINT["left_wrist"]], J[JOINT["left_shoulder"]]
    assert wrist[0] > 0.6 and abs(wrist[1] - shoulder[1]) < 0.02  # T-pose
    assert J[JOINT["left_foot"], 2] > J[JOINT["left_ankle"], 2] + 0.05  # toes point +z
    for eye in ("left_eye_smplhf", "right_eye_smplhf"):
        assert J[JOINT[eye], 2] > J[JOINT["head"], 2] + 0.05 and J[JOINT[eye], 1] > J[JOINT["head"], 1]
    left = [j for j, name in enumerate(JOINT_NAMES) if name.startswith("left_")]
    right = [JOINT[JOINT_NAMES[j].replace("left_", "right_")] for j in left]
    np.testing.assert_allclose(J[right] * [-1, 1, 1], J[left], atol=1e-12)  # mirror symmetric


def test_procedural_file_is_byte_deterministic(procedural_model_path, tmp_path):
    again = write_procedural_body_model(tmp_path / "again.npz", seed=0)
    digest = [hashlib.sha256(p.read_bytes()).hexdigest() for p in (procedural_model_path, again)]
    assert digest[0] == digest[1]
    assert not [p for p in os.listdir(tmp_path) if p != "again.npz"]  # no temporary left behind
    other = procedural_body_arrays(seed=1)
    with np.load(again, allow_pickle=False) as data:
        np.testing.assert_array_equal(other["v_template"], data["v_template"])  # seeds vary blend shapes only
        assert not np.array_equal(other["shapedirs"], data["shapedirs"])


def test_smplx_create_loads_the_procedural_file_from_a_model_folder(procedural_model_path, tmp_path):
    (tmp_path / "smplx").mkdir()
    os.symlink(procedural_model_path, tmp_path / "smplx" / "SMPLX_NEUTRAL.npz")
    model = smplx.create(str(tmp_path), model_type="smplx", num_betas=300, use_pca=False,
                         flat_hand_mean=True, gender="neutral", ext="npz", use_face_contour=True)
    with torch.no_grad():
        out = model(return_verts=True)
    assert out.vertices.shape == (1, NUM_VERTICES, 3) and model.num_betas == 300
    assert torch.isfinite(out.joints).all()


def test_shape_components_change_the_body_but_not_the_sole_plane(procedural_model_path):
    rng = np.random.default_rng(3)
    betas = np.zeros((4, NUM_BETAS))
    betas[1, 0] = 1.0  # height
    betas[2, 1] = 2.0  # girth
    betas[3] = rng.normal(size=NUM_BETAS)
    verts, _ = smplx_reference(procedural_model_path, rest_params(4, betas))
    heights = verts[:, :, 1].max(1) - verts[:, :, 1].min(1)
    assert heights[1] == pytest.approx(heights[0] * 1.03, rel=1e-3)
    width = np.ptp(verts[:, :, 2], axis=1)
    assert width[2] > width[0] * 1.05
    assert np.abs(verts[3] - verts[0]).max() > 0.01
    np.testing.assert_allclose(verts[:, :, 1].min(1), SOLE_Y, atol=1e-6)


# ---- BodyModel against the smplx package ----

def test_body_model_matches_smplx_forward(procedural_model_path, procedural_body_model):
    rng = np.random.default_rng(0)
    params = random_params(rng, 7)
    params["betas"][3:5] = params["betas"][1]  # repeated per-frame shapes, as in Embody 3D
    verts, joints = smplx_reference(procedural_model_path, params)
    for batch in (3, 100):  # uneven split and a single batch
        out = procedural_body_model.forward(params, batch_frames=batch)
        assert out.joints.dtype == np.float32 and out.shell.shape == (7, DEFAULT_SHELL_POINTS, 3)
        np.testing.assert_allclose(out.joints, joints, atol=1e-5, rtol=0)
        shell = verts[:, procedural_body_model.shell_ids]
        np.testing.assert_allclose(out.shell, shell, atol=1e-5, rtol=0)
        np.testing.assert_allclose(out.eye_mid, joints[:, [23, 24]].mean(1), atol=1e-5, rtol=0)


def test_constant_betas_and_shorter_or_zero_padded_betas(procedural_body_model):
    rng = np.random.default_rng(1)
    params = random_params(rng, 5)
    params["betas"] = np.repeat(params["betas"][:1], 5, axis=0)
    reference = procedural_body_model.forward(params)
    one_row = dict(params, betas=params["betas"][0])
    np.testing.assert_array_equal(procedural_body_model.forward(one_row).shell, reference.shell)
    padded = dict(params, betas=np.pad(params["betas"], ((0, 0), (0, 4))))
    np.testing.assert_array_equal(procedural_body_model.forward(padded).joints, reference.joints)
    short = dict(params, betas=params["betas"][:, :10])
    zero_tail = np.pad(params["betas"][:, :10], ((0, 0), (0, NUM_BETAS - 10)))
    expected = procedural_body_model.forward(dict(params, betas=zero_tail))
    np.testing.assert_array_equal(procedural_body_model.forward(short).joints, expected.joints)


def test_global_rotations_match_an_independent_fk(procedural_body_model):
    rng = np.random.default_rng(2)
    params = random_params(rng, 6, pose_scale=0.8)
    out = procedural_body_model.forward(params, batch_frames=4)
    local = np.zeros((6, NUM_JOINTS, 3))
    local[:, 0] = params["global_orient"]
    local[:, 1:22] = params["body_pose"].reshape(6, 21, 3)
    local[:, 25:40] = params["left_hand_pose"].reshape(6, 15, 3)
    local[:, 40:55] = params["right_hand_pose"].reshape(6, 15, 3)
    for t in range(6):
        chain = [None] * NUM_JOINTS
        for j, parent in enumerate(JOINT_PARENTS):
            own = Rotation.from_rotvec(local[t, j])
            chain[j] = own if parent < 0 else chain[parent] * own
        expected = np.stack([r.as_matrix() for r in chain])
        np.testing.assert_allclose(out.rotations[t], expected, atol=1e-5, rtol=0)


def test_rest_pose_head_points_and_eyes(procedural_body_model):
    out = procedural_body_model.forward(rest_params(2))
    np.testing.assert_allclose(out.rotations, np.broadcast_to(np.eye(3), out.rotations.shape), atol=1e-7)
    head = out.joints[:, JOINT["head"]]
    np.testing.assert_allclose(out.head_front - head, [[0, 0, HEAD_HALF_DEPTH]] * 2, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(out.head_front - out.head_back, axis=1), 0.2, atol=1e-6)
    assert np.all(out.eye_mid[:, 2] > head[:, 2] + 0.05)


def test_head_points_follow_the_head_yaw(procedural_body_model):
    params = rest_params(1)
    params["global_orient"][0] = [0.0, np.pi / 2, 0.0]  # turn to face +x
    out = procedural_body_model.forward(params)
    direction = out.head_front[0] - out.head_back[0]
    np.testing.assert_allclose(direction, [0.2, 0, 0], atol=1e-6)


def test_empty_sequence(procedural_body_model):
    out = procedural_body_model.forward(rest_params(0))
    assert out.joints.shape == (0, NUM_JOINTS, 3) and out.shell.shape == (0, DEFAULT_SHELL_POINTS, 3)
    assert len(out) == 0


def test_bad_parameters_are_named(procedural_body_model):
    params = rest_params(3)
    with pytest.raises(ValueError, match="body_pose"):
        procedural_body_model.forward(dict(params, body_pose=np.zeros((3, 60))))
    with pytest.raises(ValueError, match="lack transl"):
        procedural_body_model.forward({k: v for k, v in params.items() if k != "transl"})
    extra = np.pad(params["betas"], ((0, 0), (0, 1)), constant_values=1.0)
    with pytest.raises(ValueError, match="shape components"):
        procedural_body_model.forward(dict(params, betas=extra))


# ---- loading errors and model properties ----

def test_missing_or_unusable_model_file_errors_name_the_path(tmp_path):
    missing = tmp_path / "SMPLX_NEUTRAL.npz"
    with pytest.raises(BodyModelError, match="SMPLX_NEUTRAL.npz.*no such body model file.*sarah-fixtures"):
        BodyModel.from_file(missing)
    garbage = tmp_path / "broken.npz"
    garbage.write_bytes(b"not a zip archive")
    with pytest.raises(BodyModelError, match="broken.npz: unreadable"):
        BodyModel.from_file(garbage)
    partial = tmp_path / "partial.npz"
    np.savez(partial, v_template=np.zeros((3, 3)))
    with pytest.raises(BodyModelError, match="partial.npz: missing arrays"):
        BodyModel.from_file(partial)


def test_model_properties(procedural_model_path, procedural_body_model, arrays):
    assert procedural_body_model.name == "procedural_body_model"
    assert procedural_body_model.sha256 == hashlib.sha256(procedural_model_path.read_bytes()).hexdigest()
    assert procedural_body_model.num_betas == NUM_BETAS
    ids = procedural_body_model.shell_ids
    assert ids.dtype == np.int64 and len(np.unique(ids)) == DEFAULT_SHELL_POINTS
    np.testing.assert_array_equal(ids, shell_vertex_ids(arrays["v_template"]))


# ---- shell sampling and rotations ----

def test_shell_ids_are_deterministic_distinct_and_nested(arrays):
    v = arrays["v_template"]
    ids = shell_vertex_ids(v, 64)
    np.testing.assert_array_equal(ids, shell_vertex_ids(v.copy(), 64))
    np.testing.assert_array_equal(shell_vertex_ids(v, 32), ids[:32])
    assert len(np.unique(ids)) == 64
    centroid_distance = np.linalg.norm(v - v.mean(0), axis=1)
    assert ids[0] == np.argmax(centroid_distance)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), count=st.integers(1, 30))
def test_farthest_point_sampling_spreads_points(seed, count):
    points = np.random.default_rng(seed).normal(size=(60, 3))
    ids = farthest_point_sampling(points, count, start=seed % 60)
    assert ids[0] == seed % 60 and len(np.unique(ids)) == count
    # Each pick is at least as far from the earlier picks as any later pick will be.
    gaps = [np.linalg.norm(points[ids[:i]] - points[ids[i]], axis=1).min() for i in range(1, count)]
    assert np.all(np.diff(gaps) <= 1e-12)
    if count > 1:
        unpicked = np.setdiff1d(np.arange(60), ids)
        cover = np.linalg.norm(points[unpicked, None] - points[ids][None], axis=2).min(1).max()
        assert cover <= gaps[-1] + 1e-12


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-9, 1e-4, 1.0, 3.0]))
def test_axis_angle_to_matrix_matches_scipy(seed, scale):
    rotvec = np.random.default_rng(seed).normal(size=(8, 3)) * scale
    ours = axis_angle_to_matrix(torch.as_tensor(rotvec)).numpy()
    np.testing.assert_allclose(ours, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)


def test_read_only_inputs_are_accepted_without_warnings(procedural_body_model):
    import warnings

    params = random_params(np.random.default_rng(4), 3)
    expected = procedural_body_model.forward(params)
    frozen = {k: v.astype(np.float32) for k, v in params.items()}
    for v in frozen.values():
        v.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = procedural_body_model.forward(frozen)
    np.testing.assert_allclose(out.shell, expected.shell, atol=1e-6)
