"""Pictures of per-vertex quantities: cylindrical unwraps and pinhole views.

A picture is made by casting one Embree ray per pixel and interpolating the
per-vertex values of the hit face with its barycentrics, so any mesh and any
per-vertex quantity (radiance under one light, albedo, roughness, status)
becomes an image. The cylindrical view is the paper's texture-image layout:
column = angle about the vertical (y) axis, row = height, rays cast
horizontally from outside toward the axis.
"""

from __future__ import annotations

import numpy as np

from .. import srgb
from ..geometry.raycast import Hits, RayCaster
from ..geometry.rig import PinholeCamera
from ..scan.images import write_png
from ..status import STATUS_NAMES, Status

__all__ = [
    "cylindrical_hits",
    "camera_hits",
    "shade",
    "to_srgb8",
    "colormap",
    "robust_top",
    "save_png",
    "reflectance_layers",
    "scan_picture",
    "fit_camera",
    "scan_camera",
    "reflectance_figure",
    "reflectance_maps",
    "estimate_figure",
    "status_figure",
    "status_colormap",
    "STATUS_NAMES",
    "STATUS_COLOURS",
    "comparison_figure",
]


def cylindrical_hits(caster: RayCaster, width: int = 360, height: int | None = None,
                     axis_xz=(0.0, 0.0)) -> tuple[Hits, tuple[int, int]]:
    """First hits of rays cast inward toward the vertical axis through `axis_xz`.

    Column `j` looks from angle `theta = 2 pi j / width` (measured from +z
    toward +x, the scanner's head angle); row 0 is the top of the object.
    `height` defaults to keep pixels square at the object's mean radius.

    **Returns:** `(hits, (height, width))` with `hits` of `height * width` rays, row-major.
    """
    v = caster.vertices
    ax = np.array([axis_xz[0], 0.0, axis_xz[1]])
    rel = v - ax
    r_max = float(np.max(np.hypot(rel[:, 0], rel[:, 2]))) * 1.05 + 1e-6
    y0, y1 = float(v[:, 1].min()), float(v[:, 1].max())
    if height is None:
        r_mean = float(np.mean(np.hypot(rel[:, 0], rel[:, 2])))
        height = max(2, int(round(width * (y1 - y0) / (2 * np.pi * max(r_mean, 1e-9)))))
    theta = 2 * np.pi * (np.arange(width) + 0.5) / width
    ys = y1 - (np.arange(height) + 0.5) / height * (y1 - y0)
    tt, yy = np.meshgrid(theta, ys)
    s, c = np.sin(tt.ravel()), np.cos(tt.ravel())
    origins = np.stack([ax[0] + r_max * s, yy.ravel(), ax[2] + r_max * c], -1)
    dirs = np.stack([-s, np.zeros_like(s), -c], -1)
    return caster.first_hit(origins, dirs, tfar=r_max), (height, width)


def camera_hits(caster: RayCaster, camera: PinholeCamera) -> tuple[Hits, tuple[int, int]]:
    """First hits of the rays through every pixel of `camera` (row-major)."""
    origins, dirs = camera.pixel_rays()
    return caster.first_hit(origins, dirs), (camera.height, camera.width)


def shade(hits: Hits, faces: np.ndarray, values: np.ndarray, shape, background=np.nan) -> np.ndarray:
    """Image `(H, W, C)` (or `(H, W)` for 1-D `values`) of per-vertex `values`
    `(N, C)` interpolated at `hits`; pixels without a hit get `background`."""
    vals = np.asarray(values, dtype=np.float64)
    flat = vals.reshape(len(vals), -1)
    face = np.maximum(hits.face, 0)
    img = np.einsum("pk,pkc->pc", hits.barycentric, flat[faces[face]])
    img[~hits.hit] = background
    return img.reshape(*shape, *vals.shape[1:])


def to_srgb8(linear: np.ndarray, exposure: float | None = None, background=(0, 0, 0)) -> np.ndarray:
    """Tone-map a linear RGB image `(H, W, 3)` to sRGB uint8.

    `exposure` scales linear values before the sRGB curve (default: the 99.5th
    percentile of finite values maps to 1). NaN pixels get `background`.
    """
    img = np.asarray(linear, dtype=np.float64)
    finite = np.isfinite(img).all(axis=-1)
    if exposure is None:
        top = np.percentile(img[finite], 99.5) if np.any(finite) else 1.0
        exposure = 1.0 / top if top > 0 else 1.0
    x = np.clip(np.where(finite[..., None], img, 0.0) * exposure, 0.0, 1.0)
    out = srgb.from_linear8(x)
    out[~finite] = background
    return out


def colormap(values: np.ndarray, cmap: str = "viridis", vmin=None, vmax=None) -> np.ndarray:
    """A scalar image `(H, W)` as uint8 RGB through a matplotlib colormap (NaN -> black)."""
    import matplotlib

    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    lo = vmin if vmin is not None else (float(v[finite].min()) if finite.any() else 0.0)
    hi = vmax if vmax is not None else (float(v[finite].max()) if finite.any() else 1.0)
    norm = np.clip((v - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    rgb = matplotlib.colormaps[cmap](np.where(finite, norm, 0.0))[..., :3]
    out = np.round(rgb * 255).astype(np.uint8)
    out[~finite] = 0
    return out


def save_png(path, image: np.ndarray) -> None:
    """Write a uint8 `(H, W, 3)` image to PNG atomically (`jaxrefl.scan.images.write_png`)."""
    write_png(path, np.asarray(image, dtype=np.uint8))


def fit_camera(vertices, eye, target=None, width: int = 640, height: int = 480) -> PinholeCamera:
    """A pinhole camera at `eye` looking at `target` (default: the bounding-box centre
    of `vertices`) with the field of view that fits the whole object. An eye more
    than 20 fitted distances away (a distant, orthographic camera) is brought in."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    target = 0.5 * (lo + hi) if target is None else np.asarray(target, dtype=np.float64)
    eye = np.asarray(eye, dtype=np.float64)
    radius = float(np.max(np.linalg.norm(v - target, axis=1))) or 1.0
    offset = eye - target
    dist = float(np.linalg.norm(offset))
    if dist <= radius * 1.01:
        raise ValueError(f"camera: the eye {eye.round(4).tolist()} is inside the object's bounding sphere")
    snug = radius / np.sin(np.radians(20.0))  # a 40-degree view would just fit the object
    if dist > 20 * snug:
        eye, dist = target + offset / dist * snug, snug
    fov = min(float(np.degrees(2 * np.arcsin(min(radius / dist, 1.0))) * 1.1), 120.0)  # vertical
    up = np.array([0.0, 1.0, 0.0])
    if np.linalg.norm(np.cross(offset / dist, up)) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    return PinholeCamera.look_at(eye, target, up=up, fov_deg=fov, width=width, height=height)


def scan_camera(scan, width: int = 640, height: int = 480) -> PinholeCamera:
    """The scan's camera for its first observation: its own pinhole camera when the
    bundle describes one, else a camera fitted to the object from that position."""
    rig = scan.meta.get("rig", {})
    if rig.get("type") == "pinhole":
        return PinholeCamera(K=np.array(rig["K"]), R=np.array(rig["R"]), t=np.array(rig["t"]),
                             width=int(rig["width"]), height=int(rig["height"]), dist=np.array(rig["dist"]))
    eye = scan.camera_positions()[0, 0]
    return fit_camera(scan.vertices, eye, width=width, height=height)


def scan_picture(scan, what: str = "radiance", light: int = 0, view: str = "auto", width: int = 512):
    """uint8 RGB picture of a scan (see `jaxrefl render --help`)."""
    caster = RayCaster(scan.vertices, scan.faces)
    rig = scan.meta.get("rig", {})
    if view == "auto":
        view = "camera" if rig.get("type") == "pinhole" else "cylindrical"
    if view == "camera":
        if rig.get("type") == "pinhole":
            cam = PinholeCamera(K=np.array(rig["K"]), R=np.array(rig["R"]), t=np.array(rig["t"]),
                                width=rig["width"], height=rig["height"], dist=np.array(rig["dist"]))
        else:
            center = 0.5 * (scan.vertices.min(0) + scan.vertices.max(0))
            cam = PinholeCamera.look_at(center + [0.0, 0.0, 0.6], center, width=width,
                                        height=int(width * 0.75))
        hits, shape = camera_hits(caster, cam)
    else:
        hits, shape = cylindrical_hits(caster, width=width)

    def need(name):
        value = getattr(scan, name)
        if value is None:
            raise ValueError(f"{name}: the scan has none, so --what cannot be drawn")
        return value

    if what == "radiance":
        rad = need("radiance")
        if not 0 <= light < scan.n_lights:
            raise ValueError(f"light: must be in [0, {scan.n_lights - 1}], got {light}")
        ok = scan.valid[:, light] if scan.valid is not None else np.ones(scan.n_points, bool)
        values = np.where(ok[:, None], rad[:, light], np.nan)
        return to_srgb8(shade(hits, scan.faces, values, shape))
    if what == "pd":
        return to_srgb8(shade(hits, scan.faces, need("true_pd"), shape), exposure=1.0)
    if what == "ps":
        return colormap(shade(hits, scan.faces, need("true_ps"), shape), "magma")
    if what == "roughness":
        rough = scan.true_sigma if scan.true_sigma is not None else need("true_alpha")
        return colormap(shade(hits, scan.faces, rough, shape), "gray")
    if what == "normals":
        img = shade(hits, scan.faces, scan.normals, shape)
        return to_srgb8(np.where(np.isfinite(img), 0.5 * (img + 1.0), np.nan), exposure=1.0)
    count = scan.observed().sum(axis=1).astype(np.float64)
    return colormap(shade(hits, scan.faces, count, shape), "viridis", vmin=0)


# -- figures (matplotlib) ----------------------------------------------------------------

#: One discrete colour per status (`STATUS_NAMES`, from the JAX-free `jaxrefl.status`):
#: measured green, interpolated yellow, unresolved red, pooled blue.
STATUS_COLOURS = ("#2ca02c", "#f2c200", "#d62728", "#1f77b4")


def status_colormap():
    """`(cmap, norm)`: a ListedColormap of `STATUS_COLOURS` (white where not hit) and the
    BoundaryNorm that maps every status code to its own colour."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    n = len(STATUS_NAMES)
    return ListedColormap(STATUS_COLOURS).with_extremes(bad="white"), BoundaryNorm(np.arange(n + 1) - 0.5, n)


def _nearest_image(hits: Hits, shape, faces, values) -> np.ndarray:
    """`(H, W)` float: the value of the nearest vertex of each hit face (never a blend: status
    codes, standard deviations that may be infinite), NaN off the object."""
    nearest = faces[np.maximum(hits.face, 0), np.argmax(hits.barycentric, axis=1)]
    return np.where(hits.hit, np.asarray(values, dtype=np.float64)[nearest], np.nan).reshape(shape)


def _status_image(hits: Hits, shape, faces, status) -> np.ndarray:
    return _nearest_image(hits, shape, faces, status)


def _draw_status(fig, ax, image, status) -> None:
    """The status map `image` on `ax`, with a legend of the four statuses and their shares of
    all points."""
    from matplotlib.patches import Patch

    cmap, norm = status_colormap()
    ax.imshow(np.ma.masked_invalid(image), cmap=cmap, norm=norm, interpolation="nearest")
    counts = np.bincount(np.asarray(status, dtype=np.int64), minlength=len(STATUS_NAMES))
    total = max(int(counts.sum()), 1)
    ax.legend(handles=[Patch(color=c, label=f"{name} {100 * k / total:.0f}%")
                       for c, name, k in zip(STATUS_COLOURS, STATUS_NAMES, counts)],
              loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)


def status_figure(path, hits: Hits, shape, faces, status, title: str | None = None) -> None:
    """The status of every point (`jaxrefl.methods.local.STATUS_NAMES`) over the pixels `hits` of a
    view of `shape`, one discrete colour per status with a legend. Written to PNG `path`."""
    aspect = shape[1] / shape[0]
    fig = new_figure(figsize=(3.6 * min(aspect, 2.5) + 1.8, 3.8))
    ax = fig.subplots()
    _draw_status(fig, ax, _status_image(hits, shape, faces, status), status)
    ax.set_axis_off()
    ax.set_title(title or "status", fontsize=10)
    fig.tight_layout()
    _save_figure(path, fig)


def _save_figure(path, fig) -> None:
    from ..scan.io import atomic_write

    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=110))


def new_figure(**kw):
    """A figure outside pyplot (no backend chosen, nothing to close): drawing files from
    a notebook leaves its inline backend alone."""
    from matplotlib.figure import Figure

    return Figure(**kw)


def _cmap(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="white")


#: Percentile of the known points' values that tops a map's colour scale: a few points far
#: out (an unresolved lobe, a point at the energy bound) saturate instead of darkening the rest.
_TOP_PERCENTILE = 99.0


def robust_top(values, status=None) -> float:
    """Top of a colour scale for per-point `values` `(N,)`: the `_TOP_PERCENTILE` percentile
    over the points whose value was determined by data (`status` measured or pooled; all
    finite values when there are none or no `status`), 1 when that is not positive."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    if status is not None:
        known = ok & np.isin(np.asarray(status), (Status.MEASURED, Status.POOLED))
        ok = known if known.any() else ok
    top = float(np.percentile(v[ok], _TOP_PERCENTILE)) if ok.any() else 0.0
    return top if top > 0 else 1.0


def reflectance_figure(path, hits: Hits, shape, faces, est, title: str | None = None) -> None:
    """`reflectance_maps(hits, shape, faces, est, title)` written to PNG `path`."""
    _save_figure(path, reflectance_maps(hits, shape, faces, est, title))


def reflectance_layers(hits: Hits, shape, faces, est) -> dict:
    """The linear maps of a result over the pixels `hits` of a view of `shape` `(H, W)`, as
    `write_exr` layers: `RGB` pd, `ps`, `roughness` [rad], their standard deviations `std_ps`,
    `std_roughness` (inf where unknown) and `status` (the codes), these three of the nearest
    vertex, and `A` (1 on the object); NaN off the object."""
    layers = {"RGB": shade(hits, faces, est.pd, shape), "ps": shade(hits, faces, est.ps, shape),
              "roughness": shade(hits, faces, est.roughness, shape)}
    for name in ("std_ps", "std_roughness", "status"):  # nearest vertex: never a blend
        layers[name] = _nearest_image(hits, shape, faces, getattr(est, name))
    layers["A"] = np.isfinite(layers["ps"]).astype(np.float32)
    return layers


def reflectance_maps(hits: Hits, shape, faces, est, title: str | None = None):
    """The paper's Figures 10-11 for any result: (a) diffuse albedo pd as colour,
    (b) specular reflectance ps, (c) roughness in grey (largest = white), (d) status
    (measured / interpolated / unresolved / pooled, discrete colours with a legend), (a)-(c)
    each with its colour bar, over the pixels `hits` `(H*W rays)` of a view of `shape` `(H, W)`.

    **Returns:** a matplotlib `Figure` (outside pyplot)."""
    rough_name = "sigma" if est.model == "torrance-sparrow" else "alpha"
    pd = shade(hits, faces, est.pd, shape)
    ps = shade(hits, faces, est.ps, shape)
    rough = shade(hits, faces, est.roughness, shape)
    status = _status_image(hits, shape, faces, est.status)
    aspect = shape[1] / shape[0]
    fig = new_figure(figsize=(2 * 3.6 * min(aspect, 2.5) + 1.6, 2 * 3.6 + 0.8))
    axes = fig.subplots(2, 2)
    (a, b), (c, d) = axes
    pd_img = to_srgb8(pd, exposure=1.0, background=(255, 255, 255))
    a.imshow(pd_img)
    a.set_title("(a) diffuse albedo pd (sRGB)")
    for ax, img, values, cmap, label, name in (
            (b, ps, est.ps, "magma", "ps", "(b) specular reflectance ps"),
            (c, rough, est.roughness, "gray", f"{rough_name} [rad]", f"(c) roughness {rough_name}")):
        cm = _cmap(cmap)
        hi = robust_top(values, est.status)
        im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, vmin=0.0, vmax=hi)
        finite = img[np.isfinite(img)]
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label=label,
                     extend="max" if finite.size and finite.max() > hi else "neither")
        ax.set_title(name)
    _draw_status(fig, d, status, est.status)
    d.set_title("(d) status")
    for ax in axes.ravel():
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def estimate_figure(est, scan=None, view: str = "auto", width: int = 512, title: str | None = None):
    """A matplotlib `Figure` of a result `est` (nothing written).

    With `scan` (the scan it was estimated from): `reflectance_maps` over a `view` of
    its mesh, 'cylindrical' (the unwrap; 'auto' for the cylindrical scanner) or 'camera'
    (the scan's camera, `width` px wide). Without: histograms of pd (per channel), ps and
    roughness, and the points per status.
    """
    title = title or f"{est.meta.get('method', 'estimate')} ({est.model})"
    if scan is not None:
        if len(est.pd) != scan.n_points:
            raise ValueError(f"scan: the result has {len(est.pd)} points, the scan {scan.n_points}")
        caster = RayCaster(scan.vertices, scan.faces)
        if view == "auto":
            view = "cylindrical" if scan.meta.get("rig", {}).get("type") == "cylindrical-scanner" else "camera"
        if view == "cylindrical":
            hits, shape = cylindrical_hits(caster, width=width)
        elif view == "camera":
            hits, shape = camera_hits(caster, scan_camera(scan, width, max(2, width * 3 // 4)))
        else:
            raise ValueError(f"view: must be 'auto', 'cylindrical' or 'camera', got {view!r}")
        return reflectance_maps(hits, shape, scan.faces, est, title)
    rough_name = "sigma" if est.model == "torrance-sparrow" else "alpha"
    fig = new_figure(figsize=(10.0, 2.8))
    a, b, c, d = fig.subplots(1, 4)
    for k, colour in enumerate("rgb"):
        a.hist(est.pd[:, k], bins=40, color=colour, histtype="step")
    a.set_title("pd (r, g, b)")
    b.hist(est.ps, bins=40, color="0.3")
    b.set_title("ps")
    c.hist(est.roughness, bins=40, color="0.3")
    c.set_title(f"{rough_name} [rad]")
    counts = np.bincount(np.asarray(est.status, dtype=np.int64), minlength=len(STATUS_NAMES))
    d.bar(range(len(STATUS_NAMES)), counts[:len(STATUS_NAMES)], color=STATUS_COLOURS)
    d.set_xticks(range(len(STATUS_NAMES)), STATUS_NAMES, rotation=30, fontsize=8)
    d.set_title("points per status")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def comparison_figure(path, image: np.ndarray, reference: np.ndarray, labels=("relit", "reference"),
                      title: str | None = None) -> None:
    """Side by side: two linear images `(H, W, 3)` tone-mapped with one shared
    exposure (the reference's), and the luminance difference `image - reference` in
    percent of the reference's 99th-percentile luminance, with a colour bar.
    NaN pixels (off the object) are white. Written to PNG `path`."""
    if image.shape != reference.shape:
        raise ValueError(f"reference: {reference.shape[1]}x{reference.shape[0]} pixels, "
                         f"the image {image.shape[1]}x{image.shape[0]}")
    finite = np.isfinite(reference).all(axis=-1)
    top = float(np.percentile(reference[finite], 99.5)) if finite.any() else 1.0
    exposure = 1.0 / top if top > 0 else 1.0
    lum = lambda x: x.mean(axis=-1)  # noqa: E731
    scale = float(np.percentile(lum(reference)[finite], 99)) if finite.any() else 1.0
    diff = 100.0 * (lum(image) - lum(reference)) / (scale if scale > 0 else 1.0)
    limit = float(np.nanpercentile(np.abs(diff), 99.5)) if np.isfinite(diff).any() else 1.0
    limit = limit if limit > 0 else 1.0
    aspect = image.shape[1] / image.shape[0]
    fig = new_figure(figsize=(3 * 3.4 * min(aspect, 2.5) + 1.2, 3.8))
    axes = fig.subplots(1, 3)
    for ax, img, label in zip(axes, (image, reference), labels):
        ax.imshow(to_srgb8(img, exposure=exposure, background=(255, 255, 255)))
        ax.set_title(label)
    cm = _cmap("RdBu_r")
    im = axes[2].imshow(np.ma.masked_invalid(diff), cmap=cm, vmin=-limit, vmax=limit)
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.02, label="% of reference (99th pct.)")
    axes[2].set_title(f"{labels[0]} - {labels[1]}")
    for ax in axes:
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _save_figure(path, fig)
