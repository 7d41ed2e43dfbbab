"""`jaxrefl demo`: the main job on the built-in synthetic default.

Writes into one folder: synthetic scan bundles (Object A under the paper's
scanner and all 60 candidate lights, direct lighting, 1 % noise, 12-bit
sensor; Object E, diffuse set-up, with global illumination), pictures of
their ground truth and observations, the light selection for Object A (§2.2,
Figure 8 analogue), Method I on Object A captured under those lights (result
file, estimated maps, status map with one colour per status, errors against
truth; the reflectance-map figure, a PLY export, and a relit picture under a
new light beside the truth),
the error of that estimate relit under the candidate lights the capture did not
use against their images (held-out lights, `jaxrefl.outputs.holdout`), the path
tracer's furnace test and convergence study, and `summary.json` with every
number and timing.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

__all__ = ["run_demo"]


def _plot_fold(path, fold, direct, gi, mc_stderr):
    from ..outputs.render import new_figure

    bins = np.linspace(fold.min(), fold.max(), 41)
    centres = 0.5 * (bins[1:] + bins[:-1])
    which = np.clip(np.digitize(fold, bins) - 1, 0, len(centres) - 1)
    ratio = gi / np.maximum(direct, 1e-12)
    row_mean = np.array([ratio[which == k].mean() if np.any(which == k) else np.nan
                         for k in range(len(centres))])
    fig = new_figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.plot(fold * 100, ratio, ".", ms=2, alpha=0.3, color="0.6", label="vertices")
    ax.plot(centres * 100, row_mean, "-", color="C0", label="mean across the plate")
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("position across the fold [cm] (plate II < 0 < plate I)")
    ax.set_ylabel("radiance with GI / direct only")
    ax.set_title(f"Object E, white paper: interreflection (MC rel. std. err. {mc_stderr:.1%})",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _plot_convergence(path, conv):
    from ..outputs.render import new_figure

    s = np.array(conv["samples"], dtype=float)
    e = np.array(conv["rms_relative_error"])
    fig = new_figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.loglog(s, e, "o-", label=f"path tracer (slope {conv['slope']:.2f})")
    ax.loglog(s, e[0] * np.sqrt(s[0] / s), "k--", lw=0.8, label="samples$^{-1/2}$")
    ax.set_xlabel("paths per observation")
    ax.set_ylabel("RMS relative error vs reference")
    ax.set_title(f"Convergence (reference: {conv['reference_samples']} paths)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _relight_against_truth(scan, estimate, out_path, name) -> dict:
    """Relit picture of `estimate` under a light not used in the fit, beside the truth under
    the same light (side by side and difference); returns the image errors."""
    from ..geometry.raycast import RayCaster
    from ..outputs import relight as rl
    from ..outputs import render

    centre = 0.5 * (scan.vertices.min(0) + scan.vertices.max(0))
    light = centre + np.array([-0.35, 0.45, 0.4])
    camera = rl.fit_camera(scan.vertices, centre + np.array([0.2, 0.1, 0.6]), width=480, height=480)
    caster = RayCaster(scan.vertices, scan.faces)
    images = [rl.picture(caster, scan.faces, rl.relight(scan.vertices, scan.faces, scan.normals, e, light, 1.0,
                                                        camera.center, caster=caster), camera)
              for e in (estimate, rl.truth_estimate(scan))]
    finite = np.isfinite(images[1]).all(axis=-1)
    exposure = 1.0 / float(np.percentile(images[1][finite], 99.5))
    render.save_png(out_path(f"{name}_relit.png"), render.to_srgb8(images[0], exposure=exposure))
    render.comparison_figure(out_path(f"{name}_relit_vs_truth.png"), *images, labels=("relit estimate", "truth"),
                             title=f"Object {name}: new light at {np.round(light, 3).tolist()} m, direct light")
    return {"light": light.tolist(), "camera": camera.center.tolist(), **rl.image_errors(*images)}


def run_demo(out: str, resolution: int = 48, samples: int = 64, seed: int = 0,
             progress: bool = False) -> dict:
    """Run the demo into folder `out`; returns (and writes) the summary dict."""
    from data_synth.objects import fold_coordinate
    from data_synth.pathtrace import Material, PathTracer
    from data_synth.scans import Sensor, make_scan
    from data_synth.validation import convergence, furnace

    from .. import __version__
    from ..capture.select import plot_coverage, select_lights
    from ..geometry.raycast import RayCaster
    from ..methods.local import MEASURED, POOLED, STATUS_NAMES, estimate_local
    from ..outputs import render
    from ..outputs.export import export_ply
    from ..outputs.holdout import evaluate_holdout, split_scan
    from ..reflectance.classify import classify_scan
    from ..result import save_result, truth_errors
    from ..scan.io import atomic_write, save_scan

    os.makedirs(out, exist_ok=True)
    t_start = time.perf_counter()
    files, seconds = [], {}

    def out_path(name):
        files.append(name)
        return os.path.join(out, name)

    # 1. Object A, paper's scanner, all 60 candidate lights, direct only, noisy 12-bit sensor.
    t = time.perf_counter()
    scan_a, report_a = make_scan("A", resolution=resolution, sensor=Sensor(noise=0.01, bits=12),
                                 seed=seed, progress=progress)
    save_scan(out_path("scan_A.npz"), scan_a)
    brightest = int(np.argmax(scan_a.radiance.sum(axis=(0, 2))))
    for what, name in (("pd", "A_true_pd.png"), ("ps", "A_true_ps.png"),
                       ("roughness", "A_true_roughness.png"), ("observations", "A_observations.png")):
        render.save_png(out_path(name), render.scan_picture(scan_a, what))
    render.save_png(out_path("A_radiance.png"), render.scan_picture(scan_a, "radiance", light=brightest))
    seconds["object_A"] = time.perf_counter() - t

    # Light selection (§2.2) on Object A's geometry: which of the 60 candidates to capture with.
    t = time.perf_counter()
    measurability = classify_scan(scan_a, use_observations=False)
    selection = select_lights(measurability.diffuse_only, measurability.strong_specular, measurability.seen)
    plot_coverage(selection, out_path("A_light_selection.png"), title="Object A: light selection")
    seconds["light_selection_A"] = time.perf_counter() - t

    # Method I (§3) on Object A captured under the selected lights only.
    t = time.perf_counter()
    captured, _ = make_scan("A", resolution=resolution, lights=selection.selected,
                            sensor=Sensor(noise=0.01, bits=12), seed=seed)
    estimate = estimate_local(captured)
    save_result(out_path("A_result_local.npz"), estimate)
    errors_a = truth_errors(estimate, captured)
    hits, shape = render.cylindrical_hits(RayCaster(captured.vertices, captured.faces), width=512)
    render.save_png(out_path("A_estimated_pd.png"),
                    render.to_srgb8(render.shade(hits, captured.faces, estimate.pd, shape), exposure=1.0))
    render.save_png(out_path("A_estimated_ps.png"),
                    render.colormap(render.shade(hits, captured.faces, estimate.ps, shape), "magma"))
    render.save_png(out_path("A_estimated_sigma.png"),
                    render.colormap(render.shade(hits, captured.faces, estimate.roughness, shape), "gray"))
    render.status_figure(out_path("A_status.png"), hits, shape, captured.faces, estimate.status,
                         title="Object A, Method I: status")
    seconds["method_I_A"] = time.perf_counter() - t

    # Held-out lights: the estimate relit under the candidate lights the capture did not use,
    # against what the camera recorded there, and the ground truth's error (the noise floor).
    t = time.perf_counter()
    unused = np.setdiff1d(np.arange(scan_a.n_lights), selection.selected)
    _, held_out = split_scan(scan_a, unused)
    holdout_a = evaluate_holdout(estimate, held_out)
    seconds["holdout_A"] = time.perf_counter() - t

    # Relighting: Method I's estimate of Object A under a fixed light the scanner never
    # used (its rack rides the head), against the truth; the paper's Figure 10 maps; a PLY export.
    t = time.perf_counter()
    relit_a = _relight_against_truth(captured, estimate, out_path, "A")
    render.reflectance_figure(out_path("A_reflectance_maps.png"), hits, shape, captured.faces, estimate,
                              title="Object A, Method I: estimated reflectance (Figure 10 analogue)")
    export_ply(out_path("A_result_local.ply"), captured.vertices, captured.faces, captured.normals, estimate)
    seconds["relight_A"] = time.perf_counter() - t

    # 2. Object E, white paper, pinhole camera, 6 lights around it: direct vs global illumination.
    t = time.perf_counter()
    lights = [23, 26, 33, 36, 4, 55]
    scan_e, report_e = make_scan("E", resolution=resolution, setup="diffuse", lights=lights,
                                 global_illumination=True, samples=samples, seed=seed, progress=progress)
    direct_e, _ = make_scan("E", resolution=resolution, setup="diffuse", lights=lights, seed=seed)
    save_scan(out_path("scan_E_diffuse_gi.npz"), scan_e)
    render.save_png(out_path("E_gi.png"), render.scan_picture(scan_e, "radiance", light=0))
    render.save_png(out_path("E_direct.png"), render.scan_picture(direct_e, "radiance", light=0))
    fold = fold_coordinate(scan_e.vertices)
    gi_lum = scan_e.radiance[:, 0].mean(axis=1)
    direct_lum = direct_e.radiance[:, 0].mean(axis=1)
    near = np.abs(fold) < 0.02
    far = np.abs(fold) > 0.15
    boost = gi_lum / np.maximum(direct_lum, 1e-12)
    seconds["object_E_gi"] = time.perf_counter() - t

    # 3. Path tracer checks: furnace (closed form) and convergence on the glossy fold.
    t = time.perf_counter()
    furnaces = [furnace(rho, samples=256, seed=seed) for rho in (0.5, 0.8)]
    glossy, _ = make_scan("E", resolution=resolution, setup="glossy", lights=[23], seed=seed)
    material = Material(glossy.true_pd, glossy.true_ps, glossy.true_sigma)
    tracer = PathTracer(glossy.vertices, glossy.faces, glossy.normals, material)
    pick = np.flatnonzero(np.abs(fold_coordinate(glossy.vertices)) < 0.03)[::4]
    cam = glossy.camera_positions()[pick]
    light = glossy.light_positions()[pick]
    conv = convergence(tracer, pick, np.ascontiguousarray(cam), np.ascontiguousarray(light),
                       glossy.intensities(), reference_samples=4096, seed=seed)
    seconds["path_tracer_checks"] = time.perf_counter() - t

    _plot_fold(out_path("E_fold_interreflection.png"), fold, direct_lum, gi_lum,
               report_e["mc_relative_stderr_median"])
    _plot_convergence(out_path("path_tracer_convergence.png"), conv)
    seconds["total"] = time.perf_counter() - t_start

    summary = {
        "out": out,
        "jaxrefl_version": __version__,
        "object_A": {**{k: report_a[k] for k in ("points", "faces", "lights", "valid_fraction")},
                     "sensor": {"noise": 0.01, "bits": 12}},
        "light_selection_A": {k: v for k, v in selection.to_json().items() if k != "curve"},
        "method_I_A": {
            "lights": len(selection.selected),
            "measured_share_of_observed": float(np.sum(estimate.pd_measured & (estimate.status == MEASURED))
                                                / max(estimate.pd_measured.sum(), 1)),
            "known_share_of_observed": float(np.sum(estimate.pd_measured
                                                    & np.isin(estimate.status, (MEASURED, POOLED)))
                                             / max(estimate.pd_measured.sum(), 1)),
            "status_counts": {name: int(np.sum(estimate.status == code)) for code, name in enumerate(STATUS_NAMES)},
            "materials": estimate.meta.get("materials"),
            "errors": errors_a,
        },
        "holdout_A": holdout_a,
        "relight_A": relit_a,
        "object_E_diffuse": {
            **{k: report_e[k] for k in ("points", "lights", "samples", "mc_relative_stderr_median")},
            "gi_over_direct_within_2cm_of_fold": float(np.mean(boost[near])),
            "gi_over_direct_beyond_15cm": float(np.mean(boost[far])),
        },
        "furnace": furnaces,
        "convergence": conv,
        "seconds": seconds,
        "files": files + ["summary.json"],
    }
    atomic_write(os.path.join(out, "summary.json"),
                 lambda fh: fh.write(json.dumps(summary, indent=2).encode()))
    return summary
