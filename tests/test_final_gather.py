"""First-bounce final gather (Method III): a closed form, independence of the
proposal, and the brute-force path tracer beside Object E's fold."""

import numpy as np
import pytest
import trimesh

from data_synth.objects import fold_coordinate, make_object
from data_synth.pathtrace import Material, PathTracer
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods.final_gather import gather_parts, gather_rays
from jaxrefl.methods.photon import PhotonReplay

from .helpers import unit

CAM = np.array([0.0, 0.0, 0.7])
LIGHT = np.array([0.1, 0.1, 0.7])


def _inside_sphere(rho, subdivisions=4):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1]  # faces turned inward
    return v, f, -unit(v), rho


def _one_view(n, where):
    """`(N, 1, 3)` positions, all `where`."""
    return np.broadcast_to(np.asarray(where, float), (n, 1, 3)).copy()


@pytest.mark.parametrize("rho", [0.3, 0.9])
def test_inside_a_diffuse_sphere_the_first_bounce_is_rho_times_the_direct_light(rho):
    """A point light of intensity Y at the centre of a diffuse sphere of radius R lights
    it uniformly, E0 = Y / R^2; every point sees the whole sphere at radiance
    rho E0 / pi, so the first-bounce irradiance is D = rho E0 everywhere, and with
    a constant integrand the estimate has no Monte Carlo error: what is left is the
    mesh's faceting (the hit points lie on flat faces inside the sphere)."""
    v, f, nrm, _ = _inside_sphere(rho)
    n = len(v)
    caster = RayCaster(v, f)
    pd, ps, alpha = np.full((n, 3), rho), np.zeros(n), np.full(n, 0.2)
    y = 2.0
    observed = np.zeros((n, 1), bool)
    observed[::7] = True
    g = gather_rays(caster, nrm, _one_view(n, [0.3, 0.0, 0.0]), _one_view(n, [0.0, 0.0, 0.0]), y,
                    (pd, ps, alpha), observed, rays=64, seed=0)
    d, q = (np.asarray(x) for x in gather_parts(g, pd, ps, alpha, n, 1))
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(q))
    got = d[observed[:, 0], 0]
    np.testing.assert_allclose(got, rho * y, rtol=0.02)
    assert np.all(d[~observed[:, 0]] == 0)


def test_unbiased_whatever_the_proposal():
    """The weights hold the proposal's density: gathers drawn around roughness 0.05 and
    0.4 estimate the same first bounce for a reflectance of roughness 0.12."""
    obj = make_object("E", 32, "glossy")
    n = len(obj.vertices)
    caster = RayCaster(obj.vertices, obj.faces)
    fold = fold_coordinate(obj.vertices)
    observed = ((np.abs(fold) > 0.01) & (np.abs(fold) < 0.08))[:, None]
    params = (obj.pd, obj.ps, np.full(n, 0.12))
    out = []
    for a0 in (0.05, 0.4):
        g = gather_rays(caster, obj.normals, _one_view(n, CAM), _one_view(n, LIGHT), 1.0,
                        (obj.pd, obj.ps, np.full(n, a0)), observed, rays=1024, seed=1)
        d, q = gather_parts(g, *params, n, 1)
        out.append(np.asarray(obj.pd / np.pi * np.asarray(d)[:, 0] + obj.ps[:, None] * np.asarray(q)[:, 0])
                   [observed[:, 0]].sum(1))
    a, b = out
    assert np.all(a > 0)
    assert abs(a.sum() / b.sum() - 1) < 0.02
    assert np.median(np.abs(a / b - 1)) < 0.05


def test_gather_beside_the_fold_agrees_with_the_path_tracer_better_than_photons_alone():
    """Beside E's fold (glossy, 1-5 cm) the photon map blurs the mirror image of the
    other plate over its kernel (single vertices 3x off); the first bounce gathered
    from each vertex, plus the photon map of the later bounces, matches the
    brute-force path tracer closer. (Measured: 4.9 % mean absolute deviation
    against 15.8 %; what is left, +2 % on average, is the later bounces' photon map
    at the vertices on the plates' outer edges.)"""
    obj = make_object("E", 32, "glossy")
    n = len(obj.vertices)
    caster = RayCaster(obj.vertices, obj.faces)
    params = (obj.pd, obj.ps, obj.roughness)
    fold = np.abs(fold_coordinate(obj.vertices))
    region = np.flatnonzero((fold > 0.006) & (fold < 0.05))
    tracer = PathTracer(obj.vertices, obj.faces, obj.normals, Material(*params, "ward"), caster=caster)
    cam, light = _one_view(len(region), CAM), _one_view(len(region), LIGHT)
    total, se = tracer.render(cam, light, np.ones(1), samples=4096, seed=3, points=region, progress=False)
    direct, _ = tracer.render(cam, light, np.ones(1), samples=0, points=region, progress=False)
    ref, ref_se = (total - direct)[:, 0].sum(1), np.sqrt((se[:, 0] ** 2).sum(1))
    assert np.median(ref_se / ref) < 0.02

    def radiance(first_bounce, rays):
        rep = PhotonReplay.build(caster, obj.vertices, obj.faces, obj.normals, LIGHT[None], 1.0, CAM, params,
                                 n_photons=1_000_000, seed=0, first_bounce=first_bounce)
        out = np.asarray(rep.indirect(*params))[region, 0]
        if rays:
            observed = np.zeros((n, 1), bool)
            observed[region] = True
            g = gather_rays(caster, obj.normals, _one_view(n, CAM), _one_view(n, LIGHT), 1.0, params, observed,
                            rays=rays, seed=2)
            d, q = (np.asarray(x)[region, 0] for x in gather_parts(g, *params, n, 1))
            out = out + obj.pd[region] / np.pi * d + obj.ps[region, None] * q
        return out.sum(1)

    photons_only = np.abs(radiance(True, 0) / ref - 1)
    gathered = radiance(False, 1024) / ref - 1
    assert abs(np.mean(gathered)) < 0.035, np.mean(gathered)
    assert np.mean(np.abs(gathered)) < 0.5 * np.mean(photons_only), (np.mean(np.abs(gathered)),
                                                                      np.mean(photons_only))


def test_bad_input_is_named():
    obj = make_object("E", 16, "glossy")
    n = len(obj.vertices)
    caster = RayCaster(obj.vertices, obj.faces)
    prop = (obj.pd, obj.ps, obj.roughness)
    with pytest.raises(ValueError, match="rays"):
        gather_rays(caster, obj.normals, _one_view(n, CAM), _one_view(n, LIGHT), 1.0, prop,
                    np.ones((n, 1), bool), rays=0)
    with pytest.raises(ValueError, match="cam_pos and light_pos"):
        gather_rays(caster, obj.normals, _one_view(n, CAM)[:3], _one_view(n, LIGHT), 1.0, prop,
                    np.ones((n, 1), bool), rays=8)
