"""Method I: dense inverse local rendering (paper §3).

Per point, from its classified samples (`classify`):

1. **pd** — default: least squares over all diffuse-only (`T_diff`) samples,
   `pd = pi sum(E y) / sum(E^2)` per channel, `E = Y cos_i / C^2`; `paper=True`:
   Eq. 5 with the single `T_diff` sample of smallest `theta_r`. A point with no
   `T_diff` sample starts from its least specular sample and is refined below.
2. **ps, roughness** — the grey specular part `s = y - E pd / pi` of the strong
   specular (`T_spec`) samples gives `z` with `ln z = a - b x`, linear in
   (`a`, `b`): Torrance-Sparrow `z = s cos_i cos_o / E`, `x = theta_r^2`,
   `a = ln ps`, `b = 1 / (2 sigma^2)` (Eq. 7: `z` is the paper's `i_s cos theta_v`
   with `Y / C^2` divided out); Ward `z = 4 pi s sqrt(cos_i cos_o) / E`,
   `x = tan^2 theta_r`, `a = ln(ps / alpha^2)`, `b = 1 / alpha^2`. Two samples
   give the closed form; more give weighted least squares in the log domain.
3. **Polish** — Levenberg-Marquardt on the full model over all valid samples
   (`T_diff`, `T_spec`, `T_none`), parameters `(pd_rgb, ps, ln roughness)` with
   bounds `0 <= pd <= 1`, `ps >= 0` enforced by projection in every step,
   residuals weighted by a noise model `sqrt((0.01 y)^2 + floor^2)`, from two
   starts (the closed form, and the best of a roughness grid with pd and ps
   solved linearly); the lower final cost wins. A fixed number of steps with
   the Jacobian written out, all points at once (vmap, `lax.map` over chunks,
   one jit). Standard deviations from the Gauss-Newton covariance.
4. **Identifiability** — the specular part counts as measured when the point
   has two or more usable `T_spec` samples, the fit is finite, and `ps` stands
   `min_snr` standard deviations above 0 with roughness known to a factor
   `e`. Otherwise ps and roughness come from the measured points in the
   `window`-ring (`fill.window_fill`, in the log domain) and pd is re-fitted
   with that specular part fixed (closed form).

Status per point: 0 `measured` (everything from its own samples), 1
`interpolated` (specular, or with no own sample pd too, from the window), 2
`unresolved` (nothing measured within the window: filled from farther away;
its standard deviations are infinite).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from . import brdf
from .classify import T_DIFF, T_INVALID, T_SPEC, Thresholds, classify_scan
from .fill import vertex_adjacency, window_fill
from .lm import covariance, spd_solve
from .pool import pooled_specular
from .raycast import RayCaster
from .rig import observation_geometry

__all__ = ["MEASURED", "INTERPOLATED", "UNRESOLVED", "LocalOptions", "Estimate", "estimate_local",
           "prepare_rows", "fit_rows", "specular_closed_form", "quantisation_step"]

MEASURED, INTERPOLATED, UNRESOLVED = 0, 1, 2
ROUGHNESS_NAME = {"torrance-sparrow": "sigma", "ward": "alpha"}
_LN_FLOOR = -30.0  # ln of a reflectance so small it is zero for every purpose


@dataclass(frozen=True)
class LocalOptions:
    """Options of Method I (see the module docstring)."""

    model: str = "torrance-sparrow"
    paper: bool = False
    steps: int = 15
    window: int = 5
    min_snr: float = 3.0
    solver: str = "lm"
    pool: bool = False
    pool_neighbours: int = 12
    pool_tau: float = 0.05
    thresholds: Thresholds = field(default_factory=Thresholds)

    def __post_init__(self):
        if self.model not in brdf.MODELS:
            raise ValueError(f"model must be one of {sorted(brdf.MODELS)}, got {self.model!r}")
        if self.solver not in ("lm", "optimistix"):
            raise ValueError(f"solver must be 'lm' or 'optimistix', got {self.solver!r}")
        if self.steps < 1:
            raise ValueError("steps must be >= 1")


@dataclass
class Estimate:
    """Per-point reflectance: `pd` `(N, 3)`, `ps` `(N,)`, `roughness` `(N,)`
    [rad] (sigma or alpha, per `model`), `status` `(N,)` int8, standard
    deviations `std_pd` `(N, 3)`, `std_ps`, `std_roughness` `(N,)`,
    `specular_identifiable` `(N,)` bool (ps and roughness from the point's own
    samples), `pd_measured` `(N,)` bool (the point had usable samples), and
    `meta` (options, timings)."""

    pd: np.ndarray
    ps: np.ndarray
    roughness: np.ndarray
    status: np.ndarray
    std_pd: np.ndarray
    std_ps: np.ndarray
    std_roughness: np.ndarray
    specular_identifiable: np.ndarray
    pd_measured: np.ndarray
    model: str
    meta: dict = field(default_factory=dict)


# -- closed forms ---------------------------------------------------------------------


def _spec_coordinates(model, s, e, cos_i, cos_o, theta_r):
    """(z, x) of the log-linear specular model; z <= 0 where s is not positive."""
    ci, co = jnp.maximum(cos_i, brdf.COS_FLOOR), jnp.maximum(cos_o, brdf.COS_FLOOR)
    e_safe = jnp.where(e > 0, e, 1.0)
    if model == "torrance-sparrow":
        return s * ci * co / e_safe, theta_r**2
    c = jnp.maximum(jnp.cos(theta_r), brdf.COS_FLOOR)
    return 4.0 * jnp.pi * s * jnp.sqrt(ci * co) / e_safe, (jnp.sin(theta_r) / c) ** 2


def _to_parameters(model, a, b):
    """(ln ps, ln roughness) from intercept a and slope b of ln z = a - b x."""
    b = jnp.maximum(b, 1e-300)
    if model == "torrance-sparrow":
        return a, -0.5 * jnp.log(2.0 * b)
    log_alpha = -0.5 * jnp.log(b)
    return a + 2.0 * log_alpha, log_alpha


def specular_closed_form(model, z, x, use):
    """Weighted log-domain line fit per row.

    **Arguments:** `z`, `x` `(N, M)`; `use` `(N, M)` bool. Weights `z^2`
    (since var(ln z) ~ 1 / z^2); with exactly two samples this is the exact
    two-equation solution of Eq. 7.

    **Returns:** `(ln_ps, ln_roughness, ok)`, each `(N,)`; `ok` False where
    fewer than two usable samples, equal `x`, or a non-decaying lobe.
    """
    use = use & (z > 0)
    lz = jnp.log(jnp.where(use, z, 1.0))
    w = jnp.where(use, z * z, 0.0)
    w = w / jnp.maximum(jnp.max(w, axis=1, keepdims=True), 1e-300)
    sw, sx, sy = w.sum(1), (w * x).sum(1), (w * lz).sum(1)
    sxx, sxy = (w * x * x).sum(1), (w * x * lz).sum(1)
    det = sw * sxx - sx * sx
    enough = (use.sum(1) >= 2) & (det > 1e-14 * jnp.maximum(sw * sxx, 1e-300))
    det = jnp.where(enough, det, 1.0)
    slope = (sw * sxy - sx * sy) / det  # d ln z / d x = -b
    a = (sy - slope * sx) / jnp.where(sw > 0, sw, 1.0)
    b = -slope
    ln_ps, ln_rough = _to_parameters(model, a, b)
    ok = enough & (b > 0) & jnp.isfinite(ln_ps) & jnp.isfinite(ln_rough)
    return jnp.where(ok, ln_ps, _LN_FLOOR), jnp.where(ok, ln_rough, jnp.log(0.1)), ok


def quantisation_step(radiance, observed) -> float:
    """Detect a quantised sensor: the common step of the observed values, or 0.

    Returns the step when every observed value is (to 1e-3 of a step) an
    integer multiple of the smallest positive gap between distinct values and
    there are at most 2^16 distinct values; 0 otherwise.
    """
    vals = np.unique(np.asarray(radiance)[observed].ravel())
    if len(vals) < 3 or len(vals) > 65536:
        return 0.0
    gaps = np.diff(vals)
    step = float(gaps[gaps > 0].min())
    ratio = vals / step
    return step if np.all(np.abs(ratio - np.round(ratio)) < 1e-3 * np.maximum(1, ratio)) else 0.0


# -- the full model per row --------------------------------------------------------------


def _row_model(model, pd, ps, ln_rough, e, cos_i, cos_o, theta_r):
    """Predicted radiance `(M, 3)` of one point."""
    full, _ = brdf.MODELS[model]
    f = jax.vmap(full, in_axes=(None, None, None, 0, 0, 0))(pd, ps, ln_rough, cos_i, cos_o, theta_r)
    return f * e[:, None]


@lru_cache(maxsize=None)
def _make_residual(model):
    """The weighted residual of one row in `(pd_rgb, ps, ln roughness)` (cached: jit
    keys on the function's identity)."""

    def residual(p, d):
        pred = _row_model(model, p[:3], p[3], p[4], d["e"], d["cos_i"], d["cos_o"], d["theta_r"])
        return (jnp.where(d["use"][:, None], (d["y"] - pred) * d["w"], 0.0)).ravel()

    return residual


def _noise_weights(y, use, floor):
    """1 / sqrt((0.01 y)^2 + floor^2), the relative-plus-floor noise model (M, 3)."""
    row_max = jnp.max(jnp.where(use[..., None], y, 0.0), axis=(-2, -1), keepdims=True)
    f = jnp.maximum(floor, 1e-4 * row_max)
    return 1.0 / jnp.sqrt((0.01 * y) ** 2 + f**2)


# -- the estimator ------------------------------------------------------------------------------


def prepare_rows(scan, thresholds: Thresholds = Thresholds(), caster: RayCaster | None = None) -> dict:
    """Per-(point, light) arrays of a scan, each `(N, M)` (`y` `(N, M, 3)`): radiance `y`,
    irradiance `e = Y cos_i / C^2` (0 where unused), `cos_i`, `cos_o`, `theta_r`,
    `use` (measurable and observed) and `classes` (see `classify`)."""
    caster = caster or RayCaster(scan.vertices, scan.faces)
    g = observation_geometry(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos)
    classes = classify_scan(scan, thresholds, caster=caster).classes
    use = classes != T_INVALID
    y = np.where(use[..., None], scan.radiance, 0.0).astype(np.float64)
    cos_i, cos_o, theta_r = (np.asarray(a) for a in (g.cos_i, g.cos_o, g.theta_r))
    e = scan.intensities()[None, :] * np.maximum(cos_i, 0.0) / np.asarray(g.light_distance) ** 2
    return {"y": y, "e": np.where(use, e, 0.0), "cos_i": cos_i, "cos_o": cos_o, "theta_r": theta_r,
            "use": use, "classes": classes}


@jax.jit
def _diffuse_init(y, e, use, classes, theta_r, paper):
    """pd `(N, 3)` from T_diff samples (LS or Eq. 5) or, lacking any, the least specular sample."""
    diff = use & (classes == T_DIFF)
    ls = jnp.pi * jnp.sum(jnp.where(diff[..., None], e[..., None] * y, 0.0), 1) \
        / jnp.maximum(jnp.sum(jnp.where(diff, e * e, 0.0), 1), 1e-300)[:, None]
    # Eq. 5: the T_diff sample with the smallest theta_r (still > theta_th1).
    best = jnp.argmin(jnp.where(diff, theta_r, jnp.inf), axis=1)
    pick = lambda a: jnp.take_along_axis(a, best[:, None], 1)[:, 0]  # noqa: E731
    eq5 = jnp.pi * jnp.take_along_axis(y, best[:, None, None], 1)[:, 0] / jnp.maximum(pick(e), 1e-300)[:, None]
    # No T_diff sample: the valid sample with the largest theta_r bounds pd from above.
    least = jnp.argmax(jnp.where(use, theta_r, -jnp.inf), axis=1)
    e_least = jnp.take_along_axis(e, least[:, None], 1)[:, 0]
    fallback = jnp.pi * jnp.take_along_axis(y, least[:, None, None], 1)[:, 0] / jnp.maximum(e_least, 1e-300)[:, None]
    has_diff = diff.any(1)
    pd = jnp.where(has_diff[:, None], jnp.where(paper, eq5, ls), fallback)
    return jnp.where(use.any(1)[:, None], pd, 0.0), has_diff


def _specular_init(model, data, pd, paper):
    y, e, use, classes = data["y"], data["e"], data["use"], data["classes"]
    spec_use = use & (classes == T_SPEC)
    s = jnp.mean(y, -1) - e * jnp.mean(pd, -1)[:, None] / jnp.pi
    z, x = _spec_coordinates(model, s, e, data["cos_i"], data["cos_o"], data["theta_r"])
    n_spec = spec_use.sum(1)
    if paper:  # Eq. 7: the two T_spec samples with the smallest theta_r
        order = jnp.argsort(jnp.where(spec_use, data["theta_r"], jnp.inf), axis=1)
        rank = jnp.argsort(order, axis=1)
        spec_use = spec_use & (rank < 2)
    else:  # fewer than two T_spec samples: start from every non-diffuse sample (weights z^2)
        spec_use = jnp.where((n_spec >= 2)[:, None], spec_use, use & (classes != T_DIFF))
    return specular_closed_form(model, z, x, spec_use) + (n_spec,)


def _grid_init(model, data, w):
    """Robust start by variable projection: for a fixed roughness the model is linear
    in (pd_r, pd_g, pd_b, ps). Solve that weighted least-squares problem in closed
    form (ps, pd >= 0 by projection) on a dense roughness grid and keep the best.

    **Returns:** `(pd (N, 3), ln_ps (N,), ln_rough (N,))`.
    """
    e, use, y = data["e"], data["use"], data["y"]
    # Softer weights than the fit's: with purely relative weights the dim tail samples
    # make the profile so sharp in roughness that a grid step can miss its minimum.
    row_max = jnp.max(jnp.where(use[..., None], y, 0.0), axis=(1, 2), keepdims=True)
    soft = 1.0 / (y * y + (0.05 * row_max) ** 2 + 1e-300)
    ww = jnp.where(use[..., None], jnp.minimum(w * w, soft), 0.0)  # (N, M, 3)
    a1 = e / jnp.pi  # (N, M)
    wa, wy = ww * a1[..., None], ww * y  # (N, M, 3)
    s11 = jnp.einsum("nmc,nm->nc", wa, a1)
    b1 = jnp.einsum("nmc,nm->nc", wy, a1)
    yy = jnp.sum(wy * y, 1)
    s11_safe = jnp.maximum(s11, 1e-300)
    # The unit lobe factorises as amp * exp(-x * kappa(roughness)) * scale(roughness):
    # only one exp per sample and grid value is left inside the scan.
    ci = jnp.maximum(data["cos_i"], brdf.COS_FLOOR)
    co = jnp.maximum(data["cos_o"], brdf.COS_FLOOR)
    if model == "torrance-sparrow":
        amp, x = e / (ci * co), data["theta_r"] ** 2
    else:
        c = jnp.maximum(jnp.cos(data["theta_r"]), brdf.COS_FLOOR)
        amp, x = e / (4.0 * jnp.pi * jnp.sqrt(ci * co)), (jnp.sin(data["theta_r"]) / c) ** 2
    amp = jnp.where(use, amp, 0.0)

    def profile(log_r):
        r2 = jnp.exp(2.0 * log_r)
        kappa, scale = (0.5 / r2, 1.0) if model == "torrance-sparrow" else (1.0 / r2, 1.0 / r2)
        a2 = amp * jnp.exp(-jnp.minimum(x * kappa, 700.0)) * scale  # (N, M) = E * unit lobe
        s12 = jnp.einsum("nmc,nm->nc", wa, a2)
        s22 = jnp.einsum("nmc,nm->nc", ww, a2 * a2)
        b2 = jnp.einsum("nmc,nm->nc", wy, a2)
        den = s22.sum(1) - (s12 * s12 / s11_safe).sum(1)
        ps = (b2.sum(1) - (s12 * b1 / s11_safe).sum(1)) / jnp.where(den > 0, den, 1.0)
        ps = jnp.where(den > 0, jnp.maximum(ps, 0.0), 0.0)
        pd = jnp.clip((b1 - s12 * ps[:, None]) / s11_safe, 0.0, 1.0)
        # The weighted squared residual, expanded in the sums above (no (N, M, 3) temporaries).
        p2 = ps[:, None]
        cost = jnp.sum(yy - 2 * pd * b1 - 2 * p2 * b2 + pd * pd * s11 + 2 * pd * p2 * s12 + p2 * p2 * s22, 1)
        return cost, ps, pd

    # All grid values at once: rows arrive in chunks (`_CHUNK`), so the (grid, rows,
    # samples) temporaries stay small, and one wide op beats a loop of small ones.
    logs = jnp.log(jnp.asarray(brdf.ROUGHNESS_GRID))
    cost, ps, pd = jax.vmap(profile, out_axes=(1, 1, 1))(logs)
    best = jnp.argmin(cost, axis=1)
    ps = jnp.take_along_axis(ps, best[:, None], 1)[:, 0]
    pd = jnp.take_along_axis(pd, best[:, None, None], 1)[:, 0]
    return pd, jnp.log(jnp.maximum(ps, 1e-12)), logs[best]


def _refit_diffuse(model, data, ln_ps, ln_rough, w):
    """Closed-form pd `(N, 3)` and its std with the specular part fixed, over all valid samples."""
    _, spec_fn = brdf.MODELS[model]
    spec = jax.vmap(jax.vmap(spec_fn, in_axes=(None, None, 0, 0, 0)))(
        jnp.exp(ln_ps), ln_rough, data["cos_i"], data["cos_o"], data["theta_r"])
    e = data["e"]
    diffuse_part = data["y"] - (e * spec)[..., None]
    ww = jnp.where(data["use"][..., None], w * w, 0.0)
    num = jnp.sum(ww * e[..., None] * diffuse_part, 1)
    den = jnp.sum(ww * (e * e)[..., None], 1)
    pd = jnp.pi * num / jnp.maximum(den, 1e-300)
    resid = jnp.where(data["use"][..., None], (diffuse_part - e[..., None] * pd[:, None] / jnp.pi) * w, 0.0)
    n = data["use"].sum(1)
    s2 = jnp.sum(resid**2, 1) / jnp.maximum(n - 1, 1)[:, None]  # per channel
    std = jnp.pi * jnp.sqrt(s2 / jnp.maximum(den, 1e-300))
    return jnp.maximum(pd, 0.0), jnp.where(n[:, None] > 1, std, jnp.inf)


def _solve_optimistix(residual, p0, data, steps):
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)

    def one(p, d):
        sol = optx.least_squares(lambda q, a: residual(q, a), solver, p, args=d, throw=False,
                                 max_steps=max(steps, 64))
        return sol.value

    return jax.jit(jax.vmap(one))(p0, data)


def _bucket(n: int, step: int) -> int:
    return max(step, -(-n // step) * step)


_CHUNK = 4000  # rows per lax.map step: keeps the working set in cache (not a power of two)


def _pad_rows(rows: dict) -> tuple[dict, int]:
    """Pad rows and observations with unused entries to bucketed sizes, so that
    scans of similar size reuse one compilation: observations to a multiple of 4,
    rows to a multiple of the chunk (itself a multiple of 500, at most 4000).
    Returns the padded rows and the chunk size."""
    n, m = np.shape(rows["use"])
    chunk = min(_CHUNK, _bucket(n, 500))
    n_pad, m_pad = _bucket(n, chunk), _bucket(m, 4)
    out = {}
    for key, value in rows.items():
        value = np.asarray(value)
        widths = [(0, n_pad - n), (0, m_pad - m)] + [(0, 0)] * (value.ndim - 2)
        fill = T_INVALID if key == "classes" else (1.0 if key in ("cos_i", "cos_o") else 0)
        out[key] = np.pad(value, widths, constant_values=fill)
    return out, chunk


def _start(pd, ln_ps, ln_rough):
    """Parameter rows `(pd_rgb, ps, ln roughness)`: reflectances linear (kept >= 0 by
    projection in every step, so a channel at 0 can come back), roughness in logs."""
    return jnp.concatenate([jnp.clip(pd, 0.0, 1.0), jnp.exp(ln_ps)[:, None], ln_rough[:, None]], axis=1)


def _lobe_and_slope(model, ln_rough, cos_i, cos_o, theta_r):
    """Unit-ps specular BRDF `g` and `d ln g / d ln roughness`, per sample."""
    _, spec_fn = brdf.MODELS[model]
    g = spec_fn(1.0, ln_rough, cos_i, cos_o, theta_r)
    r2 = jnp.exp(2.0 * ln_rough)
    if model == "torrance-sparrow":
        slope = theta_r**2 / r2
    else:
        c = jnp.maximum(jnp.cos(theta_r), brdf.COS_FLOOR)
        slope = 2.0 * (jnp.sin(theta_r) / c) ** 2 / r2 - 2.0
    return g, slope


def _analytic_lm_row(model, steps):
    """Fixed-step projected LM for one row with the Jacobian written out.

    The model `y_cj = E_j (pd_c / pi + ps g_j)` is linear in `pd_rgb` and `ps` and
    nonlinear only in `ln roughness`; each pd column touches one channel, so
    `J^T J` and `J^T r` are short weighted sums over the samples. After each step
    the reflectances are projected onto `>= 0` (bounds, not a clip of the result).
    """

    def cost_of(p, d):
        g, _ = _lobe_and_slope(model, p[4], d["cos_i"], d["cos_o"], d["theta_r"])
        pred = d["e"][:, None] * (p[:3][None] / jnp.pi + (p[3] * g)[:, None])
        r = jnp.where(d["use"][:, None], (d["y"] - pred) * d["w"], 0.0)
        return jnp.sum(r * r)

    def row(p0, d):
        ww = jnp.where(d["use"][:, None], d["w"] ** 2, 0.0)  # (M, 3)
        e = d["e"]
        a = e / jnp.pi  # (M,) d pred / d pd_c (channel c only)

        def body(_, state):
            p, lam, cost = state
            g, slope = _lobe_and_slope(model, p[4], d["cos_i"], d["cos_o"], d["theta_r"])
            b = e * g  # (M,) d pred / d ps (all channels)
            c = b * p[3] * slope  # (M,) d pred / d ln roughness
            r = d["y"] - a[:, None] * p[:3][None] - (b * p[3])[:, None]  # (M, 3)
            wsum = jnp.sum(ww, 1)
            pdpd = jnp.sum(ww * (a * a)[:, None], 0)
            pdps = jnp.sum(ww * (a * b)[:, None], 0)
            pdro = jnp.sum(ww * (a * c)[:, None], 0)
            psro = jnp.sum(wsum * b * c)
            jtj = jnp.zeros((5, 5))
            jtj = jtj.at[jnp.arange(3), jnp.arange(3)].set(pdpd)
            jtj = jtj.at[:3, 3].set(pdps).at[3, :3].set(pdps)
            jtj = jtj.at[:3, 4].set(pdro).at[4, :3].set(pdro)
            jtj = jtj.at[3, 3].set(jnp.sum(wsum * b * b)).at[4, 4].set(jnp.sum(wsum * c * c))
            jtj = jtj.at[3, 4].set(psro).at[4, 3].set(psro)
            grad = jnp.concatenate([jnp.sum(ww * a[:, None] * r, 0),
                                    jnp.stack([jnp.sum(ww * b[:, None] * r), jnp.sum(ww * c[:, None] * r)])])
            scale = jnp.diag(jtj) + 1e-12 * (jnp.max(jnp.diag(jtj)) + 1e-300)
            step = spd_solve(jtj + lam * jnp.diag(scale), grad)
            step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
            p_new = p + step
            # Bounds: reflectances >= 0, albedo pd <= 1 (energy conservation; it also
            # removes the false minima where a broad lobe is traded for pd > 1).
            p_new = p_new.at[:4].set(jnp.maximum(p_new[:4], 0.0)).at[:3].set(jnp.minimum(p_new[:3], 1.0))
            cost_new = cost_of(p_new, d)
            ok = jnp.isfinite(cost_new) & (cost_new < cost)
            return jnp.where(ok, p_new, p), jnp.where(ok, lam / 3.0, lam * 10.0), jnp.where(ok, cost_new, cost)

        p, _, cost = jax.lax.fori_loop(0, steps, body, (p0, 1e-3, cost_of(p0, d)))
        return p, cost

    return row


def _fit_chunk(rows, noise_floor, model, paper, solver, steps):
    """Closed forms, two-start polish and covariance for one chunk of rows."""
    pd0, has_diff = _diffuse_init(rows["y"], rows["e"], rows["use"], rows["classes"], rows["theta_r"], paper)
    ln_ps0, ln_rough0, spec_ok, n_spec = _specular_init(model, rows, pd0, paper)
    w = _noise_weights(rows["y"], rows["use"], noise_floor)
    lm_data = {k: rows[k] for k in ("y", "e", "cos_i", "cos_o", "theta_r", "use")}
    lm_data["w"] = w
    residual = _make_residual(model)
    p0 = _start(pd0, ln_ps0, ln_rough0)
    if paper:
        params = p0
    else:
        # Two starts per row -- the closed form and the roughness grid -- polished
        # together; the lower final cost wins (broad, bright lobes have false minima).
        starts = jnp.concatenate([p0, _start(*_grid_init(model, rows, w))])
        both = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, a]), lm_data)
        if solver == "lm":
            polished, cost = jax.vmap(_analytic_lm_row(model, steps))(starts, both)
        else:
            polished = _solve_optimistix(residual, starts, both, steps)
            cost = jax.vmap(lambda p, d: jnp.sum(residual(p, d) ** 2))(polished, both)
        n = p0.shape[0]
        cost = jnp.where(jnp.all(jnp.isfinite(polished), axis=1), cost, jnp.inf)
        params = jnp.where((cost[n:] < cost[:n])[:, None], polished[n:], polished[:n])
        spec_ok = spec_ok | jnp.isfinite(jnp.minimum(cost[:n], cost[n:]))
    params = jnp.where(jnp.all(jnp.isfinite(params), axis=1, keepdims=True), params, p0)
    # Rows the data cannot pin down may wander; keep them in range (they stay flagged).
    params = jnp.clip(params, jnp.array([[0.0] * 4 + [np.log(1e-4)]]),
                      jnp.array([[10.0] * 4 + [np.log(np.pi / 2)]]))
    cov = covariance(residual, params, lm_data, 3 * rows["use"].sum(1))
    return {"params": params, "cov": cov, "spec_ok": spec_ok, "n_spec": n_spec, "has_diff": has_diff, "w": w}


@partial(jax.jit, static_argnames=("chunk", "model", "paper", "solver", "steps"))
def _fit_padded(rows, noise_floor, chunk, model, paper, solver, steps):
    """`_fit_chunk` over all rows, `lax.map` over chunks of `chunk` rows."""
    n = rows["use"].shape[0]
    split = jax.tree_util.tree_map(lambda a: a.reshape(n // chunk, chunk, *a.shape[1:]), rows)
    out = jax.lax.map(lambda r: _fit_chunk(r, noise_floor, model, paper, solver, steps), split)
    return jax.tree_util.tree_map(lambda a: a.reshape(n, *a.shape[2:]), out)


class RowFit(dict):
    """`fit_rows` output (a dict): `pd` `(N, 3)`, `ps` `(N,)`, `roughness` `(N,)` [rad]
    and their standard deviations `std_pd`, `std_ps`, `std_roughness` (inf where
    unknown), `identifiable` `(N,)` (specular part measured), `has_diffuse_sample`
    `(N,)`, `weights` `(N, M, 3)` residual weights."""


def fit_rows(rows: dict, options: LocalOptions = LocalOptions(), noise_floor: float = 0.0) -> RowFit:
    """Steps 1-3 of Method I (closed forms, polish, uncertainty) on `prepare_rows` output.

    `noise_floor`: absolute radiance noise floor of the weights (e.g. the
    quantisation step / sqrt(12)).
    """
    n_rows, n_obs = np.shape(rows["use"])
    padded, chunk = _pad_rows(rows)
    out = _fit_padded({k: jnp.asarray(v) for k, v in padded.items()}, float(noise_floor), chunk,
                      options.model, options.paper, options.solver, options.steps)
    params, cov = np.asarray(out["params"])[:n_rows], np.asarray(out["cov"])[:n_rows]
    spec_ok, n_spec, has_diff = (np.asarray(out[k])[:n_rows] for k in ("spec_ok", "n_spec", "has_diff"))
    var = np.diagonal(cov, axis1=1, axis2=2)
    sd = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
    rough = np.exp(params[:, 4])
    # The paper needs two T_spec samples; the full-model fit can also pin the lobe down
    # from T_none samples, so identifiability is judged on the fit's own uncertainty.
    enough = n_spec >= 2 if options.paper else np.asarray(rows["use"]).sum(1) >= 3
    identifiable = enough & spec_ok & np.all(np.isfinite(params), 1) \
        & (params[:, 3] > options.min_snr * sd[:, 3]) & (sd[:, 4] < 1.0)
    std_rough = np.where(np.isinf(sd[:, 4]), np.inf, rough * np.where(np.isinf(sd[:, 4]), 0.0, sd[:, 4]))
    return RowFit(pd=params[:, :3], ps=params[:, 3], roughness=rough, std_pd=sd[:, :3], std_ps=sd[:, 3],
                  std_roughness=std_rough, identifiable=identifiable, has_diffuse_sample=has_diff,
                  weights=out["w"][:n_rows, :n_obs])


def estimate_local(scan, options: LocalOptions = LocalOptions(), caster: RayCaster | None = None) -> Estimate:
    """Method I on a scan with radiance. See the module docstring.

    **Returns:** `Estimate` (no NaN: unresolved values are filled, their
    standard deviations infinite).
    """
    if scan.radiance is None:
        raise ValueError("radiance: the scan has no observations to estimate from")
    timings = {}
    t0 = time.perf_counter()
    rows = prepare_rows(scan, options.thresholds, caster)
    q = quantisation_step(scan.radiance, rows["use"])
    timings["classify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fit = fit_rows(rows, options, noise_floor=q / np.sqrt(12.0))
    timings["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    identifiable = fit["identifiable"]
    observed_any = rows["use"].any(1)
    pd, ps, rough = fit["pd"].copy(), fit["ps"].copy(), fit["roughness"].copy()
    std_pd, std_ps, std_rough = fit["std_pd"].copy(), fit["std_ps"].copy(), fit["std_roughness"].copy()
    status = np.full(scan.n_points, MEASURED, np.int8)

    adjacency = vertex_adjacency(scan.faces, scan.n_points)
    if options.pool and not options.paper:
        # Points that could not measure their own lobe share it with same-material
        # neighbours (`pool`); they count as interpolated, with finite std.
        pooled = pooled_specular(rows, pd, scan.vertices, options.model, k=options.pool_neighbours,
                                 tau=options.pool_tau, min_snr=options.min_snr)
        use_pool = ~identifiable & pooled["identifiable"] & observed_any
        ps[use_pool], rough[use_pool] = pooled["ps"][use_pool], pooled["roughness"][use_pool]
        std_ps_pool, std_rough_pool = pooled["std_ps"][use_pool], pooled["std_roughness"][use_pool]
    else:
        use_pool = np.zeros(scan.n_points, bool)
    need_spec = ~identifiable & ~use_pool
    if (~need_spec).any():
        logs = np.c_[np.log(np.maximum(ps, 1e-12)), np.log(rough)]
        filled = window_fill(logs, ~need_spec, adjacency, options.window)
        ps[need_spec], rough[need_spec] = np.exp(filled.values[need_spec, 0]), np.exp(filled.values[need_spec, 1])
        status[filled.window] = INTERPOLATED
        status[filled.diffused] = UNRESOLVED
    else:  # no specular reflection detected anywhere: report none, roughness undefined (0)
        ps[:], rough[:] = 0.0, 0.0
        status[:] = UNRESOLVED
    std_ps[need_spec] = np.inf
    std_rough[need_spec] = np.inf
    if use_pool.any():
        std_ps[use_pool], std_rough[use_pool] = std_ps_pool, std_rough_pool
        status[use_pool] = INTERPOLATED

    # pd of points whose specular part came from elsewhere, with that part fixed.
    refit = (need_spec | use_pool) & observed_any
    if refit.any():
        jrows = {k: jnp.asarray(v) for k, v in rows.items()}
        pd_fix, std_fix = _refit_diffuse(options.model, jrows, jnp.log(jnp.maximum(ps, 1e-300)),
                                         jnp.log(jnp.maximum(rough, 1e-300)), fit["weights"])
        pd[refit], std_pd[refit] = np.asarray(pd_fix)[refit], np.asarray(std_fix)[refit]
    if (~observed_any).any():
        if observed_any.any():
            filled = window_fill(pd, observed_any, adjacency, options.window)
            pd[~observed_any] = filled.values[~observed_any]
            status[~observed_any & filled.window] = np.maximum(status[~observed_any & filled.window],
                                                               INTERPOLATED)
            status[~observed_any & filled.diffused] = UNRESOLVED
        else:
            status[:] = UNRESOLVED
        std_pd[~observed_any] = np.inf
    timings["fill"] = time.perf_counter() - t0

    # Nothing non-finite leaves: std may be inf (unknown), values never NaN.
    for a in (pd, ps, rough):
        np.nan_to_num(a, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    for a in (std_pd, std_ps, std_rough):
        np.nan_to_num(a, copy=False, nan=np.inf, posinf=np.inf)
    meta = {"method": "local", "model": options.model,
            "options": {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v)
                        for k, v in asdict(options).items()},
            "quantisation_step": q, "seconds": timings,
            "points_with_observations": int(observed_any.sum()),
            "points_with_diffuse_only_sample": int(fit["has_diffuse_sample"].sum())}
    return Estimate(pd, ps, rough, status, std_pd, std_ps, std_rough, identifiable, observed_any,
                    options.model, meta)
