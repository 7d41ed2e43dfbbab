"""Benchmark: Method II's form factors and inverse-radiosity fixed point.

Run: `python -m benchmarks.radiosity_bench [--resolution 98] [--rays 64 256]`.

1. Form factors of Object A at about 21k vertex patches (resolution 98): `formfactors.form_factors`
   (ray generation, threaded Embree casts, sparse assembly), against raw embreex
   `run` (one thread, first hits only) on the very same rays, in the same run.
   Reported: rays per second of both and their ratio, seconds, non-zeros and
   bytes of the sparse matrix (and what a dense float64 matrix would take).
2. The inverse-radiosity fixed point (`radiosity.inverse_radiosity`) on that
   object rendered direct-only under the paper's scanner and 16 of its lights:
   light configurations, iterations and seconds (first, compiling, call apart).

Writes `benchmarks/RESULTS_radiosity.md`.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time

import numpy as np


def _median_time(fn, repeats):
    times = []
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main(argv=None):
    import jax

    jax.config.update("jax_enable_x64", True)
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from data_synth.objects import make_object
    from data_synth.scans import make_scan
    from jaxrefl.geometry import formfactors as ffm
    from jaxrefl.geometry.raycast import RayCaster
    from jaxrefl.methods.local import prepare_rows
    from jaxrefl.methods.radiosity import (
        direct_irradiance,
        first_bounce_correction,
        inverse_radiosity,
        light_configs,
    )
    from jaxrefl.reflectance.classify import T_DIFF

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=98)
    parser.add_argument("--rays", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--light-bins", type=float, nargs="+", default=[0.2],
                        help="light bins [m] for the fixed point (0.1, the estimator's default, takes minutes)")
    parser.add_argument("--out", default="benchmarks/RESULTS_radiosity.md")
    args = parser.parse_args(argv)

    obj = make_object("A", resolution=args.resolution)
    v, f, n = obj.vertices, obj.faces, obj.normals
    caster = RayCaster(v, f)
    lines = [f"# Method II: form factors and inverse radiosity (Object A, {len(v):,} patches)", "",
             f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: "
             f"{platform.machine()}, {__import__('os').cpu_count()} cores; {caster.threads} tracing threads",
             "- Timings: median of repeats; the raw baseline is embreex `run` (one thread, "
             "INTERSECT) on the same float32 rays, without ray generation or assembly.", "",
             "| rays/patch | rays | jaxrefl s | jaxrefl Mrays/s | raw embreex s | raw Mrays/s | ratio | nnz | "
             "sparse MB | dense MB |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    scene = rtcore_scene.EmbreeScene(robust=True)
    TriangleMesh(scene, v.astype(np.float32), f.astype(np.int32))
    for rays in args.rays:
        seconds, ff = _median_time(lambda: ffm.form_factors(v, f, n, rays=rays, caster=caster, cache=False),
                                   args.repeats)
        # the very same rays, rebuilt outside the timing, for the raw baseline
        rng = np.random.default_rng(0)
        patches = np.arange(len(v))
        u = (ffm.hammersley(rays)[None] + rng.random((len(v), 1, 2))) % 1.0
        dirs = ffm.cosine_directions(n, u).reshape(-1, 3)
        origins = caster.offset_origins(np.repeat(v, rays, 0), np.repeat(caster.offset_normals, rays, 0), dirs)
        o32, d32 = origins.astype(np.float32), dirs.astype(np.float32)
        raw, _ = _median_time(lambda: scene.run(o32, d32), args.repeats)
        total = len(patches) * rays
        lines.append(f"| {rays} | {total:,} | {seconds:.2f} | {total / seconds / 1e6:.1f} | {raw:.2f} | "
                     f"{total / raw / 1e6:.1f} | {raw / seconds:.2f}x | {len(ff.values):,} | "
                     f"{ff.nbytes / 1e6:.1f} | {len(v) ** 2 * 8 / 1e6:,.0f} |")
        print(lines[-1], flush=True)

    # 2. the fixed point on a direct-only scan under the scanner (per-point lights)
    lights = [0, 4, 9, 14, 19, 24, 29, 33, 36, 40, 44, 49, 50, 54, 57, 59]
    scan, _ = make_scan("A", resolution=args.resolution, lights=lights)
    rows = prepare_rows(scan, caster=caster)
    ff = ffm.form_factors(v, f, n, rays=args.rays[0], caster=caster, cache=False)
    use = rows["use"]
    diffuse = use & (rows["classes"] == T_DIFF)
    sample = np.where(diffuse.any(1)[:, None], diffuse, use)
    pd0 = np.full((len(v), 3), 0.5)
    lines += ["", f"Inverse radiosity fixed point ({args.rays[0]} rays/patch, {len(lights)} lights, scanner):", "",
              "| light bin [m] | configurations | direct + first-bounce set-up s | first call s | "
              "fixed point s | iterations | relative residual | median pd error (T_diff points) |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for light_bin in args.light_bins:
        t = time.perf_counter()
        configs = light_configs(scan.light_pos, len(v), light_bin)
        e_cfg = direct_irradiance(caster, n, configs.positions, scan.intensities()[configs.light])
        corr = first_bounce_correction(caster, ff, n, scan.light_pos, configs, scan.intensities())
        setup = time.perf_counter() - t

        def run():
            return inverse_radiosity(ff, configs, e_cfg, rows["y"], sample, rows["e"], pd0, correction=corr)

        t = time.perf_counter()
        run()
        first = time.perf_counter() - t
        seconds, inv = _median_time(run, 1)
        # pd error over points with a diffuse-only sample (the others carry their specular part here)
        has_diffuse = diffuse.any(1)
        err = np.median(np.abs(inv.pd - scan.true_pd)[has_diffuse] / scan.true_pd[has_diffuse])
        lines.append(f"| {light_bin} | {len(configs.positions)} | {setup:.2f} | {first:.2f} | {seconds:.2f} | "
                     f"{inv.iterations} | {inv.residual:.1e} | {err:.1e} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    with open(args.out, "w") as fh:
        fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
