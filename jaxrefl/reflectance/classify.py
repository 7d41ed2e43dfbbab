"""Measurability of reflection components per (point, light) (paper §2.2.2-2.2.4, §3.1).

For every point and candidate light, in one vectorised pass:

- *measurable* (Eq. 2 plus visibility): the camera and the light are both above
  the surface (`V.N > 0`, `L.N > 0`, by more than `brdf.COS_FLOOR`), the camera
  sees the point and the light reaches it (Embree segment tests), and, when
  images exist, the sample was observed and is not saturated;
- *diffuse-only* (Eq. 3): measurable and `theta_r > theta_th1` (default 60°);
- *strong specular* (Eq. 4): measurable and `theta_r <= theta_th2` (default 20°).

Classes (int8): `T_DIFF = 1`, `T_SPEC = 2`, `T_NONE = 0` (measurable, neither),
and `T_INVALID = -1` for samples that are not measurable at all (back-facing,
shadowed, occluded, unobserved or saturated): these are never fitted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.mesh import vertex_areas
from ..geometry.raycast import RayCaster
from ..geometry.rig import observation_angles
from .brdf import COS_FLOOR

__all__ = ["T_INVALID", "T_NONE", "T_DIFF", "T_SPEC", "Thresholds", "Measurability", "classify",
           "classify_scan"]

T_INVALID, T_NONE, T_DIFF, T_SPEC = -1, 0, 1, 2


@dataclass(frozen=True)
class Thresholds:
    """Half-vector angle thresholds [degrees]: diffuse-only above `diffuse_deg`
    (theta_th1), strong specular at or below `specular_deg` (theta_th2)."""

    diffuse_deg: float = 60.0
    specular_deg: float = 20.0

    def __post_init__(self):
        if not 0 <= self.specular_deg < self.diffuse_deg <= 90:
            raise ValueError("Thresholds: need 0 <= specular_deg < diffuse_deg <= 90")


class Measurability(NamedTuple):
    """Per-(point, light) results, each `(N, K)`: `measurable`, `diffuse_only`,
    `strong_specular` (bool), `classes` (int8, see module docstring),
    `theta_r` [rad], `seen` `(N,)` bool: the camera sees the point at all, and
    `pixel_weight` `(N,)`: the point's share of the image, its vertex area [m^2]
    times the cosine to the camera (how the paper's pixel counts weigh it)."""

    measurable: np.ndarray
    diffuse_only: np.ndarray
    strong_specular: np.ndarray
    classes: np.ndarray
    theta_r: np.ndarray
    seen: np.ndarray
    pixel_weight: np.ndarray


@jax.jit
def _classes(measurable, theta_r, th_diffuse, th_specular):
    diffuse = measurable & (theta_r > th_diffuse)
    specular = measurable & (theta_r <= th_specular)
    classes = jnp.where(measurable, jnp.where(diffuse, T_DIFF, jnp.where(specular, T_SPEC, T_NONE)),
                        T_INVALID).astype(jnp.int8)
    return diffuse, specular, classes


def classify(points, normals, cam_pos, light_pos, caster: RayCaster,
             thresholds: Thresholds = Thresholds(), observed=None) -> Measurability:
    """Classify every (point, light) sample.

    **Arguments:** `points` `(N, 3)` mesh vertices of `caster`; `normals` `(N, 3)`;
    `cam_pos` `(3,)`, `(K, 3)`, `(N, 1, 3)` or `(N, K, 3)`; `light_pos` `(K, 3)` or
    `(N, K, 3)` [m]; `observed` optional `(N, K)` bool (observation present and
    not saturated), None when planning before capture.

    **Returns:** `Measurability`.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    light_pos = np.asarray(light_pos, dtype=np.float64)
    k = light_pos.shape[-2]
    cos_i, cos_o, theta_r = (np.asarray(a) for a in observation_angles(points, normals, cam_pos, light_pos))

    # Camera visibility: one ray per distinct camera position of each point.
    cam = np.asarray(cam_pos, dtype=np.float64)
    cam = cam.reshape((1,) * (3 - cam.ndim) + cam.shape)  # (1 or N, 1 or K, 3)
    cam_visible = np.broadcast_to(caster.visibility(cam[0] if cam.shape[0] == 1 else cam), (n, k))
    # "Above the surface" to more than rounding: a point seen or lit edge-on (cosine at
    # rounding level, e.g. on a fold seen along it) has no image area, and the models'
    # 1 / cos factors are floored there (`brdf.COS_FLOOR`), so they cannot fit it.
    facing_cam, facing_light = cos_o > COS_FLOOR, cos_i > COS_FLOOR
    seen = np.any(facing_cam & cam_visible, axis=1)

    # Shadow rays only where everything else already holds.
    candidate = facing_light & facing_cam & cam_visible
    if observed is not None:
        observed = np.asarray(observed, dtype=bool)
        if observed.shape != (n, k):
            raise ValueError(f"observed: must be (N, K) = {(n, k)}, got {observed.shape}")
        candidate &= observed
    measurable = caster.visibility(light_pos, where=candidate)

    diffuse, specular, classes = _classes(measurable, theta_r, np.radians(thresholds.diffuse_deg),
                                          np.radians(thresholds.specular_deg))
    pixel_weight = vertex_areas(caster.vertices, caster.faces) * np.max(np.where(cam_visible, np.maximum(cos_o, 0.0), 0.0), axis=1)
    return Measurability(measurable, np.asarray(diffuse), np.asarray(specular), np.asarray(classes),
                         theta_r, seen, pixel_weight)


def classify_scan(scan, thresholds: Thresholds = Thresholds(), caster: RayCaster | None = None,
                  use_observations: bool = True) -> Measurability:
    """`classify` for a `jaxrefl.Scan`; its radiance (if any) masks unobserved and
    saturated samples unless `use_observations` is False (planning)."""
    caster = caster or RayCaster(scan.vertices, scan.faces)
    observed = scan.observed() if (use_observations and scan.radiance is not None) else None
    return classify(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos, caster, thresholds, observed)
