"""The shared reflectance prior: materials, their lobes, and how far each point leans on them.

A point's own samples may pin its specular lobe (ps, ln roughness `rho`), or see it in one
light, off-specular, or not at all. The object shares reflectance where it shares a
material, so the lobe is modelled in levels, every constant of which comes from the data:

1. **Materials** (`fit_materials`): a diagonal Gaussian mixture over per-point features
   (pd per channel; ln ps and `rho` where the point's own lobe is measured, each with the
   point's own variance added, so a point without a lobe is clustered by its colour alone).
   K = 1 .. `k_max`, chosen by the Bayesian information criterion.
2. **A material's lobe** (`material_lobes`): the joint maximum-likelihood fit of one
   (ps, `rho`) to all the material's samples at once, every point's pd profiled out. Points
   that each see one half-angle together see many.
3. **Within a material the lobe may vary** (`local_lobes`): each point's neighbourhood lobe
   is the joint fit of one lobe to the samples of its `n` nearest material-mates, itself left
   out, `n` (1, 2, 4, ... or the whole material) chosen per material by leave-one-out
   cross-validation of every row's own samples (the whole material unless a neighbourhood
   predicts better by more than a standard error). Where a neighbourhood's lobe is
   identifiable it is the point's prior, as wide as its own variance plus the field's spread
   about it, the spread (in ln ps and ln roughness) that maximises the marginal likelihood of
   the points' own samples (`spread_by_evidence`, type II maximum likelihood).
4. **Elsewhere the lobe varies smoothly** (`lobe_prior`): the prior mean of a point is
   the precision-weighted mean of the measured lobes (the points' own, or in a material whose
   lobe varies the identifiable neighbourhood lobes) among its nearest material-mates, with
   the material's lobe as one more observation; the prior's width is the spread of the
   measured lobes about their (leave-one-out) means beyond their own noise (empirical Bayes,
   robust method of moments), as it grows with the distance to the lobes a mean rests on
   (measured out to the distances the points need), never narrower than the estimate can
   resolve from the points it rests on.

Each point's estimate is then the maximum a posteriori of its own likelihood and this prior
(the row solver lives with the likelihood, in `jaxrefl.methods.local`), and `status_from_posterior`
names which of the two dominated.

5. **pd** (`diffuse_prior`): per channel, the leave-one-out mean (or local plane) of the
   nearest material-mates' own pd, or of all of them where cross-validation finds the
   material uniform, as wide as the field's spread about it; each point's pd given its lobe
   is then its Gaussian posterior.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from scipy import sparse
from scipy.optimize import brentq
from scipy.spatial.distance import cdist
from scipy.stats import chi2 as chi2_dist

from jaxrefl.reflectance import colour_mixture
from jaxrefl.reflectance.fill import neighbour_tree

__all__ = ["Materials", "fit_materials", "MaterialLobes", "material_lobes", "lobes_meta", "LocalLobes", "local_lobes",
           "cover_measured", "covered_variance",
           "LobePrior", "lobe_prior", "DiffusePrior", "diffuse_prior", "combine_with_prior", "local_prior",
           "spread_by_evidence", "status_from_posterior", "prior_conflict", "material_totals", "weighted_rows"]

_VAR_FLOOR = 1e-8  # numerical floor of every variance (ln units)
#: Fewest own lobes from which a material's spread is estimated (a variance from fewer
#: points is too uncertain to widen or narrow a prior); with fewer, the material's lobe.
_MIN_SPREAD_POINTS = 8
_RESTARTS = 4  # seedings of the mixture per K
#: EM stops when the log likelihood gains less than this share of itself: BIC compares
#: likelihoods that differ by whole units, far above it.
_EM_TOL = 1e-6
_SPREAD_SAMPLE = 2000  # measured points a distance-dependent spread is measured on
_SPREAD_PAIRS = 4_000_000  # most (point, neighbour) candidates searched per distance (memory)
_CV_ROWS = 4000  # observed rows the neighbourhood size is cross-validated on
#: Family-wise false-alarm rate of the prior-data conflict tests over all points.
_CONFLICT_ALPHA = 0.05


@dataclass(frozen=True)
class Materials:
    """Material labels `(N,)` int in `[0, k)`, the chosen `k`, and the BIC of every K tried."""

    labels: np.ndarray
    k: int
    bic: dict


def _log_density(x, v, mu, tau2, log_w, xp=np):
    """Per point and component log density `(n, K)` of the diagonal mixture; dimensions with
    infinite observation variance `v` are marginalised out (`xp`: numpy or jax.numpy)."""
    present = xp.isfinite(v)
    var = tau2[None] + xp.where(present, v, 0.0)[:, None]  # (n, K, D)
    d2 = (xp.where(present, x, 0.0)[:, None] - mu[None]) ** 2 / var
    terms = xp.where(present[:, None], d2 + xp.log(2 * np.pi * var), 0.0)
    return log_w[None] - 0.5 * terms.sum(-1)


def _lloyd_seeds(colour, k, rng):
    """Hard initial assignment `(n,)` to `k` clusters: k-means++ seeds on colour (always
    present), deterministic through `rng`, moved by Lloyd's iterations to the clusters' middles."""
    n = len(colour)
    centres = [colour[rng.integers(n)]]
    for _ in range(1, k):
        d2 = np.min(((colour[:, None] - np.array(centres)[None]) ** 2).sum(-1), 1)
        centres.append(colour[rng.choice(n, p=d2 / d2.sum())] if d2.sum() > 0 else colour[rng.integers(n)])
    centres = np.array(centres)
    for _ in range(10):
        nearest = np.argmin(((colour[:, None] - centres[None]) ** 2).sum(-1), 1)
        centres = np.array([colour[nearest == j].mean(0) if np.any(nearest == j) else centres[j] for j in range(k)])
    return np.argmin(((colour[:, None] - centres[None]) ** 2).sum(-1), 1)


@partial(jax.jit, static_argnames=("iterations",))
def _em_batch(x, v, weight, resp, active, iterations=100):
    """EM for diagonal mixtures with per-point observation variances, one per batch row.

    **Arguments:** `x`, `v` `(n, D)` (v inf: missing); `weight` `(n,)` 1 for a point, 0 for
    padding; `resp` `(B, n, K)` initial responsibilities; `active` `(B, K)` bool, the
    components each row uses (a K-component fit is a row with the first K active).

    **Returns:** per row the log likelihood `(B,)`, `mu`, `tau2` `(B, K, D)`, `log_w`
    `(B, K)` and `collapsed` `(B,)` (a component fell under `max(2, 2 D)` points).
    """
    dim = x.shape[1]
    n = weight.sum()
    present = jnp.isfinite(v) & (weight[:, None] > 0)
    xx, vv = jnp.where(present, x, 0.0), jnp.where(present, v, 0.0)
    tol = max(_EM_TOL, 10 * float(jnp.finfo(x.dtype).eps))

    def one(resp0, act):
        k = resp0.shape[1]

        def step(state):
            resp, _, _, tau2, ll, _, it, collapsed = state
            resp = resp * weight[:, None]
            nk = resp.sum(0)
            collapsed = collapsed | jnp.any(act & (nk < max(2.0, 2 * dim)))
            log_w = jnp.where(act, jnp.log(jnp.maximum(nk, 1e-30) / n), -jnp.inf)
            r = resp[:, :, None] * present[:, None, :]
            w = r / (tau2[None] + vv[:, None, :])
            sw, sr = w.sum(0), r.sum(0)
            mu = jnp.where(sw > 0, jnp.sum(w * xx[:, None, :], 0) / jnp.where(sw > 0, sw, 1.0), 0.0)
            moment = jnp.sum(r * ((xx[:, None, :] - mu[None]) ** 2 - vv[:, None, :]), 0) / jnp.where(sr > 0, sr, 1.0)
            tau2 = jnp.where(sr > 0, jnp.maximum(moment, _VAR_FLOOR), 1.0)
            logp = _log_density(x, jnp.where(present, v, jnp.inf), mu, tau2, log_w, jnp)
            total = jax.nn.logsumexp(logp, axis=1)
            return (jnp.exp(logp - total[:, None]), mu, log_w, tau2, jnp.sum(total * weight), ll, it + 1, collapsed)

        def going(state):
            ll, previous, it, collapsed = state[4:]
            return (it < iterations) & ~collapsed & ((it < 1) | (ll - previous >= tol * jnp.abs(ll) + 1e-9))

        dtype = x.dtype
        init = (resp0, jnp.zeros((k, dim), dtype), jnp.full(k, -jnp.log(k), dtype), jnp.ones((k, dim), dtype),
                jnp.asarray(-jnp.inf, dtype), jnp.asarray(-jnp.inf, dtype), 0, jnp.asarray(False))
        _, mu, log_w, tau2, ll, _, _, collapsed = jax.lax.while_loop(going, step, init)
        return ll, mu, tau2, log_w, collapsed

    return jax.vmap(one)(resp, active)


def _em_fits(x, v, ks, seed, full=False):
    """The best non-collapsed mixture of each K in `ks` over `_RESTARTS` seedings (one for
    K = 1), all in one batched EM: `{k: (log likelihood, mu, tau2, log_w)}`; with `full` (colour
    features only, `colour_mixture.em_batch`) `tau2` is each component's covariance `(k, 6)`."""
    n, k_pad = len(x), max(ks)
    n_pad = -(-n // 250) * 250  # one compilation for scans of similar size
    rows = [(k, r) for k in ks for r in range(1 if k == 1 else _RESTARTS)]
    resp = np.zeros((len(rows), n_pad, k_pad))
    for b, (k, r) in enumerate(rows):
        resp[b, np.arange(n), _lloyd_seeds(x[:, :3], k, np.random.default_rng([seed, k, r]))] = 1.0
    active = np.arange(k_pad)[None] < np.array([k for k, _ in rows])[:, None]
    dtype = jnp.float32  # clustering needs no more; twice as fast as float64
    pad = [(0, n_pad - n), (0, 0)]
    out = (colour_mixture.em_batch if full else _em_batch)(
        jnp.asarray(np.pad(x, pad), dtype), jnp.asarray(np.pad(v, pad, constant_values=np.inf), dtype),
        jnp.asarray(np.arange(n_pad) < n, dtype), jnp.asarray(resp, dtype), jnp.asarray(active))
    ll, mu, tau2, log_w = (np.asarray(a, np.float64) for a in out[:4])
    ok = ~np.asarray(out[4]) & np.isfinite(ll)
    fits = {}
    for k in ks:
        cand = [b for b, (kb, _) in enumerate(rows) if kb == k and ok[b]]
        if cand:
            b = max(cand, key=lambda i: ll[i])
            fits[k] = (ll[b], mu[b, :k], tau2[b, :k], log_w[b, :k])
    return fits


def fit_materials(features, variances, positions, k_max: int = 6, sample: int = 2000,
                  seed: int = 0, covariance: str = "diagonal") -> Materials:
    """Cluster points into materials, K chosen by BIC.

    **Arguments:** `features` `(N, D)` (the first three the colour, pd, always present for
    observed points), `variances` `(N, D)` their observation variances (inf: missing, NaN not
    allowed); `positions` `(N, 3)` (points with no feature at all take the label of the
    nearest point that has one); `k_max`; `sample`: the mixture is fitted on at most this
    many points (every point is then assigned); `seed` of that subsample and of the seeds;
    `covariance`: `"diagonal"`, or `"full"` for colour alone (`D` = 3; `colour_mixture`: an
    error the channels share does not split a material).

    **Returns:** `Materials`.
    """
    if covariance not in ("diagonal", "full"):
        raise ValueError(f"covariance must be 'diagonal' or 'full', not {covariance!r}")
    x, v = np.asarray(features, np.float64), np.asarray(variances, np.float64)
    full = covariance == "full"
    if full and x.shape[1] != 3:
        raise ValueError(f"covariance='full' clusters colour alone (3 features), not {x.shape[1]}")
    n = len(x)
    has = np.isfinite(v).any(1)
    idx = np.flatnonzero(has)
    if len(idx) == 0:
        return Materials(np.zeros(n, np.int64), 1, {1: 0.0})
    if full:  # the full mixture runs in float32: a covariance of pd's noise (1e-6) would lose
        # its digits in the cofactors. BIC is unchanged (the same affine map for every K).
        centre = np.array([np.median(x[idx][np.isfinite(v[idx, d]), d]) for d in range(3)])
        scale = np.array([np.std(x[idx][np.isfinite(v[idx, d]), d]) for d in range(3)])
        scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
        x, v = np.where(np.isfinite(x), (x - centre) / scale, 0.0), v / scale**2
    rng = np.random.default_rng(seed)
    fit_idx = np.sort(rng.choice(idx, size=min(sample, len(idx)), replace=False))
    xs, vs = x[fit_idx], v[fit_idx]
    n_fit, dim = xs.shape
    params = (lambda k: k - 1 + 9 * k) if full else (lambda k: k - 1 + 2 * k * dim)  # means, (co)variances
    # A few seedings per K: k-means++ can start two components in one material, which then
    # collapse; the best likelihood of those that do not is kept. K is searched three at a
    # time and the search stops once two more components than the best did not pay.
    best, bic, k_next, done = None, {}, 1, False
    while k_next <= k_max and not done:
        ks = list(range(k_next, min(k_max, k_next + 2) + 1))
        fits = _em_fits(xs, vs, ks, seed, full)
        for k in ks:
            if k not in fits:
                continue
            bic[k] = -2.0 * fits[k][0] + params(k) * np.log(n_fit)
            if best is None or bic[k] < bic[best[0]]:
                best = (k, fits[k])
            elif k >= best[0] + 2:  # two more components that did not pay: more will not
                done = True
                break
        k_next = ks[-1] + 1
    if best is None:
        return Materials(np.zeros(n, np.int64), 1, {1: 0.0})
    k, (_, mu, tau2, log_w) = best
    labels = np.zeros(n, np.int64)
    labels[idx] = colour_mixture.assign(x[idx], v[idx], mu, tau2, log_w) if full else \
        np.argmax(_log_density(x[idx], v[idx], mu, tau2, log_w), 1)
    if not has.all():
        _, j = neighbour_tree(positions[idx]).query(positions[~has], k=1)
        labels[~has] = labels[idx][j]
    return Materials(labels, k, bic)


@dataclass(frozen=True)
class MaterialLobes:
    """Per material `(K,)`: `ps`, `rho` (ln roughness), their standard deviations, the
    number of points it rests on, and `identifiable` (ps stands `min_snr` sd above 0 and
    `rho` is known to within 1, a factor e in roughness)."""

    ps: np.ndarray
    rho: np.ndarray
    sd_ps: np.ndarray
    sd_rho: np.ndarray
    points: np.ndarray
    identifiable: np.ndarray

    def within_bound(self, ps_bound) -> np.ndarray:
        """`(K,)` bool: the joint fit is finite and its ps within the energy bound
        `ps_bound(roughness)` of its roughness (beyond it: a sharp lobe no sample reached)."""
        roughness = np.exp(self.rho)
        finite = np.isfinite(self.ps) & np.isfinite(roughness)
        return finite & (self.ps <= ps_bound(np.where(finite, roughness, 1.0)))


def _profile(c, a, b, bound=np.inf):
    """chi^2 at the best `0 <= ps <= bound` and that ps, elementwise; chi^2 inf where it
    overflows (the sums of a sharp lobe can pass float64's range)."""
    a_safe = np.where(a > 0, a, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        ps = np.minimum(np.where((a > 0) & (b > 0), b / a_safe, 0.0), bound)
        chi2 = c - 2.0 * ps * b + ps * ps * a
    return np.where(np.isfinite(chi2), chi2, np.inf), ps


def _parabola(y0, y1, y2, h):
    """The vertex of the parabola through `(-h, y0)`, `(0, y1)`, `(h, y2)`: its offset from the
    middle, clipped to `[-h, h]`, and its curvature `d^2 y / dx^2`. Offset 0 and curvature 0
    (no information) where the parabola is not convex or a value is not finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        curv = (y0 - 2 * y1 + y2) / h**2
        ok = np.isfinite(y0) & np.isfinite(y1) & np.isfinite(y2) & np.isfinite(curv) & (curv > 0)
        shift = np.where(ok, -0.5 * (y2 - y0) / (h * np.where(ok, curv, 1.0)), 0.0)
    return np.clip(shift, -h, h), np.where(ok, curv, 0.0)


def material_lobes(material_sums, labels, k, inv_s2, rho_grid, min_snr: float = 3.0,
                   peak_samples=None, grid_sums=None) -> MaterialLobes:
    """Joint fit of one lobe per material over all its points' samples.

    **Arguments:** `material_sums(rho, labels, k, weights)` with `rho` `(G, k)` ln roughness
    per grid value and material returns `(G, 3, k)`: per material the `weights`-weighted sum
    over its rows of the squared-residual coefficients `(c0, a, b)` of
    `cost(ps) = c0 - 2 ps b + ps^2 a`, each row's pd profiled out
    (`local.ChunkedRows.material_sums`); `labels` `(N,)`; `k`; `inv_s2` `(N,)` 1 / residual
    variance scale (0 leaves a row out); `rho_grid` `(G,)` ln roughness values to search;
    `peak_samples` `(N,)` int: each row's samples near a specular peak (`classify.T_SPEC`).
    A material whose rows hold fewer than two is not identifiable, whatever its fit: a lobe
    no sample saw near its peak is a smooth trend over its flank, which light the model
    leaves out (interreflection) imitates. `grid_sums` `(G, 3, k)`: `material_sums` at
    `rho_grid` where the caller has them.

    **Returns:** `MaterialLobes`. The best grid value per material is refined on a finer
    grid around it and by a parabola, whose curvature gives `sd_rho`; `sd_ps` from the
    chi^2 curvature in ps at that roughness.
    """
    grid = np.asarray(rho_grid, np.float64)
    if grid_sums is None:
        grid_sums = material_sums(np.broadcast_to(grid[:, None], (len(grid), k)), labels, k, inv_s2)
    c, a, b = np.moveaxis(np.asarray(grid_sums, np.float64), 1, 0)
    chi2, _ = _profile(c, a, b)
    best = np.argmin(chi2, axis=0)  # (K,)
    step = float(np.mean(np.diff(grid)))
    offsets = np.linspace(-step, step, 9)
    centre = grid[best]
    c, a, b = np.moveaxis(material_sums(centre[None] + offsets[:, None], labels, k, inv_s2), 1, 0)
    chi2, ps_g = _profile(c, a, b)
    j = np.clip(np.argmin(chi2, axis=0), 1, len(offsets) - 2)
    cols = np.arange(k)
    y0, y1, y2 = chi2[j - 1, cols], chi2[j, cols], chi2[j + 1, cols]
    h = offsets[1] - offsets[0]
    shift, curv = _parabola(y0, y1, y2, h)  # curv: d^2 chi2 / d rho^2
    rho = centre + offsets[j] + shift
    c, a, b = np.moveaxis(material_sums(rho[None], labels, k, inv_s2), 1, 0)
    _, ps = _profile(c[0], a[0], b[0])
    sd_ps = np.where(a[0] > 0, 1.0 / np.sqrt(np.where(a[0] > 0, a[0], 1.0)), np.inf)
    # chi2 = min + (curv / 2) d^2, so -ln L = chi2 / 2 has curvature curv / 2: var = 2 / curv.
    sd_rho = np.where(curv > 0, np.sqrt(2.0 / np.where(curv > 0, curv, 1.0)), np.inf)
    points = np.bincount(labels, weights=(inv_s2 > 0).astype(np.float64), minlength=k)
    ident = (points > 0) & (ps > min_snr * sd_ps) & (sd_rho < 1.0) & np.isfinite(rho)
    if peak_samples is not None:
        ident &= np.bincount(labels, weights=np.asarray(peak_samples, np.float64), minlength=k) >= 2
    return MaterialLobes(ps, rho, sd_ps, sd_rho, points, ident)


def lobes_meta(lobes: MaterialLobes, spread_ps, spread_rho, ps_bound) -> list[dict]:
    """One JSON-ready dict per material: its joint lobe (`ps`, `roughness` [rad], `std_ps`,
    `std_ln_roughness`; all None where the lobe is not identifiable and beyond the energy bound
    `ps_bound(roughness)`: a sharp lobe no sample reached, whose fit runs to any value),
    `points`, `identifiable`, and the within-material spreads `spread_ps`, `spread_ln_roughness`
    `(K,)` (variances; None where unknown)."""
    def num(value, keep=True):
        return float(value) if keep and np.isfinite(value) else None

    roughness = np.exp(lobes.rho)
    shown = lobes.identifiable | lobes.within_bound(ps_bound)
    return [{"ps": num(lobes.ps[m], shown[m]), "roughness": num(roughness[m], shown[m]),
             "std_ps": num(lobes.sd_ps[m], shown[m]), "std_ln_roughness": num(lobes.sd_rho[m], shown[m]),
             "points": int(lobes.points[m]), "identifiable": bool(lobes.identifiable[m]),
             "spread_ps": num(spread_ps[m]), "spread_ln_roughness": num(spread_rho[m])}
            for m in range(len(lobes.ps))]


@dataclass(frozen=True)
class LocalLobes:
    """The lobe of each point's neighbourhood, itself left out. Per point `(N,)`: `ps`, `rho`
    (ln roughness) of the joint fit to the samples of its nearest observed material-mates
    (none of its own), their variances `var_ps`, `var_rho` from the fit's curvature, and
    `identifiable` (as a material's lobe: `material_lobes`), `radius` the distance to the
    farthest neighbour it rests on; in a material taken whole (`neighbours` 0) the material's
    joint lobe, its own samples included, and `radius` inf. Per material `(K,)`:
    `neighbours`, how many neighbours cross-validation chose (0: the whole material, a lobe
    that does not vary within the material), and `cv` `{neighbours: (K,) summed
    chi^2}` of every candidate over the rows it was cross-validated on."""

    ps: np.ndarray
    rho: np.ndarray
    var_ps: np.ndarray
    var_rho: np.ndarray
    identifiable: np.ndarray
    radius: np.ndarray
    neighbours: np.ndarray
    cv: dict


def _grid_fit(sums, grid, bound):
    """Per column of `sums` `(G, 3, n)` (coefficients `(c0, a, b)` of `c0 - 2 ps b + ps^2 a` on
    the ln roughness `grid` `(G,)`): the best `0 <= ps <= bound` `(G,)` and rho, refined by a
    parabola through the grid's best value and its neighbours; variances of ps (`1 / a`) and
    of rho (`2 / curvature` of chi^2). Returns `(ps, rho, var_ps, var_rho)`, each `(n,)`."""
    c, a, b = sums[:, 0], sums[:, 1], sums[:, 2]
    chi2, ps_g = _profile(c, a, b, bound[:, None])
    cols = np.arange(c.shape[1])
    g = np.clip(np.argmin(chi2, axis=0), 1, len(grid) - 2)
    h = float(grid[1] - grid[0])
    shift, curv = _parabola(chi2[g - 1, cols], chi2[g, cols], chi2[g + 1, cols], h)
    t = shift / h
    # The coefficients between grid values, linearly (ps and its variance at the refined rho).
    lo = np.where(t >= 0, g, g - 1)
    f = np.where(t >= 0, t, 1.0 + t)

    def at(x):
        return x[lo, cols] * (1.0 - f) + x[lo + 1, cols] * f

    aa, bb = at(a), at(b)
    lo_b, hi_b = bound[lo], bound[lo + 1]
    finite = np.isfinite(lo_b) & np.isfinite(hi_b)  # an unbounded ps (inf) stays unbounded, not inf * 0
    bnd = np.where(finite, np.where(finite, lo_b, 0.0) * (1.0 - f) + np.where(finite, hi_b, 0.0) * f, np.inf)
    ps = np.minimum(np.where((aa > 0) & (bb > 0), bb / np.where(aa > 0, aa, 1.0), 0.0), bnd)
    var_rho = np.where(curv > 0, 2.0 / np.where(curv > 0, curv, 1.0), np.inf)
    # ps's variance given rho is 1 / a; rho's own uncertainty moves the best ps along the
    # profile (d ps / d rho), so its marginal variance is 1 / a + (d ps / d rho)^2 var_rho.
    slope = (ps_g[g + 1, cols] - ps_g[g - 1, cols]) / (2 * h)
    var_ps = np.where((aa > 0) & np.isfinite(var_rho),
                      1.0 / np.where(aa > 0, aa, 1.0) + slope**2 * np.where(np.isfinite(var_rho), var_rho, 0.0), np.inf)
    return ps, grid[g] + shift, var_ps, var_rho


def material_totals(row_values, labels, k, weights) -> np.ndarray:
    """Per-row values, rows first, `(N, ...)` -> `(k, ...)`: their `weights` `(N,)`-weighted
    sums over each material's rows (`labels` `(N,)` in `[0, k)`), each material's rows
    added in order."""
    n = len(labels)
    member = sparse.csr_matrix((np.asarray(weights, np.float64), (labels, np.arange(n))), shape=(k, n))
    flat = np.asarray(row_values, np.float64).reshape(n, -1)
    return np.asarray(member @ flat).reshape((k,) + np.shape(row_values)[1:])


def _nearest_mates(labels, observed, positions, k, at):
    """The `k` nearest observed points of each point `at` `(m,)` (indices) in its own
    material, nearest first, the point itself among them where observed: distances and
    indices `(m, k)` (inf and -1 past a material's observed points)."""
    dist, nbr = np.full((len(at), k), np.inf), np.full((len(at), k), -1)
    for m in np.unique(labels[at]):
        mates = np.flatnonzero((labels == m) & observed)
        rows = np.flatnonzero(labels[at] == m)
        if len(mates) < 2:
            continue
        d, j = _neighbours(neighbour_tree(positions[mates]), mates, positions, at[rows], k)
        dist[rows, :d.shape[1]], nbr[rows, :d.shape[1]] = d, j
    return dist, nbr


def _mates_matrix(at, dist, nbr, size, n):
    """Sparse `(m, N)` 0/1: row `r` marks the first `size` of `at[r]`'s neighbours `nbr` (from
    `_nearest_mates`), itself left out; and `(m,)` the distance to the farthest of them
    (inf: none)."""
    use = _usable(at, dist, nbr, size) & (nbr >= 0)
    rows = np.broadcast_to(np.arange(len(at))[:, None], nbr.shape)[use]
    radius = np.where(use.any(1), np.max(np.where(use, dist, 0.0), axis=1), np.inf)
    return sparse.csr_matrix((np.ones(len(rows)), (rows, nbr[use])), shape=(len(at), n)), radius


def local_lobes(row_sums, labels, k, positions, inv_s2, rho_grid, ps_bound=None, min_snr: float = 3.0,
                peak_samples=None, max_neighbours: int = 64, grid_rows=None) -> LocalLobes:
    """Each point's lobe from its neighbours' samples, the neighbourhood's size chosen by
    leave-one-out cross-validation.

    **Arguments:** `row_sums(rho, rows=None)` with `rho` `(G, N)` ln roughness per row returns
    `(G, 3, N)`: each row's coefficients `(c0, a, b)` of its squared residual
    `c0 - 2 ps b + ps^2 a`, pd profiled out (`local.ChunkedRows.row_sums`; with `rows` `(m,)`
    indices, `rho` `(G, m)`, those rows only); `labels` `(N,)` materials, `k` their number;
    `positions` `(N, 3)`; `inv_s2` `(N,)` 1 / residual variance scale (0 leaves a row out);
    `rho_grid` `(G,)` evenly spaced ln roughness; `ps_bound(roughness)` the largest physical ps
    (`brdf.ps_bound`; None: unbounded); `min_snr`, `peak_samples` as `material_lobes`;
    `grid_rows` `(N, G, 3)`: `row_sums` at `rho_grid` times `inv_s2`, rows first
    (`weighted_rows`), where the caller has them.

    A point's neighbourhood is its `n` nearest observed material-mates (`n` = 1, 2, 4, ...)
    or the whole material; its lobe is their joint maximum-likelihood fit, each row's pd
    profiled out, and it never holds the point's own samples (`max_neighbours` the largest
    `n` tried short of the whole material: the cost grows with it). Which a material takes is
    decided by how well each row's own samples are predicted by the lobe fitted without them
    (summed chi^2, leave-one-out cross-validation): a lobe that varies within the material
    wants few neighbours, a uniform one the whole material. The whole material (one lobe, the
    simplest model) is kept unless the best neighbourhood predicts better by more than one
    standard error of the paired per-row differences (the one-standard-error rule: Breiman
    et al. 1984, Hastie et al. 2009 sec. 7.10). The choice is made on at most `_CV_ROWS`
    evenly spread observed rows; only the chosen size is then fitted for every point.

    **Returns:** `LocalLobes`.
    """
    grid = np.asarray(rho_grid, np.float64)
    n = len(labels)
    inv_s2 = np.asarray(inv_s2, np.float64)
    observed = inv_s2 > 0
    peaks = np.zeros(n) if peak_samples is None else np.asarray(peak_samples, np.float64) * observed
    bound = np.full(len(grid), np.inf) if ps_bound is None else np.asarray(ps_bound(np.exp(grid)), np.float64)
    if grid_rows is None:
        grid_rows = weighted_rows(row_sums(np.broadcast_to(grid[:, None], (len(grid), n))), inv_s2)
    flat_t = np.asarray(grid_rows, np.float64).reshape(n, -1)  # (N, G * 3)
    grid_shape = (len(grid), 3)
    counts = np.bincount(labels, weights=observed.astype(np.float64), minlength=k)
    sizes = [0]  # the whole material, then 1, 2, 4, ... neighbours
    while len(sizes) < 2 or sizes[-1] < min(max_neighbours, counts.max() - 1):
        sizes.append(2 ** (len(sizes) - 1))
    # Cross-validation on at most `_CV_ROWS` observed rows, evenly spread: its sums of chi^2
    # are as good a guide with a few thousand rows, and each size costs its rows x neighbours.
    obs_idx = np.flatnonzero(observed)
    cv_idx = obs_idx if len(obs_idx) <= _CV_ROWS else \
        obs_idx[np.linspace(0, len(obs_idx) - 1, _CV_ROWS).astype(np.int64)]

    material_flat = material_totals(flat_t, labels, k, np.ones(n))  # (K, G * 3)
    material_peaks = np.bincount(labels, weights=peaks, minlength=k)

    def lobes_of(sums, peak):
        """`(ps, rho, var_ps, var_rho, ident)` `(m,)` of sums `(G * 3, m)` whose rows hold
        `peak` `(m,)` samples near a specular peak (identifiable as in `material_lobes`)."""
        ps, rho, var_ps, var_rho = _grid_fit(sums.reshape(grid_shape + (sums.shape[-1],)), grid, bound)
        ident = (ps > min_snr * np.sqrt(var_ps)) & (var_rho < 1.0) & np.isfinite(rho) & (peak >= 2)
        return ps, rho, var_ps, var_rho, ident

    def fit_size(size, idx, mates=None):
        """The lobes `(ps, rho, var_ps, var_rho, ident, radius)` of rows `idx` for `size`
        (`mates`: `_nearest_mates` of `idx` for at least `size + 1` neighbours)."""
        if size == 0:  # the material's sums less the point's own
            sums = (material_flat[labels[idx]] - flat_t[idx]).T
            peak = material_peaks[labels[idx]] - peaks[idx]
            radius = np.full(len(idx), np.inf)
        else:
            if mates is None:
                mates = _nearest_mates(labels, observed, positions, size + 1, idx)
            w, radius = _mates_matrix(idx, *mates, size, n)
            sums = np.asarray(w @ flat_t).T
            peak = w @ peaks
        return (*lobes_of(sums, peak), radius)

    # Every size's lobes first (one neighbour search serves them all), then every row's own
    # chi^2 under them in one call, padded to 8 sizes (one compilation for any count).
    mates = _nearest_mates(labels, observed, positions, sizes[-1] + 1, cv_idx)
    fits = [fit_size(size, cv_idx, mates)[:2] for size in sizes]
    rho_cv = np.zeros((-(-len(sizes) // 8) * 8, len(cv_idx)))
    rho_cv[:len(sizes)] = [rho for _, rho in fits]
    own = np.asarray(row_sums(rho_cv, rows=cv_idx), np.float64) * inv_s2[cv_idx]
    cv_rows = {size: own[s, 0] - 2.0 * ps * own[s, 2] + ps * ps * own[s, 1]
               for s, (size, (ps, _)) in enumerate(zip(sizes, fits))}
    chosen = np.zeros(k, np.int64)
    cv = {size: np.bincount(labels[cv_idx], weights=cv_rows[size], minlength=k) for size in sizes}
    for m in range(k):
        rows = labels[cv_idx] == m
        # A neighbourhood of all the other mates is the whole material: not a candidate.
        smaller = [z for z in sizes[1:] if z < counts[m] - 1]
        if not smaller or not rows.any():
            continue
        best = min(smaller, key=lambda z: cv[z][m])
        chosen[m] = best if _beats_by_one_se(cv_rows[0][rows] - cv_rows[best][rows]) else 0
    pick = chosen[labels]
    out = [np.zeros(n) for _ in range(4)] + [np.zeros(n, bool), np.zeros(n)]
    for size in np.unique(pick):
        at = np.flatnonzero(pick == size)
        if size == 0:  # the material whole: its joint lobe (no prior rests on it, `local_prior`)
            fits = [f[labels[at]] for f in lobes_of(material_flat.T, material_peaks)] + [np.full(len(at), np.inf)]
        else:
            fits = fit_size(int(size), at)
        for o, v in zip(out, fits):
            o[at] = v
    return LocalLobes(*out, chosen, cv)


def weighted_rows(sums, weights, block: int = 4096) -> np.ndarray:
    """Per-row coefficients `(G, 3, N)` (`row_sums`) times `weights` `(N,)`, rows first:
    `(N, G, 3)`, the layout sums over rows gather. The transpose and the product in one pass
    over cache-sized blocks, one new array: a scan's grid sums are hundreds of MB, and each
    temporary of that size costs its pages."""
    sums, weights = np.asarray(sums, np.float64), np.asarray(weights, np.float64)
    flat = sums.reshape(-1, sums.shape[-1])
    out = np.empty(flat.shape[::-1])
    for start in range(0, flat.shape[1], block):
        np.multiply(flat[:, start:start + block].T, weights[start:start + block, None], out=out[start:start + block])
    return out.reshape((flat.shape[1],) + sums.shape[:-1])


def _beats_by_one_se(gain) -> bool:
    """Whether a richer model's paired per-row gains `(n,)` over the simpler one (positive: it
    predicts that row better) sum to more than one standard error of their sum: otherwise the
    simpler model is kept (the one-standard-error rule: Breiman et al. 1984, Hastie et al.
    2009 sec. 7.10)."""
    return not gain.sum() <= np.std(gain) * np.sqrt(len(gain))


@dataclass(frozen=True)
class LobePrior:
    """Per point `(N,)`: prior mean and variance of ps and of `rho` (ln roughness);
    `available` where a prior exists (its material's lobe is identifiable or the material
    has points with their own lobe); `spread_ps`, `spread_rho` `(K,)` the within-material
    spreads found (variances). `cover_var_ps`, `cover_var_rho` `(N,)`: the variances raised
    to cover the measured lobes around each point (`cover_measured`; `widened` where either
    is raised): a point's estimate keeps the prior's mean and width (the best guess where most of
    its neighbours agree), and its reported uncertainty takes these (`covered_variance`)."""

    mean_ps: np.ndarray
    var_ps: np.ndarray
    mean_rho: np.ndarray
    var_rho: np.ndarray
    available: np.ndarray
    spread_ps: np.ndarray
    spread_rho: np.ndarray
    cover_var_ps: np.ndarray
    cover_var_rho: np.ndarray

    @property
    def widened(self) -> np.ndarray:
        """`(N,)` bool: where `cover_measured` widened either variance."""
        return (self.cover_var_ps > self.var_ps) | (self.cover_var_rho > self.var_rho)


def _robust_spread(deviation, own_var):
    """Variance `t` of `deviation` `(n,)` beyond the noise `own_var` `(n,)`: the `t` at which
    the deviations in units of `sqrt(own_var + t)` have a robust scale (scaled median
    absolute deviation) of 1, a random-effects variance in which loose fits count little
    and a few wrong ones cannot move it (a moment would let them). 0 unless the scale at
    `t = 0` exceeds 1 by two of its standard errors (about `1.16 / sqrt(n)`): a spread from
    a few points must be significant to widen a prior."""
    n = len(deviation)
    if n < 2:
        return 0.0

    def scale(t):
        z = deviation / np.sqrt(own_var + t)
        return 1.4826 * np.median(np.abs(z - np.median(z)))

    if scale(0.0) <= 1.0 + 2.0 * 1.16 / np.sqrt(n):
        return 0.0
    hi = float(np.max(deviation**2)) + 1e-300
    if scale(hi) > 1.0:  # the deviations' own size bounds the spread
        return hi
    # The scale falls as t grows (a step function of t: Brent's method brackets the step).
    return float(brentq(lambda t: scale(t) - 1.0, 0.0, hi, xtol=1e-12 * hi, rtol=1e-10))


def _neighbours(tree, own_idx, positions, at, k):
    """The `k` nearest own-measured points of each point `at` (indices `(m,)`): distances and
    indices `(m, k)`, nearest first (`tree` holds `positions[own_idx]`)."""
    kk = min(k, len(own_idx))
    dist, j = tree.query(positions[at], k=kk, workers=-1)
    return np.asarray(dist).reshape(len(at), kk), own_idx[np.asarray(j).reshape(len(at), kk)]


def _neighbours_beyond(own_idx, positions, at, k, min_distance):
    """As `_neighbours`, but by brute force and only among the own-measured points no closer
    than `min_distance` and other than the point itself: the `k` nearest, `(m, k)` distances
    and indices (inf and the point's own index past the last). Where those are most of the
    points, a tree search for all of them costs more than every distance."""
    own_pos = positions[own_idx]
    dist, nbr = np.full((len(at), k), np.inf), np.repeat(np.asarray(at)[:, None], k, axis=1)
    step = max(1, _SPREAD_PAIRS // max(len(own_idx), 1))
    for s in range(0, len(at), step):
        rows = np.asarray(at[s:s + step])
        d = cdist(positions[rows], own_pos)
        d[(d < min_distance) | (own_idx[None] == rows[:, None])] = np.inf
        kk = min(k, d.shape[1])
        j = np.argpartition(d, kk - 1, axis=1)[:, :kk]
        dj = np.take_along_axis(d, j, axis=1)
        order = np.argsort(dj, axis=1, kind="stable")
        dj, j = np.take_along_axis(dj, order, axis=1), np.take_along_axis(j, order, axis=1)
        dist[s:s + len(rows), :kk] = dj
        nbr[s:s + len(rows), :kk] = np.where(np.isfinite(dj), own_idx[j], rows[:, None])
    return dist, nbr


def _usable(at, dist, nbr, neighbours, min_distance=0.0):
    """`(m, k)` bool: the first `neighbours` of each point's neighbours, itself left out and
    none closer than `min_distance`."""
    usable = (nbr != at[:, None]) & (dist >= min_distance)
    return usable & (np.cumsum(usable, axis=1) <= neighbours)


def _smooth_means(values, var, nbr, dist, usable, anchor, anchor_var):
    """Precision-weighted mean of each point's `usable` neighbours' `values` (`nbr`, `dist`,
    `usable` `(m, k)`, from `_neighbours` and `_usable`; `var` `(N,)` their variances), with
    `anchor` (variance `anchor_var`) as one more observation. Returns `(mean, var_of_mean,
    nearest)`, each `(m,)`: `nearest` the distance to the closest neighbour used (with neither
    neighbours nor a finite anchor: the anchor, variance inf)."""
    w = np.where(usable, 1.0 / var[nbr], 0.0)
    w0 = 1.0 / anchor_var
    total = w.sum(1) + w0
    some = total > 0
    mean = np.divide(np.sum(w * values[nbr], 1) + w0 * anchor, total, out=np.full(len(total), float(anchor)),
                     where=some)
    nearest = np.min(np.where(usable, dist, np.inf), axis=1, initial=np.inf)
    return mean, np.divide(1.0, total, out=np.full(len(total), np.inf), where=some), nearest


#: Ridge on the slopes of a local plane, relative to the neighbours' weighted spread in
#: position: keeps the fit defined where they lie on a line or the surface is flat (no slope
#: along the normal), and costs a well-spread neighbourhood nothing.
_PLANE_RIDGE = 1e-2


def _plane_design(positions, nbr, at):
    """`(m, k, 4)`: 1 and each neighbour's position relative to its point's, the design of
    `_plane_means`."""
    offset = positions[nbr] - positions[at][:, None]
    return np.concatenate([np.ones(offset.shape[:2] + (1,)), offset], axis=2)


def _plane_means(values, var, nbr, dist, usable, x):
    """As `_smooth_means`, without an anchor, but each point's value is the intercept of a
    precision-weighted plane through its `usable` neighbours (`x` from `_plane_design`):
    a field's gradient does not bias it, where the point lies at the edge of its neighbours
    (a fold, a material's border) or between them. Returns `(mean, var_of_mean, nearest)`,
    each `(m,)`."""
    w = np.where(usable, 1.0 / var[nbr], 0.0)  # (m, k)
    xw = x * w[..., None]
    a = np.matmul(xw.transpose(0, 2, 1), x)  # (m, 4, 4): batched products, not einsum (10x)
    wsum = a[:, 0, 0]
    spread = np.trace(a[:, 1:, 1:], axis1=1, axis2=2) / np.maximum(wsum, 1e-300)
    a[:, 1:, 1:] += (_PLANE_RIDGE * wsum * spread + 1e-300)[:, None, None] * np.eye(3)[None]
    some = wsum > 0
    a[~some] = np.eye(4)
    # The intercept and its variance (the (0, 0) entry of the inverse) in one solve.
    rhs = np.stack([np.matmul(xw.transpose(0, 2, 1), values[nbr][..., None])[..., 0],
                    np.broadcast_to(np.eye(4)[0], (len(a), 4))], axis=2)
    sol = np.linalg.solve(a, rhs)
    nearest = np.min(np.where(usable, dist, np.inf), axis=1, initial=np.inf)
    return np.where(some, sol[:, 0, 0], 0.0), np.where(some, sol[:, 0, 1], np.inf), nearest


def _distance_levels(nearest, shortest=0.0):
    """Distances at which a spread is measured: quantiles of the distances `nearest` from each
    point to the closest measured lobe its mean rests on, none below `shortest`."""
    finite = nearest[np.isfinite(nearest)]
    levels = np.quantile(finite, [0.0, 0.25, 0.5, 0.75, 0.95]) if len(finite) else np.zeros(1)
    return np.unique(np.maximum(levels, shortest))


def _distance_spread(value, var, tree, own_idx, positions, sample, levels, neighbours, centre, anchor_var, total,
                     nearest, resolution, found=None):
    """Spread `(N,)` of each point's value about its local mean as it grows with `nearest`
    `(N,)`, the distance to the closest measured lobe its mean rests on. At each of `levels`
    each measured point of `sample` is predicted from its `neighbours` nearest measured points
    no closer than that distance (`tree` holds `positions[own_idx]`), and the robust spread of
    the misses (beyond their noise) is the spread there; non-decreasing in distance,
    interpolated. (The search reaches as far as each level needs; the
    sample is thinned so that it holds at most `_SPREAD_PAIRS` candidate pairs.) `found`: a
    dict keeping each level's search for the next quantity measured at the same points."""
    centres, spreads = [], []
    found = {} if found is None else found
    for level in levels:
        if level not in found:
            reach = tree.query_ball_point(positions[sample], r=np.nextafter(level, 0.0), return_length=True)
            kk = int(min(len(own_idx), np.max(reach) + neighbours + 1))
            sub = sample if len(sample) * kk <= _SPREAD_PAIRS else \
                sample[np.linspace(0, len(sample) - 1, max(_SPREAD_PAIRS // kk, 1)).astype(np.int64)]
            if len(sub) * len(own_idx) <= 4 * _SPREAD_PAIRS:  # most points are within reach
                dist, nbr = _neighbours_beyond(own_idx, positions, sub, neighbours, level)
            else:
                dist, nbr = _neighbours(tree, own_idx, positions, sub, kk)
            found[level] = sub, dist, nbr, _usable(sub, dist, nbr, neighbours, level)
        sub, dist, nbr, usable = found[level]
        mean, mean_var, used = _smooth_means(value, var + total, nbr, dist, usable, centre, anchor_var + total)
        ok = np.isfinite(used)
        if ok.sum() >= _MIN_SPREAD_POINTS:
            centres.append(float(np.median(used[ok])))
            spreads.append(_robust_spread((value[sub] - mean)[ok], (var[sub] + mean_var)[ok]))
    if not centres:
        return np.full(len(nearest), total + resolution)
    order = np.argsort(centres)
    centres = np.asarray(centres)[order]
    spreads = np.maximum.accumulate(np.asarray(spreads)[order])
    return np.interp(np.where(np.isfinite(nearest), nearest, centres[-1]), centres, spreads) + resolution


def _field_search(positions, mine, at, neighbours, plane=False):
    """The neighbour search one measured field needs (`_field_dimension`): who each point
    `at` `(m,)` rests on depends on where the measured points `mine` `(N,)` are, not on their
    values, so one search serves every dimension. Returns `(own_idx, tree, dist, nbr, usable,
    sample, design, found)`, `design` the local planes' (`_plane_design`) where `plane`, else
    None, `found` an empty dict for `_distance_spread`'s searches."""
    own_idx = np.flatnonzero(mine)
    tree = neighbour_tree(positions[own_idx])
    dist, nbr = _neighbours(tree, own_idx, positions, at, neighbours + 1)
    usable = _usable(at, dist, nbr, neighbours)
    sample = own_idx if len(own_idx) <= _SPREAD_SAMPLE else \
        own_idx[np.linspace(0, len(own_idx) - 1, _SPREAD_SAMPLE).astype(np.int64)]
    return own_idx, tree, dist, nbr, usable, sample, (_plane_design(positions, nbr, at) if plane else None), {}


def _spread_terms(value, var, mine, anchor=0.0, anchor_var=np.inf):
    """What a field's prior at the measured points `mine` `(N,)` rests on: the material's
    `centre` (its `anchor` where that is finite, else the median measured value), the `total`
    spread of the measured values about it beyond their noise (neighbours differ from a point
    by it, and so does the material's value), the `resolution` of a variance estimated from
    `n` points, `median own variance * sqrt(2 / n)`, and the floored variances `(N,)`."""
    own_values, own_var = value[mine], np.maximum(var[mine], _VAR_FLOOR)
    centre = anchor if np.isfinite(anchor_var) else float(np.median(own_values))
    resolution = float(np.median(own_var)) * np.sqrt(2.0 / mine.sum()) + _VAR_FLOOR
    return centre, _robust_spread(own_values - centre, own_var), resolution, np.maximum(var, _VAR_FLOOR)


def _material_field(value, mine, at, terms):
    """The prior of one quantity when a material is uniform: at the points `at` `(m,)` the
    precision-weighted mean of all its measured values `mine` `(N,)` but the point's own
    (leave-one-out), and the spread of the measured values about those means beyond their
    noise, never below the resolution (`terms` from `_spread_terms`, no anchor). Returns
    `(mean, var_of_mean, spread)`, each `(N,)` (set at `at`)."""
    n = len(value)
    _, total, resolution, var_f = terms
    w = np.where(mine, 1.0 / (var_f + total + resolution), 0.0)
    x = np.where(mine, value, 0.0)  # a point without a fit may hold anything, NaN included
    loo_w = w.sum() - w[at]
    mean, mean_var = np.zeros(n), np.full(n, np.inf)
    mean[at] = np.divide(np.sum(w * x) - w[at] * x[at], loo_w, out=np.zeros(len(at)), where=loo_w > 0)
    mean_var[at] = np.divide(1.0, loo_w, out=np.full(len(at), np.inf), where=loo_w > 0)
    spread = _robust_spread((value - mean)[mine], (var_f + mean_var)[mine]) + resolution
    return mean, mean_var, np.full(n, spread)


def _field_dimension(value, var, mine, at, search, positions, neighbours, anchor=0.0, anchor_var=np.inf,
                     shortest=0.0, local=False, terms=None):
    """Prior of one quantity at the points `at` from its measured values at `mine` (at least
    `_MIN_SPREAD_POINTS`): `value`, `var` `(N,)`; `search` from `_field_search`; the
    material's `anchor` value (variance `anchor_var`, inf: none) one more observation;
    `terms` `_spread_terms` of these arguments where the caller has them already.
    Returns `(mean, var_of_mean, spread)`, each `(N,)` (set at `at`): the leave-one-out
    precision-weighted mean of the nearest measured values and the spread of the field about
    it at that distance (`_distance_spread`), never below the resolution of a variance from
    `n` points, `median own variance * sqrt(2 / n)`. With `local` the mean may be a local
    plane's (`_plane_means`, where that predicts the measured points better) and the spread
    is never below the one its own neighbours show (the mean of their squared misses beyond
    their variance): a material may be uniform in one part and textured in another, and a
    spread measured over all of it, robustly, is the uniform part's."""
    own_idx, tree, dist, nbr, usable, sample, design, found = search
    n = len(value)
    centre, total, resolution, var_f = _spread_terms(value, var, mine, anchor, anchor_var) if terms is None else terms
    mean, mean_var, nearest = np.zeros(n), np.full(n, np.inf), np.full(n, np.inf)
    mean[at], mean_var[at], nearest[at] = _smooth_means(
        value, var_f + total + resolution, nbr, dist, usable, centre, anchor_var + total + resolution)
    planar = False
    if local:
        # A plane follows a gradient, a mean has the smaller variance: the one whose
        # leave-one-out misses at the measured points are smaller (precision-weighted) is used.
        plane, plane_var, _ = _plane_means(value, var_f + resolution, nbr, dist, usable,
                                           _plane_design(positions, nbr, at) if design is None else design)
        own = mine[at]
        weight = 1.0 / var_f[at][own]
        if np.sum(weight * (value[at][own] - plane[own]) ** 2) < np.sum(weight * (value[at][own] - mean[at][own]) ** 2):
            mean[at], mean_var[at] = plane, plane_var
            planar = True
    if planar:  # the spread about the planes' leave-one-out predictions
        spread = np.full(n, _robust_spread((value - mean)[mine], (var_f + mean_var)[mine]) + resolution)
    else:
        spread = _distance_spread(value, var_f, tree, own_idx, positions, sample,
                                  _distance_levels(nearest[at], shortest), neighbours, centre, anchor_var, total,
                                  nearest, resolution, found)
    if local:
        excess = np.where(mine, (value - mean) ** 2 - var_f - mean_var, 0.0)
        count = usable.sum(1)
        seen = np.divide(np.sum(np.where(usable, excess[nbr], 0.0), 1), count, out=np.zeros(len(at)),
                         where=count > 0)
        spread[at] = np.maximum(spread[at], seen)
    return mean, mean_var, spread


def local_prior(local: LocalLobes, labels, spread):
    """`(mean_ps, var_ps, mean_rho, var_rho, field)` `(N,)`: the prior of each point whose
    material's lobe varies (`local.neighbours` > 0) and whose neighbourhood's lobe is
    identifiable (`field`): that lobe, as wide as its own variance plus the spread `spread`
    `(K, 2)` of the field about it (variances in ln ps and ln roughness: `spread ps^2` in ps;
    see `spread_by_evidence`). Elsewhere the variances are infinite (no prior)."""
    field = local.identifiable & (local.neighbours[labels] > 0)
    t = np.asarray(spread, np.float64).reshape(-1, 2)[labels]
    var_ps = np.where(field, local.var_ps + t[:, 0] * local.ps**2, np.inf)
    var_rho = np.where(field, local.var_rho + t[:, 1], np.inf)
    return np.where(field, local.ps, 0.0), var_ps, np.where(field, local.rho, 0.0), var_rho, field


def spread_by_evidence(log_evidence, labels, k, rows, candidates):
    """The spreads `(K, 2)` (ln ps, ln roughness) of each material that maximise the marginal
    likelihood of its rows' own data (empirical Bayes, type II maximum likelihood):
    `log_evidence(spread)` returns the log evidence `(N,)` of every row under `spread`
    `(K, 2)` (a row's depends on its material's only; `rows` `(N,)` bool say which count);
    `candidates` the spreads tried, increasing. One spread for both first, then each in turn
    with the other held (coordinate ascent); each time every material takes its best
    candidate, refined by a parabola in ln spread through its neighbours."""
    candidates = np.asarray(candidates, np.float64)
    x = np.log(candidates)
    spread = np.zeros((k, 2))

    def best_of(make):
        table = np.stack([np.bincount(labels, weights=np.where(rows, log_evidence(make(t)), 0.0), minlength=k)
                          for t in candidates])  # (C, K)
        best = np.argmax(np.where(np.isfinite(table), table, -np.inf), axis=0)
        out = candidates[best].copy()
        for m in range(k):
            j = best[m]
            if 0 < j < len(candidates) - 1:
                y0, y1, y2 = table[j - 1, m], table[j, m], table[j + 1, m]
                curv = y0 - 2 * y1 + y2
                if curv < 0:
                    out[m] = float(np.exp(x[j] + np.clip(-0.5 * (y2 - y0) / curv, -1.0, 1.0) * (x[j + 1] - x[j])))
        return out

    spread[:] = best_of(lambda t: np.full((k, 2), t))[:, None]
    for d in (0, 1):
        spread[:, d] = best_of(partial(lambda t, d: np.where(np.arange(2) == d, t, spread), d=d))
    return spread


def lobe_prior(ps, var_ps, rho, var_rho, own, labels, lobes: MaterialLobes, positions,
               neighbours: int = 16, fitted=None, local: LocalLobes | None = None, spread=None,
               materials=None) -> LobePrior:
    """Empirical-Bayes prior of every point's lobe.

    **Arguments:** each point's own fit `ps`, `var_ps`, `rho`, `var_rho` `(N,)` and `own`
    `(N,)` bool (its own samples pin its lobe); `labels` `(N,)`; `lobes` the materials'
    joint fits; `positions` `(N, 3)`; `neighbours` measured material-mates in the local mean;
    `fitted` `(N,)` bool: points with an own fit at all (default: finite variances).

    Within each material the spread of the measured lobes about their leave-one-out local
    means beyond their own variance is the prior's width (`_robust_spread`); it is never
    taken below `median own variance * sqrt(2 / n)`, the resolution of a variance estimate
    from `n` points. A material with fewer own lobes than that takes its joint lobe, as wide
    as the robust spread of all its members' own fits about it, however loose each is.

    With `local` (`local_lobes`) and `spread` `(K, 2)`: in a material whose lobe varies (its
    cross-validated neighbourhood is not the whole material) and which has enough points
    with an identifiable neighbourhood lobe, those lobes are the field the prior rests on,
    in place of the points' own: each such point's prior is its neighbourhood's lobe
    (`local_prior`), and the others take the smooth means of those lobes as above.

    `materials` `(K,)` bool: the materials whose prior is wanted (default all); the others'
    points get none (`available` False) and their spreads are inf.
    """
    n = len(ps)
    k = len(lobes.ps)
    if fitted is None:
        fitted = np.isfinite(var_ps) & np.isfinite(var_rho)
    out = {key: np.zeros(n) for key in ("mean_ps", "var_ps", "mean_rho", "var_rho")}
    available = np.zeros(n, bool)
    spreads = np.full((2, k), np.inf)
    if local is not None:
        direct = local_prior(local, labels, np.zeros((k, 2)) if spread is None else spread)
    for m in range(k):
        if materials is not None and not materials[m]:
            continue
        members = labels == m
        mine = own & members
        fields = (ps, var_ps, rho, var_rho)
        field = local is not None and (direct[4] & members).sum() >= _MIN_SPREAD_POINTS
        if field:
            mine = direct[4] & members
            fields = direct[:4]
        if not (lobes.identifiable[m] or mine.any()):
            continue
        available[members] = True
        at = np.flatnonzero(members)
        if mine.sum() >= _MIN_SPREAD_POINTS:
            search = _field_search(positions, mine, at, neighbours)
            # Two neighbourhood lobes less than two neighbourhood radii apart share samples,
            # so their difference understates the field's: spreads from farther apart only.
            shortest = 2.0 * float(np.median(local.radius[mine])) if field else 0.0
        for d, (value, var, anchor, anchor_sd) in enumerate(
                ((*fields[:2], lobes.ps[m], lobes.sd_ps[m]), (*fields[2:], lobes.rho[m], lobes.sd_rho[m]))):
            anchor_var = anchor_sd**2 if np.isfinite(anchor_sd) else np.inf
            if mine.sum() >= _MIN_SPREAD_POINTS:
                mean, mean_var, spread = _field_dimension(value, var, mine, at, search, positions, neighbours, anchor,
                                                          anchor_var, shortest)
            elif np.isfinite(anchor_var):
                # Too few own lobes to map the field: the material's value, as wide as the
                # spread of every member's own fit about it (however loose each is) demands.
                mean, mean_var = np.full(n, anchor), np.full(n, anchor_var)
                used = members & fitted
                spread = _robust_spread(value[used] - anchor, np.maximum(var[used], _VAR_FLOOR) + anchor_var)
            else:  # a few own lobes and no material lobe: too little to say what the others are
                mean, mean_var, spread = np.zeros(n), np.full(n, np.inf), np.inf
            spread = np.broadcast_to(spread, (n,))
            out["mean_" + ("ps", "rho")[d]][members] = mean[members]
            out["var_" + ("ps", "rho")[d]][members] = mean_var[members] + spread[members]
            spreads[d, m] = float(np.median(spread[members]))
            if field:  # where the neighbourhood's lobe is known, that is the point's prior
                out["mean_" + ("ps", "rho")[d]][mine] = value[mine]
                out["var_" + ("ps", "rho")[d]][mine] = var[mine]
    available &= np.isfinite(out["var_ps"]) & np.isfinite(out["var_rho"]) & np.isfinite(out["mean_ps"]) \
        & np.isfinite(out["mean_rho"])
    for key in ("var_ps", "var_rho"):
        out[key] = np.where(available, np.maximum(out[key], _VAR_FLOOR), np.inf)
    for key in ("mean_ps", "mean_rho"):
        out[key] = np.where(available, out[key], 0.0)
    cover = {name: cover_measured(value, var, own & fitted, out["mean_" + name], out["var_" + name], available,
                                  labels, positions, neighbours)[0]
             for name, value, var in (("ps", ps, var_ps), ("rho", rho, var_rho))}
    return LobePrior(out["mean_ps"], out["var_ps"], out["mean_rho"], out["var_rho"], available,
                     spreads[0], spreads[1], cover["ps"], cover["rho"])


def covered_variance(var_post, var_prior, var_cover):
    """`(N,)`: a posterior variance `var_post` with its prior's variance `var_prior` replaced
    by the wider `var_cover` (`LobePrior.cover_var_*`), the data's information
    `1 / var_post - 1 / var_prior` kept (Gaussian approximation); `var_post` where the prior
    was not widened."""
    with np.errstate(divide="ignore"):
        info = np.maximum(1.0 / var_post - 1.0 / var_prior, 0.0)
        return np.where(var_cover > var_prior, 1.0 / (info + 1.0 / var_cover), var_post)


def _cochran_q(t, dev2, var, use):
    """`(m,)`: `sum_j dev2_j / (var_j + t)` over each row's `use`d neighbours (`(m, k)`), `t` `(m,)`."""
    return np.sum(np.where(use, dev2 / (var + t[:, None]), 0.0), axis=1)


def cover_measured(value, var, own, mean, prior_var, tested, labels, positions, neighbours: int = 16,
                   alpha: float | None = None):
    """A prior checked against the measured values around each point, and widened where it
    does not cover them.

    `value`, `var` `(N,)`: the points' own estimates and variances, `own` `(N,)` where they are
    measured; `mean`, `prior_var` `(N,)` each point's prior; `tested` `(N,)` the points to check.
    Under the prior, the own values `v_j` of a point's `neighbours` nearest measured
    material-mates (itself left out) scatter about its mean with variance `prior_var + var_j`,
    so `Q = sum_j (v_j - mean)^2 / (prior_var + var_j)` is chi^2 with as many degrees of freedom
    as neighbours (Cochran's heterogeneity statistic). Where `Q` exceeds what chance allows over
    the tested points (Bonferroni at `alpha`, as `prior_conflict`), the neighbourhood holds
    lobes the prior does not describe (a glaze the colour clusters merged with its body, a
    border between lobes): its variance is raised to the larger of the `t` at which `Q(t)` equals
    its degrees of freedom (method of moments, Paule & Mandel 1982) and the largest
    `(v_j - mean)^2 - var_j`, so that every measured lobe around the point is within one
    standard deviation of its prior: the point may be any of them (a random-effects spread
    alone covers a few outlying lobes among many poorly), and its uncertainty reports the
    disagreement instead of a narrow, possibly wrong value. Returns `(variance, widened)`,
    `(N,)`.
    """
    alpha = _CONFLICT_ALPHA if alpha is None else alpha
    out, widened = np.array(prior_var, np.float64), np.zeros(len(value), bool)
    var_f = np.maximum(np.where(own, var, np.inf), _VAR_FLOOR)
    for m in np.unique(labels[tested]):
        mates = np.flatnonzero(own & (labels == m) & np.isfinite(value) & np.isfinite(var_f))
        at = np.flatnonzero(tested & (labels == m) & np.isfinite(prior_var))
        if len(mates) < 2 or not len(at):
            continue
        kk = min(neighbours + 1, len(mates))
        dist, j = neighbour_tree(positions[mates]).query(positions[at], k=kk, workers=-1)
        nbr = mates[np.asarray(j).reshape(len(at), kk)]
        use = nbr != at[:, None]
        use &= np.cumsum(use, axis=1) <= neighbours
        dof = use.sum(1)
        dev2 = np.where(use, (value[nbr] - mean[at][:, None]) ** 2, 0.0)
        vj = np.where(use, var_f[nbr], 1.0)
        limit = chi2_dist.isf(alpha / len(at), np.maximum(dof, 1))
        wide = (dof >= 2) & (_cochran_q(out[at], dev2, vj, use) > limit)
        if not wide.any():
            continue
        dev2, vj, use, dof = dev2[wide], vj[wide], use[wide], dof[wide]
        # Q(t) falls with t and Q(sum dev2 / dof) <= dof: bisection in ln t between the two.
        lo = np.log(np.maximum(out[at[wide]], _VAR_FLOOR))
        hi = np.log(np.maximum(dev2.sum(1) / dof, np.exp(lo)))
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            above = _cochran_q(np.exp(mid), dev2, vj, use) > dof
            lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
        farthest = np.max(np.where(use, dev2 - vj, 0.0), axis=1)
        out[at[wide]] = np.maximum(out[at[wide]], np.maximum(np.exp(hi), farthest))
        widened[at[wide]] = True
    return out, widened


@dataclass(frozen=True)
class DiffusePrior:
    """Per point: prior `mean` and `var` of pd `(N, 3)` (var inf: no prior); `available`
    `(N,)` where a prior exists and the point's own pd does not contradict it; `conflict`
    `(N,)` the points whose own pd does; `spread` `(K, 3)` the median spread per material
    and channel (variance; inf: too few points); `neighbours` `(K,)` the mates each
    material's means rest on (0: all of them, the material is uniform)."""

    mean: np.ndarray
    var: np.ndarray
    available: np.ndarray
    conflict: np.ndarray
    spread: np.ndarray
    neighbours: np.ndarray


def diffuse_prior(pd, var_pd, known, labels, positions, neighbours: int = 16, k: int | None = None,
                  var_test=None) -> DiffusePrior:
    """Empirical-Bayes prior of every point's diffuse albedo, per material and channel, as
    `lobe_prior` builds it for a lobe from the points' own fits: the precision-weighted mean
    of the nearest material-mates' pd (`neighbours` of them, the point left out, or a local
    plane through them), as wide as the spread of the field about such means beyond their
    noise (`_field_dimension`); or, where leave-one-out cross-validation cannot tell that
    field from one value for the whole material (`_material_field`), the mean of all
    material-mates. A uniform material's prior is narrow and pulls each point's noisy pd to
    the material's; a textured one's is wide and leaves it. A point whose own pd differs from its prior by more
    than chance allows over all points (chi^2 with 3 degrees of freedom, family-wise
    `_CONFLICT_ALPHA`) is a detail the neighbours do not share: it gets no prior.

    **Arguments:** `pd`, `var_pd` `(N, 3)` each point's own fit and its variance; `known`
    `(N,)` bool the points with an own fit; `labels` `(N,)` materials; `positions` `(N, 3)`;
    `k` the number of materials (default `labels.max() + 1`; a material may have no point);
    `var_test` `(N, 3)` the variance the conflict test takes for each point's own pd (default
    `var_pd`; the noise's alone where `var_pd` is inflated by the model's misfit, which would
    otherwise hand a point its data contradict to the prior).
    """
    pd, var_pd = np.asarray(pd, np.float64), np.asarray(var_pd, np.float64)
    n = len(pd)
    k = max(int(labels.max()) + 1 if n else 0, k or 0)
    known = np.asarray(known, bool) & np.all(np.isfinite(pd) & np.isfinite(var_pd), axis=1)
    mean, var = np.zeros((n, 3)), np.full((n, 3), np.inf)
    spreads = np.full((k, 3), np.inf)
    chosen = np.zeros(k, np.int64)
    for m in range(k):
        members = labels == m
        mine = known & members
        if mine.sum() < _MIN_SPREAD_POINTS:
            continue
        at = np.flatnonzero(members)
        search = _field_search(positions, mine, at, neighbours, plane=True)
        fields = {size: [] for size in (0, neighbours)}
        for c in range(3):
            terms = _spread_terms(pd[:, c], var_pd[:, c], mine)
            fields[neighbours].append(_field_dimension(pd[:, c], var_pd[:, c], mine, at, search, positions,
                                                       neighbours, local=True, terms=terms))
            fields[0].append(_material_field(pd[:, c], mine, at, terms))
        # Leave-one-out cross-validation, as `local_lobes` chooses a lobe's neighbourhood: the
        # whole material (the simpler model, the narrower prior) unless the neighbours predict
        # the measured pd better by more than one standard error of the paired differences.
        w = 1.0 / np.maximum(var_pd[mine], _VAR_FLOOR)
        d = np.sum(w * ((pd[mine] - np.stack([f[0][mine] for f in fields[0]], 1)) ** 2
                        - (pd[mine] - np.stack([f[0][mine] for f in fields[neighbours]], 1)) ** 2), axis=1)
        chosen[m] = neighbours if _beats_by_one_se(d) else 0
        for c, (mu, mu_var, spread) in enumerate(fields[chosen[m]]):
            mean[at, c], var[at, c] = mu[at], np.maximum(mu_var[at] + spread[at], _VAR_FLOOR)
            spreads[m, c] = float(np.median(spread[at]))
    var_test = var_pd if var_test is None else np.asarray(var_test, np.float64)
    available = np.all(np.isfinite(var), axis=1)
    tested = available & known & np.all(np.isfinite(var_test), axis=1)
    chi = np.sum((pd - mean) ** 2 / (np.where(tested[:, None], var_test, 1.0) + var), axis=1)
    threshold = chi2_dist.isf(_CONFLICT_ALPHA / max(int(tested.sum()), 1), 3)
    conflict = tested & (chi > threshold)
    available &= ~conflict
    return DiffusePrior(np.where(available[:, None], mean, 0.0), np.where(available[:, None], var, np.inf),
                        available, conflict, spreads, chosen)


def combine_with_prior(value, std, where, mean, var) -> None:
    """In place on `value`, `std` `(N, C)` at the rows `where` `(N,)`: the Gaussian posterior
    of an estimate `value +- std` under the prior `mean`, `var` `(N, C)` (an infinite std:
    the prior)."""
    v_own = np.maximum(std[where] ** 2, 1e-300)
    precision = 1.0 / v_own + 1.0 / var[where]
    value[where] = (value[where] / v_own + mean[where] / var[where]) / precision
    std[where] = np.sqrt(1.0 / precision)


def status_from_posterior(own, var_own_ps, var_own_rho, prior: LobePrior):
    """`(measured, pooled)` `(N,)` bool: `measured` where the point's own samples pin its lobe
    and carry at least the prior's precision in both ps and `rho`; `pooled` where not, but a
    prior exists."""
    dominates = (var_own_ps <= prior.var_ps) & (var_own_rho <= prior.var_rho)
    measured = own & (dominates | ~prior.available)
    return measured, ~measured & prior.available


def prior_conflict(cost_posterior, cost_own, noise_scale, tested):
    """`(N,)` bool: among the `tested` points `(N,)` bool, those whose data's chi^2 at the
    posterior mode exceeds that at their own best fit (costs `(N,)` weighted squared
    residuals, `noise_scale` `(N,)` their variance scale) by more than chance allows: the
    excess is chi^2 with 2 degrees of freedom (ps, ln roughness), whose tail is
    `exp(-x / 2)`, so over `n` tested points a threshold of `2 ln(n / alpha)` lets no point
    cross it by chance with probability `1 - alpha` (`_CONFLICT_ALPHA`, Bonferroni). The
    prior then describes other points than these (a glaze on part of one colour)."""
    tested = np.asarray(tested, bool)
    n = max(int(tested.sum()), 1)
    delta = (np.asarray(cost_posterior) - np.asarray(cost_own)) / np.asarray(noise_scale)
    return tested & np.isfinite(delta) & (delta > 2.0 * np.log(n / _CONFLICT_ALPHA))
