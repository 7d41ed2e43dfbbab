"""`jaxrefl batch`: estimate many scan bundles, resumable, here or on a Dask cluster."""

from __future__ import annotations

import sys

from ._common import add_estimate_options, method_from_options, progress


def add_batch(sub):
    p = sub.add_parser("batch", help="estimate many scan bundles, resumable, here or on a Dask cluster")
    p.add_argument("source", help="folder of scan bundles (*.npz) or a text file listing bundle paths, one per line")
    p.add_argument("--out", required=True,
                   help="output folder: NAME_result.npz and NAME_result.json per scan, summary.csv, summary.md")
    p.add_argument("--scheduler", help="Dask scheduler address (e.g. tcp://host:8786): run the scans on its workers")
    p.add_argument("--retries", type=int, default=2,
                   help="cluster: re-runs of a scan whose estimate raised (bad input is never re-run)")
    add_estimate_options(p)


def run_batch(args) -> int:
    from ..batch import run_batch, summary_table

    method = method_from_options(args)  # bad options fail before any scan is read

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
        records = run_batch(args.source, args.out, method, client=client, retries=args.retries, progress=progress())
    finally:
        if client is not None:
            client.close()
    print(summary_table(records)[1], end="")
    failed = [r for r in records if r["status"] == "failed"]
    for r in failed:
        print(f"jaxrefl batch: failed: {r['name']} ({r['scan']}): {r['error']}", file=sys.stderr)
    return 1 if failed else 0


COMMANDS = {"batch": (add_batch, run_batch)}
