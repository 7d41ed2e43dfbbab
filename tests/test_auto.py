"""`--method auto`: measurements, the error model, regions, the choice on real scans, the CLI."""

import dataclasses
import json
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from data_synth.scans import Sensor, make_scan
from jaxrefl.geometry import formfactors
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods import auto, interreflection
from jaxrefl.methods.local import LocalOptions, estimate_local, prepare_rows
from jaxrefl.methods.radiosity import RadiosityOptions, direct_irradiance
from jaxrefl.result import Estimate
from tests.helpers import grid_plane


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    """Form factors cast afresh: an empty disk cache and an empty memory cache."""
    monkeypatch.setenv("JAXREFL_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(formfactors, "_MEMORY", {})


@pytest.fixture(scope="module")
def fold_scan():
    """White-paper Object E (ps 0) under four lights, path-traced interreflections."""
    scan, _ = make_scan("E", resolution=32, setup="diffuse", lights=[23, 26, 33, 36], global_illumination=True,
                        samples=32, sensor=Sensor(noise=0.01), seed=1)
    return scan


@pytest.fixture(scope="module")
def convex_scan():
    """The convex vase: nothing on it sees anything else of it. (Sizes chosen so that the
    fold and the vase share one compilation of Method I: 4 lights, <= 1000 points.)"""
    scan, _ = make_scan("V", resolution=16, lights=[0, 15, 30, 45], sensor=Sensor(noise=0.01))
    return scan


def test_measures_see_the_fold_and_not_the_convex_vase(fold_scan, convex_scan, fresh_cache):
    options = auto.AutoOptions(radiosity=RadiosityOptions(rays=64))
    vase = auto.measure(convex_scan, options)
    assert vase.mass.max() < 0.02 and vase.gain_diffuse.max() < 0.02
    fold = auto.measure(fold_scan, options)
    # Each plate sees the other: half the hemisphere at the fold line, less far from it.
    x = np.abs(fold_scan.vertices[:, 1])  # distance from the fold plane y = 0 (untilted E)
    near, far = x < 0.02, x > 0.1
    assert fold.mass[near].mean() > 0.3 and fold.mass[far].mean() < fold.mass[near].mean()
    # white paper: the other plate sends a good share of the direct light back, most at the fold
    assert fold.gain_diffuse[near].mean() > 0.2 and fold.gain_diffuse[far].mean() < fold.gain_diffuse[near].mean()
    assert np.all(fold.gain_specular >= 0) and np.all(np.isfinite(fold.gain_specular))
    for v in (fold.rel_std_pd, fold.rel_std_ps):
        assert np.all(v[np.isfinite(v)] >= 0) and not np.any(np.isnan(v))
    assert np.isfinite(fold.rel_std_pd).mean() > 0.9  # pd: nearly every point has its own


def test_interreflection_ratios_against_the_first_radiosity_bounce(fresh_cache):
    """One light: `g` is Method II's first interreflection bounce `F (pd E)` over `E` (direct
    irradiance by `radiosity.direct_irradiance`, shadows by Embree); `s` is linear in ps,
    0 without a lobe, and larger for a sharper lobe of the same albedo (Ward)."""
    scan, _ = make_scan("E", resolution=24, setup="glossy", lights=[26], model="ward")
    caster = RayCaster(scan.vertices, scan.faces)
    ff = formfactors.form_factors(scan.vertices, scan.faces, scan.normals, rays=64, caster=caster)
    rows = prepare_rows(scan, caster=caster)
    rng = np.random.default_rng(0)
    pd = rng.uniform(0.2, 0.9, (scan.n_points, 3))

    def est(ps, alpha):
        n = scan.n_points
        return Estimate(pd, np.full(n, ps), np.full(n, alpha), np.zeros(n, np.int8), pd * 0, np.zeros(n),
                        np.zeros(n), np.ones(n, bool), np.ones(n, bool), "ward")

    g, s0 = auto.interreflection_ratios(scan, est(0.0, 0.1), ff, rows)
    e = direct_irradiance(caster, scan.normals, scan.light_positions()[0, :1], scan.intensities())[:, 0]
    lit = rows["use"][:, 0]
    assert lit.mean() > 0.5 and np.allclose(e[lit], rows["e"][lit, 0])
    expected = (ff.matrix @ (pd.mean(1) * e)) / np.where(lit, e, 1.0)
    np.testing.assert_allclose(g[lit], expected[lit], rtol=1e-9)
    assert np.all(g[~lit] == 0) and np.all(s0 == 0)
    _, s1 = auto.interreflection_ratios(scan, est(0.1, 0.1), ff, rows)
    _, s2 = auto.interreflection_ratios(scan, est(0.2, 0.1), ff, rows)
    _, sharp = auto.interreflection_ratios(scan, est(0.1, 0.03), ff, rows)
    np.testing.assert_allclose(s2, 2 * s1, rtol=1e-9)
    assert s1.max() > 0 and sharp.max() > 2 * s1.max()
    # the lobes are evaluated in chunks of (entry, light) pairs: small chunks, the same sums
    monkeypatch_pairs = interreflection._PAIRS
    try:
        interreflection._PAIRS = 997
        g_small, s_small = auto.interreflection_ratios(scan, est(0.1, 0.1), ff, rows)
    finally:
        interreflection._PAIRS = monkeypatch_pairs
    np.testing.assert_allclose(s_small, s1, rtol=1e-12)
    np.testing.assert_allclose(g_small, g, rtol=1e-12)


def _fake_measures(n, gain):
    z = np.zeros(n)
    return auto.Measures(mass=gain, gain_diffuse=gain, gain_specular=z, rel_std_pd=z + 0.01, rel_std_ps=z + 0.01,
                         local=None, ff=None, seconds={})


def test_regions_are_components_dilated_by_rings_and_small_ones_are_dropped():
    v, f = grid_plane(1.0, 21)  # 21 x 21 vertices
    ij = np.stack(np.unravel_index(np.arange(len(v)), (21, 21)), 1)
    gain = np.zeros(len(v))
    block = (np.abs(ij[:, 0] - 5) <= 1) & (np.abs(ij[:, 1] - 5) <= 1)  # 3 x 3 = 9 points
    lone = (ij[:, 0] == 15) & (ij[:, 1] == 15)  # one isolated point
    gain[block | lone] = 0.3
    scan = SimpleNamespace(faces=f, n_points=len(v))
    options = auto.AutoOptions(target_error=0.05, min_region=8, rings=1, methods=("local", "radiosity"))
    p = auto.plan(scan, _fake_measures(len(v), gain), options)
    assert p.run == "radiosity" and len(p.regions) == 1
    region = (p.method == auto.METHODS.index("radiosity")) & ~p.extended
    # one ring of the grid's triangulation around the 3 x 3 block; the lone point is in no region
    assert region[block].all() and not region[lone] and 9 < region.sum() <= 25
    assert p.regions[0]["seed_points"] == 9 and p.regions[0]["points"] == region.sum()
    assert p.needs_global[lone]
    # ... but, Method II running anyway (all its light configurations made: fixed lights), it takes
    # its result where it is predicted better, and only there
    assert p.extended[lone] and p.extended.sum() == 1
    # two rings grow it further; zero rings keep exactly the block
    wider = auto.plan(scan, _fake_measures(len(v), gain), dataclasses.replace(options, rings=2))
    assert ((wider.method > 0) & ~wider.extended).sum() > region.sum()
    exact = auto.plan(scan, _fake_measures(len(v), gain), dataclasses.replace(options, rings=0))
    assert ((exact.method > 0) & ~exact.extended).sum() == 9


def test_a_region_keeps_its_own_method_where_the_more_capable_one_is_predicted_worse():
    """Diffuse interreflection in one block (Method II's case), light sent by specular lobes in
    another (Method III's, by pd): both run, each on its block; Method III's result is not
    forced on the block where it is predicted worse."""
    v, f = grid_plane(1.0, 21)
    ij = np.stack(np.unravel_index(np.arange(len(v)), (21, 21)), 1)
    diffuse = (np.abs(ij[:, 0] - 5) <= 1) & (np.abs(ij[:, 1] - 5) <= 1)
    lobes = (np.abs(ij[:, 0] - 15) <= 1) & (np.abs(ij[:, 1] - 15) <= 1)
    m = _fake_measures(len(v), np.where(diffuse, 0.3, np.where(lobes, 0.05, 0.0)))
    m.gain_specular = np.where(lobes, 0.05, 0.0)
    scan = SimpleNamespace(faces=f, n_points=len(v))
    # Method III's error grows with the diffuse gain, Method II's with the specular one
    model = auto.ErrorModel(pd=((0.8, 2.8), (0.0, 2.8), (0.3, 1.0)), uncertainty_pd=(0.0, 0.0, 0.0))
    p = auto.plan(scan, m, auto.AutoOptions(target_error=0.01, rings=0, model=model))
    assert p.runs == ("radiosity", "photon") and p.run == "photon"
    assert np.all(p.method[diffuse] == 1) and np.all(p.method[lobes] == 2)
    assert np.all(p.method[~(diffuse | lobes)] == 0)


def test_a_cheaper_method_stays_only_if_its_inflated_bias_is_within_the_tolerance():
    """Method I's pd biased by the gain in a block, Method II's not: Method I predicted 1.05x
    Method II's error there. Trusting the model (no uncertainty) Method I is within the 10 %
    tolerance and stays; with the bias inflated by the calibrated uncertainty of the pair it is
    not, and the block takes Method II. Outside the block there is no bias to inflate and Method
    I's lower noise wins. A costlier method has the burden of proof the other way round: a
    gain of 1.05x is enough when the model is sure of the cheaper method's bias."""
    v, f = grid_plane(1.0, 21)
    ij = np.stack(np.unravel_index(np.arange(len(v)), (21, 21)), 1)
    block = (np.abs(ij[:, 0] - 10) <= 2) & (np.abs(ij[:, 1] - 10) <= 2)
    scan = SimpleNamespace(faces=f, n_points=len(v))
    model = auto.ErrorModel(pd=((1.0, 0.0), (0.0, 0.0), (0.0, 0.0)), noise_scale_pd=1.0, radiosity_noise_pd=0.001,
                            uncertainty_pd=(0.0, 0.0, 0.0))
    n_rad = np.hypot(0.01, 0.001)
    bias = np.sqrt((1.05 * n_rad) ** 2 - 0.01**2)  # local = 1.05 x radiosity in the block
    m = _fake_measures(len(v), np.where(block, bias, 0.0))
    options = auto.AutoOptions(target_error=0.0, rings=0, methods=("local", "radiosity"), model=model)
    parts = auto.predict_parts(m, model, ("local", "radiosity"))
    np.testing.assert_allclose(parts["local"]["pd"][1][block], bias)
    ratio = np.hypot(*parts["local"]["pd"]) / np.hypot(*parts["radiosity"]["pd"])
    np.testing.assert_allclose(ratio[block], 1.05)
    trusted = auto.plan(scan, m, options)
    assert trusted.run is None and np.all(trusted.method == 0)
    # the bias inflated by exp(u): within 1.1 x Method II's error exactly while exp(u) bias < limit
    limit = np.sqrt((1.1 * n_rad) ** 2 - 0.01**2) / bias
    for spread, expected in ((np.log(limit) - 0.01, None), (np.log(limit) + 0.01, "radiosity")):
        unsure = dataclasses.replace(model, uncertainty_pd=(spread, 0.0, 0.0))
        assert unsure.margin("pd", "local", "radiosity") == unsure.margin("pd", "radiosity", "local") > 1
        assert unsure.margin("pd", "local", "local") == 1.0
        p = auto.plan(scan, m, dataclasses.replace(options, model=unsure))
        assert p.run == expected and np.all(p.method[block] == (expected is not None))
        assert np.all(p.method[~block] == 0)
        # a target the user accepts keeps Method I whatever the uncertainty
        loose = auto.plan(scan, m, dataclasses.replace(options, model=unsure, target_error=0.05))
        assert loose.run is None


def test_ps_is_method_threes_wherever_it_runs_else_method_ones():
    """ps and roughness come from Method III at every point once it runs (it refits every lobe with
    the interreflected light removed), from Method I where only Method II runs (Method II's ps is
    not better where it runs); the merge takes pd and ps from their own sources and the less
    certain status."""
    v, f = grid_plane(1.0, 21)
    ij = np.stack(np.unravel_index(np.arange(len(v)), (21, 21)), 1)
    block = (np.abs(ij[:, 0] - 10) <= 3) & (np.abs(ij[:, 1] - 10) <= 3)
    scan = SimpleNamespace(faces=f, n_points=len(v))
    m = _fake_measures(len(v), np.where(block, 0.3, 0.0))
    p2 = auto.plan(scan, m, auto.AutoOptions(rings=0, methods=("local", "radiosity")))
    assert p2.run == "radiosity" and np.all(p2.method[block] == 1) and np.all(p2.ps_method == 0)
    # lobes sending light in the block: Method III needed there; its ps used everywhere
    m.gain_specular = np.where(block, 0.05, 0.0)
    p3 = auto.plan(scan, m, auto.AutoOptions(rings=0))
    assert p3.run == "photon" and np.all(p3.method[block] == 2)
    assert np.any(p3.method == 0) and np.all(p3.ps_method == 2)
    # Method III running, the points left to Method I that have a lobe of their own take its pd
    # too (not extended where only Method II runs)
    lobed = ij[:, 0] < 3
    m.local = SimpleNamespace(specular_identifiable=lobed)
    p3l = auto.plan(scan, m, auto.AutoOptions(rings=0))
    np.testing.assert_array_equal(p3l.method, np.where(lobed, 2, p3.method))
    assert p3l.extended[lobed].all() and not p3l.extended[~lobed & (p3.method == 0)].any()
    assert np.array_equal(auto.plan(scan, dataclasses.replace(m, gain_specular=np.zeros(len(v))),
                                    auto.AutoOptions(rings=0, methods=("local", "radiosity"))).method, p2.method)

    n = len(v)

    def est(value, status):
        return Estimate(np.full((n, 3), value), np.full(n, value), np.full(n, value), np.full(n, status, np.int8),
                        np.full((n, 3), value), np.full(n, value), np.full(n, value), np.full(n, value > 1),
                        np.full(n, value > 1), "ward")

    half = block & (ij[:, 0] < 10)
    merged = auto._merge(est(1.0, 0), est(2.0, 1), block, half)
    np.testing.assert_array_equal(merged.pd[:, 0], np.where(block, 2.0, 1.0))
    np.testing.assert_array_equal(merged.std_pd[:, 0], merged.pd[:, 0])
    np.testing.assert_array_equal(merged.pd_measured, block)
    for k in ("ps", "roughness", "std_ps", "std_roughness"):
        np.testing.assert_array_equal(getattr(merged, k), np.where(half, 2.0, 1.0))
    np.testing.assert_array_equal(merged.specular_identifiable, half)
    np.testing.assert_array_equal(merged.status, np.where(block, 1, 0))
    # pooled (code 3) is less certain than measured, more than interpolated (1) and unresolved (2)
    for mine, theirs, want in ((3, 2, 2), (2, 3, 2), (0, 3, 3), (3, 0, 3), (3, 1, 1)):
        merged = auto._merge(est(1.0, mine), est(2.0, theirs), block, half)
        np.testing.assert_array_equal(merged.status, np.where(half, theirs, np.where(block, want, mine)))


def test_target_is_an_error_the_user_accepts_and_zero_asks_for_the_best():
    v, f = grid_plane(1.0, 11)
    scan = SimpleNamespace(faces=f, n_points=len(v))
    m = _fake_measures(len(v), np.full(len(v), 0.1))
    model = auto.ErrorModel()
    parts = auto.predict_parts(m, model, ("local", "radiosity"))
    e_rad = float(np.hypot(*parts["radiosity"]["pd"])[0])
    pess_local = float(auto._pessimistic(parts, "local", "radiosity", "pd", model)[0])
    assert pess_local > 1.1 * e_rad
    loose = auto.plan(scan, m, auto.AutoOptions(target_error=1.01 * pess_local, methods=("local", "radiosity")))
    assert loose.run is None and np.all(loose.method == 0)
    tight = auto.plan(scan, m, auto.AutoOptions(target_error=0.99 * pess_local, methods=("local", "radiosity")))
    assert tight.run == "radiosity" and np.all(tight.method == 1)
    # the default, 0: as accurate as the best predicted method, within the tolerance
    assert auto.AutoOptions().target_error == 0.0
    best = auto.plan(scan, m, auto.AutoOptions(methods=("local", "radiosity")))
    assert best.run == "radiosity"
    assert best.predicted["plan"]["pd"] == pytest.approx(e_rad)


def test_convex_scene_is_left_to_method_one(convex_scan, fresh_cache):
    """Nothing on the vase sees anything else of it: no interreflection bias to inflate, and
    Method I's lower noise wins even when the user asks for the best (target 0, the default)."""
    options = auto.AutoOptions(radiosity=RadiosityOptions(rays=64))
    assert options.target_error == 0.0
    est = auto.estimate_auto(convex_scan, options)
    # the decision comes from the gated Method I its error model was calibrated on (`auto.measure`);
    # where Method I is kept, auto returns it as Method I gives it, with the shared prior
    local = estimate_local(convex_scan, options.local)
    assert est.meta["runs"]["local"]["options"]["prior"] and "local_prior" in est.meta["seconds"]
    a = est.meta["auto"]
    assert est.meta["method"] == "auto" and a["choice"] == "local" and a["global_method"] is None
    assert a["regions"] == [] and a["points_by_method"] == {"local": convex_scan.n_points}
    np.testing.assert_array_equal(est.pd, local.pd)
    np.testing.assert_array_equal(est.ps, local.ps)
    assert a["predicted"]["plan"]["pd"] <= min(a["predicted"][k]["pd"] for k in a["candidates"])
    assert set(a["statistics"]) == {"mass", "gain_diffuse", "gain_specular", "rel_std_pd", "rel_std_ps", "photon_k"}
    json.dumps(est.meta)  # the meta is plain JSON


def test_light_method_two_leaves_unexplained_sends_its_regions_to_method_three():
    """The data, not the calibrated model, has the last word on Method II: where its residual
    variance over its regions is twice the noise (the rest of the scan's) or more, the light it
    leaves unexplained is as large as the noise, and Method III takes its points. Once Method III
    ran, its pd is also taken where its own std is the tighter, and Method I's lobes stay outside
    the regions where Method I measured or pooled them."""
    n = 10
    est = lambda status=0, std=0.01: Estimate(  # noqa: E731
        np.full((n, 3), 0.5), np.full(n, 0.1), np.full(n, 0.1), np.asarray(np.broadcast_to(status, (n,)), np.int8),
        np.asarray(np.broadcast_to(std, (n,)))[:, None].repeat(3, 1), np.full(n, 0.01), np.full(n, 0.01),
        np.ones(n, bool), np.ones(n, bool), "ward")
    local = est()
    local.meta["residual_scale"] = {"median": 1.5, "region_median": None}
    measures = SimpleNamespace(local=local)
    assert auto._unexplained(measures, None) is None
    radiosity = est()
    radiosity.meta["residual_scale"] = {"median": 1.6, "region_median": 2.9}
    u = auto._unexplained(measures, radiosity)
    assert u["noise"] == 1.5 and u["ratio"] == pytest.approx(2.9 / 1.5) and u["ratio"] < auto._UNEXPLAINED
    radiosity.meta["residual_scale"]["region_median"] = 300.0
    assert auto._unexplained(measures, radiosity)["ratio"] == 200.0
    # Method II everywhere (its region's median is its scan's): no noise apart from it, no escalation
    radiosity.meta["residual_scale"] = {"median": 300.0, "region_median": 300.0}
    local.meta["residual_scale"] = {"median": 2000.0, "region_median": None}
    assert auto._unexplained(measures, radiosity)["ratio"] == 1.0
    radiosity.meta["residual_scale"] = {"median": 1.6, "region_median": None}  # no region reported
    assert auto._unexplained(measures, radiosity) is None

    method = np.array([0, 0, 0, 1, 1, 1, 1, 0, 0, 0])
    extended = np.array([0, 0, 0, 0, 0, 0, 1, 0, 0, 0], bool)
    plan = auto.Plan(method, "radiosity", [{"region": 0, "method": "radiosity"}], method > 0, {}, extended,
                     ("radiosity",), np.zeros(n, np.int64))
    up = auto._escalate(plan)
    np.testing.assert_array_equal(up.method, np.where(method == 1, 2, method))
    assert up.run == "photon" and up.runs == ("photon",) and up.regions[0]["method"] == "photon"
    # points 0-2: Method I measured / pooled / unresolved lobes; point 1's Method III std is the tighter
    local = est(status=np.array([0, 3, 2, 0, 0, 0, 0, 0, 2, 0]), std=0.01)
    photon = est(std=np.array([0.02, 0.005, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02, np.inf]))
    src = auto._photon_sources(up, local, photon)
    np.testing.assert_array_equal(src.method, [0, 2, 0, 2, 2, 2, 2, 0, 0, 0])
    # ps: Method III's in the regions (not at the extension, point 6) and where Method I's lobe is not its own
    np.testing.assert_array_equal(src.ps_method, [0, 0, 2, 2, 2, 2, 0, 0, 2, 0])


def test_glossy_fold_plans_method_three_and_its_ps(fresh_cache):
    """Glossy Object E (Ward, tilted so its highlights are seen, path-traced interreflections):
    the mirror images of each plate in the other are light Method II leaves in its fit, so the
    calibrated model under the default target (0: as accurate as the best) sends the fold to
    Method III, whose ps is then used everywhere; a convex vase keeps Method I (no bias to
    inflate). The plan only: Method III itself is `test_inverse_photon`'s."""
    from jaxrefl.capture.select import select_lights
    from jaxrefl.reflectance.classify import classify_scan

    kw = dict(resolution=20, setup="glossy", model="ward", tilt_deg=(25.0, 0.0))
    geo, _ = make_scan("E", **kw)
    c = classify_scan(geo, use_observations=False)
    lights = select_lights(c.diffuse_only, c.strong_specular, c.seen, weights=c.pixel_weight).selected
    scan, _ = make_scan("E", lights=lights, global_illumination=True, samples=16, sensor=Sensor(noise=0.01), seed=0,
                        **kw)
    options = auto.AutoOptions(local=LocalOptions(model="ward"), radiosity=RadiosityOptions(rays=64))
    m = auto.measure(scan, options)
    p = auto.plan(scan, m, options)
    assert p.run == "photon" and np.mean(p.method == 2) > 0.8
    assert np.all(p.ps_method == 2)
    # the pessimistic rule, not the raw prediction: Method II's inflated bias is beyond 1.1x Method III's
    region = max(p.regions, key=lambda r: r["points"])
    assert region["pessimistic_pd"]["radiosity"] > 1.1 * region["predicted"]["photon"]["pd"]
    assert region["predicted"]["radiosity"]["pd"] > region["predicted"]["photon"]["pd"]


def test_fold_needs_inverse_radiosity_and_the_form_factors_are_cast_once(fold_scan, fresh_cache, monkeypatch):
    casts = []
    real = formfactors._cast
    monkeypatch.setattr(formfactors, "_cast", lambda *a, **k: casts.append(1) or real(*a, **k))
    options = auto.AutoOptions(target_error=0.05, radiosity=RadiosityOptions(rays=64))
    caster = RayCaster(fold_scan.vertices, fold_scan.faces)
    est = auto.estimate_auto(fold_scan, options, caster)
    a = est.meta["auto"]
    assert a["global_method"] == "radiosity" and "radiosity" in a["choice"]
    assert "photon" in a["unavailable"] and "Ward" in a["unavailable"]["photon"]
    assert "radiosity" in est.meta["runs"] and est.meta["seconds"]["radiosity"] > 0
    assert len(est.meta["runs"]["radiosity"]["outer_iterations"]) == options.radiosity_outer == 2
    # all the casts happened while measuring: Method II read the form factors from the cache
    n_chunks = -(-fold_scan.n_points // (formfactors._RAYS_PER_TASK // 64))
    assert len(casts) == n_chunks
    # interreflection removed where it matters: against Method I near the fold
    local = estimate_local(fold_scan, options.local, caster)
    near = np.abs(fold_scan.vertices[:, 1]) < 0.03
    err = lambda e: (np.abs(e.pd - fold_scan.true_pd) / fold_scan.true_pd).mean(1)  # noqa: E731
    assert err(est)[near].mean() < 0.5 * err(local)[near].mean()
    for k in ("pd", "ps", "roughness", "std_pd", "std_ps", "std_roughness"):
        assert not np.any(np.isnan(getattr(est, k)))
    # where pd stays Method I's, its std holds the interreflected light measured with Method II's form factors
    ir = est.meta["interreflection"]
    assert ir["rays"] == 64 and ir["share_p90"] > 0
    region_points = sum(r["points"] for r in a["regions"])
    assert region_points + a["extended_points"] == a["points_by_method"].get("radiosity", 0) > 0
    # Method II estimated those points and no others
    assert est.meta["runs"]["radiosity"]["points_estimated"] == a["points_by_method"]["radiosity"]
    assert all(r["predicted"]["radiosity"]["pd"] < r["predicted"]["local"]["pd"] for r in a["regions"])


def test_photon_is_no_candidate_where_no_lobe_is_measured(fold_scan, fresh_cache):
    """White paper under Ward at the default target: Method I measures no lobe anywhere, so
    Method III (which differs from Method II only in the light lobes interreflect) is left
    out with the reason, and the fold goes to Method II."""
    options = auto.AutoOptions(local=LocalOptions(model="ward"), radiosity=RadiosityOptions(rays=64))
    est = auto.estimate_auto(fold_scan, options)
    a = est.meta["auto"]
    assert not est.meta["runs"].get("photon")
    assert "photon" in a["unavailable"] and "no specular lobe" in a["unavailable"]["photon"]
    assert a["global_method"] == "radiosity"
    # and the diffuse interreflection explains the fold: Method II's residuals there are the noise's
    assert a["unexplained"]["ratio"] < auto._UNEXPLAINED and not a["unexplained"]["escalated"]


def test_held_out_check_returns_method_one_where_the_global_result_predicts_worse(convex_scan, fresh_cache):
    """auto's held-out check (`jaxrefl.estimate(..., holdout=...)` with Auto): a global result
    whose relit held-out images are worse than Method I's beyond the held-out noise is replaced
    by Method I's, and says why; one that is not stays, with the comparison in its meta."""
    from jaxrefl.outputs.holdout import paired_holdout, split_scan

    fit_scan, test_scan = split_scan(convex_scan, [3])
    options = auto.AutoOptions(radiosity=RadiosityOptions(rays=64))
    local = estimate_local(fit_scan, options.local)
    meta = {"method": "auto", "auto": {"global_method": "radiosity", "global_methods": ["radiosity"],
                                       "choice": "local+radiosity"}}
    same = dataclasses.replace(local, meta=dict(meta))
    kept = auto.holdout_check(same, fit_scan, test_scan, options)
    check = kept.meta["auto"]["holdout_check"]
    assert check["kept"] == "local+radiosity" and len(check["comparisons"]) == 1  # Method II's result: vs Method I
    c = check["comparisons"][0]
    assert c["against"] == "local" and not c["worse"] and c["samples"] > 100
    assert abs(c["difference"]) <= 2 * c["se"] + 1e-12
    wrong = dataclasses.replace(local, pd=0.8 * local.pd, meta=dict(meta))
    assert paired_holdout(wrong, local, test_scan)["worse"]
    out = auto.holdout_check(wrong, fit_scan, test_scan, options)
    a = out.meta["auto"]
    assert a["choice"] == "local" and a["global_method"] is None and "held-out check" in a["reason"]
    c = a["holdout_check"]["comparisons"][0]
    assert a["holdout_check"]["kept"] == "local" and c["worse"] and c["difference"] > 2 * c["se"]
    np.testing.assert_allclose(out.pd, local.pd)
    assert out.meta["holdout"]["rel_rms"] is not None and any("held-out check" in w for w in out.meta["method_warnings"])
    # a result of Method III's model is checked against Method II first, then what is kept against Method I
    photon_meta = {"method": "auto", "auto": {"global_method": "photon", "global_methods": ["photon"],
                                              "choice": "local+photon"}}
    wrong3 = dataclasses.replace(local, pd=0.8 * local.pd, model="ward", meta=photon_meta)
    out3 = auto.holdout_check(wrong3, fit_scan, test_scan, options)
    comps = out3.meta["auto"]["holdout_check"]["comparisons"]
    assert [c["against"] for c in comps] == ["radiosity", "local"]
    assert comps[0]["worse"] and comps[1]["result"] == "radiosity" and not comps[1]["worse"]
    a3 = out3.meta["auto"]
    assert a3["holdout_check"]["kept"] == "radiosity" and a3["choice"] == "radiosity"
    # the rejected plan is kept apart; the result is Method II's pd with Method I's lobes, as auto uses Method II
    assert a3["points_by_method"] == {"radiosity": fit_scan.n_points} and "rejected" in a3["holdout_check"]
    np.testing.assert_allclose(out3.ps, local.ps)
    # a result that ran no global method is left as it is
    plain = dataclasses.replace(local, meta={"method": "auto", "auto": {"global_method": None}})
    assert auto.holdout_check(plain, fit_scan, test_scan, options) is plain


def test_api_runs_autos_held_out_check(fold_scan, fresh_cache):
    """Through `jaxrefl.estimate`: the white fold's Method II result predicts a held-out light
    no worse than Method I, so it stays, and the check is in its meta."""
    import jaxrefl

    est = jaxrefl.estimate(fold_scan, jaxrefl.Auto(target_error=0.05, radiosity=RadiosityOptions(rays=64)),
                           holdout=[1], progress=False)
    a = est.meta["auto"]
    (c,) = a["holdout_check"]["comparisons"]
    assert a["global_method"] == "radiosity" and c["against"] == "local" and not c["worse"]
    assert c["difference"] < 0  # Method II's held-out error is the smaller
    assert est.meta["holdout"]["lights"] == [1]


def test_photon_is_a_candidate_only_for_ward_and_when_installed(monkeypatch):
    ok, why = auto.photon_available("torrance-sparrow")
    assert not ok and "Ward" in why
    monkeypatch.setitem(sys.modules, "jaxrefl.methods.inverse_photon", None)  # Method III absent
    ok, why = auto.photon_available("ward")
    assert not ok and "not installed" in why


def test_options_are_checked():
    with pytest.raises(ValueError, match="target_error"):
        auto.AutoOptions(target_error=-0.01)
    assert auto.AutoOptions(target_error=0.0).target_error == 0.0
    with pytest.raises(ValueError, match="methods"):
        auto.AutoOptions(methods=("radiosity",))
    with pytest.raises(ValueError, match="radiosity_outer"):
        auto.AutoOptions(radiosity_outer=0)


def test_uncertainty_is_the_spread_of_measured_against_predicted_ratios():
    """`benchmarks.auto_bench.uncertainty`: 0 where every bin's measured ratio of two methods'
    errors is the predicted one (whatever the level), log 2 where it is off by 2 either way."""
    from benchmarks.auto_bench import uncertainty

    model = auto.ErrorModel()
    n = 400
    g = np.linspace(0.0, 0.2, n)
    f = {"gain_diffuse": g, "gain_specular": np.zeros(n), "rel_std_pd": np.full(n, 0.02),
         "rel_std_ps": np.full(n, 0.05)}
    m = auto.Measures(mass=g, gain_diffuse=g, gain_specular=f["gain_specular"], rel_std_pd=f["rel_std_pd"],
                      rel_std_ps=f["rel_std_ps"], local=None, ff=None, seconds={})
    pred = auto.predict(m, model, ("local", "radiosity"))

    def row(factor):
        errors = {k: (3.0 * pred[k]["pd"], 3.0 * pred[k]["ps"]) for k in ("local", "radiosity")}
        errors["radiosity"] = tuple(e * factor for e in errors["radiosity"])
        return {"calibration": {"features": f, "errors": errors, "photon_k": 0.0}}

    exact = uncertainty([row(1.0)], model)
    assert exact["pd"][0] == pytest.approx(0.0, abs=1e-9) and exact["ps"][0] == pytest.approx(0.0, abs=1e-9)
    assert exact["pd"][1:] == (0.0, 0.0)  # no Method III runs: no spread
    off = uncertainty([row(2.0), row(0.5)], model)
    for q in ("pd", "ps"):  # rounded to 3 digits
        assert off[q][0] == pytest.approx(np.log(2.0), abs=1e-3)


def test_cli_estimate_auto(tmp_path):
    from tests.test_cli import assert_one_line_error, jaxrefl

    scan = tmp_path / "v.npz"
    assert jaxrefl("synth", "V", "--resolution", 16, "--lights", "0,15,30,45", "--noise", 0.01,
                   "--out", scan).returncode == 0
    out = tmp_path / "auto.npz"
    r = jaxrefl("estimate", scan, "--method", "auto", "--rays", 64, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["method"] == "auto" and summary["auto"]["choice"] == "local"  # convex: Method I is the best
    assert summary["auto"]["target_error"] == 0.0 and summary["auto"]["tolerance"] == 0.1
    assert "predicted" in summary["auto"]
    with np.load(out) as z:
        meta = json.loads(str(z["meta"]))
        assert meta["method"] == "auto" and meta["auto"]["choice"] == "local" and np.all(np.isfinite(z["pd"]))
    assert_one_line_error(jaxrefl("estimate", scan, "--method", "auto", "--target-error", -1,
                                  "--out", tmp_path / "x.npz"), "target")
    assert_one_line_error(jaxrefl("estimate", scan, "--method", "auto", "--tolerance", -0.1,
                                  "--out", tmp_path / "x.npz"), "tolerance")
    assert not (tmp_path / "x.npz").exists()
