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
3. **Polish** — the full model over all valid samples (`T_diff`, `T_spec`,
   `T_none`), residuals weighted by a noise model `sqrt((0.01 y)^2 + floor^2)`,
   parameters `(pd_rgb, ps, ln roughness)` with bounds `0 <= pd <= 1`,
   `ps >= 0`. Given the roughness the model is linear in pd and ps, so by
   variable projection each point is a 1-D problem in ln roughness: pd and ps
   are solved exactly under their bounds for every trial roughness
   (`lm.bounded_arrow_solve`) and `steps` damped Gauss-Newton steps move the
   roughness (`lm.gauss_newton_1d`). The start is whichever of the closed form
   and a 32-value roughness grid a Newton step predicts lowest (float32, softer
   weights), which keeps false minima away. All points at once: rows lie along
   the last axis, the sums over samples written out in blocks of eight
   (`lm.block_sums`: the compiled program does not grow with the lights), one
   compiled call per chunk of rows. Standard deviations from the Gauss-Newton covariance.
   `solver="optimistix"` polishes the full model with optimistix's
   Levenberg-Marquardt from both starts instead (slower; for comparison).
4. **Identifiability** — a point's own lobe is pinned when its Gauss-Newton
   (Fisher) information puts ps `min_snr` standard deviations above 0 and ln
   roughness within 1 (a factor `e`), and the fitted lobe stands `min_snr` noise
   standard deviations high in two samples or more (with one, ps and roughness
   trade off along a valley the local curvature does not show). The residual
   variance of a row is at least the median row's (`_noise_scale`): a few samples,
   whose RGB channels often share their error, cannot show a noise far below
   everyone else's; nor below the rounding of the fit's own arithmetic (`_COST_ULPS`:
   in float32 a noise-free row would otherwise claim any lobe). And two of the samples
   above the noise must see the lobe at heights that pin its roughness by themselves
   (`_MIN_HEIGHT_CONTRAST`): one height seen twice (mirror-symmetric lights) or a far
   tail leaves ps and roughness on a valley.
5. **Shared prior** (default, `prior=True`; `jaxrefl.reflectance.prior`) — points are grouped
   into materials (K by BIC), each material's lobe is fitted jointly from all its
   points' samples (a material no sample saw near a specular peak, `T_spec`, has
   none: a lobe seen only on its flank is a smooth trend that interreflection
   imitates); where cross-validation finds the lobe varying within a material, each
   point's prior is the joint lobe of its nearest material-mates' samples
   (`prior.local_lobes`) widened by the spread that maximises the evidence of the
   points' own samples (`_local_spread`); elsewhere the within-material spread and its
   growth with distance are measured on the points' own (or neighbourhood) lobes; and
   every point takes the posterior mode of its own likelihood and that prior
   (`_map_polish`, the same variable projection with the prior's precision added).
   `prior=False` keeps the gated rules: own
   lobes need a `T_spec` sample; the rest pool with same-material neighbours
   (`pool.pooled_specular`) or take the window's log-mean (`fill.window_fill`);
   `paper=True` is the paper's estimator (two `T_spec` samples, window fill).
   Every ps is kept within the energy bound of its roughness (`brdf.ps_bound`).

Status per point (`STATUS_NAMES`): 0 `measured` (its own samples pin its lobe and
carry at least the prior's precision), 3 `pooled` (the prior dominates; finite
std from the posterior), 1 `interpolated` (gated rules: from the window; or, with
no own sample, pd from the window), 2 `unresolved` (nothing pins the lobe: copied
from the nearest known lobes, or 0 when there is none; std infinite).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.raycast import RayCaster
from ..geometry.rig import observation_geometry
from ..reflectance import brdf
from ..reflectance import prior as prior_mod
from ..reflectance.classify import T_DIFF, T_INVALID, T_SPEC, Thresholds, classify_scan
from ..reflectance.fill import vertex_adjacency, window_fill
from ..reflectance.pool import pooled_specular
from ..result import Estimate
from ..scan import checks
from ..status import STATUS_NAMES, Status
from .interreflection import pd_sd_with_interreflection
from .lm import (SAMPLE_BLOCK, block_sums, bounded_arrow_solve, gauss_newton_1d, msum, projected_step_terms, rowsum,
                 spd_inverse_diagonal)

__all__ = ["Status", "MEASURED", "INTERPOLATED", "UNRESOLVED", "POOLED", "STATUS_NAMES", "LocalOptions",
           "estimate_local", "fill_unobserved_pd", "finite_outputs",
           "prepare_rows", "fit_rows", "specular_closed_form", "quantisation_step"]

MEASURED, INTERPOLATED, UNRESOLVED, POOLED = Status  # `jaxrefl.status`; STATUS_NAMES by code
_LN_FLOOR = -30.0  # ln of a reflectance so small it is zero for every purpose
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalOptions:
    """Options of Method I (see the module docstring)."""

    model: str = "torrance-sparrow"
    paper: bool = False
    steps: int = 15
    window: int = 5
    min_snr: float = 3.0
    solver: str = "lm"
    prior: bool = True
    materials: int = 6
    prior_neighbours: int = 16
    pool: bool = True
    pool_neighbours: int = 12
    pool_tau: float = 0.05
    thresholds: Thresholds = field(default_factory=Thresholds)
    #: With the prior: `unresolved` points of a material with no prior report its joint fit
    #: where that shows a lobe (False: the nearest measured lobes, as Methods II and III use:
    #: under interreflection a material's direct-light joint fit may be interreflected light).
    material_fill: bool = True
    #: Rays per point that estimate the light the object reflects onto itself, which Method I
    #: leaves in pd (`interreflected_share`); its std_pd includes it. 0: noise alone.
    interreflection_rays: int = 16

    def __post_init__(self):
        if self.interreflection_rays < 0:
            raise ValueError(f"interreflection_rays must be >= 0, got {self.interreflection_rays}")
        if self.model not in brdf.MODELS:
            raise ValueError(f"model must be one of {sorted(brdf.MODELS)}, got {self.model!r}")
        if self.solver not in ("lm", "optimistix"):
            raise ValueError(f"solver must be 'lm' or 'optimistix', got {self.solver!r}")
        if self.steps < 1:
            raise ValueError("steps must be >= 1")


# -- closed forms ---------------------------------------------------------------------
#
# Inside the fit, rows lie along the last axis ("sample-major": `(M, n)`, `(M, 3, n)`),
# so every formula is a vectorised loop over the rows; sums over the M samples are
# reductions over the leading axis (`lm.msum`) once per fit, and written out in blocks
# (`lm.block_sums`) inside its iterations. The host transposes the rows into this layout
# once (`_chunked`).


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


def _line_fit(model, z, x, use):
    """`specular_closed_form` on sample-major `(M, n)` arrays."""
    use = use & (z > 0)
    lz = jnp.log(jnp.where(use, z, 1.0))
    w = jnp.where(use, z * z, 0.0)
    w = w / jnp.maximum(jnp.max(w, axis=0), 1e-300)[None]
    sw, sx, sy = msum(w), msum(w * x), msum(w * lz)
    sxx, sxy = msum(w * x * x), msum(w * x * lz)
    det = sw * sxx - sx * sx
    enough = (msum(use.astype(jnp.int32)) >= 2) & (det > 1e-14 * jnp.maximum(sw * sxx, 1e-300))
    det = jnp.where(enough, det, 1.0)
    slope = (sw * sxy - sx * sy) / det  # d ln z / d x = -b
    a = (sy - slope * sx) / jnp.where(sw > 0, sw, 1.0)
    b = -slope
    ln_ps, ln_rough = _to_parameters(model, a, b)
    ok = enough & (b > 0) & jnp.isfinite(ln_ps) & jnp.isfinite(ln_rough)
    return jnp.where(ok, ln_ps, _LN_FLOOR), jnp.where(ok, ln_rough, jnp.log(0.1)), ok


def specular_closed_form(model, z, x, use):
    """Weighted log-domain line fit per row.

    **Arguments:** `z`, `x` `(N, M)`; `use` `(N, M)` bool. Weights `z^2`
    (since var(ln z) ~ 1 / z^2); with exactly two samples this is the exact
    two-equation solution of Eq. 7.

    **Returns:** `(ln_ps, ln_roughness, ok)`, each `(N,)`; `ok` False where
    fewer than two usable samples, equal `x`, or a non-decaying lobe.
    """
    return _line_fit(model, jnp.asarray(z).T, jnp.asarray(x).T, jnp.asarray(use).T)


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


def _diffuse_init(y, e, use, classes, theta_r, paper):
    """pd `(3, n)` and `has_diff` `(n,)` from sample-major rows (`y` `(M, 3, n)`, the rest
    `(M, n)`): least squares over the T_diff samples or, `paper`, Eq. 5 with the T_diff
    sample of smallest theta_r (still > theta_th1); lacking any T_diff sample, the valid
    sample with the largest theta_r (it bounds pd from above)."""
    diff = use & (classes == T_DIFF)
    num = msum(jnp.where(diff, e, 0.0)[:, None] * y)
    den = msum(jnp.where(diff, e * e, 0.0))
    least_squares = jnp.pi * num / jnp.maximum(den, 1e-300)[None]

    def single(pick):
        """pd from the one sample `pick` `(n,)` (argmin / argmax: real reductions, so
        XLA computes them once instead of inside every later reader)."""
        y_j = jnp.take_along_axis(y, pick[None, None], 0)[0]
        e_j = jnp.take_along_axis(e, pick[None], 0)[0]
        return jnp.pi * y_j / jnp.maximum(e_j, 1e-300)[None]

    has_diff = diff.any(0)
    pd_any = single(jnp.argmax(jnp.where(use, theta_r, -jnp.inf), axis=0))
    pd_diff = single(jnp.argmin(jnp.where(diff, theta_r, jnp.inf), axis=0)) if paper else least_squares
    pd = jnp.where(has_diff[None], pd_diff, pd_any)
    return jnp.where(use.any(0)[None], pd, 0.0), has_diff


def _specular_init(model, rows, pd, paper):
    """Closed-form `(ln_ps, ln_rough, ok, n_spec)`, each `(n,)`, from sample-major rows."""
    y, e, use, classes = rows["y"], rows["e"], rows["use"], rows["classes"]
    spec_use = use & (classes == T_SPEC)
    s = jnp.mean(y, axis=1) - e * (jnp.mean(pd, axis=0) / jnp.pi)[None]  # grey specular part (M, n)
    z, x = _spec_coordinates(model, s, e, rows["cos_i"], rows["cos_o"], rows["theta_r"])
    n_spec = msum(spec_use.astype(jnp.int32))
    if paper:  # Eq. 7: the two T_spec samples with the smallest theta_r
        order = jnp.argsort(jnp.where(spec_use, rows["theta_r"], jnp.inf), axis=0)
        spec_use = spec_use & (jnp.argsort(order, axis=0) < 2)
    else:  # fewer than two T_spec samples: start from every non-diffuse sample (weights z^2)
        spec_use = jnp.where((n_spec >= 2)[None], spec_use, use & (classes != T_DIFF))
    return _line_fit(model, z, x, spec_use) + (n_spec,)


def _refit_diffuse(model, data, ln_ps, ln_rough, w):
    """Closed-form pd `(N, 3)` (within the fit's bounds `[0, 1]`) and its std with the
    specular part fixed, over all valid samples."""
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
    return jnp.clip(pd, 0.0, 1.0), jnp.where(n[:, None] > 1, std, jnp.inf)  # the fit's bounds


def _solve_optimistix(residual, p0, data, steps):
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)

    def one(p, d):
        sol = optx.least_squares(lambda q, a: residual(q, a), solver, p, args=d, throw=False,
                                 max_steps=max(steps, 64))
        return sol.value

    return jax.jit(jax.vmap(one))(p0, data)


# -- variable projection in ln roughness ------------------------------------------------------
#
# Given the roughness the model `y_jc = E_j (pd_c / pi + ps g_j)` is linear in pd (each
# channel touching one colour) and ps, so each row is a 1-D problem in ln roughness with
# (pd, ps) solved exactly under their bounds (`lm`).

_LN_ROUGH_LO, _LN_ROUGH_HI = float(np.log(1e-4)), float(np.log(np.pi / 2))
_PS_MAX = 10.0
#: Grid of starts: every other value of the shared roughness grid (32, 3.6 mrad to 1.2 rad).
_GRID = brdf.ROUGHNESS_GRID[1::2]


def _squared_weights(y, use, floor):
    """Squared residual weights `(M, 3, n)` of the noise model `sqrt((0.01 y)^2 + f^2)`,
    `f = max(floor, 1e-4 max y)`, 0 where unused; and the row's largest value `(n,)`."""
    # A reduction, not a written-out max: XLA would inline that into every element below.
    top = jnp.max(jnp.where(use[:, None], y, 0.0), axis=(0, 1))
    f = jnp.maximum(floor, 1e-4 * top)
    return jnp.where(use[:, None], 1.0 / ((0.01 * y) ** 2 + (f**2)[None, None]), 0.0), top


def _lobe_terms(model, rows):
    """Per-sample terms `(M, n)`: `a = E / pi` (d pred / d pd_c) and `(amp, x)` with
    `E * unit lobe = amp exp(-x kappa) scale` (kappa, scale from the roughness:
    `_lobes`); zero for unused samples."""
    valid = rows["use"] & (rows["cos_i"] > 0) & (rows["cos_o"] > 0)
    e = jnp.where(valid, rows["e"], 0.0)
    ci = jnp.maximum(rows["cos_i"], brdf.COS_FLOOR)
    co = jnp.maximum(rows["cos_o"], brdf.COS_FLOOR)
    if model == "torrance-sparrow":
        amp, x = e / (ci * co), rows["theta_r"] ** 2
    else:
        c = jnp.maximum(jnp.cos(rows["theta_r"]), brdf.COS_FLOOR)
        amp, x = e / (4.0 * jnp.pi * jnp.sqrt(ci * co)), (jnp.sin(rows["theta_r"]) / c) ** 2
    return {"a": e / jnp.pi, "amp": amp, "x": x}


def _weight_terms(y, lobe, ww):
    """Roughness-free weighted terms for squared weights `ww` `(M, 3, n)`: per sample `wa`
    `(M, 3, n)`, `wsum`, `wy` `(M, n)`; per row `s11`, `s11_inv`, `b1` (3 x `(n,)`), `yy`,
    all relative to `norm` `(n,)` (yy, the cost of a zero model)."""
    a = lobe["a"]
    wa, wy = ww * a[:, None], ww * y
    yy = msum(wy[:, 0] * y[:, 0] + wy[:, 1] * y[:, 1] + wy[:, 2] * y[:, 2])
    # Relative sums are better scaled, and dividing by a per-row value ends each sum in a
    # division, which XLA-CPU computes once instead of inlining the sum into every reader.
    norm = jnp.where(yy > 0, yy, 1.0)
    s11 = msum(wa * a[:, None]) / norm[None]
    return {"wa": wa, "wsum": ww[:, 0] + ww[:, 1] + ww[:, 2],
            "wy": wy[:, 0] + wy[:, 1] + wy[:, 2], "norm": norm, "yy": yy / norm, "s11": list(s11),
            "s11_inv": list(jnp.where(s11 > 0, 1.0 / jnp.where(s11 > 0, s11, 1.0), 0.0)),
            "b1": list(msum(wa * y) / norm[None])}


def _lobes(model, lobe, rho):
    """`b = E g` (unit-ps specular radiance) and `t = d ln b / d rho`, each `(M, n)`, at
    ln roughness `rho` `(n,)`."""
    inv_r2 = jnp.exp(-2.0 * rho)[None]
    amp, x = lobe["amp"], lobe["x"]
    if model == "torrance-sparrow":  # exp(-x / (2 r^2))
        kappa = 0.5 * inv_r2
        return amp * jnp.exp(-jnp.minimum(x * kappa, 700.0)), 2.0 * kappa * x
    return amp * inv_r2 * jnp.exp(-jnp.minimum(x * inv_r2, 700.0)), 2.0 * inv_r2 * x - 2.0  # exp(-x / r^2) / r^2


def _sums(model, lobe, terms, rho):
    """Weighted sums over the samples with the lobe `b` at ln roughness `rho` `(n,)` and its
    derivative `d = b t` (`_lobes`), relative to `terms["norm"]`."""

    def integrands(a):
        b, t = _lobes(model, a, rho)
        d = b * t
        wa, wsum, wy = a["wa"], a["wsum"], a["wy"]
        return [wa * b[:, None], wsum * b * b, wy * b, wa * d[:, None], wsum * b * d, wsum * d * d, wy * d]

    sums = block_sums(integrands, {"amp": lobe["amp"], "x": lobe["x"], "wa": terms["wa"], "wsum": terms["wsum"],
                                   "wy": terms["wy"]})
    out = list(sums[0]) + sums[1:3] + list(sums[3]) + sums[4:]
    out = [x / terms["norm"] for x in out]
    return {"s12": out[:3], "s22": out[3], "b2": out[4], "s1d": out[5:8], "s2d": out[8], "sdd": out[9],
            "b2d": out[10]}


def _cost(terms, s, pd, ps):
    """The weighted squared residual (relative to `norm`) expanded in the sums: no
    per-sample pass."""
    return terms["yy"] - 2.0 * ps * s["b2"] + ps * ps * s["s22"] + rowsum(
        [pd[c] * (pd[c] * terms["s11"][c] - 2.0 * terms["b1"][c] + 2.0 * ps * s["s12"][c]) for c in range(3)])


def _with_prior(s, prior):
    """The sums `s` with a Gaussian prior on ps added (`prior`: relative precisions `l_ps`,
    `l_rho` and means `m_ps`, `m_rho`, each `(n,)`): quadratic in ps, so the arrow stays."""
    if prior is None:
        return s
    return dict(s, s22=s["s22"] + prior["l_ps"], b2=s["b2"] + prior["l_ps"] * prior["m_ps"])


def _prior_cost(prior, rho):
    """The prior's constant and roughness terms of the relative cost, and half its first
    and second derivative in `rho`."""
    d = rho - prior["m_rho"]
    return prior["l_ps"] * prior["m_ps"] ** 2 + prior["l_rho"] * d * d, prior["l_rho"] * d, prior["l_rho"]


def _profile(model, lobe, terms, rho, prior=None):
    """Projected (relative) cost at `rho` `(n,)` with pd, ps solved under their bounds, half
    its derivative and half its Gauss-Newton second derivative: `(cost, g, h)`. With a
    `prior` (`_with_prior`) the cost is the negative log posterior (relative)."""
    s = _with_prior(_sums(model, lobe, terms, rho), prior)
    pd, ps, free = bounded_arrow_solve(terms["s11"], terms["s11_inv"], s["s12"], s["s22"], terms["b1"], s["b2"])
    cost = _cost(terms, s, pd, ps)
    g, h = projected_step_terms(terms["s11_inv"], s["s12"], s["s22"], pd, ps, free, s["s1d"], s["s2d"], s["sdd"],
                                s["b2d"])
    if prior is not None:
        c, gp, hp = _prior_cost(prior, rho)
        cost, g, h = cost + c, g + gp, h + hp
    return cost, g, h


def _start(model, lobe, terms, rho_closed):
    """Start `(n,)` in ln roughness, on float32 `lobe` and `terms` (of the soft weights):
    of the values of `_GRID` and the closed form `rho_closed`, the one whose Newton step
    in the projected cost (at most one grid spacing) predicts the lowest cost -- so a
    basin narrower than the grid spacing still wins."""
    logs = np.log(_GRID).astype(np.float32)
    spacing = float(logs[1] - logs[0])

    def predicted(rho):
        cost, g, h = _profile(model, lobe, terms, rho)
        newton = -g / jnp.maximum(h, jnp.finfo(jnp.float32).tiny)
        near = jnp.abs(newton) <= spacing
        cost = jnp.where(near, cost + g * newton, cost)
        return jnp.where(jnp.isfinite(cost), cost, jnp.inf), jnp.where(near, rho + newton, rho)

    def scan(best, log_r):  # the grid, one value at a time: each step's data stays in cache
        cost, rho = predicted(jnp.full_like(terms["yy"], log_r))
        better = cost < best[0]
        return (jnp.where(better, cost, best[0]), jnp.where(better, rho, best[1])), None

    (_, rho), _ = jax.lax.scan(scan, predicted(rho_closed.astype(jnp.float32)), logs)
    return jnp.clip(rho.astype(rho_closed.dtype), _LN_ROUGH_LO, _LN_ROUGH_HI)


def _solution(model, lobe, terms, rho=None, params=None, prior=None):
    """Parameters `(5, n)` (pd_rgb, ps, ln roughness), weighted cost `(n,)` and Gauss-Newton
    variances `(5, n)` (for unit noise) at ln roughness `rho` with pd, ps solved there
    (ps capped at `_PS_MAX`), or at given `params` `(5, n)`. (The cost from the sums:
    against yy its rounding is 1e-16, far below any noise.) With a `prior` the parameters
    are the posterior mode at `rho`, the variances the posterior's; the cost is the data's."""
    if params is not None:
        rho = params[4]
    s = _sums(model, lobe, terms, rho)
    post = _with_prior(s, prior)
    if params is None:
        pd, ps, _ = bounded_arrow_solve(terms["s11"], terms["s11_inv"], post["s12"], post["s22"], terms["b1"],
                                        post["b2"])
        ps = jnp.minimum(ps, _PS_MAX)
    else:
        pd, ps = [params[c] for c in range(3)], params[3]
    cost = jnp.maximum(_cost(terms, s, pd, ps), 0.0) * terms["norm"]
    # J^T J of (pd_rgb, ps, ln roughness) over the relative sums; each pd touches one channel.
    zero = jnp.zeros_like(ps)
    l_rho = zero if prior is None else prior["l_rho"]
    jtj = [[terms["s11"][0]], [zero, terms["s11"][1]], [zero, zero, terms["s11"][2]], s["s12"] + [post["s22"]],
           [ps * v for v in s["s1d"]] + [ps * s["s2d"], ps * ps * s["sdd"] + l_rho]]
    var = jnp.stack(spd_inverse_diagonal(jtj)) / terms["norm"][None]
    return jnp.stack(pd + [ps, rho]), cost, var


@partial(jax.jit, static_argnames=("model", "paper"))
def _prepare(rows, noise_floor, model, paper):
    """First stage for one sample-major chunk: closed forms, weights, per-sample terms
    and, unless `paper`, the float32 terms of the start search.

    (Two compiled stages, not one: in one program XLA fuses the per-sample preparation
    into the later loops' neighbours and ran 1.4x slower.)"""
    pd0, has_diff = _diffuse_init(rows["y"], rows["e"], rows["use"], rows["classes"], rows["theta_r"], paper)
    ln_ps0, ln_rough0, spec_ok, n_spec = _specular_init(model, rows, pd0, paper)
    ww, top = _squared_weights(rows["y"], rows["use"], noise_floor)
    lobe = _lobe_terms(model, rows)
    out = {"lobe": lobe, "terms": _weight_terms(rows["y"], lobe, ww), "spec_ok": spec_ok, "n_spec": n_spec,
           "has_diff": has_diff, "p0": jnp.concatenate([jnp.clip(pd0, 0.0, 1.0), jnp.exp(ln_ps0)[None], ln_rough0[None]]),
           "dof": 3 * msum(rows["use"].astype(jnp.int32)) - 5}
    if not paper:
        # Softer weights to choose the start: with purely relative weights the dim tail
        # samples make the profile so sharp in roughness that a grid can miss its minimum.
        soft = jnp.minimum(ww, 1.0 / (rows["y"] ** 2 + ((0.05 * top) ** 2)[None, None] + 1e-300))
        out["start"] = jax.tree_util.tree_map(lambda v: v.astype(jnp.float32),
                                              (lobe, _weight_terms(rows["y"], lobe, soft)))
    return out


@partial(jax.jit, static_argnames=("model", "paper", "solver", "steps"))
def _polish(prep, rows, noise_floor, model, paper, solver, steps):
    """Second stage for one chunk: start, polish and Gauss-Newton variances."""
    lobe, terms, p0, spec_ok = prep["lobe"], prep["terms"], prep["p0"], prep["spec_ok"]
    params = p0
    if not paper:
        rho0 = _start(model, *prep["start"], jnp.clip(p0[4], _LN_ROUGH_LO, _LN_ROUGH_HI))
        if solver == "lm":
            rho, cost = gauss_newton_1d(lambda r: _profile(model, lobe, terms, r), rho0, steps,
                                        _LN_ROUGH_LO, _LN_ROUGH_HI)
            params = None
        else:  # optimistix's LM on the full model, per row, from both starts; the lower cost wins
            row_major = {k: jnp.moveaxis(rows[k], -1, 0) for k in ("y", "e", "cos_i", "cos_o", "theta_r", "use")}
            row_major["w"] = jnp.sqrt(jnp.moveaxis(_squared_weights(rows["y"], rows["use"], noise_floor)[0], -1, 0))
            both = jax.tree_util.tree_map(lambda v: jnp.concatenate([v, v]), row_major)
            starts = jnp.concatenate([p0.T, _solution(model, lobe, terms, rho0)[0].T])
            residual = _make_residual(model)
            polished = _solve_optimistix(residual, starts, both, steps)
            cost = jax.vmap(lambda p, d: jnp.sum(residual(p, d) ** 2))(polished, both)
            cost = jnp.where(jnp.all(jnp.isfinite(polished), axis=1), cost, jnp.inf)
            n = p0.shape[1]
            params = jnp.where((cost[n:] < cost[:n])[:, None], polished[n:], polished[:n]).T
            cost = jnp.minimum(cost[:n], cost[n:])
        spec_ok = spec_ok | jnp.isfinite(cost)
    if params is None:
        params, cost, var = _solution(model, lobe, terms, rho)
    else:
        params = jnp.where(jnp.all(jnp.isfinite(params), axis=0)[None], params, p0)
        # Rows the data cannot pin down may wander; keep them in range (they stay flagged).
        params = jnp.clip(params, np.array([[0.0]] * 4 + [[_LN_ROUGH_LO]]), np.array([[_PS_MAX]] * 4 + [[_LN_ROUGH_HI]]))
        params, cost, var = _solution(model, lobe, terms, params=params)
    return {"params": params, "var": var, "cost": cost, "dof": prep["dof"], "spec_ok": spec_ok,
            "n_spec": prep["n_spec"], "has_diff": prep["has_diff"],
            "lobe_second": _second_largest(_lobe_signal(model, lobe, terms, params))}


def _lobe_signal(model, lobe, terms, params):
    """Per sample `(M, n)`: the squared weighted size of the fitted specular part,
    `sum_c (w_jc ps b_j)^2` (its squared signal-to-noise ratio for unit residual variance)."""
    b, _ = _lobes(model, lobe, params[4])
    return (params[3][None] * b) ** 2 * terms["wsum"]


def _second_largest(values):
    """Second largest over the samples of `values` `(M, n)`, per row (0 for one sample):
    written out for a few samples (faster on XLA-CPU), a sort beyond."""
    if values.shape[0] >= 2 * SAMPLE_BLOCK:
        return jnp.sort(values, axis=0)[-2]
    first, second = values[0], jnp.zeros_like(values[0])
    for v in values[1:]:
        second = jnp.maximum(second, jnp.minimum(first, v))
        first = jnp.maximum(first, v)
    return second


@partial(jax.jit, static_argnames=("model",))
def _reduced(prep, rho, model):
    """Per row and ln roughness `rho` `(G, n)`: `(G, 3, n)` coefficients `(c0, a, b)` of the
    weighted squared residual `c0 - 2 ps b + ps^2 a` with pd profiled out (unbounded): what
    a material's joint lobe fit sums over its rows."""
    lobe, terms = prep["lobe"], prep["terms"]
    wa, wsum, wy, inv, b1 = terms["wa"], terms["wsum"], terms["wy"], terms["s11_inv"], terms["b1"]
    c0 = terms["yy"] - rowsum([b1[c] * b1[c] * inv[c] for c in range(3)])

    def one(r):
        def integrands(a):
            b, _ = _lobes(model, a, r)
            return [a["wa"] * b[:, None], a["wsum"] * b * b, a["wy"] * b]

        s12, s22, b2 = block_sums(integrands, {"amp": lobe["amp"], "x": lobe["x"], "wa": wa, "wsum": wsum, "wy": wy})
        s12, s22, b2 = list(s12 / terms["norm"][None]), s22 / terms["norm"], b2 / terms["norm"]
        a = s22 - rowsum([s12[c] * s12[c] * inv[c] for c in range(3)])
        bb = b2 - rowsum([b1[c] * s12[c] * inv[c] for c in range(3)])
        return jnp.stack([c0, a, bb]) * terms["norm"][None]

    return jax.lax.map(one, rho)


@partial(jax.jit, static_argnames=("model",))
def _material_reduced(prep, rho, labels, weights, model):
    """`_reduced` summed per material on one chunk: `rho` `(G, K)` ln roughness per grid
    value and material, `labels` `(n,)`, `weights` `(n,)` per row -> `(G, 3, K)`."""
    per_row = _reduced(prep, rho[:, labels], model=model)
    # A segment sum, not a product with a one-hot matrix: a row left out (weight 0) whose sums
    # overflow adds nothing rather than inf * 0 = NaN, and a GPU does not round to TF32.
    weighted = jnp.where(weights[None, None] > 0, per_row * weights[None, None], 0.0)
    summed = jax.ops.segment_sum(jnp.moveaxis(weighted, -1, 0), labels, num_segments=rho.shape[1])
    return jnp.moveaxis(summed, 0, -1)


@partial(jax.jit, static_argnames=("model", "steps"))
def _map_polish(prep, prior, rho_own, model, steps):
    """Posterior mode per row of one chunk: the row's likelihood with the Gaussian `prior`
    (`m_ps`, `v_ps`, `m_rho`, `v_rho` `(n,)`, variances in units of the row's residual scale
    `s2` `(n,)`; infinite variance: no prior), from the better of the own fit's roughness
    `rho_own` and the prior mean. Returns params `(5, n)`, unit-noise variances `(5, n)`."""
    lobe, terms = prep["lobe"], prep["terms"]

    def precision(v):
        ok = jnp.isfinite(v) & (v > 0)
        return jnp.where(ok, prior["s2"] / (terms["norm"] * jnp.where(ok, v, 1.0)), 0.0)

    rel = {"l_ps": precision(prior["v_ps"]), "l_rho": precision(prior["v_rho"]),
           "m_ps": prior["m_ps"], "m_rho": jnp.clip(prior["m_rho"], _LN_ROUGH_LO, _LN_ROUGH_HI)}

    def evaluate(r):
        return _profile(model, lobe, terms, r, rel)

    start = jnp.clip(rho_own, _LN_ROUGH_LO, _LN_ROUGH_HI)
    start = jnp.where(evaluate(rel["m_rho"])[0] < evaluate(start)[0], rel["m_rho"], start)
    rho, _ = gauss_newton_1d(evaluate, start, steps, _LN_ROUGH_LO, _LN_ROUGH_HI)
    params, cost, var = _solution(model, lobe, terms, rho, prior=rel)
    return {"params": params, "var": var, "cost": cost, "logdet": _lobe_logdet(model, lobe, terms, params, rel)}


def _lobe_logdet(model, lobe, terms, params, rel):
    """ln det of the posterior precision of (ps, ln roughness), pd profiled out (the Schur
    complement of the Gauss-Newton matrix over pd), for unit noise: the Laplace
    approximation's volume term of a row's evidence."""
    ps, rho = params[3], params[4]
    s = _sums(model, lobe, terms, rho)
    inv = terms["s11_inv"]
    a_pp = s["s22"] + rel["l_ps"] - rowsum([s["s12"][c] ** 2 * inv[c] for c in range(3)])
    a_pr = ps * (s["s2d"] - rowsum([s["s12"][c] * s["s1d"][c] * inv[c] for c in range(3)]))
    a_rr = ps * ps * (s["sdd"] - rowsum([s["s1d"][c] ** 2 * inv[c] for c in range(3)])) + rel["l_rho"]
    det = jnp.maximum(a_pp * a_rr - a_pr * a_pr, 1e-300)
    return jnp.log(det) + 2.0 * jnp.log(terms["norm"])


def _bucket(n: int, step: int) -> int:
    return max(step, -(-n // step) * step)


_CHUNK = 4000  # rows per compiled call (not a power of two: those ran 2-2.7x slower)
_ROW_KEYS = ("y", "e", "cos_i", "cos_o", "theta_r", "use", "classes")


def _chunked(rows: dict) -> tuple[dict, int]:
    """Rows `(N, M, ...)` as sample-major chunks `(C, M, ..., chunk)`, padded with unused
    entries to bucketed sizes so that scans of similar size reuse one compilation:
    observations to a multiple of 4, rows to a multiple of the chunk (itself a multiple
    of 500, at most `_CHUNK`). Returns the chunks and the chunk size."""
    n, m = np.shape(rows["use"])
    chunk = min(_CHUNK, _bucket(n, 500))
    n_pad, m_pad = _bucket(n, chunk), _bucket(m, 4)
    out = {}
    for key in _ROW_KEYS:
        value = np.asarray(rows[key])
        if (n_pad, m_pad) != (n, m):
            widths = [(0, n_pad - n), (0, m_pad - m)] + [(0, 0)] * (value.ndim - 2)
            fill = T_INVALID if key == "classes" else (1.0 if key in ("cos_i", "cos_o") else 0)
            value = np.pad(value, widths, constant_values=fill)
        value = value.reshape(n_pad // chunk, chunk, *value.shape[1:])
        out[key] = np.ascontiguousarray(np.moveaxis(value, 1, -1))
    return out, chunk


_weights = jax.jit(_noise_weights)


def _fit(rows, options, noise_floor, steps):
    """`_prepare` and `_polish` on `prepare_rows` output; per-row results `(N, ...)` as NumPy,
    and the chunks' prepared terms (`ChunkedRows`) for further solves on the same rows.

    Compiled calls per chunk rather than `lax.map` inside one program: consecutive
    calls are dispatched asynchronously and run side by side on the CPU's cores (1.5x
    faster on two cores than the loop compiled into one program)."""
    n_rows = np.shape(rows["use"])[0]
    chunks, chunk = _chunked(rows)
    outs, preps = [], []
    for i in range(len(chunks["use"])):
        rows_i = {k: v[i] for k, v in chunks.items()}
        prep = _prepare(rows_i, float(noise_floor), model=options.model, paper=options.paper)
        preps.append({"lobe": prep["lobe"], "terms": prep["terms"]})
        outs.append(_polish(prep, rows_i if options.solver == "optimistix" else None, float(noise_floor),
                            model=options.model, paper=options.paper, solver=options.solver, steps=steps))
    out = {k: np.concatenate([np.asarray(o[k]) for o in outs], axis=-1).T[:n_rows] for k in outs[0]}
    return out, ChunkedRows(preps, chunk, n_rows, options.model)


class ChunkedRows:
    """The prepared per-sample terms of every chunk of rows, to solve again on the same data
    (`material_sums`: a material's joint lobe fit; `map_fit`: the posterior mode under a prior)."""

    def __init__(self, preps, chunk, n_rows, model):
        self.preps, self.chunk, self.n_rows, self.model = preps, chunk, n_rows, model

    def _split(self, a, fill=None):
        """`(..., N)` -> list of `(..., chunk)` per chunk (padded with `fill`, default the last
        value)."""
        a = np.asarray(a)
        pad = len(self.preps) * self.chunk - self.n_rows
        end = a[..., -1:] if fill is None else np.full(a.shape[:-1] + (1,), fill, a.dtype)
        a = np.concatenate([a, np.repeat(end, pad, axis=-1)], axis=-1) if pad else a
        return [a[..., i * self.chunk:(i + 1) * self.chunk] for i in range(len(self.preps))]

    def material_sums(self, rho, labels, k: int, weights):
        """`_reduced` summed per material with row `weights`: `rho` `(G, k)` ln roughness per
        grid value and material, `labels` `(N,)` in `[0, k)` -> `(G, 3, k)` (float64)."""
        k_pad = -(-k // 8) * 8  # one compilation for every K up to 8
        rho = np.pad(np.asarray(rho, np.float64), [(0, 0), (0, k_pad - k)])
        parts = [_material_reduced(p, jnp.asarray(rho), jnp.asarray(lab), jnp.asarray(w), model=self.model)
                 for p, lab, w in zip(self.preps, self._split(labels), self._split(weights, fill=0.0))]
        return np.sum([np.asarray(x, np.float64) for x in parts], axis=0)[..., :k]

    def row_sums(self, rho, rows=None):
        """`_reduced` per row: `rho` `(G, N)` ln roughness per grid value and row -> `(G, 3, N)`
        (float64) coefficients `(c0, a, b)` of each row's squared residual, pd profiled out.
        With `rows` `(m,)` indices: those rows only, `rho` `(G, m)` -> `(G, 3, m)`."""
        if rows is not None:
            return self.subset(rows).row_sums(rho) if len(rows) else np.zeros((len(rho), 3, 0))
        parts = [_reduced(p, jnp.asarray(r), model=self.model) for p, r in zip(self.preps, self._split(rho))]
        out = np.empty(np.shape(rho)[:-1] + (3, self.n_rows))  # contiguous: callers reshape it
        for i, part in enumerate(parts):
            start = i * self.chunk
            out[..., start:start + self.chunk] = np.asarray(part, np.float64)[..., :self.n_rows - start]
        return out

    def grid_rows(self, rho_grid, weights) -> np.ndarray:
        """Every row's `row_sums` at each ln roughness of `rho_grid` `(G,)`, times its
        `weights` `(N,)`, rows first: `(N, G, 3)` (`prior.weighted_rows`, chunk by chunk)."""
        g = len(rho_grid)
        rho = jnp.asarray(np.broadcast_to(np.asarray(rho_grid, np.float64)[:, None], (g, self.chunk)))
        parts = [_reduced(p, rho, model=self.model) for p in self.preps]
        weights = np.asarray(weights, np.float64)
        out = np.empty((self.n_rows, g, 3))
        for i, part in enumerate(parts):
            start = i * self.chunk
            stop = min(start + self.chunk, self.n_rows)
            out[start:stop] = prior_mod.weighted_rows(np.asarray(part, np.float64)[..., :stop - start],
                                                      weights[start:stop])
        return out

    def subset(self, rows) -> "ChunkedRows":
        """The rows `rows` `(m,)` (indices, m >= 1) alone, in chunks of the same size (one
        compilation serves both)."""
        if len(rows) == 0:
            raise ValueError("ChunkedRows.subset: no rows")
        rows = np.asarray(rows, np.int64)
        idx = jnp.asarray(np.r_[rows, np.full(_bucket(len(rows), self.chunk) - len(rows), rows[-1])])
        gathered = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=-1)[..., idx], *self.preps)
        preps = [jax.tree_util.tree_map(lambda a, i=i: a[..., i * self.chunk:(i + 1) * self.chunk], gathered)
                 for i in range(len(idx) // self.chunk)]
        return ChunkedRows(preps, self.chunk, len(rows), self.model)

    def map_fit(self, prior: dict, rho_own, steps: int) -> dict:
        """Posterior modes (`_map_polish`); `prior` of `(N,)` arrays; returns `params` `(N, 5)`,
        `var` `(N, 5)` (unit noise), `cost` `(N,)` and `logdet` `(N,)` (`_map_polish`)."""
        split = {k: self._split(v) for k, v in prior.items()}
        outs = [_map_polish(p, {k: jnp.asarray(v[i]) for k, v in split.items()}, jnp.asarray(r), model=self.model,
                            steps=steps) for i, (p, r) in enumerate(zip(self.preps, self._split(rho_own)))]
        return {k: np.concatenate([np.asarray(o[k]) for o in outs], axis=-1).T[:self.n_rows] for k in outs[0]}


_MIN_SPEC = 1  # T_spec samples a point needs for its own lobe (the paper's Eq. 7: 2)


#: Smallest residual variance scale: float32 rounding of radiance (6e-8 relative) against the
#: 1 % noise model. Below it a noise-free scan's "noise" is rounding, and a lobe fitted to
#: rounding would look significant.
_S2_FLOOR = 1e-10


#: Rounding of the fit's own arithmetic: the cost is a sum of about ten O(1) terms relative to
#: the data's weighted square `yy` (`_cost`), so a cost below a few ulp of `yy` is rounding,
#: not a fit that good (float32, the command line's precision: 1e-3 of a 1 % noise model).
_COST_ULPS = 16.0
#: Two heights of the lobe, each `min_snr` above the noise, must by themselves pin ln roughness
#: within 1 (the Fisher rule's bound): by Eq. 7 `ln z_j - ln z_k` is the difference of their
#: exponents (`ln roughness = -ln b / 2 + const`), so `|dx| / sqrt(1/S_j^2 + 1/S_k^2) >= 1/2`
#: (`S` signal-to-noise). Samples where the lobe is below the noise only bound it from above,
#: and the local curvature there (large on noise-free data) is no evidence: seen at one
#: height (twice, or once and in tails), ps and roughness trade off along a valley.
_MIN_HEIGHT_CONTRAST = 0.5


def _height_contrast(expo, snr2, min_snr):
    """`(N,)` best `|expo_j - expo_k| / sqrt(1/S_j^2 + 1/S_k^2)` over pairs of samples above
    `min_snr` (`snr2` `(N, M)` = S^2), one of them the strongest, the lowest or the highest
    exponent among those."""
    above = snr2 >= min_snr**2
    inv = np.where(above, 1.0 / np.maximum(snr2, 1e-300), np.inf)
    idx = np.arange(len(expo))
    best = np.zeros(len(expo))
    for j in (np.argmax(np.where(above, snr2, -np.inf), 1), np.argmin(np.where(above, expo, np.inf), 1),
              np.argmax(np.where(above, expo, -np.inf), 1)):
        q = np.abs(expo - expo[idx, j][:, None]) / np.sqrt(inv + inv[idx, j][:, None])
        best = np.maximum(best, np.max(np.where(above & above[idx, j][:, None], q, 0.0), 1))
    return best


def _lobe_heights(model, rows, ps, rough, weights):
    """The fitted lobe per sample `(N, M)`: its exponent (the lobe is `exp(-exponent)` of its
    peak) and its squared weighted size (signal-to-noise squared for unit residual variance)."""
    th = np.asarray(rows["theta_r"], np.float64)
    use = np.asarray(rows["use"])
    weights = np.where(use[..., None], weights, 0.0)  # unused samples may carry infinite weights
    r2 = np.maximum(rough, 1e-12)[:, None] ** 2
    if model == "torrance-sparrow":
        expo = th**2 / (2.0 * r2)
    else:
        expo = (np.sin(th) / np.maximum(np.cos(th), brdf.COS_FLOOR)) ** 2 / r2
    unit = np.asarray(brdf.MODELS[model][1](jnp.asarray(np.ones_like(th)), jnp.asarray(np.log(np.sqrt(r2))),
                                            jnp.asarray(rows["cos_i"]), jnp.asarray(rows["cos_o"]), jnp.asarray(th)))
    signal = (ps[:, None] * unit * np.asarray(rows["e"], np.float64)) ** 2 \
        * np.sum(np.asarray(weights, np.float64) ** 2, -1)
    return expo, np.where(use, signal, 0.0)


def _noise_scale(cost, dof, floor=_S2_FLOOR):
    """Residual variance per row `(N,)`, at least the median over the rows (inf where
    `dof <= 0`) and at least `floor` (`_S2_FLOOR`, or per row `(N,)`).

    A row's own `cost / dof` rests on a few samples (its RGB channels share
    the lobe, and often the noise: grey objects, Monte Carlo renders), so by
    chance it can be far below the noise; the scan-wide median cannot.
    """
    ok = (dof > 0) & np.isfinite(cost)
    s2 = np.where(ok, cost / np.maximum(dof, 1), np.inf)
    return np.maximum(np.maximum(s2, np.median(s2[ok])), np.maximum(floor, _S2_FLOOR)) if ok.any() else s2


class RowFit(dict):
    """`fit_rows` output (a dict): `pd` `(N, 3)`, `ps` `(N,)`, `roughness` `(N,)` [rad]
    and their standard deviations `std_pd`, `std_ps`, `std_roughness` (inf where
    unknown), `identifiable` `(N,)` (specular part measured), `has_diffuse_sample`
    `(N,)`, `weights` `(N, M, 3)` residual weights, `noise_scale` `(N,)` the residual
    variance scale of each row, `cost` `(N,)` its weighted squared residual, `std_ln_roughness` `(N,)`, `spec_samples` `(N,)` its
    strong-specular (`T_SPEC`) samples, and `chunks` (`ChunkedRows`)."""


def fit_rows(rows: dict, options: LocalOptions = LocalOptions(), noise_floor: float = 0.0) -> RowFit:
    """Steps 1-3 of Method I (closed forms, polish, uncertainty) on `prepare_rows` output.

    `noise_floor`: absolute radiance noise floor of the weights (e.g. the
    quantisation step / sqrt(12)).
    """
    out, chunks = _fit(rows, options, noise_floor, options.steps)
    params, spec_ok, n_spec, has_diff = out["params"], out["spec_ok"], out["n_spec"], out["has_diff"]
    weights = np.asarray(_weights(rows["y"], rows["use"], noise_floor))
    use = np.asarray(rows["use"])
    yy = np.sum((np.where(use[..., None], weights, 0.0) * np.asarray(rows["y"], np.float64)) ** 2, axis=(1, 2))
    eps = np.finfo(np.asarray(out["cost"]).dtype).eps  # of the arithmetic the fit ran in
    s2 = _noise_scale(out["cost"], out["dof"], _COST_ULPS * eps * yy / np.maximum(out["dof"], 1))
    var = np.where(np.isfinite(out["var"]) & np.isfinite(s2)[:, None], out["var"] * s2[:, None], np.inf)
    sd = np.sqrt(np.maximum(var, 0.0))
    rough = np.exp(params[:, 4])
    # The lobe seen above the noise at two heights that pin its roughness (`_MIN_HEIGHT_CONTRAST`).
    expo, signal = _lobe_heights(options.model, rows, params[:, 3], rough, weights)
    heights = _height_contrast(expo, signal / np.where(np.isfinite(s2), s2, np.inf)[:, None], options.min_snr) \
        >= _MIN_HEIGHT_CONTRAST
    if options.paper:
        enough = n_spec >= 2
    elif options.prior:
        # Statistics alone, no angle: the Fisher information of the point's own samples
        # (below), and the fitted lobe standing above the noise in two samples (with one, ps
        # and roughness trade off along a valley the local curvature does not show).
        enough = (use.sum(1) >= 3) & (out["lobe_second"] >= options.min_snr**2 * s2) \
            & heights
    else:
        # The full-model fit pins a lobe down from one T_spec sample and its T_none
        # flanks, but without any sample near the peak (theta_r <= theta_th2) a "lobe"
        # is only a smooth trend over the flank, which a diffuse-model mismatch
        # (interreflection, MC or sensor bias) imitates: not evidence of a lobe.
        # And the fitted lobe must stand above the noise in two samples or more: with one,
        # ps and roughness trade off along a valley whose edge (where the flanks start to
        # object) gives a sharp-looking but arbitrary minimum.
        seen_twice = out["lobe_second"] >= options.min_snr**2 * s2
        enough = (n_spec >= _MIN_SPEC) & (use.sum(1) >= 3) & seen_twice & heights
    identifiable = enough & spec_ok & np.all(np.isfinite(params), 1) \
        & (params[:, 3] > options.min_snr * sd[:, 3]) & (sd[:, 4] < 1.0)
    std_rough = np.where(np.isinf(sd[:, 4]), np.inf, rough * np.where(np.isinf(sd[:, 4]), 0.0, sd[:, 4]))
    return RowFit(pd=params[:, :3], ps=params[:, 3], roughness=rough, std_pd=sd[:, :3], std_ps=sd[:, 3],
                  std_roughness=std_rough, identifiable=identifiable, has_diffuse_sample=has_diff,
                  weights=weights, noise_scale=s2, cost=out["cost"],
                  std_ln_roughness=sd[:, 4], spec_samples=n_spec, chunks=chunks)


def _residual_scale(s2, observed, region=None) -> dict:
    """Medians of the rows' residual variance `s2` `(N,)` over the `observed` points and over
    those in `region` (None where not given or empty)."""
    def median(mask):
        v = s2[mask & np.isfinite(s2)]
        return float(np.median(v)) if v.size else None

    return {"median": median(observed),
            "region_median": None if region is None else median(observed & np.asarray(region, bool))}


def fill_unobserved_pd(pd, std_pd, status, observed_any, adjacency, window: int, keep_values: bool = False) -> None:
    """In place: pd of points without any usable sample from the observed ones in their
    window (status at least `interpolated`; `unresolved` when filled from farther away
    or when nothing is observed), their std infinite. `keep_values`: their pd is already
    filled (status and std only)."""
    if observed_any.all():
        return
    if observed_any.any():
        filled = window_fill(pd, observed_any, adjacency, window)
        if not keep_values:
            pd[~observed_any] = filled.values[~observed_any]
        near = ~observed_any & filled.window
        status[near] = np.maximum(status[near], INTERPOLATED)
        status[~observed_any & filled.diffused] = UNRESOLVED
    else:
        status[:] = UNRESOLVED
    std_pd[~observed_any] = np.inf


def _pd_with_prior(scan, labels, observed_any, dark, pd, std_pd, options, meta, var_test=None):
    """In place: each observed point's pd (given its lobe, as the stages before left it) with
    the empirical-Bayes prior of its material-mates' pd field (`prior.diffuse_prior`, built
    from those same estimates; `var_test` its conflict test's variances); the lobes stay as
    they are. A `dark` `(N, 3)` channel (every
    sample quantised to 0) has no estimate of its own: it takes the prior. `meta` gets the
    counts, and each of its `material_lobes` entries (where it has them) its pd spread.
    Returns the prior (`prior.DiffusePrior`)."""
    std_pd[dark] = np.inf
    if var_test is not None:
        var_test = np.where(dark, np.inf, var_test)
    diffuse = prior_mod.diffuse_prior(pd, std_pd**2, observed_any, labels, scan.vertices,
                                      neighbours=options.prior_neighbours, k=len(meta.get("material_lobes", [])),
                                      var_test=var_test)
    prior_mod.combine_with_prior(pd, std_pd, observed_any & diffuse.available, diffuse.mean, diffuse.var)
    np.clip(pd, 0.0, 1.0, out=pd)  # the fit's bounds
    for m, entry in enumerate(meta.get("material_lobes", [])):
        entry["spread_pd"] = [float(v) if np.isfinite(v) else None for v in diffuse.spread[m]]  # strict JSON
        entry["pd_neighbours"] = int(diffuse.neighbours[m])  # 0: the whole material
    meta["points_with_diffuse_prior"] = int((observed_any & diffuse.available).sum())
    meta["points_in_conflict_with_diffuse_prior"] = int(diffuse.conflict.sum())
    return diffuse


def dark_channels(rows) -> np.ndarray:
    """`(N, 3)` bool: channels of observed points whose every sample quantised to 0 (`rows`
    from `prepare_rows`). They only bound pd from above: not a pd of 0."""
    use = np.asarray(rows["use"])
    return use.any(1)[:, None] & ~np.any(use[..., None] & (np.asarray(rows["y"]) > 0), axis=1)


def finite_outputs(values, stds) -> None:
    """In place: nothing non-finite leaves an estimator. Values never NaN (0), std may
    be inf (unknown), never NaN."""
    for a in values:
        np.nan_to_num(a, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    for a in stds:
        np.nan_to_num(a, copy=False, nan=np.inf, posinf=np.inf)


def _features(fit, own, observed_any, dark):
    """Clustering features `(N, 5)` and their variances: pd per channel (missing where
    `dark` `(N, 3)`); ln ps and ln roughness where the point's own samples pin its lobe
    (elsewhere missing, variance inf)."""
    ps = np.where(own, fit["ps"], 1.0)  # own lobes have ps > 0
    var_ps = np.where(own, (fit["std_ps"] / ps) ** 2, np.inf)
    var_rho = np.where(own, fit["std_ln_roughness"] ** 2, np.inf)
    x = np.c_[fit["pd"], np.log(ps), np.log(fit["roughness"])]
    v = np.c_[np.where(dark, np.inf, fit["std_pd"] ** 2), var_ps, var_rho]
    v = np.where(np.isfinite(x) & np.isfinite(v) & observed_any[:, None], np.maximum(v, prior_mod._VAR_FLOOR), np.inf)
    return np.where(np.isfinite(x), x, 0.0), v


#: Spreads of a neighbourhood's lobe about a point's (variances in ln ps and ln roughness)
#: among which the evidence chooses: from far below any fit's resolution (0.1 %) to the
#: whole range a reflectance can take (a factor e).
_SPREADS = np.geomspace(1e-6, 1.0, 13)


def _local_spread(chunks, local, materials, s2, rho_own, observed_any, steps):
    """Spreads `(K, 2)` (ln ps, ln roughness) of the lobe about each point's neighbourhood
    lobe, per material whose lobe varies (`prior.local_lobes`): those under which the
    points' own samples are most probable (`prior.spread_by_evidence`), each row's evidence
    in the Laplace approximation at its posterior mode: `-(chi^2 + prior penalty + ln det
    prior covariance + ln det posterior precision) / 2`. 0 for the other materials."""
    k, labels = materials.k, materials.labels
    rows = prior_mod.local_prior(local, labels, np.zeros((k, 2)))[4] & observed_any
    if not rows.any():
        return np.zeros((k, 2))

    def log_evidence(spread):
        m_ps, v_ps, m_rho, v_rho, _ = prior_mod.local_prior(local, labels, spread)
        post = chunks.map_fit({"m_ps": m_ps, "v_ps": v_ps, "m_rho": m_rho, "v_rho": v_rho, "s2": s2}, rho_own, steps)
        ps, rho = post["params"][:, 3], post["params"][:, 4]
        v_ps, v_rho = np.where(rows, v_ps, 1.0), np.where(rows, v_rho, 1.0)
        penalty = (ps - m_ps) ** 2 / v_ps + (rho - m_rho) ** 2 / v_rho
        return np.where(rows, -0.5 * (post["cost"] / s2 + penalty + np.log(v_ps * v_rho) + post["logdet"]
                                      - 2.0 * np.log(s2)), 0.0)

    spread = prior_mod.spread_by_evidence(log_evidence, labels, k, rows, _SPREADS)
    return np.where(local.neighbours[:, None] > 0, spread, 0.0)


def _posterior_lobes(scan, fit, observed_any, dark, options):
    """The shared-prior stage of Method I (`jaxrefl.reflectance.prior`): materials, their joint lobes, the
    empirical-Bayes prior and every point's posterior mode. Returns per-point arrays and a
    meta dict."""
    own = fit["identifiable"]
    s2 = fit["noise_scale"]
    inv_s2 = np.where(np.isfinite(s2) & (s2 > 0) & observed_any, 1.0 / np.where(np.isfinite(s2) & (s2 > 0), s2, 1.0),
                      0.0)
    x, v = _features(fit, own, observed_any, dark)
    materials = prior_mod.fit_materials(x, v, scan.vertices, k_max=options.materials)
    chunks = fit["chunks"]
    peak = fit["spec_samples"] * observed_any
    # Every row's chi^2 coefficients on the roughness grid, summed per material for the joint
    # lobes and per neighbourhood for the local ones.
    grid = np.log(brdf.ROUGHNESS_GRID)
    grid_rows = chunks.grid_rows(grid, inv_s2)  # (N, G, 3)
    grid_materials = np.moveaxis(prior_mod.material_totals(grid_rows, materials.labels, materials.k,
                                                           np.ones(len(inv_s2))), 0, -1)  # (G, 3, K)
    lobes = prior_mod.material_lobes(chunks.material_sums, materials.labels, materials.k, inv_s2, grid,
                                     min_snr=options.min_snr, peak_samples=peak, grid_sums=grid_materials)
    # Own lobes count only in a material whose lobe some sample saw near its peak.
    near_peak = np.bincount(materials.labels, weights=peak.astype(np.float64), minlength=materials.k)
    seen = near_peak >= 2
    own = own & seen[materials.labels]
    rho_own = np.log(fit["roughness"])
    # Prior variances in units of each row's residual scale (the row solver's weights).
    s2_safe = np.where(np.isfinite(s2) & (s2 > 0), s2, 1.0)
    # Where the lobe varies within a material, each point's prior is its neighbourhood's lobe
    # (cross-validated size), as wide as the spread that best explains the points' own data.
    local = prior_mod.local_lobes(chunks.row_sums, materials.labels, materials.k, scan.vertices, inv_s2, grid,
                                  ps_bound=partial(brdf.ps_bound, options.model), min_snr=options.min_snr,
                                  peak_samples=peak, max_neighbours=4 * options.prior_neighbours,
                                  grid_rows=grid_rows)
    spread = _local_spread(chunks, local, materials, s2_safe, rho_own, observed_any, options.steps)
    prior = prior_mod.lobe_prior(fit["ps"], fit["std_ps"] ** 2, rho_own, fit["std_ln_roughness"] ** 2, own,
                                 materials.labels, lobes, scan.vertices, neighbours=options.prior_neighbours,
                                 fitted=observed_any & np.isfinite(fit["std_ps"]) & np.isfinite(fit["std_ln_roughness"]),
                                 local=local, spread=spread)
    post = chunks.map_fit({"m_ps": np.where(prior.available, prior.mean_ps, 0.0),
                           "v_ps": np.where(prior.available, prior.var_ps, np.inf),
                           "m_rho": np.where(prior.available, prior.mean_rho, 0.0),
                           "v_rho": np.where(prior.available, prior.var_rho, np.inf), "s2": s2_safe},
                          rho_own, options.steps)
    var = np.where(np.isfinite(post["var"]), post["var"] * s2_safe[:, None], np.inf)
    # The lobe's uncertainty under the prior widened where the measured lobes around a point
    # disagree with it (`prior.cover_measured`); the estimate keeps the prior's mode.
    var[:, 3] = prior_mod.covered_variance(var[:, 3], prior.var_ps, prior.cover_var_ps)
    var[:, 4] = prior_mod.covered_variance(var[:, 4], prior.var_rho, prior.cover_var_rho)
    sd = np.sqrt(np.maximum(var, 0.0))
    measured, pooled = prior_mod.status_from_posterior(own, fit["std_ps"] ** 2, fit["std_ln_roughness"] ** 2, prior)
    # Prior-data conflict: a point whose own samples fit the prior's lobe worse than their own
    # best lobe by more than chance allows is not of its material's lobe (a glaze on part of
    # one colour): it keeps its own fit, measured where that pins the lobe, else unresolved.
    conflict = prior_mod.prior_conflict(post["cost"], fit["cost"], s2_safe, prior.available & observed_any)
    measured, pooled = (measured | (own & conflict)), pooled & ~conflict
    own_params = np.c_[fit["pd"], fit["ps"], np.log(np.maximum(fit["roughness"], 1e-12))]
    own_sd = np.c_[fit["std_pd"], fit["std_ps"], fit["std_ln_roughness"]]
    params = np.where(conflict[:, None], own_params, post["params"])
    sd = np.where(conflict[:, None], own_sd, sd)
    meta = {"materials": materials.k, "bic": {str(k): float(b) for k, b in materials.bic.items()},
            "material_lobes": prior_mod.lobes_meta(lobes, prior.spread_ps, prior.spread_rho,
                                                      partial(brdf.ps_bound, options.model))}
    for m, entry in enumerate(meta["material_lobes"]):
        entry["samples_near_peak"] = int(near_peak[m])
        entry["neighbours"] = int(local.neighbours[m])  # 0: the whole material
        entry["spread_local_ps"], entry["spread_local_ln_roughness"] = (float(v) for v in spread[m])
    meta["points_in_conflict_with_prior"] = int(conflict.sum())
    # priors widened to cover the measured lobes around them (`prior.cover_measured`)
    meta["points_with_widened_prior"] = int((prior.widened & observed_any).sum())
    measured, pooled = measured & observed_any, pooled & observed_any
    # The lobe an unresolved point reports: its material's prior lobe; in a material with no
    # prior (joint lobe not identifiable, no point with its own) whose samples still show a
    # lobe (joint fit ps > 0, seen on its flank, within the energy bound), that joint fit,
    # where a lobe copied from the nearest known points would be another material's
    # (`material_fill`); NaN: the copy (a joint fit with ps 0 saw no lobe, and one beyond the
    # bound is a sharp lobe the samples never reached: neither's roughness says anything).
    fallback = np.where(prior.available[:, None], np.c_[prior.mean_ps, np.exp(prior.mean_rho)], np.nan)
    if options.material_fill and (measured | pooled).any():
        joint = np.c_[lobes.ps, np.exp(lobes.rho)]  # (K, 2)
        lobe = lobes.within_bound(partial(brdf.ps_bound, options.model)) & (joint[:, 0] > 0) & (joint[:, 1] > 0)
        shows = np.isnan(fallback[:, 0]) & lobe[materials.labels]
        fallback[shows] = joint[materials.labels[shows]]
    return {"params": params, "sd": sd, "measured": measured, "pooled": pooled,
            "conflict": conflict & ~measured, "labels": materials.labels, "fallback_lobe": fallback}, meta


def _bound_lobes(model, ps, rough) -> int:
    """In place: ps within the energy bound of its roughness (`brdf.ps_bound`); returns how
    many points it clipped."""
    bound = brdf.ps_bound(model, np.where(rough > 0, rough, 1.0))
    over = ps > bound
    ps[over] = bound[over]
    return int(over.sum())


def _fill_from_prior(scan, fit, observed_any, dark, adjacency, options, values, stds, status):
    """In place on `values` (pd, ps, roughness), `stds` and `status`: the posterior modes
    (`_posterior_lobes`) where the point's own samples or its prior pin the lobe
    (`measured` / `pooled`); elsewhere its material's prior lobe, or where the material has
    none its joint fit if that shows a lobe, else the lobe of the nearest such points, `unresolved`
    (or, where the point's samples reject its prior, its own fit, `unresolved`).
    Returns `(measured, need_spec, material labels, meta)`."""
    pd, ps, rough = values
    std_pd, std_ps, std_rough = stds
    post, meta = _posterior_lobes(scan, fit, observed_any, dark, options)
    known = post["measured"] | post["pooled"]
    params, sd = post["params"], post["sd"]
    pd[known], ps[known], rough[known] = params[known, :3], params[known, 3], np.exp(params[known, 4])
    std_pd[known], std_ps[known] = sd[known, :3], sd[known, 3]
    std_rough[known] = rough[known] * sd[known, 4]
    status[post["pooled"]] = POOLED
    need_spec = ~known
    if known.any():
        logs = np.c_[np.log(np.maximum(ps, 1e-12)), np.log(np.maximum(rough, 1e-12))]
        filled = window_fill(logs, known, adjacency, options.window)
        ps[need_spec], rough[need_spec] = np.exp(filled.values[need_spec, 0]), np.exp(filled.values[need_spec, 1])
    else:  # no lobe anywhere: report none, roughness undefined (0)
        ps[need_spec], rough[need_spec] = 0.0, 0.0
    # Where its material has a lobe of its own (`_posterior_lobes`' fallback), an unresolved
    # point takes that, not a mean of lobes across a material edge; still `unresolved`.
    lobe = post["fallback_lobe"]
    own = need_spec & np.isfinite(lobe[:, 0])
    ps[own], rough[own] = lobe[own, 0], lobe[own, 1]
    # Points whose data reject their prior keep their own fit: loose, but not contradicted.
    mine = post["conflict"]
    pd[mine], ps[mine], rough[mine] = params[mine, :3], params[mine, 3], np.exp(params[mine, 4])
    status[need_spec] = UNRESOLVED
    std_ps[need_spec], std_rough[need_spec] = np.inf, np.inf
    meta["points_pooled"] = int(post["pooled"].sum())
    return post["measured"], need_spec, post["labels"], meta


def _fill_from_gates(scan, rows, fit, observed_any, adjacency, options, q, values, stds, status):
    """In place, as `_fill_from_prior`, with the gated rules (`prior=False`, `paper`): a
    lobe pooled with same-material neighbours (`pool`), else the log-mean of the measured
    lobes in the `window` ring. Returns `(need_spec, use_pool)`."""
    pd, ps, rough = values
    _, std_ps, std_rough = stds
    identifiable = fit["identifiable"]
    if options.pool and not options.paper:
        # Points that could not measure their own lobe share it with same-material
        # neighbours (`pool`); they count as interpolated, with finite std.
        pooled = pooled_specular(rows, pd, scan.vertices, options.model, k=options.pool_neighbours,
                                 tau=options.pool_tau, min_snr=options.min_snr,
                                 noise_floor=q / np.sqrt(12.0), where=~identifiable & observed_any)
        use_pool = ~identifiable & pooled["identifiable"] & observed_any
        ps[use_pool], rough[use_pool] = pooled["ps"][use_pool], pooled["roughness"][use_pool]
        std_ps_pool, std_rough_pool = pooled["std_ps"][use_pool], pooled["std_roughness"][use_pool]
    else:
        use_pool = np.zeros(scan.n_points, bool)
    need_spec = ~identifiable & ~use_pool
    if identifiable.any():
        # Filled from the points' own lobes only: a rare false pooled lobe (noise) would
        # otherwise spread over a whole region without specular samples.
        logs = np.c_[np.log(np.maximum(ps, 1e-12)), np.log(rough)]
        filled = window_fill(logs, identifiable, adjacency, options.window)
        ps[need_spec], rough[need_spec] = np.exp(filled.values[need_spec, 0]), np.exp(filled.values[need_spec, 1])
        status[filled.window] = INTERPOLATED
        status[filled.diffused] = UNRESOLVED
    else:  # no lobe measured anywhere: report none, roughness undefined (0)
        ps[need_spec], rough[need_spec] = 0.0, 0.0
        status[need_spec] = UNRESOLVED
    std_ps[need_spec] = np.inf
    std_rough[need_spec] = np.inf
    if use_pool.any():
        std_ps[use_pool], std_rough[use_pool] = std_ps_pool, std_rough_pool
        status[use_pool] = INTERPOLATED
    return need_spec, use_pool


def estimate_local(scan, options: LocalOptions = LocalOptions(), caster: RayCaster | None = None,
                   rows: dict | None = None, quantisation: float | None = None, region=None) -> Estimate:
    """Method I on a scan with radiance. See the module docstring. `rows`: the scan's
    `prepare_rows(scan, options.thresholds, caster)` when the caller has it already;
    `quantisation`: the sensor's quantisation step where `scan.radiance` is not the sensor's
    values (Method II passes what is left after the interreflected light, off the sensor's
    lattice); None: detected from `scan.radiance` (`quantisation_step`); `region` `(N,)` bool
    points whose residual scale `meta['residual_scale']` reports apart.

    **Returns:** `Estimate` (no NaN: unresolved values are filled, their
    standard deviations infinite); `meta['residual_scale']`: the median over the observed
    points (and over those in `region`) of each point's residual variance in units of the
    weights (`noise_scale`, at least the scan's median): how far the model leaves the
    images unexplained, the median point's being the noise where most points fit.
    """
    scan, top = checks.method_input(scan)  # top: called by the user, not by another method
    if quantisation is not None and not (np.isfinite(quantisation) and quantisation >= 0):
        raise ValueError(f"quantisation: the sensor's step must be finite and >= 0, got {quantisation!r}")
    if region is not None and np.shape(region) != (scan.n_points,):
        raise ValueError(f"region: must be ({scan.n_points},) bool, got shape {np.shape(region)}")
    timings = {}
    t0 = time.perf_counter()
    rows = rows if rows is not None else prepare_rows(scan, options.thresholds, caster)
    q = quantisation_step(scan.radiance, rows["use"]) if quantisation is None else float(quantisation)
    timings["classify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    fit = fit_rows(rows, options, noise_floor=q / np.sqrt(12.0))
    timings["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    identifiable = fit["identifiable"]
    observed_any = rows["use"].any(1)
    dark = dark_channels(rows)
    pd, ps, rough = fit["pd"].copy(), fit["ps"].copy(), fit["roughness"].copy()
    std_pd, std_ps, std_rough = fit["std_pd"].copy(), fit["std_ps"].copy(), fit["std_roughness"].copy()
    status = np.full(scan.n_points, MEASURED, np.int8)

    adjacency = vertex_adjacency(scan.faces, scan.n_points)
    values, stds = (pd, ps, rough), (std_pd, std_ps, std_rough)
    if options.prior and not options.paper:
        identifiable, need_spec, material, extra = _fill_from_prior(scan, fit, observed_any, dark, adjacency,
                                                                    options, values, stds, status)
        refit = need_spec & observed_any
    else:
        need_spec, use_pool = _fill_from_gates(scan, rows, fit, observed_any, adjacency, options, q, values, stds,
                                               status)
        refit = (need_spec | use_pool) & observed_any
        extra, material = {"points_with_pooled_lobe": int(use_pool.sum())}, None

    extra["points_at_energy_bound"] = _bound_lobes(options.model, ps, rough)
    # pd of points whose specular part came from elsewhere, with that part fixed.
    if refit.any():
        jrows = {k: jnp.asarray(v) for k, v in rows.items()}
        pd_fix, std_fix = _refit_diffuse(options.model, jrows, jnp.log(jnp.maximum(ps, 1e-300)),
                                         # no lobe (ps 0, roughness 0 "undefined"): any roughness
                                         # gives a zero lobe, 0 would give 0/0 in the Ward lobe
                                         jnp.log(np.where(ps > 0, np.maximum(rough, 1e-300), 1.0)),
                                         fit["weights"])
        pd[refit], std_pd[refit] = np.asarray(pd_fix)[refit], np.asarray(std_fix)[refit]
    if material is not None:
        _pd_with_prior(scan, material, observed_any, dark, pd, std_pd, options, extra)
    fill_unobserved_pd(pd, std_pd, status, observed_any, adjacency, options.window)
    timings["fill"] = time.perf_counter() - t0
    finite_outputs((pd, ps, rough), (std_pd, std_ps, std_rough))
    meta = {"method": "local", "model": options.model,
            "options": {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v)
                        for k, v in asdict(options).items()},
            "quantisation_step": q, "seconds": timings,
            "points_with_observations": int(observed_any.sum()),
            "points_with_diffuse_only_sample": int(fit["has_diffuse_sample"].sum()),
            "residual_scale": _residual_scale(fit["noise_scale"], observed_any, region),
            "observation_checks": scan.meta["observation_checks"], **extra}
    est = Estimate(pd, ps, rough, status, std_pd, std_ps, std_rough, identifiable, observed_any,
                   options.model, meta, material)
    if options.interreflection_rays and observed_any.any():
        # pd's uncertainty also holds the light the object reflects onto itself, which this
        # method's model leaves in pd (Methods II, III and auto model it, and call this one with
        # `interreflection_rays` 0: on radiance with that light removed, or for a start).
        t0 = time.perf_counter()
        std_pd[:], meta["interreflection"], warning = pd_sd_with_interreflection(
            scan, est, rows, options.interreflection_rays, caster)  # in place: est's
        timings["interreflection"] = time.perf_counter() - t0
        if warning:
            meta.setdefault("method_warnings", []).append(warning)
            logger.warning(warning)
    if top:
        checks.estimate_warnings(est, logger)
    return est
