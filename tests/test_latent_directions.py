"""Latent directions: samples projected on the principal directions of the data's latents."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from PIL import Image

from sarah_models.evaluation.latent_directions import (
    PLACEMENT_R2, LatentRecorder, band_edges, directions_markdown, directions_summary,
    participation, pelvis_floor, placement_r2, plot_directions, principal_axes, step_plane)


def smooth_latents(rng, windows=60, tokens=50, channels=8):
    """Latents whose variance sits in two slow directions (random walks of large steps, mixed
    into every channel) over a small isotropic noise floor."""
    walks = np.cumsum(rng.standard_normal((windows, tokens, 2)), axis=1) * np.array([3.0, 1.5])
    mixing, _ = np.linalg.qr(rng.standard_normal((channels, channels)))
    latents = walks @ mixing[:, :2].T + 0.05 * rng.standard_normal((windows, tokens, channels))
    return latents, mixing[:, :2]


def test_samples_equal_to_the_data_fill_every_direction_as_it_does():
    data, _ = smooth_latents(np.random.default_rng(0))
    summary = directions_summary(data, data.copy())
    for row in summary["bands"]:
        for key in ("spread", "change_ratio"):
            assert row[key] == pytest.approx(1.0)
            assert row[f"{key}_low"] == pytest.approx(1.0) and row[f"{key}_high"] == pytest.approx(1.0)
    assert summary["participation"]["data"] == pytest.approx(summary["participation"]["samples"])
    assert sum(row["share"] for row in summary["bands"]) == pytest.approx(1.0)
    assert summary["windows"] == 60 and summary["tokens"] == 50 and summary["channels"] == 8


def test_a_shrunk_direction_and_a_jittering_one_are_told_apart():
    rng = np.random.default_rng(1)
    data, directions = smooth_latents(rng)
    first, second = directions.T
    samples = data.copy()
    along_second = samples @ second
    samples -= 0.5 * along_second[..., None] * second  # half the amplitude: a quarter the spread
    samples += 3.0 * rng.standard_normal(samples.shape[:2])[..., None] * first  # token jitter
    summary = directions_summary(data, samples)
    per = summary["per_direction"]
    assert per["spread"][1] == pytest.approx(0.25, rel=0.05)
    assert per["spread"][0] == pytest.approx(1.0, abs=0.1)  # jitter adds little energy there...
    assert per["sample_change"][0] > 2.5 * per["data_change"][0]  # ...and much token-to-token change
    assert per["sample_change"][1] == pytest.approx(0.25 * per["data_change"][1], rel=0.15)
    lead = summary["bands"][0]  # the two slow directions hold over 90 % of the variance
    assert lead["directions"] == [0, 2] and lead["share"] > 0.9
    assert lead["change_ratio_low"] > 1.5  # the jitter shows in the band, outside chance
    assert lead["data_change"] < 0.05  # random walks: slow against the token rate
    # data's change is 0 for a constant and about 1 for tokens drawn independently
    white = rng.standard_normal((40, 30, 4))
    assert directions_summary(white, white)["bands"][0]["data_change"] == pytest.approx(1.0, abs=0.1)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=40))
def test_band_edges_cover_every_direction_once_in_order(raw):
    values = np.sort(np.array(raw) + 1e-9)[::-1]
    shares = values / values.sum()
    edges = band_edges(shares)
    assert edges[0][0] == 0 and edges[-1][1] == len(shares)
    assert all(a[1] == b[0] for a, b in zip(edges, edges[1:]))
    assert all(start < end for start, end in edges)
    assert np.cumsum(shares)[edges[0][1] - 1] >= 0.9 - 1e-9  # the first band reaches 90 %


def test_participation_counts_equally_filled_directions():
    assert participation(np.ones(7)) == pytest.approx(7.0)
    assert participation(np.array([1.0, 0.0, 0.0])) == pytest.approx(1.0)
    assert participation(np.zeros(3)) == 0.0


def test_shapes_that_do_not_pair_up_are_refused():
    with pytest.raises(ValueError, match="must be the same"):
        directions_summary(np.zeros((4, 5, 3)), np.zeros((4, 6, 3)))
    with pytest.raises(ValueError, match="at least 2 windows of 2 tokens"):
        directions_summary(np.zeros((4, 1, 3)), np.zeros((4, 1, 3)))
    with pytest.raises(ValueError, match="do not vary"):
        directions_summary(np.ones((4, 5, 3)), np.zeros((4, 5, 3)))


def test_a_direction_the_data_never_moves_along_has_no_ratio_and_the_json_stays_valid(tmp_path):
    rng = np.random.default_rng(5)
    data = np.zeros((10, 6, 3))
    data[..., :2] = rng.standard_normal((10, 6, 2))  # the third channel never moves
    summary = directions_summary(data, data + 0.1 * rng.standard_normal(data.shape))
    assert summary["per_direction"]["spread"][2] is None
    json.dumps(summary, allow_nan=False)  # what sarah-eval writes
    with Image.open(plot_directions(tmp_path / "flat.png", summary)) as png:
        assert png.format == "PNG"


class _Result:
    def __init__(self, motion, latents):
        self.motion, self.latents = motion, latents


def test_recorder_keeps_both_sides_of_every_window_and_passes_the_motion_on(tmp_path):
    rng = np.random.default_rng(2)
    data, _ = smooth_latents(rng, windows=5, tokens=6, channels=4)
    data -= data.mean(axis=(0, 1))  # about a zero mean, twice the latents is four times the spread
    recorder = LatentRecorder(encode=lambda item: data[item["i"]])
    produce = recorder.observe(lambda item, index: _Result(np.full((24, 3), index), data[index] * 2))
    assert recorder.summary() is None
    for i in range(5):
        assert (produce({"i": i}, i) == i).all()
    summary = recorder.summary()
    assert summary["bands"][0]["spread"] == pytest.approx(4.0)  # twice the amplitude
    text = directions_markdown(summary, "caption")
    assert text.startswith("caption") and "| 1-" in text and "participation ratio of 4" in text
    with Image.open(plot_directions(tmp_path / "directions.png", summary)) as png:
        assert png.format == "PNG" and png.size[0] > 200
    silent = LatentRecorder(encode=lambda item: data[0]).observe(lambda item, index: _Result(None, None))
    with pytest.raises(ValueError, match="kept no latents"):
        silent({}, 0)


def test_the_directions_that_carry_where_the_body_stands_are_found():
    rng = np.random.default_rng(3)
    data, _ = smooth_latents(rng)
    mean, _, axes = principal_axes(data)
    second = (data - mean) @ axes[:, 1]  # where the data's second direction puts each token
    floor = np.stack([second, 0.5 * second], axis=-1)  # x, z
    samples = data + second[..., None] * axes[:, 1]  # twice as far along it
    summary = directions_summary(data, samples, placement=floor)
    r2 = summary["per_direction"]["placement_r2"]
    assert r2[1] == pytest.approx(1.0) and max(r2[0], *r2[2:]) < 1e-9
    placement = summary["placement"]
    assert placement["directions"] == [1] and placement["spread"] == pytest.approx(4.0, rel=0.05)
    assert "placement: 2" in directions_markdown(summary, "caption")
    assert np.allclose(placement_r2(np.zeros((3, 4, 2)), np.zeros((3, 4, 2))), 0.0)
    with pytest.raises(ValueError, match="placement"):
        placement_r2(np.zeros((3, 4, 2)), np.zeros((3, 5, 2)))


def test_the_plane_that_carries_the_steps_is_found_and_read_against_the_data():
    rng = np.random.default_rng(5)
    axes, _ = np.linalg.qr(rng.standard_normal((10, 10)))
    # Eight directions of unit variance; each token's floor step is read from two weak ones
    # (together: x and z each from both), a sliver of the variance
    step_part = 0.3 * rng.standard_normal((60, 50, 2))
    data = (rng.standard_normal((60, 50, 8)) @ axes[:, :8].T + step_part @ axes[:, 8:].T
            + 0.02 * rng.standard_normal((60, 50, 10)))
    floor = np.cumsum(step_part @ np.array([[1.0, 1.0], [1.0, -1.0]]), axis=1)  # x, z per token
    samples = data - 0.5 * step_part @ axes[:, 8:].T  # half the steps' amplitude, the rest as is
    summary = directions_summary(data, samples, placement=floor)
    steps = summary["steps"]
    assert steps["r2"] > 0.95 and steps["share"] < 0.03
    assert steps["spread"] == pytest.approx(0.25, rel=0.1)
    assert steps["spread_low"] <= steps["spread"] <= steps["spread_high"]
    # the band of 90 % of the variance does not hold them and reads the samples as the data
    assert summary["bands"][0]["spread"] == pytest.approx(1.0, abs=1e-3)
    assert "| steps (a plane) | " in directions_markdown(summary, "caption")
    # the same samples as the data fill the plane as the data does
    assert directions_summary(data, data.copy(), placement=floor)["steps"]["spread"] == pytest.approx(1.0)
    plane, fit = step_plane(np.zeros((3, 4, 5)), np.zeros((3, 4, 2)))  # a floor that never moves
    assert plane is None and fit == 0.0
    assert "steps" not in directions_summary(data, samples, placement=np.zeros(data.shape[:2] + (2,)))


def test_pelvis_floor_is_the_mean_of_each_token_s_frames():
    from sarah_data.skeleton import MotionLayout, ROOT

    layout = MotionLayout(shell_points=2)
    rng = np.random.default_rng(4)
    motion = rng.standard_normal((12, layout.width)).astype(np.float32)
    floor = pelvis_floor(layout, stride=4)({"motion": motion})
    pelvis = layout.joint_positions(motion.astype(np.float64), [ROOT])[:, 0]
    assert floor.shape == (3, 2)
    assert np.allclose(floor[1], pelvis[4:8][:, [0, 2]].mean(0))
