"""One entry point: `estimate(scan, method=Local(), *, holdout=None, progress=None)`.

The method is an object, not a string. `Local`, `Radiosity`, `Photon` and `Auto` are
the option classes of Methods I, II, III and auto (`LocalOptions`, `RadiosityOptions`,
`PhotonOptions`, `AutoOptions`) under short names: `Local(model="ward", prior=False)`
takes exactly the fields `LocalOptions` does, and `estimate` accepts either spelling::

    import jaxrefl

    est = jaxrefl.estimate(jaxrefl.load_scan("A.npz"), method=jaxrefl.Local())
    est = jaxrefl.estimate("E.npz", method=jaxrefl.Radiosity(rays=128), holdout=0.25)

`estimate_to_file` runs `estimate` and writes the result file with a JSON summary
(`estimate_summary`): the command line (`jaxrefl estimate`, `jaxrefl batch`) goes through it.
"""

from __future__ import annotations

import logging
import os
import sys
import time

import numpy as np

from .methods.auto import AutoOptions, estimate_auto, holdout_check
from .methods.inverse_photon import PhotonOptions, estimate_photon
from .methods.local import LocalOptions, estimate_local
from .methods.radiosity import RadiosityOptions, estimate_radiosity
from .outputs.holdout import choose_holdout, estimate_with_holdout
from .result import Estimate, save_result, truth_errors
from .scan import checks
from .scan.io import load_scan
from .status import STATUS_NAMES, Status

__all__ = ["Local", "Radiosity", "Photon", "Auto", "estimate", "estimate_to_file", "estimate_summary"]

logger = logging.getLogger(__name__)


class Local(LocalOptions):
    """Method I, inverse local rendering (`jaxrefl.methods.local`); the fields of `LocalOptions`."""


class Radiosity(RadiosityOptions):
    """Method II, inverse radiosity: diffuse interreflections removed (`jaxrefl.methods.radiosity`);
    the fields of `RadiosityOptions`."""


class Photon(PhotonOptions):
    """Method III, inverse photon mapping: diffuse and specular interreflections removed,
    Ward model (`jaxrefl.methods.inverse_photon`); the fields of `PhotonOptions`."""


class Auto(AutoOptions):
    """The cheapest of Methods I-III predicted to meet `target_error`, per region
    (`jaxrefl.methods.auto`); the fields of `AutoOptions`."""


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
      `est.meta['holdout']` (`jaxrefl.outputs.holdout`). With `Auto`, a global method's result
      that predicts them worse than a cheaper method alone is replaced by that one's
      (`jaxrefl.methods.auto.holdout_check`, `est.meta['auto']['holdout_check']`).
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

            est, fit_scan, test_scan = estimate_with_holdout(scan, fit, held)
            if name == "auto":  # it never returns a method its held-out check measures worse than a cheaper one
                est = holdout_check(est, fit_scan, test_scan, method)
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


def estimate_to_file(scan, out, method=Local(), *, holdout=None, holdout_seed: int = 0,
                     progress: bool | None = None) -> dict:
    """`estimate` of `scan` (a `Scan` or the path of a bundle) by `method`, written atomically to
    the result file `out` (`save_result`); the JSON summary: `method`, `model`, `out`, the
    `estimate_summary` and `warnings`. `jaxrefl estimate` and `jaxrefl batch` go through here."""
    load_seconds = None
    if isinstance(scan, (str, os.PathLike)):
        t0 = time.perf_counter()
        scan = load_scan(scan)
        load_seconds = time.perf_counter() - t0
    est = estimate(scan, method, holdout=holdout, holdout_seed=holdout_seed, progress=progress)
    if load_seconds is not None:
        est.meta["seconds"] = {"load": load_seconds, **est.meta["seconds"]}
    save_result(out, est)
    return {"method": est.meta.get("method"), "model": est.model, "out": str(out), **estimate_summary(est, scan),
            "warnings": checks.estimate_warnings(est, log=None)}


def estimate_summary(est: Estimate, scan) -> dict:
    """Seconds per stage, coverage, status counts, what the method reports (materials, held-out
    error, misfit, ...) and, where `scan` has ground truth, the errors of `est` (JSON-ready).

    Coverage, one definition everywhere: `coverage` is the share of observed points (with a
    usable sample) whose lobe is their own (`measured`); `known` the share whose lobe the data
    determine (`measured` or `pooled`)."""
    observed = max(int(est.pd_measured.sum()), 1)
    summary = {
        "seconds": est.meta["seconds"],
        "points": int(len(est.status)),
        "coverage": float(np.sum(est.pd_measured & (est.status == Status.MEASURED)) / observed),
        "known": float(np.sum(est.pd_measured & np.isin(est.status, (Status.MEASURED, Status.POOLED))) / observed),
        "status_counts": {name: int(np.sum(est.status == code)) for code, name in enumerate(STATUS_NAMES)},
    }
    summary.update({k: est.meta[k] for k in ("materials", "material_lobes", "outer_iterations", "form_factors",
                                             "light_configurations", "image_difference", "best_iteration",
                                             "retraces", "auto", "holdout", "misfit")
                    if k in est.meta})
    if "material_lobes" in summary:  # strict JSON: an unknown std or spread (inf) is null
        summary["material_lobes"] = [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                                      for k, v in lobe.items()} for lobe in summary["material_lobes"]]
    if scan.true_pd is not None:
        summary["errors"] = truth_errors(est, scan)
    return summary
