"""Scan bundle: round trip, atomic writes, and one rejection per kind of bad input."""

import json
import os

import numpy as np
import pytest

from jaxrefl.scan.io import FORMAT_VERSION, Scan, ScanError, atomic_write, load_scan, save_scan

from .helpers import sphere


def good_scan(n_lights=3, **changes):
    v, f = sphere(0.1, 2)
    n = len(v)
    rng = np.random.default_rng(0)
    fields = dict(
        vertices=v, faces=f, normals=v / np.linalg.norm(v, axis=1, keepdims=True),
        light_pos=rng.normal(size=(n_lights, 3)) + [0, 0, 1.0],
        light_intensity=np.full(n_lights, 2.0),
        cam_pos=np.array([0.0, 0.0, 1.0]),
        radiance=rng.uniform(0, 1, (n, n_lights, 3)).astype(np.float32),
        valid=rng.uniform(size=(n, n_lights)) > 0.2,
        saturation=0.95,
        true_pd=rng.uniform(0, 1, (n, 3)), true_ps=rng.uniform(0, 1, n), true_sigma=np.full(n, 0.1),
        meta={"object": "sphere"},
    )
    fields.update(changes)
    return Scan(**fields)


def write_raw(path, **arrays):
    arrays.setdefault("format_version", np.int64(FORMAT_VERSION))
    np.savez(path, **arrays)


def raw_fields(scan):
    out = {k: getattr(scan, k) for k in ("vertices", "faces", "normals", "light_pos", "light_intensity",
                                         "cam_pos", "radiance", "valid", "saturation")}
    out["meta"] = np.asarray(json.dumps(scan.meta))
    return out


def test_round_trip(tmp_path):
    scan = good_scan()
    path = tmp_path / "scan.npz"
    save_scan(path, scan)
    back = load_scan(path)
    for name in ("vertices", "faces", "light_pos", "cam_pos", "radiance", "valid",
                 "true_pd", "true_ps", "true_sigma"):
        np.testing.assert_array_equal(getattr(back, name), getattr(scan, name))
    np.testing.assert_allclose(back.normals, scan.normals, rtol=1e-15, atol=1e-15)  # renormalised
    assert back.saturation == 0.95 and back.meta == {"object": "sphere"}
    assert back.light_positions().shape == (scan.n_points, 3, 3)
    assert back.camera_positions().shape == (scan.n_points, 3, 3)
    sat = np.any(back.radiance >= 0.95, axis=-1)
    np.testing.assert_array_equal(back.observed(), back.valid & ~sat)
    assert [p.name for p in tmp_path.iterdir()] == ["scan.npz"]


@pytest.mark.parametrize("cam_shape", [(3,), (3, 3), ("n", 1, 3), ("n", 3, 3)])
def test_camera_and_light_layouts(tmp_path, cam_shape):
    scan = good_scan()
    n = scan.n_points
    shape = tuple(n if d == "n" else d for d in cam_shape)
    cam = np.broadcast_to([0.0, 0.0, 1.0], shape).copy()
    lights = np.broadcast_to(scan.light_pos, (n, 3, 3)).copy()
    save_scan(tmp_path / "s.npz", good_scan(cam_pos=cam, light_pos=lights))
    back = load_scan(tmp_path / "s.npz")
    np.testing.assert_allclose(back.camera_positions(), np.broadcast_to([0, 0, 1.0], (n, 3, 3)))
    assert back.light_pos.ndim == 3


def test_planning_bundle_without_radiance(tmp_path):
    save_scan(tmp_path / "plan.npz", good_scan(radiance=None, valid=None, saturation=None))
    back = load_scan(tmp_path / "plan.npz")
    assert back.radiance is None and not back.observed().any()


def _bad(field, **changes):
    return pytest.param(field, changes, id=field + ":" + ",".join(changes))


v0, f0 = sphere(0.1, 2)
N = len(v0)
nan_vertices = v0.copy()
nan_vertices[5, 1] = np.nan
neg_radiance = np.full((N, 3, 3), 0.5)
neg_radiance[3, 1, 2] = -0.1
inf_radiance = np.full((N, 3, 3), 0.5)
inf_radiance[0, 0, 0] = np.inf
zero_normals = v0.copy()
zero_normals[7] = 0.0
flat = v0.copy()
flat[:, 2] = 0.0
flat[:, 1] = 0.0
degenerate_faces = f0.copy()
degenerate_faces[4] = [1, 1, 2]

BAD = [
    _bad("vertices", vertices=nan_vertices),
    _bad("vertices", vertices=v0[:, :2]),
    _bad("faces", faces=f0.astype(np.float64)),
    _bad("faces", faces=np.where(f0 == 3, N + 5, f0)),
    _bad("faces", faces=np.where(f0 == 3, -1, f0)),
    _bad("faces", faces=degenerate_faces),
    _bad("faces", vertices=flat),
    _bad("normals", normals=zero_normals),
    _bad("normals", normals=np.ones((N - 1, 3))),
    _bad("light_pos", light_pos=np.array([[0.0, 0.0, np.nan], [0, 0, 1], [0, 1, 1]])),
    _bad("light_pos", light_pos=np.array([[0.0, 0.0, 0.0], [0, 0, 1], [0, 1, 1]])),
    _bad("light_pos", light_pos=np.zeros((4,))),
    _bad("light_intensity", light_intensity=np.array([1.0, -1.0, 1.0])),
    _bad("light_intensity", light_intensity=np.ones(4)),
    _bad("cam_pos", cam_pos=np.array([0.0, 0.0, 0.01])),
    _bad("cam_pos", cam_pos=np.ones((5, 3))),
    _bad("radiance", radiance=neg_radiance),
    _bad("radiance", radiance=inf_radiance),
    _bad("radiance", radiance=np.ones((N, 4, 3))),
    _bad("radiance", radiance=np.ones((N, 3, 3), dtype=np.complex64)),
    _bad("valid", valid=np.ones((N, 3), dtype=np.int8)),
    _bad("saturation", saturation=0.0),
    _bad("true_pd", true_pd=-np.ones((N, 3))),
    _bad("true_sigma", true_sigma=np.zeros(N)),
]


@pytest.mark.parametrize("field, changes", BAD)
def test_loader_rejects_bad_input_naming_the_field(tmp_path, field, changes):
    """Each bad field is refused both on save (no file written) and on load of a raw file."""
    scan = good_scan(**changes)
    with pytest.raises(ScanError) as err:
        save_scan(tmp_path / "bad.npz", scan)
    assert err.value.field == field and str(err.value).startswith(field + ":")
    assert list(tmp_path.iterdir()) == []
    raw = raw_fields(scan)
    for key in ("true_pd", "true_sigma"):
        if getattr(scan, key) is not None and key in changes:
            raw[key] = getattr(scan, key)
    write_raw(tmp_path / "raw.npz", **{k: v for k, v in raw.items() if v is not None})
    with pytest.raises(ScanError) as err:
        load_scan(tmp_path / "raw.npz")
    assert err.value.field == field


def test_loader_rejects_foreign_files(tmp_path):
    good = {k: v for k, v in raw_fields(good_scan()).items() if v is not None}
    good["format_version"] = np.int64(FORMAT_VERSION)
    cases = {
        "format_version": dict(good, format_version=np.int64(99)),
        "light_pos": {k: v for k, v in good.items() if k != "light_pos"},
        "colour": dict(good, colour=np.ones(3)),
        "meta": dict(good, meta=np.asarray("{not json")),
    }
    for field, arrays in cases.items():
        np.savez(tmp_path / "x.npz", **arrays)
        with pytest.raises(ScanError) as err:
            load_scan(tmp_path / "x.npz")
        assert err.value.field == field
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(ScanError, match="file"):
        load_scan(tmp_path / "junk.npz")
    np.savez(tmp_path / "old.npz", vertices=v0)
    with pytest.raises(ScanError, match="format_version"):
        load_scan(tmp_path / "old.npz")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"previous")

    def explode(fh):
        fh.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, explode)
    assert target.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["out.bin"]
