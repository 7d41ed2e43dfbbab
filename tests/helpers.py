"""Closed-form problem zoo shared by the tests."""

import numpy as np
import trimesh


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def grid_plane(half=1.0, n=21, z=0.0):
    """Square plane `z = const`, `[-half, half]^2`, facing +z: (vertices, faces)."""
    xs = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f


def plate_over_plane(plate_half=0.3, height=0.5):
    """A plane z=0 ([-1,1]^2) with a square plate hovering at z=height: (vertices, faces)."""
    v1, f1 = grid_plane(1.0, 41, 0.0)
    v2, f2 = grid_plane(plate_half, 5, height)
    return np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])


def sphere(radius=1.0, subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)
