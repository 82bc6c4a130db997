import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from sarah_data import icosahedron
from sarah_data.gaze import HEAD_HALF_DEPTH
from sarah_data.constants import FPS, JOINT, NUM_JOINTS
from sarah_models.evaluation import metrics
from sarah_models.evaluation.metrics import (Clip, FrechetRidgeWarning, MetricsConfig, Moments, evaluate, foot_slide, frechet_distance, frechet_distance_from_moments, frechet_terms, head_angle, wrist_speed)


# ---------------------------------------------------------------- Fréchet distance


def test_frechet_distance_of_a_set_with_itself_is_zero():
    x = np.random.default_rng(0).normal(size=(500, 6)) @ np.random.default_rng(1).normal(size=(6, 6))
    assert frechet_distance(x, x) == pytest.approx(0.0, abs=1e-8)


def test_frechet_distance_exact_moments_match_closed_form_for_diagonal_covariances():
    mu1, mu2 = np.array([0.0, 1.0, -2.0]), np.array([0.5, -1.0, 0.0])
    s1, s2 = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 0.25])
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(s1 + s2 - 2 * np.sqrt(s1 * s2))
    got = frechet_distance_from_moments(mu1, np.diag(s1), mu2, np.diag(s2))
    assert got == pytest.approx(expected, rel=1e-12)


def test_frechet_distance_exact_moments_full_covariance_scaled():
    # N(0, A) vs N(m, c^2 A): ||m||^2 + tr(A) (1 - c)^2 for any SPD A.
    rng = np.random.default_rng(3)
    half = rng.normal(size=(5, 5))
    a = half @ half.T + 0.1 * np.eye(5)
    m = rng.normal(size=5)
    got = frechet_distance_from_moments(np.zeros(5), a, m, 9.0 * a)
    assert got == pytest.approx(m @ m + np.trace(a) * 4.0, rel=1e-9)


def test_frechet_distance_of_large_gaussian_samples_matches_closed_form():
    rng = np.random.default_rng(7)
    mu1, mu2 = np.array([0.0, 1.0, -2.0, 0.3]), np.array([0.5, -1.0, 0.0, 0.3])
    s1, s2 = np.array([1.0, 4.0, 0.25, 2.0]), np.array([9.0, 1.0, 0.25, 0.5])
    a = mu1 + rng.normal(size=(200_000, 4)) * np.sqrt(s1)
    b = mu2 + rng.normal(size=(200_000, 4)) * np.sqrt(s2)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum(s1 + s2 - 2 * np.sqrt(s1 * s2))
    assert frechet_distance(a, b) == pytest.approx(expected, rel=0.01)
    assert frechet_distance(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(frechet_distance(a, b))


def test_frechet_terms_split_the_distance_into_mean_spread_and_directions():
    """The three terms add up to the distance; a rotated copy differs by orientation alone, a
    scaled copy by spectrum alone, a shifted copy by its mean alone; random sets of different
    shapes have both, and orientation is never negative (von Neumann's trace inequality)."""
    rng = np.random.default_rng(5)
    x = rng.normal(size=(4000, 6)) @ rng.normal(size=(6, 6))
    rotation, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    rotated, scaled, shifted = x @ rotation, 2.0 * x, x + np.arange(6.0)
    for other in (rotated, scaled, shifted, rng.normal(size=(3000, 6)) @ rng.normal(size=(6, 6))):
        terms = frechet_terms(other, x)
        assert terms.total == pytest.approx(frechet_distance(other, x), rel=1e-12)
        assert terms.mean + terms.spectrum + terms.orientation == pytest.approx(terms.total, rel=1e-9)
        assert terms.orientation >= 0.0 and terms.spectrum >= 0.0
    turned = frechet_terms(rotated - rotated.mean(0), x - x.mean(0))
    assert turned.spectrum < 1e-9 * turned.total and turned.orientation > 1.0
    assert turned.energy == pytest.approx(1.0)
    grown = frechet_terms(scaled, x)
    assert grown.orientation < 1e-6 * grown.total and grown.energy == pytest.approx(4.0)
    assert grown.spectrum == pytest.approx(np.trace(np.cov(x, rowvar=False)), rel=1e-9)  # (2 - 1)^2 tr
    moved = frechet_terms(shifted, x)
    assert moved.mean == pytest.approx(np.sum(np.arange(6.0) ** 2)) and moved.total == pytest.approx(moved.mean)


def test_frechet_distance_adds_a_ridge_for_singular_covariances():
    # Two of three dimensions are constant: the covariance product is singular.
    with pytest.warns(FrechetRidgeWarning):
        got = frechet_distance_from_moments(np.zeros(3), np.diag([1.0, 0.0, 0.0]),
                                            np.array([1.0, 2.0, 2.0]), np.diag([4.0, 0.0, 0.0]))
    assert got == pytest.approx(1 + 4 + 4 + (1 + 4 - 2 * 2), rel=1e-5)

    rng = np.random.default_rng(0)
    a = np.column_stack([rng.normal(size=1000), np.zeros(1000), np.ones(1000)])
    b = np.column_stack([rng.normal(size=1000), np.zeros(1000), np.ones(1000)])
    with pytest.warns(FrechetRidgeWarning):
        assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-9)
        assert math.isfinite(frechet_distance(a, b))


def test_frechet_distance_rejects_bad_shapes():
    with pytest.raises(ValueError):
        frechet_distance(np.zeros((10, 3)), np.zeros((10, 4)))
    with pytest.raises(ValueError):
        frechet_distance(np.zeros((1, 3)), np.zeros((10, 3)))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), dim=st.integers(1, 6), shift=st.floats(-100, 100))
def test_frechet_distance_is_symmetric_nonnegative_and_shift_invariant(seed, dim, shift):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(60, dim)) @ rng.normal(size=(dim, dim))
    b = rng.normal(size=(80, dim)) * rng.uniform(0.5, 2, size=dim) + rng.normal(size=dim)
    ab, ba = frechet_distance(a, b), frechet_distance(b, a)
    assert ab >= 0
    assert ab == pytest.approx(ba, rel=1e-6, abs=1e-8)
    assert frechet_distance(a + shift, b + shift) == pytest.approx(ab, rel=1e-5, abs=1e-6)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), sizes=st.lists(st.integers(1, 20), min_size=1, max_size=5))
def test_merged_moments_equal_moments_of_the_concatenation(seed, sizes):
    rng = np.random.default_rng(seed)
    parts = [rng.normal(size=(n, 3)) * 5 + 1000 for n in sizes]
    moments = Moments(full=True)
    for part in parts:
        moments.add(part)
    whole = np.concatenate(parts)
    assert moments.count == len(whole)
    np.testing.assert_allclose(moments.mean, whole.mean(0), rtol=1e-12)
    if len(whole) > 1:
        np.testing.assert_allclose(moments.covariance, np.cov(whole, rowvar=False), rtol=1e-8, atol=1e-9)


# ---------------------------------------------------------------- per-clip metrics


def _still_pose(frames_: int) -> tuple[np.ndarray, np.ndarray]:
    """A standing skeleton, pelvis at (0, 0.9, 0) facing +z, feet planted at 2 cm."""
    positions = np.zeros((frames_, NUM_JOINTS, 3))
    positions[:, :, 1] = 1.0
    positions[:, JOINT["pelvis"]] = [0.0, 0.9, 0.0]
    positions[:, JOINT["left_foot"]] = [0.1, 0.02, 0.05]
    positions[:, JOINT["right_foot"]] = [-0.1, 0.02, 0.05]
    positions[:, JOINT["left_wrist"]] = [0.25, 0.85, 0.0]
    positions[:, JOINT["right_wrist"]] = [-0.25, 0.85, 0.0]
    positions[:, JOINT["head"]] = [0.0, 1.6, 0.0]
    rotations = np.broadcast_to(np.eye(3), (frames_, NUM_JOINTS, 3, 3)).copy()
    return positions, rotations


def test_foot_steps_are_the_runs_a_foot_moves_in():
    from sarah_models.evaluation.metrics import foot_steps

    feet = np.zeros((20, 2, 3))
    feet[4:8, 0, 0] = 0.05 * np.arange(1, 5)  # frames 3 -> 7 move, then the foot stands there
    feet[8:, 0, 0] = 0.2
    feet[12:, 1, 2] = 0.3  # one jump between frames 11 and 12
    feet[:, 1, 0] = 0.0005 * np.arange(20)  # 1.5 cm/s of drift: under the 3 cm/s a step needs
    assert foot_steps(feet) == [[(3, 7)], [(11, 12)]]
    assert foot_steps(np.zeros((5, 2, 3))) == [[], []]


def test_a_steps_path_is_its_rise_and_share_of_the_way_from_the_last_standing_frame():
    from sarah_models.evaluation.metrics import foot_steps, step_paths, step_reaches

    feet = np.zeros((20, 2, 3))
    feet[4:9, 0, 1] = [0.03, 0.06, 0.06, 0.03, 0.0]  # rises from frame 4 (stands at 3)...
    feet[5:, 0, 2] = 0.4 * np.minimum(np.arange(15) / 2.0 + 0.5, 1.0)[:15]  # ...moves from 4 -> 5
    steps = foot_steps(feet)
    paths = step_paths(feet, steps, 5)
    np.testing.assert_allclose(paths[0, :, 0], [0.03, 0.06, 0.06, 0.03, 0.0])
    np.testing.assert_allclose(paths[0, :, 1], [0.0, 0.5, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(step_reaches(feet, steps), [0.4])
    assert step_paths(feet, steps, 17).shape == (0, 17, 2)  # runs past the clip: left out


def test_foot_slide_on_constructed_skating():
    t = np.arange(31) / FPS
    skate, _ = _still_pose(31)
    skate[:, JOINT["left_foot"], 0] += 0.10 * t  # 10 cm/s at 2 cm height
    assert foot_slide(skate) == 1.0

    planted, _ = _still_pose(31)
    assert foot_slide(planted) == 0.0

    lifted = skate.copy()
    lifted[:, JOINT["left_foot"], 1] = 0.20
    assert foot_slide(lifted) == 0.0

    slow = planted.copy()
    slow[:, JOINT["right_foot"], 2] += 0.02 * t  # 2 cm/s: below the 3 cm/s threshold
    assert foot_slide(slow) == 0.0

    half = planted.copy()
    half[15:, JOINT["left_foot"], 0] += 0.10 * t[:16]  # slides during the last 15 of 30 steps
    assert foot_slide(half) == pytest.approx(15 / 30)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_foot_slide_is_a_fraction_invariant_to_floor_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    positions, _ = _still_pose(20)
    positions[:, [JOINT["left_foot"], JOINT["right_foot"]]] += rng.normal(scale=[0.01, 0.02, 0.01], size=(20, 2, 3))
    value = foot_slide(positions)
    assert 0.0 <= value <= 1.0
    turn = Rotation.from_rotvec([0, rng.uniform(-np.pi, np.pi), 0]).as_matrix()
    moved = positions @ turn.T + np.array([rng.normal(), 0.0, rng.normal()])
    assert foot_slide(moved) == pytest.approx(value)


def test_wrist_speed_of_constant_velocity_wrists():
    positions, _ = _still_pose(31)
    t = np.arange(31) / FPS
    positions[:, JOINT["left_wrist"]] += np.outer(t, [0.3, 0.4, 0.0])  # 0.5 m/s
    positions[:, JOINT["right_wrist"]] += np.outer(t, [0.0, 0.0, -1.5])  # 1.5 m/s
    assert wrist_speed(positions) == pytest.approx(1.0)
    assert wrist_speed(_still_pose(31)[0]) == 0.0


def test_pelvis_speed_counts_floor_motion_of_the_whole_body_only():
    from sarah_models.evaluation.metrics.pelvis_speed import pelvis_speed

    positions, _ = _still_pose(31)
    assert pelvis_speed(positions) == 0.0
    t = np.arange(31) / FPS
    walking = positions + np.outer(t, [0.6, 0.0, 0.8])[:, None]  # 1 m/s over the floor
    assert pelvis_speed(walking) == pytest.approx(1.0)
    bobbing = positions.copy()
    bobbing[:, :, 1] += 0.05 * np.sin(t * 10)[:, None]  # up and down only: not walking
    assert pelvis_speed(bobbing) == pytest.approx(0.0)
    gesturing = positions.copy()
    gesturing[:, JOINT["left_wrist"]] += np.outer(t, [2.0, 0.0, 0.0])
    assert pelvis_speed(gesturing) == 0.0


def test_user_distance_and_radial_speed_tell_walking_around_the_user_from_walking_to_them():
    """An agent walking a circle around a standing user keeps its distance and has no radial
    speed; one walking straight at the user closes the distance at its full speed; the user's
    own walking is not the agent's."""
    from sarah_models.evaluation.metrics.radial_speed import radial_speed
    from sarah_models.evaluation.metrics.user_distance import user_distance

    frames_, speed, radius = 61, 1.0, 2.0
    t = np.arange(frames_) / FPS
    still, _ = _still_pose(frames_)
    pelvis = still[0, JOINT["pelvis"], [0, 2]]
    user = np.tile(pelvis + [0.0, radius], (frames_, 1))
    angle = speed * t / radius  # around the user at 1 m/s
    around = still + np.stack([radius * np.sin(angle), np.zeros(frames_),
                               radius * (1 - np.cos(angle))], axis=1)[:, None]
    assert user_distance(around, user) == pytest.approx(radius, rel=1e-9)
    assert radial_speed(around, user) == pytest.approx(0.0, abs=0.02)
    toward = still + np.outer(speed * t, [0.0, 0.0, 1.0])[:, None]  # 2 m straight at the user
    assert user_distance(toward, user) == pytest.approx(radius - speed * t.mean(), rel=1e-9)
    assert radial_speed(toward, user) == pytest.approx(speed, rel=1e-9)
    walking_user = user + np.outer(t, [1.0, 0.0])  # the user walks, the agent stands
    assert radial_speed(still, walking_user) == 0.0
    # the user where the agent starts: no direction at the first step, which counts 0; the
    # agent then walks straight away from the user
    at_start = np.tile(pelvis, (frames_, 1))
    assert radial_speed(toward, at_start) == pytest.approx(speed * (frames_ - 2) / (frames_ - 1), rel=1e-9)
    with pytest.raises(ValueError, match="at least 2 frames"):
        radial_speed(still[:1], user[:1])


def test_acceleration_rms_tells_smooth_from_jittery_motion():
    from sarah_models.evaluation.metrics.acceleration_rms import acceleration_rms

    t = np.arange(61) / FPS
    shell = np.zeros((61, 4, 3))
    assert acceleration_rms(shell) == 0.0
    walking = shell + np.outer(t, [1.0, 0.0, 0.0])[:, None]  # constant velocity: no acceleration
    assert acceleration_rms(walking) == pytest.approx(0.0, abs=1e-9)
    swinging = shell.copy()
    swinging[:, :, 0] = 0.1 * np.sin(2 * np.pi * t)[:, None]  # a(t) = -0.1 (2 pi)^2 sin(2 pi t)
    expected = 0.1 * (2 * np.pi) ** 2 / np.sqrt(2)
    assert acceleration_rms(swinging) == pytest.approx(expected, rel=0.02)
    assert acceleration_rms(swinging.reshape(61, -1)) == acceleration_rms(swinging)
    jitter = swinging + 0.002 * np.random.default_rng(0).standard_normal(swinging.shape)
    assert acceleration_rms(jitter) > 1.5 * acceleration_rms(swinging)  # 2 mm of noise
    with pytest.raises(ValueError, match="at least 3 frames"):
        acceleration_rms(shell[:2])


def _user_ahead_of_back(head_xz, facing, bearing, distance=2.0):
    """A user `distance` from the back of the head, `bearing` radians off the facing direction."""
    back = head_xz - HEAD_HALF_DEPTH * np.array([np.sin(facing), np.cos(facing)])
    return back + distance * np.array([np.sin(facing + bearing), np.cos(facing + bearing)])


@pytest.mark.parametrize("bearing, expected", [(0.0, 1.0), (np.pi, -1.0), (np.pi / 2, 0.0), (-np.pi / 2, 0.0),
                                               (np.pi / 3, 0.5)])
@pytest.mark.parametrize("facing", [0.0, 2.0])
def test_head_angle_on_constructed_facing(facing, bearing, expected):
    frames_ = 10
    head = np.tile([0.3, 1.6, -0.2], (frames_, 1))
    rotation = np.broadcast_to(Rotation.from_rotvec([0, facing, 0]).as_matrix(), (frames_, 3, 3))
    user = np.tile(_user_ahead_of_back(head[0, [0, 2]], facing, bearing), (frames_, 1))
    assert head_angle(head, rotation, user) == pytest.approx(expected, abs=1e-9)


# ---------------------------------------------------------------- clips and evaluate


def _clip(positions, rotations, shell, user_head) -> Clip:
    return Clip(icosahedron.encode(positions, rotations), shell, user_head, FPS)


def _random_clip(rng, frames_=12, shell_points=2, offset=0.0, scale=0.05, facing=0.0) -> Clip:
    """A still skeleton whose head turns `facing` from +z, the user straight ahead along +z of the
    back of the head (head angle cos(facing)), and a noisy shell."""
    positions, rotations = _still_pose(frames_)
    rotations[:, JOINT["head"]] = Rotation.from_rotvec([0, facing, 0]).as_matrix()
    shell = rng.normal(scale=scale, size=(frames_, shell_points, 3)) + offset + np.array([0.0, 1.0, 0.0])
    user = np.tile(_user_ahead_of_back(positions[0, JOINT["head"], [0, 2]], facing, -facing), (frames_, 1))
    return _clip(positions, rotations, shell, user)


def test_clip_validates_and_converts():
    clip = _random_clip(np.random.default_rng(0))
    tensor_clip = Clip(torch.from_numpy(clip.icosahedra).float(), torch.from_numpy(clip.shell),
                       torch.from_numpy(clip.user_head))
    assert isinstance(tensor_clip.icosahedra, np.ndarray) and tensor_clip.icosahedra.dtype == np.float32
    with pytest.raises(ValueError, match="user_head"):
        Clip(clip.icosahedra, clip.shell, clip.user_head[:-1])
    with pytest.raises(ValueError, match="non-finite"):
        Clip(clip.icosahedra, clip.shell * np.nan, clip.user_head)


def test_evaluate_pools_speaking_categories_and_averages_batches():
    rng = np.random.default_rng(0)
    # Speaking clips move around a different shell position from non-speaking ones, and the
    # generator is offset from the ground truth differently in each category.
    speaking = np.array([True, False, True, False, False, False])
    ground_truth = [_random_clip(rng, offset=0.3 if s else 0.0) for s in speaking]
    generated = [_random_clip(rng, offset=(0.3 if s else 0.0) + (0.02 if s else 0.05), scale=0.08)
                 for s in speaking]
    table = evaluate(generated, ground_truth, speaking, batch_clips=4)

    def flat(clips, idx):
        return np.concatenate([clips[i].shell.reshape(len(clips[i].shell), -1) for i in idx])

    def acc(clips, idx):
        return np.concatenate([metrics.accelerations(clips[i].shell.reshape(len(clips[i].shell), -1), FPS)
                               for i in idx])

    cm2 = 1e4  # m^2 -> cm^2
    for kind, samples in (("fgd", flat), ("fgd_acc", acc)):
        s = frechet_distance(samples(generated, [0, 2]), samples(ground_truth, [0, 2])) * cm2
        ns = frechet_distance(samples(generated, [1, 3, 4, 5]), samples(ground_truth, [1, 3, 4, 5])) * cm2
        batches = [frechet_distance(samples(generated, idx), samples(ground_truth, idx)) * cm2
                   for idx in ([0, 1, 2, 3], [4, 5])]
        values = table.values[kind]
        assert values.s == pytest.approx(s, rel=1e-8)
        assert values.ns == pytest.approx(ns, rel=1e-8)
        assert values.avg == pytest.approx(np.mean(batches), rel=1e-8)
        assert values.avg != pytest.approx((2 * s + 4 * ns) / 6, rel=1e-3)  # not a weighted mean
    # The ground truth's per-clip values given (the runner scores them once for the GT row):
    # the same table, every column.
    given = evaluate(generated, ground_truth, speaking, batch_clips=4,
                     reference_values=metrics.clip_values(ground_truth))
    assert given.to_dict() == table.to_dict()

    assert (table.num_clips, table.num_speaking, table.num_non_speaking) == (6, 2, 4)
    assert (table.window_frames, table.batch_clips, table.num_batches) == (12, 4, 2)


def test_pooled_frechet_interval_is_the_jackknife_over_groups_of_consecutive_clips():
    """Each group of consecutive clips left out in turn (generated and ground truth together),
    the distances recomputed here from the raw samples: pooled +- 1.96 jackknife errors."""
    rng = np.random.default_rng(1)
    ground_truth = [_random_clip(rng, offset=0.02 * i) for i in range(7)]
    generated = [_random_clip(rng, offset=0.02 * i + 0.04, scale=0.08) for i in range(7)]
    speaking = np.zeros(7, bool)
    table = evaluate(generated, ground_truth, speaking, config=MetricsConfig(pooled_groups=3))
    groups = [[0, 1, 2], [3, 4], [5, 6]]  # i * 3 // 7

    def flat(clips, idx):
        return np.concatenate([clips[i].shell.reshape(len(clips[i].shell), -1) for i in idx])

    cm2 = 1e4
    pooled = frechet_distance(flat(generated, range(7)), flat(ground_truth, range(7))) * cm2
    left_out = np.array([frechet_distance(flat(generated, rest), flat(ground_truth, rest)) * cm2
                         for rest in ([i for i in range(7) if i not in g] for g in groups)])
    error = 1.96 * np.sqrt(2 / 3 * np.sum((left_out - left_out.mean()) ** 2))
    values = table.values["fgd"]
    assert values.pooled == pytest.approx(pooled, rel=1e-8)
    assert (values.pooled_low, values.pooled_high) == (
        pytest.approx(max(pooled - error, 0.0), rel=1e-6), pytest.approx(pooled + error, rel=1e-6))
    assert error > 0
    assert table.per_group["fgd"] == pytest.approx(list(left_out), rel=1e-8)  # kept for pairing
    with pytest.raises(ValueError, match="pooled_groups"):
        evaluate(generated, ground_truth, speaking, config=MetricsConfig(pooled_groups=-1))
    # two groups are too few for an interval; none asked for, none given
    for count in (2, 0):
        few = evaluate(generated, ground_truth, speaking, config=MetricsConfig(pooled_groups=count))
        assert math.isnan(few.values["fgd"].pooled_low) and few.values["fgd"].pooled == pytest.approx(pooled)


def test_evaluate_per_clip_metrics_are_category_means_and_weighted_average():
    rng = np.random.default_rng(1)
    facings = [0.0, np.pi, np.pi / 2, 0.0, 0.0]
    speaking = np.array([True, True, False, False, False])
    generated = [_random_clip(rng, facing=f) for f in facings]
    table = evaluate(generated, generated, speaking, batch_clips=2)
    head = table.values["head_angle"]
    assert (head.s, head.ns) == (pytest.approx(0.0, abs=1e-9), pytest.approx(2 / 3))
    assert head.avg == pytest.approx((2 * head.s + 3 * head.ns) / 5)
    assert table.values["foot_slide"].avg == 0.0
    assert table.values["fgd"].avg == pytest.approx(0.0, abs=1e-6)
    assert table.values["fgd"].s == pytest.approx(0.0, abs=1e-6)


def test_look_away_is_the_share_of_windows_whose_head_angle_is_below_a_half():
    """Windows facing the user (score 1), turned 60-90 degrees off (0.26, 0) or away (-1): the
    column is the share below 0.5 per category, which Head Ang.'s mean alone cannot tell from
    an agent that half-faces the user everywhere."""
    from sarah_models.evaluation.metrics.look_away import LOOK_AWAY_SCORE, looks_away

    assert LOOK_AWAY_SCORE == 0.5 and (looks_away(0.49), looks_away(0.5), looks_away(0.9)) == (1.0, 0.0, 0.0)
    rng = np.random.default_rng(3)
    facings = [0.0, np.pi, np.pi / 2, 0.0, 1.31]  # scores 1, -1, 0, 1, 0.26
    speaking = np.array([True, True, False, False, False])
    table = evaluate([_random_clip(rng, facing=f) for f in facings],
                     [_random_clip(rng, facing=0.0) for _ in facings], speaking, batch_clips=2)
    away = table.values["look_away"]
    assert (away.s, away.ns, away.avg) == (pytest.approx(0.5), pytest.approx(2 / 3), pytest.approx(0.6))
    # half-facing the user in every window (Head Ang. 0.51) reads none looking away
    half = evaluate([_random_clip(rng, facing=np.pi / 3 - 0.01) for _ in facings],
                    [_random_clip(rng, facing=0.0) for _ in facings], speaking, batch_clips=2)
    assert half.values["look_away"].avg == 0.0


def test_evaluate_reports_centimetres_and_scales_rows():
    rng = np.random.default_rng(2)
    t = np.arange(12) / FPS
    clips = []
    for _ in range(3):
        positions, rotations = _still_pose(12)
        positions[:, JOINT["left_wrist"]] += np.outer(t, [0.3, 0.4, 0.0])
        positions[:, JOINT["right_wrist"]] += np.outer(t, [0.3, 0.4, 0.0])
        clips.append(_clip(positions, rotations, rng.normal(scale=0.05, size=(12, 2, 3)), np.ones((12, 2))))
    ground_truth = [_random_clip(rng) for _ in range(3)]
    table = evaluate(clips, ground_truth, [False, False, False])
    assert table.values["wrist_speed"].avg == pytest.approx(50.0)  # 0.5 m/s in cm/s
    assert math.isnan(table.values["wrist_speed"].s) and math.isnan(table.values["fgd"].s)
    raw, shown = table.to_row(scale=False), table.to_row(scale=True)
    assert shown["fgd/avg"] == pytest.approx(raw["fgd/avg"] / 10)
    assert shown["fgd_acc/ns"] == pytest.approx(raw["fgd_acc/ns"] / 1e5)
    assert shown["wrist_speed/avg"] == raw["wrist_speed/avg"]
    encoded = json.loads(json.dumps(table.to_dict()))
    assert encoded["values"]["fgd"]["s"] is None
    assert encoded["units"]["fgd_acc"] == "(cm/s^2)^2"


def test_evaluate_is_invariant_to_world_placement_of_clips():
    rng = np.random.default_rng(4)
    speaking = [True, False, True, False]
    generated = [_random_clip(rng, facing=f, scale=0.1) for f in (0.1, 0.5, -0.3, 1.0)]
    ground_truth = [_random_clip(rng, scale=0.1) for _ in range(4)]

    def to_world(clip, seed):
        r = np.random.default_rng(seed)
        turn = Rotation.from_rotvec([0, r.uniform(-np.pi, np.pi), 0]).as_matrix()
        shift = np.array([r.normal() * 3, 0.0, r.normal() * 3])
        user = np.column_stack([clip.user_head[:, 0], np.zeros(len(clip.user_head)), clip.user_head[:, 1]])
        return Clip(clip.icosahedra @ turn.T + shift, clip.shell @ turn.T + shift,
                    (user @ turn.T + shift)[:, [0, 2]], clip.fps)

    window = evaluate(generated, ground_truth, speaking, batch_clips=2)
    world = evaluate([to_world(c, i) for i, c in enumerate(generated)],
                     [to_world(c, 10 + i) for i, c in enumerate(ground_truth)], speaking, batch_clips=2)
    for name in (m.name for m in metrics.registered() if not m.window_frame):
        for column in ("avg", "ns", "s"):
            assert getattr(world.values[name], column) == pytest.approx(
                getattr(window.values[name], column), rel=1e-6, abs=1e-6), (name, column)


def test_evaluate_rejects_mismatched_inputs():
    rng = np.random.default_rng(5)
    clips = [_random_clip(rng) for _ in range(2)]
    with pytest.raises(ValueError, match="speaking"):
        evaluate(clips, clips, [True])
    with pytest.raises(ValueError, match="frames"):
        evaluate(clips, [clips[0], _random_clip(rng, frames_=13)], [True, False])
    with pytest.raises(ValueError, match="batch_clips"):
        evaluate(clips, clips, [True, False], config=MetricsConfig(batch_clips=0))


def _rigid_skeleton(frames: int, rng) -> np.ndarray:
    """Joint positions (T, 55, 3) of a skeleton with fixed bone lengths, turning and walking."""
    from scipy.spatial.transform import Rotation as R

    from sarah_data.constants import JOINT_PARENTS

    offsets = rng.normal(0, 0.1, (NUM_JOINTS, 3))
    positions = np.zeros((frames, NUM_JOINTS, 3))
    turn = R.from_euler("y", np.linspace(0, 2.0, frames)[:, None]).as_matrix()
    positions[:, 0] = np.stack([np.linspace(0, 1, frames), np.full(frames, 0.9), np.zeros(frames)], 1)
    for j in range(1, NUM_JOINTS):
        positions[:, j] = positions[:, JOINT_PARENTS[j]] + turn @ offsets[j]
    return positions


def test_bone_length_error_is_zero_for_a_rigid_skeleton_and_measures_stretch():
    from sarah_models.evaluation.metrics.bone_length import bone_length_error

    rng = np.random.default_rng(0)
    rigid = _rigid_skeleton(30, rng)
    assert bone_length_error(rigid) == pytest.approx(0.0, abs=1e-9)
    stretched = rigid.copy()
    wrist, elbow = JOINT["left_wrist"], JOINT["left_elbow"]
    # the forearm 10 % longer in every third frame: the median keeps the true length
    stretched[::3, wrist] = rigid[::3, elbow] + 1.1 * (rigid[::3, wrist] - rigid[::3, elbow])
    assert bone_length_error(stretched, percentile=100) == pytest.approx(10.0, rel=1e-6)


def test_frame0_offset_and_root_relative_samples():
    from sarah_models.evaluation.metrics.fgd_local import root_relative_points
    from sarah_models.evaluation.metrics.frame0_offset import frame0_offset

    rng = np.random.default_rng(1)
    joints = _rigid_skeleton(10, rng)
    assert frame0_offset(joints) == pytest.approx(0.0)  # the pelvis starts at x = z = 0
    joints[:, :, [0, 2]] += [0.3, 0.4]
    assert frame0_offset(joints) == pytest.approx(0.5)
    # Root-relative points do not change when the whole body walks and turns together.
    points = rng.normal(0, 0.3, (1, 7, 3))
    yaw = np.array([0.0, 0.7, -2.0])
    rot = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    root = np.array([[0, 0.9, 0], [1.0, 0.9, -2.0], [-3.0, 0.9, 0.5]])
    moved = np.einsum("tij,nj->tni", rot, points[0]) + root[:, None]
    local = root_relative_points(moved, root, rot)
    np.testing.assert_allclose(local, np.repeat(points.reshape(1, -1), 3, 0), atol=1e-12)


def test_seam_share_finds_jumps_between_latent_blocks():
    from sarah_models.evaluation.metrics.seam_share import seam_share

    frames, s = 80, 4
    t = np.arange(frames)[:, None]
    joints = np.zeros((frames, NUM_JOINTS, 3))
    # Accelerating evenly on every frame: a parabola has the same second difference everywhere,
    # so the two seam phases of four hold half of it.
    joints[:, :, 0] = 0.001 * t**2
    assert seam_share(joints, s) == pytest.approx(2 / s, abs=0.02)  # up to the ends
    # Walking at constant speed with a jump of the whole body at every block start: all of it.
    walk = joints.copy()
    walk[:, :, 0] = 0.02 * t
    jumpy = walk.copy()
    jumpy[:, :, 2] += np.repeat(np.random.default_rng(0).normal(0, 0.03, frames // s), s)[:, None]
    assert seam_share(jumpy, s) == pytest.approx(1.0)
    assert seam_share(np.zeros_like(walk), s) == 0.5  # standing still: the neutral value
    # Two frames later the same jumps are mid-block: not seams of these blocks.
    assert seam_share(jumpy[2:], s) < 0.01
    with pytest.raises(ValueError, match="at least 2 frames"):
        seam_share(joints, 1)
