"""Reconstruction error per body part: each part's error is its own, in mm, and a wrapped
producer is scored on the way through."""

import numpy as np
import pytest

from sarah_data import icosahedron
from sarah_data.constants import JOINT, NUM_JOINTS
from sarah_data.skeleton import JOINT_GROUPS, MotionLayout
from sarah_models.evaluation.reconstruction import ReconstructionErrors, part_errors, summary_markdown

LAYOUT = MotionLayout(shell_points=3)


def _motion(positions, rotations, shell):
    frames = len(positions)
    ico = icosahedron.encode(positions, rotations)
    return np.concatenate([ico.reshape(frames, -1), shell.reshape(frames, -1)], axis=1)


def _pose(frames=6, seed=0):
    rng = np.random.default_rng(seed)
    positions = rng.normal(size=(frames, NUM_JOINTS, 3))
    q = np.linalg.qr(rng.normal(size=(frames, NUM_JOINTS, 3, 3)))[0]
    rotations = q * np.sign(np.linalg.det(q))[..., None, None]  # proper rotations
    return positions, rotations, rng.normal(size=(frames, 3, 3))


def test_every_joint_is_in_one_group():
    names = [n for group in JOINT_GROUPS.values() for n in group]
    assert sorted(names) == sorted(JOINT) and len(names) == NUM_JOINTS


def test_a_parked_foot_and_a_turned_head_show_in_their_own_parts():
    positions, rotations, shell = _pose()
    truth = _motion(positions, rotations, shell)
    assert all(e == (0.0, 0.0) for g, e in part_errors(truth, truth, LAYOUT).items() if g != "shell")

    moved = positions.copy()
    moved[:, JOINT["left_foot"]] += [0.3, 0.0, 0.4]  # 500 mm off, one of the two feet
    turned = rotations.copy()
    angle = 0.1  # rad about y: every vertex of a 10 cm icosahedron moves 2 r sin(a/2) in xz
    c, s = np.cos(angle), np.sin(angle)
    turned[:, JOINT["head"]] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ rotations[:, JOINT["head"]]
    errors = part_errors(_motion(moved, turned, shell + [0.0, 0.002, 0.0]), truth, LAYOUT)
    assert errors["feet"][0] == pytest.approx(250.0) and errors["feet"][1] == pytest.approx(0.0, abs=1e-9)
    assert errors["legs"] == pytest.approx((0.0, 0.0), abs=1e-9)
    assert errors["spine and head"][0] == pytest.approx(0.0, abs=1e-9)
    # The head is 1 of the group's 8 joints; a vertex's move depends on its height along y.
    head_vertices = icosahedron.encode(np.zeros(3), rotations[:, JOINT["head"]])
    turned_vertices = icosahedron.encode(np.zeros(3), turned[:, JOINT["head"]])
    expected = np.linalg.norm(turned_vertices - head_vertices, axis=-1).mean() * 1000 / 8
    assert errors["spine and head"][1] == pytest.approx(expected)
    assert errors["shell"][0] == pytest.approx(2.0) and np.isnan(errors["shell"][1])


def test_observe_scores_each_window_once_and_summarises_with_intervals():
    windows = []
    for seed in range(5):
        positions, rotations, shell = _pose(seed=seed)
        windows.append({"motion": _motion(positions, rotations, shell)})
    offsets = [0.001, 0.002, 0.003, 0.004, 0.005]
    recon = ReconstructionErrors(LAYOUT)
    produce = recon.observe(lambda item, i: item["motion"] + offsets[i] * np.array([1.0, 0, 0] * (len(item["motion"][0]) // 3)))
    for i, item in enumerate(windows):
        produce(item, i)
    summary = recon.summary()
    for part in JOINT_GROUPS:
        assert summary[part]["position"] == pytest.approx(3.0)  # mean of 1..5 mm
        assert summary[part]["position_low"] < 3.0 < summary[part]["position_high"]
        assert summary[part]["orientation"] == pytest.approx(0.0, abs=1e-9)
    assert "| feet | 3.0 (" in summary_markdown(summary, "caption")
