"""Method III on glossy Object E beside the fold: the final gather against the photon
map for the first bounce, with the truth's reflectance (the forward model's floor)
and end to end over photon seeds.

    python -m benchmarks.final_gather_check

1. Oracle: photons traced from the true reflectance, step (a) of Method III with
   the true ps and alpha: mean relative pd error beside the fold (within 2 cm, the
   fold line left out) and far from it, for the photon map alone and with the
   first bounce gathered (256 and 1024 rays per observation).
2. Estimate: `estimate_photon` (2M photons per light, 50 iterations) for photon
   seeds 0-2, with and without the final gather and the chi^2 test of lobe fits.
Scene as `benchmarks.inverse_photon_bench` (oblique pinhole rig, 1024 paths per
observation, 1 % noise, 12 bits). Prints one line per run.
"""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np

from benchmarks.inverse_photon_bench import _errors, _scan
from data_synth.objects import fold_coordinate, make_object
from jaxrefl.geometry.raycast import RayCaster
from jaxrefl.methods import inverse_photon as ip
from jaxrefl.methods.final_gather import gather_rays
from jaxrefl.methods.local import prepare_rows
from jaxrefl.methods.photon import PhotonReplay


def oracle(scan, near, far, settings):
    caster = RayCaster(scan.vertices, scan.faces)
    r = prepare_rows(scan, ip.PhotonOptions().thresholds, caster)
    use = r["use"]
    rows, _ = ip._fit_rows(scan, r)
    truth = (scan.true_pd, scan.true_ps, scan.true_alpha)
    ok = use.any(1)
    for rays, photons in settings:
        rp = PhotonReplay.build(caster, scan.vertices, scan.faces, scan.normals, scan.light_pos, scan.intensities(),
                                scan.cam_pos, truth, n_photons=photons, seed=3, first_bounce=rays == 0)
        fg = None if rays == 0 else gather_rays(caster, scan.normals, scan.camera_positions(),
                                                scan.light_positions(), scan.intensities(),
                                                (scan.true_pd, scan.true_ps, np.full(scan.n_points, 0.1)), use,
                                                rays, seed=2)
        th = tuple(jnp.asarray(x, jnp.float32) for x in (scan.true_pd, scan.true_ps, np.log(scan.true_alpha)))
        d, q = ip._parts(rp.data, rp.static, None, fg, *th)
        pd, _ = ip._step_a(*th, rows, d, q)
        signed = ((np.asarray(pd) - scan.true_pd) / scan.true_pd).mean(1)
        rel = (np.abs(np.asarray(pd) - scan.true_pd) / scan.true_pd).mean(1)
        print(f"oracle rays={rays} photons={photons:,}: near {rel[near & ok].mean():.4f} "
              f"(bias {signed[near & ok].mean():+.4f}), far {rel[far & ok].mean():.4f}", flush=True)


def main():
    scan, _, _ = _scan("glossy", 32, 1024)
    fold = fold_coordinate(make_object("E", 32, "glossy").vertices)
    h = np.min(np.abs(fold[np.abs(fold) > 1e-9]))
    near, far = (np.abs(fold) > 0.5 * h) & (np.abs(fold) < 0.02), np.abs(fold) >= 0.02
    oracle(scan, near, far, [(0, 2_000_000), (0, 8_000_000), (256, 2_000_000), (1024, 2_000_000)])
    for rays, p in ((256, 0.05), (0, 0.05), (256, 0.0), (1024, 0.05)):
        for seed in (0, 1, 2):
            t = time.perf_counter()
            est = ip.estimate_photon(scan, ip.PhotonOptions(photons=2_000_000, iterations=50, gather_rays=rays,
                                                            min_fit_p=p, seed=seed))
            e = _errors(est, scan, fold, h)
            print(f"estimate rays={rays} min_fit_p={p} seed={seed}:", {k: round(v, 4) for k, v in e.items()},
                  f"{time.perf_counter() - t:.1f} s", flush=True)


if __name__ == "__main__":
    main()
