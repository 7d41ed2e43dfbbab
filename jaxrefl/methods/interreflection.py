"""The light an object reflects onto itself, first bounce, as a share of the direct light.

`interreflection_ratios` sums it through form factors (Method II's, or cheap ones of a few rays
per point) with a fitted reflectance; `--method auto` decides with it where interreflection
matters, and Method I reports what it leaves in pd with it (`pd_sd_with_interreflection`).
"""

from __future__ import annotations

import numpy as np

from ..geometry.formfactors import FormFactors, form_factors
from ..geometry.raycast import RayCaster
from ..result import Estimate

__all__ = ["interreflection_ratios", "interreflected_share", "pd_sd_with_interreflection"]

_PAIRS = 1 << 16  # (form-factor entry, light) pairs per lobe evaluation in `interreflection_ratios`


def interreflection_ratios(scan, est: Estimate, ff: FormFactors, rows: dict) -> tuple[np.ndarray, np.ndarray]:
    """First-bounce interreflected over direct irradiance per point, `(g, s)` each `(N,)`,
    under the scan's own lights and with the reflectance `est` (Method I's fit).

    For every form-factor entry `(u, v)` and light `m`, patch `v` lit by `E_vm`
    (`rows['e']`, its direct irradiance in observation `m`, 0 where shadowed) sends
    `u` the irradiance `F_uv pd_v E_vm` diffusely and `pi F_uv f_s(v; l_vm -> u) E_vm`
    through its specular lobe (`est`'s model, evaluated towards `u`). Summed over `v`
    and over the samples pd is fitted from (the diffuse-only ones where a point has any,
    else all its samples), each over the direct irradiance of the same samples."""
    from ..reflectance import brdf
    from ..reflectance.classify import T_DIFF

    use, e = rows["use"], rows["e"]
    sample = np.where((use & (rows["classes"] == T_DIFF)).any(1)[:, None], use & (rows["classes"] == T_DIFF), use)
    n = scan.n_points
    pd = np.clip(est.pd.mean(axis=1), 0.0, 1.0)
    e_used = np.where(sample, e, 0.0)
    direct = e_used.sum(axis=1)
    # diffuse: sum over the samples m of u of sum_v F_uv pd_v E_vm
    diffuse = np.einsum("nm,nm->n", sample, ff.matrix @ (pd[:, None] * e))
    # specular: only entries whose sender has a lobe, and only (entry, light) pairs where u uses
    # the sample and v is lit, evaluated in fixed-size chunks (one compiled shape)
    u, v, f = ff.rows.astype(np.int64), ff.cols.astype(np.int64), ff.values
    lobed = np.flatnonzero((est.ps[v] > 0) & (est.roughness[v] > 0))
    entry, light = np.nonzero(sample[u[lobed]] & (e[v[lobed]] > 0))
    entry = lobed[entry]
    specular = np.zeros(n)
    lobe = brdf.MODELS[est.model][1]
    lights = scan.light_positions()
    for lo in range(0, len(entry), _PAIRS):
        k, m = entry[lo:lo + _PAIRS], light[lo:lo + _PAIRS]
        pad = _PAIRS - len(k)
        k, m = np.pad(k, (0, pad), mode="edge"), np.pad(m, (0, pad), mode="edge")
        uk, vk = u[k], v[k]
        to_u = scan.vertices[uk] - scan.vertices[vk]
        to_u /= np.maximum(np.linalg.norm(to_u, axis=1, keepdims=True), 1e-300)
        to_l = lights[vk, m] - scan.vertices[vk]
        to_l /= np.maximum(np.linalg.norm(to_l, axis=1, keepdims=True), 1e-300)
        n_v = scan.normals[vk]
        cos_i, cos_o = np.einsum("kj,kj->k", n_v, to_l), np.einsum("kj,kj->k", n_v, to_u)
        theta_r = brdf.half_angle(n_v, to_l, to_u)
        f_s = np.asarray(lobe(est.ps[vk], np.log(est.roughness[vk]), cos_i, cos_o, theta_r))
        contrib = np.pi * f[k] * f_s * e[vk, m]
        contrib[len(contrib) - pad:] = 0.0
        specular += np.bincount(uk, contrib, minlength=n)
    ok = direct > 0
    ratio = lambda x: np.where(ok, x / np.where(ok, direct, 1.0), 0.0)  # noqa: E731
    return ratio(diffuse), ratio(specular)


def interreflected_share(scan, est: Estimate, rows: dict, rays: int = 16, caster: RayCaster | None = None) -> np.ndarray:
    """`(N,)`: the first bounce of light the object reflects onto each point over the direct
    light, summed over the samples its pd rests on (`interreflection_ratios`, diffuse and
    specular, with `est`'s reflectance), through form factors of `rays` cosine-weighted rays
    per point (`formfactors.form_factors`: each ray's hit estimates them without bias; few
    rays make the share noisy, not biased). A point whose light comes from the object's
    surroundings only has 0."""
    caster = caster or RayCaster(scan.vertices, scan.faces)
    ff = form_factors(scan.vertices, scan.faces, scan.normals, rays=rays, caster=caster)
    diffuse, specular = interreflection_ratios(scan, est, ff, rows)
    return _as_share(diffuse + specular)


def _as_share(x):
    """A share of light: non-negative and finite (0 elsewhere)."""
    return np.where(np.isfinite(x), np.maximum(x, 0.0), 0.0)


def pd_sd_with_interreflection(scan, est: Estimate, rows: dict, rays: int = 16,
                               caster: RayCaster | None = None, share=None) -> tuple[np.ndarray, dict, str | None]:
    """Method I's pd with the light the object reflects onto itself in its uncertainty: that
    light (`interreflected_share`, or `share` `(N,)` where the caller has it) makes pd too bright
    by `pd * share / (1 + share)` (pd = truth (1 + share)), added in quadrature to `est.std_pd`
    at the observed points. Returns the new `std_pd` `(N, 3)`, a summary (`rays`,
    `share_median`, `share_p90`, `points_beyond_noise`: where that bias exceeds three of the
    noise's sds) and a warning where those are at least 5 % of the observed points (else None)."""
    observed = np.asarray(est.pd_measured, bool)
    share = interreflected_share(scan, est, rows, rays, caster) if share is None else _as_share(share)
    bias = est.pd * (share / (1.0 + share))[:, None]
    beyond = observed & np.any(bias > 3.0 * est.std_pd, 1)
    std_pd = np.where(observed[:, None], np.sqrt(est.std_pd**2 + bias**2), est.std_pd)
    info = {"rays": int(rays), "share_median": float(np.median(share[observed])),
            "share_p90": float(np.quantile(share[observed], 0.9)), "points_beyond_noise": int(beyond.sum())}
    warning = None
    if beyond.sum() >= 0.05 * observed.sum():
        warning = (f"{beyond.sum() / observed.sum():.0%} of the observed points receive light from the object itself "
                   f"beyond three standard deviations of their pd's noise (first bounce, estimated: median "
                   f"{info['share_median']:.1%} of the direct light, 90th percentile {info['share_p90']:.1%}); "
                   "Method I leaves it in pd and its std_pd includes it. Methods II and III (or --method auto) "
                   "model it.")
    return std_pd, info, warning
