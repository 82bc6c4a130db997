"""Calibration rows: the ground truth made known amounts smoother or noisier.

A Fréchet distance has no unit a reader can picture: is an FGD_acc of 700 a slightly soft
motion or a jittering one? Scored like any method, the ground truth itself degraded by a known
amount answers that on the same windows and metrics. Two degradations bracket what a generator
does wrong with accelerations:

* ``blurred``: a centred moving average over ``frames`` frames, every channel alike. A VAE or a
  flow that cannot place quick steps and beats returns their conditional mean, which is a blur
  of this kind: it keeps the path and loses the 2-10 Hz acceleration (docs/results.md, the
  nineteenth and thirty-third runs).
* ``jittered``: i.i.d. Gaussian noise of ``mm`` millimetres on every coordinate of every frame,
  the signature of a young decoder or of latent tokens that disagree. A second difference of
  such noise has sqrt(6) times its standard deviation times fps², so 1 mm is ~2 m/s².

Both keep every frame's place in the window frame, so where the body goes (FGD) barely moves
and what each row changes is the motion's texture. The noise is a function of (seed, window
index) only, so any subset or order of windows gets the same noise.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

BLUR_FRAMES = 3  # a 3-frame average keeps ~40 % of the fixtures' shell acceleration energy
JITTER_MM = 1.0  # the calibration: 1 mm of noise on the ground truth


def blurred(motion, frames: int = BLUR_FRAMES) -> np.ndarray:
    """(T, Dx) motion averaged over a centred window of ``frames`` frames (an even count reaches
    one frame further back than forward; the ends repeat the first and last frame), float32;
    ``frames`` = 1 returns the motion unchanged."""
    if frames < 1:
        raise ValueError(f"blur: frames must be >= 1, got {frames}")
    motion = np.asarray(motion, dtype=np.float64)
    return uniform_filter1d(motion, size=frames, axis=0, mode="nearest").astype(np.float32)


def jittered(motion, mm: float = JITTER_MM, seed: int = 0, index: int = 0) -> np.ndarray:
    """(T, Dx) motion plus i.i.d. Gaussian noise of ``mm`` millimetres per coordinate, drawn
    from a generator seeded by (seed, index), float32."""
    if not mm >= 0:
        raise ValueError(f"jitter: mm must be >= 0, got {mm}")
    motion = np.asarray(motion, dtype=np.float64)
    noise = np.random.default_rng((int(seed), int(index))).normal(0.0, mm / 1000.0, motion.shape)
    return (motion + noise).astype(np.float32)
