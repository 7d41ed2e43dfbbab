"""Reflectance models as per-row `jnp` functions.

Conventions (see DESIGN.md):

- A *row* is one (point, light) sample. Every function here takes one row
  (`pd` of shape `(3,)`, everything else scalar) and is lifted to batches with
  `jax.vmap`; plain broadcasting also works for the scalar arguments.
- `pd` is an albedo in [0, 1]: the diffuse BRDF is `pd / pi` in both models
  (the paper's Eq. 1 folds this `pi` into the light strength `Y`).
- Roughness enters as its natural logarithm (`log_sigma`, `log_alpha`), the
  parameterisation the solvers optimise. It is clipped to `LOG_ROUGHNESS_RANGE`
  (roughness 1e-6 to 1e3 rad) inside the lobes, so an extreme value (even +-inf)
  gives a finite lobe, with a zero gradient beyond the range.
- `theta_r` is the angle between the normal and the half vector, computed with
  `atan2(|N x H|, N . H)` (see `half_angle`), never `arccos`.
- A sample is *valid* when `cos_i > 0` and `cos_o > 0` (light and viewer above
  the surface). Invalid samples evaluate to 0 with zero gradients, never NaN.

BRDF values are in 1/sr. The radiance a camera sees from a point light of
radiant intensity `Y` [W/sr] at distance `C` [m] is
`brdf * Y * cos_i / C**2` (`point_light_radiance`).

Torrance-Sparrow (paper Eq. 1, Gaussian facet distribution, no Fresnel or
masking term), as a BRDF:

    f = pd / pi + ps * exp(-theta_r**2 / (2 sigma**2)) / (cos_i * cos_o)

so the observed value is `Y / C**2 * (pd / pi * cos_i + ps * exp(...) / cos_o)`,
which is Eq. 1 with `pd / pi` in place of `P_d`.

Ward isotropic (paper Eq. 13, Ward 1992):

    f = pd / pi + ps * exp(-tan(theta_h)**2 / alpha**2)
                  / (4 pi alpha**2 sqrt(cos_i * cos_o))

with `theta_h == theta_r`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry.vectors import half_angle as half_angle, shading_geometry as shading_geometry

__all__ = [
    "COS_FLOOR",
    "LOG_ROUGHNESS_RANGE",
    "ROUGHNESS_GRID",
    "MODELS",
    "half_angle",
    "shading_geometry",
    "torrance_sparrow",
    "torrance_sparrow_specular",
    "ward",
    "ward_specular",
    "point_light_radiance",
    "specular_albedo",
    "ps_bound",
]

#: Smallest cosine used in a denominator. Valid samples closer to grazing than
#: this (about 0.00006 degrees) are evaluated as if at this cosine, so values
#: stay finite in float32.
COS_FLOOR = 1e-6

#: Range `(lo, hi)` of ln roughness [ln rad] the lobes evaluate: roughness 1e-6 to 1e3 rad.
#: Wider than any fit's bounds; it keeps `exp`, `1 / alpha**2` and their gradients finite
#: (float32 included) for any input, -inf and +inf among them.
LOG_ROUGHNESS_RANGE = (float(np.log(1e-6)), float(np.log(1e3)))

#: Roughness values [rad] that grid searches (variable projection) try: 3 mrad to
#: 1.2 rad, log-spaced 64 values (coarser grids missed narrow minima in the tests).
ROUGHNESS_GRID = np.geomspace(0.003, 1.2, 64)

#: Largest exponent magnitude fed to `exp`; beyond it the lobe is 0 to float64
#: precision and its gradient must stay 0 (not 0 * inf).
_EXP_CAP = 700.0


def _valid_cosines(cos_i, cos_o):
    cos_i, cos_o = jnp.asarray(cos_i), jnp.asarray(cos_o)
    ok = (cos_i > 0) & (cos_o > 0)
    ci = jnp.where(ok, jnp.maximum(cos_i, COS_FLOOR), 1.0)
    co = jnp.where(ok, jnp.maximum(cos_o, COS_FLOOR), 1.0)
    return ok, ci, co


def torrance_sparrow_specular(ps, log_sigma, cos_i, cos_o, theta_r):
    """Specular lobe of the Torrance-Sparrow BRDF, 1/sr (scalar per row)."""
    ok, ci, co = _valid_cosines(cos_i, cos_o)
    sigma = jnp.exp(jnp.clip(log_sigma, *LOG_ROUGHNESS_RANGE))
    expo = jnp.minimum(theta_r**2 / (2.0 * sigma**2), _EXP_CAP)
    return jnp.where(ok, ps * jnp.exp(-expo) / (ci * co), 0.0)


def ward_specular(ps, log_alpha, cos_i, cos_o, theta_r):
    """Specular lobe of the isotropic Ward BRDF, 1/sr (scalar per row)."""
    ok, ci, co = _valid_cosines(cos_i, cos_o)
    alpha2 = jnp.exp(2.0 * jnp.clip(log_alpha, *LOG_ROUGHNESS_RANGE))
    # tan^2 from sin/cos of theta_r with a floored cosine: finite up to grazing.
    c = jnp.maximum(jnp.cos(theta_r), COS_FLOOR)
    tan2 = (jnp.sin(theta_r) / c) ** 2
    expo = jnp.minimum(tan2 / alpha2, _EXP_CAP)
    lobe = ps * jnp.exp(-expo) / (4.0 * jnp.pi * alpha2 * jnp.sqrt(ci * co))
    return jnp.where(ok, lobe, 0.0)


def _diffuse(pd, cos_i, cos_o):
    ok = (jnp.asarray(cos_i) > 0) & (jnp.asarray(cos_o) > 0)
    return jnp.where(ok[..., None], jnp.asarray(pd) / jnp.pi, 0.0)


def torrance_sparrow(pd, ps, log_sigma, cos_i, cos_o, theta_r):
    """Torrance-Sparrow BRDF of one row.

    **Arguments:** `pd` `(3,)` diffuse albedo; `ps` specular reflectance;
    `log_sigma` log of the facet slope deviation sigma [rad] (clipped to
    `LOG_ROUGHNESS_RANGE`); `cos_i`, `cos_o`
    cosines of the light and view directions with the normal; `theta_r` [rad].

    **Returns:** `(3,)` BRDF [1/sr]; 0 for an invalid sample.
    """
    spec = torrance_sparrow_specular(ps, log_sigma, cos_i, cos_o, theta_r)
    return _diffuse(pd, cos_i, cos_o) + spec[..., None]


def ward(pd, ps, log_alpha, cos_i, cos_o, theta_r):
    """Isotropic Ward BRDF of one row; arguments as `torrance_sparrow`, with `log_alpha`."""
    spec = ward_specular(ps, log_alpha, cos_i, cos_o, theta_r)
    return _diffuse(pd, cos_i, cos_o) + spec[..., None]


#: Model name -> (full BRDF, specular lobe). Names as used on the command line.
MODELS = {
    "torrance-sparrow": (torrance_sparrow, torrance_sparrow_specular),
    "ward": (ward, ward_specular),
}


def point_light_radiance(brdf_value, intensity, cos_i, distance):
    """Radiance seen from a point lit by an isotropic point light.

    **Arguments:** `brdf_value` `(..., 3)` [1/sr]; `intensity` radiant intensity
    Y [W/sr]; `cos_i` cosine at the surface; `distance` C [m] to the light.

    **Returns:** `(..., 3)` radiance `brdf * Y * max(cos_i, 0) / C**2` [W/(sr m^2)].
    """
    irradiance = intensity * jnp.maximum(cos_i, 0.0) / distance**2
    return brdf_value * irradiance[..., None]


def specular_albedo(model: str, roughness) -> np.ndarray:
    """Directional albedo of the unit-`ps` lobe at normal incidence (host-side NumPy).

    **Arguments:** `model` a key of `MODELS`; `roughness` `(...)` [rad] (sigma or alpha).

    **Returns:** `(...)` the reflected fraction `int f_s cos_o dw_o` for `ps = 1` and light
    along the normal: about 1 for a narrow Ward lobe (its `ps` is an albedo), about
    `8 pi sigma^2` for a narrow Torrance-Sparrow lobe. Gauss-Legendre over the angle of
    view up to where the lobe has fallen below `e^-40`.
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {sorted(MODELS)}, got {model!r}")
    r = np.maximum(np.asarray(roughness, np.float64), 1e-6)
    flat = r.reshape(-1)
    # In blocks: the (values, nodes) temporaries of a whole scan would not stay in cache.
    out = np.concatenate([_specular_albedo_block(model, flat[s:s + _ALBEDO_BLOCK])
                          for s in range(0, len(flat), _ALBEDO_BLOCK)] or [np.zeros(0)])
    return out.reshape(r.shape)


_ALBEDO_BLOCK = 4096  # roughness values per block of `specular_albedo`
_ALBEDO_NODES = np.polynomial.legendre.leggauss(128)


def _specular_albedo_block(model, r):
    """`specular_albedo` of `r` `(n,)` (already floored)."""
    nodes, weights = _ALBEDO_NODES
    if model == "ward":
        top = np.minimum(np.pi / 2, 2.0 * np.arctan(r * np.sqrt(40.0)))
    else:
        top = np.minimum(np.pi / 2, 2.0 * r * np.sqrt(80.0))
    theta = 0.5 * top[..., None] * (nodes + 1.0)  # view angle; the half angle is theta / 2
    if model == "ward":
        lobe = np.exp(-np.tan(theta / 2) ** 2 / r[..., None] ** 2) / (4 * np.pi * r[..., None] ** 2) \
            * np.sqrt(np.cos(theta))
    else:
        lobe = np.exp(-(theta / 2) ** 2 / (2 * r[..., None] ** 2))
    return 2 * np.pi * 0.5 * top * np.sum(weights * lobe * np.sin(theta), axis=-1)


def ps_bound(model: str, roughness) -> np.ndarray:
    """Largest `ps` `(...)` whose lobe reflects at most all the light it receives at normal
    incidence (`ps * specular_albedo <= 1`): the energy bound every estimate keeps."""
    return 1.0 / np.maximum(specular_albedo(model, roughness), 1e-300)
