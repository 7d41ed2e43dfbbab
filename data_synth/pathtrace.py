"""Independent brute-force Monte Carlo path tracer over Embree (ground truth).

This is the reference for global illumination in the synthetic scans. It
shares nothing with jaxrefl's estimators or their fast approximations: its
BRDFs are written out again here in NumPy (a test checks they agree with
`jaxrefl.reflectance.brdf`), and it only uses `jaxrefl.geometry.raycast` to ask Embree where rays go.

For an observation (surface vertex x, camera c, point light at p with radiant
intensity Y) it returns the radiance leaving x toward c:

    L = f(x; p, c) Y cos / |p - x|^2 * visible(x, p)            (exact, no MC)
      + indirect: paths x -> y1 -> y2 ... sampled from a cosine / BRDF-lobe
        mixture, with next-event estimation to the light at every y_k and
        Russian roulette; unbiased for any number of bounces.

The room is dark (rays that leave the object are lost). Surfaces are
one-sided: a path that reaches a surface from behind its shading normal is
absorbed. Reflectance and shading normals at a hit are the barycentric
interpolation of the per-vertex values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from jaxrefl.geometry.raycast import RayCaster

__all__ = ["Material", "brdf_numpy", "PathTracer"]

_MODELS = ("torrance-sparrow", "ward")


@dataclass(frozen=True)
class Material:
    """Per-vertex reflectance: `pd` `(N, 3)` albedo, `ps` `(N,)`, `roughness`
    `(N,)` [rad] (sigma for Torrance-Sparrow, alpha for Ward), `model` name."""

    pd: np.ndarray
    ps: np.ndarray
    roughness: np.ndarray
    model: str = "torrance-sparrow"

    def __post_init__(self):
        if self.model not in _MODELS:
            raise ValueError(f"model must be one of {_MODELS}, got {self.model!r}")


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def _normalize(a):
    length = np.linalg.norm(a, axis=-1, keepdims=True)
    return a / np.where(length > 0, length, 1.0)


def brdf_numpy(model, pd, ps, rough, n, wi, wo):
    """BRDF [1/sr] of `P` samples: `pd` `(P, 3)`, `ps`, `rough` `(P,)`,
    unit `n`, `wi` (to light), `wo` (to viewer) `(P, 3)`. 0 below either horizon."""
    ci, co = _dot(n, wi), _dot(n, wo)
    ok = (ci > 0) & (co > 0)
    h = wi + wo
    cos_h = _dot(n, h)
    sin_h = np.linalg.norm(np.cross(n, h), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if model == "torrance-sparrow":
            theta = np.arctan2(sin_h, cos_h)
            spec = ps * np.exp(-(theta**2) / (2 * rough**2)) / (ci * co)
        else:
            tan2 = (sin_h / cos_h) ** 2
            spec = ps * np.exp(-tan2 / rough**2) / (4 * np.pi * rough**2 * np.sqrt(ci * co))
    spec = np.where(ok, spec, 0.0)
    return np.where(ok[:, None], pd / np.pi + spec[:, None], 0.0)


def _lobe_width(model, rough):
    # Width of the Ward-type half-vector proposal; exp(-t^2/(2 s^2)) ~ exp(-tan^2/(2 s^2)).
    return rough * np.sqrt(2.0) if model == "torrance-sparrow" else rough


def _frame(n):
    """Two unit tangents `(P, 3)` completing each normal to an orthonormal frame."""
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t = _normalize(np.cross(n, a))
    return t, np.cross(n, t)


def _sample_directions(rng, n, wo, alpha, q_lobe):
    """Sample `wi` from `(1-q) cosine + q Ward half-vector lobe`; return `wi`, pdf [1/sr]."""
    p = len(n)
    t, b = _frame(n)
    u1, u2, u3 = rng.random(p), rng.random(p), rng.random(p)
    use_lobe = u3 < q_lobe
    # cosine-weighted hemisphere
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local_cos = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0))], -1)
    # Ward half vector: tan^2(theta_h) = -alpha^2 log(u)
    tan2 = -(alpha**2) * np.log(np.maximum(1 - u1, 1e-300))
    cos_t = 1 / np.sqrt(1 + tan2)
    sin_t = np.sqrt(np.maximum(1 - cos_t**2, 0))
    local_h = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], -1)
    local = np.where(use_lobe[:, None], local_h, local_cos)
    vec = local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * n
    h_lobe = vec
    wi = np.where(use_lobe[:, None], 2 * _dot(wo, h_lobe)[:, None] * h_lobe - wo, vec)
    return wi, _mixture_pdf(n, wo, wi, alpha, q_lobe)


def _mixture_pdf(n, wo, wi, alpha, q_lobe):
    cos_i = _dot(n, wi)
    pdf_cos = np.maximum(cos_i, 0) / np.pi
    h = _normalize(wi + wo)
    cos_h = np.clip(_dot(n, h), 1e-12, 1)
    tan2 = (1 - cos_h**2) / cos_h**2
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        pdf_h = np.exp(-tan2 / alpha**2) / (np.pi * alpha**2 * cos_h**3)
        pdf_lobe = np.where(_dot(n, h) > 0, pdf_h / (4 * np.abs(_dot(wo, h))), 0.0)
    pdf_lobe = np.nan_to_num(pdf_lobe, nan=0.0, posinf=0.0)
    return (1 - q_lobe) * pdf_cos + q_lobe * pdf_lobe


class PathTracer:
    """Brute-force path tracer for one mesh with per-vertex materials.

    **Arguments:** `vertices` `(N, 3)`, `faces` `(F, 3)`, `normals` `(N, 3)`
    unit shading normals, `material` a `Material`; `max_depth` hard cap on
    bounces (Russian roulette ends almost all paths long before it).
    """

    def __init__(self, vertices, faces, normals, material: Material, max_depth: int = 64,
                 caster: RayCaster | None = None):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.normals = _normalize(np.asarray(normals, dtype=np.float64))
        self.material = material
        self.max_depth = max_depth
        self.caster = caster or RayCaster(self.vertices, self.faces)

    # -- pieces ------------------------------------------------------------------

    def _interp(self, face, bary, values):
        return np.einsum("pk,pk...->p...", bary, values[self.faces[face]])

    def _brdf(self, pd, ps, rough, n, wi, wo):
        return brdf_numpy(self.material.model, pd, ps, rough, n, wi, wo)

    def _next_event(self, x, n, wo, pd, ps, rough, light, intensity, offset_normals=None):
        """Radiance toward `wo` from the point light, with an Embree shadow ray. `(P, 3)`."""
        d = light - x
        dist = np.linalg.norm(d, axis=-1)
        wi = d / dist[:, None]
        f = self._brdf(pd, ps, rough, n, wi, wo)
        cos_i = _dot(n, wi)
        live = cos_i > 0
        vis = np.zeros(len(x), dtype=bool)
        if np.any(live):
            step = n if offset_normals is None else offset_normals
            vis[live] = ~self.caster.segments_blocked(x[live], step[live], light[live])
        return f * (intensity * np.maximum(cos_i, 0) * vis / dist**2)[:, None]

    def direct(self, idx, cam, light, intensity):
        """Exact single-bounce radiance of vertices `idx` `(P,)` toward cameras
        `(P, 3)` under lights `(P, 3)` of intensity `(P,)`. `(P, 3)`."""
        x, n = self.vertices[idx], self.normals[idx]
        wo = _normalize(cam - x)
        m = self.material
        return self._next_event(x, n, wo, m.pd[idx], m.ps[idx], m.roughness[idx], light, intensity,
                                offset_normals=self.caster.offset_normals[idx])

    def indirect(self, idx, cam, light, intensity, rng):
        """One-sample unbiased estimate `(P, 3)` of the interreflected radiance."""
        m = self.material
        p = len(idx)
        x, n = self.vertices[idx], self.normals[idx]
        wo = _normalize(cam - x)
        pd, ps, rough = m.pd[idx], m.ps[idx], m.roughness[idx]
        beta = np.ones((p, 3))
        total = np.zeros((p, 3))
        alive = (_dot(n, wo) > 0)
        step = self.caster.offset_normals[idx]  # rays leave vertices along the welded normal
        rows = np.arange(p)
        for depth in range(self.max_depth):
            rows = rows[alive]
            if len(rows) == 0:
                break
            x, n, wo, pd, ps, rough, beta, step = (
                a[alive] for a in (x, n, wo, pd, ps, rough, beta, step))
            light_r, inten_r = light[rows], intensity[rows]
            alpha = _lobe_width(m.model, rough)
            q = np.clip(ps / (ps + pd.mean(axis=1) + 1e-12), 0.0, 0.9)
            wi, pdf = _sample_directions(rng, n, wo, alpha, q)
            f = self._brdf(pd, ps, rough, n, wi, wo)
            cos_i = _dot(n, wi)
            ok = (cos_i > 0) & (pdf > 0)
            weight = np.where(ok[:, None], f * (np.maximum(cos_i, 0) / np.where(ok, pdf, 1.0))[:, None], 0.0)
            beta = beta * weight
            hits = self.caster.first_hit(self.caster.offset_origins(x, step, wi), wi)
            face = np.maximum(hits.face, 0)
            n_y = _normalize(self._interp(face, hits.barycentric, self.normals))
            wo_y = -wi
            alive = ok & hits.hit & (_dot(n_y, wo_y) > 0) & np.any(beta > 0, axis=1)
            y = np.where(alive[:, None], hits.points, x)
            pd, ps, rough = (self._interp(face, hits.barycentric, a) for a in (m.pd, m.ps, m.roughness))
            x, n, wo = y, np.where(alive[:, None], n_y, n), wo_y
            step = self.caster.face_normals[face]
            if np.any(alive):
                a = alive
                contrib = self._next_event(x[a], n[a], wo[a], pd[a], ps[a], rough[a], light_r[a], inten_r[a])
                np.add.at(total, rows[a], beta[a] * contrib)
            # Russian roulette from the second bounce on.
            if depth >= 1:
                survive = np.minimum(beta.max(axis=1), 1.0)
                keep = rng.random(len(rows)) < survive
                beta = beta / np.where(keep, np.maximum(survive, 1e-300), 1.0)[:, None]
                alive &= keep
        return total

    # -- whole observations ------------------------------------------------------

    def render(self, cam_pos, light_pos, intensity, samples: int = 64, seed: int = 0,
               indirect: bool = True, batch_paths: int = 200_000, progress: bool = True,
               points=None):
        """Radiance of every (vertex, light) observation.

        **Arguments:** `cam_pos` `(P, M, 3)`, `light_pos` `(P, M, 3)` [m] for
        the vertices `points` `(P,)` (default: all `N` vertices, `P = N`);
        `intensity` `(M,)` [W/sr]; `samples` indirect paths per observation;
        `seed` makes the result deterministic; `indirect=False` gives the
        exact direct-only image.

        **Returns:** `radiance` `(P, M, 3)` and `stderr` `(P, M, 3)`, the Monte
        Carlo standard error of the indirect part (0 when direct only).
        """
        n_pts, n_lights = cam_pos.shape[:2]
        obs = n_pts * n_lights
        points = np.arange(len(self.vertices)) if points is None else np.asarray(points)
        if len(points) != n_pts or light_pos.shape != cam_pos.shape:
            raise ValueError("cam_pos and light_pos must both be (P, M, 3) for P points")
        idx = np.repeat(points, n_lights)
        cam = cam_pos.reshape(-1, 3)
        light = light_pos.reshape(-1, 3)
        inten = np.tile(np.asarray(intensity, dtype=np.float64), n_pts)
        out = self.direct(idx, cam, light, inten)
        stderr = np.zeros_like(out)
        if indirect and samples > 0:
            total = np.zeros_like(out)
            spread = np.zeros_like(out)
            per_batch = max(1, batch_paths // samples)
            starts = range(0, obs, per_batch)
            seeds = np.random.SeedSequence(seed).spawn(len(starts))
            for s, ss in tqdm(list(zip(starts, seeds)), desc="path tracing", unit="batch",
                              disable=not progress):
                rng = np.random.default_rng(ss)
                sl = slice(s, min(s + per_batch, obs))
                k = sl.stop - sl.start
                rep = lambda a: np.repeat(a[sl], samples, axis=0)  # noqa: E731
                est = self.indirect(rep(idx), rep(cam), rep(light), rep(inten), rng)
                est = est.reshape(k, samples, 3)
                total[sl] = est.mean(axis=1)
                spread[sl] = est.std(axis=1, ddof=1) if samples > 1 else 0.0
            out = out + total
            stderr = spread / np.sqrt(samples)
        return out.reshape(n_pts, n_lights, 3), stderr.reshape(n_pts, n_lights, 3)
