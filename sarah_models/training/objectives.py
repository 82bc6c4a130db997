"""Training objectives: a batch of windows in, a dict of scalar losses out ("loss" optimised).

* ``VAEObjective``: standardize the motion, the VAE's reconstruction + KL (``CausalVAE.forward``),
  plus the planted-foot term (``PlantedFeet``) when ``vae.contact_weight`` > 0, the
  head-facing term (``HeadFacing``) when ``vae.head_weight`` > 0, the foot-lift term
  (``FootLift``) when ``vae.lift_weight`` > 0 and the acceleration-spectrum term
  (``AccelerationSpectrum``) when ``vae.spectral_weight`` > 0, the acceleration-moment term
  (``AccelerationMoments``) when ``vae.moment_weight`` > 0, and the stance head's
  cross-entropy against the data's stance (``nn.stance``) when ``vae.stance_weight`` > 0.
* ``FlowObjective``: encode with the frozen VAE, standardize the latents, then
  ``flow_matching_loss`` (eq. 4-5: x1-prediction on the straight path with CFG dropout).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from sarah_data import icosahedron
from sarah_data.constants import BODY_JOINTS, FPS
from sarah_data.gaze import FACING_AXIS
from sarah_data.skeleton import (FEET, HEAD, ICOSAHEDRON_POINTS, JOINT_GROUPS, ROOT, MotionLayout,
                                 shell_parts)

from ..config import NEEDS_STANCE_HEAD, STREAMED_TOKENS
from ..nn.flow import FlowModel, build_block_mask
from ..nn.normalizer import Normalizer
from ..nn.stance import stance_of
from ..nn.user_offset import block_starts, pelvis_floor, user_offset
from ..nn.vae import CausalVAE
from ..sampling.foot_lock import RELEASE
from ..sampling.guidance import drop_probs, sample_drop_mask
from ..sampling.path import interpolate


class VAEObjective(nn.Module):
    """Standardize the motion of a batch and return the VAE loss dict (plus each extra term whose
    ``vae.config`` weight is above 0)."""

    def __init__(self, vae: CausalVAE, normalizer: Normalizer) -> None:
        super().__init__()
        self.vae, self.normalizer = vae, normalizer
        self.contact = PlantedFeet(vae.motion_dim) if vae.config.contact_weight > 0 else None
        self.head = HeadFacing(vae.motion_dim) if vae.config.head_weight > 0 else None
        self.lift = FootLift(vae.motion_dim) if vae.config.lift_weight > 0 else None
        self.spectrum = AccelerationSpectrum(vae.motion_dim) if vae.config.spectral_weight > 0 else None
        self.moments = None
        if vae.config.moment_weight > 0:
            zeros = torch.zeros(1, vae.motion_dim, device=normalizer.motion_mean.device)
            mean_pose = normalizer.denormalize("motion", zeros)[0]  # the data's mean pose
            self.moments = AccelerationMoments(vae.motion_dim, vae.config.moment_parts, mean_pose)
        self.stance_layout = (term_layout(vae.motion_dim, "vae.stance_weight")
                              if vae.stance is not None else None)
        weight = None
        if vae.config.recon_units == "metres":
            variance = normalizer.motion_std.float().square()
            if normalizer.root_relative:
                variance = root_weighted(variance, normalizer.motion_root, vae.config.root_weight)
            weight = variance / variance.mean()
        self.register_buffer("channel_weight", weight, persistent=False)

    @property
    def trainable(self) -> nn.Module:
        return self.vae

    def forward(self, batch: Mapping[str, Tensor], generator: torch.Generator | None = None):
        device = self.normalizer.motion_mean.device
        motion = self.normalizer.normalize_batch({"motion": batch["motion"]}, device)["motion"]
        out = self.vae(motion, generator, self.channel_weight)
        if self.vae.stance is not None:
            # the latents the decoder read; the term's gradient teaches the encoder to carry it
            stance = stance_of(batch["motion"].to(device).float(), self.stance_layout)
            out["stance"] = F.binary_cross_entropy_with_logits(self.vae.stance(out["z"].float()), stance)
            out["loss"] = out["loss"] + self.vae.config.stance_weight * out["stance"]
        if all(term is None for term in (self.contact, self.head, self.lift, self.spectrum,
                                         self.moments)):
            return out
        decoded = self.normalizer.denormalize("motion", out["x_hat"].float())
        true = self.normalizer.denormalize("motion", motion.float())
        loss, terms = out["loss"], {}
        for name, term, weight in (("contact", self.contact, self.vae.config.contact_weight),
                                   ("head", self.head, self.vae.config.head_weight),
                                   ("lift", self.lift, self.vae.config.lift_weight),
                                   ("spectrum", self.spectrum, self.vae.config.spectral_weight),
                                   ("moments", self.moments, self.vae.config.moment_weight)):
            if term is not None:
                terms[name] = term(decoded, true)
                loss = loss + weight * terms[name]
        return {**out, "loss": loss, **terms}


def root_weighted(variance: Tensor, root_points: Tensor, weight: float = 1.0) -> Tensor:
    """Root-relative channels' variances with the root points' x and z counted ``weight`` times
    once per point of the body: absolute, every point carries the root's error, so at weight 1
    where the body stands weighs as much as all of its pose together, as a loss in metres of the
    absolute points would weigh it (``vae.root_weight``)."""
    points = variance.unflatten(-1, (-1, 3)).clone()
    root = root_points.to(points.device)
    points[root[:, None], torch.tensor([0, 2], device=points.device)] *= weight * points.shape[0] / root.numel()
    return points.flatten()


def term_layout(motion_dim: int, setting: str) -> MotionLayout:
    """The motion layout a loss term reads joints from; ValueError naming the ``setting`` that
    asked for the term when the motion is not icosahedra and shell points."""
    try:
        return MotionLayout.from_width(motion_dim)
    except ValueError as error:
        raise ValueError(f"{setting} needs the icosahedron motion layout: {error}") from None


class PlantedFeet(nn.Module):
    """Squared error of the decoded feet's horizontal step while the true foot is planted.

    Planted, per foot and frame step: the true foot joint (icosahedron centroid) is below the
    foot-slide metric's height at both ends of the step and moves less than its speed. The error
    is in units of that speed's step (``foot_min_speed / FPS``: 1 mm at 30 fps), averaged over
    planted steps. Inputs: motion in metres, window frame (floor at y = 0), icosahedra first."""

    def __init__(self, motion_dim: int) -> None:
        super().__init__()
        from ..evaluation.metrics import MetricsConfig

        self.layout = term_layout(motion_dim, "vae.contact_weight")
        metric = MetricsConfig()
        self.max_height, self.step = metric.foot_max_height, metric.foot_min_speed / FPS

    def feet(self, motion: Tensor) -> Tensor:
        return self.layout.joint_positions(motion, FEET)  # (B, T, feet, 3)

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        pred, gt = self.feet(decoded), self.feet(true)
        true_step = gt[:, 1:, :, [0, 2]] - gt[:, :-1, :, [0, 2]]
        pred_step = pred[:, 1:, :, [0, 2]] - pred[:, :-1, :, [0, 2]]
        planted = ((torch.maximum(gt[:, 1:, :, 1], gt[:, :-1, :, 1]) < self.max_height)
                   & (true_step.norm(dim=-1) < self.step)).float()
        error = (pred_step - true_step).square().sum(-1) / self.step ** 2
        return (error * planted).sum() / planted.sum().clamp_min(1.0)


class HeadFacing(nn.Module):
    """Squared error of the head's horizontal facing direction, a unit vector.

    Facing is the head rotation's ``gaze.FACING_AXIS`` column (what the gaze score reads),
    taken linearly from the head icosahedron's vertices (``icosahedron.axis``) and divided by
    the true icosahedron's radius, so the truth's is a unit vector; only x and z count, as in the
    gaze score. Inputs: motion in metres, icosahedra first."""

    def __init__(self, motion_dim: int) -> None:
        super().__init__()
        self.channels = term_layout(motion_dim, "vae.head_weight").joint_slice(HEAD)

    def facing(self, motion: Tensor) -> Tensor:
        points = motion[..., self.channels].unflatten(-1, (ICOSAHEDRON_POINTS, 3))
        return icosahedron.axis(points, FACING_AXIS)  # (B, T, 3): radius * the facing axis

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        gt = self.facing(true)
        radius = gt.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        error = (self.facing(decoded) - gt)[..., [0, 2]] / radius
        return error.square().sum(-1).mean()


class FootLift(nn.Module):
    """Squared error of the feet's heights in units of ``sampling.foot_lock.RELEASE``.

    The feet are the foot joints' icosahedron centroids; their heights are y in the window frame
    (floor at y = 0). A decoder whose feet lift as the data's do hands the foot lock steps it
    lets through as they came, where a gliding foot gets the lock's arc. Inputs: motion in
    metres, icosahedra first."""

    def __init__(self, motion_dim: int) -> None:
        super().__init__()
        self.layout, self.unit = term_layout(motion_dim, "vae.lift_weight"), RELEASE

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        heights = [self.layout.joint_positions(m, FEET)[..., 1] for m in (decoded, true)]
        return ((heights[0] - heights[1]) / self.unit).square().mean()


def point_accelerations(layout: MotionLayout, motion: Tensor) -> Tensor:
    """(B, T, D) motion in metres -> (B, T - 2, 3 P) accelerations in metres/s^2 of the body
    joints (icosahedron centroids, which the decoding's skeleton carries the shell with) and
    the shell points (what FGD_acc reads)."""
    icosahedra, shell = layout.split(motion)
    joints = icosahedra[..., :BODY_JOINTS, :, :].mean(-2)
    points = torch.cat([joints.flatten(-2), shell.flatten(-2)], dim=-1)
    return (points[:, 2:] - 2 * points[:, 1:-1] + points[:, :-2]).float() * FPS ** 2


class AccelerationMoments(nn.Module):
    """Relative Frobenius distance ``||M_hat - M|| / ||M||`` between the second-moment matrices
    of the decoded and the true accelerations of some parts of the pose: the body joints and
    shell points of the joint groups ``parts`` (``skeleton.JOINT_GROUPS``; a shell point
    belongs to the group of the joint it lies nearest to in ``mean_pose``), less the pelvis's
    acceleration, every frame of the batch one sample. These are the statistics FGD_acc fits
    its Gaussians with (the accelerations' mean is ~0, so the second moment is their
    covariance). The energy score rewards a decoder whose samples are the data's frame by
    frame; this asks the batch's samples together to spread the way the data's do, in each
    direction and across points. Why parts, and relative to the pelvis: the decoding draws the
    body's path (root hold) and the feet's steps (foot lock) anew, and the raw decoded pelvis
    accelerates ~6x as hard as the data's; over every point the term asked the decoder for the
    root's or the steps' energy and put it in the spine and arms (the fixture benchmark's
    seventy-fourth run). Inputs: motion in metres."""

    def __init__(self, motion_dim: int, parts: Sequence[str], mean_pose: Tensor) -> None:
        super().__init__()
        self.layout = term_layout(motion_dim, "vae.moment_weight")
        icosahedra, shell = (a.detach().double().cpu().numpy() for a in self.layout.split(mean_pose))
        shell_groups = shell_parts(icosahedra, shell, self.layout.joint_names)
        joints = [j for j, name in enumerate(self.layout.joint_names[:BODY_JOINTS])
                  if any(name in JOINT_GROUPS[part] for part in parts)]
        shell_points = sorted(BODY_JOINTS + p for part in parts for p in shell_groups.get(part, ()))
        self.register_buffer("points", torch.tensor(joints + shell_points), persistent=False)
        self.root = self.layout.joint(ROOT)  # a body joint: its index is its point's

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        moments = []
        for motion in (decoded, true):
            acc = point_accelerations(self.layout, motion).unflatten(-1, (-1, 3))
            pose = (acc[..., self.points, :] - acc[..., self.root, None, :]).flatten(0, 1).flatten(1)
            moments.append(pose.T @ pose / pose.shape[0])
        return (moments[0] - moments[1]).norm() / moments[1].norm().clamp_min(1e-12)


class AccelerationSpectrum(nn.Module):
    """Distance between the short-time magnitude spectra of the decoded and true accelerations.

    The points are the shell (what FGD_acc reads) and the body joints (icosahedron centroids,
    which the decoding's skeleton carries the shell with). Every coordinate's acceleration
    (second difference times FPS^2, metres/s^2) is cut into Hann windows of each length in
    ``windows`` (a quarter window apart); per length, the spectral
    convergence ``||S_hat| - |S|| / ||S||`` plus the mean absolute difference of the log
    magnitudes (floored at ``floor`` times the true magnitudes' RMS, so silent bins do not
    dominate), averaged over the lengths. Phases are dropped: a step or a beat whose timing the
    latent leaves open costs nothing for its phase, only for missing (or added) energy, which a
    squared error would have the decoder average away (the multi-resolution STFT loss of neural
    vocoders, for the same reason). Inputs: motion in metres (B, T, D)."""

    windows = (16, 32)
    floor = 1e-2

    def __init__(self, motion_dim: int) -> None:
        super().__init__()
        self.layout = term_layout(motion_dim, "vae.spectral_weight")

    @staticmethod
    def dft_basis(window: int, like: Tensor) -> Tensor:
        """(window, 2 * bins): the Hann-windowed cosines, then sines, of a real DFT."""
        n = torch.arange(window, device=like.device, dtype=like.dtype)
        angle = 2 * torch.pi * n[:, None] * torch.arange(window // 2 + 1, device=n.device) / window
        hann = torch.hann_window(window, device=n.device, dtype=n.dtype)[:, None]
        return torch.cat([hann * angle.cos(), hann * angle.sin()], dim=1)

    def spectra(self, acceleration: Tensor, window: int, basis: Tensor | None = None) -> Tensor:
        """(B, T, D) -> magnitudes (B, frames, D, bins): a real DFT as one matmul over the
        windowed frames, several times faster on a CPU than ``torch.stft`` over B * D series."""
        if basis is None:
            basis = self.dft_basis(window, acceleration)
        frames = acceleration.unfold(1, window, window // 4)  # (B, frames, D, window)
        real, imag = (frames @ basis).chunk(2, dim=-1)
        return (real.square() + imag.square() + 1e-12).sqrt()

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        acc = [point_accelerations(self.layout, m) for m in (decoded, true)]
        terms = []
        for window in self.windows:
            if acc[1].shape[1] < window:
                continue
            basis = self.dft_basis(window, acc[1])  # one basis for both spectra
            pred, gt = (self.spectra(a, window, basis) for a in acc)
            eps = self.floor * gt.square().mean().sqrt().detach()
            convergence = (pred - gt).norm() / gt.norm().clamp_min(1e-12)
            log_distance = ((pred + eps).log() - (gt + eps).log()).abs().mean()
            terms.append(convergence + log_distance)
        if not terms:
            raise ValueError(f"vae.spectral_weight needs windows of at least {min(self.windows) + 2} "
                             f"frames, got {true.shape[1]}")
        return torch.stack(terms).mean()


class FlowObjective(nn.Module):
    """Encode a batch with the frozen VAE and return the flow-matching loss dict."""

    def __init__(self, flow: FlowModel, vae: CausalVAE, normalizer: Normalizer,
                 latent: str = "mean") -> None:
        super().__init__()
        self.flow, self.vae, self.normalizer, self.latent = flow, vae, normalizer, latent
        self.vae.requires_grad_(False).eval()
        self.stance_layout = None
        if flow.config.stance_weight > 0:
            if vae.stance is None:
                raise ValueError(f"flow.stance_weight {NEEDS_STANCE_HEAD}")
            self.stance_layout = term_layout(vae.motion_dim, "flow.stance_weight")

    @property
    def trainable(self) -> nn.Module:
        return self.flow

    def train(self, mode: bool = True) -> "FlowObjective":
        super().train(mode)
        self.vae.eval()  # frozen: always in inference mode
        return self

    @torch.no_grad()
    def latents(self, motion: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Raw (unstandardized) latents of standardized motion."""
        mu, logvar = self.vae.encode(motion)
        if self.latent == "sample":
            noise = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
            mu = mu + noise * (0.5 * logvar).exp()
        return mu.float()

    @torch.no_grad()
    def prepare(self, batch: Mapping[str, Tensor],
                generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """The batch as the loss reads it: normalized inputs plus ``"latent"``, the frozen
        encoder's standardized latents (what ``train.flow_echo`` reuses)."""
        device = self.normalizer.motion_mean.device
        inputs = self.normalizer.normalize_batch(batch, device)
        inputs["latent"] = self.normalizer.normalize("latent", self.latents(inputs["motion"], generator))
        if self.stance_layout is not None:
            inputs["stance"] = stance_of(batch["motion"].to(device).float(), self.stance_layout)
        if self.flow.config.user_relative:  # where the data's agent stands before each block
            motion, head = (batch[k].to(device=device, dtype=torch.float32) for k in ("motion", "user_head"))
            starts = block_starts(pelvis_floor(motion), self.flow.stride)
            if self.flow.config.place_noise > 0:  # block 0 starts at the origin in generation too
                noise = torch.randn(starts.shape, generator=generator, device=device)
                noise[:, 0] = 0
                starts = starts + self.flow.config.place_noise * noise
            inputs["user_offset"] = user_offset(head, starts, self.flow.stride)
        return inputs

    def forward(self, batch: Mapping[str, Tensor], generator: torch.Generator | None = None):
        """The loss of a raw batch, or of one ``prepare`` made already (it has ``"latent"``)."""
        inputs = batch if "latent" in batch else self.prepare(batch, generator)
        out = flow_matching_loss(self.flow, inputs["latent"], inputs, generator)
        if self.stance_layout is not None:
            # what the stance head reads from the predicted clean latents, as decoding reads them
            logits = self.vae.stance(self.normalizer.denormalize("latent", out["z1_pred"].float()))
            per_sample = F.binary_cross_entropy_with_logits(
                logits, inputs["stance"], reduction="none").mean(dim=(1, 2))
            out["stance"] = (out["tau"] * per_sample).mean()
            out["loss"] = out["loss"] + self.flow.config.stance_weight * out["stance"]
        return out


def training_times(batch: int, generator: torch.Generator | None, device: torch.device | str,
                   logit_mean: float | None = None, logit_std: float = 1.0) -> Tensor:
    """One flow time per sample: U[0, 1] (the paper; ``logit_mean`` None), or the logit-normal
    sigmoid(N(logit_mean, logit_std)) (``flow.time_logit_mean``), whose median is
    sigmoid(logit_mean)."""
    if logit_mean is None:
        return torch.rand(batch, generator=generator, device=device)
    n = torch.randn(batch, generator=generator, device=device)
    return torch.sigmoid(logit_mean + logit_std * n)


def flow_matching_loss(flow: FlowModel, z: Tensor, cond: Mapping[str, Tensor],
                       generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """x1-prediction flow-matching loss (eq. 4-5) with tau ~ U[0, 1] (or the logit-normal,
    ``flow.time_logit_mean``) and CFG dropout, plus ``flow.config.difference_weight`` times the
    MSE of the tokens' differences ("difference")."""
    b, k = z.shape[:2]
    tau = training_times(b, generator, z.device, flow.config.time_logit_mean,
                         flow.config.time_logit_std)
    eps = torch.randn(z.shape, generator=generator, device=z.device, dtype=z.dtype)
    z_tau = interpolate(eps, z, tau[:, None, None].to(z.dtype))
    drop = sample_drop_mask(b, drop_probs(flow.config), generator, z.device)
    mask = None  # the model's own (``attention_window``)
    if flow.config.streamed_context > 0 and (
            torch.rand((), generator=generator, device=z.device) < flow.config.streamed_context):
        mask = build_block_mask(k, k, window=STREAMED_TOKENS, device=z.device)
    z1_pred = flow(z_tau, tau, cond, drop, attn_mask=mask)
    error = z1_pred.float() - z.float()
    recon = error.square().mean()
    difference = error.diff(dim=1).square().mean() if z.shape[1] > 1 else error.new_zeros(())
    loss = recon + flow.config.difference_weight * difference
    return {"loss": loss, "recon": recon, "difference": difference, "z1_pred": z1_pred,
            "tau": tau, "drop_rate": drop.float().mean()}
