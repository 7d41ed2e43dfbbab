"""`jaxrefl demo`: the main job on the built-in synthetic default."""

from __future__ import annotations

import json

from ._common import progress


def add_demo(sub):
    p = sub.add_parser("demo", help="the main job on the built-in synthetic default")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--resolution", type=int, default=48, help="mesh resolution of the demo objects")
    p.add_argument("--samples", type=int, default=64, help="paths per observation for the GI render")
    p.add_argument("--seed", type=int, default=0)


def run_demo(args) -> int:
    from ..paper.demo import run_demo

    summary = run_demo(args.out, resolution=args.resolution, samples=args.samples, seed=args.seed,
                       progress=progress())
    h = summary["holdout_A"]
    holdout = {"held_out_lights": len(h["lights"]), "samples": h["samples"], "rel_rms": h["rel_rms"],
               "median_rel": h["median_rel"], "truth_rel_rms": h.get("truth", {}).get("rel_rms")}
    print(json.dumps({**{k: summary[k] for k in ("out", "seconds", "files")}, "holdout_A": holdout}, indent=2))
    return 0


COMMANDS = {"demo": (add_demo, run_demo)}
