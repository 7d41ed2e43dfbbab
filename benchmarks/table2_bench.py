"""Table 2 and Figure 25 analogues: observed vs photon-mapped re-rendered images, Methods II and III.

    python3 -m benchmarks.table2_bench                  # A-D and glazed A-D -> RESULTS_table2.md, table2_fig25.png
    python3 -m benchmarks.table2_bench --setup glazed   # glazed A-D only
    python3 -m benchmarks.table2_bench --quick          # smoke run (small meshes, few paths and photons)

Paper §5.3.2, Table 2: the average and variance of the differences between the
real images and images synthesised by photon mapping with each method's
estimate, under the capture lights. Here, per object:

- the scan: Objects A-D on the paper's scanner under their selected lights,
  path-traced global illumination, 1 % noise, 12 bits, Ward model (the scenes
  of `benchmarks.auto_bench.make_scene`, imported, not copied), in their own
  reflectance (`setup='glossy'`, the default) and glazed (`setup='glazed'`:
  their pd under one uniform Ward lobe, ps 0.3, alpha 0.08, as glossy E; the
  paper's objects were glazed, and its Method II errors of 9-20 image levels
  show strong specular interreflection, which the default A-D do not carry);
- the estimates: Method II (`radiosity.estimate_radiosity`, Ward local options)
  and Method III (`inverse_photon.estimate_photon`);
- the re-rendering of every observation (each point under each of its capture
  lights, toward its camera): the direct term (Ward BRDF x `Y cos_i / C^2`, an
  Embree shadow ray: what `relight.direct_radiance` computes for one light,
  here per observation because the scanner's lights ride its head) plus
  interreflection as Method III models it and `final_gather.relight_indirect`
  renders it: the first bounce gathered from every observation
  (`final_gather.gather_rays` / `gather_parts`, rays drawn from and weighted
  by the reflectance being rendered), the later bounces from a photon map
  (`photon.PhotonReplay.build(..., first_bounce=False)` + `indirect`, photons
  traced from that reflectance, shared by the light configurations: per-point
  lights binned as Method III bins them). Both methods, and the ground truth,
  go through the same renderer; the truth also through the photon map alone
  (every bounce, `--gather-rays 0`: the renderer before the final gather), for
  the floor it had;
- the difference `|observed - re-rendered|` over every observed sample and RGB
  channel (valid, not saturated): mean and variance in radiance units, relative
  to the mean observed radiance, and in 8-bit levels of the sensor's full scale
  (the paper's units); the ratio II / III;
- floors: the same difference for the ground truth re-rendered (sensor noise +
  path-tracer noise + photon-map error: no estimate can be expected below it),
  the path tracer's own noise (two further renders with other seeds:
  `mean |a - b| / sqrt(2)`), and the sensor noise expected from its model;
- Figure 25: Method III's image difference per iteration
  (`meta['image_difference']['mean_abs']`), one curve per object.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.auto_bench import E_TILT, Scene, make_scene
from data_synth.scans import make_scan
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.geometry.rig import observation_geometry
from jaxrefl.methods.final_gather import gather_parts, gather_rays
from jaxrefl.methods.inverse_photon import ALPHA_RANGE, PhotonOptions, estimate_photon
from jaxrefl.methods.local import LocalOptions, prepare_rows
from jaxrefl.methods.photon import PhotonReplay
from jaxrefl.methods.radiosity import RadiosityOptions, config_cameras, estimate_radiosity, light_configs
from jaxrefl.outputs.relight import truth_estimate
from jaxrefl.reflectance import brdf
from jaxrefl.reflectance.classify import T_DIFF, T_NONE, T_SPEC

OBJECTS = ("A", "B", "C", "D")
SETUPS = ("glossy", "glazed")
HERE = os.path.dirname(os.path.abspath(__file__))


# -- the renderer ---------------------------------------------------------------------------


def direct_observations(scan, pd, ps, alpha, caster) -> np.ndarray:
    """Direct radiance `(N, M, 3)` of every observation toward its camera (Ward, shadows)."""
    g = observation_geometry(scan.vertices, scan.normals, scan.camera_positions(), scan.light_pos)
    full, _ = brdf.MODELS["ward"]
    dt = jnp.asarray(g.cos_i).dtype
    f = jax.vmap(full, in_axes=(None, None, None, 1, 1, 1), out_axes=1)(
        jnp.asarray(pd, dt), jnp.asarray(ps, dt), jnp.log(jnp.maximum(jnp.asarray(alpha, dt), 1e-12)),
        jnp.asarray(g.cos_i), jnp.asarray(g.cos_o), jnp.asarray(g.theta_r))
    y = scan.intensities()[None, :, None]
    radiance = np.asarray(f, np.float64) * y * np.asarray(g.cos_i)[..., None] / np.asarray(g.light_distance)[..., None] ** 2
    lit = caster.visibility(scan.light_pos) & (np.asarray(g.cos_i) > 0) & (np.asarray(g.cos_o) > 0)
    return np.where(lit[..., None] & np.isfinite(radiance), radiance, 0.0)


class Renderer(NamedTuple):
    """The fixed ray geometry of one re-rendering: the photon map (`replay`, over the light
    `configs`) and the first-bounce gather rays `fg` (None: the photon map holds every bounce)."""

    replay: PhotonReplay
    configs: object
    fg: object
    shape: tuple


def rerender(scan, pd, ps, alpha, caster, photons: int, light_bin: float, seed: int, rays: int, mask):
    """Every observation re-rendered `(N, M, 3)`: direct + interreflection, the first bounce
    gathered from each observation in `mask` `(N, M)` by `rays` rays (0: none, the photon
    map carries every bounce), the later bounces photon-mapped; rays and photons traced from
    `(pd, ps, alpha)` itself; `photons` per light (shared by the light configurations as in
    Method III). Also returns the `Renderer` (for re-weighting the same rays and photons to
    another reflectance) and facts about the render."""
    t0 = time.perf_counter()
    direct = direct_observations(scan, pd, ps, alpha, caster)
    configs = light_configs(scan.light_pos, scan.n_points, light_bin)
    n_cfg = len(configs.positions)
    per_cfg = int(max(1000, round(photons * scan.n_lights / n_cfg)))
    params = tuple(np.asarray(x, np.float64) for x in (pd, ps, alpha))
    replay = PhotonReplay.build(caster, scan.vertices, scan.faces, scan.normals, configs.positions,
                                scan.intensities()[configs.light], config_cameras(scan, configs), params,
                                n_photons=per_cfg, seed=seed, first_bounce=rays == 0)
    fg = None
    if rays:
        # The proposal needs a roughness > 0 in range (its lobe is not sampled where ps = 0).
        proposal = (np.clip(params[0], 0.0, 1.0), np.clip(params[1], 0.0, None),
                    np.clip(np.where(params[2] > 0, params[2], 0.1), *ALPHA_RANGE))
        fg = gather_rays(caster, scan.normals, scan.camera_positions(), scan.light_positions(), scan.intensities(),
                         proposal, mask, rays, seed=seed)
    r = Renderer(replay, configs, fg, (scan.n_points, scan.n_lights))
    image = direct + indirect_observations(r, *params)
    return image, r, {"configurations": n_cfg, "photons_per_configuration": per_cfg, "gather_rays": rays,
                      "gather_entries": 0 if fg is None else int(fg.row.shape[0]),
                      "seconds": time.perf_counter() - t0}


def indirect_observations(r: Renderer, pd, ps, alpha) -> np.ndarray:
    """The renderer's interreflected radiance per observation `(N, M, 3)` for `(pd, ps, alpha)`:
    the photon map's, plus the gathered first bounce `pd / pi D + ps Q` (as Method III's `_parts`)."""
    ind = np.asarray(r.replay.indirect(pd, ps, alpha), np.float64)  # (N, C, 3)
    ind = np.take_along_axis(ind, r.configs.index[..., None], axis=1)
    if r.fg is not None:
        d, q = (np.asarray(x, np.float64) for x in gather_parts(r.fg, pd, ps, alpha, *r.shape))
        ind = ind + np.asarray(pd, np.float64)[:, None, :] / np.pi * d + np.asarray(ps, np.float64)[:, None, None] * q
    return ind


# -- statistics -------------------------------------------------------------------------------


def difference_stats(observed, rendered, mask, full_scale) -> dict:
    """The difference over `mask` `(N, M)` x RGB: mean and variance of `|observed - rendered|`,
    and of the signed `observed - rendered` (the paper's Table 2 reading, below) with the
    standard error of its mean, clustered by point (a point's samples share its estimate
    and its renderer noise, so they are not independent)."""
    signed = observed - rendered
    d = np.abs(signed)[mask]  # (K, 3)
    mean_obs = float(observed[mask].mean())
    to8 = 255.0 / full_scale
    s = signed[mask]
    mean_s = float(s.mean())
    per_point = np.where(mask[..., None], signed, 0.0).sum((1, 2))  # (N,)
    count = 3.0 * mask.sum(1)
    se = float(np.sqrt(np.sum((per_point - mean_s * count) ** 2)) / count.sum())
    return {"mean": float(d.mean()), "var": float(d.var()), "relative_mean": float(d.mean()) / mean_obs,
            "mean_8bit": float(d.mean()) * to8, "var_8bit": float(d.var()) * to8**2,
            "signed_mean_relative": mean_s / mean_obs, "signed_se_relative": se / mean_obs,
            "signed_mean_8bit": mean_s * to8, "signed_var_8bit": float(s.var()) * to8**2,
            "p99_relative": float(np.percentile(d, 99)) / mean_obs}


def signed_ratio(ii: dict, iii: dict) -> tuple[float, float]:
    """`|mean II| / |mean III|` of the signed differences, and its conservative lower bound
    `(|II| - 2 se) / (|III| + 2 se)` (0 where II is within 2 se of 0)."""
    a, b = abs(ii["signed_mean_relative"]), abs(iii["signed_mean_relative"])
    lo = max(a - 2 * ii["signed_se_relative"], 0.0) / (b + 2 * iii["signed_se_relative"])
    return a / max(b, 1e-300), lo


def breakdown(observed, rendered, mask, classes, concave, share_top=0.01) -> dict:
    """Where the difference sits: mean |d| (relative to the mean observed) per sample class and
    on concave / convex points, and the share of the total carried by the worst 1 % of points."""
    d = np.abs(observed - rendered).mean(-1)  # (N, M)
    mean_obs = float(observed[mask].mean())
    out = {}
    for name, sel in (("T_diff", classes == T_DIFF), ("T_spec", classes == T_SPEC), ("T_none", classes == T_NONE),
                      ("concave", concave[:, None] & mask), ("convex", ~concave[:, None] & mask)):
        s = sel & mask
        out[name] = {"samples": int(s.sum()), "relative_mean": float(d[s].mean()) / mean_obs if s.any() else None}
    per_point = np.where(mask, d, 0.0).sum(1)
    k = max(1, int(round(share_top * len(per_point))))
    out["worst_1pct_points_share"] = float(np.sort(per_point)[-k:].sum() / max(per_point.sum(), 1e-300))
    return out


def sensor_floor(observed, mask, noise, full_scale, bits) -> float:
    """Expected mean |sensor error| (Gaussian relative `noise` + uniform quantisation)."""
    q = full_scale / (2**bits - 1)
    sd = np.sqrt((noise * observed[mask]) ** 2 + q**2 / 12.0)
    return float(np.sqrt(2.0 / np.pi) * sd.mean())


def path_tracer_noise(scene, scan, lights, args) -> dict:
    """The path tracer's own noise at the scan's paths per observation: two more clean
    renders with other seeds, `mean |a - b| / sqrt(2)` over the observed samples."""
    kw = dict(resolution=args.resolution, setup=scene.setup, rig=scene.rig, model=scene.model, lights=lights,
              global_illumination=True, samples=args.samples * scene.samples_factor)
    if scene.name == "E":  # as make_scene sets it
        kw["tilt_deg"] = (E_TILT, 0.0)
    t0 = time.perf_counter()
    a, _ = make_scan(scene.name, seed=args.seed + 1000, **kw)
    b, _ = make_scan(scene.name, seed=args.seed + 2000, **kw)
    mask = scan.observed()
    diff = np.abs(a.radiance.astype(np.float64) - b.radiance)[mask] / np.sqrt(2.0)
    mean_obs = float(scan.radiance[mask].mean())
    return {"mean": float(diff.mean()), "relative_mean": float(diff.mean()) / mean_obs,
            "seconds": time.perf_counter() - t0}, 0.5 * (a.radiance.astype(np.float64) + b.radiance)


# -- one object -------------------------------------------------------------------------------


def run_object(name, setup, args) -> dict:
    # A-D on the scanner, in their own reflectance ('glossy') or glazed; 'E': glossy Object E tilted
    # on the fixed camera (auto_bench's scene), where specular interreflection is strong, for contrast
    if name == "E":
        scene = Scene("E glossy", "E", "glossy", samples_factor=4)
    else:
        scene = Scene(name if setup == "glossy" else f"{name} {setup}", name, setup)
    t0 = time.perf_counter()
    scan, lights = make_scene(scene, args.resolution, args.samples, seed=args.seed)
    render_s = time.perf_counter() - t0
    caster = RayCaster(scan.vertices, scan.faces)
    mask = scan.observed()
    observed = scan.radiance.astype(np.float64)
    local = LocalOptions(model="ward")
    row = {"object": scene.label, "name": name, "setup": scene.setup, "points": scan.n_points, "lights": lights, "observed_samples": int(mask.sum()),
           "mean_observed": float(observed[mask].mean()), "full_scale": float(scan.saturation),
           "render_s": render_s, "seconds": {}, "diff": {}, "render": {}}
    row["pt_noise"], pt_mean = path_tracer_noise(scene, scan, lights, args)
    row["sensor_floor_relative"] = sensor_floor(observed, mask, 0.01, scan.saturation, 12) / row["mean_observed"]

    estimates = {"truth": truth_estimate(scan)}
    t = time.perf_counter()
    estimates["II"] = estimate_radiosity(scan, RadiosityOptions(local=local), caster)
    row["seconds"]["II"] = time.perf_counter() - t
    t = time.perf_counter()
    estimates["III"] = estimate_photon(scan, PhotonOptions(photons=args.photons, iterations=args.iterations,
                                                           local=local), caster)
    row["seconds"]["III"] = time.perf_counter() - t
    meta = estimates["III"].meta
    row["image_difference"] = meta["image_difference"]
    row["best_iteration"] = meta["best_iteration"]
    row["retraces"] = len(meta["retraces"])
    row["III_gather_rays"] = meta.get("gather_rays_per_observation")
    row["III_seconds_per_stage"] = meta["seconds"]

    prep = prepare_rows(scan, local.thresholds, caster)
    classes = np.asarray(prep["classes"])
    rendered = {}
    truth_params = (scan.true_pd, scan.true_ps, scan.true_alpha)
    jobs = [(label, est, args.gather_rays) for label, est in estimates.items()]
    if args.gather_rays:  # the truth through the photon map alone: the floor before the final gather
        jobs.append(("truth_pm", estimates["truth"], 0))
    for label, est, rays in jobs:
        img, renderer, info = rerender(scan, est.pd, est.ps, est.roughness, caster, args.render_photons,
                                       args.light_bin, args.seed, rays, mask)
        rendered[label] = img
        row["render"][label] = info
        row["diff"][label] = difference_stats(observed, img, mask, scan.saturation)
        if label == "truth":
            truth_renderer, truth_direct = renderer, img - indirect_observations(renderer, *truth_params)
        del renderer
    # The image error the estimate itself causes, without observation noise: each estimate
    # rendered with the truth's rays and photons re-weighted (common random numbers) against the truth.
    t = estimates["truth"]
    ind_truth = rendered["truth"] - truth_direct
    for label in ("II", "III"):
        est = estimates[label]
        img = direct_observations(scan, est.pd, est.ps, est.roughness, caster) + indirect_observations(
            truth_renderer, *(np.asarray(x, np.float64) for x in (est.pd, est.ps, est.roughness)))
        row["diff"][label]["model_vs_truth_relative"] = difference_stats(rendered["truth"], img, mask,
                                                                         scan.saturation)["relative_mean"]
    # Specular interreflection in the observations: the truth's interreflected light with and
    # without lobes (ps = 0 everywhere: what a diffuse-only interreflection model can explain).
    ind_diffuse = indirect_observations(truth_renderer, np.asarray(t.pd, np.float64),
                                        np.zeros(scan.n_points), np.asarray(t.roughness, np.float64))
    spec_ind = np.abs(ind_truth - ind_diffuse)
    row["interreflection"] = {
        "indirect_relative": float(ind_truth[mask].mean()) / row["mean_observed"],
        "specular_indirect_relative": float(spec_ind[mask].mean()) / row["mean_observed"],
        "specular_indirect_max_relative": float(spec_ind.mean(-1)[mask].max()) / row["mean_observed"],
        "specular_indirect_p99_relative": float(np.percentile(spec_ind.mean(-1)[mask], 99)) / row["mean_observed"],
    }
    share = np.where(mask, ind_truth.mean(-1) / np.maximum(observed.mean(-1), 1e-12), 0.0).max(1)
    concave = share > 0.05  # interreflected light is more than 5 % of some observation of the point
    row["concave_points"] = int(concave.sum())
    # The renderer against the path tracer, both with the true reflectance (the mean of the two
    # noise renders: its own noise is PT noise / sqrt(2)): photon-map noise, smoothing, light binning.
    for label, key in (("truth", "renderer_vs_pt"), ("truth_pm", "renderer_pm_vs_pt")):
        if label not in rendered:
            continue
        d = np.abs(rendered[label] - pt_mean).mean(-1)
        row[key] = {
            "relative_mean": float(d[mask].mean()) / row["mean_observed"],
            "concave_relative_mean": float(d[mask & concave[:, None]].mean()) / row["mean_observed"]
            if concave.any() else None,
            "convex_relative_mean": float(d[mask & ~concave[:, None]].mean()) / row["mean_observed"],
            "signed_concave_relative_mean": float((rendered[label] - pt_mean).mean(-1)[mask & concave[:, None]].mean())
            / row["mean_observed"] if concave.any() else None}
    row["breakdown"] = {k: breakdown(observed, rendered[k], mask, classes, concave) for k in rendered}
    for label in ("II", "III"):
        est = estimates[label]
        rel = (np.abs(est.pd - scan.true_pd) / np.maximum(scan.true_pd, 1e-12)).mean(1)
        ps_ok = scan.true_ps > 1e-9
        row.setdefault("errors", {})[label] = {
            "pd_median": float(np.median(rel)), "pd_concave_median": float(np.median(rel[concave]))
            if concave.any() else None,
            "ps_median": float(np.median(np.abs(est.ps[ps_ok] - scan.true_ps[ps_ok]) / scan.true_ps[ps_ok]))}
    d2, d3 = row["diff"]["II"]["mean"], row["diff"]["III"]["mean"]
    row["ratio_mean"] = d2 / d3
    row["ratio_var"] = row["diff"]["II"]["var"] / row["diff"]["III"]["var"]
    row["ratio_signed"], row["ratio_signed_low"] = signed_ratio(row["diff"]["II"], row["diff"]["III"])
    row["ratio_model"] = row["diff"]["II"]["model_vs_truth_relative"] / row["diff"]["III"]["model_vs_truth_relative"]
    return row


# -- report -------------------------------------------------------------------------------------


def fig25(rows, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    groups = [(setup, [r for r in rows if r["setup"] == setup]) for setup in dict.fromkeys(r["setup"] for r in rows)]
    fig, axes = plt.subplots(len(groups), 2, figsize=(11, 3.9 * len(groups)), squeeze=False)
    for (setup, group), ax in zip(groups, axes):
        for r in group:
            mad = np.asarray(r["image_difference"]["mean_abs"]) / r["mean_observed"]
            cost = np.asarray(r["image_difference"]["cost"])
            it = np.arange(len(mad))
            label = f"Object {r['object']}" + (" (oblique)" if r["name"] == "E" else "")
            ax[0].plot(it, 100 * mad, marker=".", label=label)
            ax[1].plot(it, cost / cost[0], marker=".", label=label)
            ax[1].plot(r["best_iteration"], cost[r["best_iteration"]] / cost[0], "o", mfc="none", ms=8,
                       color=ax[1].lines[-1].get_color())
            ax[0].axhline(100 * r["diff"]["truth"]["relative_mean"], lw=0.8, ls=":", color=ax[0].lines[-1].get_color())
        what = "own reflectance" if setup == "glossy" else setup
        ax[0].set(xlabel="iteration", ylabel="mean |observed - model| [% of mean obs.]", yscale="log")
        ax[0].set_title(f"Method III image difference, {what}\n(dotted: the truth re-rendered)", fontsize=10)
        ax[1].set(xlabel="iteration", ylabel="Eq. 14 cost / first iteration", yscale="log")
        ax[1].set_title(f"noise-weighted sum of squares, {what}\n(circle: the iteration kept)", fontsize=10)
        for a in ax:
            a.grid(alpha=0.3)
            for axis in (a.yaxis.set_major_formatter, a.yaxis.set_minor_formatter):
                axis(FuncFormatter(lambda y, _: f"{y:g}"))
        ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.2f} %"


def _findings(path) -> list[str]:
    """The hand-written `## Findings` section of an earlier report at `path` (kept across
    re-runs; check it against the new tables), or a placeholder."""
    if os.path.exists(path):
        text = open(path).read()
        if "## Findings" in text:
            body = text.split("## Findings", 1)[1].split("\n## ", 1)[0]
            return ["## Findings" + body.rstrip("\n"), ""]
    return ["## Findings", "", "(to be written by hand from the tables below)", ""]


def report(rows, args, wall, load_before, load_after, fig_path) -> str:
    cmd = "python3 -m benchmarks.table2_bench" + (" --quick" if args.quick else "") + (
        f" --setup {args.setup}" if args.setup != "both" else "") + (
        f" --objects {args.objects}" if args.objects != ",".join(OBJECTS) else "")
    lines = ["# Table 2 / Figure 25 analogue: observed vs re-rendered images", "",
             f"`{cmd}` "
             f"({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} CPUs, JAX {jax.__version__}; "
             f"wall {wall:.0f} s; load average before {load_before}, after {load_after}: the machine is shared).", ""]
    lines += _findings(args.out)
    lines += ["## Set-up", "",
              f"- Scenes (`benchmarks.auto_bench.make_scene`): Objects A-D, mesh resolution {args.resolution}, the "
              f"paper's scanner under the lights the greedy selection picks, path-traced global illumination with "
              f"{args.samples} paths per observation, 1 % noise, 12 bits (full scale at the 99.9th percentile), Ward "
              f"model, seed {args.seed}; in their own reflectance (`setup='glossy'`, `data_synth.objects` default: "
              "weak or broad lobes except small glossy parts) and glazed (`setup='glazed'`: each object's own pd "
              "under one uniform Ward lobe, ps 0.3, alpha 0.08 rad, the lobe of glossy E; the paper's objects were "
              "glazed). For contrast, E: Object E in glossy paper (Ward pd 0.7, ps 0.3, alpha 0.08) on "
              f"the fixed camera, tilted {E_TILT:g} deg about x, under its selected lights, {4 * args.samples} paths, "
              "where most interreflected light is specular.",
              f"- Method II: `estimate_radiosity(scan, RadiosityOptions(local=LocalOptions(model='ward')))`. "
              f"Method III: `estimate_photon(scan, PhotonOptions(photons={args.photons:,}, "
              f"iterations={args.iterations}))` (defaults otherwise: lm solver, damping 0.5, first bounce from "
              "the final gather, 256 rays per observation capped by its budget of 8M rays).",
              f"- Re-rendering: every observed sample (point x capture light, valid, not saturated) = direct "
              f"(Ward, shadow ray, the observation's own light and camera) + interreflection as Method III models "
              f"it and `final_gather.relight_indirect` renders it: the first bounce gathered from the observation by "
              f"{args.gather_rays} rays (`final_gather.gather_rays` / `gather_parts`, drawn from and weighted by the "
              f"reflectance being rendered), the later bounces from a photon map ({args.render_photons:,} photons "
              f"per light, `PhotonReplay.build(..., first_bounce=False)` + `indirect`, shared by the light "
              f"configurations binned at {args.light_bin} m as Method III does, traced from the reflectance being "
              "rendered). The same renderer for the truth, Method II and Method III. `truth, photon map only`: the "
              "truth through the photon map of every bounce (no gather: the renderer of the earlier run).",
              "- Difference: `|observed - re-rendered|` per sample and RGB channel; mean and variance in radiance "
              "units [W/(sr m^2)], relative to the mean observed radiance, and in 8-bit levels of the sensor's "
              "full scale (x 255 / full scale; the paper's Table 2 is in image levels).", "",
              "## Table 2 as the paper prints it", "",
              "The paper's Table 2 gives the average and the variance of the differences between the real and the "
              "synthesised images, in image levels. Read literally, that is the signed difference `observed - "
              "re-rendered`: its mean (the image's bias; the noise of the data and of the renderer averages out "
              "there) and its variance (noise and misfit together). Here in 8-bit levels of the sensor's full "
              "scale and, in brackets, relative to the mean observed radiance +- its standard error (clustered by "
              "point); `II / III`: |average II| / |average III|, in brackets its lower bound "
              "(|II| - 2 se) / (|III| + 2 se); `truth`: the true reflectance through the same renderer. The mean "
              "of |observed - re-rendered| (the other reading) is in the Summary below.", "",
              "| object | average II | average III | II / III (lower bound) | 5x | average truth | variance II | "
              "variance III | II / III | variance truth |", "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        dd = r["diff"]

        def avg(k):
            return (f"{dd[k]['signed_mean_8bit']:+.3f} ({100 * dd[k]['signed_mean_relative']:+.2f} +- "
                    f"{100 * dd[k]['signed_se_relative']:.2f} %)")
        lines.append(f"| {r['object']} | {avg('II')} | {avg('III')} | {r['ratio_signed']:.1f} "
                     f"({r['ratio_signed_low']:.1f}) | {'yes' if r['ratio_signed_low'] >= 5 else 'no'} | {avg('truth')} | "
                     f"{dd['II']['signed_var_8bit']:.3f} | {dd['III']['signed_var_8bit']:.3f} | "
                     f"{dd['II']['signed_var_8bit'] / dd['III']['signed_var_8bit']:.2f} | "
                     f"{dd['truth']['signed_var_8bit']:.3f} |")
    lines += ["", "## Summary", "",
              "Mean |observed - re-rendered| relative to the mean observed radiance; `floor`: the truth re-rendered "
              "(with the gather / photon map only); `renderer vs PT`: mean |re-rendered truth - path tracer| with the "
              "true reflectance, all samples / concave points, with the gather and with the photon map only; `specular "
              "indirect`: the truth's interreflected light that involves a lobe (below).", "",
              "| object | II | III | II / III mean (var.) | 5x | floor | floor, photon map only | renderer vs PT: all / "
              "concave | photon map only: all / concave | specular indirect |",
              "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        rv, rp = r["renderer_vs_pt"], r.get("renderer_pm_vs_pt")
        pm = r["diff"].get("truth_pm")
        lines.append(f"| {r['object']} | {_pct(r['diff']['II']['relative_mean'])} | "
                     f"{_pct(r['diff']['III']['relative_mean'])} | {r['ratio_mean']:.2f} ({r['ratio_var']:.2f}) | "
                     f"{'yes' if r['ratio_mean'] >= 5 else 'no'} | {_pct(r['diff']['truth']['relative_mean'])} | "
                     f"{_pct(pm['relative_mean']) if pm else '-'} | {_pct(rv['relative_mean'])} / "
                     f"{_pct(rv['concave_relative_mean'])} | "
                     + (f"{_pct(rp['relative_mean'])} / {_pct(rp['concave_relative_mean'])}" if rp else "-")
                     + f" | {_pct(r['interreflection']['specular_indirect_relative'])} |")
    lines += ["", "## The differences in full", "",
              "| object | points | samples | mean obs. | method | mean \\|d\\| | var \\|d\\| | mean rel. | mean / var (8-bit) "
              "| signed mean rel. | p99 rel. |",
              "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    names = {"truth": "truth (floor)", "truth_pm": "truth, photon map only"}
    for r in rows:
        for k in ("II", "III", "truth", "truth_pm"):
            if k not in r["diff"]:
                continue
            s = r["diff"][k]
            lines.append(f"| {r['object']} | {r['points']} | {r['observed_samples']} | {r['mean_observed']:.4f} | "
                         f"{names.get(k, k)} | {s['mean']:.3e} | {s['var']:.3e} | "
                         f"{_pct(s['relative_mean'])} | {s['mean_8bit']:.3f} / {s['var_8bit']:.3f} | "
                         f"{_pct(s['signed_mean_relative'])} | {_pct(s['p99_relative'])} |")
    lines += ["", "`model vs truth`: mean |re-rendered estimate - re-rendered truth| (the truth's gather rays and "
              "photons re-weighted to the estimate: the image error the estimate causes, without observation noise). "
              "`renderer vs PT`: mean |re-rendered truth - path tracer| (mean of the two noise renders), the truth's "
              "reflectance in both: the renderer's own error, all samples / concave / convex points, and on concave "
              "points signed. `indirect`: the truth's interreflected light, `specular indirect`: its part that "
              "involves a specular lobe (ps = 0 everywhere removes it), both as mean over the samples relative to "
              "the mean observed radiance (specular: its 99th percentile / maximum over the samples, relative to "
              "the same mean, in brackets).", "",
              "| object | II / III mean | II / III variance | model vs truth II / III | ratio | path tracer noise "
              "(rel.) | sensor noise expected (rel.) | indirect | specular indirect (p99 / max) | renderer vs PT: all / "
              "concave / convex (concave signed) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        ir, rv = r["interreflection"], r["renderer_vs_pt"]
        lines.append(f"| {r['object']} | {r['ratio_mean']:.2f} | {r['ratio_var']:.2f} | "
                     f"{_pct(r['diff']['II']['model_vs_truth_relative'])} / "
                     f"{_pct(r['diff']['III']['model_vs_truth_relative'])} | {r['ratio_model']:.2f} | "
                     f"{_pct(r['pt_noise']['relative_mean'])} | {_pct(r['sensor_floor_relative'])} | "
                     f"{_pct(ir['indirect_relative'])} | {_pct(ir['specular_indirect_relative'])} "
                     f"({_pct(ir['specular_indirect_p99_relative'])} / {_pct(ir['specular_indirect_max_relative'])}) | "
                     f"{_pct(rv['relative_mean'])} / {_pct(rv['concave_relative_mean'])} / "
                     f"{_pct(rv['convex_relative_mean'])} ({_pct(rv['signed_concave_relative_mean'])}) |")
    lines += ["", "## Where the difference sits", "",
              "Mean |d| relative to the mean observed radiance, per sample class (classification of the scan) and on "
              "concave points (interreflected light > 5 % of some observation, from the truth's re-rendering) vs the "
              "rest; `worst 1 %`: share of the summed difference carried by the worst 1 % of points.", "",
              "| object | method | T_diff | T_spec | T_none | concave (points) | convex | worst 1 % | pd err. median "
              "(concave) | ps err. median |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        for k in ("II", "III", "truth", "truth_pm"):
            if k not in r["breakdown"]:
                continue
            b = r["breakdown"][k]
            e = r.get("errors", {}).get(k)
            cells = [_pct(b[c]["relative_mean"]) for c in ("T_diff", "T_spec", "T_none")]
            errs = (f"{_pct(e['pd_median'])} ({_pct(e['pd_concave_median'])}) | {_pct(e['ps_median'])}"
                    if e else "- | -")
            lines.append(f"| {r['object']} | {names.get(k, k)} | " + " | ".join(cells) +
                         f" | {_pct(b['concave']['relative_mean'])} ({r['concave_points']}) | "
                         f"{_pct(b['convex']['relative_mean'])} | {_pct(b['worst_1pct_points_share'])} | {errs} |")
    lines += ["", "## Figure 25 analogue", "", f"![Method III image difference per iteration]({os.path.basename(fig_path)})",
              "", "Method III's image difference (mean |observed - model| over the used samples, the model being "
              "its own forward model, gather and photon map, at the estimate each iteration started from) per "
              "iteration, relative to the mean observed radiance; `kept`: the iteration Method III keeps (smallest "
              "noise-weighted Eq. 14 cost) and its mean |d|:", "",
              "| object | first | smallest (iteration) | last | kept (iteration) | re-traces |",
              "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        mad = np.asarray(r["image_difference"]["mean_abs"]) / r["mean_observed"]
        lines.append(f"| {r['object']} | {_pct(mad[0])} | {_pct(mad.min())} ({int(np.argmin(mad))}) | {_pct(mad[-1])} "
                     f"| {_pct(mad[r['best_iteration']])} ({r['best_iteration']}) | {r['retraces']} |")
    lines += ["", "## Timing", "", "| object | render s | PT noise renders s | II s | III s | re-render s "
              "(truth, II, III, truth photon map only) |", "|---|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['object']} | {r['render_s']:.1f} | {r['pt_noise']['seconds']:.1f} | {r['seconds']['II']:.1f} | "
                     f"{r['seconds']['III']:.1f} | " + ", ".join(f"{v['seconds']:.1f}" for v in r["render"].values())
                     + " |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smoke run: small meshes, few paths, photons, iterations")
    p.add_argument("--objects", default=",".join(OBJECTS),
                   help="comma list of A-D (scanner) and E (glossy Object E, oblique, for contrast; run once, "
                        "whatever --setup)")
    p.add_argument("--setup", choices=SETUPS + ("both",), default="both",
                   help="A-D in their own reflectance ('glossy'), glazed, or both (default)")
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--samples", type=int, default=256, help="path-traced paths per observation")
    p.add_argument("--photons", type=int, default=500_000, help="Method III photons per light")
    p.add_argument("--iterations", type=int, default=50, help="Method III iterations (the paper's th_2)")
    p.add_argument("--render-photons", type=int, default=1_000_000, help="re-rendering photons per light")
    p.add_argument("--gather-rays", type=int, default=256,
                   help="re-rendering: first-bounce gather rays per observation (0: photon map only)")
    p.add_argument("--light-bin", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default=os.path.join(HERE, "RESULTS_table2.md"))
    p.add_argument("--json", default=None, help="also write the rows (per-iteration histories included) here")
    p.add_argument("--fig", default=os.path.join(HERE, "table2_fig25.png"))
    args = p.parse_args(argv)
    if args.quick:
        args.resolution, args.samples, args.photons, args.iterations, args.render_photons = 20, 16, 100_000, 10, 200_000
        args.gather_rays = min(args.gather_rays, 64)
    setups = SETUPS if args.setup == "both" else (args.setup,)
    names = args.objects.split(",")
    jobs = [(n, s) for s in setups for n in names if n != "E"] + [("E", "glossy") for n in names if n == "E"]
    load_before = tuple(round(x, 2) for x in os.getloadavg())
    t0 = time.perf_counter()
    rows = []
    for name, setup in jobs:
        print(f"Object {name} ({setup}) ...", flush=True)
        r = run_object(name, setup, args)
        pm = r["diff"].get("truth_pm", {}).get("relative_mean", float("nan"))
        print(f"  mean |d| / mean observed: II {r['diff']['II']['relative_mean']:.4f}, III "
              f"{r['diff']['III']['relative_mean']:.4f}, truth {r['diff']['truth']['relative_mean']:.4f} "
              f"(photon map only {pm:.4f}); ratio {r['ratio_mean']:.2f}; signed II {r['diff']['II']['signed_mean_relative']:+.4f}, "
              f"III {r['diff']['III']['signed_mean_relative']:+.4f}, ratio {r['ratio_signed']:.1f} "
              f"(>= {r['ratio_signed_low']:.1f}); renderer vs PT "
              f"{r['renderer_vs_pt']['relative_mean']:.4f}; PT noise {r['pt_noise']['relative_mean']:.4f}; seconds: "
              f"render {r['render_s']:.0f}, PT noise {r['pt_noise']['seconds']:.0f}, II {r['seconds']['II']:.0f}, "
              f"III {r['seconds']['III']:.0f}, re-render " + ", ".join(f"{v['seconds']:.0f}" for v in r['render'].values())
              + f"; load {os.getloadavg()}", flush=True)
        rows.append(r)
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(rows, fh, indent=1, default=float)
    wall = time.perf_counter() - t0
    load_after = tuple(round(x, 2) for x in os.getloadavg())
    fig25(rows, args.fig)
    text = report(rows, args, wall, load_before, load_after, args.fig)
    with open(args.out, "w") as fh:
        fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
