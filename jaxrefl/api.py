"""One entry point: `estimate(scan, method=Local(), *, holdout=None, progress=None)`.

The method is an object, not a string. `Local`, `Radiosity`, `Photon` and `Auto` are
the option classes of Methods I, II, III and auto (`LocalOptions`, `RadiosityOptions`,
`PhotonOptions`, `AutoOptions`) under short names: `Local(model="ward", prior=False)`
takes exactly the fields `LocalOptions` does, and `estimate` accepts either spelling::

    import jaxrefl

    est = jaxrefl.estimate(jaxrefl.load_scan("A.npz"), method=jaxrefl.Local())
    est = jaxrefl.estimate("E.npz", method=jaxrefl.Radiosity(rays=128), holdout=0.25)

The command line (`jaxrefl estimate`, `jaxrefl batch`) goes through `estimate` too:
`method_from_options` turns its options into a method.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import time

import numpy as np

from . import checks
from .auto import AutoOptions, estimate_auto
from .holdout import choose_holdout, estimate_with_holdout
from .inverse_photon import PhotonOptions, estimate_photon
from .io import load_scan
from .local import Estimate, LocalOptions, estimate_local
from .radiosity import RadiosityOptions, estimate_radiosity

__all__ = ["Local", "Radiosity", "Photon", "Auto", "estimate", "method_from_options"]

logger = logging.getLogger(__name__)


class Local(LocalOptions):
    """Method I, inverse local rendering (`jaxrefl.local`); the fields of `LocalOptions`."""


class Radiosity(RadiosityOptions):
    """Method II, inverse radiosity: diffuse interreflections removed (`jaxrefl.radiosity`);
    the fields of `RadiosityOptions`."""


class Photon(PhotonOptions):
    """Method III, inverse photon mapping: diffuse and specular interreflections removed,
    Ward model (`jaxrefl.inverse_photon`); the fields of `PhotonOptions`."""


class Auto(AutoOptions):
    """The cheapest of Methods I-III predicted to meet `target_error`, per region
    (`jaxrefl.auto`); the fields of `AutoOptions`."""


#: option class -> (name, estimator(scan, options, tick)); `tick(done, total)` reports
#: progress inside the method where it has a hook (Method III's iterations)
_METHODS = (
    (LocalOptions, "local", lambda scan, o, tick: estimate_local(scan, o)),
    (RadiosityOptions, "radiosity", lambda scan, o, tick: estimate_radiosity(scan, o)),
    (PhotonOptions, "photon", lambda scan, o, tick: estimate_photon(scan, o, progress=tick)),
    (AutoOptions, "auto", lambda scan, o, tick: estimate_auto(scan, o)),
)


def _method(method):
    for cls, name, run in _METHODS:
        if isinstance(method, cls):
            return name, run
    raise TypeError(f"method: expected jaxrefl.Local(), Radiosity(), Photon() or Auto(), got {method!r}")


def _show(progress) -> bool:
    if progress is None:
        try:
            return sys.stderr.isatty()
        except (AttributeError, ValueError):  # stderr replaced or closed
            return False
    return bool(progress)


def estimate(scan, method=Local(), *, holdout=None, holdout_seed: int = 0, progress: bool | None = None) -> Estimate:
    """Per-point reflectance of `scan` by `method`.

    **Arguments:**

    - `scan`: a `jaxrefl.Scan` with radiance, or the path of a scan bundle (`load_scan`).
    - `method`: `Local(...)`, `Radiosity(...)`, `Photon(...)` or `Auto(...)` (or the
      `*Options` classes they are).
    - `holdout`: None (fit on every light); a fraction in (0, 1) of the lights to hold
      out, drawn with `holdout_seed`; or a list of light indices. The estimate is fitted
      without them, relit under them and compared with their images: the error lands in
      `est.meta['holdout']` (`jaxrefl.holdout`).
    - `progress`: a bar over the stages on stderr (Method III: with its iterations).
      None: only when stderr is a terminal.

    Bad frames are excluded first (`checks.checked_scan`; an `ObservationError`, a
    `ValueError`, when nothing can be fitted); warnings about the result are logged on
    this module's logger and kept in `est.meta['warnings']`.

    **Returns:** `Estimate` (frozen; `status` codes are `jaxrefl.Status`, seconds per stage
    in `est.seconds`).
    """
    from tqdm.auto import tqdm

    name, run = _method(method)
    stages = (["load"] if isinstance(scan, (str, os.PathLike)) else []) + ["check", name]
    stages += ["held-out lights"] if holdout is not None else []
    bar = tqdm(total=len(stages), desc="jaxrefl", unit="stage", file=sys.stderr, disable=not _show(progress),
               leave=False)

    def stage(text):
        bar.set_description(f"jaxrefl: {text}")

    def tick(done, total):
        bar.set_postfix_str(f"iteration {done}/{total}")

    try:
        load_seconds = None
        if isinstance(scan, (str, os.PathLike)):
            stage("load")
            t0 = time.perf_counter()
            scan = load_scan(scan)
            load_seconds = time.perf_counter() - t0
            bar.update()
        stage("check")
        top = not checks.is_checked(scan)  # the caller's scan: warnings are ours to log
        scan = checks.checked_scan(scan)  # bad frames out before any held-out split
        bar.update()
        stage(name)
        if holdout is None:
            est = run(scan, method, tick)
        else:
            fraction, lights = (holdout, None) if np.ndim(holdout) == 0 else (None, holdout)
            held = choose_holdout(scan.n_lights, fraction, lights, holdout_seed)

            def fit(fit_scan):
                out = run(fit_scan, method, tick)
                bar.update()
                stage("held-out lights")
                return out

            est = estimate_with_holdout(scan, fit, held)[0]
            if fraction is not None:
                est.meta["holdout"].update(fraction=float(fraction), seed=int(holdout_seed))
        bar.update()
        if load_seconds is not None:
            est.meta["seconds"] = {"load": load_seconds, **est.meta.get("seconds", {})}
        if top:
            checks.estimate_warnings(est, logger)
        return est
    finally:
        bar.close()


def method_from_options(options) -> LocalOptions | RadiosityOptions | PhotonOptions | AutoOptions:
    """The method the `jaxrefl estimate` / `jaxrefl batch` options choose (`options` an
    `argparse.Namespace` of them: `method`, `model`, `paper`, ... as the CLI names them,
    dashes as underscores). Raises `ValueError` naming a bad option."""
    o = options
    local = Local(model=o.model, paper=o.paper, steps=o.steps, window=o.window, min_snr=o.min_snr,
                  solver=o.solver, pool=o.pool, prior=getattr(o, "prior", True),
                  materials=getattr(o, "materials", 6))
    if local.materials < 1:
        raise ValueError(f"materials: must be >= 1, got {local.materials}")
    if o.rays < 1 or o.outer < 1 or not o.light_bin >= 0:
        raise ValueError("rays, outer: must be >= 1; light-bin: must be >= 0")
    radiosity = dict(rays=o.rays, light_bin=o.light_bin, outer=o.outer, paper=o.paper)
    photon = {"photons": o.photons, "iterations": o.iterations, "solver": o.photon_solver,
              "damping": o.damping, "retrace_ess": o.retrace_ess, "light_bin": o.light_bin,
              "min_snr": o.min_snr, "window": o.window, "gather_rays": o.gather_rays,
              "gather_budget": o.gather_budget, "min_fit_p": o.min_fit_p, "fill_sd": o.fill_sd,
              "fill_pd_scale": o.fill_pd_scale, "fill_neighbours": o.fill_neighbours, "polish": o.polish}
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
