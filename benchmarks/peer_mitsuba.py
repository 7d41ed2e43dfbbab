"""Peer benchmark: jaxrefl against Mitsuba 3 inverse rendering on the same observations.

Run: `python3 -m benchmarks.peer_mitsuba [--budget 300] [--quick] [--cells convex,fold,bowl]
[--lr 0.1] [--spp 2] [--gi-spp 4] [--gi-depth 4] [--px-per-edge 3] [--out benchmarks/RESULTS_peer.md]`
(the JSON with every number and both tools' error-vs-time traces lands next to the markdown,
`RESULTS_peer.json`, the plot as `RESULTS_peer.png`; all three are rewritten after each scene).
`--quick`: a 30 s Mitsuba budget per scene, Method I only on the jaxrefl side, a cheaper
convention check (for trying the pipeline, not for numbers).

Needs the optional `peer` extra (`pip install -e ".[peer]"`: Mitsuba 3 and Dr.Jit) and an
LLVM shared library for Dr.Jit's CPU backend (variant `llvm_ad_rgb`); without them the
benchmark stops with one message saying how to install them (`missing_message`).

Scenes (the zoo's default sizes, seed 0; `SCENES`):

- `convex`: `ring_piecewise`, the bumpy nearly convex blob on the turntable ring (24 cameras,
  each with its own light 8-12 deg beside it), 4 Ward materials, direct light only.
- `fold`: `gi_fold_coaxial`, the glossy right-angle fold, one camera, 12 lights beside it,
  full global illumination (path-traced by `data_synth.pathtrace`).
- `bowl`: `gi_bowl`, the hemispherical bowl seen from inside, 24 distant lights, full GI.

Both tools get the same scan: the same mesh, normals, light positions and intensities, the
same noisy, quantised radiance samples and the same `valid` / saturation mask.

Mitsuba side, as its documentation teaches inverse rendering:

- The scene: the scan's mesh as an `mi.Mesh` with its per-vertex normals, one `perspective`
  sensor per distinct camera position of the scan (a zoo scan stores camera *centres* only, no
  intrinsics or orientation: each sensor looks at the object's bounding-box centre, world +y
  up, square, field of view framing every vertex, resolution giving about `--px-per-edge`
  pixels per projected mesh edge; box pixel filter), one `point` emitter moved to each
  observation's light position with its radiant intensity (Mitsuba's `intensity` is the
  radiant intensity [W/sr], the scan's convention).
- The BSDF: Mitsuba has no Ward BSDF. The closest stock model is a `blendbsdf` (weight 0.5) of
  `diffuse` (Lambert) and `roughconductor` with `material: none` (Fresnel = 1) and the
  `beckmann` distribution; every parameter is a per-vertex mesh attribute read by a
  `mesh_attribute` texture (`vertex_rd` = 2 pd RGB, `vertex_rs` = 2 ks, `vertex_alpha`):
  `f = pd / pi + ks D G / (4 cos_i cos_o)`, Beckmann `D = exp(-tan^2 th_h / a^2) / (pi a^2 cos^4 th_h)`.
  Ward's lobe is `ps exp(-tan^2 th_h / a^2) / (4 pi a^2 sqrt(cos_i cos_o))`: the same
  exponent (alpha means the same), but the microfacet lobe is larger by
  `G / (cos^4 th_h sqrt(cos_i cos_o))`, so `ks` is Ward's `ps` only at normal incidence;
  pd is the same Lambert albedo in both models.
- The fit: the stock `prb` integrator (`max_depth` 2 for direct light, `--gi-depth` for the GI
  scenes), `mi.ad.Adam(lr)` on the three mesh attributes (clamped after each step) from a flat
  start (`FLAT_START`), every iteration rendering every observation (`mi.render(scene, params,
  sensor=k, spp, seed)`) and back-propagating its loss (`dr.backward`) before one `opt.step()`.
  The loss of an observation: the squared difference between the scan's radiance at each
  observed vertex and the rendered image at the vertex's projection (bilinear, as
  `jaxrefl.scan.ingest` samples photographs), mean over all observed samples. A vertex whose
  bilinear taps are not all on its own smooth surface (silhouettes, occluding edges, creases:
  tested once on a position and normal AOV, `taps_on_surface`) is left out, as ingest masks
  silhouettes; points without any usable sample stay at the flat start.
- Wall time from the first render (Dr.Jit's kernel compilation included) to each iteration's
  end; the error evaluation between iterations is not counted. Stops at `--budget` seconds.

jaxrefl side: `jaxrefl.estimate(scan, method=...)` with `Local(model='ward')` (I), and on the
GI scenes also `Radiosity(local=...)` (II), `Photon(photons=200000, iterations=20)` (III) and
`Auto(local=..., photon=same)`, as `benchmarks.rigs_gi` runs them; each twice: `first`
(in-process JAX compilation, form factors cast: `$JAXREFL_CACHE` points at a fresh folder
unless `--keep-caches`) and `warm`.

Errors: per point the relative error `|est - truth| / truth` (pd: mean over RGB; roughness:
Ward alpha against the Beckmann alpha or jaxrefl's Ward alpha; ps: jaxrefl's Ward ps, Mitsuba's
microfacet ks against the true Ward ps, *not the same quantity*, see above), median over
**all** points (unobserved ones included: jaxrefl fills them, Mitsuba leaves them at the flat
start) and over the observed ones.

Time to error: for each jaxrefl method, the first Mitsuba wall time at which its median pd
error (all points) is at or below that method's final one; `never within budget` if it does
not get there; the ratio Mitsuba time / jaxrefl time (warm and first).

Convention check (before any optimisation; `convention_check`): (1) a position AOV sampled at
each vertex's projection against the vertex; (2) the scan's *true* diffuse albedo rendered by
Mitsuba (direct light, ks = 0) against `data_synth.zoo.render` of the same diffuse truth at the
vertices -- the camera, pixel-centre, image-axis and light-intensity conventions in one number,
with the image mirrored in x and in y as a control; (3) the full truth through the stock BSDF
(pd, ks = ps, alpha) against the scan's noise-free radiance: the model mismatch (and, on GI
scenes, Mitsuba's GI against the path tracer's).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

SCENES = {"convex": "ring_piecewise", "fold": "gi_fold_coaxial", "bowl": "gi_bowl"}
FLAT_START = {"pd": 0.25, "ks": 0.1, "alpha": 0.2}
BOUNDS = {"pd": (0.0, 1.0), "ks": (0.0, 2.0), "alpha": (0.01, 1.0)}
BLEND_WEIGHT = 0.5  # blendbsdf weight: f = (1 - w) diffuse(rd) + w roughconductor(rs); rd = pd / (1 - w)
VARIANT = "llvm_ad_rgb"
MIN_LLVM = (17, 0, 0)  # Dr.Jit 1.5 aborts on LLVM 15 and 16 ("Cannot select: ... fminimum")
BUDGET, QUICK_BUDGET = 300.0, 30.0
LR = 0.1
SPP, GI_SPP, GI_DEPTH = 2, 4, 4
PX_PER_EDGE = 3.0
CHECK_SPP, QUICK_CHECK_SPP = 64, 16
PHOTON = {"photons": 200_000, "iterations": 20}
GI_METHODS = ("I", "II", "III", "auto")
TAP_TOLERANCE = 0.25  # tap surface points within this many median edges of the tangent plane (12x of the vertex)


# -- installation ------------------------------------------------------------------------


class PeerUnavailable(RuntimeError):
    """Mitsuba / Dr.Jit / LLVM missing or unusable; the message says how to install them."""


INSTALL_HINT = """\
Install the optional extra and an LLVM runtime for Dr.Jit's CPU backend, then run again:

    python3 -m pip install -e ".[peer]"      # mitsuba and drjit (pip install mitsuba drjit)
    apt-get install -y libllvm19             # Debian 12; Dr.Jit 1.5 aborts with LLVM 15 and 16
    export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1   # only if it is not found

(Dr.Jit's LLVM backend needs LLVM >= 17; libLLVM 19.1 is the one this benchmark was run with.)"""


def missing_message(reason: str) -> str:
    """The one message the benchmark stops with when Mitsuba cannot run."""
    return f"benchmarks.peer_mitsuba needs Mitsuba 3 with the {VARIANT} variant: {reason}.\n{INSTALL_HINT}"


def load_mitsuba(variant: str = VARIANT):
    """`(mitsuba, drjit)` with `variant` set, or `PeerUnavailable` with an install message."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        raise PeerUnavailable(missing_message(f"not installed ({exc})")) from None
    try:
        mi.set_variant(variant)
    except Exception as exc:  # noqa: BLE001 - ImportError / AttributeError / RuntimeError by version
        raise PeerUnavailable(missing_message(f"variant {variant!r} unavailable ({str(exc).splitlines()[0]})")) from None
    if variant.startswith("llvm"):
        version = getattr(getattr(dr, "detail", None), "llvm_version", lambda: None)()
        if version is not None and (0, 0, 0) < tuple(version) < MIN_LLVM:
            found = ".".join(map(str, version))
            raise PeerUnavailable(missing_message(f"Dr.Jit found libLLVM {found}, which aborts while compiling "
                                                  "Mitsuba's kernels"))
    return mi, dr


# -- cameras and projection (NumPy, no Mitsuba) --------------------------------------------


def _unit(a):
    a = np.asarray(a, dtype=np.float64)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Camera:
    """A pinhole in Mitsuba's `perspective` conventions: at `origin` looking at `target`,
    `up` the world direction that appears up; `fov_x` [deg] the horizontal field of view;
    `width` x `height` pixels. Image x grows along `cross(forward, up)` (to the right), image y
    grows downward; pixel `(i, j)` covers `[i, i + 1] x [j, j + 1]`, its centre at `+ 0.5`."""

    origin: tuple
    target: tuple
    up: tuple
    fov_x: float
    width: int
    height: int

    def basis(self):
        """Unit `right`, `up`, `forward` vectors of the image plane (right-handed with -forward)."""
        f = _unit(np.subtract(self.target, self.origin))
        r = _unit(np.cross(f, self.up))
        return r, np.cross(r, f), f

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.fov_x) / 2)

    def project(self, points):
        """`(P, 2)` continuous pixel coordinates (x right, y down) and `(P,)` depth along the
        view axis of world `points` `(P, 3)`."""
        r, u, f = self.basis()
        d = np.asarray(points, dtype=np.float64) - np.asarray(self.origin, dtype=np.float64)
        z = d @ f
        safe = np.where(np.abs(z) > 1e-300, z, 1e-300)
        x = 0.5 * self.width + self.focal * (d @ r) / safe
        y = 0.5 * self.height - self.focal * (d @ u) / safe
        return np.stack([x, y], -1), z

    def to_dict(self) -> dict:
        return {k: (list(map(float, v)) if isinstance(v, (tuple, list, np.ndarray)) else v)
                for k, v in asdict(self).items()}


def up_hint(forward) -> np.ndarray:
    """World +y, or +z where the view is within 10 deg of the y axis."""
    f = _unit(forward)
    return np.array([0.0, 0.0, 1.0]) if abs(f[1]) > math.cos(math.radians(10)) else np.array([0.0, 1.0, 0.0])


def mesh_edges(faces) -> np.ndarray:
    """`(E, 2)` unique undirected edges of a triangle mesh."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def frame_camera(cam_pos, vertices, faces, px_per_edge=PX_PER_EDGE, margin=1.08, min_size=64,
                 max_size=640) -> Camera:
    """A square camera at `cam_pos` looking at the bounding-box centre of `vertices`, its
    field of view framing every vertex (times `margin`), sized so the median mesh edge spans
    about `px_per_edge` pixels (clipped to `[min_size, max_size]`)."""
    v = np.asarray(vertices, dtype=np.float64)
    target = 0.5 * (v.min(0) + v.max(0))
    origin = np.asarray(cam_pos, dtype=np.float64)
    up = up_hint(target - origin)
    probe = Camera(tuple(origin), tuple(target), tuple(up), 90.0, 2, 2)  # focal 1 px: tangent units
    xy, z = probe.project(v)
    if np.any(z <= 0):
        raise ValueError("frame_camera: part of the object lies behind the camera")
    t = xy - 1.0
    half = margin * float(np.abs(t).max())
    e = mesh_edges(faces)
    edge_t = float(np.median(np.linalg.norm(t[e[:, 0]] - t[e[:, 1]], axis=1)))
    size = int(np.clip(math.ceil(2 * half * px_per_edge / max(edge_t, 1e-300)), min_size, max_size))
    return Camera(tuple(origin), tuple(target), tuple(up), math.degrees(2 * math.atan(half)), size, size)


def observation_cameras(scan):
    """Distinct camera centres `(K, 3)` and the camera index `(M,)` of each observation. A scan
    with per-point camera positions (`(N, 1, 3)`, `(N, M, 3)`) has no pinhole: `ValueError`."""
    cp = np.asarray(scan.cam_pos, dtype=np.float64)
    m = scan.n_lights
    if cp.ndim == 1:
        return cp[None], np.zeros(m, dtype=np.int64)
    if cp.ndim == 2:
        cams, index = np.unique(cp, axis=0, return_inverse=True)
        return cams, np.asarray(index, dtype=np.int64).reshape(m)
    raise ValueError("peer benchmark: per-point camera positions have no pinhole camera")


def bilinear_taps(xy, width, height):
    """Bilinear interpolation of an image at continuous pixel coordinates `xy` `(P, 2)` (pixel
    centres at `i + 0.5`): flat pixel indices `row * width + col` `(P, 4)`, weights `(P, 4)`
    summing to 1, and `(P,)` bool: all four taps inside the image (indices clipped elsewhere)."""
    s = np.asarray(xy, dtype=np.float64) - 0.5
    x0, y0 = np.floor(s[:, 0]).astype(np.int64), np.floor(s[:, 1]).astype(np.int64)
    fx, fy = s[:, 0] - x0, s[:, 1] - y0
    inside = (x0 >= 0) & (x0 + 1 < width) & (y0 >= 0) & (y0 + 1 < height)
    cols = np.stack([x0, x0 + 1, x0, x0 + 1], 1)
    rows = np.stack([y0, y0, y0 + 1, y0 + 1], 1)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    index = np.clip(rows, 0, height - 1) * width + np.clip(cols, 0, width - 1)
    return index, w, inside


def sample_image(image, index, weights) -> np.ndarray:
    """`(P, C)` values of `image` `(H, W, C)` at taps from `bilinear_taps`."""
    img = np.asarray(image, dtype=np.float64)
    flat = img.reshape(-1, img.shape[-1])
    return np.einsum("pk,pkc->pc", weights, flat[index])


def taps_on_surface(surface, index, vertices, normals, tolerance, reach=12.0, min_cos=0.9) -> np.ndarray:
    """`(P,)` bool: the bilinear footprint of each vertex lies on the vertex's own smooth
    surface. `surface` `(H*W, 6)` flat per pixel: the pixel's mean surface position and mean
    shading normal (an `aov` render, background 0); `index` `(P, 4)` taps; `vertices`, unit
    `normals` `(P, 3)`. Every tap's point must lie within `tolerance` [m] of the vertex's tangent
    plane and within `reach` x `tolerance` of the vertex, and its mean normal must have length
    and cosine to the vertex normal >= `min_cos`: a silhouette (background averaged in) or an
    occluding edge or crease (another surface) fails, a grazing view of the same surface, where
    a pixel spans a long stretch of it, passes."""
    v = np.asarray(vertices, dtype=np.float64)
    nv = np.asarray(normals, dtype=np.float64)
    s = np.asarray(surface, dtype=np.float64)[index]  # (P, 4, 6)
    d = s[..., :3] - v[:, None]
    n = s[..., 3:6]
    off_plane = np.abs(np.einsum("pkc,pc->pk", d, nv))
    length = np.linalg.norm(n, axis=-1)
    cos = np.einsum("pkc,pc->pk", n, nv) / np.maximum(length, 1e-12)
    ok = (off_plane <= tolerance) & (np.linalg.norm(d, axis=-1) <= reach * tolerance)
    return np.all(ok & (length >= min_cos) & (cos >= min_cos), axis=1)


# -- errors and time to error -------------------------------------------------------------


def relative_errors(value, truth) -> np.ndarray:
    """Per-point relative error `(N,)` `|value - truth| / |truth|`, the RGB mean for pd; `nan`
    where the truth is 0 (`benchmarks.rigs_gi.relative_errors`)."""
    value, truth = np.asarray(value, float), np.asarray(truth, float)
    n = len(truth)
    t = np.abs(truth).reshape(n, -1)
    d = np.abs(value - truth).reshape(n, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.where(t > 1e-12, d / np.where(t > 1e-12, t, 1.0), np.nan)
    return err.mean(axis=1)


def _median(err, mask=None):
    e = err if mask is None else err[np.asarray(mask, bool)]
    e = e[np.isfinite(e)]
    return float(np.median(e)) if e.size else None


def point_errors(pd, ps, roughness, truth, observed) -> dict:
    """Median relative errors over all points (`all`), their 90th percentile (`p90`) and the
    median over the `observed` points, for `pd`, `ps` and `roughness`."""
    out = {}
    for key, value in (("pd", pd), ("ps", ps), ("roughness", roughness)):
        err = relative_errors(value, truth[key])
        fin = err[np.isfinite(err)]
        out[key] = {"all": _median(err), "observed": _median(err, observed),
                    "p90": float(np.percentile(fin, 90)) if fin.size else None}
    return out


def time_to_error(times, errors, target):
    """First time in `times` at which `errors` is at or below `target` (a relative 1e-9
    allowance), or None: never within the trace."""
    if target is None:
        return None
    for t, e in zip(times, errors):
        if e is not None and np.isfinite(e) and e <= target * (1 + 1e-9):
            return float(t)
    return None


def first_iteration_overhead(trace) -> float:
    """Seconds the first iteration took beyond the median of the later ones (Dr.Jit's kernel
    compilation or cache loading, first-touch costs); 0 with fewer than 3 iterations."""
    t = [r["seconds"] for r in trace if r.get("iteration", 1) >= 1]
    if len(t) < 3:
        return 0.0
    steps = np.diff([0.0] + t)
    return float(max(steps[0] - np.median(steps[1:]), 0.0))


def time_to_error_rows(trace, jaxrefl_runs) -> list[dict]:
    """For each jaxrefl method: its final median pd error (all points), its warm and first
    seconds, the Mitsuba time to reach that error (`trace`: dicts with `iteration`, `seconds`
    and `pd`; as run, and less the first iteration's overhead, `first_iteration_overhead`) and
    the ratios: Mitsuba less overhead / jaxrefl warm, Mitsuba as run / jaxrefl first (None where
    Mitsuba never got there)."""
    times = [r["seconds"] for r in trace]
    errs = [r["pd"] for r in trace]
    overhead = first_iteration_overhead(trace)
    rows = []
    for name, run in jaxrefl_runs.items():
        if "error" in run:
            continue
        target = run["errors"]["pd"]["all"]
        t_mi = time_to_error(times, errs, target)
        at_start = t_mi is not None and t_mi <= 0.0  # the flat start is already as good: no ratio
        t_warm = None if t_mi is None else max(t_mi - overhead, 0.0)
        warm, first = run.get("seconds_warm"), run.get("seconds_first")
        rows.append({"method": name, "pd": target, "seconds_warm": warm, "seconds_first": first,
                     "mitsuba_seconds": t_mi, "mitsuba_seconds_warm": t_warm, "mitsuba_overhead": overhead,
                     "flat_start_as_good": at_start,
                     "ratio_warm": None if t_warm is None or not warm or at_start else t_warm / warm,
                     "ratio_first": None if t_mi is None or not first or at_start else t_mi / first})
    return rows


# -- Mitsuba --------------------------------------------------------------------------------


class MitsubaFit:
    """The scan as a Mitsuba scene with per-vertex stock-BSDF parameters, its observations as
    bilinear taps into rendered images, and the Adam fit.

    **Arguments:** `scan` a `jaxrefl.Scan`; `mi`, `dr` from `load_mitsuba`; `max_depth` of the
    `prb` integrator the fit uses; `px_per_edge` image resolution (`frame_camera`).
    """

    def __init__(self, scan, mi, dr, max_depth=2, px_per_edge=PX_PER_EDGE):
        self.scan, self.mi, self.dr = scan, mi, dr
        self.n = scan.n_points
        self.max_depth = int(max_depth)
        cams, self.obs_cam = observation_cameras(scan)
        self.cameras = [frame_camera(c, scan.vertices, scan.faces, px_per_edge) for c in cams]
        e = mesh_edges(scan.faces)
        self.edge = float(np.median(np.linalg.norm(scan.vertices[e[:, 0]] - scan.vertices[e[:, 1]], axis=1)))
        t0 = time.perf_counter()
        self.scene, self.params = self._build()
        self.integrator = mi.load_dict({"type": "prb", "max_depth": self.max_depth})
        self.direct = mi.load_dict({"type": "prb", "max_depth": 2})
        self.build_seconds = time.perf_counter() - t0
        self.positions = None
        self.taps = None

    # scene -----------------------------------------------------------------------------
    def _build(self):
        mi = self.mi
        scan = self.scan
        bsdf = mi.load_dict({
            "type": "blendbsdf", "weight": BLEND_WEIGHT,
            "diffuse": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_rd"}},
            "lobe": {"type": "roughconductor", "material": "none", "distribution": "beckmann",
                     "alpha": {"type": "mesh_attribute", "name": "vertex_alpha"},
                     "specular_reflectance": {"type": "mesh_attribute", "name": "vertex_rs"}},
        })
        props = mi.Properties()
        props["bsdf"] = bsdf
        mesh = mi.Mesh("object", self.n, len(scan.faces), props=props, has_vertex_normals=True)
        mp = mi.traverse(mesh)
        mp["vertex_positions"] = mi.Float(np.ravel(scan.vertices).astype(np.float32))
        mp["faces"] = mi.UInt32(np.ravel(scan.faces).astype(np.uint32))
        mp["vertex_normals"] = mi.Float(np.ravel(scan.normals).astype(np.float32))
        mp.update()
        pd, ks, alpha = self._flat()
        mesh.add_attribute("vertex_rd", 3, (pd / (1 - BLEND_WEIGHT)).ravel().tolist())
        mesh.add_attribute("vertex_rs", 1, (ks / BLEND_WEIGHT).tolist())
        mesh.add_attribute("vertex_alpha", 1, alpha.tolist())
        scene = {"type": "scene", "object": mesh,
                 "light": {"type": "point", "position": [float(x) for x in scan.light_pos[0]],
                           "intensity": {"type": "rgb", "value": [float(scan.intensities()[0])] * 3}}}
        for k, cam in enumerate(self.cameras):
            scene[f"sensor_{k}"] = {
                "type": "perspective", "fov": cam.fov_x, "fov_axis": "x",
                "near_clip": 1e-3 * float(np.linalg.norm(np.subtract(cam.target, cam.origin))),
                "to_world": mi.ScalarTransform4f().look_at(origin=[float(x) for x in cam.origin],
                                                           target=[float(x) for x in cam.target],
                                                           up=[float(x) for x in cam.up]),
                "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "rfilter": {"type": "box"},
                         "pixel_format": "rgb"},
                "sampler": {"type": "independent"},
            }
        scene = mi.load_dict(scene)
        return scene, mi.traverse(scene)

    def _flat(self):
        return (np.full((self.n, 3), FLAT_START["pd"]), np.full(self.n, FLAT_START["ks"]),
                np.full(self.n, FLAT_START["alpha"]))

    def sensor_index(self, m) -> int:
        """The scene sensor of observation `m` (`mi.render(..., sensor=k)`)."""
        return int(self.obs_cam[m])

    def set_reflectance(self, pd, ks, alpha):
        """Per-vertex Lambert albedo `pd` `(N, 3)`, microfacet `ks` `(N,)`, Beckmann `alpha` `(N,)`."""
        mi, p = self.mi, self.params
        p["object.vertex_rd"] = mi.Float((np.asarray(pd, float) / (1 - BLEND_WEIGHT)).ravel().astype(np.float32))
        p["object.vertex_rs"] = mi.Float((np.asarray(ks, float) / BLEND_WEIGHT).astype(np.float32))
        p["object.vertex_alpha"] = mi.Float(np.clip(np.asarray(alpha, float), *BOUNDS["alpha"]).astype(np.float32))
        p.update()

    def set_light(self, m):
        """Move the point light to observation `m`'s position and intensity."""
        mi, p = self.mi, self.params
        p["light.position"] = mi.Point3f(*[float(x) for x in self.scan.light_pos[m]])
        p["light.intensity.value"] = mi.Color3f(float(self.scan.intensities()[m]))
        p.update()

    def render(self, m, spp, seed=0, integrator=None, params=None):
        """Observation `m`'s image `(H, W, 3)` (a `TensorXf`; differentiable with `params`)."""
        self.set_light(m)
        return self.mi.render(self.scene, params, sensor=self.sensor_index(m), integrator=integrator or self.integrator,
                              spp=int(spp), seed=int(seed))

    def position_images(self, spp=16):
        """Per camera, `(H*W, 6)` per pixel: mean surface position and mean shading normal (an
        `aov` render, 0 on the background)."""
        if self.positions is None:
            aov = self.mi.load_dict({"type": "aov", "aovs": "p:position,n:sh_normal"})
            self.positions = []
            for k in range(len(self.cameras)):
                img = np.asarray(self.mi.render(self.scene, sensor=k, integrator=aov, spp=spp, seed=k))
                self.positions.append(img[..., :6].reshape(-1, 6))
        return self.positions

    def projected(self, m):
        """Observation `m`'s camera's taps of every vertex: `(index, weights, inside)`."""
        cam = self.cameras[self.sensor_index(m)]
        xy, z = cam.project(self.scan.vertices)
        index, w, inside = bilinear_taps(xy, cam.width, cam.height)
        return index, w, inside & (z > 0)

    def build_taps(self):
        """Per observation: the vertices used (observed, in frame, bilinear footprint on the
        surface near the vertex), their taps and radiance, as Dr.Jit arrays."""
        mi = self.mi
        positions = self.position_images()
        observed = self.scan.observed()
        self.taps, self.used = [], np.zeros_like(observed)
        for m in range(self.scan.n_lights):
            index, w, inside = self.projected(m)
            ok = observed[:, m] & inside
            ok[ok] = taps_on_surface(positions[self.sensor_index(m)], index[ok], self.scan.vertices[ok],
                                     self.scan.normals[ok], TAP_TOLERANCE * self.edge)
            rows = np.flatnonzero(ok)
            self.used[:, m] = ok
            chan = np.arange(3)
            flat_idx = (index[rows][:, :, None] * 3 + chan).transpose(1, 0, 2).reshape(4, -1)  # (4, P*3)
            flat_w = np.repeat(w[rows].T[:, :, None], 3, axis=2).reshape(4, -1)
            target = np.asarray(self.scan.radiance[rows, m], dtype=np.float32).ravel()
            self.taps.append({"rows": rows, "index": [mi.UInt32(a.astype(np.uint32)) for a in flat_idx],
                              "weights": [mi.Float(a.astype(np.float32)) for a in flat_w],
                              "target": mi.Float(target), "count": len(rows)})
        return self.used

    def predict(self, image, m):
        """The rendered values at observation `m`'s used vertices, flat `(P*3,)` (differentiable)."""
        dr, mi = self.dr, self.mi
        t = self.taps[m]
        flat = image.array
        out = dr.gather(mi.Float, flat, t["index"][0]) * t["weights"][0]
        for k in range(1, 4):
            out += dr.gather(mi.Float, flat, t["index"][k]) * t["weights"][k]
        return out

    def sample_numpy(self, image, m, rows=None):
        """NumPy `(P, 3)` values of `image` at observation `m`'s vertices `rows` (default all)."""
        index, w, _ = self.projected(m)
        rows = np.arange(self.n) if rows is None else rows
        return sample_image(np.asarray(image), index[rows], w[rows])

    # fit ----------------------------------------------------------------------------------
    def optimise(self, budget, lr=LR, spp=SPP, truth=None, observed=None, max_iterations=100_000, log=print,
                 seed=0):
        """Adam on `vertex_rd`, `vertex_rs`, `vertex_alpha` from `FLAT_START` until `budget`
        seconds of wall time (the error evaluation between iterations excluded). Returns the
        trace: per iteration `seconds`, `loss`, and with `truth` the median errors (`pd`,
        `pd_observed`, `ps`, `roughness`)."""
        mi, dr = self.mi, self.dr
        if self.taps is None:
            self.build_taps()
        pd, ks, alpha = self._flat()
        self.set_reflectance(pd, ks, alpha)
        keys = {"object.vertex_rd": (BOUNDS["pd"][0] / (1 - BLEND_WEIGHT), BOUNDS["pd"][1] / (1 - BLEND_WEIGHT)),
                "object.vertex_rs": (BOUNDS["ks"][0] / BLEND_WEIGHT, BOUNDS["ks"][1] / BLEND_WEIGHT),
                "object.vertex_alpha": BOUNDS["alpha"]}
        opt = mi.ad.Adam(lr=lr)
        for k in keys:
            opt[k] = self.params[k]
        self.params.update(opt)
        total = sum(t["count"] for t in self.taps)
        order = [m for m in range(self.scan.n_lights) if self.taps[m]["count"]]
        trace = []
        if truth is not None:
            trace.append({"iteration": 0, "seconds": 0.0, "loss": None, **self._errors(opt, truth, observed)})
        elapsed, it = 0.0, 0
        while elapsed < budget and it < max_iterations:
            t0 = time.perf_counter()
            losses = []
            for m in order:
                img = self.render(m, spp, seed=seed + it * len(order) + m, params=self.params)
                diff = self.predict(img, m) - self.taps[m]["target"]
                loss = dr.sum(dr.square(diff)) / total
                dr.eval(loss)  # (reading it with float() instead costs ~0.4 s per render on LLVM)
                dr.backward(loss)
                dr.eval(*[dr.grad(opt[k]) for k in keys])  # one backward kernel per render, not one fused at step
                losses.append(dr.detach(loss))
            opt.step()
            for k, (lo, hi) in keys.items():
                opt[k] = dr.clip(opt[k], lo, hi)
            self.params.update(opt)
            dr.eval(*[opt[k] for k in keys])
            loss_sum = float(sum(np.asarray(x, dtype=np.float64).sum() for x in losses))
            it += 1
            elapsed += time.perf_counter() - t0
            rec = {"iteration": it, "seconds": elapsed, "loss": loss_sum}
            if truth is not None:
                rec.update(self._errors(opt, truth, observed))
            trace.append(rec)
            if log and (it <= 3 or it % 10 == 0):
                log(f"  mitsuba it {it:4d}  {elapsed:7.1f} s  loss {loss_sum:.4g}"
                    + (f"  pd {rec['pd']:.2%}  ps {rec['ps']:.2%}  rough {rec['roughness']:.2%}" if truth else ""))
        self.final = self._current(opt)
        return trace

    def _current(self, opt):
        pd = np.asarray(opt["object.vertex_rd"], dtype=np.float64).reshape(self.n, 3) * (1 - BLEND_WEIGHT)
        ks = np.asarray(opt["object.vertex_rs"], dtype=np.float64) * BLEND_WEIGHT
        alpha = np.asarray(opt["object.vertex_alpha"], dtype=np.float64)
        return {"pd": pd, "ps": ks, "roughness": alpha}

    def _errors(self, opt, truth, observed):
        cur = self._current(opt)
        e = point_errors(cur["pd"], cur["ps"], cur["roughness"], truth, observed)
        return {"pd": e["pd"]["all"], "pd_observed": e["pd"]["observed"], "ps": e["ps"]["all"],
                "roughness": e["roughness"]["all"]}


def _rel_diff(a, b):
    """Median and 90th percentile of `|a - b| / b` (RGB means, `b > 0`)."""
    a, b = np.asarray(a, float).mean(-1), np.asarray(b, float).mean(-1)
    ok = b > 1e-9 * max(float(b.max()) if b.size else 0.0, 1e-300)
    r = np.abs(a[ok] - b[ok]) / b[ok]
    if not r.size:
        return {"median": None, "p90": None, "within_2pct": None, "samples": 0}
    return {"median": float(np.median(r)), "p90": float(np.percentile(r, 90)),
            "within_2pct": float(np.mean(r <= 0.02)), "samples": int(r.size)}


def convention_check(fit: MitsubaFit, info, spp=CHECK_SPP, gi_samples=256, log=print) -> dict:
    """Mitsuba's rendering of the scan's truth against the scan's own renders (module docstring)."""
    from data_synth import zoo

    scan = fit.scan
    used = fit.build_taps() if fit.taps is None else fit.used
    positions = fit.position_images()
    lights = [m for m in range(scan.n_lights) if used[:, m].any()]
    out = {"spp": spp, "used_samples": int(used.sum()), "observed_samples": int(scan.observed().sum())}
    # (1) geometry: the position AOV at each vertex's projection.
    d = []
    for m in lights:
        rows = np.flatnonzero(used[:, m])
        index, w, _ = fit.projected(m)
        p = np.einsum("pk,pkc->pc", w[rows], positions[fit.sensor_index(m)][index[rows], :3])
        d.append(np.linalg.norm(p - scan.vertices[rows], axis=1) / fit.edge)
    d = np.concatenate(d)
    out["position"] = {"median_edges": float(np.median(d)), "p99_edges": float(np.percentile(d, 99)),
                       "samples": int(d.size)}

    def compare(reference, integrator, seed0, mirrored=False):
        a, b, ax, ay = [], [], [], []
        for m in lights:
            rows = np.flatnonzero(used[:, m])
            img = np.asarray(fit.render(m, spp, seed=seed0 + m, integrator=integrator))
            a.append(fit.sample_numpy(img, m, rows))
            b.append(reference[rows, m])
            if mirrored:
                ax.append(fit.sample_numpy(img[:, ::-1], m, rows))
                ay.append(fit.sample_numpy(img[::-1], m, rows))
        a, b = np.concatenate(a), np.concatenate(b)
        if not mirrored:
            return _rel_diff(a, b), a, b
        return _rel_diff(a, b), _rel_diff(np.concatenate(ax), b), _rel_diff(np.concatenate(ay), b)

    # (2) diffuse truth, direct light: camera, pixel, axis and intensity conventions.
    truth = info["truth"]
    zero = np.zeros(scan.n_points)
    diffuse = zoo.Truth("ward", truth.pd, truth.roughness, ps=zero)
    fit.set_reflectance(truth.pd, zero, truth.roughness)
    (out["diffuse_direct"], out["diffuse_direct_mirrored_x"],
     out["diffuse_direct_mirrored_y"]) = compare(zoo.render_cell(scan, diffuse), fit.direct, 0, mirrored=True)
    gi = "gi" in info
    if gi:  # (2b) the diffuse truth with interreflection: the path tracer (fewer paths) against prb
        ref, _, _ = zoo.render_gi(scan.vertices, scan.faces, scan.normals, diffuse, scan.light_pos, scan.cam_pos,
                                     scan.intensities(), scan.valid, gi_samples, seed=1, label="peer_diffuse")
        out["diffuse_gi"] = compare(ref, fit.integrator, 500)[0]
        out["diffuse_gi"]["path_tracer_samples"] = gi_samples
    # (3) the full truth through the stock BSDF against the exact Ward renders (model mismatch).
    fit.set_reflectance(truth.pd, truth.ps, truth.roughness)
    out["stock_truth_direct"] = compare(info["direct"], fit.direct, 1000)[0]
    if gi:
        out["stock_truth_vs_clean"] = compare(info["clean"], fit.integrator, 2000)[0]
    else:
        out["stock_truth_vs_clean"] = out["stock_truth_direct"]
    c = np.concatenate([scan.radiance[np.flatnonzero(used[:, m]), m] for m in lights])
    b = np.concatenate([info["clean"][np.flatnonzero(used[:, m]), m] for m in lights])
    out["scan_noise_vs_clean"] = _rel_diff(c, b)
    if log:
        log(f"  convention check: position {out['position']['median_edges']:.3f} edges (p99 "
            f"{out['position']['p99_edges']:.3f}); diffuse truth vs zoo.render median "
            f"{out['diffuse_direct']['median']:.2%} ({out['diffuse_direct']['within_2pct']:.0%} within 2 %), mirrored "
            f"x {out['diffuse_direct_mirrored_x']['median']:.0%}, y {out['diffuse_direct_mirrored_y']['median']:.0%}"
            + (f"; diffuse GI vs path tracer {out['diffuse_gi']['median']:.2%}" if gi else "")
            + f"; stock BSDF truth direct {out['stock_truth_direct']['median']:.2%} (p90 "
            f"{out['stock_truth_direct']['p90']:.1%}), full vs clean {out['stock_truth_vs_clean']['median']:.2%} "
            f"(p90 {out['stock_truth_vs_clean']['p90']:.1%})")
    return out


# -- jaxrefl ---------------------------------------------------------------------------------


def jaxrefl_methods(names, photon=PHOTON) -> dict:
    """Method objects of the public API by short name (Ward model throughout)."""
    import jaxrefl

    ward = jaxrefl.Local(model="ward")
    make = {"I": lambda: ward, "II": lambda: jaxrefl.Radiosity(local=ward),
            "III": lambda: jaxrefl.Photon(**photon),
            "auto": lambda: jaxrefl.Auto(local=ward, photon=dict(photon))}
    return {n: make[n]() for n in names}


def run_jaxrefl(scan, truth, observed, names, photon=PHOTON, repeat=True, log=print) -> dict:
    """`jaxrefl.estimate` with each method, twice (`seconds_first`, `seconds_warm`), and the errors."""
    import jaxrefl

    out = {}
    for name, method in jaxrefl_methods(names, photon).items():
        entry = {}
        try:
            t0 = time.perf_counter()
            est = jaxrefl.estimate(scan, method=method, progress=False)
            entry["seconds_first"] = time.perf_counter() - t0
            if repeat:
                t0 = time.perf_counter()
                est = jaxrefl.estimate(scan, method=method, progress=False)
                entry["seconds_warm"] = time.perf_counter() - t0
            entry["errors"] = point_errors(est.pd, est.ps, est.roughness, truth, observed)
            entry["status"] = {s.name.lower(): int(n) for s, n in est.status_counts().items()}
            auto = est.meta.get("auto")
            if isinstance(auto, dict) and "choice" in auto:
                entry["auto_choice"] = auto["choice"]
        except Exception as exc:  # noqa: BLE001 - a benchmark records, it does not stop
            entry["error"] = f"{type(exc).__name__}: {exc}"
        out[name] = entry
        e = entry.get("errors")
        if log:
            log(f"  jaxrefl {name}: " + (entry["error"] if e is None else
                f"pd {e['pd']['all']:.2%} ps {e['ps']['all']:.2%} rough {e['roughness']['all']:.2%} "
                f"s {entry['seconds_first']:.1f}" + (f" / {entry['seconds_warm']:.1f}" if repeat else "")))
    return out


# -- one scene -------------------------------------------------------------------------------


def run_scene(key, args, mi, dr, log=print) -> dict:
    """Everything measured on one scene (JSON-ready)."""
    from data_synth import zoo

    cell = SCENES[key]
    gi = cell in zoo.GI_CELLS
    scan, info = zoo.make_cell(cell, seed=args.seed)
    observed = scan.observed().any(axis=1)
    truth = {"pd": scan.true_pd, "ps": scan.true_ps, "roughness": scan.true_alpha}
    rec = {"scene": key, "cell": cell, "global_illumination": gi, "n_points": scan.n_points,
           "n_lights": scan.n_lights, "observed_points": int(observed.sum()),
           "observed_samples": int(scan.observed().sum()), "description": (zoo.GI_CELLS.get(cell) or
                                                                          zoo.CELLS[cell]).description}
    log(f"[{key}] {cell}: {scan.n_points} points, {scan.n_lights} observations, "
        f"{'global illumination' if gi else 'direct light'}")
    # Mitsuba: scene, convention check, fit.
    depth = args.gi_depth if gi else 2
    spp = args.gi_spp if gi else args.spp
    fit = MitsubaFit(scan, mi, dr, max_depth=depth, px_per_edge=args.px_per_edge)
    fit.build_taps()
    rec["mitsuba_setup"] = {"cameras": [c.to_dict() for c in fit.cameras], "max_depth": depth, "spp": spp,
                            "lr": args.lr, "build_seconds": fit.build_seconds,
                            "used_samples": int(fit.used.sum()), "used_points": int(fit.used.any(1).sum())}
    t0 = time.perf_counter()
    rec["convention"] = convention_check(fit, info, spp=args.check_spp, log=log)
    rec["convention"]["seconds"] = time.perf_counter() - t0
    trace = fit.optimise(args.budget, lr=args.lr, spp=spp, truth=truth, observed=observed, log=log, seed=args.seed)
    final = point_errors(fit.final["pd"], fit.final["ps"], fit.final["roughness"], truth, observed)
    used_points = fit.used.any(axis=1)
    rec["mitsuba"] = {"trace": trace, "errors": final, "iterations": trace[-1]["iteration"],
                      "errors_used_points": point_errors(fit.final["pd"], fit.final["ps"], fit.final["roughness"],
                                                         truth, used_points),
                      "seconds": trace[-1]["seconds"],
                      "seconds_per_iteration": trace[-1]["seconds"] / max(trace[-1]["iteration"], 1),
                      "first_iteration_seconds": trace[1]["seconds"] if len(trace) > 1 else None}
    log(f"  mitsuba final ({rec['mitsuba']['iterations']} iterations, {rec['mitsuba']['seconds']:.0f} s): "
        f"pd {final['pd']['all']:.2%} ps(ks) {final['ps']['all']:.2%} rough {final['roughness']['all']:.2%}")
    # jaxrefl.
    names = ("I",) if args.quick else (GI_METHODS if gi else ("I",))
    rec["jaxrefl"] = run_jaxrefl(scan, truth, observed, names, repeat=True, log=log)
    rec["time_to_error"] = time_to_error_rows(trace, rec["jaxrefl"])
    return rec


# -- report ----------------------------------------------------------------------------------


def _pct(x, digits=2):
    return "-" if x is None else f"{100 * x:.{digits}f}%"


def _s(x, digits=1):
    return "-" if x is None else f"{x:.{digits}f}"


def _used(mitsuba_rec, key):
    e = mitsuba_rec.get("errors_used_points")
    return "-" if not e else _pct(e[key]["observed"])


def _ratio(x):
    return "-" if x is None else f"{x:.1f}x"


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"nproc": os.cpu_count(), "cpu": cpu, "platform": platform.platform(), "python": platform.python_version()}


def versions(mi=None, dr=None) -> dict:
    import jax

    out = {"jax": jax.__version__}
    if mi is not None:
        out.update(mitsuba=mi.__version__, drjit=dr.__version__, variant=mi.variant())
        v = getattr(getattr(dr, "detail", None), "llvm_version", lambda: None)()
        out["llvm"] = None if v is None else ".".join(map(str, v))
    return out


MISMATCH = [
    "## Where the comparison is not apples to apples",
    "",
    "- **BSDF.** Mitsuba has no Ward BSDF; the stock stand-in is Lambert + a Beckmann microfacet lobe with "
    "Fresnel 1 (`blendbsdf` of `diffuse` and `roughconductor`). pd and alpha mean the same in both models, but "
    "the microfacet lobe is `G / (cos^4 th_h sqrt(cos_i cos_o))` times Ward's: equal at normal incidence, "
    "about 4x Ward's at 75 deg grazing mirror geometry. The data are Ward; Mitsuba can only fit them with a "
    "biased ks (and a pd that absorbs what the lobe cannot), and its `ps` column is ks against the true Ward ps. "
    "jaxrefl fits the true model family. The `stock` columns of the convention check measure this mismatch.",
    "- **Observations.** The scan holds one radiance sample per (vertex, light), not photographs. jaxrefl uses "
    "them directly; Mitsuba renders images and compares them at the vertices' projections (bilinear), so a "
    "sample is an average over a pixel footprint of interpolated parameters and normals; samples whose "
    "footprint crosses a silhouette or an occluding edge are left out (`samples used / observed`).",
    "- **Priors.** jaxrefl pools lobes across points (a shared prior) and fills points without their own "
    "samples; Mitsuba fits every vertex on its own and leaves unobserved ones at the flat start. Over all points "
    "that counts against Mitsuba wherever a point's lobe is not visible in its samples.",
    "- **Interreflection.** Mitsuba's prb stops at max_depth (the path tracer that made the data uses Russian "
    "roulette, unbounded) and is a Monte Carlo estimate at a few spp per iteration; jaxrefl's Methods II / III "
    "model interreflection their own way (radiosity form factors; photon mapping).",
    "- **Precision and time.** Mitsuba runs float32 on Dr.Jit's LLVM backend, jaxrefl float64 on JAX/XLA CPU. "
    "Mitsuba's learning rate, spp, resolution and flat start are one reasonable setting, not tuned per scene; "
    "its error is read at every iteration and it stops at the budget, jaxrefl runs to completion. Both ran on "
    "the same shared 2-core machine one after the other; the load average is listed.",
    "",
]


def write_report(records, run, out, plot=True):
    """`out` (markdown), the JSON next to it and (with `plot`) the error-vs-time PNG."""
    from benchmarks.rigs import _findings

    out = Path(out)
    ver = run["versions"]
    mach = run["machine"]
    lines = [
        "# jaxrefl and Mitsuba 3 inverse rendering on the same observations",
        "",
        f"- Command: `{run['command']}`",
        f"- Date: {run['date']}; machine: {mach['cpu']}, `nproc` = {mach['nproc']}, {mach['platform']}, "
        f"Python {mach['python']}; load average at start {run['load_start']:.2f}, at end {run['load_end']:.2f} "
        "(a shared machine: timings vary). CPU only: both tools on the same cores, one after the other.",
        f"- Mitsuba {ver.get('mitsuba')} / Dr.Jit {ver.get('drjit')}, variant `{ver.get('variant')}` (LLVM "
        f"{ver.get('llvm')}); stock `prb` integrator, max_depth 2 (direct) / {run['gi_depth']} (GI); "
        f"`mi.ad.Adam(lr={run['lr']})` on `vertex_rd` (= 2 pd), `vertex_rs` (= 2 ks), `vertex_alpha`, "
        f"clamped to pd [0, 1], ks [0, 2], alpha [0.01, 1] after each step; flat start pd {FLAT_START['pd']}, "
        f"ks {FLAT_START['ks']}, alpha {FLAT_START['alpha']}; spp {run['spp']} (direct) / {run['gi_spp']} (GI) per "
        f"render, every observation rendered and back-propagated per iteration; budget {run['budget']:.0f} s per "
        f"scene; about {run['px_per_edge']:g} pixels per mesh edge. Dr.Jit's on-disk kernel cache (`~/.drjit`) "
        f"held {run.get('drjit_cache_files_at_start', '?')} files at the start (kernels of earlier runs with the same "
        "settings load from it instead of compiling).",
        f"- jaxrefl (jax {ver.get('jax')}, float64 as every benchmark here): `jaxrefl.estimate(scan, method=...)`, "
        f"`Local(model='ward')` = I, `Radiosity(local=I)` = II, `Photon(photons={PHOTON['photons']}, "
        f"iterations={PHOTON['iterations']})` = III, `Auto(local=I, photon=same)` = auto; each run twice: "
        f"`first` (in-process JAX compilation, form factors cast into a fresh `$JAXREFL_CACHE`"
        f"{'' if not run.get('keep_caches') else ' -- NOT: --keep-caches'}) and `warm`.",
        "- Errors: median relative error per point (pd: mean over RGB) over **all** points (unobserved ones "
        "included), in brackets over the observed points. Mitsuba's `ps` is its microfacet `ks` compared with "
        "the true Ward `ps` (not the same quantity; see 'not apples to apples' below). Roughness: Ward alpha vs Beckmann alpha "
        "(the same exponent).",
        f"- Sources (jaxrefl + data_synth) sha256 `{run.get('source_hash', '?')}`; "
        f"{'all scenes done' if run['complete'] else 'PARTIAL'}; {run['seconds'] / 60:.1f} min in all.",
        "",
        "## Time to error",
        "",
        "The time Mitsuba needs to reach each jaxrefl method's final median pd error (all points), over "
        "jaxrefl's time for it: `ratio warm` = Mitsuba less its first iteration's overhead (Dr.Jit kernel "
        "compilation / cache loading) over jaxrefl's warm run; `ratio first` = Mitsuba as run over jaxrefl's first "
        "call (JAX compilation, form factors). Above 1: jaxrefl is faster to that error.",
        "",
        "| scene | jaxrefl method | its pd error | jaxrefl s warm / first | Mitsuba s to that pd error (less "
        "first-iteration overhead / as run) | ratio warm | ratio first |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for rec in records:
        if "error" in rec:
            lines.append(f"| {rec['scene']} | FAILED: `{rec['error']}` |" + " |" * 5)
            continue
        for row in rec["time_to_error"]:
            never = f"never within {run['budget']:.0f} s (reached {_pct(rec['mitsuba']['errors']['pd']['all'])})"
            reached = (never if row["mitsuba_seconds"] is None else
                       "0 (Mitsuba's flat start is already as good)" if row.get("flat_start_as_good") else
                       f"{_s(row['mitsuba_seconds_warm'])} / {_s(row['mitsuba_seconds'])}")
            lines.append(
                f"| {rec['scene']} ({rec['cell']}) | {row['method']} | {_pct(row['pd'])} | {_s(row['seconds_warm'])} / "
                f"{_s(row['seconds_first'])} | {reached} | {_ratio(row['ratio_warm'])} | {_ratio(row['ratio_first'])} |")
    lines += ["", "## Final errors", "",
              "| scene | tool / method | s (warm / first) | pd all (observed) | ps all (observed) | roughness all "
              "(observed) | notes |", "|---|---|---:|---:|---:|---:|---|"]
    for rec in records:
        if "error" in rec:
            continue
        mi_ = rec["mitsuba"]
        e = mi_["errors"]
        lines.append(
            f"| {rec['scene']} ({rec['cell']}) | Mitsuba (stock BSDF, Adam) | {mi_['seconds']:.0f} "
            f"({mi_['iterations']} it., first {_s(mi_['first_iteration_seconds'])} s) | "
            f"{_pct(e['pd']['all'])} ({_pct(e['pd']['observed'])}) | {_pct(e['ps']['all'])} ({_pct(e['ps']['observed'])}) "
            f"| {_pct(e['roughness']['all'])} ({_pct(e['roughness']['observed'])}) | ps = microfacet ks; over the "
            f"{rec['mitsuba_setup']['used_points']} points Mitsuba has samples of: pd {_used(mi_, 'pd')}, ks "
            f"{_used(mi_, 'ps')}, alpha {_used(mi_, 'roughness')} |")
        for name, run_ in rec["jaxrefl"].items():
            if "error" in run_:
                lines.append(f"| | jaxrefl {name} | FAILED: `{run_['error']}` | | | | |")
                continue
            e = run_["errors"]
            lines.append(
                f"| | jaxrefl {name} | {_s(run_.get('seconds_warm'))} / {_s(run_['seconds_first'])} | "
                f"{_pct(e['pd']['all'])} ({_pct(e['pd']['observed'])}) | {_pct(e['ps']['all'])} "
                f"({_pct(e['ps']['observed'])}) | {_pct(e['roughness']['all'])} ({_pct(e['roughness']['observed'])}) "
                f"| {('auto: ' + run_['auto_choice']) if run_.get('auto_choice') else ''} |")
    lines += ["", "## Convention check (before any optimisation)", "",
              "Mitsuba renders of the scan's truth, sampled at the vertices as the fit's loss samples them; relative "
              "differences per sample, median (p90, share within 2 %). `position`: the position AOV at each vertex's "
              "projection, distance in median edge lengths. `diffuse`: true pd, ks = 0, direct light (max_depth 2), "
              "against `data_synth.zoo.render` of the same diffuse truth (exact per vertex): the camera, pixel-centre, "
              "axis and light-intensity conventions; `mirrored x / y`: the same images flipped (what a wrong axis "
              "convention would give; the fold is symmetric in x). `diffuse GI`: the diffuse truth with "
              "interreflection, prb at the fit's max_depth against the path tracer (256 paths). `stock direct`: "
              "true pd, ks = true ps, alpha = true alpha, direct light, against the exact Ward render: the BSDF "
              "model mismatch alone; `stock full`: the same at the fit's max_depth against the scan's noise-free "
              "radiance. `noise`: the scan's radiance against its noise-free radiance (the floor of any fit).", "",
              "| scene | samples used / observed | position (edges) | diffuse | mirrored x / y | diffuse GI "
              "| stock direct | stock full | noise | spp | s |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for rec in records:
        if "error" in rec:
            continue
        c = rec["convention"]

        def cell(d):
            return "-" if d is None else f"{_pct(d['median'])} ({_pct(d['p90'], 1)}, {_pct(d['within_2pct'], 0)})"

        lines.append(
            f"| {rec['scene']} | {c['used_samples']} / {c['observed_samples']} | {c['position']['median_edges']:.3f} "
            f"(p99 {c['position']['p99_edges']:.2f}) | {cell(c['diffuse_direct'])} | "
            f"{_pct(c['diffuse_direct_mirrored_x']['median'], 0)} / {_pct(c['diffuse_direct_mirrored_y']['median'], 0)} "
            f"| {cell(c.get('diffuse_gi'))} | {cell(c['stock_truth_direct'])} | "
            f"{cell(c['stock_truth_vs_clean']) if rec['global_illumination'] else '(= direct)'} | "
            f"{cell(c['scan_noise_vs_clean'])} | {c['spp']} | {c['seconds']:.0f} |")
    lines += [""] + MISMATCH
    lines += [""] + _findings(out, "above")
    lines += ["## Scenes", ""]
    for rec in records:
        if "error" in rec:
            continue
        s = rec["mitsuba_setup"]
        cams = s["cameras"]
        res = sorted({f"{c['width']}x{c['height']}" for c in cams})
        lines.append(f"- {rec['scene']}: `{rec['cell']}` ({rec['description']}); {rec['n_points']} points "
                     f"({rec['observed_points']} observed), {rec['n_lights']} observations, {len(cams)} camera(s) "
                     f"{', '.join(res)} px, fov {cams[0]['fov_x']:.3g} deg; Mitsuba uses {s['used_samples']} of "
                     f"{rec['observed_samples']} observed samples ({s['used_points']} points), max_depth "
                     f"{s['max_depth']}, spp {s['spp']}, {rec['mitsuba']['seconds_per_iteration']:.2f} s per "
                     f"iteration.")
    lines.append("")
    out.parent.mkdir(parents=True, exist_ok=True)
    if plot:
        png = out.with_suffix(".png")
        try:
            plot_traces(records, png)
            lines += [f"![median pd error against wall time]({png.name})", ""]
        except Exception as exc:  # noqa: BLE001 - the numbers matter more than the picture
            lines += [f"(plot failed: {exc})", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    from benchmarks.rigs import _json_default, _sanitise

    payload = {**run, "flat_start": FLAT_START, "bounds": BOUNDS, "blend_weight": BLEND_WEIGHT, "scenes": records}
    out.with_suffix(".json").write_text(json.dumps(_sanitise(payload), indent=1, default=_json_default) + "\n")


def plot_traces(records, path):
    """Median pd error (all points) against wall time: Mitsuba's trace per scene, jaxrefl's
    methods as points (filled: warm, open: first call)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = [r for r in records if "error" not in r]
    fig, axes = plt.subplots(1, max(len(recs), 1), figsize=(5 * max(len(recs), 1), 4), squeeze=False)
    marks = {"I": "o", "II": "s", "III": "^", "auto": "D"}
    for ax, rec in zip(axes[0], recs):
        tr = [t for t in rec["mitsuba"]["trace"] if t["seconds"] > 0 and t.get("pd") is not None]
        ax.plot([t["seconds"] for t in tr], [100 * t["pd"] for t in tr], "-", color="C3", label="Mitsuba (Adam)")
        for k, (name, run_) in enumerate(rec["jaxrefl"].items()):
            if "error" in run_:
                continue
            e = 100 * run_["errors"]["pd"]["all"]
            c = f"C{k}"
            ax.plot([run_["seconds_warm"]], [e], marks.get(name, "o"), color=c, label=f"jaxrefl {name} (warm)")
            ax.plot([run_["seconds_first"]], [e], marks.get(name, "o"), color=c, mfc="none",
                    label=f"jaxrefl {name} (first)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("median pd error, all points [%]")
        ax.set_title(f"{rec['scene']} ({rec['cell']})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- main ------------------------------------------------------------------------------------


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python3 -m benchmarks.peer_mitsuba", description=__doc__.splitlines()[0])
    p.add_argument("--cells", default=",".join(SCENES), help=f"comma-separated scenes of {sorted(SCENES)}")
    p.add_argument("--budget", type=float, default=None,
                   help=f"Mitsuba optimisation seconds per scene (default {BUDGET:g}; --quick {QUICK_BUDGET:g})")
    p.add_argument("--quick", action="store_true", help="30 s budget, Method I only, cheap convention check")
    p.add_argument("--lr", type=float, default=LR, help="Adam learning rate")
    p.add_argument("--spp", type=int, default=SPP, help="samples per pixel per render, direct-light scene")
    p.add_argument("--gi-spp", type=int, default=GI_SPP, help="samples per pixel per render, GI scenes")
    p.add_argument("--gi-depth", type=int, default=GI_DEPTH, help="prb max_depth on the GI scenes")
    p.add_argument("--check-spp", type=int, default=None, help=f"convention check spp (default {CHECK_SPP}, --quick {QUICK_CHECK_SPP})")
    p.add_argument("--px-per-edge", type=float, default=PX_PER_EDGE, help="image pixels per projected mesh edge")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep-caches", action="store_true",
                   help="leave $JAXREFL_CACHE as it is (default: a fresh folder, so `first` casts its form factors)")
    p.add_argument("--out", default="benchmarks/RESULTS_peer.md")
    args = p.parse_args(argv)
    if args.budget is None:
        args.budget = QUICK_BUDGET if args.quick else BUDGET
    if args.check_spp is None:
        args.check_spp = QUICK_CHECK_SPP if args.quick else CHECK_SPP
    args.scenes = [c for c in args.cells.split(",") if c]
    unknown = [c for c in args.scenes if c not in SCENES]
    if unknown:
        p.error(f"unknown scenes {unknown}; choose from {sorted(SCENES)}")
    return args


def _count_files(folder) -> int:
    try:
        return sum(1 for p in Path(folder).rglob("*") if p.is_file())
    except OSError:
        return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    try:
        mi, dr = load_mitsuba()
    except PeerUnavailable as exc:
        print(str(exc), file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    from benchmarks.rigs_gi import source_hash

    cache_tmp = None
    if not args.keep_caches:
        cache_tmp = tempfile.TemporaryDirectory(prefix="jaxrefl-peer-cache-")
        os.environ["JAXREFL_CACHE"] = cache_tmp.name
    command = "python3 -m benchmarks.peer_mitsuba" + ("" if not argv else " " + " ".join(argv))
    run = {"command": command, "date": datetime.datetime.now().isoformat(timespec="seconds"),
           "machine": machine(), "versions": versions(mi, dr), "source_hash": source_hash(),
           "budget": args.budget, "lr": args.lr, "spp": args.spp, "gi_spp": args.gi_spp, "gi_depth": args.gi_depth,
           "check_spp": args.check_spp, "px_per_edge": args.px_per_edge, "seed": args.seed, "quick": args.quick,
           "keep_caches": args.keep_caches, "photon": PHOTON, "load_start": os.getloadavg()[0],
           "drjit_cache_files_at_start": _count_files(Path.home() / ".drjit")}
    t0 = time.perf_counter()
    records = []
    try:
        for key in args.scenes:
            try:
                rec = run_scene(key, args, mi, dr, log=lambda s: print(s, flush=True))
            except Exception as exc:  # noqa: BLE001 - one broken scene must not stop the run
                import traceback

                traceback.print_exc()
                rec = {"scene": key, "cell": SCENES[key], "error": f"{type(exc).__name__}: {exc}"}
            records.append(rec)
            run.update(seconds=time.perf_counter() - t0, complete=len(records) == len(args.scenes),
                       load_end=os.getloadavg()[0])
            write_report(records, run, args.out)
    finally:
        if cache_tmp is not None:
            cache_tmp.cleanup()
    print(Path(args.out).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
