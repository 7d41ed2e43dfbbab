"""Held-out-light validation: fit without some lights, relight under them, compare.

The lights of a scan are split in two (`choose_holdout`, `split_scan`): the
estimate is fitted on the rest and then relit under the held-out lights, seen
from their cameras (`relight.direct_radiance` with Embree shadows, plus
`relight.indirect_observations` for Methods II and III: all held-out observations'
interreflection at once, with the settings the estimate was fitted with), and compared with the radiance the
camera recorded there (`holdout_error`). On photographs this is the accuracy
figure a user has; on a scan with ground truth, `truth_holdout_error` gives the
same figure for the true reflectance: the floor that the data's noise (and the
forward model) allows.

Samples compared: observed (`Scan.observed()`: valid and not saturated), the
camera and the light above the surface, the camera's line of sight and the
light's unblocked (`classify.classify`'s `measurable`).

Metrics over those samples, `pred` and `obs` `(S, 3)` linear RGB [W/(sr m^2)]:
`rel_rms = sqrt(sum (pred - obs)^2 / sum obs^2)` (over samples and channels);
`median_rel` the median of `|pred - obs| / max(obs, floor)` on the RGB mean, with
`floor` 1 % of the 99th percentile of the observed RGB mean.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..geometry.raycast import RayCaster
from . import relight as rl

__all__ = ["choose_holdout", "split_scan", "gi_model", "relight_settings", "holdout_error", "truth_holdout_error",
           "evaluate_holdout", "estimate_with_holdout", "paired_holdout", "held_out_chain"]


def choose_holdout(n_lights: int, fraction: float | None = None, lights=None, seed: int = 0) -> np.ndarray:
    """Sorted indices `(H,)` int64 of the observations (lights) to hold out.

    Exactly one of `fraction` (share of the `n_lights` lights in (0, 1), drawn at
    random with `seed`; at least 1 held out, at least 2 left to fit) or `lights`
    (explicit indices, unique, in range, at least 2 left) is given. Raises
    `ValueError` naming `holdout` or `holdout-lights`.
    """
    n_lights = int(n_lights)
    if (fraction is None) == (lights is None):
        raise ValueError("holdout: give exactly one of a fraction (--holdout) and light indices (--holdout-lights)")
    if fraction is not None:
        f = float(fraction)
        if not 0.0 < f < 1.0:
            raise ValueError(f"holdout: the fraction of lights held out must lie in (0, 1), got {fraction}")
        k = max(1, int(round(f * n_lights)))
        if n_lights - k < 2:
            raise ValueError(f"holdout: holding out {k} of the scan's {n_lights} lights leaves {n_lights - k} to fit, "
                             "need at least 2")
        rng = np.random.default_rng(int(seed))
        return np.sort(rng.choice(n_lights, size=k, replace=False)).astype(np.int64)
    raw = np.asarray(lights).ravel()
    if raw.size == 0:
        raise ValueError("holdout-lights: no light index given")
    if raw.dtype.kind not in "iu" and not (raw.dtype.kind == "f" and np.all(np.isfinite(raw))
                                           and np.all(raw == np.round(raw))):
        raise ValueError(f"holdout-lights: must be integer light indices, got {raw.tolist()}")
    idx = raw.astype(np.int64)
    bad = idx[(idx < 0) | (idx >= n_lights)]
    if bad.size:
        raise ValueError(f"holdout-lights: index {int(bad[0])} is out of range, the scan has lights 0-{n_lights - 1}")
    if len(np.unique(idx)) != len(idx):
        dup = [int(v) for v in np.unique(idx) if np.count_nonzero(idx == v) > 1]
        raise ValueError(f"holdout-lights: repeated index {dup[0]}")
    if n_lights - len(idx) < 2:
        raise ValueError(f"holdout-lights: holding out {len(idx)} of the scan's {n_lights} lights leaves "
                         f"{n_lights - len(idx)} to fit, need at least 2")
    return np.sort(idx)


def _take(value, keep, n, m):
    """`value` restricted to the observations `keep` where its shape is per observation."""
    if value is None:
        return None
    a = np.asarray(value)
    if a.ndim == 3 and a.shape[:2] == (n, m):
        return a[:, keep]
    if a.ndim == 2 and a.shape == (n, m):
        return a[:, keep]
    if a.ndim == 2 and a.shape == (m, 3):
        return a[keep]
    if a.ndim == 1 and a.shape == (m,):
        return a[keep]
    return value  # (3,), (N, 1, 3), scalars: shared by every observation


def _sub_scan(scan, keep, role, held, fit):
    n, m = scan.n_points, scan.n_lights
    keep = np.asarray(keep, dtype=np.int64)
    meta = dict(scan.meta)
    for key in ("light_indices",):  # per-observation lists written by data_synth
        if isinstance(meta.get(key), list) and len(meta[key]) == m:
            meta[key] = [meta[key][i] for i in keep]
    rig = meta.get("rig")
    if isinstance(rig, dict) and isinstance(rig.get("rack"), list) and len(rig["rack"]) == m:
        meta["rig"] = dict(rig, rack=[rig["rack"][i] for i in keep])
    meta["holdout"] = {"role": role, "lights": [int(i) for i in keep], "held_out_lights": [int(i) for i in held],
                       "fit_lights": [int(i) for i in fit]}
    intensity = scan.light_intensity
    if np.ndim(intensity) == 1:
        intensity = np.asarray(intensity)[keep]
    return dataclasses.replace(
        scan, light_pos=scan.light_pos[..., keep, :], light_intensity=intensity,
        cam_pos=_take(scan.cam_pos, keep, n, m), radiance=_take(scan.radiance, keep, n, m),
        valid=_take(scan.valid, keep, n, m), meta=meta)


def split_scan(scan, held):
    """`(fit_scan, test_scan)`: `scan` without and with only the observations `held`
    `(H,)` (indices into its `M` lights). Per-observation fields are sliced
    (`light_pos` `(M, 3)` / `(N, M, 3)`, `cam_pos` `(M, 3)` / `(N, M, 3)`,
    `light_intensity` `(M,)`, `radiance` `(N, M, 3)`, `valid` `(N, M)`); shared ones
    (`cam_pos` `(3,)` / `(N, 1, 3)`, scalar intensity), mesh, truth and meta are kept.
    Each sub-scan's `meta['holdout']` records its `lights` (indices into `scan`)."""
    m = scan.n_lights
    held = np.asarray(held, dtype=np.int64).ravel()
    if held.size == 0 or held.min() < 0 or held.max() >= m or len(np.unique(held)) != len(held):
        raise ValueError(f"holdout-lights: must be distinct indices in [0, {m - 1}], got {held.tolist()}")
    keep = np.setdiff1d(np.arange(m), held)
    if keep.size == 0:
        raise ValueError("holdout-lights: every light is held out, none is left to fit")
    held = np.sort(held)
    return _sub_scan(scan, keep, "fit", held, keep), _sub_scan(scan, held, "test", held, keep)


def gi_model(est) -> str:
    """The interreflection model of `est`'s method, for relighting it: 'none'
    (Method I), 'radiosity' (Method II), 'photon' (Method III, Ward results); for
    `auto`, the global method it ran."""
    method = est.meta.get("method")
    if method == "auto":
        runs = est.meta.get("auto", {}).get("global_methods") or []
        method = "photon" if "photon" in runs else "radiosity" if "radiosity" in runs else "local"
    if method == "photon" and est.model == "ward":
        return "photon"
    if method in ("radiosity", "photon"):
        return "radiosity"
    return "none"


#: Relighting settings read from a result's `meta['options']` (Method II's or III's), by the
#: keyword `relight.indirect_observations` passes on.
_SETTINGS = {"radiosity": {"light_bin": "light_bin", "rays": "rays"},
             "photon": {"light_bin": "light_bin", "photons": "n_photons", "target_photons": "target_photons",
                        "gather_rays": "rays", "gather_budget": "ray_budget", "seed": "seed"}}


def relight_settings(est, gi) -> dict:
    """The interreflection settings `est` was fitted with (its `meta['options']`), for
    relighting it under `gi` as its method modelled its own observations (the
    defaults where it holds none, e.g. a truth or an `auto` result)."""
    options = est.meta.get("options") if isinstance(est.meta, dict) else None
    options = options if isinstance(options, dict) else {}
    if est.meta.get("method") not in ("radiosity", "photon"):
        options = {k: v for k, v in options.items() if k == "light_bin"}
    return {arg: options[key] for key, arg in _SETTINGS.get(gi, {}).items() if options.get(key) is not None}


def _predict(est, scan, caster, gi, use, settings):
    """Predicted radiance `(N, H, 3)` of `est` for every observation of `scan`; the
    interreflection of the `use` `(N, H)` observations from one `relight.indirect_observations`."""
    n, m = scan.n_points, scan.n_lights
    y = scan.intensities()
    per_point_light, per_obs_cam = scan.light_pos.ndim == 3, scan.cam_pos.ndim != 1
    cams = scan.camera_positions()
    out = np.zeros((n, m, 3))
    for j in range(m):  # a loop over held-out lights (tens), each over all points
        light = scan.light_pos[:, j] if per_point_light else scan.light_pos[j]
        cam = np.ascontiguousarray(cams[:, j]) if per_obs_cam else scan.cam_pos
        out[:, j] = rl.direct_radiance(scan.vertices, scan.normals, est, light, y[j], cam, caster)
    if gi != "none":
        out += rl.indirect_observations(gi, scan, est, use, caster, settings)
    return out


def _empty(lights, gi, reason):
    return {"lights": lights, "gi": gi, "rel_rms": None, "median_rel": None, "samples": 0,
            "per_light_rel_rms": [None] * len(lights), "per_light_samples": [0] * len(lights), "reason": reason}


def _usable(test_scan, caster) -> np.ndarray:
    """`(N, H)` bool: the held-out samples compared (module docstring)."""
    from ..reflectance.classify import classify

    return classify(test_scan.vertices, test_scan.normals, test_scan.cam_pos, test_scan.light_pos, caster,
                    observed=test_scan.observed()).measurable


def _relit(est, test_scan, caster, gi, use, settings):
    """`(pred (N, H, 3), gi, note)`: `est` relit under `gi` (its settings where `settings` is
    None); direct light only, said in `note`, where the interreflection module is missing."""
    settings = relight_settings(est, gi) if settings is None else settings
    try:
        return _predict(est, test_scan, caster, gi, use, settings), gi, None
    except ImportError as exc:
        return (_predict(est, test_scan, caster, "none", use, settings), "none",
                f"{gi} interreflection unavailable ({exc}); direct light only")


def held_out_chain(results, test_scan, caster: RayCaster | None = None) -> tuple[int, list]:
    """The cheapest-not-worse result of `results` on `test_scan`'s held-out samples, each relit
    once, with the interreflection its own method modelled (`gi_model`). `results` run from
    the most capable to the cheapest; starting from the first, each next one takes the place
    of the result in hand where that predicts the samples worse (`paired_holdout`'s test).

    **Returns:** `(kept, comparisons)`: the index kept and, per later result `j`, `(i, check)`
    with `i` the index in hand when `j` was compared and `check` `paired_holdout`'s dict."""
    for e in results:
        if np.shape(e.pd)[0] != test_scan.n_points:
            raise ValueError(f"holdout: a result has {np.shape(e.pd)[0]} points, the scan {test_scan.n_points}")
    none = {"difference": None, "se": None, "worse": False, "samples": 0}
    if test_scan.radiance is None:
        return 0, [(0, dict(none)) for _ in results[1:]]
    caster = caster or RayCaster(test_scan.vertices, test_scan.faces)
    use = _usable(test_scan, caster)
    obs = np.asarray(test_scan.radiance, dtype=np.float64)[use]
    scale = float(np.mean((obs**2).sum(-1))) if use.any() else 0.0
    if use.sum() < 2 or not scale > 0:
        return 0, [(0, dict(none, samples=int(use.sum()))) for _ in results[1:]]
    relit = {}

    def errors(i):  # squared errors (S,), the model used, a fallback note
        if i not in relit:
            pred, gi, note = _relit(results[i], test_scan, caster, gi_model(results[i]), use, None)
            relit[i] = (((pred[use] - obs) ** 2).sum(-1), gi, note)
        return relit[i]

    kept, comparisons = 0, []
    for j in range(1, len(results)):
        (err_a, gi_a, note_a), (err_b, gi_b, note_b) = errors(kept), errors(j)
        d = (err_a - err_b) / scale
        mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))
        check = {"difference": mean, "se": se, "worse": bool(mean > 2.0 * se), "samples": int(use.sum()),
                 "gi": [gi_a, gi_b]}
        if note_a or note_b:
            check["note"] = "; ".join(n for n in (note_a, note_b) if n)
        comparisons.append((kept, check))
        if check["worse"]:
            kept = j
    return kept, comparisons


def paired_holdout(est, other, test_scan, caster: RayCaster | None = None) -> dict:
    """`est` against `other` on the same held-out samples, each relit with the interreflection
    its own method modelled (`gi_model`): per sample the difference of their squared errors
    (summed over RGB), its mean and standard error over the samples, both over the mean
    observed square (`difference`, `se`: 0 where both predict alike), and `worse`: `est`'s
    error above `other`'s by more than two standard errors (not a fluctuation of the held-out
    noise). JSON-ready; `samples` 0 or 1 and `worse` False where nothing can be compared;
    `gi` the models used (`note` where one fell back to direct light). A photon-mapped
    relighting adds its own Monte Carlo error to its side, shared by the samples of one map,
    which the standard error does not count: the check leans, slightly, against Method III."""
    return held_out_chain([est, other], test_scan, caster)[1][0][1]


def holdout_error(est, test_scan, caster: RayCaster | None = None, gi: str = "auto",
                  settings: dict | None = None) -> dict:
    """Error of `est` relit under the observations of `test_scan` against their radiance.

    **Arguments:** `est` an `Estimate` of `test_scan`'s mesh; `test_scan` a scan with
    radiance (usually `split_scan(...)[1]`); `caster` its `RayCaster`; `gi` one of
    `relight.GI_MODELS` or 'auto' (`gi_model(est)`: interreflections as the method
    modelled them); `settings` the interreflection's (`relight_settings(est, gi)` when None).

    **Returns:** a JSON-ready dict: `lights` (indices into the original scan),
    `gi`, `rel_rms`, `median_rel` (module docstring), `samples`,
    `per_light_rel_rms` and `per_light_samples` (one per light). Never NaN: with
    no usable sample `rel_rms` and `median_rel` are None and `reason` says why.
    """
    if np.shape(est.pd)[0] != test_scan.n_points:
        raise ValueError(f"holdout: the result has {np.shape(est.pd)[0]} points, the scan {test_scan.n_points}")
    lights = [int(i) for i in test_scan.meta.get("holdout", {}).get("lights", range(test_scan.n_lights))]
    gi = gi_model(est) if gi == "auto" else gi
    if gi not in rl.GI_MODELS:
        raise ValueError(f"model-gi: must be 'auto' or one of {', '.join(rl.GI_MODELS)}, got {gi!r}")
    if test_scan.radiance is None:
        return _empty(lights, gi, "the held-out observations have no radiance")
    caster = caster or RayCaster(test_scan.vertices, test_scan.faces)
    use = _usable(test_scan, caster)
    if not use.any():
        return _empty(lights, gi, "no held-out sample is observed (valid, unsaturated), lit and seen by its camera")
    pred, gi, note = _relit(est, test_scan, caster, gi, use, settings)
    obs = np.asarray(test_scan.radiance, dtype=np.float64)
    d2 = np.where(use[..., None], (pred - obs) ** 2, 0.0).sum(axis=-1)    # (N, H)
    o2 = np.where(use[..., None], obs**2, 0.0).sum(axis=-1)
    total = float(o2.sum())
    if not total > 0:
        return _empty(lights, gi, "the observed radiance of every usable held-out sample is 0")
    lum_o, lum_p = obs[use].mean(axis=-1), pred[use].mean(axis=-1)
    floor = max(0.01 * float(np.percentile(lum_o, 99)), 1e-300)
    rel = np.abs(lum_p - lum_o) / np.maximum(lum_o, floor)
    count = use.sum(axis=0)
    per_o2 = o2.sum(axis=0)
    per_light = [float(np.sqrt(a / b)) if c > 0 and b > 0 else None
                 for a, b, c in zip(d2.sum(axis=0), per_o2, count)]
    out = {"lights": lights, "gi": gi, "rel_rms": float(np.sqrt(d2.sum() / total)),
           "median_rel": float(np.median(rel)), "samples": int(use.sum()),
           "per_light_rel_rms": per_light, "per_light_samples": [int(c) for c in count]}
    if note:
        out["note"] = note
    return out


def truth_holdout_error(test_scan, caster: RayCaster | None = None, gi: str = "none",
                        settings: dict | None = None) -> dict:
    """`holdout_error` of the scan's own ground truth (`relight.truth_estimate`):
    the error floor its noise and the forward model `gi` (with `settings`) allow. Without truth (or
    when `gi` cannot relight the truth's model) `rel_rms` is None and `reason` says why."""
    try:
        truth = rl.truth_estimate(test_scan)
    except ValueError as exc:
        lights = [int(i) for i in test_scan.meta.get("holdout", {}).get("lights", range(test_scan.n_lights))]
        return _empty(lights, gi, str(exc))
    try:
        return holdout_error(truth, test_scan, caster, gi, settings)
    except ValueError as exc:  # e.g. photon relighting of a Torrance-Sparrow truth
        lights = [int(i) for i in test_scan.meta.get("holdout", {}).get("lights", range(test_scan.n_lights))]
        return _empty(lights, gi, str(exc))


def evaluate_holdout(est, test_scan, caster: RayCaster | None = None, gi: str = "auto", truth: bool = True) -> dict:
    """`holdout_error(est, test_scan, caster, gi)` stored in `est.meta['holdout']` (and
    returned), with the fitted lights (`fit_lights`, from `split_scan`) and, with `truth`
    and ground truth in the scan, the floor `truth_holdout_error` under `['truth']` (relit
    with `est`'s interreflection settings)."""
    t0 = time.perf_counter()
    caster = caster or RayCaster(test_scan.vertices, test_scan.faces)
    result = holdout_error(est, test_scan, caster, gi)
    fit_lights = test_scan.meta.get("holdout", {}).get("fit_lights")
    if fit_lights is not None:
        result["fit_lights"] = fit_lights
    if truth and test_scan.true_pd is not None:
        floor = truth_holdout_error(test_scan, caster, result["gi"], relight_settings(est, result["gi"]))
        result["truth"] = {k: v for k, v in floor.items() if k != "lights"}
    est.meta["holdout"] = result
    seconds = est.meta.get("seconds")
    if isinstance(seconds, dict):
        seconds["holdout"] = time.perf_counter() - t0
    return result


def estimate_with_holdout(scan, estimator, held, gi: str = "auto", truth: bool = True,
                          caster: RayCaster | None = None):
    """Fit `estimator(fit_scan) -> Estimate` without the lights `held` `(H,)` (indices
    into `scan`'s lights, e.g. from `choose_holdout`), then `evaluate_holdout` on them:
    the error lands in `est.meta['holdout']`.

    **Returns:** `(est, fit_scan, test_scan)`.
    """
    fit_scan, test_scan = split_scan(scan, held)
    est = estimator(fit_scan)
    evaluate_holdout(est, test_scan, caster, gi, truth)
    return est, fit_scan, test_scan
