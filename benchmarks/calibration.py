"""Do the reported standard deviations cover the errors? Table 2's scenes, every observed point.

    python3 -m benchmarks.calibration [--methods local,photon] [--setups glossy,glazed]
                                      [--out benchmarks/RESULTS_calibration.md]

Scenes: Objects A-D as `benchmarks.table2_bench` renders them (`auto_bench.make_scene`: the
paper's scanner, the greedy selection's lights, full global illumination by the independent
path tracer, 1 % noise, 12 bits, Ward), in their own reflectance and glazed. Methods: Method I
(`Local(model='ward')`, float32 as the command line) and, with `photon` in `--methods`, Method
III (`Photon(photons=500_000, iterations=50)`, Table 2's setting).

For pd (each channel), ps and roughness (in ln roughness: `|ln(est / truth)|` over
`std_roughness / roughness`), over the observed points with a finite standard deviation, per
status and in all: the share more than 3 sd from the truth (0.3 % for calibrated Gaussian
errors), the share within 1 sd (68 %) and the median `|error| / sd` (0.67; above 1:
overconfident). An estimate whose errors are many sd wide without saying so is a silent wrong
answer; one whose sd is wide is honest, however poor.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time

import numpy as np

STATUSES = ("measured", "pooled", "interpolated")


def z_scores(est, scan) -> dict:
    """`{quantity: (N, c) |error| / sd}` for pd (3 channels), ps and ln roughness (1 column);
    NaN where the sd is not finite and positive or the truth is missing."""
    def ratio(err, sd):
        ok = np.isfinite(sd) & (sd > 0) & np.isfinite(err)
        return np.where(ok, np.abs(err) / np.where(ok, sd, 1.0), np.nan)

    with np.errstate(divide="ignore", invalid="ignore"):
        rough = ratio(np.log(est.roughness / scan.true_alpha), est.std_roughness / est.roughness)
    return {"pd": ratio(est.pd - scan.true_pd, est.std_pd),
            "ps": ratio(est.ps - scan.true_ps, est.std_ps)[:, None],
            "roughness": rough[:, None]}


def summarise(z: np.ndarray, where: np.ndarray) -> dict | None:
    """Shares beyond 3 sd and within 1 sd, median, of the finite `z` `(N, c)` at rows `where`."""
    v = z[where]
    v = v[np.isfinite(v)]
    if not len(v):
        return None
    return {"n": int(len(v)), "beyond_3": float(np.mean(v > 3)), "within_1": float(np.mean(v <= 1)),
            "median": float(np.median(v))}


def calibration(est, scan) -> dict:
    """`{quantity: {status or 'all': summarise(...)}}` over the observed points."""
    from jaxrefl.status import Status

    observed = scan.observed().any(1)
    out = {}
    for quantity, z in z_scores(est, scan).items():
        rows = {"all": summarise(z, observed)}
        for name in STATUSES:
            rows[name] = summarise(z, observed & (est.status == Status[name.upper()]))
        out[quantity] = {k: v for k, v in rows.items() if v is not None}
    return out


def run(objects, setups, methods, resolution=32, samples=256, seed=1) -> list:
    from benchmarks.auto_bench import Scene, make_scene
    from jaxrefl.methods.inverse_photon import PhotonOptions, estimate_photon
    from jaxrefl.methods.local import LocalOptions, estimate_local

    local = LocalOptions(model="ward")
    rows = []
    for setup in setups:
        for name in objects:
            scene = Scene(name if setup == "glossy" else f"{name} {setup}", name, setup)
            t0 = time.perf_counter()
            scan, _ = make_scene(scene, resolution, samples, seed=seed)
            render = time.perf_counter() - t0
            for method in methods:
                t0 = time.perf_counter()
                if method == "local":
                    est = estimate_local(scan, local)
                else:
                    est = estimate_photon(scan, PhotonOptions(photons=500_000, iterations=50, local=local))
                row = {"object": scene.label, "method": method, "points": int(scan.n_points),
                       "observed": int(scan.observed().any(1).sum()), "render_s": render,
                       "seconds": time.perf_counter() - t0, "calibration": calibration(est, scan),
                       "widened": est.meta.get("points_with_widened_prior")}
                print(json.dumps({k: row[k] for k in ("object", "method", "seconds")}), flush=True)
                rows.append(row)
    return rows


def _cell(entry) -> str:
    if not entry:
        return ""
    return f"{100 * entry['beyond_3']:.1f} % / {100 * entry['within_1']:.0f} % (z {entry['median']:.2f})"


def table(rows) -> list:
    lines = ["| object | method | observed | quantity | all | measured | pooled | interpolated |",
             "|---|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        for quantity, by in r["calibration"].items():
            lines.append(f"| {r['object']} | {r['method']} | {r['observed']} | {quantity} | "
                         + " | ".join(_cell(by.get(k)) for k in ("all",) + STATUSES) + " |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="A,B,C,D")
    ap.add_argument("--setups", default="glossy,glazed")
    ap.add_argument("--methods", default="local", help="comma-separated: local, photon")
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="benchmarks/RESULTS_calibration.md")
    args = ap.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    if set(methods) - {"local", "photon"}:
        ap.error("--methods: local, photon")
    t0 = time.perf_counter()
    rows = run(args.objects.split(","), args.setups.split(","), methods, args.resolution, args.samples, args.seed)
    import jax

    lines = ["# Calibration: do the standard deviations cover the errors?", "",
             f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: {os.cpu_count()} cores, "
             f"{platform.platform()}; Python {platform.python_version()}, jax {jax.__version__} "
             f"({'float64' if jax.config.jax_enable_x64 else 'float32'}).",
             f"- Run: `python3 -m benchmarks.calibration {' '.join(sys.argv[1:] if argv is None else argv)}`, "
             f"{time.perf_counter() - t0:.0f} s.",
             f"- Scenes: Table 2's (resolution {args.resolution}, {args.samples} paths, seed {args.seed}); every "
             "observed point with a finite sd. Cells: share beyond 3 sd / share within 1 sd (median |error| / sd); "
             "calibrated Gaussian errors: 0.3 % / 68 % (z 0.67). Roughness in ln roughness.", "",
             *table(rows), "",
             "Points whose lobe prior was widened to cover the measured lobes around them "
             "(`meta['points_with_widened_prior']`): "
             + ", ".join(f"{r['object']} {r['method']} {r['widened']}" for r in rows) + ".", ""]
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines))
    with open(os.path.splitext(args.out)[0] + ".json", "w") as fh:
        json.dump(rows, fh, indent=1)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
