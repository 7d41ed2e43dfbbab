"""Held-out-light validation (`jaxrefl.outputs.holdout`, `jaxrefl estimate --holdout`): real Embree, real jit."""

import dataclasses
import json

import numpy as np
import pytest

from data_synth.scans import make_scan
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.outputs import holdout as ho
from jaxrefl.outputs import relight as rl
from jaxrefl.scan.io import Scan
from tests.test_cli import jaxrefl

V_LIGHTS = list(range(0, 60, 5))  # 12 of the rack's 60


@pytest.fixture(scope="module")
def vase():
    """Convex vase V, the paper's scanner (per-point lights (N, M, 3), cameras (N, 1, 3)), direct light.
    (698 points and 12 lights, 9 with a quarter held out, as the vase of `test_checks`: Method I
    compiles once for both files.)"""
    return make_scan("V", resolution=16, lights=V_LIGHTS, seed=0)[0]


@pytest.fixture(scope="module")
def fold():
    """Object E, pinhole camera (lights (M, 3), camera (3,)), direct light only."""
    return make_scan("E", resolution=16, setup="glossy", lights=[23, 26, 33, 36, 4, 55], seed=0)[0]


def test_choose_holdout():
    a = ho.choose_holdout(20, fraction=0.25, seed=3)
    assert len(a) == 5 and np.all(np.diff(a) > 0) and a.min() >= 0 and a.max() < 20
    assert np.array_equal(a, ho.choose_holdout(20, fraction=0.25, seed=3))
    assert not np.array_equal(a, ho.choose_holdout(20, fraction=0.25, seed=4))
    assert len(ho.choose_holdout(20, fraction=0.01)) == 1  # at least one held out
    assert ho.choose_holdout(10, lights=[7, 2]).tolist() == [2, 7]
    for kwargs, word in [({"fraction": 1.5}, "holdout:"), ({"fraction": 0.0}, "holdout:"),
                         ({"fraction": 0.9}, "holdout:"), ({}, "holdout:"),
                         ({"fraction": 0.2, "lights": [1]}, "holdout:"),
                         ({"lights": [10]}, "holdout-lights:"), ({"lights": [-1]}, "holdout-lights:"),
                         ({"lights": [1, 1]}, "holdout-lights:"), ({"lights": list(range(9))}, "holdout-lights:"),
                         ({"lights": []}, "holdout-lights:"), ({"lights": [1.5]}, "holdout-lights:")]:
        with pytest.raises(ValueError, match=word):
            ho.choose_holdout(10, **kwargs)
    with pytest.raises(ValueError, match="holdout"):
        ho.choose_holdout(2, fraction=0.5)  # would leave one light to fit


def _scan(n, m, light_shape, cam_shape, intensity):
    rng = np.random.default_rng(0)
    return Scan(vertices=rng.random((n, 3)), faces=np.array([[0, 1, 2]]), light_pos=rng.random(light_shape),
                cam_pos=rng.random(cam_shape), light_intensity=intensity, radiance=rng.random((n, m, 3)),
                valid=rng.random((n, m)) > 0.3, saturation=0.9, true_pd=rng.random((n, 3)),
                meta={"light_indices": list(range(100, 100 + m)), "object": "x"})


@pytest.mark.parametrize("light_shape, cam_shape, per_obs_cam", [
    ((5, 6, 3), (6, 3), True),      # per-point lights, one camera per observation
    ((6, 3), (5, 6, 3), True),      # shared lights, per-(point, observation) cameras
    ((5, 6, 3), (5, 1, 3), False),  # the scanner: per-point lights and cameras
    ((6, 3), (3,), False),          # a fixed pinhole camera
])
def test_split_scan_slices_every_observation_field(light_shape, cam_shape, per_obs_cam):
    n, m, held = 5, 6, [1, 4]
    scan = _scan(n, m, light_shape, cam_shape, np.arange(1.0, m + 1))
    fit, test = ho.split_scan(scan, held)
    for sub, idx in ((fit, [0, 2, 3, 5]), (test, held)):
        assert sub.n_lights == len(idx) and sub.n_points == n
        assert np.array_equal(sub.light_positions(), scan.light_positions()[:, idx])
        assert np.array_equal(sub.camera_positions(), scan.camera_positions()[:, idx])
        assert np.array_equal(sub.intensities(), scan.intensities()[idx])
        assert np.array_equal(sub.radiance, scan.radiance[:, idx])
        assert np.array_equal(sub.valid, scan.valid[:, idx])
        assert np.array_equal(sub.observed(), scan.observed()[:, idx])
        assert sub.cam_pos.shape == (cam_shape[:-2] + (len(idx), 3) if per_obs_cam else cam_shape)
        assert sub.true_pd is scan.true_pd and sub.vertices is scan.vertices and sub.saturation == 0.9
        assert sub.meta["light_indices"] == [100 + i for i in idx] and sub.meta["object"] == "x"
        assert sub.meta["holdout"]["lights"] == idx and sub.meta["holdout"]["held_out_lights"] == held
    assert scan.n_lights == m and "holdout" not in scan.meta  # the input is left alone
    with pytest.raises(ValueError, match="holdout-lights"):
        ho.split_scan(scan, [6])
    with pytest.raises(ValueError, match="holdout-lights"):
        ho.split_scan(scan, list(range(m)))


def test_scalar_intensity_stays_scalar(vase):
    fit, test = ho.split_scan(vase, [0, 5])
    assert np.ndim(fit.light_intensity) == 0 and test.n_lights == 2 and fit.n_lights == len(V_LIGHTS) - 2
    assert test.light_pos.shape == (vase.n_points, 2, 3) and test.cam_pos is vase.cam_pos


def test_direct_radiance_takes_per_vertex_positions(fold):
    est, caster = rl.truth_estimate(fold), RayCaster(fold.vertices, fold.faces)
    light, cam = fold.light_pos[2], fold.cam_pos
    one = rl.direct_radiance(fold.vertices, fold.normals, est, light, 1.0, cam, caster)
    n = fold.n_points
    rows = rl.direct_radiance(fold.vertices, fold.normals, est, np.tile(light, (n, 1)), 1.0, np.tile(cam, (n, 1)),
                              caster)
    assert one.shape == rows.shape == (n, 3) and one.max() > 0
    np.testing.assert_allclose(rows, one, rtol=1e-12, atol=0)


@pytest.mark.parametrize("which", ["vase", "fold", "fold_per_observation_camera"])
def test_truth_relit_under_held_out_lights_matches(which, vase, fold):
    scan = vase if which == "vase" else fold
    if which == "fold_per_observation_camera":
        scan = dataclasses.replace(fold, cam_pos=np.tile(fold.cam_pos, (fold.n_lights, 1)),
                                   light_intensity=np.full(fold.n_lights, 1.0))
    held = ho.choose_holdout(scan.n_lights, fraction=0.34, seed=1)
    _, test = ho.split_scan(scan, held)
    caster = RayCaster(scan.vertices, scan.faces)
    floor = ho.truth_holdout_error(test, caster)
    assert floor["lights"] == held.tolist() and floor["gi"] == "none"
    assert floor["samples"] > 0.3 * test.n_points * len(held)
    assert floor["rel_rms"] < 1e-5 and floor["median_rel"] < 1e-5  # noise-free; radiance stored as float32
    assert all(e is not None and e < 1e-5 for e in floor["per_light_rel_rms"])
    assert sum(floor["per_light_samples"]) == floor["samples"]

    truth = rl.truth_estimate(scan)
    wrong = dataclasses.replace(truth, pd=np.clip(truth.pd * 1.25, 0, 1), ps=truth.ps * 0.5)
    bad = ho.holdout_error(wrong, test, caster)
    assert bad["samples"] == floor["samples"]
    assert bad["rel_rms"] > 0.05 and bad["median_rel"] > 0.05
    json.dumps(bad, allow_nan=False)


def test_estimate_with_holdout_method_I(vase):
    from jaxrefl.methods.local import estimate_local

    held = ho.choose_holdout(vase.n_lights, fraction=0.25)
    est, fit, test = ho.estimate_with_holdout(vase, estimate_local, held)
    h = est.meta["holdout"]
    assert fit.n_lights + test.n_lights == vase.n_lights and h["lights"] == held.tolist()
    assert h["fit_lights"] == fit.meta["holdout"]["lights"] and not set(h["fit_lights"]) & set(h["lights"])
    assert h["gi"] == "none" and h["truth"]["rel_rms"] < 1e-5
    assert 0 < h["rel_rms"] < 0.25 and np.isfinite(h["median_rel"])
    assert est.meta["seconds"]["holdout"] >= 0
    json.dumps(est.meta, allow_nan=False)


def test_no_usable_held_out_sample_gives_a_reason_not_nan(fold):
    _, test = ho.split_scan(fold, [0, 3])
    truth = rl.truth_estimate(fold)
    cases = {"unobserved": dataclasses.replace(test, valid=np.zeros_like(test.valid)),
             "saturated": dataclasses.replace(test, saturation=1e-12),
             "no radiance": dataclasses.replace(test, radiance=None, valid=None),
             "black": dataclasses.replace(test, radiance=np.zeros_like(test.radiance))}
    for name, scan in cases.items():
        h = ho.holdout_error(truth, scan)
        assert h["rel_rms"] is None and h["median_rel"] is None and h["samples"] == 0, name
        assert isinstance(h["reason"], str) and h["reason"], name
        assert h["lights"] == [0, 3] and h["per_light_rel_rms"] == [None, None], name
        json.dumps(h, allow_nan=False)
    no_truth = dataclasses.replace(test, true_pd=None, true_ps=None, true_sigma=None)
    h = ho.truth_holdout_error(no_truth)
    assert h["rel_rms"] is None and "ground truth" in h["reason"]


def test_gi_model_follows_the_method(fold):
    est = rl.truth_estimate(fold)
    for method, model, gi in (("local", "torrance-sparrow", "none"), ("radiosity", "torrance-sparrow", "radiosity"),
                              ("photon", "ward", "photon")):
        assert ho.gi_model(dataclasses.replace(est, model=model, meta={"method": method})) == gi
    auto = dataclasses.replace(est, meta={"method": "auto", "auto": {"global_methods": ["radiosity"]}})
    assert ho.gi_model(auto) == "radiosity"


def test_cli_holdout(tmp_path):
    scan = tmp_path / "v.npz"
    r = jaxrefl("synth", "V", "--out", scan, "--resolution", 16, "--lights", ",".join(map(str, V_LIGHTS)),
                "--noise", 0.01)
    assert r.returncode == 0, r.stderr
    r = jaxrefl("estimate", scan, "--out", tmp_path / "r.npz", "--holdout", 0.25, "--json")
    assert r.returncode == 0, r.stderr
    h = json.loads(r.stdout)["holdout"]
    assert len(h["lights"]) == 3 and len(h["fit_lights"]) == 9 and h["fraction"] == 0.25 and h["seed"] == 0
    assert 0 < h["rel_rms"] < 0.25 and len(h["per_light_rel_rms"]) == 3 and h["samples"] > 0
    assert 0 < h["truth"]["rel_rms"] <= h["rel_rms"] * 1.5  # 1 % noise: the floor is about 1 %
    from jaxrefl.result import load_result

    saved = load_result(tmp_path / "r.npz").meta["holdout"]
    assert saved["lights"] == h["lights"] and saved["rel_rms"] == pytest.approx(h["rel_rms"])

    for args, word in (("--holdout 1.5", "holdout"), ("--holdout-lights 3,99", "holdout-lights"),
                       ("--holdout-lights 3,x", "holdout-lights")):
        bad = jaxrefl("estimate", scan, "--out", tmp_path / "bad.npz", *args.split())
        assert bad.returncode == 2 and word in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
        assert not (tmp_path / "bad.npz").exists()
    both = jaxrefl("estimate", scan, "--out", tmp_path / "bad.npz", "--holdout", 0.2, "--holdout-lights", 1)
    assert both.returncode == 2 and "holdout" in both.stderr


def test_indirect_observations_is_the_per_configuration_relight():
    """All observations' interreflection at once (one radiosity solve over the light configurations;
    one photon map and one final gather) against relighting each configuration / light on its own."""
    from jaxrefl.methods import final_gather
    from jaxrefl.methods.radiosity import light_configs

    scanner = make_scan("E", resolution=16, setup="glossy", rig="scanner", lights=V_LIGHTS[:6], seed=0)[0]
    _, test = ho.split_scan(scanner, [1, 4])  # per-point lights: 2 lights in many configurations
    est, caster = rl.truth_estimate(scanner), RayCaster(scanner.vertices, scanner.faces)
    use = test.observed()
    together = rl.indirect_observations("radiosity", test, est, use, caster)
    cfg = light_configs(test.light_pos, test.n_points)
    assert len(cfg.positions) > 2 * test.n_lights
    alone = np.zeros_like(together)
    for c, (pos, j) in enumerate(zip(cfg.positions, cfg.light)):
        rows = cfg.index[:, j] == c
        alone[rows, j] = rl.indirect("radiosity", scanner.vertices, scanner.faces, scanner.normals, est, pos,
                                     float(test.intensities()[j]), scanner.cam_pos)[rows]
    assert together.max() > 0
    np.testing.assert_allclose(together, alone, rtol=1e-5, atol=1e-7 * together.max())

    fold = make_scan("E", resolution=16, setup="glossy", model="ward", lights=[23, 26, 33, 36], seed=0)[0]
    _, test = ho.split_scan(fold, [0, 3])  # fixed lights, a pinhole camera: one configuration per light
    est, caster = rl.truth_estimate(fold), RayCaster(fold.vertices, fold.faces)
    use = test.observed()
    settings = {"n_photons": 200_000, "rays": 256}
    together = rl.indirect_observations("photon", test, est, use, caster, settings)
    for j in range(test.n_lights):
        alone = final_gather.relight_indirect(fold.vertices, fold.faces, fold.normals, est.pd, est.ps,
                                              est.roughness, test.light_pos[j], test.intensities()[j], fold.cam_pos,
                                              n_photons=200_000, seed=1, caster=caster)
        a, b = together[use[:, j], j].mean(-1), alone[use[:, j]].mean(-1)
        assert a.sum() > 0 and abs(a.sum() / b.sum() - 1) < 0.03  # two Monte Carlo estimates of one quantity
        assert np.corrcoef(a, b)[0, 1] > 0.95
    assert np.all(together[~use] >= 0)
