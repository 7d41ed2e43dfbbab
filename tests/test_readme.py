"""The README's command-line walkthrough runs top to bottom, and its links lead somewhere.

The walkthrough is the first ```bash block under `## Command line`. Every line is run
with bash, in order, in an empty temporary folder, as a user pastes them: `jaxrefl` is
this checkout's command line (a shim that runs `python -m jaxrefl.cli` with this
interpreter), and jaxrefl's caches are the test session's (`JAXREFL_CACHE`, set by the conftest),
never the user's home.
"""

import os
import pathlib
import re
import stat
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
HEADING = "## Command line"
LINE_TIMEOUT_S = 300


def _section(text: str, heading: str) -> str:
    parts = re.split(rf"^{re.escape(heading)}[ \t]*$", text, maxsplit=1, flags=re.M)
    assert len(parts) == 2, f"README.md has no {heading!r} section"
    return re.split(r"^## ", parts[1], maxsplit=1, flags=re.M)[0]


def walkthrough_lines(text: str) -> list[str]:
    """The commands of the section's first bash block: continuations joined, comment-only
    and blank lines dropped."""
    block = re.search(r"^```bash\n(.*?)^```", _section(text, HEADING), re.S | re.M)
    assert block, f"no ```bash block under {HEADING!r}"
    lines, pending = [], ""
    for raw in block.group(1).splitlines():
        line = pending + raw
        if line.rstrip().endswith("\\"):
            pending = line.rstrip()[:-1] + " "
            continue
        pending = ""
        if line.strip() and not line.lstrip().startswith("#"):
            lines.append(line.strip())
    assert not pending, "the block ends in a continuation line"
    return lines


def _shim(folder: pathlib.Path) -> pathlib.Path:
    folder.mkdir()
    exe = folder / "jaxrefl"
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m jaxrefl.cli "$@"\n')
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return folder


def test_walkthrough_is_self_contained():
    lines = walkthrough_lines(README.read_text())
    assert len(lines) >= 6
    assert all(line.startswith("jaxrefl ") for line in lines), lines
    commands = [line.split()[1] for line in lines]
    for needed in ("synth", "info", "select-lights", "estimate", "maps", "relight", "export"):
        assert needed in commands, f"the walkthrough lacks `jaxrefl {needed}`"
    assert any("--holdout" in line for line in lines if line.split()[1] == "estimate")
    for line in lines:  # outputs go to the folder it runs in, never into the source tree
        assert "benchmarks/" not in line and " /" not in line and ".." not in line, line


def test_walkthrough_runs(tmp_path):
    lines = walkthrough_lines(README.read_text())
    work = tmp_path / "work"
    work.mkdir()
    cache = os.environ.get("JAXREFL_CACHE") or str(tmp_path / "cache")
    env = {**os.environ,
           "PATH": f"{_shim(tmp_path / 'bin')}{os.pathsep}{os.environ.get('PATH', '')}",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
           "JAXREFL_CACHE": cache, "MPLBACKEND": "Agg"}
    for line in lines:
        r = subprocess.run(["bash", "-c", line], cwd=work, env=env, capture_output=True, text=True,
                           timeout=LINE_TIMEOUT_S)
        assert r.returncode == 0, f"`{line}` exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    # every file a line names after --out (or --plot, --compare) exists and is not empty
    named = re.findall(r"--(?:out|plot|compare)[ =](\S+)", "\n".join(lines))
    assert named
    for name in named:
        assert (work / name).stat().st_size > 0, name


def test_readme_links_resolve():
    text = README.read_text()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if "://" not in t and not t.startswith("mailto:")]
    assert local, "the README links no documentation"
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, f"README.md links to missing files: {missing}"


@pytest.mark.parametrize("forbidden", [r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", r"\bseeds? \d"])
def test_readme_holds_no_measurement_history(forbidden):
    """Commit hashes and seeds of benchmark runs belong in benchmarks/RESULTS_*.md."""
    assert not re.search(forbidden, README.read_text())
