"""Final gather of the first interreflection bounce (Method III).

A photon map estimates the light arriving at a vertex from the photons that land
in the vertex's kernel (`jaxrefl.methods.gather`): photons that arrive a few millimetres
away, from a surface a few centimetres away, arrive from directions that differ
from the vertex's by tens of degrees. A diffuse reflection barely notices; the
Ward lobe of a glossy surface (alpha ~0.1 rad) does: near a fold the photon
map blurs the reflected image of the other sheet over the kernel, enough to make
single points far too bright or too dark (measurements:
`benchmarks/RESULTS_notes.md`, `benchmarks/RESULTS_inverse_photon.md`).

The first bounce (light -> surface point `y` -> observed vertex `x`) is
therefore gathered from `x` itself: for every used observation `(x, j)`, `K`
rays leave `x` in directions drawn from a cosine / Ward-lobe mixture around the
mirror direction of the camera (`photon.sample_mixture`, the proposal's
roughness): the first `round(share K)` rays from the lobe, the others from the
cosine, each group on scrambled Sobol' points shifted per observation
(Cranley-Patterson), so that both halves are stratified (the weights
`1 / (K pdf_mixture)` are then the balance heuristic of the two groups, which is
as unbiased as the one-sample mixture); Embree finds `y`, a shadow ray to the
observation's own light gives `y`'s direct irradiance `E_y`. The ray geometry is
fixed, so under any Ward reflectance the radiance `y` sends to `x` is
`(pd_y / pi + f_s(y)) E_y`, and (one-sample mixture estimator, unbiased for
every reflectance: the proposal keeps its cosine share)

    D_xj = 1/K sum_k L_k cos_k / pdf_k,    Q_xj = 1/K sum_k L_k lobe_x(w_k) cos_k / pdf_k,

the incident irradiance [W/m^2] and its lobe-weighted sum, as `jaxrefl.methods.gather`
defines `D`, `Q` (radiance `pd_x / pi D + ps_x Q`). The photon map then gathers
only photons that reflected twice or more (`PhotonReplay.build(...,
first_bounce=False)`); the sum is the whole interreflected light.

Conventions follow `data_synth.pathtrace`: one-sided surfaces, interpolated
shading normals and reflectance at `y`, rays offset from `x` along the welded
normal and from `y` along its face normal.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import qmc

from ..geometry.raycast import RayCaster
from ..reflectance import brdf
from .gather import _EXP_CAP
from .photon import PhotonReplay, _chunked, _interp, _vdot, _vhalf_angle, _vnormalize, lobe_share, sample_mixture
from .radiosity import config_cameras, light_configs

__all__ = ["GatherRays", "gather_rays", "gather_parts", "rays_within_budget", "photons_per_configuration",
           "relight_indirect", "relight_observations"]

#: Rays per batch of the host loop (bounds the memory of one Embree call).
_BATCH = 1_000_000


class GatherRays(NamedTuple):
    """Fixed geometry of the first-bounce gather, one entry per ray that reached a
    lit point, sorted by `row` (`R` entries; `jnp` arrays):

    - `row` `(R,)` int32 observation `x * M + j`; `point` `(R,)` int32 `x`;
    - `y_vertices` `(3, R)` int32, `y_bary` `(3, R)`: where the ray landed;
    - `y_cos_i`, `y_cos_o`, `y_theta_h` `(R,)`: at `y`, toward the light, toward `x`, half angle [rad];
    - `y_irradiance` `(R,)` [W/m^2]: direct irradiance of `y` from the observation's light;
    - `weight` `(R,)` [sr]: `cos_x / (K pdf)`;
    - `lobe_w` `(R,)` [1/sr]: `1 / (4 pi sqrt(cos_x cos_cam))`, 0 where the lobe is undefined;
    - `tan2` `(R,)`: `tan^2` of the half angle at `x` between the ray and the camera.
    """

    row: jax.Array
    point: jax.Array
    y_vertices: jax.Array
    y_bary: jax.Array
    y_cos_i: jax.Array
    y_cos_o: jax.Array
    y_theta_h: jax.Array
    y_irradiance: jax.Array
    weight: jax.Array
    lobe_w: jax.Array
    tan2: jax.Array


@jax.jit
def _sample(u, n, to_cam, alpha, share):
    """Gather directions at `x` for `C` rays (component-major `(3, C)` vectors):
    returns `(w_x, w_y, w_z, pdf, cos_x, lobe_w, tan2)`."""
    n, c = _vnormalize(tuple(n)), _vnormalize(tuple(to_cam))
    w, pdf = sample_mixture(u, n, c, alpha, share)
    ci, co = _vdot(n, w), _vdot(n, c)
    h = tuple(a + b for a, b in zip(w, c))
    cos_h = _vdot(n, h)
    valid = (ci > 0) & (co > 0) & (cos_h > 0) & (pdf > 0)
    th = _vhalf_angle(n, w, c)
    tan2 = jnp.where(valid, jnp.tan(jnp.minimum(th, 1.5)) ** 2, 1e30)
    lobe_w = jnp.where(valid, 1.0 / (4.0 * jnp.pi * jnp.sqrt(jnp.maximum(ci, brdf.COS_FLOOR)
                                                            * jnp.maximum(co, brdf.COS_FLOOR))), 0.0)
    return (*w, pdf, ci, lobe_w, tan2)


@jax.jit
def _at_hit(vidx, bary, pos, w, light, normals):
    """Shading geometry at the landing points `y` (`(3, C)` arrays): returns
    `(cos_i, cos_o, theta_h, dist2)` toward the light and toward `x`."""
    n = _vnormalize(tuple(_interp(vidx, bary, normals[c]) for c in range(3)))
    to_x = tuple(-a for a in w)
    d = tuple(light[c] - pos[c] for c in range(3))
    dist2 = _vdot(d, d)
    wi = _vnormalize(d)
    ci, co = _vdot(n, wi), _vdot(n, to_x)
    return ci, co, _vhalf_angle(n, wi, to_x), dist2


def gather_rays(caster: RayCaster, normals, cam_pos, light_pos, intensity, proposal, observed, rays: int,
                seed: int = 0, dtype=np.float32) -> GatherRays:
    """Trace the first-bounce gather rays of every observed `(x, j)`.

    **Arguments:** `caster` Embree scene of the mesh (`N` vertices); `normals`
    `(N, 3)` unit shading normals; `cam_pos`, `light_pos` `(N, M, 3)` [m] of every
    observation; `intensity` `(M,)` [W/sr]; `proposal` Ward `(pd (N, 3), ps (N,),
    alpha (N,))` the directions are drawn from; `observed` `(N, M)` bool the
    observations to gather for; `rays` `K` per observation (a power of two keeps
    the Sobol' points balanced); `seed`.

    **Returns:** `GatherRays` (entries of rays that reached a lit point only).
    """
    if rays < 1:
        raise ValueError(f"rays must be >= 1, got {rays}")
    v = np.asarray(caster.vertices, np.float64)
    n_pts, m = np.shape(observed)
    if np.shape(cam_pos) != (n_pts, m, 3) or np.shape(light_pos) != (n_pts, m, 3):
        raise ValueError(f"cam_pos and light_pos must be ({n_pts}, {m}, 3)")
    nrm = np.asarray(normals, np.float64)
    intensity = np.broadcast_to(np.asarray(intensity, np.float64), (m,))
    pd, ps, alpha = (np.asarray(x, np.float64) for x in proposal)
    share = np.asarray(lobe_share(jnp.asarray(pd.mean(1)), jnp.asarray(ps)), np.float64)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    sobol = np.stack([qmc.Sobol(2, scramble=True, seed=rng).random(rays) for _ in range(2)])  # (2, K, 2)
    k = np.arange(rays)
    obs = np.flatnonzero(np.asarray(observed).ravel())
    normals_t = jnp.asarray(nrm.T, dtype)
    per_batch = max(1, _BATCH // rays)
    parts = []
    for s in range(0, len(obs), per_batch):
        o = np.repeat(obs[s:s + per_batch], rays)
        x, j = o // m, o % m
        # Ray k of an observation with lobe share q: from the lobe if k < q K (u3 below q),
        # the k-th (lobe) or (k - q K)-th (cosine) point of that group's Sobol' sequence.
        n_lobe = np.rint(share[x] * rays).astype(np.int64)
        kk = np.tile(k, len(o) // rays)
        lobe = kk < n_lobe
        pts = np.where(lobe[:, None], sobol[0][kk], sobol[1][np.where(lobe, 0, kk - n_lobe)])
        u = np.c_[(pts + np.repeat(rng.random((len(o) // rays, 2)), rays, axis=0)) % 1.0,
                  np.where(lobe, 0.0, 1.0)]
        # Fixed-size chunks (photon._chunked): one compilation, whatever the batch sizes.
        *w, pdf, cos_x, lobe_w, tan2 = (a.astype(np.float64) for a in _chunked(
            _sample, len(o), tuple(a.astype(dtype) for a in (u.T, nrm[x].T, (cam_pos[x, j] - v[x]).T, alpha[x],
                                                               share[x]))))
        w = np.stack(w).T
        go = np.flatnonzero((cos_x > 0) & (pdf > 0))
        hits = caster.first_hit(caster.offset_origins(v[x[go]], caster.offset_normals[x[go]], w[go]), w[go])
        go, hits_face = go[hits.hit], hits.face[hits.hit]
        bary, pos = hits.barycentric[hits.hit], hits.points[hits.hit]
        vidx = caster.faces[hits_face]
        lit = light_pos[x[go], j[go]]
        ci, co, th, dist2 = (a.astype(np.float64) for a in _chunked(
            _at_hit, len(go), (vidx.T.astype(np.int32),) + tuple(a.T.astype(dtype) for a in (bary, pos, w[go], lit)),
            (normals_t,)))
        keep = np.flatnonzero((co > 0) & (ci > 0))  # y faces x (one-sided) and its light
        blocked = caster.segments_blocked(pos[keep], caster.face_normals[hits_face[keep]], lit[keep])
        keep = keep[~blocked]
        g = go[keep]
        parts.append(dict(
            row=o[g], point=x[g], y_vertices=vidx[keep], y_bary=bary[keep], y_cos_i=ci[keep], y_cos_o=co[keep],
            y_theta_h=th[keep], y_irradiance=intensity[j[g]] * ci[keep] / dist2[keep],
            weight=cos_x[g] / (rays * pdf[g]), lobe_w=lobe_w[g], tan2=tan2[g]))
    cat = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in GatherRays._fields}
    order = np.argsort(cat["row"], kind="stable")
    out = {}
    for k in GatherRays._fields:
        a = cat[k][order] if len(order) else cat[k].reshape((0, 3) if k in ("y_vertices", "y_bary") else (0,))
        if k in ("y_vertices", "y_bary"):
            a = a.reshape(-1, 3).T
        out[k] = jnp.asarray(a, jnp.int32 if k in ("row", "point", "y_vertices") else dtype)
    return GatherRays(**out)


def gather_parts(g: GatherRays, pd, ps, alpha, n_points: int, n_lights: int):
    """First-bounce `(D, Q)` `(N, M, 3)` each under Ward reflectance `pd` `(N, 3)`,
    `ps` `(N,)`, `alpha` `(N,)` [rad] (pure `jnp`; see the module docstring)."""
    dt = g.y_bary.dtype
    pd, ps, alpha = (jnp.asarray(x, dt) for x in (pd, ps, alpha))
    a_y = _interp(g.y_vertices, g.y_bary, alpha)
    spec = brdf.ward_specular(_interp(g.y_vertices, g.y_bary, ps), jnp.log(jnp.maximum(a_y, jnp.finfo(dt).tiny)),
                              g.y_cos_i, g.y_cos_o, g.y_theta_h)
    a2 = jnp.maximum(alpha * alpha, jnp.finfo(dt).tiny)[g.point]
    lobe = g.lobe_w * jnp.exp(-jnp.minimum(g.tan2 / a2, _EXP_CAP)) / a2
    spec, lobe = jax.lax.optimization_barrier((spec, lobe))  # once, not once per channel
    radiance = [(_interp(g.y_vertices, g.y_bary, pd[:, c]) / jnp.pi + spec) * g.y_irradiance * g.weight
                for c in range(3)]
    vals = jnp.stack(radiance + [r * lobe for r in radiance], axis=1)  # (R, 6)
    x = jax.ops.segment_sum(vals, g.row, n_points * n_lights, indices_are_sorted=True)
    x = x.reshape(n_points, n_lights, 6)
    return x[..., :3], x[..., 3:]


#: Largest number of final-gather rays `relight_indirect` traces at once (vertices are gathered
#: in blocks that fit; the ray geometry of one block is dropped before the next).
_RELIGHT_GATHER_RAYS = 4_000_000


def relight_indirect(vertices, faces, normals, pd, ps, alpha, light_pos, intensity, cam_pos,
                     n_photons: int = 1_000_000, target_photons: float = 256.0, seed: int = 0, caster=None,
                     gather_rays: int = 256):
    """Interreflected radiance `(N, 3)` [W/(sr m^2)] of every vertex toward
    `cam_pos` (`(3,)` or `(N, 3)`) under one point light at `light_pos` `(3,)`
    of radiant intensity `intensity` [W/sr], for Ward reflectance `pd` `(N, 3)`,
    `ps` `(N,)`, `alpha` `(N,)` [rad] (photons traced from that reflectance).

    As Method III models it: the first bounce (light -> surface -> vertex) is
    gathered from every vertex that faces its camera by `gather_rays` rays drawn
    from that reflectance (`jaxrefl.methods.final_gather`; a photon map blurs the mirror
    image of nearby surfaces over its kernel), the later bounces come from the
    photon map (`first_bounce=False`). `gather_rays=0`: the photon map carries
    every bounce (cheaper, blurred beside creases of glossy surfaces)."""
    if gather_rays < 0:
        raise ValueError(f"gather_rays must be >= 0, got {gather_rays}")
    v = np.asarray(vertices, dtype=np.float64)
    cam = np.asarray(cam_pos, dtype=np.float64)
    if cam.shape == (len(v), 3):
        cam = cam[:, None, :]
    light = np.asarray(light_pos, dtype=np.float64).reshape(1, 3)
    y = np.asarray(intensity, dtype=np.float64).reshape(1)
    params = tuple(np.asarray(x, dtype=np.float64) for x in (pd, ps, alpha))
    caster = caster if caster is not None else RayCaster(v, np.asarray(faces, dtype=np.int64))
    replay = PhotonReplay.build(caster, v, faces, normals, light, y, cam, params, n_photons=n_photons,
                                target_photons=target_photons, seed=seed, first_bounce=gather_rays == 0)
    out = np.asarray(replay.indirect(*params), dtype=np.float64)[:, 0, :]
    if gather_rays:
        out = out + _relight_first_bounce(caster, replay, params, light, y, gather_rays, seed)
    return out


def rays_within_budget(rays: int, observations: int, budget: int) -> int:
    """`rays` per observation halved until `observations` of them fit in `budget` rays (at least 1)."""
    rays = int(rays)
    while rays > 1 and rays * int(observations) > budget:
        rays //= 2
    return rays


def photons_per_configuration(photons: int, n_lights: int, n_configs: int) -> int:
    """Photons each of `n_configs` light configurations gets when each of the `n_lights`
    lights has `photons` to share among its configurations (at least 1000)."""
    return int(max(1000, round(photons * n_lights / n_configs)))


def _proposal(pd, ps, alpha):
    """Gather directions drawn from the reflectance relit: its lobe needs a roughness > 0
    (where ps = 0 it is not sampled anyway)."""
    return np.clip(pd, 0.0, None), np.clip(ps, 0.0, None), np.clip(np.where(alpha > 0, alpha, 0.1), 0.005, 1.0)


def relight_observations(scan, pd, ps, alpha, observed, caster=None, *, light_bin: float = 0.1,
                         n_photons: int = 1_000_000, target_photons: float = 256.0, rays: int = 1024,
                         ray_budget: int = 8_000_000, seed: int = 0) -> np.ndarray:
    """Interreflected radiance `(N, M, 3)` [W/(sr m^2)] of every observation of `scan`
    (its lights, intensities and cameras; `light_pos` `(M, 3)` or per point `(N, M, 3)`)
    for Ward reflectance `pd` `(N, 3)`, `ps` `(N,)`, `alpha` `(N,)` [rad], as Method III
    models its own observations: one photon map over the light configurations
    (`radiosity.light_configs` with `light_bin`, `n_photons` per light shared by its
    configurations) for the later bounces, one final gather of `rays` per `observed`
    `(N, M)` observation (halved while over `ray_budget` rays in all) for the first.
    Observations not in `observed` carry only the photon map's part."""
    n, m = scan.n_points, scan.n_lights
    observed = np.asarray(observed, bool)
    if observed.shape != (n, m):
        raise ValueError(f"observed: expected ({n}, {m}), got {observed.shape}")
    params = tuple(np.asarray(x, dtype=np.float64) for x in (pd, ps, alpha))
    caster = caster if caster is not None else RayCaster(scan.vertices, scan.faces)
    configs = light_configs(scan.light_pos, n, light_bin)
    replay = PhotonReplay.build(caster, scan.vertices, scan.faces, scan.normals, configs.positions,
                                scan.intensities()[configs.light], config_cameras(scan, configs), params,
                                n_photons=photons_per_configuration(n_photons, m, len(configs.positions)),
                                target_photons=target_photons, seed=seed, first_bounce=rays == 0)
    out = np.take_along_axis(np.asarray(replay.indirect(*params), np.float64), configs.index[..., None], axis=1)
    rays = rays_within_budget(rays, observed.sum(), ray_budget) if rays else 0
    if rays and observed.any():
        g = gather_rays(caster, scan.normals, scan.camera_positions(), scan.light_positions(), scan.intensities(),
                        _proposal(*params), observed, rays, seed=seed)
        d, q = (np.asarray(x, np.float64) for x in gather_parts(g, *params, n, m))
        out = out + params[0][:, None, :] / np.pi * d + params[1][:, None, None] * q
    return out


def _relight_first_bounce(caster, replay, params, light, intensity, rays, seed):
    """First-bounce radiance `(N, 3)` toward each vertex's camera (`relight_indirect`),
    gathered in blocks of vertices of at most `_RELIGHT_GATHER_RAYS` rays."""
    s = replay.settings
    n = len(s["vertices"])
    cam = np.broadcast_to(s["cam_pos"], (n, 1, 3))
    lights = np.broadcast_to(light.reshape(1, 1, 3), (n, 1, 3))
    pd, ps, alpha = params
    proposal = _proposal(pd, ps, alpha)
    facing = np.asarray(replay.data.facing)[:, 0]
    todo = np.flatnonzero(facing)
    out = np.zeros((n, 3))
    per_block = max(1, _RELIGHT_GATHER_RAYS // rays)
    for b, start in enumerate(range(0, len(todo), per_block)):
        observed = np.zeros((n, 1), bool)
        observed[todo[start:start + per_block], 0] = True
        g = gather_rays(caster, s["normals"], cam, lights, intensity, proposal, observed, rays,
                        seed=int(np.random.SeedSequence([seed, b]).generate_state(1)[0]))
        d, q = (np.asarray(x, np.float64)[:, 0] for x in gather_parts(g, pd, ps, alpha, n, 1))
        out += pd / np.pi * d + ps[:, None] * q
    return out
