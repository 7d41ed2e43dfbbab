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
The two steps iterate to a fixed point (jaxopt Anderson acceleration, in one
jit). `paper=True` keeps the paper's combination instead: the single best
`T_diff` sample per patch (Eq. 9 with one light) and other patches'
radiosities Lambert-rescaled from their own observation (Eq. 10, which
ignores interreflection in the rescaling).

**Per-point lights** (the rotating scanner head: `light_pos` `(N, M, 3)`):
every observation has its own light. Direct irradiance is always exact;
the interreflected part uses light configurations made by binning each rack
light's positions in cells of `light_bin` metres (`light_configs`).

**Specular** (`estimate_radiosity`): the interreflected diffuse radiance
`pd I / pi` is subtracted from every observation and Method I (`local`) fits
ps and roughness on the rest; pd is the inverse-radiosity value wherever the
point has a `T_diff` sample.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxopt
import numpy as np

from . import brdf
from .classify import T_DIFF, Thresholds
from .fill import vertex_adjacency, window_fill
from .formfactors import FormFactors, form_factors
from .local import Estimate, LocalOptions, estimate_local, prepare_rows
from .raycast import RayCaster

__all__ = ["RadiosityOptions", "LightConfigs", "light_configs", "direct_irradiance", "solve_radiosity",
           "first_bounce_correction", "inverse_radiosity", "estimate_radiosity", "relight_indirect"]

_COLUMN_CHUNK = 48  # columns of B per sparse product (bounds the (nnz, k) gather)


# -- sparse products and the forward solve --------------------------------------------------------


def _apply(ff, b):
    """`F @ b` for `b` `(P, K)`; `ff` = (rows, cols, values) sorted by row."""
    rows, cols, values = ff
    n, k = b.shape

    def product(block):
        return jax.ops.segment_sum(values[:, None] * block[cols], rows, num_segments=n,
                                   indices_are_sorted=True)

    if k <= _COLUMN_CHUNK:
        return product(b)
    pad = -k % _COLUMN_CHUNK
    blocks = jnp.pad(b, ((0, 0), (0, pad))).reshape(n, -1, _COLUMN_CHUNK).transpose(1, 0, 2)
    out = jax.lax.map(product, blocks)
    return out.transpose(1, 0, 2).reshape(n, -1)[:, :k]


def _gather(ff, b):
    """`F @ b` for `b` `(P, C, 3)`."""
    p, c, _ = b.shape
    return _apply(ff, b.reshape(p, c * 3)).reshape(p, c, 3)


def _anderson(fun, init, args, tol, max_iter):
    """jaxopt Anderson acceleration with a tolerance relative to the size of the data."""
    scale = jnp.sqrt(sum(jnp.sum(jnp.square(x)) for x in jax.tree_util.tree_leaves(init)))
    solver = jaxopt.AndersonAcceleration(fun, history_size=5, maxiter=max_iter, tol=tol * (scale + 1e-30),
                                         implicit_diff=False, jit=True)
    sol = solver.run(init, *args)
    return sol.params, sol.state.iter_num, sol.state.error / (scale + 1e-30)


@partial(jax.jit, static_argnames=("max_iter",))
def _forward(ff, pd, e, tol, max_iter):
    def step(b, ff, pd, e):
        return pd[:, None, :] * (e[..., None] + _gather(ff, b))

    b0 = pd[:, None, :] * e[..., None]
    return _anderson(step, b0, (ff, pd, e), tol, max_iter)


def _jax_ff(ff: FormFactors):
    return (jnp.asarray(ff.rows), jnp.asarray(ff.cols), jnp.asarray(ff.values))


def solve_radiosity(ff: FormFactors, pd, e_direct, tol: float = 1e-8, max_iter: int = 200):
    """Forward radiosity `B = pd (E + F B)`.

    **Arguments:** `ff` form factors `(P, P)`; `pd` `(P, 3)` albedo; `e_direct`
    `(P, C)` direct irradiance [W/m^2] under `C` lights; `tol` relative
    residual; `max_iter` iterations at most.

    **Returns:** `B` `(P, C, 3)` radiosity [W/m^2] and the iteration count.
    """
    b, iters, _ = _forward(_jax_ff(ff), jnp.asarray(pd), jnp.asarray(e_direct),
                           tol, max_iter)
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
    return np.asarray(pd) * np.asarray(_gather(_jax_ff(ff), jnp.asarray(b)))[:, 0] / np.pi


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


def first_bounce_correction(caster: RayCaster, ff: FormFactors, normals, light_pos, configs: LightConfigs,
                            intensity) -> np.ndarray:
    """`(nnz, M)` exact-light correction of the first interreflection bounce for
    per-point lights: entry `k` of `F` (row `u`, column `v`) times the change in
    `v`'s direct irradiance between `u`'s own light `light_pos[u, m]` and the
    binned configuration `configs.index[u, m]`. The interreflected irradiance of
    observation `(u, m)` is then `(F B_c)_u + sum_k D_km pd_v`: the first bounce
    exact, later bounces from the configuration. One shadow ray per entry and light."""
    pos = np.asarray(light_pos, dtype=np.float64)
    rows, cols = ff.rows.astype(np.int64), ff.cols.astype(np.int64)
    y = np.asarray(intensity, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    x, n_off = caster.vertices[cols], caster.offset_normals[cols]
    out = np.empty((len(rows), pos.shape[1]))
    for m in range(pos.shape[1]):  # a loop over lights, each a batch of rays
        def irradiance(target):
            d = target - x
            dist2 = np.maximum(np.einsum("kj,kj->k", d, d), 1e-300)
            cos = np.einsum("kj,kj->k", d, normals[cols]) / np.sqrt(dist2)
            lit = cos > 0
            e = np.zeros(len(x))
            e[lit] = y[m] * cos[lit] / dist2[lit]
            e[lit] *= ~caster.segments_blocked(x[lit], n_off[lit], target[lit])
            return e

        exact = irradiance(pos[rows, m])
        binned = irradiance(configs.positions[configs.index[rows, m]])
        out[:, m] = ff.values * (exact - binned)
    return out


# -- inverse radiosity ----------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("max_iter", "paper"))
def _inverse(ff, e_cfg, b_obs, obs, e_obs, index, cfg_obs, b_cfg_obs, b_lambert, pd0, correction, tol, max_iter,
             paper):
    has_obs = obs.any(1)
    # paper: only the best T_diff sample (largest direct irradiance among them) counts
    best = jnp.argmax(jnp.where(obs, e_obs, -1.0), axis=1)
    weight = jnp.where(paper, jax.nn.one_hot(best, obs.shape[1], dtype=bool) & obs, obs)

    rows, cols, _ = ff
    n = pd0.shape[0]

    def at_observations(inter, pd):
        """(N, M, 3) interreflected irradiance of each observation."""
        out = jnp.take_along_axis(inter, index[..., None], axis=1)
        if correction is not None:
            out = out + jax.ops.segment_sum(correction[..., None] * pd[cols][:, None, :], rows,
                                            num_segments=n, indices_are_sorted=True)
        return out

    def step(state, *args):
        pd, b = state
        inter = _gather(ff, b)  # (P, C, 3) interreflected irradiance
        h = e_obs[..., None] + at_observations(inter, pd)
        num = jnp.sum(jnp.where(weight[..., None], b_obs * h, 0.0), 1)
        den = jnp.sum(jnp.where(weight[..., None], h * h, 0.0), 1)
        pd_new = jnp.where(has_obs[:, None], num / jnp.where(den > 0, den, 1.0), pd0)
        forward = jnp.where(paper, b_lambert, pd_new[:, None, :] * (e_cfg[..., None] + inter))
        b_new = jnp.where(cfg_obs[..., None], b_cfg_obs, forward)
        return pd_new, b_new

    init = (pd0, jnp.where(cfg_obs[..., None], b_cfg_obs, pd0[:, None, :] * e_cfg[..., None]))
    (pd, b), iters, err = _anderson(step, init, (), tol, max_iter)
    return pd, at_observations(_gather(ff, b), pd), iters, err


class InverseResult(NamedTuple):
    """`pd` `(N, 3)`; `interreflected` `(N, M, 3)` irradiance [W/m^2] from the rest of
    the object at each observation; `has_diffuse` `(N,)`; `iterations`; `residual`
    (relative fixed-point error)."""

    pd: np.ndarray
    interreflected: np.ndarray
    has_diffuse: np.ndarray
    iterations: int
    residual: float


def inverse_radiosity(ff: FormFactors, configs: LightConfigs, e_cfg, radiance, observed, e_obs, pd0,
                      *, correction=None, paper: bool = False, tol: float = 1e-7,
                      max_iter: int = 200) -> InverseResult:
    """Inverse radiosity fixed point (module docstring).

    **Arguments:** `ff` `(N, N)`; `configs` light configurations (`C`); `e_cfg`
    `(N, C)` direct irradiance under each configuration; `radiance` `(N, M, 3)`
    observed; `observed` `(N, M)` bool, the `T_diff` samples used; `e_obs`
    `(N, M)` direct irradiance of each observation; `pd0` `(N, 3)` start, kept
    where a point has no sample; `correction` `(nnz, M)` from
    `first_bounce_correction` for per-point lights.
    """
    n, m = observed.shape
    c = len(configs.positions)
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
    rows = np.arange(n)
    pd_lambert = np.where(observed[rows, best][:, None],
                          b_obs[rows, best] / np.maximum(e_obs[rows, best], 1e-300)[:, None], pd0)
    b_lambert = pd_lambert[:, None, :] * np.asarray(e_cfg)[..., None]
    pd, inter, iters, err = _inverse(_jax_ff(ff), jnp.asarray(e_cfg), jnp.asarray(b_obs), jnp.asarray(observed),
                                     jnp.asarray(e_obs), jnp.asarray(configs.index), jnp.asarray(cfg_obs),
                                     jnp.asarray(b_cfg_obs), jnp.asarray(b_lambert), jnp.asarray(pd0),
                                     None if correction is None else jnp.asarray(correction),
                                     tol, max_iter, paper)
    return InverseResult(np.asarray(pd), np.asarray(inter), observed.any(1), int(iters), float(err))


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
                       caster: RayCaster | None = None) -> Estimate:
    """Method II on a scan with radiance: pd by inverse radiosity, ps and roughness by
    Method I on the observations with the interreflected diffuse part removed.

    **Returns:** `Estimate` with `meta['method'] == 'radiosity'` (iterations,
    form-factor statistics and seconds per stage in `meta`).
    """
    if scan.radiance is None:
        raise ValueError("radiance: the scan has no observations to estimate from")
    local_options = dataclasses.replace(options.local, paper=options.paper)
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
    e_cfg = direct_irradiance(caster, scan.normals, configs.positions, scan.intensities()[configs.light])
    correction = None
    if scan.light_pos.ndim == 3 and options.exact_first_bounce:
        correction = first_bounce_correction(caster, ff, scan.normals, scan.light_pos, configs,
                                             scan.intensities())
    timings["direct"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    use, y, e = rows["use"], rows["y"], rows["e"]
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
    history = []
    timings["inverse_radiosity"] = timings["local"] = 0.0
    for _ in range(options.outer):
        t0 = time.perf_counter()
        inv = inverse_radiosity(ff, configs, e_cfg, np.maximum(y - specular[..., None], 0.0), sample, e, pd0,
                                correction=correction, paper=options.paper, tol=options.tol, max_iter=options.max_iter)
        timings["inverse_radiosity"] += time.perf_counter() - t0
        # Specular: Method I on what is left after the interreflected diffuse light.
        t0 = time.perf_counter()
        reflected = inv.pd[:, None, :] * inv.interreflected / np.pi
        residual = np.where(use[..., None], np.maximum(scan.radiance - reflected, 0.0), scan.radiance)
        est = estimate_local(dataclasses.replace(scan, radiance=residual.astype(scan.radiance.dtype)),
                             local_options, caster)
        timings["local"] += time.perf_counter() - t0
        # T_diff samples are free of specular light by construction (theta_r > theta_th1), so
        # only points without one take the specular estimate off their samples.
        new = np.where(use & ~has_diffuse[:, None], e * np.asarray(lobe(est.ps[:, None], np.log(np.maximum(est.roughness, 1e-12))[:, None],
                                                 rows["cos_i"], rows["cos_o"], rows["theta_r"])), 0.0)
        history.append({"iterations": inv.iterations, "fixed_point_residual": inv.residual,
                        "specular_change": float(np.abs(new - specular).max() / max(np.abs(y).max(), 1e-300))})
        specular, pd0 = new, inv.pd

    pd = est.pd.copy()
    pd[seen] = inv.pd[seen]
    np.nan_to_num(pd, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
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
    })
    return dataclasses.replace(est, pd=pd, meta=meta)
