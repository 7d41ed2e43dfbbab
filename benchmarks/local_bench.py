"""Benchmark: Method I's per-point fits, 100k points x 12 lights.

Run: `python -m benchmarks.local_bench [--points 100000] [--subset 1000]`.

Rows with random Torrance-Sparrow reflectance and geometry (5 samples inside
the specular lobe, 7 outside it) and 1 % relative noise are fitted three ways
in one run:

- jaxrefl `fit_rows` with its fixed-step Levenberg-Marquardt (vmap in one jit),
  on all points;
- the same with optimistix's LevenbergMarquardt (vmapped, `throw=False`);
- a per-point `scipy.optimize.least_squares(method='lm')` loop on the same
  residual (same weights, same starting point from jaxrefl's closed form),
  timed on `--subset` points and scaled to all.

Reported: points per second, seconds (median of repeats; the first call, which
compiles, separately), the ratio to the scipy loop, and median relative errors
of pd, ps and sigma on the subset, so speed is compared at equal error.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def scipy_fit(rows, start, weights):
    """Per-point scipy least squares on the weighted Torrance-Sparrow residual."""
    from scipy.optimize import least_squares

    out = np.empty_like(start)
    for i in range(len(start)):  # the baseline is a Python loop by design
        y, e, ci, co, th, use = (rows[k][i][rows["use"][i]] for k in ("y", "e", "cos_i", "cos_o", "theta_r",
                                                                        "use"))
        wi = weights[i][rows["use"][i]]

        def residual(p):
            pd, ps, sigma = np.exp(p[:3]), np.exp(p[3]), np.exp(p[4])
            spec = ps * np.exp(-(th**2) / (2 * sigma**2)) / (ci * co)
            pred = e[:, None] * (pd[None] / np.pi + spec[:, None])
            return ((y - pred) * wi).ravel()

        out[i] = least_squares(residual, start[i], method="lm").x
    return out


def main(argv=None):
    from jaxrefl.local import LocalOptions, _grid_init, fit_rows
    from tests.test_local import synthetic_rows

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--subset", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/RESULTS_local.md")
    args = parser.parse_args(argv)

    rng = np.random.default_rng(0)
    rows, pd, ps, sigma = synthetic_rows(rng, args.points, 12, "torrance-sparrow")
    rows["y"] = rows["y"] * (1 + 0.01 * rng.standard_normal(rows["y"].shape))
    truth = np.c_[pd, ps, sigma]
    sub = np.arange(args.subset)
    sub_rows = {k: v[sub] for k, v in rows.items()}

    def rel_err(values, idx):
        err = np.abs(values - truth[idx]) / truth[idx]
        return np.median(err[:, :3]), np.median(err[:, 3]), np.median(err[:, 4])

    results = []
    for solver in ("lm", "optimistix"):
        data = rows if solver == "lm" else sub_rows
        n = len(data["use"])
        options = LocalOptions(solver=solver)
        t0 = time.perf_counter()
        fit = fit_rows(data, options)
        first = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fit = fit_rows(data, options)
            times.append(time.perf_counter() - t0)
        t = float(np.median(times))
        results.append((f"jaxrefl fit_rows, {'fixed-step LM' if solver == 'lm' else 'optimistix LM'}", n, t, first,
                        rel_err(np.c_[fit["pd"], fit["ps"], fit["roughness"]][: args.subset], sub)))

    # scipy baseline from the same start (jaxrefl's closed form + grid, before polishing).
    import jax.numpy as jnp

    from jaxrefl.local import _diffuse_init, _noise_weights, _specular_init

    j = {k: jnp.asarray(v) for k, v in sub_rows.items()}
    w = _noise_weights(j["y"], j["use"], 0.0)
    pd0, _ = _diffuse_init(j["y"], j["e"], j["use"], j["classes"], j["theta_r"], False)
    ln_ps0, ln_s0, ok, _ = _specular_init("torrance-sparrow", j, pd0, False)
    pd_g, ln_ps_g, ln_s_g = _grid_init("torrance-sparrow", j, w)
    ok = np.asarray(ok)
    start = np.where(ok[:, None], np.c_[np.log(np.maximum(pd0, 1e-3)), ln_ps0, ln_s0],
                     np.c_[np.log(np.maximum(pd_g, 1e-3)), ln_ps_g, ln_s_g])
    t0 = time.perf_counter()
    sp = scipy_fit(sub_rows, start, np.asarray(w))
    t_sub = time.perf_counter() - t0
    t_scaled = t_sub * args.points / args.subset
    results.append(("scipy least_squares(method='lm') loop (scaled)", args.points, t_scaled, None,
                    rel_err(np.exp(sp), sub)))

    lines = [
        "# Method I per-point fits: 12 lights a point",
        "",
        f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: {os.cpu_count()} cores, "
        f"{platform.platform()}; float64",
        f"- {args.points:,} rows, random Torrance-Sparrow reflectance and geometry, 1 % noise; errors are "
        f"medians on the first {args.subset} rows (the optimistix run and the scipy loop use only those; "
        f"the scipy time is scaled x{args.points // args.subset}).",
        f"- Timings: median of {args.repeats} runs after the first (compiling) call, shown apart.",
        "",
        "| solver | rows | seconds | first call [s] | points/s | speed vs scipy | pd err | ps err | sigma err |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, n, t, first, (e_pd, e_ps, e_s) in results:
        per_second = n / t
        ratio = per_second / (args.points / t_scaled)
        lines.append(f"| {name} | {n:,} | {t:.2f} | {'' if first is None else f'{first:.1f}'} | "
                     f"{per_second:,.0f} | {ratio:.0f}x | {e_pd:.4f} | {e_ps:.4f} | {e_s:.4f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    with open(args.out, "w") as fh:
        fh.write(text)


if __name__ == "__main__":
    main()
