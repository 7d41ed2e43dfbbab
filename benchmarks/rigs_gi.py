"""Benchmark: Methods I, II, III and auto on the rig zoo's global-illumination cells.

Run: `python3 -m benchmarks.rigs_gi [--cells a,b] [--seed 0] [--photons 200000] [--iterations 20]
[--no-repeat] [--defaults-cells a,b] [--out benchmarks/RESULTS_rigs_gi.md]` (the JSON with every number lands next to
the markdown, `RESULTS_rigs_gi.json`; both are rewritten after each cell; the hand-written
`## Findings` section of an earlier report is kept).

Cells: `data_synth.zoo.GI_CELLS`, every observation path-traced by the independent path tracer
(`zoo.render_gi`, cached on disk: `zoo.gi_cache_dir()`), Ward truth, 1 % noise, 12 bits.
Per cell, on the whole scan (no held-out lights), Ward model throughout:

- `I`: `estimate_local(scan, LocalOptions(model='ward'))` (direct light only, shared prior);
- `II`: `estimate_radiosity(scan, RadiosityOptions(local=LocalOptions(model='ward')))`;
- `III`: `estimate_photon(scan, PhotonOptions(photons=P, iterations=K))`, the other options
  at their defaults; `III no lobe prior` the same with `lobe_prior=False` (run once, no target);
- `auto`: `estimate_auto(scan, AutoOptions(local=LocalOptions(model='ward'),
  photon={'photons': P, 'iterations': K}))`.

Each method runs twice in a row on the same scan (one `RayCaster`): `s first` includes JAX
compilation and the form-factor casts (cached in memory and on disk by `jaxrefl.geometry.formfactors`,
so a later method or run may read them), `s warm` is the second run. The time targets
compare warm runs.

Errors (`summarize`): per point, the relative error `|est - truth| / truth` (pd: mean over
RGB; roughness: Ward alpha), median and 90th percentile over every *observed* point (at least
one observed sample: valid, unsaturated), whatever its status; `pd interrefl.`: median pd error
over the observed points whose median share of interreflected light (path tracer less the exact
direct render, over their seen, lit observations) is >= 10 % (`interreflected_points`). On the
fold: the mean and median relative pd error of the observed points within `NEAR_FOLD` (2 cm) of
the fold line, the line's own vertices (distance below half the mesh spacing) left out as in
`benchmarks/inverse_photon_bench.py`. `misfit` (Method III, `est.meta['misfit']`): the
noise-weighted image difference at the estimate over that at the truth through the same forward
model.

Targets (`target_checks`): Method III's mean pd error within 2 cm of the fold <= 2 %; on the
bowl Method III's median pd error <= 3 %, ps and roughness <= 10 %; Method III's misfit ratio
<= 1.1 on every cell; on every cell auto's median pd and ps errors each within 10 % of the
lowest of Methods I-III (`<= 1.1 x`), and its warm time <= 1.5 x the warm time of the method
with the lowest pd error.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from benchmarks.rigs import _err_string, _findings, _finite, _json_default, _sanitise  # noqa: E402

METHODS = ("I", "II", "III", "III no lobe prior", "auto")
DEFAULTS = "III defaults"  # Method III at `PhotonOptions()` (1M photons, 50 iterations), run once, no target
PRIOR = "III no lobe prior"  # Method III with `lobe_prior=False`, run once, no target
ONCE = (DEFAULTS, PRIOR)
SINGLE = ("I", "II", "III")
NEAR_FOLD = 0.02  # m
INTERREFLECTED = 0.1  # median share of interreflected light that makes a point "interreflected"
PHOTONS = 200_000
ITERATIONS = 20
TARGETS = {"fold_pd_near": 0.02, "bowl_pd": 0.03, "bowl_ps": 0.10, "bowl_roughness": 0.10, "misfit_ratio": 1.1,
           "auto_error": 1.10, "auto_time": 1.5}


def relative_errors(value, truth) -> np.ndarray:
    """Per-point relative error `(N,)`: `|value - truth| / |truth|`, the mean over channels
    for `(N, C)` arrays (pd); `nan` where the truth is 0."""
    value, truth = np.asarray(value, float), np.asarray(truth, float)
    n = len(truth)
    t = np.abs(truth).reshape(n, -1)
    d = np.abs(value - truth).reshape(n, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.where(t > 1e-12, d / np.where(t > 1e-12, t, 1.0), np.nan)
    return err.mean(axis=1)


def near_fold_mask(distance, observed, near=NEAR_FOLD) -> np.ndarray:
    """`(N,)` bool: observed points within `near` [m] of the fold line, the line's own vertices
    (closer than half the smallest nonzero distance) left out."""
    d = np.abs(np.asarray(distance, float))
    nonzero = d[d > 1e-12]
    h = float(nonzero.min()) if nonzero.size else 0.0
    return np.asarray(observed, bool) & (d < near) & (d > 0.5 * h)


def _stats(err, mask):
    e = err[mask & np.isfinite(err)]
    if not e.size:
        return {"median": None, "p90": None, "mean": None, "points": 0}
    return {"median": float(np.median(e)), "p90": float(np.percentile(e, 90)), "mean": float(e.mean()),
            "points": int(e.size)}


def summarize(pd, ps, roughness, truth, observed, near=None, interreflected=None) -> dict:
    """Errors of one estimate: `truth` {'pd', 'ps', 'roughness'} arrays; `observed` `(N,)` the
    points summarised; `near` `(N,)` optional mask (the fold's band: pd only);
    `interreflected` `(N,)` optional mask (`pd_interreflected`, pd only)."""
    out = {}
    for name, value in (("pd", pd), ("ps", ps), ("roughness", roughness)):
        out[name] = _stats(relative_errors(value, truth[name]), np.asarray(observed, bool))
    if near is not None:
        out["pd_near_fold"] = _stats(relative_errors(pd, truth["pd"]), np.asarray(near, bool))
    if interreflected is not None:
        out["pd_interreflected"] = _stats(relative_errors(pd, truth["pd"]),
                                          np.asarray(observed, bool) & np.asarray(interreflected, bool))
    return out


def interreflected_points(clean, direct, seen, share=INTERREFLECTED) -> np.ndarray:
    """`(N,)` bool: points whose median share of interreflected light, `(clean - direct) /
    clean` (RGB means) over their seen observations with light (`seen` `(N, M)` bool, clean > 0),
    is at least `share`."""
    c, d = np.asarray(clean, float).mean(-1), np.asarray(direct, float).mean(-1)
    ok = np.asarray(seen, bool) & (c > 0)
    ratio = np.where(ok, (c - d) / np.where(ok, c, 1.0), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: points never seen lit
        med = np.nanmedian(ratio, axis=1)
    return np.isfinite(med) & (med >= share)


def _get(rec, *keys):
    for k in keys:
        if not isinstance(rec, dict) or k not in rec:
            return None
        rec = rec[k]
    return rec


def _le(value, limit):
    return None if value is None else bool(value <= limit)


def target_checks(rec) -> list[dict]:
    """The must-show checks of one cell record (`run_cell`): dicts with `cell`, `check`,
    `value`, `limit`, `met` (None where a number is missing, e.g. a method failed)."""
    cell, runs = rec["cell"], rec.get("methods", {})
    out = []

    def add(check, value, limit, context="", ratio=False):
        out.append({"cell": cell, "check": check, "value": _finite(value), "limit": limit,
                    "met": _le(_finite(value), limit), "context": context, "ratio": ratio})

    if rec.get("object") == "fold":
        add("III: mean pd error within 2 cm of the fold <= 2 %",
            _get(runs, "III", "errors", "pd_near_fold", "mean"), TARGETS["fold_pd_near"])
    if rec.get("object") == "bowl":
        for key in ("pd", "ps", "roughness"):
            add(f"III: median {key} error <= {TARGETS['bowl_' + key]:.0%}", _get(runs, "III", "errors", key, "median"),
                TARGETS["bowl_" + key])
    add("III: misfit ratio <= 1.1", _get(runs, "III", "misfit", "ratio"), TARGETS["misfit_ratio"], ratio=True)
    singles = {k: runs[k] for k in SINGLE if k in runs and "error" not in runs[k]}  # not DEFAULTS
    auto = runs.get("auto", {})
    for key in ("pd", "ps"):
        errs = {k: _get(v, "errors", key, "median") for k, v in singles.items()}
        errs = {k: v for k, v in errs.items() if v is not None}
        best = min(errs, key=errs.get) if errs else None
        a = _get(auto, "errors", key, "median")
        ratio = a / errs[best] if best is not None and a is not None and errs[best] > 0 else None
        add(f"auto: median {key} error <= 1.1x the best single method's", ratio, TARGETS["auto_error"],
            f"best {best}" if best else "", ratio=True)
    pd_errs = {k: _get(v, "errors", "pd", "median") for k, v in singles.items()}
    pd_errs = {k: v for k, v in pd_errs.items() if v is not None}
    best = min(pd_errs, key=pd_errs.get) if pd_errs else None
    t_auto = _get(auto, "seconds_warm") or _get(auto, "seconds_first")
    t_best = None if best is None else (_get(singles[best], "seconds_warm") or _get(singles[best], "seconds_first"))
    add("auto: time <= 1.5x the best single method's (by pd)", t_auto / t_best if t_auto and t_best else None,
        TARGETS["auto_time"], f"best {best}" if best else "", ratio=True)
    return out


def _methods(photon):
    from jaxrefl.methods.auto import AutoOptions, estimate_auto
    from jaxrefl.methods.inverse_photon import PhotonOptions, estimate_photon
    from jaxrefl.methods.local import LocalOptions, estimate_local
    from jaxrefl.methods.radiosity import RadiosityOptions, estimate_radiosity

    ward = LocalOptions(model="ward")
    return {
        "I": lambda scan, caster: estimate_local(scan, ward, caster),
        "II": lambda scan, caster: estimate_radiosity(scan, RadiosityOptions(local=ward), caster),
        "III": lambda scan, caster: estimate_photon(scan, PhotonOptions(**photon), caster),
        "auto": lambda scan, caster: estimate_auto(scan, AutoOptions(local=ward, photon=dict(photon)), caster),
        DEFAULTS: lambda scan, caster: estimate_photon(scan, PhotonOptions(), caster),
        PRIOR: lambda scan, caster: estimate_photon(scan, PhotonOptions(**photon, lobe_prior=False), caster),
    }


def _method_meta(est) -> dict:
    meta = est.meta
    out = {}
    if isinstance(meta.get("seconds"), dict):
        out["stages"] = {k: _finite(v) for k, v in meta["seconds"].items() if isinstance(v, (int, float))}
    if "misfit" in meta:
        out["misfit"] = {k: _finite(v) for k, v in meta["misfit"].items()}
    if "best_iteration" in meta:
        out["best_iteration"] = int(meta["best_iteration"])
        out["retraces"] = len(meta.get("retraces", []))
    auto = meta.get("auto")
    if isinstance(auto, dict):
        out["auto"] = {k: auto[k] for k in ("choice", "reason", "counts") if k in auto}
        runs = meta.get("runs") or auto.get("runs") or {}
        photon = runs.get("photon") if isinstance(runs, dict) else None
        if isinstance(photon, dict) and "misfit" in photon:
            out["misfit"] = {k: _finite(v) for k, v in photon["misfit"].items()}
    return out


def run_cell(name, seed=0, n_points=None, photon=None, methods=METHODS, repeat=True, log=print) -> dict:
    """Every measurement of one GI cell (JSON-ready; a failing method records `error`)."""
    from data_synth import zoo
    from jaxrefl.geometry.raycast import RayCaster

    photon = dict(photons=PHOTONS, iterations=ITERATIONS) if photon is None else dict(photon)
    t_cell = time.perf_counter()
    spec = zoo.GI_CELLS[name]
    t0 = time.perf_counter()
    scan, info = zoo.make_cell(name, seed=seed, n_points=n_points)
    t_make = time.perf_counter() - t0
    observed = scan.observed().any(axis=1)
    near = near_fold_mask(zoo.fold_distance(scan.vertices), observed) if spec.object == "fold" else None
    inter = interreflected_points(info["clean"], info["direct"], scan.valid & info["lit"])
    truth = {"pd": scan.true_pd, "ps": scan.true_ps, "roughness": scan.true_alpha}
    gi = info["gi"]
    rec = {"cell": name, "description": spec.description, "rig": spec.rig, "material": spec.material,
           "object": spec.object, "brdf": spec.brdf, "seed": int(seed), "n_points": scan.n_points,
           "n_lights": scan.n_lights, "samples": spec.samples, "observed_points": int(observed.sum()),
           "observed_share": float(observed.mean()), "valid_share": float(scan.valid.mean()),
           "interreflected_points": int((inter & observed).sum()),
           "lit_share_of_valid": float((scan.valid & info["lit"]).sum() / max(scan.valid.sum(), 1)),
           "indirect_share_median": gi["indirect_share_median"],
           "indirect_share_p90": _indirect_p90(scan, info),
           "mc_relative_stderr_median": gi["mc_relative_stderr_median"],
           "render_seconds": gi["seconds"], "render_cached": gi["cached"], "make_seconds": t_make,
           "photon": photon, "methods": {}}
    if near is not None:
        rec["near_fold_points"] = int(near.sum())
    log(f"[{name}] {scan.n_points} points, {scan.n_lights} lights, render {gi['seconds']:.0f} s "
        f"({'cached' if gi['cached'] else 'new'}), indirect share median {gi['indirect_share_median']:.2f}")
    caster = RayCaster(scan.vertices, scan.faces)
    runners = _methods(photon)
    for key in methods:
        entry = {}
        try:
            t0 = time.perf_counter()
            est = runners[key](scan, caster)
            entry["seconds_first"] = time.perf_counter() - t0
            if repeat and key not in ONCE:
                t0 = time.perf_counter()
                est = runners[key](scan, caster)
                entry["seconds_warm"] = time.perf_counter() - t0
            entry["errors"] = summarize(est.pd, est.ps, est.roughness, truth, observed, near, inter)
            entry["status"] = _status_counts(est.status)
            entry.update(_method_meta(est))
        except Exception as exc:  # noqa: BLE001 - a benchmark records, it does not stop
            entry["error"] = _err_string(exc)
        rec["methods"][key] = entry
        e = entry.get("errors", {})
        log(f"[{name}] {key}: " + (entry["error"] if "error" in entry else
            f"pd {_pct(_get(e, 'pd', 'median'))} ps {_pct(_get(e, 'ps', 'median'))} "
            f"rough {_pct(_get(e, 'roughness', 'median'))}"
            + (f" near fold {_pct(_get(e, 'pd_near_fold', 'mean'))}" if near is not None else "")
            + (f" misfit {entry['misfit']['ratio']:.3f}" if entry.get("misfit", {}).get("ratio") else "")
            + f" s {entry['seconds_first']:.1f}"
            + (f" / {entry['seconds_warm']:.1f}" if "seconds_warm" in entry else "")
            + (f" auto {entry['auto'].get('choice')}" if "auto" in entry else "")))
    rec["seconds"] = time.perf_counter() - t_cell
    return rec


def _status_counts(status) -> dict:
    from jaxrefl.status import STATUS_NAMES

    codes, counts = np.unique(np.asarray(status), return_counts=True)
    return {(STATUS_NAMES[c] if 0 <= c < len(STATUS_NAMES) else str(c)): int(n) for c, n in zip(codes, counts)}


def source_hash() -> str:
    """sha256 (12 hex digits) of jaxrefl's and data_synth's Python sources: which library
    state the numbers come from (the tree is edited between runs)."""
    import hashlib

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for f in sorted(list((root / "jaxrefl").rglob("*.py")) + list((root / "data_synth").glob("*.py"))):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def _indirect_p90(scan, info):
    sel = scan.valid & info["lit"]
    c, d = info["clean"].mean(-1)[sel], info["direct"].mean(-1)[sel]
    ok = c > 0
    return float(np.percentile((c - d)[ok] / c[ok], 90)) if ok.any() else None


# -- report -------------------------------------------------------------------------


def _pct(x, digits=2):
    return "-" if x is None else f"{100 * x:.{digits}f}%"


def _x(x):
    return "-" if x is None else f"{x:.2f}x"


def _mark(met):
    return {True: "met", False: "**not met**", None: "n/a"}[met]


def write_report(records, run, out, json_out=True):
    """`out` (markdown) and, with `json_out`, the JSON next to it."""
    out = Path(out)
    checks = [c for rec in records if "error" not in rec for c in target_checks(rec)]
    met = sum(1 for c in checks if c["met"])
    photon = run.get("photon", {})
    lines = [
        "# Methods I, II, III and auto on the rig zoo's global-illumination cells",
        "",
        f"- Command: `{run['command']}`",
        f"- Date: {run['date']}; machine: `nproc` = {run['nproc']}, {run['platform']}, Python {run['python']}, "
        f"jax {run['jax']}; float64; load average at start {run.get('load_start', float('nan')):.2f}, at end "
        f"{run.get('load_end', float('nan')):.2f} (a shared machine: timings vary).",
        f"- Seed {run['seed']}; sources (jaxrefl + data_synth) sha256 `{run.get('source_hash', '?')}`; "
        f"{'all cells done' if run['complete'] else f'PARTIAL: {len(records)} cells so far'}; "
        f"{run['seconds'] / 60:.1f} min in all.",
        "- Scenes: `data_synth.zoo.GI_CELLS`, every observation path-traced (`zoo.render_gi`: exact direct "
        "light + interreflection by `samples` paths, dark room), Ward truth, 1 % noise, 12 bits (full scale "
        "= largest radiance); `MC se` = the path tracer's median relative standard error per observation.",
        f"- Methods (Ward): I `LocalOptions(model='ward')`; II `RadiosityOptions(local=...)`; III "
        f"`PhotonOptions(photons={photon.get('photons')}, iterations={photon.get('iterations')})`, the rest "
        "default (final gather 1024 rays per observation, halved to the 8M budget; lm solver); auto "
        "`AutoOptions(local=..., photon=same)`. Each run twice; `s warm` is the second run (compiled, form "
        "factors cached), `s first` the first. `III defaults` (where listed): Method III at `PhotonOptions()` "
        "(1M photons per light, 50 iterations), run once, read by no target. `III no lobe prior`: Method III "
        "as above with `lobe_prior=False` (the final lobes from the fill only), run once, read by no target.",
        f"- Errors: median (p90) relative error over every observed point, whatever its status; roughness = "
        f"Ward alpha; `pd interrefl.`: median pd error of the observed points whose median share of "
        f"interreflected light is >= {INTERREFLECTED:.0%} (their count in the second column); `near fold`: "
        f"mean (median) relative pd error of observed points within "
        f"{NEAR_FOLD * 100:.0f} cm of the fold line (the line's own vertices left out). `misfit`: Method III's "
        "image difference at the estimate / at the truth through the same forward model (auto: its Method III "
        "run's, where it ran one).",
        "",
        "## Results",
        "",
        "| cell | points (obs. / interrefl.) | lights | indirect share med / p90 | MC se | method | pd | ps "
        "| roughness | pd interrefl. | near fold | misfit | s first / warm | auto's choice |",
        "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for rec in records:
        if "error" in rec:
            lines.append(f"| {rec['cell']} | FAILED: {rec['error']} |" + " |" * 12)
            continue
        first = True
        for key, m in rec["methods"].items():
            head = (f"| {rec['cell']} | {rec['n_points']} ({rec['observed_points']} / "
                    f"{rec.get('interreflected_points', '-')}) | {rec['n_lights']} | "
                    f"{_pct(rec['indirect_share_median'], 0)} / {_pct(rec['indirect_share_p90'], 0)} | "
                    f"{_pct(rec['mc_relative_stderr_median'], 1)} |") if first else "| | | | | |"
            first = False
            if "error" in m:
                lines.append(f"{head} {key} | FAILED: `{m['error']}` |" + " |" * 7)
                continue
            e = m["errors"]
            near = _get(e, "pd_near_fold")
            inter = _get(e, "pd_interreflected", "median")
            warm = "-" if m.get("seconds_warm") is None else f"{m['seconds_warm']:.1f}"
            misfit = _get(m, "misfit", "ratio")
            lines.append(
                f"{head} {key} | {_pct(e['pd']['median'])} ({_pct(e['pd']['p90'], 1)}) | "
                f"{_pct(e['ps']['median'])} ({_pct(e['ps']['p90'], 1)}) | "
                f"{_pct(e['roughness']['median'])} ({_pct(e['roughness']['p90'], 1)}) | {_pct(inter)} | "
                f"{_pct(near['mean']) + ' (' + _pct(near['median']) + ')' if near else '-'} | "
                f"{'-' if misfit is None else format(misfit, '.3f')} | {m['seconds_first']:.1f} / {warm} |")
            lines[-1] += f" {_get(m, 'auto', 'choice') or ''} |"
    lines += ["", f"## Targets: {met} of {len(checks)} met", "",
              "| cell | check | value | limit | status | context |", "|---|---|---:|---:|---|---|"]
    for c in checks:
        ratio = c.get("ratio", False)
        value = "-" if c["value"] is None else (f"{c['value']:.3f}" if ratio else _pct(c["value"]))
        limit = f"{c['limit']:g}" if ratio else _pct(c["limit"], 0)
        lines.append(f"| {c['cell']} | {c['check']} | {value} | {limit} | {_mark(c['met'])} | {c['context']} |")
    lines += [""] + _findings(out)
    lines += ["## Cells", ""]
    for rec in records:
        if "error" in rec:
            lines += [f"### {rec['cell']}", "", f"FAILED: `{rec['error']}`", ""]
            continue
        lines += [f"### {rec['cell']}", "",
                  f"{rec['description']}. Rig `{rec['rig']}`, material `{rec['material']}`, object "
                  f"`{rec['object']}`; {rec['n_points']} points ({rec['observed_share']:.0%} observed), "
                  f"{rec['n_lights']} observations, {rec['valid_share']:.0%} of (point, observation) pairs seen, "
                  f"{rec['lit_share_of_valid']:.0%} of those lit directly; {rec['samples']} paths per observation, "
                  f"render {rec['render_seconds']:.0f} s{' (from the cache)' if rec['render_cached'] else ''}"
                  + (f"; {rec['near_fold_points']} points within 2 cm of the fold" if "near_fold_points" in rec
                     else "") + ".", ""]
        for key, m in rec["methods"].items():
            if "error" in m:
                continue
            bits = []
            if m.get("stages"):
                bits.append("stages [s] " + ", ".join(f"{k} {v:.1f}" for k, v in m["stages"].items()
                                                     if v is not None))
            if "best_iteration" in m:
                bits.append(f"best iteration {m['best_iteration']}, re-traces {m['retraces']}")
            if m.get("misfit"):
                bits.append(f"misfit {m['misfit'].get('estimate'):.4g} / {m['misfit'].get('truth'):.4g}")
            if m.get("auto"):
                bits.append(f"auto: {m['auto'].get('choice')} ({m['auto'].get('reason', '')})")
            bits.append("status counts " + ", ".join(f"{k}: {v}" for k, v in m["status"].items()))
            lines.append(f"- {key}: " + "; ".join(bits) + ".")
        lines.append("")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    if json_out:
        payload = {**run, "targets": TARGETS, "checks": checks, "cells": records}
        out.with_suffix(".json").write_text(json.dumps(_sanitise(payload), indent=1, default=_json_default) + "\n")


def render_report(json_path, out):
    """Rewrite the markdown `out` from a JSON written by an earlier run (no estimation)."""
    data = json.loads(Path(json_path).read_text())
    run = {k: v for k, v in data.items() if k not in ("targets", "checks", "cells")}
    write_report(data["cells"], run, out, json_out=False)


def run_info(args, command, seconds, complete, load_start, sources=None) -> dict:
    return {"command": command, "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "nproc": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "jax": jax.__version__, "source_hash": sources or source_hash(), "seed": args.seed,
            "n_points": args.n_points, "complete": complete,
            "seconds": seconds, "load_start": load_start, "load_end": os.getloadavg()[0],
            "photon": {"photons": args.photons, "iterations": args.iterations}}


def main(argv=None):
    from data_synth import zoo

    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", default=",".join(zoo.GI_CELLS), help="comma-separated GI cells (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-points", type=int, default=None, help="mesh size (default: each cell's)")
    parser.add_argument("--photons", type=int, default=PHOTONS, help="Method III photons per light")
    parser.add_argument("--iterations", type=int, default=ITERATIONS, help="Method III outer iterations")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--no-repeat", action="store_true", help="run each method once (no warm timing)")
    parser.add_argument("--defaults-cells", default="",
                        help=f"cells on which '{DEFAULTS}' also runs (Method III at PhotonOptions() defaults, once)")
    parser.add_argument("--out", default="benchmarks/RESULTS_rigs_gi.md")
    parser.add_argument("--render", metavar="JSON", help="only rewrite --out from this run's JSON")
    args = parser.parse_args(argv)
    if args.render:
        render_report(args.render, args.out)
        return
    cells = [c for c in args.cells.split(",") if c]
    unknown = [c for c in cells if c not in zoo.GI_CELLS]
    if unknown:
        parser.error(f"unknown cells {unknown}; choose from {sorted(zoo.GI_CELLS)}")
    methods = tuple(m for m in args.methods.split(",") if m)
    command = "python3 -m benchmarks.rigs_gi" + ("" if not argv else " " + " ".join(argv))
    photon = {"photons": args.photons, "iterations": args.iterations}
    load_start = os.getloadavg()[0]
    sources = source_hash()  # at the start: the tree may be edited while the benchmark runs
    t0 = time.perf_counter()
    records = []
    for name in cells:
        try:
            extra = (DEFAULTS,) if name in args.defaults_cells.split(",") else ()
            rec = run_cell(name, seed=args.seed, n_points=args.n_points, photon=photon, methods=methods + extra,
                           repeat=not args.no_repeat, log=lambda s: print(s, flush=True))
        except Exception as exc:  # noqa: BLE001 - one broken cell must not stop the run
            rec = {"cell": name, "error": _err_string(exc)}
            print(f"[{name}] FAILED {rec['error']}", flush=True)
        records.append(_sanitise(rec))
        write_report(records, run_info(args, command, time.perf_counter() - t0, len(records) == len(cells),
                                       load_start, sources), args.out)
    print(Path(args.out).read_text())


if __name__ == "__main__":
    main()
