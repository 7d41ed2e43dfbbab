"""benchmarks/backends.py: the table writers on synthetic cells, the GPU probe, and one real
cell (Method I on a tiny scan, on the CPU) through the driver."""

import json

import pytest

from benchmarks import backends


def _cell(backend, method, first, warm, err, status=None, **extra):
    info = {"pd_median_rel": err, "status": status or {"MEASURED": 5, "POOLED": 7}}
    return {"backend": backend, "method": method, "points": 30_342, "lights": 12, "first": first, "warm": warm,
            "info": info, **extra}


def test_table_puts_the_backends_side_by_side_with_the_warm_ratio():
    cells = [_cell("cuda", "local", 21.6, 2.0, 0.001), {"backend": "cuda", "method": "photon", "error": "killed: > 65 s"},
             _cell("cpu", "local", 12.5, 5.0, 0.0011), _cell("cpu", "photon", 49.8, 20.2, 0.1586)]
    rows = backends.table(cells, ("cuda", "cpu"))
    assert rows[0].count("|") == 11 and "warm cpu / cuda" in rows[0]
    local = next(r for r in rows if r.startswith("| Method I"))
    cols = [c.strip() for c in local.split("|")[1:-1]]
    assert cols[3:] == ["21.6", "2", "0.10 %", "12.5", "5", "0.11 %", "2.50x"]
    photon = next(r for r in rows if r.startswith("| Method III"))
    assert photon.endswith("cuda: killed: > 65 s")
    assert [c.strip() for c in photon.split("|")[1:-1]][-1] == ""  # no ratio without both warm times
    status = backends.status_table(cells)
    assert len(status) == 2 + 3  # the killed cell has no statuses
    assert status[2].split("|")[3:7] == [" 5 ", " 0 ", " 0 ", " 7 "]


def test_cpu_only_machine(tmp_path):
    """Without a GPU JAX sees none; the driver runs the CPU alone and writes both files."""
    if backends.gpu_name() is not None:
        pytest.skip("this machine has a GPU")
    out = tmp_path / "R.md"
    backends.main(["--points", "600", "--lights", "4", "--methods", "local", "--out", str(out),
                   "--scans", str(tmp_path / "scans"), "--per-cell", "300"])
    text = out.read_text()
    assert "GPU: none seen by JAX" in text and "| cpu |" in text
    cell = json.loads((tmp_path / "R.json").read_text())["cells"][0]
    assert cell["backend"] == "cpu" and cell["jax_backend"] == "cpu" and "error" not in cell
    assert 0 <= cell["info"]["pd_median_rel"] < 0.05 and cell["warm"] > 0
