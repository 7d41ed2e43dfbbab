"""Checks of the path tracer against a closed form and against itself.

- `furnace`: inside a closed sphere of uniform albedo rho with a point light
  and the camera at its centre, every wall point receives direct irradiance
  `E = Y / R^2`, and since every wall point sees the whole sphere
  (form factor 1), total irradiance is `E / (1 - rho)`: the radiance leaving
  the wall is `rho / pi * E / (1 - rho)`.
- `convergence`: RMS error of renders with growing sample counts against a
  high-sample reference; an unbiased estimator falls as `samples^(-1/2)`.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .pathtrace import Material, PathTracer

__all__ = ["furnace", "convergence"]


def furnace(rho: float = 0.5, samples: int = 256, subdivisions: int = 4, radius: float = 1.0,
            stride: int = 8, seed: int = 0) -> dict:
    """Render the inside of a closed sphere; compare with `rho E / (pi (1 - rho))`.

    **Returns:** dict with `expected`, `mean` (over every `stride`-th vertex),
    `stderr` (Monte Carlo standard error of that mean) and `z` (their ratio).
    """
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = sphere.vertices
    normals = -v / np.linalg.norm(v, axis=1, keepdims=True)  # inward-facing walls
    n = len(v)
    material = Material(np.full((n, 3), rho), np.zeros(n), np.full(n, 0.3))
    tracer = PathTracer(v, sphere.faces[:, ::-1], normals, material, max_depth=256)
    idx = np.arange(0, n, stride)
    centre = np.zeros((len(idx), 1, 3))
    radiance, stderr = tracer.render(centre, centre, np.ones(1), samples=samples, seed=seed,
                                     progress=False, points=idx)
    expected = rho / np.pi / radius**2 / (1.0 - rho)
    mean = float(radiance[:, 0, 0].mean())  # grey: one channel is the whole estimate
    se = float(np.sqrt(np.sum(stderr[:, 0, 0] ** 2)) / len(idx))
    return {"rho": rho, "expected": expected, "mean": mean, "stderr": se,
            "z": (mean - expected) / se if se > 0 else 0.0, "points": len(idx), "samples": samples}


def convergence(tracer: PathTracer, points, cam_pos, light_pos, intensity,
                sample_counts=(4, 16, 64, 256), reference_samples: int = 4096, seed: int = 0) -> dict:
    """RMS relative error of the indirect radiance against a high-sample render.

    **Arguments:** `points` `(P,)` vertex indices; `cam_pos`, `light_pos`
    `(P, M, 3)`; `intensity` `(M,)`; renders with each count in
    `sample_counts` use seeds independent of the reference.

    **Returns:** dict with `samples`, `rms_relative_error` (per count),
    `slope` (least-squares slope of log error against log samples; -0.5 for
    an unbiased estimator), `reference_relative_stderr` (median).
    """
    kw = dict(points=points, progress=False)
    ref, ref_se = tracer.render(cam_pos, light_pos, intensity, samples=reference_samples,
                                seed=seed + 10_000, **kw)
    scale = np.maximum(ref.mean(axis=-1, keepdims=True), 1e-12)
    errors = []
    for k, count in enumerate(sample_counts):
        est, _ = tracer.render(cam_pos, light_pos, intensity, samples=count, seed=seed + k, **kw)
        errors.append(float(np.sqrt(np.mean(((est - ref) / scale) ** 2))))
    slope = float(np.polyfit(np.log(sample_counts), np.log(errors), 1)[0])
    return {"samples": list(sample_counts), "rms_relative_error": errors, "slope": slope,
            "reference_samples": reference_samples,
            "reference_relative_stderr": float(np.median(ref_se / scale))}
