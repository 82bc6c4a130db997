"""Every default of the models, once: the paper's numbers, then dataclasses built from them.

The constants below are the only place a paper value is written; configs, evaluation, generation
and the bench import them.

Feature widths (motion Dx, audio Da) are not configuration: they come from the data and are
stored next to the configs in every checkpoint. Every dataclass round-trips through
``asdict``/``from_dict`` as plain JSON-able values, so checkpoints stay loadable with
``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping, Sequence, TypeVar

from sarah_data.constants import FPS
from sarah_data.skeleton import JOINT_GROUPS

T = TypeVar("T")

WINDOW = 400  # T: frames per training window and per evaluated window (A.2)
STRIDE = 4  # s: frames per latent token (4)
CFG_SCALE = 1.3  # w of classifier-free guidance (A.3)
# Temperature of every token's starting noise eps: 1 is the paper's N(0, I); below 1 samples
# nearer the flow's mode (Glow-TTS and Matcha-TTS sample at 0.667).
NOISE_SCALE = 1.0
SOLVER = "midpoint"  # A.3: midpoint method, 4 steps (8 network evaluations per chunk)
SOLVERS = ("midpoint", "euler")
SOLVER_STEPS = 4
# How a streamed chunk sees its history tokens while the new one is solved: "final" re-noises
# each history token from its final latent at every solver time (eq. 4, the paper's 3.3);
# "trajectory" replays the states the token itself passed through when it was solved, so a
# stream is the offline joint solve computed causally (sampling/stream.py).
IMPUTATIONS = ("final", "trajectory")
GAZE_RANGE = (-1.0, 1.0)  # the gaze score is a cosine: targets outside cannot be reached
HISTORY_TOKENS = 2  # latents of history the streaming flow sees beside the new one (A.3)
# StreamConfig.history_tokens's default: as many latents as one layer of the flow attends to
# beside the new one (its attention window less one; HISTORY_TOKENS, the paper's, for a flow
# without a window). sampling.stream.kept_history resolves it.
HISTORY_WINDOW = "window"
STREAMED_TOKENS = HISTORY_TOKENS + 1  # what a streamed evaluation holds: the history and the new token
TINY_WINDOW = 64  # the CPU preset's training window


def check_history(history) -> None:
    """ValueError unless ``history`` is a number of tokens >= 0, None (all) or HISTORY_WINDOW."""
    if history is None or history == HISTORY_WINDOW:
        return
    if isinstance(history, bool) or not isinstance(history, numbers.Integral) or history < 0:
        raise ValueError(f"history_tokens must be >= 0, None (all) or {HISTORY_WINDOW!r}, got {history!r}")


def check_gaze(gaze: float | None) -> None:
    """A gaze target is None (no gaze control) or a finite score in ``GAZE_RANGE``."""
    low, high = GAZE_RANGE
    if gaze is not None and not (math.isfinite(gaze) and low <= gaze <= high):
        raise ValueError(f"gaze target must be in [{low:g}, {high:g}] or None, got {gaze}")


def check_noise_scale(scale: float) -> None:
    """A noise temperature is a finite number above 0 (0 would give every stream one motion)."""
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"noise scale must be a finite number above 0, got {scale}")


def from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
    """Build dataclass ``cls`` from a plain dict, rejecting unknown keys by name."""
    known = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field(s) {unknown}; known: {sorted(known)}")
    hints = typing.get_type_hints(cls)
    values = {}
    for name, value in data.items():
        if isinstance(value, list) and typing.get_origin(hints[name]) is tuple:
            value = tuple(value)
        values[name] = value
    return cls(**values)  # type: ignore[call-arg]


VELOCITY_WEIGHT_TINY = 10.0
RECON_UNITS = ("standardized", "metres")
MIN_SWING_FRAMES = 4  # a foot-lock step lifts off, travels and is set down (``sampling.foot_lock``)
SEAM_MODES = ("velocity", "position")  # VAEConfig.seam_mode: what a seam's spring continues
HOLD_READS = ("pelvis", "feet")  # VAEConfig.root_hold_reads: where the hold sees the body go
# What a setting that reads the VAE's stance head says when the VAE has none
NEEDS_STANCE_HEAD = ("reads the VAE's stance head, which only a VAE trained with "
                     "vae.stance_weight > 0 has")
LOCK_READS = ("drift", "stance")  # VAEConfig.foot_lock_reads: what makes a locked foot step
FOOT_STEPS = ("data", "arc")  # VAEConfig.foot_step: how a locked foot steps where it drifts


@dataclass(frozen=True)
class VAEConfig:
    """Causal transformer VAE with interleaved latent tokens (paper 3.2 and 4)."""

    stride: int = STRIDE  # s: frames per latent token
    latent_dim: int = 256  # Dz
    hidden: int = 256
    heads: int = 4
    encoder_layers: int = 9
    decoder_layers: int = 9
    mlp_ratio: float = 4.0
    beta: float = 1e-4  # KL weight (KL averaged per latent element, like the MSE per motion element)
    rope_base: float = 10_000.0
    # Not in the paper's eq. 3 (0 = the paper): weight of the MSE between decoded and true frame
    # differences. Short CPU runs leave frame-to-frame noise that a position loss barely sees
    # (docs/models.md); this term targets it directly.
    velocity_weight: float = 0.0
    # Not in the paper (0 = the paper): the same for second differences. A position loss and a
    # velocity loss both reward a decoder that smooths what it cannot place exactly: the
    # fixtures' hands and steps come back with a fraction of their acceleration, and FGD_acc
    # scores exactly that (docs/results.md, nineteenth run).
    acceleration_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of the planted-foot term, the squared error of
    # the decoded feet's horizontal step on the frames where the true foot is planted (by the
    # foot-slide metric's own thresholds), in units of that metric's slide threshold. The
    # standard foot-contact loss of motion generation (e.g. MDM), for a metric the position
    # MSE cannot see: 1 mm per frame decides whether a planted foot "slides". Measured on the
    # fixture benchmark it does harm: a foot that never moves meets it best, and every VAE
    # trained with it (0.01 and 1e-4) parked the foot joints away from the ankles, so the foot
    # slide it "improved" was that of parked feet (docs/results.md, fifteenth run). Kept to
    # load and retrain the models made with it; new recipes leave it at 0.
    contact_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of the head-facing term, the squared error of the
    # head's horizontal facing direction (the gaze score's d_x, a unit vector). The head's
    # orientation is 12 of ~900 points' offsets of 10 cm, so a position loss leaves it loose: a
    # VAE trained without it reconstructed the gaze score with correlation 0.65 to the truth
    # (docs/models.md), and a flow cannot be steered by gaze through latents that lose it.
    head_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of the foot-lift term, the squared error of the
    # feet's heights (their icosahedra's centroids) in units of the lift the foot lock reads as
    # a step (``sampling.foot_lock.RELEASE``, 2 cm). The fixtures' feet lift 7.9 cm per step in
    # 12 % of frames; the feet are 2 of 55 joints, so a position loss leaves their timing
    # loose: every VAE the benchmark trained decoded them lifting at most 0.2 cm, gliding every
    # step, and the foot lock replaced every step with its arc. At 0.2 in the benchmark's recipe
    # the feet lift (4.7 cm per step, in 13 % of frames) and the agent walks less (pelvis 0.82x),
    # but FGD_acc rose 10 %, the legs' 15 % (docs/results.md, sixty-third run): 0 in both presets.
    lift_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of the acceleration-spectrum term, the distance
    # between the short-time spectra of the decoded and true accelerations, magnitudes only
    # (``training.objectives.AccelerationSpectrum``). Squared errors of positions, velocities or
    # accelerations are all minimised, where the latent leaves a step's or a beat's phase open,
    # by its conditional mean: no beat; a magnitude has no phase to average away, so it asks for
    # the data's energy in every band, and costs a young decoder's frame-to-frame jitter too.
    # At the fixture benchmark's CPU budget it took the jitter out and added no steps or beats
    # (docs/results.md, forty-second run): 0 in both presets.
    spectral_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of the acceleration-moment term, the relative
    # distance between the second-moment matrices of the decoded and the true accelerations of
    # the points of the joint groups ``moment_parts`` relative to the pelvis, pooled over a
    # batch's frames (``training.objectives.AccelerationMoments``): what FGD_acc compares, asked
    # of the decoder's samples as a whole rather than frame by frame. The arms and hands only:
    # the decoding draws the body's path and the feet's steps anew, and over the whole body the
    # term put their energy in the spine and arms (docs/results.md, seventy-fourth run).
    moment_weight: float = 0.0
    moment_parts: tuple[str, ...] = ("arms", "hands")
    # Not in the paper (0 = the paper, no head): weight of the stance term, the binary
    # cross-entropy of a small head that reads the latent tokens and says, per frame and per
    # foot, whether the foot is planted (``nn.stance``; the data's stance: the foot slower than
    # 0.15 m/s on the floor plane). Above 0 the VAE has the head, its gradient reaches the
    # encoder (which learns to carry the stance where the flow can generate it), and the foot
    # lock steps when the decoded stance lifts (``vae.foot_lock_reads``). The benchmark's
    # decoders never step: the lock made every step from a gliding foot's drift, half the
    # data's length and twice as many (docs/results.md, sixty-ninth and seventieth runs).
    stance_weight: float = 0.0
    # Not in the paper (0 = the paper): Gaussian noise added to the decoder's latent input in
    # training, as a fraction of the batch's per-channel latent std. The decoder then maps a
    # neighbourhood of each latent to the same motion, so a flow sample that is slightly off
    # the encoder's latents still decodes to smooth motion. With train.freeze_encoder the latent
    # space (and so a trained flow) stays valid. Less noise reconstructs the data sharper and
    # decodes flow samples jumpier; on the fixture benchmark the generated motion's FGD_acc was
    # lowest at 0.2-0.4 of 0-0.8 (docs/results.md, fifty-eighth run).
    latent_noise: float = 0.0
    # "standardized" (the paper's MSE of standardized channels) or "metres": each channel's
    # squared error weighted by its variance over the mean variance, i.e. an error in metres.
    # Standardized, a horizontal millimetre (x/z std ~1 m: the agents walk) costs ~1000x less
    # than a vertical one (y std ~3.5 cm), which leaves horizontal jitter untrained.
    recon_units: str = "standardized"
    # Not in the paper (False = the paper): standardize motion root-relative, every point's x and
    # z less the root's (``nn.normalizer``), the root's own points absolute. Absolute, a head turn
    # is a tenth of a channel's std (the agents walk ~1 m) and the encoder barely sees it. With
    # recon_units="metres" the root's points then weigh as much as all points together: their
    # error is where the whole body stands.
    root_relative: bool = False
    # Not in the paper (1 = as above): with root_relative and recon_units="metres", the root's x
    # and z count this many times once per body point. At 1 they are ~96 % of the channel
    # weights (their std is ~1.1 m, the pose's 0.14), so a short run's VAE spends its steps on
    # where the body stands, which the root hold decides again at decoding; at 0.05 (55 %) the
    # fixture benchmark's VAE reconstructed FGD_acc 646 against 862, its arms halved
    # (docs/results.md, forty-sixth run). 1 in both presets (neither is root-relative).
    root_weight: float = 1.0
    # Not in the paper (False = the paper): with root_relative, the root's own points carry how
    # far they moved on the floor since the frame before (x and z; the window's origin before its
    # first frame) instead of where they are, and decoding sums them (``nn.normalizer``). Where
    # they are is metres from the origin after a walk, and the fixture benchmark's VAE placed the
    # pelvis 23 cm off and smoothed its steps into a drift (peak 0.28 m/s where the data's step at
    # 1.56); the steps' own displacements it reconstructs as the data takes them (docs/results.md,
    # eighty-fifth run). Their channels' std is ~1 cm a frame, so ``root_weight`` weighs them up.
    root_steps: bool = False
    # Not in the paper (False = the paper): a linear code of each latent block beside the
    # transformers, fitted to the training data's principal components before the VAE trains
    # (``nn.block_code``): the untrained VAE then reconstructs what a linear code can, and
    # training learns the rest. On the fixture benchmark it reconstructed 6x closer than the
    # benchmark's VAE, but a flow trained at that budget on its detailed latents generated far
    # worse motion (docs/results.md, fifty-second run): no preset uses it.
    block_code: bool = False
    # Not in the paper (0 = the paper's deterministic decoder): a stochastic decoder. Each latent
    # token comes with this many standard normal draws that the decoder reads beside it; training
    # decodes the same latents twice with independent draws and adds to the two samples' MSE
    # terms ``energy_weight`` times the energy score of their accelerations (``nn.vae.
    # energy_score``: second differences over overlapping units of ``energy_frames`` frames, of
    # the whole body or, ``energy_per_point``, of each point alone). An MSE teaches the decoder
    # the mean of the motions a latent leaves open, which smooths away the steps and beats the
    # latent does not pin down (the benchmark VAE keeps a fifth of the data's acceleration
    # energy, docs/results.md, fifty-second run); the energy score is least when they are
    # sampled. On positions it would ask the decoder to sample its whole error, most of which a
    # short run's VAE has for want of training, not because the data leave it open. Generators
    # draw the detail per token from their own seeded stream, so streaming and offline decode
    # the same draws.
    detail_dim: int = 0
    energy_frames: int = 8
    energy_weight: float = 1.0
    energy_per_point: bool = False
    # Not in the paper (0 = the paper): how the generators decode, not how the VAE trains. At the
    # first frame of every latent block each decoded point is offset to continue its last
    # position and velocity, and the offset decays by this factor per frame, as a critically
    # damped spring (``sampling.continuity.SeamInertia``): a flow sample's tokens disagree on
    # where the body is and how it moves, and without it every block starts with a seam. The
    # fixture benchmark's recipe: 0.6, ``seam_mode="position"``, ``seam_skips_hands``,
    # ``root_inertia`` 0 (FGD_acc 0.93x on its test windows; docs/models.md, hundred-and-fifth run).
    boundary_inertia: float = 0.0
    # The same for the root's translation, which every point shares (None: boundary_inertia).
    # Not in the paper: the root's seams are jumps of the whole body, and a slower spring there
    # leaves the pose's own motion alone (docs/results.md, sixteenth run).
    root_inertia: float | None = None
    # Not in the paper: what the seam's spring continues (``sampling.continuity``).
    # "velocity" (the sixteenth run's): the last position and velocity, so every acceleration at
    # a seam is damped, real ones too; "position": the position jump alone, read against the
    # mean of the velocities on both sides of the seam, so motion without a jump passes. On the
    # fixture benchmark "position" decoded the ground truth with FGD_acc 50 against 194, and the
    # benchmark model's samples, through the whole chain, with 785 against 880 (fortieth run).
    seam_mode: str = "velocity"
    # Not in the paper (False: every point): the seam's spring leaves the hands (the fingers'
    # icosahedra and the shell points nearest them) as the decoder put them; the rigid skeleton
    # then carries each hand on its sprung wrist (``sampling.continuity``). On the fixture
    # benchmark's recipe with position springs at 0.8: FGD_acc 313 against 317 on its 166
    # training windows, 326 against 327 on the 96 tuning ones, and on its test windows 298
    # against 306, the hands' part 35 against 41 (hundred-and-fifth run).
    seam_skips_hands: bool = False
    # Not in the paper (False = the paper): decode onto a rigid skeleton, every bone at the
    # training data's length along its decoded direction (``sampling.rigid_skeleton``); the
    # decoder alone stretches bones by ~30 % (docs/results.md, seventeenth run).
    rigid_bones: bool = False
    # Not in the paper: with ``rigid_bones``, the head, the jaw and the eyes placed along the
    # direction their parent's decoded rotation gives their bone, not along the decoded one
    # (``sampling.rigid_skeleton.SKULL``): decoded, these 3-12 cm bones pointed 65-90 degrees
    # off on the demo's clip, the head jutting from the neck and the eyes around the head
    # (docs/results.md, ninety-ninth run). False: every bone along its decoded direction, as
    # until then.
    rigid_skull: bool = True
    # Not in the paper: with ``rigid_bones``, the hips placed with the pelvis as one piece and each
    # leg moved with its hip (``sampling.rigid_skeleton.HIPS``), not each hip along its decoded
    # direction: decoded, the two came within centimetres of each other and the knees crossed
    # (docs/models.md; docs/results.md, hundred-and-first run). False: as until then.
    rigid_hips: bool = True
    # Not in the paper: with ``rigid_bones``, the collars placed with the chest as one piece, each
    # arm with its collar (``sampling.rigid_skeleton.COLLARS``), as the hips with the pelvis:
    # decoded each along its own direction they folded as the hips did (docs/models.md;
    # docs/results.md, hundred-and-second run). False: as until then.
    rigid_collars: bool = True
    # Not in the paper: with ``rigid_bones``, each hand's five knuckles placed with its wrist as one
    # piece, each finger with its knuckle (``sampling.rigid_skeleton.HANDS``): decoded each along
    # its own direction, the palm narrowed and widened (docs/models.md; docs/results.md,
    # hundred-and-second run). False: as until then.
    rigid_hands: bool = True
    # Not in the paper (0 = off): lock planted feet, stepping when the decoded foot has moved
    # this many metres away (``sampling.foot_lock``); decoded feet glide and jitter.
    foot_lock: float = 0.0
    # Not in the paper: frames a locked foot's arc step (``foot_step="arc"``) takes from lift-off
    # to landing, and the longest a foot the decoder lifts is followed (``sampling.foot_lock``).
    # 12 (0.4 s, as people walk) is the slowest of the fixtures' steps; theirs take 6-7 frames,
    # but a body that walks twice their path needs slower steps to keep its leg energy near
    # theirs (docs/results.md, twenty-sixth and forty-second runs). Again on
    # the benchmark's model (sixty-eighth run): 6 frames instead of its 8 take its VAE's
    # reconstruction of the data 1.36x nearer in FGD_acc, and the model, which steps where the
    # data stands, 2x further.
    foot_swing_frames: int = 12
    # Not in the paper: what makes a locked foot step (``sampling.foot_lock``). "drift": the
    # decoded foot moving ``foot_lock`` metres from where it is planted; "stance": the VAE's
    # stance head saying it lifts (``vae.stance_weight`` > 0), along the data's own step, and
    # drift only past ``stance_reach``.
    foot_lock_reads: str = "drift"
    # Not in the paper: metres a decoded foot drifts from where its stance keeps it planted
    # before it steps anyway (``foot_lock_reads="stance"``; a flow's body can walk on where its
    # stance stands). On the 314 tuning windows the benchmark's model gave FGD_acc 532 at 0.2 m
    # and 561 at 0.3 with arc steps; without such steps (the 296 test windows) its FGD_local rose
    # from 494 to 7,883, legs stretched to planted feet (seventieth run). With the data's step
    # profile, on 96 tuning windows: 442 at 0.12 m, 380 at 0.2, 415 at 0.3 (seventy-first run).
    # With ``root_hold`` 0.7 instead of 0.2, 0.3 m comes nearest (FGD_acc 1.07x on 296 test
    # windows), the body held where it stands facing its user more than the data's people do
    # (seventy-sixth run).
    stance_reach: float = 0.2
    # Not in the paper: how a locked foot steps where the decoded foot drifts away from it
    # (``sampling.foot_lock``). "data": as the data's people step (5 frames along their step's
    # profile, as where a decoded stance lifts); "arc": over ``foot_swing_frames`` frames along a
    # smoothstep arc, leading the body (the lock's only step until the seventy-first run). On the
    # fixture benchmark's 96 tuning windows "data" took the shipped model's streamed FGD_acc from
    # 1,121 to 823 and the benchmark recipe's model's from 516 to 380 (docs/results.md).
    foot_step: str = "data"
    # Not in the paper (0 = off): metres along the hips' line that a held foot keeps from the
    # other foot (``sampling.foot_lock``): nearer, it steps toward its decoded place where that is
    # wider. The data's ankles come nearer along that line in 0.1 % of frames (13.1 cm; min 8.2,
    # never crossed; 93,113 frames of the fixture benchmark's training corpus); held until the
    # decoded foot drifted ``stance_reach`` away, the recipe model's came within 10 cm in 2.8 % of
    # frames and crossed in 3.0 %, with 0.13 m in 0.7 % and 0.4 %, its pose (FGD_local) 0.93x
    # nearer the data (docs/results.md, hundred-and-second and hundred-and-third runs).
    foot_gap: float = 0.13
    # Not in the paper (0 = off): metres on the floor that a held foot's ankle may stand from
    # under its hip before it steps to its decoded place, where that stands nearer under the hip
    # and the other foot is planted (``sampling.foot_lock``): held until the decoded foot drifted
    # ``stance_reach`` away while the pelvis moved on, the recipe model's ankles stood 5.7 cm from
    # under their hips (each window's median; 16.8 at the 90th percentile) where the data's stand
    # 1.9 (10.2) and the decoder's own 2.9 (4.5). Measured and not chosen: at 0.2 / 0.15 / 0.1 /
    # 0.08 m the ankles come to 5.3 / 4.9 / 4.2 / 3.9 cm, the feet step 24.7 / 26.2 / 29.9 / 32.4
    # times a window (the data's 18.6, the lock's 23.5) and FGD_acc rises to 382 / 393 / 402 / 414
    # against 374 (96 tuning windows; docs/results.md, hundred-and-fifth run): the body, not the
    # feet, is what moves where the data's people stand. 0 in both presets.
    foot_lean: float = 0.0
    # Not in the paper (0 = off): metres by which the body stands higher on its legs than the
    # decoder puts it, the feet where the decoder put them (``sampling.rigid_skeleton``, with
    # ``rigid_bones``). A decoder stands lower than the data's people (the fixture benchmark's
    # recipe model: its hips 0.4 cm lower, its ankles 1.6 cm higher), and its legs, at the
    # data's lengths, bend: knees at 155 degrees where the data's stand at 166 (each window's
    # median). A constant, since a lift that changes accelerates the whole body (a running one:
    # FGD_acc 437 against 321), and with ``leg_softness``: alone, 0.7 cm left the left knee
    # straighter than the data's 99.9th percentile in 24 % of frames (the lock's held feet out of
    # reach; 13 % before) and FGD_acc at 354, 1 cm at 398. 0.01 with
    # ``leg_softness`` 0.01 in the benchmark's recipe: knees 161 degrees, the pose 0.97x nearer the
    # data, FGD_acc as it was (docs/results.md, hundred-and-fourth run); 0 in both presets.
    stand_lift: float = 0.0
    # Not in the paper (0 = off): metres over which the legs' reach eases toward their full
    # length (``two_bone_ik.soft_reach``; the rigid skeleton's and the foot lock's legs), as game
    # engines' "soft IK" does. Reaching all the way, a knee snaps straight when its foot's target
    # passes the leg's length (the foot lock holds feet the body moves away from) and bends
    # again a frame later. Alone it leaves the benchmark's recipe as it was (FGD_acc 324 against
    # 321 on the test windows, 362 against 383 on the tuning ones); beside ``stand_lift`` it is
    # what lets the body stand up (docs/results.md, hundred-and-fourth run). 0 in both presets.
    leg_softness: float = 0.0
    # Not in the paper (0 = off): the body holds its place on the floor until the decoded pelvis
    # has moved this many metres away, then follows, no faster than the data's people walk
    # (``sampling.root_hold``); the decoded pelvis wanders where people stand.
    root_hold: float = 0.0
    # Not in the paper: what the hold holds (``sampling.root_hold``). "pelvis": where the decoded
    # pelvis goes; "feet": only how far the whole body glides, the standing foot's own moves; the
    # body's moves over its standing foot pass as decoded, so real walking is not held back.
    root_hold_reads: str = "pelvis"
    # Not in the paper (0 = off): the share of the change in the body's bearing to its user that
    # the hold turns the held body by, so that it faces its user as the decoded body, where it
    # walked, does (``sampling.root_hold``). A body held in place and never turned faces its user
    # more than the data's people do (seventy-sixth run: head angle +0.11 over the data's).
    root_hold_turn: float = 0.0
    # Not in the paper (0 = off): a causal second-order low-pass of this cutoff (Hz) on the arms'
    # and hands' motion relative to the pelvis (``sampling.limb_lowpass``): the decoder's arms
    # jitter above 6 Hz, where the data's arms have a tenth of their acceleration power, and the
    # seam spring damps their beats too. On the fixture benchmark's pick at 8 Hz it took the arms'
    # FGD_acc from 51 to 41 and raised the hands' from 49 to 64, the whole shell's unchanged (594,
    # 589; docs/results.md, fifty-sixth run): 0 in both presets.
    limb_lowpass: float = 0.0

    def __post_init__(self) -> None:
        for name in ("boundary_inertia", "root_inertia"):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value < 1.0:
                raise ValueError(f"VAEConfig.{name} must be in [0, 1), got {value}")
        if self.foot_swing_frames < MIN_SWING_FRAMES:
            raise ValueError(f"VAEConfig.foot_swing_frames must be >= {MIN_SWING_FRAMES} (a step "
                             f"lifts, travels and lands), got {self.foot_swing_frames}")
        for name in ("foot_lock", "root_hold"):
            if getattr(self, name) < 0:
                raise ValueError(f"VAEConfig.{name} (metres) must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.limb_lowpass < FPS / 2:
            raise ValueError(f"VAEConfig.limb_lowpass (Hz) must be 0 (off) or below the Nyquist "
                             f"frequency {FPS / 2:g}, got {self.limb_lowpass}")
        if not 0 <= self.root_hold_turn <= 1:
            raise ValueError(f"VAEConfig.root_hold_turn must be in [0, 1] (a share of the bearing's "
                             f"change), got {self.root_hold_turn}")
        if self.root_hold_turn and not self.root_hold:
            raise ValueError("VAEConfig.root_hold_turn turns the held body, and vae.root_hold is 0 "
                             "(off): set vae.root_hold too")
        if self.root_hold_reads not in HOLD_READS:
            raise ValueError(f"VAEConfig.root_hold_reads must be one of {HOLD_READS}, got "
                             f"{self.root_hold_reads!r}")
        if self.foot_step not in FOOT_STEPS:
            raise ValueError(f"VAEConfig.foot_step must be one of {FOOT_STEPS}, got "
                             f"{self.foot_step!r}")
        if self.foot_lock_reads not in LOCK_READS:
            raise ValueError(f"VAEConfig.foot_lock_reads must be one of {LOCK_READS}, got "
                             f"{self.foot_lock_reads!r}")
        if not self.foot_gap >= 0:
            raise ValueError(f"VAEConfig.foot_gap (metres) must be >= 0 (0: off), got {self.foot_gap}")
        if not self.foot_lean >= 0:
            raise ValueError(f"VAEConfig.foot_lean (metres) must be >= 0 (0: off), got {self.foot_lean}")
        if not self.stance_reach > 0:
            raise ValueError(f"VAEConfig.stance_reach must be > 0, got {self.stance_reach}")
        if not self.leg_softness >= 0:
            raise ValueError(f"VAEConfig.leg_softness (metres) must be >= 0 (0: off), got "
                             f"{self.leg_softness}")
        if not math.isfinite(self.stand_lift):
            raise ValueError(f"VAEConfig.stand_lift (metres) must be finite, got {self.stand_lift}")
        if self.stand_lift and not self.rigid_bones:
            raise ValueError("VAEConfig.stand_lift raises the body on the rigid skeleton's legs: "
                             "set vae.rigid_bones too")
        if self.foot_lock_reads == "stance" and not self.stance_weight > 0:
            raise ValueError(f"VAEConfig.foot_lock_reads='stance' {NEEDS_STANCE_HEAD}")
        if not self.stance_weight >= 0:
            raise ValueError(f"VAEConfig.stance_weight must be >= 0, got {self.stance_weight}")
        if self.seam_mode not in SEAM_MODES:
            raise ValueError(f"VAEConfig.seam_mode must be one of {SEAM_MODES}, got "
                             f"{self.seam_mode!r}")
        if not self.root_weight > 0:
            raise ValueError(f"VAEConfig.root_weight must be > 0 (the root's place is trained), "
                             f"got {self.root_weight}")
        if self.root_steps and not self.root_relative:
            raise ValueError("VAEConfig.root_steps makes the root's points steps of root-relative "
                             "motion: set vae.root_relative too")
        if self.recon_units not in RECON_UNITS:
            raise ValueError(f"VAEConfig.recon_units must be one of {RECON_UNITS}, got "
                             f"{self.recon_units!r}")
        if self.detail_dim < 0:
            raise ValueError(f"VAEConfig.detail_dim must be >= 0 (0: a deterministic decoder), "
                             f"got {self.detail_dim}")
        for name in ("energy_weight", "spectral_weight", "moment_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"VAEConfig.{name} must be >= 0, got {getattr(self, name)}")
        unknown = [part for part in self.moment_parts if part not in JOINT_GROUPS]
        if unknown or not self.moment_parts:
            raise ValueError(f"VAEConfig.moment_parts must name joint groups of "
                             f"{tuple(JOINT_GROUPS)}, got {self.moment_parts}")
        if self.energy_frames < 3:
            raise ValueError(f"VAEConfig.energy_frames must be >= 3 (a unit of the energy score "
                             f"holds the second differences of its frames), got {self.energy_frames}")

    @classmethod
    def paper(cls) -> "VAEConfig":
        return cls()

    @classmethod
    def tiny(cls) -> "VAEConfig":
        # A latent of 128 reconstructs the fixture benchmark's arms and hands no nearer (their
        # gestures smoothed alike; docs/results.md, eighty-eighth run), so 64 stays.
        return cls(latent_dim=64, hidden=128, heads=4, encoder_layers=2, decoder_layers=2,
                   velocity_weight=VELOCITY_WEIGHT_TINY)


@dataclass(frozen=True)
class FlowConfig:
    """Causal flow matcher over latent blocks (paper 3.3, 3.4 and 4)."""

    hidden: int = 1024
    heads: int = 4
    layers: int = 4
    mlp_ratio: float = 4.0
    cond_dim: int = 256  # width of each modality's encoding before the input projection
    time_dim: int = 256  # sinusoidal embedding width of the flow time tau
    drop_prob: float = 0.05  # CFG: each modality dropped independently per sample
    # Not in the paper (None = drop_prob, the paper): the gaze score's own drop rate. With g = none
    # the flow samples from what it learned on the windows whose gaze was dropped, 5 % of them.
    # On the fixture benchmark more of them did not undo what a longer-trained flow does there
    # (faces the user in nearly every window): at 0.2 and 0.5 it faced the user more still, and
    # the agent that should stand walked less (docs/results.md, forty-eighth run); no preset uses it.
    gaze_drop_prob: float | None = None
    min_denominator: float = 0.05  # velocity = (z1 - z_tau) / max(1 - tau, this)
    # Not in the paper (None = the paper's tau ~ U[0, 1]): training draws tau = sigmoid(n) with
    # n ~ N(time_logit_mean, time_logit_std), the logit-normal of Esser et al. 2024 (SD3).
    # Eq. 5's loss on the clean latents weighs the velocity's error by (1 - tau)^2, so near the
    # data, where the solver's last steps set the fine motion, U[0, 1] trains little; a
    # positive mean draws more of the batch there (``training.objectives.training_times``). On the
    # fixture benchmark no mean or std tried came nearer the data than U[0, 1] (docs/models.md,
    # docs/results.md, ninety-fifth run); no preset uses it.
    time_logit_mean: float | None = None
    time_logit_std: float = 1.0
    rope_base: float = 10_000.0
    # A learned embedding of each token's index in the stream (the paper's learned positional
    # encoding): RoPE is relative only, so without it the first token (the agent at the window
    # origin) looks like any other. Indices past ``position_tokens`` share the last embedding,
    # so streams far longer than a training window see what offline generation sees.
    position_embedding: bool = True
    position_tokens: int = WINDOW // STRIDE  # T / s: the tokens of one training window
    # Not in the paper (None = the paper: every token attends to all earlier ones). Streaming
    # keeps HISTORY_TOKENS latents beside the new one (A.3), so a streamed token sees 3 tokens
    # while full-context training showed it up to T / s. A window of STREAMED_TOKENS per
    # layer brings training close to what streaming sees (the receptive field of stacked
    # windows is layers * 2 + 1 tokens). On the fixture benchmark (docs/results.md, ninth run)
    # it cut the streamed FGD_acc 4x at equal budget, so the tiny preset uses it. Its price is
    # offline: tokens further apart than the receptive field cannot agree on where the body
    # stands, and the joint solve wanders (twenty-seventh run; a longer window, streamed with
    # the matching history, damps the streamed motion instead). On the fixtures, whose agents
    # stand or walk for a whole sequence, it is also where the agent goes: with full context
    # the pelvis moves at 1.22x the data's speed over floor positions near the data's (at a
    # cost in FGD_acc and head angle), with windows of 3 or 9 at 2.1x and 1.5x, walking to the
    # user (forty-first run).
    attention_window: int | None = None
    # Not in the paper (0 = the paper): the share of training batches whose attention is limited
    # to what a streamed token sees, STREAMED_TOKENS per layer, the rest trained with
    # ``attention_window`` (None: full context), so that one model sees both contexts. Measured
    # as fine-tunes of the shipped model (shares 0.5, 0.9; docs/results.md, twenty-eighth run):
    # the offline solve stops wandering, but the 2-token stream starts; not used by any preset.
    streamed_context: float = 0.0
    # Not in the paper (0 = the paper): weight of the MSE between the predicted and the true
    # latents' token-to-token differences, beside eq. 5's MSE of the latents. Its minimum is the
    # same conditional mean, so it changes no target, only which errors cost most: sampled
    # latents change ~2x as much from one token to the next as the encoder's (docs/results.md,
    # twentieth run), and that jitter is what a position error barely sees.
    difference_weight: float = 0.0
    # Not in the paper (0 = the paper): weight of a stance term on the flow's prediction of the
    # clean latents, the binary cross-entropy of the VAE's stance head (``vae.stance_weight``)
    # reading them against the data's stance, weighted by the flow time tau (near the noise the
    # prediction cannot know it). The recipe's flow samples latents from which the head lifts a
    # foot 8 times a window where the data's feet step 19 times, and two of its steps in three
    # are the foot lock's drift steps (docs/results.md, seventy-fifth run). At weight 1 the head
    # lifts 17 times a window and the legs' FGD_acc comes 1.09x nearer, the head facing the
    # user 0.07 more than the data's (seventy-sixth run): no recipe uses it.
    stance_weight: float = 0.0
    # Not in the paper (False = the paper): the user's head velocity inside each block (the
    # differences of its s positions, in standardized units per second) beside the positions the
    # user_head encoder reads. It is a linear function of those positions, so it adds no
    # information; it adds scale: a walking user's head moves ~0.03 standardized units a frame,
    # a difference the encoder's first Linear has to learn to amplify ~30x before it can tell a
    # walking user from a standing one (docs/results.md, forty-first run).
    head_velocity: bool = False
    # Not in the paper (None = the paper): the user's mean head speed over about this many
    # seconds (``nn/head_travel.py``) beside each frame's head position. Which partner walks
    # and which turns in place holds for a sequence; a flow whose attention reaches a few
    # seconds cannot tell, and walks where the user walks (the forty-first and forty-seventh
    # runs). A running mean carries it at a constant cost, streamed exactly as offline. On the
    # fixtures it tells the roles apart but the agent walks as much; on root-step latents
    # (``vae.root_steps``) the walking agent walks the data's path and FGD_acc rises from 353 to
    # 391-898 (docs/results.md, eighty-seventh run); no preset uses it.
    head_travel_seconds: float | None = None
    # Not in the paper (False = the paper): the user's head as seen from where the agent stands,
    # its floor (x, z) less the agent's pelvis at the end of the previous block, in metres
    # (``nn/user_offset.py``), beside the window-frame position the user_head encoder reads.
    # Where the agent stands now is only in its latents, so a walking agent cannot tell which way
    # goes around its user; on the fixtures it walked as much toward the user as around them
    # (data: 0.17 (0.16-0.19) against 0.97 (0.96-0.97) m/s, 148 windows; forty-ninth run).
    # Generation then decodes block by block, offline too, since each block reads where the
    # decoded agent stands. On the fixtures the
    # training loss fell by a quarter, but the agent walks away from its user (User Dist. +118
    # (110-126) cm at the benchmark's pick, 296 test windows): reading its own place closes a
    # loop training never showed it (docs/results.md, fiftieth run). On root-step latents
    # (``vae.root_steps``), which hold no place, it walked to and from its user at 5.7x the
    # data's radial speed (eighty-sixth run); no preset uses it.
    user_relative: bool = False
    # With user_relative: the std in metres of the noise training adds to where the data's agent
    # stands before each block but the first (0 = none). A stream reads its own decoded pelvis,
    # which is not the data's; a flow that reads the data's exactly leans on it.
    place_noise: float = 0.0
    # With user_relative: False drops the window-frame position from what the user_head encoder
    # reads, leaving the offset (and the within-block velocity, ``head_velocity``): the place
    # the offset was taken from can then not be worked out from the two, and the flow has to
    # take where its agent stands from its own latents, the offset only for where the user is.
    # On the fixtures its walking agent goes around the user (pooled FGD offline 29,829
    # (9,244-50,413) against the benchmark pick's 173,041, 296 test windows) but walks 2.66x
    # (2.41-2.93) the data's pelvis speed at the pick (fiftieth run); no preset uses it.
    user_absolute: bool = True

    def __post_init__(self) -> None:
        if self.head_travel_seconds is not None and not self.head_travel_seconds > 0:
            raise ValueError(f"FlowConfig.head_travel_seconds must be > 0 or None, got "
                             f"{self.head_travel_seconds}")
        for name in ("drop_prob", "gaze_drop_prob"):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise ValueError(f"FlowConfig.{name} must be in [0, 1], got {value}")
        if not self.user_absolute and not self.user_relative:
            raise ValueError("FlowConfig.user_absolute=False leaves the user_head encoder "
                             "nothing to read without user_relative=True")
        if self.place_noise < 0:
            raise ValueError(f"FlowConfig.place_noise must be >= 0, got {self.place_noise}")
        if not self.stance_weight >= 0:
            raise ValueError(f"FlowConfig.stance_weight must be >= 0, got {self.stance_weight}")
        if self.time_logit_mean is not None and not math.isfinite(self.time_logit_mean):
            raise ValueError(f"FlowConfig.time_logit_mean must be finite or None, got "
                             f"{self.time_logit_mean}")
        if not (math.isfinite(self.time_logit_std) and self.time_logit_std > 0):
            raise ValueError(f"FlowConfig.time_logit_std must be finite and > 0, got "
                             f"{self.time_logit_std}")
        if self.difference_weight < 0:
            raise ValueError(f"FlowConfig.difference_weight must be >= 0, got "
                             f"{self.difference_weight}")
        if not 0.0 <= self.streamed_context <= 1.0:
            raise ValueError(f"FlowConfig.streamed_context must be in [0, 1], got "
                             f"{self.streamed_context}")
        if self.attention_window is not None and self.attention_window < 1:
            raise ValueError(f"FlowConfig.attention_window must be >= 1 or None, got "
                             f"{self.attention_window}")

    @classmethod
    def paper(cls) -> "FlowConfig":
        return cls()

    @classmethod
    def tiny(cls) -> "FlowConfig":
        return cls(hidden=128, heads=4, layers=2, cond_dim=64, time_dim=64,
                   position_tokens=TINY_WINDOW // STRIDE, attention_window=STREAMED_TOKENS)


# Config fields that change how a model decodes, not its weights: a model file may be written
# again with other values, nothing trained (``sarah-train --stage model``), and a fine-tune may
# change them.
DECODING_FIELDS = {"vae": ("boundary_inertia", "root_inertia", "seam_mode", "seam_skips_hands",
                           "rigid_bones", "rigid_skull",
                           "rigid_hips", "rigid_collars", "rigid_hands",
                           "foot_lock", "foot_swing_frames", "foot_lock_reads", "stance_reach",
                           "foot_step", "foot_gap", "foot_lean", "stand_lift", "leg_softness",
                           "root_hold", "root_hold_reads", "root_hold_turn", "limb_lowpass")}


def decoding_settings() -> list[str]:
    """DECODING_FIELDS as ``section.field`` names, for messages and --help."""
    return [f"{section}.{name}" for section, names in DECODING_FIELDS.items() for name in names]


LR_SCHEDULES = ("constant", "linear", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and data settings (paper A.2: AdamW, 1k warmup to 1e-4, 200k + 300k steps)."""

    window: int = WINDOW  # T frames per training window (K = window / stride tokens)
    batch_size: int = 16  # per process; the paper uses 16 on each of 8 GPUs
    lr: float = 1e-4
    warmup_steps: int = 1_000
    # After warmup: "constant" (the paper), or "linear"/"cosine" decay to lr * final_lr_ratio at
    # the stage's last step. Useful for short runs and fine-tunes (--init-from).
    lr_schedule: str = "constant"
    final_lr_ratio: float = 0.0
    adam_betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 1e-4
    grad_clip: float = 0.0  # 0 disables (the paper states none)
    # VAE stage: train the decoder only (encoder weights, and so its latents, stay fixed).
    freeze_encoder: bool = False
    vae_steps: int = 200_000
    flow_steps: int = 300_000
    # Not in the paper (0 = the paper): the VAE stage's first `vae_short_steps` steps train on
    # windows of `vae_short_window` frames, the rest on `window`. Short windows cost a fraction
    # per step (attention grows with the square of the length), but a causal VAE trained only on
    # them loses the agent's place past their length; the last steps on `window` teach it
    # (docs/models.md; docs/results.md, eleventh run).
    vae_short_steps: int = 0
    vae_short_window: int = 100
    latent: str = "mean"  # flow target from the frozen encoder: "mean" (mu) or "sample"
    # Not in the paper (1 = the paper): the flow stage encodes each batch with the frozen VAE
    # once and takes `flow_echo` optimizer steps on it, each with its own flow times, noise and
    # condition dropout ("data echoing", Choi et al. 2019). On a CPU the encoder is most of a
    # flow step; what echo buys is measured in docs/models.md ("Flow echo").
    flow_echo: int = 1
    latent_stats_batches: int = 64  # batches used to standardize latents before the flow stage
    log_every: int = 50
    checkpoint_every: int = 5_000
    num_workers: int = 2  # WindowLoader worker processes filling reused batch slots (0: this process)
    # torch.compile the training step's model (not in the paper; off: the first steps wait for
    # the compiler). On the 2-core AMD EPYC (tiny preset, 8 windows, 2026-11-27): the flow
    # step 0.23 -> 0.15 s and the VAE's 400-frame step 1.47 -> 0.73 s, its 100-frame step
    # 0.21 -> 0.18 s, each after ~65 s of compiling (docs/performance.md).
    compile: bool = False
    # Not in the paper (0 = off, the paper): sample with an exponential moving average of the
    # stage's weights, this decay per step after a warm-up (``training.weight_average``; DiT's
    # 0.9999 is for 400k steps, a few thousand want ~0.999). Training itself is unchanged.
    ema_decay: float = 0.0
    seed: int = 0
    split: str = "train"
    audio_features: str = "hubert-large"  # extractor name in the shards (paper: HuBERT-Large)

    def __post_init__(self) -> None:
        if self.latent not in ("mean", "sample"):
            raise ValueError(f"TrainConfig.latent must be 'mean' or 'sample', got {self.latent!r}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"TrainConfig.lr_schedule must be one of {LR_SCHEDULES}, "
                             f"got {self.lr_schedule!r}")
        if not 0.0 <= self.final_lr_ratio <= 1.0:
            raise ValueError(f"TrainConfig.final_lr_ratio must be in [0, 1], got {self.final_lr_ratio}")
        for name in ("batch_size", "vae_steps", "flow_steps", "window", "log_every",
                     "checkpoint_every", "latent_stats_batches", "vae_short_window", "flow_echo"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.num_workers < 0 or self.warmup_steps < 0 or self.seed < 0 or self.vae_short_steps < 0:
            raise ValueError("TrainConfig.num_workers, warmup_steps, seed and vae_short_steps must be >= 0, "
                             f"got {self.num_workers}, {self.warmup_steps}, {self.seed}, {self.vae_short_steps}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay must be 0 (off) or in (0, 1), got {self.ema_decay}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"TrainConfig.lr must be a positive number, got {self.lr}")

    @classmethod
    def paper(cls) -> "TrainConfig":
        return cls()

    @classmethod
    def tiny(cls) -> "TrainConfig":
        return cls(window=TINY_WINDOW, batch_size=8, lr=3e-4, warmup_steps=50, vae_steps=400,
                   flow_steps=400, latent_stats_batches=8, log_every=10, checkpoint_every=100,
                   num_workers=0, audio_features="logmel")


PRESETS = ("paper", "tiny")


@dataclass(frozen=True)
class RunConfig:
    """The three configs of one training run, saved together in every checkpoint."""

    vae: VAEConfig = field(default_factory=VAEConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        # Checked here, before a run trains its VAE: the flow's term reads the VAE's head
        if self.flow.stance_weight > 0 and not self.vae.stance_weight > 0:
            raise ValueError(f"flow.stance_weight {NEEDS_STANCE_HEAD}")

    @classmethod
    def preset(cls, name: str) -> "RunConfig":
        if name not in PRESETS:
            raise ValueError(f"unknown config preset {name!r}; choose from {PRESETS}")
        return cls(getattr(VAEConfig, name)(), getattr(FlowConfig, name)(),
                   getattr(TrainConfig, name)())

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {"vae": asdict(self.vae), "flow": asdict(self.flow), "train": asdict(self.train)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Mapping[str, Any]]) -> "RunConfig":
        flow = dict(data["flow"])
        # Runs saved before the position embedding existed were trained without one.
        flow.setdefault("position_embedding", False)
        return cls(from_dict(VAEConfig, data["vae"]), from_dict(FlowConfig, flow),
                   from_dict(TrainConfig, data["train"]))

    def target_of(self, text: str) -> tuple[str, str]:
        """The (section, field) a ``section.field=value`` (or unique ``field=value``) names."""
        sections = {"vae": self.vae, "flow": self.flow, "train": self.train}
        key, sep, _ = text.partition("=")
        if not sep:
            raise ValueError(f"--set expects field=value, got {text!r}")
        key = key.strip()
        if "." in key:
            section, name = key.split(".", 1)
            if section not in sections:
                raise ValueError(f"--set {text!r}: unknown section {section!r}; use vae/flow/train")
        else:
            owners = [s for s, c in sections.items() if name_in(c, key)]
            if len(owners) != 1:
                raise ValueError(f"--set {text!r}: field {key!r} is "
                                 f"{'ambiguous' if owners else 'unknown'}; write section.field")
            section, name = owners[0], key
        if not name_in(sections[section], name):
            raise ValueError(f"--set {text!r}: {section} has no field {name!r}")
        return section, name

    def with_overrides(self, assignments: Sequence[str]) -> "RunConfig":
        """Apply ``section.field=value`` (or ``field=value`` when the name is unique) strings."""
        sections = {"vae": self.vae, "flow": self.flow, "train": self.train}
        changes: dict[str, dict[str, Any]] = {name: {} for name in sections}
        for text in assignments:
            section, name = self.target_of(text)
            current = sections[section]
            changes[section][name] = _parse_value(getattr(current, name),
                                                  text.partition("=")[2].strip(), text,
                                                  scalar_type(type(current), name))
        # One replace per section: its checks see every setting at once, so settings that only
        # hold together (vae.root_hold=0 with vae.root_hold_turn=0) pass in either order.
        for section, values in changes.items():
            if values:
                sections[section] = dataclasses.replace(sections[section], **values)
        assigned = {(section, name) for section, values in changes.items() for name in values}
        # The position embedding spans one training window: a new window (or stride) moves it,
        # unless flow.position_tokens was set too.
        if ({("train", "window"), ("vae", "stride")} & assigned) and ("flow", "position_tokens") not in assigned:
            sections["flow"] = dataclasses.replace(
                sections["flow"], position_tokens=max(1, sections["train"].window // sections["vae"].stride))
        return RunConfig(**sections)  # type: ignore[arg-type]


def preset_values() -> list[str]:
    """Every RunConfig field as ``section.field=value`` the way ``--set`` reads it, the paper
    preset's value first and the tiny preset's after a ``|`` where they differ (for --help)."""
    paper, tiny = (RunConfig.preset(name).to_dict() for name in ("paper", "tiny"))
    values = []
    for section, names in paper.items():
        for name, value in names.items():
            text, small = set_text(value), set_text(tiny[section][name])
            values.append(f"{section}.{name}={text}" + ("" if small == text else f"|{small}"))
    return values


def name_in(config: Any, name: str) -> bool:
    return any(f.name == name for f in fields(config))


def set_text(value: Any) -> str:
    """A config value as ``--set`` writes it, so that ``_parse_value`` reads it back."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return ",".join(set_text(item) for item in value)
    return str(value)


def scalar_type(cls: type, name: str) -> type | None:
    """The one scalar type field ``name`` of dataclass ``cls`` holds besides None (``float |
    None`` -> float), else None. ``--set`` parses by it rather than by the value the field holds:
    an optional float left at None and set to 0 was read as the int 0, which then refused 0.9
    (a model file written with ``--set vae.root_inertia=0`` refused ``--decoding-from``)."""
    hint = typing.get_type_hints(cls)[name]
    kinds = [kind for kind in (typing.get_args(hint) or (hint,)) if kind is not type(None)]
    return kinds[0] if len(kinds) == 1 and kinds[0] in (bool, int, float, str) else None


def _parse_value(current: Any, raw: str, text: str, declared: type | None) -> Any:
    """``raw`` as the field holding ``current`` takes it: by ``declared`` (``scalar_type``), else
    by the value held (a tuple: its items' type)."""
    kind = declared or (None if current is None else type(current))
    try:
        if raw.lower() == "none":
            return None
        if kind is bool:
            if raw.lower() not in ("true", "false", "1", "0"):
                raise ValueError(raw)
            return raw.lower() in ("true", "1")
        if kind is int:
            return int(raw)
        if kind is float:
            return float(raw)
        if isinstance(current, tuple):
            return tuple(type(current[0])(p) for p in raw.strip("()").split(","))
        if kind is None:  # a field of no one scalar type, left at None: a number if it reads as one
            for number in (int, float):
                try:
                    return number(raw)
                except ValueError:
                    pass
        return raw
    except ValueError as exc:
        raise ValueError(f"--set {text!r}: cannot parse {raw!r} as "
                         f"{(kind or type(current)).__name__}") from exc


@dataclass(frozen=True)
class StreamConfig:
    """Inference settings; defaults are the paper's (A.3 and Tab. 2)."""

    # Latents kept as history: a number, None (never drop any) or HISTORY_WINDOW: what one layer
    # of the flow attends to beside the new token, so a flow trained with a window of 17 tokens
    # streams with 16 (with 2 it wanders; docs/results.md, forty-ninth run) and the paper's
    # (no window) and the tiny preset's (a window of 3) with the paper's 2.
    history_tokens: int | str | None = HISTORY_WINDOW
    # "final" (the paper) or "trajectory" (the stream equals offline generation), IMPUTATIONS
    imputation: str = "final"
    steps: int = SOLVER_STEPS  # solver steps (midpoint: 2 network evaluations each)
    solver: str = SOLVER
    cfg_scale: float = CFG_SCALE  # w in x1 = x1_u + w (x1_c - x1_u)
    noise_scale: float = NOISE_SCALE  # each token's eps ~ N(0, noise_scale^2 I)
    gaze: float | None = 0.8  # target gaze score on every frame; None drops g
    # Modalities dropped in the unconditional pass: all of them (the paper's w = 1.3 guides the
    # conditioning as a whole; guiding the gaze alone was a no-op for g = None), or ("gaze",)
    # to guide gaze control only.
    guide: tuple[str, ...] = ("user_head", "agent_audio", "user_audio", "gaze")
    # Not in the paper ((0, 1) = the paper: every evaluation guided): the flow times tau (0 noise,
    # 1 data) at which guidance applies, lo <= tau < hi; the other evaluations take the
    # conditional prediction alone (Kynkäänniemi et al. 2024, "Applying guidance in a limited
    # interval"): what a sample becomes is settled at different times for different traits.
    guidance_interval: tuple[float, float] = (0.0, 1.0)
    seed: int = 0
    # The VAE decoder's attention context in frames (T: one training window), whatever the
    # stride; None: unbounded. Counted in blocks it saw 200 frames at stride 2, and a stream of
    # 400 frames parted from the offline decode by 1-2 % (docs/results.md, forty-fourth run).
    decoder_frames: int | None = WINDOW

    def __post_init__(self) -> None:
        from .nn.flow import MODALITIES

        check_history(self.history_tokens)
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; choose from {', '.join(SOLVERS)}")
        if self.imputation not in IMPUTATIONS:
            raise ValueError(f"unknown imputation {self.imputation!r}; choose from "
                             f"{', '.join(IMPUTATIONS)}")
        if not math.isfinite(self.cfg_scale):
            raise ValueError(f"cfg_scale must be finite, got {self.cfg_scale}")
        check_noise_scale(self.noise_scale)
        check_gaze(self.gaze)
        lo, hi = self.guidance_interval
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError(f"guidance_interval must be (lo, hi) with 0 <= lo < hi <= 1, got "
                             f"{self.guidance_interval}")
        unknown = [m for m in self.guide if m not in MODALITIES]
        if unknown:
            raise ValueError(f"guide names unknown modalities {unknown}; choose from {MODALITIES}")
        if self.decoder_frames is not None and self.decoder_frames < 1:
            raise ValueError(f"decoder_frames must be >= 1 or None, got {self.decoder_frames}")

    def decoder_blocks(self, stride: int) -> int | None:
        """The decoder's context in latent blocks of ``stride`` frames (enough to cover
        ``decoder_frames``); None: unbounded."""
        return None if self.decoder_frames is None else -(-self.decoder_frames // stride)

    @property
    def nfe_per_step(self) -> int:
        return 2 if self.solver == "midpoint" else 1
