"""Shading geometry of samples: the cosines to light and viewer and the half angle theta_r
(`jaxrefl.reflectance.brdf` re-exports both functions)."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["half_angle", "shading_geometry"]


def _safe_norm(x):
    """Euclidean norm of the last axis with a zero (not NaN) gradient at 0."""
    sq = jnp.sum(x * x, axis=-1)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def half_angle(n, l, v):
    """Angle theta_r between the normal and the half vector of `l` and `v`.

    **Arguments:** `n`, `l`, `v`: `(..., 3)` unit normal, direction to the light,
    direction to the viewer.

    **Returns:** `(...)` radians in [0, pi]. Uses `atan2(|n x h|, n . h)` with
    the unnormalised half vector `h = l + v` (atan2 is scale-invariant), so it
    keeps full precision at the specular peak where `arccos(n . h)` loses it.
    """
    h = l + v
    return jnp.arctan2(_safe_norm(jnp.cross(n, h)), jnp.sum(n * h, axis=-1))


def shading_geometry(n, l, v):
    """Cosines and half angle of one or many samples.

    **Arguments:** `n`, `l`, `v`: `(..., 3)` unit vectors (normal, to light, to viewer).

    **Returns:** `(cos_i, cos_o, theta_r)`, each `(...)`.
    """
    return jnp.sum(n * l, axis=-1), jnp.sum(n * v, axis=-1), half_angle(n, l, v)
