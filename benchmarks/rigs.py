"""Benchmark: Method I on the rig zoo (`data_synth.zoo.CELLS`), with held-out lights.

Run: `python3 -m benchmarks.rigs [--cells a,b] [--seed 0] [--n-points N] [--holdout 0.25]
[--models ward,torrance-sparrow] [--out benchmarks/RESULTS_rigs.md]` (a JSON with every
number lands next to the markdown, `RESULTS_rigs.json`; both are rewritten after each cell).

Per cell (direct light, Embree shadows, the zoo's sensor):

1. A share `--holdout` of the lights is held out (`holdout.choose_holdout(M, fraction,
   seed)`, `split_scan`); everything is fitted on the rest.
2. Method I (`estimate_local`) with models `ward` and `torrance-sparrow`, each in three
   variants: `prior` (`LocalOptions(model=m)`: the shared reflectance prior, the default),
   `gates` (`prior=False`: pooled lobes, else window fills) and `paper` (`paper=True`).
   Each is run twice on the same scan: `first` seconds include compilation (and any cache
   left warm by earlier cells of the same shape), `second` is the warm run.
3. Per variant: median relative errors of pd, ps, roughness over all points
   (`result.truth_errors(est, fit_scan)[...]["all"]`; roughness only where the truth is in
   the fitted model: Ward truth vs Ward fits (alpha), Torrance-Sparrow truth vs TS fits
   (sigma); ps of a mismatched model is compared too but means another lobe; GGX cells have
   pd only), over the points whose true lobe is *visible* (below) and over the points of a
   true material whose lobe some point shows a fit light (`material_visible`: the scope of
   the issue's ps and roughness targets, "where the material's lobe is visible to some
   light"; pd's target is over all points); coverage by status;
   held-out relighting `holdout_error(est, test_scan, gi="none")` rel-RMS and median
   relative error; ratios to the truth floor (`truth_holdout_error`, Ward/TS cells), to the
   best-single-lobe-per-material reference (below) and to the plain per-point fit.
4. `plain`: `fit_rows` on the fit lights, every point's own (pd, ps, roughness) whether
   identifiable or not, no fill of any kind.
5. `reference` (best single lobe per material): for each TRUE material label
   (`info["labels"]`) one (ps, roughness) fitted jointly to all its points' fit-light
   samples (`prior.material_lobes` on `fit_rows(...)["chunks"].material_sums`, inverse residual
   scales `1 / noise_scale`, grid `ln brdf.ROUGHNESS_GRID`), then every point's pd re-fitted
   with that lobe fixed (`local._refit_diffuse`); points without any fit-light sample take pd
   from their observed neighbours (`local.fill_unobserved_pd`), as every variant does.
6. Calibration of every variant with finite standard deviations: share of points with
   `|est - truth| <= std` for ps and roughness, per status (matched model only).

*Visible* lobe: a point whose truth lobe shows in the data it is fitted on: it has a
fit-light sample that is observed (valid, unsaturated: `Scan.observed()`) and lit
(`info["lit"]`: light above the surface and unshadowed) whose true specular part -- the
noise-free radiance `info["clean"]` less the true diffuse part `pd / pi * Y cos_i / C^2`,
on the RGB mean -- is at least 5 % of the clean radiance.

`noise floor (clean)`: the held-out rel-RMS of the noise-free truth render `info["clean"]`
against the recorded radiance over the same samples `holdout_error` uses (classified
measurable and observed): the floor of the sensor alone, also for GGX cells, where the truth
is not in jaxrefl's models.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

MODELS = ("ward", "torrance-sparrow")
VARIANTS = ("prior", "gates", "paper")
VISIBLE_SHARE = 0.05  # true specular part / radiance of a sample that shows the lobe
TRUTH_ROUGHNESS = {"ward": "true_alpha", "torrance-sparrow": "true_sigma"}
TARGETS = {"pd": 0.01, "ps": 0.05, "roughness": 0.05, "truth_floor": 1.5, "reference": 1.2, "plain": 0.5}


def _options(model, variant):
    from jaxrefl.methods.local import LocalOptions

    if variant == "prior":
        return LocalOptions(model=model, prior=True)
    if variant == "gates":
        return LocalOptions(model=model, prior=False)
    if variant == "paper":
        return LocalOptions(model=model, paper=True)
    raise ValueError(f"unknown variant {variant!r}")


def _err_string(exc):
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"


def _finite(x):
    """JSON-safe float (None for NaN / inf / None)."""
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def _rel_errors(value, truth):
    """Per-point relative error `(N,)` (RGB mean for pd), as `result.truth_errors` computes
    it, and the points where it is defined (truth not 0)."""
    value, truth = np.asarray(value, float), np.asarray(truth, float)
    err = np.abs(value - truth) / np.maximum(np.abs(truth), 1e-12)
    err = err.reshape(len(err), -1).mean(axis=1)
    defined = np.abs(truth).reshape(len(err), -1).max(axis=1) > 1e-9
    return err, defined


def _median(err, mask):
    return float(np.median(err[mask])) if mask.any() else None


def _truths(fit_scan, model):
    """{parameter: truth array} comparable with a `model` fit."""
    out = {"pd": fit_scan.true_pd}
    if fit_scan.true_ps is not None:
        out["ps"] = fit_scan.true_ps
    rough = getattr(fit_scan, TRUTH_ROUGHNESS[model])
    if rough is not None:
        out["roughness"] = rough
    return out


def parameter_errors(est, fit_scan, visible, observed, lobe_seen=None) -> dict:
    """Median relative errors over all points (`truth_errors`), over `visible` points, over
    the rest, over `observed` points (those with a fit-light sample) and over `lobe_seen`
    points (those of a true material whose lobe some point shows a fit light:
    `material_visible`; default all)."""
    from jaxrefl.result import truth_errors

    te = truth_errors(est, fit_scan)
    out = {}
    for name, truth in _truths(fit_scan, est.model).items():
        value = {"pd": est.pd, "ps": est.ps, "roughness": est.roughness}[name]
        err, defined = _rel_errors(value, truth)
        out[name] = {"all": te.get(name, {}).get("all", {}).get("median"),
                     "all_p90": te.get(name, {}).get("all", {}).get("p90"),
                     "visible": _median(err, defined & visible),
                     "not_visible": _median(err, defined & ~visible),
                     "observed": _median(err, defined & observed),
                     "lobe_seen": _median(err, defined & (True if lobe_seen is None else lobe_seen))}
    return out


def material_visible(labels, visible) -> np.ndarray:
    """`(N,)` bool: the point's true material (`labels`) has a point whose lobe is `visible`
    to a fit light (the issue's scope of the ps and roughness targets)."""
    labels = np.asarray(labels, np.int64)
    return (np.bincount(labels, weights=np.asarray(visible, np.float64)) > 0)[labels]


def calibration(est, fit_scan, matched) -> dict:
    """Share of points with |est - truth| <= std for ps and roughness, per status name
    (points with a finite std only; matched model only)."""
    from jaxrefl.methods.local import STATUS_NAMES

    if not matched or fit_scan.true_ps is None:
        return {}
    rough_truth = getattr(fit_scan, TRUTH_ROUGHNESS[est.model])
    out = {}
    for code, name in enumerate(STATUS_NAMES):
        sel = est.status == code
        if not sel.any():
            continue
        entry = {"points": int(sel.sum())}
        for key, value, truth, std in (("ps", est.ps, fit_scan.true_ps, est.std_ps),
                                       ("roughness", est.roughness, rough_truth, est.std_roughness)):
            ok = sel & np.isfinite(std)
            entry[key] = float(np.mean(np.abs(value - truth)[ok] <= std[ok])) if ok.any() else None
            entry[key + "_points_with_std"] = int(ok.sum())
            # median |error| / std: 0.67 for calibrated Gaussian errors; >> 1 overconfident
            entry[key + "_median_z"] = (float(np.median(np.abs(value - truth)[ok] / np.maximum(std[ok], 1e-300)))
                                        if ok.any() else None)
        out[name] = entry
    return out


def coverage(est, where=None) -> dict:
    """Share of the points (of `where`, default all) per status name."""
    from jaxrefl.methods.local import STATUS_NAMES

    status = est.status if where is None else est.status[where]
    return {name: float(np.mean(status == code)) if status.size else None for code, name in enumerate(STATUS_NAMES)}


def _holdout(est, test_scan, caster) -> dict:
    from jaxrefl.outputs.holdout import holdout_error

    h = holdout_error(est, test_scan, caster, gi="none")
    out = {"rel_rms": h["rel_rms"], "median_rel": h["median_rel"], "samples": h["samples"]}
    if h.get("reason"):
        out["reason"] = h["reason"]
    return out


def visible_lobes(scan, info, fit_lights) -> np.ndarray:
    """`(N,)` bool: the point has an observed, lit fit-light sample whose true specular part
    (noise-free radiance less the true diffuse part) is >= `VISIBLE_SHARE` of its radiance."""
    v = np.asarray(scan.vertices, float)
    nrm = np.asarray(scan.normals, float)
    lp = np.asarray(scan.light_pos, float)[fit_lights]
    d = lp[None] - v[:, None]
    dist2 = np.sum(d * d, -1)
    cos_i = np.einsum("nmk,nk->nm", d, nrm) / np.sqrt(dist2)
    e = scan.intensities()[fit_lights][None] * np.maximum(cos_i, 0.0) / dist2
    lit = np.asarray(info["lit"])[:, fit_lights]
    use = scan.observed()[:, fit_lights] & lit
    clean = np.asarray(info["clean"])[:, fit_lights].mean(-1)
    diffuse = (np.asarray(scan.true_pd).mean(-1) / np.pi)[:, None] * e
    spec = clean - diffuse
    return np.any(use & (clean > 0) & (spec >= VISIBLE_SHARE * clean), axis=1)


def noise_floor(scan, test_scan, info, held, caster) -> dict:
    """Held-out rel-RMS of the noise-free truth render against the recorded radiance over the
    samples `holdout_error` compares (classified measurable, observed)."""
    from jaxrefl.reflectance.classify import classify

    use = classify(test_scan.vertices, test_scan.normals, test_scan.cam_pos, test_scan.light_pos, caster,
                   observed=test_scan.observed()).measurable
    obs = np.asarray(test_scan.radiance, float)
    pred = np.asarray(info["clean"])[:, held]
    d2 = np.where(use[..., None], (pred - obs) ** 2, 0.0).sum()
    o2 = np.where(use[..., None], obs**2, 0.0).sum()
    return {"rel_rms": float(np.sqrt(d2 / o2)) if o2 > 0 else None, "samples": int(use.sum())}


def _estimate(model, pd, ps, rough, method):
    from jaxrefl.result import Estimate

    n = len(pd)
    inf = np.full(n, np.inf)
    return Estimate(np.asarray(pd, float), np.asarray(ps, float), np.asarray(rough, float), np.zeros(n, np.int8),
                    np.full((n, 3), np.inf), inf, inf.copy(), np.ones(n, bool), np.ones(n, bool), model,
                    {"method": method, "model": model})


def plain_and_reference(fit_scan, rows, labels, n_materials, model, caster, test_scan) -> dict:
    """`plain` (every point's own fit, no fill) and `reference` (one joint lobe per true
    material, pd re-fitted per point) held-out errors and parameter estimates."""
    import jax.numpy as jnp

    from jaxrefl.methods.local import (
        LocalOptions,
        _refit_diffuse,
        fill_unobserved_pd,
        fit_rows,
        quantisation_step,
    )
    from jaxrefl.reflectance import brdf
    from jaxrefl.reflectance import prior as prior_mod
    from jaxrefl.reflectance.fill import vertex_adjacency

    q = quantisation_step(fit_scan.radiance, rows["use"])
    t0 = time.perf_counter()
    fit = fit_rows(rows, LocalOptions(model=model), noise_floor=q / np.sqrt(12.0))
    out = {"plain": {"seconds": time.perf_counter() - t0}}
    plain = _estimate(model, fit["pd"], fit["ps"], np.maximum(fit["roughness"], 1e-12), "plain fit_rows")
    out["plain"]["holdout"] = _holdout(plain, test_scan, caster)
    out["plain"]["estimate"] = plain
    observed_any = np.asarray(rows["use"]).any(1)
    out["plain"]["points_without_fit_sample"] = int((~observed_any).sum())

    t0 = time.perf_counter()
    s2 = np.asarray(fit["noise_scale"], float)
    ok = np.isfinite(s2) & (s2 > 0) & observed_any
    inv_s2 = np.where(ok, 1.0 / np.where(ok, s2, 1.0), 0.0)
    lobes = prior_mod.material_lobes(fit["chunks"].material_sums, np.asarray(labels, np.int64), int(n_materials),
                                     inv_s2, np.log(brdf.ROUGHNESS_GRID))
    # A material the joint fit cannot resolve (no rows, flat chi^2) has no lobe.
    lobe_ps = np.where(np.isfinite(lobes.ps) & np.isfinite(lobes.rho), lobes.ps, 0.0)
    lobe_rho = np.where(np.isfinite(lobes.rho), lobes.rho, np.log(0.1))
    ps = np.asarray(lobe_ps, float)[labels]
    rough = np.exp(np.asarray(lobe_rho, float))[labels]
    jrows = {k: jnp.asarray(v) for k, v in rows.items()}
    pd, std_pd = _refit_diffuse(model, jrows, jnp.log(jnp.maximum(jnp.asarray(ps), 1e-300)),
                                jnp.log(jnp.asarray(rough)),
                                jnp.asarray(fit["weights"]))
    pd, std_pd = np.array(pd), np.array(std_pd)
    status = np.zeros(len(pd), np.int8)
    fill_unobserved_pd(pd, std_pd, status, observed_any, vertex_adjacency(fit_scan.faces, fit_scan.n_points), 5)
    ref = _estimate(model, pd, ps, rough, "reference: one lobe per true material")
    out["reference"] = {"seconds": time.perf_counter() - t0, "estimate": ref,
                        "holdout": _holdout(ref, test_scan, caster),
                        "lobes": [{"ps": _finite(lobes.ps[m]), "roughness": _finite(np.exp(lobes.rho[m])),
                                   "std_ps": _finite(lobes.sd_ps[m]), "std_ln_roughness": _finite(lobes.sd_rho[m]),
                                   "points": int(lobes.points[m]), "identifiable": bool(lobes.identifiable[m])}
                                  for m in range(int(n_materials))]}
    return out


def _ratio(a, b):
    return float(a / b) if a is not None and b is not None and b > 0 else None


def run_cell(name, seed=0, n_points=None, fraction=0.25, models=MODELS, variants=VARIANTS, repeat=True,
             log=print) -> dict:
    """Every measurement of one zoo cell (a JSON-ready dict; a failing variant or stage
    records `error` and the rest goes on)."""
    from data_synth import zoo
    from jaxrefl.geometry.raycast import RayCaster
    from jaxrefl.methods.local import estimate_local, prepare_rows
    from jaxrefl.outputs.holdout import choose_holdout, split_scan, truth_holdout_error

    t_cell = time.perf_counter()
    spec = zoo.CELLS[name]
    scan, info = zoo.make_cell(name, seed=seed, n_points=n_points)
    held = choose_holdout(scan.n_lights, fraction, seed=seed)
    fit_lights = np.setdiff1d(np.arange(scan.n_lights), held)
    fit_scan, test_scan = split_scan(scan, held)
    caster = RayCaster(scan.vertices, scan.faces)
    visible = visible_lobes(scan, info, fit_lights)
    try:
        rows = prepare_rows(fit_scan, caster=caster)
        rows_error = None
    except Exception as exc:  # noqa: BLE001 - a benchmark records, it does not stop
        rows, rows_error = None, _err_string(exc)
    # Points with a usable fit-light sample (as `estimate_local`'s `pd_measured`).
    observed_any = np.asarray(rows["use"]).any(1) if rows is not None else fit_scan.observed().any(1)
    labels = np.asarray(info["labels"], np.int64)
    lobe_seen = material_visible(labels, visible)
    rec = {"cell": name, "description": spec.description, "rig": spec.rig, "material": spec.material,
           "brdf": spec.brdf, "object": spec.object, "sensor_bits": spec.sensor.bits, "seed": int(seed),
           "n_points": scan.n_points, "n_lights": scan.n_lights, "fit_lights": int(len(fit_lights)),
           "held_out_lights": [int(i) for i in held], "materials": len(info["materials"]),
           "visible_share": float(visible.mean()), "observed_share": float(observed_any.mean()),
           "seconds_make_cell": float(info["seconds"]), "models": {}}
    floor = truth_holdout_error(test_scan, caster, gi="none")
    rec["truth_floor"] = {"rel_rms": floor["rel_rms"], "median_rel": floor["median_rel"],
                          **({"reason": floor["reason"]} if floor.get("reason") else {})}
    try:
        rec["noise_floor"] = noise_floor(scan, test_scan, info, held, caster)
    except Exception as exc:  # noqa: BLE001 - a benchmark records, it does not stop
        rec["noise_floor"] = {"rel_rms": None, "error": _err_string(exc)}
    log(f"[{name}] N={scan.n_points} M={scan.n_lights} fit={len(fit_lights)} visible={visible.mean():.1%} "
        f"truth floor={floor['rel_rms']} noise floor={rec['noise_floor'].get('rel_rms')}")
    if rows_error:
        rec["rows_error"] = rows_error

    for model in models:
        matched = spec.brdf == model
        mrec = {"matched": matched, "variants": {}}
        rec["models"][model] = mrec
        estimates = {}
        if rows is not None:
            try:
                pr = plain_and_reference(fit_scan, rows, labels, len(info["materials"]), model, caster, test_scan)
                for key in ("plain", "reference"):
                    est = pr[key].pop("estimate")
                    pr[key]["errors"] = parameter_errors(est, fit_scan, visible, observed_any, lobe_seen)
                    estimates[key] = est
                mrec.update(pr)
            except Exception as exc:  # noqa: BLE001
                mrec["plain"] = {"error": _err_string(exc)}
                mrec["reference"] = {"error": _err_string(exc)}
        for variant in variants:
            vrec = {}
            mrec["variants"][variant] = vrec
            try:
                opts = _options(model, variant)
                t0 = time.perf_counter()
                est = estimate_local(fit_scan, opts, caster=caster)
                vrec["seconds_first"] = time.perf_counter() - t0
                if repeat:
                    t0 = time.perf_counter()
                    est = estimate_local(fit_scan, opts, caster=caster)
                    vrec["seconds_second"] = time.perf_counter() - t0
                vrec["errors"] = parameter_errors(est, fit_scan, visible, observed_any, lobe_seen)
                vrec["coverage"] = coverage(est)
                vrec["coverage_observed"] = coverage(est, observed_any)
                vrec["holdout"] = _holdout(est, test_scan, caster)
                vrec["calibration"] = calibration(est, fit_scan, matched)
                rel = vrec["holdout"]["rel_rms"]
                vrec["ratio_truth_floor"] = _ratio(rel, rec["truth_floor"]["rel_rms"])
                vrec["ratio_noise_floor"] = _ratio(rel, rec["noise_floor"].get("rel_rms"))
                vrec["ratio_reference"] = _ratio(rel, mrec.get("reference", {}).get("holdout", {}).get("rel_rms"))
                vrec["ratio_plain"] = _ratio(rel, mrec.get("plain", {}).get("holdout", {}).get("rel_rms"))
                vrec["meta"] = {k: est.meta.get(k) for k in ("materials", "points_pooled", "points_with_pooled_lobe",
                                                             "points_at_energy_bound", "seconds")
                                if k in est.meta}
                e = vrec["errors"]
                log(f"[{name}] {model} {variant}: {vrec['seconds_first']:.1f}s/"
                    f"{vrec.get('seconds_second', float('nan')):.1f}s pd={e['pd']['all']} "
                    f"ps={e.get('ps', {}).get('all')} rough={e.get('roughness', {}).get('all')} "
                    f"rel_rms={rel} measured={vrec['coverage']['measured']:.1%}")
            except Exception as exc:  # noqa: BLE001
                vrec["error"] = _err_string(exc)
                log(f"[{name}] {model} {variant}: FAILED {vrec['error']}")
    rec["seconds"] = time.perf_counter() - t_cell
    return rec


# -- report ---------------------------------------------------------------------------------


def _pct(x, digits=2):
    return "n/a" if x is None else f"{100 * x:.{digits}f}%"


def _x(x):
    if x is None:
        return "n/a"
    return f"{x:.2f}x" if x >= 0.1 else f"{x:.2g}x"


def _mark(ok):
    return "n/a" if ok is None else ("met" if ok else "**NOT MET**")


def _le(value, limit):
    return None if value is None else bool(value <= limit)


def _err_cells(errors, matched):
    cells = []
    for key in ("pd", "ps", "roughness"):
        e = errors.get(key)
        if e is None:
            cells.append("-")
            continue
        note = "" if matched or key == "pd" else "*"
        cells.append(" / ".join(f"{_pct(e.get(k))}{note}" for k in ("all", "observed", "visible")))
    return cells


def _cov(cov):
    return " / ".join("n/a" if cov.get(k) is None else f"{cov[k]:.0%}"
                      for k in ("measured", "pooled", "interpolated", "unresolved"))


def _calib_cell(cal, key):
    parts = []
    for status in ("measured", "pooled", "interpolated"):
        c = cal.get(status)
        if c and c.get(key) is not None:
            z = c.get(key + "_median_z")
            parts.append(f"{status[0]} {c[key]:.0%}" + ("" if z is None else f" (z {z:.2g})"))
    return ", ".join(parts) if parts else "-"


def must_shows(records) -> list[dict]:
    """The issue's targets, per cell, for the default (prior) variant."""
    out = []
    for rec in records:
        if "error" in rec:
            out.append({"cell": rec["cell"], "check": "cell ran", "value": rec["error"], "met": False})
            continue
        ggx = rec["brdf"] == "ggx"
        models = [m for m in rec["models"] if rec["models"][m]["matched"]] if not ggx else list(rec["models"])
        for model in models:
            mrec = rec["models"][model]
            v = mrec["variants"].get("prior", {})
            tag = f"{rec['cell']} ({model}, prior)"
            if "error" in v:
                out.append({"cell": rec["cell"], "model": model, "check": "prior variant ran", "value": v["error"],
                            "met": False, "label": tag})
                continue
            for key in ("pd", "ps", "roughness"):
                if key in v.get("errors", {}):
                    # ps and roughness where the material's lobe is visible to some light (the
                    # issue's scope); pd everywhere.
                    scope = "all" if key == "pd" else "lobe_seen"
                    val = v["errors"][key].get(scope)
                    obs = v["errors"][key].get("observed")
                    context = f"observed points: {_pct(obs)}"
                    if scope != "all":
                        context += f"; all points: {_pct(v['errors'][key]['all'])}"
                    ref = mrec.get("reference", {}).get("errors", {}).get(key, {}).get("all")
                    if ggx and ref is not None:  # the model's own floor: its best lobe per material
                        context += f"; best single lobe per material: {_pct(ref)}"
                    where = "all points" if scope == "all" else "points of a material whose lobe a fit light sees"
                    out.append({"cell": rec["cell"], "model": model, "check": f"median {key} error ({where}) "
                                f"<= {TARGETS[key]:.0%}", "value": _pct(val), "met": _le(val, TARGETS[key]),
                                "label": tag, "context": context})
            if not ggx:
                r = v.get("ratio_truth_floor")
                out.append({"cell": rec["cell"], "model": model, "check": "held-out rel-RMS <= 1.5x truth floor",
                            "value": _x(r), "met": _le(r, TARGETS["truth_floor"]), "label": tag})
            else:
                r = v.get("ratio_reference")
                out.append({"cell": rec["cell"], "model": model,
                            "check": "held-out rel-RMS <= 1.2x best single lobe per material",
                            "value": _x(r), "met": _le(r, TARGETS["reference"]), "label": tag})
            if rec["cell"] == "photometric_sharp":
                r = v.get("ratio_plain")
                out.append({"cell": rec["cell"], "model": model, "check": "held-out rel-RMS <= 0.5x plain per-point",
                            "value": _x(r), "met": _le(r, TARGETS["plain"]), "label": tag})
    return out


def _mismatch_notes(records):
    """For GGX cells: how far the reference itself is from the noise-free floor, and the
    variant with the lowest held-out error (the 1.2x target is relative to that reference)."""
    notes = []
    for rec in records:
        if "error" in rec or rec.get("brdf") != "ggx":
            continue
        floor = rec.get("noise_floor", {}).get("rel_rms")
        for model, mrec in rec["models"].items():
            ref = mrec.get("reference", {}).get("holdout", {}).get("rel_rms")
            runs = {k: v["holdout"]["rel_rms"] for k, v in mrec["variants"].items()
                    if "error" not in v and v["holdout"]["rel_rms"] is not None}
            if mrec.get("plain", {}).get("holdout", {}).get("rel_rms") is not None:
                runs["plain"] = mrec["plain"]["holdout"]["rel_rms"]
            best = min(runs, key=runs.get) if runs else None
            notes.append(f"{rec['cell']} {model}: reference rel-RMS {_pct(ref)} = {_x(_ratio(ref, floor))} the "
                         f"noise-free floor; lowest: {best} {_pct(runs.get(best))} ({_x(_ratio(runs.get(best), ref))} "
                         "the reference)")
    return notes


def _summary_rows(records):
    lines = [
        "| cell | truth | model | pd all / obs / vis | ps all / obs / vis | rough all / obs / vis | observed | visible "
        "| meas / pool / interp / unres | held-out rel-RMS | truth floor | / floor | / reference | / plain "
        "| calib ps | calib rough | s warm |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for rec in records:
        if "error" in rec:
            lines.append(f"| {rec['cell']} | FAILED: {rec['error']} |" + " |" * 16)
            continue
        for model, mrec in rec["models"].items():
            if not mrec["matched"] and rec["brdf"] != "ggx":
                continue
            v = mrec["variants"].get("prior", {})
            if "error" in v:
                lines.append(f"| {rec['cell']} | {rec['brdf']} | {model} | FAILED: {v['error']} |" + " |" * 13)
                continue
            lines.append(
                f"| {rec['cell']} | {rec['brdf']} | {model} | " + " | ".join(_err_cells(v["errors"], mrec["matched"]))
                + f" | {rec['observed_share']:.0%} | {rec['visible_share']:.0%} | {_cov(v['coverage'])} | "
                f"{_pct(v['holdout']['rel_rms'])} | "
                f"{_pct(rec['truth_floor']['rel_rms'] or rec['noise_floor'].get('rel_rms'))}"
                f"{'' if rec['truth_floor']['rel_rms'] else ' (clean)'} | "
                f"{_x(v['ratio_truth_floor'] or (v['ratio_noise_floor'] if rec['brdf'] == 'ggx' else None))} | "
                f"{_x(v['ratio_reference'])} | {_x(v['ratio_plain'])} | "
                f"{_calib_cell(v['calibration'], 'ps')} | {_calib_cell(v['calibration'], 'roughness')} | "
                f"{v.get('seconds_second', v['seconds_first']):.1f} |")
    return lines


def _cell_section(rec):
    lines = [f"### {rec['cell']}", ""]
    if "error" in rec:
        return lines + [f"FAILED: `{rec['error']}`", ""]
    ggx = rec["brdf"] == "ggx"  # no truth floor: the noise-free render's instead
    floor = rec["noise_floor"].get("rel_rms") if ggx else rec["truth_floor"]["rel_rms"]
    lines += [
        f"{rec['description']}. Rig `{rec['rig']}`, material `{rec['material']}` ({rec['materials']} "
        f"material{'s' if rec['materials'] > 1 else ''}), truth `{rec['brdf']}`, object `{rec['object']}`, "
        f"{rec['sensor_bits']}-bit sensor; {rec['n_points']:,} points, {rec['n_lights']} lights, "
        f"{rec['fit_lights']} fitted, held out {rec['held_out_lights']}. Points with a fit-light sample: "
        f"{rec['observed_share']:.1%}; with a visible true lobe: {rec['visible_share']:.1%}. Held-out floors: "
        f"truth {_pct(rec['truth_floor']['rel_rms'])}"
        f"{' (' + rec['truth_floor']['reason'] + ')' if rec['truth_floor'].get('reason') else ''}, "
        f"noise-free render {_pct(rec['noise_floor'].get('rel_rms'))}"
        f"{' (the `/ floor` column below)' if ggx else ''}. Cell: {rec['seconds']:.0f} s.",
        "",
        "| model | variant | pd all / obs / vis | ps all / obs / vis | rough all / obs / vis "
        "| meas / pool / interp / unres | same, observed pts | rel-RMS | median rel | / floor | / reference | / plain | calib ps (m/p/i) "
        "| calib rough (m/p/i) | s first / warm |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    notes = []
    for model, mrec in rec["models"].items():
        name = f"{model}{'' if mrec['matched'] else ' (mismatch)'}"
        for key in ("plain", "reference"):
            r = mrec.get(key, {})
            if "error" in r:
                lines.append(f"| {name} | {key} | FAILED: `{r['error']}` |" + " |" * 12)
                continue
            if not r:
                continue
            ratio_floor = _ratio(r["holdout"]["rel_rms"], floor)
            lines.append(f"| {name} | {key} | " + " | ".join(_err_cells(r["errors"], mrec["matched"]))
                         + f" | - | - | {_pct(r['holdout']['rel_rms'])} | {_pct(r['holdout']['median_rel'])} | "
                         f"{_x(ratio_floor)} | - | - | - | - | {r['seconds']:.1f} |")
        for variant, v in mrec["variants"].items():
            if "error" in v:
                lines.append(f"| {name} | {variant} | FAILED: `{v['error']}` |" + " |" * 12)
                continue
            lines.append(
                f"| {name} | {variant} | " + " | ".join(_err_cells(v["errors"], mrec["matched"]))
                + f" | {_cov(v['coverage'])} | {_cov(v['coverage_observed'])} | "
                f"{_pct(v['holdout']['rel_rms'])} | {_pct(v['holdout']['median_rel'])} | "
                f"{_x(v['ratio_noise_floor'] if ggx else v['ratio_truth_floor'])} | {_x(v['ratio_reference'])} | "
                f"{_x(v['ratio_plain'])} | "
                f"{_calib_cell(v['calibration'], 'ps')} | {_calib_cell(v['calibration'], 'roughness')} | "
                f"{v['seconds_first']:.1f} / {v.get('seconds_second', float('nan')):.1f} |")
        lobes = mrec.get("reference", {}).get("lobes")
        if lobes:
            notes.append(f"Reference lobes ({model}), per true material: " + "; ".join(
                f"ps {lb['ps']:.3g}, roughness {lb['roughness']:.3g} ({lb['points']} pts"
                f"{'' if lb['identifiable'] else ', not identifiable'})" if lb["ps"] is not None and lb["roughness"]
                is not None else "n/a" for lb in lobes) + ".")
    return lines + [""] + [x for note in notes for x in (note, "")]


def run_info(args, command, seconds, complete) -> dict:
    """Where, when and how a run was made (for the report's header and the JSON)."""
    return {"command": command, "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "nproc": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "jax": jax.__version__, "seed": args.seed, "n_points": args.n_points, "holdout": args.holdout,
            "complete": complete, "seconds": seconds}


def _findings(path, where: str = "below") -> list[str]:
    """The hand-written `## Findings` section of an earlier report at `path` (kept across runs);
    a placeholder pointing at the tables `where` ("below", "above") where there is none."""
    try:
        text = Path(path).read_text()
    except OSError:
        text = ""
    if "## Findings" in text:
        body = text.split("## Findings", 1)[1].split("\n## ", 1)[0]
        return ["## Findings" + body.rstrip("\n"), ""]
    return ["## Findings", "", f"(to be written by hand from the tables {where})", ""]


def write_report(records, run, out, json_out=True):
    """`out` (markdown) and, with `json_out`, the JSON next to it, from per-cell `records`
    (`run_cell`) and `run` (`run_info`)."""
    out = Path(out)
    shows = must_shows(records)
    met = sum(1 for s in shows if s["met"])
    failed = [s for s in shows if s["met"] is False]
    lines = [
        "# Method I on the rig zoo, with held-out lights",
        "",
        f"- Command: `{run['command']}`",
        f"- Date: {run['date']}; machine: `nproc` = {run['nproc']}, {run['platform']}, Python "
        f"{run.get('python', '?')}, jax {run.get('jax', '?')}; float64. The machine is shared: timings vary.",
        f"- Seed {run['seed']} (rig, sensor noise and held-out lights); n_points "
        f"{run['n_points'] or 'zoo default (~2500)'}; held out {run['holdout']:.0%} of each cell's lights; "
        f"{'all cells done' if run['complete'] else f'PARTIAL: {len(records)} cells so far'}; "
        f"{run['seconds'] / 60:.1f} min in all.",
        "- Variants: `prior` = `LocalOptions(model=m)` (shared reflectance prior, default); `gates` = "
        "`prior=False` (pooled lobes / window fills); `paper` = `paper=True`. `plain` = `fit_rows` output "
        "of every point, no fill; `reference` = one joint (ps, roughness) per TRUE material, pd re-fitted "
        "per point (see `benchmarks/rigs.py`).",
        "- Errors: median relative error over all points / over observed points (with a usable fit-light "
        "sample; the others have their pd filled from neighbours and their lobe filled or unresolved) / over "
        "points whose true lobe is visible in a fit light (an observed, lit fit-light sample whose true "
        "specular part is >= 5 % of its noise-free radiance). `*`: ps of the other model (a different lobe; "
        "not a target). Roughness only where truth and model agree. Coverage: share of points per status. Held-out: `holdout_error(..., "
        "gi='none')` over the held-out lights; floor: `truth_holdout_error` (for GGX cells, where there is "
        "none, the noise-free render, marked `(clean)`). Calibration: share of points with |est - truth| "
        "<= std, per status (m measured, p pooled, i interpolated with finite std), matched model only; "
        "`z` the median |est - truth| / std (0.67 for calibrated Gaussian errors, >> 1 overconfident). "
        "In a one-material cell every pooled point shares one lobe, so its share is close to 0 or 100 %.",
        "- Timings: `s first` is the first `estimate_local` call of the variant on the cell (includes JAX "
        "compilation unless an earlier cell compiled the same shapes), `s warm` the second call on the "
        "same scan.",
        "",
        "## Summary (prior variant; the truth's model, both models for GGX cells)",
        "",
        *_summary_rows(records),
        "",
        f"## Must-shows: {met} of {len(shows)} met",
        "",
    ]
    if failed:
        lines += ["Not met: " + "; ".join(f"{s.get('label', s['cell'])}: {s['check']} ({s['value']})"
                                          for s in failed) + ".", ""]
    notes = _mismatch_notes(records)
    if notes:
        lines += ["GGX cells (the truth is in neither model): " + "; ".join(notes) + ".", ""]
    lines += ["| cell | model | check | value | status | context |", "|---|---|---|---:|---|---|"]
    for s in shows:
        lines.append(f"| {s['cell']} | {s.get('model', '-')} | {s['check']} | {s['value']} | {_mark(s['met'])} "
                     f"| {s.get('context', '')} |")
    lines += ["", "## Cells", ""]
    for rec in records:
        lines += _cell_section(rec)
    lines += ["", *_findings(out, "above")]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    if json_out:
        payload = {**run, "targets": TARGETS, "must_shows": shows, "cells": records}
        out.with_suffix(".json").write_text(json.dumps(payload, indent=1, default=_json_default) + "\n")


def render_report(json_path, out):
    """Rewrite the markdown `out` from a JSON written by an earlier run (no estimation)."""
    data = json.loads(Path(json_path).read_text())
    run = {k: v for k, v in data.items() if k not in ("targets", "must_shows", "cells")}
    write_report(data["cells"], run, out, json_out=False)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _sanitise(obj):
    """NaN / inf -> None, recursively (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _sanitise(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitise(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return _finite(obj)
    return obj


def main(argv=None):
    from data_synth import zoo

    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", default=",".join(zoo.CELLS), help="comma-separated cell names (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-points", type=int, default=None, help="mesh size (default: the zoo's, ~2500)")
    parser.add_argument("--holdout", type=float, default=0.25, help="share of lights held out")
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--no-repeat", action="store_true", help="run each variant once (no warm timing)")
    parser.add_argument("--out", default="benchmarks/RESULTS_rigs.md")
    parser.add_argument("--render", metavar="JSON", help="only rewrite --out from this run's JSON")
    args = parser.parse_args(argv)
    if args.render:
        render_report(args.render, args.out)
        print(Path(args.out).read_text())
        return
    cells = [c for c in args.cells.split(",") if c]
    unknown = [c for c in cells if c not in zoo.CELLS]
    if unknown:
        parser.error(f"unknown cells {unknown}; choose from {sorted(zoo.CELLS)}")
    models = tuple(m for m in args.models.split(",") if m)
    variants = tuple(v for v in args.variants.split(",") if v)
    command = "python3 -m benchmarks.rigs" + ("" if not argv else " " + " ".join(argv))
    t0 = time.perf_counter()
    records = []
    for name in cells:
        try:
            rec = run_cell(name, seed=args.seed, n_points=args.n_points, fraction=args.holdout, models=models,
                           variants=variants, repeat=not args.no_repeat, log=lambda s: print(s, flush=True))
        except Exception as exc:  # noqa: BLE001 - one broken cell must not stop the run
            rec = {"cell": name, "error": _err_string(exc)}
            print(f"[{name}] FAILED {rec['error']}", flush=True)
        records.append(_sanitise(rec))
        write_report(records, run_info(args, command, time.perf_counter() - t0, len(records) == len(cells)),
                     args.out)
    print(Path(args.out).read_text())


if __name__ == "__main__":
    main()
