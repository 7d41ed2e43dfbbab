"""Ingest photographs: a capture folder (mesh + rig JSON + one image per light) to a scan bundle.

A capture folder holds `rig.json` and the files it names (paths relative to
the folder). Two layouts, told apart by the rig's `"type"`:

- `"pinhole"` (default): a mesh (PLY/OBJ, read with trimesh, metres), one or
  more calibrated pinhole cameras (OpenCV: `x_cam = R x_world + t`, camera x
  right, y down, z forward; `u = K [x/z, y/z, 1]` after distortion
  `(k1, k2, p1, p2, k3)`; pixel centres at integer coordinates), point lights
  (position [m], radiant intensity [W/sr], scalar or RGB) and one image per
  observation. Every mesh vertex is projected into every image and sampled
  bilinearly. A sample is masked (``valid`` False) when the vertex is behind
  the camera or its four pixels are not all in frame, when it faces away
  from the camera or Embree finds the line of sight blocked, when any of the
  four pixels sees another surface (a ray cast through it hits farther than
  2.5 pixel footprints from the vertex: silhouettes, occlusion edges), or
  when any of them is saturated.
- `"photometric-stereo"`: the convention of public photometric-stereo data
  sets: an orthographic camera, distant lights given as unit directions with
  RGB intensities, a mask and a per-pixel normal map instead of a mesh. Every
  masked pixel becomes a vertex of a flat grid mesh (`pixel_size` metres
  apart) carrying the normal map's normal. Frame: x right (image columns),
  y up (against image rows), z toward the camera. The scan format knows point
  lights only, so a light of direction `d` and intensity `I` becomes a point
  light at `centre + D d` with intensity `I D^2`, `D = 1e6 x` the grid's
  extent: the irradiance `I D^2 cos' / |D d - x|^2` is `I cos` to first order,
  within about `1e-6 I` (the distance is off by a relative `extent / D`, the
  direction by `extent / D` radians). The camera is likewise a point `D`
  along +z. A flat grid casts no shadows: cast shadows in the photographs
  are not detected.

Pixel values to radiance: PNG codes are divided by `2^bits - 1`, decoded
from sRGB unless `"transfer": "linear"` (`.npy` and `.exr` images are linear floats),
`black_level` (same units, after decoding) is subtracted (values below it, sensor
noise, become 0; an image with more than 90% of its values below it is refused as a
wrong black level or a broken image), the result divided
by the image's `exposure` and, per channel, by the light's RGB intensity
relative to its mean (so a bundle holds one intensity per light: the mean).
A pixel is saturated when any channel of its *undecoded* value reaches
`saturation` (default: the top code of a PNG; none for `.npy` and `.exr`).
"""

from __future__ import annotations

import json
import os
from typing import NamedTuple

import numpy as np

from .. import srgb
from ..geometry.mesh import area_normal_sums
from ..geometry.raycast import RayCaster
from ..geometry.rig import PinholeCamera
from .images import read_image
from .io import Scan, ScanError, validate_scan

__all__ = [
    "RIG_FILE",
    "DISTANT",
    "ingest",
    "undistort",
    "bilinear",
]

RIG_FILE = "rig.json"
#: Distant lights and the orthographic camera are placed this many scene extents away.
DISTANT = 1e6
#: A pixel sees the sampled vertex when its ray hits within this many pixel footprints of it.
_FOOTPRINTS = 2.5

#: An image with more than this share of its values below the black level is refused:
#: sensor noise puts at most about half of the dark pixels below it, a wrong black level or
#: a broken image most of them. Isolated negative values are clipped to 0.
_MAX_NEGATIVE = 0.9
#: Intrinsics `K` with a larger condition number count as singular.
_MAX_CONDITION = 1e12

def undistort(camera: PinholeCamera, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Unit ray directions `(n, 3)` in world coordinates through pixels `uv` `(n, 2)`
    of `camera`, with its distortion removed (OpenCV's fixed-point iteration)."""
    uv = np.asarray(uv, dtype=np.float64)
    pix = np.stack([uv[:, 0], uv[:, 1], np.ones(len(uv))], -1)
    xd, yd = np.linalg.solve(camera.K, pix.T)[:2]
    k1, k2, p1, p2, k3 = camera.dist
    x, y = xd.copy(), yd.copy()
    if np.any(camera.dist != 0):
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = (xd - dx) / radial, (yd - dy) / radial
    d = np.stack([x, y, np.ones_like(x)], -1) @ camera.R  # camera -> world: R^T d
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def bilinear(image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of `image` `(H, W, C)` at pixel coordinates `uv` `(n, 2)`
    (x right, y down, pixel centres at integers; callers keep `uv` inside
    `[0, W-1] x [0, H-1]`, values outside are clamped).

    **Returns:** `values` `(n, C)`, `corners` `(n, 4)` flat pixel indices and
    `weights` `(n, 4)` (they sum to 1).
    """
    h, w = image.shape[:2]
    u = np.clip(uv[:, 0], 0.0, w - 1.0)
    v = np.clip(uv[:, 1], 0.0, h - 1.0)
    u0 = np.clip(np.floor(u), 0, max(w - 2, 0)).astype(np.int64)
    v0 = np.clip(np.floor(v), 0, max(h - 2, 0)).astype(np.int64)
    fu, fv = u - u0, v - v0
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    corners = np.stack([v0 * w + u0, v0 * w + u1, v1 * w + u0, v1 * w + u1], -1)
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], -1)
    flat = image.reshape(h * w, -1)
    return np.einsum("nk,nkc->nc", weights, flat[corners]), corners, weights


# -- the rig file ------------------------------------------------------------------------


def _load_rig(folder) -> dict:
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise ScanError("folder", f"{folder} is not a folder")
    path = os.path.join(folder, RIG_FILE)
    if not os.path.isfile(path):
        raise ScanError(RIG_FILE, f"missing: a capture folder needs {path}")
    try:
        with open(path, encoding="utf-8") as fh:
            rig = json.load(fh)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ScanError(RIG_FILE, f"not valid JSON ({exc})") from None
    if not isinstance(rig, dict):
        raise ScanError(RIG_FILE, "must hold a JSON object")
    return rig


def _array(value, shape, name, *, positive=False):
    """`value` as a finite float64 array of `shape` (None = any length), else ScanError(name)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ScanError(name, f"must be numbers of shape {shape}, got {value!r}") from None
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = tuple("?" if s is None else s for s in shape)
        raise ScanError(name, f"must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ScanError(name, "must be finite")
    if positive and np.any(arr <= 0):
        raise ScanError(name, f"must be > 0, got {arr.tolist()}")
    return arr


def _list(rig, key, name=None):
    value = rig.get(key)
    if not isinstance(value, list) or not value:
        raise ScanError(name or key, f"must be a non-empty list in {RIG_FILE}")
    return value


def _number(rig, key, default, *, minimum=None):
    value = rig.get(key, default)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ScanError(key, f"must be a number, got {value!r}")
    if minimum is not None and value < minimum:
        raise ScanError(key, f"must be >= {minimum}, got {value}")
    return float(value)


def _file(folder, name, field_name):
    if not isinstance(name, str) or not name:
        raise ScanError(field_name, f"must be a file name, got {name!r}")
    path = os.path.join(folder, name)
    if not os.path.isfile(path):
        raise ScanError(field_name, f"file {name} not found in {folder}")
    return path


def _camera(entry, k) -> PinholeCamera:
    name = f"cameras[{k}]"
    if not isinstance(entry, dict):
        raise ScanError(name, "must be an object with K, R (or rvec), t, width, height")
    for key in ("K", "t", "width", "height"):
        if key not in entry:
            raise ScanError(f"{name}.{key}", "missing")
    K = _array(entry["K"], (3, 3), f"{name}.K")
    if not np.linalg.cond(K) < _MAX_CONDITION:
        raise ScanError(f"{name}.K", f"intrinsics matrix is singular (not invertible): {K.tolist()}")
    if "R" in entry:
        R = _array(entry["R"], (3, 3), f"{name}.R")
    elif "rvec" in entry:
        from scipy.spatial.transform import Rotation

        R = Rotation.from_rotvec(_array(entry["rvec"], (3,), f"{name}.rvec")).as_matrix()
    else:
        raise ScanError(f"{name}.R", "missing (give R as a 3x3 matrix or rvec as a Rodrigues vector)")
    t = _array(entry["t"], (3,), f"{name}.t")
    dist = _array(entry.get("dist", [0.0] * 5), (None,), f"{name}.dist")
    if len(dist) not in (4, 5) and not (len(dist) > 5 and np.all(dist[5:] == 0)):
        raise ScanError(f"{name}.dist", f"need (k1, k2, p1, p2[, k3]), got {len(dist)} coefficients")
    dist = np.concatenate([dist, np.zeros(5)])[:5]
    size = []
    for key in ("width", "height"):
        value = entry[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 2:
            raise ScanError(f"{name}.{key}", f"must be an integer >= 2, got {value!r}")
        size.append(value)
    try:
        return PinholeCamera(K=K, R=R, t=t, width=size[0], height=size[1], dist=dist)
    except ValueError as exc:
        raise ScanError(name, str(exc)) from None


def _light_intensity(entry, name):
    """RGB intensity `(3,)` of a light entry (scalar or RGB, default 1)."""
    value = entry.get("intensity", 1.0)
    arr = _array(value, () if np.ndim(value) == 0 else (3,), f"{name}.intensity", positive=True)
    return np.broadcast_to(arr, (3,)).astype(np.float64)


def _images(rig, folder, n_lights, n_cameras):
    """Per observation: (path, light index, camera index, exposure)."""
    entries = _list(rig, "images")
    explicit = any(isinstance(e, dict) and "light" in e for e in entries)
    if not explicit and len(entries) != n_lights:
        raise ScanError("images", f"{len(entries)} image(s) for {n_lights} light(s): give one image per "
                                  "light in the order of 'lights', or name each image's light")
    out = []
    for i, e in enumerate(entries):
        name = f"images[{i}]"
        e = {"file": e} if isinstance(e, str) else e
        if not isinstance(e, dict):
            raise ScanError(name, "must be a file name or an object with 'file'")
        light, camera = e.get("light", i), e.get("camera", 0)
        for key, value, count in (("light", light, n_lights), ("camera", camera, n_cameras)):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
                raise ScanError(f"{name}.{key}", f"must be an index in [0, {count - 1}], got {value!r}")
        exposure = _number(e, "exposure", 1.0)
        if not exposure > 0:
            raise ScanError(f"{name}.exposure", f"must be > 0, got {exposure}")
        out.append((_file(folder, e.get("file"), name), light, camera, exposure))
    unused = sorted(set(range(n_lights)) - {o[1] for o in out})
    if unused:
        raise ScanError("images", f"light(s) {unused} have no image: the light list does not match "
                                  "the images")
    return out


def _photometry(rig):
    transfer = rig.get("transfer", "srgb")
    if transfer not in ("srgb", "linear"):
        raise ScanError("transfer", f"must be 'srgb' or 'linear', got {transfer!r}")
    black = _number(rig, "black_level", 0.0, minimum=0.0)
    saturation = _number(rig, "saturation", None)
    if saturation is not None and not saturation > 0:
        raise ScanError("saturation", f"must be > 0, got {saturation}")
    return transfer, black, saturation


def _radiance(path, name, shape, transfer, black, saturation, exposure, gain):
    """Linear radiance `(H, W, 3)` and saturated mask `(H, W)` of one image file."""
    try:
        values, top = read_image(path)
    except (ValueError, OSError) as exc:
        raise ScanError(name, f"{os.path.basename(path)}: {exc}") from None
    if values.shape[:2] != shape:
        raise ScanError(name, f"{os.path.basename(path)} is {values.shape[1]}x{values.shape[0]} pixels, "
                              f"its camera is {shape[1]}x{shape[0]}")
    ch = values.shape[2]
    if ch not in (1, 2, 3, 4):
        raise ScanError(name, f"{os.path.basename(path)} has {ch} channels: need 1 (grey), 3 (RGB) "
                              "or 4 (RGBA)")
    rgb = values[..., :3] if ch >= 3 else np.repeat(values[..., :1], 3, axis=-1)
    level = saturation if saturation is not None else (1.0 if top is not None else np.inf)
    saturated = np.any(rgb >= level, axis=-1)
    linear = srgb.to_linear(rgb) if (top is not None and transfer == "srgb") else rgb
    signal = linear - black
    negative = float(np.mean(signal < 0))
    if negative > _MAX_NEGATIVE:
        raise ScanError(name, f"{os.path.basename(path)}: {negative:.0%} of its values lie below the black "
                              f"level ({black:g}, after decoding): check black_level and the image")
    signal = np.maximum(signal, 0.0) / exposure
    return signal / (gain / gain.mean()), saturated


# -- pinhole captures ------------------------------------------------------------------


def _load_mesh(path):
    import trimesh

    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ScanError("mesh", f"{os.path.basename(path)} is not a readable mesh ({exc})") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if len(v) < 3 or len(f) == 0:
        raise ScanError("mesh", f"{os.path.basename(path)} holds no triangles")
    normals = None
    ply = getattr(mesh, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
    if ply is not None and all(k in (ply.dtype.names or ()) for k in ("nx", "ny", "nz")):
        normals = np.stack([ply["nx"], ply["ny"], ply["nz"]], -1).astype(np.float64)
    return v, f, normals


def _drop_degenerate(v, f):
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    scale = float(np.linalg.norm(v.max(0) - v.min(0)))
    keep = np.linalg.norm(cross, axis=1) > 1e-12 * max(scale, 1e-300) ** 2
    keep &= (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return f[keep], int((~keep).sum())


class _View(NamedTuple):
    """What one camera sees of the mesh. `uv` `(N, 2)` pixel coordinates; `in_frame`,
    `facing`, `usable` `(N,)` bool (`usable`: in frame, facing, unoccluded and every
    bilinear pixel sees the vertex); `mixed` `(N,)` a pixel sees another surface;
    for the usable vertices `idx` `(U,)`: `corner` `(U, 4)` indices into the
    distinct corner pixels, whose surface points are `points` `(P, 3)` on faces
    `face` `(P,)` (-1 where the pixel's ray misses)."""

    uv: np.ndarray
    in_frame: np.ndarray
    facing: np.ndarray
    usable: np.ndarray
    mixed: np.ndarray
    idx: np.ndarray
    corner: np.ndarray
    weight: np.ndarray
    points: np.ndarray
    face: np.ndarray


def _view(caster, cam, vertices, normals, sees) -> _View:
    """Project every vertex into `cam` and cast one ray through each distinct
    corner pixel of the vertices it sees (`sees` `(N,)`: unoccluded line of sight)."""
    uv, depth = cam.project(vertices)
    w, h = cam.width, cam.height
    in_frame = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    to_cam = cam.center - vertices
    dist = np.linalg.norm(to_cam, axis=1)
    cos_o = np.einsum("ni,ni->n", normals, to_cam) / np.maximum(dist, 1e-300)
    seen = in_frame & (cos_o > 0) & sees
    idx = np.flatnonzero(seen)
    _, corners, weights = bilinear(np.zeros((h, w, 1)), uv[idx])
    pixels, inverse = np.unique(corners.ravel(), return_inverse=True)
    dirs = undistort(cam, np.stack([pixels % w, pixels // w], -1).astype(np.float64))
    hits = caster.first_hit(np.broadcast_to(cam.center, dirs.shape), dirs) if len(pixels) else None
    points = hits.points if hits is not None else np.zeros((0, 3))
    face = hits.face if hits is not None else np.zeros(0, np.int64)
    corner = inverse.reshape(-1, 4)
    gap = np.linalg.norm(np.where((face >= 0)[:, None], points, np.inf)[corner] - vertices[idx, None, :],
                         axis=-1)
    focal = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    tol = _FOOTPRINTS * dist[idx] / focal / np.maximum(cos_o[idx], 0.2)
    clean = np.all((gap <= tol[:, None]) | (weights <= 1e-9), axis=1)
    mixed = np.zeros(len(vertices), bool)
    mixed[idx[~clean]] = True
    return _View(uv, in_frame, cos_o > 0, seen & ~mixed, mixed, idx[clean], corner[clean], weights[clean],
                 points, face)


def _shadow_edges(caster, view: _View, light_pos, vertex_lit) -> np.ndarray:
    """`(U,)` bool for the usable vertices of `view`: some bilinear pixel is lit
    differently from the vertex (a cast-shadow edge runs between them)."""
    hit = view.face >= 0
    pixel_lit = np.zeros(len(view.face), bool)
    pts = view.points[hit]
    if len(pts):
        pixel_lit[hit] = ~caster.segments_blocked(pts, caster.face_normals[view.face[hit]],
                                                  np.broadcast_to(light_pos, pts.shape))
    differs = pixel_lit[view.corner] != vertex_lit[view.idx, None]
    return np.any(differs & (view.weight > 1e-9), axis=1)


def _ingest_pinhole(folder, rig):
    mesh_path = _file(folder, rig.get("mesh"), "mesh")
    vertices, faces, file_normals = _load_mesh(mesh_path)
    faces, dropped = _drop_degenerate(vertices, faces)
    if len(faces) == 0:
        raise ScanError("mesh", "every face is degenerate")
    if file_normals is not None:
        normals = file_normals
    else:
        normals = area_normal_sums(vertices, faces)
    length = np.linalg.norm(normals, axis=1)
    if np.any(length == 0):
        raise ScanError("mesh", f"{int((length == 0).sum())} vertices have no normal (they belong to no "
                                f"face), first at index {int(np.argmax(length == 0))}")
    normals = normals / length[:, None]

    cameras = [_camera(c, k) for k, c in enumerate(_list(rig, "cameras"))]
    lights = _list(rig, "lights")
    light_pos, light_rgb = [], []
    for k, e in enumerate(lights):
        if not isinstance(e, dict) or "position" not in e:
            raise ScanError(f"lights[{k}]", "must be an object with 'position' [m] and 'intensity' [W/sr]")
        light_pos.append(_array(e["position"], (3,), f"lights[{k}].position"))
        light_rgb.append(_light_intensity(e, f"lights[{k}]"))
    images = _images(rig, folder, len(lights), len(cameras))
    transfer, black, saturation = _photometry(rig)

    caster = RayCaster(vertices, faces)
    centres = np.stack([c.center for c in cameras])
    visible = caster.visibility(centres)  # (N, C) line of sight from each vertex to each camera
    views = [_view(caster, c, vertices, normals, visible[:, k]) for k, c in enumerate(cameras)]
    lit = caster.visibility(np.stack(light_pos))  # (N, L) vertex to light unblocked

    n, m = len(vertices), len(images)
    radiance = np.zeros((n, m, 3))
    valid = np.zeros((n, m), bool)
    reasons = ("out_of_frame", "back_facing", "occluded", "mixed_pixels", "shadow_edge", "saturated")
    counts = dict.fromkeys(reasons, 0)
    for j, (path, light, cam_k, exposure) in enumerate(images):
        cam, view = cameras[cam_k], views[cam_k]
        rad, saturated = _radiance(path, f"images[{j}]", (cam.height, cam.width), transfer, black,
                                   saturation, exposure, light_rgb[light])
        values, corners, weights = bilinear(rad, view.uv[view.idx])
        sat = np.any(saturated.ravel()[corners] & (weights > 1e-9), axis=1)
        edge = _shadow_edges(caster, view, light_pos[light], lit[:, light])
        keep = view.idx[~sat & ~edge]
        radiance[keep, j] = values[~sat & ~edge]
        valid[keep, j] = True
        counts["out_of_frame"] += int((~view.in_frame).sum())
        counts["back_facing"] += int((view.in_frame & ~view.facing).sum())
        counts["occluded"] += int((view.in_frame & view.facing & ~visible[:, cam_k]).sum())
        counts["mixed_pixels"] += int(view.mixed.sum())
        counts["shadow_edge"] += int((edge & ~sat).sum())
        counts["saturated"] += int(sat.sum())

    cam0 = cameras[images[0][2]]
    describe = lambda c: {"type": "pinhole", "K": c.K.tolist(), "R": c.R.tolist(),  # noqa: E731
                          "t": c.t.tolist(), "width": c.width, "height": c.height, "dist": c.dist.tolist()}
    intensity = np.array([light_rgb[i[1]].mean() for i in images])
    meta = {
        "generator": "jaxrefl.scan.ingest",
        "source": os.path.abspath(folder),
        "mesh": os.path.basename(mesh_path),
        "normals": "mesh file" if file_normals is not None else "area-weighted",
        "degenerate_faces_dropped": dropped,
        "rig": describe(cam0),
        "cameras": [describe(c) for c in cameras],
        "images": [{"file": os.path.relpath(p, folder), "light": li, "camera": ck, "exposure": ex}
                   for p, li, ck, ex in images],
        "light_rgb": [light_rgb[i[1]].tolist() for i in images],
        "transfer": transfer, "black_level": black, "saturation": saturation,
        "masked_samples": counts,
    }
    cam_pos = np.stack([cameras[i[2]].center for i in images])
    return Scan(vertices=vertices, faces=faces, normals=normals,
                light_pos=np.stack([light_pos[i[1]] for i in images]), light_intensity=intensity,
                cam_pos=cam_pos if len(cameras) > 1 else cam_pos[0], radiance=radiance, valid=valid,
                meta=meta)


# -- photometric-stereo data sets ---------------------------------------------------------


def _normal_map(folder, rig):
    path = _file(folder, rig.get("normals"), "normals")
    try:
        values, top = read_image(path)
    except (ValueError, OSError) as exc:
        raise ScanError("normals", f"{os.path.basename(path)}: {exc}") from None
    if values.shape[2] < 3:
        raise ScanError("normals", f"need 3 channels (nx, ny, nz), got {values.shape[2]}")
    n = values[..., :3]
    return 2.0 * n - 1.0 if top is not None else n  # PNG normal maps store (n + 1) / 2


def _ingest_photometric_stereo(folder, rig):
    normal_map = _normal_map(folder, rig)
    h, w = normal_map.shape[:2]
    length = np.linalg.norm(normal_map, axis=-1)
    if "mask" in rig:
        mpath = _file(folder, rig["mask"], "mask")
        try:
            mvals, _ = read_image(mpath)
        except (ValueError, OSError) as exc:
            raise ScanError("mask", f"{os.path.basename(mpath)}: {exc}") from None
        if mvals.shape[:2] != (h, w):
            raise ScanError("mask", f"is {mvals.shape[1]}x{mvals.shape[0]}, the normal map {w}x{h}")
        mask = np.any(mvals[..., :3] > 0, axis=-1)
        bad = mask & (length < 0.5)
        if np.any(bad):
            r, c = np.argwhere(bad)[0]
            raise ScanError("normals", f"{int(bad.sum())} masked pixel(s) without a unit normal, "
                                       f"e.g. row {r}, column {c}")
    else:
        mask = length > 0.5
    size = _number(rig, "pixel_size", 1.0 / max(h, w))
    if not size > 0:
        raise ScanError("pixel_size", f"must be > 0, got {size}")

    index = np.full((h, w), -1, np.int64)
    index[mask] = np.arange(int(mask.sum()))
    rows, cols = np.nonzero(mask)
    if len(rows) < 3:
        raise ScanError("mask", f"only {len(rows)} pixel(s) inside the mask")
    vertices = np.stack([(cols - (w - 1) / 2) * size, -(rows - (h - 1) / 2) * size, np.zeros(len(rows))], -1)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    quad = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.stack([a[quad], c[quad], d[quad]], -1),
                            np.stack([a[quad], d[quad], b[quad]], -1)])  # counter-clockwise seen from +z
    if len(faces) == 0:
        raise ScanError("mask", "holds no 2x2 block of pixels: no surface to mesh")
    normals = normal_map[mask] / length[mask][:, None]

    lights = _list(rig, "lights")
    extent = size * max(h, w)
    far = DISTANT * extent
    centre = np.zeros(3)
    light_pos, light_rgb = [], []
    for k, e in enumerate(lights):
        if not isinstance(e, dict) or "direction" not in e:
            raise ScanError(f"lights[{k}]", "must be an object with 'direction' (unit, toward the light) "
                                            "and 'intensity'")
        d = _array(e["direction"], (3,), f"lights[{k}].direction")
        if np.linalg.norm(d) < 1e-9:
            raise ScanError(f"lights[{k}].direction", "must not be zero")
        light_pos.append(centre + far * d / np.linalg.norm(d))
        light_rgb.append(_light_intensity(e, f"lights[{k}]"))
    images = _images(rig, folder, len(lights), 1)
    transfer, black, saturation = _photometry(rig)

    m = len(images)
    radiance = np.zeros((len(rows), m, 3))
    valid = np.zeros((len(rows), m), bool)
    facing = normals[:, 2] > 0
    saturated_count = 0
    for j, (path, light, _, exposure) in enumerate(images):
        rad, saturated = _radiance(path, f"images[{j}]", (h, w), transfer, black, saturation, exposure,
                                   light_rgb[light])
        sat = saturated[mask]
        radiance[:, j] = np.where(sat[:, None], 0.0, rad[mask])
        valid[:, j] = facing & ~sat
        saturated_count += int((facing & sat).sum())
    meta = {
        "generator": "jaxrefl.scan.ingest",
        "source": os.path.abspath(folder),
        "rig": {"type": "orthographic", "view": [0.0, 0.0, -1.0], "pixel_size": size, "width": w,
                "height": h, "distant": DISTANT},
        "images": [{"file": os.path.relpath(p, folder), "light": li, "exposure": ex}
                   for p, li, _, ex in images],
        "light_rgb": [light_rgb[i[1]].tolist() for i in images],
        "light_directions": [(light_pos[i[1]] / far).tolist() for i in images],
        "transfer": transfer, "black_level": black, "saturation": saturation,
        "masked_samples": {"back_facing": int((~facing).sum()) * m, "saturated": saturated_count},
    }
    intensity = np.array([light_rgb[i[1]].mean() for i in images]) * far**2
    return Scan(vertices=vertices, faces=faces, normals=normals,
                light_pos=np.stack([light_pos[i[1]] for i in images]), light_intensity=intensity,
                cam_pos=centre + np.array([0.0, 0.0, far]), radiance=radiance, valid=valid, meta=meta)


# -- entry point ------------------------------------------------------------------------


def ingest(folder) -> Scan:
    """Read a capture folder (see the module docstring) into a validated `Scan`.

    Raises `ScanError` naming the offending entry (`rig.json`, `mesh`,
    `cameras[k].K`, `lights`, `images[j]`, ...).
    """
    rig = _load_rig(folder)
    kind = rig.get("type", "pinhole")
    if kind == "pinhole":
        scan = _ingest_pinhole(os.fspath(folder), rig)
    elif kind == "photometric-stereo":
        scan = _ingest_photometric_stereo(os.fspath(folder), rig)
    else:
        raise ScanError("type", f"must be 'pinhole' or 'photometric-stereo', got {kind!r}")
    if not np.any(scan.valid):
        raise ScanError("images", "no vertex is seen unsaturated in any image: check the cameras and mesh")
    return validate_scan(scan)
