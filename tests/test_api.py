"""The public API (`jaxrefl.estimate`, method specs, `Estimate`'s conveniences, `Status`),
the README's Python example, and the package's import structure."""

import ast
import dataclasses
import json
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

import jaxrefl
from data_synth.scans import Sensor, make_scan
from jaxrefl import Status
from jaxrefl.methods.local import STATUS_NAMES

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: 12 of the rack's 60: small, and every point still seen. Twelve observations (and nine with
#: a quarter held out) as the vase of `test_checks`: Method I compiles once for both files.
LIGHTS = list(range(0, 60, 5))


@pytest.fixture(scope="module")
def scan_a():
    """Object A, the paper's scanner, 12 lights, a coarse mesh; noisy 12-bit sensor."""
    return make_scan("A", resolution=16, lights=LIGHTS, sensor=Sensor(noise=0.01, bits=12), seed=0)[0]


@pytest.fixture(scope="module")
def est_a(scan_a):
    return jaxrefl.estimate(scan_a, method=jaxrefl.Local(), progress=False)


def test_public_names():
    for name in ("estimate", "Local", "Radiosity", "Photon", "Auto", "Status", "Estimate", "load_scan",
                 "save_scan", "load_result", "save_result"):
        assert name in jaxrefl.__all__ and hasattr(jaxrefl, name)
    assert [s.name.lower() for s in Status] == list(STATUS_NAMES)
    assert [int(s) for s in Status] == [0, 1, 2, 3]
    assert jaxrefl.methods.local.POOLED is Status.POOLED
    # the specs are the option classes under short names: every option, no copy of them
    assert isinstance(jaxrefl.Local(model="ward"), jaxrefl.methods.local.LocalOptions)
    assert jaxrefl.Photon().local.model == "ward"
    with pytest.raises(ValueError, match="model"):
        jaxrefl.Local(model="phong")
    with pytest.raises(TypeError, match="method"):
        jaxrefl.estimate(None, method="local")


def test_local_through_the_api(scan_a, est_a):
    est = est_a
    assert isinstance(est, jaxrefl.Estimate) and est.meta["method"] == "local"
    assert est.pd.shape == (scan_a.n_points, 3) and np.all(np.isfinite(est.pd))
    assert set(np.unique(est.status).tolist()) <= set(Status)
    assert all(isinstance(Status(int(c)), Status) for c in np.unique(est.status))
    counts = est.status_counts()
    assert list(counts) == list(Status) and sum(counts.values()) == scan_a.n_points
    assert counts[Status.MEASURED] + counts[Status.POOLED] > 0.5 * scan_a.n_points
    assert {"classify", "fit", "fill"} <= set(est.seconds)
    with pytest.raises(dataclasses.FrozenInstanceError):
        est.pd = est.pd * 2


def test_path_and_radiosity(scan_a, tmp_path):
    jaxrefl.save_scan(tmp_path / "a.npz", scan_a)
    est = jaxrefl.estimate(str(tmp_path / "a.npz"), method=jaxrefl.Radiosity(rays=32, outer=1), progress=False)
    assert est.meta["method"] == "radiosity" and "load" in est.seconds
    assert set(np.unique(est.status).tolist()) <= set(Status)


def test_holdout_reports_the_error(scan_a):
    est = jaxrefl.estimate(scan_a, method=jaxrefl.Local(), holdout=0.25, progress=False)
    h = est.meta["holdout"]
    assert len(h["lights"]) == 3 and h["fraction"] == 0.25 and h["seed"] == 0
    assert 0 < h["rel_rms"] < 0.2 and h["samples"] > 0
    assert "holdout" in est.seconds
    same = jaxrefl.estimate(scan_a, method=jaxrefl.Local(), holdout=h["lights"], progress=False)
    assert same.meta["holdout"]["lights"] == h["lights"]
    assert same.meta["holdout"]["rel_rms"] == pytest.approx(h["rel_rms"], rel=1e-9)
    with pytest.raises(ValueError, match="holdout"):
        jaxrefl.estimate(scan_a, holdout=1.5, progress=False)


def test_progress_bar_on_request(scan_a, est_a, capsys):
    jaxrefl.estimate(scan_a, method=jaxrefl.Local(), progress=True)
    assert "jaxrefl" in capsys.readouterr().err


def test_save_figure_relight(scan_a, est_a, tmp_path):
    from matplotlib.figure import Figure

    est_a.save(tmp_path / "r.npz")
    back = jaxrefl.load_result(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.status, est_a.status)
    np.testing.assert_allclose(back.pd, est_a.pd)
    for fig in (est_a.figure(scan_a, width=96), est_a.figure()):
        assert isinstance(fig, Figure) and len(fig.axes) >= 4
    assert not list(tmp_path.glob("*.png"))  # a figure, nothing written
    image = est_a.relight(scan_a, [0.3, 0.4, 0.5], width=40, height=30)
    assert image.shape == (30, 40, 3) and np.isfinite(image).any() and np.nanmin(image) >= 0


def test_ply_round_trip_through_trimesh(scan_a, est_a, tmp_path):
    import trimesh

    path = tmp_path / "a.ply"
    est_a.to_ply(path, scan_a)
    mesh = jaxrefl.outputs.export.load_ply(path)
    attrs = mesh.vertex_attributes
    np.testing.assert_allclose(np.stack([attrs[f"pd_{c}"] for c in "rgb"], -1), est_a.pd, rtol=1e-6)
    np.testing.assert_allclose(attrs["ps"], est_a.ps, rtol=1e-6)
    np.testing.assert_allclose(attrs["sigma"], est_a.roughness, rtol=1e-6)
    np.testing.assert_array_equal(attrs["status"], est_a.status)
    np.testing.assert_array_equal(attrs["std_ps"], est_a.std_ps.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, scan_a.faces)
    raw = trimesh.load(path, process=False).metadata["_ply_raw"]["vertex"]["data"]  # trimesh alone
    np.testing.assert_array_equal(raw["status"], est_a.status)


def _readme_block(heading="## Python") -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split(f"\n{heading}\n", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_python_example_runs(scan_a, tmp_path, monkeypatch, capsys):
    code = _readme_block()
    assert "jaxrefl.estimate(" in code and len(code.strip().splitlines()) <= 12
    jaxrefl.save_scan(tmp_path / "A.npz", scan_a)  # what `jaxrefl synth A --out A.npz` writes, smaller
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {"__name__": "readme"})
    for name in ("A_result.npz", "A.ply", "A_maps.png"):
        assert (tmp_path / name).stat().st_size > 0
    out = capsys.readouterr().out
    assert "MEASURED" in out


def test_import_does_not_load_data_synth():
    code = "import sys, jaxrefl; print(json.dumps(sorted(m for m in sys.modules if m.startswith('data_synth'))))"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, "-c", "import json; " + code], capture_output=True, text=True, env=env,
                         cwd=ROOT, check=True).stdout
    assert json.loads(out) == []


def _module_imports(path: pathlib.Path, module: str, modules: set, lazy: bool) -> set:
    """Intra-package modules `module` imports at module level (with `lazy`, also inside functions)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    stack = list(ast.parse(path.read_text()).body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.If, ast.Try, ast.With)) or (lazy and isinstance(
                node, (ast.FunctionDef, ast.ClassDef, ast.For, ast.While))):
            stack.extend(ast.iter_child_nodes(node))
        elif isinstance(node, ast.ExceptHandler):
            stack.extend(node.body)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            out.update(f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names)
    return {m for m in out if m in modules and m != module}


def _cycles(graph: dict) -> list:
    state, cycles = {}, []

    def visit(m, trail):
        state[m] = "open"
        for d in sorted(graph[m]):
            if state.get(d) == "open":
                cycles.append(trail[trail.index(d):] + [d])
            elif d not in state:
                visit(d, trail + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    return cycles


def _import_graph(lazy: bool) -> dict:
    files = {}
    for path in (ROOT / "jaxrefl").rglob("*.py"):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return {m: _module_imports(p, m, set(files), lazy) for m, p in files.items()}


def test_no_import_cycles():
    """None at import time; and with the imports inside functions too, only `Estimate`'s
    conveniences (`.relight()`, `.to_ply()`, `.figure()`) reach up from `jaxrefl.result` to the
    outputs that use it."""
    graph = _import_graph(lazy=False)
    assert graph["jaxrefl.methods.local"] and "jaxrefl.api" in graph["jaxrefl"]  # the walk sees the imports
    assert _cycles(graph) == []
    graph = _import_graph(lazy=True)
    assert {"jaxrefl.outputs.relight", "jaxrefl.batch"} <= graph["jaxrefl.cli.batch"] | graph["jaxrefl.cli.relight"]
    graph["jaxrefl.result"] = {m for m in graph["jaxrefl.result"] if not m.startswith("jaxrefl.outputs.")}
    assert _cycles(graph) == []


def test_layers_import_downward():
    """The sub-packages are layers: geometry and scan I/O below the reflectance models, those
    below the methods, the methods below the outputs; hardware, the paper's experiments and
    the command line on top. No module imports (at import time) from a layer above its own."""
    order = ["status", "_version", "compile_cache", "srgb", "geometry", "scan", "reflectance", "result", "methods",
             "outputs", "api", "batch", "capture", "paper", "cli"]
    graph = _import_graph(lazy=False)

    def layer(m):
        return order.index(m.split(".")[1]) if m != "jaxrefl" else len(order)

    upward = sorted((m, d) for m, deps in graph.items() for d in deps if layer(d) > layer(m))
    assert upward == []


def test_cli_estimate_in_a_terminal_shows_progress(tmp_path):
    """`jaxrefl estimate` with stderr on a terminal draws the stage bar (tqdm); piped (every
    other CLI test) it prints none. A fresh process: the scan and the estimate are the README
    walkthrough's (`tests/test_readme.py`), whose command then loads the compiled programs
    from the session's cache, as a user's second run does."""
    import fcntl
    import pty
    import struct
    import termios
    import threading

    from .test_cli import jaxrefl

    lights = ",".join(map(str, range(0, 60, 4)))
    assert jaxrefl("synth", "A", "--resolution", 16, "--lights", lights, "--noise", 0.01, "--bits", 12,
                   "--out", tmp_path / "a.npz").returncode == 0
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    args = [sys.executable, "-m", "jaxrefl.cli", "estimate", str(tmp_path / "a.npz"), "--holdout", "0.25"]
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a new pty is 0 columns wide
    chunks = []

    def read():  # drain the terminal while the command runs (a full one would block it)
        while True:
            try:
                data = os.read(leader, 65536)
            except OSError:  # the command closed the terminal
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    run = subprocess.run(args + ["--out", str(tmp_path / "r1.npz")], stderr=follower, stdout=subprocess.DEVNULL,
                         env=env, timeout=600)
    os.close(follower)
    reader.join(timeout=10)
    os.close(leader)
    shown = b"".join(chunks).decode(errors="replace")
    assert run.returncode == 0 and "jaxrefl: local" in shown, shown[-2000:]
