"""Specular evidence pooled across neighbouring points of the same material.

A point with one or two weak highlight samples cannot pin down its own ps and
roughness, but its neighbours of the same material saw the same lobe under
other half-vector angles. For every point, `pooled_specular` fits one
(ps, roughness) to the grey radiance of itself and its `k` nearest neighbours
(within `radius`) that have the same diffuse colour (`tau`), so a material
boundary does not bleed.
Only the lobe is shared: every neighbour keeps a diffuse albedo of its own,
fitted with the lobe (held fixed instead, a neighbour's albedo from a fit that
could not separate its lobe leaves a smooth trend that a broad lobe absorbs).

The fit is variable projection: given the roughness the model is linear in
the neighbours' albedos and ps, which are eliminated in closed form (one
2 x 2 block per neighbour), so the roughness is chosen on a log grid,
refined by a parabola through the best three grid values and a few Newton
steps; standard
deviations come from the Gauss-Newton covariance of (ps, ln roughness) with
the albedos profiled out. A pooled lobe, like a point's own, needs evidence:
two strong-specular (`T_spec`) samples among the same-material neighbours.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from . import brdf
from .classify import T_SPEC

__all__ = ["pooled_specular"]

_CHUNK = 2000
#: Roughness grid of the start: every other value of the shared grid (32, 3 mrad to 1.2 rad),
#: refined by a parabola and Newton steps.
_GRID = brdf.ROUGHNESS_GRID[::2]


def _quotient(num, den):
    """num / den, 0 where den is 0 (no data): a guard that also holds in float32."""
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _lobe(model, ln_rough, cos_i, cos_o, theta_r):
    """Unit-ps specular lobe of every sample `(K, M, C)` at ln roughness `(C,)` or scalar."""
    _, spec_fn = brdf.MODELS[model]
    return spec_fn(1.0, jnp.broadcast_to(ln_rough, cos_i.shape), cos_i, cos_o, theta_r)


@partial(jax.jit, static_argnames=("model",))
def _fit_chunk(y, e, w, cos_i, cos_o, theta_r, model):
    """One chunk, each `(K, M, C)` (neighbour, sample, point; the points last, so that every
    sum runs along them vectorised): grey radiance `y`, irradiance `e`, weights `w` (0:
    unused) and angles -> ps, ln roughness, std ps, std ln roughness `(C,)`.

    Model per neighbour k: `y_kj = d_k a_kj + ps b_kj`, `a = e / pi`, `b = e lobe`."""
    a = e / jnp.pi
    saa, say = jnp.sum(w * a * a, 1), jnp.sum(w * a * y, 1)  # (K, C)
    inv_aa = _quotient(1.0, saa)
    base = jnp.sum(jnp.sum(w * y * y, 1) - say * say * inv_aa, 0)  # cost of albedos alone (C,)

    def projected(b):
        """(num, den) of ps = num / den with every d_k eliminated, `(C,)` each."""
        sab = jnp.sum(w * a * b, 1)
        num = jnp.sum(jnp.sum(w * b * y, 1) - sab * say * inv_aa, 0)
        den = jnp.sum(jnp.sum(w * b * b, 1) - sab * sab * inv_aa, 0)
        return num, den, sab

    def cost_at(ln_r):
        num, den, _ = projected(e * _lobe(model, ln_r, cos_i, cos_o, theta_r))
        ps = jnp.maximum(_quotient(num, den), 0.0)
        return base - 2.0 * ps * num + ps * ps * den

    def grid_cost(_, ln_r):
        return None, cost_at(ln_r)

    logs = jnp.log(jnp.asarray(_GRID, dtype=e.dtype))
    _, cost_g = jax.lax.scan(grid_cost, None, logs)  # (G, C), one grid value at a time
    k = jnp.clip(jnp.argmin(cost_g, 0), 1, len(_GRID) - 2)
    pick = lambda arr, off: jnp.take_along_axis(arr, (k + off)[None], 0)[0]  # noqa: E731
    c0, c1, c2 = pick(cost_g, -1), pick(cost_g, 0), pick(cost_g, 1)
    curv = c0 - 2 * c1 + c2
    shift = jnp.where(curv > 0, 0.5 * (c0 - c2) / jnp.where(curv > 0, curv, 1.0), 0.0)
    spacing = logs[1] - logs[0]
    ln_r = logs[k] + jnp.clip(shift, -1.0, 1.0) * spacing

    # Newton steps from the parabola's minimum: the grid alone leaves errors comparable to
    # the standard deviations.
    def slope(lr):  # forward mode: each row's derivative (the rows are independent)
        return jax.jvp(cost_at, (lr,), (jnp.ones_like(lr),))[1]

    def newton(_, state):
        lr, c = state
        g, h = jax.jvp(slope, (lr,), (jnp.ones_like(lr),))
        step = jnp.clip(jnp.where(h > 0, g / jnp.where(h > 0, h, 1.0), 0.0), -spacing, spacing)
        trial = jnp.clip(lr - step, logs[0], logs[-1])
        c_t = cost_at(trial)
        better = c_t < c
        return jnp.where(better, trial, lr), jnp.where(better, c_t, c)

    ln_r, _ = jax.lax.fori_loop(0, 4, newton, (ln_r, cost_at(ln_r)))

    g, dg = jax.jvp(lambda lr: _lobe(model, lr, cos_i, cos_o, theta_r), (ln_r,), (jnp.ones_like(ln_r),))
    b = e * g
    num, den, sab = projected(b)
    ps = jnp.maximum(_quotient(num, den), 0.0)
    cost = jnp.maximum(base - 2.0 * ps * num + ps * ps * den, 0.0)
    # Gauss-Newton matrix of (ps, ln roughness), the albedos profiled out (Schur complement).
    d = ps[None, None] * e * dg
    sad = jnp.sum(w * a * d, 1)
    m_pp = den
    m_pd = jnp.sum(jnp.sum(w * b * d, 1) - sab * sad * inv_aa, 0)
    m_dd = jnp.sum(jnp.sum(w * d * d, 1) - sad * sad * inv_aa, 0)
    dof = jnp.sum(w > 0, (0, 1)) - jnp.sum(saa > 0, 0) - 2
    s2 = cost / jnp.maximum(dof, 1)
    det = m_pp * m_dd - m_pd * m_pd
    ok = (det > 1e-12 * m_pp * m_dd) & (det > 0) & (dof > 0)
    det = jnp.where(ok, det, 1.0)
    sd_ps = jnp.where(ok, jnp.sqrt(jnp.maximum(s2 * m_dd / det, 0.0)), jnp.inf)
    sd_lr = jnp.where(ok, jnp.sqrt(jnp.maximum(s2 * m_pp / det, 0.0)), jnp.inf)
    return ps, ln_r, sd_ps, sd_lr


def pooled_specular(rows: dict, pd: np.ndarray, vertices: np.ndarray, model: str, k: int = 12,
                    radius: float | None = None, tau: float = 0.05, min_snr: float = 3.0,
                    noise_floor: float = 0.0, where: np.ndarray | None = None) -> dict:
    """Shared-lobe fit of every point with its same-material neighbours.

    **Arguments:** `rows` from `local.prepare_rows`; `pd` `(N, 3)` each point's
    diffuse albedo (to group by material); `vertices` `(N, 3)`; `k` neighbours
    (self included); `radius` [m] (default: 4 x the median nearest-neighbour
    spacing); `tau`: neighbours whose albedo differs by more than `1.18 tau`
    (`exp(-d^2 / (2 tau^2)) < 1/2`) are another material and left out;
    `noise_floor` absolute radiance noise floor of the weights, as in
    `local.fit_rows`; `where` `(N,)` bool: the points to fit (default all).

    **Returns:** dict of `(N,)` arrays: `ps`, `roughness`, `std_ps`,
    `std_roughness`, and `identifiable` (two or more T_spec samples among the
    same-material neighbours, ps `min_snr` std above 0, roughness known to a
    factor e). Points not fitted (outside `where`, or without that T_spec
    evidence) are not identifiable, with ps and roughness 0 and infinite std.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    n, m = np.shape(rows["use"])
    tree = cKDTree(vertices)
    if radius is None:
        d1, _ = tree.query(vertices, k=2)
        radius = 4.0 * float(np.median(d1[:, 1]))
    dist, nbr = tree.query(vertices, k=min(k, n), distance_upper_bound=radius)
    present = np.isfinite(dist)
    nbr = np.where(present, nbr, np.arange(n)[:, None])
    # Same material or not: a neighbour counts fully or not at all (partial weights would
    # count as whole degrees of freedom while adding little residual: too small a std).
    same = (np.exp(-np.sum((pd[nbr] - pd[:, None]) ** 2, -1) / (2 * tau**2)) >= 0.5) & present  # (N, K)

    y, use = np.asarray(rows["y"]), np.asarray(rows["use"])
    # As for a single point (`local.fit_rows`): a lobe needs samples near its peak, here
    # two strong-specular (T_spec) ones among the same-material neighbours.
    spec = use & (np.asarray(rows["classes"]) == T_SPEC)
    evidence = np.sum(same * spec.sum(1)[nbr], 1) >= 2
    fit = evidence if where is None else evidence & np.asarray(where, bool)

    grey = np.mean(y, -1)  # (N, M): the lobe is grey
    # Method I's noise model (`local._noise_weights`): 1 % of the value, floored per point.
    floor = np.maximum(noise_floor, 1e-4 * np.max(np.where(use, grey, 0.0), 1, keepdims=True))
    var = (0.01 * grey) ** 2 + floor**2
    weight_obs = np.divide(1.0, var, out=np.zeros_like(var), where=use & (var > 0))
    per_point = [grey, np.where(use, np.asarray(rows["e"]), 0.0), weight_obs] + [
        np.asarray(rows[key]) for key in ("cos_i", "cos_o", "theta_r")]

    out = {key: np.zeros(n) for key in ("ps", "ln_r")}
    out.update({key: np.full(n, np.inf) for key in ("sd_ps", "sd_lr")})
    todo = np.flatnonzero(fit)
    for start in range(0, len(todo), _CHUNK):  # fixed-size chunks: one compilation, bounded memory
        idx = todo[start:start + _CHUNK]
        pad = _CHUNK - len(idx)
        chunk = []
        for i, field in enumerate(per_point):
            values = field[nbr[idx]]  # (C, K, M)
            if i == 2:
                values = values * same[idx][..., None]
            values = np.pad(values, [(0, pad), (0, 0), (0, 0)], constant_values=1.0 if i in (3, 4) else 0.0)
            chunk.append(np.ascontiguousarray(np.moveaxis(values, 0, -1)))  # (K, M, C)
        res = _fit_chunk(*[jnp.asarray(c) for c in chunk], model=model)
        for key, value in zip(("ps", "ln_r", "sd_ps", "sd_lr"), res):
            out[key][idx] = np.asarray(value)[: len(idx)]
    rough = np.where(fit, np.exp(out["ln_r"]), 0.0)
    identifiable = fit & (out["ps"] > min_snr * out["sd_ps"]) & (out["sd_lr"] < 1.0)
    std_rough = np.multiply(rough, out["sd_lr"], out=np.full(n, np.inf), where=np.isfinite(out["sd_lr"]))
    return {"ps": out["ps"], "roughness": rough, "std_ps": out["sd_ps"], "std_roughness": std_rough,
            "identifiable": identifiable}
