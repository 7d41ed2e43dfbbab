"""Results as PLY meshes with per-vertex attributes that other tools open.

One binary little-endian PLY (written by trimesh): the scan's vertices
(float32, metres), unit normals `nx ny nz`, the diffuse albedo as 8-bit
sRGB-encoded vertex colours `red green blue alpha` (for viewing), and float32
properties: `pd_r pd_g pd_b` (the linear albedo itself), `ps`, `sigma` or
`alpha` [rad] (by the result's model), `std_pd_r std_pd_g std_pd_b std_ps`
and `std_sigma` / `std_alpha` (inf where unknown); uchar `status` (0
measured, 1 interpolated, 2 unresolved, 3 pooled: `jaxrefl.local.STATUS_NAMES`),
`specular_identifiable` and `pd_measured` (0/1), and where the result has
the shared prior's materials, uchar `material` (the label of each point).
Faces are the scan's triangles.
"""

from __future__ import annotations

import numpy as np

from .io import atomic_write
from .local import ROUGHNESS_NAME, Estimate

__all__ = ["result_mesh", "export_ply"]


def _srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def result_mesh(vertices, faces, normals, est: Estimate):
    """A `trimesh.Trimesh` of the scan carrying `est` as vertex colours and attributes."""
    import trimesh

    n = len(vertices)
    if len(est.pd) != n:
        raise ValueError(f"result: {len(est.pd)} points, the scan has {n} vertices")
    if est.model not in ROUGHNESS_NAME:
        raise ValueError(f"model: unknown reflectance model {est.model!r}")
    colours = np.concatenate([_srgb8(est.pd), np.full((n, 1), 255, np.uint8)], axis=1)
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           vertex_normals=np.asarray(normals, dtype=np.float64), vertex_colors=colours,
                           process=False)
    rough = ROUGHNESS_NAME[est.model]
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    attrs = {f"pd_{c}": f32(est.pd[:, k]) for k, c in enumerate("rgb")}
    attrs.update({"ps": f32(est.ps), rough: f32(est.roughness)})
    attrs.update({f"std_pd_{c}": f32(est.std_pd[:, k]) for k, c in enumerate("rgb")})
    attrs.update({"std_ps": f32(est.std_ps), f"std_{rough}": f32(est.std_roughness),
                  "status": np.asarray(est.status, dtype=np.uint8),
                  "specular_identifiable": np.asarray(est.specular_identifiable, dtype=np.uint8),
                  "pd_measured": np.asarray(est.pd_measured, dtype=np.uint8)})
    if est.material is not None:
        attrs["material"] = np.asarray(est.material, dtype=np.uint8)
    for name, value in attrs.items():
        if np.any(np.isnan(value)):
            raise ValueError(f"{name}: {int(np.isnan(value).sum())} NaN value(s) in the result")
        mesh.vertex_attributes[name] = value
    return mesh


def export_ply(path, vertices, faces, normals, est: Estimate) -> None:
    """Write `est` on the scan's mesh as a binary PLY to `path` atomically (see the module docstring)."""
    data = result_mesh(vertices, faces, normals, est).export(file_type="ply", encoding="binary",
                                                             vertex_normal=True)
    atomic_write(path, lambda fh: fh.write(data))
