"""Per-vertex quantities of a triangle mesh shared by several modules (host-side NumPy, from
trimesh's triangle functions)."""

from __future__ import annotations

import numpy as np
import trimesh

__all__ = ["face_cross", "area_normal_sums", "vertex_areas"]


def face_cross(vertices, faces) -> np.ndarray:
    """`(F, 3)` cross products of each face's edges (right-hand rule): length = 2 x area."""
    v = np.asarray(vertices, dtype=np.float64)
    return trimesh.triangles.cross(v[np.asarray(faces, dtype=np.int64).reshape(-1, 3)])


def area_normal_sums(vertices, faces, group=None) -> np.ndarray:
    """`(N, 3)` sum of the adjacent faces' `face_cross` at each vertex (unnormalised
    area-weighted normals). With `group` `(N,)` (e.g. welding coincident vertices),
    vertices of one group share the sum of the whole group."""
    f = np.asarray(faces)
    n = len(vertices)
    key = np.arange(n) if group is None else np.asarray(group).ravel()
    acc = np.zeros((key.max() + 1 if n else 0, 3))
    if len(f):
        cross = face_cross(vertices, f)
        for k in range(3):
            np.add.at(acc, key[f[:, k]], cross)
    return acc[key]


def vertex_areas(vertices, faces) -> np.ndarray:
    """`(N,)` a third of the area of every face touching each vertex [m^2]."""
    area = trimesh.triangles.area(crosses=face_cross(vertices, faces))
    return np.bincount(np.asarray(faces).ravel(), np.repeat(area / 3.0, 3), minlength=len(vertices)).astype(np.float64)
