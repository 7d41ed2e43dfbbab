"""Form factors between the vertex patches of a mesh, cast with Embree (paper §4.1).

A patch is a vertex with its hat basis function (the linear interpolant that is
1 at the vertex and 0 at its neighbours); its area is the vertex area (a third
of each adjacent face). `F[u, v]` is the fraction of the energy leaving patch
`u` diffusely that arrives at patch `v`, so that the irradiance at `u` from
surroundings of radiosity `B` is `(F @ B)[u]` and the radiosity equation reads
`B_u = E_u + pd_u sum_v F_uv B_v` (Eq. 8). Estimated by cosine-weighted rays
(stratified: a Hammersley set with a random shift per patch): each ray's first
hit on a front face shares `1 / rays` among the hit face's three vertices by
barycentric weight. Rays that escape, or hit a back face (the dark side of an
open surface), carry nothing: row sums are <= 1 and the rest leaves into the
dark room (§4.2).

Where rays start (`mode`):

- `'vertex'` (default): at the vertex, around its shading normal. This is the
  irradiance at the very point the camera observes (point collocation).
- `'cell'`: spread over the patch with density `hat_u / A_u` (Galerkin), around
  the face normal. Then `A_u F_uv = A_v F_vu` holds in expectation
  (reciprocity) and sums over patches give area-averaged form factors.

Results are cached in memory and on disk (`formfactors/` in jaxrefl's cache folder,
`jaxrefl.compile_cache.base_dir`: `$JAXREFL_CACHE`, default `~/.cache/jaxrefl`) under a
hash of the mesh and settings, so repeated runs do not recast.
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from .mesh import face_cross, vertex_areas
from .raycast import RayCaster

__all__ = ["FormFactors", "form_factors", "cosine_directions", "hammersley"]

_CACHE_VERSION = 2
_MEMORY: dict[str, FormFactors] = {}
_RAYS_PER_TASK = 32_768  # rays per worker task: traced inline (below raycast's chunk size)


@dataclass(frozen=True)
class FormFactors:
    """Sparse form factors `(P, P)` in COO order sorted by row.

    `rows`, `cols` `(nnz,)` int32; `values` `(nnz,)` float64; `areas` `(P,)` [m^2];
    `rays` per patch; `mode` 'vertex' or 'cell'.
    """

    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray
    areas: np.ndarray
    rays: int
    mode: str

    @property
    def n(self) -> int:
        return len(self.areas)

    @cached_property
    def matrix(self) -> sp.csr_matrix:
        return sp.csr_matrix((self.values, (self.rows, self.cols)), shape=(self.n, self.n))

    @cached_property
    def row_sums(self) -> np.ndarray:
        """`(P,)` fraction of each patch's hemisphere that sees the object (the rest escapes)."""
        return np.bincount(self.rows, self.values, minlength=self.n)

    @property
    def nbytes(self) -> int:
        return int(self.rows.nbytes + self.cols.nbytes + self.values.nbytes)

    def reciprocity_error(self, groups=None) -> float:
        """Relative L1 violation of `A_u F_uv = A_v F_vu`, aggregated over patch
        `groups` `(P,)` int labels (default: each patch against all others, i.e.
        `A_u sum_v F_uv` against `sum_v A_v F_vu`). 0 for exact reciprocity;
        Monte Carlo noise and (in 'vertex' mode) point collocation make it positive."""
        af = sp.diags(self.areas) @ self.matrix
        if groups is None:
            total = af.sum()
            out, into = np.asarray(af.sum(1)).ravel(), np.asarray(af.sum(0)).ravel()
            return float(np.abs(out - into).sum() / total) if total > 0 else 0.0
        labels = np.unique(groups, return_inverse=True)[1]
        s = sp.csr_matrix((np.ones(self.n), (np.arange(self.n), labels)))
        g = (s.T @ af @ s).toarray()
        total = np.abs(g).sum()
        return float(np.abs(g - g.T).sum() / total) if total > 0 else 0.0


def hammersley(n: int) -> np.ndarray:
    """`(n, 2)` Hammersley points in [0, 1)^2 (i / n, base-2 radical inverse of i)."""
    i = np.arange(n, dtype=np.uint32)
    bits = i.copy()
    bits = ((bits << 16) | (bits >> 16)) & 0xFFFFFFFF
    bits = ((bits & 0x55555555) << 1) | ((bits & 0xAAAAAAAA) >> 1)
    bits = ((bits & 0x33333333) << 2) | ((bits & 0xCCCCCCCC) >> 2)
    bits = ((bits & 0x0F0F0F0F) << 4) | ((bits & 0xF0F0F0F0) >> 4)
    bits = ((bits & 0x00FF00FF) << 8) | ((bits & 0xFF00FF00) >> 8)
    return np.c_[i / n, bits.astype(np.float64) / 2.0**32]


def _frame(n):
    """Orthonormal tangents `(P, 3)`, `(P, 3)` for unit normals `n` (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.c_[1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]]
    t2 = np.c_[b, sign + n[:, 1] ** 2 * a, -n[:, 1]]
    return t1, t2


def cosine_directions(normals, u) -> np.ndarray:
    """Cosine-weighted unit directions `(P, R, 3)` about unit `normals` `(P, 3)`
    from uniform samples `u` `(P, R, 2)` (pdf `cos / pi`)."""
    r = np.sqrt(u[..., 0])
    phi = 2.0 * np.pi * u[..., 1]
    z = np.sqrt(np.maximum(1.0 - u[..., 0], 0.0))
    t1, t2 = _frame(normals)
    return ((r * np.cos(phi))[..., None] * t1[:, None] + (r * np.sin(phi))[..., None] * t2[:, None]
            + z[..., None] * normals[:, None])


def _cell_origins(vertices, faces, patches, rays, rng):
    """Origins `(p, R, 3)` and face normals spread over the hat function of each patch:
    an adjacent face with probability proportional to its area, then barycentric
    coordinates Dirichlet(2, 1, 1) on the patch's corner."""
    cross = face_cross(vertices, faces)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    fnorm = cross / np.maximum(2 * area, 1e-300)[:, None]
    corner_v = faces.ravel()
    order = np.argsort(corner_v, kind="stable")
    corner_face = (order // 3)
    corner_slot = order % 3
    weight = area[corner_face]
    cum = np.cumsum(weight)
    start = np.searchsorted(corner_v[order], patches, side="left")
    stop = np.searchsorted(corner_v[order], patches, side="right")
    lo = np.where(start > 0, cum[np.maximum(start - 1, 0)], 0.0)
    hi = cum[np.maximum(stop - 1, 0)]
    pick = lo[:, None] + rng.random((len(patches), rays)) * (hi - lo)[:, None]
    k = np.minimum(np.searchsorted(cum, pick, side="right"), np.maximum(stop - 1, 0)[:, None])
    face, slot = corner_face[k], corner_slot[k]
    g = rng.gamma(np.array([2.0, 1.0, 1.0]), size=(len(patches), rays, 3))
    g /= g.sum(-1, keepdims=True)
    bary = np.take_along_axis(g, (np.arange(3)[None, None] - slot[..., None]) % 3, axis=-1)
    pts = np.einsum("prk,prkj->prj", bary, vertices[faces[face]])
    return pts, fnorm[face]


def _cast(caster, vertices, faces, normals, patches, rays, mode, rng):
    """COO triplets for the rows `patches`."""
    p = len(patches)
    u = (hammersley(rays)[None] + rng.random((p, 1, 2))) % 1.0
    if mode == "vertex":
        origins = np.broadcast_to(vertices[patches][:, None], (p, rays, 3))
        frame_n = normals[patches]
        off_n = np.broadcast_to(caster.offset_normals[patches][:, None], (p, rays, 3))
        dirs = cosine_directions(frame_n, u)
    else:
        origins, face_n = _cell_origins(vertices, faces, patches, rays, rng)
        dirs = cosine_directions(face_n.reshape(-1, 3), u.reshape(-1, 1, 2)).reshape(p, rays, 3)
        off_n = face_n
    o = caster.offset_origins(origins.reshape(-1, 3), off_n.reshape(-1, 3), dirs.reshape(-1, 3))
    hits = caster.first_hit(o, dirs.reshape(-1, 3))
    face = np.where(hits.hit, hits.face, 0)
    # Front or back: the geometric normal, turned to the side of the shading normals (a grazing
    # ray into the next face of a curved surface can be on the wrong side of the shading normal).
    shading = np.einsum("rk,rkj->rj", hits.barycentric, normals[faces[face]])
    geometric = caster.face_normals[face]
    geometric *= np.where(np.einsum("rj,rj->r", geometric, shading) < 0, -1.0, 1.0)[:, None]
    front = hits.hit & (np.einsum("rj,rj->r", geometric, dirs.reshape(-1, 3)) < 0)
    ray_row = np.repeat(patches, rays)[front]
    cols = faces[face[front]].ravel()
    rows = np.repeat(ray_row, 3)
    vals = hits.barycentric[front].ravel() / rays
    return rows, cols, vals


def _key(vertices, faces, normals, rays, mode, seed, offset_factor) -> str:
    h = hashlib.sha1()
    for a in (vertices, faces, normals):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr((rays, mode, seed, offset_factor, _CACHE_VERSION)).encode())
    return h.hexdigest()


def _cache_dir() -> str | None:
    from ..compile_cache import base_dir

    base = base_dir()
    return None if base is None else os.path.join(base, "formfactors")


def form_factors(vertices, faces, normals=None, *, rays: int = 256, mode: str = "vertex", seed: int = 0,
                 caster: RayCaster | None = None, cache: bool = True) -> FormFactors:
    """Form factors between the vertex patches of a mesh (see the module docstring).

    **Arguments:** `vertices` `(P, 3)` [m]; `faces` `(F, 3)`; `normals` `(P, 3)`
    unit shading normals (default: area-weighted from the mesh); `rays` per
    patch; `mode` 'vertex' or 'cell'; `seed` for the per-patch random shifts;
    `caster` an existing `RayCaster` of this mesh; `cache` read and write the
    memory and disk caches.

    **Returns:** `FormFactors`.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if mode not in ("vertex", "cell"):
        raise ValueError(f"mode: must be 'vertex' or 'cell', got {mode!r}")
    if int(rays) < 1:
        raise ValueError(f"rays: must be >= 1, got {rays}")
    caster = caster or RayCaster(vertices, faces)
    normals = caster.offset_normals if normals is None else np.ascontiguousarray(normals, dtype=np.float64)
    key = _key(vertices, faces, normals, int(rays), mode, seed, caster.offset / caster.scale)
    folder = _cache_dir()
    path = None if folder is None else os.path.join(folder, key + ".npz")
    if cache and key in _MEMORY:
        return _MEMORY[key]
    if cache and path is not None and os.path.exists(path):
        try:
            with np.load(path) as z:
                ff = FormFactors(z["rows"], z["cols"], z["values"], z["areas"], int(rays), mode)
            _MEMORY[key] = ff
            return ff
        except (OSError, KeyError, ValueError):  # a damaged cache file is recomputed
            pass

    # Chunks of patches small enough to trace inline, each generated, traced and reduced in
    # a worker thread (NumPy and Embree release the GIL); one random stream per chunk keeps
    # the result independent of the thread count.
    p = len(vertices)
    chunk = max(1, _RAYS_PER_TASK // int(rays))
    starts = list(range(0, p, chunk))
    seeds = np.random.SeedSequence(seed).spawn(len(starts))

    def task(k):
        return _cast(caster, vertices, faces, normals, np.arange(starts[k], min(starts[k] + chunk, p)), int(rays),
                     mode, np.random.default_rng(seeds[k]))

    with ThreadPoolExecutor(caster.threads) as pool:
        parts = list(pool.map(task, range(len(starts))))
    rows, cols, vals = (np.concatenate(x) for x in zip(*parts))
    coo = sp.coo_matrix((vals, (rows, cols)), shape=(p, p)).tocsr()
    coo.sum_duplicates()
    coo = coo.tocoo()
    ff = FormFactors(coo.row.astype(np.int32), coo.col.astype(np.int32), coo.data.astype(np.float64),
                     vertex_areas(vertices, faces), int(rays), mode)
    if cache:
        _MEMORY[key] = ff
        try:
            from ..scan.io import atomic_write

            if path is None:  # JAXREFL_CACHE=off
                return ff
            os.makedirs(os.path.dirname(path), exist_ok=True)
            atomic_write(path, lambda fh: np.savez(fh, rows=ff.rows, cols=ff.cols, values=ff.values,
                                                   areas=ff.areas))
        except OSError:  # read-only cache folder: keep the memory copy only
            pass
    return ff
