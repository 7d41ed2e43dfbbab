"""Synthetic range images from a Cyberware-style cylindrical rangefinder, with true normals.

The scanner head turns about the y axis; for every column angle `theta` (from +z toward
+x) and row height `y` (row 0 at the top) a ray comes in horizontally from outside the
object toward the axis and the first surface it meets gives the range `r`, the distance
of the hit from the axis. Rays stop at the axis (the far side is another column's
business), so a column that meets nothing before the axis has no return (NaN).

Truth comes from a fine mesh of the object (resolution 128, true normals ~1 degree):
the true point is the hit on the ray, the true normal the barycentric interpolation of
the object's exact vertex normals at the hit. The sensor then adds Gaussian noise to
`r`, replaces a fraction of the returns by spikes and quantises `r`.
"""

from __future__ import annotations

import numpy as np

from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.scan.preprocess import RangeImage

from .objects import make_object

__all__ = ["cylindrical_grid", "make_range_image", "scan_mesh"]


def cylindrical_grid(vertices: np.ndarray, width: int, height: int | None = None):
    """Scanner grid around `vertices` `(N, 3)`: `theta` `(W,)` = `2 pi (j + 1/2) / W`,
    `y` `(H,)` from just below the top to just above the bottom (pixel centres),
    and the ray start radius `r_max` [m]. `height` defaults to square pixels at the
    mean vertex radius."""
    v = np.asarray(vertices, dtype=np.float64)
    rad = np.hypot(v[:, 0], v[:, 2])
    r_max = float(rad.max()) * 1.05 + 1e-6
    y0, y1 = float(v[:, 1].min()), float(v[:, 1].max())
    if height is None:
        height = max(2, int(round(width * (y1 - y0) / (2 * np.pi * max(float(rad.mean()), 1e-9)))))
    theta = 2 * np.pi * (np.arange(width) + 0.5) / width
    y = y1 - (np.arange(height) + 0.5) / height * (y1 - y0)
    return theta, y, r_max


def scan_mesh(vertices, faces, normals, width: int = 512, height: int | None = None):
    """Noise-free scan of a mesh with per-vertex `normals`.

    **Returns:** `theta` `(W,)`, `y` `(H,)`, `r` `(H, W)` [m] (NaN where no return),
    `true_points` `(H, W, 3)`, `true_normals` `(H, W, 3)` (NaN where no return),
    `hit` `(H, W)` bool.
    """
    caster = RayCaster(vertices, faces)
    theta, y, r_max = cylindrical_grid(caster.vertices, width, height)
    H, W = len(y), len(theta)
    tt, yy = np.meshgrid(theta, y)
    s, c = np.sin(tt.ravel()), np.cos(tt.ravel())
    origins = np.stack([r_max * s, yy.ravel(), r_max * c], -1)
    dirs = np.stack([-s, np.zeros_like(s), -c], -1)
    hits = caster.first_hit(origins, dirs, tfar=r_max)
    hit = hits.hit.reshape(H, W)
    # Range along the ray in float64 from the barycentric hit point.
    r = np.where(hit, np.hypot(hits.points[:, 0], hits.points[:, 2]).reshape(H, W), np.nan)
    true_points = np.stack([r * np.sin(tt), np.where(hit, yy, np.nan), r * np.cos(tt)], -1)
    nv = np.asarray(normals, dtype=np.float64)[caster.faces[np.maximum(hits.face, 0)]]
    n = np.einsum("pk,pkj->pj", hits.barycentric, nv)
    n /= np.where(hits.hit, np.linalg.norm(n, axis=1), 1.0)[:, None]
    n[~hits.hit] = np.nan
    return theta, y, r, true_points, n.reshape(H, W, 3), hit


def make_range_image(name: str = "A", width: int = 512, height: int | None = None,
                     noise: float = 0.0003, outlier_fraction: float = 0.002,
                     outlier_scale: float = 0.01, quantization: float = 0.0001,
                     resolution: int = 128, seed: int = 0):
    """Noisy range image of synthetic object `name` (`data_synth.objects`).

    Sensor model, in this order: Gaussian noise of std `noise` [m] on `r`; a
    fraction `outlier_fraction` of the returns (chosen at random) replaced by
    spikes `r +- outlier_scale` [m] (random sign); `r` rounded to multiples of
    `quantization` [m] (0 = none); `r` clipped at 0. Deterministic for a `seed`.

    **Returns:** `(noisy, true_points, true_normals, hit)`: `noisy` RangeImage
    (`H x W`, NaN where no return); `true_points` `(H, W, 3)` [m] and
    `true_normals` `(H, W, 3)` unit (NaN where no return); `hit` `(H, W)` bool.
    """
    for field, val in (("noise", noise), ("outlier_fraction", outlier_fraction),
                       ("outlier_scale", outlier_scale), ("quantization", quantization)):
        if not np.isfinite(val) or val < 0:
            raise ValueError(f"{field}: must be a finite number >= 0, got {val!r}")
    if outlier_fraction > 1:
        raise ValueError(f"outlier_fraction: must be <= 1, got {outlier_fraction!r}")
    if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or width < 3:
        raise ValueError(f"width: must be an integer >= 3, got {width!r}")
    if height is not None and (isinstance(height, bool) or not isinstance(height, (int, np.integer))
                               or height < 2):
        raise ValueError(f"height: must be an integer >= 2, got {height!r}")
    obj = make_object(name, resolution)
    theta, y, r, true_points, true_normals, hit = scan_mesh(
        obj.vertices, obj.faces, obj.normals, width, height)
    rng = np.random.default_rng(seed)
    noisy = r + rng.normal(0.0, noise, r.shape) if noise > 0 else r.copy()
    hit_idx = np.flatnonzero(hit)
    n_out = int(round(outlier_fraction * len(hit_idx)))
    if n_out:
        pick = rng.choice(hit_idx, size=n_out, replace=False)
        noisy.ravel()[pick] += outlier_scale * rng.choice([-1.0, 1.0], size=n_out)
    if quantization > 0:
        noisy = np.round(noisy / quantization) * quantization
    noisy = np.where(hit, np.maximum(noisy, 0.0), np.nan)
    return RangeImage(noisy, theta, y), true_points, true_normals, hit
