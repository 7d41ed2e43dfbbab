"""`jaxrefl maps`: reflectance maps of a result (the paper's Figures 10-11)."""

from __future__ import annotations

from ._common import result_and_scan


def add_maps(sub):
    p = sub.add_parser("maps", help="reflectance maps of a result (the paper's Figures 10-11)")
    p.add_argument("result", help="result file (.npz)")
    p.add_argument("scan", help="the scan bundle it was estimated from")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--view", choices=["auto", "cylindrical", "camera"], default="auto",
                   help="cylindrical unwrap (auto for scanner bundles) or the scan's camera")
    p.add_argument("--width", type=int, default=512, help="image width [px]")


def run_maps(args) -> int:
    from ..geometry.raycast import RayCaster
    from ..outputs import render
    from ..outputs.relight import scan_camera

    est, scan = result_and_scan(args)
    caster = RayCaster(scan.vertices, scan.faces)
    view = args.view
    if view == "auto":
        view = "cylindrical" if scan.meta.get("rig", {}).get("type") == "cylindrical-scanner" else "camera"
    if view == "cylindrical":
        hits, shape = render.cylindrical_hits(caster, width=args.width)
    else:
        hits, shape = render.camera_hits(caster, scan_camera(scan, args.width, max(2, args.width * 3 // 4)))
    if str(args.out).lower().endswith(".exr"):
        from ..scan.images import write_exr

        write_exr(args.out, render.reflectance_layers(hits, shape, scan.faces, est))
    else:
        render.reflectance_figure(args.out, hits, shape, scan.faces, est,
                                  title=f"{est.meta.get('method', 'estimate')} ({est.model})")
    print(f"wrote {args.out} ({view} view)")
    return 0


COMMANDS = {"maps": (add_maps, run_maps)}
