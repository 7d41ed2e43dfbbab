"""The independent path tracer: furnace, convex objects, convergence, agreement of BRDFs."""

import jax
import numpy as np
import pytest

from data_synth.objects import fold_coordinate, make_object
from data_synth.pathtrace import Material, PathTracer, brdf_numpy
from data_synth.validation import convergence, furnace
from jaxrefl.reflectance import brdf

from .helpers import grid_plane, sphere, unit


@pytest.mark.parametrize("model", list(brdf.MODELS))
def test_numpy_brdf_agrees_with_jaxrefl(model):
    """The path tracer's own BRDF code is an independent re-implementation of jaxrefl.reflectance.brdf."""
    rng = np.random.default_rng(0)
    p = 5000
    n = unit(rng.normal(size=(p, 3)))
    wi, wo = unit(rng.normal(size=(p, 3))), unit(rng.normal(size=(p, 3)))
    pd, ps, rough = rng.uniform(0, 1, (p, 3)), rng.uniform(0, 1, p), np.exp(rng.uniform(-4, 0, p))
    ours = brdf_numpy(model, pd, ps, rough, n, wi, wo)
    f, _ = brdf.MODELS[model]
    ref = jax.vmap(lambda a, b, c, nn, l, v: f(a, b, jax.numpy.log(c), *brdf.shading_geometry(nn, l, v)))(
        pd, ps, rough, n, wi, wo)
    valid = (np.sum(n * wi, 1) > 1e-3) & (np.sum(n * wo, 1) > 1e-3)
    assert valid.sum() > 500
    np.testing.assert_allclose(ours[valid], np.asarray(ref)[valid], rtol=1e-9)
    np.testing.assert_array_equal(ours[~valid & ((np.sum(n * wi, 1) <= 0) | (np.sum(n * wo, 1) <= 0))], 0)


@pytest.mark.parametrize("rho", [0.5, 0.8])
def test_furnace_converges_to_closed_form(rho):
    """Closed sphere of albedo rho, light at the centre: L = rho/pi * E / (1 - rho)."""
    r = furnace(rho, samples=128, stride=8, seed=1)
    # Monte Carlo error, plus < 0.3 % for the icosphere's facets and the depth cap.
    assert abs(r["mean"] - r["expected"]) < 4 * r["stderr"] + 3e-3 * r["expected"]
    assert r["stderr"] < 0.01 * r["expected"]


def test_convex_object_has_no_interreflection():
    """On a sphere seen from outside every indirect path escapes: GI equals direct exactly."""
    v, f = sphere(0.2, 3)
    n = len(v)
    tracer = PathTracer(v, f, unit(v), Material(np.full((n, 3), 0.7), np.full(n, 0.3), np.full(n, 0.1)))
    cam = np.broadcast_to([0.0, 0.0, 1.0], (n, 2, 3)).copy()
    light = np.broadcast_to([[0.3, 0.4, 1.0], [-0.5, 0.0, 0.8]], (n, 2, 3)).copy()
    gi, se = tracer.render(cam, light, np.ones(2), samples=16, progress=False)
    direct, _ = tracer.render(cam, light, np.ones(2), samples=0, progress=False)
    np.testing.assert_array_equal(gi, direct)
    assert np.all(se == 0)


def test_direct_light_on_a_plane_is_exact():
    v, f = grid_plane(0.5, 9)
    n = len(v)
    pd = np.array([0.3, 0.6, 0.9])
    tracer = PathTracer(v, f, np.tile([0.0, 0, 1], (n, 1)), Material(np.tile(pd, (n, 1)), np.zeros(n),
                                                                        np.full(n, 0.2)))
    light = np.array([0.2, 0.1, 0.8])
    out, _ = tracer.render(np.broadcast_to([0.0, 0, 2], (n, 1, 3)).copy(),
                           np.broadcast_to(light, (n, 1, 3)).copy(), np.array([1.5]), samples=8,
                           progress=False)
    d = light - v
    r = np.linalg.norm(d, axis=1)
    np.testing.assert_allclose(out[:, 0], pd * (1.5 * d[:, 2] / r**3)[:, None] / np.pi, rtol=1e-12)


def _fold_setup(resolution=32, setup="glossy"):
    obj = make_object("E", resolution, setup)
    tracer = PathTracer(obj.vertices, obj.faces, obj.normals, Material(obj.pd, obj.ps, obj.roughness))
    pick = np.flatnonzero(np.abs(fold_coordinate(obj.vertices)) < 0.04)[::3]
    cam = np.broadcast_to([0.0, 0.0, 0.7], (len(pick), 1, 3)).copy()
    light = np.broadcast_to([0.1, 0.1, 0.7], (len(pick), 1, 3)).copy()
    return tracer, pick, cam, light


def test_deterministic_by_seed():
    tracer, pick, cam, light = _fold_setup()
    a, _ = tracer.render(cam, light, np.ones(1), samples=8, seed=5, points=pick, progress=False)
    b, _ = tracer.render(cam, light, np.ones(1), samples=8, seed=5, points=pick, progress=False)
    c, _ = tracer.render(cam, light, np.ones(1), samples=8, seed=6, points=pick, progress=False)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_error_falls_as_inverse_square_root_of_samples():
    tracer, pick, cam, light = _fold_setup()
    conv = convergence(tracer, pick, cam, light, np.ones(1), sample_counts=(4, 16, 64),
                       reference_samples=1024, seed=0)
    errors = conv["rms_relative_error"]
    assert errors[0] > errors[1] > errors[2]
    assert -0.7 < conv["slope"] < -0.35


def test_fold_receives_interreflected_light_everywhere():
    """Every vertex near the fold, the fold's own vertices included, gets indirect light."""
    tracer, pick, cam, light = _fold_setup(setup="diffuse")
    gi, se = tracer.render(cam, light, np.ones(1), samples=64, points=pick, progress=False)
    direct, _ = tracer.render(cam, light, np.ones(1), samples=0, points=pick, progress=False)
    gain = (gi - direct)[:, 0, 0] / direct[:, 0, 0]
    assert np.all(gain > 0.1)


@pytest.mark.parametrize("model", list(brdf.MODELS))
def test_glossy_single_bounce_matches_quadrature(model):
    """One bounce between the glossy plates of Object E: the path tracer's estimate (lobe +
    cosine mixture sampling) equals a deterministic quadrature over plate II."""
    obj = make_object("E", 32, "glossy")
    tracer = PathTracer(obj.vertices, obj.faces, obj.normals, Material(obj.pd, obj.ps, obj.roughness, model),
                        max_depth=1)
    cam, light = np.array([0.0, 0.0, 0.7]), np.array([0.05, -0.1, 0.6])
    fold = fold_coordinate(obj.vertices)
    pick = np.flatnonzero((fold > 0.02) & (fold < 0.09) & (np.abs(obj.vertices[:, 0]) < 0.03))[:4]
    gi, se = tracer.render(np.broadcast_to(cam, (len(pick), 1, 3)).copy(),
                           np.broadcast_to(light, (len(pick), 1, 3)).copy(), np.ones(1), samples=8192,
                           points=pick, progress=False, seed=3)
    direct, _ = tracer.render(np.broadcast_to(cam, (len(pick), 1, 3)).copy(),
                              np.broadcast_to(light, (len(pick), 1, 3)).copy(), np.ones(1), samples=0,
                              points=pick, progress=False)
    mc = (gi - direct)[:, 0, 0]

    # Quadrature over plate II (midpoint rule, 0.4 mm cells).
    k = 500
    u = (np.arange(k) + 0.5) / k
    xs, ss = np.meshgrid(-0.1 + 0.2 * u, 0.2 * u, indexing="ij")
    s45 = np.sqrt(0.5)
    y = np.stack([xs.ravel(), -s45 * ss.ravel(), s45 * ss.ravel()], 1)
    n_y = np.tile([0.0, s45, s45], (len(y), 1))
    area = (0.2 / k) ** 2
    p = len(y)
    pd, ps, rough = np.tile(obj.pd[0], (p, 1)), np.full(p, obj.ps[0]), np.full(p, obj.roughness[0])
    to_light = light - y
    d_l = np.linalg.norm(to_light, axis=1)
    expected = []
    for i in pick:
        x, n_x = obj.vertices[i], obj.normals[i]
        to_x = x - y
        r = np.linalg.norm(to_x, axis=1)
        w_yx = to_x / r[:, None]
        l_y = brdf_numpy(model, pd, ps, rough, n_y, to_light / d_l[:, None], w_yx)[:, 0] \
            * np.maximum(np.sum(n_y * to_light, 1) / d_l, 0) / d_l**2
        wo_x = np.tile(unit(cam - x), (p, 1))
        f_x = brdf_numpy(model, pd, ps, rough, np.tile(n_x, (p, 1)), -w_yx, wo_x)[:, 0]
        geom = np.maximum(np.sum(n_x * -w_yx, 1), 0) * np.maximum(np.sum(n_y * w_yx, 1), 0) / r**2
        expected.append(np.sum(f_x * l_y * geom) * area)
    expected = np.array(expected)
    assert np.all(expected > 0)
    assert np.all(se[:, 0, 0] < 0.03 * expected)  # the comparison is sharp
    np.testing.assert_array_less(np.abs(mc - expected), 4 * se[:, 0, 0] + 0.01 * expected)
