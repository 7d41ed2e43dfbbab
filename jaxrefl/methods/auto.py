"""Method choice (`--method auto`): model only what a scene needs.

Before anything global is fitted, every point gets these numbers:

- `mass` `m_u = sum_v F_uv`: the share of its hemisphere that sees the object
  itself (the row sums of Method II's form factors; the same Embree casts with
  the same settings, so Method II later reads them from the cache);
- `gain_diffuse` `g_u`, `gain_specular` `s_u`: the light its surroundings send it
  after one bounce, over the direct light, under the scan's own lights and with
  the reflectance of a Method I fit (`interreflection_ratios`): every form-factor
  neighbour `v` lit by light `m` sends `F_uv pd_v E_vm` diffusely and
  `pi F_uv f_s(v; light -> u) E_vm` through its specular lobe, so `s` grows with
  the neighbours' ps and with how sharply their lobes aim the light at `u`
  (form-factor mass x albedo for `g`);
- `rel_std_pd`, `rel_std_ps`: Method I's relative standard deviations (scaled,
  the error no choice of method removes; a fixed value where the point has no
  estimate of its own).

**Error model** (`ErrorModel`, calibrated by `benchmarks/auto_bench.py
--calibrate` on the benchmark scenes; numbers in `benchmarks/RESULTS_auto.md`). Per point
and method `k` the predicted relative error of pd (likewise ps) is

    e_k = sqrt(noise^2 + bias_k^2),  bias_k = a_k g + b_k s  (Methods I, II)

Method I leaves all the interreflected light in its fit (`a_I`, `b_I`), Method II
removes the diffuse part but not what a specular lobe carries (`b_II`) and adds
its own noise (a floor in quadrature), Method III removes both at the cost of its
Monte Carlo error, which grows with the light it estimates and falls with the
photons each light configuration gets: `bias_III = (a_III + c k) g + b_III s`,
`k = sqrt(points / photons per configuration)`, plus a floor and `spread k` (noise
at every point) in quadrature. The calibration also measures how far the model's
*comparison* of two methods can be trusted: per pair, the spread of the log ratio of
measured to predicted error ratios over bins of points (`uncertainty_pd`, `_ps`;
about a factor 1.5 for pd).

**Choice**: methods are ranked by cost (local < radiosity < photon, as measured
at the benchmark's settings: `RESULTS_auto.md`). Each predicted error
has two parts (`predict_parts`): `noise`, which the model takes from Method I's own
covariance and the methods' noise floors, and `bias`, the interreflected light a
method leaves in its fit, which is what the model is unsure of. The burden of proof
is on the cheaper method: `j` is *good enough* where, against every other candidate
`k`, `sqrt(noise_j^2 + (margin_jk bias_j)^2) <= max(target, (1 + tolerance) e_k)`,
`margin_jk = exp(uncertainty)` of the pair (`ErrorModel.margin`) and `e_k` `k`'s
nominal error. Where interreflection is negligible (a convex object, the convex parts
of any object, light that reaches few other points) the bias is ~0 and Method I's lower
noise keeps it; where it is not, the method that removes it runs. `target` is an error
the user accepts (`--target-error`): a method within it is good enough whatever the
others; 0 (the default) asks for the best method's accuracy within the tolerance. A
point *needs a global method* where Method I is not good enough.
Regions are the connected components (mesh edges) of that mask with at least
`min_region` points, dilated by `rings` rings; per region the cheapest method good
enough on the medians of its points (pessimistic and nominal errors each reduced by
the median) is chosen (none: the least short of its limits, then the cheapest). The
most capable method any region needs is run: Method III on the whole object (it has
no way to fit part of one: the photon map and its fit need every point's
reflectance), Method II for the regions' points only (the rest of the object enters
its radiosity with Method I's albedo; its cost is the light configurations the
regions' observations use; two alternations of pd and specular part,
`radiosity_outer`). Its pd is used inside the regions and at the points outside them
where it is predicted (nominally) to beat Method I at no extra cost (`_extension`), and,
where Method III runs, at the points left to Method I that have a lobe of their own
(Method I fits pd there jointly with a lobe its noise leaves loose; Method III refits the
lobes and polishes pd at them); everywhere else Method I's result stands (it is what was
fitted to measure the scene, and where interreflection is negligible it is at least as
accurate: `RESULTS_auto.md`).
The choice is made on pd: the ps model cannot rank the methods (it predicts about the
same ps error for every method where the measured ones differ by orders of magnitude).

**The data's check on Method II.** The model's gains come from Method I's lobes, which
can miss the light a glossy cavity mirrors into itself. So where Method II runs, its own
residuals decide whether it explained the regions: the median residual variance of its
last fit over the regions' points against the noise (the scan-wide median, the smaller of
Methods I's and II's: where most points fit, that is the noise). At twice the noise or
more (`_UNEXPLAINED`: the light left unexplained as large as the noise) Method III runs
instead and takes Method II's points, and `meta['auto']['unexplained']` says so. Where the
regions cover most of the scan there is no noise apart from them to compare with, and the
model's choice stands.

**ps and roughness** come from Method III in the regions (Method II's as well) and wherever Method I's lobe is
neither measured nor pooled (its fill spreads lobes fitted with the interreflected light
removed), else from Method I: outside the regions the interreflected light is negligible,
and a lobe Method I measured there is the same light's fit without the photon map's Monte
Carlo error. Once Method III ran, its pd is also taken wherever its own standard deviation
is below Method I's. Where only Method II runs, ps is Method I's (Method II removes only
the diffuse interreflection, so its ps is no better). Measurements:
`benchmarks/RESULTS_notes.md`.

Method III (`jaxrefl.methods.inverse_photon`) is imported only when needed; it fits the
Ward model, so it is a candidate only with `local.model == 'ward'`, when the
module is present, and when Method I measured a specular lobe somewhere (without
one it models the same light as Method II, with Monte Carlo noise, and the noise
floors alone could otherwise make it look better at many times the cost). `meta['auto']` of the result reports the measured
statistics, the predicted errors, every region and the reasons.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..geometry.formfactors import FormFactors, form_factors
from ..geometry.raycast import RayCaster
from ..reflectance.fill import vertex_adjacency
from ..result import Estimate
from ..scan import checks
from .interreflection import interreflection_ratios, pd_sd_with_interreflection
from .local import INTERPOLATED, MEASURED, POOLED, UNRESOLVED, LocalOptions, estimate_local, prepare_rows
from .radiosity import RadiosityOptions, estimate_radiosity

__all__ = ["METHODS", "ErrorModel", "AutoOptions", "Measures", "Plan", "interreflection_ratios", "photon_k", "measure", "predict_parts", "predict", "plan", "estimate_auto", "holdout_check", "photon_available"]

#: Candidate methods, cheapest first.
METHODS = ("local", "radiosity", "photon")

_PD_FLOOR = 0.05  # albedo below which a point's own relative quantities are not trusted
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ErrorModel:
    """Coefficients of `e = sqrt(noise^2 + bias^2 [+ photon_noise^2])` per method
    (`METHODS` order). `pd` and `ps` hold `(a, b)`: `bias = a g + b s` for Methods I and
    II; Method III's `bias = (a + photon_mc * k) g + b s` (its Monte Carlo error grows with the
    interreflected light it estimates and with `k = sqrt(points / photons per light
    configuration)`), and its Monte Carlo noise `photon_spread * k` at every
    point (it refits all of them from photon-replayed images) adds to the floor
    `photon_noise` in quadrature; Method II's own noise (form-factor rays, light
    configurations, its separate specular fit) is `radiosity_noise`. `noise` is `noise_scale_pd` (`_ps`) times Method
    I's relative standard deviation where the point has its own estimate, else
    `unknown_pd` (`unknown_ps`: the error of a value filled from neighbours), at most 1.

    `uncertainty_pd` (`_ps`): how far the model's predicted ratio of two methods' errors
    is from the measured one, per pair (local/radiosity, local/photon, radiosity/photon):
    the weighted RMS of `log(measured ratio / predicted ratio)` over the calibration's bins
    of points. `exp(uncertainty)` (`margin`) inflates a method's bias when it is compared with
    another (`_pessimistic`). Fitted by `benchmarks/auto_bench.py --calibrate`
    (`RESULTS_auto.md`)."""

    # Fitted by `benchmarks/auto_bench.py --calibrate` on the synthetic benchmark scenes; the
    # command, and a refit that was not adopted because it ranked the methods worse, are in
    # benchmarks/RESULTS_notes.md.
    pd: tuple = ((0.794, 2.773), (0.0, 2.825), (0.0, 1.046))
    ps: tuple = ((0.0, 0.0), (0.0, 0.0), (0.0, 5.473))
    photon_mc_pd: float = 0.262
    photon_mc_ps: float = 0.001
    noise_scale_pd: float = 0.558
    noise_scale_ps: float = 0.344
    unknown_pd: float = 0.132
    unknown_ps: float = 0.03
    photon_noise: float = 0.0041
    photon_spread_pd: float = 0.0
    photon_spread_ps: float = 0.0114
    radiosity_noise_pd: float = 0.0053
    radiosity_noise_ps: float = 0.0121
    uncertainty_pd: tuple = (0.402, 0.364, 0.355)
    uncertainty_ps: tuple = (0.392, 1.157, 1.281)

    def coefficients(self, quantity: str, method: str) -> tuple[float, float]:
        return getattr(self, quantity)[METHODS.index(method)]

    def margin(self, quantity: str, a: str, b: str) -> float:
        """`exp(uncertainty)` of the predicted ratio of `a`'s and `b`'s errors (1 for a == b)."""
        if a == b:
            return 1.0
        i, j = sorted((METHODS.index(a), METHODS.index(b)))
        return float(np.exp(getattr(self, f"uncertainty_{quantity}")[i + j - 1]))

    def noise(self, quantity: str, rel_std) -> np.ndarray:
        """Error `(N,)` no method removes, from Method I's relative std (inf: no own estimate)."""
        scale, unknown = getattr(self, f"noise_scale_{quantity}"), getattr(self, f"unknown_{quantity}")
        known = np.isfinite(rel_std)
        return np.minimum(np.where(known, scale * np.where(known, rel_std, 0.0), unknown), 1.0)

    def bias(self, quantity: str, method: str, g, s, photon_k: float = 0.0) -> np.ndarray:
        """Predicted relative bias `(N,)` of `method` from the gains `g`, `s` `(N,)`."""
        a, b = self.coefficients(quantity, method)
        if method == "photon":
            return (a + getattr(self, f"photon_mc_{quantity}") * photon_k) * g + b * s
        return a * g + b * s


@dataclass(frozen=True)
class AutoOptions:
    """Settings of `estimate_auto` (module docstring). `target_error`: relative pd error
    the user accepts (median per region; 0: as accurate as the best method); `tolerance`:
    a method whose error, its bias inflated by the model's uncertainty, is within this
    fraction of the best predicted error counts as good enough; `min_region` points
    a region needs; `rings` it is dilated by; `methods` the candidates; `local`,
    `radiosity` the options of Methods I and II (the form factors are cast with
    `radiosity.rays` and `radiosity.seed`, Method I's options replace
    `radiosity.local`); `photon` keyword arguments of `PhotonOptions` (Method III);
    `model` the error model; `radiosity_outer` Method II's alternations of pd and the specular
    part in the regions, at most `radiosity.outer`: its pd settles after two (measurements:
    `benchmarks/RESULTS_notes.md`), and the third refines a specular fit auto takes from
    Method I (Method II's ps is not used)."""

    target_error: float = 0.0
    tolerance: float = 0.1
    min_region: int = 8
    rings: int = 2
    methods: tuple = METHODS
    local: LocalOptions = field(default_factory=LocalOptions)
    radiosity: RadiosityOptions = field(default_factory=RadiosityOptions)
    photon: dict = field(default_factory=dict)
    model: ErrorModel = field(default_factory=ErrorModel)
    radiosity_outer: int = 2

    def __post_init__(self):
        if not self.target_error >= 0:
            raise ValueError(f"target_error: must be >= 0, got {self.target_error}")
        if not self.tolerance >= 0:
            raise ValueError(f"tolerance: must be >= 0, got {self.tolerance}")
        if self.rings < 0 or self.min_region < 1 or self.radiosity_outer < 1:
            raise ValueError("rings: must be >= 0; min_region, radiosity_outer: must be >= 1")
        unknown = set(self.methods) - set(METHODS)
        if unknown or "local" not in self.methods:
            raise ValueError(f"methods: a subset of {METHODS} including 'local', got {self.methods}")


# -- measurements --------------------------------------------------------------------------


@dataclass
class Measures:
    """Per-point measurements `(N,)`: `mass`, `gain_diffuse`, `gain_specular` (module
    docstring); `rel_std_pd`, `rel_std_ps` Method I's relative standard deviations of
    pd (mean over RGB) and ps, inf where the point has no estimate of its own; `local`
    the Method I estimate they came from (the gated rules: the error model was built on
    them); `ff` the form factors; `seconds` per stage; `photon_k` = sqrt(points / photons per
    light configuration) of Method III's settings; `rows` Method I's rows (`prepare_rows`)."""

    mass: np.ndarray
    gain_diffuse: np.ndarray
    gain_specular: np.ndarray
    rel_std_pd: np.ndarray
    rel_std_ps: np.ndarray
    local: Estimate
    ff: FormFactors
    seconds: dict
    photon_k: float = 0.0
    rows: dict | None = None

    def statistics(self) -> dict:
        """Median, 90th percentile and maximum of each measurement (relative stds over the
        points with their own estimate, whose share is `own`)."""
        out = {}
        for name in ("mass", "gain_diffuse", "gain_specular", "rel_std_pd", "rel_std_ps"):
            v = getattr(self, name)
            v = v[np.isfinite(v)]
            out[name] = ({"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max())}
                         if v.size else {"median": None, "p90": None, "max": None})
            if name.startswith("rel_std"):
                out[name]["own"] = float(v.size / max(len(getattr(self, name)), 1))
        out["photon_k"] = self.photon_k
        return out


def photon_k(scan, photon: dict) -> float:
    """`sqrt(N / photons per light configuration)` for Method III's settings `photon`
    (`PhotonOptions` keywords; per-point lights are binned into configurations as
    Method III does): the relative Monte Carlo error of a gather, up to a constant."""
    from .radiosity import light_configs

    photons, light_bin = photon.get("photons", 1_000_000), photon.get("light_bin", 0.1)
    configs = len(light_configs(scan.light_pos, scan.n_points, light_bin).positions)
    per_config = max(1000, round(photons * scan.n_lights / configs))
    return float(np.sqrt(scan.n_points / per_config))


def _relative_std(std, value, own):
    """`std / value` `(N,)` where the point has its own finite estimate, inf elsewhere."""
    ok = own & np.isfinite(std) & (value > 0)
    return np.where(ok, np.asarray(std) / np.where(ok, value, 1.0), np.inf)


def measure(scan, options: AutoOptions = AutoOptions(), caster: RayCaster | None = None) -> Measures:
    """Form factors (cached, the same casts as Method II) and a Method I fit, and from
    them the per-point measurements of the module docstring."""
    caster = caster or RayCaster(scan.vertices, scan.faces)
    t0 = time.perf_counter()
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=options.radiosity.rays,
                      seed=options.radiosity.seed, caster=caster)
    t_ff = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows = prepare_rows(scan, options.local.thresholds, caster)
    # The error model's coefficients were fitted against Method I's gated rules, so its
    # statistics (and the Method I estimate auto keeps) come from those, not the prior.
    local = estimate_local(scan, dataclasses.replace(options.local, prior=False, interreflection_rays=0), caster,
                           rows=rows)
    t_local = time.perf_counter() - t0

    t0 = time.perf_counter()
    g, s = interreflection_ratios(scan, local, ff, rows)
    rel_pd = _relative_std(local.std_pd.mean(axis=1), np.maximum(local.pd.mean(axis=1), 0.01), local.pd_measured)
    rel_ps = _relative_std(local.std_ps, local.ps, local.specular_identifiable)
    k = photon_k(scan, options.photon) if "photon" in options.methods else 0.0
    seconds = {"form_factors": t_ff, "local": t_local, "measures": time.perf_counter() - t0}
    return Measures(ff.row_sums, g, s, rel_pd, rel_ps, local, ff, seconds, k, rows)


def predict_parts(measures: Measures, model: ErrorModel = ErrorModel(), methods=METHODS) -> dict:
    """Per point the two parts of each method's predicted relative error, `{method: {"pd": (noise,
    bias), "ps": (noise, bias)}}` each `(N,)`: `noise` what the model is sure of (Method I's
    scaled relative std, Method II's and III's own noise floors in quadrature), `bias` the
    interreflected light the method leaves in its fit (and Method III's Monte Carlo error of it),
    the part the model's uncertainty is about."""
    out = {}
    for k in methods:
        out[k] = {}
        for q in ("pd", "ps"):
            noise = model.noise(q, getattr(measures, f"rel_std_{q}"))
            bias = model.bias(q, k, measures.gain_diffuse, measures.gain_specular, measures.photon_k)
            floor = getattr(model, f"radiosity_noise_{q}") if k == "radiosity" else 0.0
            if k == "photon":  # Monte Carlo noise at every point, interreflection or not
                floor = np.hypot(model.photon_noise, getattr(model, f"photon_spread_{q}") * measures.photon_k)
            out[k][q] = (np.hypot(noise, floor), np.abs(bias))
    return out


def predict(measures: Measures, model: ErrorModel = ErrorModel(), methods=METHODS) -> dict:
    """Predicted relative errors per point: `{method: {"pd": (N,), "ps": (N,)}}`,
    `sqrt(noise^2 + bias^2)` of `predict_parts`."""
    return {k: {q: np.hypot(*v[q]) for q in v} for k, v in predict_parts(measures, model, methods).items()}


# -- the plan -------------------------------------------------------------------------------


@dataclass
class Plan:
    """`method` `(N,)` index into `METHODS` whose pd is used at each point; `ps_method` `(N,)`
    the one whose ps and roughness are used (Method III's everywhere when it runs, else Method
    I's; once Method III ran, `_photon_sources` narrows it and widens `method`); `run` the most
    capable global method run (None: Method I alone); `regions`
    one dict per region; `needs_global` `(N,)` the mask before regions were formed;
    `predicted` per-method scene medians and those of the plan; `extended` `(N,)` points
    outside the regions that take a global method's result as well (`_extension`, and the points
    with a lobe of their own where Method III runs); `runs`
    every global method to run, cheapest first (`run` is the last)."""

    method: np.ndarray
    run: str | None
    regions: list
    needs_global: np.ndarray
    predicted: dict
    extended: np.ndarray | None = None
    runs: tuple = ()
    ps_method: np.ndarray | None = None


def _pessimistic(parts: dict, j: str, k: str, q: str, model: ErrorModel) -> np.ndarray:
    """`(N,)` `j`'s error with its bias inflated by the model's uncertainty on comparing it with
    `k` (`ErrorModel.margin`): `sqrt(noise_j^2 + (margin_jk bias_j)^2)`; `j`'s nominal error for
    `j == k`."""
    noise, bias = parts[j][q]
    return np.hypot(noise, model.margin(q, j, k) * bias)


def _meets(parts: dict, candidates, target: float, tolerance: float, model: ErrorModel, reduce=lambda e: e,
           quantities=("pd",)) -> dict:
    """For each candidate `j`, whether it is good enough: for every other candidate `k`, `j`'s
    (reduced) pessimistic error (`_pessimistic`, against `k`) is at most `max(target, (1 + tol)
    e_k)`, `e_k` `k`'s (reduced) nominal error. The burden of proof is on the cheaper method:
    its bias must be small enough that even inflated by what the model cannot tell apart it stays
    within the tolerance of the best prediction (where interreflection is negligible, bias ~ 0 and
    Method I's lower noise wins)."""
    ok = {}
    for q in quantities:
        nominal = {k: np.asarray(reduce(np.hypot(*parts[k][q]))) for k in candidates}
        for j in candidates:
            good = ok.get(j, True)
            for k in candidates:
                if k != j:
                    mine = np.asarray(reduce(_pessimistic(parts, j, k, q, model)))
                    good = good & (mine <= np.maximum(target, (1.0 + tolerance) * nominal[k]))
            ok[j] = good
    return ok


def _median(e):
    return float(np.median(e))


def _shortfall(parts: dict, candidates, method: str, core, options) -> tuple:
    """Largest ratio over the other candidates of `method`'s median pessimistic pd error in `core`
    to its limit (`_meets`), floored at 1, then cost: the fallback where no candidate is good
    enough (each has a bias the others' predictions beat once inflated)."""
    worst = 1.0
    for k in candidates:
        if k == method:
            continue
        mine = _median(_pessimistic(parts, method, k, "pd", options.model)[core])
        limit = max(options.target_error, (1.0 + options.tolerance) * _median(np.hypot(*parts[k]["pd"])[core]))
        worst = max(worst, mine / max(limit, 1e-12))
    return (worst, METHODS.index(method))


_NO_LOBE = ("no specular lobe measured anywhere (Method I): Method III would model the same light as Method II, "
            "with Monte Carlo noise, at many times its cost")


def _no_lobe(measures: Measures) -> bool:
    """Method I measured no specular lobe anywhere: Method III, which differs from Method II
    only in the light specular lobes interreflect, is then no candidate (False when the
    measures carry no Method I estimate)."""
    return measures.local is not None and not measures.local.specular_identifiable.any()


def plan(scan, measures: Measures, options: AutoOptions = AutoOptions(), available=None) -> Plan:
    """Regions and a method per region (module docstring); `available` the runnable
    candidates (default `options.methods`; Method III left out where `_no_lobe`)."""
    available = [k for k in METHODS if k in (available if available is not None else options.methods)
                 and not (k == "photon" and _no_lobe(measures))]
    model = options.model
    parts = predict_parts(measures, model, available)
    errors = {k: {q: np.hypot(*v[q]) for q in v} for k, v in parts.items()}
    n = scan.n_points
    needs = ~_meets(parts, available, options.target_error, options.tolerance, model)["local"]
    adjacency = vertex_adjacency(scan.faces, n)

    def components(mask):
        sub = adjacency[mask][:, mask]
        _, labels = connected_components(sub, directed=False)
        out = np.full(n, -1)
        out[mask] = labels
        return out

    seeds = np.zeros(n, bool)
    labels = components(needs)
    if needs.any():
        sizes = np.bincount(labels[needs])
        seeds = needs & (sizes[np.maximum(labels, 0)] >= options.min_region)
    grown = seeds.copy()
    step = adjacency + sp.identity(n, format="csr")
    for _ in range(options.rings):
        grown = (step @ grown.astype(np.float64)) > 0
    labels = components(grown)

    method = np.zeros(n, np.int64)
    regions, wanted, cores = [], [], []
    for r in range(labels.max() + 1):
        pts = labels == r
        core = pts & seeds  # the ring is a margin, not evidence: decide on the points that needed it
        ok = _meets(parts, available, options.target_error, options.tolerance, model,
                    reduce=lambda e, core=core: _median(e[core]))
        choice = next((k for k in available if ok[k]), None)
        if choice is None:  # every candidate's inflated bias is beaten: the least short, then the cheapest
            choice = min(available, key=lambda k, core=core: _shortfall(parts, available, k, core, options))
        wanted.append(choice)
        cores.append(core)
        regions.append({
            "region": r, "points": int(pts.sum()), "seed_points": int((pts & seeds).sum()),
            "needed": choice,
            "predicted": {k: {q: _median(errors[k][q][core]) for q in ("pd", "ps")} for k in available},
            "pessimistic_pd": {k: max(_median(_pessimistic(parts, k, o, "pd", model)[core]) for o in available)
                               for k in available},
            "statistics": {name: float(np.median(getattr(measures, name)[core]))
                           for name in ("mass", "gain_diffuse", "gain_specular")},
        })
    run = max(wanted, key=METHODS.index) if wanted else None
    if run == "local":
        run = None
    for reg, choice, core in zip(regions, wanted, cores):
        # The most capable method any region needs runs anyway: a region that would make do with
        # less (not Method I) takes its result where its pd is predicted no worse (within the
        # tolerance); otherwise its own method runs as well.
        no_worse = run is not None and (_median(errors[run]["pd"][core])
                                        <= (1.0 + options.tolerance) * _median(errors[choice]["pd"][core]))
        used = run if choice != "local" and no_worse else choice
        reg["method"] = used
        method[labels == reg["region"]] = METHODS.index(used)
    runs = tuple(k for k in METHODS[1:] if np.any(method == METHODS.index(k)))
    extended = np.zeros(n, bool)
    for k in runs:  # cheapest first: a point predicted to gain from both takes the more capable
        more = _extension(scan, errors, k, method, options)
        method[more] = METHODS.index(k)
        extended |= more
    if "photon" in runs and getattr(measures.local, "specular_identifiable", None) is not None:
        # Method III runs on the whole object: at the points left to Method I that have a lobe of
        # their own its pd is taken too. Method I fits pd there jointly with a lobe its noise leaves
        # loose; Method III refits the lobes and polishes pd at them with the interreflected light
        # removed (measurements: benchmarks/RESULTS_notes.md)
        lobed = (method == 0) & np.asarray(measures.local.specular_identifiable, bool)
        method[lobed] = METHODS.index("photon")
        extended |= lobed
    # ps and roughness: Method III's at every point where it runs (it refits every lobe with the
    # interreflected light removed, and the fill spreads those lobes, not Method I's); Method I's
    # elsewhere (Method II's ps is no better where it runs: module docstring)
    ps_method = np.full(n, METHODS.index("photon") if "photon" in runs else 0, np.int64)

    def plan_errors(q, which):
        return _median(np.choose(which, [errors.get(k, {q: np.zeros(n)})[q] for k in METHODS]))

    predicted = {k: {q: _median(errors[k][q]) for q in ("pd", "ps")} for k in available}
    predicted["plan"] = {"pd": plan_errors("pd", method), "ps": plan_errors("ps", ps_method)}
    return Plan(method, run, regions, needs, predicted, extended, runs, ps_method)


def _configs_made(scan, points, options: AutoOptions):
    """`(N,)` points all of whose Method II light configurations the observations of `points`
    `(N,)` already make; None where every configuration is made anyway (fixed lights)."""
    light_pos = getattr(scan, "light_pos", None)
    if light_pos is None or np.ndim(light_pos) != 3:
        return None
    from .radiosity import light_configs

    index = light_configs(light_pos, scan.n_points, options.radiosity.light_bin).index
    made = np.zeros(index.max() + 1, bool)
    made[index[points]] = True
    return made[index].all(axis=1)


def _extension(scan, errors: dict, run: str, method, options: AutoOptions) -> np.ndarray:
    """`(N,)` points outside the regions that take the global method `run` too: those where it
    is predicted to beat Method I in pd (nominal errors: the method's result is at hand) and
    that add nothing to its cost. Method III runs on the whole object anyway; Method II makes
    one light configuration per rack light and head position bin, so with per-point lights
    only points whose configurations the regions use already come for free."""
    better = (errors[run]["pd"] < errors["local"]["pd"]) & (method == 0)
    if run != "radiosity" or not better.any():
        return better
    free = _configs_made(scan, method == METHODS.index("radiosity"), options)
    return better if free is None else better & free


# -- running it ------------------------------------------------------------------------------


_UNEXPLAINED = 2.0  # residual variance over the noise at which the light left unexplained equals the noise


def _unexplained(measures: Measures, radiosity: Estimate | None) -> dict | None:
    """How much of the regions' images Method II leaves unexplained: the median residual
    variance of its last Method I fit over the regions' points (`meta['residual_scale']`)
    over the noise, the smaller of Method I's and Method II's scan-wide medians (each
    point's residual variance is at least its fit's median; where most points fit, that is
    the noise). None where Method II did not run or reports none."""
    if radiosity is None:
        return None
    scales = radiosity.meta.get("residual_scale", {})
    region = scales.get("region_median")
    noise = [v for v in (scales.get("median"), measures.local.meta.get("residual_scale", {}).get("median"))
             if v is not None and v > 0]
    if region is None or not noise:
        return None
    return {"region_residual": region, "noise": min(noise), "ratio": region / min(noise), "limit": _UNEXPLAINED}


def _escalate(p: Plan) -> Plan:
    """`p` with Method III in place of Method II at every point (and region) Method II was to give
    (`predicted` stays the model's prediction of the plan before)."""
    method = np.where(p.method == METHODS.index("radiosity"), METHODS.index("photon"), p.method)
    runs = tuple(k for k in p.runs if k != "radiosity") + ("photon",)
    regions = [dict(r, method="photon", escalated=True) if r.get("method") == "radiosity" else r for r in p.regions]
    return dataclasses.replace(p, method=method, run="photon", runs=runs, regions=regions)


def _photon_sources(p: Plan, local: Estimate, photon: Estimate) -> Plan:
    """Where Method III's estimate replaces Method I's once both are at hand. pd: at the points
    the plan gives it (its regions and extensions) and wherever its own standard deviation
    (mean over RGB) is below Method I's. ps and roughness: in the regions (Method II's as well), and outside them
    where Method I's lobe is not measured or pooled (interpolated, unresolved): outside the
    regions the interreflected light is negligible, and a lobe Method I measured there is the
    same light's fit without the photon map's Monte Carlo error."""
    photon_i = METHODS.index("photon")
    region = (p.method > 0) & ~(p.extended if p.extended is not None else False)  # Method II's too
    tighter = np.nanmean(photon.std_pd, axis=1) < np.nanmean(local.std_pd, axis=1)
    method = np.where(tighter & (p.method == 0), photon_i, p.method)
    own = np.isin(local.status, (MEASURED, POOLED))
    ps_method = np.where(region | ~own, photon_i, 0)
    return dataclasses.replace(p, method=method, ps_method=ps_method.astype(np.int64))


def holdout_check(est: Estimate, fit_scan, test_scan, options: AutoOptions = AutoOptions(),
                  caster: RayCaster | None = None) -> Estimate:
    """auto's held-out check, where lights were held out (`jaxrefl.estimate(..., holdout=...)`):
    `est`, auto's result on `fit_scan`, against each cheaper method alone on the same lights,
    most capable first (Method II's pd with Method I's lobes, as auto uses Method II, where `est`
    models the specular interreflection too; then Method I, `options.local`), every result
    relit under `test_scan`'s held-out lights with its own interreflection model
    (`holdout.held_out_chain`, each relit once). Where the result in hand predicts the held-out images worse
    than the cheaper one's (beyond the held-out noise), the cheaper one takes its place: auto
    never returns a method its own held-out check measures worse than a cheaper one.
    `meta['auto']['holdout_check']` holds every comparison, what was kept and (where replaced)
    the rejected plan's point counts and regions; the returned result's `meta['holdout']` is
    its own held-out error (`evaluate_holdout`). A held-out check on coaxial lights cannot see
    interreflection that every light makes alike (pd absorbs it for all of them): it can veto
    a global method, not ask for one."""
    from ..outputs.holdout import evaluate_holdout, gi_model, held_out_chain

    auto_meta = est.meta.get("auto", {})
    if not auto_meta.get("global_method"):
        return est
    caster = caster or RayCaster(fit_scan.vertices, fit_scan.faces)  # the two scans share the mesh
    local = estimate_local(fit_scan, options.local, caster)  # kept whole where it wins: its std_pd as Method I's
    names, results = [auto_meta.get("choice")], [est]
    if gi_model(est) == "photon" and "radiosity" in options.methods:
        radiosity = _run("radiosity", fit_scan, options, caster)
        everywhere = np.ones(fit_scan.n_points, bool)
        merged = _merge(local, radiosity, everywhere, ~everywhere)
        names.append("radiosity")
        results.append(dataclasses.replace(merged, meta=dict(radiosity.meta)))
    names.append("local")
    results.append(local)
    index, chain = held_out_chain(results, test_scan, caster)  # each result relit once
    comparisons = [{"result": names[i], "against": names[j], **check} for j, (i, check) in enumerate(chain, 1)]
    kept, current = names[index], results[index]
    record = {"kept": kept, "comparisons": comparisons}
    meta = dict(est.meta, auto=dict(auto_meta, holdout_check=record))
    if current is est:
        return dataclasses.replace(est, meta=meta)
    vetoes = [c for c in comparisons if c["worse"]]
    why = "held-out check: " + "; ".join(
        f"{c['result']} predicts the held-out lights worse than {c['against']} alone (squared-error difference "
        f"{c['difference']:.3g} +- {c['se']:.3g} of the mean observed square)" for c in vetoes) + f": {kept}'s result"
    logger.warning(why)
    plan_keys = ("points_by_method", "ps_points_by_method", "regions", "extended_points", "global_methods")
    record["rejected"] = {k: auto_meta[k] for k in plan_keys if k in auto_meta}
    n = fit_scan.n_points
    meta["auto"].update(choice=kept, reason=why, global_method=None if kept == "local" else kept,
                        global_methods=[] if kept == "local" else [kept], points_by_method={kept: n},
                        ps_points_by_method={"local": n}, regions=[], extended_points=0)
    meta["method_warnings"] = list(meta.get("method_warnings", [])) + [why]
    out = dataclasses.replace(current, meta=_jsonable(meta))
    evaluate_holdout(out, test_scan, caster)
    return out


def photon_available(model: str) -> tuple[bool, str]:
    """Whether Method III can run for results in `model`, and why not."""
    if model != "ward":
        return False, "Method III fits the Ward model (use --model ward)"
    try:
        # import_module, not `from . import`: the latter finds an already imported
        # submodule on the package even when sys.modules says it is unavailable
        importlib.import_module(f"{__package__}.inverse_photon")
    except ImportError as exc:
        return False, f"Method III is not installed ({exc})"
    return True, ""


def _run(method: str, scan, options: AutoOptions, caster, points=None) -> Estimate:
    """Run `method`; Method II only for `points` (its cost shrinks with the regions)."""
    if method == "radiosity":
        outer = min(options.radiosity.outer, options.radiosity_outer)
        return estimate_radiosity(scan, dataclasses.replace(options.radiosity, local=options.local, outer=outer),
                                  caster, points=points)
    if method == "photon":
        from .inverse_photon import PhotonOptions, estimate_photon

        return estimate_photon(scan, PhotonOptions(**{"local": options.local, **options.photon}), caster)
    raise ValueError(f"method: unknown {method!r}")


_PD_FIELDS = ("pd", "std_pd", "pd_measured")
# Status codes (`jaxrefl.methods.local.STATUS_NAMES`) from most to least certain: measured, pooled,
# interpolated, unresolved (the codes' own order puts pooled, 3, last).
_STATUS_RANK = np.zeros(4, np.int8)
_STATUS_RANK[[MEASURED, POOLED, INTERPOLATED, UNRESOLVED]] = np.arange(4)
_PS_FIELDS = ("ps", "roughness", "std_ps", "std_roughness", "specular_identifiable")


def _merge(est: Estimate, other: Estimate, pd_from: np.ndarray, ps_from: np.ndarray) -> Estimate:
    """`est` with `other`'s pd (and its std, `pd_measured`) at `pd_from` `(N,)` and its ps and
    roughness (their stds, `specular_identifiable`) at `ps_from`; `status` the less certain of
    the two sources'."""
    if not (pd_from.any() or ps_from.any()):
        return dataclasses.replace(est, meta=dict(est.meta))

    def pick(field, mask):
        a, b = getattr(est, field), getattr(other, field)
        return np.where(mask.reshape((-1,) + (1,) * (np.ndim(a) - 1)), b, a)

    out = {f: pick(f, pd_from) for f in _PD_FIELDS} | {f: pick(f, ps_from) for f in _PS_FIELDS}
    a, b = pick("status", pd_from), pick("status", ps_from)
    less_certain = np.where(_STATUS_RANK[b] > _STATUS_RANK[a], b, a)
    out["status"] = np.where(pd_from | ps_from, less_certain, est.status).astype(est.status.dtype)
    return dataclasses.replace(est, **out, meta=dict(est.meta))


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


def estimate_auto(scan, options: AutoOptions = AutoOptions(), caster: RayCaster | None = None) -> Estimate:
    """Measure, plan, run the global method the plan needs and merge (module docstring).

    **Returns:** `Estimate` in `options.local.model` with `meta['method'] == 'auto'`
    and `meta['auto']`: target, the choice and why, measured statistics, predicted
    errors (per method and of the plan, scene medians), regions, candidates left
    out and why, and the meta of every method run (`meta['runs']`).
    """
    scan, top = checks.method_input(scan)  # top: called by the user, not by another method
    t_start = time.perf_counter()
    caster = caster or RayCaster(scan.vertices, scan.faces)
    measures = measure(scan, options, caster)
    seconds = dict(measures.seconds)

    t0 = time.perf_counter()
    available, unavailable = [], {}
    for k in options.methods:
        ok, why = photon_available(options.local.model) if k == "photon" else (True, "")
        if ok and k == "photon" and _no_lobe(measures):
            ok, why = False, _NO_LOBE
        (available.append(k) if ok else unavailable.__setitem__(k, why))
    p = plan(scan, measures, options, available)
    seconds["plan"] = time.perf_counter() - t0

    others = {}
    for k in p.runs:
        t0 = time.perf_counter()
        others[k] = _run(k, scan, options, caster, points=p.method == METHODS.index(k))
        seconds[k] = time.perf_counter() - t0
    escalation = _unexplained(measures, others.get("radiosity"))
    if escalation is not None:
        escalation["escalated"] = bool(escalation["ratio"] >= _UNEXPLAINED and "photon" in available
                                       and "photon" not in others)
        if escalation["escalated"]:
            # The diffuse interreflection does not explain the regions' images: what is left (the
            # light specular lobes interreflect) is as large as the noise. Method III models it.
            t0 = time.perf_counter()
            others["photon"] = _run("photon", scan, options, caster)
            seconds["photon"] = time.perf_counter() - t0
            p = _escalate(p)
    t0 = time.perf_counter()
    local = measures.local
    if options.local.prior and not options.local.paper and (p.ps_method is None or np.any(p.ps_method == 0)
                                                            or "photon" in others):
        # Where Method I's lobes are kept, keep them as Method I gives them: with the shared prior.
        local = estimate_local(scan, dataclasses.replace(options.local, interreflection_rays=0), caster,
                               rows=measures.rows)
        seconds["local_prior"] = time.perf_counter() - t0
        t0 = time.perf_counter()
    if "photon" in others:
        p = _photon_sources(p, local, others["photon"])
    # Where pd stays Method I's, its std holds the interreflected light Method I leaves in it, as a
    # Method I run reports it, from the ratios measured above (Method II's form factors).
    std_pd, local_ir, _ = pd_sd_with_interreflection(scan, local, measures.rows, options.radiosity.rays, caster,
                                                     share=measures.gain_diffuse + measures.gain_specular)
    est = dataclasses.replace(local, std_pd=std_pd, meta=dict(local.meta))
    for k, other in others.items():
        est = _merge(est, other, p.method == METHODS.index(k), p.ps_method == METHODS.index(k))
    seconds["merge"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_start

    counts = {k: int(np.sum(p.method == i)) for i, k in enumerate(METHODS) if np.any(p.method == i)}
    t, tol = options.target_error, options.tolerance
    good = (f"within the target {t:g} or, its interreflection bias inflated by the model's uncertainty, within "
            f"{tol:.0%} of the best method's predicted error")
    if p.run is None:
        choice = "local"
        if not p.needs_global.any():
            reason = f"Method I's predicted error is {good} at every point"
        else:
            reason = (f"Method I's predicted error is not {good} at {int(p.needs_global.sum())} point(s), in no "
                      f"region of {options.min_region} or more points whose median needs a global method")
    else:
        choice = "+".join(k for k in METHODS if counts.get(k, 0) > 0)
        reason = (f"{len(p.regions)} region(s), {int(np.count_nonzero(p.method))} of {scan.n_points} points, where "
                  f"Method I's predicted error is not {good}; {' / '.join(p.runs)}: the cheapest method that is "
                  "there")
        short = [r for r in p.regions if r["method"] != "local" and r["needed"] == p.run
                 and r["pessimistic_pd"][p.run] > max(t, (1.0 + tol) * min(v["pd"] for v in r["predicted"].values()))]
        if short:
            reason += f" (in {len(short)} of them none is: {p.run} is the least short)"
        if escalation is not None and escalation["escalated"]:
            reason += (f"; Method II left {escalation['ratio']:.3g} times the noise's variance unexplained in them "
                       f"(limit {_UNEXPLAINED:g}): Method III instead")
        if "photon" in p.runs:
            reason += ("; ps and roughness from Method III in the regions and where Method I's lobe is not "
                       "measured or pooled, pd also where Method III's is the tighter")
    notes = []
    for k, why in unavailable.items():
        notes.append(f"{k} not available: {why}")
    best_unavailable = {}
    if unavailable:  # would a missing method have done better? (its prediction, for the report)
        errs = predict(measures, options.model, tuple(unavailable))
        best_unavailable = {k: {q: _median(v[q]) for q in ("pd", "ps")} for k, v in errs.items()}
    auto = {
        "target_error": options.target_error, "tolerance": options.tolerance,
        "choice": choice, "reason": reason, "global_method": p.run, "global_methods": list(p.runs),
        "points_by_method": counts,
        "ps_points_by_method": {k: int(np.sum(p.ps_method == i)) for i, k in enumerate(METHODS)
                                if np.any(p.ps_method == i)},
        "candidates": available, "unavailable": unavailable, "notes": notes, "unexplained": escalation,
        "statistics": measures.statistics(),
        "predicted": p.predicted, "predicted_unavailable": best_unavailable,
        "needs_global_points": int(p.needs_global.sum()),
        "extended_points": int(p.extended.sum()) if p.extended is not None else 0,
        "regions": p.regions, "rings": options.rings, "min_region": options.min_region,
        "error_model": asdict(options.model),
        "form_factors": {"rays": measures.ff.rays, "nonzeros": int(len(measures.ff.values)),
                         "mean_row_sum": float(measures.mass.mean())},
    }
    runs = {"local": local.meta, **{k: other.meta for k, other in others.items()}}
    est = dataclasses.replace(est, meta=_jsonable({
        "method": "auto", "model": options.local.model, "auto": auto, "seconds": seconds, "runs": runs,
        "options": {"target_error": options.target_error, "tolerance": options.tolerance, "rings": options.rings,
                    "min_region": options.min_region, "methods": list(options.methods),
                    "photon": dict(options.photon)},
        "points_with_observations": measures.local.meta.get("points_with_observations"),
        "observation_checks": scan.meta["observation_checks"],
        "interreflection": local_ir,  # Method I's, over every observed point; its pd's std where kept
    }))
    if top:
        checks.estimate_warnings(est, logger)
    return est
