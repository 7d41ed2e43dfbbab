"""The `jaxrefl` command line: dense surface reflectance of a scanned object by inverse rendering.

A scan bundle (`.npz`: mesh, normals, camera, lights, linear images; `docs/formats.md`)
goes in, a result file (per-point pd, ps, roughness, standard deviations, status) comes
out. Commands: `synth` and `render` (synthetic scans), `info`, `select-lights`, `capture`
and `ingest` (your own rig and photographs), `estimate` (Methods I, II, III and auto,
optionally with held-out lights), `batch`, `maps`, `relight`, `export` (PLY), `fold`,
`figure18`, `table1` and `demo` (the paper's experiments). Bad input ends with one line
on stderr naming the field, exit code 2, and no output file; so does an output path that
names one of the command's inputs or an existing path that is not a regular file.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import sys

import numpy as np

__all__ = ["main"]


def _progress() -> bool:
    return sys.stderr.isatty()


def _int_list(text: str):
    if text in ("all", ""):
        return None
    try:
        return [int(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers or 'all', got {text!r}")


def _add_synth(sub):
    p = sub.add_parser("synth", help="render a synthetic scan bundle with known reflectance")
    p.add_argument("object", choices=["A", "B", "C", "D", "E", "V"],
                   help="procedural object (A-E: the paper's analogues; V: a convex glazed vase)")
    p.add_argument("--out", required=True, help="scan bundle to write (.npz)")
    p.add_argument("--resolution", type=int, default=64, help="mesh resolution (voxels across the object)")
    p.add_argument("--setup", choices=["diffuse", "glossy", "glazed"], default="glossy",
                   help="Object E set-up; 'glazed': any object under a uniform Ward glaze (ps 0.3, alpha 0.08)")
    p.add_argument("--rig", choices=["scanner", "pinhole"], default=None,
                   help="rotating-head scanner (default for A-D) or fixed pinhole camera (default for E)")
    p.add_argument("--lights", type=_int_list, default=None, help="rack indices, e.g. 0,7,23 (default all 60)")
    p.add_argument("--model", choices=["torrance-sparrow", "ward"], default="torrance-sparrow")
    p.add_argument("--gi", action="store_true", help="global illumination by the brute-force path tracer")
    p.add_argument("--samples", type=int, default=64, help="paths per observation with --gi")
    p.add_argument("--noise", type=float, default=0.0, help="relative Gaussian noise (0.01 = 1%%)")
    p.add_argument("--read-noise", type=float, default=0.0, help="additive noise, fraction of full scale")
    p.add_argument("--bits", type=int, default=None, help="quantise to this many bits (e.g. 8, 12)")
    p.add_argument("--full-scale", type=float, default=None, help="sensor maximum (default: brightest value)")
    p.add_argument("--saturate", action="store_true", help="clip at full scale and flag saturation")
    p.add_argument("--intensity", type=float, default=1.0, help="radiant intensity of each light [W/sr]")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON report on stdout")


def _add_render(sub):
    p = sub.add_parser("render", help="a picture of a scan: radiance under one light or a truth map")
    p.add_argument("scan", help="scan bundle (.npz)")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--what", default="radiance",
                   choices=["radiance", "pd", "ps", "roughness", "normals", "observations"],
                   help="radiance under --light, a ground-truth map, normals, or observations per point")
    p.add_argument("--light", type=int, default=0, help="observation index for --what radiance")
    p.add_argument("--view", choices=["auto", "cylindrical", "camera"], default="auto",
                   help="cylindrical unwrap about the y axis, or the scan's pinhole camera")
    p.add_argument("--width", type=int, default=512, help="image width [px] of a cylindrical view")


def _add_demo(sub):
    p = sub.add_parser("demo", help="the main job on the built-in synthetic default")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--resolution", type=int, default=48, help="mesh resolution of the demo objects")
    p.add_argument("--samples", type=int, default=64, help="paths per observation for the GI render")
    p.add_argument("--seed", type=int, default=0)


def _add_select_lights(sub):
    p = sub.add_parser("select-lights", help="choose capture lights among the bundle's candidates (§2.2)")
    p.add_argument("scan", help="scan bundle (.npz); radiance optional (planning before capture)")
    p.add_argument("--json", action="store_true", help="print the selection as one JSON object")
    p.add_argument("--plot", default=None, help="write the coverage plot (Figure 8 analogue) to this PNG")
    p.add_argument("--diffuse-deg", type=float, default=60.0, help="theta_th1: diffuse-only above [deg]")
    p.add_argument("--specular-deg", type=float, default=20.0, help="theta_th2: strong specular at or below [deg]")
    p.add_argument("--th1", type=float, default=0.8, help="share of the specular limit past which a stall stops")
    p.add_argument("--target", type=float, default=0.99, help="stop at this share of the specular limit")
    p.add_argument("--min-gain", type=float, default=0.0,
                   help="a light adding fewer than this fraction of points counts as a stall")
    p.add_argument("--paper", action="store_true", help="rank lights by raw D_p / S_p counts as the paper")
    p.add_argument("--exact", action="store_true", help="also solve the covering problem exactly (MILP)")
    p.add_argument("--ignore-images", action="store_true",
                   help="plan from geometry alone even if the bundle holds radiance")
    p.add_argument("--weighting", choices=["pixels", "points"], default="pixels",
                   help="count image pixels (area x cosine to the camera, as the paper) or points")


def _add_table1(sub):
    p = sub.add_parser("table1", help="Table 1 / Figure 8 analogue on the synthetic Objects A-D")
    p.add_argument("--out", required=True, help="folder for table1.md, table1.json and fig8_*.png")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--no-exact", action="store_true", help="skip the exact integer-program comparison")


def _add_estimate(sub):
    p = sub.add_parser("estimate", help="estimate per-point reflectance from a scan bundle")
    p.add_argument("scan", help="scan bundle (.npz) with radiance")
    p.add_argument("--out", required=True, help="result file to write (.npz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    g = p.add_argument_group("held-out lights (validation)")
    h = g.add_mutually_exclusive_group()
    h.add_argument("--holdout", type=float, default=None, metavar="F",
                   help="fit without this fraction of the lights (drawn with --holdout-seed), then relight the "
                        "estimate under them and report its error against their images")
    h.add_argument("--holdout-lights", default=None, metavar="I,J,...",
                   help="fit without these observations (comma-separated light indices) and report the error there")
    g.add_argument("--holdout-seed", type=int, default=0, help="seed of the lights --holdout draws")
    _add_estimate_options(p)


def _add_estimate_options(p):
    """The estimator options, shared by `estimate` and `batch`."""
    p.add_argument("--method", choices=["local", "radiosity", "photon", "auto"], default="local",
                   help="local: Method I, inverse local rendering (§3); radiosity: Method II, inverse "
                        "radiosity, diffuse interreflections removed (§4); photon: Method III, inverse "
                        "photon mapping, diffuse and specular interreflections removed (§5, Ward model); "
                        "auto: the cheapest of them predicted to meet --target-error, per region")
    p.add_argument("--model", choices=["torrance-sparrow", "ward"], default="torrance-sparrow")
    p.add_argument("--paper", action="store_true",
                   help="the paper's estimator: Eq. 5 single best diffuse sample, Eq. 7 from two samples, "
                        "the gated lobe fill (no shared prior)")
    p.add_argument("--window", type=int, default=5,
                   help="interpolation window W (a (W-1)/2-ring): where points without a lobe of their own "
                        "(with the prior: unresolved ones) take it from")
    p.add_argument("--steps", type=int, default=15, help="Newton steps of the polish in ln roughness (solver lm)")
    p.add_argument("--solver", choices=["lm", "optimistix"], default="lm")
    p.add_argument("--min-snr", type=float, default=3.0, help="ps / std(ps) needed to call it measured")
    p.add_argument("--prior", action=argparse.BooleanOptionalAction, default=True,
                   help="Method I: a shared reflectance prior (default): materials chosen by BIC, one lobe fitted "
                        "jointly per material, each point's lobe the posterior mode of its own samples and the "
                        "prior (status measured or pooled); --no-prior: the gated rules (--pool, --window)")
    p.add_argument("--materials", type=int, default=6, metavar="K",
                   help="most materials the prior tries (K = 1..this, chosen by BIC)")
    p.add_argument("--pool", action=argparse.BooleanOptionalAction, default=True,
                   help="with --no-prior: points without their own lobe share one fitted with same-colour "
                        "neighbours (default; --no-pool: window interpolation only)")
    g = p.add_argument_group("radiosity (Method II)")
    g.add_argument("--rays", type=int, default=256, help="form-factor rays per patch (vertex)")
    g.add_argument("--light-bin", type=float, default=0.1,
                   help="per-point lights: bin size [m] of the light configurations for later bounces")
    g.add_argument("--outer", type=int, default=3, help="alternations of pd and the specular part")
    g = p.add_argument_group("photon (Method III; always the Ward model)")
    g.add_argument("--photons", type=int, default=1_000_000, help="photons emitted per light")
    g.add_argument("--iterations", type=int, default=50, help="outer iterations (the paper's th_2)")
    g.add_argument("--photon-solver", choices=["lm", "simplex"], default="lm",
                   help="step (b): Newton in ln alpha with ps projected out, or the paper's downhill simplex")
    g.add_argument("--damping", type=float, default=0.5, help="share of each iteration's change taken")
    g.add_argument("--retrace-ess", type=float, default=0.3,
                   help="re-trace the photons when the effective sample size falls below this fraction")
    g.add_argument("--gather-rays", type=int, default=1024,
                   help="final-gather rays per observation for the first interreflection bounce (0: the photon "
                        "map gathers every bounce); halved until --gather-budget rays in all")
    g.add_argument("--gather-budget", type=int, default=8_000_000, help="most final-gather rays in all")
    g.add_argument("--min-fit-p", type=float, default=0.0,
                   help="a lobe counts as measured only if its fit passes a chi^2 test at this p-value (0: no "
                        "test; a misfit lobe's covariance is inflated by its chi^2 either way)")
    g.add_argument("--fill-pd-scale", type=float, default=0.2,
                   help="the lobe fill pools lobes of alike diffuse albedo: a neighbour whose pd is this share "
                        "apart counts e^-1 (0: pool regardless of pd)")
    g.add_argument("--fill-sd", type=float, default=0.02,
                   help="each point's lobe is a precision-weighted Huber estimate over the nearest measured lobes, "
                        "taken until they pin ln ps and ln alpha to this standard deviation")
    g.add_argument("--fill-neighbours", type=int, default=64, help="most measured lobes one point's lobe uses")
    g.add_argument("--polish", type=int, default=10, help="steps (a) at the final lobes")
    g = p.add_argument_group("auto (model only what the scene needs)")
    g.add_argument("--target-error", type=float, default=0.0,
                   help="relative pd error you accept (median per region): a cheaper method that reaches it is "
                        "kept; 0 (default): as accurate as the best method, within --tolerance. Method III is a "
                        "candidate with --model ward")
    g.add_argument("--tolerance", type=float, default=0.1,
                   help="a cheaper method is kept where its error, its interreflection bias inflated by the "
                        "error model's uncertainty, is within this fraction of the best method's prediction")


def _add_batch(sub):
    p = sub.add_parser("batch", help="estimate many scan bundles, resumable, here or on a Dask cluster")
    p.add_argument("source", help="folder of scan bundles (*.npz) or a text file listing bundle paths, one per line")
    p.add_argument("--out", required=True,
                   help="output folder: NAME_result.npz and NAME_result.json per scan, summary.csv, summary.md")
    p.add_argument("--scheduler", help="Dask scheduler address (e.g. tcp://host:8786): run the scans on its workers")
    p.add_argument("--retries", type=int, default=2,
                   help="cluster: re-runs of a scan whose estimate raised (bad input is never re-run)")
    _add_estimate_options(p)


def _add_capture(sub):
    p = sub.add_parser("capture", help="one image per planned light through a serial light rig (resumable)")
    p.add_argument("plan", help="plan JSON: {\"lights\": [...]}, a list, or select-lights --json output")
    p.add_argument("--out", required=True, help="session folder (images + manifest.json); rerun to resume")
    p.add_argument("--port", default=None, help="serial device of the light controller, e.g. /dev/ttyUSB0")
    p.add_argument("--simulate", nargs="?", const="", default=None, metavar="FAULTS",
                   help="use a simulated controller on a pty instead of --port; optional faults, e.g. "
                        "garble_rate=0.1,seed=1 or disconnect_after=20")
    p.add_argument("--camera-cmd", default=None,
                   help="shell template: must write the image to {out} (a temporary path) for light {light}; "
                        "with --simulate the default writes a small PNG")
    p.add_argument("--ext", default=".png", help="image file extension")
    p.add_argument("--baud", type=int, default=115200)
    p.add_argument("--timeout", type=float, default=0.5, help="reply timeout per try [s]")
    p.add_argument("--retries", type=int, default=3, help="re-sends after a timeout or garbled reply")
    p.add_argument("--backoff", type=float, default=0.05, help="wait before the first re-send [s], doubling")
    p.add_argument("--settle-timeout", type=float, default=10.0, help="time a positioner may take [s]")
    p.add_argument("--camera-timeout", type=float, default=60.0, help="time the camera command may take [s]")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def _add_fold(sub):
    p = sub.add_parser("fold", help="pd across the fold of Object E for one or more results (Fig. 12/16/21)")
    p.add_argument("scan", help="the Object E scan bundle the results were estimated from")
    p.add_argument("results", nargs="+", help="result files; label one as LABEL=PATH")
    p.add_argument("--out", required=True, help="figure to write (.png)")
    p.add_argument("--near", type=float, default=0.02, help="half-width [m] of the band around the fold")
    p.add_argument("--json", action="store_true", help="print the errors and profiles as JSON")


def _add_figure18(sub):
    p = sub.add_parser("figure18", help="Figure 18 analogue: Methods I and II on Objects A-D with interreflections")
    p.add_argument("--out", required=True, help="folder for figure18.md, figure18.json and the maps")
    p.add_argument("--resolution", type=int, default=48)
    p.add_argument("--samples", type=int, default=64, help="path-traced samples per observation")
    p.add_argument("--rays", type=int, default=256, help="form-factor rays per vertex")


def _add_info(sub):
    p = sub.add_parser("info", help="validate a scan bundle and print a summary")
    p.add_argument("scan")
    p.add_argument("--json", action="store_true")


def cmd_synth(args) -> int:
    from data_synth.scans import Sensor, make_scan

    from .io import save_scan

    sensor = Sensor(noise=args.noise, read_noise=args.read_noise, bits=args.bits,
                    full_scale=args.full_scale, saturate=args.saturate)
    scan, report = make_scan(
        args.object, resolution=args.resolution, setup=args.setup, rig=args.rig,
        lights=args.lights, model=args.model, global_illumination=args.gi,
        samples=args.samples, sensor=sensor, intensity=args.intensity, seed=args.seed,
        progress=_progress(),
    )
    save_scan(args.out, scan)
    report["out"] = args.out
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"wrote {args.out}: {report['points']} points x {report['lights']} lights, "
              f"{report['valid_fraction']:.1%} observed, {report['seconds']['total']:.1f} s")
    return 0


def cmd_render(args) -> int:
    from . import render
    from .io import load_scan

    scan = load_scan(args.scan)
    image = render.scan_picture(scan, args.what, args.light, args.view, args.width)
    render.save_png(args.out, image)
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]})")
    return 0


def cmd_info(args) -> int:
    from .io import load_scan

    scan = load_scan(args.scan)
    info = {
        "points": scan.n_points,
        "faces": int(len(scan.faces)),
        "lights": scan.n_lights,
        "per_point_lights": scan.light_pos.ndim == 3,
        "has_radiance": scan.radiance is not None,
        "observed_fraction": float(scan.observed().mean()) if scan.radiance is not None else 0.0,
        "saturation": scan.saturation,
        "truth": [k for k in ("true_pd", "true_ps", "true_sigma", "true_alpha", "true_normals")
                  if getattr(scan, k) is not None],
        "meta": {k: scan.meta[k] for k in ("object", "model", "global_illumination", "rig") if k in scan.meta},
    }
    if "rig" in info["meta"]:
        info["meta"]["rig"] = info["meta"]["rig"].get("type")
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k}: {v}")
    return 0


def cmd_select_lights(args) -> int:
    from .classify import Thresholds, classify_scan
    from .io import load_scan
    from .lights import exact_minimum, plot_coverage, select_lights

    for name in ("th1", "target", "min_gain"):
        if not 0 <= getattr(args, name) <= 1:
            raise ValueError(f"{name.replace('_', '-')}: must lie in [0, 1], got {getattr(args, name)}")
    scan = load_scan(args.scan)
    thresholds = Thresholds(diffuse_deg=args.diffuse_deg, specular_deg=args.specular_deg)
    m = classify_scan(scan, thresholds, use_observations=not args.ignore_images)
    weights = m.pixel_weight if args.weighting == "pixels" else None
    sel = select_lights(m.diffuse_only, m.strong_specular, m.seen, th1=args.th1, target=args.target,
                        min_gain=args.min_gain, marginal=not args.paper, weights=weights)
    result = sel.to_json()
    result["weighting"] = args.weighting
    result["thresholds_deg"] = {"diffuse": args.diffuse_deg, "specular": args.specular_deg}
    if args.exact:
        result["exact"] = exact_minimum(m.diffuse_only, m.strong_specular, m.seen, target=args.target,
                                        weights=weights)
    if args.plot:
        plot_coverage(sel, args.plot)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"selected {len(sel.selected)} of {scan.n_lights} lights: {sel.selected}")
        print(f"diffuse needed {sel.diffuse_only_count}; coverage diffuse {sel.diffuse_coverage:.2%} "
              f"(all {sel.diffuse_coverage_all:.2%}), specular {sel.specular_coverage:.2%} "
              f"(all {sel.specular_coverage_all:.2%})")
    return 0


def estimate_to_file(scan_path, out, args) -> dict:
    """Load the scan bundle `scan_path`, run `jaxrefl.estimate` with the method that `args`
    (the `estimate` options) choose (`api.method_from_options`), write the result file `out`
    atomically; the JSON summary. `estimate` and `batch` both go through here."""
    import time

    from .api import estimate, method_from_options
    from .checks import checked_scan, estimate_warnings
    from .io import load_scan
    from .result import save_result

    method = method_from_options(args)  # bad options fail before the bundle is read
    holdout, holdout_lights = getattr(args, "holdout", None), getattr(args, "holdout_lights", None)
    if holdout is not None and not 0 < holdout < 1:
        raise ValueError(f"holdout: the fraction of lights held out must lie in (0, 1), got {holdout}")
    if holdout_lights is not None:
        try:
            holdout = [int(t) for t in str(holdout_lights).split(",")]
        except ValueError:
            raise ValueError(f"holdout-lights: expected comma-separated light indices, "
                             f"got {holdout_lights!r}") from None
    t0 = time.perf_counter()
    scan = checked_scan(load_scan(scan_path))  # bad frames out before any held-out split; exit 2 if unphysical
    load_seconds = time.perf_counter() - t0
    est = estimate(scan, method, holdout=holdout, holdout_seed=getattr(args, "holdout_seed", 0),
                   progress=_progress())
    est.meta["seconds"] = {"load": load_seconds, **est.meta["seconds"]}
    save_result(out, est)
    return {"method": args.method, "model": est.model, "out": str(out), **estimate_summary(est, scan),
            "warnings": estimate_warnings(est, log=None)}


def estimate_summary(est, scan) -> dict:
    """Seconds per stage, coverage, status counts and (with ground truth) errors of `est`."""
    from .local import MEASURED, POOLED, STATUS_NAMES
    from .result import truth_errors

    observed = max(int(est.pd_measured.sum()), 1)
    summary = {
        "seconds": est.meta["seconds"],
        "points": int(len(est.status)),
        # measured: the lobe is the point's own; known: its own or pinned by the shared prior
        "coverage": float(np.sum(est.pd_measured & (est.status == MEASURED)) / observed),
        "known": float(np.sum(est.pd_measured & np.isin(est.status, (MEASURED, POOLED))) / observed),
        "status_counts": {name: int(np.sum(est.status == code)) for code, name in enumerate(STATUS_NAMES)},
    }
    summary.update({k: est.meta[k] for k in ("materials", "material_lobes", "outer_iterations", "form_factors",
                                             "light_configurations", "image_difference", "best_iteration",
                                             "retraces", "auto", "holdout", "misfit")
                    if k in est.meta})
    if "material_lobes" in summary:  # strict JSON: an unknown std or spread (inf) is null
        summary["material_lobes"] = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                                      for k, v in lobe.items()} for lobe in summary["material_lobes"]]
    if scan.true_pd is not None:
        summary["errors"] = truth_errors(est, scan)
    return summary


def cmd_estimate(args) -> int:
    summary = estimate_to_file(args.scan, args.out, args)
    if args.json:
        print(json.dumps(summary))
    else:
        counts = ", ".join(f"{n} {name}" for name, n in summary["status_counts"].items())
        print(f"wrote {args.out}: {summary['coverage']:.1%} of observed points measured, "
              f"{summary['known']:.1%} measured or pooled ({counts})")
        if "materials" in summary:
            print(materials_lines(summary))
        if "holdout" in summary:
            print(holdout_line(summary["holdout"]))
    if summary["warnings"]:  # one line on stderr; the details are in the logging records and --json
        print(f"jaxrefl estimate: warning: {'; '.join(summary['warnings'])}", file=sys.stderr)
    return 0


def materials_lines(summary: dict) -> str:
    """Text for the shared prior's materials (`materials`, `material_lobes` of a summary):
    the chosen K, then one line per material: its joint lobe with standard deviations and the
    spread of its points' lobes (standard deviations; roughness's relative, from ln roughness)."""
    def num(value, scale=1.0, root=False, unit=""):
        if value is None or not np.isfinite(value):
            return "?"
        return f"{scale * (np.sqrt(value) if root else value):.2g}{unit}"

    k = summary["materials"]
    lines = [f"prior: {k} material{'s' if k != 1 else ''} (BIC)"]
    for m, lobe in enumerate(summary.get("material_lobes", [])):
        lines.append(f"  material {m}: {lobe['points']} points, ps {lobe['ps']:.3g} +- {num(lobe['std_ps'])}, "
                     f"roughness {lobe['roughness']:.3g} rad +- {num(lobe['std_ln_roughness'], 100, unit='%')}; "
                     f"spread within it: ps {num(lobe['spread_ps'], root=True)}, "
                     f"roughness {num(lobe['spread_ln_roughness'], 100, True, '%')}"
                     + ("" if lobe.get("identifiable", True) else " (joint lobe not identifiable)"))
    return "\n".join(lines)


def holdout_line(h: dict) -> str:
    """One line of text for a `holdout` block (see `jaxrefl.holdout.holdout_error`)."""
    lights = h["lights"] if len(h["lights"]) <= 12 else h["lights"][:12] + ["..."]
    model = "direct light" if h["gi"] == "none" else f"direct light + {h['gi']} interreflection"
    head = f"held-out lights {lights} ({model}): "
    if h["rel_rms"] is None:
        return head + f"no error: {h.get('reason')}"
    text = (f"{head}relative RMS error {h['rel_rms']:.2%}, median per sample {h['median_rel']:.2%} "
            f"over {h['samples']} samples")
    truth = h.get("truth")
    if truth is not None:
        text += (f"; the ground truth's {truth['rel_rms']:.2%} (noise floor)" if truth["rel_rms"] is not None
                 else f"; ground truth: {truth.get('reason')}")
    per = [f"{i}: {e:.1%}" if e is not None else f"{i}: -" for i, e in zip(h["lights"], h["per_light_rel_rms"])]
    if len(per) > 1:
        text += "\n  per light: " + ", ".join(per[:24]) + (" ..." if len(per) > 24 else "")
    return text


def cmd_batch(args) -> int:
    from .batch import run_batch, summary_table

    if args.retries < 0:
        raise ValueError("retries: must be >= 0")
    client = None
    if args.scheduler:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("scheduler: needs Dask (pip install 'jaxrefl[batch]')") from None
        try:
            client = Client(args.scheduler)
        except OSError as exc:
            raise ValueError(f"scheduler: cannot reach {args.scheduler} ({exc})") from None
    try:
        records = run_batch(args.source, args.out, args, client=client, retries=args.retries, progress=_progress())
    finally:
        if client is not None:
            client.close()
    print(summary_table(records)[1], end="")
    failed = [r for r in records if r["status"] == "failed"]
    for r in failed:
        print(f"jaxrefl batch: failed: {r['name']} ({r['scan']}): {r['error']}", file=sys.stderr)
    return 1 if failed else 0


def cmd_capture(args) -> int:
    from .capture import CaptureError, capture, load_plan, shell_camera
    from .rig.serial import LinkOptions, RigError
    from .rig.simulator import Faults, Simulator

    if (args.port is None) == (args.simulate is None):
        raise ValueError("port: give exactly one of --port and --simulate")
    if args.camera_cmd is None and args.simulate is None:
        raise ValueError("camera-cmd: required with --port")
    plan = load_plan(args.plan)
    options = LinkOptions(baudrate=args.baud, timeout=args.timeout, retries=args.retries, backoff=args.backoff,
                          settle_timeout=args.settle_timeout)
    camera = shell_camera(args.camera_cmd, args.camera_timeout) if args.camera_cmd is not None else None
    sim = Simulator(max(60, max(plan.lights) + 1), Faults.parse(args.simulate)) if args.simulate is not None else None
    try:
        summary = capture(plan, args.out, sim.port if sim else args.port, camera or sim.camera, options=options,
                          ext=args.ext, progress=_progress())
    except (RigError, CaptureError, KeyboardInterrupt) as exc:
        saved, total = getattr(exc, "saved", (0, len(plan.lights)))
        print(f"jaxrefl capture: error: {str(exc) or 'interrupted'}; {saved} of {total} images saved in {args.out}, "
              "run the same command to resume", file=sys.stderr)
        return 3
    finally:
        if sim is not None:
            sim.stop()
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{args.out}: {summary['captured']} images captured, {summary['recovery']['entries_verified']} "
              f"already there; {'complete' if summary['complete'] else 'incomplete'}")
    return 0


def _add_ingest(sub):
    p = sub.add_parser("ingest", help="photographs of a capture folder (rig.json + mesh + images) to a scan bundle")
    p.add_argument("folder", help="capture folder holding rig.json (see README: capture folder)")
    p.add_argument("--out", required=True, help="scan bundle to write (.npz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def _add_relight(sub):
    p = sub.add_parser("relight", help="render an estimated object under a new point light")
    p.add_argument("result", help="result file (.npz) from jaxrefl estimate")
    p.add_argument("scan", help="the scan bundle the result was estimated from (geometry)")
    p.add_argument("--light", required=True, help="light position X,Y,Z [m] (--light=X,Y,Z when X < 0)")
    p.add_argument("--intensity", type=float, default=None,
                   help="radiant intensity [W/sr] (default: the scan's first light)")
    p.add_argument("--camera", default=None,
                   help="EX,EY,EZ[,TX,TY,TZ]: eye [m] and target (default: the object's centre); "
                        "default camera: the scan's camera for its first light")
    p.add_argument("--width", type=int, default=640, help="image width [px] of a fitted camera")
    p.add_argument("--height", type=int, default=480, help="image height [px] of a fitted camera")
    p.add_argument("--model-gi", choices=["none", "radiosity", "photon"], default="none",
                   help="interreflections added to the direct light")
    p.add_argument("--out", required=True, help="image to write: .png (tone-mapped sRGB) or .npy (linear)")
    p.add_argument("--reference", default=None,
                   help="'truth' (the scan's ground truth, same light and camera) or an image: .npy linear "
                        "radiance, or .png (sRGB, scaled to the relit image by least squares)")
    p.add_argument("--compare", default=None, help="write relit | reference | difference to this PNG")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def _add_maps(sub):
    p = sub.add_parser("maps", help="reflectance maps of a result (the paper's Figures 10-11)")
    p.add_argument("result", help="result file (.npz)")
    p.add_argument("scan", help="the scan bundle it was estimated from")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--view", choices=["auto", "cylindrical", "camera"], default="auto",
                   help="cylindrical unwrap (auto for scanner bundles) or the scan's camera")
    p.add_argument("--width", type=int, default=512, help="image width [px]")


def _add_export(sub):
    p = sub.add_parser("export", help="a result as a PLY mesh with per-vertex attributes")
    p.add_argument("result", help="result file (.npz)")
    p.add_argument("scan", help="the scan bundle it was estimated from")
    p.add_argument("--out", required=True, help="PLY file to write")


def _numbers(text, name, counts):
    try:
        values = [float(t) for t in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) not in counts or not all(np.isfinite(values)):
        raise ValueError(f"{name}: expected {' or '.join(map(str, counts))} comma-separated numbers, got {text!r}")
    return np.array(values)


def _result_and_scan(args):
    from .io import load_scan
    from .result import load_result

    est, scan = load_result(args.result), load_scan(args.scan)
    if len(est.pd) != scan.n_points:
        raise ValueError(f"result: {len(est.pd)} points, but the scan has {scan.n_points} vertices")
    return est, scan


def cmd_ingest(args) -> int:
    from .ingest import ingest
    from .io import save_scan

    scan = ingest(args.folder)
    save_scan(args.out, scan)
    report = {"out": args.out, "points": scan.n_points, "observations": scan.n_lights,
              "valid_fraction": float(scan.valid.mean()), "masked_samples": scan.meta["masked_samples"]}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"wrote {args.out}: {scan.n_points} points x {scan.n_lights} observations, "
              f"{report['valid_fraction']:.1%} valid; masked {report['masked_samples']}")
    return 0


def cmd_relight(args) -> int:
    from . import relight as rl
    from . import render
    from .ingest import read_image
    from .srgb import to_linear
    from .io import atomic_write
    from .raycast import RayCaster

    if args.compare and not args.reference:
        raise ValueError("compare: needs --reference")
    if not str(args.out).lower().endswith((".png", ".npy")):
        raise ValueError(f"out: must end in .png or .npy, got {args.out!r}")
    est, scan = _result_and_scan(args)
    light = _numbers(args.light, "light", (3,))
    intensity = float(scan.intensities()[0]) if args.intensity is None else args.intensity
    if args.width < 2 or args.height < 2:
        raise ValueError("width: width and height must be >= 2")
    if args.camera is None:
        camera = rl.scan_camera(scan, args.width, args.height)
    else:
        c = _numbers(args.camera, "camera", (3, 6))
        camera = rl.fit_camera(scan.vertices, c[:3], c[3:] if len(c) == 6 else None, args.width, args.height)
    caster = RayCaster(scan.vertices, scan.faces)
    radiance = rl.relight(scan.vertices, scan.faces, scan.normals, est, light, intensity, camera.center,
                          args.model_gi, caster)
    image = rl.picture(caster, scan.faces, radiance, camera)
    reference, label, summary = None, None, {}
    if args.reference == "truth":
        truth = rl.relight(scan.vertices, scan.faces, scan.normals, rl.truth_estimate(scan), light, intensity,
                           camera.center, args.model_gi, caster)
        reference, label = rl.picture(caster, scan.faces, truth, camera), "truth"
    elif args.reference:
        try:
            values, top = read_image(args.reference)
        except OSError as exc:
            raise ValueError(f"reference: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"reference: {exc}") from None
        rgb = values[..., :3] if values.shape[2] >= 3 else np.repeat(values[..., :1], 3, axis=-1)
        on = np.isfinite(image).all(axis=-1)
        if rgb.shape != image.shape:
            raise ValueError(f"reference: {rgb.shape[1]}x{rgb.shape[0]} pixels, the relit image "
                             f"{image.shape[1]}x{image.shape[0]}")
        if top is not None:  # a photograph: sRGB, unknown exposure
            rgb = to_linear(rgb)
            scale = float(np.sum(image[on] * rgb[on]) / max(np.sum(rgb[on] ** 2), 1e-300))
            rgb, summary["reference_scale"] = rgb * scale, scale
        reference, label = np.where(on[..., None], rgb, np.nan), "reference"
    if reference is not None:
        summary["errors"] = rl.image_errors(image, reference)
    finite = np.isfinite(reference if reference is not None else image).all(axis=-1)
    if str(args.out).lower().endswith(".npy"):
        atomic_write(args.out, lambda fh: np.save(fh, np.where(np.isfinite(image), image, 0.0)))
    else:
        base = reference if reference is not None else image
        top = float(np.percentile(base[finite], 99.5)) if finite.any() else 1.0
        render.save_png(args.out, render.to_srgb8(image, exposure=1.0 / top if top > 0 else 1.0))
    if args.compare:
        render.comparison_figure(args.compare, image, reference, labels=("relit", label),
                                 title=f"{est.model}, model-gi {args.model_gi}, light {light.round(3).tolist()}")
    summary.update(out=args.out, compare=args.compare, width=camera.width, height=camera.height,
                   camera=camera.center.round(6).tolist(), light=light.tolist(), intensity=intensity,
                   model_gi=args.model_gi)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        err = summary.get("errors")
        print(f"wrote {args.out} ({camera.width}x{camera.height})"
              + (f"; RMS relative error against {label} {err['rms_relative']:.2%}" if err else ""))
    return 0


def cmd_maps(args) -> int:
    from . import render
    from .raycast import RayCaster
    from .relight import scan_camera

    est, scan = _result_and_scan(args)
    caster = RayCaster(scan.vertices, scan.faces)
    view = args.view
    if view == "auto":
        view = "cylindrical" if scan.meta.get("rig", {}).get("type") == "cylindrical-scanner" else "camera"
    if view == "cylindrical":
        hits, shape = render.cylindrical_hits(caster, width=args.width)
    else:
        hits, shape = render.camera_hits(caster, scan_camera(scan, args.width, max(2, args.width * 3 // 4)))
    render.reflectance_figure(args.out, hits, shape, scan.faces, est,
                              title=f"{est.meta.get('method', 'estimate')} ({est.model})")
    print(f"wrote {args.out} ({view} view)")
    return 0


def cmd_export(args) -> int:
    from .export import export_ply

    est, scan = _result_and_scan(args)
    export_ply(args.out, scan.vertices, scan.faces, scan.normals, est)
    print(f"wrote {args.out}: {scan.n_points} vertices, {len(scan.faces)} faces")
    return 0


def cmd_fold(args) -> int:
    from .io import load_scan
    from .reports import fold_profile
    from .result import load_result

    scan = load_scan(args.scan)
    results = {}
    for item in args.results:
        label, _, path = item.rpartition("=")
        est = load_result(path)
        if len(est.pd) != scan.n_points:
            raise ValueError(f"{path}: {len(est.pd)} points, the scan has {scan.n_points}")
        results[label or est.meta.get("method", path)] = est
    out = fold_profile(scan, results, args.out, near=args.near)
    if args.json:
        print(json.dumps(out))
    else:
        for label in results:
            print(f"{label}: mean pd error within {args.near * 100:.0f} cm of the fold "
                  f"{out[label].get('near_fold_mean_rel_error')}")
        print(f"wrote {args.out}")
    return 0


def cmd_figure18(args) -> int:
    from .reports import figure18

    print(figure18(args.out, resolution=args.resolution, samples=args.samples, rays=args.rays,
                   progress=_progress())["markdown"])
    return 0


def cmd_table1(args) -> int:
    from .reports import table1

    result = table1(args.out, resolution=args.resolution, exact=not args.no_exact)
    print(result["markdown"])
    return 0


def cmd_demo(args) -> int:
    from .demo import run_demo

    summary = run_demo(args.out, resolution=args.resolution, samples=args.samples, seed=args.seed,
                       progress=_progress())
    h = summary["holdout_A"]
    holdout = {"held_out_lights": len(h["lights"]), "samples": h["samples"], "rel_rms": h["rel_rms"],
               "median_rel": h["median_rel"], "truth_rel_rms": h.get("truth", {}).get("rel_rms")}
    print(json.dumps({**{k: summary[k] for k in ("out", "seconds", "files")}, "holdout_A": holdout}, indent=2))
    return 0


#: Options naming files a command writes, and commands whose --out is a folder.
_FILE_OUTPUTS = {"synth": ("out",), "render": ("out",), "select-lights": ("plot",), "estimate": ("out",),
                 "fold": ("out",), "ingest": ("out",), "relight": ("out", "compare"), "maps": ("out",),
                 "export": ("out",)}
_FOLDER_OUTPUTS = ("demo", "table1", "figure18", "capture", "batch")


def _check_outputs(args) -> None:
    """Before any work: refuse an output that is an input of the command, another output,
    or an existing path that is not a regular file (a folder for folder outputs)."""
    from .io import check_output_path

    inputs = [getattr(args, k, None) for k in ("scan", "result", "folder", "plan", "source")]
    if getattr(args, "reference", None) not in (None, "truth"):
        inputs.append(args.reference)
    inputs += [item.rpartition("=")[2] for item in getattr(args, "results", None) or ()]
    if args.command in _FOLDER_OUTPUTS:
        check_output_path(args.out, "out", inputs, folder=True)
        return
    seen = {}
    for name in _FILE_OUTPUTS.get(args.command, ()):
        path = getattr(args, name, None)
        if path is None:
            continue
        check_output_path(path, name, inputs)
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{name}: {path} is also --{seen[key]}")
        seen[key] = name


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxrefl", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    # every command's --help shows the defaults
    sub = parser.add_subparsers(dest="command", parser_class=functools.partial(
        argparse.ArgumentParser, formatter_class=argparse.ArgumentDefaultsHelpFormatter))
    for add in (_add_synth, _add_render, _add_info, _add_select_lights, _add_estimate, _add_fold, _add_figure18, _add_table1,
                _add_demo, _add_capture):
        add(sub)
    for add in (_add_ingest, _add_relight, _add_maps, _add_export):
        add(sub)
    _add_batch(sub)
    args = parser.parse_args(argv)
    from .compile_cache import enable as enable_compile_cache

    enable_compile_cache()  # later runs load the compiled solvers from disk
    if args.version:
        from . import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2
    # jaxrefl's logged warnings reach stderr as each command's own one-line summary
    quiet = logging.getLogger("jaxrefl")
    if not any(isinstance(h, logging.NullHandler) for h in quiet.handlers):
        quiet.addHandler(logging.NullHandler())
    commands = {"synth": cmd_synth, "render": cmd_render, "info": cmd_info, "demo": cmd_demo,
                "select-lights": cmd_select_lights, "table1": cmd_table1, "estimate": cmd_estimate,
                "capture": cmd_capture, "fold": cmd_fold, "figure18": cmd_figure18}
    commands.update({"ingest": cmd_ingest, "relight": cmd_relight, "maps": cmd_maps, "export": cmd_export})
    commands["batch"] = cmd_batch
    try:
        _check_outputs(args)
        return commands[args.command](args)
    except (ValueError, FileNotFoundError, IsADirectoryError) as exc:
        msg = str(exc) if not isinstance(exc, OSError) else f"{exc.filename}: {exc.strerror}"
        print(f"jaxrefl {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
