"""A linear code of each latent block, fitted to the data's principal components, beside the VAE.

Not in the paper (``vae.block_code``, off by default). A block of s frames maps to a latent of
Dz numbers through two linear steps, each frame onto the data's first ``rank`` per-frame
principal components and the block's s * rank coefficients onto their first Dz principal
components, whitened; decoding is the transpose. The VAE adds it to what its transformers
compute: mu_k gains ``encode`` of block k's frames, block k's decoded frames gain ``decode`` of
z_k, so causality is the VAE's own (mu_k sees frames up to the end of block k; frames of block k
see z_1..z_k).

Why: on the fixture benchmark a tiny VAE trained within the CPU budget reconstructed the
root-relative motion with an RMS point error of 66 mm and 18 % of the data's acceleration
energy, where this code alone (fitted, untrained) at the same latent width reconstructs it with
10 mm (docs/results.md, fifty-second run). Starting from it the transformers only learn what a
linear code of one block cannot carry (the seams between blocks, the pose's non-linear part).

``fit`` sets the weights from a sample of standardized motion: principal components of the
channels weighted as the VAE's loss weighs them (``channel_weight``), so the code keeps what
the loss counts. Its steps are float64 eigendecompositions of fixed batches: deterministic.
"""

from __future__ import annotations

from typing import Callable, Iterable

import torch
from torch import Tensor, nn

# Eigenvalues below this fraction of the largest are treated as this (whitening divides by
# their square roots; a direction with no variance in the sample must not blow up).
MIN_EIGENVALUE = 1e-10


class BlockCode(nn.Module):
    """Linear block code: (B, K, s, Dx) frames <-> (B, K, Dz) latents; weights start at zero
    (a VAE whose code is not fitted adds nothing) and ``fit`` sets them."""

    def __init__(self, motion_dim: int, stride: int, latent_dim: int, rank: int) -> None:
        super().__init__()
        self.stride, self.rank = stride, min(rank, motion_dim)
        self.frame_in = nn.Linear(motion_dim, self.rank, bias=False)
        self.block_in = nn.Linear(stride * self.rank, latent_dim, bias=False)
        self.block_out = nn.Linear(latent_dim, stride * self.rank, bias=False)
        self.frame_out = nn.Linear(self.rank, motion_dim, bias=False)
        for layer in (self.frame_in, self.block_in, self.block_out, self.frame_out):
            nn.init.zeros_(layer.weight)

    def encoder_modules(self) -> list[nn.Module]:
        return [self.frame_in, self.block_in]

    def encode(self, blocks: Tensor) -> Tensor:
        """(B, K, s, Dx) standardized frames -> (B, K, Dz)."""
        coefficients = self.frame_in(blocks)
        return self.block_in(coefficients.flatten(-2))

    def decode(self, z: Tensor) -> Tensor:
        """(B, K, Dz) -> (B, K, s, Dx) standardized frames."""
        coefficients = self.block_out(z).unflatten(-1, (self.stride, self.rank))
        return self.frame_out(coefficients)

    @torch.no_grad()
    def fit(self, batches: Callable[[], Iterable[Tensor]],
            channel_weight: Tensor | None = None) -> dict[str, float]:
        """Set the weights from standardized motion (mean ~0): ``batches()`` yields (B, T, Dx)
        tensors, T a multiple of the stride, the same ones each call (two passes, second
        moments accumulated in float64, so memory does not grow with the sample). Returns the
        share of the weighted variance each stage keeps."""
        s, dx = self.stride, self.frame_in.in_features
        weight = torch.ones(dx, dtype=torch.float64) if channel_weight is None \
            else channel_weight.detach().double().cpu().clamp_min(MIN_EIGENVALUE)
        root = weight.sqrt()

        def weighted_blocks():
            for batch in batches():
                b, t, width = batch.shape
                if t % s or width != dx:
                    raise ValueError(f"BlockCode.fit: motion of {t} frames x {width} channels, "
                                     f"the code takes multiples of {s} frames x {dx}")
                yield (batch.detach().double().cpu() * root).reshape(b * t // s, s, dx)

        frame_moment, _ = _second_moment(blocks.reshape(-1, dx) for blocks in weighted_blocks())
        frame_basis, frame_values = _principal(frame_moment, self.rank)
        block_moment, _ = _second_moment((blocks @ frame_basis).reshape(len(blocks), -1)
                                         for blocks in weighted_blocks())
        block_basis, block_values = _principal(block_moment, self.block_in.out_features)
        scale = block_values.clamp_min(block_values[0] * MIN_EIGENVALUE).sqrt()
        dtype = self.frame_in.weight.dtype
        self.frame_in.weight.copy_((frame_basis.T * root).to(dtype))
        self.frame_out.weight.copy_((frame_basis / root[:, None]).to(dtype))
        self.block_in.weight.copy_((block_basis.T / scale[:, None]).to(dtype))
        self.block_out.weight.copy_((block_basis * scale).to(dtype))
        total = frame_moment.trace()
        return {"frame": float(frame_values.sum() / total),
                "block": float(block_values.sum() / (total * s))}


def _second_moment(rows) -> tuple[Tensor, int]:
    """Mean outer product of the rows of a stream of (N, C) float64 tensors, and the row count."""
    moment, count = None, 0
    for chunk in rows:
        product = chunk.T @ chunk
        moment = product if moment is None else moment + product
        count += len(chunk)
    if not count:
        raise ValueError("BlockCode.fit: no motion to fit")
    return moment / count, count


def _principal(second_moment: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """The ``count`` leading eigenvectors (columns) of a second-moment matrix and their
    eigenvalues, largest first."""
    values, vectors = torch.linalg.eigh(second_moment)
    order = torch.argsort(values, descending=True)[:count]
    vectors = vectors[:, order]
    # eigh's signs are arbitrary: make each direction's largest entry positive, for a fixed result
    signs = torch.sign(vectors.gather(0, vectors.abs().argmax(0, keepdim=True)))
    return vectors * signs, values[order].clamp_min(0.0)
