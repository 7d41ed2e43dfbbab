"""Speed against error: every method on Objects A-E, error against seconds (Pareto fronts).

    python3 -m benchmarks.pareto [--quick] [--repeats R] [--out benchmarks/RESULTS.md]

Writes `RESULTS.md` (what was run, on what, how it was timed; one table per scene
and its Pareto fronts), `pareto.png` (error against warm seconds, log axes, one
marker per method and setting, Pareto front drawn) and `RESULTS.json` (raw
numbers) beside `--out`.

Scenes (built by the other benchmarks' scene builders, not copies of them):
Objects A-D on the paper's scanner under their greedily selected lights, path-traced
global illumination, 1 % noise, 12 bits (`auto_bench.make_scene`); Object E, glossy
and diffuse paper, on the fixed camera tilted 25 deg (`inverse_photon_bench._scan`).
The truth is Ward everywhere (Method III fits Ward); Method I with Torrance-Sparrow is
then a model mismatch, which its ps error shows.

Settings: Method I (Torrance-Sparrow and Ward) under all selected lights and under the
first half of the greedy selection; Method II; Method III over photons per light,
iterations and solver; `--method auto` at its default target error.

Timing: per setting a first call (compilation included) is reported separately, then
the median of `--repeats` warm calls. Every call builds its own Embree scene and casts
form factors afresh (caches cleared), as `jaxrefl estimate` does on a new scan.
Errors against the truth: median relative pd error (mean over RGB) over all points,
median relative ps error over points whose true ps > 0, and on E the mean relative pd
error of measured points within 2 cm of the fold (`inverse_photon_bench._errors`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import tempfile
import textwrap
import time
import warnings

import numpy as np

from benchmarks.auto_bench import Scene, _fresh_caches, _rel_errors, make_scene
from benchmarks.inverse_photon_bench import _errors as fold_errors
from benchmarks.inverse_photon_bench import _scan as e_scan

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = ("A", "B", "C", "D", "E glossy", "E diffuse")
QUICK_SCENES = ("A", "E glossy")
METRICS = {"pd": "median rel. pd error", "ps": "median rel. ps error (true ps > 0)",
           "fold": "mean rel. pd error within 2 cm of the fold"}


@dataclasses.dataclass(frozen=True)
class Setting:
    """One point of the sweep: `method` 'local', 'radiosity', 'photon' or 'auto'; `model`
    Method I's BRDF; `half` use only the first half of the greedy light selection;
    Method III's `photons` per light, `iterations` and `solver`; `objects` the scene
    labels it runs on (None: all)."""

    method: str
    model: str = "ward"
    half: bool = False
    photons: int = 200_000
    iterations: int = 10
    solver: str = "lm"
    objects: tuple | None = None

    @property
    def label(self) -> str:
        lights = " half" if self.half else ""
        if self.method == "local":
            return f"I {'TS' if self.model == 'torrance-sparrow' else 'Ward'}{lights}"
        if self.method == "radiosity":
            return f"II{lights}"
        if self.method == "photon":
            p = f"{self.photons // 1000}k" if self.photons < 1_000_000 else f"{self.photons / 1e6:g}M"
            return f"III {p}/{self.iterations}{' simplex' if self.solver == 'simplex' else ''}{lights}"
        return f"auto{lights}"


def settings(quick: bool) -> list[Setting]:
    """The sweep (quick: fewer settings). The photon count, iteration and solver sweep of
    Method III runs in full on A and glossy E only (budget: ~25 min on 2 cores)."""
    if quick:
        return [Setting("local", "ward"), Setting("local", "ward", half=True),
                Setting("radiosity"), Setting("photon", photons=50_000, iterations=10),
                Setting("photon", photons=200_000, iterations=10, solver="simplex"), Setting("auto")]
    sweep = ("A", "E glossy")
    return [Setting("local", "torrance-sparrow"), Setting("local", "ward"), Setting("local", "ward", half=True),
            Setting("radiosity"),
            Setting("photon", photons=50_000, iterations=10), Setting("photon", photons=200_000, iterations=10),
            Setting("photon", photons=1_000_000, iterations=10, objects=sweep),
            Setting("photon", photons=200_000, iterations=50, objects=sweep),
            Setting("photon", photons=200_000, iterations=10, solver="simplex", objects=sweep),
            Setting("auto")]


def subset_lights(scan, keep):
    """The scan with only the observations of lights `keep` (indices, in order)."""
    keep = np.asarray(keep, dtype=np.int64)
    m = scan.n_lights

    def take(a):
        a = np.asarray(a)
        if a.ndim >= 2 and a.shape[-2] == m and not (a.ndim == 3 and a.shape[1] == 1 and m != 1):
            return np.take(a, keep, axis=-2)
        return a

    li = scan.light_intensity
    li = li if np.ndim(li) == 0 else np.asarray(li)[keep]
    return dataclasses.replace(scan, light_pos=take(scan.light_pos), cam_pos=take(scan.cam_pos),
                               light_intensity=li, radiance=np.take(scan.radiance, keep, axis=1),
                               valid=None if scan.valid is None else np.take(scan.valid, keep, axis=1))


def pareto_front(seconds, errors) -> np.ndarray:
    """`(K,)` bool: points not dominated (another point at most as slow and at most as
    wrong, strictly better in one). Points with a non-finite coordinate are never on it."""
    t, e = np.asarray(seconds, dtype=float), np.asarray(errors, dtype=float)
    ok = np.isfinite(t) & np.isfinite(e)
    le = (t[None, :] <= t[:, None]) & (e[None, :] <= e[:, None])
    lt = (t[None, :] < t[:, None]) | (e[None, :] < e[:, None])
    dominated = (le & lt & ok[None, :]).any(axis=1)
    return ok & ~dominated


# -- scenes -------------------------------------------------------------------------------------


def build_scene(label: str, cfg) -> dict:
    """Scan and description of scene `label` ('A'-'D', 'E glossy', 'E diffuse')."""
    t0 = time.perf_counter()
    if label.startswith("E"):
        from data_synth.objects import fold_coordinate, make_object

        setup = label.split()[1]
        scan, lights, rep = e_scan(setup, cfg.resolution_e, cfg.samples_e)
        fold = fold_coordinate(make_object("E", cfg.resolution_e, setup).vertices)
        h = float(np.min(np.abs(fold[np.abs(fold) > 1e-9])))
        desc = (f"Object E, {setup} paper, pinhole camera tilted 25 deg, resolution {cfg.resolution_e}, "
                f"{cfg.samples_e} paths per observation, 1 % noise, 12 bits (full scale 8), seed 0")
        extra = {"fold": fold, "h": h, "mc_stderr": rep["mc_relative_stderr_median"]}
    else:
        scan, lights = make_scene(Scene(label, label), cfg.resolution, cfg.samples, seed=cfg.seed)
        desc = (f"Object {label}, scanner, resolution {cfg.resolution}, {cfg.samples} paths per observation, "
                f"1 % noise, 12 bits (full scale at the 99.9th percentile), seed {cfg.seed}")
        extra = {}
    return {"label": label, "scan": scan, "lights": [int(i) for i in lights], "describe": desc,
            "render_s": time.perf_counter() - t0, **extra}


def _runner(s: Setting, scan):
    from jaxrefl.methods import auto
    from jaxrefl.methods.local import LocalOptions, estimate_local
    from jaxrefl.methods.radiosity import RadiosityOptions, estimate_radiosity

    local = LocalOptions(model=s.model)
    if s.method == "local":
        return lambda c: estimate_local(scan, local, c)
    if s.method == "radiosity":
        return lambda c: estimate_radiosity(scan, RadiosityOptions(local=local), c)
    if s.method == "photon":
        from jaxrefl.methods.inverse_photon import PhotonOptions, estimate_photon

        opts = PhotonOptions(photons=s.photons, iterations=s.iterations, solver=s.solver, local=local)
        return lambda c: estimate_photon(scan, opts, c)
    ok, _ = auto.photon_available("ward")
    methods = auto.METHODS if ok else tuple(k for k in auto.METHODS if k != "photon")
    opts = auto.AutoOptions(local=local, methods=methods,
                            photon={"photons": s.photons, "iterations": s.iterations, "solver": s.solver})
    return lambda c: auto.estimate_auto(scan, opts, c)


def measure(scene: dict, s: Setting, repeats: int, tmp: str) -> dict:
    """First call and `repeats` warm calls of setting `s` on `scene`: seconds and errors."""
    from jaxrefl.geometry.raycast import RayCaster

    scan = scene["scan"]
    if s.half:
        scan = subset_lights(scan, np.arange((scan.n_lights + 1) // 2))
    run = _runner(s, scan)
    times = []
    for _ in range(1 + repeats):
        _fresh_caches(tmp)
        t = time.perf_counter()
        est = run(RayCaster(scan.vertices, scan.faces))
        times.append(time.perf_counter() - t)
    pd, ps = _rel_errors(est, scene["scan"])
    err = {"pd": float(np.median(pd)), "ps": float(np.nanmedian(ps)) if np.isfinite(ps).any() else None}
    if "fold" in scene:
        with warnings.catch_warnings():  # no measured point beside the fold on a coarse mesh: NaN -> None
            warnings.simplefilter("ignore", RuntimeWarning)
            err["fold"] = fold_errors(est, scene["scan"], scene["fold"], scene["h"])["near"]
    err = {k: v if v is not None and math.isfinite(v) else None for k, v in err.items()}
    out = {"label": s.label, "setting": dataclasses.asdict(s), "lights": scan.n_lights, "first_s": times[0],
           "warm_s": times[1:], "seconds": float(np.median(times[1:])), "errors": err}
    if s.method == "auto":
        a = est.meta["auto"]
        out["auto"] = {"choice": a["choice"], "points_by_method": a["points_by_method"]}
    return out


def _source() -> str:
    """Commit of the code that ran, and files changed against it (if any)."""
    import subprocess

    def git(*a):
        return subprocess.run(["git", *a], cwd=os.path.dirname(HERE), capture_output=True, text=True,
                              timeout=30).stdout

    try:
        commit = git("rev-parse", "--short", "HEAD").strip()
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", "jaxrefl", "data_synth", "benchmarks")
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    changed = [line[3:] for line in dirty.splitlines()]
    return (commit or "unknown") + (f" with uncommitted changes to {', '.join(changed)}" if changed else " (clean)")


def run_bench(scene_labels, sweep, cfg, log=print) -> dict:
    """Every setting of `sweep` on every scene of `scene_labels`; returns the raw results
    (Pareto fronts marked) for `write_outputs`."""
    t0, cpu0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()
    started, source = time.strftime("%Y-%m-%dT%H:%M:%S"), _source()
    scenes = []
    with tempfile.TemporaryDirectory() as tmp:
        for label in scene_labels:
            sc = build_scene(label, cfg)
            log(f"{label}: {sc['scan'].n_points} points, lights {sc['lights']}, render {sc['render_s']:.1f} s")
            rows = []
            for s in sweep:
                if s.objects is not None and label not in s.objects:
                    continue
                r = measure(sc, s, cfg.repeats, tmp)
                rows.append(r)
                log(f"  {label} {r['label']}: first {r['first_s']:.2f} s, warm {r['seconds']:.2f} s, "
                    f"errors {json.dumps({k: None if v is None else round(v, 4) for k, v in r['errors'].items()})}"
                    f"  (load {os.getloadavg()[0]:.1f})")
            for m in METRICS:
                e = [np.nan if r["errors"].get(m) is None else r["errors"][m] for r in rows]
                if np.isfinite(e).any():
                    for r, on in zip(rows, pareto_front([r["seconds"] for r in rows], e)):
                        r.setdefault("front", {})[m] = bool(on)
            scenes.append({"scene": label, "points": sc["scan"].n_points, "lights": sc["lights"],
                           "describe": sc["describe"], "render_s": sc["render_s"],
                           "mc_stderr": sc.get("mc_stderr"), "rows": rows})
    return {"command": cfg.command, "date": started, "source": source,
            "machine": f"{os.cpu_count()} cores, {platform.platform()}, Python {platform.python_version()}",
            "load_start": list(load0), "load_end": list(os.getloadavg()), "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - cpu0,
            "repeats": cfg.repeats, "scenes": scenes}


# -- outputs ------------------------------------------------------------------------------------


def _pct(x):
    return "-" if x is None or not math.isfinite(x) else f"{100 * x:.2f}%"


def markdown(res) -> str:
    import jax

    lines = ["# Speed against error: every method on Objects A-E", "",
             f"- Run: `{res['command']}`, started {res['date']}, {res['wall_s']:.0f} s wall"
             + (f", {res['cpu_s']:.0f} s CPU of this process" if "cpu_s" in res else "")
             + f" (scene rendering included); code: commit {res.get('source', 'unknown')}; machine: {res['machine']}, "
             f"jax {jax.__version__}.",
             f"- Load average (1/5/15 min) at start {'/'.join(f'{x:.2f}' for x in res['load_start'])}, at end "
             f"{'/'.join(f'{x:.2f}' for x in res['load_end'])}: the 2 cores are shared with other jobs, so seconds "
             "are noisy (up to ~2x) and pessimistic; compare settings within one scene.",
             f"- Timing: per setting one first call (compilation included, column `first s`), then the median of "
             f"{res['repeats']} warm call(s) (`warm s`, the x axis of the plot and of the Pareto fronts). Every call "
             "builds its own Embree scene and casts form factors afresh (caches cleared). Scene rendering is not "
             "timed here. Compiled code lives for the whole process: a setting whose array shapes match an "
             "earlier one's starts "
             "compiled (`auto` after Methods I-III; E diffuse after E glossy, same mesh and lights), so its `first s` "
             "can be close to its `warm s`.",
             "- Errors against the truth: `pd` median relative pd error (mean over RGB) over all points; `ps` median "
             "relative ps error over points whose true ps > 0; `fold` (Object E) mean relative pd error of measured "
             "points within 2 cm of the fold, the fold line itself left out.",
             "- Truth: Ward (Method III fits Ward); `I TS` fits Torrance-Sparrow to it: a model mismatch, and "
             "its ps is "
             "a differently normalised lobe height, so its ps error measures the mismatch, not the fit. "
             "`half`: only the first half of the greedy light selection (the lights chosen first). Method II: "
             "256 form-factor rays per patch, exact first bounce. Method III: `III <photons per light>/<iterations>`, "
             "LM unless `simplex`. `auto`: `--method auto` at its default target error (0.05), Ward, candidates "
             "I-III, Method III at 200k photons / 10 iterations (`III 200k/10`; the CLI's default is 1M / 50).",
             "- Front: `pd` / `ps` / `fold` mark the settings on that metric's Pareto front (no other setting both "
             "at most as slow and at most as wrong).", ""]
    for sc in res["scenes"]:
        has_fold = any("fold" in r["errors"] for r in sc["rows"])
        lines += [f"## {sc['scene']}: {sc['points']} points, {len(sc['lights'])} lights {sc['lights']}", "",
                  f"{sc['describe']}; render {sc['render_s']:.0f} s"
                  + (f", path tracer median rel. std. error {sc['mc_stderr']:.1%}" if sc.get("mc_stderr") else "")
                  + ".", "",
                  "| setting | lights | pd error | ps error |" + (" fold pd error |" if has_fold else "")
                  + " first s | warm s | front |",
                  "|---|---:|---:|---:|" + ("---:|" if has_fold else "") + "---:|---:|---|"]
        for r in sc["rows"]:
            e = r["errors"]
            front = ", ".join(m for m, on in r.get("front", {}).items() if on) or "-"
            label = r["label"] + (f" ({r['auto']['choice']})" if "auto" in r else "")
            lines.append(f"| {label} | {r['lights']} | {_pct(e['pd'])} | {_pct(e['ps'])} |"
                         + (f" {_pct(e.get('fold'))} |" if has_fold else "")
                         + f" {r['first_s']:.2f} | {r['seconds']:.2f} | {front} |")
        lines.append("")
        best = min((r for r in sc["rows"] if r["errors"]["pd"] is not None), key=lambda r: r["errors"]["pd"])
        near = min((r for r in sc["rows"] if r["errors"]["pd"] is not None
                    and r["errors"]["pd"] <= 1.1 * best["errors"]["pd"]), key=lambda r: r["seconds"])
        lines.append(f"- Lowest pd error: {best['label']} ({_pct(best['errors']['pd'])}, {best['seconds']:.2f} s); "
                     f"fastest within 10 % of it: {near['label']} ({_pct(near['errors']['pd'])}, "
                     f"{near['seconds']:.2f} s, {near['seconds'] / best['seconds']:.2g}x the time).")
        for m in METRICS:
            on = [r for r in sc["rows"] if r.get("front", {}).get(m)]
            if on:
                on.sort(key=lambda r: r["seconds"])
                lines.append(f"- Pareto front, {METRICS[m]}: " + " -> ".join(
                    f"{r['label']} ({r['seconds']:.2f} s, {_pct(r['errors'][m])})" for r in on))
        lines.append("")
    lines += ["Plot: `pareto.png` (one column per scene, rows pd / ps / fold error; log axes; the line is the "
              "Pareto front). Raw numbers: `RESULTS.json`.", ""]
    return "\n".join(lines)


_COLOURS = {"local": "tab:blue", "radiosity": "tab:green", "photon": "tab:red", "auto": "black"}


def plot(res, path: str) -> None:
    """Error against warm seconds, one panel per scene and metric, log axes, fronts drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = res["scenes"]
    metrics = [m for m in METRICS if any(r["errors"].get(m) is not None for sc in scenes for r in sc["rows"])]
    fig, axes = plt.subplots(len(metrics), len(scenes), figsize=(4.2 * len(scenes), 3.6 * len(metrics)),
                             squeeze=False)
    for j, sc in enumerate(scenes):
        for i, m in enumerate(metrics):
            ax = axes[i, j]
            rows = [r for r in sc["rows"] if r["errors"].get(m) is not None and np.isfinite(r["errors"][m])
                    and r["errors"][m] > 0]
            if not rows:
                ax.set_axis_off()
                continue
            for k, r in enumerate(sorted(rows, key=lambda r: r["seconds"])):
                s = r["setting"]
                ax.scatter(r["seconds"], r["errors"][m], c=_COLOURS[s["method"]],
                           marker="s" if s["half"] else ("^" if s["solver"] == "simplex" else "o"),
                           s=36, zorder=3, edgecolors="k" if r.get("front", {}).get(m) else "none")
                ax.annotate(r["label"], (r["seconds"], r["errors"][m]), fontsize=6.5,
                            xytext=(3, 3 if k % 2 == 0 else -9),
                            textcoords="offset points")
            on = sorted((r for r in rows if r.get("front", {}).get(m)), key=lambda r: r["seconds"])
            if on:
                ax.step([r["seconds"] for r in on], [r["errors"][m] for r in on], where="post", c="0.4", lw=1,
                        zorder=2)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.grid(True, which="both", lw=0.3, alpha=0.5)
            ax.set_title(f"{sc['scene']} ({sc['points']} points, {len(sc['lights'])} lights)", fontsize=9)
            if j == 0 or not axes[i, j - 1].axison:
                ax.set_ylabel(METRICS[m], fontsize=8)
            if i == len(metrics) - 1 or (i + 1 < len(metrics) and not any(
                    r["errors"].get(metrics[i + 1]) is not None for r in sc["rows"])):
                ax.set_xlabel(f"warm seconds (median of {res['repeats']})", fontsize=8)
    title = (f"Error against warm seconds: `{res['command']}`, {res['date']}, load {res['load_start'][0]:.1f} -> "
             f"{res['load_end'][0]:.1f} on {os.cpu_count()} cores. Blue: Method I, green: II, red: III, black: auto; "
             "square: half the lights, triangle: simplex; outlined and joined: the Pareto front.")
    fig.suptitle("\n".join(textwrap.wrap(title, int(13 * 4.2 * len(scenes)))), fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.1 / len(metrics)))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(res, out_md: str) -> dict:
    """RESULTS.md at `out_md`, pareto.png and RESULTS.json beside it; returns the paths."""
    folder = os.path.dirname(os.path.abspath(out_md))
    os.makedirs(folder, exist_ok=True)
    paths = {"md": out_md, "png": os.path.join(folder, "pareto.png"),
             "json": os.path.join(folder, os.path.splitext(os.path.basename(out_md))[0] + ".json")}
    with open(paths["md"], "w") as fh:
        fh.write(markdown(res))
    plot(res, paths["png"])
    with open(paths["json"], "w") as fh:
        json.dump(res, fh, indent=1, allow_nan=False)
    return paths


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="two scenes, fewer settings, smaller meshes, one repeat")
    p.add_argument("--repeats", type=int, default=None, help="warm calls per setting (default 3; quick 1)")
    p.add_argument("--out", default=os.path.join(HERE, "RESULTS.md"))
    p.add_argument("--scenes", default=None, help="comma list of scene labels (default: all, quick: A, E glossy)")
    p.add_argument("--resolution", type=int, default=None, help="mesh resolution of A-D (default 32, quick 20)")
    p.add_argument("--resolution-e", type=int, default=None, help="mesh resolution of E (default 32, quick 24)")
    p.add_argument("--samples", type=int, default=None, help="paths per observation, A-D (default 16, quick 8)")
    p.add_argument("--samples-e", type=int, default=None, help="paths per observation, E (default 256, quick 64)")
    p.add_argument("--seed", type=int, default=1, help="render and noise seed of A-D")
    p.add_argument("--from-json", default=None, help="rewrite the outputs from a RESULTS.json instead of running")
    args = p.parse_args(argv)
    q = args.quick
    args.repeats = args.repeats if args.repeats is not None else (1 if q else 3)
    if args.repeats < 1:
        p.error("--repeats: must be >= 1")
    args.resolution = args.resolution or (20 if q else 32)
    args.resolution_e = args.resolution_e or (24 if q else 32)
    args.samples = args.samples or (8 if q else 16)
    args.samples_e = args.samples_e or (64 if q else 256)
    args.command = "python3 -m benchmarks.pareto" + "".join(f" {a}" for a in (sys.argv[1:] if argv is None else argv))
    labels = args.scenes.split(",") if args.scenes else list(QUICK_SCENES if q else SCENES)
    if args.from_json:
        with open(args.from_json) as fh:
            res = json.load(fh)
    else:
        res = run_bench(labels, settings(q), args, log=lambda s: print(s, flush=True))
    paths = write_outputs(res, args.out)
    print(markdown(res))
    print("wrote", ", ".join(paths.values()))


if __name__ == "__main__":
    main()
