"""Never a silent wrong answer: physical consistency before fitting (`jaxrefl.scan.checks`),
bounds and honest status after it, warnings when the data say little.

Every scan here is the vase V at resolution 16 under 12 lights of the paper's rack (or
one), so the estimators compile once for the whole file."""

import dataclasses
import logging

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from data_synth.scans import Sensor, direct_radiance, make_scan
from data_synth.zoo import make_cell
from jaxrefl.cli import main
from jaxrefl.methods.auto import AutoOptions, estimate_auto
from jaxrefl.methods.local import MEASURED, POOLED, UNRESOLVED, estimate_local
from jaxrefl.methods.radiosity import RadiosityOptions, estimate_radiosity
from jaxrefl.outputs import render
from jaxrefl.reflectance import brdf
from jaxrefl.scan.checks import ObservationError, check_observations, checked_scan, exclude_bad_lights
from jaxrefl.scan.io import save_scan

LIGHTS = list(range(20, 32))
RAYS = RadiosityOptions(rays=32)


@pytest.fixture(scope="module")
def vase():
    scan, _ = make_scan("V", resolution=16, lights=LIGHTS, sensor=Sensor(noise=0.01, bits=12))
    return scan


@pytest.fixture(scope="module")
def vase_estimate(vase):
    return estimate_local(vase)


def rendered(scan, ps, rough):
    """`scan` re-rendered noise-free (float32 radiance, no saturation) with uniform ps, sigma."""
    ps, sigma = np.full(scan.n_points, ps), np.full(scan.n_points, rough)
    radiance = np.where(scan.valid[..., None], direct_radiance(scan, scan.true_pd, ps, sigma), 0.0)
    return dataclasses.replace(scan, radiance=radiance.astype(np.float32), saturation=None, true_ps=ps,
                               true_sigma=sigma)


def scaled(scan, s):
    """Every length times `s`, intensity times `s^2`: the same observations."""
    return dataclasses.replace(scan, vertices=scan.vertices * s, light_pos=scan.light_pos * s, cam_pos=scan.cam_pos * s,
                               light_intensity=np.asarray(scan.light_intensity) * s * s)


# -- no false alarms on the scans we make ---------------------------------------------------


@pytest.mark.parametrize("name, options", [
    ("A", {}),
    ("V", {"setup": "glazed", "sensor": Sensor(noise=0.01, bits=8)}),
    ("E", {"resolution": 16, "setup": "glossy", "lights": [23, 26, 33, 36], "global_illumination": True,
           "samples": 16}),
    ("E", {"resolution": 16, "setup": "diffuse", "rig": "scanner", "lights": [24, 9, 0, 50, 59]}),
])
def test_synthetic_scans_raise_no_alarm(name, options):
    scan, _ = make_scan(name, **{"resolution": 24, **options})
    report = check_observations(scan)
    assert not report.errors and not report.bad_lights, report.reasons
    assert 0.05 < report.implied_pd < 1.0


@pytest.mark.parametrize("cell", ["coaxial_fold", "ring_ggx", "photometric_sharp", "photometric_piecewise",
                                  "handheld_broad", "sparse_piecewise"])
def test_zoo_rigs_raise_no_alarm(cell):
    """Rigs unlike the paper's (coaxial, turntable, distant-light photometric stereo, hand-held,
    sparse; 8-bit sensors, GGX lobes the models lack)."""
    scan, _ = make_cell(cell, n_points=642)
    report = check_observations(scan)
    assert not report.errors and not report.bad_lights, report.reasons
    # every frame within a factor 2 of the others at most points: far from DARK_RATIO / BRIGHT_RATIO
    assert np.nanmin(report.frame_ratio) > 0.5 and np.nanmax(report.frame_ratio_low) < 2.0


def test_a_good_estimate_carries_no_warning(vase_estimate):
    assert vase_estimate.meta["warnings"] == []
    assert vase_estimate.meta["observation_checks"]["excluded_lights"] == []


# -- nothing to fit -------------------------------------------------------------------------


@pytest.mark.parametrize("spoil, words", [
    (lambda s: {"valid": np.zeros_like(s.valid)}, "masked"),
    (lambda s: {"radiance": np.where(s.valid[..., None], s.saturation, 0.0).astype(np.float32)}, "saturated"),
    (lambda s: {"normals": -s.normals}, "normals probably point inward"),
], ids=["all-masked", "all-saturated", "normals-inward"])
def test_no_valid_observations_is_an_error_naming_the_cause(vase, spoil, words):
    """Was: exit 0, pd = ps = roughness = 0, coverage 0, no message."""
    scan = dataclasses.replace(vase, **spoil(vase))
    for estimator in (estimate_local, lambda s: estimate_radiosity(s, RAYS)):
        with pytest.raises(ObservationError, match="no valid observations") as info:
            estimator(scan)
        assert words in str(info.value) and info.value.cause == "no valid observations"


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_radiance_from_python_is_an_error_naming_the_field(vase, bad):
    """Was: NaN samples went on into the fit with "All-NaN slice" warnings; a file with them
    is refused on load (`validate_scan`), a scan built in Python is refused by the methods."""
    from jaxrefl.scan.io import ScanError

    radiance = np.array(vase.radiance, np.float64)
    radiance[::7, 0, 1] = bad
    scan = dataclasses.replace(vase, radiance=radiance)
    for estimator in (estimate_local, lambda s: estimate_radiosity(s, RAYS)):
        with pytest.raises(ScanError, match="radiance.*non-finite.*valid"):
            estimator(scan)


def test_cli_exits_2_without_observations(vase, tmp_path, capsys):
    path, out = tmp_path / "masked.npz", tmp_path / "r.npz"
    save_scan(path, dataclasses.replace(vase, valid=np.zeros_like(vase.valid)))
    assert main(["estimate", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no valid observations" in err[0] and "masked" in err[0]
    assert not out.exists()


# -- units and exposure ---------------------------------------------------------------------


@pytest.mark.parametrize("change, words", [
    (lambda s: {"vertices": s.vertices * 1000, "light_pos": s.light_pos * 1000, "cam_pos": s.cam_pos * 1000},
     "millimetres"),
    (lambda s: {"radiance": s.radiance * np.float32(1e30), "saturation": None}, "too bright"),
    (lambda s: {"radiance": s.radiance * np.float32(1e-30), "saturation": None}, "darker than any real surface"),
    (lambda s: {"light_intensity": 1e4}, "light intensities too high"),
], ids=["millimetres", "radiance-x1e30", "radiance-x1e-30", "intensity-x1e4"])
def test_implausible_units_or_exposure_is_an_error(vase, change, words):
    """Was: Method I pd = 1.0 everywhere with ps up to 4.6e5, Method II pd up to 9.9e5 (mm);
    Method I pd = 0, Method II pd up to 1e30 (radiance x 1e30)."""
    scan = dataclasses.replace(vase, **change(vase))
    report = check_observations(scan)
    assert [cause for cause, _ in report.errors] == ["units or exposure"]
    assert not 1e-3 <= report.implied_pd <= 3.0
    for estimator in (estimate_local, lambda s: estimate_radiosity(s, RAYS)):
        with pytest.raises(ObservationError, match="units or exposure") as info:
            estimator(scan)
        assert words in str(info.value) and "exposure" in str(info.value)


def test_cli_exits_2_on_millimetres(vase, tmp_path, capsys):
    path, out = tmp_path / "mm.npz", tmp_path / "r.npz"
    # lengths in millimetres, intensities as they were (x 1e6 would make it consistent again)
    save_scan(path, dataclasses.replace(scaled(vase, 1000.0), light_intensity=vase.light_intensity))
    assert main(["estimate", str(path), "--out", str(out), "--method", "radiosity", "--rays", "16"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "units or exposure" in err[0] and "millimetres" in err[0]
    assert not out.exists()


@settings(max_examples=5, deadline=None)
@given(exponent=st.floats(-3.0, 3.0))
def test_scale_invariance(vase, vase_estimate, exponent):
    """Lengths x s with intensity x s^2: the same checks and the same estimate, to a tenth of
    its own standard deviation (the rows agree to 1e-15; the fit's float32 start search and
    finite Gauss-Newton steps leave ~1e-3 std). Rounding may still tip a point that sits on
    the border of a hard decision: a pooled point whose posterior has two equal modes, or one
    whose pd is at the limit of the diffuse prior's conflict test, which also moves the prior
    of its material-mates (0.23 std for 54 points of a material at s = 10^-1.06 on an AMD
    EPYC). So: every measured point within 0.1 std, 90 % of all, 99 % within 0.5 std."""
    scan = scaled(vase, 10.0**exponent)
    assert check_observations(scan).implied_pd == pytest.approx(check_observations(vase).implied_pd, rel=1e-9)
    est, ref = estimate_local(scan), vase_estimate
    np.testing.assert_array_equal(est.status, ref.status)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.c_[np.abs(est.pd - ref.pd) / ref.std_pd, np.abs(est.ps - ref.ps)[:, None] / ref.std_ps[:, None],
                  np.abs(est.roughness - ref.roughness)[:, None] / ref.std_roughness[:, None]]
    z = np.where(np.isfinite(z), z, 0.0).max(1)
    assert np.all(z[est.status == MEASURED] <= 0.1)
    assert np.mean(z <= 0.1) >= 0.9 and np.mean(z <= 0.5) >= 0.99


# -- bad frames -----------------------------------------------------------------------------


def _spoil_frame(scan, k, frame):
    r, valid = scan.radiance.copy(), scan.valid[:, k, None]
    extra = {}
    if frame == "black":
        r[:, k] = 0.0
    elif frame == "saturated":
        r[:, k] = np.where(valid, scan.saturation, 0.0)
    elif frame == "constant":  # blown, no saturation level given
        r[:, k] = np.where(valid, r.max(), 0.0)
        extra["saturation"] = None
    else:  # "bright": a wrong exposure, 30x
        r[:, k] *= 30.0
        extra["saturation"] = None
    return dataclasses.replace(scan, radiance=r, **extra)


@pytest.mark.parametrize("frame", ["black", "saturated", "constant", "bright"])
def test_a_bad_frame_is_excluded_with_a_warning(vase, vase_estimate, frame, caplog):
    """Was (one all-black frame among 12 lights): median pd 0.10 -> 0.0003, 484 points still
    `pd_measured`. Now the frame is found by its implied albedo against the other lights'
    at the same points, masked out with a warning, and the estimate is the 11-light one."""
    k = 5
    scan = _spoil_frame(vase, k, frame)
    report = check_observations(scan)
    assert report.bad_lights == (k,) and not report.errors
    assert report.reasons[k].startswith("dark" if frame == "black" else "blown")
    with caplog.at_level(logging.WARNING, logger="jaxrefl"):
        est = estimate_local(scan)
    assert any(f"light {k} excluded" in m for m in caplog.messages)
    assert est.meta["observation_checks"]["excluded_lights"] == [k]
    assert any(f"light {k} excluded" in w for w in est.meta["warnings"])
    valid = vase.valid.copy()
    valid[:, k] = False
    eleven = estimate_local(dataclasses.replace(scan, valid=valid))
    for field in ("pd", "ps", "roughness", "status", "pd_measured"):
        np.testing.assert_array_equal(getattr(est, field), getattr(eleven, field))
    both = est.pd_measured & vase_estimate.pd_measured  # and near the estimate from all 12 good frames
    assert np.median(np.abs(est.pd - vase_estimate.pd)[both]) < 0.01
    masked = exclude_bad_lights(scan, report)
    assert not masked.valid[:, k].any() and np.array_equal(masked.valid[:, :k], vase.valid[:, :k])


def test_checked_scan_is_idempotent(vase):
    once = checked_scan(_spoil_frame(vase, 3, "black"))
    assert checked_scan(once) is once and once.meta["observation_checks"]["excluded_lights"] == [3]


# -- bounds and honest status -----------------------------------------------------------------


def test_every_method_keeps_pd_in_bounds_with_one_light():
    """Was: Method II pd up to 1.83 (here; 1.03 on the issue's scan) flagged `pd_measured`."""
    scan, _ = make_scan("V", resolution=16, lights=[25], sensor=Sensor(noise=0.01, bits=12))
    for est in (estimate_local(scan), estimate_radiosity(scan, RAYS)):
        assert np.all((est.pd >= 0) & (est.pd <= 1))
        assert np.all(est.ps <= brdf.ps_bound(est.model, np.where(est.roughness > 0, est.roughness, 1.0)) * (1 + 1e-9))
        assert np.all(np.isfinite(est.pd)) and not np.any(est.status == MEASURED)


@pytest.mark.parametrize("precision, ps, rough", [
    ("float32", 0.0, 0.1),     # was: measured points with ps up to 10, std 0 (issue), pd 5 std off (here)
    ("float32", 0.3, 0.005),   # was: 68 measured, ps 100 % off (roughness 1790 % on the scan)
    ("float32", 0.1, 1.0),     # was: 640 measured, pd 5+ std off (pd 0 at std 0.002-0.013 on the issue's)
    ("float64", 0.3, 0.01),    # was: 32 measured, ps and roughness 5+ std off (one height seen twice)
], ids=["ps0-f32", "sharp-f32", "broad-f32", "sharp-f64"])
def test_measured_means_the_own_samples_determine_it(vase, precision, ps, rough):
    """Noise-free scans whose lobes the samples cannot pin (none, too sharp to be seen at two
    heights, too broad to part from pd in float32, the command line's precision): a point is
    `measured` only with finite, non-zero standard deviations and its truth within 5 of them."""
    scan = rendered(vase, ps, rough)
    with jax.enable_x64(precision == "float64"):
        est = estimate_local(scan)
    m = est.status == MEASURED
    for std in (est.std_pd[m], est.std_ps[m], est.std_roughness[m]):
        assert np.all(np.isfinite(std) & (std > 0))
    assert np.all(np.abs(est.pd - scan.true_pd)[m] <= 5 * est.std_pd[m])
    assert np.all(np.abs(est.ps - scan.true_ps)[m] <= 5 * est.std_ps[m])
    if ps > 0:
        assert np.all(np.abs(est.roughness - scan.true_sigma)[m] <= 5 * est.std_roughness[m])
    assert np.all((est.pd >= 0) & (est.pd <= 1))
    assert np.all(est.ps <= brdf.ps_bound(est.model, np.where(est.roughness > 0, est.roughness, 1.0)) * (1 + 1e-9))


# -- warnings -------------------------------------------------------------------------------


def test_most_points_unresolved_is_a_warning(vase, tmp_path, caplog, capsys):
    """Was (Methods I, II, auto on `synth E`): coverage 0, ps and roughness 100 % off, no word
    of warning. A diffuse object (ps = 0) has no lobe anywhere: every method logs a warning on
    its own logger, and the command line prints one line on stderr."""
    scan = rendered(vase, 0.0, 0.1)
    runs = {"jaxrefl.methods.local": lambda: estimate_local(scan), "jaxrefl.methods.radiosity": lambda: estimate_radiosity(scan, RAYS),
            "jaxrefl.methods.auto": lambda: estimate_auto(scan, AutoOptions(radiosity=RAYS, methods=("local", "radiosity")))}
    for logger, run in runs.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="jaxrefl"):
            est = run()
        assert np.mean(est.status[est.pd_measured] == UNRESOLVED) > 0.5
        hits = [r for r in caplog.records if r.name == logger and "unresolved" in r.getMessage()]
        assert len(hits) == 1, (logger, [(r.name, r.getMessage()) for r in caplog.records])
        assert any("unresolved" in w for w in est.meta["warnings"])
    path, out = tmp_path / "diffuse.npz", tmp_path / "r.npz"
    save_scan(path, scan)
    capsys.readouterr()
    assert main(["estimate", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxrefl estimate: warning:") and "unresolved" in err[0]


def test_maps_colour_scale_ignores_unresolved_outliers(vase, vase_estimate):
    """Was: 85 unresolved points at ps = 10 stretched the ps scale and left the map black."""
    ps, status = vase_estimate.ps.copy(), vase_estimate.status.copy()
    known = np.isin(status, (MEASURED, POOLED))
    far = np.flatnonzero(known)[:85]
    ps[far], status[far] = 10.0, UNRESOLVED
    est = dataclasses.replace(vase_estimate, ps=ps, status=status)
    top = render.robust_top(est.ps, est.status)
    assert top == pytest.approx(np.percentile(ps[np.isin(status, (MEASURED, POOLED))], 99))
    assert top < 2 * vase_estimate.ps[known].max()
    fig = render.estimate_figure(est, vase, view="camera", width=48)
    clim = [im.get_clim() for ax in fig.axes for im in ax.get_images()]
    assert (0.0, top) in [tuple(map(float, c)) for c in clim]
