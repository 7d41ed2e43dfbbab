"""Physical consistency of a scan's observations, checked before any fit.

A scan whose numbers cannot be right gives an estimate that looks fine and is wrong
(albedos clipped at 1, lobes of 1e5, maps of zeros). The checks here look only at the
observations and the direct-light geometry, with statistics that do not change when
every length is scaled by `s` and every intensity by `s^2`, or all radiance by one
factor relative to its own level:

- **Something to fit**: samples that are valid, unsaturated and face both their camera
  and their light (`cos > 0`). None at all is an error naming where they were lost: all
  masked (`valid`), all saturated, or all facing away (normals flipped inward?).
- **Units and exposure**: the Lambertian albedo the direct light implies for a sample,
  `pd = pi y C^2 / (Y cos_i)` (`y` mean RGB radiance, `Y` intensity, `C` distance), has
  a median over the scan's samples near the object's albedo, in [0, 1] for any real
  surface (specular peaks and interreflections raise single samples, not the median).
  A median above `IMPLIED_PD_HIGH` or below `IMPLIED_PD_LOW` is an error naming the
  likely causes: lengths of the mesh / lights / camera in another unit (millimetres
  for metres scale `C^2` by 1e6), the light intensity, or the exposure (radiance scale).
- **Frames**: a light whose samples are far darker or brighter than the albedo the
  other lights imply at the same points (`DARK_RATIO`, `BRIGHT_RATIO`), whose valid
  samples are all saturated, or whose samples mostly sit at one clipped value, is a
  bad frame: `exclude_bad_lights` masks it (`valid` False) with a logged warning.

`checked_scan` runs all three the way the estimators do (they call it first): bad
frames excluded, an `ObservationError` (a `ValueError`) for the rest. After a fit,
`estimate_warnings` logs when most points have no lobe determined by the data. Everything
goes through `logging` (loggers `jaxrefl.<module>`); the command line prints it as one line.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from ..status import Status
from .io import ScanError

__all__ = ["ObservationError", "ObservationReport", "check_observations", "exclude_bad_lights", "checked_scan",
           "is_checked", "method_input", "estimate_warnings", "IMPLIED_PD_HIGH", "IMPLIED_PD_LOW", "DARK_RATIO", "BRIGHT_RATIO"]

logger = logging.getLogger(__name__)

#: Median implied Lambertian albedo above which the scan's units or exposure are wrong. An
#: albedo is at most 1; the median sample sits at the diffuse albedo plus a little lobe and
#: interreflected light (a highlight covers few samples). 3 leaves room for glossy rigs that
#: see many samples near their highlight, and still catches unit slips, which are powers of
#: 10 (mm for m: 1e6; W for mW: 1e3). (Measured values on synthetic rigs:
#: benchmarks/RESULTS_notes.md.)
IMPLIED_PD_HIGH = 3.0
#: Median implied albedo below which the observations are too dark to be this light's
#: reflection: an order of magnitude below the darkest common materials (carbon black,
#: black velvet: albedo 0.01-0.05).
IMPLIED_PD_LOW = 1e-3
#: A frame is dark when at 90 % of its points (`_FRAME_QUANTILE`) its implied albedo is
#: below this share of what the other lights imply there: the geometry is already divided
#: out, so only a fault (light off, shutter, lost frame) or a shadow over nearly all
#: of the frame's points does that; a highlight or shadow covers a few.
DARK_RATIO = 0.1
#: ... and bright (blown, a wrong exposure) when at 90 % of its points it is above this
#: multiple of it (a highlight covers a few points of a frame, not nine in ten).
BRIGHT_RATIO = 10.0
_FRAME_QUANTILE = 90.0
#: Samples nearer grazing than this cosine (78 degrees) are left out of the implied
#: albedo: there a small normal error multiplies it.
_COS_MIN = 0.2
#: Samples of a frame needed before its statistic is trusted; points need this many
#: usable lights for their own reference albedo (the median over their lights).
_MIN_FRAME_SAMPLES = 10
_MIN_POINT_LIGHTS = 3
#: A frame whose samples sit at its own maximum in more than this share is clipped
#: (a blown frame without a declared saturation level).
_CLIPPED_SHARE = 0.5

_MARK = "observation_checks"  # scan.meta key of a scan `checked_scan` returned


class ObservationError(ValueError):
    """The observations cannot give a physical estimate; `cause` is a short key
    ('no valid observations', 'units or exposure')."""

    def __init__(self, cause: str, message: str):
        super().__init__(f"{cause}: {message}")
        self.cause = cause


@dataclass(frozen=True)
class ObservationReport:
    """What `check_observations` found. Counts of samples `(point, light)`: `samples`
    (all), `valid`, `unsaturated` (valid and below saturation), `usable` (also facing
    camera and light); `implied_pd` the median implied Lambertian albedo over the usable
    samples off grazing (NaN when none); `frame_ratio` `(M,)` per light, the 90th
    percentile (`dark`) and `frame_ratio_low` the 10th (`bright`) of its implied albedo
    over the other lights' median at the same points (NaN without enough samples);
    `dark_lights`, `blown_lights` (with `reasons` per light), `errors` (fatal messages)."""

    samples: int
    valid: int
    unsaturated: int
    usable: int
    implied_pd: float
    frame_ratio: np.ndarray
    frame_ratio_low: np.ndarray
    dark_lights: tuple
    blown_lights: tuple
    reasons: dict
    errors: tuple

    @property
    def bad_lights(self) -> tuple:
        return tuple(sorted(set(self.dark_lights) | set(self.blown_lights)))

    def as_dict(self) -> dict:
        """JSON-ready summary (for an estimate's `meta`)."""
        finite = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {"samples": self.samples, "valid": self.valid, "unsaturated": self.unsaturated, "usable": self.usable,
                "implied_pd_median": finite(self.implied_pd), "excluded_lights": list(self.bad_lights),
                "reasons": {str(k): v for k, v in self.reasons.items()}}


def _direct_terms(scan):
    """`(cos_i, cos_o, irradiance)`, each `(N, M)`, by plain NumPy one light at a time
    (no shadows: a check, not a fit)."""
    n, m = scan.n_points, scan.n_lights
    normals = scan.normals if scan.normals is not None else np.zeros((n, 3))
    lp = scan.light_pos if scan.light_pos.ndim == 3 else np.broadcast_to(scan.light_pos[None], (n, m, 3))
    cp = scan.camera_positions()
    intensity = scan.intensities()
    cos_i, cos_o, e = np.zeros((n, m)), np.zeros((n, m)), np.zeros((n, m))
    for k in range(m):
        to_l = lp[:, k] - scan.vertices
        d2 = np.maximum(np.einsum("ij,ij->i", to_l, to_l), 1e-300)
        cos_i[:, k] = np.einsum("ij,ij->i", to_l, normals) / np.sqrt(d2)
        to_c = cp[:, k] - scan.vertices
        cos_o[:, k] = np.einsum("ij,ij->i", to_c, normals) / np.maximum(np.linalg.norm(to_c, axis=1), 1e-300)
        e[:, k] = intensity[k] * np.maximum(cos_i[:, k], 0.0) / d2
    return cos_i, cos_o, e


def _no_observations(scan, valid, unsaturated, lit_any, cos_i, cos_o) -> str:
    """Where every sample was lost (the message of the 'no valid observations' error);
    `lit_any` `(N, M)`: some channel above 0."""
    if not valid.any():
        return "every observation is masked out (`valid` is False everywhere)"
    if not (unsaturated & lit_any).any():
        if (valid & ~unsaturated).any():
            return (f"every valid sample is saturated (at or above the sensor maximum {scan.saturation:g}) or black: "
                    "lower the exposure, or give the true saturation level")
        return "every valid sample is black (0 in every channel): were the lights on, the frames read right?"
    ok = unsaturated & lit_any
    lit, seen = (cos_i > 0) & ok, (cos_o > 0) & ok
    if not lit.any() and not seen.any():
        return ("every valid sample faces away from both its camera and its light (cos <= 0): "
                "the normals probably point inward (flip them, or fix the faces' winding)")
    if not seen.any():
        return "every valid sample faces away from its camera (cos_o <= 0): are the normals flipped inward?"
    if not lit.any():
        return "every valid sample faces away from its light (cos_i <= 0): are the normals flipped inward?"
    return "no valid, unsaturated, non-black sample faces both its camera and its light"


def _frame_statistics(z, usable):
    """Per light, the 90th and 10th percentiles over its points of `z / reference`, the
    reference being the median of `z` over each point's usable lights (points with at least
    `_MIN_POINT_LIGHTS`). `(M,)` each, NaN with fewer than `_MIN_FRAME_SAMPLES`."""
    n_lights = usable.sum(1)
    zz = np.where(usable, z, np.nan)
    ok_point = n_lights >= _MIN_POINT_LIGHTS
    ref = np.full(len(z), np.nan)
    if ok_point.any():
        ref[ok_point] = np.nanmedian(zz[ok_point], axis=1)
    good = ok_point & (ref > 0)
    ratio = np.where(usable & good[:, None], zz / np.where(good, ref, 1.0)[:, None], np.nan)
    hi, lo = np.full(z.shape[1], np.nan), np.full(z.shape[1], np.nan)
    for k in range(z.shape[1]):
        r = ratio[:, k][np.isfinite(ratio[:, k])]
        if len(r) >= _MIN_FRAME_SAMPLES:
            hi[k], lo[k] = np.percentile(r, _FRAME_QUANTILE), np.percentile(r, 100.0 - _FRAME_QUANTILE)
    return hi, lo


def _clipped_frames(y, valid, unsaturated):
    """Lights whose valid samples sit at the frame's own positive maximum in more than
    `_CLIPPED_SHARE` of them (constant or clipped frames)."""
    out = []
    peak = y.max(-1)
    for k in range(y.shape[1]):
        v = valid[:, k] & unsaturated[:, k]
        if v.sum() < _MIN_FRAME_SAMPLES:
            continue
        top = peak[v, k].max()
        if top > 0 and np.mean(peak[v, k] >= top) > _CLIPPED_SHARE:
            out.append(k)
    return out


def check_observations(scan) -> ObservationReport:
    """Check a scan's observations (module docstring); raises nothing.

    **Arguments:** `scan` a `jaxrefl.Scan` with radiance.

    **Returns:** `ObservationReport`; `errors` empty when the scan can be fitted
    (after `exclude_bad_lights`).
    """
    if scan.radiance is None:
        raise ValueError("radiance: the scan has no observations to estimate from")
    n, m = scan.n_points, scan.n_lights
    y = np.asarray(scan.radiance, np.float64)
    valid = np.ones((n, m), bool) if scan.valid is None else np.asarray(scan.valid, bool)
    unsaturated = scan.observed()
    cos_i, cos_o, e = _direct_terms(scan)
    usable = unsaturated & (cos_i > 0) & (cos_o > 0)
    # Blown frames: every valid sample saturated, or most of them at one clipped value.
    reasons = {}
    for k in np.flatnonzero(valid.sum(0) >= _MIN_FRAME_SAMPLES):
        if not unsaturated[:, k].any():
            reasons[int(k)] = "blown: every valid sample saturated"
    for k in _clipped_frames(y, valid, unsaturated):
        reasons.setdefault(int(k), "blown: most samples at one clipped value")
    blown = set(reasons)
    off_grazing = usable & (cos_i >= _COS_MIN) & (cos_o >= _COS_MIN)
    off_grazing[:, sorted(blown)] = False
    z = np.where(off_grazing, np.pi * y.mean(-1) / np.where(e > 0, e, 1.0), np.nan)
    hi, lo = _frame_statistics(z, off_grazing)
    dark = [int(k) for k in np.flatnonzero(hi < DARK_RATIO) if k not in blown]
    for k in dark:
        reasons[k] = (f"dark: at 90 % of its points its samples reach at most {hi[k]:.1%} of the albedo the other "
                      "lights imply there")
    bright = [int(k) for k in np.flatnonzero(lo > BRIGHT_RATIO) if k not in blown]
    for k in bright:
        reasons[k] = (f"blown: at 90 % of its points its samples are at least {lo[k]:.3g} times the albedo the "
                      "other lights imply there")
    blown |= set(bright)
    keep = off_grazing.copy()
    keep[:, dark + sorted(blown)] = False
    errors = []
    lit_any = y.max(-1) > 0
    usable_kept = usable & lit_any
    usable_kept[:, dark + sorted(blown)] = False
    if not usable_kept.any():
        errors.append(("no valid observations", _no_observations(scan, valid, unsaturated, lit_any, cos_i, cos_o)
                       if not (usable & lit_any).any() else "every light with samples is a bad frame: "
                       + "; ".join(f"light {k}: {r}" for k, r in sorted(reasons.items()))))
    if not keep.any():  # nothing off grazing: every usable sample then
        keep = usable_kept
        z = np.where(keep, np.pi * y.mean(-1) / np.where(e > 0, e, 1.0), np.nan)
    implied = float(np.median(z[keep])) if keep.any() else np.nan
    if errors:  # nothing to fit: the units are beside the point
        implied = np.nan
    if np.isfinite(implied) and not IMPLIED_PD_LOW <= implied <= IMPLIED_PD_HIGH:
        errors.append(("units or exposure", _units_message(implied)))
    return ObservationReport(samples=n * m, valid=int(valid.sum()), unsaturated=int(unsaturated.sum()),
                             usable=int(usable.sum()), implied_pd=implied, frame_ratio=hi, frame_ratio_low=lo,
                             dark_lights=tuple(dark), blown_lights=tuple(sorted(blown)), reasons=reasons,
                             errors=tuple(errors))


def _units_message(implied: float) -> str:
    factor = implied / 0.5  # against a mid-grey albedo, only to name the order of magnitude
    if implied > IMPLIED_PD_HIGH:
        return (f"the observed radiance is {implied:.3g} times what a white Lambertian surface under these lights "
                f"would reflect (median over the samples; an albedo is at most 1, so about {factor:.0e} too bright). "
                "Likely causes: lengths of the mesh, lights and camera in another unit than metres (millimetres "
                "scale the squared light distances by 1e6), light intensities too low, or the radiance not "
                "divided by the exposure")
    size = "black (0)" if implied <= 0 else f"{implied:.3g}, about {1 / factor:.0e} times darker than any real surface"
    return (f"the observed radiance implies a median albedo of {size} (or below the noise). Likely causes: "
            "lengths of the mesh, lights and camera in another unit than metres, light intensities too high, "
            "or the radiance scaled down (exposure, a wrong bit depth)")


def exclude_bad_lights(scan, report: ObservationReport | None = None):
    """`scan` with the frames `report` (default: `check_observations(scan)`) found dark or
    blown masked out (`valid` False for those lights), each logged as a warning. The same
    scan when none is."""
    report = check_observations(scan) if report is None else report
    bad = list(report.bad_lights)
    if not bad:
        return scan
    for k in bad:
        logger.warning("light %d excluded from the fit (%s)", k, report.reasons[k])
    valid = np.ones((scan.n_points, scan.n_lights), bool) if scan.valid is None else np.array(scan.valid, bool)
    valid[:, bad] = False
    return dataclasses.replace(scan, valid=valid)


def is_checked(scan) -> bool:
    """Whether `scan` came out of `checked_scan` (then it is not checked again)."""
    return isinstance(scan.meta, dict) and _MARK in scan.meta


def checked_scan(scan):
    """The scan an estimator fits: bad frames excluded (`exclude_bad_lights`), an
    `ObservationError` when nothing can be fitted or the units / exposure are off; its
    `meta['observation_checks']` holds the report. A scan already checked is returned as is.
    """
    if is_checked(scan):
        return scan
    report = check_observations(scan)
    if report.errors:
        cause, message = report.errors[0]
        raise ObservationError(cause, message)
    scan = exclude_bad_lights(scan, report)
    return dataclasses.replace(scan, meta={**(scan.meta if isinstance(scan.meta, dict) else {}),
                                           _MARK: report.as_dict()})


#: Share of the observed points below which an estimate's lobes count as mostly unknown.
_LOW_COVERAGE = 0.5


def method_input(scan) -> tuple:
    """What every method does first: `(checked_scan(scan), top)`, `top` True where `scan` had not
    been checked yet (the caller is the user, whose warnings the method logs, not another method).
    Raises `ValueError` for a scan without radiance, `ScanError` for non-finite radiance,
    `ObservationError` where nothing can be fitted."""
    if scan.radiance is None:
        raise ValueError("radiance: the scan has no observations to estimate from")
    top = not is_checked(scan)
    if top:
        bad = int(np.count_nonzero(~np.isfinite(np.asarray(scan.radiance))))
        if bad:  # a scan built in Python skips `validate_scan`, which a file's load applies
            raise ScanError("radiance", f"contains {bad} non-finite value(s) (NaN or inf): mark samples that "
                            "were not measured False in `valid` and give them any finite value")
    return checked_scan(scan), top


def estimate_warnings(est, log: logging.Logger | None = logger) -> list[str]:
    """Warnings about an estimate (`jaxrefl.Estimate`): lights the checks excluded
    (`meta['observation_checks']`; logged when they were excluded), what the method itself
    noted (`meta['method_warnings']`), and lobes determined by the data (status `measured` or
    `pooled`) at fewer than half of the observed points, or most of them `unresolved` (these
    two logged on `log`; None: not logged). All of them are returned and kept in
    `est.meta['warnings']`."""
    report = est.meta.get(_MARK) or {}
    out = [f"light {k} excluded from the fit ({report['reasons'][str(k)]})" for k in report.get("excluded_lights", [])]
    coverage = []
    observed = np.asarray(est.pd_measured, bool)
    if observed.any():
        status = np.asarray(est.status)[observed]
        known = float(np.mean(np.isin(status, (Status.MEASURED, Status.POOLED))))
        unresolved = float(np.mean(status == Status.UNRESOLVED))
        if unresolved > _LOW_COVERAGE:
            coverage.append(f"{unresolved:.0%} of the observed points are unresolved: their ps and roughness are "
                            "not determined by the data (their material's loose joint fit, copied from neighbours, "
                            "or 0)")
        elif known < _LOW_COVERAGE:
            coverage.append(f"lobes measured or pooled at only {known:.0%} of the observed points: the rest are "
                            "interpolated or unresolved")
    else:
        coverage.append("no point has a usable sample: every value is a fill")
    if log is not None:
        for msg in coverage:
            log.warning(msg)
    out += list(est.meta.get("method_warnings", []))
    est.meta["warnings"] = out + coverage
    return out + coverage


