"""Reflectance models: closed forms, reciprocity, positivity, finiteness at the hard cases."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxrefl.geometry import rig
from jaxrefl.reflectance import brdf

from .helpers import grid_plane, unit

MODELS = list(brdf.MODELS)


def hemisphere_vector(theta, phi):
    return jnp.array([jnp.sin(theta) * jnp.cos(phi), jnp.sin(theta) * jnp.sin(phi), jnp.cos(theta)])


angles = st.floats(0.0, np.pi / 2 - 1e-9)  # up to grazing, inclusive of theta = 0
azimuths = st.floats(0.0, 2 * np.pi)
log_roughness = st.floats(np.log(1e-3), 0.0)  # 1e-3 .. 1 rad
reflectance = st.floats(0.0, 1.0, allow_subnormal=False)  # XLA flushes subnormals


def test_lambertian_plane_matches_closed_form():
    """Radiance of a Lambertian plane under a point light is pd/pi * Y cos / r^2."""
    v, _ = grid_plane(0.5, 11)
    normals = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    light = np.array([[0.1, -0.2, 0.7]])
    cam = np.array([0.3, 0.3, 2.0])
    pd = np.array([0.2, 0.5, 0.9])
    intensity = 3.0
    g = rig.observation_geometry(v, normals, cam, light)
    f = jax.vmap(jax.vmap(lambda ci, co, tr: brdf.torrance_sparrow(pd, 0.0, 0.0, ci, co, tr)))(
        g.cos_i, g.cos_o, g.theta_r
    )
    radiance = brdf.point_light_radiance(f, intensity, g.cos_i, g.light_distance)
    d = light[0] - v
    r = np.linalg.norm(d, axis=1)
    expected = pd[None] / np.pi * intensity * (d[:, 2] / r)[:, None] / r[:, None] ** 2
    np.testing.assert_allclose(np.asarray(radiance[:, 0]), expected, rtol=1e-13, atol=0)


@pytest.mark.parametrize("model", MODELS)
@settings(max_examples=200, deadline=None)
@given(ti=angles, pi_=azimuths, to=angles, po=azimuths, ps=reflectance, lr=log_roughness,
       pd=st.tuples(reflectance, reflectance, reflectance))
def test_reciprocity_and_positivity(model, ti, pi_, to, po, ps, lr, pd):
    fwd, back = _both_ways(model, jnp.array(pd), ps, lr, ti, pi_, to, po)
    np.testing.assert_allclose(fwd, back, rtol=1e-12, atol=1e-300)
    assert np.all(np.asarray(fwd) >= 0)
    if np.cos(ti) > 0 and np.cos(to) > 0:
        assert np.all(np.asarray(fwd) >= np.asarray(pd) / np.pi * (1 - 1e-12) - 1e-300)


@partial(jax.jit, static_argnums=0)
def _both_ways(model, pd, ps, lr, ti, pi_, to, po):
    f, _ = brdf.MODELS[model]
    n = jnp.array([0.0, 0.0, 1.0])
    wi, wo = hemisphere_vector(ti, pi_), hemisphere_vector(to, po)
    return (f(pd, ps, lr, *brdf.shading_geometry(n, wi, wo)),
            f(pd, ps, lr, *brdf.shading_geometry(n, wo, wi)))


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@settings(max_examples=150, deadline=None)
@given(ti=angles, pi_=azimuths, to=angles, po=azimuths, ps=reflectance, lr=log_roughness,
       pd=reflectance, mirror=st.booleans())
def test_values_and_gradients_finite(model, dtype, ti, pi_, to, po, ps, lr, pd, mirror):
    """Finite values and gradients (parameters and geometry) up to grazing, at theta_r = 0,
    for roughness 1e-3 .. 1 rad, in float32 and float64."""
    if mirror:  # exact specular configuration: theta_r == 0
        to, po = ti, pi_ + np.pi
    params = tuple(jnp.asarray(x, dtype) for x in (pd, ps, lr))
    vecs = tuple(jnp.asarray(x, dtype) for x in
                 ([0.0, 0.0, 1.0], hemisphere_vector(ti, pi_), hemisphere_vector(to, po)))
    value, (g_params, g_vecs) = _value_and_grad(model, params, vecs)
    assert np.isfinite(value)
    for g in (*g_params, *g_vecs):
        assert np.all(np.isfinite(np.asarray(g)))


@partial(jax.jit, static_argnums=0)
def _value_and_grad(model, params, vecs):
    f, _ = brdf.MODELS[model]

    def radiance(params, vecs):
        pd_, ps_, lr_ = params
        n, l, v = vecs
        val = f(jnp.full(3, pd_), ps_, lr_, *brdf.shading_geometry(n, l, v))
        return jnp.sum(brdf.point_light_radiance(val, 1.0, jnp.sum(n * l), 0.5))

    return jax.value_and_grad(radiance, argnums=(0, 1))(params, vecs)


@pytest.mark.parametrize("model", MODELS)
def test_invalid_samples_are_zero_with_zero_gradient(model):
    f, _ = brdf.MODELS[model]
    pd = jnp.array([0.5, 0.5, 0.5])

    def total(lr, ci):
        return jnp.sum(f(pd, 0.3, lr, ci, 0.5, 0.1))

    for ci in (-0.3, 0.0):
        assert float(total(-2.0, ci)) == 0.0
        g = jax.grad(total, argnums=(0, 1))(-2.0, ci)
        assert all(float(x) == 0.0 for x in g)


def test_half_angle_keeps_precision_at_the_peak():
    """atan2 recovers a 1e-7 rad half angle, where arccos(N.H) returns garbage."""
    for true in (1e-9, 1e-7, 1e-4, 0.3):
        n = jnp.array([0.0, 0.0, 1.0])
        h = jnp.array([np.sin(true), 0.0, np.cos(true)])
        # l and v symmetric about h (40 degrees either side).
        axis = jnp.array([0.0, 1.0, 0.0])
        rot = lambda a: h * np.cos(a) + jnp.cross(axis, h) * np.sin(a)  # noqa: E731
        got = float(brdf.half_angle(n, rot(0.7), rot(-0.7)))
        assert abs(got - true) <= 1e-9 * true + 1e-15
        if true <= 1e-7:
            naive = float(np.arccos(np.clip(float(jnp.dot(n, h)), -1, 1)))
            assert abs(naive - true) > 10 * abs(got - true)


@pytest.mark.parametrize("alpha, tolerance", [(0.02, 0.003), (0.08, 0.03)])
def test_ward_lobe_is_normalised(alpha, tolerance):
    """Ward 1992: the lobe's directional albedo at normal view tends to ps as alpha -> 0
    (the deficit grows like alpha^2: about 2 % at alpha = 0.08)."""
    ps = 0.4
    t = np.linspace(0, np.pi / 2, 8001)[1:]
    ph = np.linspace(0, 2 * np.pi, 129)[:-1]
    tt, pp = np.meshgrid(t, ph, indexing="ij")
    wi = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1).reshape(-1, 3)
    n = jnp.array([0.0, 0.0, 1.0])
    wo = jnp.array([0.0, 0.0, 1.0])
    lobe = jax.jit(jax.vmap(lambda l: brdf.ward_specular(ps, np.log(alpha), *brdf.shading_geometry(n, l, wo))))
    integrand = np.asarray(lobe(wi)).reshape(tt.shape) * np.cos(tt) * np.sin(tt)
    albedo = np.trapezoid(integrand.mean(axis=1) * 2 * np.pi, t)
    assert ps * (1 - tolerance) < albedo <= ps


def test_torrance_sparrow_matches_paper_equation_1():
    """i = Y/C^2 {pd/pi cos(theta_d) + ps/cos(theta_v) exp(-theta_r^2 / 2 sigma^2)} (pd/pi per DESIGN)."""
    n = unit([0.0, 0.0, 1.0])
    l, v = unit([0.3, 0.1, 1.0]), unit([-0.2, 0.05, 1.0])
    pd, ps, sigma, y, c = np.array([0.3, 0.4, 0.5]), 0.7, 0.2, 2.0, 0.8
    ci, co = l @ n, v @ n
    h = unit(l + v)
    theta_r = np.arctan2(np.linalg.norm(np.cross(n, h)), n @ h)
    expected = y / c**2 * (pd / np.pi * ci + ps / co * np.exp(-theta_r**2 / (2 * sigma**2)))
    f = brdf.torrance_sparrow(jnp.array(pd), ps, np.log(sigma), *brdf.shading_geometry(n, l, v))
    got = brdf.point_light_radiance(f, y, ci, c)
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-13)
