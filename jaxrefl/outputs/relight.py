"""Relighting: an estimated object under a new point light, seen by a pinhole camera.

Per vertex, the radiance toward the camera centre is the direct term

    L = f(pd, ps, roughness; cos_i, cos_o, theta_r) * Y * cos_i / C^2 * visible

(`f` the result's model, Torrance-Sparrow or Ward, see `jaxrefl.reflectance.brdf`; `Y`
the light's radiant intensity [W/sr], `C` its distance [m]; `visible` an
Embree shadow ray from the vertex to the light) plus an interreflection term
from `indirect`. The per-vertex radiance is pictured by casting one ray per
pixel and interpolating over the hit face (`render.camera_hits` + `render.shade`).

Global illumination is one pluggable function: `indirect(model_gi, ...)`
returns the `(N, 3)` radiance to add. `"none"` adds nothing; `"radiosity"`
and `"photon"` call `jaxrefl.methods.radiosity.relight_indirect` or
`jaxrefl.methods.final_gather.relight_indirect` with the arguments
`(vertices, faces, normals, est, light_pos, intensity, cam_pos)` and expect
`(N, 3)` finite radiance [W/(sr m^2)] back; where the module or the function
is missing, a `ValueError` says so.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry.raycast import RayCaster
from ..geometry.rig import PinholeCamera, observation_geometry
from ..methods.final_gather import relight_indirect as photon_indirect
from ..methods.final_gather import relight_observations as photon_observations
from ..methods.radiosity import relight_indirect as radiosity_indirect
from ..methods.radiosity import relight_observations as radiosity_observations
from ..reflectance import brdf
from ..result import Estimate
from . import render
from .render import fit_camera, scan_camera  # cameras live with the pictures; re-exported here

__all__ = [
    "GI_MODELS",
    "indirect",
    "indirect_observations",
    "direct_radiance",
    "relight",
    "relight_image",
    "fit_camera",
    "scan_camera",
    "truth_estimate",
    "picture",
    "image_errors",
]

GI_MODELS = ("none", "radiosity", "photon")


def _check_model_gi(model_gi, est: Estimate) -> None:
    """`model_gi` is one of `GI_MODELS`, and `est` a Ward result where it is 'photon'."""
    if model_gi not in GI_MODELS:
        raise ValueError(f"model-gi: must be one of {', '.join(GI_MODELS)}, got {model_gi!r}")
    if model_gi == "photon" and est.model != "ward":  # photon mapping traces the Ward model (Method III's)
        raise ValueError(f"model-gi: photon relighting needs a Ward result, this one is {est.model!r} "
                         "(estimate with --model ward, or use --model-gi radiosity)")


def _checked(out, model_gi, shape) -> np.ndarray:
    """`out` as float64, refused unless finite and of `shape`."""
    out = np.asarray(out, dtype=np.float64)
    if out.shape != shape or not np.all(np.isfinite(out)):
        bad = int(np.count_nonzero(~np.isfinite(out)))
        raise ValueError(f"model-gi: {model_gi} relighting returned {out.shape} "
                         f"with {bad} non-finite value(s), want {shape}")
    return out


def indirect(model_gi, vertices, faces, normals, est: Estimate, light_pos, intensity, cam_pos) -> np.ndarray:
    """Interreflected radiance `(N, 3)` toward `cam_pos` `(3,)` under one point light
    at `light_pos` `(3,)` of intensity `intensity` [W/sr]; `model_gi` in `GI_MODELS`."""
    n = len(vertices)
    if model_gi == "none":
        return np.zeros((n, 3))
    _check_model_gi(model_gi, est)
    if model_gi == "radiosity":  # diffuse interreflection only (Method II's model)
        out = radiosity_indirect(vertices, faces, normals, est.pd, light_pos, intensity)
    else:
        out = photon_indirect(vertices, faces, normals, est.pd, est.ps, est.roughness, light_pos, intensity,
                              cam_pos)
    return _checked(out, model_gi, (n, 3))


def indirect_observations(model_gi, scan, est: Estimate, observed, caster: RayCaster | None = None,
                          settings: dict | None = None) -> np.ndarray:
    """Interreflected radiance `(N, M, 3)` of every observation of `scan` (its own lights
    and cameras) as the method `model_gi` models its observations: `indirect` for all
    of them at once, the lights binned into configurations (`radiosity.light_configs`)
    and, for 'photon', one photon map over them and one final gather of the
    `observed` `(N, M)` observations. `settings`: keyword arguments of
    `radiosity.relight_observations` / `final_gather.relight_observations`."""
    n, m = scan.n_points, scan.n_lights
    _check_model_gi(model_gi, est)
    settings = dict(settings or {})
    if model_gi == "none":
        return np.zeros((n, m, 3))
    if model_gi == "radiosity":
        out = radiosity_observations(scan, est.pd, caster=caster, **settings)
    else:
        out = photon_observations(scan, est.pd, est.ps, est.roughness, observed, caster, **settings)
    return _checked(out, model_gi, (n, m, 3))


def direct_radiance(vertices, normals, est: Estimate, light_pos, intensity, cam_pos,
                    caster: RayCaster) -> np.ndarray:
    """Direct radiance `(N, 3)` [W/(sr m^2)] of every vertex toward `cam_pos` `(3,)`
    under a point light at `light_pos` `(3,)` of `intensity` [W/sr], with Embree shadows.
    Either position may also be `(N, 3)`: one per vertex (a light or camera riding a
    scanner head)."""
    if est.model not in brdf.MODELS:
        raise ValueError(f"model: unknown reflectance model {est.model!r}")
    n = len(vertices)
    light_pos = np.asarray(light_pos, dtype=np.float64)
    light_pos = light_pos.reshape(n, 1, 3) if light_pos.shape == (n, 3) else light_pos.reshape(1, 3)
    cam_pos = np.asarray(cam_pos, dtype=np.float64)
    cam_pos = cam_pos.reshape(n, 1, 3) if cam_pos.shape == (n, 3) else cam_pos.reshape(3)
    g = observation_geometry(vertices, normals, cam_pos, light_pos)
    cos_i, cos_o, theta_r = (jnp.asarray(a)[:, 0] for a in (g.cos_i, g.cos_o, g.theta_r))
    full, _ = brdf.MODELS[est.model]
    log_rough = jnp.log(jnp.maximum(jnp.asarray(est.roughness, dtype=cos_i.dtype), 1e-12))
    f = full(jnp.asarray(est.pd, dtype=cos_i.dtype), jnp.asarray(est.ps, dtype=cos_i.dtype), log_rough,
             cos_i, cos_o, theta_r)
    radiance = np.asarray(brdf.point_light_radiance(f, float(intensity), cos_i, g.light_distance[:, 0]),
                          dtype=np.float64)
    lit = caster.visibility(light_pos)[:, 0]
    return np.where(lit[:, None] & np.isfinite(radiance), radiance, 0.0)


def relight(vertices, faces, normals, est: Estimate, light_pos, intensity, cam_pos,
            model_gi: str = "none", caster: RayCaster | None = None) -> np.ndarray:
    """Radiance `(N, 3)` of the estimated object under a new point light: direct + `indirect`.

    **Arguments:** `vertices` `(N, 3)` [m], `faces` `(F, 3)`, `normals` `(N, 3)`
    unit; `est` per-vertex reflectance; `light_pos` `(3,)` [m]; `intensity` Y
    [W/sr] > 0; `cam_pos` `(3,)` [m]; `model_gi` one of `GI_MODELS`.
    """
    n = len(vertices)
    for name, value in (("pd", est.pd), ("ps", est.ps), ("roughness", est.roughness)):
        if np.shape(value)[0] != n:
            raise ValueError(f"{name}: the result has {np.shape(value)[0]} points, the scan {n}")
    light_pos = np.asarray(light_pos, dtype=np.float64)
    if light_pos.shape != (3,) or not np.all(np.isfinite(light_pos)):
        raise ValueError(f"light: must be three finite numbers, got {light_pos.tolist()}")
    if not (np.isfinite(intensity) and intensity > 0):
        raise ValueError(f"intensity: must be > 0, got {intensity}")
    if model_gi not in GI_MODELS:
        raise ValueError(f"model-gi: must be one of {', '.join(GI_MODELS)}, got {model_gi!r}")
    caster = caster or RayCaster(vertices, faces)
    extra = indirect(model_gi, vertices, faces, normals, est, light_pos, intensity, cam_pos)
    return direct_radiance(vertices, normals, est, light_pos, intensity, cam_pos, caster) + extra


def relight_image(est: Estimate, scan, light_pos, intensity: float | None = None, *,
                  camera: PinholeCamera | None = None, model_gi: str = "none", width: int = 640,
                  height: int = 480) -> np.ndarray:
    """Linear image `(H, W, 3)` [W/(sr m^2)] of `est` on `scan`'s mesh under a point light at
    `light_pos` `(3,)` [m] of `intensity` [W/sr] (default: the scan's first light's), seen
    by `camera` (default `scan_camera(scan, width, height)`); NaN off the object.
    `model_gi` as in `relight`."""
    if len(est.pd) != scan.n_points:
        raise ValueError(f"scan: the result has {len(est.pd)} points, the scan {scan.n_points}")
    intensity = float(scan.intensities()[0]) if intensity is None else float(intensity)
    camera = camera if camera is not None else scan_camera(scan, width, height)
    caster = RayCaster(scan.vertices, scan.faces)
    radiance = relight(scan.vertices, scan.faces, scan.normals, est, light_pos, intensity, camera.center,
                       model_gi, caster)
    return picture(caster, scan.faces, radiance, camera)


def truth_estimate(scan) -> Estimate:
    """The scan's ground-truth reflectance as an `Estimate` (for rendering the truth)."""
    if scan.true_pd is None or scan.true_ps is None:
        raise ValueError("reference: the scan has no ground truth (true_pd, true_ps)")
    if scan.true_sigma is not None:
        model, rough = "torrance-sparrow", scan.true_sigma
    elif scan.true_alpha is not None:
        model, rough = "ward", scan.true_alpha
    else:
        raise ValueError("reference: the scan has no ground-truth roughness (true_sigma or true_alpha)")
    n = scan.n_points
    zeros = np.zeros(n)
    return Estimate(scan.true_pd, scan.true_ps, rough, np.zeros(n, np.int8), np.zeros((n, 3)), zeros, zeros,
                    np.ones(n, bool), np.ones(n, bool), model, {"method": "ground truth", "model": model})


def picture(caster: RayCaster, faces, values, camera: PinholeCamera) -> np.ndarray:
    """Linear image `(H, W, 3)` of per-vertex `values` `(N, 3)` seen by `camera`;
    pixels off the object are NaN."""
    hits, shape = render.camera_hits(caster, camera)
    return render.shade(hits, faces, values, shape)


def image_errors(image: np.ndarray, reference: np.ndarray) -> dict:
    """Errors of a linear image against a reference `(H, W, 3)` over pixels finite in both:
    RMS relative (RMS difference / RMS reference), and the median and 90th percentile
    of per-pixel relative errors where the reference is above 5 % of its 99th percentile."""
    if image.shape != reference.shape:
        raise ValueError(f"reference: image is {reference.shape[1]}x{reference.shape[0]}, "
                         f"the relit picture {image.shape[1]}x{image.shape[0]}")
    both = np.all(np.isfinite(image), axis=-1) & np.all(np.isfinite(reference), axis=-1)
    if not np.any(both):
        raise ValueError("reference: no pixel is on the object in both images")
    a, b = image[both], reference[both]
    rms = float(np.sqrt(np.mean((a - b) ** 2)) / max(np.sqrt(np.mean(b**2)), 1e-300))
    lum_a, lum_b = a.mean(axis=1), b.mean(axis=1)
    bright = lum_b > 0.05 * np.percentile(lum_b, 99)
    rel = np.abs(lum_a - lum_b)[bright] / lum_b[bright]
    return {"pixels": int(both.sum()), "rms_relative": rms,
            "median_relative": float(np.median(rel)) if rel.size else 0.0,
            "p90_relative": float(np.percentile(rel, 90)) if rel.size else 0.0}
