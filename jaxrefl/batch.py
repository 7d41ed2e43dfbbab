"""Batch runs: `jaxrefl estimate` on many scan bundles, resumable, here or on a Dask cluster.

For every scan bundle `NAME.npz` the output folder gets `NAME_result.npz` (the
result file of `jaxrefl.result`) and `NAME_result.json` (the estimate's JSON
summary plus `name`, `scan`, `status`, `wall_seconds`, or the reason it
failed); the batch ends by writing `summary.csv` and `summary.md`. Every file is
written to a temporary name beside it and renamed into place, so a reader (or
a resumed batch) sees a whole file or none, and two attempts at one scan leave
exactly one result (the last rename wins).

A scan whose result file exists and loads (finite values, consistent shapes)
is skipped; one whose result is missing or damaged is (re)computed and the
damaged file removed first. `.lock` keeps a second batch out of the folder
while one runs; temporaries left by a killed process are removed at the start
and at the end of a batch.

Each scan runs through `jaxrefl.api.estimate_to_file`, the code path of
`jaxrefl estimate`, with one method (`jaxrefl.Local()`, `Radiosity()`, `Photon()` or `Auto()`).
"""

from __future__ import annotations

import csv
import functools
import io
import json
import os
import time
import zipfile
from dataclasses import dataclass

import numpy as np

from .api import estimate_summary, estimate_to_file
from .scan.io import atomic_write, folder_lock

__all__ = ["Job", "find_scans", "plan_jobs", "result_loads", "run_job", "run_batch", "summary_table"]

RESULT_SUFFIX = "_result.npz"
SUMMARY_SUFFIX = "_result.json"
# Errors of the input itself: running the scan again would fail the same way.
INPUT_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError,
                zipfile.BadZipFile)
CSV_COLUMNS = ("name", "status", "seconds", "coverage", "known", "points", "pd_err_median", "pd_err_p90",
               "ps_err_median", "ps_err_p90", "roughness_err_median", "roughness_err_p90", "scan", "error")


@dataclass(frozen=True)
class Job:
    """One scan of a batch: its name and absolute paths of the bundle and its two outputs."""

    name: str
    scan: str
    result: str
    summary: str


def find_scans(source) -> list[str]:
    """Scan bundle paths named by `source`: the `*.npz` files of a folder (sorted by
    name, hidden files left out), or a text file listing one path per line (blank lines and `#` comments
    skipped; relative paths are relative to the list's folder). Absolute paths."""
    source = os.path.abspath(os.fspath(source))
    if os.path.isdir(source):
        return [os.path.join(source, f) for f in sorted(os.listdir(source))
                if f.endswith(".npz") and not f.startswith(".") and os.path.isfile(os.path.join(source, f))]
    if not os.path.exists(source):
        raise FileNotFoundError(2, "No such file or directory", source)
    if zipfile.is_zipfile(source):
        raise ValueError(f"source: {source} is a scan bundle; give a folder of bundles or a text file listing them")
    try:
        with open(source, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"source: {source} is neither a folder nor a text file of bundle paths") from None
    folder = os.path.dirname(source)
    scans = []
    for line in lines:
        line = line.strip()
        if line and not line.startswith("#"):
            scans.append(os.path.normpath(os.path.join(folder, os.path.expanduser(line))))
    return scans


def plan_jobs(scans, outdir) -> list[Job]:
    """One `Job` per scan path, outputs named after the bundle's file name in `outdir`.
    Raises ValueError for an empty list or two bundles with the same name."""
    outdir = os.path.abspath(os.fspath(outdir))
    if not scans:
        raise ValueError("source: no scan bundles (*.npz) found")
    jobs, seen = [], {}
    for scan in scans:
        scan = os.path.abspath(os.fspath(scan))
        name = os.path.splitext(os.path.basename(scan))[0]
        if name in seen:
            raise ValueError(f"source: two bundles named {name!r} ({seen[name]}, {scan}); their results would collide")
        seen[name] = scan
        jobs.append(Job(name, scan, os.path.join(outdir, name + RESULT_SUFFIX),
                        os.path.join(outdir, name + SUMMARY_SUFFIX)))
    return jobs


def result_loads(path) -> bool:
    """Whether `path` is a whole, readable result file: it loads, its arrays agree in
    length and hold no NaN."""
    from .result import load_result

    if not os.path.isfile(path):
        return False
    try:
        est = load_result(path)
    except Exception:  # truncated zip, bad CRC, missing key, unknown version: all mean "not done"
        return False
    n = len(est.status)
    arrays = (est.pd, est.ps, est.roughness, est.std_pd, est.std_ps, est.std_roughness,
              est.specular_identifiable, est.pd_measured)
    return (all(len(a) == n for a in arrays) and np.isfinite(est.pd).all() and np.isfinite(est.ps).all()
            and np.isfinite(est.roughness).all())


def _reason(exc: BaseException) -> str:
    """A one-line description of an exception."""
    text = " ".join(str(exc).split()) or repr(exc)
    return f"{type(exc).__name__}: {text}"[:500]


def _write_json(path, record) -> None:
    data = json.dumps(record, indent=2, sort_keys=True).encode()
    atomic_write(path, lambda fh: fh.write(data))


def run_job(job: Job, method, estimate=None) -> dict:
    """Estimate one scan: write `job.result` (by `estimate(scan, out, method)`, default
    `jaxrefl.api.estimate_to_file`) then `job.summary`, both atomically; its record.

    Bad input (the bundle does not load or validate, bad options) gives a record with
    `status` 'failed' and the reason; any other exception propagates, so a cluster
    can retry it."""
    if estimate is None:
        estimate = functools.partial(estimate_to_file, progress=False)  # the batch has its own bar

    t0 = time.perf_counter()
    try:
        summary = estimate(job.scan, job.result, method)
    except INPUT_ERRORS as exc:
        return {"name": job.name, "scan": job.scan, "status": "failed", "error": _reason(exc),
                "wall_seconds": time.perf_counter() - t0}
    record = dict(summary, name=job.name, scan=job.scan, status="done", wall_seconds=time.perf_counter() - t0)
    record["out"] = os.path.basename(job.result)
    _write_json(job.summary, record)
    return record


def _remote_job(job: Job, method, estimate=None) -> dict:
    """`run_job` on a cluster worker: with the XLA compilation cache a worker does not
    recompile what another process compiled before."""
    from .compile_cache import enable as _enable_compilation_cache

    _enable_compilation_cache()
    return run_job(job, method, estimate)


def _skipped_record(job: Job) -> dict:
    """The record of a finished scan: its summary file, or one rebuilt from the result
    (and the scan's ground truth) when that is missing or unreadable."""
    try:
        with open(job.summary, encoding="utf-8") as fh:
            record = json.load(fh)
        if record.get("status") != "done":
            raise ValueError("summary: not a finished scan")
    except (OSError, ValueError):
        from .result import load_result
        from .scan.io import load_scan

        est = load_result(job.result)
        record = {"method": est.meta.get("method"), "model": est.model, "out": os.path.basename(job.result),
                  "name": job.name, "scan": job.scan, "status": "done", "summary_rebuilt": True}
        try:
            record.update(estimate_summary(est, load_scan(job.scan)))
        except (*INPUT_ERRORS, KeyError) as exc:  # the scan has gone or changed: keep what the result says
            record["summary_error"] = _reason(exc)
        record["wall_seconds"] = float(sum(est.meta.get("seconds", {}).values()))
        _write_json(job.summary, record)
    return dict(record, status="skipped")


def _remove_temporaries(outdir, jobs) -> int:
    """Remove the temporaries `atomic_write` leaves when its process is killed mid-write."""
    names = {os.path.basename(p) for j in jobs for p in (j.result, j.summary)} | {"summary.csv", "summary.md"}
    removed = 0
    for f in os.listdir(outdir):
        if f.startswith(".tmp-") and any(f.endswith(n) for n in names):
            try:
                os.unlink(os.path.join(outdir, f))
                removed += 1
            except FileNotFoundError:
                pass
    return removed


def _error_stats(record, name):
    """(median, p90) relative error of `name` over measured points, or (None, None)."""
    entry = record.get("errors", {}).get(name, {}).get("measured", {})
    return entry.get("median"), entry.get("p90")


def _row(record) -> dict:
    row = {"name": record["name"], "status": record["status"], "scan": record["scan"],
           "seconds": record.get("wall_seconds"), "coverage": record.get("coverage"),
           "known": record.get("known"), "points": record.get("points"), "error": record.get("error", "")}
    for name in ("pd", "ps", "roughness"):
        row[f"{name}_err_median"], row[f"{name}_err_p90"] = _error_stats(record, name)
    return row


def summary_table(records) -> tuple[str, str]:
    """(CSV text, Markdown text) of a batch: one row per scan. `coverage` (measured) and
    `known` (measured or pooled) are shares of the observed points (`jaxrefl.api.estimate_summary`).
    Errors are median and 90th percentile relative errors against the scan's ground truth over
    measured points."""
    rows = [_row(r) for r in records]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v) for k, v in row.items()})

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    lines = ["| scan | status | seconds | measured | measured or pooled | pd err (median / p90) | ps err | "
             "roughness err | error |",
             "|---|---|---:|---:|---:|---|---|---|---|"]
    for row in rows:
        errs = [f"{num(row[f'{n}_err_median'], '.2%')} / {num(row[f'{n}_err_p90'], '.2%')}"
                if row[f"{n}_err_median"] is not None else "-" for n in ("pd", "ps", "roughness")]
        error = row["error"].replace("|", "\\|")
        lines.append(f"| {row['name']} | {row['status']} | {num(row['seconds'], '.1f')} | "
                     f"{num(row['coverage'], '.1%')} | {num(row['known'], '.1%')} | {' | '.join(errs)} | {error} |")
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed")}
    lines.append("")
    lines.append(f"{len(rows)} scans: {counts['done']} done, {counts['skipped']} skipped, {counts['failed']} failed")
    return buf.getvalue(), "\n".join(lines) + "\n"


def run_batch(source, outdir, method, *, client=None, retries: int = 2, estimate=None,
              progress: bool = False) -> list[dict]:
    """Estimate every scan of `source` into `outdir`; one record per scan, in source order.

    **Arguments:** `source` a folder of bundles, a list file (see `find_scans`) or a
    sequence of bundle paths; `method` the method of every scan (`jaxrefl.Local()`,
    `Radiosity()`, `Photon()` or `Auto()`); `client` a `distributed.Client` to run the scans on a Dask
    cluster (the bundles and `outdir` must be at the same paths on every worker), None
    to run them one after another here; `retries` how often the cluster re-runs a scan
    that raised something other than bad input (a worker that dies is handled by the
    scheduler's `allowed-failures`); `estimate` replaces `jaxrefl.api.estimate_to_file`
    (called as `estimate(scan_path, out, method)`); `progress` a tqdm bar.

    **Returns:** records (`name`, `scan`, `status` 'done' | 'skipped' | 'failed',
    `wall_seconds`, and the estimate's summary or `error`); `summary.csv` and
    `summary.md` are written to `outdir`.
    """
    from tqdm.auto import tqdm

    outdir = os.path.abspath(os.fspath(outdir))
    if isinstance(source, (str, os.PathLike)):
        if os.path.isdir(source) and os.path.isdir(outdir) and os.path.samefile(source, outdir):
            raise ValueError("out: must not be the folder of scan bundles")
        scans = find_scans(source)
    else:
        scans = list(source)
    jobs = plan_jobs(scans, outdir)
    os.makedirs(outdir, exist_ok=True)
    with folder_lock(outdir, f"out: {outdir} is in use by another batch"):
        _remove_temporaries(outdir, jobs)
        records = {}
        todo = []
        for job in jobs:
            if result_loads(job.result):
                records[job.name] = _skipped_record(job)
                continue
            if os.path.lexists(job.result):  # damaged or partial: never leave it beside the others
                os.unlink(job.result)
            todo.append(job)
        bar = tqdm(total=len(jobs), initial=len(records), unit="scan", disable=not progress, desc="batch")
        try:
            for job, record in _execute(todo, method, client, retries, estimate):
                if record["status"] == "failed":
                    _write_json(job.summary, record)
                records[job.name] = record
                bar.set_postfix_str(f"{job.name}: {record['status']}", refresh=False)
                bar.update(1)
        finally:
            bar.close()
            _remove_temporaries(outdir, jobs)
        ordered = [records[job.name] for job in jobs]
        csv_text, md_text = summary_table(ordered)
        atomic_write(os.path.join(outdir, "summary.csv"), lambda fh: fh.write(csv_text.encode()))
        atomic_write(os.path.join(outdir, "summary.md"), lambda fh: fh.write(md_text.encode()))
    return ordered


def _failed(job: Job, reason: str, t0: float | None) -> dict:
    return {"name": job.name, "scan": job.scan, "status": "failed", "error": reason,
            "wall_seconds": None if t0 is None else time.perf_counter() - t0}


def _execute(jobs, method, client, retries, estimate):
    """Yield `(job, record)` as scans finish: one after another here, or on `client`."""
    if client is None:
        for job in jobs:
            t0 = time.perf_counter()
            try:
                yield job, run_job(job, method, estimate)
            except Exception as exc:  # one scan's crash must not stop the others
                yield job, _failed(job, _reason(exc), t0)
        return
    from distributed import as_completed

    # pure=False: every submission is a fresh task (a resumed batch must not reuse an old
    # key's state); the job itself is idempotent, so a re-run after a worker death
    # rewrites the same files by rename.
    futures = {client.submit(_remote_job, job, method, estimate, pure=False, retries=retries,
                             key=f"jaxrefl-batch-{job.name}-{os.urandom(6).hex()}"): job for job in jobs}
    for future in as_completed(futures):
        job = futures[future]
        try:
            yield job, future.result()
        except Exception as exc:  # raised on every attempt, or KilledWorker: workers kept dying on it
            yield job, _failed(job, _reason(exc), None)
        finally:
            future.release()
