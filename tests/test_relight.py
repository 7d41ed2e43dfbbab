"""Relighting, comparison and reflectance-map figures, and PLY export."""

import json

import numpy as np
import pytest
import trimesh

from data_synth.scans import make_scan
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.outputs import relight as rl
from jaxrefl.outputs import render
from jaxrefl.outputs.export import export_ply
from jaxrefl.result import Estimate, save_result
from jaxrefl.scan.io import save_scan
from jaxrefl.status import STATUS_NAMES

from .helpers import grid_plane
from .test_cli import assert_one_line_error, jaxrefl


def test_status_colours_cover_every_status():
    """The maps draw each of `jaxrefl.methods.local.STATUS_NAMES` in its own discrete colour."""
    assert render.STATUS_NAMES == STATUS_NAMES
    assert len(set(render.STATUS_COLOURS)) == len(STATUS_NAMES)
    cmap, norm = render.status_colormap()
    colours = [cmap(norm(code)) for code in range(len(STATUS_NAMES))]
    assert len(set(colours)) == len(STATUS_NAMES)


@pytest.fixture(scope="module")
def scan_a():
    """Object A in front of a pinhole camera under 3 rack lights (direct light, no noise)."""
    scan, _ = make_scan("A", resolution=20, rig="pinhole", lights=[14, 25, 44])
    return scan


def _estimate(scan, rng=None, model="torrance-sparrow"):
    """The scan's truth as an Estimate, optionally perturbed, with every status and two
    materials."""
    est = rl.truth_estimate(scan)
    n = scan.n_points
    status = (np.arange(n) % len(STATUS_NAMES)).astype(np.int8)
    pd, ps, rough = est.pd, est.ps, est.roughness
    if rng is not None:
        pd = np.clip(pd * (1 + 0.05 * rng.standard_normal(pd.shape)), 0, 1)
        ps = ps * (1 + 0.1 * rng.standard_normal(n)) ** 2
        rough = rough * np.exp(0.1 * rng.standard_normal(n))
    std = np.where(status[:, None] == 2, np.inf, 0.01 * np.ones((n, 3)))
    return Estimate(pd, ps, rough, status, std, std[:, 0], std[:, 0], status == 0, status != 2, model,
                    {"method": "test", "model": model}, material=(np.arange(n) // 7) % 2)


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
def test_relight_reproduces_the_path_tracers_direct_light(model):
    """Relighting the truth under each capture light, from the capture camera, gives the
    bundle's own observations (rendered by data_synth's independent NumPy BRDF and shadows)."""
    scan, _ = make_scan("A", resolution=20, rig="pinhole", lights=[3, 25, 52], model=model)
    truth = rl.truth_estimate(scan)
    assert truth.model == model
    caster = RayCaster(scan.vertices, scan.faces)
    for k in range(scan.n_lights):
        got = rl.relight(scan.vertices, scan.faces, scan.normals, truth, scan.light_pos[k],
                         scan.intensities()[k], scan.cam_pos, caster=caster)
        ok = scan.valid[:, k]
        assert ok.sum() > 100 and np.all(np.isfinite(got))
        np.testing.assert_allclose(got[ok], scan.radiance[ok, k], rtol=2e-4, atol=1e-6 * scan.radiance.max())
        assert np.any(scan.radiance[ok, k].max(axis=1) == 0)  # some of them in cast shadow


def test_lambertian_plane_closed_form():
    v, f = grid_plane(half=0.5, n=11)
    n = len(v)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    est = Estimate(np.full((n, 3), 0.4), np.zeros(n), np.full(n, 0.2), np.zeros(n, np.int8), np.zeros((n, 3)),
                   np.zeros(n), np.zeros(n), np.ones(n, bool), np.ones(n, bool), "torrance-sparrow", {})
    light, y = np.array([0.2, -0.1, 1.5]), 3.0
    got = rl.relight(v, f, normals, est, light, y, np.array([0.0, 0.3, 2.0]))
    d = light - v
    r2 = np.sum(d * d, axis=1)
    want = 0.4 / np.pi * y * (d[:, 2] / np.sqrt(r2)) / r2
    np.testing.assert_allclose(got, np.repeat(want[:, None], 3, axis=1), rtol=1e-6)
    below = rl.relight(v, f, normals, est, np.array([0.0, 0.0, -1.0]), y, np.array([0.0, 0.3, 2.0]))
    assert np.all(below == 0)  # lit from behind: nothing, not NaN


def test_indirect_is_pluggable_and_fails_clearly(scan_a):
    est = _estimate(scan_a)
    light = np.array([0.3, 0.3, 0.8])
    args = (scan_a.vertices, scan_a.faces, scan_a.normals, est, light, 1.0, scan_a.cam_pos)
    assert np.array_equal(rl.indirect("none", *args), np.zeros((scan_a.n_points, 3)))
    with pytest.raises(ValueError, match="model-gi: must be one of none, radiosity, photon"):
        rl.indirect("bogus", *args)
    out = rl.indirect("radiosity", *args)
    assert out.shape == (scan_a.n_points, 3) and np.all(np.isfinite(out)) and np.all(out >= 0) and out.max() > 0
    with pytest.raises(ValueError, match="model-gi: photon relighting needs a Ward result"):
        rl.indirect("photon", *args)


def test_bad_relight_arguments(scan_a):
    est = _estimate(scan_a)
    base = dict(vertices=scan_a.vertices, faces=scan_a.faces, normals=scan_a.normals, est=est,
                light_pos=np.array([0.3, 0.3, 0.8]), intensity=1.0, cam_pos=scan_a.cam_pos)
    for change, field in ((dict(light_pos=np.array([0.0, 1.0])), "light"),
                          (dict(intensity=-1.0), "intensity"),
                          (dict(est=_estimate(make_scan("V", resolution=16, lights=[3])[0])), "pd")):
        with pytest.raises(ValueError, match=f"^{field}: "):
            rl.relight(**{**base, **change})
    with pytest.raises(ValueError, match="inside the object's bounding sphere"):
        rl.fit_camera(scan_a.vertices, scan_a.vertices.mean(0))


def test_pictures_comparison_and_maps(scan_a, tmp_path):
    cam = rl.scan_camera(scan_a)
    assert cam.width == 640 and np.allclose(cam.center, scan_a.cam_pos)  # the bundle's own camera
    caster = RayCaster(scan_a.vertices, scan_a.faces)
    light = np.array([-0.3, 0.35, 0.5])  # not one of the capture lights
    truth = rl.picture(caster, scan_a.faces, rl.relight(scan_a.vertices, scan_a.faces, scan_a.normals,
                       rl.truth_estimate(scan_a), light, 1.0, cam.center, caster=caster), cam)
    est = _estimate(scan_a, np.random.default_rng(0))
    relit = rl.picture(caster, scan_a.faces, rl.relight(scan_a.vertices, scan_a.faces, scan_a.normals, est,
                       light, 1.0, cam.center, caster=caster), cam)
    on = np.isfinite(truth).all(axis=-1)
    assert 0.02 < on.mean() < 0.9 and np.array_equal(on, np.isfinite(relit).all(axis=-1))
    assert rl.image_errors(truth, truth)["rms_relative"] == 0
    err = rl.image_errors(relit, truth)
    assert 0.01 < err["rms_relative"] < 0.5 and err["pixels"] == on.sum()
    render.comparison_figure(tmp_path / "cmp.png", relit, truth, labels=("relit", "truth"))
    hits, shape = render.camera_hits(caster, cam)
    render.reflectance_figure(tmp_path / "maps.png", hits, shape, scan_a.faces, est, title="test")
    hits, shape = render.cylindrical_hits(caster, width=128)
    render.reflectance_figure(tmp_path / "maps_cyl.png", hits, shape, scan_a.faces, est)
    render.status_figure(tmp_path / "status.png", hits, shape, scan_a.faces, est.status)
    for name in ("cmp.png", "maps.png", "maps_cyl.png", "status.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A fitted camera sees the whole object (the first and last columns and rows are empty).
    far = rl.fit_camera(scan_a.vertices, scan_a.vertices.mean(0) + [0.0, 0.1, 50.0], width=160, height=120)
    img = rl.picture(caster, scan_a.faces, np.ones((scan_a.n_points, 3)), far)
    hit = np.isfinite(img).all(axis=-1)
    assert hit.mean() > 0.1 and not hit[0].any() and not hit[-1].any() and not hit[:, 0].any()
    assert np.linalg.norm(far.center - scan_a.vertices.mean(0)) < 1.0  # brought in from 50 m


def _plain_ply(path):
    """Parse a binary little-endian PLY with numpy only: {element: structured array}."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4", "char": "i1",
             "short": "<i2", "ushort": "<u2"}
    elements, current = [], None
    for line in header:
        words = line.split()
        if words[0] == "element":
            current = (words[1], int(words[2]), [])
            elements.append(current)
        elif words[0] == "property" and words[1] == "list":
            assert words[2] == "uchar"  # triangles only: count byte then three indices
            current[2].extend([("count", "u1"), (words[4], types[words[3]], 3)])
        elif words[0] == "property":
            current[2].append((words[2], types[words[1]]))
    out, offset = {}, end
    for name, count, props in elements:
        dtype = np.dtype(props)
        out[name] = np.frombuffer(data, dtype, count, offset)
        offset += dtype.itemsize * count
    assert offset == len(data)
    return out


def test_export_ply_reopens_with_trimesh_and_plain_parsing(scan_a, tmp_path):
    est = _estimate(scan_a, np.random.default_rng(1))
    path = tmp_path / "result.ply"
    export_ply(path, scan_a.vertices, scan_a.faces, scan_a.normals, est)
    mesh = trimesh.load(path, process=False)
    np.testing.assert_allclose(mesh.vertices, scan_a.vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, scan_a.faces)
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(raw["ps"], est.ps, rtol=1e-6)
    plain = _plain_ply(path)
    v, f = plain["vertex"], plain["face"]
    np.testing.assert_array_equal(f["vertex_indices"], scan_a.faces)
    assert np.all(f["count"] == 3)
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], -1), scan_a.vertices, atol=1e-6)
    np.testing.assert_allclose(np.stack([v["nx"], v["ny"], v["nz"]], -1), scan_a.normals, atol=1e-6)
    np.testing.assert_allclose(np.stack([v["pd_r"], v["pd_g"], v["pd_b"]], -1), est.pd, rtol=1e-6)
    np.testing.assert_allclose(v["sigma"], est.roughness, rtol=1e-6)
    np.testing.assert_array_equal(v["status"], est.status)
    np.testing.assert_array_equal(v["std_ps"], est.std_ps.astype(np.float32))  # inf where unknown
    assert np.isinf(v["std_sigma"][est.status == 2]).all()
    np.testing.assert_array_equal(v["pd_measured"], est.pd_measured)
    np.testing.assert_array_equal(v["material"], est.material)
    srgb = np.where(est.pd <= 0.0031308, 12.92 * est.pd, 1.055 * est.pd ** (1 / 2.4) - 0.055)
    colours = np.stack([v["red"], v["green"], v["blue"]], -1).astype(float)
    assert np.abs(colours - srgb * 255).max() <= 0.5 + 1e-9
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], colours)
    bad = Estimate(*[np.where(True, a, a) for a in (est.pd, est.ps * np.nan, est.roughness)], est.status,
                   est.std_pd, est.std_ps, est.std_roughness, est.specular_identifiable, est.pd_measured,
                   est.model, {})
    with pytest.raises(ValueError, match="ps: .* NaN"):
        export_ply(tmp_path / "bad.ply", scan_a.vertices, scan_a.faces, scan_a.normals, bad)
    assert not (tmp_path / "bad.ply").exists()


def test_cli_relight_maps_export(scan_a, tmp_path):
    save_scan(tmp_path / "a.npz", scan_a)
    save_result(tmp_path / "r.npz", _estimate(scan_a, np.random.default_rng(2)))
    r = jaxrefl("relight", tmp_path / "r.npz", tmp_path / "a.npz", "--light=-0.3,0.35,0.5", "--reference",
                "truth", "--compare", tmp_path / "cmp.png", "--out", tmp_path / "relit.png", "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert 0.01 < summary["errors"]["rms_relative"] < 0.5 and summary["model_gi"] == "none"
    r = jaxrefl("relight", tmp_path / "r.npz", tmp_path / "a.npz", "--light=-0.3,0.35,0.5", "--camera",
                "0.4,0.3,0.6", "--width", 96, "--height", 64, "--out", tmp_path / "relit.npy")
    assert r.returncode == 0, r.stderr
    img = np.load(tmp_path / "relit.npy")
    assert img.shape == (64, 96, 3) and np.all(np.isfinite(img)) and img.max() > 0
    for command, out in (("maps", "maps.png"), ("export", "r.ply")):
        r = jaxrefl(command, tmp_path / "r.npz", tmp_path / "a.npz", "--out", tmp_path / out)
        assert r.returncode == 0, r.stderr
    for name in ("relit.png", "cmp.png", "maps.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert trimesh.load(tmp_path / "r.ply", process=False).vertices.shape == scan_a.vertices.shape
    out = tmp_path / "never.png"
    r = jaxrefl("relight", tmp_path / "r.npz", tmp_path / "a.npz", "--light", "1,2", "--out", out)
    assert_one_line_error(r, "light")
    assert not out.exists()


def test_exr_relit_image_and_maps_are_linear_and_named(scan_a, tmp_path):
    """`relight --out X.exr` writes the same linear radiance as `.npy` with its coverage in `A`;
    `maps --out X.exr` writes the result's maps as named float layers, readable by OpenEXR."""
    from jaxrefl.cli import main
    from jaxrefl.scan.images import read_exr, read_image, write_exr

    save_scan(tmp_path / "a.npz", scan_a)
    est = _estimate(scan_a, np.random.default_rng(3))
    save_result(tmp_path / "r.npz", est)
    view = ["--light=-0.3,0.35,0.5", "--camera", "0.4,0.3,0.6", "--width", "48", "--height", "32"]
    for out in ("relit.npy", "relit.exr"):
        assert main(["relight", str(tmp_path / "r.npz"), str(tmp_path / "a.npz"), *view,
                     "--out", str(tmp_path / out)]) == 0
    linear, exr = np.load(tmp_path / "relit.npy"), read_exr(tmp_path / "relit.exr")
    assert set(exr) == {"RGB", "A"} and exr["RGB"].shape == (32, 48, 3)
    on = exr["A"] == 1
    assert 0 < on.sum() < on.size and np.all(exr["RGB"][~on] == 0)
    np.testing.assert_allclose(exr["RGB"], linear, rtol=1e-6, atol=1e-12)  # float32 of the same image
    np.testing.assert_allclose(read_image(tmp_path / "relit.exr")[0], linear, rtol=1e-6, atol=1e-12)

    assert main(["maps", str(tmp_path / "r.npz"), str(tmp_path / "a.npz"), "--view", "camera", "--width", "40",
                 "--out", str(tmp_path / "maps.exr")]) == 0
    maps = read_exr(tmp_path / "maps.exr")
    assert set(maps) == {"RGB", "ps", "roughness", "std_ps", "std_roughness", "status", "A"}
    on = maps["A"] == 1
    assert on.any() and np.isnan(maps["ps"][~on]).all()
    assert set(np.unique(maps["status"][on])) <= set(np.unique(est.status).astype(np.float32))
    assert maps["ps"][on].min() >= est.ps.min() - 1e-6 and maps["ps"][on].max() <= est.ps.max() + 1e-6
    write_exr(tmp_path / "ps.exr", {"ps": maps["ps"]})
    with pytest.raises(ValueError, match="RGB or Y"):  # an image needs colour or grey
        read_image(tmp_path / "ps.exr")
    with pytest.raises(ValueError, match="one size"):
        write_exr(tmp_path / "bad.exr", {"RGB": exr["RGB"], "A": maps["A"]})
