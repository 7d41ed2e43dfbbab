"""`jaxrefl render`: a picture of a scan (radiance under one light, a truth map, normals)."""

from __future__ import annotations


def add_render(sub):
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


def run_render(args) -> int:
    from ..outputs import render
    from ..scan.io import load_scan

    scan = load_scan(args.scan)
    image = render.scan_picture(scan, args.what, args.light, args.view, args.width)
    render.save_png(args.out, image)
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]})")
    return 0


COMMANDS = {"render": (add_render, run_render)}
