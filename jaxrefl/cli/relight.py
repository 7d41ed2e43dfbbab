"""`jaxrefl relight`: render an estimated object under a new point light, optionally against a reference."""

from __future__ import annotations

import json

import numpy as np

from ._common import numbers, result_and_scan


def add_relight(sub):
    p = sub.add_parser("relight", help="render an estimated object under a new point light")
    p.add_argument("result", help="result file (.npz) from jaxrefl estimate")
    p.add_argument("scan", help="the scan bundle the result was estimated from (geometry)")
    p.add_argument("--light", required=True, help="light position X,Y,Z [m] (--light=X,Y,Z when X < 0)")
    p.add_argument("--intensity", type=float, default=None,
                   help="radiant intensity [W/sr] (default: the scan's first light)")
    p.add_argument("--camera", default=None,
                   help="EX,EY,EZ[,TX,TY,TZ]: eye [m] and target (default: the object's centre); "
                        "default camera: the scan's camera for its first light")
    p.add_argument("--width", type=int, default=640, help="image width [px] of a fitted camera")
    p.add_argument("--height", type=int, default=480, help="image height [px] of a fitted camera")
    p.add_argument("--model-gi", choices=["none", "radiosity", "photon"], default="none",
                   help="interreflections added to the direct light")
    p.add_argument("--out", required=True, help="image to write: .png (tone-mapped sRGB), .exr (linear RGB + coverage A) or .npy (linear)")
    p.add_argument("--reference", default=None,
                   help="'truth' (the scan's ground truth, same light and camera) or an image: .npy or .exr "
                        "linear radiance, or .png (sRGB, scaled to the relit image by least squares)")
    p.add_argument("--compare", default=None, help="write relit | reference | difference to this PNG")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def run_relight(args) -> int:
    from ..geometry.raycast import RayCaster
    from ..outputs import relight as rl
    from ..outputs import render
    from ..scan.images import read_image, write_exr
    from ..scan.io import atomic_write
    from ..srgb import to_linear

    if args.compare and not args.reference:
        raise ValueError("compare: needs --reference")
    if not str(args.out).lower().endswith((".png", ".npy", ".exr")):
        raise ValueError(f"out: must end in .png, .exr or .npy, got {args.out!r}")
    est, scan = result_and_scan(args)
    light = numbers(args.light, "light", (3,))
    intensity = float(scan.intensities()[0]) if args.intensity is None else args.intensity
    if args.width < 2 or args.height < 2:
        raise ValueError("width: width and height must be >= 2")
    if args.camera is None:
        camera = rl.scan_camera(scan, args.width, args.height)
    else:
        c = numbers(args.camera, "camera", (3, 6))
        camera = rl.fit_camera(scan.vertices, c[:3], c[3:] if len(c) == 6 else None, args.width, args.height)
    caster = RayCaster(scan.vertices, scan.faces)
    radiance = rl.relight(scan.vertices, scan.faces, scan.normals, est, light, intensity, camera.center,
                          args.model_gi, caster)
    image = rl.picture(caster, scan.faces, radiance, camera)
    reference, label, summary = None, None, {}
    if args.reference == "truth":
        truth = rl.relight(scan.vertices, scan.faces, scan.normals, rl.truth_estimate(scan), light, intensity,
                           camera.center, args.model_gi, caster)
        reference, label = rl.picture(caster, scan.faces, truth, camera), "truth"
    elif args.reference:
        try:
            values, top = read_image(args.reference)
        except OSError as exc:
            raise ValueError(f"reference: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"reference: {exc}") from None
        rgb = values[..., :3] if values.shape[2] >= 3 else np.repeat(values[..., :1], 3, axis=-1)
        on = np.isfinite(image).all(axis=-1)
        if rgb.shape != image.shape:
            raise ValueError(f"reference: {rgb.shape[1]}x{rgb.shape[0]} pixels, the relit image "
                             f"{image.shape[1]}x{image.shape[0]}")
        if top is not None:  # a photograph: sRGB, unknown exposure
            rgb = to_linear(rgb)
            scale = float(np.sum(image[on] * rgb[on]) / max(np.sum(rgb[on] ** 2), 1e-300))
            rgb, summary["reference_scale"] = rgb * scale, scale
        reference, label = np.where(on[..., None], rgb, np.nan), "reference"
    if reference is not None:
        summary["errors"] = rl.image_errors(image, reference)
    finite = np.isfinite(reference if reference is not None else image).all(axis=-1)
    if str(args.out).lower().endswith(".npy"):
        atomic_write(args.out, lambda fh: np.save(fh, np.where(np.isfinite(image), image, 0.0)))
    elif str(args.out).lower().endswith(".exr"):
        on = np.isfinite(image).all(axis=-1)
        write_exr(args.out, {"RGB": np.where(on[..., None], image, 0.0), "A": on.astype(np.float32)})
    else:
        base = reference if reference is not None else image
        top = float(np.percentile(base[finite], 99.5)) if finite.any() else 1.0
        render.save_png(args.out, render.to_srgb8(image, exposure=1.0 / top if top > 0 else 1.0))
    if args.compare:
        render.comparison_figure(args.compare, image, reference, labels=("relit", label),
                                 title=f"{est.model}, model-gi {args.model_gi}, light {light.round(3).tolist()}")
    summary.update(out=args.out, compare=args.compare, width=camera.width, height=camera.height,
                   camera=camera.center.round(6).tolist(), light=light.tolist(), intensity=intensity,
                   model_gi=args.model_gi)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        err = summary.get("errors")
        print(f"wrote {args.out} ({camera.width}x{camera.height})"
              + (f"; RMS relative error against {label} {err['rms_relative']:.2%}" if err else ""))
    return 0


COMMANDS = {"relight": (add_relight, run_relight)}
