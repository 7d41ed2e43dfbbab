"""A rig zoo: synthetic scans on rigs and materials unlike the paper's scanner.

Each *cell* is an object (a bumpy, nearly convex blob; a 90-degree fold of two plates;
a hemispherical bowl seen from inside; a cup seen from outside and inside) under one
rig with one material set, one BRDF family and one sensor.
Units: metres, radians; lights are isotropic point lights of radiant intensity `Y`
[W/sr]; radiance = BRDF x `Y cos_i / C^2` [W/(sr m^2)] with Embree shadows: direct light
only in `CELLS`; in `GI_CELLS` plus every interreflection, path-traced (below). `pd` is an
albedo (diffuse term `pd / pi`) in every family. Surfaces are one-sided (the side the
vertex normals point to; light reaching a surface from behind is absorbed).

Global-illumination cells (`GI_CELLS`, Ward truth stored as `true_pd`, `true_ps`,
`true_alpha`; 1 % noise, 12 bits): every observation (vertex, camera, light) seen by its
camera is rendered by the independent path tracer `data_synth.pathtrace` (`render_gi`:
exact direct light with a shadow ray, interreflection by `samples` paths per observation,
unbiased, a dark room). A render is cached on disk (`gi_cache_dir()`:
`$JAXREFL_ZOO_CACHE` or `~/.cache/jaxrefl-zoo`), keyed by a hash of the mesh, truth, rig,
samples and seed, so a cell is path-traced once. `info['direct']` holds the exact
direct-only render of the same cell, `info['gi']` the Monte Carlo standard error:

- `gi_fold_coaxial`: the fold at Object E's size (plates 0.2 m), `coaxial` rig viewing
  15 deg off plate I's normal (75 deg off plate II's), grey gloss pd 0.5, ps 0.3, alpha
  0.15: each plate sees the other's mirror image. ~1500 points, 1024 paths.
- `gi_bowl`: the bowl (diameter 0.1 m), `photometric` camera on its axis and 24 distant
  lights 10-75 deg off it (the rim shades the inside), smooth pd / ps / roughness fields.
  ~1500 points, 512 paths.
- `gi_cup`: the cup (0.1 m tall), 20 `handheld` camera/flash pairs, two Ward glazes
  (outside celadon, inside ivory pd 0.8). ~2000 points, 1024 paths.
- `gi_bumpy_ring`: the blob on the turntable `ring`, 4 materials: nearly convex, the
  control (little interreflection). 2562 points, 256 paths.

Rigs (`RIGS`, each `fn(center, size, seed) -> RigSetup`; intensities are
`C^2` at the object centre times a factor near 1, so irradiance there is O(1) W/m^2):

- `coaxial`: one camera at 5 sizes, 12 lights 5-8 deg off the camera direction.
- `ring`: turntable ring of 24 cameras at 4 sizes, 10 deg elevation; observation
  `m` seen by camera `m`, lit by a light 8-12 deg beside it (`cam_pos` `(M, 3)`).
- `photometric`: camera at 1000 sizes on +z (near-orthographic), 96 lights at
  1000 sizes on a cap 10-75 deg from +z.
- `handheld`: 20 camera/light pairs, independent random directions within 75 deg
  of +z at 2.5-4 object radii (`cam_pos` `(M, 3)`), flash strengths vary +-25 %.
- `sparse`: one camera at 5 sizes, 6 lights 20/35 deg around it.

BRDF families: `ward`, `torrance-sparrow` (`jaxrefl.reflectance.brdf`, evaluated with
`data_synth.pathtrace.brdf_numpy`) and `ggx` (not fitted by jaxrefl): Lambert `pd / pi` plus
the Walter et al. 2007 microfacet lobe `D F G / (4 cos_i cos_o)`: Trowbridge-Reitz `D`,
Schlick Fresnel with RGB `f0`, separable Smith `G` (`ggx_brdf`).

`make_cell(name, seed, n_points) -> (Scan, info)`; `render` / `render_cell` render any
per-point `Truth` under a rig or under a scan's own rig (direct light), `render_gi` with
global illumination.
"""

from __future__ import annotations

import functools
import hashlib
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

import jaxrefl
from jaxrefl.geometry.mesh import area_normal_sums
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.scan.io import Scan, validate_scan

from .objects import make_object
from .pathtrace import Material, PathTracer, brdf_numpy
from .scans import Sensor, apply_sensor

__all__ = [
    "RigSetup", "RIGS", "Truth", "ZooObject", "CellSpec", "CELLS", "GI_CELLS", "MATERIALS", "OBJECTS",
    "bumpy_object", "fold_object", "bowl_object", "cup_object", "ggx_brdf", "render", "render_cell",
    "render_gi", "gi_cache_dir", "camera_valid", "make_cell", "fold_distance",
]

BRDFS = ("ward", "torrance-sparrow", "ggx")


# -- objects ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ZooObject:
    """Mesh: `vertices` `(N, 3)` [m], `faces` `(F, 3)` CCW seen from the side the normals
    point to, unit `normals` `(N, 3)`; `center` `(3,)` bounding-box centre, `size` largest
    extent [m]; `parts` `(N,)` int part index where the object has named parts (the cup:
    0 outside, 1 inside), else None."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    center: np.ndarray
    size: float
    parts: np.ndarray | None = None


def _unit(a):
    a = np.asarray(a, dtype=np.float64)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


# Fixed bump field (wave vectors on the unit sphere, phases): the shape never depends on the seed.
_BUMP_K = np.array([[4.1, 1.3, -2.2], [-1.7, 4.4, 1.1], [2.3, -2.0, 4.0], [-3.2, -2.9, -1.6]])
_BUMP_PHASE = np.array([0.3, 1.7, 2.9, 4.4])


def bumpy_object(n_points: int | None = None, size: float = 0.1, bumps: float = 0.05) -> ZooObject:
    """A bumpy, nearly convex blob centred at the origin, `size` [m] across.

    An icosphere (the subdivision whose vertex count 10 4^s + 2 is nearest `n_points`
    in ratio; default 2562 vertices) displaced radially by four sinusoidal waves of
    relative amplitude `bumps` each, squashed to axes 1 : 0.9 : 0.8, normals
    area-weighted from the mesh.
    """
    n_points = 2562 if n_points is None else int(n_points)
    counts = 10 * 4 ** np.arange(1, 7) + 2
    sub = int(1 + np.argmin(np.abs(np.log(counts / max(n_points, 1)))))
    ico = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
    u = _unit(ico.vertices)
    r = 1.0 + bumps * np.sin(u @ _BUMP_K.T + _BUMP_PHASE).sum(axis=1)
    v = u * r[:, None] * np.array([1.0, 0.9, 0.8])
    f = np.asarray(ico.faces, dtype=np.int64)
    v = v * (size / float(np.max(v.max(0) - v.min(0))))
    v -= 0.5 * (v.max(0) + v.min(0))
    n = _unit(area_normal_sums(v, f))
    return ZooObject("bumpy", v, f, n, np.zeros(3), size)


def fold_object(n_points: int | None = None, size: float = 0.1) -> ZooObject:
    """Object E's right-angle fold (`objects.make_object('E')`), scaled to plates `size` [m]
    long, centred at the origin: fold along x, the V opening toward +z; exact plate normals."""
    n_points = 2450 if n_points is None else int(n_points)
    k = max(8, int(round(np.sqrt(n_points / 2.0))) - 1)
    e = make_object("E", resolution=2 * k)
    v = e.vertices * (size / 0.2)
    c = 0.5 * (v.max(0) + v.min(0))
    return ZooObject("fold", v - c, e.faces.astype(np.int64), _unit(e.normals), np.zeros(3),
                     float(np.max(v.max(0) - v.min(0))))


def fold_distance(vertices) -> np.ndarray:
    """Signed distance `(N,)` [m] along the plates from a `fold_object`'s fold line (along x,
    at `y = 0` and the lowest `z` of the vertices): positive on plate I (`y > 0`)."""
    v = np.asarray(vertices, dtype=np.float64)
    return np.sign(v[:, 1]) * np.hypot(v[:, 1], v[:, 2] - v[:, 2].min())


def _zip_rings(a, b):
    """Triangles `(T, 3)` joining two rings of vertex indices `a`, `b` (each in angular
    order from azimuth 0, evenly spaced; a ring of one index is a pole): a zipper walk
    that always advances the ring whose next vertex comes first in azimuth."""
    na, nb = len(a), len(b)
    if na == 1:
        return [(a[0], b[j], b[(j + 1) % nb]) for j in range(nb)]
    if nb == 1:
        return [(a[i], a[(i + 1) % na], b[0]) for i in range(na)]
    tris, i, j = [], 0, 0
    while i < na or j < nb:
        if j >= nb or (i < na and (i + 1) / na <= (j + 1) / nb):
            tris.append((a[i], a[(i + 1) % na], b[j % nb]))
            i += 1
        else:
            tris.append((a[i % na], b[(j + 1) % nb], b[j]))
            j += 1
    return tris


def _lathe(profile, normals2d, n_points, parts=None):
    """A surface of revolution about +z from a densely sampled profile curve.

    `profile` `(K, 2)` points `(r, z)` [m] in order along the curve, `normals2d` `(K, 2)`
    the unit surface normal `(n_r, n_z)` there (the side the surface is seen from),
    `parts` `(K,)` optional int labels. Rings are placed at equal arc length, about as far
    apart as the vertices on each ring (`2 pi r / spacing` of them, one at `r = 0`), with
    the spacing that gives about `n_points` vertices. Faces are oriented CCW seen from
    the normals' side. Returns vertices `(N, 3)`, faces `(F, 3)`, unit normals `(N, 3)`,
    parts `(N,)` (or None).
    """
    prof = np.asarray(profile, dtype=np.float64)
    seg = np.linalg.norm(np.diff(prof, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    area = float(np.sum(2 * np.pi * 0.5 * (prof[1:, 0] + prof[:-1, 0]) * seg))
    spacing = np.sqrt(area / max(int(n_points), 8))
    n_rings = max(2, int(round(s[-1] / spacing)) + 1)
    st = np.linspace(0.0, s[-1], n_rings)
    r = np.interp(st, s, prof[:, 0])
    z = np.interp(st, s, prof[:, 1])
    nr, nz = np.interp(st, s, normals2d[:, 0]), np.interp(st, s, normals2d[:, 1])
    length = np.hypot(nr, nz)
    nr, nz = nr / length, nz / length
    lab = None if parts is None else np.asarray(parts)[np.clip(np.searchsorted(s, st), 0, len(s) - 1)]
    verts, norms, labels, rings, faces = [], [], [], [], []
    for k in range(n_rings):
        count = 1 if r[k] < 0.25 * spacing else max(6, int(round(2 * np.pi * r[k] / spacing)))
        phi = 2 * np.pi * np.arange(count) / count
        start = sum(len(x) for x in verts)
        rad = 0.0 if count == 1 else r[k]
        verts.append(np.stack([rad * np.cos(phi), rad * np.sin(phi), np.full(count, z[k])], 1))
        if count == 1:
            norms.append(np.array([[0.0, 0.0, np.sign(nz[k]) or 1.0]]))
        else:
            norms.append(np.stack([nr[k] * np.cos(phi), nr[k] * np.sin(phi), np.full(count, nz[k])], 1))
        labels.append(np.full(count, 0 if lab is None else lab[k]))
        rings.append(np.arange(start, start + count))
    for a, b in zip(rings[:-1], rings[1:]):
        faces += _zip_rings(a, b)
    v, n = np.concatenate(verts), _unit(np.concatenate(norms))
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = _dot(cross, n[f].sum(axis=1)) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f, n, (None if parts is None else np.concatenate(labels).astype(np.int64))


def bowl_object(n_points: int | None = None, size: float = 0.1) -> ZooObject:
    """A hemispherical bowl seen from inside: the inner face of a half sphere of diameter
    `size` [m], opening toward +z, normals toward the sphere's centre (the outside is not
    a surface: rays reaching the shell from behind are absorbed, as everywhere). Its rim
    (the sphere's equator) shades the inside from oblique lights. Every pair of its points
    sees each other; the point-to-area form factor on a sphere is `dA / (4 pi R^2)`.
    Axis on z, the rim at `z = size / 4`, the bottom at `-size / 4`; default about 2000 vertices."""
    n_points = 2000 if n_points is None else int(n_points)
    radius = 0.5 * size
    theta = np.linspace(0.0, 0.5 * np.pi, 2001)
    prof = np.stack([radius * np.sin(theta), -radius * np.cos(theta)], 1)
    nrm = np.stack([-np.sin(theta), np.cos(theta)], 1)
    v, f, n, _ = _lathe(prof, nrm, n_points)
    n = -_unit(v)  # exactly on the sphere (the profile is interpolated along chords)
    v = -radius * n
    v[:, 2] += 0.5 * radius
    return ZooObject("bowl", v, f, n, np.zeros(3), float(np.max(v.max(0) - v.min(0))))


def _arc(center, radius, a0, a1, k, inward=False):
    a = np.linspace(a0, a1, k)
    d = np.stack([np.cos(a), np.sin(a)], 1)
    return np.asarray(center) + radius * d, (-d if inward else d)


def _line(p0, p1, normal, k):
    t = np.linspace(0.0, 1.0, k)[:, None]
    return (1 - t) * np.asarray(p0, float) + t * np.asarray(p1, float), np.tile(normal, (k, 1)).astype(float)


def cup_object(n_points: int | None = None, size: float = 0.1) -> ZooObject:
    """A cup `size` [m] tall, seen from outside and inside: a closed solid of revolution
    about +z (outer radius `0.4 size`, wall `0.06 size`, base `0.08 size` thick), one
    surface with outward normals: flat base, rounded base edge (radius `0.08 size`),
    outer wall, a half-round rim, inner wall, rounded inner corner (`0.12 size`) and floor.
    `parts`: 0 outside (base, outer wall, the rim's outer half), 1 inside. Axis on z, from
    `z = -size / 2` to about `size / 2`; default about 2500 vertices."""
    n_points = 2500 if n_points is None else int(n_points)
    h, ro, t, tb, rf, ri = size, 0.4 * size, 0.06 * size, 0.08 * size, 0.08 * size, 0.12 * size
    rin = ro - t
    k = 400
    pieces = [
        (_line((0.0, 0.0), (ro - rf, 0.0), (0.0, -1.0), k), 0),
        (_arc((ro - rf, rf), rf, -0.5 * np.pi, 0.0, k), 0),
        (_line((ro, rf), (ro, h - 0.5 * t), (1.0, 0.0), k), 0),
        (_arc((ro - 0.5 * t, h - 0.5 * t), 0.5 * t, 0.0, 0.5 * np.pi, k), 0),
        (_arc((ro - 0.5 * t, h - 0.5 * t), 0.5 * t, 0.5 * np.pi, np.pi, k), 1),
        (_line((rin, h - 0.5 * t), (rin, tb + ri), (-1.0, 0.0), k), 1),
        (_arc((rin - ri, tb + ri), ri, 0.0, -0.5 * np.pi, k, inward=True), 1),
        (_line((rin - ri, tb), (0.0, tb), (0.0, 1.0), k), 1),
    ]
    prof = np.concatenate([p[0][0][(1 if i else 0):] for i, p in enumerate(pieces)])
    nrm = np.concatenate([p[0][1][(1 if i else 0):] for i, p in enumerate(pieces)])
    parts = np.concatenate([np.full(len(p[0][0]) - (1 if i else 0), p[1]) for i, p in enumerate(pieces)])
    v, f, n, lab = _lathe(prof, nrm, n_points, parts)
    v[:, 2] -= 0.5 * h
    return ZooObject("cup", v, f, n, np.zeros(3), float(np.max(v.max(0) - v.min(0))), parts=lab)


OBJECTS: dict[str, Callable[..., ZooObject]] = {"bumpy": bumpy_object, "fold": fold_object,
                                                "bowl": bowl_object, "cup": cup_object}


# -- rigs ------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RigSetup:
    """Positions of one rig: `light_pos` `(M, 3)` [m], `cam_pos` `(3,)` or `(M, 3)` [m]
    (one camera, or one per observation), `intensity` `(M,)` [W/sr], `params` (JSON-able)."""

    name: str
    light_pos: np.ndarray
    cam_pos: np.ndarray
    intensity: np.ndarray
    params: dict = field(default_factory=dict)

    def describe(self) -> dict:
        """JSON description for `scan.meta['rig']`."""
        return {"type": "zoo", "name": self.name, **self.params}


def _frame(axis):
    """Unit `axis` `(3,)` and two tangents completing it to a right-handed frame."""
    w = _unit(axis)
    a = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t = _unit(np.cross(a, w))
    return t, np.cross(w, t), w


def _directions(axis, polar, azimuth):
    """Unit directions `(K, 3)` at `polar` [rad] from `axis`, `azimuth` [rad] about it."""
    t, b, w = _frame(axis)
    polar, azimuth = np.asarray(polar, float)[:, None], np.asarray(azimuth, float)[:, None]
    return np.sin(polar) * (np.cos(azimuth) * t + np.sin(azimuth) * b) + np.cos(polar) * w


def _rng(seed, salt):
    return np.random.default_rng(np.random.SeedSequence([int(seed), salt]))


def _intensity_for(center, light_pos, factor=1.0):
    """`(M,)` intensities giving irradiance `factor` W/m^2 (at normal incidence) at `center`."""
    return factor * np.sum((np.asarray(light_pos) - center) ** 2, axis=1)


def coaxial_rig(center, size, seed=0, view_dir=(0.0, 0.0, 1.0), n_lights=12) -> RigSetup:
    """One camera 5 `size` from `center` along `view_dir`; `n_lights` lights at the same
    distance, 5-8 deg off the camera direction (seen from `center`), evenly around it."""
    rng = _rng(seed, 11)
    dist = 5.0 * size
    axis = _unit(view_dir)
    off = np.radians(rng.uniform(5.0, 8.0, n_lights))
    az = 2 * np.pi * (np.arange(n_lights) + rng.uniform(-0.25, 0.25, n_lights)) / n_lights
    lights = center + dist * _directions(axis, off, az)
    return RigSetup("coaxial", lights, center + dist * axis, _intensity_for(center, lights),
                    {"view_dir": axis.tolist(), "distance": dist, "offset_deg": [5.0, 8.0]})


def ring_rig(center, size, seed=0, n_views=24, elevation_deg=10.0) -> RigSetup:
    """Turntable ring: camera `m` of `n_views` at azimuth `m 360/n_views` deg about +y,
    `elevation_deg` up, 4 `size` from `center`; its light 8-12 deg beside it (random side)."""
    rng = _rng(seed, 12)
    dist = 4.0 * size
    az = 2 * np.pi * np.arange(n_views) / n_views
    el = np.radians(elevation_deg)
    dirs = np.stack([np.cos(el) * np.sin(az), np.full(n_views, np.sin(el)), np.cos(el) * np.cos(az)], 1)
    off = np.radians(rng.uniform(8.0, 12.0, n_views))
    side = rng.uniform(0, 2 * np.pi, n_views)
    ldirs = np.stack([_directions(d, [o], [s])[0] for d, o, s in zip(dirs, off, side)])
    lights = center + dist * ldirs
    return RigSetup("ring", lights, center + dist * dirs, _intensity_for(center, lights),
                    {"views": n_views, "elevation_deg": elevation_deg, "distance": dist,
                     "offset_deg": [8.0, 12.0], "axis": [0.0, 1.0, 0.0]})


def photometric_rig(center, size, seed=0, n_lights=96, far=1000.0) -> RigSetup:
    """Distant-light photometric stereo: camera `far` `size` from `center` on +z; `n_lights`
    lights on a Fibonacci spiral 10-75 deg from +z (random turn), also `far` `size` away,
    intensity `C^2` (irradiance 1 W/m^2 at normal incidence)."""
    rng = _rng(seed, 13)
    dist = far * size
    i = np.arange(n_lights) + 0.5
    c0, c1 = np.cos(np.radians(10.0)), np.cos(np.radians(75.0))
    polar = np.arccos(c0 - (c0 - c1) * i / n_lights)
    az = i * np.pi * (3.0 - np.sqrt(5.0)) + rng.uniform(0, 2 * np.pi)
    lights = center + dist * _directions([0.0, 0.0, 1.0], polar, az)
    return RigSetup("photometric", lights, center + np.array([0.0, 0.0, dist]),
                    _intensity_for(center, lights),
                    {"distance": dist, "polar_deg": [10.0, 75.0], "view_dir": [0.0, 0.0, 1.0]})


def handheld_rig(center, size, seed=0, n_views=20, cap_deg=75.0) -> RigSetup:
    """`n_views` camera/light pairs: camera and light each in an independent uniform
    direction within `cap_deg` of +z, at 2.5-4 object radii (radius `size / 2`);
    intensity `C^2` times a flash factor in [0.75, 1.25]."""
    rng = _rng(seed, 14)
    radius = 0.5 * size

    def draw():
        cos_t = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n_views)
        d = _directions([0.0, 0.0, 1.0], np.arccos(cos_t), rng.uniform(0, 2 * np.pi, n_views))
        return center + radius * rng.uniform(2.5, 4.0, n_views)[:, None] * d

    cams, lights = draw(), draw()
    flash = rng.uniform(0.75, 1.25, n_views)
    return RigSetup("handheld", lights, cams, _intensity_for(center, lights, flash),
                    {"views": n_views, "cap_deg": cap_deg, "radii": [2.5, 4.0],
                     "flash_factor": flash.tolist()})


def sparse_rig(center, size, seed=0, view_dir=(0.0, 0.0, 1.0)) -> RigSetup:
    """One camera 5 `size` along `view_dir`; 6 lights at the same distance, 20 and 35 deg
    (alternating) off the camera direction, 60 deg apart around it (random turn)."""
    rng = _rng(seed, 15)
    dist = 5.0 * size
    axis = _unit(view_dir)
    polar = np.radians(np.tile([20.0, 35.0], 3))
    az = np.radians(60.0 * np.arange(6)) + rng.uniform(0, 2 * np.pi)
    lights = center + dist * _directions(axis, polar, az)
    return RigSetup("sparse", lights, center + dist * axis, _intensity_for(center, lights),
                    {"view_dir": axis.tolist(), "distance": dist, "offset_deg": [20.0, 35.0]})


RIGS: dict[str, Callable[..., RigSetup]] = {
    "coaxial": coaxial_rig, "ring": ring_rig, "photometric": photometric_rig,
    "handheld": handheld_rig, "sparse": sparse_rig,
}


# -- BRDFs and truth -------------------------------------------------------------


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def ggx_brdf(pd, f0, alpha, n, wi, wo):
    """GGX BRDF [1/sr] of `P` samples: `pd`, `f0` `(P, 3)`, `alpha` `(P,)` (Trowbridge-Reitz
    width, dimensionless), unit `n`, `wi` (to light), `wo` (to viewer) `(P, 3)`.

    `pd / pi + D(h) F(wo.h) G1(wi) G1(wo) / (4 cos_i cos_o)`, with
    `D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)`, `F = f0 + (1 - f0)(1 - wo.h)^5`,
    `G1(c) = 2c / (c + sqrt(a^2 + (1 - a^2) c^2))`. 0 below either horizon.
    """
    ci, co = _dot(n, wi), _dot(n, wo)
    ok = (ci > 0) & (co > 0)
    ci_s, co_s = np.where(ok, ci, 1.0), np.where(ok, co, 1.0)
    h = _unit(np.where(ok[:, None], wi + wo, n))
    ch, vh = np.clip(_dot(n, h), 0.0, 1.0), np.clip(_dot(wo, h), 0.0, 1.0)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    d = a2 / (np.pi * (ch**2 * (a2 - 1.0) + 1.0) ** 2)

    def g1(c):
        return 2.0 * c / (c + np.sqrt(a2 + (1.0 - a2) * c**2))

    fres = f0 + (1.0 - f0) * ((1.0 - vh) ** 5)[:, None]
    spec = (d * g1(ci_s) * g1(co_s) / (4.0 * ci_s * co_s))[:, None] * fres
    return np.where(ok[:, None], pd / np.pi + spec, 0.0)


@dataclass(frozen=True, eq=False)
class Truth:
    """Per-point reflectance of one BRDF family. `pd` `(N, 3)` albedo; `roughness` `(N,)`:
    Ward alpha [rad], Torrance-Sparrow sigma [rad] or GGX alpha; `ps` `(N,)` (Ward, TS) or
    `f0` `(N, 3)` (GGX, Schlick reflectance at normal incidence)."""

    brdf: str
    pd: np.ndarray
    roughness: np.ndarray
    ps: np.ndarray | None = None
    f0: np.ndarray | None = None

    def __post_init__(self):
        if self.brdf not in BRDFS:
            raise ValueError(f"brdf must be one of {BRDFS}, got {self.brdf!r}")
        if (self.brdf == "ggx") != (self.f0 is not None) or (self.brdf == "ggx") == (self.ps is not None):
            raise ValueError("Truth: give ps for ward / torrance-sparrow, f0 for ggx")

    def values(self, idx, n, wi, wo):
        """BRDF `(P, 3)` [1/sr] of points `idx` `(P,)` with unit `n`, `wi`, `wo` `(P, 3)`."""
        if self.brdf == "ggx":
            return ggx_brdf(self.pd[idx], self.f0[idx], self.roughness[idx], n, wi, wo)
        return brdf_numpy(self.brdf, self.pd[idx], self.ps[idx], self.roughness[idx], n, wi, wo)


def render(vertices, normals, truth: Truth, light_pos, cam_pos, intensity, caster=None,
           shadows=True, where=None):
    """Direct radiance of every (vertex, observation): BRDF x `Y cos_i / C^2` x unshadowed.

    **Arguments:** `vertices`, `normals` `(N, 3)`; `truth` a `Truth`; `light_pos` `(M, 3)`;
    `cam_pos` `(3,)` or `(M, 3)` [m]; `intensity` scalar or `(M,)` [W/sr]; `caster` a
    `RayCaster` over the mesh (needed when `shadows`); `where` optional `(N, M)` bool:
    render only these (others 0).

    **Returns:** `radiance` `(N, M, 3)` [W/(sr m^2)] and `lit` `(N, M)` bool (`cos_i > 0`
    and, with `shadows`, the light unoccluded). The camera's view is not tested.
    """
    v = np.asarray(vertices, dtype=np.float64)
    nrm = _unit(normals)
    lp = np.asarray(light_pos, dtype=np.float64)
    n, m = len(v), len(lp)
    cam = np.broadcast_to(np.asarray(cam_pos, dtype=np.float64).reshape(-1, 3), (m, 3))
    y = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (m,))
    d = lp[None] - v[:, None]
    dist = np.linalg.norm(d, axis=-1)
    wi = d / dist[..., None]
    wo = _unit(cam[None] - v[:, None])
    cos_i = _dot(nrm[:, None], wi)
    lit = cos_i > 0
    if where is not None:
        lit &= where
    if shadows:
        lit &= caster.visibility(lp, where=lit)
    rows, cols = np.nonzero(lit)
    out = np.zeros((n, m, 3))
    f = truth.values(rows, nrm[rows], wi[rows, cols], wo[rows, cols])
    out[rows, cols] = f * (y[cols] * cos_i[rows, cols] / dist[rows, cols] ** 2)[:, None]
    return out, lit


def camera_valid(vertices, normals, cam_pos, n_obs, caster) -> np.ndarray:
    """`(N, M)` bool: the camera of each observation faces the vertex and sees it unoccluded."""
    v = np.asarray(vertices, dtype=np.float64)
    cam = np.broadcast_to(np.asarray(cam_pos, dtype=np.float64).reshape(-1, 3), (n_obs, 3))
    facing = _dot(normals[:, None], cam[None] - v[:, None]) > 0
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    if cam_pos.ndim == 1:  # one camera: one ray per vertex
        return facing & caster.visibility(cam_pos, where=facing[:, :1])
    return facing & caster.visibility(cam_pos, where=facing)


def render_cell(scan: Scan, truth: Truth, shadows=True, caster=None) -> np.ndarray:
    """`(N, M, 3)` direct radiance of any per-point `truth` under `scan`'s own rig (lights,
    cameras, intensities, normals), 0 where `scan.valid` is False. `light_pos` `(M, 3)` only."""
    if scan.light_pos.ndim != 2:
        raise ValueError("render_cell: needs one light position per observation (M, 3)")
    caster = caster or RayCaster(scan.vertices, scan.faces)
    valid = np.ones((scan.n_points, scan.n_lights), bool) if scan.valid is None else scan.valid
    cam = scan.cam_pos if scan.cam_pos.ndim <= 2 else None
    if cam is None:
        raise ValueError("render_cell: needs cam_pos (3,) or (M, 3)")
    rad, _ = render(scan.vertices, scan.normals, truth, scan.light_pos, cam, scan.intensities(),
                    caster=caster, shadows=shadows, where=valid)
    return rad


# -- materials -------------------------------------------------------------------

# Per-material parameters. Ward / TS: pd albedo RGB, ps, roughness [rad];
# GGX: pd, f0 RGB, alpha (pd + specular albedo stays below 1 at every direction).
_PIECEWISE = [
    {"name": "red glaze", "pd": [0.60, 0.12, 0.10], "ps": 0.30, "roughness": 0.06},
    {"name": "green matte", "pd": [0.15, 0.50, 0.20], "ps": 0.04, "roughness": 0.30},
    {"name": "blue satin", "pd": [0.10, 0.20, 0.55], "ps": 0.15, "roughness": 0.15},
    {"name": "white gloss", "pd": [0.80, 0.80, 0.75], "ps": 0.40, "roughness": 0.035},
]
_GGX_PIECEWISE = [
    {"name": "brass", "pd": [0.10, 0.08, 0.04], "f0": [0.70, 0.55, 0.30], "alpha": 0.12},
    {"name": "blue plastic", "pd": [0.10, 0.20, 0.55], "f0": [0.05, 0.05, 0.05], "alpha": 0.25},
    {"name": "copper lacquer", "pd": [0.30, 0.12, 0.08], "f0": [0.45, 0.25, 0.18], "alpha": 0.06},
]
_GGX_UNIFORM = [
    {"name": "tinted metal", "pd": [0.25, 0.22, 0.12], "f0": [0.55, 0.45, 0.25], "alpha": 0.1},
]
_UNIFORM = {"uniform": {"name": "terracotta glaze", "pd": [0.55, 0.38, 0.25], "ps": 0.25, "roughness": 0.10},
            "sharp": {"name": "sharp glaze", "pd": [0.30, 0.45, 0.60], "ps": 0.15, "roughness": 0.02},
            "broad": {"name": "broad sheen", "pd": [0.45, 0.45, 0.40], "ps": 0.30, "roughness": 0.30},
            # The reference fold: Ward pd 0.5, ps 0.3, alpha 0.15.
            "grey_gloss": {"name": "grey gloss", "pd": [0.50, 0.50, 0.50], "ps": 0.30, "roughness": 0.15}}
# A glazed cup: celadon outside, a light ivory glaze inside (strong interreflection in the well).
_GLAZES = [
    {"name": "celadon glaze (outside)", "pd": [0.35, 0.50, 0.40], "ps": 0.25, "roughness": 0.08},
    {"name": "ivory glaze (inside)", "pd": [0.80, 0.76, 0.65], "ps": 0.30, "roughness": 0.10},
]
# Region seeds of the piecewise sets (directions from the object centre): fixed, not seeded.
_REGION_DIRS = _unit(np.array([[1.0, 1.0, 0.6], [-1.0, 0.8, -0.7], [0.7, -1.0, -0.9], [-0.6, -0.7, 1.0]]))


def _regions(u, k):
    return np.argmax(u @ _REGION_DIRS[:k].T, axis=1)


def _from_labels(materials, labels, brdf):
    pd = np.array([m["pd"] for m in materials], dtype=np.float64)[labels]
    if brdf == "ggx":
        f0 = np.array([m["f0"] for m in materials], dtype=np.float64)[labels]
        return Truth("ggx", pd, np.array([m["alpha"] for m in materials])[labels], f0=f0)
    ps = np.array([m["ps"] for m in materials], dtype=np.float64)[labels]
    return Truth(brdf, pd, np.array([m["roughness"] for m in materials], dtype=np.float64)[labels], ps=ps)


def _material_set(materials, region=False, by_part=False):
    """`region`: materials by direction from the centre (`_REGION_DIRS`); `by_part`: material
    `k` on the object's part `k` (`ZooObject.parts`); else one material everywhere."""
    def make(u, brdf, parts=None):
        if by_part:
            if parts is None:
                raise ValueError("this material set needs an object with parts (e.g. the cup)")
            labels = np.asarray(parts, np.int64)
        else:
            labels = _regions(u, len(materials)) if region else np.zeros(len(u), np.int64)
        return labels, [dict(m) for m in materials], _from_labels(materials, labels, brdf)
    return make


def _smooth(u, brdf, parts=None):
    """Low-frequency fields over the directions `u` from the centre: pd 0.2-0.7 per channel,
    ps 0.1-0.4, roughness 0.05-0.2 rad (log-sinusoidal)."""
    w = np.array([[1.9, 0.7, -1.2], [-0.8, 1.6, 1.0], [1.1, -1.4, 1.5], [0.5, 1.2, 1.8], [-1.6, -0.9, 0.6]])
    s = np.sin(u @ w.T + np.array([0.4, 1.9, 3.1, 0.9, 2.4]))  # (N, 5) in [-1, 1]
    pd = 0.45 + 0.25 * s[:, :3]
    ps = 0.25 + 0.15 * s[:, 3]
    rough = np.exp(np.log(0.1) + np.log(2.0) * s[:, 4])
    truth = Truth(brdf, pd, rough, ps=ps)
    stats = {"name": "smooth field", "field": True, "pd": pd.mean(0).tolist(), "ps": float(ps.mean()),
             "roughness": float(np.exp(np.log(rough).mean())), "pd_range": [0.2, 0.7],
             "ps_range": [0.1, 0.4], "roughness_range": [0.05, 0.2]}
    return np.zeros(len(u), np.int64), [stats], truth


#: name -> fn(directions from the centre (N, 3), brdf, parts=None) -> (labels (N,), materials, Truth).
MATERIALS: dict[str, Callable] = {
    "uniform": _material_set([_UNIFORM["uniform"]]),
    "sharp": _material_set([_UNIFORM["sharp"]]),
    "broad": _material_set([_UNIFORM["broad"]]),
    "grey_gloss": _material_set([_UNIFORM["grey_gloss"]]),
    "glazes": _material_set(_GLAZES, by_part=True),
    "piecewise": _material_set(_PIECEWISE, region=True),
    "smooth": _smooth,
    "ggx": _material_set(_GGX_PIECEWISE, region=True),
    "ggx_uniform": _material_set(_GGX_UNIFORM),
}
_GGX_MATERIALS = ("ggx", "ggx_uniform")


# -- cells -----------------------------------------------------------------------


@dataclass(frozen=True)
class CellSpec:
    """One zoo cell: `rig` (key of `RIGS`), `material` (key of `MATERIALS`), `brdf`
    family, `sensor`, `object` (key of `OBJECTS`), extra `rig_options`, `description`;
    `object_options` keywords of the object's function (e.g. `size`); `samples` path-traced
    paths per observation for global illumination (`data_synth.pathtrace`; 0: direct light
    only, exact, with Embree shadows); `n_points` the cell's default mesh size (None: the
    object's)."""

    rig: str
    material: str
    brdf: str
    sensor: Sensor = Sensor(noise=0.01, bits=12)
    object: str = "bumpy"
    rig_options: dict = field(default_factory=dict)
    description: str = ""
    object_options: dict = field(default_factory=dict)
    samples: int = 0
    n_points: int | None = None

    def __post_init__(self):
        if self.rig not in RIGS or self.material not in MATERIALS or self.object not in OBJECTS:
            raise ValueError(f"CellSpec: unknown rig, material or object in {self}")
        if self.brdf not in BRDFS or (self.brdf == "ggx") != (self.material in _GGX_MATERIALS):
            raise ValueError(f"CellSpec: brdf {self.brdf!r} does not fit material {self.material!r}")
        if self.samples < 0 or (self.samples and self.brdf == "ggx"):
            raise ValueError("CellSpec: samples must be >= 0; the path tracer has no GGX")

    @property
    def global_illumination(self) -> bool:
        return self.samples > 0


_S12, _S8 = Sensor(noise=0.01, bits=12), Sensor(noise=0.01, bits=8)
_FOLD_VIEW = (0.0, -0.5, float(np.sqrt(0.75)))  # 15 deg off plate I's normal, 75 deg off plate II's

CELLS: dict[str, CellSpec] = {
    "coaxial_uniform": CellSpec("coaxial", "uniform", "ward", _S12,
                                description="lights beside the camera: lobe seen only where normals face it"),
    "coaxial_fold": CellSpec("coaxial", "uniform", "ward", _S12, object="fold",
                             rig_options={"view_dir": _FOLD_VIEW},
                             description="glossy right-angle fold, near-coaxial lights (direct light only)"),
    "ring_piecewise": CellSpec("ring", "piecewise", "ward", _S12,
                               description="turntable ring, 4 materials by region"),
    "ring_smooth": CellSpec("ring", "smooth", "ward", _S12,
                            description="turntable ring, pd / ps / roughness varying smoothly"),
    "ring_ggx": CellSpec("ring", "ggx", "ggx", _S12,
                         description="turntable ring, 3 GGX materials with coloured lobes (model mismatch)"),
    "photometric_piecewise": CellSpec("photometric", "piecewise", "torrance-sparrow", _S12,
                                      description="distant-light photometric stereo, 4 materials"),
    "photometric_sharp": CellSpec("photometric", "sharp", "ward", _S12,
                                  description="photometric stereo, one sharp 0.02 rad lobe"),
    "photometric_ggx": CellSpec("photometric", "ggx_uniform", "ggx", _S12,
                                description="photometric stereo, one tinted GGX lobe (model mismatch)"),
    "handheld_piecewise": CellSpec("handheld", "piecewise", "torrance-sparrow", _S12,
                                   description="20 hand-held camera/flash pairs near the object, 4 materials"),
    "handheld_broad": CellSpec("handheld", "broad", "ward", _S8,
                               description="hand-held pairs, one broad 0.3 rad lobe, 8-bit sensor"),
    "sparse_uniform": CellSpec("sparse", "uniform", "ward", _S12,
                               description="one camera, 6 lights around it"),
    "sparse_piecewise": CellSpec("sparse", "piecewise", "torrance-sparrow", _S8,
                                 description="one camera, 6 lights, 4 materials, 8-bit sensor"),
}



#: Cells with global illumination: every observation path-traced (`render_gi`), Ward truth.
GI_CELLS: dict[str, CellSpec] = {
    "gi_fold_coaxial": CellSpec("coaxial", "grey_gloss", "ward", _S12, object="fold",
                                object_options={"size": 0.2}, rig_options={"view_dir": _FOLD_VIEW},
                                samples=1024, n_points=1500,
                                description="glossy right-angle fold (plates 0.2 m, Object E's), 12 lights "
                                            "beside the camera, diffuse and specular interreflection"),
    "gi_bowl": CellSpec("photometric", "smooth", "ward", _S12, object="bowl", rig_options={"n_lights": 24},
                        samples=512, n_points=1500,
                        description="hemispherical bowl seen from inside, smooth pd / ps / roughness, 24 distant "
                                    "lights 10-75 deg off the axis (rim shadows)"),
    "gi_cup": CellSpec("handheld", "glazes", "ward", _S12, object="cup", samples=1024, n_points=2000,
                       description="glazed cup (celadon outside, ivory inside) from 20 hand-held camera/flash "
                                   "pairs, outside and inside seen"),
    "gi_bumpy_ring": CellSpec("ring", "piecewise", "ward", _S12, samples=256, n_points=2562,
                              description="bumpy, nearly convex blob on a turntable ring, 4 materials, "
                                          "weak interreflection in its hollows"),
}

#: Bump when the GI render changes (invalidates cached renders).
_GI_VERSION = 1


def gi_cache_dir() -> Path:
    """Where GI renders are cached: `$JAXREFL_ZOO_CACHE`, else `~/.cache/jaxrefl-zoo`."""
    return Path(os.environ.get("JAXREFL_ZOO_CACHE") or Path.home() / ".cache" / "jaxrefl-zoo")


def render_gi(vertices, faces, normals, truth: Truth, light_pos, cam_pos, intensity, valid, samples,
              seed=0, caster=None, cache=True, label="gi"):
    """Radiance with global illumination of the observations `valid` `(N, M)`, by the
    independent path tracer (`data_synth.pathtrace.PathTracer`: the direct part exact with
    a shadow ray, interreflection by `samples` paths per observation, a dark room).

    **Arguments:** mesh `vertices` `(N, 3)`, `faces`, unit `normals`; `truth` a Ward or
    Torrance-Sparrow `Truth`; `light_pos` `(M, 3)`, `cam_pos` `(3,)` or `(M, 3)` [m],
    `intensity` `(M,)` [W/sr]; `seed` fixes the paths (observation `m` draws from
    `SeedSequence([seed, 7, m])`); `cache` True (`gi_cache_dir()`), a folder, or False:
    the result is stored as `<label>_<hash>.npz` keyed by a hash of every input, so the
    same cell is rendered once.

    **Returns:** `radiance` `(N, M, 3)` [W/(sr m^2)] (0 where not `valid`), `stderr`
    `(N, M, 3)` its Monte Carlo standard error, and `info` (`seconds`, `cached`, `path`).
    """
    if truth.brdf == "ggx":
        raise ValueError("render_gi: the path tracer has Ward and Torrance-Sparrow only")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    nrm = _unit(normals)
    lp = np.asarray(light_pos, dtype=np.float64)
    n, m = len(v), len(lp)
    cams = np.broadcast_to(np.asarray(cam_pos, dtype=np.float64).reshape(-1, 3), (m, 3))
    y = np.broadcast_to(np.asarray(intensity, dtype=np.float64), (m,))
    valid = np.asarray(valid, bool)
    key = hashlib.sha256(f"{_GI_VERSION}|{truth.brdf}|{int(samples)}|{int(seed)}".encode())
    for a in (v, f, nrm, truth.pd, truth.ps, truth.roughness, lp, cams, y, valid):
        key.update(np.ascontiguousarray(a).tobytes())
    path = None
    if cache:
        folder = gi_cache_dir() if cache is True else Path(cache)
        path = folder / f"{label}_{key.hexdigest()[:20]}.npz"
        if path.exists():
            try:
                with np.load(path) as z:
                    return z["radiance"], z["stderr"], {"seconds": float(z["seconds"]), "cached": True,
                                                         "path": str(path)}
            except Exception:  # noqa: BLE001 - a broken cache file is rendered again
                pass
    t0 = time.perf_counter()
    tracer = PathTracer(v, f, nrm, Material(truth.pd, truth.ps, truth.roughness, truth.brdf),
                        caster=caster or RayCaster(v, f))
    out, err = np.zeros((n, m, 3)), np.zeros((n, m, 3))
    for j in range(m):
        idx = np.flatnonzero(valid[:, j])
        if not len(idx):
            continue
        p = len(idx)
        ss = int(np.random.SeedSequence([int(seed), 7, j]).generate_state(1)[0])
        rad, se = tracer.render(np.ascontiguousarray(np.broadcast_to(cams[j], (p, 1, 3))),
                                np.ascontiguousarray(np.broadcast_to(lp[j], (p, 1, 3))), y[j:j + 1],
                                samples=int(samples), seed=ss, points=idx, progress=False)
        out[idx, j], err[idx, j] = rad[:, 0], se[:, 0]
    seconds = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, radiance=out, stderr=err.astype(np.float32), seconds=seconds)
        os.replace(tmp, path)
    return out, err, {"seconds": seconds, "cached": False, "path": None if path is None else str(path)}


def make_cell(name: str, seed: int = 0, n_points: int | None = None, cache=True) -> tuple[Scan, dict]:
    """Build zoo cell `name` (a key of `CELLS` or `GI_CELLS`): a validated `Scan` and `info`.

    `seed` fixes the rig's random parts, the path tracer's paths and the sensor noise;
    `n_points` picks the mesh size nearest it (default about 2500; the bumpy blob comes in
    42, 162, 642, 2562, 10242); `cache` (GI cells) as `render_gi`'s.

    **info:** `labels` `(N,)` material index; `materials` list of parameter dicts;
    `truth` a `Truth` (GGX parameters included for ggx cells, also as `ggx`); `clean`
    `(N, M, 3)` noise-free radiance (0 where not valid; for GI cells the path tracer's,
    direct + interreflected, with its Monte Carlo error); `direct` `(N, M, 3)` the exact
    direct-only radiance (= `clean` for direct cells); `lit` `(N, M)` bool light reaches
    the point directly; `rig`, `material`, `brdf`, `object` names; `rig_setup` the
    `RigSetup`; `object_parts` the object's `parts` (or None); `render`
    `fn(light_pos, cam_pos, intensity) -> (radiance, lit)` re-renders the truth under other
    lights, direct light only; `sensor`; `seconds`; for GI cells `gi` (`samples`,
    `stderr` `(N, M, 3)`, `seconds` of the render, `cached`, `path`,
    `mc_relative_stderr_median`, `indirect_share_median`: median of (clean - direct) /
    clean over valid lit samples). For ggx cells the scan carries `true_pd` only.
    """
    spec = CELLS.get(name) or GI_CELLS.get(name)
    if spec is None:
        raise ValueError(f"cell must be one of {sorted(CELLS) + sorted(GI_CELLS)}, got {name!r}")
    t0 = time.perf_counter()
    obj = OBJECTS[spec.object](spec.n_points if n_points is None else n_points, **spec.object_options)
    rig = RIGS[spec.rig](obj.center, obj.size, seed, **spec.rig_options)
    rel = obj.vertices - obj.center
    dirs = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-12)
    labels, materials, truth = MATERIALS[spec.material](dirs, spec.brdf, parts=obj.parts)
    caster = RayCaster(obj.vertices, obj.faces)
    m = len(rig.light_pos)

    valid = camera_valid(obj.vertices, obj.normals, rig.cam_pos, m, caster)
    radiance, lit = render(obj.vertices, obj.normals, truth, rig.light_pos, rig.cam_pos, rig.intensity,
                           caster=caster)
    direct = np.where(valid[..., None], radiance, 0.0)
    gi = None
    if spec.global_illumination:
        clean, stderr, gi = render_gi(obj.vertices, obj.faces, obj.normals, truth, rig.light_pos, rig.cam_pos,
                                      rig.intensity, valid, spec.samples, seed=seed, caster=caster, cache=cache,
                                      label=f"{name}_s{int(seed)}_n{len(obj.vertices)}")
        sel = valid & lit & (clean.mean(-1) > 0)
        rel_se = stderr.mean(-1)[sel] / clean.mean(-1)[sel]
        share = (clean - direct).mean(-1)[sel] / clean.mean(-1)[sel]
        gi = {"samples": spec.samples, "stderr": stderr, **gi,
              "mc_relative_stderr_median": float(np.median(rel_se)) if rel_se.size else 0.0,
              "indirect_share_median": float(np.median(share)) if share.size else 0.0}
    else:
        clean = direct
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    observed, saturation = apply_sensor(clean, valid, spec.sensor, rng)
    observed = np.where(valid[..., None], observed, 0.0)

    rough_key = {"ward": "true_alpha", "torrance-sparrow": "true_sigma"}.get(spec.brdf)
    meta = {
        "generator": "data_synth.zoo.make_cell",
        "jaxrefl_version": jaxrefl.__version__,
        "cell": name, "description": spec.description,
        "object": obj.name, "rig": rig.describe(), "rig_name": rig.name,
        "material": spec.material, "materials": materials,
        "model": spec.brdf, "brdf": spec.brdf,
        "global_illumination": spec.global_illumination, "sensor": asdict(spec.sensor), "seed": int(seed),
    }
    if gi is not None:
        meta.update(samples=spec.samples, mc_relative_stderr_median=gi["mc_relative_stderr_median"])
    scan = validate_scan(Scan(
        vertices=obj.vertices, faces=obj.faces, normals=obj.normals,
        light_pos=rig.light_pos, light_intensity=rig.intensity, cam_pos=rig.cam_pos,
        radiance=observed.astype(np.float32), valid=valid, saturation=saturation,
        true_pd=truth.pd, true_ps=truth.ps, true_normals=obj.normals, meta=meta,
        **({rough_key: truth.roughness} if rough_key else {}),
    ))
    info = {
        "labels": labels, "materials": materials, "truth": truth, "clean": clean, "direct": direct, "lit": lit,
        "rig": rig.name, "material": spec.material, "brdf": spec.brdf, "object": obj.name,
        "rig_setup": rig, "sensor": spec.sensor, "object_parts": obj.parts,
        "render": functools.partial(render, obj.vertices, obj.normals, truth, caster=caster),
        "valid_fraction": float(valid.mean()),
        "seconds": time.perf_counter() - t0,
    }
    if gi is not None:
        info["gi"] = gi
    if spec.brdf == "ggx":
        info["ggx"] = {"pd": truth.pd, "f0": truth.f0, "alpha": truth.roughness}
    return scan, info
