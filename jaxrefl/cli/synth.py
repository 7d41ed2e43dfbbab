"""`jaxrefl synth`: render a synthetic scan bundle with known reflectance (uses `data_synth`)."""

from __future__ import annotations

import json

from ._common import int_list, progress


def add_synth(sub):
    p = sub.add_parser("synth", help="render a synthetic scan bundle with known reflectance")
    p.add_argument("object", choices=["A", "B", "C", "D", "E", "V"],
                   help="procedural object (A-E: the paper's analogues; V: a convex glazed vase)")
    p.add_argument("--out", required=True, help="scan bundle to write (.npz)")
    p.add_argument("--resolution", type=int, default=64, help="mesh resolution (voxels across the object)")
    p.add_argument("--setup", choices=["diffuse", "glossy", "glazed"], default="glossy",
                   help="Object E set-up; 'glazed': any object under a uniform Ward glaze (ps 0.3, alpha 0.08)")
    p.add_argument("--rig", choices=["scanner", "pinhole"], default=None,
                   help="rotating-head scanner (default for A-D) or fixed pinhole camera (default for E)")
    p.add_argument("--lights", type=int_list, default=None, help="rack indices, e.g. 0,7,23 (default all 60)")
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


def run_synth(args) -> int:
    from data_synth.scans import Sensor, make_scan

    from ..scan.io import save_scan

    sensor = Sensor(noise=args.noise, read_noise=args.read_noise, bits=args.bits,
                    full_scale=args.full_scale, saturate=args.saturate)
    scan, report = make_scan(
        args.object, resolution=args.resolution, setup=args.setup, rig=args.rig,
        lights=args.lights, model=args.model, global_illumination=args.gi,
        samples=args.samples, sensor=sensor, intensity=args.intensity, seed=args.seed,
        progress=progress(),
    )
    save_scan(args.out, scan)
    report["out"] = args.out
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"wrote {args.out}: {report['points']} points x {report['lights']} lights, "
              f"{report['valid_fraction']:.1%} observed, {report['seconds']['total']:.1f} s")
    return 0


COMMANDS = {"synth": (add_synth, run_synth)}
