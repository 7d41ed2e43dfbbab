"""Method I: closed forms, recovery of noise-free parameters, calibration, hard cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from data_synth.scans import Sensor, direct_radiance, make_scan
from jaxrefl.capture.select import select_lights
from jaxrefl.methods.local import (
    INTERPOLATED,
    MEASURED,
    POOLED,
    UNRESOLVED,
    LocalOptions,
    estimate_local,
    fit_rows,
    specular_closed_form,
)
from jaxrefl.reflectance import brdf
from jaxrefl.reflectance.classify import T_DIFF, T_INVALID, T_NONE, T_SPEC, classify_scan

from .helpers import unit


def _reflect(wo, h):
    return 2 * np.sum(wo * h, -1, keepdims=True) * h - wo


def synthetic_rows(rng, n, m, model, rough=None, ps=None, spec_samples=5, grazing=False):
    """Rows with random reflectance and geometry (normal +z), noise-free radiance.

    The first `spec_samples` lights sit inside the specular lobe (half-vector angle
    up to 1.5 roughness, within 20 degrees), the rest between 20 and 50 degrees."""
    pd = rng.uniform(0.05, 0.9, (n, 3))
    ps = rng.uniform(0.05, 1.0, n) if ps is None else np.full(n, ps)
    rough = rng.uniform(0.03, 0.4, n) if rough is None else np.full(n, rough)
    tv = rng.uniform(0, np.radians(89.9 if grazing else 50), n)
    pv = rng.uniform(0, 2 * np.pi, n)
    wo = np.stack([np.sin(tv) * np.cos(pv), np.sin(tv) * np.sin(pv), np.cos(tv)], -1)
    th = np.where(np.arange(m)[None] < spec_samples,
                  rng.uniform(0, 1, (n, m)) * np.minimum(1.5 * rough[:, None], np.radians(20)),
                  rng.uniform(np.radians(21), np.radians(50), (n, m)))
    ph = rng.uniform(0, 2 * np.pi, (n, m))
    h = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    wi = unit(_reflect(wo[:, None], h))
    cos_i, cos_o = wi[..., 2], np.broadcast_to(wo[:, None, 2], (n, m))
    theta_r = np.arctan2(np.linalg.norm(np.cross([0, 0, 1.0], h), axis=-1), h[..., 2])
    use = cos_i > 1e-3
    e = np.where(use, rng.uniform(0.5, 2.0, (n, m)) * np.maximum(cos_i, 0), 0.0)
    full, _ = brdf.MODELS[model]
    f = jax.vmap(jax.vmap(full, in_axes=(None, None, None, 0, 0, 0)))(
        jnp.asarray(pd), jnp.asarray(ps), jnp.log(jnp.asarray(rough)), cos_i, cos_o, theta_r)
    y = np.where(use[..., None], np.asarray(f) * e[..., None], 0.0)
    classes = np.where(~use, T_INVALID, np.where(theta_r <= np.radians(20), T_SPEC,
                                                 np.where(theta_r > np.radians(60), T_DIFF, T_NONE)))
    rows = {"y": y, "e": e, "cos_i": cos_i, "cos_o": np.asarray(cos_o), "theta_r": theta_r, "use": use,
            "classes": classes.astype(np.int8)}
    return rows, pd, ps, rough


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_noise_free_parameters_are_recovered(model, seed):
    rows, pd, ps, rough = synthetic_rows(np.random.default_rng(seed), 64, 10, model)
    fit = fit_rows(rows, LocalOptions(model=model))
    assert fit["identifiable"].mean() > 0.95
    ok = fit["identifiable"]
    np.testing.assert_allclose(fit["pd"][ok], pd[ok], rtol=1e-4)
    np.testing.assert_allclose(fit["ps"][ok], ps[ok], rtol=1e-4)
    np.testing.assert_allclose(fit["roughness"][ok], rough[ok], rtol=1e-4)


def test_two_sample_closed_form_is_equation_7():
    """i_s cos(theta_v) = ps exp(-theta_r^2 / 2 sigma^2) at two samples, solved exactly."""
    ps, sigma = 0.37, 0.083
    t1, t2 = 0.02, 0.11
    z = np.array([[ps * np.exp(-t1**2 / (2 * sigma**2)), ps * np.exp(-t2**2 / (2 * sigma**2))]])
    ln_ps, ln_sigma, ok = specular_closed_form("torrance-sparrow", jnp.asarray(z),
                                               jnp.asarray([[t1**2, t2**2]]), jnp.ones((1, 2), bool))
    # Eq. 7 by hand: ln z1 - ln z2 = (t2^2 - t1^2) / (2 sigma^2).
    sigma_eq7 = np.sqrt((t2**2 - t1**2) / (2 * np.log(z[0, 0] / z[0, 1])))
    ps_eq7 = z[0, 0] * np.exp(t1**2 / (2 * sigma_eq7**2))
    assert bool(ok[0])
    assert float(np.exp(ln_sigma[0])) == pytest.approx(sigma_eq7, rel=1e-12)
    assert float(np.exp(ln_ps[0])) == pytest.approx(ps_eq7, rel=1e-12)
    assert sigma_eq7 == pytest.approx(sigma, rel=1e-12)
    # Ward: ln z = ln(ps / alpha^2) - tan^2 / alpha^2.
    alpha = 0.07
    x = np.tan([t1, t2]) ** 2
    zw = ps / alpha**2 * np.exp(-x / alpha**2)
    ln_ps_w, ln_alpha, ok = specular_closed_form("ward", jnp.asarray(zw[None]), jnp.asarray(x[None]),
                                                 jnp.ones((1, 2), bool))
    assert float(np.exp(ln_alpha[0])) == pytest.approx(alpha, rel=1e-12)
    assert float(np.exp(ln_ps_w[0])) == pytest.approx(ps, rel=1e-12)
    # Equal angles or a non-decaying lobe: no solution, flagged.
    _, _, ok = specular_closed_form("torrance-sparrow", jnp.asarray(z), jnp.asarray([[t1**2, t1**2]]),
                                    jnp.ones((1, 2), bool))
    assert not bool(ok[0])


@pytest.fixture(scope="module")
def convex_noisy():
    plan, _ = make_scan("V", resolution=64)
    m = classify_scan(plan, use_observations=False)
    selected = select_lights(m.diffuse_only, m.strong_specular, m.seen, weights=m.pixel_weight).selected
    scan, _ = make_scan("V", resolution=64, lights=selected, sensor=Sensor(noise=0.01, bits=8), seed=3)
    return scan, estimate_local(scan)


def test_convex_object_accuracy(convex_noisy):
    scan, est = convex_noisy
    known = (est.status == MEASURED) | (est.status == POOLED)
    rel = lambda a, b: np.abs(a - b) / b  # noqa: E731
    for mask in (known, est.pd_measured):  # the lobes known, and every observed point
        assert np.median(rel(est.pd, scan.true_pd)[mask]) <= 0.01
        assert np.median(rel(est.ps, scan.true_ps)[mask]) <= 0.05
        assert np.median(rel(est.roughness, scan.true_sigma)[mask]) <= 0.05
    # Every point with a strong-specular sample has its lobe measured or pooled, but those
    # whose samples reject the prior (few, and kept as their own fit, unresolved), and so do
    # most others (their material's lobe, fitted from all its points).
    with_spec = (classify_scan(scan).classes == T_SPEC).any(1)
    conflicts = est.meta["points_in_conflict_with_prior"]
    assert conflicts <= 0.002 * est.pd_measured.sum() and (~known[with_spec]).sum() <= conflicts
    assert known.sum() >= 0.9 * est.pd_measured.sum()


def test_residual_scale_is_the_noise_in_the_weights_units():
    """`meta['residual_scale']`: the median point's residual variance in the units of the weights
    (1 % relative noise) is the sensor's noise where the model fits: about 1 at 1 % noise and 9
    times that at 3 %; a region's own median is reported apart (here the lower half of the vase,
    no different from the rest)."""
    lights = [23, 24, 25, 26, 34, 35, 36]
    medians = []
    for noise in (0.01, 0.03):
        scan, _ = make_scan("V", resolution=32, lights=lights, sensor=Sensor(noise=noise, bits=16), seed=5)
        region = scan.vertices[:, 1] < np.median(scan.vertices[:, 1])
        rs = estimate_local(scan, region=region).meta["residual_scale"]
        medians.append(rs["median"])
        assert rs["region_median"] == pytest.approx(rs["median"], rel=0.3)
    assert 0.6 <= medians[0] <= 1.6
    assert 7.0 <= medians[1] / medians[0] <= 11.0
    assert estimate_local(scan).meta["residual_scale"]["region_median"] is None
    with pytest.raises(ValueError, match="region"):
        estimate_local(scan, region=np.ones(3, bool))


def test_uncertainty_is_calibrated(convex_noisy):
    """55-80 % of measured points lie within one reported standard deviation (68 % ideal);
    pooled points at least 55 % (their prior's width is measured on the points with their
    own lobe, which on this vase are the harder ones: it errs on the wide side)."""
    scan, est = convex_noisy
    for code, top in ((MEASURED, 0.80), (POOLED, 1.0)):
        mask = est.status == code
        assert mask.sum() > 100
        for value, truth, std in ((est.pd, scan.true_pd, est.std_pd), (est.ps, scan.true_ps, est.std_ps),
                                  (est.roughness, scan.true_sigma, est.std_roughness)):
            inside = (np.abs(value - truth) <= std)[mask].mean()
            assert 0.55 <= inside <= top, (code, inside)


def test_outputs_are_finite_and_flagged(convex_noisy):
    scan, est = convex_noisy
    for a in (est.pd, est.ps, est.roughness):
        assert np.all(np.isfinite(a))
    for a in (est.std_pd, est.std_ps, est.std_roughness):
        assert not np.any(np.isnan(a))
    assert np.all(est.status[~est.specular_identifiable] != MEASURED)
    # A lobe not measured at the point is either the posterior of its prior (pooled, finite
    # std) or copied from the nearest known lobes (unresolved, std unknown).
    pooled = est.status == POOLED
    assert pooled.sum() == est.meta["points_pooled"] > 0
    assert np.all(np.isfinite(est.std_ps[pooled])) and np.all(np.isfinite(est.std_roughness[pooled]))
    unresolved = est.status == UNRESOLVED
    assert np.all(np.isinf(est.std_ps[unresolved]))


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
def test_specular_below_noise_is_flagged(model):
    rng = np.random.default_rng(5)
    rows, pd, _, _ = synthetic_rows(rng, 32, 10, model, ps=1e-6)
    rows["y"] = rows["y"] * (1 + 0.01 * rng.standard_normal(rows["y"].shape))
    fit = fit_rows(rows, LocalOptions(model=model))
    assert not fit["identifiable"].any()
    assert all(np.all(np.isfinite(fit[k])) for k in ("pd", "ps", "roughness"))


@pytest.mark.parametrize("m", [5, 8])
def test_no_lobe_without_a_sample_near_the_peak(m):
    """Model mismatch: diffuse points (ps = 0) seen only between 21 and 50 degrees, with
    interreflected light (independent of the light's incidence, so relative to the direct
    light it grows like 1 / cos_i) and noise shared by the RGB channels (Monte Carlo).
    A broad "lobe" fits that trend well above its own row noise (the earlier rule took
    12-24 % of these rows); without a T_spec sample it is not evidence of a lobe."""
    rng = np.random.default_rng(21)
    rows, pd, _, _ = synthetic_rows(rng, 400, m, "torrance-sparrow", ps=0.0, spec_samples=0)
    normal_incidence = rows["e"] / np.maximum(rows["cos_i"], 1e-3)
    y = rows["y"] + np.where(rows["use"], 0.2 * normal_incidence, 0.0)[..., None] * pd[:, None] / np.pi
    rows["y"] = y * (1 + 0.01 * rng.standard_normal(y.shape[:2]))[..., None]
    gated = LocalOptions(prior=False)  # with the prior the test is per material: see the fold test
    fit = fit_rows(rows, gated)
    assert not fit["identifiable"].any()
    # One T_spec sample of a real lobe (and its flanks) is enough again, mostly: 80.5 % (m = 5)
    # and 88 % here, 79 % on a GPU (the float32 start search rounds otherwise); the binomial
    # sd of a share near 80 % of 400 rows is 2 %, so the bound sits 2.5 of them below.
    rows, _, _, _ = synthetic_rows(np.random.default_rng(22), 400, m, "torrance-sparrow", spec_samples=1)
    assert fit_rows(rows, gated)["identifiable"].mean() > 0.75


def test_fold_object_pd_rises_toward_the_fold():
    """Object E (white paper, ps = 0) with interreflections on the scanner (paper Figs.
    12-13): no sample is strong-specular, so no lobe is measured or pooled anywhere, and
    the interreflected light goes to pd, which rises toward the fold (the spurious broad
    lobes of the earlier rule took it instead: pd fell to 0.06 at the fold). Points on the
    fold line, seen exactly edge-on, have no usable sample."""
    from data_synth.objects import fold_coordinate
    from jaxrefl.methods.local import prepare_rows

    scan, _ = make_scan("E", resolution=24, setup="diffuse", rig="scanner", lights=[24, 9, 0, 50, 59],
                        global_illumination=True, samples=256, seed=0)
    est = estimate_local(scan)
    assert not est.specular_identifiable.any() and est.meta["points_pooled"] == 0
    assert not any(m["identifiable"] for m in est.meta["material_lobes"])
    assert np.all(est.ps == 0) and np.all(est.status != MEASURED)
    assert np.all(np.isfinite(est.pd)) and np.all((est.pd >= 0) & (est.pd <= 1))
    rows = prepare_rows(scan)
    assert not np.any(rows["use"] & (np.minimum(rows["cos_i"], rows["cos_o"]) <= brdf.COS_FLOOR))
    d = np.abs(fold_coordinate(scan.vertices))
    grey = est.pd.mean(1)
    edges = [0.0, 0.02, 0.05, 0.1, 0.15, 0.21]
    profile = [np.median(grey[(d >= a) & (d < b) & est.pd_measured]) for a, b in zip(edges[:-1], edges[1:])]
    assert np.all(np.diff(profile) <= 0.005), profile  # falls away from the fold ...
    assert profile[0] > 0.95 and profile[-1] < 0.9 and profile[-1] > 0.8  # ... to above the truth, 0.8


def test_pooled_lobes_relight_a_sharp_highlight_better():
    """A sharp glaze (sigma 0.02 rad) on the convex object, fitted under the selected lights
    (1 % noise, 8 bits), relit under the 52 others: pooling lobes across same-material
    neighbours beats window interpolation, which beats plain per-point fits, and the
    shared prior (the default) does as well as the pool
    (benchmarks/RESULTS_local.md has the full-resolution numbers)."""
    import dataclasses

    from data_synth.scans import apply_sensor
    from jaxrefl.methods.local import prepare_rows

    plan, _ = make_scan("V", resolution=32)
    m = classify_scan(plan, use_observations=False)
    selected = select_lights(m.diffuse_only, m.strong_specular, m.seen, weights=m.pixel_weight).selected
    held = np.setdiff1d(np.arange(plan.n_lights), selected)
    ps, sigma = np.full(plan.n_points, 0.4), np.full(plan.n_points, 0.02)
    truth = direct_radiance(plan, plan.true_pd, ps, sigma)
    scan, _ = make_scan("V", resolution=32, lights=selected)
    observed, level = apply_sensor(truth[:, selected], scan.valid, Sensor(noise=0.01, bits=8),
                                   np.random.default_rng(3))
    scan = dataclasses.replace(scan, radiance=np.where(scan.valid[..., None], observed, 0.0).astype(np.float32),
                               saturation=level, true_ps=ps, true_sigma=sigma)
    lit = m.measurable[:, held]

    def relit_error(pd, ps_e, sigma_e):
        pred = direct_radiance(plan, pd, ps_e, np.maximum(sigma_e, 1e-6))[:, held]
        return np.sqrt(np.sum((pred - truth[:, held])[lit] ** 2) / np.sum(truth[:, held][lit] ** 2))

    plain = fit_rows(prepare_rows(scan))
    pooled = estimate_local(scan, LocalOptions(prior=False))
    window = estimate_local(scan, LocalOptions(prior=False, pool=False))
    shared = estimate_local(scan)
    assert pooled.meta["points_with_pooled_lobe"] > 0
    errors = [relit_error(plain["pd"], plain["ps"], plain["roughness"]),
              relit_error(window.pd, window.ps, window.roughness),
              relit_error(pooled.pd, pooled.ps, pooled.roughness),
              relit_error(shared.pd, shared.ps, shared.roughness)]
    # (The window fills from own lobes seen at two heights only: the 128 rows here that saw
    # one height in two mirror-symmetric lights, ps 66 % off at 12 reported std, no longer
    # spread, so the window comes near the pool.)
    assert errors[2] <= errors[1] < 0.85 * 0.85 * errors[0], errors
    assert errors[3] <= 1.05 * errors[2], errors  # as good as the gated pool here (one lobe, seen often)


@pytest.mark.parametrize("rough", [0.01, 0.5])
def test_extreme_roughness(rough):
    rows, pd, ps, _ = synthetic_rows(np.random.default_rng(6), 32, 10, "torrance-sparrow", rough=rough)
    fit = fit_rows(rows, LocalOptions(steps=40))
    ok = fit["identifiable"]
    assert ok.mean() > 0.9
    np.testing.assert_allclose(fit["roughness"][ok], rough, rtol=1e-3)
    np.testing.assert_allclose(fit["ps"][ok], ps[ok], rtol=1e-3)


def test_grazing_geometry_and_exact_peak_stay_finite():
    rng = np.random.default_rng(7)
    rows, pd, ps, rough = synthetic_rows(rng, 32, 8, "ward", grazing=True)
    rows["theta_r"][:, 0] = 0.0  # an exact mirror sample
    fit = fit_rows(rows, LocalOptions(model="ward"))
    assert all(np.all(np.isfinite(fit[k])) for k in ("pd", "ps", "roughness"))
    assert not any(np.any(np.isnan(fit[k])) for k in ("std_pd", "std_ps", "std_roughness"))


def test_saturated_samples_are_not_fitted():
    clean, _ = make_scan("V", resolution=32, lights=[23, 24, 25, 26, 34, 35, 36])
    top = float(np.percentile(clean.radiance[clean.valid].max(-1), 97))
    scan, _ = make_scan("V", resolution=32, lights=[23, 24, 25, 26, 34, 35, 36],
                        sensor=Sensor(full_scale=top, saturate=True))
    est = estimate_local(scan)
    saturated = np.any(scan.radiance >= scan.saturation, -1).any(1)
    assert saturated.sum() > 10
    measured = est.status == MEASURED
    # Clipped highlights would drag ps down if they were fitted: they are not.
    rel = np.abs(est.ps - scan.true_ps) / scan.true_ps
    assert np.median(rel[measured & saturated]) < 1e-3


def test_point_seen_by_one_light_only():
    rng = np.random.default_rng(8)
    rows, pd, ps, rough = synthetic_rows(rng, 16, 6, "torrance-sparrow", spec_samples=0)
    rows["use"][:, 1:] = False
    rows["classes"][:, 1:] = T_INVALID
    rows["e"][:, 1:] = 0.0
    fit = fit_rows(rows, LocalOptions())
    assert not fit["identifiable"].any()
    assert all(np.all(np.isfinite(fit[k])) for k in ("pd", "ps", "roughness"))


def test_interpolated_points_get_neighbour_values():
    scan, _ = make_scan("V", resolution=16, lights=[24, 25, 34, 35])
    est = estimate_local(scan, LocalOptions(prior=False, pool=False))
    interp = est.status == INTERPOLATED
    assert interp.any() and (est.status == MEASURED).any()
    assert np.all(np.isfinite(est.ps[interp])) and np.all(est.ps[interp] > 0)
    assert np.all(np.isinf(est.std_roughness[interp]))


def test_paper_mode_runs_and_is_no_better():
    scan, _ = make_scan("V", resolution=32, lights=[14, 24, 25, 34, 35, 45], sensor=Sensor(noise=0.01))
    ours, paper = estimate_local(scan), estimate_local(scan, LocalOptions(paper=True))
    both = (ours.status == MEASURED) & (paper.status == MEASURED)
    assert both.sum() > 50
    err = lambda e: np.median(np.abs(e.pd - scan.true_pd)[both] / scan.true_pd[both])  # noqa: E731
    assert err(ours) <= err(paper)


@pytest.mark.parametrize("model, rough", [("torrance-sparrow", 0.05), ("ward", 0.07)])
def test_pooled_lobe_recovers_what_single_points_cannot(model, rough):
    """Neighbours of one material (albedos within 3 %) each see the lobe once: their own fits
    cannot tell ps from roughness, pooled (each keeping its own albedo) they pin it down,
    with calibrated standard deviations."""
    from jaxrefl.reflectance.pool import pooled_specular

    n = 500  # one chunk of 500 rows, 8 observations: the compiled fit of the tests above
    rng = np.random.default_rng(11)
    rows, pd, _, _ = synthetic_rows(rng, n, 8, model, rough=rough, ps=0.5, spec_samples=1)
    pd = pd[0] * rng.uniform(0.97, 1.03, (n, 1))  # re-render the same geometry, one material
    full, _ = brdf.MODELS[model]
    f = jax.vmap(jax.vmap(full, in_axes=(None, None, None, 0, 0, 0)), in_axes=(0, None, None, 0, 0, 0))(
        jnp.asarray(pd), 0.5, np.log(rough), rows["cos_i"], rows["cos_o"], rows["theta_r"])
    clean = np.asarray(f) * rows["e"][..., None]
    rows["y"] = np.where(rows["use"][..., None], clean * (1 + 0.01 * rng.standard_normal(clean.shape)), 0.0)
    own = fit_rows(rows, LocalOptions(model=model))
    strip = np.c_[np.linspace(0, 0.06, n), np.zeros(n), np.zeros(n)]  # neighbours 0.1 mm apart
    pooled = pooled_specular(rows, own["pd"], strip, model, k=12, radius=1.0)
    assert own["identifiable"].mean() < 0.05 < 0.95 < pooled["identifiable"].mean()
    good = pooled["identifiable"]
    assert np.median(np.abs(pooled["roughness"][good] / rough - 1)) < 0.01
    assert np.median(np.abs(pooled["ps"][good] / 0.5 - 1)) < 0.01
    for value, truth, std in ((pooled["ps"], 0.5, pooled["std_ps"]), (pooled["roughness"], rough, pooled["std_roughness"])):
        assert 0.5 <= np.mean(np.abs(value - truth)[good] <= std[good]) <= 0.85


def test_pooled_lobe_needs_strong_specular_evidence():
    """The same rows with no sample near any lobe (all between 21 and 50 degrees) and an
    interreflection-like trend: no pooled lobe, however well a broad one would fit."""
    from jaxrefl.reflectance.pool import pooled_specular

    n = 200
    rng = np.random.default_rng(23)
    rows, pd, _, _ = synthetic_rows(rng, n, 8, "torrance-sparrow", ps=0.0, spec_samples=0)
    pd[:] = pd[0]
    normal_incidence = rows["e"] / np.maximum(rows["cos_i"], 1e-3)
    rows["y"] = rows["y"] + np.where(rows["use"], 0.2 * normal_incidence, 0.0)[..., None] * pd[:, None] / np.pi
    strip = np.c_[np.linspace(0, 0.02, n), np.zeros(n), np.zeros(n)]
    pooled = pooled_specular(rows, pd, strip, "torrance-sparrow", k=12, radius=1.0)
    assert not pooled["identifiable"].any()
    assert np.all(pooled["ps"] == 0) and np.all(np.isinf(pooled["std_ps"]))


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
def test_no_noise_free_row_is_left_in_a_wrong_basin(model, monkeypatch):
    """16,000 noise-free rows: every one recovered to 1e-4, none stuck in a false minimum
    (coarse roughness grids without the Newton-predicted start left 1-14 per 15k). In
    chunks of 500 rows: each row's fit is the same, and so is the compiled fit of the
    64-row tests above (the 4000-row chunks of large scans: `convex_noisy`)."""
    from jaxrefl.methods import local

    monkeypatch.setattr(local, "_CHUNK", 500)
    rows, pd, ps, rough = synthetic_rows(np.random.default_rng(12), 16_000, 10, model)
    fit = fit_rows(rows, LocalOptions(model=model))
    est, truth = np.c_[fit["pd"], fit["ps"], fit["roughness"]], np.c_[pd, ps, rough]
    assert np.all(np.abs(est - truth) <= 1e-4 * truth), np.flatnonzero(np.any(np.abs(est - truth) > 1e-4 * truth, 1))


def test_bounded_linear_solve_matches_scipy():
    """The exact solve of pd in [0, 1], ps >= 0 for a fixed roughness, against scipy's
    bounded least squares on the explicit design matrix, with bounds active and not."""
    from scipy.optimize import lsq_linear

    from jaxrefl.methods.lm import bounded_arrow_solve

    rng = np.random.default_rng(13)
    n, m = 300, 8
    a = rng.uniform(0.1, 2.0, (m, n))  # d pred / d pd_c
    b = rng.uniform(0.0, 3.0, (m, n)) * (rng.uniform(size=(m, n)) < 0.7)  # d pred / d ps
    w = rng.uniform(0.5, 2.0, (m, 3, n))
    truth = np.r_[rng.uniform(-0.5, 1.5, (3, n)), rng.uniform(-0.5, 1.5, (1, n))]  # outside the bounds too
    y = a[:, None] * truth[None, :3] + (b * truth[3])[:, None] + 0.2 * rng.standard_normal((m, 3, n))
    s11 = (w * a[:, None] ** 2).sum(0)
    s12 = (w * (a * b)[:, None]).sum(0)
    s22 = (w * (b * b)[:, None]).sum((0, 1))
    b1 = (w * a[:, None] * y).sum(0)
    b2 = (w * b[:, None] * y).sum((0, 1))
    u, v, free = bounded_arrow_solve(list(s11), list(1.0 / s11), list(s12), s22, list(b1), b2)
    got = np.r_[np.asarray(u), np.asarray(v)[None]]
    ref = np.empty((4, n))
    for i in range(n):  # the reference is a per-row scipy call by design
        design = np.zeros((m, 3, 4))
        design[:, np.arange(3), np.arange(3)] = a[:, i, None]
        design[:, :, 3] = b[:, i, None]
        sw = np.sqrt(w[..., i])[..., None]
        ref[:, i] = lsq_linear((design * sw).reshape(-1, 4), (y[..., i] * sw[..., 0]).ravel(),
                               bounds=([0, 0, 0, 0], [1, 1, 1, np.inf]), tol=1e-14).x
    assert (got[:3] == 0).any() and (got[:3] == 1).any() and (got[3] == 0).any()
    np.testing.assert_allclose(got, ref, atol=1e-8)
    np.testing.assert_array_equal(np.asarray(free), (got[:3] > 0) & (got[:3] < 1))


def test_inverse_diagonal_matches_numpy():
    from jaxrefl.methods.lm import spd_inverse_diagonal

    rng = np.random.default_rng(14)
    j = rng.standard_normal((200, 9, 5)) * np.logspace(-3, 3, 5)  # badly scaled columns
    a = np.einsum("nki,nkj->nij", j, j)
    got = np.asarray(spd_inverse_diagonal([[a[:, i, k] for k in range(i + 1)] for i in range(5)])).T
    ridge = 1e-12 * a[:, np.arange(5), np.arange(5)].max(1)
    ref = np.diagonal(np.linalg.inv(a + ridge[:, None, None] * np.eye(5)), axis1=1, axis2=2)
    np.testing.assert_allclose(got, ref, rtol=1e-8)


@pytest.mark.parametrize("model", ["torrance-sparrow", "ward"])
def test_standard_deviations_match_autodiff_covariance(model):
    """The std from the written-out sums equal s^2 (J^T J)^-1 with J by autodiff of the
    BRDF (`brdf`), at the fitted parameters."""
    from jaxrefl.methods.local import _make_residual, _noise_weights

    rng = np.random.default_rng(15)
    rows, _, _, _ = synthetic_rows(rng, 40, 10, model)
    rows["y"] = rows["y"] * (1 + 0.01 * rng.standard_normal(rows["y"].shape))
    fit = fit_rows(rows, LocalOptions(model=model))
    params = jnp.asarray(np.c_[fit["pd"], fit["ps"], np.log(fit["roughness"])])
    data = {k: jnp.asarray(rows[k]) for k in ("y", "e", "cos_i", "cos_o", "theta_r", "use")}
    data["w"] = _noise_weights(data["y"], data["use"], 0.0)
    residual = _make_residual(model)
    r = jax.vmap(residual)(params, data)
    jac = jax.vmap(jax.jacfwd(residual))(params, data)
    s2 = jnp.sum(r * r, 1) / (3 * rows["use"].sum(1) - 5)
    s2 = jnp.maximum(s2, jnp.median(s2))  # no row's noise below the median row's
    var = s2[:, None] * jnp.diagonal(jnp.linalg.inv(jnp.einsum("nki,nkj->nij", jac, jac)), axis1=1, axis2=2)
    sd = np.sqrt(np.asarray(var))
    sd[:, 4] *= fit["roughness"]  # std of the roughness itself, from that of its log
    np.testing.assert_allclose(np.c_[fit["std_pd"], fit["std_ps"], fit["std_roughness"]], sd, rtol=1e-5)


def test_ward_diffuse_object_without_any_lobe_keeps_its_albedo():
    """No point has a measurable highlight (white paper): ps is 0 everywhere, and pd
    still comes from the samples (the Ward lobe at roughness 0 must not turn it to 0)."""
    # six lights (padded to eight observations): the compiled Ward fit of the row tests above
    scan, _ = make_scan("E", resolution=16, setup="diffuse", lights=[23, 26, 33, 36, 4, 55], model="ward")
    est = estimate_local(scan, LocalOptions(model="ward"))
    assert np.all(est.ps == 0) and np.all(np.isfinite(est.pd))
    np.testing.assert_allclose(est.pd[est.pd_measured], scan.true_pd[est.pd_measured], rtol=0.02)


def test_std_pd_holds_the_light_the_object_reflects_onto_itself():
    """A diffuse 90-degree fold under full global illumination (the path tracer): Method I's pd
    keeps the light each half sends the other, 14 noise sds too bright at the median point. Its
    std_pd now holds that light's estimated share (first bounce through 16-ray form factors), so
    few points lie beyond 3 sd; the values do not change, and a warning says why."""
    scan, _ = make_scan("E", resolution=16, setup="diffuse", lights=[26, 40, 50], global_illumination=True,
                        samples=64, sensor=Sensor(noise=0.01), seed=0)
    est = estimate_local(scan)
    noise_only = estimate_local(scan, LocalOptions(interreflection_rays=0))
    for name in ("pd", "ps", "roughness", "status", "std_ps", "std_roughness"):
        np.testing.assert_array_equal(getattr(est, name), getattr(noise_only, name), err_msg=name)
    obs = est.pd_measured

    def beyond(e):
        return np.mean((np.abs(e.pd - scan.true_pd) > 3 * e.std_pd)[obs])

    assert beyond(noise_only) > 0.5 and beyond(est) < 0.1
    assert np.all(est.std_pd >= noise_only.std_pd)
    info = est.meta["interreflection"]
    assert info["rays"] == 16 and 0.05 < info["share_median"] < 0.5 and info["points_beyond_noise"] > 0
    assert any("receive light from the object itself" in w for w in est.meta["warnings"])
    assert "interreflection" not in noise_only.meta


def test_a_convex_object_receives_no_light_from_itself(convex_noisy):
    """The vase sees none of itself: the share is 0 and std_pd is the noise's alone."""
    scan, est = convex_noisy
    assert est.meta["interreflection"]["share_p90"] == 0.0
    assert not any("receive light from the object itself" in w for w in est.meta["warnings"])
