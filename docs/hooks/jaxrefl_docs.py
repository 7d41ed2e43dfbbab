"""MkDocs hooks for jaxrefl's documentation.

`<!-- jaxrefl-help: COMMAND -->` in a page becomes the `jaxrefl COMMAND --help` text,
taken from the command line's own parser (an empty COMMAND: `jaxrefl --help`), so the CLI
reference cannot drift from the code.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MARKER = re.compile(r"^<!-- jaxrefl-help: ?([a-z0-9-]*) -->$", re.M)


def _help(command: str) -> str:
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    from jaxrefl import cli

    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps at the terminal width
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            try:
                cli.main([command, "--help"] if command else ["--help"])
            except SystemExit:
                pass
    finally:
        if saved is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = saved
    text = out.getvalue()
    if not text.startswith("usage: jaxrefl"):
        raise RuntimeError(f"jaxrefl {command} --help printed no usage: {text[:200]!r}")
    return text


def on_page_markdown(markdown, page, config, files, **kwargs):
    return MARKER.sub(lambda m: "```text\n" + _help(m.group(1)).rstrip() + "\n```", markdown)
