import numpy as np
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from sarah_data import frames, gaze


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_window_transform_puts_root_at_origin_facing_z(seed):
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi)
    tilt = Rotation.from_rotvec(rng.normal(scale=0.2, size=3))  # a root that leans a little
    root_rotation = (Rotation.from_rotvec([0, yaw, 0]) * tilt).as_matrix()
    root_position = rng.normal(size=3) + np.array([0, 0.9, 0])
    t = frames.window_transform(root_position, root_rotation)
    moved = t.apply_points(root_position[None])[0]
    assert abs(moved[0]) < 1e-9 and abs(moved[2]) < 1e-9
    assert abs(moved[1] - root_position[1]) < 1e-9  # height kept: floor stays at y = 0
    assert abs(frames.yaw_of(t.apply_rotations(root_rotation))) < 1e-9

    points = rng.normal(size=(7, 3))
    np.testing.assert_allclose(t.invert_points(t.apply_points(points)), points, atol=1e-12)
    homogeneous = np.concatenate([points, np.ones((7, 1))], 1)
    np.testing.assert_allclose(homogeneous @ t.matrix(), t.apply_points(points), atol=1e-12)
    floor = rng.normal(size=(7, 2))
    np.testing.assert_allclose(t.invert_floor(t.apply_floor(floor)), floor, atol=1e-12)
    np.testing.assert_allclose(t.apply_floor(points[:, [0, 2]]), t.apply_points(points)[:, [0, 2]], atol=1e-12)
    rots = Rotation.random(4, random_state=seed).as_matrix()
    np.testing.assert_allclose(t.invert_rotations(t.apply_rotations(rots)), rots, atol=1e-12)
    assert frames.WindowTransform.from_array(t.as_array()).yaw == np.float32(t.yaw)


def test_gaze_score_geometry():
    head = np.zeros((4, 3)) + np.array([0.0, 1.6, 0.0])
    facing = Rotation.from_rotvec([[0, 0, 0], [0, np.pi, 0], [0, np.pi / 2, 0], [0.3, 0, 0]]).as_matrix()
    front, back = gaze.head_points(head, facing)
    np.testing.assert_allclose(np.linalg.norm(front - back, axis=-1), 2 * gaze.HEAD_HALF_DEPTH)
    user = np.tile([[0.0, 2.0]], (4, 1))  # the user stands 2 m ahead along +z
    g = gaze.gaze_score(front, back, user)
    # facing, facing away, perpendicular, and nodding down while facing (still 1 in the floor plane);
    # d_y starts at the back of the head, so "perpendicular" sees the user 10 cm off the ear axis
    perpendicular = gaze.HEAD_HALF_DEPTH / np.hypot(gaze.HEAD_HALF_DEPTH, 2.0)
    np.testing.assert_allclose(g, [1.0, -1.0, perpendicular, 1.0], atol=1e-9)


def test_head_trajectory_is_floor_projection():
    eyes = np.array([[1.0, 1.7, -2.0]])
    np.testing.assert_array_equal(gaze.head_trajectory(eyes), [[1.0, -2.0]])
