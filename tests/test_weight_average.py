"""train.ema_decay: the weight average's rule, and training stages that sample with it."""

from __future__ import annotations

import torch
from torch import nn

from sarah_models.training.checkpoint import load_checkpoint, load_models
from sarah_models.training.stages import train
from sarah_models.training.weight_average import WeightAverage, decay_at

from test_train import STATS, SyntheticWindows, losses, tiny_config


class Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(3, 2)
        self.frozen = nn.Parameter(torch.randn(4), requires_grad=False)
        self.register_buffer("count", torch.tensor(7))  # not averaged: not floating point


def test_the_average_follows_its_warmed_up_rule_and_leaves_frozen_weights_alone():
    torch.manual_seed(0)
    net = Net()
    frozen = net.frozen.detach().clone()
    average = WeightAverage(net, decay=0.9)
    expected = net.linear.weight.detach().clone()
    for t in range(30):
        with torch.no_grad():
            net.linear.weight.add_(torch.randn_like(net.linear.weight))
        average.update()
        d = min(0.9, (1 + t) / (10 + t))
        expected = d * expected + (1 - d) * net.linear.weight.detach()
    assert decay_at(0, 0.9) == 0.1 and decay_at(1000, 0.9) == 0.9
    state = average.state_dict()
    torch.testing.assert_close(state["linear.weight"], expected)
    assert not torch.allclose(state["linear.weight"], net.linear.weight)
    assert torch.equal(state["frozen"], frozen)  # an average of equal values, bit for bit
    assert state["count"] == 7 and set(state) == set(net.state_dict())


def stage(name, out, steps, resume=False, **train_settings):
    return train(name, tiny_config(steps, **train_settings), None, out, resume=resume,
                 device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                 echo=lambda _: None)


def test_a_stage_with_an_average_trains_as_without_samples_with_it_and_resumes_exactly(tmp_path):
    plain, straight, broken = (tmp_path / n for n in ("plain", "straight", "broken"))
    for out in (plain, straight, broken):  # one VAE for all three flows
        stage("vae", out, 4)
    stage("flow", plain, 8)
    stage("flow", straight, 8, ema_decay=0.5)
    stage("flow", broken, 5, ema_decay=0.5)
    stage("flow", broken, 8, resume=True, ema_decay=0.5)
    base, a, b = (load_checkpoint(out / "flow.pt") for out in (plain, straight, broken))
    # The average changes what is sampled, not how the flow trains.
    assert losses(plain, "flow") == losses(straight, "flow") == losses(broken, "flow")
    for key, value in base["flow"].items():
        assert torch.equal(a["trained"][key], value), key
        assert torch.equal(b["trained"][key], value), key
        assert torch.equal(a["flow"][key], b["flow"][key]), key  # resumed: the same average
    assert "trained" not in base
    moved = [k for k in base["flow"] if not torch.equal(a["flow"][k], base["flow"][k])]
    assert "out.proj.weight" in moved
    models = load_models(straight / "flow.pt", device="cpu")
    torch.testing.assert_close(models.flow.state_dict()["out.proj.weight"], a["flow"]["out.proj.weight"])


def test_a_vae_stage_with_an_average_hands_the_flow_stage_the_average(tmp_path):
    stage("vae", tmp_path, 5, ema_decay=0.5)
    vae = load_checkpoint(tmp_path / "vae.pt")
    assert any(not torch.equal(vae["vae"][k], vae["trained"][k]) for k in vae["vae"])
    stage("flow", tmp_path, 2)
    flow = load_checkpoint(tmp_path / "flow.pt")
    for key, value in vae["vae"].items():
        assert torch.equal(flow["vae"][key], value), key
