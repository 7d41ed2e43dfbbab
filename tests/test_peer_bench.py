"""benchmarks.peer_mitsuba: the pieces that need no Mitsuba (camera and projection conventions,
bilinear taps, the silhouette test, error metrics, time to error, the report, the message
without Mitsuba); one test with Mitsuba, skipped where it is not installed."""

import json
import math
import sys

import numpy as np
import pytest

from benchmarks import peer_mitsuba as pm
from jaxrefl.scan.io import Scan, validate_scan


def _plate_scan(cam_pos=(0.0, 0.0, 1.0), n=5):
    """A flat n x n grid plate in z = 0, 0.1 m wide, normals +z, one light above."""
    g = np.linspace(-0.05, 0.05, n)
    x, y = np.meshgrid(g, g, indexing="xy")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            faces += [(a, b, d), (a, d, c)]
    return validate_scan(Scan(vertices=v, faces=np.array(faces), light_pos=np.array([[0.1, 0.0, 1.0]]),
                              cam_pos=np.asarray(cam_pos, float), normals=np.tile([0.0, 0.0, 1.0], (n * n, 1))))


def test_camera_projection_follows_mitsubas_look_at():
    cam = pm.Camera(origin=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_x=90.0, width=100,
                    height=80)
    r, u, f = cam.basis()
    np.testing.assert_allclose(f, [0, 0, -1])
    np.testing.assert_allclose(r, [1, 0, 0])  # cross(forward, up): image x grows to world +x here
    np.testing.assert_allclose(u, [0, 1, 0])
    assert math.isclose(cam.focal, 50.0)
    xy, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(z, 1.0)
    np.testing.assert_allclose(xy[0], [50.0, 40.0])  # the target: the image centre (pixel corners at integers)
    np.testing.assert_allclose(xy[1], [75.0, 40.0])  # right of the target: right in the image
    np.testing.assert_allclose(xy[2], [50.0, 15.0])  # above the target: up in the image (smaller row)
    np.testing.assert_allclose(xy[3], [100.0, 40.0])  # at fov_x / 2: the image's right edge
    assert cam.to_dict()["width"] == 100 and cam.to_dict()["origin"] == [0.0, 0.0, 1.0]


def test_up_hint_and_frame_camera_fit_the_object():
    np.testing.assert_allclose(pm.up_hint([0, 0, -1]), [0, 1, 0])
    np.testing.assert_allclose(pm.up_hint([0, -1, 0.05]), [0, 0, 1])  # looking along y: +z up
    scan = _plate_scan(cam_pos=(0.02, -0.3, 0.8), n=9)
    cam = pm.frame_camera(scan.cam_pos, scan.vertices, scan.faces, px_per_edge=4.0, min_size=8)
    xy, z = cam.project(scan.vertices)
    assert np.all(z > 0)
    assert np.all((xy > 0) & (xy < cam.width)) and cam.width == cam.height
    np.testing.assert_allclose(cam.target, [0, 0, 0], atol=1e-12)
    e = pm.mesh_edges(scan.faces)
    assert len(e) == 8 * 9 * 2 + 64  # grid edges + one diagonal per cell
    px = np.median(np.linalg.norm(xy[e[:, 0]] - xy[e[:, 1]], axis=1))
    assert 3.5 < px < 4.5
    with pytest.raises(ValueError, match="behind"):
        pm.frame_camera((0.0, 0.0, 0.0), scan.vertices[:, [0, 2, 1]] + [0, 0, 0.04], scan.faces)  # straddles


def test_bilinear_taps_interpolate_between_pixel_centres():
    h, w = 6, 8
    cols, rows = np.meshgrid(np.arange(w), np.arange(h), indexing="xy")
    img = np.stack([2.0 * cols + 3.0 * rows, np.ones((h, w)), cols * 0.0], -1)  # linear in the pixel index
    xy = np.array([[0.5, 0.5], [3.5, 2.5], [3.75, 2.25], [6.2, 4.9], [0.2, 3.0], [7.9, 1.0]])
    index, weights, inside = pm.bilinear_taps(xy, w, h)
    np.testing.assert_allclose(weights.sum(1), 1.0)
    np.testing.assert_array_equal(inside, [True, True, True, True, False, False])
    got = pm.sample_image(img, index, weights)
    s = xy - 0.5  # pixel centres at i + 0.5
    np.testing.assert_allclose(got[inside, 0], 2.0 * s[inside, 0] + 3.0 * s[inside, 1])
    np.testing.assert_allclose(got[:, 1], 1.0)
    assert index.min() >= 0 and index.max() < h * w  # clipped where outside


def test_taps_on_surface_rejects_silhouettes_and_occluders():
    v = np.zeros((5, 3))
    n = np.tile([0.0, 0.0, 1.0], (5, 1))
    index = np.arange(20).reshape(5, 4)
    surf = np.zeros((20, 6))
    surf[:, 5] = 1.0  # normals +z: the vertex's own surface
    surf[:4, 0] = [0.01, -0.01, 0.0, 0.005]  # in the tangent plane, near: on the surface
    surf[5, :3] = [0.0, 0.0, -0.05]  # another surface behind (off the plane)
    surf[8:12, 0] = 0.2  # in the plane but too far away
    surf[13, 3:] = [0.5, 0.0, 0.5]  # a crease: the pixel's mean normal is half another surface's
    surf[18, 3:] = [0.0, 0.0, 0.5]  # a silhouette: half the pixel is background (normal 0)
    ok = pm.taps_on_surface(surf, index, v, n, tolerance=0.02, reach=4.0)
    np.testing.assert_array_equal(ok, [True, False, False, False, False])
    far_grazing = surf.copy()
    far_grazing[8:12, 0] = 0.06  # a grazing footprint: long, but on the plane and within reach
    assert pm.taps_on_surface(far_grazing, index, v, n, tolerance=0.02, reach=4.0)[2]


def test_observation_cameras():
    scan = _plate_scan()
    cams, idx = pm.observation_cameras(scan)
    assert cams.shape == (1, 3) and idx.tolist() == [0]
    moving = validate_scan(Scan(vertices=scan.vertices, faces=scan.faces,
                                light_pos=np.array([[0.1, 0, 1], [0, 0.1, 1], [-0.1, 0, 1]]),
                                cam_pos=np.array([[0, 0, 1.0], [0.2, 0, 1.0], [0, 0, 1.0]])))
    cams, idx = pm.observation_cameras(moving)
    assert len(cams) == 2 and idx[0] == idx[2] != idx[1]
    per_point = validate_scan(Scan(vertices=scan.vertices, faces=scan.faces, light_pos=scan.light_pos,
                                   cam_pos=np.tile([0.0, 0.0, 1.0], (scan.n_points, 1, 1))))
    with pytest.raises(ValueError, match="per-point"):
        pm.observation_cameras(per_point)


def test_error_metrics():
    truth = {"pd": np.array([[0.5, 0.5, 0.5], [0.2, 0.4, 0.1], [0.4, 0.4, 0.4]]),
             "ps": np.array([0.2, 0.4, 0.0]), "roughness": np.array([0.1, 0.2, 0.3])}
    pd = np.array([[0.55, 0.45, 0.5], [0.2, 0.4, 0.1], [0.2, 0.2, 0.2]])
    err = pm.relative_errors(pd, truth["pd"])
    np.testing.assert_allclose(err, [0.2 / 3, 0.0, 0.5])
    e = pm.point_errors(pd, np.array([0.3, 0.4, 0.1]), np.array([0.1, 0.1, 0.3]), truth,
                        observed=np.array([True, True, False]))
    assert math.isclose(e["pd"]["all"], 0.2 / 3) and math.isclose(e["pd"]["observed"], 0.1 / 3)
    assert math.isclose(e["ps"]["all"], 0.25)  # the point with ps truth 0 has no relative error
    assert math.isclose(e["roughness"]["all"], 0.0) and math.isclose(e["roughness"]["observed"], 0.25)


def _trace():
    # a first iteration of 10 s (compilation), then 2 s each; pd error falling
    return [{"iteration": 0, "seconds": 0.0, "pd": 0.6},
            {"iteration": 1, "seconds": 10.0, "pd": 0.4},
            {"iteration": 2, "seconds": 12.0, "pd": 0.2},
            {"iteration": 3, "seconds": 14.0, "pd": 0.1},
            {"iteration": 4, "seconds": 16.0, "pd": 0.12},
            {"iteration": 5, "seconds": 18.0, "pd": 0.05}]


def test_time_to_error():
    tr = _trace()
    times, errs = [t["seconds"] for t in tr], [t["pd"] for t in tr]
    assert pm.time_to_error(times, errs, 0.1) == 14.0  # the first time at or below
    assert pm.time_to_error(times, errs, 0.11) == 14.0
    assert pm.time_to_error(times, errs, 0.6) == 0.0
    assert pm.time_to_error(times, errs, 0.01) is None  # never within the trace
    assert pm.time_to_error(times, [None, float("nan"), 0.1, 0, 0, 0], 0.1) == 12.0
    assert pm.time_to_error(times, errs, None) is None
    assert math.isclose(pm.first_iteration_overhead(tr), 8.0)
    assert pm.first_iteration_overhead(tr[:3]) == 0.0
    runs = {"I": {"seconds_first": 20.0, "seconds_warm": 1.0, "errors": {"pd": {"all": 0.1}}},
            "II": {"seconds_first": 5.0, "seconds_warm": 4.0, "errors": {"pd": {"all": 0.01}}},
            "III": {"error": "RuntimeError: boom"}}
    rows = pm.time_to_error_rows(tr, runs)
    assert [r["method"] for r in rows] == ["I", "II"]
    i, ii = rows
    assert i["mitsuba_seconds"] == 14.0 and math.isclose(i["mitsuba_seconds_warm"], 6.0)
    assert math.isclose(i["ratio_warm"], 6.0) and math.isclose(i["ratio_first"], 0.7)
    assert ii["mitsuba_seconds"] is None and ii["ratio_warm"] is None and ii["ratio_first"] is None
    assert not i["flat_start_as_good"]
    worse = pm.time_to_error_rows(tr, {"I": {"seconds_first": 2.0, "seconds_warm": 1.0, "errors": {"pd": {"all": 0.7}}}})
    assert worse[0]["flat_start_as_good"] and worse[0]["mitsuba_seconds"] == 0.0 and worse[0]["ratio_warm"] is None


def test_missing_mitsuba_is_one_message(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # `import mitsuba` raises ImportError
    with pytest.raises(pm.PeerUnavailable) as info:
        pm.load_mitsuba()
    text = str(info.value)
    assert "pip install" in text and ".[peer]" in text and "libllvm" in text and "DRJIT_LIBLLVM_PATH" in text
    out = tmp_path / "peer.md"
    assert pm.main(["--quick", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert "needs Mitsuba 3" in captured.err and "Traceback" not in captured.err + captured.out
    assert not out.exists()


def test_parse_args_quick_and_budget():
    a = pm.parse_args(["--quick"])
    assert a.budget == pm.QUICK_BUDGET and a.check_spp == pm.QUICK_CHECK_SPP and a.scenes == list(pm.SCENES)
    a = pm.parse_args(["--budget", "12", "--cells", "fold"])
    assert a.budget == 12.0 and a.scenes == ["fold"] and a.check_spp == pm.CHECK_SPP
    with pytest.raises(SystemExit):
        pm.parse_args(["--cells", "nope"])


def _errors(pd, ps, rough):
    return {"pd": {"all": pd, "observed": pd, "p90": pd}, "ps": {"all": ps, "observed": ps, "p90": ps},
            "roughness": {"all": rough, "observed": rough, "p90": rough}}


def test_report_from_records(tmp_path):
    d = {"median": 0.001, "p90": 0.01, "within_2pct": 0.95, "samples": 10}
    tr = _trace()
    for t in tr:
        t.update(ps=0.5, roughness=0.5, pd_observed=t["pd"])
    jr = {"I": {"seconds_first": 20.0, "seconds_warm": 1.0, "errors": _errors(0.1, 0.02, 0.03), "status": {}},
          "III": {"seconds_first": 40.0, "seconds_warm": 20.0, "errors": _errors(0.01, 0.02, 0.03), "status": {},
                  "auto_choice": "photon"}}
    rec = {"scene": "fold", "cell": "gi_fold_coaxial", "global_illumination": True, "n_points": 10, "n_lights": 2,
           "observed_points": 10, "observed_samples": 20, "description": "a fold",
           "mitsuba_setup": {"cameras": [pm.Camera((0, 0, 1.0), (0, 0, 0.0), (0, 1, 0.0), 10.0, 64, 64).to_dict()],
                             "max_depth": 4, "spp": 4, "lr": 0.1, "build_seconds": 0.1, "used_samples": 18,
                             "used_points": 10},
           "convention": {"spp": 16, "used_samples": 18, "observed_samples": 20, "seconds": 3.0,
                          "position": {"median_edges": 0.01, "p99_edges": 0.1, "samples": 18},
                          "diffuse_direct": d, "diffuse_direct_mirrored_x": d, "diffuse_direct_mirrored_y": d,
                          "diffuse_gi": d, "stock_truth_direct": d, "stock_truth_vs_clean": d,
                          "scan_noise_vs_clean": d},
           "mitsuba": {"trace": tr, "errors": _errors(0.05, 0.5, 0.5), "errors_used_points": _errors(0.04, 0.4, 0.4),
                       "iterations": 5, "seconds": 18.0,
                       "seconds_per_iteration": 3.6, "first_iteration_seconds": 10.0},
           "jaxrefl": jr, "time_to_error": pm.time_to_error_rows(tr, jr)}
    run = {"command": "python3 -m benchmarks.peer_mitsuba", "date": "today", "machine": pm.machine(),
           "versions": {"jax": "0", "mitsuba": "3", "drjit": "1", "variant": "llvm_ad_rgb", "llvm": "19"},
           "budget": 18.0, "lr": 0.1, "spp": 2, "gi_spp": 4, "gi_depth": 4, "px_per_edge": 3.0, "load_start": 1.0,
           "load_end": 1.0, "seconds": 60.0, "complete": True}
    out = tmp_path / "RESULTS_peer.md"
    pm.write_report([rec, {"scene": "bowl", "cell": "gi_bowl", "error": "RuntimeError: x"}], run, out)
    text = out.read_text()
    assert "| fold (gi_fold_coaxial) | I | 10.00% | 1.0 / 20.0 | 6.0 / 14.0 | 6.0x | 0.7x |" in text
    assert "never within 18 s (reached 5.00%)" in text
    assert "FAILED" in text and "not apples to apples" in text and "auto: photon" in text
    assert "over the 10 points Mitsuba has samples of: pd 4.00%" in text
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["scenes"][0]["time_to_error"][0]["mitsuba_seconds"] == 14.0
    assert out.with_suffix(".png").exists()
    # a hand-written findings section survives a rewrite
    out.write_text(text.replace("(to be written by hand from the tables above)", "Mitsuba is slower."))
    pm.write_report([rec], run, out, plot=False)
    assert "Mitsuba is slower." in out.read_text()


def test_mitsuba_renders_the_scans_conventions():
    """With Mitsuba: a small direct-light zoo cell rendered with its true diffuse albedo agrees
    with the zoo's own render at the vertices, and a mirrored image does not."""
    pytest.importorskip("mitsuba")
    try:
        mi, dr = pm.load_mitsuba()
    except pm.PeerUnavailable as exc:
        pytest.skip(str(exc).splitlines()[0])
    from data_synth import zoo

    scan, info = zoo.make_cell("coaxial_uniform", n_points=162)
    fit = pm.MitsubaFit(scan, mi, dr, max_depth=2, px_per_edge=3.0)
    used = fit.build_taps()
    assert used.sum() > 0.5 * scan.observed().sum()
    check = pm.convention_check(fit, info, spp=8, log=None)
    assert check["position"]["median_edges"] < 0.1
    assert check["diffuse_direct"]["median"] < 0.02
    assert check["diffuse_direct_mirrored_y"]["median"] > 0.1
    trace = fit.optimise(1e9, lr=0.1, spp=1, truth={"pd": scan.true_pd, "ps": scan.true_ps,
                                                     "roughness": scan.true_alpha},
                         observed=scan.observed().any(1), max_iterations=2, log=None)
    assert [t["iteration"] for t in trace] == [0, 1, 2]
    assert trace[-1]["pd_observed"] < trace[0]["pd_observed"]  # moving toward the truth (56 % unseen)
