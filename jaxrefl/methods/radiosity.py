"""Method II: inverse radiosity (paper §4) — diffuse interreflections removed.

Patches are the mesh's vertices (`formfactors`). Units follow the design:
`pd` is an albedo, a Lambertian patch of irradiance `H` [W/m^2] has radiosity
`B = pd H` and radiance `B / pi`; a point light of intensity `Y` gives
`E = Y cos_i / C^2` (0 in shadow).

**Forward** (`solve_radiosity`): `B = pd (E + F B)` (Eq. 8, dark room: no
environment term) by a fixed-point iteration inside `jit`.

**Inverse** (`inverse_radiosity`): for each light configuration `c` the
irradiance of patch `u` is `H_uc = E_uc + sum_v F_uv B_vc`, where `B_vc` is
the observed radiosity `pi y` where `v` was seen diffuse-only (`T_diff`) under
that light, and the current estimate's forward value `pd_v H_vc` elsewhere.
`pd_u` is the least-squares fit of `B = pd H` over all the `T_diff`
observations of `u` (per channel), which is Eq. 9 generalised to many lights.
The two steps iterate to a fixed point (Anderson acceleration driven from the
host: the sparse products `F B` by scipy's CSR kernel in threads, the per-point
updates in jit; each of the `outer` passes starts from the last one's fixed point).
`paper=True` keeps the paper's combination instead: the single best `T_diff`
sample per patch (Eq. 9 with one light) and other patches' radiosities Lambert-rescaled from their own observation (Eq. 10, which
ignores interreflection in the rescaling).

**Per-point lights** (the rotating scanner head: `light_pos` `(N, M, 3)`):
every observation has its own light. Direct irradiance is always exact, so is
the first interreflection bounce (`first_bounce_correction`); later bounces use
light configurations made by binning each rack light's positions in cells of
`light_bin` metres (`light_configs`). The work is the products `F B` over all
configurations (`N x C x 3`); estimating a region (`points`) makes only the
configurations its observations use.

**Specular** (`estimate_radiosity`): the interreflected diffuse radiance
`pd I / pi` is subtracted from every observation and Method I (`local`) fits
ps, roughness and pd jointly on the rest (with the shared reflectance prior, and
the sensor's quantisation step of the original radiance). That pd, from every sample,
is the estimate; the inverse radiosity's (from the `T_diff` samples) only makes the
interreflection. `paper=True` keeps the inverse-radiosity pd wherever the point has an
observation, as the paper does.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.formfactors import FormFactors, form_factors
from ..geometry.raycast import RayCaster, default_threads
from ..reflectance import brdf
from ..reflectance.classify import T_DIFF, Thresholds
from ..reflectance.fill import vertex_adjacency, window_fill
from ..result import Estimate
from ..scan import checks
from .local import LocalOptions, estimate_local, prepare_rows, quantisation_step

__all__ = ["RadiosityOptions", "LightConfigs", "light_configs", "direct_irradiance", "solve_radiosity",
           "first_bounce_correction", "inverse_radiosity", "restrict_configs", "estimate_radiosity",
           "relight_indirect", "relight_observations"]

_HOST_WORK = 1 << 20  # nonzeros x columns above which a product is split over threads
_CONFIG_STEP = 16  # light configurations are padded to a multiple of this (fewer compilations)
logger = logging.getLogger(__name__)


class _Sparse:
    """`F` as scipy CSR row blocks of about equal nonzeros, one per thread: `F @ b` on
    the host (scipy's kernel releases the GIL). On CPU this is many times faster than
    a gather + segment sum in XLA, which materialises an `(nnz, K)` temporary."""

    def __init__(self, ff: FormFactors, dtype):
        m = ff.matrix.astype(dtype)
        m.sort_indices()
        self.n, self.nnz = m.shape[0], m.nnz
        self.rows = jnp.asarray(ff.rows)  # COO rows and columns for the per-entry correction
        self.cols = jnp.asarray(ff.cols)
        parts = default_threads()
        cuts = np.searchsorted(m.indptr, np.linspace(0, m.nnz, parts + 1)[1:-1])
        self.blocks = [(int(a), int(b), m[a:b]) for a, b in zip(np.r_[0, cuts], np.r_[cuts, self.n]) if b > a]
        self.whole = m

    def __matmul__(self, b):
        b = np.ascontiguousarray(b)
        shape = b.shape
        b = b.reshape(self.n, -1)
        if self.nnz * b.shape[1] < _HOST_WORK or len(self.blocks) < 2:
            return (self.whole @ b).astype(b.dtype, copy=False).reshape(shape)
        out = np.empty_like(b)

        def block(part):
            r0, r1, m = part
            out[r0:r1] = m @ b

        with ThreadPoolExecutor(len(self.blocks)) as pool:
            list(pool.map(block, self.blocks))
        return out.reshape(shape)


def _anderson(fun, init, tol, max_iter, history: int = 5, ridge: float = 1e-10):
    """Anderson acceleration (mixing 1, `history` last iterates) of the fixed point
    `x = fun(x)` for a tuple of arrays, driven from the host so that every
    iteration costs one `fun` and a few passes over the state. Stops when the
    residual `|fun(x) - x|` is at most `tol` times `|init|`.

    **Returns:** `fun(x)` at the last iterate (tuple of arrays), iterations
    (evaluations of `fun`), relative residual.

    Not `jaxopt.AndersonAcceleration`: measured on the 642-patch furnace (tol 1e-12), it reaches the same B
    (1.5e-12) but, jitted with `F @ b` as a `pure_callback`, takes 82 iterations and 2 s (a compile per
    solve) against 11 and 0.02 s here; unjitted (host `F @ b` as is) it is ~300x slower per iteration."""
    shapes = [np.shape(a) for a in init]
    x = [np.asarray(a).ravel() for a in init]
    scale = float(np.sqrt(sum(float(np.dot(a, a)) for a in x))) + 1e-30
    xs = [np.empty((history, a.size), a.dtype) for a in x]
    rs = [np.empty((history, a.size), a.dtype) for a in x]
    gram = np.zeros((history, history))
    err = np.inf
    for it in range(1, max_iter + 1):
        fx = [np.asarray(a).ravel() for a in fun(*[a.reshape(s) for a, s in zip(x, shapes)])]
        r = [f - a for f, a in zip(fx, x)]
        pos, k = (it - 1) % history, min(it, history)
        for h, v in zip(xs + rs, x + r):
            h[pos] = v
        row = sum(np.asarray(h[:k] @ v, np.float64) for h, v in zip(rs, r))
        gram[pos, :k] = gram[:k, pos] = row
        err = float(np.sqrt(max(gram[pos, pos], 0.0)))
        if err <= tol * scale or it == max_iter:
            break
        # mixing weights: min |sum_i a_i r_i| subject to sum_i a_i = 1
        g = gram[:k, :k] + ridge * max(np.trace(gram[:k, :k]) / k, 1e-300) * np.eye(k)
        try:
            a = np.linalg.solve(g, np.ones(k))
            a = a / a.sum()
        except np.linalg.LinAlgError:
            a = None
        if a is None or not np.all(np.isfinite(a)):
            x = fx  # plain iteration
            continue
        a = a.astype(x[0].dtype)
        x = [a @ hx[:k] + a @ hr[:k] for hx, hr in zip(xs, rs)]
    return tuple(f.reshape(s) for f, s in zip(fx, shapes)), it, err / scale


@jax.jit
def _forward_step(pd, e, inter):
    return pd[:, None, :] * (e[..., None] + inter)


def solve_radiosity(ff: FormFactors, pd, e_direct, tol: float = 1e-8, max_iter: int = 200):
    """Forward radiosity `B = pd (E + F B)`.

    **Arguments:** `ff` form factors `(P, P)`; `pd` `(P, 3)` albedo; `e_direct`
    `(P, C)` direct irradiance [W/m^2] under `C` lights; `tol` relative
    residual; `max_iter` iterations at most.

    **Returns:** `B` `(P, C, 3)` radiosity [W/m^2] and the iteration count.
    """
    pd, e = jnp.asarray(pd), jnp.asarray(e_direct)
    f = _Sparse(ff, pd.dtype)
    b0 = np.asarray(_forward_step(pd, e, jnp.zeros(e.shape + (3,), pd.dtype)))
    (b,), iters, _ = _anderson(lambda b: (_forward_step(pd, e, f @ b),), (b0,), tol, max_iter)
    return np.asarray(b), int(iters)


def direct_irradiance(caster: RayCaster, normals, light_pos, intensity, vertices=None) -> np.ndarray:
    """`(P, C)` irradiance [W/m^2] `Y cos_i / C^2` at mesh vertices from point lights
    `light_pos` `(C, 3)` or `(P, C, 3)` of intensity `intensity` `(C,)` [W/sr], 0 in shadow."""
    idx = np.arange(len(caster.vertices)) if vertices is None else np.asarray(vertices)
    x = caster.vertices[idx]
    pos = np.asarray(light_pos, dtype=np.float64)
    d = (pos if pos.ndim == 3 else pos[None]) - x[:, None, :]
    dist2 = np.maximum(np.einsum("pcj,pcj->pc", d, d), 1e-300)
    cos = np.einsum("pcj,pj->pc", d, np.asarray(normals)[idx]) / np.sqrt(dist2)
    lit = cos > 0
    vis = caster.visibility(pos if pos.ndim == 3 else pos, vertices=idx, where=lit)
    return np.where(vis, np.asarray(intensity, dtype=np.float64)[None, :] * cos / dist2, 0.0)


def relight_indirect(vertices, faces, normals, pd, light_pos, intensity, *, rays: int = 256,
                     caster: RayCaster | None = None, **_unused) -> np.ndarray:
    """Interreflected diffuse radiance `(N, 3)` [W/m^2/sr] leaving each vertex under one
    point light (`light_pos` `(3,)`, `intensity` [W/sr]): `pd (F B) / pi` with `B`
    the forward radiosity. Specular interreflection is not modelled (that is
    Method III); extra keyword arguments (ps, roughness, camera) are ignored."""
    caster = caster or RayCaster(vertices, faces)
    ff = form_factors(vertices, faces, normals, rays=rays, caster=caster)
    e = direct_irradiance(caster, normals, np.reshape(light_pos, (1, 3)), np.reshape(intensity, (1,)))
    b, _ = solve_radiosity(ff, pd, e)
    return np.asarray(pd) * (ff.matrix @ b[:, 0]) / np.pi


def relight_observations(scan, pd, *, light_bin: float = 0.1, rays: int = 256,
                         caster: RayCaster | None = None) -> np.ndarray:
    """Interreflected diffuse radiance `(N, M, 3)` [W/m^2/sr] of every observation of
    `scan` (its lights and intensities; `light_pos` `(M, 3)` or per point `(N, M, 3)`,
    binned into configurations by `light_configs` with `light_bin`) for albedo `pd`
    `(N, 3)`: `relight_indirect` for all configurations in one solve."""
    caster = caster or RayCaster(scan.vertices, scan.faces)
    configs = light_configs(scan.light_pos, scan.n_points, light_bin)
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=rays, caster=caster)
    e = direct_irradiance(caster, scan.normals, configs.positions, scan.intensities()[configs.light])
    b, _ = solve_radiosity(ff, pd, e)
    n, c = e.shape
    fb = np.asarray(ff.matrix @ np.asarray(b, np.float64).reshape(n, c * 3)).reshape(n, c, 3)
    fb = np.take_along_axis(fb, configs.index[..., None], axis=1)
    return np.asarray(pd, np.float64)[:, None, :] * fb / np.pi


# -- light configurations ---------------------------------------------------------------------------


class LightConfigs(NamedTuple):
    """Physical light positions the interreflection is solved for.

    `positions` `(C, 3)` [m]; `light` `(C,)` which of the `M` lights each is;
    `index` `(N, M)` the configuration of each observation.
    """

    positions: np.ndarray
    light: np.ndarray
    index: np.ndarray


def light_configs(light_pos, n_points: int, light_bin: float = 0.1) -> LightConfigs:
    """Light configurations for `light_pos` `(M, 3)` (one each) or `(N, M, 3)`: each
    light's per-point positions binned in cubes of `light_bin` metres, a bin's
    configuration at the mean of its positions (`light_bin = 0`: every distinct position)."""
    pos = np.asarray(light_pos, dtype=np.float64)
    if pos.ndim == 2:
        m = len(pos)
        return LightConfigs(pos, np.arange(m), np.broadcast_to(np.arange(m), (n_points, m)).copy())
    n, m, _ = pos.shape
    positions, light, index, offset = [], [], np.empty((n, m), np.int64), 0
    for j in range(m):  # a loop over lights (tens), not points
        p = pos[:, j]
        keys = np.floor(p / light_bin).astype(np.int64) if light_bin > 0 else p
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        k = inv.max() + 1
        counts = np.bincount(inv, minlength=k)
        means = np.stack([np.bincount(inv, p[:, a], minlength=k) for a in range(3)], 1) / counts[:, None]
        positions.append(means)
        light.append(np.full(k, j))
        index[:, j] = inv + offset
        offset += k
    return LightConfigs(np.concatenate(positions), np.concatenate(light), index)


def config_cameras(scan, configs: LightConfigs) -> np.ndarray:
    """`(N, C, 3)` camera of each (point, configuration): the observation's camera where
    the point is observed under that configuration, else a point on its normal (a
    gather there is never used)."""
    out = scan.vertices[:, None, :] + scan.normals[:, None, :] + np.zeros((1, len(configs.positions), 1))
    out[np.arange(scan.n_points)[:, None], configs.index] = scan.camera_positions()
    return out


def first_bounce_correction(caster: RayCaster, ff: FormFactors, normals, light_pos, configs: LightConfigs,
                            intensity, *, e_cfg=None, points=None) -> np.ndarray:
    """`(nnz, M)` exact-light correction of the first interreflection bounce for
    per-point lights: entry `k` of `F` (row `u`, column `v`) times the change in
    `v`'s direct irradiance between `u`'s own light `light_pos[u, m]` and the
    binned configuration `configs.index[u, m]`. The interreflected irradiance of
    observation `(u, m)` is then `(F B_c)_u + sum_k D_km pd_v`: the first bounce
    exact, later bounces from the configuration. One shadow ray per entry and
    light, all in one Embree batch; the configuration's irradiance is read from
    `e_cfg` `(N, C)` (`direct_irradiance` of `configs`: the same rays) when given.
    `points` `(N,)` bool: only the rows of these points (the others are 0)."""
    pos = np.asarray(light_pos, dtype=np.float64)
    m = pos.shape[1]
    keep = np.arange(len(ff.rows)) if points is None else np.flatnonzero(np.asarray(points)[ff.rows])
    rows, cols = ff.rows[keep].astype(np.int64), ff.cols[keep].astype(np.int64)
    y = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (m,))
    normals = np.asarray(normals, dtype=np.float64)
    x, n_v, n_off = caster.vertices[cols], normals[cols], caster.offset_normals[cols]

    def irradiance(target):  # (K, M, 3) light positions -> (K, M) direct irradiance at the columns
        d = target - x[:, None]
        dist2 = np.maximum(np.einsum("kmj,kmj->km", d, d), 1e-300)
        cos = np.einsum("kmj,kj->km", d, n_v) / np.sqrt(dist2)
        lit = np.flatnonzero(cos > 0)
        k = lit // m
        free = ~caster.segments_blocked(x[k], n_off[k], target.reshape(-1, 3)[lit])
        e = np.zeros(cos.size)
        e[lit[free]] = (y[None] * cos / dist2).ravel()[lit[free]]
        return e.reshape(cos.shape)

    exact = irradiance(pos[rows])
    if e_cfg is not None:
        binned = np.asarray(e_cfg)[cols[:, None], configs.index[rows]]
    else:
        binned = irradiance(configs.positions[configs.index[rows]])
    out = np.zeros((len(ff.rows), m))
    out[keep] = ff.values[keep, None] * (exact - binned)
    return out


# -- inverse radiosity ----------------------------------------------------------------------------


@jax.jit
def _observed_inter(inter, pd, index, rows, cols, correction):
    """`(N, M, 3)` interreflected irradiance of each observation: the configuration's
    `inter` `(N, C, 3)` at `index` `(N, M)` plus the first-bounce `correction` `(nnz, M)`."""
    out = jnp.take_along_axis(inter, index[..., None], axis=1)
    if correction is not None:
        out = out + jax.ops.segment_sum(correction[..., None] * pd[cols][:, None, :], rows,
                                        num_segments=pd.shape[0], indices_are_sorted=True)
    return out


@partial(jax.jit, static_argnames=("paper",))
def _inverse_step(pd, b, inter, e_cfg, b_obs, weight, e_obs, index, rows, cols, correction, cfg_obs, b_cfg_obs,
                  b_lambert, pd0, free, paper):
    """One step of the inverse fixed point given `inter = F b`: pd by least squares over
    the weighted samples (points in `free` with a sample), then the forward radiosity. The
    least squares is bounded, `0 <= pd <= 1`: per channel a 1-D quadratic, whose bounded
    minimum is its free minimum moved into the interval."""
    h = e_obs[..., None] + _observed_inter(inter, pd, index, rows, cols, correction)
    num = jnp.sum(jnp.where(weight[..., None], b_obs * h, 0.0), 1)
    den = jnp.sum(jnp.where(weight[..., None], h * h, 0.0), 1)
    fit = free & weight.any(1)
    pd_new = jnp.where(fit[:, None], jnp.clip(num / jnp.where(den > 0, den, 1.0), 0.0, 1.0), pd0)
    forward = b_lambert if paper else pd_new[:, None, :] * (e_cfg[..., None] + inter)
    return pd_new, jnp.where(cfg_obs[..., None], b_cfg_obs, forward)


class InverseResult(NamedTuple):
    """`pd` `(N, 3)`; `interreflected` `(N, M, 3)` irradiance [W/m^2] from the rest of
    the object at each observation (0 outside `points`); `has_diffuse` `(N,)`;
    `iterations`; `residual` (relative fixed-point error); `radiosity` `(N, C, 3)`
    [W/m^2] per configuration (a warm start for another solve)."""

    pd: np.ndarray
    interreflected: np.ndarray
    has_diffuse: np.ndarray
    iterations: int
    residual: float
    radiosity: np.ndarray | None = None


def inverse_radiosity(ff: FormFactors, configs: LightConfigs, e_cfg, radiance, observed, e_obs, pd0,
                      *, correction=None, paper: bool = False, tol: float = 1e-7,
                      max_iter: int = 200, points=None, init=None) -> InverseResult:
    """Inverse radiosity fixed point (module docstring).

    **Arguments:** `ff` `(N, N)`; `configs` light configurations (`C`); `e_cfg`
    `(N, C)` direct irradiance under each configuration; `radiance` `(N, M, 3)`
    observed; `observed` `(N, M)` bool, the `T_diff` samples used; `e_obs`
    `(N, M)` direct irradiance of each observation; `pd0` `(N, 3)` start, kept
    where a point has no sample; `correction` `(nnz, M)` from
    `first_bounce_correction` for per-point lights; `points` `(N,)` bool: fit
    only these points' pd (the others keep `pd0`; default all); `init` `(pd,
    radiosity)` of an earlier solve with the same configurations (warm start).
    """
    n, m = observed.shape
    c = len(configs.positions)
    dtype = jnp.asarray(np.zeros(1)).dtype
    free = np.ones(n, bool) if points is None else np.asarray(points, bool)
    observed = observed & free[:, None]
    b_obs = np.pi * np.where(observed[..., None], radiance, 0.0)
    cfg_obs = np.zeros((n, c), bool)
    b_cfg_obs = np.zeros((n, c, 3))
    rr, mm = np.nonzero(observed)
    if correction is not None:  # observations are under their own lights, not the configuration's
        rr, mm = rr[:0], mm[:0]
    cfg_obs[rr, configs.index[rr, mm]] = True
    b_cfg_obs[rr, configs.index[rr, mm]] = b_obs[rr, mm]
    # Eq. 10: a patch's radiosity under another light from its own best T_diff sample by Lambert's law
    best = np.argmax(np.where(observed, e_obs, -1.0), axis=1)
    idx = np.arange(n)
    pd_lambert = np.where(observed[idx, best][:, None],
                          np.clip(b_obs[idx, best] / np.maximum(e_obs[idx, best], 1e-300)[:, None], 0.0, 1.0), pd0)
    e_cfg = np.asarray(e_cfg)
    b_lambert = pd_lambert[:, None, :] * e_cfg[..., None]
    # paper: only the best T_diff sample (largest direct irradiance among them) counts
    weight = (np.eye(m, dtype=bool)[best] & observed) if paper else observed
    if init is None:
        init = (pd0, np.where(cfg_obs[..., None], b_cfg_obs, pd0[:, None, :] * e_cfg[..., None]))
    # dark configurations up to a multiple of _CONFIG_STEP: a region's solve compiles once per size class
    pad = ((0, 0), (0, -c % _CONFIG_STEP))
    e_cfg, cfg_obs, init = np.pad(e_cfg, pad), np.pad(cfg_obs, pad), (init[0], np.pad(init[1], pad + ((0, 0),)))
    b_cfg_obs, b_lambert = np.pad(b_cfg_obs, pad + ((0, 0),)), np.pad(b_lambert, pad + ((0, 0),))
    f = _Sparse(ff, dtype)
    index = jnp.asarray(np.clip(configs.index, 0, c - 1))  # rows outside `points` may have none (< 0)
    corr = None if correction is None else jnp.asarray(correction, dtype)
    consts = tuple(jnp.asarray(a, dtype) for a in (e_cfg, b_obs)) + (jnp.asarray(weight),) + (
        jnp.asarray(e_obs, dtype), index, f.rows, f.cols, corr, jnp.asarray(cfg_obs),
        jnp.asarray(b_cfg_obs, dtype), jnp.asarray(b_lambert, dtype), jnp.asarray(pd0, dtype), jnp.asarray(free))

    def step(pd, b):
        return _inverse_step(jnp.asarray(pd), jnp.asarray(b), jnp.asarray(f @ b), *consts, paper=paper)

    init = tuple(np.asarray(a, dtype) for a in init)
    (pd, b), iters, err = _anderson(step, init, tol, max_iter)
    inter = np.asarray(_observed_inter(jnp.asarray(f @ b), jnp.asarray(pd), index, f.rows, f.cols, corr))
    inter = np.where(free[:, None, None], inter, 0.0)
    return InverseResult(np.asarray(pd, np.float64), inter, observed.any(1), int(iters), float(err), b[:, :c])


def restrict_configs(configs: LightConfigs, points) -> LightConfigs:
    """The configurations observations of `points` `(N,)` bool use, renumbered; `index`
    is -1 for the other points."""
    used = np.unique(configs.index[np.asarray(points, bool)])
    remap = np.full(len(configs.positions), -1)
    remap[used] = np.arange(len(used))
    index = np.where(np.asarray(points, bool)[:, None], remap[configs.index], -1)
    return LightConfigs(configs.positions[used], configs.light[used], index)


@dataclass(frozen=True)
class RadiosityOptions:
    """Method II settings. `rays` per patch for the form factors; `light_bin` [m]
    for per-point lights (`exact_first_bounce`: the first interreflection bounce
    from each observation's own light, see `first_bounce_correction`); `paper` Eq. 9 from one light + Eq. 10 rescaling (also
    passed to the specular step); `outer` alternations of pd (inverse radiosity) and the specular part
    (Method I); `local` options of the Method I specular step."""

    rays: int = 256
    seed: int = 0
    light_bin: float = 0.1
    paper: bool = False
    tol: float = 1e-7
    max_iter: int = 200
    outer: int = 3
    exact_first_bounce: bool = True
    local: LocalOptions = field(default_factory=LocalOptions)

    @property
    def thresholds(self) -> Thresholds:
        return self.local.thresholds


def estimate_radiosity(scan, options: RadiosityOptions = RadiosityOptions(),
                       caster: RayCaster | None = None, points=None) -> Estimate:
    """Method II on a scan with radiance: the interreflected diffuse light by inverse
    radiosity, then pd, ps and roughness by Method I on the observations less that light.

    `points` `(N,)` bool (default all): estimate only these points (`--method auto`'s
    regions). The other points' albedo enters the radiosity as a fixed source (Method
    I's, after the first pass), and only the light configurations and first-bounce
    rays the observations of `points` need are made, so the cost shrinks with the
    region; outside `points` the result is Method I's.

    **Returns:** `Estimate` with `meta['method'] == 'radiosity'` (iterations,
    form-factor statistics and seconds per stage in `meta`; `meta['residual_scale']` that of
    the last Method I fit, on the images less the interreflected diffuse light, its `region_median`
    over `points`: what the diffuse interreflection leaves unexplained there).
    """
    scan, top = checks.method_input(scan)  # top: called by the user, not by another method
    region = np.ones(scan.n_points, bool) if points is None else np.asarray(points, bool)
    if region.shape != (scan.n_points,) or not region.any():
        raise ValueError(f"points: must be ({scan.n_points},) bool with at least one True")
    # Unresolved lobes from the nearest measured ones (`LocalOptions.material_fill`): what is left
    # after the diffuse interreflection still holds the specular one, which a material's joint
    # fit without a measured lobe may take for its own.
    # Method I on what is left after the interreflected light: none left to report (`interreflection_rays`)
    local_options = dataclasses.replace(options.local, paper=options.paper, material_fill=False,
                                        interreflection_rays=0)
    timings = {}
    t0 = time.perf_counter()
    caster = caster or RayCaster(scan.vertices, scan.faces)
    rows = prepare_rows(scan, options.thresholds, caster)
    timings["classify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=options.rays, seed=options.seed,
                      caster=caster)
    timings["form_factors"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    configs = light_configs(scan.light_pos, scan.n_points, options.light_bin)
    if points is not None:
        configs = restrict_configs(configs, region)
    e_cfg = direct_irradiance(caster, scan.normals, configs.positions, scan.intensities()[configs.light])
    correction = None
    if scan.light_pos.ndim == 3 and options.exact_first_bounce:
        correction = first_bounce_correction(caster, ff, scan.normals, scan.light_pos, configs,
                                             scan.intensities(), e_cfg=e_cfg,
                                             points=None if points is None else region)
    timings["direct"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    use, y, e = rows["use"], rows["y"], rows["e"]
    # The residuals below are off the sensor's lattice: Method I is told its step.
    q_step = quantisation_step(scan.radiance, use)
    has_diffuse = (use & (rows["classes"] == T_DIFF)).any(1)
    # Samples for pd: the T_diff ones where a point has any, else all of its samples with the
    # current specular estimate taken off (it starts at zero and is refined by the outer loop).
    sample = np.where(has_diffuse[:, None], use & (rows["classes"] == T_DIFF), use)
    pd0 = np.pi * np.einsum("nm,nmc->nc", np.where(sample, e, 0.0), y) \
        / np.maximum(np.einsum("nm,nm->n", np.where(sample, e, 0.0), e), 1e-300)[:, None]
    seen = use.any(1)
    if seen.any() and not seen.all():
        pd0[~seen] = window_fill(pd0, seen, vertex_adjacency(scan.faces, scan.n_points)).values[~seen]
    pd0 = np.clip(pd0, 0.0, 1.0)
    lobe = brdf.MODELS[options.local.model][1]
    specular = np.zeros(use.shape)
    history, inv = [], None
    timings["inverse_radiosity"] = timings["local"] = 0.0
    for _ in range(options.outer):
        t0 = time.perf_counter()
        # each pass starts from the last one's fixed point (the same fixed point, fewer iterations)
        inv = inverse_radiosity(ff, configs, e_cfg, np.maximum(y - specular[..., None], 0.0), sample, e, pd0,
                                correction=correction, paper=options.paper, tol=options.tol, max_iter=options.max_iter,
                                points=None if points is None else region,
                                init=None if inv is None else (pd0, inv.radiosity))
        timings["inverse_radiosity"] += time.perf_counter() - t0
        # Specular: Method I on what is left after the interreflected diffuse light.
        t0 = time.perf_counter()
        reflected = inv.pd[:, None, :] * inv.interreflected / np.pi
        residual = np.where(use[..., None], np.maximum(scan.radiance - reflected, 0.0), scan.radiance)
        est = estimate_local(dataclasses.replace(scan, radiance=residual.astype(scan.radiance.dtype)),
                             local_options, caster, quantisation=q_step, region=region)
        timings["local"] += time.perf_counter() - t0
        # T_diff samples are free of specular light by construction (theta_r > theta_th1), so
        # only points without one take the specular estimate off their samples.
        new = np.where(use & ~has_diffuse[:, None], e * np.asarray(lobe(est.ps[:, None], np.log(np.maximum(est.roughness, 1e-12))[:, None],
                                                 rows["cos_i"], rows["cos_o"], rows["theta_r"])), 0.0)
        history.append({"iterations": inv.iterations, "fixed_point_residual": inv.residual,
                        "specular_change": float(np.abs(new - specular).max() / max(np.abs(y).max(), 1e-300))})
        specular, pd0 = new, np.where(region[:, None], inv.pd, est.pd)

    pd = est.pd.copy()
    if options.paper:
        pd[seen & region] = inv.pd[seen & region]
    # Otherwise pd is the last Method I fit's: on the observations less the interreflected
    # diffuse light, jointly with the lobe, over every sample (a broad lobe leaves light in
    # T_diff samples too), with material-mates' pd as a prior; the inverse radiosity's own pd
    # (T_diff samples only) gave that interreflection and agrees with it up to noise.
    np.nan_to_num(pd, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.clip(pd, 0.0, 1.0, out=pd)  # already so (bounded fits); kept for every path
    meta = dict(est.meta)
    meta.update({
        "method": "radiosity",
        "options": {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v)
                    for k, v in asdict(options).items()},
        "seconds": {**timings, "local_stages": est.meta["seconds"]},
        "outer_iterations": history,
        "form_factors": {"rays": ff.rays, "nonzeros": int(len(ff.values)), "bytes": ff.nbytes,
                         "mean_row_sum": float(ff.row_sums.mean()), "max_row_sum": float(ff.row_sums.max())},
        "light_configurations": int(len(configs.positions)),
        "points_estimated": int(region.sum()),
    })
    est = dataclasses.replace(est, pd=pd, meta=meta)
    if top:
        checks.estimate_warnings(est, logger)
    return est
