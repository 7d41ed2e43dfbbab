"""`jaxrefl select-lights`: choose capture lights among the bundle's candidates (paper §2.2)."""

from __future__ import annotations

import json


def add_select_lights(sub):
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


def run_select_lights(args) -> int:
    from ..capture.select import exact_minimum, plot_coverage, select_lights
    from ..reflectance.classify import Thresholds, classify_scan
    from ..scan.io import load_scan

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


COMMANDS = {"select-lights": (add_select_lights, run_select_lights)}
