"""The causal flow matcher: inputs, CFG dropout, velocity, caching, and that it learns."""

import math
from dataclasses import replace

import pytest
import torch
from helpers import randomize

from sarah_models.config import FlowConfig
from sarah_models.nn.flow import MODALITIES, FlowModel, build_block_mask
from sarah_models.nn.head_travel import head_travel
from sarah_models.nn.layers import KVCache
from sarah_models.sampling.guidance import drop_probs, sample_drop_mask
from sarah_models.sampling.path import velocity_from_x1
from sarah_models.training.objectives import flow_matching_loss

S, K, DZ, DA = 4, 6, 16, 5
T = S * K


def make_cond(b: int, g: torch.Generator, frames: int = T) -> dict:
    return {"user_head": torch.randn(b, frames, 2, generator=g),
            "agent_audio": torch.randn(b, frames, DA, generator=g),
            "user_audio": torch.randn(b, frames, DA, generator=g),
            "gaze": torch.rand(b, frames, generator=g) * 2 - 1}


def trained_weights(model: FlowModel, seed: int = 0) -> FlowModel:
    """Perturb the zero-initialised layers so outputs depend on every input."""
    return randomize(model, seed, 0.1, add=True)


@pytest.fixture(scope="module")
def flow():
    torch.manual_seed(0)
    return trained_weights(FlowModel(FlowConfig.tiny(), DZ, S, DA))


def test_output_is_zero_at_init_and_shapes():
    torch.manual_seed(0)
    model = FlowModel(FlowConfig.tiny(), DZ, S, DA)
    g = torch.Generator().manual_seed(0)
    z = torch.randn(3, K, DZ, generator=g)
    out = model(z, torch.rand(3, generator=g), make_cond(3, g))
    assert out.shape == z.shape and torch.equal(out, torch.zeros_like(z))  # AdaLN-Zero output


def test_tau_forms_agree(flow):
    g = torch.Generator().manual_seed(1)
    z, cond = torch.randn(2, K, DZ, generator=g), make_cond(2, g)
    a = flow(z, 0.3, cond)
    b = flow(z, torch.full((2,), 0.3), cond)
    c = flow(z, torch.full((2, K), 0.3), cond)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(a, c)
    assert not torch.allclose(a, flow(z, 0.7, cond))


def test_cached_condition_tokens_equal_direct_call(flow):
    g = torch.Generator().manual_seed(2)
    z, cond = torch.randn(2, K, DZ, generator=g), make_cond(2, g)
    drop = torch.tensor([[True, False, False, True], [False, True, False, False]])
    tokens = flow.encode_condition(cond, drop)
    assert tokens.shape == (2, K, FlowConfig.tiny().hidden)
    torch.testing.assert_close(flow(z, 0.5, cond_tokens=tokens), flow(z, 0.5, cond, drop))


def test_gaze_accepts_both_shapes_and_bad_widths_fail(flow):
    g = torch.Generator().manual_seed(3)
    z, cond = torch.randn(1, K, DZ, generator=g), make_cond(1, g)
    flat = flow(z, 0.5, cond)
    cond3 = dict(cond, gaze=cond["gaze"][..., None])
    torch.testing.assert_close(flat, flow(z, 0.5, cond3))
    with pytest.raises(ValueError, match="agent_audio"):
        flow(z, 0.5, dict(cond, agent_audio=torch.randn(1, T, DA + 1)))
    with pytest.raises(ValueError, match="frames"):
        flow(z, 0.5, dict(cond, user_head=torch.randn(1, T - S, 2)))
    with pytest.raises(KeyError):
        flow(z, 0.5, {k: v for k, v in cond.items() if k != "gaze"})


@pytest.mark.parametrize("index", range(len(MODALITIES)))
def test_dropped_modality_is_ignored(flow, index):
    g = torch.Generator().manual_seed(4 + index)
    z, cond = torch.randn(2, K, DZ, generator=g), make_cond(2, g)
    other = make_cond(2, g)
    name = MODALITIES[index]
    changed = dict(cond, **{name: other[name]})
    drop = torch.zeros(2, len(MODALITIES), dtype=torch.bool)
    drop[:, index] = True
    torch.testing.assert_close(flow(z, 0.4, cond, drop), flow(z, 0.4, changed, drop))
    assert not torch.allclose(flow(z, 0.4, cond), flow(z, 0.4, changed))


def test_cfg_drop_rates_are_five_percent_and_independent(flow):
    drop = sample_drop_mask(40_000, flow.config.drop_prob, torch.Generator().manual_seed(0))
    rates = drop.float().mean(0)
    assert drop.shape == (40_000, 4) and drop.dtype == torch.bool
    assert torch.all((rates - 0.05).abs() < 0.005), rates
    both = (drop[:, 0] & drop[:, 3]).float().mean().item()
    assert abs(both - 0.05 * 0.05) < 0.0015
    # flow.gaze_drop_prob: the gaze score's own rate, the others' unchanged, the same draws
    config = replace(flow.config, gaze_drop_prob=0.3)
    assert drop_probs(flow.config) == (0.05,) * 4 and drop_probs(config) == (0.05,) * 3 + (0.3,)
    gaze = sample_drop_mask(40_000, drop_probs(config), torch.Generator().manual_seed(0))
    assert torch.equal(gaze[:, :3], drop[:, :3]) and torch.all(gaze[:, 3] >= drop[:, 3])
    assert abs(gaze[:, 3].float().mean().item() - 0.3) < 0.01
    with pytest.raises(ValueError, match="gaze_drop_prob must be in"):
        replace(flow.config, gaze_drop_prob=1.5)


def test_velocity_matches_linear_path_and_is_clamped(flow):
    g = torch.Generator().manual_seed(5)
    z1, eps = torch.randn(2, K, DZ, generator=g), torch.randn(2, K, DZ, generator=g)
    tau = torch.tensor([0.25, 0.6])
    z_tau = tau[:, None, None] * z1 + (1 - tau[:, None, None]) * eps
    torch.testing.assert_close(velocity_from_x1(z1, z_tau, tau, flow.config.min_denominator), z1 - eps)  # exact x1 -> dz/dtau
    v = velocity_from_x1(z1, z1 * 0.999, 1.0, flow.config.min_denominator)
    torch.testing.assert_close(v, (z1 - z1 * 0.999) / FlowConfig.tiny().min_denominator)
    assert torch.isfinite(v).all()


def test_incremental_forward_with_caches_equals_full(flow):
    g = torch.Generator().manual_seed(6)
    z, cond = torch.randn(1, K, DZ, generator=g), make_cond(1, g)
    full = flow(z, 0.35, cond)
    caches = [KVCache() for _ in flow.blocks]
    parts = []
    for lo, hi in ((0, 2), (2, 3), (3, K)):
        piece = {k: v[:, lo * S:hi * S] for k, v in cond.items()}
        parts.append(flow(z[:, lo:hi], 0.35, piece, caches=caches))
    torch.testing.assert_close(torch.cat(parts, 1), full, atol=1e-5, rtol=1e-5)
    # An explicit windowed mask is honoured: with window 1 each block sees only itself.
    alone = flow(z, 0.35, cond, attn_mask=build_block_mask(K, window=1))
    for k in range(K):
        single = {n: v[:, k * S:(k + 1) * S] for n, v in cond.items()}
        torch.testing.assert_close(alone[:, k:k + 1],
                                   flow(z[:, k:k + 1], 0.35, single,
                                        positions=torch.tensor([k])), atol=1e-5, rtol=1e-5)


def test_flow_loss_falls():
    torch.manual_seed(0)
    model = FlowModel(FlowConfig.tiny(), DZ, S, DA)
    g = torch.Generator().manual_seed(0)
    cond = make_cond(8, g)
    # Latents that are a fixed function of the conditioning, so there is something to learn.
    proj = torch.randn(S * DA, DZ, generator=g) / (S * DA) ** 0.5
    z = (cond["agent_audio"].reshape(8, K, S * DA) @ proj).tanh() * 2

    def eval_loss() -> float:
        with torch.no_grad():
            return flow_matching_loss(model, z, cond, torch.Generator().manual_seed(123))["loss"].item()

    before = eval_loss()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    for step in range(120):
        out = flow_matching_loss(model, z, cond, torch.Generator().manual_seed(step))
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
    after = eval_loss()
    assert after < before / 3, (before, after)


def test_difference_term_weighs_the_error_of_token_to_token_changes():
    """flow.difference_weight adds the MSE of the error's token-to-token differences; at 0 (the
    paper) the loss is eq. 5 alone."""
    from dataclasses import replace

    g = torch.Generator().manual_seed(0)
    cond, z = make_cond(2, g), torch.randn(2, K, DZ, generator=g)
    paper = trained_weights(FlowModel(FlowConfig.tiny(), DZ, S, DA))
    weighted = FlowModel(replace(FlowConfig.tiny(), difference_weight=3.0), DZ, S, DA)
    weighted.load_state_dict(paper.state_dict())
    with torch.no_grad():
        a = flow_matching_loss(paper, z, cond, torch.Generator().manual_seed(1))
        b = flow_matching_loss(weighted, z, cond, torch.Generator().manual_seed(1))
    error = a["z1_pred"] - z
    assert torch.allclose(a["loss"], error.square().mean())
    assert torch.allclose(b["difference"], (error[:, 1:] - error[:, :-1]).square().mean())
    assert torch.allclose(b["loss"], a["loss"] + 3.0 * b["difference"])
    with pytest.raises(ValueError, match="difference_weight"):
        FlowConfig(difference_weight=-1.0)


def test_training_times_are_the_papers_uniform_unless_a_logit_mean_is_set():
    """flow.time_logit_mean None draws tau ~ U[0, 1] (torch.rand's draws, so the paper's runs keep
    their bits); a mean m draws the logit-normal sigmoid(N(m, std)), median sigmoid(m), and the
    loss trains at those times."""
    from dataclasses import replace

    from sarah_models.training.objectives import training_times

    uniform = training_times(8, torch.Generator().manual_seed(3), "cpu")
    assert torch.equal(uniform, torch.rand(8, generator=torch.Generator().manual_seed(3)))
    for mean, std in ((0.0, 1.0), (1.0, 1.0), (-0.5, 0.5)):
        tau = training_times(20_000, torch.Generator().manual_seed(0), "cpu", mean, std)
        assert 0 < tau.min() and tau.max() < 1
        assert abs(tau.median().item() - torch.sigmoid(torch.tensor(mean)).item()) < 0.01
        logits = torch.logit(tau.double())
        assert abs(logits.std().item() - std) < 0.02
    g = torch.Generator().manual_seed(0)
    cond, z = make_cond(4, g), torch.randn(4, K, DZ, generator=g)
    flow = FlowModel(replace(FlowConfig.tiny(), time_logit_mean=1.5, time_logit_std=0.5), DZ, S, DA)
    with torch.no_grad():
        out = flow_matching_loss(flow, z, cond, torch.Generator().manual_seed(1))
    assert torch.equal(out["tau"], training_times(4, torch.Generator().manual_seed(1), "cpu", 1.5, 0.5))
    with pytest.raises(ValueError, match="time_logit_std"):
        FlowConfig(time_logit_std=0.0)
    with pytest.raises(ValueError, match="time_logit_mean"):
        FlowConfig(time_logit_mean=float("nan"))


def test_attention_window_limits_each_layer_to_the_streaming_context():
    """flow.attention_window = history + 1 limits every layer to the last 3 tokens, so token k
    depends on tokens k - layers * 2 .. k only (receptive field of stacked windows)."""
    torch.manual_seed(0)
    config = FlowConfig(**{**FlowConfig.tiny().__dict__, "attention_window": 3})
    model = trained_weights(FlowModel(config, DZ, S, DA))
    reach = config.layers * (config.attention_window - 1)
    g = torch.Generator().manual_seed(5)
    z, cond = torch.randn(1, K, DZ, generator=g), make_cond(1, g)
    base = model(z, 0.4, cond)
    moved = z.clone()
    moved[:, 0] += 3.0
    out = model(moved, 0.4, cond)
    assert torch.equal(out[:, reach + 1:], base[:, reach + 1:])
    assert not torch.allclose(out[:, reach], base[:, reach])
    with pytest.raises(ValueError, match="attention_window"):
        FlowConfig(attention_window=0)



def test_streamed_context_trains_a_share_of_batches_with_the_streaming_window():
    """flow.streamed_context = 1 trains every batch as a window of history + 1 tokens (the loss of
    a model whose attention_window is 3, same draws); 0 as the model's own context."""
    from dataclasses import replace

    g = torch.Generator().manual_seed(0)
    cond, z = make_cond(2, g), torch.randn(2, K, DZ, generator=g)
    full = trained_weights(FlowModel(replace(FlowConfig.tiny(), attention_window=None), DZ, S, DA))
    windowed, streamed = (FlowModel(replace(FlowConfig.tiny(), **fields), DZ, S, DA) for fields in
                          ({"attention_window": 3}, {"attention_window": None, "streamed_context": 1.0}))
    for model in (windowed, streamed):
        model.load_state_dict(full.state_dict())
    with torch.no_grad():
        losses = [flow_matching_loss(m, z, cond, torch.Generator().manual_seed(1))["loss"]
                  for m in (full, windowed, streamed)]
    assert torch.equal(losses[1], losses[2]) and not torch.allclose(losses[0], losses[1])
    with pytest.raises(ValueError, match="streamed_context"):
        FlowConfig(streamed_context=1.5)


def test_head_velocity_reads_each_block_alone():
    """flow.head_velocity: each block's encoding depends on that block's head positions only
    (a streamed block sees what the same block sees offline), and the velocity half reads the
    head's motion inside the block, not where it stands."""
    torch.manual_seed(0)
    config = FlowConfig(**{**FlowConfig.tiny().__dict__, "head_velocity": True})
    model = trained_weights(FlowModel(config, DZ, S, DA))
    assert model.encoders["user_head"][0].in_features == S * 2 + (S - 1) * 2
    g = torch.Generator().manual_seed(7)
    cond = make_cond(1, g)
    whole = model.encode_condition(cond, positions=torch.arange(K))
    for k in range(K):
        block = {name: value[:, k * S:(k + 1) * S] for name, value in cond.items()}
        torch.testing.assert_close(model.encode_condition(block, first_token=k), whole[:, k:k + 1])
    stacked = model._stack("user_head", cond["user_head"], K)
    shifted = model._stack("user_head", cond["user_head"] + 2.0, K)
    torch.testing.assert_close(shifted[..., S * 2:], stacked[..., S * 2:])
    walking = cond["user_head"].clone()
    walking[:, 1::S] += 0.1
    moved = model._stack("user_head", walking, K)
    assert not torch.allclose(moved[..., S * 2:], stacked[..., S * 2:])
    plain = FlowModel(FlowConfig.tiny(), DZ, S, DA)
    assert plain.encoders["user_head"][0].in_features == S * 2


def test_head_travel_is_a_running_mean_a_stream_computes_block_by_block():
    """nn/head_travel: a constant speed reads as that speed from the second frame on, a standing
    user as 0; after a long walk and ``seconds`` of standing, e^-1 of the walk's speed is left;
    fed block by block (past the exact scan's chunk), it is the one-call value."""
    line = torch.stack([torch.arange(60.0) * 0.01, torch.zeros(60)], -1)[None]  # 0.3 units/s
    speed, _ = head_travel(line, 5.0)
    assert speed[0, 0, 0] == 0.0
    torch.testing.assert_close(speed[0, 1:, 0], torch.full((59,), 0.3))
    assert torch.equal(head_travel(torch.ones(1, 9, 2), 5.0)[0], torch.zeros(1, 9, 1))
    seconds, walk = 0.5, 40 * 15  # a walk 40 time constants long, then one constant standing
    path = torch.cat([torch.arange(walk + 1.0) * 0.01, torch.full((15,), walk * 0.01)])
    after, _ = head_travel(torch.stack([path, torch.zeros_like(path)], -1)[None], seconds)
    torch.testing.assert_close(after[0, -1, 0].item(), 0.3 * math.exp(-1.0), atol=1e-4, rtol=0)
    g = torch.Generator().manual_seed(3)
    head = torch.cumsum(torch.randn(2, 1100, 2, generator=g) * 0.02, 1)
    whole, end = head_travel(head, 2.0)
    parts, state = [], None
    for i in range(0, 1100, S):
        part, state = head_travel(head[:, i:i + S], 2.0, state)
        parts.append(part)
    torch.testing.assert_close(torch.cat(parts, 1), whole)
    torch.testing.assert_close(state.total, end.total)
    with pytest.raises(ValueError, match="seconds"):
        head_travel(head, 0.0)
    with pytest.raises(ValueError, match="head_travel_seconds"):
        FlowConfig(head_travel_seconds=-1.0)


def test_head_travel_carries_the_users_walk_past_the_attention():
    """flow.head_travel_seconds: a block's encoding reads how much the user walked before it,
    further back than the flow attends; given the stream's running mean, a block encodes as the
    same block does inside the whole window (to float rounding: other matrix shapes)."""
    torch.manual_seed(0)
    config = FlowConfig(**{**FlowConfig.tiny().__dict__, "head_travel_seconds": 3.0})
    model = trained_weights(FlowModel(config, DZ, S, DA))
    assert model.encoders["user_head"][0].in_features == S * 2 + S
    g = torch.Generator().manual_seed(7)
    cond = make_cond(1, g)
    whole = model.encode_condition(cond, positions=torch.arange(K))
    travel, _ = head_travel(cond["user_head"], 3.0)
    for k in range(K):
        block = {name: value[:, k * S:(k + 1) * S] for name, value in cond.items()}
        block["head_travel"] = travel[:, k * S:(k + 1) * S]
        torch.testing.assert_close(model.encode_condition(block, first_token=k), whole[:, k:k + 1],
                                   atol=1e-4, rtol=1e-4)
    standing = dict(cond, user_head=cond["user_head"][:, :1].expand(-1, T, -1).clone())
    walked = dict(standing, user_head=standing["user_head"].clone())
    walked["user_head"][:, :S] += torch.linspace(0, 1, S)[None, :, None]  # walks in block 0
    last = [model.encode_condition(c, positions=torch.arange(K))[:, -1] for c in (standing, walked)]
    assert not torch.allclose(*last)
    plain = trained_weights(FlowModel(FlowConfig.tiny(), DZ, S, DA))
    last = [plain.encode_condition(c, positions=torch.arange(K))[:, -1] for c in (standing, walked)]
    torch.testing.assert_close(*last)
