"""The shell: a fixed, evenly spread subset of mesh vertices carried alongside the joints (paper 3.1).

Vertices are chosen once per body model by farthest point sampling on the rest mesh
(`v_template`, betas = 0), so the same model file always yields the same ids. The first pick is
the vertex farthest from the mesh's centroid (an extremity, hence on the surface; ties go to the
lowest index), each next pick the vertex farthest from all picks so far.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import DEFAULT_SHELL_POINTS


def farthest_point_sampling(points: np.ndarray, count: int, start: int) -> np.ndarray:
    """Indices (count,) int64 of `count` distinct points of (N,3) `points`, greedily spread out."""
    points = np.asarray(points, dtype=np.float64)
    if not 1 <= count <= len(points):
        raise ValueError(f"cannot sample {count} of {len(points)} points")
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = start
    nearest = np.linalg.norm(points - points[start], axis=1)
    for i in range(1, count):
        chosen[i] = int(np.argmax(nearest))
        if nearest[chosen[i]] == 0.0:
            raise ValueError(f"cannot sample {count} distinct positions: only {i} exist")
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def shell_vertex_ids(rest_vertices: np.ndarray, count: int = DEFAULT_SHELL_POINTS) -> np.ndarray:
    """The shell's vertex ids (count,) int64 for a rest mesh (N,3); deterministic."""
    rest_vertices = np.asarray(rest_vertices, dtype=np.float64)
    start = int(np.argmax(np.linalg.norm(rest_vertices - rest_vertices.mean(axis=0), axis=1)))
    return farthest_point_sampling(rest_vertices, count, start)
