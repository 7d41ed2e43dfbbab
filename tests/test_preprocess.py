"""Range-data preprocessing (§2.1): outliers, adaptive quadratic normals, meshing."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from data_synth.rangescan import make_range_image
from jaxrefl.scan.preprocess import (
    RangeImage,
    angular_error_deg,
    face_averaged_normals,
    mesh_quadratic_normals,
    quadratic_fit,
    range_image_to_mesh,
    remove_outliers,
)

from .helpers import sphere, unit


def grid(width=256, height=96, y_top=0.06, y_bottom=-0.06, span=2 * np.pi):
    theta = span * (np.arange(width) + 0.5) / width
    y = y_top - (np.arange(height) + 0.5) / height * (y_top - y_bottom)
    return theta, y


def cylinder_image(radius=0.05, **kw):
    theta, y = grid(**kw)
    r = np.full((len(y), len(theta)), radius)
    normals = np.stack(np.broadcast_arrays(np.sin(theta), 0.0 * y[:, None], np.cos(theta)), -1)
    return RangeImage(r, theta, y), normals


def sphere_image(radius=0.05, centre=(0.0, 0.0, 0.0), **kw):
    """Range image of a sphere (rays from outside toward the axis, first hit before
    the axis) and its exact normals; NaN where the ray misses."""
    theta, y = grid(**kw)
    tt, yy = np.meshgrid(theta, y)
    c = np.asarray(centre, dtype=np.float64)
    b = c[0] * np.sin(tt) + c[2] * np.cos(tt)
    disc = b * b - (c[0] ** 2 + (yy - c[1]) ** 2 + c[2] ** 2 - radius**2)
    with np.errstate(invalid="ignore"):
        r = b + np.sqrt(disc)
    r = np.where((disc > 0) & (r > 0), r, np.nan)
    p = np.stack([r * np.sin(tt), yy, r * np.cos(tt)], -1)
    return RangeImage(r, theta, y), (p - c) / radius


def add_spikes(img, fraction, scale, rng):
    """Replace `fraction` of the returns by `r +- scale`; returns (image, spike mask)."""
    idx = np.flatnonzero(img.valid)
    pick = rng.choice(idx, size=int(round(fraction * len(idx))), replace=False)
    r = img.r.copy()
    r.ravel()[pick] += scale * rng.choice([-1.0, 1.0], size=len(pick))
    spikes = np.zeros(img.shape, dtype=bool)
    spikes.ravel()[pick] = True
    return img.with_r(np.maximum(r, 0.0)), spikes


# -- RangeImage ----------------------------------------------------------------------


def test_points_and_full_circle():
    img, normals = cylinder_image(0.05, width=64, height=8)
    p = img.points()
    assert p.shape == (8, 64, 3)
    np.testing.assert_allclose(np.hypot(p[..., 0], p[..., 2]), 0.05)
    np.testing.assert_allclose(p[..., 1], np.broadcast_to(img.y[:, None], (8, 64)))
    # Column angle is measured from +z toward +x.
    np.testing.assert_allclose(np.arctan2(p[0, :, 0], p[0, :, 2]) % (2 * np.pi), img.theta)
    assert img.full_circle
    half, _ = cylinder_image(0.05, width=64, height=8, span=np.pi)
    assert not half.full_circle
    r = img.r.copy()
    r[0, 0] = np.nan
    assert np.isnan(img.with_r(r).points()[0, 0]).all()


@pytest.mark.parametrize("field, kwargs", [
    ("r", dict(r=np.ones(5), theta=np.arange(5.0), y=np.array([1.0]))),
    ("theta", dict(r=np.ones((3, 5)), theta=np.arange(4.0), y=np.array([3.0, 2.0, 1.0]))),
    ("y", dict(r=np.ones((3, 5)), theta=np.arange(5.0), y=np.array([1.0, 2.0]))),
    ("y", dict(r=np.ones((3, 5)), theta=np.arange(5.0), y=np.array([1.0, 2.0, 3.0]))),
    ("theta", dict(r=np.ones((3, 5)), theta=np.array([0.0, 2.0, 1.0, 3.0, 4.0]),
                   y=np.array([3.0, 2.0, 1.0]))),
    ("theta", dict(r=np.ones((3, 5)), theta=np.linspace(0, 7, 5), y=np.array([3.0, 2.0, 1.0]))),
    ("r", dict(r=-np.ones((3, 5)), theta=np.arange(5.0), y=np.array([3.0, 2.0, 1.0]))),
    ("r", dict(r=np.full((3, 5), np.inf), theta=np.arange(5.0), y=np.array([3.0, 2.0, 1.0]))),
    ("r", dict(r=[["a"]], theta=np.arange(1.0), y=np.array([1.0]))),
])
def test_range_image_rejects_bad_fields(field, kwargs):
    with pytest.raises(ValueError, match=rf"RangeImage\.{field}"):
        RangeImage(**kwargs)


def test_functions_reject_bad_arguments():
    img, _ = cylinder_image(0.05, width=32, height=12)
    v, f = sphere(0.05, 2)
    for call, name in [
        (lambda: remove_outliers(img, window=4), "window"),
        (lambda: remove_outliers(img, k=-1.0), "k"),
        (lambda: remove_outliers(img, min_scale=np.nan), "min_scale"),
        (lambda: remove_outliers(img.r), "img"),
        (lambda: quadratic_fit(img, window=1), "window"),
        (lambda: quadratic_fit(img, select="smallest"), "select"),
        (lambda: quadratic_fit(img, min_samples=5), "min_samples"),
        (lambda: range_image_to_mesh(img, max_jump=0.0), "max_jump"),
        (lambda: mesh_quadratic_normals(v[:, :2], f), "vertices"),
        (lambda: mesh_quadratic_normals(v, f + len(v)), "faces"),
        (lambda: mesh_quadratic_normals(v, f, k=3), "k"),
        (lambda: mesh_quadratic_normals(v, f, outlier_k=0.0), "outlier_k"),
        (lambda: face_averaged_normals(v, f.astype(float)), "faces"),
        (lambda: make_range_image("A", noise=-1.0), "noise"),
        (lambda: make_range_image("A", width=2), "width"),
    ]:
        with pytest.raises(ValueError, match=name):
            call()


# -- quadratic normals -----------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6), st.booleans())
def test_quadratic_surface_is_recovered_exactly(c, adaptive):
    """r = quadratic in (theta, y) is fitted exactly, at every pixel and both
    with and without adaptive windows; the normal is P_theta x P_y."""
    theta = np.linspace(0.2, 1.4, 17)
    y = np.linspace(0.03, -0.03, 13)
    tt, yy = np.meshgrid(theta - 0.8, y / 0.05)
    quad = c[0] + c[1] * tt + c[2] * yy + c[3] * tt**2 + c[4] * tt * yy + c[5] * yy**2
    r = 0.06 + 0.01 * quad / 6
    r_th = 0.01 * (c[1] + 2 * c[3] * tt + c[4] * yy) / 6
    r_y = 0.01 * (c[2] + c[4] * tt + 2 * c[5] * yy) / 6 / 0.05
    img = RangeImage(r, theta, y)
    p, n, valid, res = quadratic_fit(img, adaptive=adaptive)
    assert valid.all()
    np.testing.assert_allclose(p, img.points(), atol=1e-12)
    s, co = np.sin(theta), np.cos(theta)
    expect = unit(np.stack([r * s - r_th * co, -r * r_y, r * co + r_th * s], -1))
    np.testing.assert_allclose(n, expect, atol=1e-9)
    assert np.all(res < 1e-12)


@pytest.mark.parametrize("adaptive", [False, True])
def test_cylinder_and_sphere_normals_noise_free(adaptive):
    img, truth = cylinder_image(0.05)
    p, n, valid, _ = quadratic_fit(img, adaptive=adaptive)
    assert valid.all()  # the seam wraps: no border in theta, top and bottom fit one-sided
    assert angular_error_deg(n, truth).max() < 1e-6
    # Off-axis sphere (the axis inside it): r depends on theta and y, all columns wrap.
    c = np.array([0.01, 0.0, 0.01])
    img, truth = sphere_image(0.05, centre=c, width=512, height=128, y_top=0.055, y_bottom=-0.055)
    p, n, valid, _ = quadratic_fit(img, adaptive=adaptive)
    assert valid.sum() > 0.95 * img.valid.sum()
    assert np.isfinite(n[valid]).all() and np.isnan(n[~valid]).all()
    assert np.all(np.sum(n[valid] * truth[valid], -1) > 0)
    # Away from grazing incidence (near the poles r(theta, y) is far from quadratic).
    ray = -unit(img.points() * np.array([1.0, 0.0, 1.0]))
    facing = valid & (-np.sum(truth * ray, -1) > np.cos(np.radians(60)))
    assert facing.sum() > 0.7 * img.valid.sum()
    assert angular_error_deg(n[facing], truth[facing]).max() < 0.5
    np.testing.assert_allclose(np.linalg.norm(p[facing] - c, axis=-1), 0.05, atol=1e-5)


def test_normals_point_outward_and_noise_is_reduced():
    rng = np.random.default_rng(3)
    img, truth = sphere_image(0.05, width=256, height=80, y_top=0.04, y_bottom=-0.04)
    noisy = img.with_r(img.r + rng.normal(0, 2e-4, img.shape))
    p, n, valid, res = quadratic_fit(noisy)
    assert valid.all()
    assert np.all(np.sum(n * truth, -1) > 0.9)
    # The fitted points lie closer to the sphere than the samples do.
    spread_fit = np.std(np.linalg.norm(p, axis=-1) - 0.05)
    assert spread_fit < 0.5 * np.std(np.linalg.norm(noisy.points(), axis=-1) - 0.05)
    assert 1e-4 < np.median(res) < 3e-4  # RMS residual ~ the noise


def test_adaptive_windows_avoid_a_depth_discontinuity():
    """Two coaxial cylinders (r = 5 cm above y = 0, 3 cm below): the normal is
    radial everywhere; centred windows straddle the step, adaptive ones do not."""
    rng = np.random.default_rng(0)
    theta, y = grid(width=256, height=60)
    r = np.where(y[:, None] > 0, 0.05, 0.03) + 0.0 * theta
    truth = np.stack(np.broadcast_arrays(np.sin(theta), 0.0 * y[:, None], np.cos(theta)), -1)
    near = np.abs(np.arange(60) - 29.5)[:, None].repeat(256, 1) < 3  # three rows each side
    for noise in (0.0, 5e-5):
        img = RangeImage(r + rng.normal(0, noise, r.shape), theta, y)
        _, n_fix, v_fix, _ = quadratic_fit(img, adaptive=False)
        _, n_ad, v_ad, _ = quadratic_fit(img, adaptive=True)
        assert v_fix.all() and v_ad.all()
        e_fix = angular_error_deg(n_fix, truth)[near]
        e_ad = angular_error_deg(n_ad, truth)[near]
        assert np.mean(e_ad) < 0.2 * np.mean(e_fix)
        assert np.median(e_ad) < (1e-6 if noise == 0 else 2.0)
    # Yokoya & Levine's rule as written (smallest residual) also avoids the step.
    img = RangeImage(r, theta, y)
    _, n_res, _, _ = quadratic_fit(img, select="residual")
    assert angular_error_deg(n_res, truth).max() < 1e-6


# -- outliers -------------------------------------------------------------------------


def test_injected_spikes_are_removed():
    rng = np.random.default_rng(1)
    img, _ = sphere_image(0.05, centre=(0.01, 0.0, 0.0), width=360, height=120)
    noisy = img.with_r(np.round((img.r + rng.normal(0, 3e-4, img.shape)) / 1e-4) * 1e-4)
    spiked, spikes = add_spikes(noisy, 0.005, 0.01, rng)
    cleaned, removed = remove_outliers(spiked)
    assert removed.shape == img.shape and not removed[~img.valid].any()
    assert (removed & spikes).sum() >= 0.95 * spikes.sum()
    assert (removed & ~spikes).sum() < 0.01 * img.valid.sum()
    assert np.isnan(cleaned.r[removed]).all()
    np.testing.assert_array_equal(cleaned.r[~removed & img.valid], spiked.r[~removed & img.valid])


def test_no_outliers_in_clean_data():
    img, _ = sphere_image(0.05, width=256, height=80)
    _, removed = remove_outliers(img)
    assert not removed.any()
    # Returns right at a depth step are not outliers either.
    theta, y = grid(width=128, height=40)
    r = np.where(y[:, None] > 0, 0.05, 0.03) + 0.0 * theta
    _, removed = remove_outliers(RangeImage(r, theta, y))
    assert not removed.any()


# -- meshes ---------------------------------------------------------------------------


def test_mesh_of_full_circle_is_closed_in_theta_and_outward():
    img, _ = sphere_image(0.05, centre=(0.0, 0.0, 0.0), width=96, height=40,
                          y_top=0.045, y_bottom=-0.045)
    v, f, pixel = range_image_to_mesh(img)
    H, W = img.shape
    assert len(v) == H * W and len(f) == 2 * (H - 1) * W  # the seam quad column is there
    np.testing.assert_allclose(v, img.points()[pixel[:, 0], pixel[:, 1]])
    m = trimesh.Trimesh(v, f, process=False)
    edges, counts = np.unique(m.edges_sorted, axis=0, return_counts=True)
    boundary = np.unique(edges[counts == 1])
    assert np.all(counts <= 2)
    # Only the top and bottom rows are open.
    assert set(pixel[boundary, 0]) == {0, H - 1}
    centroid = v[f].mean(1)
    assert np.all(np.sum(m.face_normals * centroid, -1) > 0)  # outward (away from the axis)
    fn = face_averaged_normals(v, f)
    np.testing.assert_allclose(np.linalg.norm(fn, axis=1), 1.0)
    assert angular_error_deg(fn, unit(v)).max() < 5.0


def test_mesh_partial_circle_and_depth_jump():
    theta, y = grid(width=64, height=20, span=np.pi)
    r = np.where(y[:, None] > 0, 0.05, 0.03) + 0.0 * theta
    r[3, 5] = np.nan
    img = RangeImage(r, theta, y)
    v, f, pixel = range_image_to_mesh(img)
    H, W = img.shape
    # No wrap (half circle), no quads across the step, none touching the hole.
    assert len(f) == 2 * ((H - 2) * (W - 1) - 4)
    rows = pixel[f][..., 0]
    assert not np.any((rows.min(1) < 10) & (rows.max(1) >= 10))
    assert not np.any((pixel[:, 0] == 3) & (pixel[:, 1] == 5))
    v2, f2, _ = range_image_to_mesh(img, max_jump=0.05)  # a large max_jump bridges the step
    assert len(f2) == len(f) + 2 * (W - 1)


def test_mesh_quadratic_normals_beat_face_averaged_on_noisy_sphere():
    rng = np.random.default_rng(2)
    v, f = sphere(0.05, 4)
    truth = unit(v)
    edge = np.mean(np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1))
    noisy = v + truth * rng.normal(0, 0.15 * edge, (len(v), 1))
    spikes = rng.random(len(v)) < 0.01
    noisy[spikes] += truth[spikes] * 5 * edge * rng.choice([-1.0, 1.0], (spikes.sum(), 1))
    clean = ~spikes
    e_face = angular_error_deg(face_averaged_normals(noisy, f), truth)
    dv, n, outlier = mesh_quadratic_normals(noisy, f)
    e_quad = angular_error_deg(n, truth)
    assert np.median(e_quad[clean]) < 0.5 * np.median(e_face[clean])
    assert np.percentile(e_quad, 90) < 0.5 * np.percentile(e_face, 90)
    assert (outlier & spikes).sum() >= 0.95 * spikes.sum()
    assert (outlier & ~spikes).sum() < 0.01 * len(v)
    # Vertices move onto the fitted surface, spikes included.
    err_before = np.abs(np.linalg.norm(noisy, axis=1) - 0.05)
    err_after = np.abs(np.linalg.norm(dv, axis=1) - 0.05)
    assert np.median(err_after) < 0.5 * np.median(err_before)
    assert np.max(err_after[spikes]) < 2 * edge
    assert np.isfinite(dv).all() and np.allclose(np.linalg.norm(n, axis=1), 1.0)
    # Noise-free: the fit is near exact and nothing is an outlier.
    dv0, n0, out0 = mesh_quadratic_normals(v, f, adaptive=False)
    assert not out0.any() and angular_error_deg(n0, truth).max() < 0.1


# -- the key requirement: Object A ----------------------------------------------------


@pytest.fixture(scope="module")
def scan_a():
    return make_range_image("A")


def test_make_range_image_is_deterministic_and_consistent(scan_a):
    img, tp, tn, hit = scan_a
    assert img.full_circle and img.shape[1] == 512
    np.testing.assert_array_equal(hit, img.valid)
    assert np.isnan(tp[~hit]).all() and np.isnan(tn[~hit]).all()
    np.testing.assert_allclose(np.linalg.norm(tn[hit], axis=-1), 1.0)
    # Truth sits on the rays: the same theta and y as its pixel.
    np.testing.assert_allclose(np.arctan2(tp[hit][:, 0], tp[hit][:, 2]) % (2 * np.pi),
                               np.broadcast_to(img.theta, img.shape)[hit], atol=1e-9)
    err = img.r[hit] - np.hypot(tp[hit][:, 0], tp[hit][:, 2])
    spikes = np.abs(err) > 0.005
    assert abs(spikes.mean() - 0.002) < 0.0005
    assert 2.5e-4 < np.std(err[~spikes]) < 3.5e-4  # noise 0.3 mm (+ quantisation)
    np.testing.assert_allclose(img.r[hit] / 1e-4, np.round(img.r[hit] / 1e-4), atol=1e-6)
    def small(seed):
        return make_range_image("A", width=64, resolution=32, seed=seed)[0].r

    np.testing.assert_array_equal(small(5), small(5))
    assert not np.array_equal(small(5), small(6), equal_nan=True)


def test_quadratic_normals_beat_face_averaged_on_object_a(scan_a):
    img, tp, tn, hit = scan_a
    spikes = hit & (np.abs(img.r - np.hypot(tp[..., 0], tp[..., 2])) > 0.005)
    cleaned, removed = remove_outliers(img)
    assert (removed & spikes).sum() >= 0.95 * spikes.sum()
    assert (removed & ~spikes).sum() < 0.01 * hit.sum()
    _, n_quad, valid, _ = quadratic_fit(cleaned)
    v, f, pixel = range_image_to_mesh(cleaned)
    n_face = np.full(img.shape + (3,), np.nan)
    n_face[pixel[:, 0], pixel[:, 1]] = face_averaged_normals(v, f)
    same = valid & np.isfinite(n_face).all(-1) & hit
    assert same.sum() > 0.9 * hit.sum()
    e_quad = np.median(angular_error_deg(n_quad[same], tn[same]))
    e_face = np.median(angular_error_deg(n_face[same], tn[same]))
    assert e_quad * 2 <= e_face, (e_quad, e_face)
