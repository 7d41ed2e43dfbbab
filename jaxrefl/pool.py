"""Specular evidence pooled across neighbouring points of the same material.

A point with one or two weak highlight samples cannot pin down its own ps and
roughness, but its neighbours of the same material saw the same lobe under
other half-vector angles. For every point, `pooled_specular` fits one
(ps, roughness) to the grey specular residuals `s = y - E pd / pi` of itself
and its `k` nearest neighbours (within `radius`), each neighbour weighted by
how alike its diffuse colour is, `exp(-|pd_k - pd_i|^2 / (2 tau^2))`, so a
material boundary does not bleed. Each neighbour keeps its own pd (from the
local fit); only the lobe is shared.

The fit is variable projection: ps is linear given the roughness, so the
roughness is chosen on a dense log grid, refined by a parabola through the best
three grid values, and ps solved in closed form; standard deviations come from
the 2 x 2 Gauss-Newton covariance at the solution.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from . import brdf

__all__ = ["pooled_specular"]

_CHUNK = 2000


def _lobe(model, ln_rough, cos_i, cos_o, theta_r):
    _, spec_fn = brdf.MODELS[model]
    return spec_fn(1.0, ln_rough, cos_i, cos_o, theta_r)


@partial(jax.jit, static_argnames=("model",))
def _fit_chunk(s, e, w, cos_i, cos_o, theta_r, model):
    """One chunk: `s`, `e`, `w`, angles `(C, K*M)` -> ps, ln rough, std ps, std ln rough, cost, dof."""
    lobe = jax.vmap(jax.vmap(jax.vmap(partial(_lobe, model), in_axes=(None, 0, 0, 0)),
                             in_axes=(None, 0, 0, 0)), in_axes=(0, None, None, None))
    logs = jnp.log(jnp.asarray(brdf.ROUGHNESS_GRID))
    a = e[None] * lobe(logs, cos_i, cos_o, theta_r)  # (G, C, S)
    saa = jnp.sum(w[None] * a * a, -1)
    sas = jnp.sum(w[None] * a * s[None], -1)
    ps_g = jnp.maximum(sas / jnp.maximum(saa, 1e-300), 0.0)
    cost_g = jnp.sum(w[None] * (s[None] - ps_g[..., None] * a) ** 2, -1)  # (G, C)
    k = jnp.clip(jnp.argmin(cost_g, 0), 1, len(brdf.ROUGHNESS_GRID) - 2)
    pick = lambda arr, off: jnp.take_along_axis(arr, (k + off)[None], 0)[0]  # noqa: E731
    c0, c1, c2 = pick(cost_g, -1), pick(cost_g, 0), pick(cost_g, 1)
    step = logs[1] - logs[0]
    curv = c0 - 2 * c1 + c2
    shift = jnp.where(curv > 0, 0.5 * (c0 - c2) / jnp.where(curv > 0, curv, 1.0), 0.0)
    ln_r = logs[k] + jnp.clip(shift, -1.0, 1.0) * step

    def solve(ln_r_row, s_row, e_row, w_row, ci, co, th):
        g = jax.vmap(partial(_lobe, model), in_axes=(None, 0, 0, 0))(ln_r_row, ci, co, th)
        a_row = e_row * g
        ps = jnp.maximum(jnp.sum(w_row * a_row * s_row) / jnp.maximum(jnp.sum(w_row * a_row * a_row), 1e-300), 0.0)
        resid = s_row - ps * a_row
        # Gauss-Newton covariance of (ps, ln roughness).
        d_ln = jax.jacfwd(lambda lr: jax.vmap(partial(_lobe, model), in_axes=(None, 0, 0, 0))(lr, ci, co, th))(ln_r_row)
        jac = jnp.stack([a_row, ps * e_row * d_ln], -1) * jnp.sqrt(w_row)[:, None]
        jtj = jac.T @ jac
        dof = jnp.sum(w_row > 0) - 2
        s2 = jnp.sum(w_row * resid * resid) / jnp.maximum(dof, 1)
        det = jtj[0, 0] * jtj[1, 1] - jtj[0, 1] ** 2
        ok = (det > 1e-12 * jnp.maximum(jtj[0, 0] * jtj[1, 1], 1e-300)) & (dof > 0)
        det = jnp.where(ok, det, 1.0)
        var_ps = jnp.where(ok, s2 * jtj[1, 1] / det, jnp.inf)
        var_lr = jnp.where(ok, s2 * jtj[0, 0] / det, jnp.inf)
        return ps, jnp.sqrt(var_ps), jnp.sqrt(var_lr)

    ps, sd_ps, sd_lr = jax.vmap(solve)(ln_r, s, e, w, cos_i, cos_o, theta_r)
    return ps, ln_r, sd_ps, sd_lr


def pooled_specular(rows: dict, pd: np.ndarray, vertices: np.ndarray, model: str, k: int = 12,
                    radius: float | None = None, tau: float = 0.05, min_snr: float = 3.0) -> dict:
    """Shared-lobe fit of every point with its same-material neighbours.

    **Arguments:** `rows` from `local.prepare_rows`; `pd` `(N, 3)` each point's
    diffuse albedo (held fixed); `vertices` `(N, 3)`; `k` neighbours (self
    included); `radius` [m] (default: 4 x the median nearest-neighbour spacing);
    `tau` albedo distance at which a neighbour's weight falls to `e^-1/2`.

    **Returns:** dict of `(N,)` arrays: `ps`, `roughness`, `std_ps`,
    `std_roughness`, and `identifiable` (ps `min_snr` std above 0, roughness
    known to a factor e).
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
    colour = np.exp(-np.sum((pd[nbr] - pd[:, None]) ** 2, -1) / (2 * tau**2)) * present  # (N, K)

    y, e, use = np.asarray(rows["y"]), np.asarray(rows["e"]), np.asarray(rows["use"])
    grey_s = np.mean(y, -1) - e * np.mean(pd, -1)[:, None] / np.pi  # (N, M) per point
    weight_obs = np.where(use, 1.0 / np.maximum(np.mean(y, -1), 1e-3 * y.max()) ** 2, 0.0)

    def gather(a):
        return a[nbr].reshape(n, -1)

    w = (colour[..., None] * weight_obs[nbr]).reshape(n, -1)
    fields = [gather(grey_s), gather(e), w, gather(rows["cos_i"]), gather(rows["cos_o"]), gather(rows["theta_r"])]
    out = {key: np.empty(n) for key in ("ps", "ln_r", "sd_ps", "sd_lr")}
    for start in range(0, n, _CHUNK):  # fixed-size chunks: one compilation, bounded memory
        sl = slice(start, min(start + _CHUNK, n))
        chunk = [np.pad(f[sl], [(0, _CHUNK - (sl.stop - sl.start)), (0, 0)]) for f in fields]
        res = _fit_chunk(*[jnp.asarray(c) for c in chunk], model=model)
        for key, value in zip(("ps", "ln_r", "sd_ps", "sd_lr"), res):
            out[key][sl] = np.asarray(value)[: sl.stop - sl.start]
    rough = np.exp(out["ln_r"])
    identifiable = (out["ps"] > min_snr * out["sd_ps"]) & (out["sd_lr"] < 1.0)
    return {"ps": out["ps"], "roughness": rough, "std_ps": out["sd_ps"],
            "std_roughness": np.where(np.isfinite(out["sd_lr"]), rough * out["sd_lr"], np.inf),
            "identifiable": identifiable}
