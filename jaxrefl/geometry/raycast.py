"""Batched ray queries over a triangle mesh with Embree (embreex).

Everything here is host-side NumPy: rays go to Embree in float32 chunks, on a
small thread pool (embreex releases the GIL while tracing), and come back as
fixed-shape arrays plus masks, ready to be fed into jitted code.

Self-intersection: a ray leaving a surface point starts `offset` metres off the
surface along the normal, on the side the ray leaves to, where
`offset = offset_factor * scale` and `scale` is the mesh's bounding-box
diagonal; segment queries (point to light, point to camera) stop `offset`
short of their target.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property
from typing import NamedTuple

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from .mesh import area_normal_sums, face_cross

__all__ = ["Hits", "RayCaster"]

_CHUNK = 65_536
_NO_HIT = -1


class Hits(NamedTuple):
    """First hits of `n` rays. `hit` `(n,)` bool; `face` `(n,)` int64 (-1 where
    no hit); `t` `(n,)` distance [m] (inf where no hit); `barycentric`
    `(n, 3)` weights of the face's three vertices; `points` `(n, 3)`."""

    hit: np.ndarray
    face: np.ndarray
    t: np.ndarray
    barycentric: np.ndarray
    points: np.ndarray


def default_threads() -> int:
    """Tracing threads used when none are asked for: the cores, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


class RayCaster:
    """Embree scene over one triangle mesh.

    **Arguments:** `vertices` `(N, 3)` float [m]; `faces` `(F, 3)` int;
    `offset_factor` origin offset as a fraction of the bounding-box diagonal;
    `threads` size of the tracing thread pool (default: cores, at most 4).
    """

    #: Embree scenes are built in robust (watertight) mode: rays through vertices and edges
    #: are not lost (the default mode lost 22 % of rays aimed at the vertices of a sphere).
    robust = True

    def __init__(self, vertices, faces, offset_factor: float = 1e-5, threads: int | None = None):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or len(self.vertices) == 0:
            raise ValueError(f"RayCaster: vertices must be (N, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"RayCaster: faces must be (F, 3), got {self.faces.shape}")
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.scale = float(np.linalg.norm(hi - lo)) or 1.0
        self.offset = offset_factor * self.scale
        self.threads = threads or default_threads()
        self._scene = rtcore_scene.EmbreeScene(robust=self.robust)
        TriangleMesh(
            self._scene,
            self.vertices.astype(np.float32),
            self.faces.astype(np.int32),
        )
        # Commit the BVH now rather than racing to build it on the first threaded query.
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), dists=0.0)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    @cached_property
    def offset_normals(self) -> np.ndarray:
        """`(N, 3)` unit area-weighted vertex normals of the mesh with coincident
        vertices welded, used to step rays off vertices.

        Welding matters where a mesh duplicates vertices along a crease (e.g.
        two plates meeting at a fold): each copy's own normal points along the
        other plate, while the welded normal points into the crease.
        """
        _, weld = np.unique(self.vertices, axis=0, return_inverse=True)
        n = area_normal_sums(self.vertices, self.faces, group=weld)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """`(F, 3)` unit geometric normals (right-hand rule on the face's vertex order)."""
        n = face_cross(self.vertices, self.faces)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)

    # -- raw Embree ------------------------------------------------------------

    def _map(self, fn, n):
        starts = range(0, n, _CHUNK)
        if self._pool is None or n <= _CHUNK:
            return [fn(s, min(s + _CHUNK, n)) for s in starts]
        return list(self._pool.map(lambda s: fn(s, min(s + _CHUNK, n)), starts))

    @staticmethod
    def _prepare(origins, directions, tfar):
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
        if tfar is None:
            tf = np.full(len(o), np.inf, dtype=np.float32)
        else:
            tf = np.ascontiguousarray(np.broadcast_to(tfar, (len(o),)), dtype=np.float32)
        return o, d, tf

    def occluded(self, origins, directions, tfar=None) -> np.ndarray:
        """`(n,)` bool: does a ray hit anything with `0 <= t < tfar`?

        **Arguments:** `origins`, `directions` `(n, 3)` (directions need not be
        unit; `t` is in units of their length); `tfar` scalar or `(n,)`, default inf.
        """
        o, d, tf = self._prepare(origins, directions, tfar)
        out = np.empty(len(o), dtype=bool)

        def run(a, b):
            out[a:b] = self._scene.run(o[a:b], d[a:b], dists=tf[a:b].copy(), query="OCCLUDED") != _NO_HIT

        self._map(run, len(o))
        return out

    def first_hit(self, origins, directions, tfar=None) -> Hits:
        """Closest hit of each ray (directions need not be unit; `t` is in their units)."""
        o, d, tf = self._prepare(origins, directions, tfar)
        n = len(o)
        hit = np.empty(n, dtype=bool)
        face = np.empty(n, dtype=np.int64)
        t = np.empty(n, dtype=np.float64)
        bary = np.empty((n, 3), dtype=np.float64)
        points = np.empty((n, 3), dtype=np.float64)

        def run(a, b):  # trace and post-process one chunk inside the worker thread
            r = self._scene.run(o[a:b], d[a:b], dists=tf[a:b].copy(), output=1)
            h = r["primID"] >= 0
            hit[a:b] = h
            face[a:b] = np.where(h, r["primID"], -1)
            t[a:b] = np.where(h, r["tfar"], np.inf)
            u, v = r["u"].astype(np.float64), r["v"].astype(np.float64)
            w = np.stack([1.0 - u - v, u, v], axis=1)
            bary[a:b] = np.where(h[:, None], w, 0.0)
            pts = np.full((b - a, 3), np.nan)
            # Hit points from the barycentrics in float64, not origin + t * dir in float32.
            tri = self.vertices[self.faces[r["primID"][h]]]
            pts[h] = np.einsum("nk,nkj->nj", w[h], tri)
            points[a:b] = pts

        self._map(run, n)
        return Hits(hit, face, t, bary, points)

    # -- surface-aware queries -------------------------------------------------

    def offset_origins(self, points, normals, directions) -> np.ndarray:
        """`(n, 3)` origins moved `offset` off the surface along `normals`,
        toward the side each ray leaves to, plus `offset / 10` along the ray
        (unit `directions`), which keeps grazing rays off their own face."""
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        side = np.sign(np.sum(normals * directions, axis=-1, keepdims=True))
        side = np.where(side == 0, 1.0, side)
        return points + self.offset * (side * normals + 0.1 * directions)

    def _blocked(self, points, normals, targets) -> np.ndarray:
        """Occlusion of segments from surface points to targets, all `(n, 3)`; one chunk."""
        dvec = targets - points
        length = np.linalg.norm(dvec, axis=-1)
        unit = dvec / np.where(length > 0, length, 1.0)[:, None]
        o = self.offset_origins(points, normals, unit).astype(np.float32)
        tfar = np.maximum(length - 3.0 * self.offset, 0.0).astype(np.float32)
        return self._scene.run(o, unit.astype(np.float32), dists=tfar, query="OCCLUDED") != _NO_HIT

    def segments_blocked(self, points, normals, targets) -> np.ndarray:
        """Is the segment from each surface point to its target blocked?

        **Arguments:** `points` `(n, 3)`, `normals` `(n, 3)`, `targets` `(n, 3)` [m].

        **Returns:** `(n,)` bool.
        """
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        targets = np.asarray(targets, dtype=np.float64)
        out = np.empty(len(points), dtype=bool)

        def run(a, b):  # ray set-up happens per chunk, inside the worker thread
            out[a:b] = self._blocked(points[a:b], normals[a:b], targets[a:b])

        self._map(run, len(points))
        return out

    def visibility(self, positions, vertices=None, where=None) -> np.ndarray:
        """Unoccluded line of sight between mesh vertices and positions.

        **Arguments:** `positions` `(3,)`, `(M, 3)`, `(P, 1, 3)` or `(P, M, 3)`
        (lights or camera centres) for the vertices `vertices` `(P,)` (indices;
        default all, `P = N`); `where` optional `(P, M)` bool: trace only these
        pairs (the others come back False). Rays start from the vertices,
        stepped off along `offset_normals`; gathering happens per chunk in the
        worker threads.

        **Returns:** `(P, M)` bool, True where nothing blocks the segment. The
        facing test (cosines > 0) is separate: see `rig.observation_geometry`.
        """
        idx = np.arange(len(self.vertices)) if vertices is None else np.asarray(vertices)
        p = len(idx)
        pos = np.asarray(positions, dtype=np.float64)
        pos = pos.reshape((1,) * (3 - pos.ndim) + pos.shape)
        m = pos.shape[1] if where is None else np.shape(where)[1]
        if pos.shape[0] not in (1, p) or pos.shape[1] not in (1, m):
            raise ValueError(f"positions {np.shape(positions)} do not fit {p} vertices x {m} targets")
        flat = np.arange(p * m) if where is None else np.flatnonzero(where)
        out = np.zeros(p * m, dtype=bool)
        row_of = (lambda i: i) if pos.shape[0] > 1 else (lambda i: 0)
        col_of = (lambda j: j) if pos.shape[1] > 1 else (lambda j: 0)

        def run(a, b):
            i, j = np.divmod(flat[a:b], m)
            v = idx[i]
            out[flat[a:b]] = ~self._blocked(self.vertices[v], self.offset_normals[v], pos[row_of(i), col_of(j)])

        self._map(run, len(flat))
        return out.reshape(p, m)

    def all_hits(self, origins, directions, max_hits: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Up to `max_hits` intersections along each ray, nearest first.

        **Returns:** `t` `(n, max_hits)` (inf where none), `face` `(n, max_hits)`
        (-1 where none), `mask` `(n, max_hits)` bool.
        """
        o = np.asarray(origins, dtype=np.float64).copy()
        d = np.asarray(directions, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        n = len(o)
        t_all = np.full((n, max_hits), np.inf)
        f_all = np.full((n, max_hits), -1, dtype=np.int64)
        travelled = np.zeros(n)
        live = np.arange(n)
        for k in range(max_hits):
            if len(live) == 0:
                break
            h = self.first_hit(o[live], d[live])
            live = live[h.hit]
            travelled[live] += h.t[h.hit]
            t_all[live, k] = travelled[live]
            f_all[live, k] = h.face[h.hit]
            # Restart just past the hit (along the ray, so no normal is needed).
            step = self.offset
            o[live] = o[live] + d[live] * (h.t[h.hit] + step)[:, None]
            travelled[live] += step
        return t_all, f_all, f_all >= 0
