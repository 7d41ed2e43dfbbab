"""What the commands share: the estimator options (`estimate`, `batch`), progress on a terminal,
number lists, and loading a result with its scan."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..api import Auto, Local, Photon, Radiosity


def progress() -> bool:
    return sys.stderr.isatty()


def int_list(text: str):
    if text in ("all", ""):
        return None
    try:
        return [int(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers or 'all', got {text!r}")


def numbers(text, name, counts):
    try:
        values = [float(t) for t in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) not in counts or not all(np.isfinite(values)):
        raise ValueError(f"{name}: expected {' or '.join(map(str, counts))} comma-separated numbers, got {text!r}")
    return np.array(values)


def result_and_scan(args):
    from ..result import load_result
    from ..scan.io import load_scan

    est, scan = load_result(args.result), load_scan(args.scan)
    if len(est.pd) != scan.n_points:
        raise ValueError(f"result: {len(est.pd)} points, but the scan has {scan.n_points} vertices")
    return est, scan


def add_estimate_options(p):
    """The estimator options, shared by `estimate` and `batch`."""
    p.add_argument("--method", choices=["local", "radiosity", "photon", "auto"], default="local",
                   help="local: Method I, inverse local rendering (§3); radiosity: Method II, inverse "
                        "radiosity, diffuse interreflections removed (§4); photon: Method III, inverse "
                        "photon mapping, diffuse and specular interreflections removed (§5, Ward model); "
                        "auto: the cheapest of them predicted to meet --target-error, per region")
    p.add_argument("--model", choices=["torrance-sparrow", "ward"], default="torrance-sparrow")
    p.add_argument("--paper", action="store_true",
                   help="the paper's estimator: Eq. 5 single best diffuse sample, Eq. 7 from two samples, "
                        "the gated lobe fill (no shared prior)")
    p.add_argument("--window", type=int, default=5,
                   help="interpolation window W (a (W-1)/2-ring): where points without a lobe of their own "
                        "(with the prior: unresolved ones) take it from")
    p.add_argument("--steps", type=int, default=15, help="Newton steps of the polish in ln roughness (solver lm)")
    p.add_argument("--solver", choices=["lm", "optimistix"], default="lm")
    p.add_argument("--min-snr", type=float, default=3.0, help="ps / std(ps) needed to call it measured")
    p.add_argument("--prior", action=argparse.BooleanOptionalAction, default=True,
                   help="Method I: a shared reflectance prior (default): materials chosen by BIC, one lobe fitted "
                        "jointly per material, each point's lobe the posterior mode of its own samples and the "
                        "prior (status measured or pooled); --no-prior: the gated rules (--pool, --window)")
    p.add_argument("--materials", type=int, default=6, metavar="K",
                   help="most materials the prior tries (K = 1..this, chosen by BIC)")
    p.add_argument("--interreflection-rays", type=int, default=16, metavar="N",
                   help="Method I: rays per point estimating the light the object reflects onto itself, which "
                        "Method I leaves in pd; its std_pd includes it (0: noise alone)")
    p.add_argument("--pool", action=argparse.BooleanOptionalAction, default=True,
                   help="with --no-prior: points without their own lobe share one fitted with same-colour "
                        "neighbours (default; --no-pool: window interpolation only)")
    g = p.add_argument_group("radiosity (Method II)")
    g.add_argument("--rays", type=int, default=256, help="form-factor rays per patch (vertex)")
    g.add_argument("--light-bin", type=float, default=0.1,
                   help="per-point lights: bin size [m] of the light configurations for later bounces")
    g.add_argument("--outer", type=int, default=3, help="alternations of pd and the specular part")
    g = p.add_argument_group("photon (Method III; always the Ward model)")
    g.add_argument("--photons", type=int, default=1_000_000, help="photons emitted per light")
    g.add_argument("--iterations", type=int, default=50, help="outer iterations (the paper's th_2)")
    g.add_argument("--photon-solver", choices=["lm", "simplex"], default="lm",
                   help="step (b): Newton in ln alpha with ps projected out, or the paper's downhill simplex")
    g.add_argument("--damping", type=float, default=0.5, help="share of each iteration's change taken")
    g.add_argument("--retrace-ess", type=float, default=0.3,
                   help="re-trace the photons when the effective sample size falls below this fraction")
    g.add_argument("--gather-rays", type=int, default=1024,
                   help="final-gather rays per observation for the first interreflection bounce (0: the photon "
                        "map gathers every bounce); halved until --gather-budget rays in all")
    g.add_argument("--gather-budget", type=int, default=8_000_000, help="most final-gather rays in all")
    g.add_argument("--min-fit-p", type=float, default=0.0,
                   help="a lobe counts as measured only if its fit passes a chi^2 test at this p-value (0: no "
                        "test; a misfit lobe's covariance is inflated by its chi^2 either way)")
    g.add_argument("--fill-pd-scale", type=float, default=0.2,
                   help="the lobe fill pools lobes of alike diffuse albedo: a neighbour whose pd is this share "
                        "apart counts e^-1 (0: pool regardless of pd)")
    g.add_argument("--fill-sd", type=float, default=0.02,
                   help="each point's lobe is a precision-weighted Huber estimate over the nearest measured lobes, "
                        "taken until they pin ln ps and ln alpha to this standard deviation")
    g.add_argument("--fill-neighbours", type=int, default=64, help="most measured lobes one point's lobe uses")
    g.add_argument("--polish", type=int, default=10, help="steps (a) at the final lobes")
    g.add_argument("--no-lobe-prior", dest="lobe_prior", action="store_false",
                   help="final lobes from the iterations' own fits and the fill only (default: also fit every lobe "
                        "with the shared reflectance prior through the interreflection model, pd profiled out, and "
                        "keep the lobes that explain the images better)")
    g.add_argument("--refine", type=int, default=0,
                   help="after the iterations, this many L-BFGS steps on the whole image difference over one pd "
                        "and one lobe per material, the interreflection recomputed at each step; kept only where "
                        "it explains the images better, the per-point fits then start from it (0: none). Leaves "
                        "fixed points of the iterations far from the truth (a glossy fold lit from both sides)")
    g = p.add_argument_group("auto (model only what the scene needs)")
    g.add_argument("--target-error", type=float, default=0.0,
                   help="relative pd error you accept (median per region): a cheaper method that reaches it is "
                        "kept; 0 (default): as accurate as the best method, within --tolerance. Method III is a "
                        "candidate with --model ward")
    g.add_argument("--tolerance", type=float, default=0.1,
                   help="a cheaper method is kept where its error, its interreflection bias inflated by the "
                        "error model's uncertainty, is within this fraction of the best method's prediction")


def method_from_options(options) -> Local | Radiosity | Photon | Auto:
    """The method the `jaxrefl estimate` / `jaxrefl batch` options choose (`options` the
    `argparse.Namespace` of `add_estimate_options`: `method`, `model`, `paper`, ... as the CLI names them,
    dashes as underscores). Raises `ValueError` naming a bad option."""
    from ..api import Auto, Local, Photon, Radiosity
    from ..methods.radiosity import RadiosityOptions

    o = options
    local = Local(model=o.model, paper=o.paper, steps=o.steps, window=o.window, min_snr=o.min_snr,
                  solver=o.solver, pool=o.pool, prior=getattr(o, "prior", True),
                  materials=getattr(o, "materials", 6), interreflection_rays=getattr(o, "interreflection_rays", 16))
    if local.materials < 1:
        raise ValueError(f"materials: must be >= 1, got {local.materials}")
    if o.rays < 1 or o.outer < 1 or not o.light_bin >= 0:
        raise ValueError("rays, outer: must be >= 1; light-bin: must be >= 0")
    radiosity = dict(rays=o.rays, light_bin=o.light_bin, outer=o.outer, paper=o.paper)
    photon = {"photons": o.photons, "iterations": o.iterations, "solver": o.photon_solver,
              "damping": o.damping, "retrace_ess": o.retrace_ess, "light_bin": o.light_bin,
              "min_snr": o.min_snr, "window": o.window, "gather_rays": o.gather_rays,
              "gather_budget": o.gather_budget, "min_fit_p": o.min_fit_p, "fill_sd": o.fill_sd,
              "fill_pd_scale": o.fill_pd_scale, "fill_neighbours": o.fill_neighbours, "polish": o.polish,
              "lobe_prior": getattr(o, "lobe_prior", True), "refine": getattr(o, "refine", 0)}
    if o.method == "radiosity":
        return Radiosity(**radiosity, local=local)
    if o.method == "photon":
        return Photon(**photon, local=dataclasses.replace(local, model="ward"))
    if o.method == "auto":
        if not o.target_error >= 0 or not o.tolerance >= 0:
            raise ValueError(f"target-error, tolerance: must be >= 0, got {o.target_error}, {o.tolerance}")
        return Auto(target_error=o.target_error, tolerance=o.tolerance, local=local, photon=photon,
                    radiosity=RadiosityOptions(**radiosity))
    if o.method != "local":
        raise ValueError(f"method: must be local, radiosity, photon or auto, got {o.method!r}")
    return local
