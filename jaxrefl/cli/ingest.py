"""`jaxrefl ingest`: photographs of a capture folder to a scan bundle."""

from __future__ import annotations

import json


def add_ingest(sub):
    p = sub.add_parser("ingest", help="photographs of a capture folder (rig.json + mesh + images) to a scan bundle")
    p.add_argument("folder", help="capture folder holding rig.json (see README: capture folder)")
    p.add_argument("--out", required=True, help="scan bundle to write (.npz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def run_ingest(args) -> int:
    from ..scan.ingest import ingest
    from ..scan.io import save_scan

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


COMMANDS = {"ingest": (add_ingest, run_ingest)}
