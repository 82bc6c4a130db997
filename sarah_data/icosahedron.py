"""Joints as icosahedra (paper 3.1): a fully Euclidean encoding of position and orientation.

Each joint becomes the 12 vertices of a regular icosahedron of radius `DEFAULT_RADIUS`, rotated by
the joint's global rotation and placed at its global position. Decoding takes the centroid as the
position and the rotation that best maps the reference icosahedron onto the (possibly noisy)
vertices (Kabsch: the SVD of their cross-covariance), so a network's imperfect output still decodes
to a proper rotation.

Works on numpy arrays and torch tensors alike; the output has the input's type.
"""

from __future__ import annotations

import numpy as np
import torch

# 10 cm: large enough that a rotation error weighs in a position-space loss like a centimetre
# error of the joint itself (0.1 rad of rotation moves a vertex by 1 cm).
DEFAULT_RADIUS = 0.10

# trimesh.creation.icosahedron()'s vertices, in its order (the shards rely on it; a test checks
# they still agree), written out so that importing this module does not import trimesh and scipy
# (~1 s in every prep worker).
_PHI = (1.0 + 5.0 ** 0.5) / 2.0
TEMPLATE = np.array([[-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
                     [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
                     [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]], dtype=np.float64)
TEMPLATE /= np.linalg.norm(TEMPLATE, axis=1, keepdims=True)


def encode(positions, rotations, radius: float = DEFAULT_RADIUS):
    """positions (...,J,3), rotations (...,J,3,3) -> icosahedra (...,J,12,3)."""
    if isinstance(positions, torch.Tensor):
        template = torch.as_tensor(TEMPLATE * radius, dtype=positions.dtype, device=positions.device)
        return torch.einsum("...ij,vj->...vi", rotations, template) + positions[..., None, :]
    dtype = np.result_type(positions, rotations, np.float32)
    template = (TEMPLATE * radius).astype(dtype)
    # (R t_v)^T = t_v^T R^T as one batched matmul: much faster than the equivalent einsum
    return template @ np.swapaxes(np.asarray(rotations, dtype), -1, -2) + np.asarray(positions, dtype)[..., None, :]


def axis(icosahedra, column: int):
    """icosahedra (...,J,12,3) -> radius * the rotation's ``column`` (...,J,3), linear in the vertices.

    The template's second moment is isotropic (sum_v u_v u_v^T = 4 I for the 12 unit vertices),
    so sum_v (x_v - centroid) u_v^T / 4 = radius * R exactly for a rigid icosahedron. Unlike
    ``decode``'s SVD this is cheap and smooth to differentiate, which a training loss needs.
    """
    if isinstance(icosahedra, torch.Tensor):
        weights = torch.as_tensor(TEMPLATE[:, column] / 4.0, dtype=icosahedra.dtype,
                                  device=icosahedra.device)
        centred = icosahedra - icosahedra.mean(dim=-2, keepdim=True)
        return torch.einsum("...vi,v->...i", centred, weights)
    x = np.asarray(icosahedra)
    return np.einsum("...vi,v->...i", x - x.mean(axis=-2, keepdims=True), TEMPLATE[:, column] / 4.0)


def decode(icosahedra):
    """icosahedra (...,J,12,3) -> (positions (...,J,3), rotations (...,J,3,3)).

    The rotation is the proper rotation nearest to the vertices' cross-covariance with the
    template; a reflection (det < 0, possible for noisy or mirrored input) is corrected by
    flipping the axis of the smallest singular value.
    """
    if isinstance(icosahedra, torch.Tensor):
        dtype = icosahedra.dtype
        x = icosahedra.double()
        centroid = x.mean(dim=-2)
        template = torch.as_tensor(TEMPLATE, dtype=torch.float64, device=x.device)
        cov = torch.einsum("...vi,vj->...ij", x - centroid[..., None, :], template)
        u, _, vh = torch.linalg.svd(cov)
        det = torch.linalg.det(u @ vh)
        u = torch.cat([u[..., :2], u[..., 2:] * det[..., None, None]], dim=-1)
        return centroid.to(dtype), (u @ vh).to(dtype)
    dtype = np.result_type(icosahedra, np.float32)
    x = np.asarray(icosahedra, dtype=np.float64)
    centroid = x.mean(axis=-2)
    cov = np.einsum("...vi,vj->...ij", x - centroid[..., None, :], TEMPLATE)
    u, _, vh = np.linalg.svd(cov)
    det = np.linalg.det(u @ vh)
    u[..., :, 2] *= det[..., None]
    return centroid.astype(dtype), (u @ vh).astype(dtype)
