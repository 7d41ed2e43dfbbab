"""The paper's experiments: `jaxrefl table1`, `fold` and `figure18` (use `data_synth`)."""

from __future__ import annotations

import json

from ._common import progress


def add_table1(sub):
    p = sub.add_parser("table1", help="Table 1 / Figure 8 analogue on the synthetic Objects A-D")
    p.add_argument("--out", required=True, help="folder for table1.md, table1.json and fig8_*.png")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--no-exact", action="store_true", help="skip the exact integer-program comparison")


def run_table1(args) -> int:
    from ..paper.reports import table1

    result = table1(args.out, resolution=args.resolution, exact=not args.no_exact)
    print(result["markdown"])
    return 0


def add_fold(sub):
    p = sub.add_parser("fold", help="pd across the fold of Object E for one or more results (Fig. 12/16/21)")
    p.add_argument("scan", help="the Object E scan bundle the results were estimated from")
    p.add_argument("results", nargs="+", help="result files; label one as LABEL=PATH")
    p.add_argument("--out", required=True, help="figure to write (.png)")
    p.add_argument("--near", type=float, default=0.02, help="half-width [m] of the band around the fold")
    p.add_argument("--json", action="store_true", help="print the errors and profiles as JSON")


def run_fold(args) -> int:
    from ..paper.reports import fold_profile
    from ..result import load_result
    from ..scan.io import load_scan

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


def add_figure18(sub):
    p = sub.add_parser("figure18", help="Figure 18 analogue: Methods I and II on Objects A-D with interreflections")
    p.add_argument("--out", required=True, help="folder for figure18.md, figure18.json and the maps")
    p.add_argument("--resolution", type=int, default=48)
    p.add_argument("--samples", type=int, default=64, help="path-traced samples per observation")
    p.add_argument("--rays", type=int, default=256, help="form-factor rays per vertex")


def run_figure18(args) -> int:
    from ..paper.reports import figure18

    print(figure18(args.out, resolution=args.resolution, samples=args.samples, rays=args.rays,
                   progress=progress())["markdown"])
    return 0


COMMANDS = {"table1": (add_table1, run_table1), "fold": (add_fold, run_fold), "figure18": (add_figure18, run_figure18)}
