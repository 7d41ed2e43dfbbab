"""The same estimates on each JAX backend of this machine, side by side (CPU, and a GPU where
one is there).

    python3 -m benchmarks.backends [--points 30000] [--lights 12] [--methods local,photon]
                                   [--out benchmarks/RESULTS_backends.md] [--total-budget 600]

The scene, the methods and the timing are those of `benchmarks.scaling` (the bowl under distant
lights, direct light only, Method III with `scaling.PHOTON`'s reduced settings; each cell a fresh
process, `first` = the first `jaxrefl.estimate` call with compilation, `warm` = a later one), run
once per backend: the child sets `jax_platforms` to `cpu` or `cuda`. A GPU is looked for in a
separate process (`jax.devices('cuda')`), so this one never holds it. Each cell compiles cold
(`JAXREFL_CACHE=off`): the two backends compile different programs. The table gives both
backends' seconds, the CPU / GPU ratio of the warm calls, and the median relative pd error over
all points, which must agree between backends (float32 rounding apart). Cells run GPU first;
those that would start after `--total-budget` seconds are skipped and say so.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time

from benchmarks import scaling

#: `jax_platforms` names of the backends compared, in the order they run.
BACKENDS = ("cuda", "cpu")


def gpu_name() -> str | None:
    """The first CUDA device's name as JAX reports it, or None where JAX sees no GPU (asked in a
    child process, so that this one never initialises a GPU backend)."""
    code = "import jax; d = jax.devices('cuda'); print(d[0].device_kind)"
    try:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                              env=scaling._child_env())
    except subprocess.TimeoutExpired:
        return None
    return done.stdout.strip().splitlines()[-1] if done.returncode == 0 and done.stdout.strip() else None


def run(points: int, lights: int, methods, backends, budget: float, per_cell: float, scans: str,
        logs: str | None = None) -> tuple[list, float]:
    """One cell per (backend, method); returns the cells and the seconds spent building the scan."""
    path, built = scaling.ensure_scan(points, lights, scans)
    mem_limit = int(0.8 * scaling.mem_available()) or 16 * scaling.GIB
    t0, cells = time.perf_counter(), []
    for backend in backends:
        for method in methods:
            cell = {"backend": backend, "method": method, "points": points, "lights": lights}
            if time.perf_counter() - t0 > budget:
                cell["error"] = f"skipped: the run's {budget:.0f} s were spent"
            else:
                spec = {"scan": path, "method": method, "platform": backend}
                log = os.path.join(logs, f"{backend}_{method}.log") if logs else None
                report = scaling.run_child(spec, timeout=per_cell, mem_limit=mem_limit, log_path=log)
                report["jax_backend"] = report.pop("backend", None)  # JAX's name for it ("gpu")
                cell.update(report)
            print(json.dumps({k: v for k, v in cell.items() if not k.startswith(("stages", "substages"))}),
                  flush=True)
            cells.append(cell)
    return cells, built


def _s(cell, key):
    v = cell.get(key)
    return "" if v is None else f"{v:.3g}"


def table(cells: list, backends) -> list:
    """Markdown rows: one per method, each backend's first / warm seconds and pd error beside each other."""
    head = ["method", "points", "lights"]
    for b in backends:
        head += [f"{b}: first [s]", f"{b}: warm [s]", f"{b}: pd error (median rel.)"]
    if len(backends) == 2:
        head += [f"warm {backends[1]} / {backends[0]}"]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * 3 + "---:|" * (len(head) - 3)]
    for method in dict.fromkeys(c["method"] for c in cells):
        mine = {c["backend"]: c for c in cells if c["method"] == method}
        sized = [c for c in mine.values() if "points" in c]
        row = [scaling.LABELS[method], f"{sized[0]['points']:,}" if sized else "",
               str(sized[0]["lights"]) if sized else ""]
        notes = []
        for b in backends:
            c = mine.get(b, {})
            err = c.get("info", {}).get("pd_median_rel")
            row += [_s(c, "first"), _s(c, "warm"), "" if err is None else f"{100 * err:.2f} %"]
            if "error" in c:
                notes.append(f"{b}: {c['error']}")
        if len(backends) == 2:
            a, b = (mine.get(x, {}).get("warm") for x in backends)
            row.append(f"{b / a:.2f}x" if a and b else "")
        rows.append("| " + " | ".join(row) + " |" + (f" {'; '.join(notes)}" if notes else ""))
    return rows


def status_table(cells: list) -> list:
    """Markdown rows: each cell's point statuses (`est.status_counts()`), which must agree
    between backends as closely as the errors do."""
    names = ("MEASURED", "INTERPOLATED", "UNRESOLVED", "POOLED")
    rows = ["| method | backend | " + " | ".join(n.lower() for n in names) + " |", "|---|---|" + "---:|" * len(names)]
    for c in cells:
        counts = c.get("info", {}).get("status")
        if counts:
            rows.append(f"| {scaling.LABELS[c['method']]} | {c['backend']} | "
                        + " | ".join(str(counts.get(n, 0)) for n in names) + " |")
    return rows


def write(path: str, cells: list, backends, gpu: str | None, command: str, wall: float, built: float) -> None:
    import jax

    lines = ["# The same estimates on the CPU and on a GPU", "",
             f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: {os.cpu_count()} cores, "
             f"{platform.platform()}; Python {platform.python_version()}, jax {jax.__version__}; "
             f"GPU: {gpu or 'none seen by JAX'}.",
             f"- Run: `{command}`, {wall:.0f} s wall (scan built: {built:.0f} s of it).",
             "- Scene and methods as `benchmarks.scaling` (bowl, distant lights, direct light only; "
             f"`Photon(**{scaling.PHOTON})`); each cell a fresh process compiling cold; `first` includes "
             "compilation, `warm` is the fastest later call (form factors cast again). float32, the default.",
             "", *table(cells, backends), "", "Statuses of the points (the same scan on every backend):", "",
             *status_table(cells), ""]
    with open(path, "w") as fh:
        fh.write("\n".join(lines))
    with open(os.path.splitext(path)[0] + ".json", "w") as fh:
        json.dump({"gpu": gpu, "cells": cells}, fh, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=30_000)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--methods", default="local,photon", help="comma-separated subset of "
                    + ",".join(scaling.METHODS))
    ap.add_argument("--out", default="benchmarks/RESULTS_backends.md")
    ap.add_argument("--total-budget", type=float, default=600.0, help="no cell starts after this many seconds")
    ap.add_argument("--per-cell", type=float, default=300.0, help="kill a cell after this many seconds")
    ap.add_argument("--scans", default=scaling.SCAN_DIR, help="folder of the cached scans")
    ap.add_argument("--logs", default=None, help="folder for the children's stderr")
    args = ap.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    unknown = set(methods) - set(scaling.METHODS)
    if unknown:
        ap.error(f"unknown methods {sorted(unknown)}; choose from {scaling.METHODS}")
    if args.logs:
        os.makedirs(args.logs, exist_ok=True)
    t0 = time.perf_counter()
    gpu = gpu_name()
    backends = BACKENDS if gpu else ("cpu",)
    if not gpu:
        print("no GPU seen by JAX: CPU figures only", flush=True)
    cells, built = run(args.points, args.lights, methods, backends, args.total_budget, args.per_cell,
                       args.scans, args.logs)
    command = "python3 -m benchmarks.backends " + " ".join(argv if argv is not None else sys.argv[1:])
    write(args.out, cells, backends, gpu, command.strip(), time.perf_counter() - t0, built)
    print("\n".join(table(cells, backends)))


if __name__ == "__main__":
    main()
