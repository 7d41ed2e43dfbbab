"""Radiance from stored photons: a density estimate on the mesh (Method III).

A photon that lands on face `f` at barycentrics `b` is *splatted* to the
face's three vertices with weights `b` (the linear "hat" functions of the
mesh). The integral of vertex `u`'s hat is exactly its area `A_u`
(`mesh.vertex_areas`), so `sum_j b_ju Phi_j / A_u` estimates the
hat-weighted average of the incident flux density without bias, with the
mesh's own boundaries and creases respected (a photon on another sheet never
lands in `u`'s hat) and no kernel-area correction needed.

Where photons are sparse the splat is smoothed over the mesh graph: level `s`
applies the one-ring random-walk operator `P` (uniform over a vertex and its
neighbours) `s` times to both the splat and the areas, giving the kernel
estimate `(P^s X)_n / (P^s A)_n`. The level is chosen per (vertex, light) from
the proposal's photons: the smallest `s` whose effective photon count (Kish,
`(sum w)^2 / sum w^2` over kernel weights times powers) reaches `target`.

A kernel mean is biased where its kernel is lopsided: at the mesh's open boundary the
random walk can only go inward, so the estimate is the density a little way inside,
too high where the light grows away from the edge (about 10 % of the light that
reflected twice, at the corners of a fold). `linear_correction` takes each
(vertex, light) to the intercept of a kernel-weighted local-linear fit instead
(the classical boundary correction of kernel smoothers), measured on the
proposal's photons and kept as a factor.

What is splatted per (vertex `u`, light `m`), evaluated with `u`'s shading
normal, the photon's incoming direction and `u`'s direction to the camera:

- `D`: `sum b Phi [cos_i > 0]`, the incident flux; diffuse radiance is
  `pd_n / pi * D / area` (exact at the gathering vertex `n`);
- `Q`: `sum b Phi lobe_u(alpha_u)`, the Ward lobe
  `exp(-tan^2 theta_h / alpha^2) / (4 pi alpha^2 sqrt(cos_i cos_o))`; the
  specular radiance is `ps_n * Q / area` (the lobe is evaluated at the splat
  vertex, so smoothing at level `s > 0` averages it over the kernel).

Host-side NumPy builds the fixed geometry once; `gather_radiance` is pure `jnp`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..geometry.mesh import vertex_areas
from ..reflectance import brdf

__all__ = ["MeshKernel", "Splat", "mesh_kernel", "splat_geometry", "choose_levels", "linear_correction",
           "gather_radiance"]

_EXP_CAP = 80.0  # exp(-80) is 0 in float32: lobe tails beyond it do not matter


class MeshKernel(NamedTuple):
    """One-ring smoothing operator and per-level normalisers of a mesh (NumPy).

    `neighbours` `(N, D)` int32 (a vertex and its one-ring, padded with itself),
    `weights` `(N, D)` float rows summing to 1 (0 on padding); `area` `(S + 1, N)`
    `P^s A` [m^2]; `kish_area` `(S + 1, N)` `(P^s A)^2 / ((P^s)^2 A)` [m^2], the
    effective area of the level-`s` kernel; `matrix` the sparse `P` (CSR); `max_level`
    `(N,)` int the widest level whose kernel holds no vertex facing away from the vertex
    (normals more than 90 degrees apart: the two see disjoint half-spaces, so their photons
    are not the same light; a kernel that grew over a thin wall's rim would bring the
    inside's light to the outside); all `S` where no normals were given."""

    neighbours: np.ndarray
    weights: np.ndarray
    area: np.ndarray
    kish_area: np.ndarray
    matrix: sp.csr_matrix
    max_level: np.ndarray


class Splat(NamedTuple):
    """Fixed geometry of the photon -> vertex splats, one entry per (photon, vertex
    of its arrival face) that can carry light, sorted by `row`, `(E,)` each:
    `photon` int32, `vertex` int32, `row` int32 (`vertex * M + light`),
    `w_diffuse` `b [cos_i > 0]`, `w_lobe` `b [valid] / (4 pi sqrt(cos_i cos_o))`
    [1/sr], `tan2` `tan^2 theta_h` (`b` the photon's barycentric weight)."""

    photon: np.ndarray
    vertex: np.ndarray
    row: np.ndarray
    w_diffuse: np.ndarray
    w_lobe: np.ndarray
    tan2: np.ndarray


#: A normal this far below perpendicular to the gathering vertex's faces away from it (a
#: right-angle crease, normals 90 degrees apart up to rounding, does not).
_FACING_AWAY = -1e-6


def mesh_kernel(vertices, faces, max_rings: int = 5, normals=None) -> MeshKernel:
    """Build the smoothing operator and its level normalisers (levels `0..max_rings`), and
    with `normals` `(N, 3)` (unit) each vertex's widest level without a vertex facing away."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = len(v)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0], np.arange(n)])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2], np.arange(n)])
    adj = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    adj.data[:] = 1.0  # duplicates (edges shared by two faces) summed: back to 0/1
    deg = np.asarray(adj.sum(axis=1)).ravel()
    p = sp.diags(1.0 / deg) @ adj
    p = p.tocsr()
    p.sort_indices()
    width = int(np.diff(p.indptr).max())
    counts = np.diff(p.indptr)
    slot = np.arange(len(p.indices)) - np.repeat(p.indptr[:-1], counts)
    rows = np.repeat(np.arange(n), counts)
    nbr = np.tile(np.arange(n)[:, None], (1, width))
    wts = np.zeros((n, width))
    nbr[rows, slot] = p.indices
    wts[rows, slot] = p.data
    areas = vertex_areas(v, f)
    area = [areas]
    kish = [areas.copy()]
    ps = sp.identity(n, format="csr")
    max_level = np.full(n, max_rings, np.int32)
    open_ = np.ones(n, bool)  # no vertex facing away within the levels so far
    for s in range(1, max_rings + 1):
        ps = (p @ ps).tocsr()
        ka = ps @ areas
        area.append(ka)
        k2a = ps.multiply(ps) @ areas
        kish.append(np.where(k2a > 0, ka * ka / np.where(k2a > 0, k2a, 1.0), 0.0))
        if normals is not None:
            rows = np.repeat(np.arange(n), np.diff(ps.indptr))
            dots = np.einsum("ij,ij->i", normals[rows], normals[ps.indices])
            closes = open_ & (np.minimum.reduceat(dots, ps.indptr[:-1]) < _FACING_AWAY)
            max_level[closes] = s - 1
            open_ &= ~closes
    return MeshKernel(nbr.astype(np.int32), wts, np.stack(area), np.stack(kish), p, max_level)


_CHUNK = 200_000


@jax.jit
def _splat_chunk(vidx, bary, wi, light, vertices, normals, cam):
    """Splat weights of a chunk of `C` photons (see `Splat`), component-major:
    `vidx`, `bary`, `wi` `(3, C)`, `light` `(C,)`, `vertices`, `normals` `(3, N)`,
    `cam` `(3, N * M)`. Returns `(w_diffuse, w_lobe, tan2)`, each `(3, C)` (one
    row per vertex of the face). (XLA on CPU runs this layout 4x faster than
    `(C, 3, 3)` arrays.)"""
    m = cam.shape[1] // vertices.shape[1]
    row = vidx * m + light[None, :]
    nu = [normals[c][vidx] for c in range(3)]
    to_cam = [cam[c][row] - vertices[c][vidx] for c in range(3)]
    length = jnp.sqrt(to_cam[0] ** 2 + to_cam[1] ** 2 + to_cam[2] ** 2)
    wo = [t / jnp.maximum(length, 1e-30) for t in to_cam]
    h = [wi[c][None, :] + wo[c] for c in range(3)]
    ci = nu[0] * wi[0][None, :] + nu[1] * wi[1][None, :] + nu[2] * wi[2][None, :]
    co = nu[0] * wo[0] + nu[1] * wo[1] + nu[2] * wo[2]
    cos_h = nu[0] * h[0] + nu[1] * h[1] + nu[2] * h[2]
    cx, cy, cz = nu[1] * h[2] - nu[2] * h[1], nu[2] * h[0] - nu[0] * h[2], nu[0] * h[1] - nu[1] * h[0]
    front = ci > 0
    valid = front & (co > 0) & (cos_h > 0)
    tan2 = jnp.where(valid, (cx * cx + cy * cy + cz * cz) / jnp.where(valid, cos_h * cos_h, 1.0), 1e30)
    cif = jnp.maximum(ci, brdf.COS_FLOOR)
    cof = jnp.maximum(co, brdf.COS_FLOOR)
    w_lobe = jnp.where(valid, bary / (4.0 * jnp.pi * jnp.sqrt(cif * cof)), 0.0)
    return jnp.where(front, bary, 0.0), w_lobe, jnp.minimum(tan2, 1e30)


def splat_geometry(vertices, faces, normals, cam_pos, face, bary, direction, light) -> Splat:
    """Splat geometry of `P` photons arriving on `face` `(P,)` at `bary` `(P, 3)`
    from `direction` `(P, 3)` (unit, toward where they came from), emitted by
    `light` `(P,)`; `cam_pos` `(N, M, 3)` camera of every (vertex, light).
    Geometry is evaluated in float32."""
    n, m = cam_pos.shape[:2]
    f32 = np.float32
    dev_v, dev_n = (jnp.asarray(np.asarray(x).T, f32) for x in (vertices, normals))
    dev_c = jnp.asarray(np.asarray(cam_pos, f32).reshape(n * m, 3).T)
    vidx = np.ascontiguousarray(np.asarray(faces)[face].T.astype(np.int32))  # (3, P)
    light = np.asarray(light, np.int32)
    host = (vidx, np.ascontiguousarray(np.asarray(bary, f32).T), np.ascontiguousarray(np.asarray(direction, f32).T),
            light)
    p = len(face)
    out = [np.empty((3, p), f32) for _ in range(3)]
    for s in range(0, p, _CHUNK):
        e = min(s + _CHUNK, p)
        pad = _CHUNK - (e - s)
        args = [np.pad(x[..., s:e], [(0, 0)] * (x.ndim - 1) + [(0, pad)]) for x in host]
        res = _splat_chunk(*args, dev_v, dev_n, dev_c)
        for o, r in zip(out, res):
            o[:, s:e] = np.asarray(r)[:, : e - s]
    # entries in photon-major order: entry 3 j + k is photon j's k-th face vertex
    w_d, w_l, t2 = (np.ascontiguousarray(o.T).ravel() for o in out)
    flat_v = np.ascontiguousarray(vidx.T).ravel()
    keep = np.flatnonzero(w_d > 0)
    row = flat_v[keep].astype(np.int64) * m + light[keep // 3]
    # Stable counting sort by row (scipy's COO -> CSR conversion), 2-3x faster than argsort.
    order = keep[sp.csr_matrix((np.ones(len(keep), np.int8), (row, np.arange(len(keep)))),
                               shape=(n * m, max(len(keep), 1))).indices]
    return Splat(
        photon=(order // 3).astype(np.int32),
        vertex=flat_v[order],
        row=(flat_v[order].astype(np.int64) * m + light[order // 3]).astype(np.int32),
        w_diffuse=w_d[order],
        w_lobe=w_l[order],
        tan2=t2[order],
    )


def _splatted_flux(splat: Splat, power, n: int, n_lights: int):
    """`(N, M)` level-0 sums of the splat weights times `|power|` `(P,)`, and of their squares."""
    w = splat.w_diffuse * np.abs(np.asarray(power))[splat.photon]
    return tuple(np.bincount(splat.row, v, minlength=n * n_lights).reshape(n, n_lights) for v in (w, w * w))


def choose_levels(kernel: MeshKernel, splat: Splat, power, n_lights: int, target: float) -> np.ndarray:
    """`(N, M)` int smoothing level per (vertex, light): the smallest whose
    predicted effective count of photons reaches `target` (else the largest), at most the
    vertex's `kernel.max_level`.

    The count is predicted, not measured at each level: the photon density
    comes from the widest kernel (low noise) and is multiplied by each level's
    effective area. Choosing by each level's own count would keep the vertices
    that happened to receive many photons at small kernels and bias them high
    (+64 % at one vertex of the furnace at 50k photons).

    **Arguments:** `power` `(P,)` scalar proposal power of each photon."""
    n = len(kernel.neighbours)
    k1, k2 = _splatted_flux(splat, power, n, n_lights)
    top = kernel.area.shape[0] - 1
    for _ in range(top):
        k1, k2 = kernel.matrix @ k1, kernel.matrix @ k2
    # Kish count (sum w Phi)^2 / sum w^2 Phi^2 of a level-s kernel over photons of
    # densities rho1 = K c1 / K A, rho2 = K c2 / K A: (rho1^2 / rho2) * kish_area.
    area = kernel.area[top][:, None]
    ratio = np.where(k2 > 0, k1 * k1 / np.where(k2 > 0, k2 * area, 1.0), 0.0)  # rho1^2 / rho2
    n_eff = ratio[None] * kernel.kish_area[:, :, None]  # (S + 1, N, M)
    enough = n_eff >= target
    level = np.where(enough.any(axis=0), np.argmax(enough, axis=0), top)
    return np.minimum(level, kernel.max_level[:, None]).astype(np.int32)


#: Bound on `linear_correction`'s factor (either way): a fit this far from the kernel mean
#: rests on a few photons, not on the kernel's shape.
_LINEAR_BOUND = 2.0


def _tangent_frames(normals) -> np.ndarray:
    """`(N, 3, 2)` two orthonormal tangents of each unit normal `(N, 3)`."""
    nrm = np.asarray(normals, np.float64)
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.stack([t1, np.cross(nrm, t1)], axis=2)


def linear_correction(kernel: MeshKernel, splat: Splat, power, n_lights: int, level, vertices,
                      normals) -> np.ndarray:
    """`(N, M)` factor taking the kernel mean `(P^s X)_n / (P^s A)_n` of vertex `n` at level
    `s = level[n, m]` to the intercept at `p_n` of the density's linear least-squares fit in
    `n`'s tangent plane, `rho(p) ~ a + g . T_n^T (p - p_n)` (`T_n` `(3, 2)` tangents of the
    unit `normals` `(N, 3)`), over the same kernel weights `P^s[n, v] A_v`, measured on the
    proposal's photons (`power` `(P,)`, as `choose_levels`) summed over the vertex's lights at
    that level: the kernel's lean is the geometry's (edges, creases), and one light's few
    photons make its own fit noisy.

    With the kernel's moments of `d_v = T_n^T (p_v - p_n)`, `a1 = sum K A d`,
    `a2 = sum K A d d^T`, and the photons' `s1 = sum K X d`, the intercept is
    `(S0 - s1 . a2^-1 a1) / (A0 - a1 . a2^-1 a1)`: the kernel mean where the kernel is
    balanced (`a1 = 0`: inside a regular mesh, and at level 0), else the mean less the fitted
    gradient times the kernel's offset. (In 3-D coordinates the fit would also take a slope
    along the normal from a curved kernel's small depth, and its noise with it.) The factor
    is bounded to `[1/2, 2]` (`_LINEAR_BOUND`) and is 1 where the kernel holds no photon."""
    n = len(kernel.neighbours)
    level = np.asarray(level)
    x = _splatted_flux(splat, power, n, n_lights)[0]
    pos = np.asarray(vertices, np.float64)
    pos = pos - pos.mean(axis=0)
    frames = _tangent_frames(normals)
    area = kernel.area[0]
    # Level-s sums, smoothed together: A, A p (3), A p p^T (9) per vertex; X, X p (3) per light.
    geo = np.concatenate([area[:, None], area[:, None] * pos,
                          (area[:, None, None] * pos[:, :, None] * pos[:, None, :]).reshape(n, 9)], axis=1)
    phot = np.concatenate([x[:, :, None], x[:, :, None] * pos[:, None, :]], axis=2).reshape(n, 4 * n_lights)
    factor = np.ones((n, n_lights))
    for s in range(kernel.area.shape[0]):
        if s:
            geo, phot = kernel.matrix @ geo, kernel.matrix @ phot
        at = level == s
        if s == 0 or not at.any():
            continue
        a0, ap, app = geo[:, 0], geo[:, 1:4], geo[:, 4:].reshape(n, 3, 3)
        a1 = ap - pos * a0[:, None]  # sum K A (p - p_n)
        a2 = app - pos[:, :, None] * ap[:, None, :] - ap[:, :, None] * pos[:, None, :] \
            + a0[:, None, None] * pos[:, :, None] * pos[:, None, :]
        a1 = np.einsum("nij,ni->nj", frames, a1)
        a2 = np.einsum("nik,nij,njl->nkl", frames, a2, frames)
        det = a2[:, 0, 0] * a2[:, 1, 1] - a2[:, 0, 1] * a2[:, 1, 0]
        ok = det > 1e-12 * np.maximum(a2[:, 0, 0] + a2[:, 1, 1], 1e-300) ** 2
        adj = np.stack([a2[:, 1, 1], -a2[:, 0, 1], -a2[:, 1, 0], a2[:, 0, 0]], axis=1).reshape(n, 2, 2)
        g = np.where(ok[:, None], np.einsum("nij,nj->ni", adj, a1) / np.where(ok, det, 1.0)[:, None], 0.0)
        shrink = 1.0 - np.einsum("ni,ni->n", a1, g) / np.maximum(a0, 1e-300)  # (A0 - a1 a2^-1 a1) / A0
        ph = phot.reshape(n, n_lights, 4)
        s0 = ph[:, :, 0]
        tilt = np.einsum("nij,nmi,nj->nm", frames, ph[:, :, 1:] - pos[:, None, :] * s0[:, :, None], g)
        tilt, s0 = (np.broadcast_to(np.where(at, t, 0.0).sum(1, keepdims=True), t.shape) for t in (tilt, s0))
        good = at & (s0 > 0) & (shrink[:, None] > 0)
        ratio = (1.0 - tilt / np.where(good, s0, 1.0)) / np.where(good, shrink[:, None], 1.0)
        factor = np.where(good, np.clip(ratio, 1.0 / _LINEAR_BOUND, _LINEAR_BOUND), factor)
    return factor


def gather_radiance(kernel_nbr, kernel_w, inv_area, level, splat: Splat, power, alpha, n_points: int,
                    n_lights: int, n_levels: int):
    """Diffuse and lobe parts of the photon-map radiance (pure `jnp`).

    **Arguments:** kernel and splat arrays as built by `mesh_kernel`,
    `splat_geometry` and `choose_levels` (`inv_area` `(N, M)` = `1 / (P^s A)`
    at the chosen level); `power` `(3, P)` photon powers [W], channel-major;
    `alpha` `(N,)` Ward roughness [rad]; static sizes.

    **Returns:** `(D, Q)`, each `(N, M, 3)`: radiance is `pd / pi * D + ps * Q`.
    """
    a2 = (alpha * alpha)[splat.vertex]
    lobe = splat.w_lobe * jnp.exp(-jnp.minimum(splat.tan2 / a2, _EXP_CAP)) / a2
    lobe = jax.lax.optimization_barrier(lobe)  # evaluated once, not once per channel
    p = power[:, splat.photon]  # (3, E)
    vals = jnp.concatenate([splat.w_diffuse[None, :] * p, lobe[None, :] * p], axis=0)  # (6, E)
    x = jax.ops.segment_sum(vals.T, splat.row, n_points * n_lights, indices_are_sorted=True)
    x = x.reshape(n_points, n_lights, 6)
    # One smoothing level per loop step: written as a Python loop, XLA fused the
    # levels into the selects and recomputed them (6x slower).
    def level_step(s, carry):
        x, out = carry
        y = kernel_w[:, 0, None, None] * x[kernel_nbr[:, 0]]
        for d in range(1, kernel_nbr.shape[1]):
            y = y + kernel_w[:, d, None, None] * x[kernel_nbr[:, d]]
        return y, jnp.where((level == s)[..., None], y, out)

    out = jnp.where((level == 0)[..., None], x, 0.0)
    x, out = jax.lax.fori_loop(1, n_levels, level_step, (x, out))
    out = out * inv_area[..., None]
    return out[..., :3], out[..., 3:]
