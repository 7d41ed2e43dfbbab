"""Benchmark: Method III's photon map against the brute-force path tracer, and its speed.

Run: `python -m benchmarks.photon_bench [--quick] [--out benchmarks/RESULTS_photon.md]`.

1. Forward check and convergence on Object E (glossy and diffuse paper, Ward):
   photon-map indirect radiance at vertices beside the fold (not on it: the
   point value there is singular, see tests/test_photon.py) against
   `data_synth.pathtrace.PathTracer` with many samples, for growing photon
   counts and several target gather sizes, three seeds each. Reported: the mean
   relative deviation over the vertices (the estimator's bias, with its standard
   error from both estimators' noise), the per-vertex RMS relative error with
   the reference's own noise taken out, the seed-to-seed relative spread, and
   the seconds per build (trace + gather set-up).
2. The furnace (closed sphere of albedo rho, light at the centre) against
   `rho^2 E / (pi (1 - rho))`.
3. Path replay: photons traced from one proposal, re-weighted to other
   reflectances, against photons traced from those reflectances; the
   effective sample size the replay reports.
4. Final gathering (diffuse paper): one exact bounce by rays from every
   vertex, the photon map at the hit points, against the plain density
   estimate, as error per second.
5. Speed at the Method III target: ~100k vertices, 12 lights, 2M photons per
   light: tracing, gather set-up, one replay iteration, memory; with raw Embree
   throughput measured in the same process as the reference.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def _load():
    return os.getloadavg()[0]


def _setup(setup, resolution, n_pick, seed=0):
    from data_synth.objects import fold_coordinate, make_object
    from jaxrefl.geometry.raycast import RayCaster

    obj = make_object("E", resolution, setup)
    s, x = fold_coordinate(obj.vertices), obj.vertices[:, 0]
    region = np.flatnonzero((np.abs(s) > 0.02) & (np.abs(s) < 0.16) & (np.abs(x) < 0.08))
    pick = np.sort(np.random.default_rng(seed).choice(region, min(n_pick, len(region)), replace=False))
    return obj, RayCaster(obj.vertices, obj.faces), pick


CAM = np.array([0.0, 0.0, 0.7])
LIGHT = np.array([0.1, 0.1, 0.7])


def _reference(obj, caster, pick, samples):
    from data_synth.pathtrace import Material, PathTracer

    tracer = PathTracer(obj.vertices, obj.faces, obj.normals, Material(obj.pd, obj.ps, obj.roughness, "ward"),
                        caster=caster)
    cam = np.broadcast_to(CAM, (len(pick), 1, 3)).copy()
    light = np.broadcast_to(LIGHT, (len(pick), 1, 3)).copy()
    t = time.perf_counter()
    total, se = tracer.render(cam, light, np.ones(1), samples=samples, seed=99, points=pick, progress=False)
    direct, _ = tracer.render(cam, light, np.ones(1), samples=0, points=pick, progress=False)
    return (total - direct)[:, 0, 0], se[:, 0, 0], time.perf_counter() - t


def _score(runs, ref, ref_se, region_means=None):
    """Bias (mean relative deviation over the vertices) and its standard error,
    per-vertex RMS relative error of one run (reference noise removed), and the
    per-vertex relative spread between runs.

    `runs` `(K, R)`; the photon map's part of the bias error comes from
    independent region means `region_means` (batches; default: the runs')."""
    runs = np.asarray(runs)
    k = len(runs)
    rel = runs.mean(0) / ref - 1
    means = np.asarray(region_means if region_means is not None else (runs / ref).mean(1))
    bias_se = np.sqrt(np.sum((ref_se / ref) ** 2) / len(ref) ** 2 + means.var(ddof=1) / len(means))
    spread = runs.std(0, ddof=1) / np.maximum(runs.mean(0), 1e-300) if k > 1 else np.zeros_like(ref)
    per_run = runs / ref - 1
    rms = np.sqrt(max(np.mean(per_run**2) - np.mean((ref_se / ref) ** 2), 0.0))
    return dict(bias=float(rel.mean()), bias_se=float(bias_se), rms=float(rms),
                spread=float(np.sqrt(np.mean(spread**2))))


def convergence(setup, photon_counts, targets, resolution, n_pick, ref_samples, seeds):
    from jaxrefl.methods.photon import PhotonReplay

    obj, caster, pick = _setup(setup, resolution, n_pick)
    params = (obj.pd, obj.ps, obj.roughness)
    ref, ref_se, t_ref = _reference(obj, caster, pick, ref_samples)
    rows = []
    for n in photon_counts:
        for target in targets:
            runs, secs, batch_means = [], [], []
            for s in range(seeds):
                t = time.perf_counter()
                rep = PhotonReplay.build(caster, obj.vertices, obj.faces, obj.normals, LIGHT[None], 1.0, CAM, params,
                                         n_photons=n, target_photons=target, seed=s)
                out = np.asarray(rep.indirect(*params))[:, 0, 0]
                secs.append(time.perf_counter() - t)
                runs.append(out[pick])
                b = np.asarray(rep.indirect_batches(*params, batches=8))[:, pick, 0, 0]
                batch_means.extend((b / ref).mean(1))
            lv = np.bincount(np.asarray(rep.data.level)[pick, 0], minlength=6)
            rows.append(dict(photons=n, target=target, stored=rep.n_photons, seconds=float(np.median(secs)),
                             levels=lv.tolist(), **_score(runs, ref, ref_se, batch_means)))
    return dict(setup=setup, vertices=len(obj.vertices), picked=len(pick), ref_samples=ref_samples,
                ref_rel_se=float(np.median(ref_se / ref)), ref_seconds=t_ref, rows=rows)


def furnace(rhos, photon_counts):
    import trimesh

    from jaxrefl.geometry.mesh import vertex_areas
    from jaxrefl.methods.photon import PhotonReplay

    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)[:, ::-1]
    nrm = -v / np.linalg.norm(v, axis=1, keepdims=True)
    area = vertex_areas(v, f)
    rows = []
    for rho in rhos:
        params = (np.full((len(v), 3), rho), np.zeros(len(v)), np.full(len(v), 0.3))
        expected = rho / np.pi * rho / (1 - rho)
        exact_poly = rho / np.pi * 4 * np.pi * rho / (1 - rho) / area.sum()
        for n in photon_counts:
            t = time.perf_counter()
            rep = PhotonReplay.build(None, v, f, nrm, np.zeros((1, 3)), 1.0, np.zeros(3), params, n_photons=n, seed=1)
            out = np.asarray(rep.indirect(*params))[:, 0, 0]
            sec = time.perf_counter() - t
            mean = float(np.sum(area * out) / area.sum())
            rows.append(dict(rho=rho, photons=n, seconds=sec, depth=len(rep.paths.level_offsets) - 1,
                             sphere=mean / expected - 1, poly=mean / exact_poly - 1,
                             vertex_sd=float(np.std(out / expected)),
                             vertex_max=float(np.max(np.abs(out / expected - 1)))))
    return dict(vertices=len(v), rows=rows)


def replay_check(resolution, n_photons):
    from jaxrefl.methods.photon import PhotonReplay

    obj, caster, pick = _setup("glossy", resolution, 10**9)
    n = len(obj.vertices)
    proposals = {
        "grey diffuse (cosine sampling only)": (np.full((n, 3), 0.5), np.zeros(n), np.full(n, 0.3)),
        "true glossy paper": (obj.pd, obj.ps, obj.roughness),
    }
    targets = {
        "true glossy paper (pd .7, ps .3, alpha .08)": (obj.pd, obj.ps, obj.roughness),
        "coloured, sharper (pd .8/.5/.2, ps .4, alpha .04)": (np.tile([0.8, 0.5, 0.2], (n, 1)), np.full(n, 0.4),
                                                              np.full(n, 0.04)),
        "dark matte (pd .2, ps .05, alpha .3)": (np.full((n, 3), 0.2), np.full(n, 0.05), np.full(n, 0.3)),
    }
    args = (caster, obj.vertices, obj.faces, obj.normals, LIGHT[None], 1.0, CAM)
    rows = []

    def estimates(rep, params):
        return np.asarray(rep.indirect_batches(*params, batches=16))[:, pick, 0]  # (16, R, 3)

    def compare(a, b):
        ma, mb = a.mean(0), b.mean(0)
        pooled = np.mean(a.var(0, ddof=1) / ma**2) / len(a) + np.mean(b.var(0, ddof=1) / mb**2) / len(b)
        ra, rb = a.mean(axis=(1, 2)), b.mean(axis=(1, 2))
        rel_se = np.sqrt(ra.var(ddof=1) / len(ra) + rb.var(ddof=1) / len(rb)) / rb.mean()
        return ra.mean() / rb.mean() - 1, rel_se, float(np.mean((ma - mb) ** 2 / (mb**2 * pooled)))

    fresh = {}
    for tname, target in targets.items():
        reps = [PhotonReplay.build(*args, target, n_photons=n_photons, seed=100 + s) for s in range(2)]
        fresh[tname] = [estimates(r, target) for r in reps]
    for pname, prop in proposals.items():
        rep = PhotonReplay.build(*args, prop, n_photons=n_photons, seed=0)
        for tname, target in targets.items():
            jax.block_until_ready(rep.indirect(*target))
            t = time.perf_counter()
            jax.block_until_ready(rep.indirect(*target))
            sec = time.perf_counter() - t
            a = estimates(rep, target)
            b, c = fresh[tname]
            bias, bias_se, chi2 = compare(a, b)
            chi2_ff = compare(c, b)[2]
            rows.append(dict(proposal=pname, target=tname, ess=float(np.asarray(rep.ess(*target))[0]),
                             bias=float(bias), bias_se=float(bias_se), chi2=chi2, chi2_fresh=chi2_ff,
                             replay_sd=float(np.sqrt(np.mean(a.var(0, ddof=1) / a.mean(0) ** 2))),
                             fresh_sd=float(np.sqrt(np.mean(b.var(0, ddof=1) / b.mean(0) ** 2))), seconds=sec))
    return dict(vertices=n, picked=len(pick), photons=n_photons, rows=rows)


def _final_gather(obj, caster, replay, rays, seed):
    """Diffuse final gather at every vertex: `rays` cosine-sampled rays; the radiance
    seen at each hit is exact direct light plus the photon map's incident flux."""
    from jaxrefl.methods.photon import _normalize

    rng = np.random.default_rng(seed)
    v, nrm, faces = obj.vertices, obj.normals, obj.faces
    n = len(v)
    d_vertex = np.asarray(replay.parts(replay.powers(obj.pd, obj.ps, obj.roughness), obj.roughness)[0])[:, 0, 0]
    out = np.zeros(n)
    for s in range(0, n, max(1, 200_000 // rays)):
        idx = np.arange(s, min(n, s + max(1, 200_000 // rays)))
        p = np.repeat(idx, rays)
        nn = nrm[p]
        a = np.where(np.abs(nn[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t = _normalize(np.cross(nn, a))
        b = np.cross(nn, t)
        u1, u2 = rng.random(len(p)), rng.random(len(p))
        r, phi = np.sqrt(u1), 2 * np.pi * u2
        d = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + np.sqrt(1 - u1)[:, None] * nn
        hits = caster.first_hit(caster.offset_origins(v[p], caster.offset_normals[p], d), d)
        face = np.maximum(hits.face, 0)
        n_y = _normalize(np.einsum("pk,pkj->pj", hits.barycentric, nrm[faces[face]]))
        ok = hits.hit & (np.sum(n_y * -d, 1) > 0)
        y = np.where(ok[:, None], hits.points, v[p])
        to_l = LIGHT - y
        dist = np.linalg.norm(to_l, axis=1)
        cos_l = np.sum(n_y * to_l, 1) / dist
        lit = ok & (cos_l > 0)
        vis = np.zeros(len(p), bool)
        vis[lit] = ~caster.segments_blocked(y[lit], caster.face_normals[face[lit]],
                                            np.broadcast_to(LIGHT, y[lit].shape))
        e_dir = np.where(vis, cos_l / dist**2, 0.0)
        d_ind = np.einsum("pk,pk->p", hits.barycentric, d_vertex[faces[face]])
        pd_y = np.einsum("pk,pk->p", hits.barycentric, obj.pd[faces[face], 0])
        radiance_y = np.where(ok, pd_y / np.pi * (e_dir + d_ind), 0.0)
        # cosine sampling: L_ind(x) = pd_x / pi * (pi / G) * sum L(y)
        out[idx] = obj.pd[idx, 0] * radiance_y.reshape(len(idx), rays).mean(1)
    return out


def final_gather(resolution, n_pick, ref_samples, photon_counts, gather_rays, seeds):
    from jaxrefl.methods.photon import PhotonReplay

    obj, caster, pick = _setup("diffuse", resolution, n_pick)
    params = (obj.pd, obj.ps, obj.roughness)
    ref, ref_se, _ = _reference(obj, caster, pick, ref_samples)
    rows = []
    for n in photon_counts:
        for g in [0] + list(gather_rays):
            runs, secs = [], []
            for s in range(seeds):
                t = time.perf_counter()
                rep = PhotonReplay.build(caster, obj.vertices, obj.faces, obj.normals, LIGHT[None], 1.0, CAM, params,
                                         n_photons=n, seed=s)
                out = np.asarray(rep.indirect(*params))[:, 0, 0] if g == 0 else _final_gather(obj, caster, rep, g, s)
                secs.append(time.perf_counter() - t)
                runs.append(out[pick])
            score = _score(runs, ref, ref_se)
            rows.append(dict(photons=n, rays=g, seconds=float(np.median(secs)), **score,
                             error_x_seconds=float(score["rms"] ** 2 * np.median(secs))))
    return dict(vertices=len(obj.vertices), picked=len(pick), rows=rows)


def speed(resolution, n_lights, n_photons, repeats):
    from data_synth.objects import make_object
    from data_synth.scans import make_rig
    from jaxrefl.geometry.raycast import RayCaster
    from jaxrefl.geometry.rig import paper_light_rack
    from jaxrefl.methods.photon import PhotonReplay

    obj = make_object("E", resolution, "glossy")
    v, f = obj.vertices, obj.faces
    center = 0.5 * (v.min(0) + v.max(0))
    rack = paper_light_rack()
    sel = np.linspace(0, len(rack) - 1, n_lights).astype(int)
    rig = make_rig("pinhole", center, rack[sel])
    lights = rig.rack_positions(rack[sel])
    caster = RayCaster(v, f)
    params = (obj.pd, obj.ps, obj.roughness)
    # Raw Embree reference in this process: the first light's emission rays (as the
    # tracer makes them), single-threaded, on the same scene.
    from jaxrefl.methods.photon import _emit

    _, d, _ = _emit(caster, np.random.default_rng(0), lights[0], n_photons, np.float32)
    d = np.ascontiguousarray(d.T)
    o32 = np.ascontiguousarray(np.broadcast_to(lights[0].astype(np.float32), d.shape))
    t = time.perf_counter()
    caster._scene.run(o32, d, dists=np.full(len(d), np.inf, np.float32), output=1)
    raw_rate = len(d) / (time.perf_counter() - t)
    m = n_lights * n_photons
    load0 = _load()
    t = time.perf_counter()
    rep = PhotonReplay.build(caster, v, f, obj.normals, lights, 1.0, rig.center, params, n_photons=n_photons, seed=0)
    build = time.perf_counter() - t
    rays = m + int(np.sum(rep.paths.bounce >= 1))  # emission + one ray per stored photon (a lower bound)
    timings = {}
    for name, fn in (("indirect", lambda: rep.indirect(*params)), ("powers", lambda: rep.powers(*params)),
                     ("ess", lambda: rep.ess(*params))):
        jax.block_until_ready(fn())
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn())
            ts.append(time.perf_counter() - t)
        timings[name] = float(np.median(ts))
    nbytes = sum(int(np.asarray(x).nbytes) for x in jax.tree_util.tree_leaves(rep.data))
    # Monte Carlo error of every (vertex, light) estimate, from 8 photon batches.
    b = np.asarray(rep.indirect_batches(*params, batches=8))[..., 0]  # (8, N, M)
    mean = b.mean(0)
    ok = mean > 0
    rel_se = (b.std(0, ddof=1) / np.sqrt(8))[ok] / mean[ok]
    return dict(vertices=len(v), faces=len(f), lights=n_lights, photons_per_light=n_photons, stored=rep.n_photons,
                entries=int(len(rep.data.splat.row)), levels=np.bincount(np.asarray(rep.data.level).ravel()).tolist(),
                build=build, trace=rep.seconds["trace"], gather_setup=rep.seconds["gather_setup"],
                raw_embree_mrays=raw_rate / 1e6, trace_mrays=rays / rep.seconds["trace"] / 1e6,
                replay_mbytes=nbytes / 2**20, load=(load0, _load()), rel_se=np.percentile(rel_se, [50, 90]).tolist(),
                **timings)


def _fmt_conv(c):
    lines = [f"Object E `{c['setup']}` ({c['vertices']} vertices), {c['picked']} vertices beside the fold; "
             f"reference: path tracer, {c['ref_samples']} paths per vertex (median relative standard error "
             f"{c['ref_rel_se']:.2%}, {c['ref_seconds']:.1f} s).", "",
             "| photons/light | target | stored | bias (mean rel. dev.) | per-vertex RMS rel. error | seed spread | "
             "s per build+gather | smoothing levels at the vertices |", "|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in c["rows"]:
        lines.append(f"| {r['photons']:,} | {r['target']:g} | {r['stored']:,} | "
                     f"{r['bias']:+.2%} ± {r['bias_se']:.2%} | "
                     f"{r['rms']:.2%} | {r['spread']:.2%} | {r['seconds']:.2f} | {r['levels']} |")
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller counts (a smoke run)")
    parser.add_argument("--out", default="benchmarks/RESULTS_photon.md")
    args = parser.parse_args(argv)
    q = args.quick
    t_all = time.perf_counter()
    load_start = _load()
    res = {}
    counts = (50_000, 200_000) if q else (50_000, 200_000, 1_000_000, 4_000_000)
    res["glossy"] = convergence("glossy", counts, (256,), 64, 60 if q else 150, 2048 if q else 16384, 3)
    res["targets"] = convergence("glossy", (1_000_000,) if not q else (200_000,), (16, 64, 256, 1024), 64,
                                 60 if q else 150,
                                 2048 if q else 16384, 3)
    res["diffuse"] = convergence("diffuse", counts, (256,), 64, 60 if q else 150, 2048 if q else 16384, 3)
    res["furnace"] = furnace((0.5, 0.8), (50_000, 200_000) if q else (50_000, 200_000, 1_000_000))
    res["replay"] = replay_check(32, 100_000 if q else 500_000)
    res["final_gather"] = final_gather(64, 60 if q else 150, 2048 if q else 16384,
                                       (200_000,) if q else (200_000, 1_000_000),
                                       (16, 64), 3 if not q else 2)
    res["speed"] = speed(120 if q else 446, 12, 200_000 if q else 2_000_000, 3)
    wall = time.perf_counter() - t_all

    lines = ["# Photon map (Method III forward machinery): accuracy and speed", "",
             f"- Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: {os.cpu_count()} cores, "
             f"{platform.platform()}; Python {platform.python_version()}, jax {jax.__version__}",
             f"- Run: `python -m benchmarks.photon_bench{' --quick' if q else ''}`, {wall:.0f} s wall; load average "
             f"at start {load_start:.2f} (other processes share the 2 cores: timings vary up to ~2x between runs)",
             "- Light and camera: point light (0.1, 0.1, 0.7) m, Y = 1 W/sr; camera (0, 0, 0.7) m. Reflectance "
             "model Ward (`alpha` = the object's roughness), the same in the path tracer.",
             "- bias = mean over the vertices of (photon map / path tracer - 1), ± its standard error from both "
             "estimators' noise; RMS = per-vertex RMS relative error of one run, with the reference's own "
             "variance subtracted; seed spread = RMS relative standard deviation between seeds.", "",
             "## 1. Forward check and convergence (Object E, glossy paper: pd 0.7, ps 0.3, alpha 0.08)", ""]
    lines += _fmt_conv(res["glossy"])
    lines += ["", "Gather size (target effective photon count per gather) at fixed photons:", ""]
    lines += _fmt_conv(res["targets"])
    lines += ["", "## 1b. Forward check, diffuse paper (pd 0.8, ps 0)", ""]
    lines += _fmt_conv(res["diffuse"])
    fr = res["furnace"]
    lines += ["", f"## 2. Furnace (icosphere, {fr['vertices']} vertices, inward, light at the centre)", "",
              "`sphere` = area-weighted mean / (rho^2 E / (pi (1 - rho))) - 1 (the polyhedron has 0.3 % less area "
              "than the sphere); `polyhedron` = the same against the polyhedron's exact power balance.", "",
              "| rho | photons | bounce levels | vs sphere | vs polyhedron | per-vertex rel. sd | "
              "max per-vertex dev. | s |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in fr["rows"]:
        lines.append(f"| {r['rho']} | {r['photons']:,} | {r['depth']} | {r['sphere']:+.2%} | {r['poly']:+.2%} | "
                     f"{r['vertex_sd']:.2%} | {r['vertex_max']:.2%} | {r['seconds']:.2f} |")
    rp = res["replay"]
    lines += ["", f"## 3. Path replay vs a fresh trace (Object E glossy, {rp['vertices']} vertices, "
              f"{rp['photons']:,} photons)", "",
              "Replayed: paths traced from the proposal (one trace), powers re-weighted to the target inside "
              "jit. Fresh: photons traced from the target (two traces). Errors from 16 photon batches per "
              "trace. chi2 = mean squared per-vertex difference over its standard error (relative variance "
              "pooled over the vertices), ~1 when they agree; `chi2 fresh` is the same between the two fresh "
              "traces, for scale. sd = per-vertex relative sd of one batch (x 1/4 for a whole "
              "trace). All RGB channels.", "",
              "| proposal | target | ESS (fraction) | replay - fresh (mean rel.) | chi2 | chi2 fresh | replay sd | "
              "fresh sd | s per replay |", "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rp["rows"]:
        lines.append(f"| {r['proposal']} | {r['target']} | {r['ess']:.3f} | {r['bias']:+.2%} ± {r['bias_se']:.2%} | "
                     f"{r['chi2']:.2f} | {r['chi2_fresh']:.2f} | {r['replay_sd']:.1%} | {r['fresh_sd']:.1%} | "
                     f"{r['seconds']:.4f} |")
    fg = res["final_gather"]
    lines += ["", f"## 4. Density estimate vs final gathering (Object E diffuse, {fg['vertices']} vertices)", "",
              "rays = 0: the photon map's own estimate at the vertex; rays > 0: cosine-sampled gather rays from "
              "every vertex, exact direct light at the hits plus the photon map there (one bounce exact). "
              "Seconds cover all vertices for one light (build included); error x seconds = RMS^2 x s (lower is "
              "better).", "",
              "| photons | gather rays | bias | per-vertex RMS | s | RMS^2 x s |", "|---:|---:|---:|---:|---:|---:|"]
    for r in fg["rows"]:
        lines.append(f"| {r['photons']:,} | {r['rays']} | {r['bias']:+.2%} ± {r['bias_se']:.2%} | {r['rms']:.2%} | "
                     f"{r['seconds']:.2f} | {r['error_x_seconds']:.2e} |")
    sp = res["speed"]
    lines += ["", f"## 5. Speed at the Method III target (Object E, {sp['vertices']:,} vertices, "
              f"{sp['faces']:,} faces, "
              f"{sp['lights']} lights, {sp['photons_per_light']:,} photons per light)", "",
              "| quantity | value |", "|---|---:|",
              f"| stored photons (reflected at least once, all lights) | {sp['stored']:,} |",
              f"| splat entries (photon x vertex) | {sp['entries']:,} |",
              f"| smoothing levels over (vertex, light) | {sp['levels']} |",
              f"| trace, all lights [s] | {sp['trace']:.1f} |",
              f"| trace rate (emitted + stored photons / s; more rays are cast) [Mrays/s] | {sp['trace_mrays']:.2f} |",
              f"| raw embreex first-hit of the same emission rays, 1 thread [Mrays/s] | {sp['raw_embree_mrays']:.2f} |",
              f"| gather set-up (kernel, splats, levels, device copies) [s] | {sp['gather_setup']:.1f} |",
              f"| one replay iteration `indirect(pd, ps, alpha)` [s] | {sp['indirect']:.3f} |",
              f"| of which photon powers (`powers`) [s] | {sp['powers']:.3f} |",
              f"| `ess` [s] | {sp['ess']:.3f} |",
              f"| replay arrays on the device [MiB] | {sp['replay_mbytes']:.0f} |",
              f"| relative standard error of one (vertex, light) indirect estimate, median / 90th pct. (red) | "
              f"{sp['rel_se'][0]:.1%} / {sp['rel_se'][1]:.1%} |",
              f"| load average before / after | {sp['load'][0]:.2f} / {sp['load'][1]:.2f} |"]
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
