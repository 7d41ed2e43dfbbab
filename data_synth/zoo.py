"""A rig zoo: synthetic direct-light scans on rigs and materials unlike the paper's scanner.

Each *cell* is an object (a bumpy, nearly convex blob, or a 90-degree fold of two
plates) under one rig with one material set, one BRDF family and one sensor.
Units: metres, radians; lights are isotropic point lights of radiant intensity `Y`
[W/sr]; radiance = BRDF x `Y cos_i / C^2` [W/(sr m^2)], direct light only, with
Embree shadows. `pd` is an albedo (diffuse term `pd / pi`) in every family.

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

BRDF families: `ward`, `torrance-sparrow` (`jaxrefl.brdf`, evaluated with
`data_synth.pathtrace.brdf_numpy`) and `ggx` (not fitted by jaxrefl): Lambert `pd / pi` plus
the Walter et al. 2007 microfacet lobe `D F G / (4 cos_i cos_o)`: Trowbridge-Reitz `D`,
Schlick Fresnel with RGB `f0`, separable Smith `G` (`ggx_brdf`).

`make_cell(name, seed, n_points) -> (Scan, info)`; `render` / `render_cell` render any
per-point `Truth` under a rig or under a scan's own rig.
"""

from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import trimesh

import jaxrefl
from jaxrefl.io import Scan, validate_scan
from jaxrefl.mesh import area_normal_sums
from jaxrefl.raycast import RayCaster

from .objects import make_object
from .pathtrace import brdf_numpy
from .scans import Sensor, apply_sensor

__all__ = [
    "RigSetup", "RIGS", "Truth", "ZooObject", "CellSpec", "CELLS", "MATERIALS", "OBJECTS",
    "bumpy_object", "fold_object", "ggx_brdf", "render", "render_cell", "camera_valid", "make_cell",
]

BRDFS = ("ward", "torrance-sparrow", "ggx")


# -- objects ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ZooObject:
    """Mesh: `vertices` `(N, 3)` [m], `faces` `(F, 3)` outward CCW, unit `normals` `(N, 3)`;
    `center` `(3,)` bounding-box centre, `size` largest extent [m]."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    center: np.ndarray
    size: float


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


OBJECTS: dict[str, Callable[..., ZooObject]] = {"bumpy": bumpy_object, "fold": fold_object}


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
            "broad": {"name": "broad sheen", "pd": [0.45, 0.45, 0.40], "ps": 0.30, "roughness": 0.30}}
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


def _material_set(materials, region=False):
    def make(u, brdf):
        labels = _regions(u, len(materials)) if region else np.zeros(len(u), np.int64)
        return labels, [dict(m) for m in materials], _from_labels(materials, labels, brdf)
    return make


def _smooth(u, brdf):
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


#: name -> fn(directions from the centre (N, 3), brdf) -> (labels (N,), materials, Truth).
MATERIALS: dict[str, Callable] = {
    "uniform": _material_set([_UNIFORM["uniform"]]),
    "sharp": _material_set([_UNIFORM["sharp"]]),
    "broad": _material_set([_UNIFORM["broad"]]),
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
    family, `sensor`, `object` (key of `OBJECTS`), extra `rig_options`, `description`."""

    rig: str
    material: str
    brdf: str
    sensor: Sensor = Sensor(noise=0.01, bits=12)
    object: str = "bumpy"
    rig_options: dict = field(default_factory=dict)
    description: str = ""

    def __post_init__(self):
        if self.rig not in RIGS or self.material not in MATERIALS or self.object not in OBJECTS:
            raise ValueError(f"CellSpec: unknown rig, material or object in {self}")
        if self.brdf not in BRDFS or (self.brdf == "ggx") != (self.material in _GGX_MATERIALS):
            raise ValueError(f"CellSpec: brdf {self.brdf!r} does not fit material {self.material!r}")


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


def make_cell(name: str, seed: int = 0, n_points: int | None = None) -> tuple[Scan, dict]:
    """Build zoo cell `name` (a key of `CELLS`): a validated direct-light `Scan` and `info`.

    `seed` fixes the rig's random parts and the sensor noise; `n_points` picks the mesh
    size nearest it (default about 2500; the bumpy blob comes in 42, 162, 642, 2562, 10242).

    **info:** `labels` `(N,)` material index; `materials` list of parameter dicts;
    `truth` a `Truth` (GGX parameters included for ggx cells, also as `ggx`); `clean`
    `(N, M, 3)` noise-free radiance (0 where not valid); `lit` `(N, M)` bool light reaches
    the point; `rig`, `material`, `brdf`, `object` names; `rig_setup` the `RigSetup`;
    `render` `fn(light_pos, cam_pos, intensity) -> (radiance, lit)` re-renders the truth
    under other lights; `sensor`; `seconds`. For ggx cells the scan carries `true_pd` only.
    """
    if name not in CELLS:
        raise ValueError(f"cell must be one of {sorted(CELLS)}, got {name!r}")
    spec = CELLS[name]
    t0 = time.perf_counter()
    obj = OBJECTS[spec.object](n_points)
    rig = RIGS[spec.rig](obj.center, obj.size, seed, **spec.rig_options)
    rel = obj.vertices - obj.center
    dirs = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-12)
    labels, materials, truth = MATERIALS[spec.material](dirs, spec.brdf)
    caster = RayCaster(obj.vertices, obj.faces)
    m = len(rig.light_pos)

    valid = camera_valid(obj.vertices, obj.normals, rig.cam_pos, m, caster)
    radiance, lit = render(obj.vertices, obj.normals, truth, rig.light_pos, rig.cam_pos, rig.intensity,
                           caster=caster)
    clean = np.where(valid[..., None], radiance, 0.0)
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
        "global_illumination": False, "sensor": asdict(spec.sensor), "seed": int(seed),
    }
    scan = validate_scan(Scan(
        vertices=obj.vertices, faces=obj.faces, normals=obj.normals,
        light_pos=rig.light_pos, light_intensity=rig.intensity, cam_pos=rig.cam_pos,
        radiance=observed.astype(np.float32), valid=valid, saturation=saturation,
        true_pd=truth.pd, true_ps=truth.ps, true_normals=obj.normals, meta=meta,
        **({rough_key: truth.roughness} if rough_key else {}),
    ))
    info = {
        "labels": labels, "materials": materials, "truth": truth, "clean": clean, "lit": lit,
        "rig": rig.name, "material": spec.material, "brdf": spec.brdf, "object": obj.name,
        "rig_setup": rig, "sensor": spec.sensor,
        "render": functools.partial(render, obj.vertices, obj.normals, truth, caster=caster),
        "valid_fraction": float(valid.mean()),
        "seconds": time.perf_counter() - t0,
    }
    if spec.brdf == "ggx":
        info["ggx"] = {"pd": truth.pd, "f0": truth.f0, "alpha": truth.roughness}
    return scan, info
