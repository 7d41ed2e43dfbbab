"""The documentation site (`docs/`, `mkdocs.yml`) builds with `mkdocs build --strict`:
no broken link or anchor, no page left out of the navigation, every `::: module` of the
Python reference importable by griffe, and the CLI reference generated from the parser."""

import importlib.util
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NEEDED = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")


def _missing() -> list[str]:
    out = []
    for name in NEEDED:
        try:
            found = importlib.util.find_spec(name) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            out.append(name)
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    missing = _missing()
    if missing:
        pytest.skip(f"documentation tools not installed ({', '.join(missing)}): "
                    'python3 -m pip install -c constraints.txt -e ".[test]"')
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                        str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout[-3000:]}\n{r.stderr[-6000:]}"
    return out


def _text(site, page) -> str:
    html = (site / page / "index.html").read_text()
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", html))


def test_docs_build_strict(site):
    for page in ("concepts", "methods", "formats", "cli", "python", "hardware", "results"):
        assert (site / page / "index.html").exists(), page
    assert (site / "index.html").exists() and (site / "img" / "maps_A.png").exists()


def test_python_reference_comes_from_the_docstrings(site):
    text = _text(site, "reference/api")
    for name in ("jaxrefl.api", "estimate", "Local", "Radiosity", "Photon", "Auto", "Estimate", "Status",
                 "to hold out"):  # from estimate's docstring
        assert name in text, name
    assert "load_scan" in _text(site, "reference/io") and "estimate_local" in _text(site, "reference/local")


def test_cli_reference_is_the_parsers_help(site):
    text = _text(site, "cli")
    commands = re.findall(r"usage: jaxrefl ([a-z0-9-]+)", text)
    for command in ("synth", "info", "select-lights", "estimate", "maps", "relight", "export", "ingest",
                    "capture", "batch"):
        assert command in commands, command
    for option in ("--holdout", "--method", "--photons", "--model-gi", "--scheduler"):
        assert option in text, option
