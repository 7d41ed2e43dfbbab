"""The notebooks in notebooks/ run top to bottom without error and draw figures.

Each notebook is executed by a real Jupyter kernel (nbclient + ipykernel, kernel
`python3` of this interpreter) in a temporary working directory, so whatever it
writes stays out of the source tree. The kernel imports jaxrefl and data_synth
from this checkout whether or not the package is installed.
"""

import os
from pathlib import Path

import nbclient
import nbformat
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
TIMEOUT_S = 300  # per cell; each notebook takes about a minute on two cores


def test_notebooks_exist():
    names = {p.name for p in NOTEBOOKS}
    assert {"01_quick_start.ipynb", "02_light_selection.ipynb",
            "03_interreflections_object_E.ipynb", "04_photons_iterations.ipynb", "05_relighting.ipynb"} <= names, names


def test_figure_writers_leave_the_backend_alone(tmp_path):
    """jaxrefl.outputs.render's figure writers draw off pyplot, so a notebook's inline backend stays
    selected after them (they used to switch matplotlib to Agg)."""
    import matplotlib

    from jaxrefl.outputs import render

    before = matplotlib.get_backend()
    matplotlib.use("svg")
    try:
        image = np.random.default_rng(0).random((12, 16, 3))
        render.comparison_figure(str(tmp_path / "cmp.png"), image, 1.1 * image)
        assert matplotlib.get_backend() == "svg"
        assert (tmp_path / "cmp.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        matplotlib.use(before)


#: Notebooks whose run takes a minute or more on two cores (Methods II and III on Object E,
#: Method III's iterations): the slow profile.
SLOW = {"03_interreflections_object_E", "04_photons_iterations"}


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.slow) if p.stem in SLOW else p
                                  for p in NOTEBOOKS], ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_and_draws(path, tmp_path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))
    client = nbclient.NotebookClient(nb, timeout=TIMEOUT_S, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()  # raises CellExecutionError, naming the cell, on the first failing cell

    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if o.output_type in ("display_data", "execute_result")
              and "image/png" in o.get("data", {})]
    assert images, f"{path.name} drew no figure"
    # every code cell ran, in order
    counts = [cell.execution_count for cell in nb.cells if cell.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1))
