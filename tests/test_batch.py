"""Batch runs (`jaxrefl.batch`, `jaxrefl batch`): one result per scan, resume, failures
reported without stopping the others, a Dask cluster with a worker killed mid-scan."""

import argparse
import csv
import functools
import json
import os
import signal
import threading
import time

import numpy as np
import pytest

import jaxrefl
from data_synth.scans import make_scan
from jaxrefl import batch, cli, compile_cache
from jaxrefl.api import estimate_to_file
from jaxrefl.cli._common import add_estimate_options, method_from_options
from jaxrefl.result import load_result
from jaxrefl.scan.io import atomic_write, folder_lock

NAMES = ("s0", "s1", "s2")


def estimate_options(*argv):
    """The method the `jaxrefl estimate` options choose, exactly as the command line parses them."""
    parser = argparse.ArgumentParser()
    add_estimate_options(parser)
    return method_from_options(parser.parse_args(list(argv)))


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    """Three small Object A scans under different lights (one shape: Method I compiles once)."""
    folder = tmp_path_factory.mktemp("scans")
    for k, name in enumerate(NAMES):
        scan, _ = make_scan("A", resolution=16, lights=[3 + k, 17 + k, 29 + k, 42 + k])
        jaxrefl.save_scan(folder / f"{name}.npz", scan)
    return folder


def outputs(folder):
    return sorted(f for f in os.listdir(folder) if not f.startswith(".lock"))


def assert_one_whole_result_per_scan(out, scan_dir, names=NAMES):
    files = outputs(out)
    assert not [f for f in os.listdir(out) if f.startswith(".tmp-")]
    for name in names:
        assert files.count(f"{name}_result.npz") == 1 and files.count(f"{name}_result.json") == 1
        est = load_result(out / f"{name}_result.npz")
        n = jaxrefl.load_scan(scan_dir / f"{name}.npz").n_points
        assert est.pd.shape == (n, 3) and est.roughness.shape == (n,)
        for a in (est.pd, est.ps, est.roughness):
            assert np.isfinite(a).all()
        assert batch.result_loads(out / f"{name}_result.npz")


def statuses(out):
    with open(out / "summary.csv", newline="") as fh:
        return {row["name"]: row["status"] for row in csv.DictReader(fh)}


def test_local_batch_writes_one_result_per_scan(scan_dir, tmp_path):
    out = tmp_path / "out"
    records = batch.run_batch(scan_dir, out, estimate_options())
    assert [r["name"] for r in records] == list(NAMES) and {r["status"] for r in records} == {"done"}
    assert_one_whole_result_per_scan(out, scan_dir)
    assert outputs(out) == sorted([f"{n}_result.{e}" for n in NAMES for e in ("npz", "json")]
                                  + ["summary.csv", "summary.md"])
    summary = json.loads((out / "s0_result.json").read_text())
    assert summary["status"] == "done" and summary["method"] == "local" and 0 < summary["coverage"] <= 1
    assert summary["coverage"] <= summary["known"] <= 1 and "materials" in summary  # the shared prior
    with open(out / "summary.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["known"]) == summary["known"]
    assert 0 <= summary["errors"]["pd"]["all"]["median"] < 0.1  # the bundle holds the truth
    assert statuses(out) == dict.fromkeys(NAMES, "done")
    assert "3 scans: 3 done, 0 skipped, 0 failed" in (out / "summary.md").read_text()
    # The same code path as `jaxrefl estimate`: the same numbers.
    direct = estimate_to_file(str(scan_dir / "s1.npz"), str(tmp_path / "direct.npz"), estimate_options())
    assert direct["status_counts"] == records[1]["status_counts"]
    np.testing.assert_array_equal(load_result(tmp_path / "direct.npz").pd, load_result(out / "s1_result.npz").pd)


def test_resume_recomputes_only_missing_and_damaged_results(scan_dir, tmp_path):
    out = tmp_path / "out"
    batch.run_batch(scan_dir, out, estimate_options())
    first = {n: os.stat(out / f"{n}_result.npz").st_mtime_ns for n in NAMES}
    os.unlink(out / "s1_result.npz")
    damaged = (out / "s2_result.npz").read_bytes()
    (out / "s2_result.npz").write_bytes(damaged[: len(damaged) // 2])  # a partial write
    os.unlink(out / "s0_result.json")  # finished, but its summary lost: rebuilt, not recomputed
    (out / ".tmp-x1y2z3s1_result.npz").write_bytes(b"PK\x03\x04 half")  # left by a killed writer
    assert not batch.result_loads(out / "s2_result.npz")
    time.sleep(0.01)

    records = {r["name"]: r for r in batch.run_batch(scan_dir, out, estimate_options())}
    assert {n: r["status"] for n, r in records.items()} == {"s0": "skipped", "s1": "done", "s2": "done"}
    assert statuses(out) == {"s0": "skipped", "s1": "done", "s2": "done"}
    assert os.stat(out / "s0_result.npz").st_mtime_ns == first["s0"]
    assert os.stat(out / "s2_result.npz").st_mtime_ns > first["s2"]
    assert_one_whole_result_per_scan(out, scan_dir)
    rebuilt = json.loads((out / "s0_result.json").read_text())
    assert rebuilt["summary_rebuilt"] and rebuilt["status"] == "done" and "pd" in rebuilt["errors"]
    assert records["s0"]["coverage"] == pytest.approx(records["s1"]["coverage"], abs=0.2)

    second = {n: os.stat(out / f"{n}_result.npz").st_mtime_ns for n in NAMES}
    again = batch.run_batch(scan_dir, out, estimate_options())
    assert {r["status"] for r in again} == {"skipped"}
    assert {n: os.stat(out / f"{n}_result.npz").st_mtime_ns for n in NAMES} == second


def test_failing_scans_are_reported_and_the_others_finish(scan_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(compile_cache, "enable", lambda: None)  # keep this process's JAX config
    (tmp_path / "garbage.npz").write_text("not a scan bundle")
    listing = tmp_path / "scans.txt"
    listing.write_text(f"# two good scans, two bad\n{scan_dir / 's0.npz'}\n\ngarbage.npz\n"
                       f"missing.npz\n  {os.path.relpath(scan_dir / 's2.npz', tmp_path)}  \n")
    out = tmp_path / "out"
    rc = cli.main(["batch", str(listing), "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 1
    failures = captured.err.strip().splitlines()
    assert len(failures) == 2 and "Traceback" not in captured.err
    assert failures[0].startswith("jaxrefl batch: failed: garbage (") and "not a readable .npz" in failures[0]
    assert failures[1].startswith("jaxrefl batch: failed: missing (") and "missing.npz" in failures[1]
    assert statuses(out) == {"s0": "done", "garbage": "failed", "missing": "failed", "s2": "done"}
    assert_one_whole_result_per_scan(out, scan_dir, names=("s0", "s2"))
    assert not (out / "garbage_result.npz").exists()
    assert json.loads((out / "garbage_result.json").read_text())["status"] == "failed"
    assert "| garbage | failed |" in captured.out and "4 scans: 2 done, 0 skipped, 2 failed" in captured.out

    # Bad batches end before anything runs: exit code 2, one line.
    listing.write_text(f"{scan_dir / 's0.npz'}\n{scan_dir / 's0.npz'}\n")
    assert cli.main(["batch", str(listing), "--out", str(tmp_path / "dup")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two bundles named 's0'" in err[0]
    with folder_lock(str(out), "held by the test"):
        with pytest.raises(ValueError, match="in use by another batch"):
            batch.run_batch(scan_dir, out, estimate_options())


# --- Dask -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with Client(cluster) as c:
            yield c


def hang_once(scan, out, method, hang_name, hang_marker):
    """The real estimate, except the first attempt at `hang_name`: it starts the atomic write
    of the result, writes half a file and blocks until its process is killed."""
    if os.path.basename(scan) == hang_name and not os.path.exists(hang_marker):
        def write(fh):
            fh.write(b"PK\x03\x04 half a result")
            fh.flush()
            atomic_write(hang_marker, lambda m: m.write(str(os.getpid()).encode()))
            time.sleep(120)

        atomic_write(out, write)
    return estimate_to_file(scan, out, method)


def fail_once(scan, out, method, marker_dir):
    """The real estimate, except that the first attempt at every scan raises."""
    marker = os.path.join(marker_dir, os.path.basename(scan))
    if not os.path.exists(marker):
        atomic_write(marker, lambda fh: fh.write(b"1"))
        raise RuntimeError("transient failure")
    return estimate_to_file(scan, out, method)


def test_dask_batch_and_concurrent_attempts_leave_one_result(client, scan_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(compile_cache, "enable", lambda: None)
    out = tmp_path / "out"
    assert cli.main(["batch", str(scan_dir), "--out", str(out), "--scheduler", client.scheduler.address]) == 0
    assert "3 scans: 3 done, 0 skipped, 0 failed" in capsys.readouterr().out
    assert_one_whole_result_per_scan(out, scan_dir)
    assert statuses(out) == dict.fromkeys(NAMES, "done")
    assert json.loads((out / "s2_result.json").read_text())["method"] == "local"

    # Two attempts at one scan at the same time (a straggler and its re-run): one whole result.
    job = batch.plan_jobs([scan_dir / "s1.npz"], tmp_path / "twice")[0]
    workers = list(client.scheduler_info()["workers"])
    futures = [client.submit(batch._remote_job, job, estimate_options(), pure=False, workers=[w]) for w in workers]
    assert [r["status"] for r in client.gather(futures)] == ["done", "done"]
    assert outputs(tmp_path / "twice") == ["s1_result.json", "s1_result.npz"]
    assert_one_whole_result_per_scan(tmp_path / "twice", scan_dir, names=("s1",))


def test_dask_worker_killed_mid_scan(client, scan_dir, tmp_path):
    out = tmp_path / "out"
    marker = str(tmp_path / "hung.pid")
    killed = []

    def kill_when_hung():
        deadline = time.monotonic() + 100
        while not os.path.exists(marker) and time.monotonic() < deadline:
            time.sleep(0.05)
        pid = int(open(marker).read())
        mid_write = any(f.startswith(".tmp-") for f in os.listdir(out))
        os.kill(pid, signal.SIGKILL)
        killed.append((pid, mid_write))

    watcher = threading.Thread(target=kill_when_hung, daemon=True)
    watcher.start()
    records = batch.run_batch(scan_dir, out, estimate_options(), client=client,
                              estimate=functools.partial(hang_once, hang_name="s1.npz", hang_marker=marker))
    watcher.join(timeout=5)
    (pid, mid_write), = killed
    assert pid != os.getpid() and mid_write  # a worker process, killed with half a result on disk
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    assert {r["status"] for r in records} == {"done"}, records
    assert_one_whole_result_per_scan(out, scan_dir)


@pytest.mark.parametrize("retries, status", [(1, "done"), (0, "failed")])
def test_dask_retries_a_scan_that_raised(client, scan_dir, tmp_path, retries, status):
    records = batch.run_batch([scan_dir / "s0.npz"], tmp_path / "out", estimate_options(), client=client,
                              retries=retries, estimate=functools.partial(fail_once, marker_dir=str(tmp_path)))
    assert [r["status"] for r in records] == [status]
    if status == "failed":
        assert records[0]["error"] == "RuntimeError: transient failure"
        assert outputs(tmp_path / "out") == ["s0_result.json", "summary.csv", "summary.md"]
    else:
        assert_one_whole_result_per_scan(tmp_path / "out", scan_dir, names=("s0",))
