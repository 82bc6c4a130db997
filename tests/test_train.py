"""Staged training: schedule, data order, checkpoints, exact resume, DDP, and the CLI."""

import json
import os
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from sarah_cli.train import build_parser, main
from sarah_data.skeleton import JOINT_GROUPS
from sarah_models.training.checkpoint import (capture_rng_state, load_checkpoint, load_models, restore_rng_state,
                                              save_checkpoint)
from sarah_models.config import FlowConfig, RunConfig, TrainConfig, VAEConfig, preset_values
from sarah_models.training.batches import EpochBatches
from sarah_models.training.distributed import DistInfo
from sarah_models.training.loop import lr_at
from sarah_models.training.objectives import (AccelerationMoments, AccelerationSpectrum, FootLift,
                                              HeadFacing, PlantedFeet, VAEObjective)
from sarah_models.training.stages import model_stats, train

WINDOW, DX, DA = 16, 21, 6


class SyntheticWindows(torch.utils.data.Dataset):
    """Test input following the WindowDataset item contract; item i is a function of (i, epoch)."""

    def __init__(self, length: int = 24) -> None:
        self.length, self.epoch = length, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> dict:
        rng = np.random.default_rng((i, self.epoch))
        t = np.arange(WINDOW)[:, None] / 30.0
        motion = np.sin(t * rng.uniform(1, 4, DX) + rng.uniform(0, 6, DX)) + 1.0
        f32 = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))  # noqa: E731
        return {"motion": f32(motion), "user_head": f32(rng.normal(0, 1.5, (WINDOW, 2))),
                "agent_audio": f32(rng.normal(0, 2, (WINDOW, DA))),
                "user_audio": f32(rng.normal(0, 2, (WINDOW, DA))),
                "gaze": f32(rng.uniform(-1, 1, WINDOW)),
                "agent_speaking": f32(rng.integers(0, 2, WINDOW)),
                "user_speaking": f32(rng.integers(0, 2, WINDOW)),
                "transform": f32([0.1 * i, 0.0, 0.0, 0.0]), "sequence": f"seq{i}",
                "agent": "A", "start": 0}


STATS = {"motion": (np.ones(DX), np.full(DX, 0.7)), "user_head": (np.zeros(2), np.full(2, 1.5)),
         "audio": (np.zeros(DA), np.full(DA, 2.0))}


def tiny_config(steps: int, **train) -> RunConfig:
    base = RunConfig.preset("tiny")
    vae = replace(base.vae, hidden=32, latent_dim=8, encoder_layers=1, decoder_layers=1)
    flow = replace(base.flow, hidden=32, cond_dim=16, time_dim=16, layers=1)
    tcfg = replace(base.train, window=WINDOW, batch_size=4, vae_steps=steps, flow_steps=steps,
                   warmup_steps=3, log_every=1, checkpoint_every=3, latent_stats_batches=2,
                   **train)
    return RunConfig(vae, flow, tcfg)


def run(stage: str, out: Path, steps: int, resume: bool = False) -> Path:
    return train(stage, tiny_config(steps), None, out, resume=resume, device="cpu",
                 dataset=SyntheticWindows(), stats=STATS, progress=False, echo=lambda _: None)


def losses(out: Path, stage: str) -> list[tuple[int, float]]:
    rows = [json.loads(line) for line in (out / f"{stage}_log.jsonl").read_text().splitlines()]
    return [(r["step"], r["loss"]) for r in rows]


def test_warmup_schedule():
    cfg = TrainConfig()
    assert lr_at(0, cfg) == pytest.approx(1e-7)
    assert lr_at(499, cfg) == pytest.approx(5e-5)
    assert lr_at(999, cfg) == lr_at(50_000, cfg) == 1e-4


@pytest.mark.parametrize("schedule", ["linear", "cosine"])
def test_decay_schedules_reach_the_final_ratio_at_the_last_step(schedule):
    cfg = TrainConfig(lr=1e-3, warmup_steps=10, lr_schedule=schedule, final_lr_ratio=0.1)
    total = 110
    rates = [lr_at(step, cfg, total) for step in range(total)]
    assert rates[:10] == [lr_at(step, replace(cfg, lr_schedule="constant"), total) for step in range(10)]
    assert rates[10] == pytest.approx(1e-3) and rates[-1] == pytest.approx(1e-4)
    assert all(a >= b for a, b in zip(rates[10:], rates[11:]))  # never rises after warmup
    midpoint = 0.5 * (1e-3 + 1e-4)  # both shapes pass the midpoint half way through the decay
    assert lr_at(60, cfg, total) == pytest.approx(midpoint, rel=0.02)
    assert lr_at(10_000, cfg, total) == pytest.approx(1e-4)
    with pytest.raises(ValueError, match="lr_schedule"):
        TrainConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="final_lr_ratio"):
        TrainConfig(final_lr_ratio=2.0)


def _feet_motion(left_xz, left_y, frames: int) -> torch.Tensor:
    """(1, T, Dx) icosahedron-first motion in metres: the left foot at the given track, every
    other joint at the origin (0.5 m up), 4 shell points."""
    from sarah_data import icosahedron
    from sarah_data.constants import JOINT, NUM_JOINTS

    positions = np.zeros((frames, NUM_JOINTS, 3))
    positions[..., 1] = 0.5
    positions[:, JOINT["left_foot"], [0, 2]] = left_xz
    positions[:, JOINT["left_foot"], 1] = left_y
    positions[:, JOINT["right_foot"], 1] = 0.5  # lifted: never planted
    ico = icosahedron.encode(positions, np.broadcast_to(np.eye(3), (frames, NUM_JOINTS, 3, 3)))
    motion = np.concatenate([ico.reshape(frames, -1), np.zeros((frames, 12))], axis=1)
    return torch.tensor(motion[None], dtype=torch.float32)


def test_planted_feet_term_counts_only_planted_steps_in_threshold_units():
    from sarah_data.constants import NUM_JOINTS

    frames = 9
    still = np.zeros((frames, 2))
    true = _feet_motion(still, np.full(frames, 0.03), frames)  # planted below 5 cm throughout
    term = PlantedFeet(true.shape[-1])
    assert float(term(true, true)) == 0.0
    # Decoded foot jitters 1 mm per frame along x (= 3 cm/s at 30 fps): one threshold unit.
    jitter = np.stack([1e-3 * (np.arange(frames) % 2), np.zeros(frames)], 1)
    assert float(term(_feet_motion(jitter, np.full(frames, 0.03), frames), true)) == pytest.approx(1.0, rel=1e-3)
    # Steps where the true foot is lifted (> 5 cm) or really moving (> 3 cm/s) do not count;
    # on a walk the decoded foot following the true step costs nothing.
    lifted = _feet_motion(still, np.full(frames, 0.2), frames)
    assert float(term(_feet_motion(jitter, np.full(frames, 0.2), frames), lifted)) == 0.0
    walk = np.stack([0.01 * np.arange(frames), np.zeros(frames)], 1)
    walking = _feet_motion(walk, np.full(frames, 0.03), frames)
    assert float(term(_feet_motion(walk + jitter, np.full(frames, 0.03), frames), walking)) == 0.0
    with pytest.raises(ValueError, match="icosahedron motion layout"):
        PlantedFeet(NUM_JOINTS * 36 - 1)


def _head_motion(yaw: np.ndarray, radius: float = 0.1) -> torch.Tensor:
    """(1, T, Dx) motion whose head turns by ``yaw`` (radians about y) per frame."""
    from scipy.spatial.transform import Rotation

    from sarah_data import icosahedron
    from sarah_data.constants import JOINT, NUM_JOINTS

    frames = len(yaw)
    rotations = np.broadcast_to(np.eye(3), (frames, NUM_JOINTS, 3, 3)).copy()
    rotations[:, JOINT["head"]] = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    positions = np.zeros((frames, NUM_JOINTS, 3))
    positions[:, JOINT["head"], 1] = 1.6
    ico = icosahedron.encode(positions, rotations, radius)
    motion = np.concatenate([ico.reshape(frames, -1), np.zeros((frames, 12))], axis=1)
    return torch.tensor(motion[None], dtype=torch.float32)


def test_head_facing_term_is_the_squared_error_of_the_horizontal_facing_unit_vector():
    from sarah_data.constants import NUM_JOINTS

    true = _head_motion(np.zeros(6))
    term = HeadFacing(true.shape[-1])
    assert float(term(true, true)) == 0.0
    # A head turned by angle a faces a unit vector |2 sin(a/2)| away, at any icosahedron radius.
    for angle in (0.1, 0.5, np.pi):
        turned = _head_motion(np.full(6, angle))
        assert float(term(turned, true)) == pytest.approx((2 * np.sin(angle / 2)) ** 2, rel=1e-4)
    big = _head_motion(np.zeros(6), radius=0.3)
    assert float(term(_head_motion(np.full(6, 0.5), radius=0.3), big)) == pytest.approx(
        (2 * np.sin(0.25)) ** 2, rel=1e-4)
    # Nodding (about x) tilts the facing axis out of the floor plane: only its x, z count.
    from scipy.spatial.transform import Rotation

    from sarah_data.skeleton import MotionLayout

    nod = true.clone()
    layout = MotionLayout.from_width(true.shape[-1])
    head = layout.joint_slice("head")
    points = true[0, :, head].reshape(6, 12, 3)
    centre = points.mean(1, keepdim=True)
    tilt = torch.tensor(Rotation.from_euler("x", 0.3).as_matrix(), dtype=torch.float32)
    nod[0, :, head] = ((points - centre) @ tilt.T + centre).reshape(6, -1)
    assert float(term(nod, true)) == pytest.approx((1 - np.cos(0.3)) ** 2, rel=1e-3)
    with pytest.raises(ValueError, match="icosahedron motion layout"):
        HeadFacing(NUM_JOINTS * 36 - 1)


def test_foot_lift_term_is_the_squared_height_error_of_the_feet_in_lock_release_units():
    from sarah_data.constants import NUM_JOINTS
    from sarah_data.skeleton import MotionLayout

    true = _head_motion(np.zeros(6))
    term = FootLift(true.shape[-1])
    assert float(term(true, true)) == 0.0
    layout = MotionLayout.from_width(true.shape[-1])
    lifted = true.clone()
    left = layout.joint_slice("left_foot")
    lifted[0, 2:4, left.start + 1:left.stop:3] += 0.06  # the left foot 6 cm up in 2 of 6 frames
    # (0.06 / 0.02)^2 = 9 in 2 of the 6 frames x 2 feet
    assert float(term(lifted, true)) == pytest.approx(9 * 2 / 12, rel=1e-4)
    sideways = true.clone()
    sideways[0, :, left.start:left.stop:3] += 0.5  # only heights count
    assert float(term(sideways, true)) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="vae.lift_weight"):
        FootLift(NUM_JOINTS * 36 - 1)


def _beating_motion(frames: int, hz: float, phase: float, amplitude: float = 0.02,
                    jitter: float = 0.0, seed: int = 0) -> torch.Tensor:
    """(1, T, Dx) motion: every point swings along x at ``hz``, plus white ``jitter`` (metres)."""
    from sarah_data.constants import NUM_JOINTS

    t = np.arange(frames)[:, None] / 30.0
    width = NUM_JOINTS * 36 + 4 * 3
    motion = np.zeros((frames, width))
    motion[:, 0::3] = amplitude * np.sin(2 * np.pi * hz * t + phase)
    motion += jitter * np.random.default_rng(seed).standard_normal(motion.shape)
    return torch.tensor(motion[None], dtype=torch.float32)


def test_acceleration_spectrum_counts_missing_and_added_energy_not_phase():
    """Magnitudes only: a beat at another phase costs far less than no beat, or jitter on top."""
    true = _beating_motion(120, 4.5, 0.0)
    term = AccelerationSpectrum(true.shape[-1])
    assert float(term(true, true)) == 0.0
    shifted = float(term(_beating_motion(120, 4.5, 1.3), true))
    missing = float(term(_beating_motion(120, 4.5, 0.0, amplitude=0.0), true))
    jittery = float(term(_beating_motion(120, 4.5, 0.0, jitter=0.002), true))
    assert shifted < 0.2 * missing and shifted < 0.2 * jittery
    # A squared error of accelerations says the opposite: the shifted beat costs more than none.
    acc = lambda m: m[:, 2:] - 2 * m[:, 1:-1] + m[:, :-2]  # noqa: E731
    assert (acc(_beating_motion(120, 4.5, 1.3)) - acc(true)).square().mean() > acc(true).square().mean()
    decoded = _beating_motion(120, 4.5, 1.3).requires_grad_()
    term(decoded, true).backward()
    assert decoded.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="at least 18 frames"):
        term(true[:, :10], true[:, :10])
    with pytest.raises(ValueError, match="icosahedron motion layout"):
        AccelerationSpectrum(7)


def _posed_beats(frames: int, hz: float, phase: float, jitter: float = 0.0, seed: int = 0) -> torch.Tensor:
    """``_beating_motion`` with each point's beat its own amplitude: a pose that moves."""
    motion = _beating_motion(frames, hz, phase, jitter=jitter, seed=seed)
    return motion * torch.linspace(0.2, 1.8, motion.shape[-1])


def _moment_term(parts=tuple(JOINT_GROUPS)):
    """An ``AccelerationMoments`` over ``_beating_motion``'s layout, its mean pose's joints a
    metre apart along x and its 4 shell points at the left wrist, the left index finger, the
    left knee and the head."""
    from sarah_data.constants import JOINT, NUM_JOINTS

    centres = torch.zeros(NUM_JOINTS, 3)
    centres[:, 0] = torch.arange(NUM_JOINTS, dtype=torch.float32)
    shell = centres[[JOINT["left_wrist"], JOINT["left_index1"], JOINT["left_knee"], JOINT["head"]]] + 0.01
    mean_pose = torch.cat([centres[:, None].expand(NUM_JOINTS, 12, 3).flatten(), shell.flatten()])
    return AccelerationMoments(mean_pose.numel(), parts, mean_pose)


def test_acceleration_moments_read_the_batch_as_a_whole():
    """The pooled second moments of the pose: which window is which does not count (the
    windows swapped cost nothing where a squared error pays for both), nor does a path the
    whole body shares (the root hold's to decide); scaled motion costs |c^2 - 1|, a beat at
    another frequency or white jitter costs more than one at another phase."""
    true = torch.cat([_posed_beats(60, 4.5, 0.0, jitter=0.001, seed=1),
                      _posed_beats(60, 2.0, 0.7, jitter=0.001, seed=2)])
    term = _moment_term()
    assert float(term(true, true)) == 0.0
    swapped = true.flip(0)
    assert float(term(swapped, true)) < 1e-6 < float((swapped - true).square().mean())
    wander = 0.05 * torch.randn(2, 60, 1, 1, generator=torch.Generator().manual_seed(3))
    carried = (true.unflatten(-1, (-1, 3)) + wander * torch.tensor([1.0, 0.0, 1.0])).flatten(-2)
    assert float(term(carried, true)) < 1e-5
    assert float(term(0.5 * true, true)) == pytest.approx(0.75, rel=1e-4)
    beats = lambda hz, phase, jitter=0.0: torch.cat([  # noqa: E731
        _posed_beats(90, hz, phase, jitter=jitter), _posed_beats(90, 2.0, 0.0)])
    reference = beats(4.5, 0.0)
    shifted = float(term(beats(4.5, 1.3), reference))
    assert shifted < 0.1 * float(term(beats(3.0, 0.0), reference))
    assert shifted < 0.1 * float(term(beats(4.5, 0.0, jitter=0.005), reference))
    decoded = (0.8 * true).requires_grad_()
    term(decoded, true).backward()
    assert decoded.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="vae.moment_weight needs the icosahedron motion layout"):
        AccelerationMoments(7, ("arms",), torch.zeros(7))


def test_acceleration_moments_read_only_their_parts():
    """The arms and hands: their body joints and the shell points nearest them; a leg or the
    head moved otherwise costs nothing, a wrist or a finger's shell point does."""
    from sarah_data.constants import BODY_JOINTS, JOINT

    term = _moment_term(("arms", "hands"))
    arms = [JOINT[n] for n in JOINT_GROUPS["arms"]]
    assert term.points.tolist() == sorted(arms) + [BODY_JOINTS, BODY_JOINTS + 1]
    true = _posed_beats(60, 4.5, 0.0, jitter=0.001)
    points = true.unflatten(-1, (-1, 3))
    for index, counted in ((len(points[0, 0]) - 2, False), (len(points[0, 0]) - 1, False),
                           (len(points[0, 0]) - 4, True), (len(points[0, 0]) - 3, True)):
        moved = points.clone()
        moved[..., index, :] *= 3.0
        assert (float(term(moved.flatten(-2), true)) > 1e-3) is counted, index
    with pytest.raises(ValueError, match="moment_parts must name joint groups"):
        replace(tiny_config(1).vae, moment_parts=("fingers",))


def test_acceleration_spectrum_matches_torch_stft():
    acceleration = torch.randn(2, 70, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    term = AccelerationSpectrum(_beating_motion(20, 1.0, 0.0).shape[-1])
    reference = torch.stft(acceleration.transpose(1, 2).flatten(0, 1), 16, hop_length=4, center=False,
                           window=torch.hann_window(16, dtype=torch.float64), return_complex=True).abs()
    ours = term.spectra(acceleration, 16).permute(0, 2, 3, 1).flatten(0, 1)
    assert torch.allclose(ours, reference, atol=1e-9)


def test_vae_objective_adds_the_weighted_contact_and_head_terms():
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.nn.vae import CausalVAE

    motion = _head_motion(np.linspace(0, 1, 8))  # feet on the floor: planted; the head turns
    dx = motion.shape[-1]
    stats = {"motion": (np.zeros(dx), np.full(dx, 0.3))}
    config = replace(tiny_config(1).vae, hidden=32, latent_dim=8, encoder_layers=1,
                     decoder_layers=1, contact_weight=0.5, head_weight=0.25)
    torch.manual_seed(0)
    objective = VAEObjective(CausalVAE(config, dx), Normalizer(stats))
    out = objective({"motion": motion}, torch.Generator().manual_seed(0))
    plain = out["recon"] + config.beta * out["kl"] + config.velocity_weight * out["velocity"]
    assert out["contact"].item() > 0 and out["head"].item() > 0
    expected = plain + 0.5 * out["contact"] + 0.25 * out["head"]
    assert out["loss"].item() == pytest.approx(expected.item(), rel=1e-5)
    out["loss"].backward()  # differentiable through the de-standardization
    assert objective.vae.frame_out.weight.grad.abs().sum() > 0
    plain_objective = VAEObjective(CausalVAE(replace(config, contact_weight=0.0, head_weight=0.0), dx),
                                   Normalizer(stats))
    assert not {"contact", "head"} & set(plain_objective({"motion": motion}))


@pytest.mark.parametrize("setting, term, motion", [
    ("spectral_weight", "spectrum", lambda: _beating_motion(24, 4.5, 0.0)),
    ("moment_weight", "moments", lambda: _posed_beats(24, 4.5, 0.0))])
def test_vae_objective_adds_the_weighted_term(setting, term, motion):
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.nn.vae import CausalVAE

    motion = motion()
    dx = motion.shape[-1]
    stats = {"motion": (np.zeros(dx), np.full(dx, 0.3))}
    config = replace(tiny_config(1).vae, hidden=32, latent_dim=8, encoder_layers=1,
                     decoder_layers=1, **{setting: 0.5})
    torch.manual_seed(0)
    out = VAEObjective(CausalVAE(config, dx), Normalizer(stats))({"motion": motion},
                                                               torch.Generator().manual_seed(0))
    plain = out["recon"] + config.beta * out["kl"] + config.velocity_weight * out["velocity"]
    assert out[term].item() > 0
    assert out["loss"].item() == pytest.approx((plain + 0.5 * out[term]).item(), rel=1e-5)
    with pytest.raises(ValueError, match=f"{setting} must be >= 0"):
        replace(config, **{setting: -1.0})


def test_vae_loss_in_metres_weights_channels_by_their_variance():
    """recon_units="metres": the reconstruction term is the squared error in metres over the
    mean channel variance, so a millimetre costs the same on every axis."""
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.nn.vae import CausalVAE

    dx, frames = 6, 8
    std = np.array([1.0, 0.035, 1.0, 0.5, 0.035, 0.5])
    stats = {"motion": (np.zeros(dx), std)}
    motion = torch.randn(2, frames, dx, generator=torch.Generator().manual_seed(0)) * torch.tensor(std)
    config = replace(tiny_config(1).vae, hidden=32, latent_dim=8, encoder_layers=1,
                     decoder_layers=1, recon_units="metres")
    torch.manual_seed(0)
    objective = VAEObjective(CausalVAE(config, dx), Normalizer(stats))
    out = objective({"motion": motion}, torch.Generator().manual_seed(0))
    error_m = (out["x_hat"].detach() - motion / torch.tensor(std).float()) * torch.tensor(std).float()
    expected = error_m.square().mean() / float(np.mean(std ** 2))
    assert out["recon"].item() == pytest.approx(expected.item(), rel=1e-5)
    with pytest.raises(ValueError, match="recon_units"):
        replace(config, recon_units="inches")


def test_config_round_trip_and_overrides():
    cfg = RunConfig.preset("paper")
    assert cfg.vae == VAEConfig() and cfg.flow == FlowConfig() and cfg.train == TrainConfig()
    assert RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    new = cfg.with_overrides(["train.lr=3e-4", "flow.layers=2", "beta=0.01",
                              "train.adam_betas=0.8,0.99"])
    assert (new.train.lr, new.flow.layers, new.vae.beta) == (3e-4, 2, 0.01)
    assert new.train.adam_betas == (0.8, 0.99)
    # The position embedding follows the training window unless set itself.
    tiny = RunConfig.preset("tiny")
    assert tiny.flow.position_tokens == tiny.train.window // tiny.vae.stride
    assert tiny.with_overrides(["train.window=400"]).flow.position_tokens == 100
    assert tiny.with_overrides(["train.window=400", "flow.position_tokens=8"]).flow.position_tokens == 8
    for bad in (["hidden=3"], ["nope=1"], ["vae.nope=1"], ["train.lr=fast"], ["lr"]):
        with pytest.raises(ValueError):
            cfg.with_overrides(bad)
    # Settings that only hold together are checked together, in either order; the last of two
    # settings of one field wins.
    turning = cfg.with_overrides(["vae.root_hold=0.7", "vae.root_hold_turn=1"])
    for order in (["vae.root_hold=0", "vae.root_hold_turn=0"],
                  ["vae.root_hold_turn=0", "vae.root_hold=0"]):
        assert turning.with_overrides(order).vae == cfg.vae
    assert cfg.with_overrides(["train.lr=1e-3", "train.lr=2e-3"]).train.lr == 2e-3
    with pytest.raises(ValueError, match="root_hold"):
        turning.with_overrides(["vae.root_hold=0"])
    with pytest.raises(ValueError, match="unknown field"):
        RunConfig.from_dict({**cfg.to_dict(), "vae": {"stride": 4, "bogus": 1}})


def test_overrides_parse_by_the_fields_declared_type():
    """An optional float set to 0 is the float 0.0, so a later --set of 0.9 reads; a file that
    already holds the int 0 there (model files written before this was fixed) reads 0.9 too."""
    tiny = RunConfig.preset("tiny")
    assert tiny.vae.root_inertia is None
    zero = tiny.with_overrides(["vae.root_inertia=0"])
    assert type(zero.vae.root_inertia) is float and zero.vae.root_inertia == 0.0
    written = RunConfig.from_dict(json.loads(json.dumps(zero.to_dict())))
    assert written.with_overrides(["vae.root_inertia=0.9"]).vae.root_inertia == 0.9
    old = tiny.to_dict()
    old["vae"]["root_inertia"] = 0  # as such files hold it
    assert RunConfig.from_dict(old).with_overrides(["vae.root_inertia=0.9"]).vae.root_inertia == 0.9
    assert tiny.with_overrides(["vae.root_inertia=none"]).vae.root_inertia is None
    with pytest.raises(ValueError, match="as float"):
        tiny.with_overrides(["vae.root_inertia=stiff"])
    assert tiny.with_overrides(["flow.layers=3"]).flow.layers == 3
    with pytest.raises(ValueError, match="as int"):
        tiny.with_overrides(["flow.layers=2.5"])


def test_epoch_batches_resume_and_split_across_ranks():
    data = SyntheticWindows(length=10)
    cfg = replace(TrainConfig.tiny(), batch_size=3)
    whole = EpochBatches(data, cfg, DistInfo(0, 1, 0, torch.device("cpu")))
    batches = [b["sequence"] for _, b in zip(range(7), whole)]
    assert whole.per_epoch == 3  # 10 windows -> 3 full batches, the rest dropped
    resumed = EpochBatches(data, cfg, DistInfo(0, 1, 0, torch.device("cpu")), start_batch=4)
    assert [b["sequence"] for _, b in zip(range(3), resumed)] == batches[4:]
    ranks = [EpochBatches(data, replace(cfg, batch_size=2), DistInfo(r, 2, r, torch.device("cpu")))
             for r in (0, 1)]
    seen = [set(sum((b for b in r.epoch_batches(0)), [])) for r in ranks]
    assert not seen[0] & seen[1] and len(seen[0]) == len(seen[1]) == 4


def test_model_stats_from_stats_h5_keys():
    raw = {"motion/mean": np.zeros(3), "motion/std": np.ones(3), "user_head/mean": np.zeros(2),
           "user_head/std": np.ones(2), "audio/logmel/mean": np.zeros(4),
           "audio/logmel/std": np.ones(4)}
    assert set(model_stats(raw, "logmel")) == {"motion", "user_head", "audio"}
    with pytest.raises(ValueError, match="hubert-large"):
        model_stats(raw, "hubert-large")


def test_rng_state_round_trip():
    state = capture_rng_state()
    a = (np.random.rand(), torch.rand(1).item(), __import__("random").random())
    restore_rng_state(state)
    assert (np.random.rand(), torch.rand(1).item(), __import__("random").random()) == a


def test_training_writes_run_folder_and_checkpoints_load_weights_only(tmp_path):
    path = run("vae", tmp_path, 4)
    assert path == tmp_path / "vae.pt"
    assert {p.name for p in tmp_path.iterdir()} == {"vae.pt", "vae_log.jsonl", "vae_loss.png",
                                                    "config.json"}
    raw = torch.load(path, weights_only=True)
    assert raw["step"] == 4 and raw["stage"] == "vae" and raw["features"] == "logmel"
    assert raw["dims"] == {"motion": DX, "audio": DA}
    assert {"python", "numpy", "torch", "cuda"} <= set(raw["rng"])
    assert [s for s, _ in losses(tmp_path, "vae")] == [1, 2, 3, 4]
    with pytest.raises(FileExistsError, match="resume"):
        run("vae", tmp_path, 4)
    with pytest.raises(FileNotFoundError, match="vae stage"):
        run("flow", tmp_path / "elsewhere", 2)
    run("flow", tmp_path, 3)
    models = load_models(tmp_path / "flow.pt", device="cpu")
    assert models.flow is not None and models.stage == "flow" and models.step == 3
    assert set(models.normalizer.keys) == {"motion", "user_head", "audio", "latent"}
    latent_std = models.normalizer.latent_std
    assert latent_std.shape == (8,) and torch.all(latent_std > 0)
    torch.testing.assert_close(models.vae.state_dict()["frame_in.weight"],
                               load_models(path, device="cpu").vae.state_dict()["frame_in.weight"])
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt"):
        load_checkpoint(tmp_path / "bad.pt")


def test_resume_repeats_the_uninterrupted_run_exactly(tmp_path):
    straight, broken = tmp_path / "straight", tmp_path / "broken"
    run("vae", straight, 6)
    run("flow", straight, 6)
    run("vae", broken, 3)
    run("vae", broken, 6, resume=True)
    run("flow", broken, 3)
    run("flow", broken, 6, resume=True)
    for stage in ("vae", "flow"):
        assert losses(straight, stage) == losses(broken, stage)
        a, b = load_checkpoint(straight / f"{stage}.pt"), load_checkpoint(broken / f"{stage}.pt")
        for key, value in a[stage].items():
            assert torch.equal(value, b[stage][key]), key
    # The flow really trained: its zero-initialised output layer moved.
    assert load_checkpoint(straight / "flow.pt")["flow"]["out.proj.weight"].abs().sum() > 0


def test_the_same_run_twice_writes_byte_identical_checkpoints(tmp_path):
    import random

    for name in ("a", "b"):
        random.random(), np.random.rand()  # whatever ran before must not leak into the run
        run("vae", tmp_path / name, 3)
        run("flow", tmp_path / name, 2)
    for stage in ("vae", "flow"):
        assert (tmp_path / "a" / f"{stage}.pt").read_bytes() == (tmp_path / "b" / f"{stage}.pt").read_bytes()


def test_compiled_training_learns_what_eager_training_learns(tmp_path):
    """train.compile: the same losses to float rounding, and checkpoints holding the modules'
    own weights (no compiler wrapper in their names), resumable without the compiler."""
    def stage(out: Path, steps: int, compile: bool, resume: bool = False) -> Path:
        return train("vae", tiny_config(steps, compile=compile), None, out, resume=resume,
                     device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                     echo=lambda _: None)

    stage(tmp_path / "eager", 4, compile=False)
    stage(tmp_path / "compiled", 3, compile=True)
    stage(tmp_path / "compiled", 4, compile=False, resume=True)
    eager, compiled = losses(tmp_path / "eager", "vae"), losses(tmp_path / "compiled", "vae")
    assert [s for s, _ in compiled] == [1, 2, 3, 4]
    np.testing.assert_allclose([v for _, v in compiled], [v for _, v in eager], rtol=1e-4)
    weights = load_checkpoint(tmp_path / "compiled" / "vae.pt")["vae"]
    assert set(weights) == set(load_checkpoint(tmp_path / "eager" / "vae.pt")["vae"])


def test_resume_compares_config_meanings_and_replace_changed_sets_stale_stages_aside(tmp_path):
    """A checkpoint saved before a config field existed resumes under that field's default; a
    stage trained with another config is moved aside (never deleted) by set_aside, its flow with
    it when the VAE changed."""
    from sarah_models.training.checkpoint import save_checkpoint
    from sarah_models.training.stages import set_aside, stale_stages

    out = tmp_path / "run"
    config = tiny_config(3)
    config = replace(config, flow=replace(config.flow, attention_window=None))
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    train("vae", config, None, out, **common)
    train("flow", config, None, out, **common)
    old = load_checkpoint(out / "flow.pt")
    del old["config"]["flow"]["attention_window"]  # as written before the field existed
    save_checkpoint(out / "flow.pt", old)
    train("flow", config, None, out, resume=True, **common)  # the same meaning: accepted

    windowed = replace(config, flow=replace(config.flow, attention_window=3))
    with pytest.raises(ValueError, match="differs from the requested"):
        train("flow", windowed, None, out, resume=True, **common)
    assert stale_stages(out, config, ("vae", "flow")) == []
    assert stale_stages(out, windowed, ("vae", "flow")) == ["flow"]
    aside = set_aside(out, ["flow"])
    assert sorted(p.name for p in aside.iterdir()) == ["flow.pt", "flow_log.jsonl", "flow_loss.png"]
    assert (out / "vae.pt").is_file() and not (out / "flow.pt").exists()
    train("flow", windowed, None, out, resume=True, **common)
    new_vae = replace(windowed, vae=replace(windowed.vae, beta=1e-3))
    assert stale_stages(out, new_vae, ("vae", "flow")) == ["vae", "flow"]
    assert stale_stages(out, new_vae, ("vae",)) == ["vae", "flow"]  # its flow learned those latents


def test_init_from_fine_tunes_with_a_new_loss_and_schedule(tmp_path):
    base, tuned = tmp_path / "base", tmp_path / "tuned"
    run("vae", base, 4)
    run("flow", base, 4)
    source = load_checkpoint(base / "vae.pt")
    config = tiny_config(3, lr_schedule="linear")
    config = replace(config, vae=replace(config.vae, velocity_weight=100.0),
                     flow=replace(config.flow, drop_prob=0.2))
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    # Step 0 of the fine-tune starts from the source's weights: its first loss is the source
    # model's loss on that batch, far below a fresh model's.
    fresh = tmp_path / "fresh"
    train("vae", config, None, fresh, **common)
    train("vae", config, None, tuned, init_from=base, **common)
    assert losses(tuned, "vae")[0][1] < 0.8 * losses(fresh, "vae")[0][1]
    tuned_ckpt = load_checkpoint(tuned / "vae.pt")
    assert tuned_ckpt["step"] == 3 and tuned_ckpt["config"]["vae"]["velocity_weight"] == 100.0
    assert tuned_ckpt["init_from"] == {"path": str(base / "vae.pt"), "step": 4}
    for key, value in source["normalizer"].items():  # the source's data statistics are kept
        assert torch.equal(value, tuned_ckpt["normalizer"][key]), key
    assert not torch.equal(source["vae"]["frame_out.weight"], tuned_ckpt["vae"]["frame_out.weight"])
    # The flow starts from the source's flow on this run's (new) VAE, with a new dropout.
    train("flow", config, None, tuned, init_from=base / "flow.pt", **common)
    flow_ckpt = load_checkpoint(tuned / "flow.pt")
    assert flow_ckpt["config"]["flow"]["drop_prob"] == 0.2
    assert flow_ckpt["init_from"]["path"] == str(base / "flow.pt")
    for key, value in flow_ckpt["vae"].items():
        assert torch.equal(value, tuned_ckpt["vae"][key]), key
    # Resuming an interrupted fine-tune keeps its origin.
    train("vae", replace(config, train=replace(config.train, vae_steps=5)), None, tuned,
          resume=True, **common)
    assert load_checkpoint(tuned / "vae.pt")["init_from"]["step"] == 4


def test_a_fine_tune_may_weigh_the_root_otherwise(tmp_path):
    """vae.root_weight weighs the loss, not the weights: a decoder stage may train with another
    (the benchmark's frozen-encoder stage; a change of size is refused, as
    test_init_from_refuses_what_cannot_be_loaded shows)."""
    run("vae", tmp_path / "base", 2)
    config = tiny_config(2)
    train("vae", replace(config, vae=replace(config.vae, root_weight=0.3)), None,
          tmp_path / "tuned", init_from=tmp_path / "base", device="cpu",
          dataset=SyntheticWindows(), stats=STATS, progress=False, echo=lambda _: None)
    assert load_checkpoint(tmp_path / "tuned" / "vae.pt")["config"]["vae"]["root_weight"] == 0.3


def test_a_deterministic_vae_fine_tunes_into_a_stochastic_decoder(tmp_path):
    """--init-from a VAE without detail draws into --set vae.detail_dim=N keeps every weight
    it has and adds the decoder's detail input; a stochastic decoder does not fine-tune into
    another width or back into a deterministic one (weights would be dropped)."""
    base, tuned = tmp_path / "base", tmp_path / "tuned"
    run("vae", base, 2)
    config = tiny_config(2)
    stochastic = replace(config, vae=replace(config.vae, detail_dim=4))
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    train("vae", stochastic, None, tuned, init_from=base, **common)
    source, result = load_checkpoint(base / "vae.pt"), load_checkpoint(tuned / "vae.pt")
    assert set(result["vae"]) == set(source["vae"]) | {"detail_in.weight", "detail_in.bias"}
    assert result["vae"]["detail_in.weight"].shape[1] == 4
    assert "energy" in json.loads((tuned / "vae_log.jsonl").read_text().splitlines()[0])
    for vae_config, out in ((replace(config.vae, detail_dim=8), "wider"), (config.vae, "plain")):
        with pytest.raises(ValueError, match="detail_dim"):
            train("vae", replace(config, vae=vae_config), None, tmp_path / out,
                  init_from=tuned, **common)


def test_a_decoder_stage_leaves_the_flow_trained_on_its_encoder_as_it_was(tmp_path):
    """The flow's initial weights come from the seed and the flow's config alone: a flow trained
    on a decoder stage's VAE (the same frozen encoder, so the same latents) is, to the bit, the
    flow trained on the VAE that stage started from, also when the decoder gained the stochastic
    detail input, whose construction draws from the RNG before the flow is built."""
    base, tuned = tmp_path / "base", tmp_path / "tuned"
    run("vae", base, 2)
    config = tiny_config(2)
    stochastic = replace(config, vae=replace(config.vae, detail_dim=4),
                         train=replace(config.train, freeze_encoder=True))
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    train("vae", stochastic, None, tuned, init_from=base, **common)
    for out in (base, tuned):
        train("flow", config, None, out, **common)
    plain, other = (load_checkpoint(out / "flow.pt") for out in (base, tuned))
    assert plain["config"]["vae"]["detail_dim"] == 0 and other["config"]["vae"]["detail_dim"] == 4
    assert plain["flow"].keys() == other["flow"].keys()
    for key, value in plain["flow"].items():
        assert torch.equal(value, other["flow"][key]), key


def test_init_from_takes_a_model_file(tmp_path):
    """A shared model.safetensors (a shipped model too) fine-tunes exactly like the checkpoint it
    was written from: same weights after the same steps, same data statistics."""
    from sarah_models.training.model_file import write_model_file

    base = tmp_path / "base"
    run("vae", base, 2)
    run("flow", base, 2)
    shared = write_model_file(base / "flow.pt", tmp_path / "shared.safetensors")
    config = tiny_config(2, lr_schedule="linear")
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    for source, out in ((base, tmp_path / "from_run"), (shared, tmp_path / "from_file")):
        for stage in ("vae", "flow"):
            train(stage, config, None, out, init_from=source, **common)
    from_file = load_checkpoint(tmp_path / "from_file" / "flow.pt")
    from_run = load_checkpoint(tmp_path / "from_run" / "flow.pt")
    assert from_file["init_from"] == {"path": str(shared), "step": 2}
    for part in ("vae", "flow", "normalizer"):
        for key, value in from_run[part].items():
            assert torch.equal(value, from_file[part][key]), (part, key)
    moved = load_checkpoint(base / "flow.pt")["flow"]["out.proj.weight"]
    assert not torch.equal(moved, from_file["flow"]["out.proj.weight"])  # it did train
    other = tmp_path / "other.safetensors"
    other.write_bytes(len(b'{"__metadata__":{}}').to_bytes(8, "little") + b'{"__metadata__":{}}')
    with pytest.raises(ValueError, match="not a SARAH model file"):
        train("vae", config, None, tmp_path / "d", init_from=other, **common)


def test_a_flow_fine_tune_takes_its_vae_from_the_model_file(tmp_path):
    """--stage flow --init-from a model file into an empty folder fine-tunes that file's flow on
    that file's VAE (copied to vae.pt, bit for bit, decoding settings and all); without a source
    the stage still asks for a VAE."""
    from sarah_models.training.model_file import read_model_file, write_model_file

    base = tmp_path / "base"
    run("vae", base, 2)
    run("flow", base, 2)
    shared = write_model_file(base / "flow.pt", tmp_path / "shared.safetensors",
                              ["vae.boundary_inertia=0.5"])
    config = tiny_config(2)
    # Loss weights and the attention window change no weight: a fine-tune may change them.
    config = replace(config, flow=replace(config.flow, difference_weight=5.0, attention_window=None))
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    with pytest.raises(FileNotFoundError, match="run the vae stage first"):
        train("flow", config, None, tmp_path / "empty", **common)
    out = tmp_path / "tuned"
    train("flow", config, None, out, init_from=shared, **common)
    source, vae_ckpt = read_model_file(shared), load_checkpoint(out / "vae.pt")
    tuned = load_checkpoint(out / "flow.pt")
    for part in ("vae", "normalizer"):
        for key, value in source[part].items():
            if not key.startswith("latent"):  # the flow refits its latent statistics
                assert torch.equal(value, vae_ckpt[part][key]), (part, key)
    for key, value in source["vae"].items():
        assert torch.equal(value, tuned["vae"][key]), key
    assert tuned["config"]["vae"]["boundary_inertia"] == 0.5
    assert tuned["config"]["flow"]["difference_weight"] == 5.0
    assert tuned["config"]["flow"]["attention_window"] is None
    assert tuned["init_from"] == {"path": str(shared), "step": 2}
    assert not torch.equal(source["flow"]["out.proj.weight"], tuned["flow"]["out.proj.weight"])
    # Resuming finds the copied VAE and goes on.
    more = replace(config, train=replace(config.train, flow_steps=3))
    train("flow", more, None, out, resume=True, **common)
    assert load_checkpoint(out / "flow.pt")["step"] == 3


def test_decoder_fine_tune_with_latent_noise_keeps_the_encoder(tmp_path):
    """train.freeze_encoder + vae.latent_noise: only the decoder moves, so the latents a flow
    was trained on stay exactly the same."""
    base, tuned = tmp_path / "base", tmp_path / "tuned"
    run("vae", base, 3)
    config = tiny_config(3, freeze_encoder=True)
    config = replace(config, vae=replace(config.vae, latent_noise=0.3))
    train("vae", config, None, tuned, init_from=base, device="cpu", dataset=SyntheticWindows(),
          stats=STATS, progress=False, echo=lambda _: None)
    before, after = load_checkpoint(base / "vae.pt")["vae"], load_checkpoint(tuned / "vae.pt")["vae"]
    encoder = ("frame_in.", "mu_token", "sigma_token", "encoder.", "encoder_norm.", "mu_out.",
               "logvar_out.")
    assert sum(k.startswith(encoder) for k in before) >= 7
    for key, value in before.items():
        if key.startswith(encoder):
            assert torch.equal(value, after[key]), key
    assert not torch.equal(before["frame_out.weight"], after["frame_out.weight"])


def test_stage_model_takes_a_decoder_trained_on_the_frozen_encoder(tmp_path, capsys):
    """--decoder-from: a decoder stage on the model's frozen encoder reads the latents its flow
    learned, so the model file takes that VAE beside the same flow, with the model's decoding
    settings; a VAE with another encoder is refused and nothing is written."""
    from sarah_models.training.model_file import load_model_file, read_model_file

    base, tuned, other = tmp_path / "base", tmp_path / "tuned", tmp_path / "other"
    run("vae", base, 3)
    run("flow", base, 3)
    config = tiny_config(3, freeze_encoder=True)
    # its own decoding turns a held body; the model's holds none, and the model's is what is kept
    config = replace(config, vae=replace(config.vae, latent_noise=0.3, detail_dim=2,
                                         root_hold=0.7, root_hold_turn=1.0))
    train("vae", config, None, tuned, init_from=base, device="cpu", dataset=SyntheticWindows(),
          stats=STATS, progress=False, echo=lambda _: None)
    out = tmp_path / "swapped"
    assert main(["--stage", "model", "--init-from", str(base), "--decoder-from", str(tuned),
                 "--out", str(out), "--set", "vae.boundary_inertia=0.5"]) == 0
    written, flow, decoder = (read_model_file(out / "model.safetensors"),
                              load_checkpoint(base / "flow.pt"), load_checkpoint(tuned / "vae.pt"))
    assert written["vae"].keys() == decoder["vae"].keys() != flow["vae"].keys()  # detail_in came
    for part, source in (("vae", decoder), ("flow", flow), ("normalizer", flow)):
        for key, value in source[part].items():
            assert torch.equal(written[part][key], value), (part, key)
    assert not torch.equal(written["vae"]["frame_out.weight"], flow["vae"]["frame_out.weight"])
    assert written["config"]["vae"]["detail_dim"] == 2  # the decoder's sizes
    assert written["config"]["vae"]["boundary_inertia"] == 0.5  # the model's decoding, as --set
    assert (written["config"]["vae"]["root_hold"], written["config"]["vae"]["root_hold_turn"]) == (0, 0)
    assert written["config"]["flow"] == flow["config"]["flow"]
    assert load_model_file(out / "model.safetensors", "cpu").vae.detail_in is not None
    # another encoder: refused by name, before anything is written
    run("vae", other, 4)
    assert main(["--stage", "model", "--init-from", str(base), "--decoder-from", str(other),
                 "--out", str(tmp_path / "no")]) == 2
    err = capsys.readouterr().err
    assert f"{other / 'vae.pt'}: its encoder is not the model's" in err
    assert "train.freeze_encoder=true" in err
    assert not (tmp_path / "no").exists()
    # the same encoder with other data's motion statistics (a VAE stage keeps its source's, so
    # only another source or an edited file has them): refused too
    shifted = load_checkpoint(tuned / "vae.pt")
    shifted["normalizer"]["motion_mean"] = shifted["normalizer"]["motion_mean"] + 0.5
    save_checkpoint(tmp_path / "shifted.pt", shifted)
    assert main(["--stage", "model", "--init-from", str(base), "--decoder-from",
                 str(tmp_path / "shifted.pt"), "--out", str(tmp_path / "no")]) == 2
    assert "its motion statistics are not the model's" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
    with pytest.raises(SystemExit):
        main(["--stage", "flow", "--shards", str(tmp_path), "--out", str(tmp_path / "no"),
              "--decoder-from", str(tuned)])
    assert "--decoder-from goes with --stage model" in capsys.readouterr().err


def test_latent_noise_perturbs_only_the_decoder_input():
    from sarah_models.nn.vae import CausalVAE

    x = torch.randn(2, WINDOW, DX, generator=torch.Generator().manual_seed(0))
    vae_config = tiny_config(1).vae
    outs = {}
    for noise in (0.0, 0.5):
        torch.manual_seed(0)
        vae = CausalVAE(replace(vae_config, latent_noise=noise), DX)
        outs[noise] = vae(x, torch.Generator().manual_seed(1))
    assert torch.equal(outs[0.0]["mu"], outs[0.5]["mu"])
    assert not torch.allclose(outs[0.0]["x_hat"], outs[0.5]["x_hat"])


def test_init_from_refuses_what_cannot_be_loaded(tmp_path):
    base = tmp_path / "base"
    run("vae", base, 2)
    common = dict(device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
                  echo=lambda _: None)
    wider = tiny_config(2)
    wider = replace(wider, vae=replace(wider.vae, hidden=64))
    with pytest.raises(ValueError, match=r"hidden: 32 there, 64 here"):
        train("vae", wider, None, tmp_path / "a", init_from=base, **common)
    with pytest.raises(ValueError, match="no flow weights"):
        run("vae", tmp_path / "b", 2)
        train("flow", tiny_config(2), None, tmp_path / "b", init_from=base / "vae.pt", **common)
    with pytest.raises(ValueError, match="use one of them"):
        train("vae", tiny_config(2), None, base, resume=True, init_from=base, **common)
    with pytest.raises(FileNotFoundError, match="missing"):
        train("vae", tiny_config(2), None, tmp_path / "c", init_from=tmp_path / "missing", **common)
    assert not (tmp_path / "a" / "vae.pt").exists() and not (tmp_path / "c").exists()


def _ddp_replica_worker(rank: int, world: int, port: int, out: str) -> None:
    """Two DDP steps on gloo via train_loop (saving each replica's own weights), then a
    DDP run of train() itself (rank 0 alone writes the run folder)."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE=str(world),
                      RANK=str(rank), LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from torch.nn.parallel import DistributedDataParallel

    from sarah_models.training.checkpoint import build_models
    from sarah_models.nn.normalizer import Normalizer
    from sarah_models.training.distributed import cleanup_distributed, setup_distributed
    from sarah_models.training.loop import make_optimizer, train_loop
    from sarah_models.training.objectives import VAEObjective

    try:
        info = setup_distributed("cpu")
        assert (info.rank, info.world_size) == (rank, world)
        config = tiny_config(2)
        torch.manual_seed(rank)  # different initial weights: DDP must broadcast rank 0's
        vae, _ = build_models(config, {"motion": DX, "audio": DA})
        objective = VAEObjective(vae, Normalizer(STATS))
        model = DistributedDataParallel(objective)
        optimizer = make_optimizer(vae, config.train)
        batches = EpochBatches(SyntheticWindows(), config.train, info)
        first = next(iter(batches))["sequence"]
        train_loop(model, batches, optimizer, config.train, total_steps=2, rank=rank)
        torch.save({"weights": vae.state_dict(), "first": first}, Path(out) / f"replica{rank}.pt")
        train("vae", tiny_config(3), None, Path(out) / "run", device="cpu",
              dataset=SyntheticWindows(), stats=STATS, progress=False, echo=lambda _: None)
    finally:
        cleanup_distributed()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_two_processes_keep_identical_replicas_and_write_once(tmp_path):
    mp.spawn(_ddp_replica_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    a, b = (torch.load(tmp_path / f"replica{r}.pt", weights_only=True) for r in (0, 1))
    assert a["first"] != b["first"]  # the ranks read different windows
    for key, value in a["weights"].items():
        assert torch.equal(value, b["weights"][key]), key
    torch.manual_seed(0)
    from sarah_models.training.checkpoint import build_models

    init, _ = build_models(tiny_config(2), {"motion": DX, "audio": DA})
    assert not torch.equal(init.state_dict()["frame_in.weight"], a["weights"]["frame_in.weight"])
    assert torch.load(tmp_path / "run" / "vae.pt", weights_only=True)["step"] == 3
    assert [s for s, _ in losses(tmp_path / "run", "vae")] == [1, 2, 3]  # rank 0 alone logged


def test_cli_help_lists_every_option(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    options = [o for action in build_parser()._actions for o in action.option_strings]
    assert len(options) >= 12
    for option in options:
        assert option in text, option
    assert "(default: paper)" in text and "(default: all)" in text
    unwrapped = "".join(text.split())  # argparse wraps the epilog at spaces and hyphens
    for value in preset_values():
        assert value in unwrapped, value


def test_preset_values_read_back_as_both_presets():
    """What --help lists is what --set reads: each preset rebuilt from its listed values."""
    listed = [value.partition("|") for value in preset_values()]
    paper = [f"{key_value}" for key_value, _, _ in listed]
    tiny = [key_value if not sep else f"{key_value.split('=')[0]}={small}"
            for key_value, sep, small in listed]
    assert len(listed) == sum(len(section) for section in RunConfig().to_dict().values())
    assert RunConfig.preset("tiny").with_overrides(paper) == RunConfig.preset("paper")
    assert RunConfig.preset("paper").with_overrides(tiny) == RunConfig.preset("tiny")
    assert any(sep for _, sep, _ in listed) and "train.adam_betas=0.9,0.999" in paper


def test_cli_reports_bad_input_clearly(tmp_path, capsys):
    assert main(["--shards", str(tmp_path / "missing"), "--out", str(tmp_path / "run"),
                 "--config", "tiny", "--device", "cpu", "--no-progress"]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["--shards", str(tmp_path), "--out", str(tmp_path / "run"),
                 "--set", "train.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
    # Settings are checked before any work: one line each, nothing written.
    for extra, words in ((["--batch-size", "0"], "batch_size must be >= 1"),
                         (["--steps", "0"], "vae_steps must be >= 1"),
                         (["--set", "train.lr=-1"], "lr must be a positive number"),
                         (["--device", "gpu"], "'gpu' is not a device"),
                         (["--device", "cuda:7"] if torch.cuda.device_count() < 8 else [], "cuda:7")):
        if not extra:
            continue
        assert main(["--shards", str(tmp_path), "--out", str(tmp_path / "run"), "--config", "tiny",
                     *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, err
    assert not (tmp_path / "run").exists()


def _write_shards(root: Path) -> None:
    """A small real shards folder (sarah_data.shards writer + stats) with two train sequences."""
    from scipy.spatial.transform import Rotation

    from sarah_data import icosahedron
    from sarah_data.constants import JOINT_NAMES
    from sarah_data.shards import (MANIFEST_NAME, Manifest, ProcessedPerson, ProcessedSequence,
                                   ShardWriter, write_manifest)
    from sarah_data.stats import compute_stats

    joints, shell, frames = 2, 3, 120
    rng = np.random.default_rng(0)

    def person(name: str) -> ProcessedPerson:
        root = np.stack([np.cumsum(rng.normal(0, 0.01, frames)), np.full(frames, 0.9),
                         np.cumsum(rng.normal(0, 0.01, frames))], 1)
        yaw = Rotation.from_euler("Y", np.cumsum(rng.normal(0, 0.05, frames))[:, None]).as_matrix()
        rot = np.broadcast_to(yaw[:, None], (frames, joints, 3, 3))
        pos = root[:, None] + rng.normal(0, 0.2, (frames, joints, 3))
        return ProcessedPerson(
            name=name, icosahedra=icosahedron.encode(pos, rot).astype(np.float32),
            shell=(root[:, None] + rng.normal(0, 0.2, (frames, shell, 3))).astype(np.float32),
            head=root[:, [0, 2]].astype(np.float32), gaze=rng.uniform(-1, 1, frames).astype(np.float32),
            speaking=rng.random(frames) < 0.5, valid=np.ones(frames, bool),
            root_position=root.astype(np.float32), root_rotation=yaw.astype(np.float32),
            audio={"logmel": rng.normal(size=(frames, DA)).astype(np.float32)})

    from helpers import shard_attrs

    attrs = shard_attrs(JOINT_NAMES[:joints], shell, {"logmel": {"n_mels": DA}})
    infos, entries = [], {}
    for split in ("train", "val", "test"):
        with ShardWriter(root, split, attrs) as writer:
            if split == "train":
                for name in ("seq-a", "seq-b"):
                    writer.add(ProcessedSequence(name=name, session=f"s-{name}", split=split,
                                                 persons=(person("AAA"), person("BBB"))))
        infos += writer.close()
        entries.update(writer.entries)
    write_manifest(root / MANIFEST_NAME, Manifest(toolkit_version="0.1.0", config={}, splits={},
                                                  shards=infos, sequences=entries))
    compute_stats(root, window=WINDOW)


# sarah-train --set for a model small enough to train in a test
SMALL_CLI = ["vae.hidden=32", "vae.latent_dim=8", "vae.encoder_layers=1", "vae.decoder_layers=1",
             "flow.hidden=32", "flow.cond_dim=16", "flow.time_dim=16", "flow.layers=1",
             f"train.window={WINDOW}", "train.latent_stats_batches=1"]


def test_cli_trains_both_stages_on_real_shards(tmp_path, capsys):
    shards, out = tmp_path / "shards", tmp_path / "run"
    shards.mkdir()
    _write_shards(shards)
    small = SMALL_CLI + ["train.log_every=1"]
    args = ["--stage", "all", "--config", "tiny", "--shards", str(shards), "--out", str(out),
            "--steps", "2", "--batch-size", "2", "--device", "cpu", "--no-progress"]
    assert main(args + sum((["--set", s] for s in small), [])) == 0, capsys.readouterr().err
    models = load_models(out / "flow.pt", device="cpu")
    assert models.dims == {"motion": 2 * 36 + 3 * 3, "audio": DA}
    assert models.features == "logmel" and models.step == 2
    assert json.loads((out / "config.json").read_text())["train"]["window"] == WINDOW
    assert len(losses(out, "flow")) == 2
    # The shareable model file sits beside the checkpoint, with the same weights.
    from sarah_models.training.model_file import MODEL_FILE, load_model_file

    assert f"model file (for sarah-generate and sharing; loads without pickle): {out / MODEL_FILE}" \
        in capsys.readouterr().out
    shared = load_model_file(out / MODEL_FILE, device="cpu")
    assert shared.step == 2 and shared.dims == models.dims
    for name, value in models.flow.state_dict().items():
        assert torch.equal(value, shared.flow.state_dict()[name]), name


def test_cli_flow_stage_refuses_vae_settings_its_vae_lacks_and_keeps_decoding_ones(tmp_path, capsys):
    """--stage flow trains on OUT/vae.pt: a --set vae.* that would need another VAE is one
    error line naming the file and the field (nothing written), one that the VAE already has is
    fine, and a decoding setting reaches the model file (the flow stage used to drop both)."""
    import shutil

    from sarah_models.training.model_file import MODEL_FILE, read_model_file

    shards, base = tmp_path / "shards", tmp_path / "base"
    shards.mkdir()
    _write_shards(shards)
    small = SMALL_CLI + ["vae.root_weight=0.5"]
    common = ["--config", "tiny", "--shards", str(shards), "--steps", "2", "--batch-size", "2",
              "--device", "cpu", "--no-progress"]
    sets = lambda extra: sum((["--set", s] for s in small + extra), [])  # noqa: E731
    assert main(["--stage", "vae", "--out", str(base)] + common + sets([])) == 0
    capsys.readouterr()

    def flow(name: str, extra: list[str]) -> int:
        (tmp_path / name).mkdir()
        shutil.copy(base / "vae.pt", tmp_path / name / "vae.pt")
        return main(["--stage", "flow", "--out", str(tmp_path / name)] + common + sets(extra))

    assert flow("other_vae", ["vae.root_weight=0.25", "vae.beta=0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "other_vae" / "vae.pt") in err[0], err
    assert "vae.root_weight=0.25 (it has 0.5)" in err[0] and "vae.beta=0.5" in err[0], err
    assert not (tmp_path / "other_vae" / "flow.pt").exists()
    assert flow("decoding", ["vae.foot_swing_frames=7"]) == 0, capsys.readouterr().err
    written = read_model_file(tmp_path / "decoding" / MODEL_FILE)["config"]["vae"]
    assert written["foot_swing_frames"] == 7 and written["root_weight"] == 0.5


def test_phased_batches_take_the_first_steps_then_the_rest_and_close_the_first():
    from sarah_models.training.batches import phased_batches

    closed = []

    def first():
        try:
            yield from ("a0", "a1", "a2", "a3")
        finally:
            closed.append(True)

    batches = phased_batches(first(), 2, iter(("b0", "b1")))
    assert next(batches) == "a0" and next(batches) == "a1" and not closed
    assert list(batches) == ["b0", "b1"] and closed == [True]
    assert list(phased_batches(first(), 0, iter(("b0",)))) == ["b0"]  # resumed past the switch


def test_vae_short_windows_first_then_full_ones_resuming_across_the_switch(tmp_path, monkeypatch):
    """train.vae_short_steps: the VAE's first steps read short windows from the shards, the rest
    full ones; a run stopped before the switch and resumed equals the uninterrupted one."""
    from sarah_models.training import stages

    shards = tmp_path / "shards"
    shards.mkdir()
    _write_shards(shards)
    lengths: list[int] = []
    real_loop = stages.train_loop

    def watched(model, batches, *args, **kwargs):
        def spy():
            for batch in batches:
                lengths.append(batch["motion"].shape[1])
                yield batch
        return real_loop(model, spy(), *args, **kwargs)

    monkeypatch.setattr(stages, "train_loop", watched)

    def vae(out: Path, steps: int, resume: bool = False, short_steps: int = 3) -> dict:
        config = tiny_config(steps, vae_short_steps=short_steps, vae_short_window=8)
        train("vae", config, shards, out, resume=resume, device="cpu", progress=False, echo=lambda _: None)
        return load_checkpoint(out / "vae.pt")["vae"]

    straight = vae(tmp_path / "straight", 6)
    assert lengths == [8, 8, 8, WINDOW, WINDOW, WINDOW]
    lengths.clear()
    vae(tmp_path / "broken", 2)
    resumed = vae(tmp_path / "broken", 6, resume=True)
    assert lengths == [8, 8, 8, WINDOW, WINDOW, WINDOW]
    assert all(torch.equal(value, resumed[key]) for key, value in straight.items())
    assert losses(tmp_path / "straight", "vae") == losses(tmp_path / "broken", "vae")
    without = vae(tmp_path / "full", 6, short_steps=0)
    assert not all(torch.equal(value, without[key]) for key, value in straight.items())
    with pytest.raises(ValueError, match="vae_short_window 6 is not a multiple of the VAE stride 4"):
        config = tiny_config(6, vae_short_steps=3, vae_short_window=6)
        train("vae", config, shards, tmp_path / "bad", device="cpu", progress=False, echo=lambda _: None)


def test_stage_model_rewrites_decoding_settings_and_nothing_else(tmp_path, capsys):
    """sarah-train --stage model: the same weights, bit for bit, with another seam inertia; a
    setting that needs training is refused before anything is written."""
    from sarah_cli.train import main
    from sarah_models.pretrained import model_path
    from sarah_models.training.model_file import read_model_file

    source = model_path("fixture-tiny")
    out = tmp_path / "run"
    assert main(["--stage", "model", "--init-from", str(source), "--out", str(out),
                 "--set", "vae.boundary_inertia=0.5"]) == 0
    before, after = read_model_file(source), read_model_file(out / "model.safetensors")
    assert after["config"]["vae"]["boundary_inertia"] == 0.5
    for part in ("vae", "flow", "normalizer"):
        assert before[part].keys() == after[part].keys()
        for key, value in before[part].items():
            assert torch.equal(value, after[part][key]), (part, key)
    for section, stored in before["config"].items():  # every other setting as it was
        for key, value in stored.items():
            if (section, key) != ("vae", "boundary_inertia"):
                assert after["config"][section][key] == value, (section, key)
    assert main(["--stage", "model", "--init-from", str(source), "--out", str(tmp_path / "no"),
                 "--set", "vae.hidden=64"]) == 2
    from sarah_models.config import decoding_settings
    assert f"only decoding settings ({', '.join(decoding_settings())})" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_stage_model_copies_the_decoding_settings_of_another_model(tmp_path, capsys):
    """--decoding-from: a model written with no settings spelled decodes as the shipped one does,
    and --set still changes one of them; it belongs to --stage model only."""
    from sarah_cli.train import main
    from sarah_models.config import RunConfig, decoding_settings
    from sarah_models.pretrained import model_path
    from sarah_models.training.model_file import read_model_file

    def decoding(run):
        config = read_model_file(Path(run) / "model.safetensors")["config"]
        return {name: config["vae"][name.split(".")[1]] for name in decoding_settings()}

    # read as every loader reads it: a field the file predates (vae.seam_mode) at its default
    shipped = RunConfig.from_dict(read_model_file(model_path("fixture-tiny"))["config"]).to_dict()["vae"]
    assert "seam_mode" not in read_model_file(model_path("fixture-tiny"))["config"]["vae"]
    assert shipped["seam_mode"] == "velocity"
    plain = tmp_path / "plain"  # the shipped weights with every decoding setting at its default
    defaults = RunConfig.preset("tiny").to_dict()["vae"]
    assert main(["--stage", "model", "--init-from", str(model_path("fixture-tiny")), "--out", str(plain)]
                + [a for name in decoding_settings() for a in
                   ("--set", f"{name}={defaults[name.split('.')[1]]}")]) == 0
    wanted = {name: shipped[name.split(".")[1]] for name in decoding_settings()}
    assert decoding(plain) != wanted
    # the defaults come back as they went (vae.root_inertia None, booleans, strings)
    assert decoding(plain)["vae.root_inertia"] is None
    assert main(["--stage", "model", "--init-from", str(plain), "--out", str(tmp_path / "again"),
                 "--decoding-from", str(plain)]) == 0
    assert decoding(tmp_path / "again") == decoding(plain)
    assert main(["--stage", "model", "--init-from", str(plain), "--out", str(tmp_path / "same"),
                 "--decoding-from", "fixture-tiny"]) == 0
    # a shipped model by its name, as --decoding-from takes it: its weights and its settings
    assert main(["--stage", "model", "--init-from", "fixture-tiny", "--out", str(tmp_path / "named")]) == 0
    named = RunConfig.from_dict(read_model_file(tmp_path / "named" / "model.safetensors")["config"])
    assert {name: named.to_dict()["vae"][name.split(".")[1]] for name in decoding_settings()} == wanted
    assert decoding(tmp_path / "same") == wanted
    same, before = (read_model_file(Path(run) / "model.safetensors")["config"]
                    for run in (tmp_path / "same", plain))
    for section in same:  # nothing but the decoding settings came across
        assert {k: v for k, v in same[section].items() if f"{section}.{k}" not in wanted} == \
            {k: v for k, v in before[section].items() if f"{section}.{k}" not in wanted}
    assert main(["--stage", "model", "--init-from", str(plain), "--out", str(tmp_path / "other"),
                 "--decoding-from", str(tmp_path / "same"), "--set", "vae.foot_lock=0"]) == 0
    assert decoding(tmp_path / "other") == {**wanted, "vae.foot_lock": 0.0} != wanted
    with pytest.raises(SystemExit):
        main(["--stage", "flow", "--shards", str(tmp_path), "--out", str(tmp_path / "no"),
              "--decoding-from", "fixture-tiny"])
    assert "--decoding-from goes with --stage model" in capsys.readouterr().err


def test_stage_model_takes_the_skeleton_of_shards_for_a_rigid_decoding(prepared_shards, tmp_path,
                                                                       capsys):
    """A model trained before stats.h5 had bone lengths: asked to decode onto a rigid skeleton
    it says where to get one, and --shards gives it that of their training split."""
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    from sarah_cli.train import main
    from sarah_data.stats import load_stats
    from sarah_models.pretrained import model_path
    from sarah_models.training.model_file import read_model_file

    old = tmp_path / "old.safetensors"  # the shipped model without its skeleton
    with safe_open(str(model_path("fixture-tiny")), framework="pt") as handle:
        metadata = handle.metadata()
    tensors = {k: v for k, v in load_file(str(model_path("fixture-tiny"))).items()
               if not k.startswith("normalizer.bone_length")}
    save_file(tensors, str(old), metadata=metadata)
    assert main(["--stage", "model", "--init-from", str(old), "--out", str(tmp_path / "no"),
                 "--set", "vae.rigid_bones=true"]) == 2
    assert "--stage model --init-from MODEL --shards SHARDS" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
    assert main(["--stage", "model", "--init-from", str(old), "--out", str(tmp_path / "yes"),
                 "--shards", str(prepared_shards), "--set", "vae.rigid_bones=true"]) == 0
    written = read_model_file(tmp_path / "yes" / "model.safetensors")
    assert written["config"]["vae"]["rigid_bones"] is True
    np.testing.assert_array_equal(written["normalizer"]["bone_length_mean"].numpy(),
                                  load_stats(prepared_shards)["bone_length/mean"])


def test_echoed_batches_prepare_each_batch_once_and_resume_mid_echo():
    from sarah_models.training.batches import echoed_batches

    made: list[tuple[str, int]] = []

    def prepare(batch: str, step: int) -> str:
        made.append((batch, step))
        return batch.upper()

    straight = list(echoed_batches(iter("abc"), prepare, 3))
    assert straight == ["A", "A", "A", "B", "B", "B", "C", "C", "C"]
    assert made == [("a", 0), ("b", 3), ("c", 6)]  # once per batch, at its first step
    for start in range(9):  # the batch source resumes at start // 3, as EpochBatches does
        made.clear()
        resumed = list(echoed_batches(iter("abc"[start // 3:]), prepare, 3, start_step=start))
        assert resumed == straight[start:], start
        assert made[0] == ("abc"[start // 3], 3 * (start // 3))
    assert list(echoed_batches(iter("ab"), prepare, 1)) == ["A", "B"]


def test_flow_loss_of_a_prepared_batch_is_the_loss_of_the_raw_batch(tmp_path):
    """What train.flow_echo reuses is what the un-echoed step computes: a batch encoded once
    by ``prepare`` gives the loss, to the bit, that the raw batch gives."""
    from sarah_models.training.loop import step_generator
    from sarah_models.training.objectives import FlowObjective

    run("vae", tmp_path, 2)
    run("flow", tmp_path, 2)
    models = load_models(tmp_path / "flow.pt", device="cpu")
    objective = FlowObjective(models.flow, models.vae, models.normalizer)
    data = SyntheticWindows()
    batch = {k: torch.stack([data[i][k] for i in range(4)]) for k in
             ("motion", "user_head", "agent_audio", "user_audio", "gaze")}
    generator = lambda: step_generator(torch.device("cpu"), 0, 0, 5)  # noqa: E731
    raw = objective(batch, generator())
    prepared = objective.prepare(batch)
    again = objective(prepared, generator())
    assert torch.equal(raw["loss"], again["loss"]) and torch.equal(raw["z1_pred"], again["z1_pred"])
    other = objective(prepared, step_generator(torch.device("cpu"), 0, 0, 6))
    assert not torch.equal(other["loss"], raw["loss"])  # each echo draws its own times and noise


def test_flow_echo_trains_fewer_encodings_and_resumes_mid_echo_exactly(tmp_path, monkeypatch):
    from sarah_models.training.objectives import FlowObjective

    encoded: list[int] = []
    real_latents = FlowObjective.latents

    def counted(self, motion, generator=None):
        encoded.append(motion.shape[0])
        return real_latents(self, motion, generator)

    monkeypatch.setattr(FlowObjective, "latents", counted)

    def flow(out: Path, steps: int, resume: bool = False, echo_times: int = 3) -> dict:
        if not (out / "vae.pt").exists():
            run("vae", out, 2)
        train("flow", tiny_config(steps, flow_echo=echo_times), None, out, resume=resume,
              device="cpu", dataset=SyntheticWindows(), stats=STATS, progress=False,
              echo=lambda _: None)
        return load_checkpoint(out / "flow.pt")["flow"]

    stats_batches = tiny_config(1).train.latent_stats_batches
    straight = flow(tmp_path / "straight", 6)
    assert len(encoded) == stats_batches + 2  # 6 steps, 2 encoded batches
    broken = tmp_path / "broken"
    flow(broken, 4)  # stops after the first step of the second batch's echo
    resumed = flow(broken, 6, resume=True)
    assert losses(tmp_path / "straight", "flow") == losses(broken, "flow")
    assert all(torch.equal(value, resumed[key]) for key, value in straight.items())
    plain = flow(tmp_path / "plain", 6, echo_times=1)
    assert not all(torch.equal(value, plain[key]) for key, value in straight.items())
    with pytest.raises(ValueError, match="flow_echo must be >= 1"):
        tiny_config(1, flow_echo=0)


def test_root_relative_standardization_is_exact_both_ways_and_travels_with_the_normalizer():
    """vae.root_relative: every point's x and z less the root's, the root's points absolute, so
    denormalize(normalize(x)) is x for any motion; the root's points survive a state dict."""
    from sarah_models.nn.normalizer import Normalizer

    points = 9
    rng = np.random.default_rng(0)
    stats = {"motion": (rng.normal(0, 1, 3 * points), rng.uniform(0.1, 2, 3 * points))}
    norm = Normalizer(stats)
    norm.set_root_relative([2, 3])
    for _ in range(5):
        x = torch.from_numpy(rng.normal(0, 3, (4, 7, 3 * points))).float()
        shifted = x.clone().unflatten(-1, (points, 3))
        shifted[..., [0, 2]] += torch.tensor([1.5, -2.0])  # the whole body walks elsewhere
        shifted = shifted.flatten(-2)
        assert torch.allclose(norm.denormalize("motion", norm.normalize("motion", x)), x, atol=1e-5)
        moved = norm.normalize("motion", shifted) - norm.normalize("motion", x)
        by_point = moved.unflatten(-1, (points, 3))
        others = [p for p in range(points) if p not in (2, 3)]
        assert by_point[..., others, :].abs().max() < 1e-5  # relative points do not see the walk
        assert by_point[..., [2, 3], 0].abs().min() > 0.1  # the root's own points do
    copy = Normalizer.from_state_dict(norm.state_dict())
    assert copy.root_relative and copy.motion_root.tolist() == [2, 3]
    assert not Normalizer(stats).root_relative
    with pytest.raises(ValueError, match="root points"):
        norm.set_root_relative([])


def test_root_steps_are_exact_both_ways_and_a_stream_sums_them_as_the_whole_window_does():
    """vae.root_steps: the root's points standardized as their floor steps since the frame
    before (the origin before the first), so a body walking at a constant speed has constant
    step channels; denormalize sums them back exactly, and blocks decoded one after another
    from the frame before give the window decoded at once; the form survives a state dict."""
    from sarah_models.nn.normalizer import Normalizer

    points, frames = 9, 12
    rng = np.random.default_rng(1)
    stats = {"motion": (rng.normal(0, 0.01, 3 * points), rng.uniform(0.01, 2, 3 * points))}
    norm = Normalizer(stats)
    norm.set_root_relative([2, 3], steps=True)
    assert norm.root_steps and norm.root_relative
    x = torch.from_numpy(rng.normal(0, 1, (2, frames, 3 * points)))
    walk = x.clone().unflatten(-1, (points, 3))
    walk[..., [0, 2]] += 0.05 * torch.arange(frames, dtype=x.dtype)[:, None, None]  # 5 cm a frame
    walk = walk.flatten(-2)
    assert torch.allclose(norm.denormalize("motion", norm.normalize("motion", x)), x, atol=1e-9)
    moved = (norm.normalize("motion", walk) - norm.normalize("motion", x)).unflatten(-1, (points, 3))
    std = norm.motion_std.unflatten(-1, (points, 3))
    steps = moved[..., 1:, [2, 3], 0] * std[[2, 3], 0]  # the walk's own part of the root's steps
    assert torch.allclose(steps, torch.full_like(steps, 0.05), atol=1e-9)
    assert moved[..., [0, 1, 4], :].abs().max() < 1e-9  # relative points do not see the walk
    standardized = norm.normalize("motion", walk)
    blocks, before = [], None
    for start in range(0, frames, 4):
        block = norm.denormalize("motion", standardized[:, start:start + 4], before)
        blocks.append(block)
        before = block[:, -1]
    assert torch.allclose(torch.cat(blocks, dim=1), walk, atol=1e-9)
    copy = Normalizer.from_state_dict(norm.state_dict())
    assert copy.root_steps and torch.allclose(copy.denormalize("motion", standardized), walk, atol=1e-9)
    plain = Normalizer(stats)
    plain.set_root_relative([2, 3])
    assert not plain.root_steps and not Normalizer.from_state_dict(plain.state_dict()).root_steps
    with pytest.raises(ValueError, match="root_relative"):
        VAEConfig(root_steps=True)


def test_root_step_training_fits_step_statistics_and_the_model_file_keeps_the_form(prepared_shards,
                                                                                   tmp_path):
    """A vae.root_steps stage fits the root's x and z as a frame's floor steps (centimetres,
    where their places spread over the window), and its flow's model file standardizes and
    decodes in the same form; a fine-tune cannot change the form."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.skeleton import ICOSAHEDRON_POINTS, ROOT, MotionLayout
    from sarah_models.training.model_file import load_model_file, write_model_file

    config = tiny_config(2).with_overrides(["train.window=16", "vae.root_relative=true",
                                            "vae.root_steps=true", "vae.recon_units=metres",
                                            "train.latent_stats_batches=4"])
    out = tmp_path / "run"
    common = dict(device="cpu", progress=False, echo=lambda _: None)
    train("vae", config, prepared_shards, out, **common)
    train("flow", config, prepared_shards, out, **common)
    norm = load_models(out / "flow.pt", device="cpu").normalizer
    assert norm.root_steps
    layout = MotionLayout.from_width(norm.motion_mean.numel())
    root_x = layout.joint(ROOT) * ICOSAHEDRON_POINTS * 3  # the root's first point's x
    windows = WindowDataset.sliding(prepared_shards, "train", extractor=None, window=16)
    motion = torch.stack([windows[i]["motion"] for i in range(len(windows))])
    places = motion[..., root_x]
    steps = torch.cat([places[:, :1], places.diff(dim=1)], dim=1)
    assert norm.motion_std[root_x] < 0.5 * places.std()
    assert 0.5 < norm.motion_std[root_x] / steps.std() < 2
    loaded = load_model_file(write_model_file(out / "flow.pt", tmp_path / "m.safetensors"),
                             device="cpu").normalizer
    assert loaded.root_steps
    assert torch.allclose(loaded.denormalize("motion", loaded.normalize("motion", motion)), motion,
                          atol=1e-4)
    other = config.with_overrides(["vae.root_steps=false"])
    with pytest.raises(ValueError, match="root_steps"):
        train("vae", other, prepared_shards, tmp_path / "mixed", init_from=out, **common)


def test_root_weighted_counts_the_root_once_per_point_of_the_body():
    from sarah_models.training.objectives import root_weighted

    variance = torch.arange(1.0, 13.0)  # 4 points
    weighted = root_weighted(variance, torch.tensor([1])).unflatten(-1, (4, 3))
    expected = variance.unflatten(-1, (4, 3)).clone()
    expected[1, 0] *= 4
    expected[1, 2] *= 4
    assert torch.equal(weighted, expected)
    quarter = root_weighted(variance, torch.tensor([1]), 0.25).unflatten(-1, (4, 3))
    expected[1, [0, 2]] /= 4  # the root's place counts a quarter as much; the pose as before
    assert torch.equal(quarter, expected)
    with pytest.raises(ValueError, match="root_weight"):
        VAEConfig(root_weight=0.0)


def test_root_relative_training_fits_its_statistics_and_the_model_file_keeps_them(prepared_shards,
                                                                                    tmp_path):
    """A root-relative VAE stage standardizes root-relative channels (about zero mean and unit
    std on the batches it fitted them on, the head's x far narrower than absolute), its flow
    and model file carry the same normalizer, and generation decodes to absolute motion."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.skeleton import HEAD, ICOSAHEDRON_POINTS, ROOT, MotionLayout
    from sarah_models.training.model_file import load_model_file, write_model_file
    from sarah_models.training.objectives import VAEObjective

    config = tiny_config(2).with_overrides(["train.window=16", "vae.root_relative=true",
                                            "vae.recon_units=metres", "train.latent_stats_batches=4"])
    out = tmp_path / "run"
    common = dict(device="cpu", progress=False, echo=lambda _: None)
    train("vae", config, prepared_shards, out, **common)
    train("flow", config, prepared_shards, out, **common)
    models = load_models(out / "flow.pt", device="cpu")
    norm = models.normalizer
    dims = norm.motion_mean.numel()
    layout = MotionLayout.from_width(dims)
    start = layout.joint(ROOT) * ICOSAHEDRON_POINTS
    assert norm.motion_root.tolist() == list(range(start, start + ICOSAHEDRON_POINTS))
    windows = WindowDataset.sliding(prepared_shards, "train", extractor=None, window=16)
    motion = torch.stack([windows[i]["motion"] for i in range(len(windows))])
    standardized = norm.normalize("motion", motion).reshape(-1, dims)
    assert standardized.mean(0).abs().median() < 0.5
    assert (standardized.std(0).median() - 1).abs() < 0.5
    absolute = motion.reshape(-1, dims).std(0)
    head_x = layout.joint_slice(HEAD).start  # the head icosahedron's first point's x
    assert norm.motion_std[head_x] < 0.5 * absolute[head_x]
    objective = VAEObjective(models.vae, norm)
    weight = objective.channel_weight.unflatten(-1, (-1, 3))
    assert weight[start, 0] > 20 * weight[start, 1]  # the root's x counts for every point
    shared = write_model_file(out / "flow.pt", tmp_path / "m.safetensors")
    loaded = load_model_file(shared, device="cpu").normalizer
    assert loaded.root_relative and torch.equal(loaded.motion_root, norm.motion_root)
    assert torch.allclose(loaded.denormalize("motion", loaded.normalize("motion", motion)), motion,
                          atol=1e-4)
    other = config.with_overrides(["vae.root_relative=false"])
    with pytest.raises(ValueError, match="root_relative"):
        train("vae", other, prepared_shards, tmp_path / "mixed", init_from=out, **common)
