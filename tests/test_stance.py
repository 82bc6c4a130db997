"""The stance head (nn.stance), its training term and the foot lock stepping by it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from sarah_data.constants import FPS, JOINT
from sarah_data.dataset import WindowDataset
from sarah_data.skeleton import MotionLayout, bone_lengths
from sarah_models.config import StreamConfig, VAEConfig
from sarah_models.nn.stance import RECEPTIVE_TOKENS, STANCE_SPEED, StanceHead, stance_of
from sarah_models.sampling.foot_lock import (STANCE_LIFT, STANCE_REACH, STANCE_SWING_FRAMES,
                                             STEP_SHARE, SWING_FRAMES, FootLock)
from sarah_models.sampling.decoding import stream_decoding
from sarah_models.sampling.stream import StreamingGenerator, offline_with_latents
from sarah_models.testing import random_models

FEET = [JOINT["left_foot"], JOINT["right_foot"]]
SHELL = 16
STANCE = ("vae.stance_weight=0.2", "vae.foot_lock=0.1", "vae.foot_lock_reads=stance")


def joints_of(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    return layout.split(np.asarray(motion, np.float64))[0].mean(axis=-2)


def test_the_datas_stance_is_where_a_foot_moves_slower_than_the_threshold_blips_left_out():
    layout = MotionLayout(shell_points=SHELL)
    frames = 12
    motion = np.zeros((1, frames, layout.width))
    # the left foot moves at 0.6 m/s in frames 3-6 and for one frame at 9, slower elsewhere
    speed = np.full(frames, 0.05)
    speed[[3, 4, 5, 6, 9]] = 0.6
    x = np.cumsum(speed) / FPS
    icosahedra, shell = layout.split(motion[0])
    icosahedra[:, JOINT["left_foot"], :, 0] = x[:, None]
    motion[0] = np.concatenate([icosahedra.reshape(frames, -1), shell.reshape(frames, -1)], 1)
    planted = stance_of(torch.from_numpy(motion), layout)[0].numpy()
    assert planted.shape == (frames, 2)
    assert planted[:, 1].all()  # the right foot never moves
    np.testing.assert_array_equal(planted[:, 0], [1, 1, 1, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    assert 0.05 < STANCE_SPEED < 0.6


def test_the_stance_head_is_causal_and_a_stream_reads_the_offline_values():
    torch.manual_seed(0)
    head = StanceHead(latent_dim=8, stride=4)
    z = torch.randn(2, 12, 8)
    full = head(z)
    assert full.shape == (2, 48, 2)
    for k in range(1, 13):
        torch.testing.assert_close(head.last(z[:, :k]), full[:, 4 * (k - 1):4 * k])
    # a token later than the receptive field's reach changes nothing before it
    later = z.clone()
    later[:, 8:] += 1.0
    torch.testing.assert_close(head(later)[:, :32], full[:, :32])
    assert not torch.allclose(head(later)[:, 32:], full[:, 32:])
    early = z.clone()
    early[:, 0] += 1.0
    torch.testing.assert_close(head(early)[:, 4 * RECEPTIVE_TOKENS:], full[:, 4 * RECEPTIVE_TOKENS:])


def test_the_stance_term_trains_the_head_and_reaches_the_encoder(prepared_shards):
    from sarah_data.stats import load_stats
    from sarah_models.config import RunConfig
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.training.checkpoint import build_models
    from sarah_models.training.objectives import VAEObjective
    from sarah_models.training.stages import model_stats

    windows = WindowDataset(prepared_shards, "train", extractor="logmel", window=40, seed=0, length=4)
    config = RunConfig.preset("tiny").with_overrides(("vae.stance_weight=0.5",))
    dims = {"motion": windows.motion_dim, "audio": windows.audio_dim}
    torch.manual_seed(0)
    vae, _ = build_models(config, dims)
    normalizer = Normalizer(model_stats(load_stats(prepared_shards), "logmel"))
    objective = VAEObjective(vae, normalizer)
    batch = {"motion": torch.stack([windows[i]["motion"] for i in range(4)])}
    out = objective(batch, torch.Generator().manual_seed(0))
    assert 0.0 < out["stance"].item() < 2.0
    vae.zero_grad()
    out["stance"].backward()
    assert vae.stance.out.weight.grad.abs().sum() > 0
    assert vae.mu_out.weight.grad.abs().sum() > 0  # the encoder learns to carry the stance
    with pytest.raises(ValueError, match="stance_weight"):
        dataclasses.replace(VAEConfig(), foot_lock=0.1, foot_lock_reads="stance")


def test_the_flows_stance_term_reads_the_head_on_its_predicted_latents_weighted_by_tau():
    """flow.stance_weight: the frozen stance head reads the flow's clean-latent prediction as the
    decoder would (denormalized), against the data's stance, each sample's cross-entropy times
    its flow time; its gradient trains the flow and leaves the VAE as it is."""
    from torch.nn import functional as F

    from sarah_models.training.objectives import FlowObjective

    vae, flow, normalizer = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                                          audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                                          overrides=STANCE + ("flow.stance_weight=0.5",))
    layout = MotionLayout(shell_points=SHELL)
    frames, rng = 32, np.random.default_rng(0)
    motion = normalizer.motion_mean.numpy() + rng.normal(0, 0.01, (3, frames, layout.width))
    icosahedra, shell = layout.split(motion)
    icosahedra[:, 8:20, JOINT["left_foot"], :, 0] += np.linspace(0, 0.4, 12)[None, :, None]
    motion = np.concatenate([icosahedra.reshape(3, frames, -1), shell.reshape(3, frames, -1)], -1)
    f32 = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
    batch = {"motion": f32(motion), "user_head": f32(rng.normal(0, 1, (3, frames, 2))),
             "agent_audio": f32(rng.normal(0, 1, (3, frames, 8))),
             "user_audio": f32(rng.normal(0, 1, (3, frames, 8))),
             "gaze": f32(rng.uniform(0, 1, (3, frames)))}
    objective = FlowObjective(flow, vae, normalizer)
    prepared = objective.prepare(batch)
    stance = stance_of(batch["motion"], layout)
    torch.testing.assert_close(prepared["stance"], stance)
    assert 0 < stance.mean() < 1  # the left foot travels in frames 8-19
    out = objective(prepared, torch.Generator().manual_seed(0))
    logits = vae.stance(normalizer.denormalize("latent", out["z1_pred"]))
    per_sample = F.binary_cross_entropy_with_logits(logits, stance, reduction="none").mean((1, 2))
    torch.testing.assert_close(out["stance"], (out["tau"] * per_sample).mean())
    torch.testing.assert_close(out["loss"], out["recon"] + 0.5 * out["stance"])
    flow.zero_grad()
    out["stance"].backward()
    assert sum(p.grad.abs().sum() for p in flow.parameters() if p.grad is not None) > 0
    assert all(p.grad is None for p in vae.parameters())
    plain, _, _ = random_models("tiny", 8, SHELL, 0)
    with pytest.raises(ValueError, match="flow.stance_weight"):
        FlowObjective(flow, plain, normalizer)
    with pytest.raises(ValueError, match="stance_weight must be >= 0"):
        dataclasses.replace(flow.config, stance_weight=-1.0)


@pytest.fixture(scope="module")
def gliding(prepared_shards):
    """A body standing as the fixture's first frame, gliding 0.5 m/s along x, feet dragged."""
    windows = WindowDataset(prepared_shards, "train", extractor="logmel", window=64, seed=0, length=8)
    layout = MotionLayout.from_width(windows.motion_dim)
    body = np.repeat(windows[4]["motion"].numpy().astype(np.float64)[:1], 64, axis=0)
    glide = np.zeros((64, layout.width // 3, 3))
    glide[:, :, 0] = 0.5 / FPS * np.arange(64)[:, None]
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    return layout, body + glide.reshape(64, -1), lengths


def test_a_foot_steps_where_its_stance_lifts_along_the_datas_step(gliding):
    layout, decoded, lengths = gliding
    frames = len(decoded)
    stance = np.ones((frames, 2), bool)
    lifts = {0: [4, 14, 24, 34, 44, 54], 1: [9, 19, 29, 39, 49]}  # each foot every 1/3 s
    for side, starts in lifts.items():
        for start in starts:
            stance[start:start + STANCE_SWING_FRAMES, side] = False
    # the body glides less than STANCE_REACH per step; sideways (x is its hips' line), so a held
    # left foot comes within the lock's gap of the right one and steps early: not kept apart here
    lock = FootLock(layout, lengths, radius=0.1, gap=0.0)
    out = lock(decoded, stance)
    feet = joints_of(out, layout)[:, FEET]
    dragged = joints_of(decoded, layout)[:, FEET]
    for side, starts in lifts.items():
        moved = np.linalg.norm(np.diff(feet[:, side, [0, 2]], axis=0), axis=-1) > 1e-9
        # planted while the stance is: the foot moves only in the stance's swing frames (from
        # each foot's second step: the standing pose's legs are straight, so a foot planted
        # before the body set off is dragged until it first steps)
        moving = np.flatnonzero(moved) + 1
        np.testing.assert_array_equal(moving[moving >= 14],
                                      [f for s in starts[1:] for f in range(s, s + STANCE_SWING_FRAMES)])
        for start in starts[1:]:
            travel = feet[start - 1:start + STANCE_SWING_FRAMES, side, 0]
            share = (travel - travel[0]) / (travel[-1] - travel[0])
            # the data's step profile: the landing spot stays put for a body gliding evenly
            np.testing.assert_allclose(share, STEP_SHARE, atol=1e-6)
            assert travel[-1] - travel[0] > 0.5 / FPS * 7  # where the body has gone since
            lifted = feet[start:start + STANCE_SWING_FRAMES, side, 1] - dragged[start:start + STANCE_SWING_FRAMES, side, 1]
            assert lifted.max() > 0.9 * STANCE_LIFT and lifted.min() > 0
    lock.reset()
    blocks = np.concatenate([lock(decoded[i:i + 4], stance[i:i + 4]) for i in range(0, frames, 4)])
    np.testing.assert_array_equal(blocks, out)
    # a stance that never lifts leaves the lock stepping by drift alone, at STANCE_REACH, as its
    # step says (the data's: the test below)
    for step in ("data", "arc"):
        drift = FootLock(layout, lengths, radius=STANCE_REACH, step=step)
        alone = drift(decoded)
        drift.reset()
        np.testing.assert_array_equal(drift(decoded, np.ones_like(stance)), alone)
        assert np.abs(alone - out).max() > 0.05


@pytest.mark.parametrize("speed, reach", [(0.5, STANCE_REACH), (1.2, STANCE_REACH), (0.5, 0.3)])
def test_a_foot_whose_stance_stays_planted_steps_by_drift_along_the_datas_step(gliding, speed,
                                                                              reach):
    """The lock's targets for one foot gliding evenly under a stance that never lifts: planted
    until the decoded foot is ``reach`` away (vae.stance_reach, not the lock's radius), then the
    data's step (STANCE_SWING_FRAMES frames, STEP_SHARE of the way, lifted) to where the decoded
    foot is when it lands, and planted there for good, whatever the stance says; the arc (no
    stance) steps otherwise."""
    layout, _, lengths = gliding
    feet = [np.array([speed / FPS * t, 0.03, 0.0]) for t in range(60)]
    lock = FootLock(layout, lengths, radius=0.1, stance_reach=reach)
    targets = [lock._target(0, foot, True) for foot in feet]
    assert targets[0] is None  # planted where it stands
    x = np.array([feet[0][0]] + [target[0] for target in targets[1:]])
    first = next(t for t, foot in enumerate(feet) if foot[0] - feet[0][0] > reach)
    assert np.all(x[:first] == feet[0][0])  # held until the drift passes the reach
    steps = 0
    start = first
    while start + STANCE_SWING_FRAMES <= len(feet):
        land = start + STANCE_SWING_FRAMES - 1
        share = (x[start - 1:land + 1] - x[start - 1]) / (feet[land][0] - x[start - 1])
        np.testing.assert_allclose(share, STEP_SHARE, atol=1e-9)
        heights = np.array([targets[t][1] - feet[t][1] for t in range(start, land + 1)])
        assert np.all(heights > 0) and heights.max() == pytest.approx(STANCE_LIFT)
        steps += 1
        spot = feet[land][0]  # planted where it landed until the drift passes the reach again
        after = [t for t in range(land + 1, len(feet)) if feet[t][0] - spot > reach]
        held = range(land + 1, after[0] if after else len(feet))
        assert all(x[t] == spot for t in held)
        if not after:
            break
        start = after[0]
    assert steps >= 2
    arc = FootLock(layout, lengths, radius=reach, step="arc")
    arc_targets = [arc._target(0, foot) for foot in feet]
    arc_x = [feet[0][0] if target is None else target[0] for target in arc_targets]
    assert not np.allclose(arc_x, x)


def turning(layout, body, rate: float, start: int) -> np.ndarray:
    """``body``'s frames turned about the vertical through its pelvis at ``rate`` degrees a
    second (positive: toward its left) from frame ``start`` on, feet and all."""
    pelvis = joints_of(body[:1], layout)[0, JOINT["pelvis"]]
    points = body.reshape(len(body), -1, 3).copy()
    angle = np.deg2rad(rate) / FPS * np.maximum(np.arange(len(body)) - start, 0)[:, None]
    x, z = points[..., 0] - pelvis[0], points[..., 2] - pelvis[2]
    points[..., 0] = pelvis[0] + np.cos(angle) * x + np.sin(angle) * z
    points[..., 2] = pelvis[2] - np.sin(angle) * x + np.cos(angle) * z
    return points.reshape(len(body), -1)


def lateral_gap(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """The left ankle's floor offset from the right along the hips' line, per frame (m)."""
    joints = joints_of(motion, layout)
    across = (joints[:, JOINT["left_hip"]] - joints[:, JOINT["right_hip"]]) * [1, 0, 1]
    across /= np.linalg.norm(across, axis=-1, keepdims=True)
    return np.sum((joints[:, JOINT["left_ankle"]] - joints[:, JOINT["right_ankle"]]) * across, -1)


def foot_moves(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """(frames - 1, 2) whether each foot moves on the floor from one frame to the next."""
    feet = joints_of(motion, layout)[:, FEET]
    return np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1) > 1e-9


@pytest.mark.parametrize("rate", [90.0, -90.0])
def test_a_held_foot_steps_before_it_comes_under_the_other(gliding, rate):
    """Both stances planted and a far reach, the body turning on the spot: held where they stand,
    the feet come under and across each other along the turned hips' line; with ``gap`` a held
    foot steps (to its decoded place) when the feet come within ``gap``, so they never come much
    nearer (the turn narrows them by under 2 cm a frame). Turning toward its left, the feet take
    turns, as people turning on the spot do. Gliding the way it faces, the feet keep their width
    and the gap changes nothing. Streamed block by block as at once."""
    layout, body, lengths = gliding
    body = body[:1].repeat(72, axis=0)
    # the body stands while the lock plants its feet (its right foot, raised, comes down by
    # SWING_FRAMES), then turns
    still = SWING_FRAMES + 1
    turned = turning(layout, body, rate, still)
    stance = np.ones((len(body), 2), bool)
    gap = 0.13
    assert lateral_gap(turned, layout).min() > gap + 0.05  # the decoded feet stand wide
    crossing = FootLock(layout, lengths, radius=0.1, stance_reach=0.6, gap=0.0)(turned, stance)
    assert lateral_gap(crossing, layout).min() < -0.2
    lock = FootLock(layout, lengths, radius=0.1, stance_reach=0.6, gap=gap)
    apart = lock(turned, stance)
    assert lateral_gap(apart, layout).min() > gap - 0.02
    if rate > 0:
        moves = foot_moves(apart, layout)
        assert not moves[:still - 1].any()
        stepping = [int(np.flatnonzero(moves[t])[0]) for t in range(len(moves)) if moves[t].any()]
        assert not moves.all(axis=1).any()  # one foot at a time
        changes = np.flatnonzero(np.diff(stepping)) + 1
        runs = np.diff(np.concatenate([[0], changes, [len(stepping)]]))
        assert len(runs) >= 6 and np.all(runs[:-1] == STANCE_SWING_FRAMES)  # in turns, each the data's step
    lock.reset()
    blocks = np.concatenate([lock(turned[i:i + 4], stance[i:i + 4]) for i in range(0, len(body), 4)])
    np.testing.assert_array_equal(blocks, apart)
    glide = np.zeros((len(body), layout.width // 3, 3))
    glide[:, :, 2] = 0.5 / FPS * np.maximum(np.arange(len(body)) - still, 0)[:, None]
    forward = body + glide.reshape(len(body), -1)  # z: the way the fixture body faces
    wide = [FootLock(layout, lengths, radius=0.1, stance_reach=0.3, gap=g)(forward, stance)
            for g in (0.0, gap)]
    np.testing.assert_array_equal(wide[0], wide[1])
    assert np.abs(wide[0] - forward).max() > 0.05  # the lock held the feet there too
    with pytest.raises(ValueError, match="gap must be >= 0"):
        FootLock(layout, lengths, radius=0.1, gap=-0.1)


def walked_targets(lock: FootLock, frames: int, speed: float) -> np.ndarray:
    """The lock's (frames, 2, 3) feet for a body walking ``speed`` m/s along z with its feet
    dragged under its hips (x = +-9 cm), both stances planted, each frame as ``FootLock`` feeds
    ``_target``."""
    hips = np.array([[0.09, 0.9, 0.0], [-0.09, 0.9, 0.0]])
    ankles, feet = hips * [1, 0, 1] + [0, 0.08, 0], hips * [1, 0, 1] + [0, 0.03, 0.05]
    out = np.empty((frames, 2, 3))
    for t in range(frames):
        walked = np.array([0.0, 0.0, speed / FPS * t])
        for side in range(2):
            target = lock._target(side, feet[side] + walked, True, ankles + walked, np.zeros(3),
                                  hips + walked)
            held = np.zeros(3) if target is None else target - feet[side] - walked
            lock._ankles[side] = ankles[side] + walked + held
            out[t, side] = feet[side] + walked + held
    return out


def test_a_held_foot_left_behind_its_hip_steps_under_it(gliding):
    """Both stances planted and a far reach, the body walking: held where they stand, the feet
    trail ever further behind the hips; with ``lean`` a held ankle further than that from under
    its hip steps (the data's step, to its decoded place under the hip) while the other foot
    stands, so the feet take turns and never trail much further than ``lean``. Through the whole
    filter a body standing still is left as it was, and a bad lean is refused."""
    layout, body, lengths = gliding
    speed, lean, frames = 0.5, 0.1, 90
    trailing = walked_targets(FootLock(layout, lengths, radius=0.1, stance_reach=0.6, gap=0.0), frames, speed)
    behind = speed / FPS * np.arange(frames)[:, None] + 0.05 - trailing[..., 2]
    assert behind.max() > 0.5
    feet = walked_targets(FootLock(layout, lengths, radius=0.1, stance_reach=0.6, gap=0.0, lean=lean),
                          frames, speed)
    behind = speed / FPS * np.arange(frames)[:, None] + 0.05 - feet[..., 2]
    # a foot steps as its ankle passes lean, or waits for the other's step to land first
    assert behind.max() < lean + (STANCE_SWING_FRAMES + 1) * speed / FPS
    moves = np.abs(np.diff(feet[..., 2], axis=0)) > 1e-9
    starts = moves[1:] & ~moves[:-1]
    assert np.all(starts.sum(axis=0) >= 3)  # both feet step, again and again...
    both = moves.all(axis=1)
    assert not (both[1:] & both[:-1]).any()  # ...in turns: a foot lifts as the other lands
    standing = np.repeat(body[:1], 32, axis=0)
    still = [FootLock(layout, lengths, radius=0.1, lean=value)(standing) for value in (0.0, 0.05)]
    np.testing.assert_array_equal(still[0], still[1])
    with pytest.raises(ValueError, match="lean must be >= 0"):
        FootLock(layout, lengths, radius=0.1, lean=-0.1)

def stance_models():
    """Tiny random models whose decoding steps by their stance head, feet near the floor."""
    vae, flow, normalizer = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                                          audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                                          overrides=STANCE)
    layout = MotionLayout(shell_points=SHELL)
    mean = normalizer.motion_mean.double().numpy().copy()
    icosahedra, shell = layout.split(mean[None])
    for name in ("left_ankle", "right_ankle", "left_foot", "right_foot"):
        icosahedra[0, JOINT[name], :, 1] += 0.03 - icosahedra[0, JOINT[name], :, 1].mean()
    mean = np.concatenate([icosahedra.reshape(-1), shell.reshape(-1)])
    normalizer.set("motion", mean, normalizer.motion_std.double().numpy())
    lengths = bone_lengths(joints_of(mean[None], layout), layout.bones)[0]
    normalizer.set("bone_length", lengths, np.zeros_like(lengths))
    return vae, flow, normalizer


def test_a_stream_steps_by_its_stance_as_the_offline_solve_does():
    models = stance_models()
    vae = models[0]
    assert vae.stance is not None
    frames = 4 * 20
    rng = np.random.default_rng(0)
    head = np.stack([1.5 * np.cos(np.linspace(0, 2, frames)), 1.5 * np.sin(np.linspace(0, 2, frames))], 1)
    inputs = (head.astype(np.float32), rng.normal(size=(frames, 8)).astype(np.float32),
              rng.normal(size=(frames, 8)).astype(np.float32))
    config = StreamConfig(imputation="trajectory", noise_scale=0.6)
    gen = StreamingGenerator(*models, config)
    streamed = np.concatenate([gen.step(*(x[i:i + 4] for x in inputs)) for i in range(0, frames, 4)])
    offline, z = offline_with_latents(*models, *inputs, config)
    np.testing.assert_allclose(streamed, offline, atol=1e-5)
    # the stance was read and stepped by: drift alone decodes the same latents otherwise
    tokens = models[2].denormalize("latent", z)[None]
    planted = vae.stance.planted(vae.stance(tokens))[0].numpy()
    assert 0.05 < planted.mean() < 0.95
    vae.config = dataclasses.replace(vae.config, foot_lock_reads="drift")
    try:
        drift, _ = offline_with_latents(*models, *inputs, config)
    finally:
        vae.config = dataclasses.replace(vae.config, foot_lock_reads="stance")
    assert np.abs(drift - offline).max() > 1e-3
    # the model's vae.stance_reach is the reach its lock steps by drift at
    vae.config = dataclasses.replace(vae.config, stance_reach=0.35)
    locks = [f for f in stream_decoding(vae, models[2]).filters if isinstance(f, FootLock)]
    assert [lock.stance_reach for lock in locks] == [0.35]
    with pytest.raises(ValueError, match="stance_reach must be > 0"):
        dataclasses.replace(vae.config, stance_reach=0.0)
    # and its vae.foot_gap the gap its lock keeps between the feet
    vae.config = dataclasses.replace(vae.config, foot_gap=0.1)
    assert [f.gap for f in stream_decoding(vae, models[2]).filters if isinstance(f, FootLock)] == [0.1]
    with pytest.raises(ValueError, match="foot_gap .* must be >= 0"):
        dataclasses.replace(vae.config, foot_gap=-0.1)
    # and its vae.foot_lean how far from under its hip a held ankle may stand
    vae.config = dataclasses.replace(vae.config, foot_lean=0.12)
    assert [f.lean for f in stream_decoding(vae, models[2]).filters if isinstance(f, FootLock)] == [0.12]
    with pytest.raises(ValueError, match="foot_lean .* must be >= 0"):
        dataclasses.replace(vae.config, foot_lean=-0.1)


def test_a_recipe_with_a_stance_head_trains_writes_its_model_file_and_generates(prepared_shards,
                                                                                 tmp_path, capsys):
    """Both stages with vae.stance_weight, a model file that steps by the stance, generation
    from it; a model without the head refuses to step by one, naming the setting it lacks."""
    from sarah_cli.train import main
    from sarah_models.sampling.stream import generate_offline
    from sarah_models.training.model_file import load_model_file

    out = tmp_path / "run"
    small = ["vae.hidden=32", "vae.latent_dim=8", "vae.encoder_layers=1", "vae.decoder_layers=1",
             "flow.hidden=32", "flow.cond_dim=16", "flow.time_dim=16", "flow.layers=1",
             "train.window=16", "train.latent_stats_batches=1", "vae.stance_weight=0.2"]
    args = ["--stage", "all", "--config", "tiny", "--shards", str(prepared_shards), "--out", str(out),
            "--steps", "2", "--batch-size", "2", "--device", "cpu", "--no-progress"]
    assert main(args + sum((["--set", s] for s in small), [])) == 0, capsys.readouterr().err
    assert main(["--stage", "model", "--init-from", str(out), "--out", str(out), "--shards",
                 str(prepared_shards), "--set", "vae.foot_lock=0.1", "--set",
                 "vae.foot_lock_reads=stance"]) == 0, capsys.readouterr().err
    models = load_model_file(out / "model.safetensors", device="cpu")
    assert models.vae.stance is not None and models.vae.config.foot_lock_reads == "stance"
    trained = torch.load(out / "vae.pt", weights_only=True)["vae"]
    for name, value in models.vae.stance.state_dict().items():
        assert torch.equal(value, trained[f"stance.{name}"]), name
    frames = 16
    head = np.stack([np.linspace(1.0, 1.5, frames), np.zeros(frames)], 1).astype(np.float32)
    audio = np.zeros((frames, models.dims["audio"]), np.float32)
    motion = generate_offline(models.vae, models.flow, models.normalizer, head, audio, audio)
    assert motion.shape == (frames, models.dims["motion"]) and np.isfinite(motion).all()
    # The VAE fine-tuned with another stance weight keeps its head (only the loss weighs
    # otherwise); without one it would lose the head, which --init-from refuses by name.
    def fine_tune(folder, settings):
        return main(["--stage", "vae", "--config", "tiny", "--shards", str(prepared_shards),
                     "--out", str(tmp_path / folder), "--steps", "1", "--batch-size", "2",
                     "--device", "cpu", "--no-progress", "--init-from", str(out / "vae.pt")]
                    + sum((["--set", s] for s in settings), []))

    reweighed = [s.replace("vae.stance_weight=0.2", "vae.stance_weight=1.0") for s in small]
    assert fine_tune("tuned", reweighed) == 0, capsys.readouterr().err
    tuned = torch.load(tmp_path / "tuned" / "vae.pt", weights_only=True)
    assert tuned["config"]["vae"]["stance_weight"] == 1.0
    assert any(name.startswith("stance.") for name in tuned["vae"])
    capsys.readouterr()
    assert fine_tune("headless", [s for s in small if not s.startswith("vae.stance_weight")]) == 2
    assert "stance_weight: 0.2 there, 0.0 here" in capsys.readouterr().err
    assert main(["--stage", "model", "--init-from", "fixture-tiny", "--out", str(tmp_path / "no"),
                 "--set", "vae.foot_lock_reads=stance"]) == 2
    assert "vae.stance_weight" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_a_flow_stance_term_without_a_stance_head_stops_before_any_training(tmp_path, capsys):
    """`sarah-train --stage all` with flow.stance_weight and no vae.stance_weight: one line
    naming the setting, before the VAE stage trains (nothing written)."""
    from sarah_cli.train import main
    from sarah_models.config import RunConfig

    with pytest.raises(ValueError, match="flow.stance_weight"):
        RunConfig.preset("tiny").with_overrides(("flow.stance_weight=1",))
    out = tmp_path / "run"
    assert main(["--stage", "all", "--config", "tiny", "--shards", str(tmp_path / "shards"),
                 "--out", str(out), "--device", "cpu", "--no-progress",
                 "--set", "flow.stance_weight=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flow.stance_weight" in err[0]
    assert not out.exists()
    assert RunConfig.preset("tiny").with_overrides(
        ("vae.stance_weight=0.2", "flow.stance_weight=1")).flow.stance_weight == 1
