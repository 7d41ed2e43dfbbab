"""Rig geometry: candidate point lights and camera models.

World frame: metres, right-handed, **+y up**. Two camera models:

- `CylindricalScanner` (paper §2.1): a range scanner whose camera and light rack
  ride a head rotating about the vertical (y) axis. A surface point is imaged
  when the head faces it: head angle `phi = atan2(x, z)`, camera at
  `(R sin phi, h, R cos phi)` looking horizontally at the axis. The lights move
  with the head, so every (point, light) pair has its own light position.
- `PinholeCamera`: one fixed calibrated camera, OpenCV convention
  (`x_cam = R x_world + t`, `u = K [x/z, y/z, 1]`, camera y axis pointing down
  in the image), optional distortion `(k1, k2, p1, p2, k3)`.

Light racks are given as offsets `(right, up)` [m] in the plane through the
camera centre perpendicular to its optical axis. The paper's rack holds 60
positions on a 2-D grid at 5 cm spacing around the camera (`paper_light_rack`).

`observation_geometry` turns points, normals, camera and light positions into
the per-(point, light) arrays every later stage uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .vectors import shading_geometry

__all__ = [
    "paper_light_rack",
    "CylindricalScanner",
    "PinholeCamera",
    "ObservationGeometry",
    "observation_geometry",
    "observation_angles",
]


def paper_light_rack(columns: int = 10, rows: int = 6, spacing: float = 0.05) -> np.ndarray:
    """Offsets `(K, 2)` [m] of a `columns x rows` grid centred on the camera.

    Default: the paper's 60 candidate positions at 5 cm spacing (Fig. 3), with
    the camera in the middle of the grid (no light on the optical axis).
    Ordered row by row from bottom-left.
    """
    if columns < 1 or rows < 1 or spacing <= 0:
        raise ValueError("paper_light_rack: columns, rows must be >= 1 and spacing > 0")
    xs = (np.arange(columns) - (columns - 1) / 2.0) * spacing
    ys = (np.arange(rows) - (rows - 1) / 2.0) * spacing
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


@dataclass(frozen=True)
class CylindricalScanner:
    """Rotating-head scanner (paper §2.1) with its light rack.

    **Fields:** `radius` camera distance from the rotation (y) axis [m];
    `height` camera height y [m]; `rack` `(K, 2)` light offsets `(right, up)`
    [m] in the head frame, where *right* is `forward x up`.
    """

    radius: float = 0.6
    height: float = 0.1
    rack: np.ndarray = field(default_factory=paper_light_rack)

    def __post_init__(self):
        if not self.radius > 0:
            raise ValueError("CylindricalScanner.radius must be > 0")
        rack = np.asarray(self.rack, dtype=np.float64)
        if rack.ndim != 2 or rack.shape[1] != 2:
            raise ValueError(f"CylindricalScanner.rack must be (K, 2), got {rack.shape}")
        object.__setattr__(self, "rack", rack)

    def head_angle(self, points: np.ndarray) -> np.ndarray:
        """`(N,)` head angle [rad] at which each point `(N, 3)` is imaged."""
        points = np.asarray(points, dtype=np.float64)
        return np.arctan2(points[:, 0], points[:, 2])

    def _frame(self, phi):
        s, c = np.sin(phi), np.cos(phi)
        cam = np.stack([self.radius * s, np.full_like(s, self.height), self.radius * c], -1)
        forward = np.stack([-s, np.zeros_like(s), -c], -1)
        up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), cam.shape)
        right = np.cross(forward, up)
        return cam, right, up

    def camera_positions(self, points: np.ndarray) -> np.ndarray:
        """`(N, 3)` camera centre for each point `(N, 3)`."""
        return self._frame(self.head_angle(points))[0]

    def light_positions(self, points: np.ndarray) -> np.ndarray:
        """`(N, K, 3)` position of every rack light when each point is imaged."""
        cam, right, up = self._frame(self.head_angle(points))
        return (
            cam[:, None, :]
            + self.rack[None, :, 0, None] * right[:, None, :]
            + self.rack[None, :, 1, None] * up[:, None, :]
        )


@dataclass(frozen=True)
class PinholeCamera:
    """Calibrated pinhole camera, OpenCV convention.

    **Fields:** `K` `(3, 3)` intrinsics [px]; `R` `(3, 3)` world-to-camera
    rotation; `t` `(3,)` translation [m]; `width`, `height` [px]; `dist`
    `(5,)` OpenCV distortion `(k1, k2, p1, p2, k3)`, zeros for none.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        for name, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("dist", (5,))):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"PinholeCamera.{name} must be finite {shape}, got {value.shape}")
            object.__setattr__(self, name, value)
        if not np.linalg.cond(self.K) < 1e12:
            raise ValueError("PinholeCamera.K must be invertible, got a singular matrix")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            raise ValueError("PinholeCamera.R must be a rotation matrix")
        if self.width < 1 or self.height < 1:
            raise ValueError("PinholeCamera.width and height must be >= 1")

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), fov_deg=30.0, width=640, height=480):
        """Camera at `eye` looking at `target`, vertical field of view `fov_deg`."""
        eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:
            raise ValueError("PinholeCamera.look_at: up is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # image y points down
        R = np.stack([x, y, z])
        f = 0.5 * height / np.tan(np.radians(fov_deg) / 2.0)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0, 0, 1.0]])
        return cls(K=K, R=R, t=-R @ eye, width=width, height=height)

    @property
    def center(self) -> np.ndarray:
        """`(3,)` camera centre in world coordinates [m]."""
        return -self.R.T @ self.t

    def rack_positions(self, rack: np.ndarray) -> np.ndarray:
        """`(K, 3)` world positions of rack offsets `(K, 2)` (right, up) around the camera."""
        rack = np.asarray(rack, dtype=np.float64)
        right, up = self.R[0], -self.R[1]
        return self.center + rack[:, :1] * right + rack[:, 1:2] * up

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates `(N, 2)` (x right, y down, pixel centres at integers)
        and depth `(N,)` [m] of world points `(N, 3)`; depth <= 0 is behind."""
        pc = np.asarray(points, dtype=np.float64) @ self.R.T + self.t
        z = pc[:, 2]
        zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
        x, y = pc[:, 0] / zs, pc[:, 1] / zs
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        uv = np.stack([xd, yd, np.ones_like(xd)], -1) @ self.K.T
        return uv[:, :2], z

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins `(H*W, 3)` and unit directions `(H*W, 3)` through every pixel
        centre, row-major; distortion is ignored (rays of the ideal pinhole)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], -1).astype(np.float64)
        d = np.linalg.solve(self.K, pix.T).T @ self.R
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.center, d.shape).copy(), d


class ObservationGeometry(NamedTuple):
    """Per-(point, light) geometry, every field `(N, M)` unless stated.

    `to_light`, `to_camera`: `(N, M, 3)` unit vectors from the point;
    `light_distance`, `camera_distance` [m]; `cos_i`, `cos_o`: cosines with
    the normal (may be <= 0: not measurable); `theta_r` [rad] half-vector angle.
    """

    to_light: jax.Array
    to_camera: jax.Array
    light_distance: jax.Array
    camera_distance: jax.Array
    cos_i: jax.Array
    cos_o: jax.Array
    theta_r: jax.Array


def _unit_and_length(d):
    length = jnp.sqrt(jnp.sum(d * d, axis=-1))
    safe = jnp.where(length > 0, length, 1.0)
    return d / safe[..., None], length


@jax.jit
def _geometry_rows(points, normals, cam_pos, light_pos):
    def row(p, n, c, lp):  # one point (3,) against its M lights (M, 3)
        l, dl = _unit_and_length(lp - p[None])
        v, dv = _unit_and_length(c - p[None])
        cos_i, cos_o, theta_r = shading_geometry(n[None], l, v)
        return ObservationGeometry(l, v, dl, dv, cos_i, cos_o, theta_r)

    return jax.vmap(row)(points, normals, cam_pos, light_pos)


@jax.jit
def _angle_rows(points, normals, cam_pos, light_pos):
    def row(p, n, c, lp):
        l, _ = _unit_and_length(lp - p[None])
        v, _ = _unit_and_length(c - p[None])
        return shading_geometry(n[None], l, v)

    return jax.vmap(row)(points, normals, cam_pos, light_pos)


def _checked(name, value, shapes):
    """`value` as a jax array of one of `shapes` (None: any size), finite; else ValueError(name).
    Traced values (inside jit) are checked for shape only."""
    arr = jnp.asarray(value)
    if not any(len(arr.shape) == len(s) and all(d is None or d == a for a, d in zip(arr.shape, s))
               for s in shapes):
        want = " or ".join(str(tuple("?" if d is None else d for d in s)) for s in shapes)
        raise ValueError(f"{name}: must have shape {want}, got {arr.shape}")
    if not isinstance(arr, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(arr))):
        bad = int(jnp.sum(~jnp.isfinite(arr)))
        raise ValueError(f"{name}: contains {bad} non-finite value(s) (NaN or inf)")
    return arr


def _broadcast_rows(points, normals, cam_pos, light_pos):
    """Check the arguments of `observation_geometry` (ValueError naming the argument) and
    broadcast them to `(N, 3)`, `(N, 3)`, `(N, M, 3)`, `(N, M, 3)`."""
    points = _checked("points", points, [(None, 3)])
    n = points.shape[0]
    normals = _checked("normals", normals, [(n, 3)])
    light_pos = _checked("light_pos", light_pos, [(None, 3), (n, None, 3)])
    if light_pos.ndim == 2:
        light_pos = jnp.broadcast_to(light_pos, (n, *light_pos.shape))
    m = light_pos.shape[1]
    cam_pos = _checked("cam_pos", cam_pos, [(3,), (m, 3), (n, 1, 3), (n, m, 3)])
    cam_pos = jnp.broadcast_to(cam_pos.reshape((1,) * (3 - cam_pos.ndim) + cam_pos.shape), (n, m, 3))
    return points, normals, cam_pos, light_pos


def observation_angles(points, normals, cam_pos, light_pos):
    """`(cos_i, cos_o, theta_r)`, each `(N, M)`: `observation_geometry` without the
    vector fields (a lighter pass for classification). Arguments as there."""
    points, normals, cam_pos, light_pos = _broadcast_rows(points, normals, cam_pos, light_pos)
    return _angle_rows(points, normals, cam_pos, light_pos)


def observation_geometry(points, normals, cam_pos, light_pos) -> ObservationGeometry:
    """Geometry of every (point, light) observation.

    **Arguments:** `points` `(N, 3)`; `normals` `(N, 3)` unit; `cam_pos`
    `(3,)`, `(M, 3)` or `(N, M, 3)`; `light_pos` `(M, 3)` or `(N, M, 3)` [m].

    **Returns:** `ObservationGeometry` with `(N, M)` fields. Raises `ValueError` naming the
    argument for a wrong shape or a non-finite value.
    """
    points, normals, cam_pos, light_pos = _broadcast_rows(points, normals, cam_pos, light_pos)
    return _geometry_rows(points, normals, cam_pos, light_pos)
