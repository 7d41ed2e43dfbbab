"""Scaling: seconds and peak memory of every method against points and lights.

    python3 -m benchmarks.scaling [--quick] [--out benchmarks] [--budget 120] [--max-gib 16]

Two sweeps, each cell in a fresh Python process:

- points (about 10k, 30k, 100k, 300k, 1M) at 12 lights;
- lights (6, 12, 24, 48, 96) at 30k points;

for Method I (`jaxrefl.Local()`: the shared prior, the default), Method II
(`jaxrefl.Radiosity()`), Method III (`jaxrefl.Photon(...)` with fewer photons and
iterations than its defaults, `PHOTON`) and auto (`jaxrefl.Auto()`).

**Scene.** The zoo's hemispherical bowl seen from inside (`data_synth.zoo.bowl_object`:
every pair of its points sees each other, so Methods II and III have interreflection
to model everywhere), a smooth pd / ps / roughness field (Ward truth), the zoo's
distant-light photometric rig with M lights (`photometric_rig(n_lights=M)`: camera on
the axis, lights 10-75 deg off it, the rim shading the inside), 1 % noise, 12 bits,
**direct light only** (`zoo.render` with Embree shadows: cheap at 1M points). The
methods do all their work on a direct-only render; only their accuracy would differ.
A scan is built once per (points, lights) in its own process and cached under
`--scans` (default `/tmp/jaxrefl-scaling-scans`); its construction is never timed.

**Timing.** The child loads the scan, then calls `jaxrefl.estimate(scan, method)`
again and again: `first` (in a fresh process: compilation included) and `warm`
(compiled; the form-factor memory cache is cleared first, so Method II and auto cast
their rays again: warm is the whole estimate without compilation; the fastest of up
to `WARM_REPEATS` calls while they take under `WARM_SECONDS` together). Compilation takes 50-60 s of
every first call on two busy cores, whatever the size, so by default
(`--compile-cache shared`) each method's cells share one JAX persistent compilation
cache (a fresh folder per run): the method's first cell compiles cold ("cold
compile" in the table), the later ones load its programs from the cache as the
command line does after its first run, and compile only programs of new shapes.
`--compile-cache off` compiles cold in every cell (`JAXREFL_CACHE=off` in every child:
no form-factor files either). Stage seconds are `est.meta['seconds']` (every method fills
them), and sub-stages are timed by wrapping a few host-level library functions in the
child (`SUBSTAGES`; nested: a sub-stage's time is also in its stage). Precision:
the library's default (float32, as the command line; `--x64` for float64).

**Memory.** Peak RSS of the child over its whole life (`os.wait4`'s `ru_maxrss` of
that child: scan, JAX runtime and both calls), and its RSS after imports and after
loading the scan, so that the estimate's own share is visible.

**Skips.** Before a cell runs, the method's previous cells in the sweep are
extrapolated (`predict`): the first call as its compile time (first - warm of the
last cell compiled alike, held; a share `CACHED_SHARE` of a cold cell's before a cached
one is measured) plus the warm time scaled by `ratio ** p`, `p` the measured log-log
slope of the warm time between the last two sizes, never below 1; memory as baseline + scan share x ratio
+ the estimate's share x `ratio ** q` (`q` likewise, never below 1). A cell whose
predicted first call exceeds `--budget` seconds (the cell then takes about twice
that: the warm call follows) or whose predicted peak exceeds the memory limit
(`--max-gib`, at most 80 % of the memory available when the run starts) is skipped and
says so; so is every larger one. A watchdog kills a child whose RSS passes the limit
(or when the machine's available memory falls below 1 GiB), or that runs past
`--timeout-factor` times the budget, and the cell says so. `--resume RESULTS.json`
reuses the measured cells of an earlier run (with `--compile-cache-dir` its compile
cache) and runs only the others.

`--quick` runs a tiny grid (10k / 20k points, 6 / 12 lights, Methods I and II) for a test.
`--report RESULTS.json` only rewrites the markdown and the plot; `--fill-check` times
`window_fill` against points (the N^1.5 path the findings describe). Outputs: `RESULTS_scaling.md` (+ `.json`) and `scaling.png` under `--out`. A section of the
markdown written by hand (after `FINDINGS_MARK`) is kept when the file is rewritten.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time

import numpy as np

POINTS = (10_000, 30_000, 100_000, 300_000, 1_000_000)
LIGHTS = (6, 12, 24, 48, 96)
FIXED_POINTS, FIXED_LIGHTS = 30_000, 12
QUICK_POINTS, QUICK_LIGHTS, QUICK_FIXED_POINTS = (10_000, 20_000), (6, 12), 10_000
METHODS = ("local", "radiosity", "photon", "auto")
QUICK_METHODS = ("local", "radiosity")
LABELS = {"local": "Method I (Local(), prior)", "radiosity": "Method II (Radiosity())",
          "photon": "Method III (Photon(reduced))", "auto": "auto (Auto())"}
#: Method III's settings here (its defaults: 1M photons per light, 50 iterations, final gather 1024 rays
#: per observation halved until the scan's total fits 8M rays); the rest default.
PHOTON = {"photons": 100_000, "iterations": 5, "gather_budget": 2_000_000}
SCAN_DIR = "/tmp/jaxrefl-scaling-scans"
FINDINGS_MARK = "<!-- findings: written by hand; kept when `python3 -m benchmarks.scaling` rewrites this file -->"
RESULT_TAG = "SCALING_RESULT "
WARM_REPEATS, WARM_SECONDS = 3, 10.0  # warm calls: at most this many, fewer once this many seconds are spent
GIB = 1024**3

#: Host-level library functions timed inside the child: (module, attribute, label). Functions
#: return NumPy (they block on JAX), so their time is their work. Wrapped wherever a loaded
#: `jaxrefl` module holds them (names imported with `from x import y` included).
SUBSTAGES = (
    ("jaxrefl.scan.checks", "checked_scan", "checks"),
    ("jaxrefl.methods.local", "prepare_rows", "prepare_rows (classify)"),
    ("jaxrefl.methods.local", "fit_rows", "I: fit_rows (per-point fits)"),
    ("jaxrefl.methods.local", "_posterior_lobes", "I: shared prior (all)"),
    ("jaxrefl.reflectance.prior", "fit_materials", "I: prior: materials (EM, BIC)"),
    ("jaxrefl.reflectance.prior", "material_lobes", "I: prior: material lobes"),
    ("jaxrefl.reflectance.prior", "lobe_prior", "I: prior: lobe prior (k-d trees)"),
    ("jaxrefl.methods.local", "ChunkedRows.map_fit", "I: prior: posterior modes"),
    ("jaxrefl.methods.local", "_fill_from_gates", "I: gated fill (prior=False)"),
    ("jaxrefl.reflectance.pool", "pooled_specular", "I: pooled lobes (prior=False)"),
    ("jaxrefl.reflectance.fill", "vertex_adjacency", "vertex adjacency"),
    ("jaxrefl.reflectance.fill", "window_fill", "window fill"),
    ("jaxrefl.reflectance.fill", "window_reach", "window reach (sparse ring matrix)"),
    ("jaxrefl.methods.local", "estimate_local", "estimate_local (Method I, also inside II/III/auto)"),
    ("jaxrefl.geometry.formfactors", "form_factors", "form factors (cast)"),
    ("jaxrefl.methods.radiosity", "direct_irradiance", "II: direct irradiance"),
    ("jaxrefl.methods.radiosity", "inverse_radiosity", "II: inverse radiosity (all)"),
    ("jaxrefl.methods.radiosity", "_Sparse.__matmul__", "II: sparse products F @ B"),
    ("jaxrefl.methods.radiosity", "estimate_radiosity", "estimate_radiosity (Method II, also inside auto)"),
    ("jaxrefl.methods.photon", "PhotonReplay.build", "III: photon trace + replay build"),
    ("jaxrefl.methods.final_gather", "gather_rays", "III: final gather rays"),
    ("jaxrefl.reflectance.fill", "nearest_candidates", "III: nearest candidates (k-d tree)"),
    ("jaxrefl.methods.interreflection", "interreflection_ratios", "interreflection ratios (auto; Method I: its pd sd)"),
    ("jaxrefl.methods.auto", "plan", "auto: plan"),
)


# -- the scene ------------------------------------------------------------------------------


def scan_path(points: int, lights: int, folder: str = SCAN_DIR) -> str:
    return os.path.join(folder, f"bowl_n{points}_m{lights}.npz")


def build_scan(points: int, lights: int, seed: int = 0):
    """The bowl under `lights` distant lights, direct light only, 1 % noise, 12 bits
    (module docstring): a validated `jaxrefl.Scan`."""
    import jaxrefl
    from data_synth import zoo
    from data_synth.scans import Sensor, apply_sensor
    from jaxrefl.geometry.raycast import RayCaster
    from jaxrefl.scan.io import Scan, validate_scan

    obj = zoo.bowl_object(points)
    rig = zoo.photometric_rig(obj.center, obj.size, seed, n_lights=lights)
    rel = obj.vertices - obj.center
    dirs = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-12)
    _, materials, truth = zoo.MATERIALS["smooth"](dirs, "ward")
    caster = RayCaster(obj.vertices, obj.faces)
    valid = zoo.camera_valid(obj.vertices, obj.normals, rig.cam_pos, lights, caster)
    radiance, _ = zoo.render(obj.vertices, obj.normals, truth, rig.light_pos, rig.cam_pos, rig.intensity,
                             caster=caster)
    sensor = Sensor(noise=0.01, bits=12)
    observed, saturation = apply_sensor(np.where(valid[..., None], radiance, 0.0), valid, sensor,
                                        np.random.default_rng(np.random.SeedSequence([seed, 1])))
    del radiance
    meta = {"generator": "benchmarks.scaling", "jaxrefl_version": jaxrefl.__version__, "object": "bowl",
            "rig": rig.describe(), "rig_name": rig.name, "material": "smooth", "materials": materials,
            "model": "ward", "global_illumination": False, "sensor": {"noise": 0.01, "bits": 12}, "seed": seed}
    return validate_scan(Scan(
        vertices=obj.vertices, faces=obj.faces, normals=obj.normals, light_pos=rig.light_pos,
        light_intensity=rig.intensity, cam_pos=rig.cam_pos,
        radiance=np.where(valid[..., None], observed, 0.0).astype(np.float32), valid=valid,
        saturation=saturation, true_pd=truth.pd, true_ps=truth.ps, true_alpha=truth.roughness,
        true_normals=obj.normals, meta=meta))


def ensure_scan(points: int, lights: int, folder: str) -> tuple[str, float]:
    """The cached scan's path (built in a child process when missing) and the seconds spent building."""
    path = scan_path(points, lights, folder)
    if os.path.exists(path):
        return path, 0.0
    os.makedirs(folder, exist_ok=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "benchmarks.scaling", "--build", str(points), str(lights), path],
                   check=True, env=_child_env())
    return path, time.perf_counter() - t0


# -- the child: one measurement -------------------------------------------------------------


def _rss_bytes(pid="self") -> int:
    """Resident set size [bytes] of a process (Linux `/proc`), 0 when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _instrument(totals: dict) -> list:
    """Wrap the `SUBSTAGES` functions so that each call adds its seconds to `totals[label]`
    (`[calls, seconds]`). Returns what `_uninstrument` needs to put the originals back."""
    import functools
    import importlib

    undo = []
    for module_name, attr, label in SUBSTAGES:
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        owner, name = module, attr
        if "." in attr:
            cls, name = attr.split(".")
            owner = getattr(module, cls, None)
        raw = vars(owner).get(name) if owner is not None else None
        if raw is None:
            continue
        original = raw.__func__ if isinstance(raw, (classmethod, staticmethod)) else raw

        def wrapper(*args, __f=original, __label=label, **kwargs):
            t0 = time.perf_counter()
            try:
                return __f(*args, **kwargs)
            finally:
                entry = totals.setdefault(__label, [0, 0.0])
                entry[0] += 1
                entry[1] += time.perf_counter() - t0

        wrapped = functools.wraps(original)(wrapper)
        if owner is not module:  # a method: the class attribute serves every caller
            undo.append((owner, name, raw))
            setattr(owner, name, type(raw)(wrapped) if isinstance(raw, (classmethod, staticmethod)) else wrapped)
            continue
        for mod in list(sys.modules.values()):
            if getattr(mod, "__name__", "").startswith("jaxrefl") and vars(mod).get(name) is original:
                undo.append((mod, name, original))
                setattr(mod, name, wrapped)
    return undo


def _uninstrument(undo: list) -> None:
    for owner, name, raw in reversed(undo):
        setattr(owner, name, raw)


def method_spec(name: str, photon: dict | None = None):
    import jaxrefl

    if name == "local":
        return jaxrefl.Local()
    if name == "radiosity":
        return jaxrefl.Radiosity()
    if name == "photon":
        return jaxrefl.Photon(**(PHOTON if photon is None else photon))
    if name == "auto":
        return jaxrefl.Auto()
    raise ValueError(f"unknown method {name!r}")


def flatten_seconds(seconds: dict, prefix: str = "") -> dict:
    """`est.meta['seconds']` with nested dicts flattened to `outer/inner` keys."""
    out = {}
    for key, value in seconds.items():
        if isinstance(value, dict):
            out.update(flatten_seconds(value, f"{prefix}{key}/"))
        elif isinstance(value, (int, float)):
            out[f"{prefix}{key}"] = float(value)
    return out


def child(spec: dict) -> dict:
    """Load the scan, estimate twice (first, warm), report seconds, stages and memory."""
    import resource

    import jax

    if spec.get("x64"):
        jax.config.update("jax_enable_x64", True)
    if spec.get("platform"):  # "cpu" or "cuda": the backend this child runs JAX on
        jax.config.update("jax_platforms", spec["platform"])
    if spec.get("compile_cache"):  # JAX's persistent cache, shared by this method's cells
        jax.config.update("jax_compilation_cache_dir", spec["compile_cache"])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    import jaxrefl
    from jaxrefl.geometry import formfactors

    current = {"totals": {}}
    _instrument(_Proxy(current))
    rss_imports = _rss_bytes()
    t0 = time.perf_counter()
    scan = jaxrefl.load_scan(spec["scan"])
    load = time.perf_counter() - t0
    rss_loaded = _rss_bytes()
    method = method_spec(spec["method"], spec.get("photon"))
    out = {"load_seconds": load, "rss_imports": rss_imports, "rss_loaded": rss_loaded,
           "points": int(scan.n_points), "lights": int(scan.n_lights),
           "observations": int(np.asarray(scan.valid).sum()), "backend": jax.default_backend()}
    # first; then warm calls, repeated while they are quick (at most `WARM_REPEATS`, until
    # `WARM_SECONDS` are spent), the fastest kept: the machine is shared, and the least time is
    # the one least disturbed by others
    calls, warm_times = 0, []
    while True:
        which = "first" if calls == 0 else "warm"
        if which == "warm":
            formfactors._MEMORY.clear()  # cast the rays again: warm = everything but compilation
            if spec.get("first_only") or len(warm_times) >= WARM_REPEATS or sum(warm_times) >= WARM_SECONDS:
                break
        totals = {}
        current["totals"] = totals
        t0 = time.perf_counter()
        est = jaxrefl.estimate(scan, method=method)
        seconds = time.perf_counter() - t0
        calls += 1
        if which == "warm":
            warm_times.append(seconds)
            if seconds > min(warm_times):
                del est
                continue
        out[which] = seconds
        out[f"stages_{which}"] = flatten_seconds(est.meta.get("seconds", {}))
        out[f"substages_{which}"] = {k: {"calls": v[0], "seconds": v[1]} for k, v in totals.items()}
        out[f"rss_after_{which}"] = _rss_bytes()
        meta = est.meta
        info = {"status": {s.name: int(n) for s, n in est.status_counts().items()}}
        if scan.true_pd is not None:  # median relative pd error over all points (the truth is in the scan)
            rel = np.abs(np.asarray(est.pd) - scan.true_pd) / np.maximum(scan.true_pd, 1e-6)
            info["pd_median_rel"] = float(np.median(rel.mean(axis=1)))
        if "form_factors" in meta:
            info["form_factors"] = meta["form_factors"]
        if meta.get("method") == "auto":
            a = meta["auto"]
            info.update(choice=a["choice"], points_by_method=a["points_by_method"],
                        form_factors=a["form_factors"])
        if meta.get("method") == "photon":
            info.update({k: meta[k] for k in ("photons_per_configuration", "stored_photons",
                                               "gather_rays_per_observation", "gather_entries") if k in meta})
        if meta.get("method") == "radiosity":
            info["outer_iterations"] = [h["iterations"] for h in meta["outer_iterations"]]
        out["info"] = info
        del est
    out["warm_all"] = warm_times
    out["ru_maxrss_self"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return out


class _Proxy(dict):
    """A dict whose `setdefault` goes to `current['totals']`: the wrappers are installed once and
    count into the first or the warm call's totals."""

    def __init__(self, current):
        super().__init__()
        self.current = current

    def setdefault(self, key, default=None):
        return self.current["totals"].setdefault(key, default)


def _child_env() -> dict:
    env = dict(os.environ)
    env["JAXREFL_CACHE"] = "off"  # no persistent compile cache, no form-factor files: first = cold
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def mem_available() -> int:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def run_child(spec: dict, timeout: float, mem_limit: int, log_path: str | None = None,
              min_free: int = GIB) -> dict:
    """Run one measurement in a fresh process under a watchdog. Returns the child's report with
    `peak_rss` (its `ru_maxrss` from `os.wait4`) and `wall`, or `{'error': why, 'peak_rss': ...}`."""
    log = open(log_path, "w") if log_path else subprocess.DEVNULL
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "benchmarks.scaling", "--child", json.dumps(spec)],
                            stdout=subprocess.PIPE, stderr=log, env=_child_env(), text=True)
    killed, peak_seen = None, 0
    import threading

    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)  # not `poll`: it would reap the rusage
        if pid:
            break
        rss = _rss_bytes(proc.pid)
        peak_seen = max(peak_seen, rss)
        elapsed = time.perf_counter() - t0
        if rss > mem_limit:
            killed = f"out of memory: killed at {rss / GIB:.1f} GiB RSS (limit {mem_limit / GIB:.1f} GiB)"
        elif mem_available() and mem_available() < min_free:
            killed = (f"out of memory: killed at {rss / GIB:.1f} GiB RSS, the machine's available memory "
                      f"below {min_free / GIB:.0f} GiB")
        elif elapsed > timeout:
            killed = f"killed: > {timeout:.0f} s"
        if killed:
            proc.kill()
            _, status, usage = os.wait4(proc.pid, 0)
            break
        time.sleep(0.2)
    proc.returncode = os.waitstatus_to_exitcode(status)
    reader.join(timeout=5)
    wall = time.perf_counter() - t0
    if log_path:
        log.close()
    peak = max(usage.ru_maxrss * 1024, peak_seen)
    if killed:
        return {"error": killed, "peak_rss": peak, "wall": wall}
    report = next((json.loads(line[len(RESULT_TAG):]) for line in lines if line.startswith(RESULT_TAG)), None)
    if proc.returncode != 0 or report is None:
        tail = ""
        if log_path and os.path.exists(log_path):
            with open(log_path) as fh:
                tail = fh.read().strip().splitlines()[-1:] or [""]
            tail = tail[0][:200]
        why = "out of memory (killed by the system)" if proc.returncode in (-9, 137) else \
            f"failed (exit {proc.returncode}): {tail}"
        return {"error": why, "peak_rss": peak, "wall": wall}
    report.update(peak_rss=peak, wall=wall)
    return report


# -- extrapolation and skips ----------------------------------------------------------------


def fit_exponent(xs, ys) -> tuple[float, float]:
    """Least-squares slope and intercept of `log y` against `log x` (NaN with fewer than two
    distinct positive points): `y ~ exp(intercept) x ** slope`."""
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    ok = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    x, y = np.log(x[ok]), np.log(y[ok])
    if len(np.unique(x)) < 2:
        return float("nan"), float("nan")
    slope, intercept = np.polyfit(x, y, 1)
    return float(slope), float(intercept)


def _slope(history, key, floor=1.0):
    """Log-log slope of `key` between the last two cells of `history`, never below `floor`
    (1 without two usable cells)."""
    if len(history) < 2:
        return floor
    (x0, a), (x1, b) = ((h["x"], h[key]) for h in history[-2:])
    if not (a > 0 and b > 0 and x1 > x0):
        return floor
    return max(floor, math.log(b / a) / math.log(x1 / x0))


#: Share of a cold first call's extra seconds (first - warm) left when the programs come from
#: the compile cache, used until a cached cell of the method has been measured (Method I at
#: 10k points: 10 of 55 s).
CACHED_SHARE = 0.2


def predict(history: list, x: float, cold: bool = True) -> dict:
    """Seconds (first + warm) and peak RSS [bytes] of the next cell at size `x` from the
    method's measured cells `history` (each `{x, first, warm, peak_rss, rss_imports,
    rss_loaded, cold}`, in increasing `x`), as the module docstring describes; None without
    history. `cold`: the next cell compiles every program (else it loads them from the
    compile cache); its first call's extra seconds are those of the last cell compiled alike,
    else (`CACHED_SHARE`) a share of a cold one's."""
    if not history:
        return None
    last = history[-1]
    ratio = x / last["x"]
    work = [dict(h, work_rss=max(h["peak_rss"] - h["rss_loaded"], 1)) for h in history]
    p = _slope(work, "warm")
    q = _slope(work, "work_rss")
    alike = [h for h in history if bool(h.get("cold", True)) == cold]
    ref = alike[-1] if alike else last
    compile_s = max(ref["first"] - ref["warm"], 0.0) * (1.0 if alike else CACHED_SHARE)
    warm = last["warm"] * ratio**p
    scan_share = max(last["rss_loaded"] - last["rss_imports"], 0)
    rss = last["rss_imports"] + scan_share * ratio + work[-1]["work_rss"] * ratio**q
    return {"seconds": compile_s + 2.0 * warm, "first": compile_s + warm, "warm": warm, "peak_rss": rss,
            "p": p, "q": q}


def skip_reason(history: list, x: float, budget: float, mem_limit: int, cold: bool = True) -> str | None:
    """Why the cell at `x` is skipped (None: run it), from `predict`."""
    pred = predict(history, x, cold)
    if pred is None:
        return None
    if pred["peak_rss"] > mem_limit:
        return (f"skipped: predicted {pred['peak_rss'] / GIB:.1f} GiB > {mem_limit / GIB:.1f} GiB memory "
                f"limit")
    if pred["first"] > budget:
        return f"skipped: predicted {pred['first']:.0f} s (first call) > {budget:.0f} s budget"
    return None


# -- tables, markdown, plot -----------------------------------------------------------------


def _fmt_s(v):
    return "" if v is None else (f"{v:.2f}" if v < 10 else f"{v:.1f}" if v < 100 else f"{v:.0f}")


def table(cells: list, sweep: str) -> list:
    """Markdown table rows of one sweep's cells (measured and skipped)."""
    lines = ["| method | points | lights | first [s] | warm [s] | peak RSS [MiB] | RSS before estimate [MiB] "
             "| points/s (warm) | note |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for c in cells:
        if c["sweep"] != sweep:
            continue
        if "error" in c:
            rss = f"{c['peak_rss'] / 2**20:,.0f}" if c.get("peak_rss") else ""
            lines.append(f"| {LABELS[c['method']]} | {c['points']:,} | {c['lights']} | | | {rss} | | | "
                         f"{c['error']} |")
            continue
        note = "; ".join(filter(None, ["cold compile" if c.get("cold") and c.get("compile_cache") else "",
                                       c.get("note", "")]))
        lines.append(f"| {LABELS[c['method']]} | {c['points']:,} | {c['lights']} | {_fmt_s(c['first'])} | "
                     f"{_fmt_s(c.get('warm'))} | {c['peak_rss'] / 2**20:,.0f} | {c['rss_loaded'] / 2**20:,.0f} | "
                     f"{c['points'] / c['warm']:,.0f} | {note} |")
    return lines


def measured(cells, method, sweep):
    key = "points" if sweep == "points" else "lights"
    out = sorted((c for c in cells if c["method"] == method and c["sweep"] == sweep and "error" not in c),
                 key=lambda c: c[key])
    return out, key


def exponents(cells, methods) -> dict:
    """Per method and sweep: slope of log seconds (warm, first) and log peak RSS against log size,
    over all measured cells and between the two largest."""
    out = {}
    for m in methods:
        for sweep in ("points", "lights"):
            cs, key = measured(cells, m, sweep)
            xs = [c[key] for c in cs]
            entry = {"n": len(cs)}
            for q in ("warm", "first", "peak_rss"):
                entry[q] = fit_exponent(xs, [c[q] for c in cs])[0]
                entry[q + "_last"] = fit_exponent(xs[-2:], [c[q] for c in cs[-2:]])[0] if len(cs) >= 2 \
                    else float("nan")
            out[f"{m}/{sweep}"] = entry
    return out


def _e(v):
    return "" if not np.isfinite(v) else f"{v:.2f}"


def stage_growth(cells, method, sweep="points", which="warm") -> list:
    """Rows (stage, seconds at the smallest and the largest measured size, local exponent) of a
    method's stages and sub-stages between those two sizes."""
    cs, key = measured(cells, method, sweep)
    if len(cs) < 2:
        return []
    a, b = cs[0], cs[-1]
    rows = []
    for kind in ("stages", "substages"):
        sa, sb = a[f"{kind}_{which}"], b[f"{kind}_{which}"]
        for name in sb:
            va = sa.get(name)
            vb = sb[name]
            va = va["seconds"] if isinstance(va, dict) else va
            vb = vb["seconds"] if isinstance(vb, dict) else vb
            if va is None or name.endswith("total"):
                continue
            slope = fit_exponent([a[key], b[key]], [va, vb])[0] if va > 0 and vb > 0 else float("nan")
            rows.append((("" if kind == "stages" else "sub: ") + name, va, vb, slope))
    return rows


def write_markdown(path, cells, settings, methods) -> str:
    """Write the results markdown (keeping a hand-written findings section) and return its text."""
    ex = exponents(cells, methods)
    lines = [
        "# Scaling: seconds and peak memory against points and lights",
        "",
        f"- Date: {settings['date']}; machine: {settings['cores']} cores, {settings['platform']}; Python "
        f"{settings['python']}, jax {settings['jax']} on {settings['backend']}; precision "
        f"{'float64' if settings['x64'] else 'float32 (the default, as the command line)'}.",
        f"- Run: `{settings['command']}`, {settings['wall']:.0f} s wall (scans built: "
        f"{settings['build_seconds']:.0f} s of it"
        + (f"; cells measured by the earlier run it resumed took {settings['wall_before']:.0f} s more"
           if settings.get("wall_before") else "") + f"); load average at start {settings['load'][0]:.2f}, at end "
        f"{settings['load'][1]:.2f} (the 2 cores were shared with other jobs: seconds are pessimistic and vary "
        "up to ~2x between runs).",
        "- Scene: the zoo's hemispherical bowl seen from inside (every point sees every other), smooth "
        "pd / ps / roughness field, distant-light photometric rig (camera on the axis, M lights 10-75 deg off "
        "it; the rim shades about half the samples), 1 % noise, 12 bits, direct light only.",
        f"- Methods: `jaxrefl.Local()` (shared prior), `jaxrefl.Radiosity()` (256 rays per patch), "
        f"`jaxrefl.Photon({', '.join(f'{k}={v:_}' for k, v in settings['photon'].items())})` "
        "(reduced from 1M photons per light, 50 iterations and an 8M-ray final gather: 1024 rays per "
        "observation halved until the scan's total fits the budget), `jaxrefl.Auto()`; each cell in a fresh "
        "process: `first` = the first `jaxrefl.estimate` call, `warm` = a later call in the same process "
        f"(form factors cast again; the fastest of up to {WARM_REPEATS} while they take under "
        f"{WARM_SECONDS:.0f} s together). "
        + ("Compilation: each method's cells share one JAX persistent compile cache, so its first cell "
           "compiles cold (`cold compile`) and the others load the programs (compiling only new shapes), as "
           "the command line after its first run (`--compile-cache off`: cold in every cell)."
           if settings.get("compile_cache") == "shared" else "Every cell compiles cold.")
        + " Peak RSS: the child's `ru_maxrss` (scan, JAX runtime and both calls); `RSS before estimate`: "
        "after imports and loading the scan.",
        f"- Skips: per-cell budget {settings['budget']:.0f} s for the first call (extrapolated from the "
        f"method's previous sizes; the warm call follows), memory limit {settings['mem_limit'] / GIB:.1f} GiB (the smaller of "
        f"{settings['max_gib']:.0f} GiB and 80 % of the memory available at the start).",
        "",
        f"## Against points ({settings['fixed_lights']} lights)",
        "",
        *table(cells, "points"),
        "",
        f"## Against lights ({settings['fixed_points']:,} points requested)",
        "",
        *table(cells, "lights"),
        "",
        "## Fitted exponents",
        "",
        "Slope of log seconds (warm; first in brackets) and of log peak RSS against log points or log lights, "
        "least squares over the measured cells, and between the two largest measured cells (`last`: the "
        "asymptotic one, once fixed costs such as dispatch and compilation no longer dominate). 1 is linear.",
        "",
        "| method | points: all | points: last | RSS vs points: last | lights: all | lights: last |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for m in methods:
        p, li = ex[f"{m}/points"], ex[f"{m}/lights"]
        pair = lambda e, k: f"{_e(e[k])} ({_e(e[k.replace('warm', 'first')])})" if np.isfinite(e[k]) else ""  # noqa: E731
        lines.append(f"| {LABELS[m]} | {pair(p, 'warm')} | {pair(p, 'warm_last')} | {_e(p['peak_rss_last'])} "
                     f"| {pair(li, 'warm')} | {pair(li, 'warm_last')} |")
    lines += ["", "## Where the time goes: stages at the smallest and largest measured size", "",
              "`est.meta['seconds']` per stage of the warm call (nested stages as `outer/inner`) and, marked "
              "`sub:`, the library functions timed in the child (`benchmarks.scaling.SUBSTAGES`; a sub-stage's "
              "time is also in its stage). Exponent: log-log slope between the two sizes.", ""]
    for m in methods:
        for sweep in ("points", "lights"):
            rows = stage_growth(cells, m, sweep)
            if not rows:
                continue
            cs, key = measured(cells, m, sweep)
            lines += [f"### {LABELS[m]}, against {sweep}: {cs[0][key]:,} -> {cs[-1][key]:,}", "",
                      f"| stage | {cs[0][key]:,} [s] | {cs[-1][key]:,} [s] | exponent |", "|---|---:|---:|---:|"]
            lines += [f"| {name} | {va:.3f} | {vb:.3f} | {_e(s)} |" for name, va, vb, s in rows
                      if max(va, vb) >= 0.01]
            lines.append("")
    lines += ["Plot: `scaling.png` (log-log seconds against points and lights, peak RSS against points; dashed: "
              "slope 1).", ""]
    text = "\n".join(lines) + "\n"
    old = open(path).read() if os.path.exists(path) else ""
    _, mark, findings = old.partition(FINDINGS_MARK)
    if mark:
        text += "\n" + FINDINGS_MARK + findings
    with open(path, "w") as fh:
        fh.write(text)
    return text


def plot(path, cells, methods, fixed_points=None, fixed_lights=FIXED_LIGHTS):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    panels = ((axes[0], "points", "warm", "seconds (warm; dotted: first call)"),
              (axes[1], "lights", "warm", "seconds (warm; dotted: first call)"),
              (axes[2], "points", "peak_rss", "peak RSS [MiB]"))
    for ax, sweep, q, ylabel in panels:
        lo_hi = []
        for i, m in enumerate(methods):
            cs, key = measured(cells, m, sweep)
            if not cs:
                continue
            x = [c[key] for c in cs]
            y = [c[q] / (2**20 if q == "peak_rss" else 1) for c in cs]
            ax.plot(x, y, "o-", c=f"C{i}", label=LABELS[m])
            if q == "warm":
                ax.plot(x, [c["first"] for c in cs], ":", c=f"C{i}", lw=1)
            skipped = [c for c in cells if c["method"] == m and c["sweep"] == sweep and "error" in c]
            for c in skipped[:1]:
                ax.annotate("larger: skipped", (x[-1], y[-1]), textcoords="offset points", xytext=(4, -10), fontsize=7,
                            color=f"C{i}")
            lo_hi += list(zip(x, y))
        if lo_hi:
            xs = np.array([a for a, _ in lo_hi])
            ys = np.array([b for _, b in lo_hi])
            x0, x1 = xs.min(), xs.max()
            y0 = np.exp(np.mean(np.log(ys)))  # through the geometric middle of the data
            xm = np.exp(np.mean(np.log(xs)))
            ax.plot([x0, x1], [y0 * x0 / xm, y0 * x1 / xm], "k--", lw=1, label="slope 1 (linear)")
        ax.set(xscale="log", yscale="log", xlabel=sweep, ylabel=ylabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_title(f"seconds against points ({fixed_lights} lights)")
    axes[1].set_title("seconds against lights" + (f" ({fixed_points:,} points)" if fixed_points else ""))
    axes[2].set_title("peak memory against points")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fill_check(sizes=(10_000, 40_000, 160_000, 640_000)) -> list:
    """`jaxrefl.reflectance.fill.window_fill` on the bowl with a fixed cap (the lowest 10 % of
    its depth) unknown: seconds against points. Each diffusion sweep is a product with the
    whole adjacency (O(N)) and the sweeps reach across the cap one ring at a time (O(sqrt N)
    of them), so the fill grows like N^1.5 (`--fill-check`; a few seconds, no JAX)."""
    from data_synth import zoo
    from jaxrefl.reflectance.fill import vertex_adjacency, window_fill

    out = []
    for n in sizes:
        obj = zoo.bowl_object(n)
        z = obj.vertices[:, 2]
        known = z > z.min() + 0.1 * (z.max() - z.min())
        adj = vertex_adjacency(obj.faces, len(z))
        vals = np.random.default_rng(0).random((len(z), 2))
        t0 = time.perf_counter()
        window_fill(vals, known, adj, 5)
        out.append((len(z), int((~known).sum()), time.perf_counter() - t0))
        print(f"window_fill: {len(z):,} points, {out[-1][1]:,} unknown: {out[-1][2]:.3f} s", flush=True)
    for (n0, _, t0), (n1, _, t1) in zip(out[:-1], out[1:]):
        print(f"  exponent {n0:,} -> {n1:,}: {math.log(t1 / t0) / math.log(n1 / n0):.2f}")
    return out


# -- the driver -----------------------------------------------------------------------------


def grid(quick: bool, methods, points=None, lights=None, fixed_points=None, fixed_lights=FIXED_LIGHTS):
    """Cells in run order: the points sweep then the lights sweep, per method in increasing size;
    `(sweep, method, points, lights)`."""
    points = points or (QUICK_POINTS if quick else POINTS)
    lights = lights or (QUICK_LIGHTS if quick else LIGHTS)
    fixed_points = fixed_points or (QUICK_FIXED_POINTS if quick else FIXED_POINTS)
    out = [("points", m, n, fixed_lights) for m in methods for n in points]
    out += [("lights", m, fixed_points, k) for m in methods for k in lights]
    return out


def previous_cells(cells: list, todo: list) -> dict:
    """Measured cells of an earlier run keyed as `run_grid` looks them up, `(method, requested
    points, lights)`; a cell without `requested_points` is matched to the `todo` size nearest its
    actual point count (within 10 %)."""
    sizes = sorted({n for _, _, n, _ in todo})
    out = {}
    for c in cells:
        if "error" in c or "first" not in c:
            continue
        n = c.get("requested_points")
        if n is None:
            n = min(sizes, key=lambda s: abs(math.log(c["points"] / s)))
            if abs(c["points"] / n - 1) > 0.1:
                continue
        out[(c["method"], n, c["lights"])] = c
    return out


def run_grid(todo, measure, budget: float, mem_limit: int, total_budget: float = float("inf"),
             shared_cache: bool = True, start: float | None = None, clock=time.perf_counter, log=print,
             previous: dict | None = None) -> list:
    """Run the cells `todo` (`grid`) in order with `measure(method, points, lights, cold) -> report`
    (`run_child`'s; `{'error': why, ...}` when it failed), skipping as the module docstring says.
    A cell both sweeps hold is measured once. Returns every cell: the report with `sweep`,
    `method`, `points`, `lights`, `cold`, or `error` (why it was skipped or failed).
    `previous` (`previous_cells`): cells measured before, used instead of measuring again."""
    start = clock() if start is None else start
    cells, history, stopped, done = [], {}, {}, {}
    previous = previous or {}
    for sweep, method, n, m in todo:
        key = (sweep, method)
        hist = history.setdefault(key, [])
        x = n if sweep == "points" else m
        cell = {"sweep": sweep, "method": method, "points": n, "lights": m}
        if (method, n, m) in previous and (method, n, m) not in done:
            res = {k: v for k, v in previous[(method, n, m)].items() if k not in ("sweep", "note")}
            res = {**cell, **res, "requested_points": n}
            cells.append(res)
            done[(method, n, m)] = res
            hist.append(dict(res, x=x))
            log(f"{sweep} {method} n={res['points']} m={m}: measured before (--resume)")
            continue
        if (method, n, m) in done:
            prev = done[(method, n, m)]
            cells.append(dict(prev, sweep=sweep, note="same cell as the other sweep"))
            if "error" in prev:
                stopped[key] = prev["error"]
            else:
                hist.append(dict(prev, x=x))
            continue
        # the method's first measured cell compiles cold; with a shared cache the others load its programs
        cold = not shared_cache or not any(c["method"] == method and "error" not in c for c in cells)
        if key in stopped:
            reason = "skipped: a smaller size was skipped or failed"
        elif clock() - start > total_budget:
            reason = f"skipped: the run's {total_budget:.0f} s were spent"
        else:
            reason = skip_reason(hist, x, budget, mem_limit, cold)
        if reason:
            cells.append(dict(cell, error=reason))
            stopped[key] = reason
            log(f"{sweep} {method} n={n} m={m}: {reason}")
            continue
        res = measure(method, n, m, cold)
        res = {**cell, **res, "points": res.get("points", n), "lights": m, "cold": cold,
               "compile_cache": shared_cache, "requested_points": n}
        cells.append(res)
        done[(method, n, m)] = res
        if "error" in res:
            stopped[key] = res["error"]
        else:
            hist.append(dict(res, x=x))
        log(f"{sweep} {method} n={res['points']} m={m}: "
            + (res["error"] if "error" in res else
               f"first {res['first']:.1f} s, warm {res['warm']:.1f} s, peak {res['peak_rss'] / 2**20:.0f} MiB"))
    return cells


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny grid (10k/20k points, 6/12 lights, Methods I, II)")
    ap.add_argument("--out", default="benchmarks", help="folder for RESULTS_scaling.md/.json and scaling.png")
    ap.add_argument("--budget", type=float, default=120.0, help="per-cell seconds of the first call, extrapolated")
    ap.add_argument("--max-gib", type=float, default=16.0, help="memory limit per cell [GiB]")
    ap.add_argument("--timeout-factor", type=float, default=3.0, help="kill a cell after this x budget")
    ap.add_argument("--resume", default=None, help="results JSON of an earlier run: reuse its measured cells")
    ap.add_argument("--compile-cache-dir", default=None,
                    help="root of the shared compile caches (default: a fresh folder; with --resume, that run's)")
    ap.add_argument("--total-budget", type=float, default=2700.0,
                    help="seconds for the whole run; later cells are skipped once spent")
    ap.add_argument("--methods", default=None, help="comma-separated subset of " + ",".join(METHODS))
    ap.add_argument("--points", default=None, help="comma-separated point counts of the points sweep")
    ap.add_argument("--lights", default=None, help="comma-separated light counts of the lights sweep")
    ap.add_argument("--fixed-points", type=int, default=None, help="points of the lights sweep")
    ap.add_argument("--photons", type=int, default=PHOTON["photons"])
    ap.add_argument("--iterations", type=int, default=PHOTON["iterations"])
    ap.add_argument("--compile-cache", choices=("shared", "off"), default="shared",
                    help="shared: one JAX compile cache per method, so only its first cell compiles cold; "
                         "off: every cell compiles cold")
    ap.add_argument("--x64", action="store_true", help="float64 (default: float32, the library's default)")
    ap.add_argument("--scans", default=SCAN_DIR, help="folder of the cached scans")
    ap.add_argument("--logs", default="/tmp/jaxrefl-scaling-logs", help="folder of the children's stderr")
    ap.add_argument("--name", default="scaling", help="output names: RESULTS_<name>.md, <name>.png")
    ap.add_argument("--report", default=None, metavar="JSON",
                    help="only rewrite the markdown and the plot from this results JSON (no measurement)")
    ap.add_argument("--fill-check", action="store_true",
                    help="only time window_fill's diffusion against points (the N^1.5 path; seconds)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--build", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        print(RESULT_TAG + json.dumps(child(json.loads(args.child))), flush=True)
        return
    if args.build:
        import jaxrefl

        n, m, path = int(args.build[0]), int(args.build[1]), args.build[2]
        jaxrefl.save_scan(path, build_scan(n, m))
        return

    if args.fill_check:
        fill_check()
        return
    if args.report:
        with open(args.report) as fh:
            res = json.load(fh)
        methods = tuple(res["settings"]["methods"])
        md = os.path.join(args.out, f"RESULTS_{args.name}.md")
        print(write_markdown(md, res["cells"], res["settings"], methods))
        plot(os.path.join(args.out, f"{args.name}.png"), res["cells"], methods, res["settings"].get("fixed_points"),
             res["settings"].get("fixed_lights", FIXED_LIGHTS))
        return

    t_all = time.perf_counter()
    load0 = os.getloadavg()[0]
    methods = tuple(args.methods.split(",")) if args.methods else (QUICK_METHODS if args.quick else METHODS)
    photon = dict(PHOTON, photons=args.photons, iterations=args.iterations)
    mem_limit = int(min(args.max_gib * GIB, 0.8 * mem_available() or args.max_gib * GIB))
    ints = lambda s: tuple(int(float(v)) for v in s.split(",")) if s else None  # noqa: E731
    cells_todo = grid(args.quick, methods, ints(args.points), ints(args.lights), args.fixed_points)
    os.makedirs(args.out, exist_ok=True)
    os.makedirs(args.logs, exist_ok=True)
    cache_root = None
    if args.compile_cache == "shared":
        import tempfile

        cache_root = args.compile_cache_dir or tempfile.mkdtemp(prefix="jaxrefl-scaling-jaxcache-")
    build_seconds = [0.0]

    def measure(method, n, m, cold):
        path, built = ensure_scan(n, m, args.scans)
        build_seconds[0] += built
        spec = {"method": method, "scan": path, "x64": args.x64, "photon": photon,
                "compile_cache": None if cache_root is None else os.path.join(cache_root, method)}
        log = os.path.join(args.logs, f"{method}_n{n}_m{m}.log")
        return run_child(spec, args.budget * args.timeout_factor, mem_limit, log)

    previous, wall_before = {}, 0.0
    if args.resume:
        with open(args.resume) as fh:
            old = json.load(fh)
        previous = previous_cells(old["cells"], cells_todo)
        wall_before = float(old["settings"].get("wall", 0.0)) + float(old["settings"].get("wall_before", 0.0))
    cells = run_grid(cells_todo, measure, args.budget, mem_limit, args.total_budget,
                     shared_cache=cache_root is not None, start=t_all, previous=previous)
    build_seconds = build_seconds[0]

    import jax

    wall = time.perf_counter() - t_all
    settings = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "cores": os.cpu_count(),
                "platform": platform.platform(), "python": platform.python_version(), "jax": jax.__version__,
                "backend": next((c["backend"] for c in cells if "backend" in c), "cpu"), "x64": args.x64,
                "command": "python3 -m benchmarks.scaling" + (" --quick" if args.quick else "")
                + "".join(" " + a for a in (sys.argv[1:] if argv is None else argv) if a != "--quick"),
                "wall": wall, "wall_before": wall_before, "resumed_from": args.resume,
                "compile_cache_dir": cache_root, "build_seconds": build_seconds, "load": [load0, os.getloadavg()[0]],
                "photon": photon, "budget": args.budget, "max_gib": args.max_gib, "mem_limit": mem_limit,
                "fixed_lights": FIXED_LIGHTS, "compile_cache": args.compile_cache,
                "fixed_points": args.fixed_points or (QUICK_FIXED_POINTS if args.quick else FIXED_POINTS),
                "methods": list(methods)}
    md = os.path.join(args.out, f"RESULTS_{args.name}.md")
    text = write_markdown(md, cells, settings, methods)
    with open(os.path.splitext(md)[0] + ".json", "w") as fh:
        json.dump({"settings": settings, "cells": cells, "exponents": exponents(cells, methods)}, fh, indent=1,
                  default=float)
    plot(os.path.join(args.out, f"{args.name}.png"), cells, methods, settings["fixed_points"], FIXED_LIGHTS)
    print(text)


if __name__ == "__main__":
    main()
