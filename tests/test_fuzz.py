"""Never a silent wrong answer, fuzzed: hypothesis-generated corruptions of a scan bundle
and extreme but valid scans, through load -> estimate -> save -> load -> relight -> export.

Every run ends in a named error (a `ValueError` subclass naming the field or the cause;
exit code 2 and one line on stderr from the command line) or in a finite, bounded, honestly
flagged result, never a traceback. The default run draws a few examples (derandomized by
the conftest profile); the `slow` variants draw many more and add Methods II, III and auto.

Every scan is the vase V at resolution 16 under the 12 lights of `test_checks` (698 points),
changed in place without changing its shapes, so the estimators compile once for the file
(and once for both files in a full run)."""

import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import jaxrefl
from jaxrefl import cli
from jaxrefl.outputs.export import load_ply
from jaxrefl.reflectance import brdf
from jaxrefl.result import check_estimate, load_result
from jaxrefl.scan.checks import ObservationError
from jaxrefl.scan.io import ScanError, save_scan, validate_scan

from .test_checks import LIGHTS, rendered, scaled, vase  # noqa: F401 (vase: the shared fixture)

QUICK = settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
MANY = settings(max_examples=1000, deadline=None, suppress_health_check=list(HealthCheck))
QUICK_SCANS = settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck))
MANY_SCANS = settings(deadline=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def bundle(vase, folder):
    """The vase saved as a bundle: (its path, its arrays by key)."""
    path = folder / "vase.npz"
    save_scan(path, vase)
    with np.load(path) as z:
        return path, {k: z[k] for k in z.files}


# -- corrupted bundles -------------------------------------------------------------------------

REQUIRED = ("format_version", "vertices", "faces", "light_pos", "cam_pos", "light_intensity")
FLOATS = ("vertices", "normals", "light_pos", "cam_pos", "light_intensity", "radiance", "saturation", "true_pd",
          "true_ps", "true_sigma", "true_normals")
#: keys whose values must be >= 0 (radiance, truth) or > 0 (intensity, saturation, sigma)
NON_NEGATIVE = ("radiance", "light_intensity", "saturation", "true_pd", "true_ps", "true_sigma", "faces")
KEYS = ("format_version", "vertices", "faces", "normals", "light_pos", "light_intensity", "cam_pos", "radiance",
        "valid", "saturation", "true_pd", "true_ps", "true_sigma", "true_normals", "meta")


def _wrong_dtype(key, value, choice):
    """`value` in a dtype the format does not allow for `key`."""
    if key == "meta":  # a number or a list of numbers: valid JSON at best, never an object
        return np.full((choice % 3,), 0.5) if choice % 2 else np.float64(0.5)
    kinds = {"faces": (np.float64, np.complex64, "U"), "valid": (np.int8, np.float64, "U"),
             "format_version": (np.float64, np.bool_, "U")}.get(key, (np.complex64, np.bool_, "U"))
    kind = kinds[choice % 3]
    return value.astype(str) if kind == "U" else value.astype(kind)


def _wrong_shape(value, lead):
    """`value` with a leading axis of 1 (`lead`), or one element short along its last axis
    (a scalar becomes two values)."""
    if lead:
        return value[None]
    if value.ndim == 0:
        return np.stack([value, value])
    return value[..., :-1]


def _empty(value):
    return np.zeros((0, *value.shape[1:]), value.dtype) if value.ndim else np.zeros((0,), value.dtype)


def damaged(kind, key=None, *args):
    """One damage: (description, `write(path, arrays, raw_bytes)` writing the damaged file,
    the field its error must name; None: the damage leaves a valid bundle)."""
    description = (kind, key, *args)
    if kind == "truncate":  # key: the share of the bytes kept
        return description, lambda path, arrays, raw: path.write_bytes(raw[: int(len(raw) * key)]), "file"
    if kind == "garbage":  # key: the bytes
        return description, lambda path, arrays, raw: path.write_bytes(key), "file"
    if kind == "npy":  # a plain .npy array under an .npz name
        return description, lambda path, arrays, raw: path.write_bytes(_npy_bytes(arrays["radiance"])), "file"
    if kind == "unknown_key":
        return description, _savez(lambda a: dict(a, colour=np.ones(3))), "colour"
    if kind == "version":  # key: the version number
        return description, _savez(lambda a: dict(a, format_version=np.int64(key))), "format_version"
    if kind == "drop":
        field = key if key in REQUIRED else ("valid" if key == "radiance" else None)
        return description, _savez(lambda a: {k: v for k, v in a.items() if k != key}), field
    change = {
        "dtype": lambda a: _wrong_dtype(key, a[key], *args),
        "shape": lambda a: _wrong_shape(a[key], *args),
        "empty": lambda a: _empty(a[key]),
        "poke": lambda a: _poke(a[key], *args),  # args: (index, value)
    }[kind]
    return description, _savez(lambda a: dict(a, **{key: change(a)})), key


@st.composite
def corruptions(draw):
    """A damage (`damaged`) drawn over every kind, key and value."""
    kind = draw(st.sampled_from(["drop", "dtype", "shape", "nonfinite", "negative", "empty", "truncate",
                                 "garbage", "npy", "unknown_key", "version"]))
    if kind == "truncate":
        return damaged(kind, draw(st.floats(0.0, 0.999)))
    if kind == "garbage":
        return damaged(kind, draw(st.binary(max_size=256)))
    if kind in ("npy", "unknown_key"):
        return damaged(kind)
    if kind == "version":
        return damaged(kind, draw(st.sampled_from([0, 2, -1, 99])))
    if kind in ("drop", "empty"):
        return damaged(kind, draw(st.sampled_from(KEYS)))
    if kind == "dtype":
        return damaged(kind, draw(st.sampled_from(KEYS)), draw(st.integers(0, 5)))
    if kind == "shape":
        return damaged(kind, draw(st.sampled_from(KEYS)), draw(st.booleans()))
    index = draw(st.integers(0, 10**6))
    if kind == "nonfinite":
        return damaged("poke", draw(st.sampled_from(FLOATS)), index, draw(st.sampled_from([np.nan, np.inf, -np.inf])))
    key = draw(st.sampled_from(NON_NEGATIVE))
    return damaged("poke", key, index, -draw(st.integers(1, 10**6)) if key == "faces" else -draw(st.floats(1e-6, 1e30)))


def _poke(value, index, bad):
    out = np.array(value, copy=True)
    out.flat[index % out.size] = bad
    return out


def _npy_bytes(array):
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _savez(change):
    def write(path, arrays, raw):
        np.savez(path, **change(dict(arrays)))
    return write


def run_cli(*args):
    """`jaxrefl <args>` in this process: (exit code, stderr lines)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in args])
    return code, err.getvalue().strip().splitlines()


def _check_corruption(vase_bundle, folder, damage):
    path, arrays = vase_bundle
    description, write, field = damage
    bad, out = folder / "bad.npz", folder / "bad_result.npz"
    for stale in (bad, out):
        if stale.exists():
            stale.unlink()
    write(bad, arrays, path.read_bytes())
    if field is None:  # an optional key dropped: still a valid bundle
        scan = jaxrefl.load_scan(bad)
        assert scan.n_points == len(arrays["vertices"]), description
        return
    with pytest.raises(ScanError) as info:
        jaxrefl.load_scan(bad)
    assert info.value.field == field, (description, str(info.value))
    assert str(info.value).startswith(f"{field}: "), (description, str(info.value))
    code, lines = run_cli("estimate", bad, "--out", out)
    assert code == 2, (description, lines)
    assert len(lines) == 1 and lines[0].startswith(f"jaxrefl estimate: error: {field}: "), (description, lines)
    assert not out.exists()


@QUICK
@given(damage=corruptions())
def test_a_corrupted_bundle_is_refused_naming_the_field(bundle, folder, damage):
    """Each damaged bundle (a key dropped, a wrong dtype or shape, NaN / inf / a negative value
    in each array, empty arrays, truncated bytes, a file that is not an .npz, an unknown key,
    another version) is refused by `load_scan` with a `ScanError` naming the field, and by
    `jaxrefl estimate` with exit code 2, one line naming it and no result file."""
    _check_corruption(bundle, folder, damage)


@pytest.mark.slow
@MANY
@given(damage=corruptions())
def test_a_corrupted_bundle_is_refused_naming_the_field_many(bundle, folder, damage):
    _check_corruption(bundle, folder, damage)


def test_every_key_and_damage_is_refused(bundle, folder):
    """The catalogue behind the fuzzer, once each: every key dropped, in each wrong dtype, in
    both wrong shapes, and empty; NaN and inf in every float array; a negative value in every
    array that must be >= 0; truncated, empty and foreign files."""
    cases = [damaged(kind, key, *args) for key in KEYS
             for kind, args in [("drop", ()), ("empty", ()), ("shape", (False,)), ("shape", (True,))]
             + [("dtype", (c,)) for c in range(3)]]
    cases += [damaged("poke", key, 7, bad) for key in FLOATS for bad in (np.nan, np.inf)]
    cases += [damaged("poke", key, 7, -1) for key in NON_NEGATIVE]
    cases += [damaged("truncate", f) for f in (0.0, 0.5, 0.99)] + [damaged("garbage", b"not an npz"),
                                                                   damaged("npy")]
    for damage in cases:
        _check_corruption(bundle, folder, damage)


# -- extreme but valid scans -------------------------------------------------------------------


@st.composite
def extremes(draw):
    """How to change the vase: lengths x 10^scale (intensity x 10^(2 scale): the same
    observations), radiance and saturation x 10^exposure; optionally re-rendered noise-free
    (or with 1 % noise) with one lobe everywhere, roughness 0.003-1 rad and ps 0 up to the
    energy bound; a share of the observations masked, or all lights but one; the saturation
    level removed, at a quantile of the samples or below them all; a share of the normals
    flipped; one frame black or blown."""
    p = {"scale": draw(st.one_of(st.just(0.0), st.floats(-3.0, 3.0))),
         "exposure": draw(st.one_of(st.just(0.0), st.floats(-1.0, 1.0), st.floats(-30.0, 30.0)))}
    if draw(st.booleans()):
        p["rough"] = draw(st.floats(np.log(0.003), 0.0).map(np.exp))
        p["ps"] = draw(st.one_of(st.just(0.0), st.floats(0.0, 1.0)))  # of min(1, the energy bound)
        p["noise"] = draw(st.sampled_from([0.0, 0.01]))
    p["lights"] = draw(st.one_of(st.just("all"), st.integers(0, len(LIGHTS) - 1), st.floats(0.0, 0.95)))
    p["saturation"] = draw(st.one_of(st.sampled_from(["keep", "none", "all"]), st.floats(0.0, 1.0)))
    p["flip"] = draw(st.one_of(st.just(0.0), st.floats(0.0, 1.0)))
    p["frame"] = draw(st.sampled_from([None, "black", "blown"]))
    return p


def extreme_scan(vase, p):
    """The vase changed as `p` (from `extremes`) says, validated: a scan bundle that
    `save_scan` would write."""
    rng = np.random.default_rng(0)
    scan = vase
    if "rough" in p:
        bound = float(brdf.ps_bound("torrance-sparrow", p["rough"]))
        scan = rendered(scan, p["ps"] * min(1.0, bound), p["rough"])
        if p["noise"]:
            noisy = scan.radiance * (1 + p["noise"] * rng.standard_normal(scan.radiance.shape))
            scan = dataclasses.replace(scan, radiance=np.maximum(noisy, 0).astype(np.float32))
    valid, radiance = scan.valid.copy(), scan.radiance.copy()
    if p["lights"] != "all":
        if isinstance(p["lights"], int):
            valid[:, np.arange(scan.n_lights) != p["lights"]] = False
        else:
            valid &= rng.uniform(size=valid.shape) >= p["lights"]
    if p["frame"] is not None:
        radiance[:, 5] = 0.0 if p["frame"] == "black" else np.where(valid[:, 5, None], 30 * radiance[:, 5], 0.0)
    saturation = scan.saturation
    if p["saturation"] == "none" or p["frame"] == "blown":
        saturation = None
    elif p["saturation"] == "all":
        seen = radiance[valid]
        saturation = float(seen[seen > 0].min()) if (seen > 0).any() else 1.0
    elif not isinstance(p["saturation"], str):
        seen = radiance[valid].max(-1)
        saturation = float(np.quantile(seen, p["saturation"])) if seen.size and seen.max() > 0 else None
        saturation = saturation if saturation else None
    normals = scan.normals.copy()
    normals[rng.uniform(size=scan.n_points) < p["flip"]] *= -1
    exposure = np.float32(10.0 ** p["exposure"])
    scan = dataclasses.replace(scan, valid=valid, radiance=radiance * exposure, normals=normals,
                               saturation=None if saturation is None else saturation * float(exposure))
    return validate_scan(scaled(scan, 10.0 ** p["scale"]))


def assert_bounded(est, scan):
    """Finite, in the documented bounds, honestly flagged (see docs/reliability.md)."""
    n = scan.n_points
    check_estimate(est)  # shapes, dtypes, finite values, std never NaN, status codes
    assert est.pd.shape == (n, 3) and est.ps.shape == est.roughness.shape == est.status.shape == (n,)
    for value in (est.pd, est.ps, est.roughness):
        assert np.all(np.isfinite(value))
    for std in (est.std_pd, est.std_ps, est.std_roughness):
        assert not np.any(np.isnan(std)) and np.all(std >= 0)
    assert np.all((est.pd >= 0) & (est.pd <= 1))
    rough = est.roughness
    lobe = rough > 0
    assert np.all(est.ps[~lobe] == 0)  # roughness 0: no lobe, ps 0 too
    assert np.all((rough[lobe] >= 1e-4 * (1 - 1e-9)) & (rough[lobe] <= np.pi / 2 * (1 + 1e-9)))
    assert np.all(est.ps >= 0)
    assert np.all(est.ps <= brdf.ps_bound(est.model, np.where(lobe, rough, 1.0)) * (1 + 1e-9))
    assert set(np.unique(est.status).tolist()) <= {int(s) for s in jaxrefl.Status}
    measured = est.status == jaxrefl.Status.MEASURED
    for std in (est.std_pd[measured], est.std_ps[measured], est.std_roughness[measured]):
        assert np.all(np.isfinite(std) & (std > 0))
    observed = est.pd_measured
    if observed.any():
        status = est.status[observed]
        known = np.mean(np.isin(status, (jaxrefl.Status.MEASURED, jaxrefl.Status.POOLED)))
        if np.mean(status == jaxrefl.Status.UNRESOLVED) > 0.5:
            assert any("unresolved" in w for w in est.meta["warnings"])
        elif known < 0.5:
            assert any("measured or pooled" in w for w in est.meta["warnings"])


def through_everything(scan, method, folder):
    """estimate -> save -> load -> relight -> PLY; None after a named error, else the estimate."""
    try:
        est = jaxrefl.estimate(scan, method=method, progress=False)
    except ValueError as exc:
        named = isinstance(exc, ObservationError) and exc.cause or isinstance(exc, ScanError) and exc.field
        assert named and str(exc).startswith(f"{named}: "), repr(exc)
        return None
    assert_bounded(est, scan)
    est.save(folder / "result.npz")
    back = load_result(folder / "result.npz")
    for name in ("pd", "ps", "roughness", "status", "std_pd", "std_ps", "std_roughness", "pd_measured"):
        np.testing.assert_array_equal(getattr(back, name), getattr(est, name))
    light = scan.light_positions()[0, 0]
    image = back.relight(scan, light, width=24, height=16)
    on = ~np.isnan(image)
    assert on.any() and np.all(np.isfinite(image[on])) and np.all(image[on] >= 0)
    direct = jaxrefl.outputs.relight.relight(scan.vertices, scan.faces, scan.normals, back, light,
                                     float(scan.intensities()[0]), scan.camera_positions()[0, 0])
    assert np.all(np.isfinite(direct)) and np.all(direct >= 0)
    back.to_ply(folder / "result.ply", scan)
    mesh = load_ply(folder / "result.ply")
    attrs = mesh.vertex_attributes
    np.testing.assert_array_equal(attrs["status"], est.status.astype(np.uint8))
    np.testing.assert_array_equal(attrs[PLY_ROUGHNESS[est.model]], est.roughness.astype(np.float32))
    for name in ("pd_r", "pd_g", "pd_b", "ps"):
        assert np.all(np.isfinite(attrs[name]))
    json.dumps(back.meta)  # the result's meta stays JSON
    return est


#: the PLY property of each model's roughness (Ward's is not `alpha`: the colour's channel)
PLY_ROUGHNESS = {"torrance-sparrow": "sigma", "ward": "ward_alpha"}


def test_ply_round_trip_for_both_models(vase, folder):
    """Was: a Ward result (Method III, `Local(model="ward")`) wrote its roughness as a second
    `alpha` property beside the colour's, and the PLY could not be read back ("PLY is
    unexpected length!"; found by the Method III fuzz below)."""
    n = vase.n_points
    rng = np.random.default_rng(1)
    for model in PLY_ROUGHNESS:
        est = jaxrefl.Estimate(rng.uniform(size=(n, 3)), rng.uniform(size=n), rng.uniform(0.01, 0.5, n),
                               rng.integers(0, 4, n).astype(np.int8), np.full((n, 3), 0.01), np.full(n, np.inf),
                               np.full(n, 0.02), np.ones(n, bool), np.ones(n, bool), model, {"model": model},
                               rng.integers(0, 6, n))
        est.to_ply(folder / f"{model}.ply", vase)
        mesh = load_ply(folder / f"{model}.ply")
        attrs = mesh.vertex_attributes
        np.testing.assert_array_equal(attrs[PLY_ROUGHNESS[model]], est.roughness.astype(np.float32))
        assert np.all(attrs[f"std_{PLY_ROUGHNESS[model]}"] == np.float32(0.02)) and np.all(attrs["std_ps"] == np.inf)
        np.testing.assert_array_equal(attrs["status"], est.status)
        np.testing.assert_array_equal(attrs["material"], est.material)
        assert np.all(mesh.visual.vertex_colors[:, 3] == 255) and len(mesh.vertices) == n


PS0 = {"scale": 0.0, "exposure": 0.0, "rough": 0.1, "ps": 0.0, "noise": 0.0, "lights": "all", "saturation": "none",
       "flip": 0.0, "frame": None}


def _extreme_examples(test):
    """The issue's cases, always run: true ps 0 noise-free, roughness 0.003 and 1 rad, one
    light, every sample saturated, one black frame, millimetres with intensities x 1e6."""
    for p in (PS0, dict(PS0, ps=0.5, rough=0.003), dict(PS0, ps=1.0, rough=1.0, noise=0.01),
              dict(PS0, lights=3), dict(PS0, saturation="all"), dict(PS0, frame="black", ps=0.3),
              dict(PS0, scale=3.0, exposure=0.0, ps=0.3)):
        test = example(p=p)(test)
    return test


@QUICK_SCANS
@_extreme_examples
@given(p=extremes())
def test_extreme_scans_end_named_or_bounded(vase, folder, p):
    """Method I on extreme but valid scans: a named `ValueError`, or a result that is
    finite, in its bounds, honestly flagged, and survives save, load, relight and export."""
    through_everything(extreme_scan(vase, p), jaxrefl.Local(), folder)


def slow_method(name, scale):
    """Method `name` with few rays / photons / iterations. `light_bin` is in metres: scaled
    with the scan, so that a scan x 1e3 keeps the unscaled number of light configurations
    (with the default 0.1 m, Method III took ~4 min on one such scan; ~20 s unscaled)."""
    light_bin = 0.1 * 10.0**scale
    radiosity = jaxrefl.Radiosity(rays=16, outer=1, light_bin=light_bin)
    return {"local": jaxrefl.Local(),
            "radiosity": radiosity,
            "auto": jaxrefl.Auto(methods=("local", "radiosity"), radiosity=radiosity),
            "photon": jaxrefl.Photon(photons=5_000, iterations=2, check_every=1, gather_rays=64, polish=2,
                                     light_bin=light_bin)}[name]


@pytest.mark.slow
@pytest.mark.parametrize("method, examples", [("local", 100), ("radiosity", 30), ("auto", 20), ("photon", 8)])
def test_extreme_scans_end_named_or_bounded_many(vase, folder, method, examples):
    """Methods I, II, auto and III on many more extreme scans (Method III: ~20 s each)."""

    @settings(MANY_SCANS, max_examples=examples)
    @_extreme_examples
    @given(p=extremes())
    def run(p):
        through_everything(extreme_scan(vase, p), slow_method(method, p["scale"]), folder)

    run()
