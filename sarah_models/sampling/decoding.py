"""What a stream's decoded motion goes through before anyone sees it, as its VAE config asks.

In order: ``SeamInertia`` (``vae.boundary_inertia``, ``vae.root_inertia``: the seams between
latent blocks), ``LimbLowpass`` (``vae.limb_lowpass``: the arms' and hands' jitter), ``RootHold`` (``vae.root_hold``: a body that stands still until the decoder
walks it), ``RigidSkeleton`` (``vae.rigid_bones``: bones at the training data's lengths, or
at an agent's own) and
``FootLock`` (``vae.foot_lock``: planted feet, and steps). All five are causal and off in
the paper's config; one ``StreamDecoding`` per stream, fed its frames in order, whole blocks at a
time; streaming, the offline protocol and sarah-eval's VAE row all decode through it. A filter
is called with a block's frames, the stance the VAE's head reads from their latent tokens
(``decoded_stance``; None unless ``vae.foot_lock_reads="stance"``), which only the foot lock
reads, and the user's floor-projected head at those frames in the same frame, which only a root
hold that turns reads (``vae.root_hold_turn``).
"""

from __future__ import annotations

import numpy as np
import torch

from sarah_data.skeleton import ROOT, MotionLayout

from ..nn.vae import detail_generator
from .continuity import SeamInertia
from .foot_lock import FootLock
from .limb_lowpass import LimbLowpass
from .rigid_skeleton import (COLLARS, HANDS, HIPS, RigidSkeleton, check_lengths, piece_directions,
                             skull_directions)
from .root_hold import RootHold


class StreamDecoding:
    """The chain of one stream's filters; ``(n, Dx)`` metres in, the same frames out."""

    def __init__(self, filters: list) -> None:
        self.filters = filters

    def reset(self) -> None:
        for f in self.filters:
            f.reset()

    @property
    def reads_user(self) -> bool:
        """Whether a filter reads the user's floor path (a ``RootHold`` that turns)."""
        return any(isinstance(f, RootHold) and f.reads_user for f in self.filters)

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        """``stance`` (n, feet) bool, the frames' decoded stance: for the foot lock; ``user``
        (n, 2), the user's floor-projected head in the motion's frame: for a root hold that
        turns."""
        for f in self.filters:
            motion = f(motion, stance, user)
        return motion


def reads_stance(vae) -> bool:
    """Whether this VAE's decoding steps by its stance head (``vae.foot_lock_reads``)."""
    return vae.config.foot_lock > 0 and vae.config.foot_lock_reads == "stance"


def decoded_stance(vae, tokens: torch.Tensor, last: bool = False) -> np.ndarray | None:
    """The stance (frames, feet) bool that the stance head reads from the decoder's latent
    tokens (1, K, Dz): of every token's frames, or with ``last`` of the newest token's only
    (a stream's, from the tokens it has); None when the decoding does not step by it."""
    if not reads_stance(vae):
        return None
    with torch.no_grad():
        logits = vae.stance.last(tokens) if last else vae.stance(tokens)
    return vae.stance.planted(logits)[0].cpu().numpy()


def decoder_frames(vae, normalizer, tokens: torch.Tensor,
                   detail_seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Latent tokens (1, K, Dz) as the decoder reads them -> what the decoding chain reads: the
    decoder's frames (K * stride, Dx), metres, float64, its detail drawn from ``detail_seed`` as a
    whole solve draws it, and their decoded stance (``decoded_stance``). The offline protocol and
    sarah-eval's VAE row decode through it, so a study of the chain can record these frames and
    replay the chain on them (scripts/decode_replay.py)."""
    with torch.no_grad():
        detail = vae.detail_noise(1, tokens.shape[1], detail_generator(detail_seed), tokens.device)
        frames = normalizer.denormalize("motion", vae.decode(tokens, detail)[0])
    return frames.double().cpu().numpy(), decoded_stance(vae, tokens)


def takes_bone_lengths(vae) -> bool:
    """Whether this VAE's decoding puts the motion on a skeleton of given bone lengths
    (``vae.rigid_bones``), and so on an agent's own where ``stream_decoding`` is given one;
    without it the bones are the decoder's."""
    return bool(vae.config.rigid_bones)


def body_bone_lengths(vae, rest_joints) -> np.ndarray | None:
    """The bone lengths this VAE's decoding takes for a body whose rest joints (55, 3) are
    ``rest_joints`` (an avatar's, a shard person's): ``stream_decoding``'s ``bone_lengths``; None
    where the decoding keeps no lengths (``takes_bone_lengths``)."""
    if not takes_bone_lengths(vae):
        return None
    return MotionLayout.from_width(vae.motion_dim).rest_bone_lengths(rest_joints)


def skeleton_lengths(normalizer) -> np.ndarray:
    """The training data's bone lengths the model carries (metres, ``MotionLayout.bones``
    order); ValueError when it carries none."""
    if normalizer is None or "bone_length" not in normalizer.keys:
        raise ValueError("vae.rigid_bones and vae.foot_lock need the training data's bone "
                         "lengths, and this model carries none (trained on shards prepared "
                         "before stats.h5 had them): write it again with `sarah-train --stage "
                         "model --init-from MODEL --shards SHARDS`")
    return normalizer.bone_length_mean.detach().double().cpu().numpy()


def stream_decoding(vae, normalizer, bone_lengths=None) -> StreamDecoding:
    """A new stream's decoding for this VAE's output (its normalizer carries the training data's
    skeleton). ``bone_lengths``: the agent's own (metres, ``MotionLayout.bones`` order:
    ``body_bone_lengths`` of an avatar's rest joints, ``MotionLayout.motion_bone_lengths``
    of a captured person's motion), which the rigid skeleton and the foot lock put the motion on in
    place of the training data's, the body lowered or raised by its legs' length
    (``rigid_skeleton.leg_height_change``); None: the training data's. Only a chain that puts
    bones at lengths (``vae.rigid_bones``) reads it: ``takes_bone_lengths``."""
    cfg = vae.config
    layout = MotionLayout.from_width(vae.motion_dim)
    channels = layout.joint_slice(ROOT)
    filters: list = [SeamInertia(vae.stride, cfg.boundary_inertia, cfg.root_inertia,
                                 slice(channels.start // 3, channels.stop // 3), cfg.seam_mode,
                                 layout, ("hands",) if cfg.seam_skips_hands else ())]
    if cfg.limb_lowpass:
        filters.append(LimbLowpass(layout, cfg.limb_lowpass))
    if cfg.root_hold:
        filters.append(RootHold(layout, cfg.root_hold, reads=cfg.root_hold_reads,
                                turn=cfg.root_hold_turn))
    if cfg.rigid_bones or cfg.foot_lock:
        lengths = reference = skeleton_lengths(normalizer)
        if bone_lengths is not None and cfg.rigid_bones:
            lengths = check_lengths(layout, bone_lengths, "the agent's ")
        if cfg.rigid_bones:
            mean = normalizer.motion_mean.detach().double().cpu().numpy()
            skull = skull_directions(layout, mean) if cfg.rigid_skull else None
            wanted = [piece for piece, on in ((HIPS, cfg.rigid_hips), (COLLARS, cfg.rigid_collars),
                                              *((hand, cfg.rigid_hands) for hand in HANDS)) if on]
            pieces = {piece: piece_directions(layout, mean, piece, normalizer.root_relative,
                                              normalizer.root_steps) for piece in wanted}
            pieces = {piece: rest for piece, rest in pieces.items() if rest is not None}
            filters.append(RigidSkeleton(layout, lengths, reference, skull, pieces,
                                         cfg.stand_lift, cfg.leg_softness))
        if cfg.foot_lock:
            if reads_stance(vae) and getattr(vae, "stance", None) is None:
                raise ValueError("vae.foot_lock_reads='stance' needs the VAE's stance head, and "
                                 "this VAE has none")
            filters.append(FootLock(layout, lengths, cfg.foot_lock, cfg.foot_swing_frames,
                                    step=cfg.foot_step, stance_reach=cfg.stance_reach,
                                    gap=cfg.foot_gap, lean=cfg.foot_lean,
                                    softness=cfg.leg_softness))
    return StreamDecoding(filters)
