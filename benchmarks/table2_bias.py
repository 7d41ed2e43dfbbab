"""Where Method III's signed Table 2 average comes from (a diagnostic, truth needed).

    python3 -m benchmarks.table2_bias --objects B,A,D --seed 0

On a Table 2 scene (`benchmarks.table2_bench`'s: `auto_bench.make_scene`, re-rendered with the
truth's gather rays and photons re-weighted to each estimate), two experiments:

- **noise weights:** Method III with its noise weights taken from the observations (the
  default), from the truth re-rendered (an oracle: noise-free weights, independent of each
  sample's own noise), and from Method I's start (a noise-free weight a user could have);
  per variant the signed average of `observed - re-rendered`, mean |d| against the
  observations and against the re-rendered truth (`model vs truth`), and pd / ps errors;
- **attribution:** the re-rendered image's direct and interreflected means (relative to the
  mean observed radiance) with the truth's reflectance, then with one of Method III's pd, ps,
  alpha swapped in, on all points and on those whose lobe was measured / filled / unobserved.
"""

from __future__ import annotations

import argparse
from unittest import mock

import jax.numpy as jnp
import numpy as np

from benchmarks.auto_bench import Scene, make_scene
from benchmarks.table2_bench import difference_stats, direct_observations, indirect_observations, rerender
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods import inverse_photon
from jaxrefl.methods.local import estimate_local, prepare_rows
from jaxrefl.outputs.relight import truth_estimate

_noise_weights = inverse_photon._noise_weights


def _params(est):
    return [np.asarray(x, np.float64) for x in (est.pd, est.ps, est.roughness)]


def weights_experiment(scan, caster, options, t_img, t_r, mask) -> dict:
    """Method III with noise weights from the observations, the re-rendered truth, Method I's start."""
    obs = scan.radiance.astype(np.float64)
    rows = prepare_rows(scan, options.thresholds, caster)
    init = estimate_local(scan, options.local, caster, rows=rows)
    pd0, ps0, a0 = inverse_photon._start(init)
    geo = {k: jnp.asarray(rows[k]) for k in ("cos_i", "cos_o", "theta_r", "e")}
    zero = jnp.zeros(obs.shape)
    start = np.asarray(inverse_photon._predicted(jnp.asarray(pd0), jnp.asarray(ps0), jnp.asarray(np.log(a0)),
                                                 geo, zero, zero))
    out = {}
    for name, smooth in (("observed", None), ("truth (oracle)", t_img), ("Method I start", start)):
        if smooth is None:
            est = inverse_photon.estimate_photon(scan, options, caster)
        else:
            def weights(y, use, floor, _s=smooth):
                return _noise_weights(jnp.asarray(_s, y.dtype), use, floor)
            with mock.patch.object(inverse_photon, "_noise_weights", weights):
                est = inverse_photon.estimate_photon(scan, options, caster)
        p = _params(est)
        img = direct_observations(scan, *p, caster) + indirect_observations(t_r, *p)
        vs_obs = difference_stats(obs, img, mask, scan.saturation)
        vs_truth = difference_stats(t_img, img, mask, scan.saturation)
        ok = scan.true_ps > 1e-9
        pd_rel = ((est.pd - scan.true_pd) / scan.true_pd).mean(1)
        out[name] = {"signed": vs_obs["signed_mean_relative"], "se": vs_obs["signed_se_relative"],
                     "mean_abs": vs_obs["relative_mean"], "model_vs_truth": vs_truth["relative_mean"],
                     "pd_median_abs": float(np.median(np.abs(pd_rel))),
                     "pd_signed_mean": float(np.mean(pd_rel[est.pd_measured])),
                     "ps_median_abs": float(np.median(np.abs(est.ps - scan.true_ps)[ok] / scan.true_ps[ok])),
                     "estimate": est}
    return out


def attribution(scan, caster, est, truth, t_r, mask) -> list[tuple[str, float, float]]:
    """`(label, direct, interreflected)` changes (relative to the mean observed radiance) when
    Method III's parameters replace the truth's, in whole and per parameter and point group."""
    mean_obs = scan.radiance[mask].mean()

    def means(p):
        return (direct_observations(scan, *p, caster)[mask].mean() / mean_obs,
                indirect_observations(t_r, *p)[mask].mean() / mean_obs)

    base = means(truth)
    mine = _params(est)
    groups = {"all": np.ones(scan.n_points, bool), "lobe measured": est.specular_identifiable,
              "lobe filled": est.pd_measured & ~est.specular_identifiable, "unobserved": ~est.pd_measured}
    rows = [("truth itself (absolute, not a change)", *base)]
    d, i = means(mine)
    rows.append(("Method III, every parameter", d - base[0], i - base[1]))
    for gname, g in groups.items():
        for k, pname in enumerate(("pd", "ps", "alpha")):
            p = list(truth)
            p[k] = np.where(g[:, None] if mine[k].ndim == 2 else g, mine[k], truth[k])
            d, i = means(p)
            rows.append((f"{pname} on {gname} points", d - base[0], i - base[1]))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", default="B,A,D")
    ap.add_argument("--setup", default="glossy", choices=("glossy", "glazed"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--photons", type=int, default=500_000)
    args = ap.parse_args(argv)
    options = inverse_photon.PhotonOptions(photons=args.photons)
    for name in args.objects.split(","):
        scan, _ = make_scene(Scene(name, name, args.setup), 32, 256, seed=args.seed)
        caster = RayCaster(scan.vertices, scan.faces)
        mask = scan.observed()
        truth = _params(truth_estimate(scan))
        t_img, t_r, _ = rerender(scan, *truth, caster, 1_000_000, 0.1, args.seed, 256, mask)
        floor = difference_stats(scan.radiance.astype(np.float64), t_img, mask, scan.saturation)
        print(f"## {name} ({args.setup}, seed {args.seed}): truth re-rendered, signed "
              f"{100 * floor['signed_mean_relative']:+.3f} %", flush=True)
        print("| noise weights from | signed average | mean abs | model vs truth | pd median abs | pd signed mean "
              "| ps median abs |\n|---|---:|---:|---:|---:|---:|---:|")
        res = weights_experiment(scan, caster, options, t_img, t_r, mask)
        for label, r in res.items():
            print(f"| {label} | {100 * r['signed']:+.3f} +- {100 * r['se']:.3f} % | {100 * r['mean_abs']:.2f} % | "
                  f"{100 * r['model_vs_truth']:.2f} % | {100 * r['pd_median_abs']:.2f} % | "
                  f"{100 * r['pd_signed_mean']:+.3f} % | {100 * r['ps_median_abs']:.2f} % |", flush=True)
        print("\n| Method III's in place of the truth's | direct change | interreflected change |\n|---|---:|---:|")
        for label, d, i in attribution(scan, caster, res["observed"]["estimate"], truth, t_r, mask):
            print(f"| {label} | {100 * d:+.3f} % | {100 * i:+.3f} % |")
        print(flush=True)


if __name__ == "__main__":
    main()
