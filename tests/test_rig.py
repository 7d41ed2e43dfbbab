"""Rig geometry: the paper's light rack, the rotating-head scanner and pinhole cameras."""

import numpy as np
import pytest

from jaxrefl.geometry import rig

from .helpers import unit


def test_paper_rack_is_60_positions_at_5cm():
    rack = rig.paper_light_rack()
    assert rack.shape == (60, 2)
    np.testing.assert_allclose(rack.mean(0), 0.0, atol=1e-15)
    xs, ys = np.unique(rack[:, 0]), np.unique(rack[:, 1])
    np.testing.assert_allclose(np.diff(xs), 0.05)
    np.testing.assert_allclose(np.diff(ys), 0.05)
    assert len(xs) * len(ys) == 60
    assert np.min(np.linalg.norm(rack, axis=1)) > 0  # no light on the optical axis
    with pytest.raises(ValueError, match="spacing"):
        rig.paper_light_rack(spacing=0)


def test_scanner_faces_each_point_and_carries_its_rack():
    sc = rig.CylindricalScanner(radius=0.6, height=0.1)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (50, 3)) + [0, 0.1, 0]
    phi = sc.head_angle(pts)
    cam = sc.camera_positions(pts)
    np.testing.assert_allclose(np.hypot(cam[:, 0], cam[:, 2]), 0.6)
    np.testing.assert_allclose(cam[:, 1], 0.1)
    # The camera sits on the ray from the axis through the point's azimuth.
    np.testing.assert_allclose(np.arctan2(cam[:, 0], cam[:, 2]), phi, atol=1e-12)
    lights = sc.light_positions(pts)
    assert lights.shape == (50, 60, 3)
    # The rack lies in the plane through the camera perpendicular to its (horizontal) axis,
    # and the offsets are preserved: |light - cam| equals |rack offset|.
    forward = -unit(cam * [1, 0, 1])
    offsets = lights - cam[:, None, :]
    np.testing.assert_allclose(np.einsum("nmi,ni->nm", offsets, forward), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=-1),
                               np.broadcast_to(np.linalg.norm(sc.rack, axis=1), (50, 60)), atol=1e-12)
    np.testing.assert_allclose(offsets[..., 1], np.broadcast_to(sc.rack[:, 1], (50, 60)), atol=1e-12)


def test_scanner_point_in_front_is_seen_head_on():
    sc = rig.CylindricalScanner(radius=0.6, height=0.0)
    p = np.array([[0.0, 0.0, 0.1]])
    n = np.array([[0.0, 0.0, 1.0]])
    g = rig.observation_geometry(p, n, sc.camera_positions(p)[:, None, :], sc.light_positions(p))
    assert float(g.cos_o[0, 0]) == pytest.approx(1.0)
    assert float(g.camera_distance[0, 0]) == pytest.approx(0.5)
    # Light offset (dx, dy) at 0.5 m: cos_i = 0.5 / sqrt(0.25 + dx^2 + dy^2).
    r2 = np.sum(sc.rack**2, axis=1)
    np.testing.assert_allclose(np.asarray(g.cos_i[0]), 0.5 / np.sqrt(0.25 + r2), rtol=1e-12)


def test_observation_geometry_shapes_and_units():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(7, 3))
    nrm = unit(rng.normal(size=(7, 3)))
    lights = rng.normal(size=(4, 3)) * 3
    for cam in (np.array([0.0, 0, 5]), rng.normal(size=(4, 3)) * 5, rng.normal(size=(7, 1, 3)) * 5,
                rng.normal(size=(7, 4, 3)) * 5):
        g = rig.observation_geometry(pts, nrm, cam, lights)
        assert g.to_light.shape == (7, 4, 3) and g.cos_i.shape == (7, 4)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(g.to_light), axis=-1), 1.0)
        np.testing.assert_allclose(np.asarray(g.light_distance),
                                   np.linalg.norm(lights[None] - pts[:, None], axis=-1))
        cam_full = np.broadcast_to(cam.reshape((1,) * (3 - cam.ndim) + cam.shape), (7, 4, 3))
        np.testing.assert_allclose(np.asarray(g.cos_o),
                                   np.einsum("nmi,ni->nm", unit(cam_full - pts[:, None]), nrm))
        for a, b in zip(rig.observation_angles(pts, nrm, cam, lights), (g.cos_i, g.cos_o, g.theta_r)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_pinhole_opencv_convention():
    cam = rig.PinholeCamera.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], fov_deg=40, width=64, height=48)
    np.testing.assert_allclose(cam.center, [0, 0, 2])
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [31.5, 23.5])  # the principal point
    assert depth[0] == pytest.approx(2.0)
    assert uv[1, 1] < uv[0, 1]  # world up is image up: smaller row index
    # Rays through pixel centres project back onto those pixels.
    o, d = cam.pixel_rays()
    uv2, _ = cam.project(o + 1.7 * d)
    v, u = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv2, np.stack([u.ravel(), v.ravel()], 1), atol=1e-9)


def test_pinhole_distortion_matches_opencv_model():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cam = rig.PinholeCamera(K=K, R=np.eye(3), t=np.zeros(3), width=640, height=480,
                            dist=np.array([0.1, -0.05, 0.001, 0.002, 0.01]))
    x, y = 0.2, -0.1
    r2 = x * x + y * y
    radial = 1 + 0.1 * r2 - 0.05 * r2**2 + 0.01 * r2**3
    xd = x * radial + 2 * 0.001 * x * y + 0.002 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * 0.002 * x * y
    uv, _ = cam.project(np.array([[x * 3, y * 3, 3.0]]))
    np.testing.assert_allclose(uv[0], [500 * xd + 320, 500 * yd + 240], rtol=1e-12)


def test_pinhole_rejects_bad_calibration():
    with pytest.raises(ValueError, match="R"):
        rig.PinholeCamera(K=np.eye(3), R=np.diag([1.0, 1.0, -1.0]), t=np.zeros(3), width=4, height=4)
    with pytest.raises(ValueError, match="K"):
        rig.PinholeCamera(K=np.full((3, 3), np.nan), R=np.eye(3), t=np.zeros(3), width=4, height=4)
    rack = rig.PinholeCamera.look_at([0, 0, 1.0], [0, 0, 0.0]).rack_positions(rig.paper_light_rack())
    np.testing.assert_allclose(rack[:, 2], 1.0)  # the rack lies in the camera's plane
