"""Building blocks of the procedural body mesh: tubes along bone chains and ellipsoids, each a
closed surface with skinning weights and joint regressors (``procedural.py`` assembles them)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sarah_data.constants import NUM_JOINTS


@dataclass
class Part:
    """One closed surface of the body, with per-vertex skinning weights and joint regressors."""

    vertices: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3) local indices
    weights: np.ndarray  # (n, 55)
    axis: np.ndarray  # (n, 3) the point on the bone each vertex is measured from (girth)
    girth: float  # how strongly the girth component acts on this part
    regress: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> local vertex ids


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def ring_faces(first: int, second: int, around: int) -> list[tuple[int, int, int]]:
    """Two triangles per quad between consecutive rings, wound so normals point outward."""
    faces = []
    for k in range(around):
        a, b = first + k, first + (k + 1) % around
        c, d = second + (k + 1) % around, second + k
        faces += [(a, b, c), (a, c, d)]
    return faces


def tube(points, radii, joints, owners, around, rings, ref, caps, girth=1.0, cap_rings=3) -> Part:
    """An elliptic tube along a polyline, closed by rounded caps.

    points (n,3); radii (n,2) as (along u, along w) where u is `ref` made perpendicular to the
    axis and w = axis x u; joints: the joint centred on each point's ring (or None); owners
    (n+1): the joint driving the stretch before point 0, each segment, and after the last point;
    rings (n-1): extra rings inside each segment. Weights change owner at each point, blended
    smoothly over a zone a third of the shorter neighbouring segment long.
    """
    points, radii = np.asarray(points, float), np.asarray(radii, float)
    seg = np.diff(points, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    seg_dir = seg / seg_len[:, None]
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    point_dir = np.vstack([seg_dir[:1], unit(seg_dir[:-1] + seg_dir[1:]), seg_dir[-1:]])

    # (centre, axis direction, radius pair, arc position, polyline point index or -1)
    ring_specs = []
    start_cap, end_cap = caps
    for i in range(cap_rings, 0, -1):  # start cap, outermost first
        phi = 0.5 * np.pi * i / (cap_rings + 1)
        ring_specs.append((points[0] - point_dir[0] * start_cap * np.sin(phi), point_dir[0],
                           radii[0] * np.cos(phi), -start_cap * np.sin(phi), -1))
    for k in range(len(points)):
        ring_specs.append((points[k], point_dir[k], radii[k], arc[k], k))
        if k < len(seg):
            for j in range(1, rings[k] + 1):
                t = j / (rings[k] + 1)
                ring_specs.append((points[k] + t * seg[k], seg_dir[k],
                                   (1 - t) * radii[k] + t * radii[k + 1], arc[k] + t * seg_len[k], -1))
    for i in range(1, cap_rings + 1):
        phi = 0.5 * np.pi * i / (cap_rings + 1)
        ring_specs.append((points[-1] + point_dir[-1] * end_cap * np.sin(phi), point_dir[-1],
                           radii[-1] * np.cos(phi), arc[-1] + end_cap * np.sin(phi), -1))

    theta = 2.0 * np.pi * np.arange(around) / around
    ref = np.asarray(ref, float)
    verts = [points[0] - point_dir[0] * start_cap]
    axis = [verts[0]]
    arc_of = [-start_cap]
    regress = {}
    for centre, direction, (ra, rb), s, k in ring_specs:
        u = unit(ref - np.dot(ref, direction) * direction)
        w = np.cross(direction, u)
        ring = centre + ra * np.cos(theta)[:, None] * u + rb * np.sin(theta)[:, None] * w
        if k >= 0 and joints[k] is not None:
            regress[joints[k]] = np.arange(len(verts), len(verts) + around)
        verts.extend(ring)
        axis.extend([centre] * around)
        arc_of.extend([s] * around)
    verts.append(points[-1] + point_dir[-1] * end_cap)
    axis.append(verts[-1])
    arc_of.append(arc[-1] + end_cap)

    n_rings = len(ring_specs)
    faces = [(0, 1 + (k + 1) % around, 1 + k) for k in range(around)]
    for r in range(n_rings - 1):
        faces += ring_faces(1 + r * around, 1 + (r + 1) * around, around)
    last, pole = 1 + (n_rings - 1) * around, 1 + n_rings * around
    faces += [(last + k, last + (k + 1) % around, pole) for k in range(around)]

    arc_of = np.asarray(arc_of)
    weights = np.zeros((len(verts), NUM_JOINTS))
    # Owner changes at each point: nearest point decides which transition a vertex is in.
    nearest = np.argmin(np.abs(arc_of[:, None] - arc[None, :]), axis=1)
    for k in range(len(points)):
        neighbours = [seg_len[j] for j in (k - 1, k) if 0 <= j < len(seg_len)]
        half = min(neighbours) / 3.0
        mine = nearest == k
        after = smoothstep(arc[k] - half, arc[k] + half, arc_of[mine])
        weights[mine, owners[k]] += 1.0 - after
        weights[mine, owners[k + 1]] += after
    return Part(np.asarray(verts), np.asarray(faces, dtype=np.int64), weights,
                 np.asarray(axis), girth, regress)


def ellipsoid(centre, radii, n_lat, n_lon, joint, girth=0.0) -> Part:
    """A latitude/longitude ellipsoid about the y axis; every latitude ring is centred on it."""
    centre, radii = np.asarray(centre, float), np.asarray(radii, float)
    polar = np.pi * np.arange(1, n_lat + 1) / (n_lat + 1)
    lon = 2.0 * np.pi * np.arange(n_lon) / n_lon
    unit = np.stack([np.sin(polar)[:, None] * np.sin(lon)[None, :],
                     np.repeat(np.cos(polar)[:, None], n_lon, axis=1),
                     np.sin(polar)[:, None] * np.cos(lon)[None, :]], axis=-1).reshape(-1, 3)
    verts = np.vstack([centre + [0, radii[1], 0], centre + unit * radii, centre - [0, radii[1], 0]])
    faces = [(0, 1 + k, 1 + (k + 1) % n_lon) for k in range(n_lon)]
    for r in range(n_lat - 1):  # rings run downward here, so the quads turn the other way
        faces += [f[::-1] for f in ring_faces(1 + r * n_lon, 1 + (r + 1) * n_lon, n_lon)]
    last, pole = 1 + (n_lat - 1) * n_lon, 1 + n_lat * n_lon
    faces += [(last + (k + 1) % n_lon, last + k, pole) for k in range(n_lon)]
    weights = np.zeros((len(verts), NUM_JOINTS))
    weights[:, joint] = 1.0
    return Part(verts, np.asarray(faces, dtype=np.int64), weights,
                 np.repeat(centre[None], len(verts), axis=0), girth,
                 {joint: np.arange(len(verts))})
