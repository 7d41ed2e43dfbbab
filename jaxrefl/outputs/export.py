"""Results as PLY meshes with per-vertex attributes that other tools open.

One binary little-endian PLY (written by trimesh): the scan's vertices
(float32, metres), unit normals `nx ny nz`, the diffuse albedo as 8-bit
sRGB-encoded vertex colours `red green blue alpha` (for viewing), and float32
properties: `pd_r pd_g pd_b` (the linear albedo itself), `ps`, `sigma` or
`ward_alpha` [rad] (by the result's model; not `alpha`, the colour's channel),
`std_pd_r std_pd_g std_pd_b std_ps` and `std_sigma` / `std_ward_alpha` (inf
where unknown); uchar `status` (0
measured, 1 interpolated, 2 unresolved, 3 pooled: `jaxrefl.methods.local.STATUS_NAMES`),
`specular_identifiable` and `pd_measured` (0/1), and where the result has
the shared prior's materials, uchar `material` (the label of each point).
Faces are the scan's triangles.

Reading it back: `load_ply(path)` gives a `trimesh.Trimesh` whose
`vertex_attributes` hold every property above by name::

    mesh = jaxrefl.outputs.export.load_ply("A.ply")
    mesh.vertex_attributes["ps"], mesh.vertex_attributes["status"]  # (N,) float32, uint8

With trimesh alone (5.2's PLY loader keeps custom vertex properties out of
`vertex_attributes`, in the raw PLY elements it stores as metadata)::

    mesh = trimesh.load("A.ply", process=False)
    props = mesh.metadata["_ply_raw"]["vertex"]["data"]  # structured array
    props["ps"], props["pd_r"], props["status"]
"""

from __future__ import annotations

import numpy as np

from .. import srgb
from ..result import ROUGHNESS_NAME, Estimate
from ..scan.io import atomic_write

__all__ = ["result_mesh", "export_ply", "load_ply"]


def result_mesh(vertices, faces, normals, est: Estimate):
    """A `trimesh.Trimesh` of the scan carrying `est` as vertex colours and attributes."""
    import trimesh

    n = len(vertices)
    if len(est.pd) != n:
        raise ValueError(f"result: {len(est.pd)} points, the scan has {n} vertices")
    if est.model not in ROUGHNESS_NAME:
        raise ValueError(f"model: unknown reflectance model {est.model!r}")
    colours = np.concatenate([srgb.from_linear8(est.pd), np.full((n, 1), 255, np.uint8)], axis=1)
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           vertex_normals=np.asarray(normals, dtype=np.float64), vertex_colors=colours,
                           process=False)
    # Ward's roughness is not called `alpha` here: that is the colour's alpha channel, and a
    # second `alpha` property made the file unreadable (trimesh: "PLY is unexpected length!")
    rough = {"ward": "ward_alpha"}.get(est.model, ROUGHNESS_NAME[est.model])
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


#: vertex properties trimesh itself reads into the mesh (position, normal, colour)
_GEOMETRY = ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha")


def load_ply(path):
    """A PLY written by `export_ply` (or any PLY) as a `trimesh.Trimesh` (not processed:
    vertices and faces as in the file) with every extra per-vertex property in
    `mesh.vertex_attributes[name]` `(N,)`, in the file's dtype."""
    import trimesh

    mesh = trimesh.load(path, process=False, force="mesh")
    raw = mesh.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = getattr(getattr(raw, "dtype", None), "names", None) or (raw.keys() if isinstance(raw, dict) else ())
    for name in names:
        if name not in _GEOMETRY:
            mesh.vertex_attributes[name] = np.asarray(raw[name])
    return mesh
