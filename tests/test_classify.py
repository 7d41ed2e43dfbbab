"""Measurability classes against hand-computed cases."""

import numpy as np
import pytest

from data_synth.scans import Sensor, make_scan
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.reflectance.classify import (
    T_DIFF,
    T_INVALID,
    T_NONE,
    T_SPEC,
    Thresholds,
    classify,
    classify_scan,
)

from .helpers import grid_plane, plate_over_plane, sphere, unit


def expected_classes(points, normals, cam, lights, lit=None, th1=60.0, th2=20.0):
    """Independent per-sample reference (float64 arccos is fine away from 0)."""
    v = unit(cam[None, None] - points[:, None])
    l = unit(lights[None] - points[:, None])
    h = unit(v + l)
    ci, co = np.einsum("nki,ni->nk", l, normals), np.einsum("nki,ni->nk", v, normals)
    theta = np.degrees(np.arccos(np.clip(np.einsum("nki,ni->nk", h, normals), -1, 1)))
    ok = (ci > 0) & (co > 0) & (True if lit is None else lit)
    out = np.where(theta > th1, T_DIFF, np.where(theta <= th2, T_SPEC, T_NONE))
    return np.where(ok, out, T_INVALID), theta


def test_plane_with_lights_at_known_angles():
    v, f = grid_plane(0.05, 5)
    n = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    a = np.radians(70)
    cam = 2 * np.array([-np.sin(a), 0.0, np.cos(a)])
    lights = 2 * np.array([
        [-np.sin(a), 0.0, np.cos(a)],  # beside the camera: theta_r = 70 -> diffuse-only
        [np.sin(a), 0.0, np.cos(a)],  # mirror direction: theta_r = 0 -> strong specular
        [0.0, 0.0, 1.0],  # overhead: theta_r = 35 -> neither
        [0.0, 0.0, -1.0],  # below the plane -> not measurable
    ])
    m = classify(v, n, cam, lights, RayCaster(v, f))
    centre = len(v) // 2
    np.testing.assert_array_equal(m.classes[centre], [T_DIFF, T_SPEC, T_NONE, T_INVALID])
    np.testing.assert_allclose(np.degrees(m.theta_r[centre, :3]), [70, 0, 35], atol=1e-9)
    ref, _ = expected_classes(v, n, cam, lights)
    np.testing.assert_array_equal(m.classes, ref)
    assert m.seen.all()


def test_sphere_classes_follow_the_half_vector():
    v, f = sphere(0.1, 4)
    n = unit(v)
    cam = np.array([0.0, 0.0, 3.0])
    lights = np.array([[0.0, 0.0, 3.0], [0.5, 0.0, 3.0], [3.0, 0.0, 0.0]])
    m = classify(v, n, cam, lights, RayCaster(v, f))
    ref, theta = expected_classes(v, n, cam, lights)
    clear = (np.abs(theta - 60) > 0.5) & (np.abs(theta - 20) > 0.5)
    facing = np.einsum("nki,ni->nk", unit(lights[None] - v[:, None]), n)
    clear &= np.abs(facing) > 0.05  # away from the terminator, where faceting decides shadows
    np.testing.assert_array_equal(m.classes[clear], ref[clear])
    assert {T_DIFF, T_SPEC, T_NONE, T_INVALID} <= set(np.unique(m.classes).tolist())


def test_shadow_cast_by_a_second_object():
    a, h, L = 0.3, 0.5, 2.0
    v, f = plate_over_plane(a, h)
    n = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    on_plane = np.arange(len(v)) < 41 * 41
    m = classify(v, n, np.array([0.0, 1.0, 4.0]), np.array([[0.0, 0.0, L]]), RayCaster(v, f))
    edge = a / (1 - h / L)
    under = on_plane & np.all(np.abs(v[:, :2]) < edge - 1e-3, axis=1)
    # The camera at (0, 1, 4) sees under the plate only partly; wherever it does, the light cannot.
    assert np.all(m.classes[under, 0] == T_INVALID)
    clear = on_plane & np.any(np.abs(v[:, :2]) > edge + 0.2, axis=1)
    assert np.all(m.measurable[clear, 0])


def test_saturated_and_unobserved_samples_are_never_classified():
    scan, _ = make_scan("A", resolution=24, lights=[10, 25, 34], sensor=Sensor(full_scale=0.02, saturate=True))
    m = classify_scan(scan)
    saturated = np.any(scan.radiance >= scan.saturation, axis=-1)
    assert saturated.any()
    assert np.all(m.classes[saturated] == T_INVALID)
    assert np.all(m.classes[~scan.valid] == T_INVALID)
    # Planning mode ignores the images.
    plan = classify_scan(scan, use_observations=False)
    assert plan.measurable.sum() > m.measurable.sum()


def test_classes_never_hold_shadowed_or_back_facing_samples():
    scan, _ = make_scan("B", resolution=32)
    caster = RayCaster(scan.vertices, scan.faces)
    m = classify_scan(scan, caster=caster, use_observations=False)
    rows, cols = np.nonzero(m.classes != T_INVALID)
    lights = scan.light_positions()[rows, cols]
    cams = scan.camera_positions()[rows, cols]
    p, nrm = scan.vertices[rows], scan.normals[rows]
    assert np.all(np.einsum("ni,ni->n", lights - p, nrm) > 0)
    assert np.all(np.einsum("ni,ni->n", cams - p, nrm) > 0)
    assert not caster.segments_blocked(p, caster.offset_normals[rows], lights).any()
    assert not caster.segments_blocked(p, caster.offset_normals[rows], cams).any()
    invalid_but_facing = (m.classes == T_INVALID) & np.asarray(m.measurable)
    assert not invalid_but_facing.any()


def test_thresholds_are_validated():
    with pytest.raises(ValueError, match="specular_deg"):
        Thresholds(diffuse_deg=20, specular_deg=30)
