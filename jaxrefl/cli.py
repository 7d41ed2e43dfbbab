"""The `jaxrefl` command line.

Subcommands: `synth` (make a synthetic scan bundle), `render` (a picture of a
scan), `info` (validate and summarise a scan), `select-lights` (choose capture
lights, §2.2), `estimate` (per-point reflectance, Method I), `table1` (the
paper's Table 1 on the synthetic objects) and `demo` (the main job on the
built-in synthetic default). Bad input ends with one line on stderr naming the
field, exit code 2, and no output file.
"""

from __future__ import annotations

import argparse
import json
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
    p.add_argument("--setup", choices=["diffuse", "glossy"], default="glossy", help="Object E set-up")
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
    p.add_argument("--method", choices=["local"], default="local",
                   help="local: Method I, inverse local rendering (§3)")
    p.add_argument("--model", choices=["torrance-sparrow", "ward"], default="torrance-sparrow")
    p.add_argument("--out", required=True, help="result file to write (.npz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--paper", action="store_true",
                   help="the paper's estimator: Eq. 5 single best diffuse sample, Eq. 7 from two samples")
    p.add_argument("--window", type=int, default=5, help="interpolation window W (a (W-1)/2-ring)")
    p.add_argument("--steps", type=int, default=15, help="Levenberg-Marquardt steps")
    p.add_argument("--solver", choices=["lm", "optimistix"], default="lm")
    p.add_argument("--min-snr", type=float, default=3.0, help="ps / std(ps) needed to call it measured")
    p.add_argument("--pool", action="store_true",
                   help="experimental: points without their own lobe share it with same-colour neighbours")


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


def cmd_estimate(args) -> int:
    import time

    from .io import load_scan
    from .local import LocalOptions, estimate_local
    from .result import save_result, truth_errors

    options = LocalOptions(model=args.model, paper=args.paper, steps=args.steps, window=args.window,
                           min_snr=args.min_snr, solver=args.solver, pool=args.pool)
    t0 = time.perf_counter()
    scan = load_scan(args.scan)
    load_seconds = time.perf_counter() - t0
    est = estimate_local(scan, options)
    est.meta["seconds"] = {"load": load_seconds, **est.meta["seconds"]}
    save_result(args.out, est)
    observed = max(int(est.pd_measured.sum()), 1)
    summary = {
        "method": "local", "model": args.model, "out": args.out,
        "seconds": est.meta["seconds"],
        "points": int(len(est.status)),
        "coverage": float(np.sum(est.status == 0) / observed),
        "status_counts": {name: int(np.sum(est.status == code))
                          for code, name in enumerate(("measured", "interpolated", "unresolved"))},
    }
    if scan.true_pd is not None:
        summary["errors"] = truth_errors(est, scan)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.out}: {summary['coverage']:.1%} of observed points measured "
              f"({summary['status_counts']})")
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
    print(json.dumps({k: summary[k] for k in ("out", "seconds", "files")}, indent=2))
    return 0


def _enable_compilation_cache() -> None:
    """Keep XLA compilations between runs (a fresh process otherwise recompiles for seconds)."""
    import os

    import jax

    folder = os.environ.get("JAXREFL_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "jaxrefl"))
    try:
        os.makedirs(folder, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    except OSError:  # read-only home: run without the cache
        pass


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxrefl", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command")
    for add in (_add_synth, _add_render, _add_info, _add_select_lights, _add_estimate, _add_table1,
                _add_demo):
        add(sub)
    args = parser.parse_args(argv)
    if args.version:
        from . import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2
    _enable_compilation_cache()
    commands = {"synth": cmd_synth, "render": cmd_render, "info": cmd_info, "demo": cmd_demo,
                "select-lights": cmd_select_lights, "table1": cmd_table1, "estimate": cmd_estimate}
    try:
        return commands[args.command](args)
    except (ValueError, FileNotFoundError, IsADirectoryError) as exc:
        msg = str(exc) if not isinstance(exc, OSError) else f"{exc.filename}: {exc.strerror}"
        print(f"jaxrefl {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
