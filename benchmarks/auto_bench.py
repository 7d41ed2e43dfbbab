"""`--method auto` against Methods I-III on Objects A-E (and V): errors, times, choices.

    python3 -m benchmarks.auto_bench            # full run -> benchmarks/RESULTS_auto.md
    python3 -m benchmarks.auto_bench --quick    # smoke run (smaller meshes, fewer scenes)
    python3 -m benchmarks.auto_bench --calibrate  # also fit the error model (auto.ErrorModel)

Scenes are rendered with global illumination by the independent path tracer
(`data_synth`), 1 % noise, 12 bits with the sensor's full scale at the 99.9th
percentile of the rendered radiance (a path-traced firefly must not set the
exposure). Objects A-D and V on the paper's scanner under their selected lights
(§2.2); Object E on the fixed camera, tilted as in the paper so that its
highlights are observable, in the 'diffuse' and 'glossy' set-ups (glossy twice:
Torrance-Sparrow, where Method III is no candidate, and Ward, where it is).

Timing: every method first runs once (compilation included, reported
separately), then `--repeats` times warm; the median warm wall time is
reported. Form factors are cast afresh in every timed run (memory cache
cleared, disk cache in a temporary folder), so Method II and `auto` both pay
for them; inside one `auto` run Method II reads them from the cache.
Errors: medians over all points of the relative pd error (mean over RGB) and,
where the truth is not 0, of the relative ps error (`result.truth_errors`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import platform
import sys
import tempfile
import time

import numpy as np

from data_synth.scans import Sensor, apply_sensor, make_scan
from jaxrefl.capture.select import select_lights
from jaxrefl.geometry import formfactors
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods import auto
from jaxrefl.methods.local import LocalOptions, estimate_local
from jaxrefl.methods.radiosity import RadiosityOptions, estimate_radiosity
from jaxrefl.reflectance.classify import classify_scan
from jaxrefl.result import truth_errors
from jaxrefl.scan.io import validate_scan

E_TILT = 25.0  # degrees about x (as the Method III tests): E's highlights land inside the rack's reach


@dataclasses.dataclass(frozen=True)
class Scene:
    label: str
    name: str
    setup: str = "glossy"
    model: str = "ward"
    rig: str | None = None
    samples_factor: int = 1  # E's fold needs more paths per observation for the same noise


SCENES = (
    Scene("A", "A"), Scene("B", "B"), Scene("C", "C"), Scene("D", "D"), Scene("V (convex)", "V"),
    Scene("E diffuse", "E", "diffuse", samples_factor=4),
    Scene("E glossy", "E", "glossy", samples_factor=4),
    Scene("E diffuse (TS)", "E", "diffuse", model="torrance-sparrow", samples_factor=4),
    Scene("E glossy (TS)", "E", "glossy", model="torrance-sparrow", samples_factor=4),
)
QUICK = ("A", "V (convex)", "E diffuse", "E glossy")


def make_scene(scene: Scene, resolution: int, samples: int, seed: int = 0, tilt: float = E_TILT):
    """A path-traced scan of `scene` under its selected lights (E tilted by `tilt` degrees
    about x); returns (scan, lights)."""
    kw = dict(resolution=resolution, setup=scene.setup, rig=scene.rig, model=scene.model)
    if scene.name == "E":
        kw["tilt_deg"] = (float(tilt), 0.0)
    geometry, _ = make_scan(scene.name, **kw)
    m = classify_scan(geometry, use_observations=False)
    lights = select_lights(m.diffuse_only, m.strong_specular, m.seen, weights=m.pixel_weight).selected
    clean, _ = make_scan(scene.name, lights=lights, global_illumination=True, samples=samples * scene.samples_factor,
                         seed=seed, **kw)
    full = float(np.percentile(clean.radiance[clean.valid], 99.9))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 2]))
    noisy, saturation = apply_sensor(clean.radiance.astype(np.float64), clean.valid,
                                     Sensor(noise=0.01, bits=12, full_scale=full), rng)
    noisy = np.where(clean.valid[..., None], noisy, 0.0).astype(np.float32)
    scan = validate_scan(dataclasses.replace(clean, radiance=noisy, saturation=saturation))
    return scan, [int(i) for i in lights]


def _fresh_caches(folder):
    formfactors._MEMORY.clear()
    os.environ["JAXREFL_CACHE"] = tempfile.mkdtemp(dir=folder)


def _rel_errors(est, scan):
    """Per-point relative pd error (mean over RGB) and ps error (NaN where the truth is 0)."""
    pd = (np.abs(est.pd - scan.true_pd) / np.maximum(scan.true_pd, 1e-12)).mean(1)
    ps = np.where(scan.true_ps > 1e-9, np.abs(est.ps - scan.true_ps) / np.maximum(scan.true_ps, 1e-12), np.nan)
    return pd, ps


def _medians(est, scan):
    pd, ps = _rel_errors(est, scan)
    return {"pd": float(np.median(pd)), "ps": float(np.nanmedian(ps)) if np.isfinite(ps).any() else None}


def run_scene(scene: Scene, args, tmp) -> dict:
    t0 = time.perf_counter()
    scan, lights = make_scene(scene, args.resolution if scene.name != "E" else args.resolution_e, args.samples,
                              seed=args.seed, tilt=args.tilt)
    row = {"scene": scene.label, "points": scan.n_points, "lights": lights, "model": scene.model,
           "render_s": time.perf_counter() - t0, "methods": {}}
    local_opts = LocalOptions(model=scene.model)
    photon_kw = {"photons": args.photons, "iterations": args.iterations}
    runners = {"local": lambda c: estimate_local(scan, local_opts, c),
               "radiosity": lambda c: estimate_radiosity(scan, RadiosityOptions(local=local_opts), c)}
    have_photon, why = auto.photon_available(scene.model)
    if have_photon and (scene.name in args.photon_objects or "all" in args.photon_objects):
        from jaxrefl.methods.inverse_photon import PhotonOptions, estimate_photon

        runners["photon"] = lambda c: estimate_photon(scan, PhotonOptions(local=local_opts, **photon_kw), c)
    else:
        row["photon_skipped"] = why or "not run on this object (--photon-objects)"
    candidates = tuple(k for k in auto.METHODS if k in runners)
    options = auto.AutoOptions(target_error=args.targets[0], local=local_opts, photon=photon_kw, methods=candidates)
    for target in args.targets:
        opts = dataclasses.replace(options, target_error=target)
        runners[_auto_name(target)] = lambda c, opts=opts: auto.estimate_auto(scan, opts, c)
    per_point = {}
    for name, fn in runners.items():
        _fresh_caches(tmp)
        t = time.perf_counter()
        est = fn(RayCaster(scan.vertices, scan.faces))
        cold = time.perf_counter() - t
        warm = []
        for _ in range(args.repeats):
            _fresh_caches(tmp)
            t = time.perf_counter()
            est = fn(RayCaster(scan.vertices, scan.faces))
            warm.append(time.perf_counter() - t)
        entry = {"first_s": cold, "warm_s": float(np.median(warm)) if warm else None, "errors": _medians(est, scan),
                 "truth_errors": truth_errors(est, scan)}
        entry["seconds"] = est.meta.get("seconds")
        if name.startswith("auto"):
            a = est.meta["auto"]
            entry.update(choice=a["choice"], reason=a["reason"], predicted=a["predicted"],
                         points_by_method=a["points_by_method"], regions=len(a["regions"]),
                         statistics=a["statistics"], unavailable=a["unavailable"], seconds=est.meta["seconds"])
        row["methods"][name] = entry
        per_point[name] = _rel_errors(est, scan)
        print(f"  {scene.label}: {name} first {cold:.1f} s, warm {entry['warm_s']}, errors {entry['errors']}",
              flush=True)
    # Per-point measurements and errors for the calibration of the error model.
    measures = auto.measure(scan, options, RayCaster(scan.vertices, scan.faces))
    row["calibration"] = {
        "features": {k: getattr(measures, k) for k in ("gain_diffuse", "gain_specular", "rel_std_pd", "rel_std_ps")},
        "pd_measured": measures.local.pd_measured, "identifiable": measures.local.specular_identifiable,
        "mass": measures.mass, "local_ps": measures.local.ps, "local_roughness": measures.local.roughness,
        "faces": scan.faces,
        "photon_k": auto.photon_k(scan, photon_kw),
        "errors": {k: v for k, v in per_point.items() if not k.startswith("auto")},
    }
    # The merge against the global method on the whole object, at the same global result.
    row["merge_check"] = _merge_check(row, per_point, scan, options, measures)
    return row


def _auto_name(target) -> str:
    return f"auto {target:g}"


def _merge_check(row, per_point, scan, options, measures):
    """Errors where auto used Method I vs what each global method gives at those points."""
    out = {}
    p = auto.plan(scan, measures, options, list(options.methods))
    local_pts = p.method == 0
    for k in ("local", "radiosity", "photon"):
        if k in per_point and local_pts.any():
            pd, ps = per_point[k]
            out[k] = {"pd_median_where_auto_uses_local": float(np.median(pd[local_pts])),
                      "ps_median_where_auto_uses_local": float(np.nanmedian(ps[local_pts]))
                      if np.isfinite(ps[local_pts]).any() else None}
    out["points_local"] = int(local_pts.sum())
    return out


# -- calibration --------------------------------------------------------------------------------


def _failed(pd_errors) -> bool:
    """A run that returned no albedo at all (median relative pd error ~1: pd 0 nearly
    everywhere) is a failure of that run, not an error level: left out of the fit."""
    return bool(np.median(pd_errors) > 0.95)


def _groups(rows, method, qi, bins):
    """Per scene, equal-count bins of points by `g + s`: (g, s, rel_std, photon k, measured median error)."""
    q = ("pd", "ps")[qi]
    out = []
    for r in rows:
        c = r["calibration"]
        # the measurements come from Method I: a failed Method I run leaves the scene out
        if method not in c["errors"] or _failed(c["errors"][method][0]) or _failed(c["errors"]["local"][0]):
            continue
        f = c["features"]
        err = c["errors"][method][qi]
        x = f["gain_diffuse"] + f["gain_specular"]
        idx = np.flatnonzero(np.isfinite(err))
        idx = idx[np.argsort(x[idx], kind="stable")]
        for chunk in np.array_split(idx, max(1, min(bins, len(idx) // 20))):
            if len(chunk) >= 10:
                out.append((f["gain_diffuse"][chunk], f["gain_specular"][chunk], f[f"rel_std_{q}"][chunk],
                            c["photon_k"], float(np.median(err[chunk]))))
    return out


_WEIGHT_BELOW = 0.02  # bins whose measured error is below this count less (weight error / this)


def _fit(groups, predict_median, start):
    """Log parameters minimising the squared log ratio of predicted to measured bin medians,
    weighted by `min(1, error / 2 %)`: choices are made at errors of a few per cent, and
    below that a bin's error is mostly noise (several starts, Nelder-Mead)."""
    from scipy.optimize import minimize

    def loss(theta):
        return sum(min(1.0, obs / _WEIGHT_BELOW) * (np.log(max(predict_median(np.exp(theta), g, s, n, k), 1e-6))
                                                     - np.log(max(obs, 1e-6))) ** 2
                   for g, s, n, k, obs in groups)

    best = None
    for factor in (1.0, 0.3, 3.0):
        res = minimize(loss, np.log(np.maximum(np.asarray(start) * factor, 1e-3)), method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-8, "maxiter": 4000})
        best = res if best is None or res.fun < best.fun else best
    return np.exp(best.x), float(best.fun)


def calibrate(rows, bins: int = 8, log=None) -> auto.ErrorModel:
    """Fit `ErrorModel` to the measured errors: per quantity, `unknown` = Method I's median
    error where a point has no estimate of its own; Method I's `(a, b)` and the noise scale
    together, then with that scale Method II's `(a, b)` and Method III's `a`, `photon_mc`
    (and its floor, from pd), each minimising the weighted squared log ratio of the
    predicted to the measured median error over bins of points (per scene, equal-count
    bins of `g + s`)."""
    base = auto.ErrorModel()
    values = {"pd": list(base.pd), "ps": list(base.ps)}
    extra = {}
    for qi, q in enumerate(("pd", "ps")):
        unknown = np.concatenate([r["calibration"]["errors"]["local"][qi][~np.isfinite(
            r["calibration"]["features"][f"rel_std_{q}"])] for r in rows
            if not _failed(r["calibration"]["errors"]["local"][0])])
        unknown = unknown[np.isfinite(unknown)]
        extra[f"unknown_{q}"] = round(float(np.median(unknown)), 3) if unknown.size else getattr(base, f"unknown_{q}")

        def noise(n, scale, unknown=extra[f"unknown_{q}"]):
            return np.minimum(np.where(np.isfinite(n), scale * np.where(np.isfinite(n), n, 0), unknown), 1.0)

        scale = None
        for mi, k in enumerate(auto.METHODS):
            groups = _groups(rows, k, qi, bins)
            if not groups:
                continue
            if k == "local":
                def pm(t, g, s, n, pk):
                    return np.median(np.sqrt(noise(n, t[2]) ** 2 + (t[0] * g + t[1] * s) ** 2))

                t, loss = _fit(groups, pm, [0.5, 0.5, 1.0])
                scale = round(float(t[2]), 3)
                extra[f"noise_scale_{q}"] = scale
                values[q][mi] = (round(float(t[0]), 3), round(float(t[1]), 3))
                label = f"a, b = {values[q][mi]}, noise scale {scale}"
            elif k == "radiosity":
                def pm(t, g, s, n, pk):
                    return np.median(np.sqrt(noise(n, scale) ** 2 + (t[0] * g + t[1] * s) ** 2 + t[2] ** 2))

                t, loss = _fit(groups, pm, [0.5, 0.5, 0.003])
                values[q][mi] = (round(float(t[0]), 3), round(float(t[1]), 3))
                extra[f"radiosity_noise_{q}"] = round(float(t[2]), 4)
                label = f"a, b = {values[q][mi]}, noise {extra[f'radiosity_noise_{q}']}"
            else:
                # Method III's Monte Carlo error grows with the interreflected light it estimates and
                # with k (few photons per point), and it refits every point from photon-replayed
                # images: noise ~ spread * k everywhere. It models the light a lobe carries, but
                # whether it removes it is the data's to say: a term in s as for Methods I and II.
                floor = extra.get("photon_noise", 0.005)
                free_floor = q == "pd"

                def pm(t, g, s, n, pk, free_floor=free_floor, floor=floor):
                    f = t[4] if free_floor else floor
                    return np.median(np.sqrt(noise(n, scale) ** 2 + ((t[0] + t[1] * pk) * g + t[3] * s) ** 2
                                             + f**2 + (t[2] * pk) ** 2))

                t, loss = _fit(groups, pm, [0.1, 0.5, 0.01, 0.5] + ([floor] if free_floor else []))
                values[q][mi] = (round(float(t[0]), 3), round(float(t[3]), 3))
                extra[f"photon_mc_{q}"] = round(float(t[1]), 3)
                extra[f"photon_spread_{q}"] = round(float(t[2]), 4)
                if free_floor:
                    extra["photon_noise"] = round(float(t[4]), 4)
                label = (f"a, b = {values[q][mi]}, mc {extra[f'photon_mc_{q}']}, "
                         f"spread {extra[f'photon_spread_{q}']}")
            line = f"{q} {k}: {label} (loss {loss:.3f}, {len(groups)} bins)"
            print("  calibrated " + line, flush=True)
            if log is not None:
                log.append(line)
    model = auto.ErrorModel(pd=tuple(values["pd"]), ps=tuple(values["ps"]), **extra)
    spread = uncertainty(rows, model, bins)
    for q in ("pd", "ps"):
        line = f"{q} uncertainty (local/radiosity, local/photon, radiosity/photon): {spread[q]}"
        print("  calibrated " + line, flush=True)
        if log is not None:
            log.append(line)
    return dataclasses.replace(model, uncertainty_pd=spread["pd"], uncertainty_ps=spread["ps"])


def uncertainty(rows, model: auto.ErrorModel, bins: int = 8) -> dict:
    """Per quantity and pair of methods (local/radiosity, local/photon, radiosity/photon): the
    weighted RMS over bins of points (per scene, equal-count bins of `g + s`, weights as in
    `_fit` from the larger of the two measured errors) of `log(measured ratio / predicted
    ratio)` of the two methods' median errors: how far the model's comparison of two methods
    can be trusted."""
    out = {}
    for qi, q in enumerate(("pd", "ps")):
        terms = {pair: [] for pair in ((0, 1), (0, 2), (1, 2))}
        for r in rows:
            c = r["calibration"]
            f, errors = c["features"], c["errors"]
            if _failed(errors["local"][0]):
                continue
            ran = [k for k in auto.METHODS if k in errors and not _failed(errors[k][0])]
            m = auto.Measures(mass=f["gain_diffuse"], gain_diffuse=f["gain_diffuse"], gain_specular=f["gain_specular"],
                              rel_std_pd=f["rel_std_pd"], rel_std_ps=f["rel_std_ps"], local=None, ff=None, seconds={},
                              photon_k=c["photon_k"])
            pred = auto.predict(m, model, ran)
            x = f["gain_diffuse"] + f["gain_specular"]
            for (i, j), acc in terms.items():
                a, b = auto.METHODS[i], auto.METHODS[j]
                if a not in ran or b not in ran:
                    continue
                idx = np.flatnonzero(np.isfinite(errors[a][qi]) & np.isfinite(errors[b][qi]))
                idx = idx[np.argsort(x[idx], kind="stable")]
                for chunk in np.array_split(idx, max(1, min(bins, len(idx) // 20))):
                    if len(chunk) < 10:
                        continue
                    ma, mb = (max(float(np.median(errors[k][qi][chunk])), 1e-6) for k in (a, b))
                    pa, pb = (max(float(np.median(pred[k][q][chunk])), 1e-6) for k in (a, b))
                    acc.append((min(1.0, max(ma, mb) / _WEIGHT_BELOW), np.log(ma / mb) - np.log(pa / pb)))
        out[q] = tuple(round(float(np.sqrt(sum(w * d * d for w, d in v) / sum(w for w, _ in v))), 3) if v else 0.0
                       for v in terms.values())
    return out


# -- report -------------------------------------------------------------------------------------


def _pct(x):
    return "-" if x is None else f"{100 * x:.1f}%"


def _secs(x):
    return "-" if x is None else f"{x:.2f}"


def verdicts(row) -> dict:
    """Per auto run: the best method (lowest pd error, ps as tie-break), auto against it, and
    whether a cheaper method than the best would have done (within 10 % of its pd and ps errors)."""
    methods = {k: v for k, v in row["methods"].items() if not k.startswith("auto")}

    def key(k):
        e = methods[k]["errors"]
        return (e["pd"], e["ps"] if e["ps"] is not None else 0.0)

    best = min(methods, key=key)

    def within(e, ref):
        return all(e[q] is None or ref[q] is None or e[q] <= 1.1 * ref[q] + 1e-4 for q in ("pd", "ps"))

    ref = methods[best]["errors"]
    cheaper = [k for k in auto.METHODS if k in methods and auto.METHODS.index(k) < auto.METHODS.index(best)
               and within(methods[k]["errors"], ref)]
    t_best = methods[best]["warm_s"] or methods[best]["first_s"]
    t_global = [methods[k]["warm_s"] or methods[k]["first_s"] for k in ("radiosity", "photon") if k in methods]
    out = {}
    for name, a in row["methods"].items():
        if not name.startswith("auto"):
            continue
        t_auto = a["warm_s"] or a["first_s"]
        out[name] = {"best": best, "auto_within_10pct": within(a["errors"], ref), "cheaper_suffices": cheaper,
                     "time_ratio": t_auto / t_best if t_best else None,
                     "time_vs_global": t_auto / min(t_global) if t_global else None,
                     "auto_half_time": (t_auto <= 0.5 * t_best) if cheaper else None}
    return out


def report(rows, args, model, seconds, calibration=None) -> str:
    import jax

    lines = ["# `--method auto`: the cheapest method good enough, per region", "",
             f"- Date: {time.strftime('%Y-%m-%dT%H:%M:%S')}; machine: {os.cpu_count()} cores, "
             f"{platform.platform()}; Python {platform.python_version()}, jax {jax.__version__}; "
             f"load average at start {os.getloadavg()[0]:.2f} (shared machine: timings vary up to ~2x)",
             f"- Run: `python3 -m benchmarks.auto_bench {' '.join(sys.argv[1:])}`, {seconds:.0f} s wall",
             f"- Scenes: path-traced global illumination ({args.samples} paths per observation, x4 on E), 1 % "
             f"noise, 12 bits (full scale at the 99.9th percentile); mesh resolution {args.resolution} "
             f"(E: {args.resolution_e}); A-D and V on the scanner under their selected lights, E on the fixed "
             f"camera tilted {args.tilt:g} deg about x; seed {args.seed}; Ward model unless marked TS. Method III: {args.photons:,} photons per light, "
             f"{args.iterations} iterations, on {', '.join(args.photon_objects)} (not on TS scenes: it fits Ward).",
             f"- auto: target errors {', '.join(f'{t:g}' for t in args.targets)} (relative, median per region; "
             "rows `auto T`; 0 = as accurate as the best method, the default), tolerance 10 %: a cheaper method "
             "is kept where its error with its bias inflated by the model's uncertainty is within 10 % of the best "
             "prediction; regions of >= 8 points dilated by 2 rings; ps from Method III everywhere where it runs, "
             "else from Method I. Times: median of "
             f"{args.repeats} warm runs (first run with compilation in brackets), form factors cast in every run.",
             "- Errors: medians over all points of the relative pd error (mean over RGB) / relative ps error "
             "(points whose true ps > 0).", ""]
    lines += ["| scene | points | method | pd error | ps error | s warm (first) | auto: choice, points per method |",
              "|---|---:|---|---:|---:|---:|---|"]
    for r in rows:
        for k, e in r["methods"].items():
            extra = ""
            if k.startswith("auto"):
                extra = f"{e['choice']}; {e['points_by_method']}"
            lines.append(f"| {r['scene']} | {r['points']} | {k} | {_pct(e['errors']['pd'])} | "
                         f"{_pct(e['errors']['ps'])} | {_secs(e['warm_s'])} ({_secs(e['first_s'])}) | {extra} |")
    lines += ["", "## Against the best method", "",
              "`best` = lowest pd error (ps breaks ties); `cheaper suffices` = a cheaper method within 10 % of "
              "the best's pd and ps errors (the last column is asked only then); times warm.", "",
              "| scene | run | best | auto within 10 % of best (pd and ps) | cheaper suffices | auto time / best | "
              "auto time / fastest global method | auto <= half the best's time |", "|---|---|---|---|---|---:|---:|---|"]
    for r in rows:
        for name, v in r["verdict"].items():
            half = "-" if v["auto_half_time"] is None else ("yes" if v["auto_half_time"] else "no")
            ratio = "-" if v["time_ratio"] is None else f"{v['time_ratio']:.2f}"
            vs_global = "-" if v["time_vs_global"] is None else f"{v['time_vs_global']:.2f}"
            lines.append(f"| {r['scene']} | {name} | {v['best']} | {'yes' if v['auto_within_10pct'] else 'no'} | "
                         f"{', '.join(v['cheaper_suffices']) or '-'} | {ratio} | {vs_global} | {half} |")
    lines += ["", "## Region-wise merge: Method I where auto keeps it", "",
              f"Median errors at the points where auto (target {args.targets[0]:g}) keeps Method I's result, for each "
              "method's own estimate "
              "there (the global methods were run on the whole object).", "",
              "| scene | points kept local | local pd / ps | radiosity pd / ps | photon pd / ps |",
              "|---|---:|---|---|---|"]
    for r in rows:
        m = r["merge_check"]

        def cell(k, m=m):
            if k not in m:
                return "-"
            return f"{_pct(m[k]['pd_median_where_auto_uses_local'])} / {_pct(m[k]['ps_median_where_auto_uses_local'])}"

        lines.append(f"| {r['scene']} | {m['points_local']} | {cell('local')} | {cell('radiosity')} | {cell('photon')} |")
    lines += ["", "## Predicted and measured (scene medians)", "",
              "| scene | method | predicted pd / ps | measured pd / ps |", "|---|---|---|---|"]
    for r in rows:
        first = _auto_name(args.targets[0])
        pred = dict(r["methods"][first]["predicted"])
        for name, e in r["methods"].items():
            if name.startswith("auto"):
                pred[name] = e["predicted"]["plan"]
        for k, p in pred.items():
            if k == "plan":
                continue
            meas = r["methods"][k]["errors"] if k in r["methods"] else None
            label = f"{k}: plan" if k.startswith("auto") else k
            lines.append(f"| {r['scene']} | {label} | {_pct(p['pd'])} / {_pct(p['ps'])} | "
                         + (f"{_pct(meas['pd'])} / {_pct(meas['ps'])}" if meas else "-") + " |")
    lines += ["", "## Measured statistics per scene (auto's measurements: median / 90th percentile)", "",
              "`rel std` over the points with an estimate of their own (their share in brackets).", "",
              "| scene | mass | gain diffuse | gain specular | rel std pd | rel std ps |", "|---|---|---|---|---|---|"]
    for r in rows:
        s = r["methods"][_auto_name(args.targets[0])]["statistics"]

        def cell(k, s=s):
            v = s[k]
            text = "-" if v["median"] is None else f"{v['median']:.3f} / {v['p90']:.3f}"
            return text + (f" ({v['own']:.0%})" if "own" in v else "")

        lines.append(f"| {r['scene']} | " + " | ".join(cell(k) for k in ("mass", "gain_diffuse", "gain_specular",
                                                                          "rel_std_pd", "rel_std_ps")) + " |")
    lines += ["", "## Error model", "",
              f"{'Fitted here (`--calibrate`)' if args.calibrate else 'In use (`jaxrefl.methods.auto.ErrorModel`)'}: "
              "`e = sqrt(noise^2 + bias^2 [+ photon_noise^2])` per method, (a, b) for pd and ps:", "",
              "| method | pd (a, b) | ps (a, b) |", "|---|---|---|"]
    for i, k in enumerate(auto.METHODS):
        lines.append(f"| {k} | {model.pd[i]} | {model.ps[i]} |")
    if calibration:
        lines += ["", f"Fitted by `python3 -m benchmarks.auto_bench --calibrate --repeats 0 --seed 0 --tilt 30 "
                  f"--dump FILE` on {calibration['scenes']} (weighted squared log ratio of predicted to measured "
                  "bin medians; a scene whose Method I run returned no albedo is left out):", ""]
        lines += [f"- {line}" for line in calibration["log"]]
    lines += ["", f"Method III: bias = (a + photon_mc k) g + b s with photon_mc pd {model.photon_mc_pd}, ps "
              f"{model.photon_mc_ps} (k = sqrt(points / photons per light configuration)), floor photon_noise "
              f"{model.photon_noise} and spread k (pd {model.photon_spread_pd}, ps {model.photon_spread_ps}) in "
              f"quadrature. Method II's own noise pd {model.radiosity_noise_pd}, ps {model.radiosity_noise_ps}. Noise scale pd {model.noise_scale_pd}, ps {model.noise_scale_ps}; unknown_pd "
              f"{model.unknown_pd}, unknown_ps {model.unknown_ps}. Uncertainty of the predicted ratio of two methods' "
              f"errors (log scale; local/radiosity, local/photon, radiosity/photon): pd {model.uncertainty_pd}, ps "
              f"{model.uncertainty_ps}: a method's bias is inflated by exp(uncertainty) of the pair when it is "
              "compared with another.", ""]
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smoke run: 4 scenes, small meshes, one repeat")
    p.add_argument("--calibrate", action="store_true", help="fit the error model on these runs and report it")
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--resolution-e", type=int, default=32)
    p.add_argument("--samples", type=int, default=16, help="paths per observation (x4 on E)")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--targets", default="0,0.05",
                   help="auto's target errors, comma list (one auto run each; 0: the default, the best method's accuracy)")
    p.add_argument("--seed", type=int, default=1, help="render and noise seed (the calibration used 0)")
    p.add_argument("--tilt", type=float, default=E_TILT, help="Object E's tilt about x [deg]")
    p.add_argument("--photons", type=int, default=200_000)
    p.add_argument("--iterations", type=int, default=20)
    p.add_argument("--photon-objects", default="all", help="objects Method III runs on (comma list or 'all')")
    p.add_argument("--scenes", default=None, help="comma list of scene labels (default: all, or the quick set)")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS_auto.md"))
    p.add_argument("--json", default=None, help="also write the rows as JSON here")
    p.add_argument("--dump", default=None, help="pickle the rows (per-point calibration data included) here")
    p.add_argument("--load", default=None, help="report (and calibrate) from a --dump instead of running")
    p.add_argument("--calibration-dump", default=None,
                   help="a --dump of a calibration run: fit the error model on it and report the fit")
    args = p.parse_args(argv)
    if args.quick:
        args.resolution, args.resolution_e, args.samples, args.repeats = 24, 24, 8, 1
        args.photons, args.iterations = min(args.photons, 100_000), min(args.iterations, 10)
    args.photon_objects = args.photon_objects.split(",")
    args.targets = [float(t) for t in args.targets.split(",")]
    wanted = args.scenes.split(",") if args.scenes else (QUICK if args.quick else [s.label for s in SCENES])
    scenes = [s for s in SCENES if s.label in wanted]
    t0 = time.perf_counter()
    rows = []
    if args.load:
        with open(args.load, "rb") as fh:
            rows = pickle.load(fh)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            for scene in scenes:
                print(f"{scene.label} ...", flush=True)
                row = run_scene(scene, args, tmp)
                row["verdict"] = verdicts(row)
                rows.append(row)
                if args.dump:
                    with open(args.dump, "wb") as fh:
                        pickle.dump(rows, fh)
    model, calibration = auto.ErrorModel(), None
    if args.calibrate or args.calibration_dump:
        source = rows
        if args.calibration_dump:
            with open(args.calibration_dump, "rb") as fh:
                source = pickle.load(fh)
        log = []
        fitted = calibrate(source, log=log)
        calibration = {"scenes": ", ".join(r["scene"] for r in source), "log": log}
        model = fitted if args.calibrate else model
    text = report(rows, args, model, time.perf_counter() - t0, calibration)
    with open(args.out, "w") as fh:
        fh.write(text)
    if args.json:
        slim = [{k: v for k, v in r.items() if k != "calibration"} for r in rows]
        with open(args.json, "w") as fh:
            json.dump(slim, fh, indent=1, default=float)
    print(text)


if __name__ == "__main__":
    main()
