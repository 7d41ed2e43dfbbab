"""`jaxrefl export`: a result as a PLY mesh with per-vertex attributes."""

from __future__ import annotations

from ._common import result_and_scan


def add_export(sub):
    p = sub.add_parser("export", help="a result as a PLY mesh with per-vertex attributes")
    p.add_argument("result", help="result file (.npz)")
    p.add_argument("scan", help="the scan bundle it was estimated from")
    p.add_argument("--out", required=True, help="PLY file to write")


def run_export(args) -> int:
    from ..outputs.export import export_ply

    est, scan = result_and_scan(args)
    export_ply(args.out, scan.vertices, scan.faces, scan.normals, est)
    print(f"wrote {args.out}: {scan.n_points} vertices, {len(scan.faces)} faces")
    return 0


COMMANDS = {"export": (add_export, run_export)}
