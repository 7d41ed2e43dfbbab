"""`jaxrefl estimate`: per-point reflectance from a scan bundle, optionally with held-out lights."""

from __future__ import annotations

import json
import sys

import numpy as np

from ._common import add_estimate_options, method_from_options, progress


def add_estimate(sub):
    p = sub.add_parser("estimate", help="estimate per-point reflectance from a scan bundle")
    p.add_argument("scan", help="scan bundle (.npz) with radiance")
    p.add_argument("--out", required=True, help="result file to write (.npz)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    g = p.add_argument_group("held-out lights (validation)")
    h = g.add_mutually_exclusive_group()
    h.add_argument("--holdout", type=float, default=None, metavar="F",
                   help="fit without this fraction of the lights (drawn with --holdout-seed), then relight the "
                        "estimate under them and report its error against their images")
    h.add_argument("--holdout-lights", default=None, metavar="I,J,...",
                   help="fit without these observations (comma-separated light indices) and report the error there")
    g.add_argument("--holdout-seed", type=int, default=0, help="seed of the lights --holdout draws")
    add_estimate_options(p)


def run_estimate(args) -> int:
    from ..api import estimate_to_file

    method = method_from_options(args)  # bad options fail before the bundle is read
    holdout = args.holdout
    if holdout is not None and not 0 < holdout < 1:
        raise ValueError(f"holdout: the fraction of lights held out must lie in (0, 1), got {holdout}")
    if args.holdout_lights is not None:
        try:
            holdout = [int(t) for t in str(args.holdout_lights).split(",")]
        except ValueError:
            raise ValueError(f"holdout-lights: expected comma-separated light indices, "
                             f"got {args.holdout_lights!r}") from None
    summary = estimate_to_file(args.scan, args.out, method, holdout=holdout, holdout_seed=args.holdout_seed,
                               progress=progress())
    if args.json:
        print(json.dumps(summary))
    else:
        counts = ", ".join(f"{n} {name}" for name, n in summary["status_counts"].items())
        print(f"wrote {args.out}: {summary['coverage']:.1%} of observed points measured, "
              f"{summary['known']:.1%} measured or pooled ({counts})")
        if "materials" in summary:
            print(materials_lines(summary))
        if "holdout" in summary:
            print(holdout_line(summary["holdout"]))
    if summary["warnings"]:  # one line on stderr; the details are in the logging records and --json
        print(f"jaxrefl estimate: warning: {'; '.join(summary['warnings'])}", file=sys.stderr)
    return 0


def materials_lines(summary: dict) -> str:
    """Text for the shared prior's materials (`materials`, `material_lobes` of a summary):
    the chosen K, then one line per material: its joint lobe with standard deviations and the
    spread of its points' lobes (standard deviations; roughness's relative, from ln roughness)."""
    def num(value, scale=1.0, root=False, unit="", digits=2):
        if value is None or not np.isfinite(value):
            return "?"
        return f"{scale * (np.sqrt(value) if root else value):.{digits}g}{unit}"

    k = summary["materials"]
    lines = [f"prior: {k} material{'s' if k != 1 else ''} (BIC)"]
    for m, lobe in enumerate(summary.get("material_lobes", [])):
        lines.append(f"  material {m}: {lobe['points']} points, ps {num(lobe['ps'], digits=3)} +- {num(lobe['std_ps'])}, "
                     f"roughness {num(lobe['roughness'], digits=3)} rad +- {num(lobe['std_ln_roughness'], 100, unit='%')}; "
                     f"spread within it: ps {num(lobe['spread_ps'], root=True)}, "
                     f"roughness {num(lobe['spread_ln_roughness'], 100, True, '%')}"
                     + ("" if lobe.get("identifiable", True) else " (joint lobe not identifiable)"))
    return "\n".join(lines)


def holdout_line(h: dict) -> str:
    """One line of text for a `holdout` block (see `jaxrefl.outputs.holdout.holdout_error`)."""
    lights = h["lights"] if len(h["lights"]) <= 12 else h["lights"][:12] + ["..."]
    model = "direct light" if h["gi"] == "none" else f"direct light + {h['gi']} interreflection"
    head = f"held-out lights {lights} ({model}): "
    if h["rel_rms"] is None:
        return head + f"no error: {h.get('reason')}"
    text = (f"{head}relative RMS error {h['rel_rms']:.2%}, median per sample {h['median_rel']:.2%} "
            f"over {h['samples']} samples")
    truth = h.get("truth")
    if truth is not None:
        text += (f"; the ground truth's {truth['rel_rms']:.2%} (noise floor)" if truth["rel_rms"] is not None
                 else f"; ground truth: {truth.get('reason')}")
    per = [f"{i}: {e:.1%}" if e is not None else f"{i}: -" for i, e in zip(h["lights"], h["per_light_rel_rms"])]
    if len(per) > 1:
        text += "\n  per light: " + ", ".join(per[:24]) + (" ..." if len(per) > 24 else "")
    return text


COMMANDS = {"estimate": (add_estimate, run_estimate)}
