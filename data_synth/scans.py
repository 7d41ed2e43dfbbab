"""Synthetic scan bundles with known reflectance: object + rig + render + sensor.

`make_scan` builds one of the procedural objects (A-E), places it in a rig
(the paper's rotating-head scanner, or a fixed pinhole camera with the same
60-light rack around it), renders every (vertex, light) observation either
direct-only (exact local model with Embree shadows) or with full global
illumination by the independent path tracer, applies an optional sensor model
(noise, quantisation, saturation) and returns a validated `jaxrefl.Scan`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass

import numpy as np

import jaxrefl
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.geometry.rig import CylindricalScanner, PinholeCamera, paper_light_rack
from jaxrefl.scan.io import Scan, validate_scan

from .objects import EXTRA_NAMES, OBJECT_NAMES, make_object
from .pathtrace import Material, PathTracer

__all__ = ["Sensor", "apply_sensor", "make_rig", "make_scan", "direct_radiance"]

RIGS = ("scanner", "pinhole")


@dataclass(frozen=True)
class Sensor:
    """Sensor model applied to rendered radiance.

    **Fields:** `noise` relative Gaussian noise (std as a fraction of each
    value); `read_noise` additive Gaussian noise as a fraction of full scale;
    `bits` quantisation depth (None: no quantisation); `full_scale` sensor
    maximum in radiance units (None: the largest rendered value, so nothing
    saturates); `saturate` clip at full scale and mark those samples saturated
    (implied by `bits`).
    """

    noise: float = 0.0
    read_noise: float = 0.0
    bits: int | None = None
    full_scale: float | None = None
    saturate: bool = False

    def __post_init__(self):
        if self.noise < 0 or self.read_noise < 0:
            raise ValueError("Sensor.noise and read_noise must be >= 0")
        if self.bits is not None and not 1 <= self.bits <= 24:
            raise ValueError(f"Sensor.bits must be in 1..24, got {self.bits}")
        if self.full_scale is not None and not self.full_scale > 0:
            raise ValueError("Sensor.full_scale must be > 0")


def apply_sensor(radiance, valid, sensor: Sensor, rng) -> tuple[np.ndarray, float | None]:
    """Apply `sensor` to `radiance` `(N, M, 3)`; returns (values, saturation level or None)."""
    full = sensor.full_scale
    if full is None:
        full = float(radiance[valid].max()) if np.any(valid) else 1.0
        full = full if full > 0 else 1.0
    full = float(np.float32(full))  # bundles store radiance as float32: keep the level exact
    out = radiance.copy()
    if sensor.noise > 0 or sensor.read_noise > 0:
        z1, z2 = rng.standard_normal(out.shape), rng.standard_normal(out.shape)
        out = out * (1 + sensor.noise * z1) + sensor.read_noise * full * z2
    out = np.maximum(out, 0.0)
    clip = sensor.saturate or sensor.bits is not None
    if clip:
        out = np.minimum(out, full)
    if sensor.bits is not None:
        levels = 2**sensor.bits - 1
        q = np.round(out / full * levels)
        out = np.where(q >= levels, full, q * (full / levels))
    return out, (full if clip else None)


def make_rig(kind: str, center: np.ndarray, rack=None):
    """A rig around an object centred at `center` `(3,)`: `'scanner'` (paper
    §2.1, 0.6 m from the y axis at the object's mid height) or `'pinhole'`
    (fixed camera 0.6 m in front of the object on +z, 640x480, 30° field)."""
    rack = paper_light_rack() if rack is None else rack
    if kind == "scanner":
        return CylindricalScanner(radius=0.6, height=float(center[1]), rack=rack)
    if kind == "pinhole":
        eye = center + np.array([0.0, 0.0, 0.6])
        return PinholeCamera.look_at(eye, center, fov_deg=30.0, width=640, height=480)
    raise ValueError(f"rig must be one of {RIGS}, got {kind!r}")


def _rig_positions(rig, vertices, rack):
    """cam_pos and light_pos in scan-bundle shapes, and a rig description."""
    if isinstance(rig, CylindricalScanner):
        cam = rig.camera_positions(vertices)[:, None, :]
        lights = rig.light_positions(vertices)
        desc = {"type": "cylindrical-scanner", "radius": rig.radius, "height": rig.height,
                "rack": rig.rack.tolist(), "axis": [0.0, 1.0, 0.0]}
    else:
        cam = rig.center
        lights = rig.rack_positions(rack)
        desc = {"type": "pinhole", "K": rig.K.tolist(), "R": rig.R.tolist(), "t": rig.t.tolist(),
                "width": rig.width, "height": rig.height, "dist": rig.dist.tolist(),
                "rack": np.asarray(rack).tolist()}
    return cam, lights, desc


def _tilted(obj, about_x: float, about_z: float):
    """`obj` turned by `about_x` then `about_z` degrees about its bounding-box centre."""
    ax, az = np.radians(about_x), np.radians(about_z)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    r = rz @ rx
    c = 0.5 * (obj.vertices.min(0) + obj.vertices.max(0))
    return dataclasses.replace(obj, vertices=(obj.vertices - c) @ r.T + c, normals=obj.normals @ r.T)


def make_scan(
    name: str = "A",
    *,
    resolution: int = 64,
    setup: str = "glossy",
    rig: str | None = None,
    lights=None,
    model: str = "torrance-sparrow",
    global_illumination: bool = False,
    samples: int = 64,
    sensor: Sensor = Sensor(),
    intensity: float = 1.0,
    seed: int = 0,
    progress: bool = False,
    tilt_deg: tuple[float, float] = (0.0, 0.0),
) -> tuple[Scan, dict]:
    """Render a synthetic scan bundle of object `name`.

    **Arguments:** `resolution` mesh resolution (see `objects.make_object`);
    `setup` 'diffuse' or 'glossy' (Object E only) or 'glazed' (any object:
    `objects.make_object`); `rig` 'scanner' (default for
    A-D) or 'pinhole' (default for E); `lights` indices into the 60-position
    rack (default: all); `model` 'torrance-sparrow' or 'ward' (the truth is
    stored as `true_sigma` or `true_alpha` accordingly); `global_illumination`
    renders interreflections with `samples` paths per observation; `sensor`
    noise model; `intensity` radiant intensity of every light [W/sr]; `seed`
    fixes path sampling and noise; `tilt_deg` `(about x, about z)` [deg] turns the
    object about its bounding-box centre before anything is rendered (the paper
    sets Object E "on the table obliquely"); `meta['tilt_deg']` records it.

    **Returns:** `(scan, report)`; `report` holds timings and the Monte Carlo
    standard error of the global-illumination render.
    """
    if name not in OBJECT_NAMES + EXTRA_NAMES:
        raise ValueError(f"object must be one of {OBJECT_NAMES + EXTRA_NAMES}, got {name!r}")
    if model not in ("torrance-sparrow", "ward"):
        raise ValueError(f"model must be 'torrance-sparrow' or 'ward', got {model!r}")
    if not intensity > 0:
        raise ValueError("intensity must be > 0")
    t0 = time.perf_counter()
    obj = make_object(name, resolution=resolution, setup=setup)
    if any(tilt_deg):
        obj = _tilted(obj, *tilt_deg)
    rig = rig or ("pinhole" if name == "E" else "scanner")
    center = 0.5 * (obj.vertices.min(0) + obj.vertices.max(0))
    rack = paper_light_rack()
    if lights is not None:
        lights = np.asarray(lights, dtype=np.int64).ravel()
        if len(lights) == 0 or lights.min() < 0 or lights.max() >= len(rack):
            raise ValueError(f"lights must be indices in [0, {len(rack) - 1}]")
        rack = rack[lights]
    rig_obj = make_rig(rig, center, rack)
    cam, light_pos, rig_desc = _rig_positions(rig_obj, obj.vertices, rack)
    n, m = len(obj.vertices), len(rack)
    cam_full = np.broadcast_to(cam, (n, m, 3))
    light_full = np.broadcast_to(light_pos, (n, m, 3))
    t_geom = time.perf_counter()

    caster = RayCaster(obj.vertices, obj.faces)
    material = Material(obj.pd, obj.ps, obj.roughness, model)
    tracer = PathTracer(obj.vertices, obj.faces, obj.normals, material, caster=caster)
    y = np.full(m, float(intensity))
    radiance, stderr = tracer.render(
        np.ascontiguousarray(cam_full), np.ascontiguousarray(light_full), y,
        samples=samples, seed=seed, indirect=global_illumination, progress=progress,
    )
    t_render = time.perf_counter()

    # An observation exists where the camera sees the vertex (facing, unoccluded, in frame).
    to_cam = cam_full - obj.vertices[:, None, :]
    facing = np.einsum("nmi,ni->nm", to_cam, obj.normals) > 0
    valid = facing & caster.visibility(cam)
    if isinstance(rig_obj, PinholeCamera):
        uv, depth = rig_obj.project(obj.vertices)
        in_frame = (depth > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= rig_obj.width - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= rig_obj.height - 0.5)
        valid &= in_frame[:, None]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 1]))
    observed, saturation = apply_sensor(radiance, valid, sensor, rng)
    observed = np.where(valid[..., None], observed, 0.0)

    rough_key = "true_sigma" if model == "torrance-sparrow" else "true_alpha"
    rel_se = stderr[valid] / np.maximum(radiance[valid], 1e-12)
    report = {
        "object": name,
        "points": n,
        "faces": int(len(obj.faces)),
        "lights": m,
        "valid_fraction": float(valid.mean()),
        "global_illumination": global_illumination,
        "samples": samples if global_illumination else 0,
        "mc_relative_stderr_median": float(np.median(rel_se)) if rel_se.size else 0.0,
        "mc_relative_stderr_p99": float(np.percentile(rel_se, 99)) if rel_se.size else 0.0,
        "seconds": {"geometry": t_geom - t0, "render": t_render - t_geom,
                    "total": time.perf_counter() - t0},
    }
    meta = {
        "generator": "data_synth.make_scan",
        "jaxrefl_version": jaxrefl.__version__,
        "object": name,
        "description": obj.description,
        "setup": setup if (name == "E" or setup == "glazed") else None,
        "part_names": list(obj.part_names),
        "rig": rig_desc,
        "light_indices": (lights.tolist() if lights is not None else list(range(m))),
        "model": model,
        "global_illumination": global_illumination,
        "samples": samples if global_illumination else 0,
        "sensor": asdict(sensor),
        "seed": seed,
        "tilt_deg": [float(t) for t in tilt_deg],
        "mc_relative_stderr_median": report["mc_relative_stderr_median"],
    }
    scan = Scan(
        vertices=obj.vertices,
        faces=obj.faces,
        normals=obj.normals,
        light_pos=np.asarray(light_pos),
        light_intensity=np.float64(intensity),
        cam_pos=np.asarray(cam),
        radiance=observed.astype(np.float32),
        valid=valid,
        saturation=saturation,
        true_pd=obj.pd,
        true_ps=obj.ps,
        true_normals=obj.normals,
        meta=meta,
        **{rough_key: obj.roughness},
    )
    return validate_scan(scan), report


def direct_radiance(scan: Scan, pd, ps, sigma) -> np.ndarray:
    """Direct Torrance-Sparrow radiance `(N, K, 3)` [W/(sr m^2)] of `scan`'s geometry
    under its lights for reflectance `pd` `(N, 3)`, `ps` `(N,)`, `sigma` `(N,)` [rad]:
    no cast shadows, no sensor (relighting errors under held-out lights)."""
    import jax
    import jax.numpy as jnp

    from jaxrefl.geometry.rig import observation_geometry
    from jaxrefl.reflectance import brdf

    g = observation_geometry(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos)
    full, _ = brdf.MODELS["torrance-sparrow"]
    f = jax.vmap(jax.vmap(full, in_axes=(None, None, None, 0, 0, 0)))(
        jnp.asarray(pd), jnp.asarray(ps), jnp.log(jnp.asarray(sigma)), g.cos_i, g.cos_o, g.theta_r)
    e = scan.intensities()[None] * np.maximum(np.asarray(g.cos_i), 0) / np.asarray(g.light_distance) ** 2
    return np.asarray(f) * e[..., None]
