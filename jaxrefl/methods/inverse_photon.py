"""Method III: inverse photon mapping (paper §5), diffuse and specular
interreflections removed.

Model of observation `(x, j)` (Ward, `jaxrefl.reflectance.brdf`), radiance [W/(sr m^2)]:

    y_xj = pd_x / pi (E_xj + D_xj) + ps_x (E_xj k_xj(alpha_x) + Q_xj)

with `E = Y cos_i / C^2` the direct irradiance (0 where shadowed or unused),
`k` the unit Ward lobe of the direct light, and `D`, `Q` the incident flux
density and lobe-weighted sum of light that reflected at least once: the first
bounce from a final gather at every observation (`jaxrefl.methods.final_gather`,
`gather_rays` per observation; a photon map blurs the mirror image of nearby
surfaces over its kernel), the later bounces from the photon map
(`jaxrefl.methods.photon`, `jaxrefl.methods.gather`); both are functions of every point's
reflectance through fixed ray geometry.

Photon paths are traced once from a proposal (Method I's Ward estimate) and
re-weighted by path replay, so each outer iteration is one compiled function of
`(pd, ps, alpha)`; between blocks of `check_every` iterations the effective
sample size is measured and the paths are re-traced from the current estimate
when it has fallen below `retrace_ess`.

Outer iteration `k` (all points at once, `jax.lax.scan` inside one `jit`):

0. photon map `(D, Q)` at the current estimate; its image difference (Eq. 14,
   noise-weighted: `sum w^2 (y - y_hat)^2` over all used samples) is recorded,
   and the estimate with the smallest one is kept (§5.2);
1. step (a): `pd` per channel by least squares with `D` added to the irradiance and
   the current specular part taken off (closed form, clipped to `[0, 1]`), over all
   the point's samples where its own lobe is fitted from them (lobe evidence, below),
   else over its `T_diff` samples (all when it has none): a lobe filled from other
   points may be wrong, and would leak into pd. The paper (`local.paper`) uses the
   `T_diff` samples wherever there are any, which are few and dark (measurements:
   `benchmarks/RESULTS_rigs_gi.md`);
2. step (b), on the points with lobe evidence only (a `T_spec` sample and two
   step (b) samples): `ps`, `alpha` from the `T_spec` and `T_none` samples with
   `pd` fixed and `Q` held at the current `alpha`: `ps` projected out (least
   squares, `0 <= ps <= PS_MAX`) and `ln alpha` by a 16-value grid then
   safeguarded Newton steps (`solver='lm'`, `lm.gauss_newton_1d`), or both by a
   downhill simplex over `(ln ps, ln alpha)` as the paper (`solver='simplex'`,
   optimistix NelderMead, vmapped over the points). Only lobes the data pin down (the
   identifiability test below) are taken; every point's lobe is then set from the
   measured lobes (the lobe fill below), so that an unmeasurable lobe cannot feed
   invented light to its neighbours;
3. the new estimate moves a share `damping` of the way to (a) and (b) (0.5 by
   default: where interreflection is strong the plain alternation of the two coupled
   fits overshoots and can swing between two states).

After the iterations the specular part counts as measured where the point has
a `T_spec` sample, two or more samples in step (b), `ps` above `min_snr`
standard deviations, `ln alpha` known to +-1 (Gauss-Newton covariance,
scaled by the reduced chi^2 when above 1), and, where `min_fit_p` > 0, a fit
that passes a chi^2 goodness-of-fit test at that p-value (`_identifiable`).
The test is off by default: a lobe its samples do not fit already carries a
covariance inflated by that chi^2, so the precision-weighted fill below outvotes
it; the test, on top, also rejects good lobes whose samples the model explains
less well for other reasons (ps varying across a point's samples), so that lobes
are filled from too few, and it raised the image error (measurements:
`benchmarks/RESULTS_notes.md`).

**Lobe fill** (`_fill_lobes`, in every iteration and at the end): each point's
`ln ps` and `ln alpha` are the precision-weighted Huber M-estimate, scale
`fill_sd` (`fill.precise_huber`: a mean of values that agree to `fill_sd`, a
median of those farther apart), of the measured lobes nearest it in space
(itself first where measured; at most `fill_neighbours`), taken in order of distance until their precisions
(`1 / var`) add up to `1 / fill_sd^2`; each precision is scaled by how alike the two
points' diffuse albedo is (`_material_affinity`, scale `fill_pd_scale`: pd
apart by that share counts e^-1; from the pd at the start of every
`check_every` iterations, and the final pd at the end), so lobes are pooled within a material and
not across its edge (a glossy part beside a matte one would otherwise take the matte
lobe). A lobe measured to `fill_sd` or better
stands alone; a looser one is outvoted by its neighbours; an unmeasured one is
filled from the nearest measured ones, reaching as far as it takes to pin it.
The point's status says `interpolated` where a measured lobe lies in its
`window` ring, `unresolved` where it had to reach farther. Why not the window
mean (as Methods I and II): beside a concave fold no lobe may be measurable, and
the few lobes measured farther off, at the edge of the highlight, are loose and
some are wrong; averaged into the fold they send the wrong mirrored light to the
facing surface and bias pd there (measurements: `benchmarks/RESULTS_notes.md`).

**pd at the final lobes** (`polish` steps (a), lobes fixed, undamped unless a step
raises the image difference): `pd` is taken to the fixed point of its own
interreflection under the final lobes. The
kept iterate's `pd` was fitted against the lobes of its own iteration, which
the fill and the damping still moved; every point is refitted, to the fixed point,
since each point's pd depends through the interreflected light on its neighbours'
lobes and pd (refitting only the filled points, once, left pd beside a fold further
off: `benchmarks/RESULTS_notes.md`).

Per-point lights (a rotating scanner, `light_pos` `(N, M, 3)`) are binned into
light configurations as Method II (`radiosity.light_configs`, `light_bin`);
each configuration gets `photons * M / C` photons.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..geometry.raycast import RayCaster
from ..reflectance import brdf
from ..reflectance.classify import T_DIFF, T_SPEC, Thresholds
from ..reflectance.fill import nearest_candidates, precise_huber, vertex_adjacency, window_reach
from ..result import Estimate
from ..scan import checks
from .final_gather import gather_parts, gather_rays
from .lm import gauss_newton_1d
from .local import (
    INTERPOLATED,
    MEASURED,
    UNRESOLVED,
    LocalOptions,
    _noise_weights,
    _pd_with_prior,
    dark_channels,
    estimate_local,
    fill_unobserved_pd,
    finite_outputs,
    prepare_rows,
    quantisation_step,
)
from .photon import PhotonReplay, replay_parts
from .radiosity import config_cameras, light_configs

__all__ = ["PhotonOptions", "estimate_photon", "ALPHA_RANGE"]

#: Range of the Ward roughness alpha [rad] the fits search.
ALPHA_RANGE = (0.005, 1.0)
logger = logging.getLogger(__name__)
#: Largest specular reflectance the fits accept (an energy bound: larger values make the
#: photon powers grow without limit along paths).
PS_MAX = 1.0
_GRID = 16


@dataclass(frozen=True)
class PhotonOptions:
    """Method III settings (see the module docstring). `photons` emitted per
    light; `iterations` outer iterations (the paper's th_2); `solver` 'lm' or
    'simplex'; `steps` Newton steps in ln alpha per iteration (lm) or simplex
    steps (simplex, x 10); `target_photons` effective photons per gather;
    `retrace_ess` re-trace threshold on the effective sample size (fraction);
    `check_every` iterations between checks; `damping` share of each
    iteration's change taken (1: the paper's plain alternation, which can swing
    between two states where interreflection is strong); `light_bin` [m] for per-point lights;
    `gather_rays` final-gather rays per observation for the first bounce
    (`jaxrefl.methods.final_gather`; 0: the photon map gathers every bounce), halved
    until the scan's total fits `gather_budget`; `min_snr`, `min_fit_p` the
    identifiability test; `fill_sd`, `fill_neighbours`, `fill_pd_scale` the lobe fill;
    `polish` steps (a) at the final lobes; `window` the ring that decides
    `interpolated` against `unresolved`; `local` Method I options of the start (Ward)."""

    photons: int = 1_000_000
    iterations: int = 50
    solver: str = "lm"
    steps: int = 8
    damping: float = 0.5
    target_photons: float = 256.0
    retrace_ess: float = 0.3
    check_every: int = 10
    light_bin: float = 0.1
    gather_rays: int = 1024
    gather_budget: int = 8_000_000
    seed: int = 0
    min_snr: float = 3.0
    min_fit_p: float = 0.0
    fill_neighbours: int = 64
    fill_sd: float = 0.02
    fill_pd_scale: float = 0.2
    polish: int = 10
    window: int = 5
    local: LocalOptions = field(default_factory=lambda: LocalOptions(model="ward"))

    def __post_init__(self):
        if self.solver not in ("lm", "simplex"):
            raise ValueError(f"solver must be 'lm' or 'simplex', got {self.solver!r}")
        if self.photons < 1000 or self.iterations < 1 or self.steps < 1 or self.check_every < 1:
            raise ValueError("photons must be >= 1000; iterations, steps, check_every >= 1")
        if self.gather_rays < 0 or self.gather_budget < 1:
            raise ValueError("gather_rays must be >= 0 and gather_budget >= 1")
        if not self.fill_sd > 0 or self.fill_neighbours < 1 or self.polish < 0 or not self.fill_pd_scale >= 0:
            raise ValueError("fill_sd must be > 0, fill_neighbours >= 1, polish >= 0, fill_pd_scale >= 0")
        if not 0 < self.damping <= 1:
            raise ValueError("damping must lie in (0, 1]")
        if not 0 <= self.retrace_ess < 1:
            raise ValueError("retrace_ess must lie in [0, 1)")
        if self.local.model != "ward":
            raise ValueError("Method III uses the Ward model: local.model must be 'ward'")

    @property
    def thresholds(self) -> Thresholds:
        return self.local.thresholds


# -- per-row pieces ----------------------------------------------------------------------


def _lobe_rows(rho, ci, co, th):
    """Unit Ward lobe `(N, M)` [1/sr] at `ln alpha = rho` `(N,)` (or `(N, 1)`)."""
    return brdf.ward_specular(1.0, jnp.reshape(rho, (-1, 1)), ci, co, th)


def _predicted(pd, ps, rho, r, d, q):
    """Predicted radiance `(N, M, 3)` of every observation."""
    k = _lobe_rows(rho, r["cos_i"], r["cos_o"], r["theta_r"])
    e = r["e"][..., None]
    return pd[:, None, :] / jnp.pi * (e + d) + ps[:, None, None] * (e * k[..., None] + q)


def _image_difference(pd, ps, rho, r, d, q):
    """Eq. 14 summed over the scan, noise-weighted, and the mean absolute difference."""
    diff = jnp.where(r["use"][..., None], r["y"] - _predicted(pd, ps, rho, r, d, q), 0.0)
    n = jnp.maximum(3.0 * jnp.sum(r["use"]), 1.0)
    return jnp.sum(r["w2"] * diff**2), jnp.sum(jnp.abs(diff)) / n


def _step_a(pd, ps, rho, r, d, q):
    """pd `(N, 3)` by least squares over the step (a) samples, and its information
    `sum w^2 (E + D)^2` `(N, 3)` (0 where the point has no sample)."""
    k = _lobe_rows(rho, r["cos_i"], r["cos_o"], r["theta_r"])
    e = r["e"][..., None]
    a = r["a"][..., None]
    x = (e + d) / jnp.pi
    s = r["y"] - ps[:, None, None] * (e * k[..., None] + q)
    num = jnp.sum(jnp.where(a, r["w2"] * x * s, 0.0), axis=1)
    den = jnp.sum(jnp.where(a, r["w2"] * x * x, 0.0), axis=1)
    ok = den > 0
    new = jnp.where(ok, num / jnp.where(ok, den, 1.0), pd)
    return jnp.clip(new, 0.0, 1.0), den


def _spec_args(pd, r, d, q):
    s = r["y"] - pd[:, None, :] / jnp.pi * (r["e"][..., None] + d)
    return (s, r["e"], r["cos_i"], r["cos_o"], r["theta_r"], q, r["w2"], r["b"])


def _spec_coefficients(args):
    """Per-row sums of step (b)'s projected cost over the channels.

    With `g = E k + Q` on the step (b) samples (`k` the unit lobe `(M,)`) the cost
    `sum w (s - ps g)^2` is quadratic in `k`; the sums `A = E sum_c w s`,
    `B = E^2 sum_c w`, `C = 2 E sum_c w Q` `(N, M)` and `c_sq`, `c_qq`, `c_ss` `(N,)`
    are taken once per step (b), and each cost evaluation then needs only `k`."""
    s, e, ci, co, th, q, w2, b = args
    bm = b[..., None]
    sv, qv = jnp.where(bm, s, 0.0), jnp.where(bm, q, 0.0)
    a_m = e * jnp.sum(w2 * sv, -1)
    b_m = jnp.where(b, e * e * jnp.sum(w2, -1), 0.0)
    c_m = 2.0 * e * jnp.sum(w2 * qv, -1)
    sums = tuple(jnp.sum(w2 * x * y, (-2, -1)) for x, y in ((sv, qv), (qv, qv), (sv, sv)))
    return (ci, co, th, a_m, b_m, c_m) + sums


def _spec_row(rho, ci, co, th, a_m, b_m, c_m, c_sq, c_qq, c_ss):
    """Projected cost of one row at `ln alpha = rho` and its `ps >= 0`, from the
    row's `_spec_coefficients`: `ssg = k.A + c_sq`, `sgg = k^2.B + k.C + c_qq`,
    cost `c_ss - 2 ps ssg + ps^2 sgg` (a difference of large numbers: its rounding
    error is ~1e-7 of the signal's chi^2 in float32, far below the noise's)."""
    k = brdf.ward_specular(1.0, rho, ci, co, th)
    ssg = jnp.sum(k * a_m) + c_sq
    sgg = jnp.sum(k * k * b_m + k * c_m) + c_qq
    ok = sgg > 0
    ps = jnp.where(ok, jnp.maximum(ssg, 0.0) / jnp.where(ok, sgg, 1.0), 0.0)
    return jnp.maximum(c_ss - ps * (2.0 * ssg - ps * sgg), 0.0), ps


def _row_derivatives(rho, *coef):
    """Cost and its first and second derivative in `ln alpha` (forward mode: one
    variable, so a second-order `jvp` is the cheapest way to both)."""
    first = lambda r: jax.jvp(lambda x: _spec_row(x, *coef)[0], (r,), (jnp.ones_like(r),))  # noqa: E731
    (cost, g), (_, h) = jax.jvp(first, (rho,), (jnp.ones_like(rho),))
    return cost, g, h


_cost_rows = jax.vmap(lambda rho, *coef: _spec_row(rho, *coef)[0])
_derivative_rows = jax.vmap(_row_derivatives)


def _step_b_lm(rho0, args, steps):
    """`(ps, rho)` `(N,)` minimising the projected cost: the best of `rho0` and a
    16-value grid over `ln ALPHA_RANGE`, then safeguarded Newton steps."""
    lo, hi = np.log(ALPHA_RANGE[0]), np.log(ALPHA_RANGE[1])
    coef = _spec_coefficients(args)
    grid = jnp.linspace(lo, hi, _GRID, dtype=rho0.dtype)
    costs = jax.vmap(lambda g: _cost_rows(jnp.full_like(rho0, g), *coef))(grid)  # (G, N)
    start = jnp.where(_cost_rows(rho0, *coef) <= jnp.min(costs, axis=0), rho0, grid[jnp.argmin(costs, axis=0)])

    def evaluate(rho):
        cost, g, h = _derivative_rows(rho, *coef)
        return cost, 0.5 * g, 0.5 * h

    rho, _ = gauss_newton_1d(evaluate, start, steps, lo, hi, radius=0.5)
    _, ps = jax.vmap(_spec_row)(rho, *coef)
    return ps, rho


def _step_b_simplex(ps0, rho0, args, steps):
    """`(ps, rho)` by a downhill simplex over `(ln ps, ln alpha)` per row (the paper)."""
    lo, hi = np.log(ALPHA_RANGE[0]), np.log(ALPHA_RANGE[1])
    solver = optx.NelderMead(rtol=1e-6, atol=1e-8)

    def one(y0, row):
        def cost(p, row):
            ps = jnp.exp(jnp.clip(p[0], -20.0, 5.0))
            rho = jnp.clip(p[1], lo, hi)
            s, e, ci, co, th, q, w2, b = row
            k = brdf.ward_specular(1.0, rho, ci, co, th)
            g = jnp.where(b[:, None], e[:, None] * k[:, None] + q, 0.0)
            return jnp.sum(jnp.where(b[:, None], w2 * (s - ps * g) ** 2, 0.0))

        sol = optx.minimise(cost, solver, y0, row, max_steps=10 * steps, throw=False)
        return jnp.exp(jnp.clip(sol.value[0], -20.0, 5.0)), jnp.clip(sol.value[1], lo, hi)

    y0 = jnp.stack([jnp.log(jnp.maximum(ps0, 1e-4)), rho0], axis=1)
    return jax.vmap(one)(y0, args)


def _spec_information(ps, rho, args, pd, d, joint):
    """Gauss-Newton covariance diagonal `(var ps, var rho)` and chi^2 of step (b) per row.

    Where `joint` (the point has no `T_diff` sample, so its pd rests on the same samples
    as its lobe) a grey scale of pd is a third parameter: a broad lobe and pd explain such
    samples almost equally well, and the variances must say so."""

    def one(ps, rho, s, e, ci, co, th, q, w2, b, pd, d, joint):
        def g_of(rr):
            k = brdf.ward_specular(1.0, rr, ci, co, th)
            return jnp.where(b[:, None], e[:, None] * k[:, None] + q, 0.0)

        g = g_of(rho)
        j_ps, j_rho = g, ps * jax.jacfwd(g_of)(rho)
        j_pd = jnp.where(b[:, None], pd[None, :] * (e[:, None] + d) / jnp.pi, 0.0)
        cols = (j_pd, j_ps, j_rho)
        a = [[jnp.sum(w2 * cols[i] * cols[j]) for j in range(3)] for i in range(3)]
        det2 = a[1][1] * a[2][2] - a[1][2] ** 2
        det3 = a[0][0] * det2 - a[0][1] * (a[0][1] * a[2][2] - a[1][2] * a[0][2]) \
            + a[0][2] * (a[0][1] * a[1][2] - a[1][1] * a[0][2])
        num_ps = jnp.where(joint, a[0][0] * a[2][2] - a[0][2] ** 2, a[2][2])
        num_rho = jnp.where(joint, a[0][0] * a[1][1] - a[0][1] ** 2, a[1][1])
        det = jnp.where(joint, det3, det2)
        scale = jnp.where(joint, a[0][0] * a[1][1] * a[2][2], a[1][1] * a[2][2])
        ok = det > 1e-12 * jnp.maximum(scale, 1e-300)
        inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), jnp.inf)
        chi2 = jnp.sum(jnp.where(b[:, None], w2 * (s - ps * g) ** 2, 0.0))
        return num_ps * inv_det, num_rho * inv_det, chi2

    return jax.vmap(one)(ps, rho, *args, pd, d, joint)


def _dof(n_b):
    """Degrees of freedom of a lobe fit `(N,)`: 3 channels per step (b) sample, less ps and alpha (at least 1)."""
    return jnp.maximum(3.0 * n_b - 2.0, 1.0)


def _lobe_sd(var_ps, var_rho, chi2, rows):
    """Standard deviations `(sd_ps, sd_rho)` of a lobe fit: its covariance scaled by the
    reduced chi^2 where that exceeds 1 (infinite where the variance is not positive:
    a near-singular information matrix is no information)."""
    dof = _dof(rows["n_b"])
    scale = jnp.maximum(1.0, chi2 / dof)
    return tuple(jnp.where(v > 0, jnp.sqrt(jnp.where(v > 0, v, 1.0) * scale), jnp.inf) for v in (var_ps, var_rho))


@partial(jax.jit, static_argnames=("scale",))
def _material_affinity(pd, nbr, scale):
    """`(N, K)` in `[0, 1]`: how far the candidate lobes `nbr` `(N, K)` speak for each row,
    from how alike their diffuse albedo is: `exp(-((d - d_min) / scale)^2)`, `d` the RGB
    distance of the two `pd` relative to their mean length, `d_min` the row's smallest (a
    row with no alike candidate keeps its most alike ones); None (all alike) where
    `scale` is 0. A relative distance, not one of `ln pd` per channel: a dark channel's
    noise would part points of one material."""
    if not scale:
        return None
    a, b = pd[:, None, :], pd[nbr]
    size = 0.5 * (jnp.linalg.norm(a, axis=-1) + jnp.linalg.norm(b, axis=-1))
    d = jnp.linalg.norm(a - b, axis=-1) / jnp.maximum(size, 1e-6)
    d = d - jnp.min(d, axis=1, keepdims=True)
    return jnp.exp(-jnp.minimum((d / scale) ** 2, 50.0))


def _fill_lobes(ps, rho, known, sd_ps, sd_rho, nbr, target, steps=30, warm=False, affinity=None):
    """`(ps, rho)` `(N,)`: every row's lobe from the measured (`known`) lobes nearest it,
    itself first where measured (`fill.precise_huber` over `nbr`, a Huber M-estimate in
    `ln ps` and `ln alpha`, each weighted by its precision, until they pin it to
    `1 / sqrt(target)`):
    a lobe measured that precisely stands alone, a looser one is outvoted by its
    neighbours, an unmeasured one is filled. Rows with no measured candidate keep theirs.
    `warm`: start from `(ps, rho)` themselves (inside the iterations, where they are the
    last iteration's fill and `steps` can be few)."""
    ln_ps = jnp.log(jnp.maximum(ps, 1e-12))
    w_ps = jnp.where(known, (ps / sd_ps) ** 2, 0.0)
    w_rho = jnp.where(known, 1.0 / sd_rho**2, 0.0)
    f_ps, t_ps = precise_huber(ln_ps, w_ps, nbr, target, steps, ln_ps if warm else None, affinity)
    f_rho, t_rho = precise_huber(rho, w_rho, nbr, target, steps, rho if warm else None, affinity)
    return jnp.where(t_ps > 0, jnp.exp(f_ps), ps), jnp.where(t_rho > 0, f_rho, rho)


def _identifiable(ps, var_ps, var_rho, chi2, rows, min_snr, min_fit_p):
    """Specular part measured: lobe evidence, `ps` above `min_snr` sd, `ln alpha` to +-1
    (covariance scaled by the reduced chi^2 where it exceeds 1), and a fit the noise
    explains: chi^2 goodness of fit with p-value >= `min_fit_p` (chi^2 over the median
    reduced chi^2 of all lobe fits where that exceeds 1). A lobe fitted to
    samples the model does not explain (interreflection it gets wrong, a bad normal)
    is biased however small its covariance (measurements: `benchmarks/RESULTS_notes.md`)."""
    dof = _dof(rows["n_b"])
    sd_ps, sd_rho = _lobe_sd(var_ps, var_rho, chi2, rows)
    # The noise model of the weights may be off by a factor on real data: chi^2 is
    # measured against the median reduced chi^2 of the lobe fits (when above 1).
    red = jnp.where(rows["lobe"] & jnp.isfinite(chi2), chi2 / dof, jnp.nan)
    # (no lobe fit at all, e.g. no point with lobe evidence: nothing to scale by)
    typical = jnp.maximum(1.0, jnp.nan_to_num(jnp.nanmedian(red), nan=1.0)) if red.size else 1.0
    fits = jax.scipy.special.gammaincc(0.5 * dof, 0.5 * jnp.maximum(chi2, 0.0) / typical) >= min_fit_p
    return rows["lobe"] & jnp.isfinite(sd_ps) & jnp.isfinite(sd_rho) & (ps > min_snr * sd_ps) & (sd_rho < 1.0) \
        & fits


# -- the outer loop ----------------------------------------------------------------------


def _to_obs(x, index):
    """Per-configuration `(N, C, 3)` to per-observation `(N, M, 3)`."""
    if index is None:
        return x
    return jnp.take_along_axis(x, index[..., None], axis=1)


def _parts(data, static, index, fg, pd, ps, rho):
    """Interreflected `(D, Q)` `(N, M, 3)` of every observation: the photon map, plus
    the first-bounce final gather `fg` where there is one (then the photon map holds
    only the later bounces)."""
    alpha = jnp.exp(rho)
    d, q = (_to_obs(x, index) for x in replay_parts(data, static, pd, ps, alpha))
    if fg is None:
        return d, q
    dg, qg = gather_parts(fg, pd, ps, alpha, *d.shape[:2])
    return d + dg.astype(d.dtype), q + qg.astype(q.dtype)


#: A step that raises the image difference above this multiple of the lowest one so far
#: overshot (a cavity of high albedo swings by orders of magnitude; a converging
#: alternation wanders within a few per cent of its best, and must be let wander).
_OVERSHOOT = 2.0


def _track(theta, damping, shape, dtype):
    """The line search's state at a fresh start (or after a re-trace, whose photons make
    earlier costs incomparable): `(anchor theta, its (D, Q) of `shape` `(N, M, 3)` and
    `dtype`, its cost, step share)`, the anchor the lowest-cost estimate so far."""
    zero = jnp.zeros(shape, dtype)
    return theta, (zero, zero), jnp.asarray(jnp.inf, dtype), jnp.asarray(damping, dtype)


def _where(flag, new, old):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(flag, a, b), new, old)


def _line_search(anchor, theta, dq, cost, most):
    """One backtracking decision (`_block`): `anchor` (`_track`) updated with the estimate
    `theta` of image difference `cost` and interreflected light `dq`; returns it and the
    estimate to step from, with its `dq`: `theta` unless it overshot (`_OVERSHOOT`), then
    the anchor. The share (`anchor[3]`) halves after an overshoot and doubles, up to
    `most`, with each new lowest image difference (growing back after every accepted step
    would retrace the path that overshot, in a cycle)."""
    best, best_dq, best_cost, share = anchor
    accept = cost <= _OVERSHOOT * best_cost
    lower = cost < best_cost
    best, best_dq = _where(lower, theta, best), _where(lower, dq, best_dq)
    best_cost = jnp.where(lower, cost, best_cost)
    share = jnp.where(accept, jnp.where(lower, jnp.minimum(2.0 * share, most), share), 0.5 * share)
    start = _where(accept, (theta, dq), (best, best_dq))
    return (best, best_dq, best_cost, share), start


@partial(jax.jit, static_argnames=("static", "n_iter", "solver", "steps"))
def _block(data, static, index, fg, rows, lobe_rows, nbr, theta, best, track, n_iter, solver, steps, damping,
           min_snr, min_fit_p, fill_target, affinity):
    """`n_iter` outer iterations from `theta = (pd, ps, rho)`; `best = (theta, cost)`;
    `track` the line search's state (`_track`); `lobe_rows` `(K,)` int32 the points with
    lobe evidence (the only ones step (b) fits); `affinity` `(N, K')` (or None) the
    material affinity of the fill's candidates `nbr`.

    Each iteration moves a share of the way to its steps (a) and (b). Where interreflection
    is strong (a cavity of high albedo) the steps overshoot and the plain alternation swings
    between states orders of magnitude apart in cost: an estimate whose image difference
    exceeds `_OVERSHOOT` times the lowest so far (the anchor) is not stepped from; the next
    step leaves the anchor again with half the share (backtracking), and each new lowest
    image difference doubles the share again, up to `damping`.

    **Returns:** `(theta, best, track, history)`, `history = (cost, mean_abs)` `(n_iter,)`
    each: the image difference of the estimate each iteration started from."""

    spec_rows = {k: rows[k][lobe_rows] for k in ("lobe", "n_b", "joint")}

    def body(carry, _):
        (pd, ps, rho), (best_theta, best_cost), anchor = carry
        d, q = _parts(data, static, index, fg, pd, ps, rho)
        cost, mad = _image_difference(pd, ps, rho, rows, d, q)
        better = cost < best_cost
        best_theta = _where(better, (pd, ps, rho), best_theta)
        best_cost = jnp.where(better, cost, best_cost)
        anchor, ((pd, ps, rho), (d, q)) = _line_search(anchor, (pd, ps, rho), (d, q), cost, damping)
        share = anchor[3]
        pd_new, _ = _step_a(pd, ps, rho, rows, d, q)
        pd = pd + share * (pd_new - pd)
        # Step (b) only where a lobe can be measured at all (the rows `lobe_rows`).
        args = tuple(a[lobe_rows] for a in _spec_args(pd, rows, d, q))
        if solver == "lm":
            ps_k, rho_k = _step_b_lm(rho[lobe_rows], args, steps)
        else:
            ps_k, rho_k = _step_b_simplex(ps[lobe_rows], rho[lobe_rows], args, steps)
        ps_k = jnp.minimum(ps_k, PS_MAX)
        # Lobes the data pin down move; the others are filled from them, as at the end.
        var_ps, var_rho, chi2 = _spec_information(ps_k, rho_k, args, pd[lobe_rows], d[lobe_rows],
                                                  spec_rows["joint"])
        known = jnp.zeros(rho.shape, bool).at[lobe_rows].set(
            _identifiable(ps_k, var_ps, var_rho, chi2, spec_rows, min_snr, min_fit_p))
        sd_ps, sd_rho = (jnp.full(rho.shape, jnp.inf, rho.dtype).at[lobe_rows].set(v)
                         for v in _lobe_sd(var_ps, var_rho, chi2, spec_rows))
        ps_new, rho_new = ps.at[lobe_rows].set(ps_k), rho.at[lobe_rows].set(rho_k)
        ps_new, rho_new = _fill_lobes(jnp.where(known, ps_new, ps), jnp.where(known, rho_new, rho), known,
                                      sd_ps, sd_rho, nbr, fill_target, steps=4, warm=True, affinity=affinity)
        ps = ps + share * (ps_new - ps)
        rho = rho + share * (rho_new - rho)
        return ((pd, ps, rho), (best_theta, best_cost), anchor), (cost, mad)

    (theta, best, track), hist = jax.lax.scan(body, (theta, best, track), None, length=n_iter)
    return theta, best, track, hist


@partial(jax.jit, static_argnames=("static", "n_iter"))
def _polish(data, static, index, fg, rows, theta, n_iter):
    """`n_iter` steps (a) at the final lobes: `pd` to the fixed point of its own
    interreflection, undamped where that lowers the image difference (the interreflected
    share of the light below 1), with `_block`'s backtracking where it does not (a cavity
    of high albedo). Returns `theta` at the lowest image difference met."""
    _, ps, rho = theta

    def body(carry, _):
        pd, anchor = carry
        d, q = _parts(data, static, index, fg, pd, ps, rho)
        cost, _ = _image_difference(pd, ps, rho, rows, d, q)
        anchor, (pd_from, (d, q)) = _line_search(anchor, pd, (d, q), cost, 1.0)
        return (pd_from + anchor[3] * (_step_a(pd_from, ps, rho, rows, d, q)[0] - pd_from), anchor), None

    start = _track(theta[0], 1.0, rows["y"].shape, rows["y"].dtype)
    (pd, (best, _, cost, _)), _ = jax.lax.scan(body, (theta[0], start), None, length=n_iter)
    d, q = _parts(data, static, index, fg, pd, ps, rho)
    last, _ = _image_difference(pd, ps, rho, rows, d, q)
    return jnp.where(last < cost, pd, best), ps, rho


@partial(jax.jit, static_argnames=("static",))
def _final(data, static, index, fg, rows, theta):
    """Photon map at `theta`: image difference, step (a) and step (b) statistics."""
    pd, ps, rho = theta
    d, q = _parts(data, static, index, fg, pd, ps, rho)
    cost, mad = _image_difference(pd, ps, rho, rows, d, q)
    pd_new, info_pd = _step_a(pd, ps, rho, rows, d, q)
    args = _spec_args(pd, rows, d, q)
    var_ps, var_rho, chi2 = _spec_information(ps, rho, args, pd, d, rows["joint"])
    return dict(cost=cost, mad=mad, pd=pd_new, info_pd=info_pd, var_ps=var_ps, var_rho=var_rho, chi2=chi2,
                d=d, q=q)


def _misfit(scan, replay, index, fg, rows, estimate, dtype):
    """Where the scan carries Ward ground truth (`true_pd`, `true_ps`, `true_alpha`): the
    image difference (Eq. 14, noise-weighted) at the estimate and at the truth through the
    same forward model (direct light, photon replay, final gather), and their ratio: near 1
    when the iterations reached what the data allow, above it at a wrong fixed point.
    None without truth."""
    if scan.true_pd is None or scan.true_ps is None or scan.true_alpha is None:
        return None

    def cost(pd, ps, alpha):
        theta = (jnp.asarray(pd, dtype), jnp.asarray(ps, dtype),
                 jnp.asarray(np.log(np.clip(alpha, *ALPHA_RANGE)), dtype))
        return float(_final(replay.data, replay.static, index, fg, rows, theta)["cost"])

    at_estimate, at_truth = cost(*estimate), cost(scan.true_pd, scan.true_ps, scan.true_alpha)
    ratio = at_estimate / at_truth if at_truth > 0 else None
    return {"estimate": at_estimate, "truth": at_truth, "ratio": ratio}


def _start(est: Estimate):
    """A valid Ward start/proposal from a Method I estimate."""
    pd = np.clip(est.pd, 0.0, 1.0)
    ps = np.clip(np.nan_to_num(est.ps), 0.0, PS_MAX)
    alpha = np.where(est.roughness > 0, est.roughness, 0.1)
    return pd, ps, np.clip(alpha, *ALPHA_RANGE)


def _fit_rows(scan, rows_np, paper=False):
    """Device arrays of the observations for the fits, and the quantisation step: those of
    `prepare_rows` plus `w2` noise weights squared, `a` step (a)'s samples (all where the
    point has lobe evidence or no `T_diff` sample, else its `T_diff` ones; with `paper` the
    `T_diff` ones wherever it has any), `b` step (b)'s (`T_spec`, `T_none`), `lobe` lobe
    evidence (a `T_spec` sample and two step (b) samples: only these points move their
    lobe; the others keep the start's until the final fill), `joint` (no `T_diff`
    sample), `n_b`."""
    use, classes = rows_np["use"], rows_np["classes"]
    has_diff = (use & (classes == T_DIFF)).any(1)
    b_mask = use & (classes != T_DIFF)
    q_step = quantisation_step(scan.radiance, use)
    w = np.asarray(_noise_weights(jnp.asarray(rows_np["y"]), jnp.asarray(use), q_step / np.sqrt(12.0)))
    rows = {k: jnp.asarray(rows_np[k]) for k in ("y", "e", "cos_i", "cos_o", "theta_r", "use")}
    lobe = ((use & (classes == T_SPEC)).sum(1) >= 1) & (b_mask.sum(1) >= 2)
    # pd from every sample where the point's own lobe is fitted from them (the lobe is taken
    # off; broad lobes light T_diff samples too); from the T_diff samples where the lobe is
    # borrowed (filled), so that a wrong borrowed lobe cannot leak into pd; the paper: T_diff.
    diffuse_only = has_diff if paper else has_diff & ~lobe
    a = np.where(diffuse_only[:, None], use & (classes == T_DIFF), use)
    rows.update(w2=jnp.asarray(w**2), a=jnp.asarray(a),
                b=jnp.asarray(b_mask), lobe=jnp.asarray(lobe), joint=jnp.asarray(~has_diff),
                n_b=jnp.asarray(b_mask.sum(1)))
    return rows, q_step


def estimate_photon(scan, options: PhotonOptions = PhotonOptions(), caster: RayCaster | None = None,
                    progress=None) -> Estimate:
    """Method III on a scan with radiance (see the module docstring).

    **Returns:** `Estimate` (model 'ward') with `meta['method'] == 'photon'`;
    `meta['image_difference']` per iteration (`cost` Eq. 14 noise-weighted,
    `mean_abs` [W/(sr m^2)]), `meta['best_iteration']`, re-traces, effective
    sample sizes and seconds per stage; `meta['misfit']` where the scan has Ward ground
    truth (`_misfit`). `progress(done, total)` is called after
    every block of iterations when given.
    """
    scan, top = checks.method_input(scan)  # top: called by the user, not by another method
    timings = {}
    t0 = time.perf_counter()
    caster = caster or RayCaster(scan.vertices, scan.faces)
    rows_np = prepare_rows(scan, options.thresholds, caster)
    timings["classify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    init = estimate_local(scan, options.local, caster, rows=rows_np)
    timings["local_start"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rows, q_step = _fit_rows(scan, rows_np, options.local.paper)
    use = rows_np["use"]
    joint, lobe = (np.asarray(rows[k]) for k in ("joint", "lobe"))
    lobe_rows = jnp.asarray(np.flatnonzero(lobe), jnp.int32)
    adjacency = vertex_adjacency(scan.faces, scan.n_points)
    nbr = jnp.asarray(nearest_candidates(scan.vertices, np.flatnonzero(lobe), options.fill_neighbours), jnp.int32) \
        if lobe.any() else jnp.zeros((scan.n_points, 1), jnp.int32)
    fill_target = 1.0 / options.fill_sd**2
    configs = light_configs(scan.light_pos, scan.n_points, options.light_bin)
    n_cfg = len(configs.positions)
    per_config = scan.light_pos.ndim == 3
    index = jnp.asarray(configs.index) if per_config else None
    photons = int(max(1000, round(options.photons * scan.n_lights / n_cfg)))
    timings["prepare"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pd0, ps0, alpha0 = _start(init)
    replay = PhotonReplay.build(caster, scan.vertices, scan.faces, scan.normals, configs.positions,
                                scan.intensities()[configs.light], config_cameras(scan, configs),
                                (pd0, ps0, alpha0), n_photons=photons, target_photons=options.target_photons,
                                seed=options.seed, first_bounce=options.gather_rays == 0)
    timings["trace"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    n_rays, fg = options.gather_rays, None
    while n_rays > 1 and n_rays * int(use.sum()) > options.gather_budget:
        n_rays //= 2
    if n_rays:
        fg = gather_rays(caster, scan.normals, scan.camera_positions(), scan.light_positions(), scan.intensities(),
                         (pd0, ps0, alpha0), use, n_rays, seed=options.seed)
    timings["final_gather"] = time.perf_counter() - t0
    dt = rows["y"].dtype
    theta = (jnp.asarray(pd0, dt), jnp.asarray(ps0, dt), jnp.asarray(np.log(alpha0), dt))
    best = (theta, jnp.asarray(np.inf, dt))
    track = _track(theta, options.damping, rows["y"].shape, dt)
    costs, mads, retraces, ess_log = [], [], [], []
    timings["iterations"] = 0.0
    done = 0
    while done < options.iterations:
        n_iter = min(options.check_every, options.iterations - done)
        t0 = time.perf_counter()
        affinity = _material_affinity(theta[0], nbr, options.fill_pd_scale)  # per block: pd moves slowly
        theta, best, track, (c, m) = _block(replay.data, replay.static, index, fg, rows, lobe_rows, nbr, theta, best,
                                            track, n_iter, options.solver, options.steps, options.damping,
                                            options.min_snr, options.min_fit_p, fill_target, affinity)
        costs += np.asarray(c).tolist()
        mads += np.asarray(m).tolist()
        done += n_iter
        timings["iterations"] += time.perf_counter() - t0
        if progress is not None:
            progress(done, options.iterations)
        if done < options.iterations:
            ess = float(np.min(np.asarray(replay.ess(theta[0], theta[1], jnp.exp(theta[2])))))
            ess_log.append({"iteration": done, "ess": ess})
            if ess < options.retrace_ess:
                t0 = time.perf_counter()
                replay = replay.retrace(*(np.asarray(x, np.float64) for x in (theta[0], theta[1],
                                                                              jnp.exp(theta[2]))),
                                        seed=options.seed + 1 + len(retraces))
                retraces.append({"iteration": done, "ess": ess, "seconds": time.perf_counter() - t0})
                track = _track(track[0], options.damping, rows["y"].shape, dt)  # costs of the new photons
                timings["trace"] += retraces[-1]["seconds"]

    t0 = time.perf_counter()
    last = _final(replay.data, replay.static, index, fg, rows, theta)
    costs.append(float(last["cost"]))
    mads.append(float(last["mad"]))
    if float(last["cost"]) < float(best[1]):
        best = (theta, last["cost"])
    best_iteration = int(np.argmin(costs))
    fin = fin_best = _final(replay.data, replay.static, index, fg, rows, best[0])
    pd, ps, rho = (np.array(x, np.float64) for x in best[0])
    observed_any = use.any(1)
    alpha = np.exp(rho)
    method_warnings = []

    # Identifiability of the specular part, then the fill and pd with it.
    dof = np.asarray(_dof(rows["n_b"]), np.float64)
    sd_ps, sd_rho = (np.asarray(v, np.float64) for v in _lobe_sd(fin["var_ps"], fin["var_rho"], fin["chi2"], rows))
    identifiable = np.asarray(_identifiable(jnp.asarray(ps), fin["var_ps"], fin["var_rho"], fin["chi2"], rows,
                                            options.min_snr, options.min_fit_p))
    status = np.full(scan.n_points, MEASURED, np.int8)
    known = identifiable
    if known.any():
        nbr_f = jnp.asarray(nearest_candidates(scan.vertices, np.flatnonzero(known), options.fill_neighbours))
        ps, rho = (np.array(x, np.float64) for x in _fill_lobes(
            jnp.asarray(ps), jnp.asarray(rho), jnp.asarray(known), jnp.asarray(sd_ps), jnp.asarray(sd_rho),
            nbr_f, fill_target, affinity=_material_affinity(jnp.asarray(pd), nbr_f, options.fill_pd_scale)))
        alpha = np.exp(rho)
        in_window = window_reach(adjacency, options.window) @ known.astype(np.float64) > 0
        status[~known] = np.where(in_window[~known], INTERPOLATED, UNRESOLVED)
        theta_f = _polish(replay.data, replay.static, index, fg, rows,
                          tuple(jnp.asarray(x, dt) for x in (pd, ps, rho)), options.polish)
        fin = _final(replay.data, replay.static, index, fg, rows, theta_f)
        pd = np.array(theta_f[0], np.float64)
        if not float(fin["cost"]) <= float(fin_best["cost"]):
            # The filled lobes explain the images worse than the best iterate did: the measured
            # points' lobes do not carry over to the others. Keep the best iterate, whose other
            # points hold Method I's lobes (step (b) moves only points with lobe evidence).
            method_warnings.append(
                f"Method III's lobe fill raised the image difference from {float(fin_best['cost']):.4g} to "
                f"{float(fin['cost']):.4g}: kept the best iteration's values, the unmeasured lobes Method I's")
            logger.warning(method_warnings[-1])
            fin = fin_best
            pd, ps, alpha = (np.array(x, np.float64) for x in best[0])
            alpha = np.exp(alpha)
    else:  # no specular reflection measured anywhere: none reported, roughness undefined (0)
        ps, alpha = np.zeros_like(ps), np.zeros_like(alpha)
        status[:] = UNRESOLVED
    scale_a = np.maximum(1.0, np.asarray(fin["chi2"]) / dof)[:, None]
    info = np.asarray(fin["info_pd"], np.float64)
    std_pd = np.where(info > 0, np.sqrt(scale_a / np.where(info > 0, info, 1.0)), np.inf)
    std_ps = np.where(known, sd_ps, np.inf)
    std_alpha = np.where(known, alpha * np.where(known, sd_rho, 0.0), np.inf)
    # pd, as Method I's, shares evidence with its material-mates (the start's materials).
    prior_meta = {}
    if init.material is not None:
        _pd_with_prior(scan, init.material, observed_any, dark_channels(rows_np), pd, std_pd, options.local,
                       prior_meta)
    # Unobserved points keep the pd the images were explained with (their start's, filled by
    # Method I): their light reaches the observed points, and in a cavity of high albedo a
    # window fill from the iterations' per-point pd would change the images it returns.
    fill_unobserved_pd(pd, std_pd, status, observed_any, adjacency, options.window, keep_values=True)
    timings["fill"] = time.perf_counter() - t0
    finite_outputs((pd, ps, alpha), (std_pd, std_ps, std_alpha))
    misfit = _misfit(scan, replay, index, fg, rows, (pd, ps, alpha), dt)
    meta = {
        "method": "photon", "model": "ward",
        "options": {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v) for k, v in asdict(options).items()},
        "seconds": timings,
        "image_difference": {"cost": costs, "mean_abs": mads},
        "best_iteration": best_iteration,
        "retraces": retraces, "ess": ess_log, "method_warnings": method_warnings,
        "photons_per_configuration": photons, "light_configurations": n_cfg,
        "stored_photons": int(replay.n_photons),
        "gather_rays_per_observation": n_rays, "gather_entries": 0 if fg is None else int(fg.row.shape[0]),
        "quantisation_step": q_step,
        "points_with_observations": int(observed_any.sum()),
        "points_with_diffuse_only_sample": int((~joint).sum()),
        "start": {"coverage": float(np.mean(init.status == MEASURED))},
        **prior_meta,
        "observation_checks": scan.meta["observation_checks"],
    }
    if misfit is not None:
        meta["misfit"] = misfit
    est = Estimate(pd, ps, alpha, status, std_pd, std_ps, std_alpha, identifiable, observed_any, "ward", meta)
    if top:
        checks.estimate_warnings(est, logger)
    return est
