"""Tests for the procedural synthetic objects A–E (data_synth.objects)."""

import numpy as np
import pytest
import trimesh

from data_synth.objects import OBJECT_NAMES, SynthObject, fold_coordinate, make_object

SOLIDS = ("A", "B", "C", "D")


@pytest.fixture(scope="module")
def objects() -> dict[str, SynthObject]:
    objs = {name: make_object(name) for name in OBJECT_NAMES}
    objs["E_diffuse"] = make_object("E", setup="diffuse")
    return objs


def _area_weighted_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    fn = np.cross(b - a, c - a)  # length = 2 × area
    n = np.zeros_like(v)
    for i in range(3):
        np.add.at(n, f[:, i], fn)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _part(o: SynthObject, *names: str) -> np.ndarray:
    return np.isin(o.part, [o.part_names.index(n) for n in names])


@pytest.mark.parametrize("key", OBJECT_NAMES + ("E_diffuse",))
def test_shapes_dtypes_ranges(objects, key):
    o = objects[key]
    n = len(o.vertices)
    assert o.name == key[0]
    assert o.vertices.shape == (n, 3) and o.vertices.dtype == np.float64
    assert o.faces.ndim == 2 and o.faces.shape[1] == 3 and o.faces.dtype == np.int64
    assert o.faces.min() >= 0 and o.faces.max() < n
    assert np.array_equal(np.unique(o.faces), np.arange(n))  # no unreferenced vertices
    assert o.normals.shape == (n, 3) and o.normals.dtype == np.float64
    assert o.pd.shape == (n, 3) and o.pd.dtype == np.float64
    assert o.ps.shape == (n,) and o.ps.dtype == np.float64
    assert o.roughness.shape == (n,) and o.roughness.dtype == np.float64
    assert o.part.shape == (n,) and o.part.dtype == np.int16
    for arr in (o.vertices, o.normals, o.pd, o.ps, o.roughness):
        assert np.all(np.isfinite(arr))
    assert np.all((o.pd >= 0.02) & (o.pd <= 0.9))
    assert np.all(o.ps >= 0.0)
    assert np.all((o.roughness >= 0.02) & (o.roughness <= 0.6))
    np.testing.assert_allclose(np.linalg.norm(o.normals, axis=1), 1.0, atol=1e-12)
    # every named part is present on the mesh
    assert np.array_equal(np.unique(o.part), np.arange(len(o.part_names)))
    assert isinstance(o.description, str) and o.description.endswith(".")


@pytest.mark.parametrize("name", SOLIDS)
def test_solids_are_closed_outward_and_placed(objects, name):
    o = objects[name]
    mesh = trimesh.Trimesh(o.vertices, o.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0.0
    assert 3_000 <= len(o.vertices) <= 30_000
    lo, hi = o.vertices.min(axis=0), o.vertices.max(axis=0)
    assert -0.005 <= lo[1] <= 0.01  # stands on y = 0
    assert 0.15 <= hi[1] - lo[1] <= 0.25
    centre = 0.5 * (lo + hi)
    assert abs(centre[0]) < 0.03 and abs(centre[2]) < 0.03  # vertical axis is the y axis


@pytest.mark.parametrize("name", SOLIDS)
def test_true_normals_match_mesh(objects, name):
    o = objects[name]
    cos = np.sum(_area_weighted_normals(o.vertices, o.faces) * o.normals, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    assert np.median(angle) < 5.0
    assert np.mean(angle < 30.0) > 0.95


@pytest.mark.parametrize("name", SOLIDS)
def test_low_resolution_still_closed(name):
    o = make_object(name, resolution=16)
    mesh = trimesh.Trimesh(o.vertices, o.faces, process=False)
    assert mesh.is_watertight and mesh.volume > 0.0
    assert len(o.vertices) < len(make_object(name, resolution=24).vertices)


def test_a_beak_and_legs_far_more_specular(objects):
    o = objects["A"]
    glossy = _part(o, "beak", "legs", "feet")
    body = _part(o, "body")
    assert o.ps[glossy].mean() >= 5.0 * o.ps[body].mean()
    assert o.roughness[glossy].max() < o.roughness[body].min()
    assert np.all((o.ps[body] >= 0.03) & (o.ps[body] <= 0.05))
    assert o.pd[body].std(axis=0).min() > 0.1  # dark back, white belly


def test_b_non_uniform_diffuse_and_specular(objects):
    o = objects["B"]
    assert o.pd.std(axis=0).min() > 0.05
    assert o.ps.std() > 0.05 and o.roughness.std() > 0.03
    means = [o.ps[o.part == i].mean() for i in range(len(o.part_names))]
    assert max(means) > 5.0 * min(means)
    assert o.ps[_part(o, "torso")].std() > 0.01  # varies within a part too


@pytest.mark.parametrize("name", ("C", "D"))
def test_c_d_uniform_specular(objects, name):
    o = objects[name]
    assert np.ptp(o.ps) == 0.0 and np.ptp(o.roughness) == 0.0
    assert o.ps[0] > 0.1
    assert o.pd.std(axis=0).min() > 0.03


def test_deterministic():
    a, b = make_object("D", 24), make_object("D", 24)
    for field in ("vertices", "faces", "normals", "pd", "ps", "roughness", "part"):
        assert np.array_equal(getattr(a, field), getattr(b, field))


@pytest.mark.parametrize("key", ("E", "E_diffuse"))
def test_e_plates(objects, key):
    o = objects[key]
    c = np.sqrt(0.5)
    assert o.part_names == ("plate_I", "plate_II")
    assert len(o.vertices) == 2 * 33 * 33
    one, two = o.part == 0, o.part == 1
    np.testing.assert_allclose(o.normals[one], np.tile([0.0, -c, c], (one.sum(), 1)), atol=1e-15)
    np.testing.assert_allclose(o.normals[two], np.tile([0.0, c, c], (two.sum(), 1)), atol=1e-15)
    # plate geometry: on the planes through the x axis, plate I at y >= 0, II at y <= 0
    v = o.vertices
    np.testing.assert_allclose(v[:, 2], np.abs(v[:, 1]), atol=1e-15)
    assert np.all(v[one, 1] >= 0.0) and np.all(v[two, 1] <= 0.0)
    np.testing.assert_allclose([v[:, 0].min(), v[:, 0].max()], [-0.1, 0.1])
    # fold row duplicated: 33 vertices on the x axis per plate
    on_fold = np.all(v[:, 1:] == 0.0, axis=1)
    assert on_fold[one].sum() == 33 and on_fold[two].sum() == 33
    # winding matches the normals; plates face each other
    np.testing.assert_allclose(_area_weighted_normals(v, o.faces), o.normals, atol=1e-12)
    assert np.all(o.part[o.faces] == o.part[o.faces[:, :1]])  # no face spans the fold
    s = fold_coordinate(v)
    assert s.dtype == np.float64 and s.shape == (len(v),)
    np.testing.assert_allclose([s.min(), s.max()], [-0.2, 0.2])
    assert np.all(s[one] >= 0.0) and np.all(s[two] <= 0.0)
    assert np.all(np.isin(np.round(np.abs(s) / 0.00625, 9), np.arange(33)))


def test_e_setups(objects):
    glossy, diffuse = objects["E"], objects["E_diffuse"]
    assert np.all(diffuse.ps == 0.0) and np.allclose(diffuse.pd, 0.8)
    assert np.allclose(glossy.ps, 0.3) and np.allclose(glossy.roughness, 0.08)
    assert np.allclose(glossy.pd, 0.7)
    assert len(make_object("E", resolution=16).vertices) == 2 * 9 * 9


@pytest.mark.parametrize("name", ["A", "B", "C", "D", "E", "V"])
def test_glazed_setup_keeps_pd_and_puts_one_uniform_lobe_over_it(name):
    """'glazed': the object's own mesh and diffuse albedo (E: its glossy paper's), one
    Ward lobe ps 0.3, roughness 0.08 rad everywhere; the default is unchanged."""
    base = make_object(name, resolution=20)
    glazed = make_object(name, resolution=20, setup="glazed")
    np.testing.assert_array_equal(glazed.vertices, base.vertices)
    np.testing.assert_array_equal(glazed.faces, base.faces)
    np.testing.assert_array_equal(glazed.pd, base.pd)
    assert np.all(glazed.ps == 0.3) and np.all(glazed.roughness == 0.08)
    assert "Glazed" in glazed.description
    if name in SOLIDS:  # the default A-D lobes vary over the object; the glaze does not
        assert np.ptp(base.ps) > 0 or base.ps[0] != 0.3
        np.testing.assert_array_equal(make_object(name, resolution=20, setup="glossy").ps, base.ps)


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"name": "F"}, "name"),
        ({"name": "a"}, "name"),
        ({"name": "A", "setup": "matte"}, "setup"),
        ({"name": "E", "setup": "shiny"}, "setup"),
        ({"name": "A", "resolution": 15}, "resolution"),
        ({"name": "E", "resolution": 8}, "resolution"),
        ({"name": "B", "resolution": 32.5}, "resolution"),
    ],
)
def test_bad_arguments(kwargs, word):
    with pytest.raises(ValueError, match=word):
        make_object(**kwargs)
