"""Streaming generation: causality, imputation, guidance, offline agreement, frames, sessions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sarah_data import icosahedron
from sarah_data.constants import NUM_JOINTS, SAMPLES_PER_FRAME
from sarah_data.frames import rotation_about_y, window_transform
from sarah_models.config import HISTORY_WINDOW, RunConfig, StreamConfig
from sarah_models.nn.flow import MODALITIES
from sarah_models.sampling.decoding import stream_decoding
from sarah_models.sampling.guidance import drop_masks, scale_at
from sarah_models.sampling.solver import imputer, integrate
from sarah_models.sampling.stream import (
    StreamingGenerator,
    StreamingSession,
    generate_offline,
    kept_history,
    offline_with_latents,
    push_together,
    solve,
    step_together,
)
from sarah_models.testing import random_models

SHELL = 4
S = 4  # stride of the tiny VAE


def tiny_models(audio_dim: int = 8, seed: int = 0, audio_mean: float = 0.0,
                audio_std: float = 1.0, shell_points: int = SHELL):
    """A tiny VAE + flow (untrained, random AdaLN weights) and a normalizer, in eval mode."""
    config = RunConfig.preset("tiny")
    dims = {"motion": NUM_JOINTS * 36 + 3 * shell_points, "audio": audio_dim}
    vae, flow, normalizer = random_models("tiny", audio_dim, shell_points, seed, motion_std=0.02,
                                          init_std=0.05, audio_mean=audio_mean, audio_std=audio_std,
                                          latent_mean_std=0.1)
    return config, dims, vae, flow, normalizer


@pytest.fixture(scope="module")
def models():
    _, _, vae, flow, normalizer = tiny_models()
    return vae, flow, normalizer


def make_inputs(frames: int, seed: int = 0, audio_dim: int = 8):
    rng = np.random.default_rng(seed)
    head = np.stack([1.5 * np.cos(np.linspace(0, 2, frames)),
                     1.5 * np.sin(np.linspace(0, 2, frames))], 1)
    return (head.astype(np.float32), rng.normal(size=(frames, audio_dim)).astype(np.float32),
            rng.normal(size=(frames, audio_dim)).astype(np.float32))


def stream(models, inputs, config: StreamConfig, anchor=None) -> np.ndarray:
    """``inputs`` streamed one latent block (the VAE's stride) at a time."""
    head, a, b = inputs
    gen, s = StreamingGenerator(*models, config, anchor), models[0].stride
    return np.concatenate([gen.step(head[i:i + s], a[i:i + s], b[i:i + s])
                           for i in range(0, len(head), s)])


def test_output_shape_and_world_frame(models):
    out = stream(models, make_inputs(12), StreamConfig())
    assert out.shape == (12, NUM_JOINTS * 36 + 3 * SHELL) and out.dtype == np.float32
    positions, rotations = icosahedron.decode(out[:, :NUM_JOINTS * 36].reshape(12, -1, 12, 3))
    assert np.isfinite(positions).all()
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-4)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(k=st.integers(1, 4), seed=st.integers(0, 1000), history=st.sampled_from([0, 1, 2, None]))
def test_first_chunks_ignore_later_inputs(models, k, seed, history):
    """Outputs of the first k chunks are byte-identical whether later inputs exist or change."""
    config = StreamConfig(history_tokens=history, steps=2)
    head, a, b = make_inputs(5 * S)
    base = stream(models, (head, a, b), config)
    rng = np.random.default_rng(seed)
    changed = [x.copy() for x in (head, a, b)]
    for x in changed:
        x[k * S:] = rng.normal(size=x[k * S:].shape) * 3
    other = stream(models, tuple(changed), config)
    prefix = stream(models, tuple(x[:k * S] for x in (head, a, b)), config)
    assert np.array_equal(base[:k * S], other[:k * S])
    assert np.array_equal(base[:k * S], prefix)
    assert not np.array_equal(base[k * S:], other[k * S:])


def test_same_seed_same_bytes_and_reset(models):
    inputs = make_inputs(12)
    config = StreamConfig(seed=3)
    first = stream(models, inputs, config)
    assert np.array_equal(first, stream(models, inputs, config))
    assert not np.array_equal(first, stream(models, inputs, StreamConfig(seed=4)))
    gen = StreamingGenerator(*models, config)
    head, a, b = inputs
    gen.step(head[:S], a[:S], b[:S])
    gen.reset()
    again = np.concatenate([gen.step(head[i:i + S], a[i:i + S], b[i:i + S]) for i in (0, 4, 8)])
    assert np.array_equal(first, again)


def test_gaze_target_changes_the_motion(models):
    inputs = make_inputs(12)
    outs = {g: stream(models, inputs, StreamConfig(gaze=g)) for g in (None, 0.8, -0.5)}
    assert not np.allclose(outs[None], outs[0.8], atol=1e-4)
    assert not np.allclose(outs[0.8], outs[-0.5], atol=1e-4)


def test_guidance_formula_end_points(models):
    """x1 = x1_u + w (x1_c - x1_u): with gaze-only guidance w = 0 is the gaze-dropped model
    (gaze=None), and w = 1 is the conditional model alone (one pass)."""
    inputs = make_inputs(12)
    gaze_only = ("gaze",)
    dropped = stream(models, inputs, StreamConfig(gaze=None, guide=gaze_only))
    np.testing.assert_allclose(stream(models, inputs, StreamConfig(gaze=0.8, cfg_scale=0.0,
                                                                   guide=gaze_only)),
                               dropped, atol=1e-5)
    assert drop_masks(0.8, ("gaze",), 1.0).shape == (1, 4)
    assert drop_masks(None, ("gaze",), 1.3).shape == (1, 4)  # both passes equal: one pass
    masks = drop_masks(0.8, ("gaze",), 1.3)
    assert masks.tolist() == [[False] * 4, [False, False, False, True]]
    conditional = stream(models, inputs, StreamConfig(gaze=0.8, cfg_scale=1.0))
    guided = stream(models, inputs, StreamConfig(gaze=0.8, cfg_scale=1.3, guide=gaze_only))
    # Guidance extrapolates past the conditional model, away from the gaze-dropped one.
    assert np.abs(guided - dropped).mean() > np.abs(conditional - dropped).mean()


def test_default_guidance_guides_the_whole_conditioning(models):
    """The default unconditional pass drops every modality, so w = 1.3 acts for g = None too
    (with gaze-only guidance both passes were the same there and nothing was guided)."""
    everything = StreamConfig().guide
    assert set(everything) == set(MODALITIES)
    assert drop_masks(None, everything, 1.3).tolist() == [[False, False, False, True], [True] * 4]
    inputs = make_inputs(12)
    unguided = stream(models, inputs, StreamConfig(gaze=None, cfg_scale=1.0))
    guided = stream(models, inputs, StreamConfig(gaze=None))
    assert np.abs(guided - unguided).max() > 1e-4


def test_guiding_the_gaze_score_matters_only_with_a_gaze_target(models):
    """g = None drops the gaze score from both passes, so guiding it too (`--guide
    user_head,gaze`) is bit for bit guiding the user's position alone (`--guide user_head`):
    a sampling setting tuned at g = None holds for either, and the two differ only where a gaze
    target is given (the fixture benchmark's gaze sweep, docs/models.md)."""
    inputs = make_inputs(12)
    position = StreamConfig(gaze=None, cfg_scale=4.5, guide=("user_head",))
    position_and_gaze = dataclasses.replace(position, guide=("user_head", "gaze"))
    np.testing.assert_array_equal(stream(models, inputs, position),
                                  stream(models, inputs, position_and_gaze))
    with_target = dataclasses.replace(position, gaze=0.8)
    assert np.abs(stream(models, inputs, with_target) - stream(
        models, inputs, dataclasses.replace(position_and_gaze, gaze=0.8))).max() > 1e-4


def test_guidance_interval_guides_only_the_evaluations_inside_it(models):
    """Four midpoint steps evaluate at tau = 0, 1/8, ..., 7/8: an interval holding none of them
    is the conditional model alone; one holding all of them is full guidance; one holding some
    is neither."""
    inputs = make_inputs(12)
    config = StreamConfig(gaze=None, cfg_scale=4.0, noise_scale=0.6)
    conditional = stream(models, inputs, dataclasses.replace(config, cfg_scale=1.0))
    full = stream(models, inputs, config)
    np.testing.assert_allclose(
        stream(models, inputs, dataclasses.replace(config, guidance_interval=(0.9, 1.0))),
        conditional, atol=1e-5)
    np.testing.assert_array_equal(
        stream(models, inputs, dataclasses.replace(config, guidance_interval=(0.0, 0.9))), full)
    early = stream(models, inputs, dataclasses.replace(config, guidance_interval=(0.0, 0.5)))
    late = stream(models, inputs, dataclasses.replace(config, guidance_interval=(0.5, 1.0)))
    for other in (conditional, full, late):
        assert np.abs(early - other).max() > 1e-4
    assert np.abs(late - conditional).max() > 1e-4 and np.abs(late - full).max() > 1e-4
    assert [scale_at(t, 4.0, (0.25, 0.5)) for t in (0.0, 0.25, 0.375, 0.5)] == [1.0, 4.0, 4.0, 1.0]


def test_unguided_evaluations_run_the_conditional_branch_alone(models):
    """Outside the guidance interval the unconditional branch would be computed and dropped:
    those evaluations run the conditional rows only, inside it both branches run as one batch."""
    _, flow, _ = models
    rows: list[int] = []
    hook = flow.register_forward_pre_hook(lambda module, args: rows.append(args[0].shape[0]))
    try:
        stream(models, make_inputs(2 * S), StreamConfig(gaze=None, cfg_scale=4.0,
                                                        guidance_interval=(0.0, 0.5)))
    finally:
        hook.remove()
    # 4 midpoint steps evaluate at tau = 0, 1/8, ..., 7/8: the first four are guided
    assert rows == [2, 2, 2, 2, 1, 1, 1, 1] * 2


def test_position_embedding_gives_streaming_the_offline_indices(models):
    """Token k of a stream gets the position embedding offline generation gives it, also past
    the training window's tokens (they share the last one), and the first token is told apart
    from the others when every input is the same."""
    _, flow, _ = models
    n = flow.config.position_tokens + 3
    same = {"user_head": torch.ones(1, n * S, 2), "agent_audio": torch.ones(1, n * S, 8),
            "user_audio": torch.ones(1, n * S, 8), "gaze": torch.zeros(1, n * S, 1)}
    with torch.no_grad():
        offline = flow.encode_condition(same)
        for k in range(n):
            block = {key: value[:, k * S:(k + 1) * S] for key, value in same.items()}
            torch.testing.assert_close(flow.encode_condition(block, first_token=k)[:, 0],
                                       offline[:, k])
    assert not torch.allclose(offline[:, 0], offline[:, 1])
    assert torch.equal(offline[:, -1], offline[:, flow.config.position_tokens - 1])
    with pytest.raises(ValueError, match="first_token"):
        flow.encode_condition(same, first_token=-1)


def test_runs_saved_before_the_position_embedding_load_without_one():
    stored = RunConfig.preset("tiny").to_dict()
    del stored["flow"]["position_embedding"]
    config = RunConfig.from_dict(stored)
    assert config.flow.position_embedding is False
    from sarah_models.training.checkpoint import build_models

    _, flow = build_models(config, {"motion": 1992, "audio": 8})
    assert not hasattr(flow, "token_positions")


def test_solve_keeps_history_tokens_exactly(models):
    _, flow, _ = models
    g = torch.Generator().manual_seed(0)
    noise, known = torch.randn(3, flow.latent_dim, generator=g), torch.randn(2, flow.latent_dim, generator=g)
    cond = {"user_head": torch.randn(1, 3 * S, 2, generator=g),
            "agent_audio": torch.randn(1, 3 * S, 8, generator=g),
            "user_audio": torch.randn(1, 3 * S, 8, generator=g), "gaze": torch.zeros(1, 3 * S, 1)}
    with torch.no_grad():
        tokens = flow.encode_condition(cond)
        z = solve(flow, tokens, noise, known, StreamConfig())
        # The new token depends on the history values, not only on their noise.
        z_other = solve(flow, tokens, noise, known + 1.0, StreamConfig())
    assert torch.equal(z[:2], known)
    assert not torch.allclose(z[2], z_other[2])


def test_streaming_equals_offline_where_the_maths_says_so(models):
    inputs = make_inputs(24)
    head, a, b = inputs
    # (b) one Euler step: the only evaluation is at tau = 0, where imputed history = its noise.
    one_step = StreamConfig(history_tokens=None, solver="euler", steps=1)
    np.testing.assert_allclose(stream(models, inputs, one_step),
                               generate_offline(*models, head, a, b, one_step), atol=1e-5)
    # (a) a single token, any solver.
    full = StreamConfig(history_tokens=None)
    one = tuple(x[:S] for x in inputs)
    np.testing.assert_allclose(stream(models, one, full), generate_offline(*models, *one, full),
                               atol=1e-5)
    # In general only the first token agrees (causality); later ones differ, because offline
    # history tokens follow curved solver paths while streaming imputes straight ones.
    streamed, offline = stream(models, inputs, full), generate_offline(*models, head, a, b, full)
    np.testing.assert_allclose(streamed[:S], offline[:S], atol=1e-5)
    assert np.abs(streamed[S:] - offline[S:]).max() > 1e-4


@pytest.mark.parametrize("gaze, cfg, solver, interval", [
    (0.8, 1.3, "midpoint", (0.0, 1.0)), (None, 0.6, "midpoint", (0.0, 1.0)),
    (0.3, 1.0, "euler", (0.0, 1.0)), (None, 4.0, "midpoint", (0.3, 0.7))])
def test_trajectory_imputation_streams_the_offline_solve(models, gaze, cfg, solver, interval):
    """With each history token's own trajectory replayed, and as many history tokens as the
    tiny flow's stacked attention windows reach, a stream is offline generation computed
    causally: the same latents and frames, past the position embedding's last index too."""
    vae, flow, _ = models
    assert flow.context_tokens == 5  # 2 layers of windows of 3 tokens
    inputs = make_inputs(4 * 22)  # 22 tokens: past the 16 position indices
    config = StreamConfig(imputation="trajectory", gaze=gaze, cfg_scale=cfg, solver=solver,
                          noise_scale=0.6, guidance_interval=interval)
    gen = StreamingGenerator(*models, config)
    streamed, latents = [], []
    for i in range(0, len(inputs[0]), S):
        streamed.append(gen.step(*(x[i:i + S] for x in inputs)))
        latents.append(gen.last_latent)
    offline, z = offline_with_latents(*models, *inputs, config)
    torch.testing.assert_close(torch.stack(latents), z, atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.concatenate(streamed), offline, atol=1e-5)
    # the paper's imputation of the same stream parts from offline after the first token
    final = stream(models, inputs, dataclasses.replace(config, imputation="final"))
    assert np.abs(final[S:] - offline[S:]).max() > 1e-4


def test_trajectory_imputation_with_unbounded_attention_keeps_what_it_is_told():
    """A flow that attends to every earlier token (the paper's) equals offline when the stream
    keeps all its history, and not when it keeps the default two tokens."""
    models = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                           audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                           overrides=("flow.attention_window=None",))
    assert models[1].context_tokens is None
    inputs = make_inputs(4 * 10)
    offline = generate_offline(*models, *inputs, StreamConfig(imputation="trajectory"))
    every = stream(models, inputs, StreamConfig(imputation="trajectory", history_tokens=None))
    np.testing.assert_allclose(every, offline, atol=1e-5)
    two = stream(models, inputs, StreamConfig(imputation="trajectory"))
    np.testing.assert_allclose(two[:3 * S], offline[:3 * S], atol=1e-5)
    assert np.abs(two[3 * S:] - offline[3 * S:]).max() > 1e-4
    with pytest.raises(ValueError, match="imputation"):
        StreamConfig(imputation="straight")


def test_the_default_history_is_what_one_layer_of_the_flow_attends_to():
    """StreamConfig's default keeps the latents one layer of the flow attends to beside the new
    token: 16 for a flow trained with a 17-token window (with the paper's 2 such a flow wanders,
    docs/results.md, forty-ninth run), the paper's 2 for the tiny preset's window of 3 and for a
    flow without a window. A number is kept as given; trajectory imputation keeps the whole
    reach of the stacked windows."""
    flows = {window: random_models("tiny", 8, SHELL, 0, overrides=(f"flow.attention_window={window}",))[1]
             for window in (None, 3, 17)}
    assert StreamConfig().history_tokens == HISTORY_WINDOW
    assert {w: kept_history(f, StreamConfig()) for w, f in flows.items()} == {None: 2, 3: 2, 17: 16}
    assert {w: kept_history(f, StreamConfig(history_tokens=5)) for w, f in flows.items()} == {None: 5, 3: 5, 17: 5}
    assert kept_history(flows[17], StreamConfig(imputation="trajectory")) == flows[17].context_tokens - 1 == 32
    for bad in ("windows", True, 2.0, -1):
        with pytest.raises(ValueError, match="history_tokens"):
            StreamConfig(history_tokens=bad)
    # the stream keeps that many: by default a 6-token window streams as --history 5 does
    models = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05, audio_mean=0.0,
                           audio_std=1.0, latent_mean_std=0.1, overrides=("flow.attention_window=6",))
    inputs = make_inputs(S * 12)
    default = stream(models, inputs, StreamConfig())
    np.testing.assert_array_equal(default, stream(models, inputs, StreamConfig(history_tokens=5)))
    assert np.abs(default - stream(models, inputs, StreamConfig(history_tokens=2))).max() > 1e-4


def test_two_frame_tokens_stream_causally_and_as_the_offline_solve():
    """At stride 2 (the fixture benchmark's forty-fourth run, docs/results.md) a chunk is 2
    frames: the first chunks ignore later inputs, and with trajectory imputation the stream is
    the offline solve, past the position embedding's last index and past 100 tokens (the
    decoder's context is T = 400 frames whatever the stride, 200 tokens here)."""
    models = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                           audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                           overrides=("vae.stride=2", "flow.attention_window=6"))
    vae, flow, _ = models
    s = vae.stride
    assert s == 2 and flow.config.position_tokens == 32 and flow.context_tokens == 11
    assert StreamConfig().decoder_blocks(s) == 200 and StreamConfig().decoder_blocks(4) == 100
    inputs = make_inputs(s * 110)
    config = StreamConfig(imputation="trajectory", cfg_scale=1.3, noise_scale=0.6)
    streamed = stream(models, inputs, config)
    assert streamed.shape[0] == len(inputs[0])
    np.testing.assert_allclose(streamed, generate_offline(*models, *inputs, config), atol=1e-5)
    changed = [x.copy() for x in inputs]
    for x in changed:
        x[5 * s:] = np.random.default_rng(1).normal(size=x[5 * s:].shape) * 3
    for imputation in ("trajectory", "final"):
        config = StreamConfig(imputation=imputation, steps=2)
        base, other = stream(models, inputs, config), stream(models, changed, config)
        assert np.array_equal(base[:5 * s], other[:5 * s])
        assert not np.array_equal(base[5 * s:], other[5 * s:])


def test_noise_scale_is_the_temperature_of_every_tokens_noise(models):
    """noise_scale multiplies each token's eps, in streaming and offline alike (the one-step
    Euler stream still equals offline), and 1 is the paper's standard normal."""
    from sarah_models.sampling.solver import token_noise

    draws = [token_noise(torch.Generator().manual_seed(5), 16, scale) for scale in (1.0, 0.6)]
    assert torch.equal(draws[1], draws[0] * 0.6)
    inputs = make_inputs(24)
    head, a, b = inputs
    cool = StreamConfig(history_tokens=None, solver="euler", steps=1, noise_scale=0.6)
    np.testing.assert_allclose(stream(models, inputs, cool),
                               generate_offline(*models, head, a, b, cool), atol=1e-5)
    assert np.array_equal(stream(models, inputs, StreamConfig()),
                          stream(models, inputs, StreamConfig(noise_scale=1.0)))
    assert not np.allclose(stream(models, inputs, StreamConfig()),
                           stream(models, inputs, StreamConfig(noise_scale=0.6)), atol=1e-4)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="noise scale"):
            StreamConfig(noise_scale=bad)


def test_recorded_latents_are_the_ones_decoded(models):
    """generate()'s Result.latents (what motion_anatomy's latent table reads) are the flow's
    standardized latents of each protocol: decoding them gives the motion, token 1 is the same
    in both protocols (causality) and later tokens are not."""
    from sarah_models.generation.inputs import Inputs
    from sarah_models.generation.run import generate
    from sarah_models.sampling.stream import IDENTITY
    from sarah_models.training.checkpoint import LoadedModels

    vae, flow, normalizer = models
    head, a, b = make_inputs(24)
    loaded = LoadedModels(vae, flow, normalizer, RunConfig.preset("tiny"), {}, "logmel", 0, "flow")
    inputs = Inputs(user_head=head, agent_speaking=np.zeros(24, bool),
                    user_speaking=np.zeros(24, bool), anchor=IDENTITY, source={},
                    agent_audio=a, user_audio=b)
    config = StreamConfig(history_tokens=None)
    streamed, offline = (generate(loaded, inputs, config, offline=o) for o in (False, True))
    assert streamed.latents.shape == offline.latents.shape == (24 // S, flow.latent_dim)
    np.testing.assert_allclose(streamed.latents[0], offline.latents[0], atol=1e-5)
    assert np.abs(streamed.latents[1:] - offline.latents[1:]).max() > 1e-4
    for result in (streamed, offline):
        z = normalizer.denormalize("latent", torch.from_numpy(result.latents))
        with torch.inference_mode():
            motion = normalizer.denormalize("motion", vae.decode(z[None])[0]).double().numpy()
        decoded = stream_decoding(vae, normalizer)(motion)
        np.testing.assert_allclose(decoded.astype(np.float32), result.motion, atol=1e-4)


def test_a_stream_sums_the_root_steps_as_its_latents_decoded_at_once_do(models):
    """vae.root_steps: a stream sums the root's floor steps block by block from the frame it
    decoded last (``Normalizer.denormalize``'s ``before``); its latents decoded at once, the
    steps summed from the origin, give the same motion, and a root summed from the origin at
    every block would not."""
    from sarah_models.generation.inputs import Inputs
    from sarah_models.generation.run import generate
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.sampling.stream import IDENTITY
    from sarah_models.training.checkpoint import LoadedModels

    vae, flow, normalizer = models
    steps = Normalizer.from_state_dict(normalizer.state_dict())
    steps.set_root_relative([0, 1], steps=True)
    head, a, b = make_inputs(24)
    loaded = LoadedModels(vae, flow, steps, RunConfig.preset("tiny"), {}, "logmel", 0, "flow")
    inputs = Inputs(user_head=head, agent_speaking=np.zeros(24, bool),
                    user_speaking=np.zeros(24, bool), anchor=IDENTITY, source={},
                    agent_audio=a, user_audio=b)
    streamed = generate(loaded, inputs, StreamConfig(history_tokens=None), offline=False)
    z = steps.denormalize("latent", torch.from_numpy(streamed.latents))
    with torch.inference_mode():
        decoded = vae.decode(z[None])[0]
    at_once = stream_decoding(vae, steps)(steps.denormalize("motion", decoded).double().numpy())
    np.testing.assert_allclose(at_once.astype(np.float32), streamed.motion, atol=1e-4)
    by_block = torch.cat([steps.denormalize("motion", decoded[i:i + S]) for i in range(0, 24, S)])
    restarted = stream_decoding(vae, steps)(by_block.double().numpy())
    assert np.abs(restarted.astype(np.float32) - streamed.motion).max() > 1e-3


@pytest.mark.parametrize("solver, order", [("midpoint", 2), ("euler", 1)])
def test_solver_converges_at_its_order(solver, order):
    """On dz/dtau = (cos 3 tau - 1.5) z (exact: z0 exp(sin(3)/3 - 1.5)), halving the step
    divides the error by 2^order: fewer steps approximate the same solution, they do not
    draw another one."""
    z0 = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    exact = z0 * np.exp(np.sin(3.0) / 3.0 - 1.5)

    def error(steps: int) -> float:
        z = integrate(lambda z, tau: (np.cos(3.0 * tau) - 1.5) * z, z0, imputer(z0, None),
                      StreamConfig(steps=steps, solver=solver))
        return float((z - exact).abs().max())

    errors = [error(n) for n in (16, 32, 64, 128)]
    for coarse, fine in zip(errors, errors[1:]):
        assert coarse / fine == pytest.approx(2.0 ** order, rel=0.2)


def test_fewer_steps_approach_the_many_step_stream(models):
    """The same seed gives every token the same noise whatever the step count, so streams with
    more steps converge to one motion (random weights: a rough field, slow but steady)."""
    inputs = make_inputs(32)
    reference = stream(models, inputs, StreamConfig(steps=8))
    deviation = [np.abs(stream(models, inputs, StreamConfig(steps=n)) - reference).max()
                 for n in (1, 2, 4)]
    assert deviation[0] > deviation[1] > deviation[2] > 0
    other_seed = np.abs(stream(models, inputs, StreamConfig(steps=4, seed=1)) - reference).max()
    assert other_seed > 2 * deviation[2]


def test_history_window_slides():
    """With 2 history tokens the window equals full history for 3 chunks, then drops tokens
    (a flow with full attention context, so that older tokens would matter)."""
    models = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                           audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                           overrides=("flow.attention_window=None",))
    inputs = make_inputs(20)
    limited = stream(models, inputs, StreamConfig(history_tokens=2))
    full = stream(models, inputs, StreamConfig(history_tokens=None))
    np.testing.assert_allclose(limited[:3 * S], full[:3 * S], atol=1e-5)
    assert np.abs(limited[3 * S:] - full[3 * S:]).max() > 1e-4


def test_anchor_maps_world_inputs_and_outputs(models):
    """Generating with an anchor == generating in the anchor's frame, then mapping to world."""
    anchor = window_transform(np.array([1.0, 0.9, -2.0]), rotation_about_y(0.7))
    head, a, b = make_inputs(12)
    world = stream(models, (head, a, b), StreamConfig(), anchor)
    local = stream(models, (anchor.apply_floor(head.astype(np.float64)).astype(np.float32), a, b),
                   StreamConfig())
    expected = anchor.invert_points(local.reshape(12, -1, 3).astype(np.float64)).reshape(12, -1)
    np.testing.assert_allclose(world, expected, atol=1e-4)


def test_bad_inputs_and_settings_are_refused(models):
    gen = StreamingGenerator(*models)
    head, a, b = make_inputs(S)
    with pytest.raises(ValueError, match="user_head"):
        gen.step(head[:3], a, b)
    with pytest.raises(ValueError, match="agent_audio"):
        gen.step(head, a[:, :5], b)
    with pytest.raises(ValueError, match="non-finite"):
        gen.step(head, np.full_like(a, np.nan), b)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        gen.set_gaze(1.5)
    for bad in ({"gaze": -1.01}, {"steps": 0}, {"solver": "rk4"}, {"guide": ("face",)},
                {"history_tokens": -1}, {"guidance_interval": (0.5, 0.5)},
                {"guidance_interval": (-0.1, 1.0)}, {"guidance_interval": (0.0, 1.5)}):
        with pytest.raises(ValueError):
            StreamConfig(**bad)


def test_session_streams_raw_audio_in_any_chunking():
    """Raw audio through the causal log-mel stream, pushed in irregular pieces, gives the same
    frames as stepping with the offline features (log-mel streaming equals offline)."""
    from sarah_data.features import get_extractor

    extractor = get_extractor("logmel")
    _, _, vae, flow, normalizer = tiny_models(audio_dim=extractor.dim, audio_mean=-8.0,
                                              audio_std=4.0)
    frames = 12
    rng = np.random.default_rng(1)
    t = np.arange(frames * SAMPLES_PER_FRAME) / 48_000
    agent = (0.3 * np.sin(2 * np.pi * 220 * t) * (t > 0.15)).astype(np.float32)
    user = (0.05 * rng.normal(size=t.size)).astype(np.float32)
    head = make_inputs(frames)[0]
    config = StreamConfig(steps=2)
    reference = stream((vae, flow, normalizer),
                       (head, extractor.extract(agent, frames), extractor.extract(user, frames)),
                       config)
    session = StreamingSession(StreamingGenerator(vae, flow, normalizer, config), extractor)
    cuts = np.sort(rng.choice(np.arange(1, t.size), 7, replace=False))
    out, frame_done = [], 0
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, t.size]):
        done = hi // SAMPLES_PER_FRAME
        out.append(session.push(head[frame_done:done], agent[lo:hi], user[lo:hi]))
        frame_done = done
    got = np.concatenate(out)
    assert got.shape == reference.shape
    np.testing.assert_allclose(got, reference, atol=1e-5)
    np.testing.assert_allclose(session.features("agent"), extractor.extract(agent, frames),
                               atol=1e-5)


def test_streams_stepped_together_get_what_each_gets_alone(models):
    """``step_together`` over streams that differ in seed, gaze (one guidance branch or two),
    steps, imputation and history length gives each stream the frames and latents of its own ``step``
    (to summation order), round after round."""
    configs = [StreamConfig(seed=0), StreamConfig(seed=1, gaze=0.8), StreamConfig(seed=2),
               StreamConfig(seed=3, steps=2), StreamConfig(seed=4, imputation="trajectory"),
               StreamConfig(seed=5, imputation="trajectory"), StreamConfig(seed=6)]
    inputs = [make_inputs(24, seed=i) for i in range(len(configs))]
    alone = [StreamingGenerator(*models, c) for c in configs]
    together = [StreamingGenerator(*models, c) for c in configs]
    for generators in (alone, together):  # the last stream starts a block ahead: a shorter window
        generators[-1].step(*(x[:S] for x in inputs[-1]))
    for k in range(4, 24, S):
        block = [tuple(x[k:k + S] for x in stream_inputs) for stream_inputs in inputs]
        expected = [g.step(*b) for g, b in zip(alone, block)]
        got = step_together(together, block)
        for e, g in zip(expected, got):
            np.testing.assert_allclose(g, e, atol=1e-5)
        for a, t in zip(alone, together):
            torch.testing.assert_close(t.last_latent, a.last_latent, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="twice"):
        step_together([together[0], together[0]], block[:2])
    with pytest.raises(ValueError, match="inputs"):
        step_together(together, block[:2])
    # one stream's bad input stops the round before any stream moves on
    bad = [block[0], (block[1][0][:2], *block[1][1:])] + block[2:]
    with pytest.raises(ValueError, match="user_head"):
        step_together(together, bad)
    expected = [g.step(*b) for g, b in zip(alone, block)]
    for e, g in zip(expected, step_together(together, block)):
        np.testing.assert_allclose(g, e, atol=1e-5)


def test_sessions_pushed_together_get_what_each_gets_alone():
    """``push_together`` with pushes of different lengths (one session completes two blocks in
    a round, another none) gives each session the frames and features of its own ``push``."""
    from sarah_data.features import get_extractor

    extractor = get_extractor("logmel")
    vae, flow, normalizer = tiny_models(audio_dim=extractor.dim, audio_mean=-8.0, audio_std=4.0)[2:]
    rng = np.random.default_rng(2)
    frames = 16
    audio = [(0.1 * rng.normal(size=frames * SAMPLES_PER_FRAME)).astype(np.float32)
             for _ in range(6)]
    head = make_inputs(frames)[0]
    cuts = [(0, 4, 8, 16), (0, 8, 10, 16), (0, 3, 9, 16)]  # frames pushed per round, per session

    def sessions():
        return [StreamingSession(StreamingGenerator(vae, flow, normalizer, StreamConfig(seed=i)),
                                 extractor) for i in range(3)]

    def piece(i, r):
        lo, hi = cuts[i][r], cuts[i][r + 1]
        span = slice(lo * SAMPLES_PER_FRAME, hi * SAMPLES_PER_FRAME)
        return head[lo:hi], audio[2 * i][span], audio[2 * i + 1][span]

    alone, together = sessions(), sessions()
    for r in range(3):
        expected = [s.push(*piece(i, r)) for i, s in enumerate(alone)]
        got = push_together(together, [piece(i, r) for i in range(3)])
        for i in range(3):
            assert got[i].shape == expected[i].shape
            np.testing.assert_allclose(got[i], expected[i], atol=1e-5)
            for person in ("agent", "user"):
                np.testing.assert_array_equal(together[i].last_features[person],
                                              alone[i].last_features[person])
    assert [len(s.features("agent")) for s in together] == [16, 16, 16]


def test_a_stream_carries_the_users_head_travel_as_offline_does():
    """flow.head_travel_seconds: the stream carries the running mean of the user's head speed
    from block to block, so with trajectory imputation it is still the offline solve; and a
    walk in the first block changes the last block's latent, which without the feature lies
    beyond what the windowed flow's joint solve carries (float rounding)."""
    def walk_reaches_the_last_token(models) -> float:
        standing = (np.repeat(inputs[0][-1:], len(inputs[0]), 0), *inputs[1:])
        walked = standing[0].copy()
        walked[:S] = inputs[0][:S]  # the user walks in the first block only
        still = offline_with_latents(*models, *standing, config)[1]
        return float((offline_with_latents(*models, walked, *inputs[1:], config)[1][-1]
                      - still[-1]).abs().max())

    travel, plain = (random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                                   audio_mean=0.0, audio_std=1.0, latent_mean_std=0.1,
                                   overrides=overrides)
                     for overrides in (("flow.head_travel_seconds=2.0",), ()))
    inputs = make_inputs(4 * 22)
    config = StreamConfig(imputation="trajectory", cfg_scale=1.3, noise_scale=0.6)
    gen = StreamingGenerator(*travel, config)
    latents = []
    for i in range(0, len(inputs[0]), S):
        gen.step(*(x[i:i + S] for x in inputs))
        latents.append(gen.last_latent)
    torch.testing.assert_close(torch.stack(latents),
                               offline_with_latents(*travel, *inputs, config)[1], atol=1e-5, rtol=0)
    assert walk_reaches_the_last_token(travel) > 1e-2
    assert walk_reaches_the_last_token(plain) < 1e-4


def test_a_turning_hold_reads_the_user_in_the_generation_frame_streamed_and_offline():
    """vae.root_hold_turn turns the held body by its bearing to the user, which the decoding
    reads in the generation frame: a stream is the offline solve with it, and the same motion
    put anywhere in the world (an anchor) comes out the same, moved with it."""
    from sarah_data.frames import WindowTransform

    _, _, vae, flow, normalizer = tiny_models()
    models = (vae, flow, normalizer)
    inputs = make_inputs(4 * 12)
    config = StreamConfig(imputation="trajectory", noise_scale=0.6)
    vae.config = dataclasses.replace(vae.config, root_hold=0.005)
    held = generate_offline(*models, *inputs, config)
    vae.config = dataclasses.replace(vae.config, root_hold_turn=1.0)
    assert stream_decoding(vae, normalizer).reads_user
    turned = generate_offline(*models, *inputs, config)
    assert np.abs(turned - held).max() > 1e-4  # the turn reached the decoding
    anchor = WindowTransform(0.7, 1.0, -2.0)  # world -> generation frame
    head = anchor.invert_floor(inputs[0].astype(np.float64)).astype(np.float32)
    moved = (head, *inputs[1:])
    gen = StreamingGenerator(*models, config, anchor)
    streamed = np.concatenate([gen.step(*(x[i:i + S] for x in moved)) for i in range(0, len(head), S)])
    offline = generate_offline(*models, *moved, config, anchor)
    np.testing.assert_allclose(streamed, offline, atol=1e-5)
    back = anchor.apply_points(offline.reshape(len(offline), -1, 3).astype(np.float64))
    np.testing.assert_allclose(back.reshape(turned.shape), turned, atol=1e-4)
