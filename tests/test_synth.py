"""Synthetic scans: rig placement, observation masks, truth fields, sensor model, determinism."""

import numpy as np
import pytest

from data_synth.scans import Sensor, apply_sensor, make_scan
from jaxrefl.geometry import rig


def test_scanner_scan_is_consistent_with_rig_geometry():
    scan, report = make_scan("C", resolution=24, lights=[0, 24, 35, 59])
    assert scan.light_pos.shape == (scan.n_points, 4, 3)  # lights ride the scanner head
    assert scan.cam_pos.shape == (scan.n_points, 1, 3)
    g = rig.observation_geometry(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos)
    # Observed only where the camera faces the point; unlit (cos_i <= 0) observations are black.
    assert not np.any(scan.valid & (np.asarray(g.cos_o) <= 0))
    dark = scan.valid & (np.asarray(g.cos_i) <= 0)
    assert np.all(scan.radiance[dark] == 0)
    assert 0.5 < report["valid_fraction"] < 1.0
    assert scan.true_sigma is not None and scan.true_alpha is None
    assert scan.meta["rig"]["type"] == "cylindrical-scanner" and scan.meta["light_indices"] == [0, 24, 35, 59]


def test_direct_scan_matches_local_model():
    """Direct-only radiance = BRDF x Y cos / r^2 wherever the light is unshadowed."""
    import jax

    from jaxrefl.reflectance import brdf

    scan, _ = make_scan("A", resolution=24, lights=[5, 30], intensity=2.0)
    g = rig.observation_geometry(scan.vertices, scan.normals, scan.cam_pos, scan.light_pos)
    f = jax.vmap(jax.vmap(brdf.torrance_sparrow, in_axes=(None, None, None, 0, 0, 0)))(
        scan.true_pd, scan.true_ps, np.log(scan.true_sigma), g.cos_i, g.cos_o, g.theta_r)
    model = np.asarray(brdf.point_light_radiance(f, 2.0, g.cos_i, g.light_distance))
    lit = scan.valid & (scan.radiance.sum(-1) > 0)
    np.testing.assert_allclose(scan.radiance[lit], model[lit], rtol=1e-5)  # float32 storage
    shadowed = scan.valid & (np.asarray(g.cos_i) > 0.1) & (scan.radiance.sum(-1) == 0)
    assert shadowed.sum() > 0  # the beak and legs cast shadows


def test_pinhole_scan_and_ward_truth():
    scan, _ = make_scan("E", resolution=24, setup="glossy", lights=[3, 4], model="ward")
    assert scan.cam_pos.shape == (3,) and scan.light_pos.shape == (2, 3)
    assert scan.true_alpha is not None and scan.true_sigma is None
    assert scan.valid.all()


def test_global_illumination_adds_light_and_is_deterministic():
    direct, _ = make_scan("E", resolution=24, setup="diffuse", lights=[24])
    gi, report = make_scan("E", resolution=24, setup="diffuse", lights=[24], global_illumination=True,
                           samples=16, seed=2)
    gi2, _ = make_scan("E", resolution=24, setup="diffuse", lights=[24], global_illumination=True,
                       samples=16, seed=2)
    np.testing.assert_array_equal(gi.radiance, gi2.radiance)
    assert np.all(gi.radiance >= direct.radiance * (1 - 1e-6))
    assert gi.radiance.mean() > 1.05 * direct.radiance.mean()
    assert 0 < report["mc_relative_stderr_median"] < 0.2


def test_sensor_noise_quantisation_and_saturation():
    rng = np.random.default_rng(0)
    clean = np.full((2000, 4, 3), 0.5)
    clean[0, 0] = 2.0
    valid = np.ones((2000, 4), bool)
    noisy, sat = apply_sensor(clean, valid, Sensor(noise=0.02), rng)
    assert sat is None
    assert np.std(noisy[1:] / 0.5 - 1) == pytest.approx(0.02, rel=0.05)
    q, sat = apply_sensor(clean, valid, Sensor(bits=8, full_scale=1.0), rng)
    assert sat == 1.0
    assert len(np.unique(q)) <= 256 and q.max() == 1.0
    np.testing.assert_allclose(q[1:], np.round(0.5 * 255) / 255)
    scan, _ = make_scan("A", resolution=24, lights=[20, 30], sensor=Sensor(bits=8, saturate=True,
                                                                           full_scale=0.05))
    assert scan.saturation == pytest.approx(0.05, rel=1e-6)
    saturated = np.any(scan.radiance >= scan.saturation, axis=-1) & scan.valid
    assert saturated.any()
    assert not np.any(scan.observed() & saturated)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="object"):
        make_scan("Z")
    with pytest.raises(ValueError, match="lights"):
        make_scan("A", resolution=24, lights=[60])
    with pytest.raises(ValueError, match="model"):
        make_scan("A", resolution=24, model="phong")
    with pytest.raises(ValueError, match="bits"):
        Sensor(bits=0)
