"""`jaxrefl info`: validate a scan bundle and print a summary."""

from __future__ import annotations

import json


def add_info(sub):
    p = sub.add_parser("info", help="validate a scan bundle and print a summary")
    p.add_argument("scan")
    p.add_argument("--json", action="store_true")


def run_info(args) -> int:
    from ..scan.io import load_scan

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


COMMANDS = {"info": (add_info, run_info)}
