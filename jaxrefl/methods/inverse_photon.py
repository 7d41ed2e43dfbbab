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

**Shared prior on the lobes** (`lobe_prior`, on by default, not under `local.paper`;
`_lobe_posterior`): a second candidate for the final lobes. At the kept iterate's
interreflected light every point's lobe is fitted jointly with its pd over all its samples
(pd profiled out, `_joint_row`: the alternation of steps (a) and (b) trades pd against the
lobe slowly along their common valley, and stalls); materials are clustered by colour
(`prior.fit_materials` on pd), each material's lobe is fitted to all its points' samples at
once (`prior.material_lobes`; a lobe at the edge of the roughness range does not count), where
the lobe varies within a material each point's neighbourhood lobe is fitted to its nearest
mates' samples (`prior.local_lobes`, the neighbourhood's size cross-validated, the spread
about it by the rows' evidence: `_local_spread`), and each point takes its posterior mode
under the empirical-Bayes prior (`prior.lobe_prior`;
`measured` or `pooled` by `prior.status_from_posterior`, its own fit where its samples
reject the prior). pd is taken to its fixed point under both candidates and the lobes with
the lower image difference are kept (`meta['lobe_stage']`) (measurements:
`benchmarks/RESULTS_rigs_gi.md`).

**pd prior** (Method I's `prior.diffuse_prior` over the kept materials): the polish is run
once more with each step (a) the posterior mode under it and the backtracking on the image
difference plus the prior's cost: pd's MAP through the interreflection. Applied to the
polished pd afterwards, the pulls (each within its point's noise) add up in a cavity's
interreflected light; and an image-difference test of the result rejects even the truth's
pd where the forward model's own error is common to a point's samples, which the
per-point pd absorbs (measurements: `benchmarks/RESULTS_notes.md`).

Per-point lights (a rotating scanner, `light_pos` `(N, M, 3)`) are binned into
light configurations as Method II (`radiosity.light_configs`, `light_bin`);
each configuration gets `photons * M / C` photons.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field, replace
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..geometry.raycast import RayCaster
from ..reflectance import brdf
from ..reflectance import prior as prior_mod
from ..reflectance.classify import T_DIFF, T_SPEC, Thresholds
from ..reflectance.fill import nearest_candidates, precise_huber, vertex_adjacency, window_reach
from ..result import Estimate
from ..scan import checks
from .final_gather import gather_parts, gather_rays, photons_per_configuration, rays_within_budget
from .interreflection import pd_sd_with_interreflection
from .lm import gauss_newton_1d
from .local import (
    _SPREADS,
    INTERPOLATED,
    MEASURED,
    POOLED,
    UNRESOLVED,
    LocalOptions,
    _features,
    _noise_scale,
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
#: Matrix products at full float32 precision (a GPU's default rounds their inputs to TF32).
_EXACT = jax.lax.Precision.HIGHEST
#: Most rows a material's spread about its neighbourhood lobes is chosen on (`_local_spread`).
_EVIDENCE_ROWS = 2000


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
    `interpolated` against `unresolved`; `lobe_prior` the shared prior's lobes as a second
    candidate for the final lobes (`_lobe_posterior`; not under `local.paper`); `refine`
    L-BFGS steps on the whole image difference over one pd and lobe per material after the
    iterations, kept where it explains the images better (`_refine`; 0: none);
    `local` Method I options of the start (Ward)."""

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
    lobe_prior: bool = True
    refine: int = 0
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
        if self.refine < 0:
            raise ValueError("refine must be >= 0")
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


def _step_a(pd, ps, rho, r, d, q, prior=None):
    """pd `(N, 3)` by least squares over the step (a) samples, and its information
    `sum w^2 (E + D)^2` `(N, 3)` (0 where the point has no sample). With `prior`
    `(mean, precision, fixed)` `(N, 3)` each: the posterior mode under a Gaussian prior of
    that precision (in the image difference's units; 0: none), the mean itself where `fixed`."""
    k = _lobe_rows(rho, r["cos_i"], r["cos_o"], r["theta_r"])
    e = r["e"][..., None]
    a = r["a"][..., None]
    x = (e + d) / jnp.pi
    s = r["y"] - ps[:, None, None] * (e * k[..., None] + q)
    num = jnp.sum(jnp.where(a, r["w2"] * x * s, 0.0), axis=1)
    den = jnp.sum(jnp.where(a, r["w2"] * x * x, 0.0), axis=1)
    if prior is not None:
        mean, precision, fixed = prior
        num, tot = num + precision * mean, den + precision
    else:
        tot = den
    ok = tot > 0
    new = jnp.where(ok, num / jnp.where(ok, tot, 1.0), pd)
    if prior is not None:
        new = jnp.where(fixed, mean, new)
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


def _lobe_sums(rho, ci, co, th, a_m, b_m, c_m, c_sq, c_qq):
    """`(ssg, sgg)` of one row at `ln alpha = rho` from its `_spec_coefficients`:
    `ssg = k.A + c_sq` (`sum w s g`) and `sgg = k^2.B + k.C + c_qq` (`sum w g^2`)."""
    k = brdf.ward_specular(1.0, rho, ci, co, th)
    return jnp.sum(k * a_m) + c_sq, jnp.sum(k * k * b_m + k * c_m) + c_qq


def _reduced_cost(b, a, c0, rho, inv_s2, l_ps, m_ps, l_rho, m_rho):
    """Posterior cost of one row and its `ps >= 0`, from its reduced sums at `ln alpha = rho`:
    the data's cost `c0 - 2 ps b + ps^2 a` (a difference of large numbers: its rounding
    error is ~1e-7 of the signal's chi^2 in float32, far below the noise's) over the row's
    residual scale `1 / inv_s2`, plus the Gaussian prior `l_ps (ps - m_ps)^2 +
    l_rho (rho - m_rho)^2` (precisions `l`; 0: no prior)."""
    den = inv_s2 * a + l_ps
    ok = den > 0
    ps = jnp.where(ok, jnp.maximum(inv_s2 * b + l_ps * m_ps, 0.0) / jnp.where(ok, den, 1.0), 0.0)
    fit = jnp.maximum(c0 - ps * (2.0 * b - ps * a), 0.0)
    return inv_s2 * fit + l_ps * (ps - m_ps) ** 2 + l_rho * (rho - m_rho) ** 2, ps


def _spec_row(rho, *coef):
    """Projected cost of one row at `ln alpha = rho` and its `ps >= 0`, from the row's
    `_spec_coefficients` (pd held; no prior)."""
    ssg, sgg = _lobe_sums(rho, *coef[:8])
    return _reduced_cost(ssg, sgg, coef[8], rho, 1.0, 0.0, 0.0, 0.0, 0.0)


def _joint_coefficients(rows, d, q):
    """Per-row sums of the joint fit of pd (per channel), ps and the lobe over every used
    sample, the interreflected `(D, Q)` `(N, M, 3)` held: with `x_c = (E + D_c) / pi` (pd's
    term) and `g_c = E k + Q_c` (the lobe's, `k` the unit lobe `(M,)`), the normal equations
    at a roughness are `s11_c = sum w x_c^2`, `b1_c = sum w x_c y_c`, `s12_c = k.P_c + R_c`,
    `s22 = k^2.B + k.C + c_qq`, `b2 = k.A + c_sq`. Returns `(cos_i, cos_o, theta_r, A, B, C,
    c_sq, c_qq, P, R, b1, 1/s11, c0)`, `c0 = sum w y^2 - sum_c b1_c^2 / s11_c` (pd profiled
    out; its bounds are left to the pd fit)."""
    use = r_use = rows["use"][..., None]
    w = jnp.where(r_use, rows["w2"], 0.0)
    y, e = jnp.where(use, rows["y"], 0.0), rows["e"]
    qv = jnp.where(use, q, 0.0)
    x = (e[..., None] + d) / jnp.pi
    s11 = jnp.sum(w * x * x, 1)
    b1 = jnp.sum(w * x * y, 1)
    inv11 = jnp.where(s11 > 0, 1.0 / jnp.where(s11 > 0, s11, 1.0), 0.0)
    p = w * e[..., None] * x
    r = jnp.sum(w * x * qv, 1)
    a_m = e * jnp.sum(w * y, -1)
    b_m = e * e * jnp.sum(w, -1)
    c_m = 2.0 * e * jnp.sum(w * qv, -1)
    c_sq, c_qq = jnp.sum(w * y * qv, (-2, -1)), jnp.sum(w * qv * qv, (-2, -1))
    c0 = jnp.sum(w * y * y, (-2, -1)) - jnp.sum(b1 * b1 * inv11, -1)
    return (rows["cos_i"], rows["cos_o"], rows["theta_r"], a_m, b_m, c_m, c_sq, c_qq, p, r, b1, inv11, c0)


def _joint_sums(rho, ci, co, th, a_m, b_m, c_m, c_sq, c_qq, p, r, b1, inv11):
    """`(b, a)` of one row at `ln alpha = rho` (`_joint_coefficients`), pd profiled out:
    `b = b2 - sum_c s12_c b1_c / s11_c`, `a = s22 - sum_c s12_c^2 / s11_c`."""
    k = brdf.ward_specular(1.0, rho, ci, co, th)
    s12 = jnp.matmul(k, p, precision=_EXACT) + r
    b = jnp.sum(k * a_m) + c_sq - jnp.sum(s12 * b1 * inv11)
    a = jnp.sum(k * k * b_m + k * c_m) + c_qq - jnp.sum(s12 * s12 * inv11)
    return b, a


def _joint_row(rho, *coef):
    """Posterior cost of one row at `ln alpha = rho`, pd profiled out, and its `ps`
    (`coef`: `_joint_coefficients` then the prior's `inv_s2, l_ps, m_ps, l_rho, m_rho`)."""
    b, a = _joint_sums(rho, *coef[:12])
    return _reduced_cost(b, a, coef[12], rho, *coef[13:])


def _joint_info(ps, rho, ci, co, th, a_m, b_m, c_m, c_sq, c_qq, p, r, b1, inv11):
    """One row's Gauss-Newton information of `(ps, rho)` at `(ps, rho)`, pd profiled out (unit
    noise): `(i_pp, i_pr, i_rr)`, and `(s12, d12)` `(3,)`, pd's cross terms with ps and rho."""
    k, dk = jax.jvp(lambda x: brdf.ward_specular(1.0, x, ci, co, th), (rho,), (jnp.ones_like(rho),))
    s12, d12 = jnp.matmul(k, p, precision=_EXACT) + r, ps * jnp.matmul(dk, p, precision=_EXACT)
    i_pp = jnp.sum(k * k * b_m + k * c_m) + c_qq - jnp.sum(s12 * s12 * inv11)
    i_pr = ps * jnp.sum(dk * (k * b_m + 0.5 * c_m)) - jnp.sum(s12 * d12 * inv11)
    i_rr = ps * ps * jnp.sum(dk * dk * b_m) - jnp.sum(d12 * d12 * inv11)
    return i_pp, i_pr, i_rr, s12, d12


def _joint_information(ps, rho, coef):
    """The joint fit's pd `(N, 3)` at `(ps, rho)` and the Gauss-Newton variances (unit noise)
    of pd `(N, 3)`, ps and rho `(N,)`: the inverse of the information matrix of
    `(pd_c, ps, rho)`, through the Schur complement over pd (inf where singular)."""

    def one(ps, rho, *c):
        i_pp, i_pr, i_rr, s12, d12 = _joint_info(ps, rho, *c[:12])
        inv11, b1 = c[11], c[10]
        det = i_pp * i_rr - i_pr**2
        ok = det > 1e-12 * jnp.maximum(i_pp * i_rr, 1e-300)
        inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), jnp.inf)
        v_pp, v_rr, v_pr = i_rr * inv_det, i_pp * inv_det, -i_pr * jnp.where(ok, inv_det, 0.0)
        # pd's block of the inverse: 1/s11 + (1/s11)^2 e^T S^-1 e, e_c = (s12_c, d12_c).
        spread = s12 * s12 * v_pp + 2.0 * s12 * d12 * v_pr + d12 * d12 * jnp.where(ok, v_rr, 0.0)
        var_pd = jnp.where(inv11 > 0, inv11 + inv11 * inv11 * spread, jnp.inf)
        pd = jnp.clip((b1 - ps * s12) * inv11, 0.0, 1.0)
        return pd, var_pd, v_pp, v_rr

    return jax.vmap(one)(ps, rho, *coef)


@jax.jit
def _posterior_logdet(ps, rho, coef, inv_s2, l_ps, l_rho):
    """`(N,)` ln det of each row's posterior precision of `(ps, rho)` (its samples' information
    over its residual scale `1 / inv_s2`, plus the prior's precisions): the Laplace
    approximation's volume term of the row's evidence."""
    i_pp, i_pr, i_rr, _, _ = jax.vmap(_joint_info)(ps, rho, *coef[:12])
    det = (inv_s2 * i_pp + l_ps) * (inv_s2 * i_rr + l_rho) - (inv_s2 * i_pr) ** 2
    return jnp.log(jnp.maximum(det, 1e-300))


@jax.jit
def _row_sums(rho, coef):
    """`(G, 3, n)`: each row's `(c0, a, b)` (`_joint_sums`, pd profiled out) at ln roughness
    `rho` `(G, n)` (`prior.local_lobes`' `row_sums`)."""

    def one(rr):
        b, a = jax.vmap(_joint_sums)(rr, *coef[:12])
        return jnp.stack([coef[12], a, b])

    return jax.lax.map(one, rho)


def _rows_minimum(row, rho0, coef, steps, starts=()):
    """`(ps, rho)` `(N,)` minimising `row(rho, *coef) -> (cost, ps)` per row (`coef` a tuple
    of per-row arrays): the best of `rho0`, the `starts` and a 16-value grid over
    `ln ALPHA_RANGE`, then safeguarded Newton steps (the derivatives by forward mode: one
    variable, so a second-order `jvp` is the cheapest way to both)."""
    lo, hi = np.log(ALPHA_RANGE[0]), np.log(ALPHA_RANGE[1])
    cost_rows = jax.vmap(lambda r, *c: row(r, *c)[0])
    grid = jnp.linspace(lo, hi, _GRID, dtype=rho0.dtype)
    costs = jax.vmap(lambda g: cost_rows(jnp.full_like(rho0, g), *coef))(grid)  # (G, N)
    start, best = grid[jnp.argmin(costs, axis=0)], jnp.min(costs, axis=0)
    for cand in (*starts, rho0):  # rho0 last: it wins ties
        c = cost_rows(cand, *coef)
        start, best = jnp.where(c <= best, cand, start), jnp.minimum(c, best)

    def derivatives(r, *c):
        first = lambda x: jax.jvp(lambda y: row(y, *c)[0], (x,), (jnp.ones_like(x),))  # noqa: E731
        (cost, g), (_, h) = jax.jvp(first, (r,), (jnp.ones_like(r),))
        return cost, 0.5 * g, 0.5 * h

    rho, _ = gauss_newton_1d(lambda r: jax.vmap(derivatives)(r, *coef), start, steps, lo, hi, radius=0.5)
    _, ps = jax.vmap(row)(rho, *coef)
    return ps, rho


def _step_b_lm(rho0, args, steps):
    """`(ps, rho)` `(N,)` minimising the projected cost (`_rows_minimum` from `rho0`)."""
    return _rows_minimum(_spec_row, rho0, _spec_coefficients(args), steps)


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


@partial(jax.jit, static_argnames=("steps", "warm"))
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


#: Photon groups the photon map's Monte Carlo variance is estimated from (`PhotonReplay.indirect_variance`).
_MAP_BATCHES = 16

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


@partial(jax.jit, static_argnames=("static", "steps", "k"))
def _refine(data, static, index, fg, rows, theta, free, labels, k, steps):
    """`steps` L-BFGS steps on the image difference (Eq. 14) as a function of one pd `(3,)` and
    one lobe `(ps, ln alpha)` per material (`labels` `(N,)` in `[0, k)`), the interreflected
    light `(D, Q)` recomputed from them at each evaluation (photon replay and final gather,
    differentiated through), from each material's median over the points `free` `(N,)` (the
    observed ones; only they move). Steps (a) and (b) hold `(D, Q)` while a point moves: their
    fixed point is one where no point can lower the cost alone, which on a glossy fold lit
    from both sides can lie far from the joint minimum (a broad lobe and a dark pd everywhere
    light each other as the images demand). A few parameters per material, not per point:
    with a pd or a lobe per point the whole-cost minimum follows the photon map's and the
    gather's Monte Carlo noise; the caller keeps the result only where it explains the images
    better than the iterations did, and the per-point stages that follow (lobe fill or prior,
    pd polish) start from it. pd stays in (0, 1), ps in (0, PS_MAX], alpha in `ALPHA_RANGE`.
    Returns `(theta, its cost)`."""
    lo, hi = np.log(ALPHA_RANGE[0]), np.log(ALPHA_RANGE[1])
    pd0, ps0, rho0 = theta
    eps = 1e-4
    members = jax.nn.one_hot(labels, k, dtype=rho0.dtype) * free[:, None]  # (N, K)

    def material_median(x):
        return jax.vmap(lambda m: jnp.nanmedian(jnp.where(m > 0, x, jnp.nan)))(members.T)

    pd_m = jnp.clip(jnp.nan_to_num(jnp.stack([material_median(pd0[:, c]) for c in range(3)], 1), nan=0.5),
                    eps, 1.0 - eps)
    x0 = (jnp.log(pd_m / (1.0 - pd_m)),
          jnp.nan_to_num(jnp.log(jnp.clip(material_median(ps0), eps, PS_MAX)), nan=np.log(eps)),
          jnp.nan_to_num(material_median(rho0), nan=float(np.log(0.1))))

    def unpack(x):
        pd = jnp.where(free[:, None], jax.nn.sigmoid(x[0])[labels], pd0)
        ps = jnp.where(free, jnp.minimum(jnp.exp(x[1]), PS_MAX)[labels], ps0)
        rho = jnp.where(free, jnp.clip(x[2], lo, hi)[labels], rho0)
        return pd, ps, rho

    def cost(x, _):
        pd, ps, rho = unpack(x)
        d, q = _parts(data, static, index, fg, pd, ps, rho)
        return _image_difference(pd, ps, rho, rows, d, q)[0]

    sol = optx.minimise(cost, optx.LBFGS(rtol=1e-7, atol=1e-7), x0, max_steps=steps, throw=False)
    return unpack(sol.value), cost(sol.value, None)


def _no_prior(pd):
    """`_step_a`'s prior that changes nothing: mean and precision 0, nothing fixed, shaped as `pd`."""
    zero = jnp.zeros_like(pd)
    return zero, zero, jnp.zeros(pd.shape, bool)


@partial(jax.jit, static_argnames=("static", "n_iter"))
def _polish(data, static, index, fg, rows, theta, n_iter, prior):
    """`n_iter` steps (a) at the final lobes: `pd` to the fixed point of its own
    interreflection, undamped where that lowers the image difference (the interreflected
    share of the light below 1), with `_block`'s backtracking where it does not (a cavity
    of high albedo). Returns `theta` at the lowest image difference met. With `prior`
    (`_step_a`'s) the steps take the posterior mode and the cost adds the prior's
    `sum precision (pd - mean)^2`: pd's MAP through the interreflection, where each point's
    pull to its material-mates also changes the light its neighbours receive. Without one,
    `_no_prior(pd)` (precision 0 adds exact zeros: the same steps, one compiled program)."""
    _, ps, rho = theta
    mean, precision, fixed = prior

    def objective(pd, d, q):
        cost, _ = _image_difference(pd, ps, rho, rows, d, q)
        return cost + jnp.sum(jnp.where(fixed, 0.0, precision * (pd - mean) ** 2))

    def body(carry, _):
        pd, anchor = carry
        d, q = _parts(data, static, index, fg, pd, ps, rho)
        anchor, (pd_from, (d, q)) = _line_search(anchor, pd, (d, q), objective(pd, d, q), 1.0)
        return (pd_from + anchor[3] * (_step_a(pd_from, ps, rho, rows, d, q, prior)[0] - pd_from), anchor), None

    start = _track(theta[0], 1.0, rows["y"].shape, rows["y"].dtype)
    (pd, (best, _, cost, _)), _ = jax.lax.scan(body, (theta[0], start), None, length=n_iter)
    d, q = _parts(data, static, index, fg, pd, ps, rho)
    return jnp.where(objective(pd, d, q) < cost, pd, best), ps, rho


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


def _image_cost(replay, index, fg, rows, pd, ps, alpha, dtype) -> float:
    """The image difference (Eq. 14, noise-weighted) at the Ward values `pd` `(N, 3)`, `ps`,
    `alpha` `(N,)` through the photon replay and final gather (`_final`)."""
    theta = (jnp.asarray(pd, dtype), jnp.asarray(ps, dtype), jnp.asarray(np.log(np.clip(alpha, *ALPHA_RANGE)), dtype))
    return float(_final(replay.data, replay.static, index, fg, rows, theta)["cost"])


def _misfit(scan, replay, index, fg, rows, estimate, dtype):
    """Where the scan carries Ward ground truth (`true_pd`, `true_ps`, `true_alpha`): the
    image difference (Eq. 14, noise-weighted) at the estimate and at the truth through the
    same forward model (direct light, photon replay, final gather), and their ratio: near 1
    when the iterations reached what the data allow, above it at a wrong fixed point.
    None without truth."""
    if scan.true_pd is None or scan.true_ps is None or scan.true_alpha is None:
        return None

    at_estimate = _image_cost(replay, index, fg, rows, *estimate, dtype)
    at_truth = _image_cost(replay, index, fg, rows, scan.true_pd, scan.true_ps, scan.true_alpha, dtype)
    ratio = at_estimate / at_truth if at_truth > 0 else None
    return {"estimate": at_estimate, "truth": at_truth, "ratio": ratio}


@partial(jax.jit, static_argnames=("steps",))
def _own_lobes(rows, d, q, rho0, steps):
    """Every row's own lobe through the interreflection model, `(D, Q)` held: pd, ps and
    alpha jointly over all its used samples (`_joint_row`, pd profiled out) from `rho0`: pd,
    ps, rho, their Gauss-Newton variances (`_joint_information`) and chi^2, and the row coefficients
    `coef` (`_joint_coefficients`) the prior's fits reuse."""
    coef = _joint_coefficients(rows, d, q)
    none = tuple(jnp.full_like(rho0, v) for v in (1.0, 0.0, 0.0, 0.0, 0.0))
    ps, rho = _rows_minimum(_joint_row, rho0, coef + none, steps)
    ps = jnp.minimum(ps, PS_MAX)
    pd, var_pd, var_ps, var_rho = _joint_information(ps, rho, coef)
    b, a = jax.vmap(_joint_sums)(rho, *coef[:12])
    return dict(pd=pd, var_pd=var_pd, ps=ps, rho=rho, var_ps=var_ps, var_rho=var_rho, chi2=jnp.maximum(coef[12] - ps * (2.0 * b - ps * a),
                                                                                  0.0), coef=coef)


@partial(jax.jit, static_argnames=("steps",))
def _map_lobes(coef, prior, rho0, steps):
    """Posterior modes `(ps, rho)` `(N,)` of every row's lobe under the Gaussian `prior`
    (`inv_s2`, `l_ps`, `m_ps`, `l_rho`, `m_rho` `(N,)`, `_joint_row`), from the best of
    `rho0`, the prior mean and the grid; and the row's own chi^2 there (the prior left out)."""
    terms = (prior["inv_s2"], prior["l_ps"], prior["m_ps"], prior["l_rho"], prior["m_rho"])
    ps, rho = _rows_minimum(_joint_row, rho0, coef + terms, steps, starts=(prior["m_rho"],))
    ps = jnp.minimum(ps, PS_MAX)
    b, a = jax.vmap(_joint_sums)(rho, *coef[:12])
    return ps, rho, jnp.maximum(coef[12] - ps * (2.0 * b - ps * a), 0.0)


@partial(jax.jit, static_argnames=("k",))
def _material_reduced(coef, rho, labels, weights, k):
    """`(G, 3, k)`: per ln roughness `rho` `(G, k)` and material, the `weights`-weighted sums
    over its rows of `(c0, a, b)` (`_joint_sums`: pd profiled out; `prior.material_lobes`)."""

    def one(rr):
        b, a = jax.vmap(_joint_sums)(rr[labels], *coef[:12])
        parts = jnp.stack([coef[12], a, b]) * weights[None]
        return jax.vmap(lambda x: jax.ops.segment_sum(x, labels, num_segments=k))(parts)

    return jax.lax.map(one, rho)


def _posterior(coef, inv_s2, m_ps, v_ps, m_rho, v_rho, start, steps, evidence=True):
    """Every row's posterior mode under a Gaussian prior (means `m_*`, variances `v_*` `(N,)`,
    all finite) from `start` `(N,)` (`_map_lobes`) and, with `evidence`, its log evidence in
    the Laplace approximation, `-(chi^2 / s2 + prior penalty + ln det prior covariance + ln det
    posterior precision) / 2`: a dict of `(N,)` arrays `ps`, `rho`, `chi2` (the row's own,
    prior left out) and `evidence`."""
    dt = coef[0].dtype
    terms = {key: jnp.asarray(val, dt) for key, val in (("inv_s2", inv_s2), ("l_ps", 1.0 / v_ps), ("m_ps", m_ps),
                                                        ("l_rho", 1.0 / v_rho), ("m_rho", m_rho))}
    ps, rho, chi2 = _map_lobes(coef, terms, jnp.asarray(start, dt), steps)
    post = {key: np.array(a, np.float64) for key, a in (("ps", ps), ("rho", rho), ("chi2", chi2))}
    if evidence:
        logdet = np.asarray(_posterior_logdet(ps, rho, coef, terms["inv_s2"], terms["l_ps"], terms["l_rho"]),
                            np.float64)
        penalty = (post["ps"] - m_ps) ** 2 / v_ps + (post["rho"] - m_rho) ** 2 / v_rho
        post["evidence"] = -0.5 * (inv_s2 * post["chi2"] + penalty + np.log(v_ps * v_rho) + logdet)
    return post


def _local_spread(coef, local, labels, k, inv_s2, rho0, rows, steps):
    """Spreads `(K, 2)` (ln ps, ln roughness) of the lobe about each point's neighbourhood lobe
    (`prior.local_lobes`) in a material whose lobe varies: those under which the own samples
    of the `rows` `(N,)` bool (observed, with an identifiable neighbourhood lobe; at most
    `_EVIDENCE_ROWS` of them) are most probable (`prior.spread_by_evidence` of `_posterior`'s
    evidence). 0 for the other materials (`local._local_spread`, through the interreflection
    model)."""
    idx = np.flatnonzero(rows)
    if not len(idx):
        return np.zeros((k, 2))
    if len(idx) > _EVIDENCE_ROWS:  # evenly spread rows: the evidence's sums need no more
        idx = idx[np.linspace(0, len(idx) - 1, _EVIDENCE_ROWS).astype(np.int64)]
    rows = np.zeros(len(labels), bool)
    rows[idx] = True
    # Padded (with the first row again, its evidence dropped) to a multiple of 500 rows: few
    # compiled shapes across scans.
    padded = np.pad(idx, (0, -len(idx) % 500), mode="edge")
    sub = tuple(c[padded] for c in coef)
    start = rho0[padded]

    def log_evidence(spread):
        m_ps, v_ps, m_rho, v_rho, _ = (a[padded] for a in prior_mod.local_prior(local, labels, spread))
        out = np.zeros(len(labels))
        out[idx] = _posterior(sub, inv_s2[padded], m_ps, v_ps, m_rho, v_rho, start, steps)["evidence"][:len(idx)]
        return out

    spread = prior_mod.spread_by_evidence(log_evidence, labels, k, rows, _SPREADS)
    return np.where(local.neighbours[:, None] > 0, spread, 0.0)


def _posterior_where(coef, prior, own, rho_own, inv_s2, observed_any, steps, evidence=True):
    """`_posterior` under `prior` (`prior.LobePrior`) on the observed rows where it is
    available (`avail`), from the prior's mean, or the own fit where the row pins its lobe;
    elsewhere the own fit, evidence 0."""
    avail = prior.available & observed_any
    one = np.ones(len(own))
    post = _posterior(coef, inv_s2, np.where(avail, prior.mean_ps, 0.0), np.where(avail, prior.var_ps, one),
                      np.where(avail, prior.mean_rho, 0.0), np.where(avail, prior.var_rho, one),
                      np.where(own | ~avail, rho_own, prior.mean_rho), steps, evidence)
    if evidence:
        post["evidence"] = np.where(avail, post["evidence"], 0.0)
    post["avail"] = avail
    return post


def _choose_prior(first, second, labels, k) -> np.ndarray:
    """`(K,)` bool: the materials whose rows' own samples are more probable under the `second`
    prior than under the `first` (each a `_posterior_where` result), by more than one standard
    error of the paired per-row differences (`prior._beats_by_one_se`), over the rows both
    priors cover."""
    both = first["avail"] & second["avail"]
    gain = second["evidence"] - first["evidence"]
    return np.array([bool((both & (labels == m)).any()) and prior_mod._beats_by_one_se(gain[both & (labels == m)])
                     for m in range(k)], bool)


def _select_prior(first, second, chosen, labels):
    """One `prior.LobePrior` of two: each material's from `second` where `chosen` `(K,)`, else
    from `first`."""
    pick = chosen[labels]
    return prior_mod.LobePrior(*(np.where(pick, getattr(second, f), getattr(first, f)) for f in
                                 ("mean_ps", "var_ps", "mean_rho", "var_rho", "available")),
                               np.where(chosen, second.spread_ps, first.spread_ps),
                               np.where(chosen, second.spread_rho, first.spread_rho),
                               *(np.where(pick, getattr(second, f), getattr(first, f)) for f in
                                 ("cover_var_ps", "cover_var_rho")))


def _lobe_posterior(scan, rows, theta, d, q, std_pd, observed_any, dark, peak, options):
    """The shared reflectance prior (`jaxrefl.reflectance.prior`) on Method III's lobes, at the
    kept iterate `theta` and its interreflected light `(D, Q)`: every point's own lobe through
    the interreflection model (`_own_lobes`); materials clustered by the colour of Method III's
    pd (Method I's, interreflection left in, splits one material by its distance from a concave
    part); each material's lobe fitted to all its points' samples at once
    (`prior.material_lobes`); each point's neighbourhood lobe where the lobe varies within a
    material (`prior.local_lobes`, `_local_spread`); the empirical-Bayes prior of every lobe
    (`prior.lobe_prior`);
    and every point's posterior mode (`_map_lobes`). Points whose own samples reject their
    prior keep their own fit (`prior.prior_conflict`).

    **Returns:** a dict of `(N,)` arrays `ps`, `rho`, `sd_ps`, `sd_rho` (posterior; inf where
    neither the point nor its prior pins the lobe), `own` (the point's own samples pin its
    lobe: lobe evidence, ps `min_snr` sd above 0, ln alpha known to +-1), `measured`,
    `pooled` (`prior.status_from_posterior`), `labels`; and a meta dict. `std_pd` `(N, 3)`, `dark` `(N, 3)` (`local.dark_channels`) and `peak`
    `(N,)` (each point's `T_spec` samples) as `local._features` and `prior.material_lobes`
    take them."""
    pd = theta[0]
    steps = options.steps
    own_fit = {k: (v if k == "coef" else np.asarray(v, np.float64))
               for k, v in _own_lobes(rows, d, q, theta[2], steps).items()}
    n_use = np.asarray(rows["use"]).sum(1)
    dof = np.maximum(3.0 * n_use - 5.0, 1.0)  # 3 channels per sample less pd (3), ps and alpha
    s2 = np.maximum(_noise_scale(np.where(observed_any, own_fit["chi2"], np.nan), np.where(observed_any, dof, 0)),
                    1.0)
    s2 = np.where(np.isfinite(s2), s2, 1.0)
    var_ps, var_rho = (np.where(np.isfinite(own_fit[k]) & (own_fit[k] > 0), own_fit[k] * s2, np.inf)
                       for k in ("var_ps", "var_rho"))
    ps_own, rho_own = own_fit["ps"], own_fit["rho"]
    # Its own samples pin a point's lobe: lobe evidence, ps above min_snr sd, ln alpha to +-1.
    own = np.asarray(rows["lobe"]) & observed_any & (ps_own > options.min_snr * np.sqrt(var_ps)) \
        & (np.sqrt(var_rho) < 1.0)
    local = options.local
    fit = {"pd": np.asarray(pd, np.float64), "std_pd": std_pd, "ps": ps_own, "std_ps": np.sqrt(var_ps),
           "roughness": np.exp(rho_own), "std_ln_roughness": np.sqrt(var_rho)}
    x, v = _features(fit, own, observed_any, dark)
    # Materials by colour alone: a lobe's own fit is loose wherever pd and the lobe trade off
    # (a flash beside the camera), and clusters that split on it take lobes of their own. One
    # full colour covariance per material: beside a fold the pd left too bright by light the
    # model misses is so in every channel, and diagonal clusters split one material on it.
    materials = prior_mod.fit_materials(x[:, :3], v[:, :3], scan.vertices, k_max=local.materials, covariance="full")
    labels, k = materials.labels, materials.k
    inv_s2 = np.where(observed_any, 1.0 / s2, 0.0)
    coef = own_fit["coef"]
    dt = rows["y"].dtype
    k_pad = -(-k // 8) * 8  # one compilation for every K up to 8

    def material_sums(rho, labels_, k_, weights):
        g = len(rho)  # the grid, its refinement, the optimum: padded to one compilation
        rho = np.pad(np.asarray(rho, np.float64), [(0, max(_GRID - g, 0)), (0, k_pad - k_)], mode="edge")
        out = _material_reduced(coef, jnp.asarray(rho, dt), jnp.asarray(labels_), jnp.asarray(weights, dt), k_pad)
        return np.asarray(out, np.float64)[:g, :, :k_]

    grid = np.log(np.geomspace(*ALPHA_RANGE, _GRID))
    lobes = prior_mod.material_lobes(material_sums, labels, k, inv_s2, grid,
                                     min_snr=options.min_snr, peak_samples=peak * observed_any)
    # A joint lobe at the edge of the roughness range searched is a bound, not a located minimum.
    step = grid[1] - grid[0]
    lobes = replace(lobes, identifiable=lobes.identifiable & (lobes.rho > grid[0] + step)
                    & (lobes.rho < grid[-1] - step))
    fitted = observed_any & np.isfinite(var_ps) & np.isfinite(var_rho)
    # Two priors: the smooth field of the points' own lobes, and (where the lobe varies within a
    # material) of each point's neighbourhood lobe, whose joint fit also holds the samples of
    # mates that show no highlight (own lobes are those broad enough to be seen, so their
    # field leans broad where the lobe is sharp). Each material takes the one under which its
    # rows' own samples are more probable (`_choose_prior`).
    local_fit = prior_mod.local_lobes(lambda rho, rows=None: _row_sums(jnp.asarray(rho, dt), coef if rows is None
                                      else tuple(c[rows] for c in coef)), labels, k, scan.vertices, inv_s2, grid,
                                      ps_bound=partial(brdf.ps_bound, "ward"), min_snr=options.min_snr,
                                      peak_samples=peak * observed_any, max_neighbours=4 * local.prior_neighbours)
    # Materials where enough points have an identifiable neighbourhood lobe (`prior.lobe_prior`).
    field_rows = prior_mod.local_prior(local_fit, labels, np.zeros((k, 2)))[4]
    varies = np.bincount(labels, weights=field_rows, minlength=k) >= prior_mod._MIN_SPREAD_POINTS
    prior = prior_mod.lobe_prior(ps_own, var_ps, rho_own, var_rho, own, labels, lobes, scan.vertices,
                                 neighbours=local.prior_neighbours, fitted=fitted)
    post = _posterior_where(coef, prior, own, rho_own, inv_s2, observed_any, steps, evidence=varies.any())
    field = np.zeros(k, bool)
    if varies.any():
        spread = _local_spread(coef, local_fit, labels, k, inv_s2, rho_own, field_rows & observed_any, steps)
        second = prior_mod.lobe_prior(ps_own, var_ps, rho_own, var_rho, own, labels, lobes, scan.vertices,
                                      neighbours=local.prior_neighbours, fitted=fitted, local=local_fit,
                                      spread=spread, materials=varies)
        # Every row, though only those of `varies` have this prior: one compiled shape.
        post_second = _posterior_where(coef, second, own, rho_own, inv_s2, observed_any, steps)
        field = varies & _choose_prior(post, post_second, labels, k)
        prior = _select_prior(prior, second, field, labels)
        pick = field[labels]
        for key in ("ps", "rho", "chi2"):
            post[key][pick] = post_second[key][pick]
    avail = prior.available & observed_any
    ps_map, rho_map, chi2_map = post["ps"], post["rho"], post["chi2"]
    measured, pooled = prior_mod.status_from_posterior(own, var_ps, var_rho, prior)
    conflict = prior_mod.prior_conflict(chi2_map, own_fit["chi2"], s2, avail)
    measured, pooled = (measured | (own & conflict)) & observed_any, pooled & ~conflict & observed_any
    # the uncertainty under the prior widened where the measured lobes around a point disagree
    # with it (`prior.cover_measured`); the estimate keeps the prior's mode
    post_ps = np.where(avail, 1.0 / (1.0 / var_ps + 1.0 / np.where(avail, prior.cover_var_ps, 1.0)), var_ps)
    post_rho = np.where(avail, 1.0 / (1.0 / var_rho + 1.0 / np.where(avail, prior.cover_var_rho, 1.0)), var_rho)
    mine = conflict | ~avail
    ps = np.where(mine, ps_own, ps_map)
    rho = np.where(mine, rho_own, rho_map)
    pinned = measured | pooled
    sd_ps = np.where(pinned, np.sqrt(np.where(mine, var_ps, post_ps)), np.inf)
    sd_rho = np.where(pinned, np.sqrt(np.where(mine, var_rho, post_rho)), np.inf)
    meta = {"materials": k, "bic": {str(key): float(b) for key, b in materials.bic.items()},
            "material_lobes": prior_mod.lobes_meta(lobes, prior.spread_ps, prior.spread_rho,
                                                  partial(brdf.ps_bound, "ward")),
            "points_pooled": int(pooled.sum()), "points_in_conflict_with_prior": int(conflict.sum()),
            "points_with_widened_prior": int((prior.widened & observed_any).sum())}
    for m, entry in enumerate(meta["material_lobes"]):
        entry["neighbours"] = int(local_fit.neighbours[m])  # 0: the whole material
        entry["prior_field"] = "neighbourhood lobes" if field[m] else "own lobes"
    return {"ps": ps, "rho": rho, "sd_ps": sd_ps, "sd_rho": sd_rho, "own": own, "measured": measured,
            "pooled": pooled, "labels": labels}, meta


def _pd_scale(fin, dof):
    """`(N, 1)` variance scale of step (a)'s pd at `_final`'s `fin`: the reduced chi^2 of the
    lobe fit where above 1."""
    return np.maximum(1.0, np.asarray(fin["chi2"]) / dof)[:, None]


def _pd_noise_var(fin):
    """`(N, 3)` variance of step (a)'s pd at `_final`'s `fin` from the samples' weights alone:
    the inverse of its information (inf: no sample)."""
    info = np.asarray(fin["info_pd"], np.float64)
    return np.where(info > 0, 1.0 / np.where(info > 0, info, 1.0), np.inf)


def _pd_std(fin, dof):
    """`(N, 3)` standard deviation of step (a)'s pd at `_final`'s `fin`: `_pd_noise_var` scaled
    by `_pd_scale` (inf: no sample)."""
    return np.sqrt(_pd_scale(fin, dof) * _pd_noise_var(fin))


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
    `meta['image_difference']` per iteration (`cost` Eq. 14 noise-weighted through the photons
    of that iteration, `mean_abs` [W/(sr m^2)]; `best` the best iterate's cost through the last
    photons), `meta['best_iteration']`, `meta['refine']` (with `options.refine`: the image
    difference before and after, and whether it was kept), re-traces, effective
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
    # The start's unresolved lobes are the nearest measured ones (`LocalOptions.material_fill`):
    # a direct-light joint fit of a material without a measured lobe may be interreflected light.
    init = estimate_local(scan, replace(options.local, material_fill=False, interreflection_rays=0), caster,
                          rows=rows_np)
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
    photons = photons_per_configuration(options.photons, scan.n_lights, n_cfg)
    timings["prepare"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pd0, ps0, alpha0 = _start(init)
    replay = PhotonReplay.build(caster, scan.vertices, scan.faces, scan.normals, configs.positions,
                                scan.intensities()[configs.light], config_cameras(scan, configs),
                                (pd0, ps0, alpha0), n_photons=photons, target_photons=options.target_photons,
                                seed=options.seed, first_bounce=options.gather_rays == 0)
    timings["trace"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fg = None
    n_rays = rays_within_budget(options.gather_rays, use.sum(), options.gather_budget) if options.gather_rays else 0
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
    best_iteration, best_cost = 0, np.inf  # `best` on the host, in the current photons' costs
    while done < options.iterations:
        n_iter = min(options.check_every, options.iterations - done)
        t0 = time.perf_counter()
        affinity = _material_affinity(theta[0], nbr, options.fill_pd_scale)  # per block: pd moves slowly
        theta, best, track, (c, m) = _block(replay.data, replay.static, index, fg, rows, lobe_rows, nbr, theta, best,
                                            track, n_iter, options.solver, options.steps, options.damping,
                                            options.min_snr, options.min_fit_p, fill_target, affinity)
        for i, cost in enumerate(np.asarray(c).tolist()):
            if cost < best_cost:
                best_iteration, best_cost = done + i, cost
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
                # The best so far, in the new photons' costs too: image differences through two
                # photon sets differ by their Monte Carlo noise (tens of per cent in a cavity), so
                # an old cost would outbid every later iterate or none.
                best_cost = float(_final(replay.data, replay.static, index, fg, rows, best[0])["cost"])
                best = (best[0], jnp.asarray(best_cost, dt))
                timings["trace"] += retraces[-1]["seconds"]

    refined = None
    if options.refine:
        t0 = time.perf_counter()
        labels = np.zeros(scan.n_points, np.int64) if init.material is None else np.asarray(init.material)
        before = best[1]  # the best iterate's cost through these photons (re-costed at every re-trace)
        theta_r, after = _refine(replay.data, replay.static, index, fg, rows, best[0], jnp.asarray(use.any(1)),
                                 jnp.asarray(labels), int(labels.max()) + 1, options.refine)
        refined = {"steps": options.refine, "image_difference_before": float(before),
                   "image_difference_after": float(after), "kept": bool(after < before)}
        if refined["kept"]:  # else the iterations' last and best stand as they are
            theta = theta_r
        timings["refine"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    last = _final(replay.data, replay.static, index, fg, rows, theta)
    costs.append(float(last["cost"]))
    mads.append(float(last["mad"]))
    if float(last["cost"]) < float(best[1]):
        best, best_iteration = (theta, last["cost"]), len(costs) - 1
    # The photon map's Monte Carlo error joins each sample's noise from here on: a sample lit by
    # one stray photon of a sharp lobe's path (tens of times its noise) would otherwise pull a
    # whole material's lobe in the fits below.
    var_map = _to_obs(replay.indirect_variance(best[0][0], best[0][1], jnp.exp(best[0][2]), _MAP_BATCHES), index)
    over = np.asarray(var_map * rows["w2"], np.float64).mean(-1) > 1.0  # the map's error above the noise
    map_dominated = float(over[use].mean()) if use.any() else 0.0
    noise_rows, rows = rows, dict(rows, w2=rows["w2"] / (1.0 + rows["w2"] * var_map.astype(dt)))
    fin = fin_best = _final(replay.data, replay.static, index, fg, rows, best[0])
    pd, ps, rho = (np.array(x, np.float64) for x in best[0])
    observed_any = use.any(1)
    alpha = np.exp(rho)
    method_warnings = []
    at_start = False  # the values kept are the start's (Method I's estimate)

    # The lobes: (1) the iterations' own lobes, the unmeasured ones filled from them; (2) with
    # the shared prior, every lobe's posterior through the interreflection model. pd is then
    # taken to its fixed point under each; the one that explains the images better is kept.
    dof = np.asarray(_dof(rows["n_b"]), np.float64)
    candidates = []
    dark = dark_channels(rows_np)

    def finish(name, ps_c, rho_c, sd_ps_c, sd_rho_c, known, keep_known, own, extra):
        if not known.any():
            return
        nbr_f = jnp.asarray(nearest_candidates(scan.vertices, np.flatnonzero(known), options.fill_neighbours))
        filled = (np.array(x, np.float64) for x in _fill_lobes(
            jnp.asarray(ps_c), jnp.asarray(rho_c), jnp.asarray(known), jnp.asarray(sd_ps_c), jnp.asarray(sd_rho_c),
            nbr_f, fill_target, affinity=_material_affinity(jnp.asarray(pd), nbr_f, options.fill_pd_scale)))
        ps_c, rho_c = ((np.where(known, x, f) for x, f in zip((ps_c, rho_c), filled)) if keep_known else filled)
        theta_c = tuple(jnp.asarray(x, dt) for x in (pd, ps_c, rho_c))
        theta_c = _polish(replay.data, replay.static, index, fg, rows, theta_c, options.polish,
                          _no_prior(theta_c[0]))
        fin_c = _final(replay.data, replay.static, index, fg, rows, theta_c)
        candidates.append(dict(name=name, pd=np.array(theta_c[0], np.float64), ps=ps_c, rho=rho_c, sd_ps=sd_ps_c,
                               sd_rho=sd_rho_c, known=known, own=own, fin=fin_c, cost=float(fin_c["cost"]), **extra))

    if options.lobe_prior and not options.local.paper:
        peak = (use & (rows_np["classes"] == T_SPEC)).sum(1)
        post, post_meta = _lobe_posterior(scan, rows, best[0], fin["d"], fin["q"], _pd_std(fin, dof), observed_any,
                                          dark, peak, options)
        finish("prior", post["ps"], post["rho"], post["sd_ps"], post["sd_rho"], post["measured"] | post["pooled"],
               True, post["own"], dict(pooled=post["pooled"], labels=post["labels"], meta=post_meta))
    sd_ps_f, sd_rho_f = (np.asarray(v, np.float64) for v in _lobe_sd(fin["var_ps"], fin["var_rho"], fin["chi2"], rows))
    own_f = np.asarray(_identifiable(jnp.asarray(ps), fin["var_ps"], fin["var_rho"], fin["chi2"], rows,
                                     options.min_snr, options.min_fit_p))
    finish("fill", ps, rho, sd_ps_f, sd_rho_f, own_f, False, own_f, {})
    status = np.full(scan.n_points, MEASURED, np.int8)
    labels, prior_meta, lobe_costs = init.material, {}, {c["name"]: c["cost"] for c in candidates}
    if candidates:
        pick = min(candidates, key=lambda c: c["cost"])  # the prior's first: it wins a tie
        pd, ps, rho, known, identifiable = (pick[k] for k in ("pd", "ps", "rho", "known", "own"))
        sd_ps, sd_rho, fin = pick["sd_ps"], pick["sd_rho"], pick["fin"]
        alpha = np.exp(rho)
        if pick["name"] == "prior":
            labels, prior_meta = pick["labels"], pick["meta"]
            status[pick["pooled"]] = POOLED
        in_window = window_reach(adjacency, options.window) @ known.astype(np.float64) > 0
        status[~known] = np.where(in_window[~known], INTERPOLATED, UNRESOLVED)
        if not float(fin["cost"]) <= float(fin_best["cost"]):
            # The filled lobes explain the images worse than the best iterate did: the measured
            # points' lobes do not carry over to the others. Keep the best iterate, whose other
            # points hold Method I's lobes (step (b) moves only points with lobe evidence).
            at_start = best_iteration == 0
            if not at_start:
                method_warnings.append(
                    f"Method III's lobe fill raised the image difference from {float(fin_best['cost']):.4g} to "
                    f"{float(fin['cost']):.4g}: kept the best iteration's values, the unmeasured lobes Method I's")
                logger.warning(method_warnings[-1])
            fin = fin_best
            pd, ps, alpha = (np.array(x, np.float64) for x in best[0])
            alpha = np.exp(alpha)
    else:  # no specular reflection measured anywhere: none reported, roughness undefined (0)
        identifiable = known = np.zeros(scan.n_points, bool)
        sd_ps = sd_rho = np.full(scan.n_points, np.inf)
        ps, alpha = np.zeros_like(ps), np.zeros_like(alpha)
        status[:] = UNRESOLVED
    if at_start:
        # No iteration explained the images better than the start (as on a convex object,
        # where the interreflection adds nothing the data see): Method I's estimate is the
        # answer, with its own uncertainties, statuses and materials (pd already shares its
        # material-mates').
        method_warnings.append(
            "no Method III iteration explained the images better than its start: returned Method I's "
            f"estimate (image difference {float(fin_best['cost']):.4g})")
        logger.warning(method_warnings[-1])
        pd, ps, alpha, status = init.pd.copy(), init.ps.copy(), init.roughness.copy(), init.status.copy()
        std_pd, std_ps, std_alpha = init.std_pd.copy(), init.std_ps.copy(), init.std_roughness.copy()
        identifiable, labels, prior_meta = init.specular_identifiable.copy(), init.material, {}
        if options.local.interreflection_rays:  # as Method I reports it: the light it leaves in pd
            std_pd, prior_meta["interreflection"], warning = pd_sd_with_interreflection(
                scan, init, rows_np, options.local.interreflection_rays, caster)
            if warning:
                method_warnings.append(warning)
                logger.warning(warning)
    else:
        std_pd = _pd_std(fin, dof)
        std_ps = np.where(known, sd_ps, np.inf)
        std_alpha = np.where(known, alpha * np.where(known, sd_rho, 0.0), np.inf)
        # pd, as Method I's, shares evidence with its material-mates (the prior's materials). Here
        # each point's pd also lights the others: in a cavity of high albedo the prior's pulls,
        # each within its point's noise, add up in the interreflected light. So the prior enters
        # step (a) itself (pd's MAP through the interreflection, `_polish`), not its result.
        if labels is not None:
            before = float(fin["cost"])
            # Its conflict test with the samples' own variance (noise and the photon map's error), not
            # the misfit-scaled one: a point the model fits badly has a wide scaled std, and would be
            # handed to its material's pd however far its data are.
            diffuse = _pd_with_prior(scan, labels, observed_any, dark, pd, std_pd, options.local, prior_meta,
                                     var_test=_pd_noise_var(fin))
            on = np.broadcast_to((observed_any & diffuse.available)[:, None], pd.shape)  # var finite there
            scale = _pd_scale(fin, dof)
            fixed = on & dark
            precision = np.where(on & ~fixed, scale / np.where(on, diffuse.var, 1.0), 0.0)
            prior = tuple(jnp.asarray(x) for x in (np.where(on, diffuse.mean, 0.0).astype(dt), precision.astype(dt),
                                                    fixed))
            theta_p = _polish(replay.data, replay.static, index, fg, rows,
                              tuple(jnp.asarray(x, dt) for x in (pd, ps, np.log(np.clip(alpha, *ALPHA_RANGE)))),
                              options.polish, prior)
            fin_p = _final(replay.data, replay.static, index, fg, rows, theta_p)
            pd = np.array(theta_p[0], np.float64)
            info = np.asarray(fin_p["info_pd"], np.float64) / scale
            std_pd = np.where(fixed, np.sqrt(np.where(on, diffuse.var, 1.0)),
                              np.where(on, 1.0 / np.sqrt(info + 1.0 / np.where(on, diffuse.var, 1.0)), std_pd))
            prior_meta["pd_prior_image_difference"] = {"without": before, "with": float(fin_p["cost"])}
        # Unobserved points keep the pd the images were explained with (their start's, filled by
        # Method I): their light reaches the observed points, and in a cavity of high albedo a
        # window fill from the iterations' per-point pd would change the images it returns.
        fill_unobserved_pd(pd, std_pd, status, observed_any, adjacency, options.window, keep_values=True)
    timings["fill"] = time.perf_counter() - t0
    finite_outputs((pd, ps, alpha), (std_pd, std_ps, std_alpha))
    misfit = _misfit(scan, replay, index, fg, noise_rows, (pd, ps, alpha), dt)  # Eq. 14 as documented
    meta = {
        "method": "photon", "model": "ward",
        "options": {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v) for k, v in asdict(options).items()},
        "seconds": timings,
        "image_difference": {"cost": costs, "mean_abs": mads, "best": float(fin_best["cost"])},
        "best_iteration": best_iteration, "refine": refined,
        "retraces": retraces, "ess": ess_log, "method_warnings": method_warnings,
        "photons_per_configuration": photons, "light_configurations": n_cfg,
        "stored_photons": int(replay.n_photons),
        "gather_rays_per_observation": n_rays,
        "photon_map_variance_dominated": map_dominated, "gather_entries": 0 if fg is None else int(fg.row.shape[0]),
        "quantisation_step": q_step,
        "lobe_stage": {"image_difference": lobe_costs, "kept": pick["name"] if candidates else None},
        "points_with_observations": int(observed_any.sum()),
        "points_with_diffuse_only_sample": int((~joint).sum()),
        "start": {"coverage": float(np.mean(init.status == MEASURED))},
        **prior_meta,
        "observation_checks": scan.meta["observation_checks"],
    }
    if misfit is not None:
        meta["misfit"] = misfit
    est = Estimate(pd, ps, alpha, status, std_pd, std_ps, std_alpha, identifiable, observed_any, "ward", meta,
                   labels)
    if top:
        checks.estimate_warnings(est, logger)
    return est
