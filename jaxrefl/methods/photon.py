"""Photon tracing and path replay for Method III (paper §5).

Photons leave each point light, are traced with Embree, and scatter at every
surface they reach; directions come from a fixed *proposal* reflectance, so
the ray geometry never depends on the reflectance being estimated. Under any
other reflectance `theta = (pd, ps, alpha)` a photon's power is its emitted
power times, at every scattering event b along its path,

    f_theta(y_b; w_in, w_out) cos(n_b, w_out) / (pdf_proposal(w_out) q_proposal)

(*path replay*): importance weights that equal 1 at the proposal, and that are
unbiased for every `theta` because the proposal density always keeps a
cosine component (> 0 wherever a BRDF can be) and the Russian-roulette survival
`q` has a floor (`min_survival`).

Only photons that have reflected at least once are stored (the direct term is
exact with shadow rays and belongs to the estimator). A stored photon is one
scattering event plus the surface point the photon reaches after it; a photon
that has bounced `b` times is the child of the one that bounced `b - 1` times
on the same path, so the powers of all photons follow from one BRDF evaluation
per event and a product along the parent links, bounce level by bounce level,
inside `jax.jit`. `jaxrefl.methods.gather` turns stored photons into radiance.

Conventions follow `jaxrefl.reflectance.brdf` (Ward, `pd` an albedo, `pd / pi` diffuse)
and the independent path tracer `data_synth.pathtrace` (one-sided surfaces: a
photon reaching a surface from behind its shading normal is absorbed; shading
normals and reflectance are barycentric interpolations of per-vertex values;
rays leave hit points offset along the face normal). A point light of radiant
intensity `Y` [W/sr] emits `4 pi Y` W; photons are emitted uniformly into the
cone that holds the mesh's bounding sphere, each carrying `Y Omega / n` W.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.raycast import RayCaster
from ..reflectance import brdf
from . import gather

__all__ = ["PhotonPaths", "trace_photons", "PhotonReplay", "photon_powers", "replay_parts"]

#: Largest share of directions drawn from the Ward lobe; the rest are cosine-weighted,
#: which keeps the proposal density > 0 wherever any BRDF is.
MAX_LOBE_SHARE = 0.9


class PhotonPaths(NamedTuple):
    """Stored photons (host NumPy), sorted by bounce: bounce `b` photons are rows
    `level_offsets[b - 1]:level_offsets[b]`. `P` photons, `M` lights.

    - `light` `(P,)` int: the light that emitted it; `path` `(P,)` int: which
      emitted photon it descends from (`light * n + k` for the `k`-th of `n`
      emitted; shared by all photons of one path); `bounce` `(P,)` int >= 1;
      `parent` `(P,)` int: row of the photon that bounced one time less on the
      same path (-1 for bounce 1).
    - Scattering event that sent it on (at the previous surface point):
      `ev_vertices` `(P, 3)` int vertices of the face, `ev_bary` `(P, 3)`,
      `ev_cos_i` (toward where it came from), `ev_cos_o` (toward where it goes),
      `ev_theta_h` [rad] half angle, `ev_weight` `cos_o / (pdf q)` [sr]: the
      event's power ratio is `ward(...) * ev_weight`.
    - Arrival: `face` `(P,)`, `bary` `(P, 3)`, `position` `(P, 3)` [m],
      `direction` `(P, 3)` unit, pointing from the arrival point back toward the
      event (the BRDF's incoming direction there).
    - `power` `(P, 3)` [W] under the proposal; `emitted` `(M,)` [W] power of one
      emitted photon of each light; `n_emitted` `(M,)`.
    """

    light: np.ndarray
    path: np.ndarray
    bounce: np.ndarray
    parent: np.ndarray
    level_offsets: tuple
    ev_vertices: np.ndarray
    ev_bary: np.ndarray
    ev_cos_i: np.ndarray
    ev_cos_o: np.ndarray
    ev_theta_h: np.ndarray
    ev_weight: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    position: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    emitted: np.ndarray
    n_emitted: np.ndarray


# -- sampling (jnp, fixed-size chunks) --------------------------------------------------
#
# Vectors are tuples of three arrays (x, y, z) and per-face data is (3, C): XLA on
# CPU runs this structure-of-arrays form 3-5x faster than (C, 3) arrays.

#: Bounce levels whose power products are unrolled in the replay; deeper ones run in a loop.
_UNROLLED_LEVELS = 8

#: Photons per jitted sampling call (the last chunk of a level is padded).
_CHUNK = 200_000


def _vdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _vcross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _vnormalize(a):
    sq = _vdot(a, a)
    ok = sq > 0
    r = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, sq, 1.0)), 0.0)
    return tuple(x * r for x in a)


def _vframe(n):
    """Two unit tangents completing unit normals `n` to orthonormal frames."""
    use_x = jnp.abs(n[0]) < 0.9
    one, zero = jnp.ones_like(n[0]), jnp.zeros_like(n[0])
    a = (jnp.where(use_x, one, zero), jnp.where(use_x, zero, one), zero)
    t = _vnormalize(_vcross(n, a))
    return t, _vcross(n, t)


def _vhalf_angle(n, wi, wo):
    """theta_h by `atan2(|n x h|, n . h)` (as `brdf.half_angle`)."""
    h = tuple(a + b for a, b in zip(wi, wo))
    c = _vcross(n, h)
    return jnp.arctan2(jnp.sqrt(_vdot(c, c)), _vdot(n, h))


def lobe_share(pd_mean, ps):
    """Probability of sampling the Ward lobe rather than the cosine:
    `ps / (ps + mean(pd))`, at most `MAX_LOBE_SHARE`."""
    return jnp.clip(ps / (ps + pd_mean + 1e-12), 0.0, MAX_LOBE_SHARE)


def mixture_pdf(n, wi, wo, alpha, share):
    """Solid-angle density [1/sr] of `wo` under `(1 - share)` cosine + `share`
    Ward half-vector sampling around unit normal `n` reflecting `wi` (vectors
    as `(x, y, z)` tuples)."""
    pdf_cos = jnp.maximum(_vdot(n, wo), 0.0) / jnp.pi
    h = _vnormalize(tuple(a + b for a, b in zip(wi, wo)))
    cos_h = _vdot(n, h)
    c = jnp.clip(cos_h, 1e-6, 1.0)
    tan2 = (1.0 - c * c) / (c * c)
    a2 = alpha * alpha
    pdf_h = jnp.exp(-jnp.minimum(tan2 / a2, 80.0)) / (jnp.pi * a2 * c**3)
    pdf_lobe = jnp.where(cos_h > 0, pdf_h / (4.0 * jnp.maximum(jnp.abs(_vdot(wo, h)), 1e-6)), 0.0)
    return (1.0 - share) * pdf_cos + share * pdf_lobe


def sample_mixture(u, n, wi, alpha, share):
    """Draw `wo` from `mixture_pdf` with uniforms `u` `(3, C)`; returns `(wo, pdf)`."""
    t, b = _vframe(n)
    u1, u2, u3 = u[0], u[1], u[2]
    phi = 2.0 * jnp.pi * u2
    cphi, sphi = jnp.cos(phi), jnp.sin(phi)
    use_lobe = u3 < share
    # cosine-weighted direction, or a Ward half vector (tan^2 theta_h = -alpha^2 log u)
    r = jnp.sqrt(u1)
    tan2 = -(alpha**2) * jnp.log(jnp.maximum(1.0 - u1, 1e-30))
    cos_t = jax.lax.rsqrt(1.0 + tan2)
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t**2, 0.0))
    lx = jnp.where(use_lobe, sin_t, r) * cphi
    ly = jnp.where(use_lobe, sin_t, r) * sphi
    lz = jnp.where(use_lobe, cos_t, jnp.sqrt(jnp.maximum(1.0 - u1, 0.0)))
    vec = tuple(lx * t[c] + ly * b[c] + lz * n[c] for c in range(3))
    d = 2.0 * _vdot(wi, vec)
    wo = _vnormalize(tuple(jnp.where(use_lobe, d * vec[c] - wi[c], vec[c]) for c in range(3)))
    return wo, mixture_pdf(n, wi, wo, alpha, share)


def _interp(vidx, bary, table):
    """Barycentric interpolation of a per-vertex `table` `(N,)` at `(3, C)` vertices."""
    g = table[vidx]
    return bary[0] * g[0] + bary[1] * g[1] + bary[2] * g[2]


def _ward_rgb(pd, ps, alpha, ci, co, th):
    """Ward BRDF as three `(C,)` channels; `pd` a tuple of three channels (see `brdf.ward`)."""
    spec = brdf.ward_specular(ps, jnp.log(alpha), ci, co, th)
    ok = (ci > 0) & (co > 0)
    return tuple(jnp.where(ok, p / jnp.pi, 0.0) + spec for p in pd)


@jax.jit
def _scatter_chunk(u, vidx, bary, pos, face_normal, wi, power, normals, pd, ps, alpha, min_survival, offset):
    """One scattering event for a chunk of `C` photons under the proposal.

    **Arguments:** `u` `(4, C)` uniforms; `vidx`, `bary` `(3, C)` the face and
    barycentrics where the photon is; `pos`, `face_normal`, `wi` (toward where
    it came from), `power` `(3, C)`; per-vertex `normals`, `pd` `(3, N)`, `ps`,
    `alpha` `(N,)`; survival floor; ray `offset` [m].

    **Returns:** a flat tuple of `(C,)` arrays: `origin` (3), `wo` (3),
    `cos_i`, `cos_o`, `theta_h`, `weight` (`cos_o / (pdf q)`), new power (3),
    `survive` (bool). (Stacking the outputs inside the jit made XLA recompute
    the whole chain per output: 10x slower.)
    """
    n = _vnormalize(tuple(_interp(vidx, bary, normals[c]) for c in range(3)))
    pd_y = tuple(_interp(vidx, bary, pd[c]) for c in range(3))
    ps_y, a_y = _interp(vidx, bary, ps), _interp(vidx, bary, alpha)
    wi = tuple(wi)
    wo, pdf = sample_mixture(u, n, wi, a_y, lobe_share((pd_y[0] + pd_y[1] + pd_y[2]) / 3.0, ps_y))
    ci, co = _vdot(n, wi), _vdot(n, wo)
    th = _vhalf_angle(n, wi, wo)
    f = _ward_rgb(pd_y, ps_y, a_y, ci, co, th)
    ok = (co > 0) & (pdf > 0)
    ratio = jnp.where(ok, co / jnp.where(ok, pdf, 1.0), 0.0)
    thr = tuple(fc * ratio for fc in f)
    q = jnp.clip(jnp.maximum(jnp.maximum(thr[0], thr[1]), thr[2]), min_survival, 1.0)
    survive = ok & (u[3] < q) & ((thr[0] > 0) | (thr[1] > 0) | (thr[2] > 0))
    # Leave the surface as RayCaster.offset_origins does: off the face on the side wo goes to.
    side = jnp.where(_vdot(face_normal, wo) < 0, -1.0, 1.0)
    origin = tuple(pos[c] + offset * (side * face_normal[c] + 0.1 * wo[c]) for c in range(3))
    new_power = tuple(power[c] * thr[c] / q for c in range(3))
    return (*origin, *wo, ci, co, th, ratio / q, *new_power, survive)


@jax.jit
def _facing(vidx, bary, wi, normals):
    """Does the interpolated shading normal face `wi` (`(3, C)`, toward where the photon came from)?"""
    return _vdot(tuple(_interp(vidx, bary, normals[c]) for c in range(3)), tuple(wi)) > 0


@jax.jit
def _emission_chunk(u, axis, cos_max):
    """Unit directions `(3, C)` uniform in the cone of half-angle `acos(cos_max)` around `axis` `(3,)`."""
    cos_t = 1.0 - u[0] * (1.0 - cos_max)
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t**2, 0.0))
    phi = 2.0 * jnp.pi * u[1]
    ax = tuple(jnp.broadcast_to(axis[c], u[0].shape) for c in range(3))
    t, b = _vframe(ax)
    x, y = sin_t * jnp.cos(phi), sin_t * jnp.sin(phi)
    return tuple(x * t[c] + y * b[c] + cos_t * ax[c] for c in range(3))


def _chunks(n):
    """Chunk bounds covering `n` items; one empty chunk when `n == 0` (for output shapes)."""
    return [(s, min(s + _CHUNK, n)) for s in range(0, n, _CHUNK)] or [(0, 0)]


def _pad(x, size):
    """Pad the last axis of `x` to `size` (zeros)."""
    extra = size - x.shape[-1]
    return x if extra == 0 else np.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, extra)])


def _chunked(fn, n, host_args, dev_args=(), rng=None, n_uniform=0, dtype=np.float32):
    """Run jitted `fn` over `n` items in `_CHUNK`-sized pieces (last axis of each
    host array); returns each output as a host array over all items (last axis)."""
    outs = None
    for s, e in _chunks(n):
        args = [_pad(np.ascontiguousarray(a[..., s:e]), _CHUNK) for a in host_args]
        if n_uniform:
            args.insert(0, _pad(rng.random((n_uniform, e - s), dtype=dtype), _CHUNK))
        res = fn(*args, *dev_args)
        res = res if isinstance(res, tuple) else (res,)
        if outs is None:
            outs = [np.empty(np.shape(r)[:-1] + (n,), np.asarray(r).dtype) for r in res]
        for o, r in zip(outs, res):
            o[..., s:e] = np.asarray(r)[..., : e - s]
    return outs


def _emit(caster, rng, light, n_photons, dtype):
    """Emit `n_photons` from `light` `(3,)` into the cone around the mesh's bounding
    sphere and find where they land. Returns `(hits, directions (3, n), solid angle)`."""
    v = caster.vertices
    centre = 0.5 * (v.min(0) + v.max(0))
    radius = float(np.linalg.norm(v - centre, axis=1).max()) * (1.0 + 1e-6) + caster.offset
    axis = centre - light
    dist = float(np.linalg.norm(axis))
    cos_max = -1.0 if dist <= radius else float(np.sqrt(max(1.0 - (radius / dist) ** 2, 0.0)))
    axis = axis / dist if dist > 0 else np.array([0.0, 0.0, 1.0])
    d = np.stack(_chunked(lambda u: _emission_chunk(u, axis.astype(dtype), dtype(cos_max)), n_photons, (),
                          rng=rng, n_uniform=2, dtype=dtype))
    hits = caster.first_hit(np.broadcast_to(light.astype(dtype), (n_photons, 3)), d.T)
    return hits, d, 2.0 * np.pi * (1.0 - cos_max)


def trace_photons(caster: RayCaster, normals, light_pos, intensity, proposal, n_photons: int,
                  seed: int = 0, max_depth: int = 64, min_survival: float = 0.1) -> PhotonPaths:
    """Trace `n_photons` photons from each point light and keep those that reflected.

    **Arguments:** `caster` Embree scene of the mesh; `normals` `(N, 3)` unit
    shading normals; `light_pos` `(M, 3)` [m]; `intensity` `(M,)` or scalar
    radiant intensity [W/sr]; `proposal` `(pd (N, 3), ps (N,), alpha (N,))`
    Ward reflectance that directions and survival are drawn from; `seed`;
    `max_depth` cap on reflections a photon makes; `min_survival` floor of the
    Russian-roulette survival probability.

    **Returns:** `PhotonPaths`, bounce levels in order. Sampling runs in float32
    (Embree traces in float32 anyway); the event geometry is float32-accurate.
    """
    light_pos = np.asarray(light_pos, dtype=np.float64).reshape(-1, 3)
    m = len(light_pos)
    intensity = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (m,))
    pd, ps, alpha = _check_params(proposal, len(caster.vertices), "proposal")
    if not 0 < min_survival <= 1:
        raise ValueError(f"min_survival must be in (0, 1], got {min_survival}")
    if n_photons < 1 or max_depth < 1:
        raise ValueError("n_photons and max_depth must be >= 1")
    dt = np.float32
    faces_t = np.ascontiguousarray(caster.faces.T.astype(np.int32))  # (3, F)
    fnorm_t = np.ascontiguousarray(caster.face_normals.T.astype(dt))
    normals_t = jnp.asarray(_normalize(np.asarray(normals, dtype=np.float64)).T, dt)
    dev = (normals_t, jnp.asarray(pd.T, dt), jnp.asarray(ps, dt), jnp.asarray(alpha, dt), dt(min_survival),
           dt(caster.offset))
    rng = np.random.default_rng(np.random.SeedSequence(seed))

    def facing(face, bary_t, wi_t):
        (ok,) = _chunked(_facing, len(face), (faces_t[:, face], bary_t, wi_t), (normals_t,))
        return ok

    # Bounce 0: emission and first landing (not stored: the direct term is exact elsewhere).
    emitted = np.zeros(m)
    parts = []
    for k in range(m):
        hits, d, omega = _emit(caster, rng, light_pos[k], int(n_photons), dt)
        emitted[k] = intensity[k] * omega / n_photons
        h = np.flatnonzero(hits.hit)
        face, bary_t, wi_t = hits.face[h], hits.barycentric[h].T.astype(dt), -d[:, h]
        front = facing(face, bary_t, wi_t)
        parts.append(dict(face=face[front], bary=bary_t[:, front], pos=hits.points[h][front].T.astype(dt),
                          wi=wi_t[:, front], light=np.full(int(front.sum()), k, np.int32),
                          path=k * int(n_photons) + h[front],
                          power=np.full((3, int(front.sum())), emitted[k], dt)))
    live = {key: np.concatenate([p[key] for p in parts], axis=-1) for key in parts[0]}
    live["parent"] = np.full(len(live["face"]), -1, dtype=np.int64)
    levels, stored = [], 0
    for _ in range(max_depth):
        p = len(live["face"])
        if p == 0:
            break
        host = (faces_t[:, live["face"]], live["bary"], live["pos"], fnorm_t[:, live["face"]], live["wi"],
                live["power"])
        out = _chunked(_scatter_chunk, p, host, dev, rng=rng, n_uniform=4)
        origin, wo, power = np.stack(out[0:3]), np.stack(out[3:6]), np.stack(out[10:13])
        ci, co, th, weight, survive = out[6], out[7], out[8], out[9], out[13]
        idx = np.flatnonzero(survive)
        hits = caster.first_hit(origin[:, idx].T, wo[:, idx].T)
        landed = np.flatnonzero(hits.hit)
        nf = hits.face[landed]
        nb = hits.barycentric[landed].T.astype(dt)
        front = facing(nf, nb, -wo[:, idx[landed]])
        arrive = landed[front]
        j = idx[arrive]
        level = dict(
            light=live["light"][j], path=live["path"][j], parent=live["parent"][j],
            ev_vertices=faces_t[:, live["face"][j]].T,
            ev_bary=live["bary"][:, j].T, ev_cos_i=ci[j], ev_cos_o=co[j], ev_theta_h=th[j],
            ev_weight=weight[j], face=hits.face[arrive], bary=hits.barycentric[arrive],
            position=hits.points[arrive], direction=-wo[:, j].T, power=power[:, j].T,
        )
        levels.append(level)
        count = len(j)
        live = dict(face=level["face"], bary=nb[:, front], pos=level["position"].T.astype(dt),
                    wi=-wo[:, j], power=power[:, j], light=level["light"], path=level["path"],
                    parent=stored + np.arange(count))
        stored += count
    return _sort_levels(_merge(levels, emitted, np.full(m, int(n_photons))), m)


def _sort_levels(paths: PhotonPaths, n_lights: int) -> PhotonPaths:
    """Reorder photons within each bounce level by (arrival face, light).

    Gathers then read photon powers nearly in order (faces are numbered
    coherently in space), which makes the splat several times faster than the
    order photons were traced in (measurements: `benchmarks/RESULTS_notes.md`)."""
    p = len(paths.light)
    perm = np.empty(p, dtype=np.int64)
    off = paths.level_offsets
    for s, e in zip(off[:-1], off[1:]):
        perm[s:e] = s + np.argsort(paths.face[s:e] * n_lights + paths.light[s:e], kind="stable")
    inv = np.empty(p, dtype=np.int64)
    inv[perm] = np.arange(p)
    fields = {k: getattr(paths, k)[perm] for k in PhotonPaths._fields
              if k not in ("level_offsets", "emitted", "n_emitted", "parent")}
    parent = paths.parent[perm]
    parent = np.where(parent >= 0, inv[np.maximum(parent, 0)], -1)
    return paths._replace(parent=parent, **fields)


def _merge(levels, emitted, n_emitted) -> PhotonPaths:
    """Concatenate bounce levels (dicts of arrays) into one `PhotonPaths`."""
    offsets = tuple(int(x) for x in np.cumsum([0] + [len(lv["face"]) for lv in levels]))
    shapes = {"light": (), "path": (), "parent": (), "ev_vertices": (3,), "ev_bary": (3,), "ev_cos_i": (),
              "ev_cos_o": (), "ev_theta_h": (), "ev_weight": (), "face": (), "bary": (3,), "position": (3,),
              "direction": (3,), "power": (3,)}
    ints = ("light", "path", "parent", "ev_vertices", "face")
    cat = {}
    for key, shape in shapes.items():
        dtype = np.int64 if key in ints else np.float64
        parts = [np.asarray(lv[key], dtype=dtype) for lv in levels]
        cat[key] = np.concatenate(parts) if parts else np.zeros((0,) + shape, dtype)
    bounce = np.concatenate([np.full(len(lv["face"]), b + 1, np.int32) for b, lv in enumerate(levels)] or
                            [np.zeros(0, np.int32)])
    return PhotonPaths(bounce=bounce, level_offsets=offsets, emitted=np.asarray(emitted, dtype=np.float64),
                       n_emitted=np.asarray(n_emitted, dtype=np.int64), **cat)


def _normalize(a):
    length = np.linalg.norm(a, axis=-1, keepdims=True)
    return a / np.where(length > 0, length, 1.0)


def _check_params(params, n, name):
    """Validate a `(pd, ps, alpha)` triple for `n` vertices; returns float64 arrays."""
    if not isinstance(params, (tuple, list)) or len(params) != 3:
        raise ValueError(f"{name}: expected (pd, ps, alpha)")
    pd = np.broadcast_to(np.asarray(params[0], dtype=np.float64), (n, 3))
    ps = np.broadcast_to(np.asarray(params[1], dtype=np.float64), (n,))
    alpha = np.broadcast_to(np.asarray(params[2], dtype=np.float64), (n,))
    for label, a in (("pd", pd), ("ps", ps), ("alpha", alpha)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: {label} must be finite")
    if np.any(pd < 0) or np.any(ps < 0):
        raise ValueError(f"{name}: pd and ps must be >= 0")
    if np.any(alpha <= 0):
        raise ValueError(f"{name}: alpha must be > 0")
    return pd, ps, alpha


# -- path replay (jnp) ----------------------------------------------------------------


def photon_powers(ev_vertices, ev_bary, ev_cos_i, ev_cos_o, ev_theta_h, ev_weight, light, parent, bounce,
                  emitted, pd, ps, alpha, offsets, depth):
    """Photon powers `(3, P)` [W] (channel-major) under reflectance `pd` `(N, 3)`,
    `ps` `(N,)`, `alpha` `(N,)`: the emitted power times the product of every
    event's `ward * ev_weight` along the photon's path. Event arrays as in
    `PhotonPaths` but component-major: `ev_vertices`, `ev_bary` `(3, P)`.
    `offsets` (static) bound bounce levels `1..H` (`level_offsets` or a padded
    version); rows from `offsets[-1]` on hold the deeper levels, up to the static
    `depth`."""
    ps_e = _interp(ev_vertices, ev_bary, ps)
    a_e = _interp(ev_vertices, ev_bary, alpha)
    spec = brdf.ward_specular(ps_e, jnp.log(jnp.maximum(a_e, jnp.finfo(a_e.dtype).tiny)), ev_cos_i, ev_cos_o,
                              ev_theta_h)
    ok = (ev_cos_i > 0) & (ev_cos_o > 0)
    # The barrier keeps XLA from recomputing the lobe once per colour channel.
    spec, ok = jax.lax.optimization_barrier((spec, ok))
    ratio = jnp.stack([(jnp.where(ok, _interp(ev_vertices, ev_bary, pd[:, c]) / jnp.pi, 0.0) + spec) * ev_weight
                       for c in range(3)])
    out = jnp.zeros_like(ratio)
    head = len(offsets) - 1
    for b in range(1, head + 1):
        s, e = offsets[b - 1], offsets[b]
        if e == s:
            continue
        prev = emitted[light[s:e]][None, :] if b == 1 else out[:, parent[s:e]]
        out = out.at[:, s:e].set(prev * ratio[:, s:e])
    t0 = offsets[-1]
    if t0 < ratio.shape[1]:
        # The long, thin tail of deep bounces: one masked step per level over the tail
        # block in a loop with static bounds (unrolled, 60 furnace levels took seconds
        # to compile; dynamic bounds would not differentiate). Tail parents lie in the
        # last unrolled level or in the tail itself.
        h0 = offsets[-2]
        t_parent, t_ratio, t_bounce = parent[t0:] - h0, ratio[:, t0:], bounce[t0:]
        last = out[:, h0:t0]

        def level_step(b, tail):
            src = jnp.concatenate([last, tail], axis=1)
            return jnp.where((t_bounce == b)[None, :], src[:, t_parent] * t_ratio, tail)

        tail = jax.lax.fori_loop(head + 1, max(depth, head) + 1, level_step, out[:, t0:])
        out = out.at[:, t0:].set(tail)
    return out


class _Static(NamedTuple):
    offsets: tuple
    n_points: int
    n_lights: int
    depth: int
    n_levels: int


class _Data(NamedTuple):
    """Device arrays of one replay (a pytree passed to the jitted functions)."""

    ev_vertices: jax.Array
    ev_bary: jax.Array
    ev_cos_i: jax.Array
    ev_cos_o: jax.Array
    ev_theta_h: jax.Array
    ev_weight: jax.Array
    light: jax.Array
    parent: jax.Array
    bounce: jax.Array
    emitted: jax.Array
    proposal_power: jax.Array
    path: jax.Array
    kernel_nbr: jax.Array
    kernel_w: jax.Array
    inv_area: jax.Array
    level: jax.Array
    splat: gather.Splat
    facing: jax.Array


def _params(data: _Data, pd, ps, alpha):
    dt = data.ev_bary.dtype
    return jnp.asarray(pd, dt), jnp.asarray(ps, dt), jnp.asarray(alpha, dt)


def _powers(data: _Data, pd, ps, alpha, static: _Static):
    return photon_powers(data.ev_vertices, data.ev_bary, data.ev_cos_i, data.ev_cos_o, data.ev_theta_h,
                         data.ev_weight, data.light, data.parent, data.bounce, data.emitted, pd, ps, alpha,
                         static.offsets, static.depth)


def _parts_from_powers(data: _Data, power, alpha, static: _Static):
    return gather.gather_radiance(data.kernel_nbr, data.kernel_w, data.inv_area, data.level, data.splat, power,
                                  alpha, static.n_points, static.n_lights, static.n_levels)


def replay_parts(data: _Data, static: _Static, pd, ps, alpha):
    """`(D, Q)` `(N, M, 3)` each under Ward reflectance `(pd, ps, alpha)` (see
    `PhotonReplay.parts`): photon powers by path replay, gathered with `alpha`;
    0 where a vertex faces away from its camera. Pure `jnp`, for use inside a
    caller's `jit` with a replay's `data` and (static) `static`."""
    pd, ps, alpha = _params(data, pd, ps, alpha)
    power = _powers(data, pd, ps, alpha, static)
    d, q = _parts_from_powers(data, power, alpha, static)
    facing = data.facing[..., None]
    return jnp.where(facing, d, 0.0), jnp.where(facing, q, 0.0)


@partial(jax.jit, static_argnames="static")
def _indirect(data: _Data, pd, ps, alpha, static: _Static):
    d, q = replay_parts(data, static, pd, ps, alpha)
    pd, ps, _ = _params(data, pd, ps, alpha)
    return pd[:, None, :] / jnp.pi * d + ps[:, None, None] * q


@partial(jax.jit, static_argnames="static")
def _powers_jit(data: _Data, real, pd, ps, alpha, static: _Static):
    return _powers(data, *_params(data, pd, ps, alpha), static)[:, real].T


@partial(jax.jit, static_argnames="static")
def _parts_jit(data: _Data, real, power, alpha, static: _Static):
    padded = jnp.zeros_like(data.proposal_power).at[:, real].set(jnp.asarray(power, data.ev_bary.dtype).T)
    d, q = _parts_from_powers(data, padded, jnp.asarray(alpha, data.ev_bary.dtype), static)
    return jnp.where(data.facing[..., None], d, 0.0), jnp.where(data.facing[..., None], q, 0.0)


def _batch_radiance(data: _Data, power, pd, ps, alpha, static: _Static, b, batches: int):
    """`indirect` from the emitted photons of group `b` of `batches` (a split fixed
    before tracing), scaled to the full count."""
    group = data.path % batches
    d, q = _parts_from_powers(data, jnp.where((group == b)[None, :], power * batches, 0.0), alpha, static)
    rad = pd[:, None, :] / jnp.pi * d + ps[:, None, None] * q
    return jnp.where(data.facing[..., None], rad, 0.0)


@partial(jax.jit, static_argnames=("static", "batches"))
def _indirect_batches(data: _Data, pd, ps, alpha, static: _Static, batches: int):
    pd, ps, alpha = _params(data, pd, ps, alpha)
    power = _powers(data, pd, ps, alpha, static)
    return jax.lax.map(lambda b: _batch_radiance(data, power, pd, ps, alpha, static, b, batches),
                       jnp.arange(batches))


@partial(jax.jit, static_argnames=("static", "batches"))
def _indirect_variance(data: _Data, pd, ps, alpha, static: _Static, batches: int):
    pd, ps, alpha = _params(data, pd, ps, alpha)
    power = _powers(data, pd, ps, alpha, static)
    full = _indirect(data, pd, ps, alpha, static)  # the batches' mean, exactly

    def add(b, acc):  # about the mean, not sum x^2 - n mean^2: no cancellation in float32
        return acc + (_batch_radiance(data, power, pd, ps, alpha, static, b, batches) - full) ** 2

    acc = jax.lax.fori_loop(0, batches, add, jnp.zeros_like(full))
    return acc / (batches * (batches - 1))


@partial(jax.jit, static_argnames="static")
def _ess(data: _Data, pd, ps, alpha, static: _Static):
    power = _powers(data, *_params(data, pd, ps, alpha), static).sum(axis=0)
    p0 = data.proposal_power.sum(axis=0)
    ok = p0 > 0
    r = jnp.where(ok, power / jnp.where(ok, p0, 1.0), 0.0)
    s1 = jax.ops.segment_sum(r, data.light, static.n_lights)
    s2 = jax.ops.segment_sum(r * r, data.light, static.n_lights)
    cnt = jax.ops.segment_sum(ok.astype(r.dtype), data.light, static.n_lights)
    good = (s2 > 0) & (cnt > 0)
    return jnp.where(good, s1 * s1 / jnp.where(good, s2 * cnt, 1.0), 0.0)


#: Smallest padded block of photons (levels of very different small sizes share shapes).
_MIN_BLOCK = 1024


def _bucket(n: int) -> int:
    """`n` rounded up to `k 2^j` with `16 <= k < 32` (at most 6.25 % more), so that
    replays of similar size share array shapes and compiled code."""
    if n <= 32:
        return n
    step = 1 << (int(n).bit_length() - 5)
    return -(-n // step) * step


def _padded_paths(paths: PhotonPaths):
    """Photon arrays with bounce levels `1.._UNROLLED_LEVELS` (empty or not) and the
    deeper tail each padded to `_bucket` sizes (at least `_MIN_BLOCK`) by dummy
    photons (zero weight, bounce 0), so that replays of similar size compile once.

    **Returns:** `(arrays, offsets, new_index)`: dict of padded arrays (those of
    `PhotonPaths`), the static level bounds, and `(P,)` each photon's
    new row."""
    off = paths.level_offsets
    depth = len(off) - 1
    head = _UNROLLED_LEVELS
    ends = [off[min(b, depth)] for b in range(head + 1)] + [off[-1]]
    blocks = list(zip(ends[:-1], ends[1:]))  # head levels (possibly empty), then the tail
    sizes = [max(_MIN_BLOCK, _bucket(e - s)) for s, e in blocks]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    total = int(starts[-1])
    new_index = np.concatenate([starts[i] + np.arange(e - s) for i, (s, e) in enumerate(blocks)] or
                               [np.zeros(0, np.int64)]).astype(np.int64)
    fields = dict(ev_vertices=paths.ev_vertices, ev_bary=paths.ev_bary, ev_cos_i=paths.ev_cos_i,
                  ev_cos_o=paths.ev_cos_o, ev_theta_h=paths.ev_theta_h, ev_weight=paths.ev_weight,
                  light=paths.light, path=paths.path, bounce=paths.bounce, power=paths.power)
    out = {}
    for key, x in fields.items():
        y = np.zeros((total,) + x.shape[1:], x.dtype)
        y[new_index] = x
        out[key] = y
    # Dummy events sit on vertex 0 of face 0 (a real vertex: finite gradients) with no weight.
    pad = np.ones(total, bool)
    pad[new_index] = False
    out["ev_bary"][pad, 0] = 1.0
    parent = np.zeros(total, np.int64)
    parent[new_index] = np.where(paths.parent >= 0, new_index[np.maximum(paths.parent, 0)], 0)
    out["parent"] = parent
    offsets = tuple(int(x) for x in starts[: head + 1])
    return out, offsets, new_index


def _padded_splat(splat: gather.Splat, new_index, n_rows: int) -> gather.Splat:
    """Splat entries with photons renumbered to their padded rows and the entry
    count padded to a `_bucket` size (zero-weight entries on the last row)."""
    e = len(splat.row)
    extra = _bucket(e) - e

    def pad(x, value):
        return np.concatenate([x, np.full(extra, value, x.dtype)])

    return gather.Splat(
        photon=pad(new_index[splat.photon].astype(np.int32), 0),
        vertex=pad(splat.vertex, 0),
        row=pad(splat.row, n_rows - 1),
        w_diffuse=pad(splat.w_diffuse, 0.0),
        w_lobe=pad(splat.w_lobe, 0.0),
        tan2=pad(splat.tan2, 1e30),
    )


def _broadcast_positions(x, n, m, name):
    x = np.asarray(x, dtype=np.float64)
    if x.shape not in ((3,), (m, 3), (n, 1, 3), (n, m, 3)):
        raise ValueError(f"{name}: expected (3,), ({m}, 3), ({n}, 1, 3) or ({n}, {m}, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: must be finite")
    return np.broadcast_to(x.reshape((1,) * (3 - x.ndim) + x.shape), (n, m, 3))


@dataclass(frozen=True, eq=False)
class PhotonReplay:
    """Photon paths traced once from a proposal reflectance, re-weighted for any other.

    Build with `PhotonReplay.build`; then `indirect(pd, ps, alpha)` is a
    jit-compiled function of the reflectance only (the ray geometry, the
    splats and the smoothing levels are fixed). `ess` tells when the proposal
    has gone stale; `retrace` traces afresh from a new proposal.
    """

    paths: PhotonPaths
    data: _Data
    static: _Static
    real: jax.Array  # (P,) padded row of each stored photon
    settings: dict = field(repr=False)
    seconds: dict = field(default_factory=dict)

    @classmethod
    def build(cls, caster, vertices, faces, normals, light_pos, intensity, cam_pos, proposal,
              n_photons: int = 1_000_000, target_photons: float = 256.0, max_rings: int = 5, seed: int = 0,
              max_depth: int = 64, min_survival: float = 0.1, first_bounce: bool = True,
              dtype=np.float32) -> "PhotonReplay":
        """Trace photons from every light and precompute the gathers.

        **Arguments:** `caster` a `RayCaster` of (`vertices` `(N, 3)`, `faces`
        `(F, 3)`) or None to build one; `normals` `(N, 3)` shading normals;
        `light_pos` `(M, 3)` [m]; `intensity` `(M,)` or scalar [W/sr];
        `cam_pos` `(3,)`, `(M, 3)`, `(N, 1, 3)` or `(N, M, 3)` camera of every
        observation; `proposal` `(pd (N, 3), ps (N,), alpha (N,))` Ward
        reflectance the paths are sampled from; `n_photons` emitted per light;
        `target_photons` effective photon count each gather aims for (sets the
        smoothing level); `max_rings` largest smoothing level; `seed`;
        `max_depth`, `min_survival` as `trace_photons`; `first_bounce=False`
        gathers only photons that reflected twice or more (the first bounce
        then comes from `jaxrefl.methods.final_gather`); `dtype` of the replay.
        """
        settings = dict(n_photons=n_photons, target_photons=target_photons, max_rings=max_rings,
                        seed=seed, max_depth=max_depth, min_survival=min_survival, first_bounce=first_bounce,
                        dtype=dtype)
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"vertices and faces must be (N, 3) and (F, 3), got {v.shape} and {f.shape}")
        nrm = _normalize(np.asarray(normals, dtype=np.float64))
        if nrm.shape != v.shape or not np.all(np.isfinite(nrm)):
            raise ValueError(f"normals must be finite and {v.shape}, got {nrm.shape}")
        light_pos = np.asarray(light_pos, dtype=np.float64)
        if light_pos.ndim != 2 or light_pos.shape[1] != 3 or len(light_pos) == 0:
            raise ValueError(f"light_pos: expected (M, 3), got {light_pos.shape}")
        m = len(light_pos)
        intensity = np.asarray(intensity, dtype=np.float64)
        if intensity.shape not in ((), (m,)) or not np.all(intensity > 0) or not np.all(np.isfinite(intensity)):
            raise ValueError(f"intensity: expected a positive scalar or ({m},), got {intensity!r}")
        if target_photons <= 0 or max_rings < 0:
            raise ValueError("target_photons must be > 0 and max_rings >= 0")
        cam = _broadcast_positions(cam_pos, len(v), m, "cam_pos")
        caster = caster if caster is not None else RayCaster(v, f)
        if caster.vertices.shape != v.shape or caster.faces.shape != f.shape:
            raise ValueError("caster was built for another mesh")
        t0 = time.perf_counter()
        paths = trace_photons(caster, nrm, light_pos, intensity, proposal, n_photons, seed=seed,
                              max_depth=max_depth, min_survival=min_survival)
        t1 = time.perf_counter()
        replay = cls.from_paths(paths, v, f, nrm, cam, target_photons=target_photons, max_rings=max_rings,
                                max_depth=max_depth, first_bounce=first_bounce, dtype=dtype)
        replay.settings.update(settings, caster=caster, light_pos=light_pos, intensity=intensity)
        replay.seconds["trace"] = t1 - t0
        return replay

    @classmethod
    def from_paths(cls, paths: PhotonPaths, vertices, faces, normals, cam_pos, target_photons: float = 256.0,
                   max_rings: int = 5, max_depth: int = 64, first_bounce: bool = True,
                   dtype=np.float32) -> "PhotonReplay":
        """Gathers for already traced `paths` (arguments as `build`; `cam_pos`
        `(N, M, 3)` or broadcastable): other gather settings without re-tracing."""
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        nrm = _normalize(np.asarray(normals, dtype=np.float64))
        m = len(paths.emitted)
        if target_photons <= 0 or max_rings < 0:
            raise ValueError("target_photons must be > 0 and max_rings >= 0")
        if len(paths.level_offsets) - 1 > max_depth:
            raise ValueError(f"max_depth: the paths have {len(paths.level_offsets) - 1} bounce levels")
        cam = _broadcast_positions(cam_pos, len(v), m, "cam_pos")
        t1 = time.perf_counter()
        kernel = gather.mesh_kernel(v, f, max_rings, nrm)
        splat = gather.splat_geometry(v, f, nrm, cam, paths.face, paths.bary, paths.direction, paths.light)
        if not first_bounce:  # the photons stay (parents of deeper ones) but gather no light
            splat = gather.Splat(*(x[paths.bounce[splat.photon] > 1] for x in splat))
        power = paths.power.mean(axis=1)
        level = gather.choose_levels(kernel, splat, power, m, target_photons)
        inv_area = 1.0 / np.maximum(np.take_along_axis(kernel.area.T, level, axis=1), 1e-300)
        inv_area = inv_area * gather.linear_correction(kernel, splat, power, m, level, v, nrm)
        to_cam = cam - v[:, None, :]
        facing = np.einsum("nmi,ni->nm", to_cam, nrm) > 0
        pp, offsets, new_index = _padded_paths(paths)
        sp_ = _padded_splat(splat, new_index, len(v) * m)
        a = partial(jnp.asarray, dtype=dtype)
        i32 = partial(jnp.asarray, dtype=jnp.int32)
        data = _Data(
            ev_vertices=i32(pp["ev_vertices"].T), ev_bary=a(pp["ev_bary"].T), ev_cos_i=a(pp["ev_cos_i"]),
            ev_cos_o=a(pp["ev_cos_o"]), ev_theta_h=a(pp["ev_theta_h"]), ev_weight=a(pp["ev_weight"]),
            light=i32(pp["light"]), parent=i32(pp["parent"]), bounce=i32(pp["bounce"]), emitted=a(paths.emitted),
            proposal_power=a(pp["power"].T), path=i32(pp["path"]), kernel_nbr=i32(kernel.neighbours),
            kernel_w=a(kernel.weights), inv_area=a(inv_area), level=i32(level),
            splat=gather.Splat(*(i32(x) if x.dtype.kind in "iu" else a(x) for x in sp_)),
            facing=jnp.asarray(facing),
        )
        static = _Static(offsets, len(v), m, int(max_depth), int(max_rings) + 1)
        settings = dict(target_photons=target_photons, max_rings=max_rings, max_depth=max_depth,
                        first_bounce=first_bounce, dtype=dtype, vertices=v, faces=f, normals=nrm, cam_pos=cam)
        seconds = {"gather_setup": time.perf_counter() - t1}
        return cls(paths, data, static, jnp.asarray(new_index, jnp.int32), settings, seconds)

    @property
    def n_photons(self) -> int:
        """Number of stored photons (all lights)."""
        return len(self.paths.light)

    def indirect(self, pd, ps, alpha):
        """`(N, M, 3)` radiance [W/(sr m^2)] leaving each vertex toward its camera
        under each light, carried by light that reflected at least once, for Ward
        reflectance `pd` `(N, 3)`, `ps` `(N,)`, `alpha` `(N,)` [rad] (jit-compiled;
        0 where the vertex faces away from the camera)."""
        return _indirect(self.data, pd, ps, alpha, self.static)

    def powers(self, pd, ps, alpha):
        """`(P, 3)` photon powers [W] under the given reflectance (jit-compiled)."""
        return _powers_jit(self.data, self.real, pd, ps, alpha, self.static)

    def parts(self, power, alpha):
        """`(D, Q)` `(N, M, 3)` each from photon powers `(P, 3)`: the indirect
        radiance is `pd / pi * D + ps * Q`; `D` is the incident flux density
        [W/m^2] of light that reflected at least once, `Q` its Ward-lobe
        weighted sum [W/(sr m^2)] with roughness `alpha` `(N,)` (jit-compiled)."""
        return _parts_jit(self.data, self.real, power, alpha, self.static)

    def indirect_batches(self, pd, ps, alpha, batches: int = 8):
        """`(B, N, M, 3)` independent estimates of `indirect` from `B` disjoint
        groups of emitted photons (whole paths), each scaled to the full count:
        their mean is `indirect`, and their standard deviation over `sqrt(B)` is
        its Monte Carlo standard error (given the smoothing levels)."""
        if batches < 2:
            raise ValueError(f"batches must be >= 2, got {batches}")
        return _indirect_batches(self.data, pd, ps, alpha, self.static, int(batches))

    def indirect_variance(self, pd, ps, alpha, batches: int = 16):
        """`(N, M, 3)` Monte Carlo variance [(W/(sr m^2))^2] of `indirect` (given the
        smoothing levels), from the spread of its `batches` disjoint photon groups as in
        `indirect_batches`, accumulated one group at a time (memory of one `indirect`)."""
        if batches < 2:
            raise ValueError(f"batches must be >= 2, got {batches}")
        return _indirect_variance(self.data, pd, ps, alpha, self.static, int(batches))

    def ess(self, pd, ps, alpha):
        """`(M,)` effective sample size of each light's photons under the given
        reflectance as a fraction of their number: 1 at the proposal, falling as
        the importance weights spread; re-trace when it drops below ~0.3."""
        return _ess(self.data, pd, ps, alpha, self.static)

    def retrace(self, pd, ps, alpha, seed: int | None = None) -> "PhotonReplay":
        """A new replay of the same scene and settings with proposal `(pd, ps, alpha)`."""
        s = dict(self.settings)
        if "caster" not in s:
            raise ValueError("retrace: this replay was made from paths (from_paths); build one with build()")
        caster = s.pop("caster")
        args = [s.pop(k) for k in ("vertices", "faces", "normals", "light_pos", "intensity", "cam_pos")]
        if seed is not None:
            s["seed"] = seed
        pd, ps, alpha = (np.asarray(x, dtype=np.float64) for x in (pd, ps, alpha))
        return PhotonReplay.build(caster, *args, (pd, ps, alpha), **s)
