"""Embree ray throughput of `jaxrefl.geometry.raycast` relative to raw embreex, same rays, same run.

What: on a procedural mesh (Object A by default) we trace two ray sets that matter to the
pipeline: (a) shadow segments from mesh vertices to every light of the
`CylindricalScanner` rack (~0.6 m away), as `RayCaster.visibility` builds them, and
(b) incoherent first-hit rays from random surface points over the outward hemisphere
(path-tracing-like). Origins/directions/tfar are prepared once with
`RayCaster.offset_origins` (exactly as `segments_blocked` does) and the identical float32
arrays go to every implementation.

How: baseline = raw embreex, one `scene.run` call in this thread (`query='OCCLUDED'`
with `dists=tfar`; `output=1` for first hits), on a scene built with the same flags as
`RayCaster`'s (robust mode, `RayCaster.robust`); a raw scene with embreex's default
flags is timed too, to show what robust mode costs. Measured: `RayCaster.occluded` /
`first_hit` with threads=1, 2 and the default, the full `RayCaster.visibility` call
(offsetting and array prep included), and trimesh's `RayMeshIntersector` as a second
reference. Each timing is the median of `--repeats` after one untimed warm-up; results
are Mrays/s and the ratio to raw embreex single-thread (ratio > 1 = faster). Hit /
occlusion agreement with raw embreex is checked on the same rays.

    python -m benchmarks.raycast_bench [--rays N] [--repeats R] \
        [--out benchmarks/RESULTS_raycast.md]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import time
from importlib import metadata

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from data_synth.objects import make_object
from jaxrefl.geometry.raycast import RayCaster, default_threads
from jaxrefl.geometry.rig import CylindricalScanner


def _median_time(fn, repeats: int) -> tuple[float, object]:
    """Median wall time [s] of `fn()` over `repeats` runs after one untimed warm-up."""
    result = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def _busy_cpu_seconds() -> float | None:
    """Machine-wide busy CPU time [s] from /proc/stat (Linux), None elsewhere."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def _raw_scene(vertices, faces, robust: bool):
    scene = rtcore_scene.EmbreeScene(robust=robust) if robust else rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices.astype(np.float32), faces.astype(np.int32))
    return scene


def _version(pkg: str) -> str:
    try:
        return metadata.version(pkg)
    except metadata.PackageNotFoundError:
        return "?"


def _shadow_rays(rc: RayCaster, n_target: int, rng):
    """Vertex-to-light segments: P vertices x all K rack lights (P*K ~ n_target)."""
    scanner = CylindricalScanner()
    k = len(scanner.rack)
    n_vert = len(rc.vertices)
    p = max(1, n_target // k)
    idx = np.sort(rng.choice(n_vert, p, replace=p > n_vert))
    lights = scanner.light_positions(rc.vertices[idx])  # (P, K, 3)
    # Same arithmetic as RayCaster.visibility -> segments_blocked.
    pts = np.repeat(rc.vertices[idx], k, axis=0)
    nrm = np.repeat(rc.offset_normals[idx], k, axis=0)
    d = lights.reshape(-1, 3) - pts
    length = np.linalg.norm(d, axis=-1)
    unit = d / np.where(length > 0, length, 1.0)[:, None]
    origins = rc.offset_origins(pts, nrm, unit)
    tfar = np.maximum(length - 3.0 * rc.offset, 0.0)
    return idx, lights, origins, unit, tfar


def _hemisphere_rays(rc: RayCaster, n: int, rng):
    """Area-uniform random surface points, uniform directions over the outward hemisphere."""
    tri = rc.vertices[rc.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(area), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    pts = np.einsum("nk,nkj->nj", bary, tri[face])
    nrm = rc.face_normals[face]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.where(np.sum(d * nrm, axis=1, keepdims=True) < 0, -1.0, 1.0)
    return rc.offset_origins(pts, nrm, d), d


def run(n_rays: int, repeats: int, obj_name: str, resolution: int, seed: int) -> str:
    rng = np.random.default_rng(seed)
    t0, busy0, own0 = time.perf_counter(), _busy_cpu_seconds(), _own_cpu_seconds()
    obj = make_object(obj_name, resolution)
    n_vert, n_face = len(obj.vertices), len(obj.faces)

    n_threads_default = default_threads()
    thread_counts = sorted({1, 2, n_threads_default})
    casters = {t: RayCaster(obj.vertices, obj.faces, threads=t) for t in thread_counts}
    rc1 = casters[1]

    idx, lights, s_o, s_d, s_tf = _shadow_rays(rc1, n_rays // 2, rng)
    h_o, h_d = _hemisphere_rays(rc1, n_rays - n_rays // 2, rng)
    s_o32, s_d32, s_tf32 = (np.ascontiguousarray(a, dtype=np.float32) for a in (s_o, s_d, s_tf))
    h_o32, h_d32 = (np.ascontiguousarray(a, dtype=np.float32) for a in (h_o, h_d))
    h_tf32 = np.full(len(h_o32), np.inf, dtype=np.float32)
    n_s, n_h = len(s_o32), len(h_o32)

    robust = RayCaster.robust
    raw = _raw_scene(rc1.vertices, rc1.faces, robust)
    raw_other = _raw_scene(rc1.vertices, rc1.faces, not robust)
    mode, other_mode = ("robust", "default flags") if robust else ("default flags", "robust")

    try:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        tmi = RayMeshIntersector(trimesh.Trimesh(obj.vertices, obj.faces, process=False))
    except Exception as exc:  # trimesh or its embree backend missing
        print(f"trimesh reference skipped: {exc!r}")
        tmi = None

    rows = []  # (ray set, implementation, threads, seconds, agreement)

    # -- (a) shadow / occlusion segments ---------------------------------------------
    t_raw_s, occ_raw = _median_time(
        lambda: raw.run(s_o32, s_d32, dists=s_tf32, query="OCCLUDED") != -1, repeats)
    rows.append(("shadow", f"raw embreex `run(OCCLUDED)`, {mode} (reference)", 1, t_raw_s, 1.0))
    t, occ = _median_time(
        lambda: raw_other.run(s_o32, s_d32, dists=s_tf32, query="OCCLUDED") != -1, repeats)
    rows.append(("shadow", f"raw embreex `run(OCCLUDED)`, {other_mode}", 1, t,
                 np.mean(occ == occ_raw)))
    if tmi is not None:
        t, occ = _median_time(lambda: tmi.intersects_any(s_o32, s_d32), repeats)
        rows.append(("shadow", "trimesh `intersects_any` (no tfar)", 1, t, np.mean(occ == occ_raw)))
    for th, rc in casters.items():
        t, occ = _median_time(lambda rc=rc: rc.occluded(s_o32, s_d32, s_tf32), repeats)
        label = f"{th} (default)" if th == n_threads_default else th
        rows.append(("shadow", "jaxrefl `occluded`", label, t, np.mean(occ == occ_raw)))
    for th in sorted({1, n_threads_default}):
        rc = casters[th]
        t, vis = _median_time(lambda rc=rc: rc.visibility(lights, idx), repeats)
        label = f"{th} (default)" if th == n_threads_default else th
        rows.append(("shadow", "jaxrefl `visibility` (full call)", label, t,
                     np.mean(vis.ravel() == ~occ_raw)))
    assert np.array_equal(s_tf32, s_tf.astype(np.float32)), "raw run modified tfar in place"

    # -- (b) incoherent first hits -----------------------------------------------------
    t_raw_h, r = _median_time(lambda: raw.run(h_o32, h_d32, output=1), repeats)
    face_raw = r["primID"].astype(np.int64)
    rows.append(("first-hit", f"raw embreex `run(output=1)`, {mode} (reference)", 1, t_raw_h,
                 1.0))
    t, r2 = _median_time(lambda: raw_other.run(h_o32, h_d32, output=1), repeats)
    rows.append(("first-hit", f"raw embreex `run(output=1)`, {other_mode}", 1, t,
                 np.mean(r2["primID"] == face_raw)))
    if tmi is not None:
        t, face = _median_time(lambda: tmi.intersects_first(h_o32, h_d32), repeats)
        rows.append(("first-hit", "trimesh `intersects_first`", 1, t, np.mean(face == face_raw)))
    t_err = 0.0
    for th, rc in casters.items():
        t, hits = _median_time(lambda rc=rc: rc.first_hit(h_o32, h_d32, h_tf32), repeats)
        same = hits.face == face_raw
        both = same & hits.hit
        t_err = max(t_err, float(np.max(np.abs(hits.t[both] - r["tfar"][both]), initial=0.0)))
        label = f"{th} (default)" if th == n_threads_default else th
        rows.append(("first-hit", "jaxrefl `first_hit`", label, t, np.mean(same)))

    wall = time.perf_counter() - t0
    busy1 = _busy_cpu_seconds()
    other = None
    if busy0 is not None and busy1 is not None:
        other = max(0.0, busy1 - busy0 - (_own_cpu_seconds() - own0))

    # -- report --------------------------------------------------------------------------
    base = {"shadow": (t_raw_s, n_s), "first-hit": (t_raw_h, n_h)}
    table = [
        "| ray set | implementation | threads | median [ms] | Mrays/s | ratio vs raw 1T "
        "| agreement with raw |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for rays, impl, th, t, agree in rows:
        t_ref, n = base[rays]
        table.append(f"| {rays} | {impl} | {th} | {1e3 * t:.1f} | {n / t / 1e6:.2f} | "
                     f"{t_ref / t:.2f} | {agree:.6f} |")

    header = [
        "# Ray-casting throughput: `jaxrefl.geometry.raycast` vs raw embreex",
        "",
        f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- Machine: os.cpu_count()={os.cpu_count()}, {platform.platform()}, "
        f"{platform.processor() or platform.machine()}, Python {platform.python_version()}",
        f"- Versions: embreex {_version('embreex')}, trimesh {_version('trimesh')}, "
        f"numpy {np.__version__}",
        f"- Mesh: Object {obj_name} at resolution {resolution}: "
        f"{n_vert:,} vertices, {n_face:,} faces",
        f"- Rays: {n_s + n_h:,} total; shadow = {n_s:,} segments ({len(idx):,} vertices x "
        f"{lights.shape[1]} `CylindricalScanner` rack lights, {occ_raw.mean():.1%} occluded); "
        f"first-hit = {n_h:,} uniform-hemisphere rays from area-uniform surface points "
        f"({np.mean(face_raw >= 0):.1%} hit)",
        f"- Method: median of {repeats} repeats, one warm-up excluded; all implementations get "
        "the same float32 origins/directions/tfar (prepared once via `RayCaster.offset_origins`); "
        f"ratio = time of raw embreex single-thread on a {mode} scene (as `RayCaster` "
        "builds it) / time (> 1 = faster). `visibility` rebuilds "
        "its rays from (vertex, light) pairs inside the timed call. trimesh's `intersects_any` "
        "has no tfar (closest hit to infinity, on its own rescaled default-flags scene). "
        f"Default RayCaster threads here: {n_threads_default}.",
        f"- Run: {wall:.1f} s wall; CPU used by other processes meanwhile: "
        + ("unknown" if other is None else f"{other / wall:.2f} cores on average")
        + " (threaded rows are only meaningful when this is ~0)",
        f"- First-hit `t` max |jaxrefl - raw| where faces agree: {t_err:.3g} m",
        "",
    ]
    return "\n".join(header + table) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=1 << 20,
                    help="total rays (half shadow, half first-hit)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--object", default="A")
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/RESULTS_raycast.md")
    args = ap.parse_args(argv)
    md = run(args.rays, args.repeats, args.object, args.resolution, args.seed)
    print(md)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            f.write(md)


if __name__ == "__main__":
    main()
