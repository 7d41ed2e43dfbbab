"""The `jaxrefl` command line: dense surface reflectance of a scanned object by inverse rendering.

A scan bundle (`.npz`: mesh, normals, camera, lights, linear images; `docs/formats.md`)
goes in, a result file (per-point pd, ps, roughness, standard deviations, status) comes
out. Commands: `synth` and `render` (synthetic scans), `info`, `select-lights`, `capture`
and `ingest` (your own rig and photographs), `estimate` (Methods I, II, III and auto,
optionally with held-out lights), `batch`, `maps`, `relight`, `export` (PLY), `fold`,
`figure18`, `table1` and `demo` (the paper's experiments); one module of `jaxrefl.cli` per
command (`paper` holds `fold`, `figure18` and `table1`). Bad input ends with one line
on stderr naming the field, exit code 2, and no output file; so does an output path that
names one of the command's inputs or an existing path that is not a regular file.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import sys

from . import batch, capture, demo, estimate, export, info, ingest, maps, paper, relight, render, select_lights, synth

__all__ = ["main"]

#: The commands' modules, in the order `--help` lists them; each has `COMMANDS`:
#: name -> (add its sub-parser, run it).
_MODULES = (synth, render, info, select_lights, estimate, paper, demo, capture, ingest, relight, maps, export, batch)

#: Options naming files a command writes, and commands whose --out is a folder.
_FILE_OUTPUTS = {"synth": ("out",), "render": ("out",), "select-lights": ("plot",), "estimate": ("out",),
                 "fold": ("out",), "ingest": ("out",), "relight": ("out", "compare"), "maps": ("out",),
                 "export": ("out",)}
_FOLDER_OUTPUTS = ("demo", "table1", "figure18", "capture", "batch")


def _check_outputs(args) -> None:
    """Before any work: refuse an output that is an input of the command, another output,
    or an existing path that is not a regular file (a folder for folder outputs)."""
    from ..scan.io import check_output_path

    inputs = [getattr(args, k, None) for k in ("scan", "result", "folder", "plan", "source")]
    if getattr(args, "reference", None) not in (None, "truth"):
        inputs.append(args.reference)
    inputs += [item.rpartition("=")[2] for item in getattr(args, "results", None) or ()]
    if args.command in _FOLDER_OUTPUTS:
        check_output_path(args.out, "out", inputs, folder=True)
        return
    seen = {}
    for name in _FILE_OUTPUTS.get(args.command, ()):
        path = getattr(args, name, None)
        if path is None:
            continue
        check_output_path(path, name, inputs)
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{name}: {path} is also --{seen[key]}")
        seen[key] = name


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaxrefl", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    # every command's --help shows the defaults
    sub = parser.add_subparsers(dest="command", parser_class=functools.partial(
        argparse.ArgumentParser, formatter_class=argparse.ArgumentDefaultsHelpFormatter))
    commands = {}
    for module in _MODULES:
        for name, (add, run) in module.COMMANDS.items():
            add(sub)
            commands[name] = run
    args = parser.parse_args(argv)
    from ..compile_cache import enable as enable_compile_cache

    enable_compile_cache()  # later runs load the compiled solvers from disk
    if args.version:
        from .._version import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2
    # jaxrefl's logged warnings reach stderr as each command's own one-line summary
    quiet = logging.getLogger("jaxrefl")
    if not any(isinstance(h, logging.NullHandler) for h in quiet.handlers):
        quiet.addHandler(logging.NullHandler())
    try:
        _check_outputs(args)
        return commands[args.command](args)
    except (ValueError, FileNotFoundError, IsADirectoryError) as exc:
        msg = str(exc) if not isinstance(exc, OSError) else f"{exc.filename}: {exc.strerror}"
        print(f"jaxrefl {args.command}: error: {msg}", file=sys.stderr)
        return 2
