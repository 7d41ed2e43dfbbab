"""Method II: form factors against closed forms, the furnace, forward radiosity against
the independent path tracer, and inverse radiosity on the fold object (§4)."""

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import spsolve

from data_synth.objects import fold_coordinate
from data_synth.pathtrace import Material, PathTracer
from data_synth.scans import make_scan
from jaxrefl.geometry.formfactors import form_factors
from jaxrefl.geometry.mesh import area_normal_sums
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods.local import estimate_local, prepare_rows
from jaxrefl.methods.radiosity import (
    RadiosityOptions,
    direct_irradiance,
    estimate_radiosity,
    inverse_radiosity,
    light_configs,
    solve_radiosity,
)
from jaxrefl.paper.reports import fold_profile


def rectangle(origin, eu, ev, n=12):
    """Unit-parameter rectangle `origin + s eu + t ev`, normal `eu x ev`: (vertices, faces)."""
    s = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(s, s, indexing="ij")
    v = np.asarray(origin) + uu.reshape(-1, 1) * np.asarray(eu) + vv.reshape(-1, 1) * np.asarray(ev)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.r_[np.c_[a, b, c], np.c_[a, c, d]]


def disc(radius, z, facing, segments=96, rings=10):
    """Disc of `radius` in the plane `z`, normal `(0, 0, facing)`: a centre fan and `rings` rings."""
    r = np.linspace(0.0, radius, rings + 1)[1:]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    pts = np.r_[[[0.0, 0.0, z]], np.stack([np.outer(r, np.cos(phi)).ravel(), np.outer(r, np.sin(phi)).ravel(),
                                           np.full(rings * segments, z)], 1)]
    faces = []
    ring = lambda k, j: 1 + k * segments + (j % segments)  # noqa: E731
    for j in range(segments):
        faces.append([0, ring(0, j), ring(0, j + 1)])
        for k in range(rings - 1):
            faces += [[ring(k, j), ring(k + 1, j), ring(k + 1, j + 1)], [ring(k, j), ring(k + 1, j + 1), ring(k, j + 1)]]
    faces = np.asarray(faces)
    if facing < 0:
        faces = faces[:, ::-1]
    return pts, faces


def combine(*parts):
    vs, fs, labels, offset = [], [], [], 0
    for k, (v, f) in enumerate(parts):
        vs.append(v)
        fs.append(f + offset)
        labels.append(np.full(len(v), k))
        offset += len(v)
    v, f = np.vstack(vs), np.vstack(fs)
    n = area_normal_sums(v, f)
    return v, f, n / np.linalg.norm(n, axis=1, keepdims=True), np.concatenate(labels)


def patch_form_factor(ff, labels, a, b):
    """Area-averaged form factor from the patches labelled `a` to those labelled `b`."""
    rows = labels == a
    to_b = np.asarray(ff.matrix[rows][:, labels == b].sum(1)).ravel()
    return float(ff.areas[rows] @ to_b / ff.areas[rows].sum())


def binomial_se(f, patches, rays):
    return np.sqrt(f * (1 - f) / (patches * rays))


@pytest.mark.parametrize("case", ["perpendicular", "parallel"])
def test_rectangle_form_factors_match_closed_forms(case):
    """Unit squares with a common edge: 0.20004; aligned at unit gap: 0.19982 (Howell's catalogue)."""
    a = rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0])  # normal +z
    if case == "perpendicular":
        b, exact = rectangle([0, 0, 0], [0, 1, 0], [0, 0, 1]), 0.200044  # normal +x
    else:
        b, exact = rectangle([0, 0, 1], [0, 1, 0], [1, 0, 0]), 0.199825  # normal -z, facing a
    v, f, n, labels = combine(a, b)
    ff = form_factors(v, f, n, rays=1024, mode="cell", cache=False)
    got = patch_form_factor(ff, labels, 0, 1)
    se = binomial_se(exact, (labels == 0).sum(), 1024)
    assert abs(got - exact) < 4 * se + 1e-3, (got, exact, se)
    # reciprocity between the two squares (equal areas: F_ab = F_ba)
    assert abs(patch_form_factor(ff, labels, 1, 0) - got) < 8 * se + 2e-3
    assert ff.reciprocity_error(labels) < 0.02


def test_coaxial_discs():
    """Parallel coaxial discs r1 = 0.5, r2 = 0.8 at distance 0.6."""
    r1, r2, h = 0.5, 0.8, 0.6
    v, f, n, labels = combine(disc(r1, 0.0, +1), disc(r2, h, -1))
    ff = form_factors(v, f, n, rays=512, mode="cell", cache=False)
    big1, big2 = r1 / h, r2 / h
    x = 1 + (1 + big2**2) / big1**2
    exact = 0.5 * (x - np.sqrt(x * x - 4 * (big2 / big1) ** 2))
    # the polygonal discs (96 sides) differ from circles by < 0.1 % in area
    assert abs(patch_form_factor(ff, labels, 0, 1) - exact) < 4 * binomial_se(exact, (labels == 0).sum(), 512) + 3e-3


@pytest.mark.parametrize("mode", ["vertex", "cell"])
def test_sphere_interior(mode):
    """Inside a sphere every point sees region v with F = A_v / A_sphere, and nothing escapes."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1]  # inward-facing
    n = -v / np.linalg.norm(v, axis=1, keepdims=True)
    ff = form_factors(v, f, n, rays=256, mode=mode, cache=False)
    # closed: nothing escapes but the odd grazing ray that slips past a vertex in float32
    assert ff.row_sums.max() <= 1 + 1e-12 and ff.row_sums.mean() > 0.999 and ff.row_sums.min() > 0.98
    octant = (v[:, 0] > 0) * 4 + (v[:, 1] > 0) * 2 + (v[:, 2] > 0)
    total = ff.areas.sum()
    for b in range(8):
        got = patch_form_factor(ff, octant, 0, b)
        exact = ff.areas[octant == b].sum() / total
        assert abs(got - exact) < 4 * binomial_se(exact, (octant == 0).sum(), 256) + 2e-3, (b, got, exact)
    if mode == "cell":
        assert ff.reciprocity_error(octant) < 0.03


def test_form_factors_are_cached_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXREFL_CACHE", str(tmp_path))
    v, f, n, _ = combine(rectangle([0, 0, 0], [1, 0, 0], [0, 1, 0], 4), rectangle([0, 0, 0], [0, 1, 0], [0, 0, 1], 4))
    first = form_factors(v, f, n, rays=16, seed=3)
    files = list((tmp_path / "formfactors").glob("*.npz"))
    assert len(files) == 1
    from jaxrefl.geometry import formfactors as module

    module._MEMORY.clear()
    second = form_factors(v, f, n, rays=16, seed=3)
    np.testing.assert_array_equal(first.values, second.values)
    assert form_factors(v, f, n, rays=16, seed=4).values.shape != () and len(list(
        (tmp_path / "formfactors").glob("*.npz"))) == 2


def closed_sphere(subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1]
    return v, f, -v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("rho", [0.5, 0.8])
def test_furnace_forward(rho):
    """Closed sphere of albedo rho under uniform irradiance E: B = rho E / (1 - rho)."""
    v, f, n = closed_sphere()
    ff = form_factors(v, f, n, rays=64, cache=False)
    e = np.full((len(v), 2), 1.7)
    b, iters = solve_radiosity(ff, np.full((len(v), 3), rho), e, tol=1e-12)
    # the jitted fixed point against a direct sparse solve of (I - rho F) B = rho E ...
    exact = spsolve((sp.identity(len(v)) - rho * ff.matrix).tocsc(), rho * e[:, 0])
    np.testing.assert_allclose(b[:, 0, 0], exact, rtol=1e-9)
    # ... and against the closed form, up to the odd grazing ray that escapes (1 in 64 at worst)
    rel = np.abs(b / (rho * 1.7 / (1 - rho)) - 1)
    assert rel.mean() < 1e-3 and rel.max() < 0.02, (rel.mean(), rel.max())
    assert iters < 200


def test_furnace_inverse_returns_rho():
    """Inverse radiosity in a closed sphere lit from inside returns a random rho from the
    forward-solved radiosity, every patch observed under every light."""
    v, f, n = closed_sphere()
    caster = RayCaster(v, f)
    ff = form_factors(v, f, n, rays=64, caster=caster, cache=False)
    rho = np.random.default_rng(0).uniform(0.1, 0.9, (len(v), 3))
    lights = np.array([[0.1, 0.0, 0.0], [-0.2, 0.1, 0.05]])
    e = direct_irradiance(caster, n, lights, np.ones(2))
    b, _ = solve_radiosity(ff, rho, e, tol=1e-13)
    configs = light_configs(lights, len(v))
    seen = np.ones((len(v), 2), bool)
    inv = inverse_radiosity(ff, configs, e, b / np.pi, seen, e, np.full((len(v), 3), 0.5), tol=1e-12)
    np.testing.assert_allclose(inv.pd, rho, rtol=1e-8)
    assert np.all(np.isfinite(inv.interreflected))


def test_forward_radiosity_matches_path_tracer_on_the_fold():
    """Diffuse Object E under one light: radiosity radiance against the independent path tracer."""
    scan, _ = make_scan("E", resolution=32, setup="diffuse", lights=[23])
    caster = RayCaster(scan.vertices, scan.faces)
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=1024, caster=caster, cache=False)
    light = scan.light_positions()[0:1, 0]
    e = direct_irradiance(caster, scan.normals, light, scan.intensities())
    b, _ = solve_radiosity(ff, scan.true_pd, e)
    radiance = scan.true_pd * (e + ff.matrix @ b[:, 0, :1]) / np.pi
    pick = np.flatnonzero((np.abs(fold_coordinate(scan.vertices)) > 0.01) & (e[:, 0] > 0))[::5]
    tracer = PathTracer(scan.vertices, scan.faces, scan.normals, Material(scan.true_pd, scan.true_ps, scan.true_sigma),
                        caster=caster)
    cam = np.ascontiguousarray(scan.camera_positions()[pick][:, :1])
    ref, se = tracer.render(cam, np.ascontiguousarray(np.broadcast_to(light, (len(pick), 1, 3))), scan.intensities(),
                            samples=512, seed=1, indirect=True, points=pick)
    ratio = radiance[pick, 0] / ref[:, 0, 0]
    assert abs(np.median(ratio) - 1) < 0.01, np.median(ratio)
    assert np.all(np.abs(radiance[pick, 0] - ref[:, 0, 0]) < 4 * se[:, 0, 0] + 0.02 * ref[:, 0, 0])


def test_light_configs_bin_per_point_lights():
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1, 1, (50, 3, 3))
    cfg = light_configs(pos, 50, light_bin=0.5)
    assert cfg.index.shape == (50, 3) and cfg.positions.shape[0] == cfg.light.shape[0]
    # every observation's configuration is within a bin diagonal of its own light
    assert np.all(np.linalg.norm(cfg.positions[cfg.index] - pos, axis=-1) <= 0.5 * np.sqrt(3) + 1e-12)
    assert np.all(cfg.light[cfg.index] == np.arange(3)[None])
    exact = light_configs(pos, 50, light_bin=0.0)
    np.testing.assert_allclose(exact.positions[exact.index], pos)


def test_inverse_radiosity_removes_interreflection_on_the_fold(tmp_path):
    """§4.3 / Figure 16: white-paper Object E on the scanner, rendered with global
    illumination by the path tracer. Within 2 cm of the fold Method II's mean pd
    error is <= 3 % while Method I's is at least 3x larger."""
    scan, _ = make_scan("E", resolution=32, setup="diffuse", rig="scanner", lights=[24, 9, 0, 50, 59],
                        global_illumination=True, samples=1024, seed=0)
    near = np.abs(fold_coordinate(scan.vertices)) < 0.02
    errors = {}
    results = {"I": estimate_local(scan), "II": estimate_radiosity(scan, RadiosityOptions(rays=256))}
    for name, est in results.items():
        rel = (np.abs(est.pd - scan.true_pd) / scan.true_pd).mean(1)
        errors[name] = rel[near & est.pd_measured].mean()
        assert np.all(np.isfinite(est.pd)) and np.all(np.isfinite(est.ps)) and np.all(np.isfinite(est.roughness))
    assert errors["II"] <= 0.03, errors
    assert errors["I"] >= 3 * errors["II"], errors
    # the Figure 16 analogue reports the same numbers
    profile = fold_profile(scan, results, str(tmp_path / "fold.png"))
    assert (tmp_path / "fold.png").stat().st_size > 0 and np.array(profile["II"]["profile"]).shape == (30, 3)
    assert profile["II"]["near_fold_mean_rel_error"] == pytest.approx(errors["II"])


def test_cli_estimate_radiosity(tmp_path):
    """`jaxrefl estimate --method radiosity` writes the same result format as Method I, its
    summary carries the fixed point's statistics; bad input is one line, no file."""
    import json

    from tests.test_cli import assert_one_line_error, jaxrefl

    scan = tmp_path / "e.npz"
    assert jaxrefl("synth", "E", "--setup", "diffuse", "--rig", "scanner", "--lights", "24,9,0,50,59", "--gi",
                   "--samples", 16, "--resolution", 24, "--out", scan).returncode == 0
    out = tmp_path / "e_II.npz"
    r = jaxrefl("estimate", scan, "--method", "radiosity", "--rays", 64, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["method"] == "radiosity" and summary["form_factors"]["rays"] == 64
    assert summary["light_configurations"] >= 5 and len(summary["outer_iterations"]) == 3
    assert all(h["fixed_point_residual"] < 1e-5 for h in summary["outer_iterations"])
    with np.load(out) as z:
        assert {"pd", "ps", "sigma", "status", "std_pd"} <= set(z.files)
        assert json.loads(str(z["meta"]))["method"] == "radiosity" and np.all(np.isfinite(z["pd"]))
    assert_one_line_error(jaxrefl("estimate", scan, "--method", "radiosity", "--rays", 0,
                                  "--out", tmp_path / "x.npz"), "rays")
    assert not (tmp_path / "x.npz").exists()


def _reference_inverse(ff, configs, e_cfg, radiance, observed, e_obs, pd0, correction, free, iters=5000):
    """The inverse fixed point by its definition: plain iteration, dense products, no acceleration."""
    f = ff.matrix.toarray()
    n, m = observed.shape
    to_row = sp.csr_matrix((np.ones(len(ff.rows)), (ff.rows, np.arange(len(ff.rows)))), shape=(n, len(ff.rows)))
    b_obs = np.pi * np.where(observed[..., None], radiance, 0.0)
    fit = free & observed.any(1)
    pd, b = pd0.copy(), pd0[:, None, :] * e_cfg[..., None]
    for _ in range(iters):
        inter = np.einsum("uv,vcj->ucj", f, b)
        at = np.take_along_axis(inter, np.clip(configs.index, 0, None)[..., None], axis=1)
        at = at + (to_row @ (correction[..., None] * pd[ff.cols][:, None, :]).reshape(-1, m * 3)).reshape(n, m, 3)
        h = e_obs[..., None] + at
        num = np.sum(np.where(observed[..., None], b_obs * h, 0.0), 1)
        den = np.sum(np.where(observed[..., None], h * h, 0.0), 1)
        new = np.where(fit[:, None], num / np.where(den > 0, den, 1.0), pd0)
        b_new = new[:, None, :] * (e_cfg[..., None] + inter)
        done = np.abs(new - pd).max() < 1e-15 and np.abs(b_new - b).max() <= 1e-15 * np.abs(b).max()
        pd, b = new, b_new
        if done:
            break
    return pd, np.where(free[:, None, None], at, 0.0)


def test_inverse_radiosity_per_point_lights_matches_plain_iteration():
    """The host-driven Anderson solve with threaded sparse products (and the first-bounce
    correction read from the configurations' irradiance) against the definition: plain
    fixed-point iteration with dense products and the correction's binned part ray-cast
    on its own. Also: a warm start returns the same fixed point at once, and a region
    solve on the configurations its points use equals the solve on all of them."""
    from jaxrefl.methods.radiosity import first_bounce_correction, restrict_configs
    from jaxrefl.reflectance.classify import T_DIFF

    scan, _ = make_scan("A", resolution=16, lights=[0, 20, 40])
    caster = RayCaster(scan.vertices, scan.faces)
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=32, caster=caster, cache=False)
    rows = prepare_rows(scan, caster=caster)
    configs = light_configs(scan.light_pos, scan.n_points, 0.1)
    e_cfg = direct_irradiance(caster, scan.normals, configs.positions, scan.intensities()[configs.light])
    cast = first_bounce_correction(caster, ff, scan.normals, scan.light_pos, configs, scan.intensities())
    corr = first_bounce_correction(caster, ff, scan.normals, scan.light_pos, configs, scan.intensities(),
                                   e_cfg=e_cfg)
    np.testing.assert_allclose(corr, cast, rtol=0, atol=1e-12)
    assert np.abs(corr).max() > 0
    sample = rows["use"] & (rows["classes"] == T_DIFF)
    y, e = rows["y"], rows["e"]
    pd0 = np.full((scan.n_points, 3), 0.5)
    everyone = np.ones(scan.n_points, bool)
    inv = inverse_radiosity(ff, configs, e_cfg, y, sample, e, pd0, correction=corr, tol=1e-13)
    ref_pd, ref_inter = _reference_inverse(ff, configs, e_cfg, y, sample, e, pd0, corr, everyone)
    np.testing.assert_allclose(inv.pd, ref_pd, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(inv.interreflected, ref_inter, rtol=1e-9, atol=1e-12 * np.abs(ref_inter).max())
    assert np.abs(ref_inter).max() > 0 and inv.iterations < 60
    again = inverse_radiosity(ff, configs, e_cfg, y, sample, e, pd0, correction=corr, tol=1e-13,
                              init=(inv.pd, inv.radiosity))
    assert again.iterations <= 2
    np.testing.assert_allclose(again.pd, inv.pd, rtol=1e-12)
    # a region: its points' pd from only the configurations they use; the rest keep pd0
    region = scan.vertices[:, 1] > np.median(scan.vertices[:, 1])
    sub = restrict_configs(configs, region)
    assert 0 < len(sub.positions) < len(configs.positions) and np.all(sub.index[~region] == -1)
    e_sub = direct_irradiance(caster, scan.normals, sub.positions, scan.intensities()[sub.light])
    corr_sub = first_bounce_correction(caster, ff, scan.normals, scan.light_pos, sub, scan.intensities(),
                                       e_cfg=e_sub, points=region)
    part = inverse_radiosity(ff, sub, e_sub, y, sample, e, pd0, correction=corr_sub, tol=1e-13, points=region)
    full = inverse_radiosity(ff, configs, e_cfg, y, sample, e, pd0, correction=corr, tol=1e-13, points=region)
    np.testing.assert_allclose(part.pd, full.pd, rtol=1e-9)
    np.testing.assert_array_equal(part.pd[~region], pd0[~region])
    np.testing.assert_allclose(part.interreflected, full.interreflected, rtol=1e-9, atol=1e-15)
    ref_pd, _ = _reference_inverse(ff, configs, e_cfg, y, sample, e, pd0, corr, region)
    np.testing.assert_allclose(part.pd, ref_pd, rtol=1e-9, atol=1e-12)


def test_region_estimate_makes_only_its_configurations_and_keeps_method_one_elsewhere():
    """`estimate_radiosity(points=...)` (auto's regions) on a scanner scan: fewer light
    configurations than the whole object; pd inside mostly as the whole-object estimate (points
    without a diffuse-only sample lean on specular fits that see Method I's result around the
    region, so some differ) and about as far from the truth; Method I's result away from it."""
    scan, _ = make_scan("D", resolution=16, lights=list(range(0, 60, 6)), global_illumination=True, samples=16,
                        seed=0)
    caster = RayCaster(scan.vertices, scan.faces)
    options = RadiosityOptions(rays=64)
    region = scan.vertices[:, 0] > np.percentile(scan.vertices[:, 0], 70)
    whole = estimate_radiosity(scan, options, caster)
    part = estimate_radiosity(scan, options, caster, points=region)
    local = estimate_local(scan, options.local, caster)
    assert part.meta["points_estimated"] == region.sum() < whole.meta["points_estimated"] == scan.n_points
    assert 0 < part.meta["light_configurations"] < 0.8 * whole.meta["light_configurations"]
    rel = (np.abs(part.pd - whole.pd) / np.maximum(whole.pd, 1e-3)).max(1)
    assert np.median(rel[region]) < 2e-3, np.median(rel[region])
    err = lambda e: np.median((np.abs(e.pd - scan.true_pd) / scan.true_pd).mean(1)[region])  # noqa: E731
    assert err(part) < 1.25 * err(whole) + 0.005, (err(part), err(whole))
    far = scan.vertices[:, 0] < np.percentile(scan.vertices[:, 0], 40)
    # Method I's result away from the region, up to the shared prior: its materials and their
    # lobes are fitted from every point, the region's residual samples included, so a few far
    # points (those whose lobe is pooled or copied) may take another lobe; as accurate overall.
    rel_far = (np.abs(part.pd - local.pd) / np.maximum(local.pd, 1e-3)).max(1)[far]
    assert np.median(rel_far) < 2e-3, np.median(rel_far)
    err_far = lambda e: np.median((np.abs(e.pd - scan.true_pd) / scan.true_pd).mean(1)[far])  # noqa: E731
    assert err_far(part) <= 1.1 * err_far(local) + 0.002, (err_far(part), err_far(local))
    for k in ("pd", "ps", "roughness"):
        assert np.all(np.isfinite(getattr(part, k)))
    with pytest.raises(ValueError, match="points"):
        estimate_radiosity(scan, options, caster, points=np.zeros(scan.n_points, bool))


def test_method_two_on_a_quantised_convex_scan_agrees_with_method_one():
    """A nearly convex object (little interreflection), four Ward materials with broad and
    sharp lobes, a 12-bit sensor: Method II must give what Method I gives. Its residuals (the
    observations less the interreflected light) leave the sensor's lattice, so Method I is
    told the sensor's step (without it the quantised noise looked noise-free and a fifth of
    the lobes ran to the roughness bound), and pd comes from every sample with the lobe, not
    from the `T_diff` samples alone (a broad lobe still lights those: pd was 10x worse)."""
    from data_synth import zoo
    from jaxrefl.methods.local import LocalOptions, quantisation_step

    scan, _ = zoo.make_cell("ring_piecewise", n_points=642)
    assert quantisation_step(scan.radiance, scan.observed()) > 0
    caster = RayCaster(scan.vertices, scan.faces)
    ward = LocalOptions(model="ward")
    one = estimate_local(scan, ward, caster)
    two = estimate_radiosity(scan, RadiosityOptions(local=ward), caster)
    seen = scan.observed().any(1)
    for name, truth in (("pd", scan.true_pd), ("ps", scan.true_ps), ("roughness", scan.true_alpha)):
        err_one = np.median(np.abs(getattr(one, name) - truth)[seen] / truth[seen])
        err_two = np.median(np.abs(getattr(two, name) - truth)[seen] / truth[seen])
        assert err_two <= 1.2 * err_one + 2e-3, (name, err_one, err_two)
    assert np.mean(two.roughness[seen] > 1.0) < 0.01  # no lobe ran to the bound (pi / 2)
    assert np.isfinite(two.pd).all() and np.isfinite(two.ps).all()


def test_method_one_rejects_a_bad_quantisation_step():
    """The sensor's step Method II hands to Method I: a negative or non-finite one is an
    error naming the argument, before any work."""
    from data_synth import zoo

    scan, _ = zoo.make_cell("ring_piecewise", n_points=162)
    for bad in (-0.01, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="quantisation"):
            estimate_local(scan, quantisation=bad)
