"""Procedural test objects A–E with known, spatially non-uniform reflectance and exact normals.

Analogues of the seed paper's test objects (Fig. 7, Fig. 14): A a penguin doll with glossy
beak and feet, B a seated figure full of concavities, C a cat and D a pig (uniform specular,
non-uniform diffuse), E two plates meeting at a right-angle fold.

A–D are smooth unions of primitive signed distance functions (SDFs) meshed by marching
cubes; their vertices are projected onto the zero level set and their true normals are the
normalised SDF gradient there. E is an open grid mesh with exact plate normals.
Units are metres, +y is up; A–D stand on y = 0 around the y axis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

OBJECT_NAMES = ("A", "B", "C", "D", "E")  # analogues of the paper's objects
#: Beyond the paper: V, a convex glazed vase (no interreflection, no cast shadow) for
#: checking local estimation where the local model is exact.
EXTRA_NAMES = ("V",)
SETUPS = ("diffuse", "glossy", "glazed")
#: The "glazed" set-up: one uniform Ward lobe over every object (the glossy paper of E).
GLAZE_PS, GLAZE_ALPHA = 0.3, 0.08

_SQRT_HALF = float(np.sqrt(0.5))
_PD_RANGE = (0.02, 0.9)
_ROUGH_RANGE = (0.02, 0.6)


@dataclass(frozen=True, eq=False)  # eq=False: field-wise == on arrays is ambiguous
class SynthObject:
    """A synthetic object with per-vertex ground-truth reflectance.

    vertices (N, 3) float64 m; faces (F, 3) int64, counter-clockwise seen from outside;
    normals (N, 3) float64 unit true normals; pd (N, 3) diffuse albedo; ps (N,) specular
    reflectance; roughness (N,) Torrance-Sparrow sigma in radians; part (N,) int16 index
    into part_names.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    pd: np.ndarray
    ps: np.ndarray
    roughness: np.ndarray
    part: np.ndarray
    part_names: tuple[str, ...]
    description: str

    def __post_init__(self) -> None:
        n = len(self.vertices)
        shapes = {
            "vertices": (self.vertices, (n, 3)),
            "normals": (self.normals, (n, 3)),
            "pd": (self.pd, (n, 3)),
            "ps": (self.ps, (n,)),
            "roughness": (self.roughness, (n,)),
            "part": (self.part, (n,)),
        }
        for field, (arr, shape) in shapes.items():
            if np.shape(arr) != shape:
                raise ValueError(f"{field} has shape {np.shape(arr)}, expected {shape}")
        if np.ndim(self.faces) != 2 or np.shape(self.faces)[1] != 3:
            raise ValueError(f"faces has shape {np.shape(self.faces)}, expected (F, 3)")


def make_object(name: str, resolution: int = 64, setup: str = "glossy") -> SynthObject:
    """Build synthetic object `name` ('A'..'E').

    resolution: voxels along the object's largest extent (A–D); for E each plate is a
    (resolution//2 + 1)^2 vertex grid. setup: 'diffuse' or 'glossy' (the default) choose
    E's paper and leave A–D and V as they are; 'glazed' (every object) keeps the
    object's own diffuse albedo pd (E: its glossy paper's 0.7) and replaces its specular
    part by one uniform glaze lobe, ps = 0.3 and roughness 0.08 rad everywhere (used as
    the Ward alpha; the lobe of glossy E, `GLAZE_PS`, `GLAZE_ALPHA`). The paper's
    objects were glazed pottery whose concavities evidently carried strong specular
    interreflection; the default A–D carry little (their lobes are weak or broad away
    from the small glossy parts). pd is not reduced under the glaze, so pd + ps
    reaches 1.2 on the brightest parts (A's belly): more than a real glaze would
    pass, harmless for these open shapes (no photon or path is kept by it forever).
    """
    if name not in OBJECT_NAMES + EXTRA_NAMES:
        raise ValueError(f"name must be one of {OBJECT_NAMES + EXTRA_NAMES}, got {name!r}")
    if setup not in SETUPS:
        raise ValueError(f"setup must be one of {SETUPS}, got {setup!r}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
        raise ValueError(f"resolution must be an integer >= 16, got {resolution!r}")
    if resolution < 16:
        raise ValueError(f"resolution must be >= 16, got {resolution}")
    if name == "E":
        return _glazed(_make_plates(int(resolution), "glossy")) if setup == "glazed" else \
            _make_plates(int(resolution), setup)
    prims, reflect, part_names, description = _SPECS[name]()
    v, f, n, prim_idx = _mesh_sdf(prims, int(resolution))
    part_of_prim = np.array([part_names.index(p.part) for p in prims], dtype=np.int16)
    part = part_of_prim[prim_idx]
    pd, ps, rough = reflect(v, part, part_names)
    obj = SynthObject(
        name=name,
        vertices=v,
        faces=f,
        normals=n,
        pd=np.clip(pd, *_PD_RANGE),
        ps=np.maximum(ps, 0.0),
        roughness=np.clip(rough, *_ROUGH_RANGE),
        part=part,
        part_names=part_names,
        description=description,
    )
    return _glazed(obj) if setup == "glazed" else obj


def _glazed(obj: SynthObject) -> SynthObject:
    """`obj` under a uniform glaze: pd kept, ps `GLAZE_PS`, roughness `GLAZE_ALPHA` everywhere."""
    n = len(obj.vertices)
    return replace(obj, ps=np.full(n, GLAZE_PS), roughness=np.full(n, GLAZE_ALPHA),
                   description=f"{obj.description} Glazed: a uniform lobe (ps {GLAZE_PS}, roughness "
                               f"{GLAZE_ALPHA} rad) over its own diffuse colours.")


def fold_coordinate(vertices: np.ndarray) -> np.ndarray:
    """Signed arc length (N,) in m from E's fold: positive on plate I (y > 0), negative on II."""
    v = np.asarray(vertices, dtype=np.float64)
    return np.sign(v[:, 1]) * np.hypot(v[:, 1], v[:, 2])


# ---------------------------------------------------------------------------------------
# SDF primitives. Each takes points (M, 3) and returns signed distances (M,), negative inside.


class _Prim(NamedTuple):
    part: str
    sdf: Callable[[np.ndarray], np.ndarray]
    lo: np.ndarray  # (3,) axis-aligned bounds
    hi: np.ndarray
    blend: float  # smooth-union radius (m) with the primitives listed before it


def _sphere(part: str, centre, radius: float, blend: float) -> _Prim:
    c = np.asarray(centre, dtype=np.float64)

    def sdf(p):
        return np.linalg.norm(p - c, axis=-1) - radius

    return _Prim(part, sdf, c - radius, c + radius, blend)


def _ellipsoid(part: str, centre, radii, blend: float, rot=None) -> _Prim:
    """Ellipsoid with semi-axes `radii` along the columns of `rot` (world frame)."""
    c = np.asarray(centre, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    rmat = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)

    def sdf(p):
        # Quilez's bound: exact zero set, distance-like near the surface.
        q = (p - c) @ rmat
        k0 = np.linalg.norm(q / r, axis=-1)
        k1 = np.linalg.norm(q / (r * r), axis=-1)
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)

    half = np.sqrt(((rmat * r) ** 2).sum(axis=1))
    return _Prim(part, sdf, c - half, c + half, blend)


def _round_cone(part: str, a, b, ra: float, rb: float, blend: float) -> _Prim:
    """Exact SDF of the hull of spheres (a, ra) and (b, rb); a capsule when ra == rb."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ba = b - a
    l2 = float(ba @ ba)
    rr = ra - rb
    a2 = l2 - rr * rr
    il2 = 1.0 / l2

    def sdf(p):
        pa = p - a
        y = pa @ ba
        z = y - l2
        x2 = np.sum((pa * l2 - y[:, None] * ba) ** 2, axis=-1)
        y2 = y * y * l2
        z2 = z * z * l2
        k = np.sign(rr) * rr * rr * x2
        side = (np.sqrt(x2 * a2 * il2) + y * rr) * il2 - ra
        cap_a = np.sqrt(x2 + y2) * il2 - ra
        cap_b = np.sqrt(x2 + z2) * il2 - rb
        inner = np.where(np.sign(y) * a2 * y2 < k, cap_a, side)
        return np.where(np.sign(z) * a2 * z2 > k, cap_b, inner)

    lo = np.minimum(a - ra, b - rb)
    hi = np.maximum(a + ra, b + rb)
    return _Prim(part, sdf, lo, hi, blend)


def _torus(part: str, centre, axis, major: float, minor: float, blend: float) -> _Prim:
    c = np.asarray(centre, dtype=np.float64)
    ax = np.asarray(axis, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)

    def sdf(p):
        q = p - c
        h = q @ ax
        radial = np.linalg.norm(q - h[:, None] * ax, axis=-1)
        return np.hypot(radial - major, h) - minor

    ext = major + minor
    return _Prim(part, sdf, c - ext, c + ext, blend)


def _grooved(prim: _Prim, depth: float, period: float, wobble: float) -> _Prim:
    """Cut horizontal sinusoidal grooves of `depth` m every `period` m into `prim`."""

    def sdf(p):
        theta = np.arctan2(p[:, 0], p[:, 2])
        phase = 2.0 * np.pi * p[:, 1] / period + wobble * np.sin(3.0 * theta)
        # raising the SDF by depth*g moves the surface inward by ~depth where g = 1
        return prim.sdf(p) + depth * (0.5 + 0.5 * np.cos(phase)) ** 2

    return prim._replace(sdf=sdf)


def _rot(axis, degrees: float) -> np.ndarray:
    """(3, 3) rotation about `axis` by `degrees` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    t = np.radians(degrees)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(t) * kx + (1.0 - np.cos(t)) * (kx @ kx)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum with blend radius k (C1; equals min where |a - b| >= k)."""
    if k <= 0.0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * h * h


def _union_sdf(prims: list[_Prim], p: np.ndarray) -> np.ndarray:
    d = prims[0].sdf(p)
    for prim in prims[1:]:
        d = _smin(d, prim.sdf(p), prim.blend)
    return d


def _gradient(prims: list[_Prim], p: np.ndarray, eps: float) -> np.ndarray:
    """(M, 3) central-difference gradient of the union SDF."""
    g = np.empty_like(p)
    for i in range(3):
        dp = np.zeros(3)
        dp[i] = eps
        g[:, i] = (_union_sdf(prims, p + dp) - _union_sdf(prims, p - dp)) / (2.0 * eps)
    return g


# ---------------------------------------------------------------------------------------
# Meshing.


def _mesh_sdf(prims: list[_Prim], resolution: int):
    """Mesh the zero set of the smooth union of `prims`.

    Returns vertices (N, 3), faces (F, 3) int64 outward-oriented, true normals (N, 3) and
    the index (N,) of the primitive nearest each vertex.
    """
    lo = np.min([p.lo for p in prims], axis=0)
    hi = np.max([p.hi for p in prims], axis=0)
    h = float(np.max(hi - lo)) / resolution
    # smin can grow the surface by k/4 past the primitives; keep 2+ voxels of margin.
    pad = 2.0 * h + max(p.blend for p in prims)
    # an irrational-ish offset keeps grid nodes off the surface (exact zeros make
    # coincident marching-cubes vertices and zero-area faces)
    origin = lo - pad + 0.3719 * h
    shape = np.ceil((hi + pad - origin) / h).astype(int) + 1
    vol = np.empty(tuple(shape))
    axes = [origin[i] + h * np.arange(shape[i]) for i in range(3)]
    yz = np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), axis=-1).reshape(-1, 2)
    slab = max(1, 400_000 // len(yz))
    for i0 in range(0, shape[0], slab):  # slabs bound the memory at high resolution
        xs = axes[0][i0 : i0 + slab]
        pts = np.concatenate(
            [np.repeat(xs, len(yz))[:, None], np.tile(yz, (len(xs), 1))], axis=1
        )
        vol[i0 : i0 + slab] = _union_sdf(prims, pts).reshape(len(xs), shape[1], shape[2])

    v, f, _, _ = marching_cubes(vol, level=0.0, spacing=(h, h, h))
    v = v.astype(np.float64) + origin
    v, f = _clean(v, f.astype(np.int64), h)

    v = _project(prims, v, h)
    g = _gradient(prims, v, 1e-3 * h)
    n = g / np.linalg.norm(g, axis=1, keepdims=True)

    if _signed_volume(v, f) < 0.0:
        f = f[:, ::-1].copy()
    prim_idx = np.argmin(np.stack([p.sdf(v) for p in prims]), axis=0)
    return v, f, n, prim_idx


def _clean(v: np.ndarray, f: np.ndarray, h: float):
    """Merge coincident vertices, drop degenerate faces, keep the largest component.

    The other components are sealed voids of a few vertices where parts nearly touch.
    """
    key = np.round(v / (1e-7 * h)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    v = v[first]
    f = inverse.reshape(-1)[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]

    nv = len(v)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    adj = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(nv, nv))
    _, label = connected_components(adj, directed=False)
    biggest = np.argmax(np.bincount(label[f[:, 0]]))
    f = f[label[f[:, 0]] == biggest]

    used = np.unique(f)
    remap = np.full(nv, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def _project(prims: list[_Prim], v: np.ndarray, h: float, steps: int = 2) -> np.ndarray:
    """Newton steps onto the zero level set (marching cubes only interpolates linearly)."""
    for _ in range(steps):
        d = _union_sdf(prims, v)
        g = _gradient(prims, v, 1e-3 * h)
        step = -(d / np.maximum(np.sum(g * g, axis=1), 1e-12))[:, None] * g
        length = np.linalg.norm(step, axis=1, keepdims=True)
        v = v + step * np.minimum(1.0, 0.5 * h / np.maximum(length, 1e-300))
    return v


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


# ---------------------------------------------------------------------------------------
# Reflectance helpers.


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _spots(v: np.ndarray, centres, sigmas) -> np.ndarray:
    """(N,) in [0, 1]: Gaussian blobs sharpened into spots with soft (~sigma/2) edges."""
    c = np.asarray(centres, dtype=np.float64)
    s = np.broadcast_to(np.asarray(sigmas, dtype=np.float64), (len(c),))
    d2 = np.sum((v[:, None, :] - c[None]) ** 2, axis=-1)
    w = np.exp(-0.5 * d2 / (s * s)).max(axis=1)
    return _smoothstep(0.3, 0.7, w)


def _mix(base: np.ndarray, colour, w: np.ndarray) -> np.ndarray:
    return base + w[:, None] * (np.asarray(colour, dtype=np.float64) - base)


def _in(part: np.ndarray, names: tuple[str, ...], *which: str) -> np.ndarray:
    return np.isin(part, [names.index(w) for w in which])


def _uniform(n: int, colour) -> np.ndarray:
    return np.tile(np.asarray(colour, dtype=np.float64), (n, 1))


# ---------------------------------------------------------------------------------------
# Object A: penguin doll, facing +z.


def _spec_a():
    mm = 1e-3
    prims = [
        _ellipsoid("body", (0, 0.090, 0), (0.052, 0.072, 0.048), 0.0),
        _sphere("head", (0, 0.172, 0.006), 0.034, 8 * mm),
        _round_cone("beak", (0, 0.172, 0.030), (0, 0.166, 0.068), 0.011, 0.003, 2 * mm),
    ]
    for s in (-1.0, 1.0):
        prims += [
            _ellipsoid("wings", (s * 0.050, 0.098, -0.004), (0.010, 0.050, 0.026), 4 * mm,
                       rot=_rot((0, 0, 1), s * 12.0)),
            _round_cone("legs", (s * 0.020, 0.032, 0.010), (s * 0.022, 0.010, 0.020),
                        0.008, 0.007, 3 * mm),
            _ellipsoid("feet", (s * 0.022, 0.0065, 0.030), (0.015, 0.0065, 0.024), 3 * mm),
        ]
    names = ("body", "head", "beak", "wings", "legs", "feet")
    return prims, _reflect_a, names, (
        "Penguin doll: dark back and white belly with coloured spots, low-gloss plumage, "
        "glossy orange beak and yellow legs and feet."
    )


def _reflect_a(v, part, names):
    x, y, z = v.T
    n = len(v)
    plumage = _in(part, names, "body", "head", "wings")
    # one smooth colour field across body, head and wings (one material)
    belly = _smoothstep(0.0, 0.02, z - 0.35 * np.abs(x)) * (1.0 - _smoothstep(0.145, 0.16, y))
    pd = _mix(_uniform(n, (0.06, 0.07, 0.10)), (0.88, 0.87, 0.82), belly)
    ear_dirs = np.array([[-0.8, 0.35, -0.3], [0.8, 0.35, -0.3]])
    ear_dirs /= np.linalg.norm(ear_dirs, axis=1)[:, None]
    ears = np.array([0, 0.172, 0.006]) + 0.034 * ear_dirs  # on the head sphere
    pd = _mix(pd, (0.90, 0.62, 0.10), _spots(v, ears, 0.008))
    pd = _mix(pd, (0.75, 0.12, 0.10), _spots(v, [(0, 0.12, 0.0436)], 0.007))
    back_spots = _spots(v, [(-0.02, 0.07, -0.042), (0.02, 0.07, -0.042)], 0.007)
    pd = _mix(pd, (0.15, 0.30, 0.80), back_spots)
    ps = 0.03 + 0.02 * belly
    rough = 0.30 - 0.04 * belly

    beak = _in(part, names, "beak")
    tip = _smoothstep(0.03, 0.068, z)  # a little glossier towards the tip
    pd[beak] = (0.85, 0.45, 0.06)
    ps[beak] = (0.50 + 0.10 * tip)[beak]
    rough[beak] = 0.05

    legs = _in(part, names, "legs", "feet")
    pd[legs] = (0.85, 0.62, 0.10)
    ps[legs] = 0.45
    rough[legs] = 0.07
    assert np.all(plumage | beak | legs)
    return pd, ps, rough


# ---------------------------------------------------------------------------------------
# Object B: seated figure (arms bent against a grooved body, legs forward, hat, handle loop).


def _spec_b():
    mm = 1e-3
    torso = _ellipsoid("torso", (0, 0.085, 0), (0.048, 0.060, 0.038), 0.0)
    prims = [
        _grooved(torso, depth=3 * mm, period=0.022, wobble=0.6),
        _ellipsoid("legs", (0, 0.035, 0.010), (0.050, 0.030, 0.045), 6 * mm),  # seat
        _sphere("head", (0, 0.175, 0.0), 0.032, 6 * mm),
        _round_cone("hat", (0, 0.200, 0.0), (0, 0.240, -0.005), 0.026, 0.004, 3 * mm),
        _torus("handle", (0, 0.095, -0.040), (1, 0, 0), 0.025, 0.007, 3 * mm),
    ]
    for s in (-1.0, 1.0):
        shoulder, elbow = (s * 0.050, 0.125, 0.0), (s * 0.060, 0.080, 0.010)
        wrist = (s * 0.024, 0.085, 0.048)
        knee = (s * 0.030, 0.025, 0.085)
        prims += [
            _round_cone("arms", shoulder, elbow, 0.013, 0.012, 4 * mm),
            _round_cone("arms", elbow, wrist, 0.012, 0.011, 3 * mm),
            _sphere("hands", (s * 0.020, 0.085, 0.052), 0.015, 3 * mm),
            _round_cone("legs", (s * 0.028, 0.030, 0.020), knee, 0.018, 0.017, 4 * mm),
            _ellipsoid("feet", (s * 0.030, 0.035, 0.105), (0.016, 0.026, 0.012), 3 * mm),
        ]
    names = ("torso", "head", "hat", "arms", "hands", "legs", "feet", "handle")
    return prims, _reflect_b, names, (
        "Seated figure with arms bent against a grooved body, legs forward, a hat and a "
        "handle loop on its back; diffuse and specular vary within and between parts."
    )


def _reflect_b(v, part, names):
    x, y, z = v.T
    n = len(v)
    theta = np.arctan2(x, z)
    pd = np.empty((n, 3))
    ps = np.empty(n)
    rough = np.empty(n)

    m = _in(part, names, "torso")  # knitted jumper: colour fades with height, glossy bands
    t = _smoothstep(0.03, 0.14, y)
    pd[m] = _mix(_uniform(n, (0.12, 0.22, 0.60)), (0.35, 0.50, 0.80), t)[m]
    ps[m] = (0.06 + 0.14 * (0.5 + 0.5 * np.sin(3.0 * theta)))[m]
    rough[m] = (0.12 + 0.12 * t)[m]

    skin = _mix(_uniform(n, (0.85, 0.64, 0.50)), (0.85, 0.35, 0.35),
                _spots(v, [(-0.022, 0.168, 0.022), (0.022, 0.168, 0.022)], 0.006))
    m = _in(part, names, "head", "hands")
    pd[m] = skin[m]
    ps[m] = (0.10 + 0.05 * _smoothstep(0.15, 0.2, y))[m]
    rough[m] = 0.25

    m = _in(part, names, "hat")
    t = _smoothstep(0.2, 0.24, y)
    pd[m] = _mix(_uniform(n, (0.70, 0.10, 0.10)), (0.85, 0.75, 0.20), t)[m]
    ps[m] = (0.40 - 0.20 * t)[m]
    rough[m] = (0.08 + 0.10 * t)[m]

    m = _in(part, names, "arms")
    pd[m] = (0.20, 0.55, 0.25)
    ps[m] = (0.25 - 0.10 * _smoothstep(0.08, 0.13, y))[m]
    rough[m] = 0.15

    m = _in(part, names, "legs")
    pd[m] = (0.12, 0.12, 0.16)
    ps[m] = 0.05
    rough[m] = (0.40 - 0.10 * _smoothstep(0.0, 0.09, z))[m]

    m = _in(part, names, "feet")
    pd[m] = (0.05, 0.05, 0.05)
    ps[m] = 0.60
    rough[m] = 0.05

    m = _in(part, names, "handle")
    pd[m] = (0.75, 0.55, 0.12)
    ps[m] = 0.80
    rough[m] = 0.04
    return pd, ps, rough


# ---------------------------------------------------------------------------------------
# Object C: standing cat, facing +z.


def _spec_c():
    mm = 1e-3
    prims = [
        _ellipsoid("body", (0, 0.095, 0), (0.036, 0.038, 0.085), 0.0),
        _round_cone("neck", (0, 0.115, 0.060), (0, 0.148, 0.082), 0.024, 0.020, 6 * mm),
        _ellipsoid("head", (0, 0.163, 0.090), (0.033, 0.030, 0.030), 6 * mm),
        _ellipsoid("head", (0, 0.153, 0.116), (0.016, 0.012, 0.012), 3 * mm),  # muzzle
    ]
    for s in (-1.0, 1.0):
        prims.append(
            _round_cone("ears", (s * 0.017, 0.183, 0.088), (s * 0.026, 0.212, 0.085),
                        0.011, 0.002, 3 * mm)
        )
        for zf in (0.055, -0.055):
            prims.append(
                _round_cone("legs", (s * 0.020, 0.085, zf), (s * 0.021, 0.009, 1.06 * zf),
                            0.014, 0.009, 5 * mm)
            )
    tail = [(0, 0.110, -0.078), (0, 0.125, -0.110), (0, 0.155, -0.125), (0, 0.190, -0.120)]
    for a, b in zip(tail[:-1], tail[1:]):
        prims.append(_round_cone("tail", a, b, 0.0085, 0.0085, 3 * mm))
    names = ("body", "neck", "head", "ears", "legs", "tail")
    return prims, _reflect_c, names, (
        "Standing cat with tabby stripes, cream chest, muzzle and paws, and one glaze "
        "(uniform specular) all over."
    )


def _reflect_c(v, part, names):
    x, y, z = v.T
    n = len(v)
    # one global stripe field: rings on legs and tail, bands across body and head
    phase = (z + 0.5 * y) / 0.028 + 0.35 * np.sin(2.0 * np.pi * x / 0.04)
    stripe = _smoothstep(0.2, 0.8, 0.5 + 0.5 * np.sin(2.0 * np.pi * phase))
    pd = _mix(_uniform(n, (0.78, 0.50, 0.26)), (0.28, 0.16, 0.08), stripe)
    cream = np.maximum(1.0 - _smoothstep(0.012, 0.024, y),  # paws
                       _spots(v, [(0, 0.125, 0.085), (0, 0.150, 0.124)], 0.012))
    pd = _mix(pd, (0.88, 0.80, 0.66), cream)
    pd = _mix(pd, (0.85, 0.45, 0.50), _spots(v, [(0, 0.160, 0.128)], 0.004))  # nose
    eyes = _spots(v, [(-0.014, 0.172, 0.117), (0.014, 0.172, 0.117)], 0.004)
    pd = _mix(pd, (0.30, 0.70, 0.25), eyes)
    return pd, np.full(n, 0.20), np.full(n, 0.10)


# ---------------------------------------------------------------------------------------
# Object D: pig, facing +z.


def _spec_d():
    mm = 1e-3
    prims = [
        _ellipsoid("body", (0, 0.095, -0.010), (0.058, 0.056, 0.095), 0.0),
        _sphere("head", (0, 0.110, 0.080), 0.045, 8 * mm),
        _round_cone("snout", (0, 0.100, 0.110), (0, 0.095, 0.140), 0.022, 0.020, 3 * mm),
        _round_cone("tail", (0, 0.110, -0.090), (0, 0.112, -0.108), 0.005, 0.005, 3 * mm),
        _torus("tail", (0, 0.122, -0.112), (0, 0, 1), 0.010, 0.005, 2 * mm),
    ]
    for s in (-1.0, 1.0):
        prims.append(_ellipsoid("ears", (s * 0.030, 0.158, 0.085), (0.020, 0.007, 0.022), 4 * mm,
                                rot=_rot((0, 0, 1), s * 30.0) @ _rot((1, 0, 0), 20.0)))
        for zf in (0.045, -0.060):
            prims.append(_round_cone("legs", (s * 0.034, 0.060, zf), (s * 0.036, 0.014, zf),
                                     0.016, 0.014, 5 * mm))
    names = ("body", "head", "snout", "ears", "legs", "tail")
    return prims, _reflect_d, names, (
        "Pig with pink skin, darker patches, darker snout and hooves, and one glaze "
        "(uniform specular) all over."
    )


def _reflect_d(v, part, names):
    y = v[:, 1]
    n = len(v)
    patches = _spots(v, [(0.05, 0.11, -0.03), (-0.04, 0.13, 0.02), (0.0, 0.15, -0.06),
                         (-0.055, 0.08, -0.05), (0.035, 0.14, 0.07)],
                     (0.018, 0.015, 0.020, 0.014, 0.012))
    pd = _mix(_uniform(n, (0.88, 0.60, 0.58)), (0.38, 0.22, 0.20), patches)
    snout = _in(part, names, "snout")
    nostrils = _spots(v, [(-0.007, 0.097, 0.160), (0.007, 0.097, 0.160)], 0.003)
    pd[snout] = _mix(_uniform(n, (0.80, 0.45, 0.48)), (0.30, 0.12, 0.14), nostrils)[snout]
    legs = _in(part, names, "legs")
    hoof = 1.0 - _smoothstep(0.012, 0.016, y)
    pd[legs] = _mix(pd, (0.22, 0.18, 0.16), hoof)[legs]
    return pd, np.full(n, 0.25), np.full(n, 0.12)


def _spec_v():
    prims = [_ellipsoid("body", (0, 0.10, 0), (0.065, 0.10, 0.065), 0.0)]
    return prims, _reflect_v, ("body",), (
        "Convex glazed egg-shaped vase: painted diffuse bands and spots, a glossy glaze band "
        "with a sharp highlight, a satin glaze elsewhere."
    )


def _reflect_v(v, part, names):
    x, y, z = v.T
    n = len(v)
    band = _smoothstep(-0.004, 0.004, 0.025 - np.abs(y - 0.10))  # glossy band around the middle
    phase = np.arctan2(x, z)
    pd = _mix(_uniform(n, (0.70, 0.62, 0.45)), (0.15, 0.25, 0.55),
              _smoothstep(0.3, 0.7, 0.5 + 0.5 * np.sin(3 * phase + 40 * y)))
    pd = _mix(pd, (0.75, 0.20, 0.15), _spots(v, [(0.05, 0.16, 0.04), (-0.05, 0.05, -0.03)], 0.012))
    ps = 0.12 + 0.38 * band
    rough = 0.18 - 0.12 * band  # 0.06 rad in the glossy band, 0.18 elsewhere
    return pd, ps, rough


_SPECS = {"A": _spec_a, "B": _spec_b, "C": _spec_c, "D": _spec_d, "V": _spec_v}


# ---------------------------------------------------------------------------------------
# Object E: two plates at a right-angle fold along the x axis, opening towards +z.


def _make_plates(resolution: int, setup: str) -> SynthObject:
    k = resolution // 2
    xs = np.linspace(-0.1, 0.1, k + 1)
    s = np.linspace(0.0, 0.2, k + 1)
    xx, ss = (a.reshape(-1) for a in np.meshgrid(xs, s, indexing="ij"))  # i along x, j along s
    c = _SQRT_HALF
    v1 = np.stack([xx, ss * c, ss * c], axis=1)  # plate I: direction (0, +sin45, +cos45)
    v2 = np.stack([xx, -ss * c, ss * c], axis=1)  # plate II: direction (0, -sin45, +cos45)

    idx = np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    a, b, cc, d = (q.reshape(-1) for q in (idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]))
    # winding (x-step, then s-step) gives normal x_hat × s_hat = plate I's normal;
    # plate II's s_hat is mirrored, so its winding is reversed.
    f1 = np.concatenate([np.stack([a, b, cc], 1), np.stack([a, cc, d], 1)])
    f2 = f1[:, ::-1] + len(v1)

    m = len(v1)
    n1 = np.tile([0.0, -c, c], (m, 1))
    n2 = np.tile([0.0, c, c], (m, 1))
    if setup == "diffuse":
        pd, ps, rough = (0.8, 0.8, 0.8), 0.0, 0.3
        what = "white paper"
    else:
        pd, ps, rough = (0.7, 0.7, 0.7), 0.3, 0.08
        what = "glossy paper"
    return SynthObject(
        name="E",
        vertices=np.concatenate([v1, v2]),
        faces=np.concatenate([f1, f2]).astype(np.int64),
        normals=np.concatenate([n1, n2]),
        pd=_uniform(2 * m, pd),
        ps=np.full(2 * m, ps),
        roughness=np.full(2 * m, rough),
        part=np.repeat(np.array([0, 1], dtype=np.int16), m),
        part_names=("plate_I", "plate_II"),
        description=f"Two 20 cm plates of {what} meeting at a right-angle fold along the x axis.",
    )
