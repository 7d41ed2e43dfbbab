"""The command line, run as a user runs it: `jaxrefl.cli.main` with its arguments, its exit
code, stdout and stderr, in float32. In this process, so that a test does not pay for an
interpreter and JAX start and a recompilation of every solver; the installed console
script (`test_console_script_is_installed`), `python -m jaxrefl.cli` behind a terminal
(`tests/test_api.py`) and the README's walkthrough (`tests/test_readme.py`) run as
subprocesses."""

import contextlib
import io
import json
import os
import shutil
import subprocess
import warnings

import jax
import numpy as np
import pytest

from jaxrefl import cli

#: Warnings a fresh interpreter does not show (Python's default filters)
_HIDDEN_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def jaxrefl(*args, cwd=None):
    """`jaxrefl <args>` in this process: a `CompletedProcess` with the exit code, stdout and
    stderr as text. As the command runs for a user: float32 (the conftest turns float64 on
    for the library's tests), argparse's exits as exit codes, and Python warnings written to
    stderr (so that "one line on stderr" still means one)."""
    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    with warnings.catch_warnings(record=True) as caught, jax.enable_x64(False), \
            contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            if cwd is not None:
                os.chdir(cwd)
            code = cli.main([str(a) for a in args])
        except SystemExit as exc:  # argparse: a usage error (2) or --help (0)
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            if isinstance(exc.code, str):
                print(exc.code, file=err)
        finally:
            os.chdir(here)
    shown = {(str(w.message), w.category, w.filename, w.lineno): w for w in caught
             if not issubclass(w.category, _HIDDEN_WARNINGS)}  # each once, as the "default" action
    for w in shown.values():
        err.write(warnings.formatwarning(w.message, w.category, w.filename, w.lineno))
    return subprocess.CompletedProcess(list(args), code, out.getvalue(), err.getvalue())


def corrupted_bundle(tmp_path, obj, lights, corrupt):
    """A synthetic bundle written, then damaged by `corrupt(dict_of_arrays)`; its path."""
    scan = tmp_path / "s.npz"
    assert jaxrefl("synth", obj, "--out", scan, "--resolution", 20, "--lights", lights).returncode == 0
    data = dict(np.load(scan))
    corrupt(data)
    np.savez(tmp_path / "bad.npz", **data)
    return tmp_path / "bad.npz"


def assert_one_line_error(result, field):
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in result.stderr


def test_synth_render_info(tmp_path):
    scan = tmp_path / "e.npz"
    r = jaxrefl("synth", "E", "--out", scan, "--resolution", 24, "--lights", "4,5", "--gi", "--samples", 4,
                "--noise", 0.01, "--bits", 12, "--json")
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["points"] > 0 and report["lights"] == 2 and report["global_illumination"]
    for what in ("radiance", "pd", "normals", "observations"):
        png = tmp_path / f"{what}.png"
        r = jaxrefl("render", scan, "--what", what, "--light", 1, "--out", png)
        assert r.returncode == 0, r.stderr
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = jaxrefl("render", scan, "--view", "cylindrical", "--width", 64, "--out", tmp_path / "cyl.png")
    assert r.returncode == 0, r.stderr
    r = jaxrefl("info", scan, "--json")
    info = json.loads(r.stdout)
    assert info["lights"] == 2 and info["saturation"] is not None and "true_pd" in info["truth"]


@pytest.mark.parametrize("corrupt, field", [
    (lambda d: d.update(radiance=-d["radiance"] - 1), "radiance"),
    (lambda d: d.update(faces=d["faces"] + 10_000), "faces"),
    (lambda d: d.update(vertices=d["vertices"] * np.nan), "vertices"),
])
def test_bad_input_is_one_line_naming_the_field(tmp_path, corrupt, field):
    bad = corrupted_bundle(tmp_path, "C", "0", corrupt)
    out = tmp_path / "never.png"
    assert_one_line_error(jaxrefl("render", bad, "--out", out), field)
    assert not out.exists()


def test_missing_file_and_bad_arguments(tmp_path):
    r = jaxrefl("info", tmp_path / "nope.npz")
    assert r.returncode == 2 and "nope.npz" in r.stderr and "Traceback" not in r.stderr
    r = jaxrefl("synth", "A", "--out", tmp_path / "x.npz", "--lights", "1,99")
    assert r.returncode == 2 and "lights" in r.stderr
    assert not (tmp_path / "x.npz").exists()


def test_demo_writes_summary_and_pictures(tmp_path):
    out = tmp_path / "demo"
    r = jaxrefl("demo", "--out", out, "--resolution", 16, "--samples", 8)
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    for name in summary["files"]:
        assert (out / name).stat().st_size > 0
    assert any(n.endswith(".png") for n in summary["files"])
    assert summary["object_E_diffuse"]["gi_over_direct_within_2cm_of_fold"] > 1.1
    holdout = summary["holdout_A"]  # Method I relit under the candidate lights the capture did not use
    assert 0 < holdout["truth"]["rel_rms"] < holdout["rel_rms"] < 0.5 and holdout["samples"] > 0
    assert json.loads(r.stdout)["holdout_A"]["rel_rms"] == holdout["rel_rms"]
    for f in summary["furnace"]:
        assert abs(f["z"]) < 5


def test_console_script_is_installed():
    exe = shutil.which("jaxrefl")
    if exe is None:
        pytest.skip("jaxrefl is not installed (pip install -e .): console script not on PATH")
    r = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip()


def test_select_lights_with_and_without_radiance(tmp_path):
    scan = tmp_path / "a.npz"
    assert jaxrefl("synth", "A", "--out", scan, "--resolution", 24).returncode == 0
    data = {k: v for k, v in np.load(scan).items() if k not in ("radiance", "valid")}
    np.savez(tmp_path / "plan.npz", **data)
    results = []
    for path in (scan, tmp_path / "plan.npz"):
        png = tmp_path / "fig8.png"
        r = jaxrefl("select-lights", path, "--json", "--plot", png, "--exact")
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        for key in ("selected", "diffuse_only_count", "diffuse_coverage", "specular_coverage",
                    "specular_coverage_all", "curve"):
            assert key in out
        assert out["specular_coverage"] >= 0.99 * out["specular_coverage_all"]
        assert len(set(out["selected"])) == len(out["selected"]) and 0 < len(out["selected"]) < 60
        assert out["exact"]["count"] <= len(out["selected"])
        assert png.read_bytes()[:4] == b"\x89PNG"
        results.append(out["selected"])
    assert results[0] == results[1]  # noise-free, unsaturated: images change nothing
    r = jaxrefl("select-lights", scan, "--target", "1.5")
    assert r.returncode == 2 and "target" in r.stderr


#: The vase's estimates here, in `test_holdout` and `test_checks` (698 points, 12 lights, 9 with a
#: quarter held out): Method I compiles once for all of them, as do the README's and the demo's
#: Object A (530 points, 10 or 11 lights fitted).
V_LIGHTS = ",".join(map(str, range(0, 60, 5)))


def test_estimate_writes_result_and_summary(tmp_path):
    scan = tmp_path / "v.npz"
    assert jaxrefl("synth", "V", "--out", scan, "--resolution", 16, "--lights", V_LIGHTS,
                   "--noise", 0.01).returncode == 0
    out = tmp_path / "result.npz"
    r = jaxrefl("estimate", scan, "--method", "local", "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["method"] == "local" and summary["model"] == "torrance-sparrow"
    assert 0 < summary["coverage"] <= 1 and {"classify", "fit", "fill"} <= set(summary["seconds"])
    assert summary["errors"]["pd"]["measured"]["median"] < 0.02
    with np.load(out) as z:
        assert {"pd", "ps", "sigma", "status", "std_pd", "std_ps", "std_rough", "meta"} <= set(z.files)
        assert z["status"].dtype == np.int8 and np.all(np.isfinite(z["pd"]))
        assert json.loads(str(z["meta"]))["method"] == "local"
    r = jaxrefl("estimate", scan, "--model", "ward", "--out", tmp_path / "w.npz")
    assert r.returncode == 0, r.stderr
    assert "alpha" in np.load(tmp_path / "w.npz").files


def test_estimate_with_and_without_the_shared_prior(tmp_path):
    """Default (shared prior) and `--no-prior` both run; the summaries count all four statuses,
    the default reports its materials, and the result file keeps their labels."""
    scan = tmp_path / "v.npz"
    assert jaxrefl("synth", "V", "--out", scan, "--resolution", 16, "--lights", V_LIGHTS,
                   "--noise", 0.01).returncode == 0
    summaries = {}
    for flag in ("--no-prior", "--prior"):
        r = jaxrefl("estimate", scan, flag, "--out", tmp_path / "r.npz", "--json")
        assert r.returncode == 0, r.stderr
        summaries[flag] = s = json.loads(r.stdout)
        assert list(s["status_counts"]) == ["measured", "interpolated", "unresolved", "pooled"]
        assert sum(s["status_counts"].values()) == s["points"]
        assert 0 < s["coverage"] <= s["known"] <= 1
    gated, prior = summaries["--no-prior"], summaries["--prior"]
    assert "materials" not in gated and gated["status_counts"]["pooled"] == 0
    assert gated["known"] == gated["coverage"]
    assert 1 <= prior["materials"] <= 6 and len(prior["material_lobes"]) == prior["materials"]
    assert {"ps", "roughness", "std_ps", "points", "identifiable"} <= set(prior["material_lobes"][0])
    assert prior["status_counts"]["interpolated"] == 0 and prior["status_counts"]["pooled"] > 0
    with np.load(tmp_path / "r.npz") as z:
        assert set(np.unique(z["material"])) <= set(range(prior["materials"]))
        assert set(np.unique(z["status"])) <= {0, 2, 3}
    r = jaxrefl("estimate", scan, "--materials", 1, "--out", tmp_path / "one.npz")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert "measured or pooled" in lines[0] and "pooled" in lines[0].split("(")[-1]
    assert lines[1].startswith("prior: 1 material ") and len(lines) == 3 and "material 0:" in lines[2]
    r = jaxrefl("estimate", scan, "--materials", 0, "--out", tmp_path / "never.npz")
    assert_one_line_error(r, "materials")


BAD_ESTIMATE_INPUTS = [
    ("radiance", lambda d: d.update(radiance=np.where(np.arange(d["radiance"].size).reshape(
        d["radiance"].shape) == 7, np.nan, d["radiance"]))),
    ("radiance", lambda d: d.update(radiance=d["radiance"] - 1.0)),
    ("radiance", lambda d: d.update(radiance=d["radiance"][:, :1])),
    ("faces", lambda d: d.update(faces=d["faces"] + len(d["vertices"]))),
    ("normals", lambda d: d.update(normals=np.zeros_like(d["vertices"]))),
    ("light_pos", lambda d: d.update(light_pos=d["light_pos"] * np.inf)),
    ("radiance", lambda d: [d.pop(k) for k in ("radiance", "valid")]),  # planning bundle: no images
]


@pytest.mark.parametrize("field, corrupt", BAD_ESTIMATE_INPUTS)
def test_estimate_bad_input(tmp_path, field, corrupt):
    bad = corrupted_bundle(tmp_path, "V", "24,25", corrupt)
    out = tmp_path / "result.npz"
    assert_one_line_error(jaxrefl("estimate", bad, "--out", out), field)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz", "s.npz"]
