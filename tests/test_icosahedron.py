import numpy as np
import torch
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from sarah_data import icosahedron


def _angle_between(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    # ||R1 - R2||_F = 2 sqrt(2) sin(angle / 2): well conditioned near zero, unlike arccos of the trace
    diff = np.linalg.norm(r1.astype(np.float64) - r2.astype(np.float64), axis=(-2, -1))
    return 2.0 * np.arcsin(np.clip(diff / (2.0 * np.sqrt(2.0)), 0.0, 1.0))


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.01, 5.0))
def test_round_trip_float32(seed, scale):
    rng = np.random.default_rng(seed)
    rotations = Rotation.random(55 * 3, random_state=seed).as_matrix().reshape(3, 55, 3, 3)
    positions = rng.normal(scale=scale, size=(3, 55, 3))
    ico = icosahedron.encode(positions.astype(np.float32), rotations.astype(np.float32))
    assert ico.dtype == np.float32 and ico.shape == (3, 55, 12, 3)
    pos, rot = icosahedron.decode(ico)
    assert np.abs(pos - positions).max() < 1e-5
    assert _angle_between(rot, rotations).max() < 1e-4


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_torch_matches_numpy(seed):
    rotations = Rotation.random(8, random_state=seed).as_matrix().astype(np.float32)
    positions = np.random.default_rng(seed).normal(size=(8, 3)).astype(np.float32)
    ico_np = icosahedron.encode(positions, rotations)
    ico_t = icosahedron.encode(torch.from_numpy(positions), torch.from_numpy(rotations))
    assert isinstance(ico_t, torch.Tensor)
    np.testing.assert_allclose(ico_t.numpy(), ico_np, atol=1e-6)
    pos_t, rot_t = icosahedron.decode(ico_t)
    pos_n, rot_n = icosahedron.decode(ico_np)
    np.testing.assert_allclose(pos_t.numpy(), pos_n, atol=1e-6)
    np.testing.assert_allclose(rot_t.numpy(), rot_n, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), noise=st.floats(0.0, 0.02))
def test_noisy_input_decodes_to_nearest_proper_rotation(seed, noise):
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(1, random_state=seed).as_matrix()
    ico = icosahedron.encode(np.zeros((1, 3)), rotation) + rng.normal(scale=noise, size=(1, 12, 3))
    _, rot = icosahedron.decode(ico)
    np.testing.assert_allclose(rot[0] @ rot[0].T, np.eye(3), atol=1e-5)
    assert np.linalg.det(rot[0]) > 0.999
    # noise of n metres on 10 cm-radius vertices moves the fit by about n / radius radians
    assert _angle_between(rot, rotation).max() < 5 * noise / icosahedron.DEFAULT_RADIUS + 1e-4


def test_mirrored_icosahedron_decodes_to_a_rotation():
    mirrored = icosahedron.encode(np.zeros((1, 3)), np.eye(3)[None]) * np.array([-1.0, 1.0, 1.0])
    _, rot = icosahedron.decode(mirrored)
    assert np.linalg.det(rot[0]) > 0.999


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), radius=st.floats(0.01, 1.0), column=st.integers(0, 2))
def test_axis_is_radius_times_the_rotation_column_linear_in_the_vertices(seed, radius, column):
    rng = np.random.default_rng(seed)
    rotations = Rotation.random(6, random_state=seed).as_matrix()
    positions = rng.normal(size=(6, 3))
    ico = icosahedron.encode(positions, rotations, radius)
    np.testing.assert_allclose(icosahedron.axis(ico, column), radius * rotations[..., column], atol=1e-12)
    torch_axis = icosahedron.axis(torch.from_numpy(ico), column)
    np.testing.assert_allclose(torch_axis.numpy(), radius * rotations[..., column], atol=1e-12)
    # linear: the axis of a sum of vertex offsets is the sum of the axes
    other = icosahedron.encode(positions, rotations[::-1].copy(), radius)
    np.testing.assert_allclose(icosahedron.axis(ico + other, column),
                               icosahedron.axis(ico, column) + icosahedron.axis(other, column), atol=1e-12)
