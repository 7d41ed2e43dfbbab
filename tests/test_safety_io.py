"""Never a silent wrong answer at the edges: every file read is checked (naming the file and
key), every file written refuses to destroy an input or a non-regular path and honours the
umask, and the public numeric entry points reject non-finite input (naming the argument)."""

import json
import os
import stat

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxrefl.geometry.rig import PinholeCamera
from jaxrefl.reflectance import brdf
from jaxrefl.result import Estimate
from jaxrefl.scan.io import ScanError, atomic_write, save_scan

from .helpers import grid_plane
from .test_cli import assert_one_line_error, jaxrefl
from .test_io import good_scan

# -- fixtures ----------------------------------------------------------------------------------


def _estimate(n, model="torrance-sparrow", **changes):
    fields = dict(pd=np.full((n, 3), 0.5), ps=np.full(n, 0.1), roughness=np.full(n, 0.2),
                  status=np.zeros(n, np.int8), std_pd=np.full((n, 3), 0.01), std_ps=np.full(n, np.inf),
                  std_roughness=np.full(n, 0.02), specular_identifiable=np.ones(n, bool),
                  pd_measured=np.ones(n, bool), model=model, meta={"method": "test", "model": model})
    fields.update(changes)
    return Estimate(**fields)


@pytest.fixture
def scan_and_result(tmp_path):
    """A small valid scan bundle and a valid result for it: (scan path, result path, N)."""
    from jaxrefl.result import save_result

    scan = good_scan()
    save_scan(tmp_path / "scan.npz", scan)
    save_result(tmp_path / "result.npz", _estimate(scan.n_points))
    return tmp_path / "scan.npz", tmp_path / "result.npz", scan.n_points


def _result_arrays(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _bad_results(tmp_path, scan_path, result_path):
    """name -> (path of a damaged result file, key its error must name)."""
    data = _result_arrays(result_path)
    out = {}
    raw = result_path.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    out["truncated"] = (tmp_path / "truncated.npz", "file")
    np.savez(tmp_path / "no_meta.npz", **{k: v for k, v in data.items() if k != "meta"})
    out["no_meta"] = (tmp_path / "no_meta.npz", "meta")
    out["scan_as_result"] = (scan_path, "pd")
    np.savez(tmp_path / "pd_n2.npz", **dict(data, pd=data["pd"][:, :2]))
    out["pd_n2"] = (tmp_path / "pd_n2.npz", "pd")
    return out


# -- every file in: results ---------------------------------------------------------------------


@pytest.mark.parametrize("case", ["truncated", "no_meta", "scan_as_result", "pd_n2"])
def test_load_result_names_the_file_and_key(tmp_path, scan_and_result, case):
    from jaxrefl.result import load_result

    scan_path, result_path, _ = scan_and_result
    path, key = _bad_results(tmp_path, scan_path, result_path)[case]
    with pytest.raises(ScanError) as info:
        load_result(path)
    assert info.value.field == key and str(path) in str(info.value)


def test_load_result_rejects_nan_and_bad_status(tmp_path, scan_and_result):
    from jaxrefl.result import load_result

    _, result_path, _ = scan_and_result
    data = _result_arrays(result_path)
    for key, value in (("sigma", np.where(np.arange(len(data["sigma"])) == 3, np.nan, data["sigma"])),
                       ("std_pd", data["std_pd"] * np.nan), ("status", data["status"] + 7),
                       ("pd_measured", data["pd_measured"].astype(np.float64))):
        np.savez(tmp_path / "bad.npz", **dict(data, **{key: value}))
        with pytest.raises(ScanError) as info:
            load_result(tmp_path / "bad.npz")
        assert info.value.field == key, key
    assert load_result(result_path).std_ps[0] == np.inf  # inf: an unknown std, allowed


@pytest.mark.parametrize("command, case", [("maps", "truncated"), ("relight", "no_meta"),
                                           ("export", "scan_as_result"), ("relight", "pd_n2")])
def test_cli_result_readers_exit_2_naming_the_key(tmp_path, scan_and_result, command, case):
    scan_path, result_path, _ = scan_and_result
    path, key = _bad_results(tmp_path, scan_path, result_path)[case]
    out = tmp_path / ("out.ply" if command == "export" else "out.png")
    extra = ["--light", "0,0,1"] if command == "relight" else []
    r = jaxrefl(command, path, scan_path, "--out", out, *extra)
    assert_one_line_error(r, f"{key}:")
    assert str(path) in r.stderr and not out.exists()


def test_save_result_refuses_nan(tmp_path):
    from jaxrefl.result import save_result

    est = _estimate(10, pd=np.where(np.arange(10)[:, None] == 4, np.nan, 0.5) * np.ones((10, 3)))
    with pytest.raises(ScanError) as info:
        save_result(tmp_path / "r.npz", est)
    assert info.value.field == "pd" and "point 4" in str(info.value)
    assert not os.listdir(tmp_path)


# -- every file in: ingest ----------------------------------------------------------------------


def _photometric_folder(folder, image, black_level):
    h, w = image.shape[:2]
    np.save(folder / "normals.npy", np.tile([0.0, 0.0, 1.0], (h, w, 1)))
    np.save(folder / "img0.npy", image)
    rig = {"type": "photometric-stereo", "normals": "normals.npy", "transfer": "linear",
           "black_level": black_level, "lights": [{"direction": [0.0, 0.0, 1.0], "intensity": 1.0}],
           "images": ["img0.npy"]}
    (folder / "rig.json").write_text(json.dumps(rig))
    return folder


def test_ingest_refuses_an_image_below_the_black_level(tmp_path):
    from jaxrefl.scan.ingest import ingest

    folder = _photometric_folder(tmp_path, np.full((8, 8, 3), -1.0), black_level=0.5)
    with pytest.raises(ScanError) as info:
        ingest(folder)
    assert info.value.field == "images[0]" and "img0.npy" in str(info.value)
    assert "black" in str(info.value)
    r = jaxrefl("ingest", folder, "--out", tmp_path / "s.npz")
    assert_one_line_error(r, "images[0]")
    assert not (tmp_path / "s.npz").exists()


def test_ingest_clips_sensor_noise_below_the_black_level(tmp_path):
    """Dark pixels scatter around the black level: a minority below it is noise, set to 0."""
    from jaxrefl.scan.ingest import ingest

    image = np.full((8, 8, 3), 0.9)
    image[::2] = 0.45  # 50% of the values 0.05 below the black level
    scan = ingest(_photometric_folder(tmp_path, image, black_level=0.5))
    assert scan.radiance.min() == 0.0 and np.isclose(scan.radiance.max(), 0.4)


def test_ingest_singular_intrinsics_name_the_field(tmp_path):
    from jaxrefl.scan.ingest import ingest

    v, f = grid_plane(0.1, 5)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "mesh.ply")
    cam = PinholeCamera.look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], width=64, height=48)
    K = cam.K.copy()
    K[2] = 0.0  # singular
    np.save(tmp_path / "img0.npy", np.full((48, 64, 3), 0.5))
    rig = {"mesh": "mesh.ply", "transfer": "linear",
           "cameras": [{"K": K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(), "width": 64, "height": 48}],
           "lights": [{"position": [0.0, 0.2, 1.0], "intensity": 1.0}], "images": ["img0.npy"]}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(ScanError) as info:
        ingest(tmp_path)
    assert info.value.field == "cameras[0].K" and "singular" in str(info.value)


# -- every file out -----------------------------------------------------------------------------


def test_estimate_refuses_to_overwrite_its_input(tmp_path):
    scan = good_scan()
    save_scan(tmp_path / "x.npz", scan)
    before = (tmp_path / "x.npz").read_bytes()
    r = jaxrefl("estimate", tmp_path / "x.npz", "--out", tmp_path / "x.npz")
    assert_one_line_error(r, "out:")
    assert (tmp_path / "x.npz").read_bytes() == before


def _special(tmp_path, kind):
    path = tmp_path / kind
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        try:
            os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a /dev/null twin
        except (PermissionError, OSError, AttributeError):
            pytest.skip("cannot create a character device here")
    return path


@pytest.mark.parametrize("kind", ["fifo", "folder", "chardev"])
def test_cli_out_refuses_a_path_that_is_not_a_regular_file(tmp_path, kind):
    save_scan(tmp_path / "x.npz", good_scan())
    path = _special(tmp_path, kind)
    mode = os.lstat(path).st_mode
    r = jaxrefl("estimate", tmp_path / "x.npz", "--out", path)
    assert_one_line_error(r, "out:")
    assert os.lstat(path).st_mode == mode  # the node is still there, untouched


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_atomic_write_refuses_a_path_that_is_not_a_regular_file(tmp_path, kind):
    path = _special(tmp_path, kind)
    mode = os.lstat(path).st_mode
    with pytest.raises(ValueError, match="not a regular file|is a folder"):
        atomic_write(path, lambda fh: fh.write(b"x"))
    assert os.lstat(path).st_mode == mode
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]


def test_check_output_path_refuses_dev_null_and_inputs(tmp_path):
    from jaxrefl.scan.io import check_output_path

    with pytest.raises(ValueError, match="out: /dev/null exists and is not a regular file"):
        check_output_path("/dev/null")
    (tmp_path / "a.npz").write_bytes(b"a")
    os.link(tmp_path / "a.npz", tmp_path / "b.npz")
    with pytest.raises(ValueError, match="plot: .* is also an input"):
        check_output_path(tmp_path / "b.npz", "plot", [tmp_path / "a.npz"])
    check_output_path(tmp_path / "c.npz", "out", [tmp_path / "a.npz"])  # new paths are fine
    check_output_path(tmp_path, "out", folder=True)
    with pytest.raises(ValueError, match="not a folder"):
        check_output_path(tmp_path / "a.npz", "out", folder=True)


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        atomic_write(tmp_path / "a.bin", lambda fh: fh.write(b"x"))
        save_scan(tmp_path / "s.npz", good_scan())
        (tmp_path / "old.bin").write_bytes(b"")
        os.chmod(tmp_path / "old.bin", 0o600)
        atomic_write(tmp_path / "old.bin", lambda fh: fh.write(b"y"))  # replacing an existing file too
    finally:
        os.umask(old)
    for name in ("a.bin", "s.npz", "old.bin"):
        assert stat.S_IMODE(os.stat(tmp_path / name).st_mode) == mode, name


# -- public API inputs --------------------------------------------------------------------------


@pytest.mark.parametrize("argument", ["points", "normals", "cam_pos", "light_pos"])
def test_observation_geometry_rejects_nan_naming_the_argument(argument):
    from jaxrefl.geometry.rig import observation_angles, observation_geometry

    v, _ = grid_plane(0.1, 3)
    args = dict(points=v, normals=np.tile([0.0, 0.0, 1.0], (len(v), 1)), cam_pos=np.array([0.0, 0.0, 1.0]),
                light_pos=np.array([[0.0, 0.3, 1.0], [0.3, 0.0, 1.0]]))
    args[argument] = np.array(args[argument], dtype=np.float64)
    args[argument].flat[1] = np.nan
    for fn in (observation_geometry, observation_angles):
        with pytest.raises(ValueError, match=f"^{argument}: contains 1 non-finite"):
            fn(**args)


def test_observation_geometry_rejects_bad_shapes():
    from jaxrefl.geometry.rig import observation_geometry

    v, _ = grid_plane(0.1, 3)
    n = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    with pytest.raises(ValueError, match="^normals: must have shape"):
        observation_geometry(v, n[:-1], [0.0, 0.0, 1.0], [[0.0, 0.3, 1.0]])
    with pytest.raises(ValueError, match="^cam_pos: must have shape"):
        observation_geometry(v, n, np.zeros((5, 3)), [[0.0, 0.3, 1.0]])


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
@pytest.mark.parametrize("log_rough", [-np.inf, -1e4, 1e4, np.inf])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_brdf_is_finite_at_extreme_roughness(model, log_rough, dtype):
    full = brdf.MODELS[model][0]
    theta = jnp.asarray([0.0, 1e-4, 0.3, 1.5], dtype)
    cos = jnp.asarray([1.0, 0.5, 1e-9, 0.8], dtype)
    pd = jnp.full((4, 3), 0.5, dtype)

    def value(lr):
        return full(pd, jnp.asarray(0.3, dtype), lr, cos, cos, theta)

    f = value(jnp.asarray(log_rough, dtype))
    assert f.shape == (4, 3) and bool(jnp.all(jnp.isfinite(f)))
    grad = jax.grad(lambda lr: jnp.sum(value(lr)))(jnp.asarray(log_rough, dtype))
    assert bool(jnp.isfinite(grad))
    lo, hi = brdf.LOG_ROUGHNESS_RANGE
    inside = value(jnp.asarray(np.clip(log_rough, lo, hi), dtype))
    np.testing.assert_allclose(np.asarray(f), np.asarray(inside))  # clipped, documented range
