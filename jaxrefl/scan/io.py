"""The scan bundle: a versioned `.npz` file every jaxrefl command reads.

Format version 1 (all lengths in metres, angles in radians, `N` vertices,
`M` observations = lights, `F` faces). Required:

| key | shape, dtype | meaning |
|---|---|---|
| `format_version` | scalar int | 1 |
| `vertices` | (N, 3) float | surface points |
| `faces` | (F, 3) int | triangles, indices into `vertices` |
| `light_pos` | (M, 3) or (N, M, 3) float | point-light positions; per point when the lights move with a scanner head |
| `light_intensity` | scalar or (M,) float > 0 | radiant intensity Y [W/sr] of each isotropic point light |
| `cam_pos` | (3,), (M, 3), (N, 1, 3) or (N, M, 3) float | camera centre each observation was seen from |

Optional: `normals` (N, 3) (default: area-weighted vertex normals of the mesh),
`radiance` (N, M, 3) float >= 0 linear RGB [W/(sr m^2)] (absent while planning
a capture), `valid` (N, M) bool (observation exists: in frame and seen by the
camera; default all True), `saturation` scalar (sensor maximum: samples at or
above it are saturated), ground truth `true_pd` (N, 3), `true_ps` (N,),
`true_sigma` (N,) [rad, Torrance-Sparrow], `true_alpha` (N,) [rad, Ward],
`true_normals` (N, 3), and `meta` (a JSON string: provenance, rig, options).

`load_scan` validates everything and raises `ScanError` naming the field.
`save_scan` writes atomically (temporary file in the target folder, then rename), with
mode `0o666 & ~umask`; it refuses to replace an existing path that is not a regular file.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from dataclasses import dataclass, field, fields

import numpy as np
from jaxtyping import Bool, Float, Int

from ..geometry.mesh import area_normal_sums

__all__ = ["FORMAT_VERSION", "Scan", "ScanError", "load_scan", "save_scan", "validate_scan", "atomic_write",
           "check_output_path"]

FORMAT_VERSION = 1


class ScanError(ValueError):
    """A scan bundle failed validation; `field` names the offending key."""

    def __init__(self, field_name: str, message: str):
        super().__init__(f"{field_name}: {message}")
        self.field = field_name


@dataclass(frozen=True)
class Scan:
    """An in-memory scan bundle (see the module docstring for every field)."""

    vertices: Float[np.ndarray, "N 3"]
    faces: Int[np.ndarray, "F 3"]
    light_pos: Float[np.ndarray, "M 3"] | Float[np.ndarray, "N M 3"]
    cam_pos: Float[np.ndarray, " 3"] | Float[np.ndarray, "M 3"] | Float[np.ndarray, "N M 3"]
    light_intensity: Float[np.ndarray, " M"] | float = 1.0
    normals: Float[np.ndarray, "N 3"] | None = None
    radiance: Float[np.ndarray, "N M 3"] | None = None
    valid: Bool[np.ndarray, "N M"] | None = None
    saturation: float | None = None
    true_pd: Float[np.ndarray, "N 3"] | None = None
    true_ps: Float[np.ndarray, " N"] | None = None
    true_sigma: Float[np.ndarray, " N"] | None = None
    true_alpha: Float[np.ndarray, " N"] | None = None
    true_normals: Float[np.ndarray, "N 3"] | None = None
    meta: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_lights(self) -> int:
        return int(self.light_pos.shape[-2])

    def light_positions(self) -> np.ndarray:
        """`(N, M, 3)` light position of every observation (a broadcast view)."""
        lp = self.light_pos if self.light_pos.ndim == 3 else self.light_pos[None]
        return np.broadcast_to(lp, (self.n_points, self.n_lights, 3))

    def camera_positions(self) -> np.ndarray:
        """`(N, M, 3)` camera centre of every observation (a broadcast view)."""
        cp = self.cam_pos.reshape((1,) * (3 - self.cam_pos.ndim) + self.cam_pos.shape)
        return np.broadcast_to(cp, (self.n_points, self.n_lights, 3))

    def intensities(self) -> np.ndarray:
        """`(M,)` radiant intensity of each light [W/sr]."""
        return np.broadcast_to(np.asarray(self.light_intensity, dtype=np.float64), (self.n_lights,))

    def observed(self) -> np.ndarray:
        """`(N, M)` bool: observation present and not saturated (all False without radiance)."""
        if self.radiance is None:
            return np.zeros((self.n_points, self.n_lights), dtype=bool)
        ok = np.ones((self.n_points, self.n_lights), bool) if self.valid is None else self.valid
        if self.saturation is not None:
            ok = ok & ~np.any(self.radiance >= self.saturation, axis=-1)
        return ok


# -- validation ------------------------------------------------------------------


def _float_array(name, value, shapes, *, min_value=None, positive=False):
    """Check `value` is a finite float array of one of `shapes` (None = any size)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise ScanError(name, f"must be a float array, got dtype {arr.dtype}")
    if not any(_shape_matches(arr.shape, s) for s in shapes):
        want = " or ".join(str(tuple("?" if d is None else d for d in s)) for s in shapes)
        raise ScanError(name, f"must have shape {want}, got {arr.shape}")
    arr = arr.astype(np.float64 if arr.dtype != np.float32 else np.float32)
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise ScanError(name, f"contains {bad} non-finite value(s) (NaN or inf)")
    if min_value is not None and arr.size and arr.min() < min_value:
        raise ScanError(name, f"must be >= {min_value}, found {arr.min():.6g}")
    if positive and arr.size and arr.min() <= 0:
        raise ScanError(name, f"must be > 0, found {arr.min():.6g}")
    return arr


def _shape_matches(shape, pattern):
    return len(shape) == len(pattern) and all(p is None or p == s for s, p in zip(shape, pattern))


def winding_numbers(vertices, faces, queries) -> np.ndarray:
    """Generalised winding number of the mesh at each query point `(Q, 3)`.

    About 1 inside a closed, outward-oriented mesh, 0 outside, and a smooth
    in-between for open meshes (van Oosterom-Strackee solid angles).
    """
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    out = np.empty(len(queries))
    chunk = max(1, 1_000_000 // len(tri))  # bounds the (chunk, F, 3) temporaries
    for s in range(0, len(queries), chunk):
        q = np.asarray(queries[s : s + chunk], dtype=np.float64)
        a, b, c = (tri[None, :, k, :] - q[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("qfi,qfi->qf", a, b) * lc
            + np.einsum("qfi,qfi->qf", b, c) * la
            + np.einsum("qfi,qfi->qf", c, a) * lb
        )
        out[s : s + chunk] = np.sum(2.0 * np.arctan2(det, den), axis=1) / (4.0 * np.pi)
    return out


def _check_outside(name, vertices, faces, positions):
    """Reject positions inside the object (winding number > 1/2)."""
    pts = np.unique(np.asarray(positions, dtype=np.float64).reshape(-1, 3), axis=0)
    lo, hi = vertices.min(0), vertices.max(0)
    near = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    if len(near) == 0:
        return
    w = winding_numbers(vertices, faces, near)
    inside = w > 0.5
    if np.any(inside):
        p = near[np.argmax(inside)]
        raise ScanError(
            name, f"{int(inside.sum())} position(s) lie inside the object, e.g. {np.round(p, 4).tolist()}"
        )


def validate_scan(scan: Scan) -> Scan:
    """Check every field of `scan`; return a normalised copy or raise `ScanError`."""
    v = _float_array("vertices", scan.vertices, [(None, 3)]).astype(np.float64)
    n = len(v)
    if n < 3:
        raise ScanError("vertices", f"need at least 3 vertices, got {n}")

    f = np.asarray(scan.faces)
    if f.dtype.kind not in "iu":
        raise ScanError("faces", f"must be an integer array, got dtype {f.dtype}")
    if not _shape_matches(f.shape, (None, 3)) or len(f) == 0:
        raise ScanError("faces", f"must have shape (F, 3) with F >= 1, got {f.shape}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= n:
        raise ScanError("faces", f"indices must lie in [0, {n - 1}], found [{f.min()}, {f.max()}]")
    tri = v[f]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = float(np.linalg.norm(v.max(0) - v.min(0)))
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    degenerate |= area2 <= 1e-12 * max(scale, 1e-300) ** 2
    if scale == 0 or np.all(degenerate):
        raise ScanError("faces", "the mesh is degenerate: every face has zero area")
    if np.any(degenerate):
        raise ScanError(
            "faces",
            f"{int(degenerate.sum())} degenerate face(s) (repeated or collinear vertices), "
            f"first at index {int(np.argmax(degenerate))}; remove them before saving",
        )

    if scan.normals is None:
        nr = area_normal_sums(v, f)
        length = np.linalg.norm(nr, axis=1)
        if np.any(length == 0):
            raise ScanError("normals", f"absent, and {int((length == 0).sum())} vertices belong to no face")
    else:
        nr = _float_array("normals", scan.normals, [(n, 3)]).astype(np.float64)
        length = np.linalg.norm(nr, axis=1)
        if np.any(length < 1e-12):
            raise ScanError("normals", f"{int((length < 1e-12).sum())} zero-length normal(s), "
                            f"first at vertex {int(np.argmax(length < 1e-12))}")
    nr = nr / length[:, None]

    lp = _float_array("light_pos", scan.light_pos, [(None, 3), (n, None, 3)]).astype(np.float64)
    m = lp.shape[-2]
    if m == 0:
        raise ScanError("light_pos", "no lights")
    li = _float_array("light_intensity", scan.light_intensity, [(), (m,)], positive=True)
    cp = _float_array("cam_pos", scan.cam_pos, [(3,), (m, 3), (n, 1, 3), (n, m, 3)]).astype(np.float64)
    _check_outside("light_pos", v, f, lp)
    _check_outside("cam_pos", v, f, cp)

    rad = valid = sat = None
    if scan.radiance is not None:
        rad = _float_array("radiance", scan.radiance, [(n, m, 3)], min_value=0.0)
    if scan.valid is not None:
        valid = np.asarray(scan.valid)
        if valid.dtype != bool or valid.shape != (n, m):
            raise ScanError("valid", f"must be a bool array of shape {(n, m)}, got {valid.dtype} {valid.shape}")
        if rad is None:
            raise ScanError("valid", "given without radiance")
    if scan.saturation is not None:
        sat = float(_float_array("saturation", scan.saturation, [()], positive=True))

    truth = {}
    for name, shape, lo in (
        ("true_pd", (n, 3), 0.0),
        ("true_ps", (n,), 0.0),
        ("true_sigma", (n,), None),
        ("true_alpha", (n,), None),
        ("true_normals", (n, 3), None),
    ):
        value = getattr(scan, name)
        if value is not None:
            positive = name in ("true_sigma", "true_alpha")
            truth[name] = _float_array(name, value, [shape], min_value=lo, positive=positive).astype(np.float64)

    meta = scan.meta if isinstance(scan.meta, dict) else None
    if meta is None:
        raise ScanError("meta", f"must be a JSON object (dict), got {type(scan.meta).__name__}")
    return Scan(
        vertices=v, faces=f, light_pos=lp, cam_pos=cp,
        light_intensity=np.float64(li) if li.ndim == 0 else li.astype(np.float64),
        normals=nr, radiance=rad, valid=valid, saturation=sat, meta=meta, **truth,
    )


# -- files -----------------------------------------------------------------------


def load_scan(path) -> Scan:
    """Read and validate a scan bundle; raises `ScanError` (a `ValueError`) naming the field."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except Exception as exc:  # zipfile / pickle / format errors: not an npz scan bundle
        raise ScanError("file", f"{path} is not a readable .npz scan bundle ({exc})") from None
    if "format_version" not in data:
        raise ScanError("format_version", "missing: not a jaxrefl scan bundle")
    version = data.pop("format_version")
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != FORMAT_VERSION:
        raise ScanError("format_version", f"unsupported version {version!r}, this jaxrefl reads {FORMAT_VERSION}")
    known = {f.name for f in fields(Scan)}
    for required in ("vertices", "faces", "light_pos", "cam_pos", "light_intensity"):
        if required not in data:
            raise ScanError(required, "missing")
    unknown = sorted(set(data) - known)
    if unknown:
        raise ScanError(unknown[0], f"unknown key in a version-{FORMAT_VERSION} bundle")
    if "meta" in data:
        try:
            data["meta"] = json.loads(str(data["meta"]))
        except json.JSONDecodeError as exc:
            raise ScanError("meta", f"not valid JSON ({exc})") from None
    return validate_scan(Scan(**data))


def save_scan(path, scan: Scan) -> None:
    """Validate `scan` and write it to `path` atomically (no partial file on failure)."""
    scan = validate_scan(scan)
    arrays = {"format_version": np.int64(FORMAT_VERSION)}
    for f in fields(Scan):
        value = getattr(scan, f.name)
        if value is None:
            continue
        if f.name == "meta":
            arrays["meta"] = np.asarray(json.dumps(value, sort_keys=True))
        else:
            arrays[f.name] = np.asarray(value)
    atomic_write(path, lambda fh: np.savez(fh, **arrays))


def folder_lock(folder, busy: str):
    """The lock file `folder/.lock`, held exclusively for a `with` block (filelock: `flock`
    on POSIX, `msvcrt` on Windows); `ValueError(busy)` at once when another process, or
    another lock in this one, holds it. The file stays after release."""
    from filelock import FileLock, Timeout

    lock = FileLock(os.path.join(folder, ".lock"), preserve_lock_file=True)
    try:
        return lock.acquire(timeout=0)
    except Timeout:
        raise ValueError(busy) from None


def _umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux /proc)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # not thread-safe, but only where /proc is unavailable
    os.umask(mask)
    return mask


def check_output_path(path, name: str = "out", inputs=(), *, folder: bool = False) -> None:
    """Refuse an output path that would destroy something: an existing path that is not a
    regular file (with `folder`: not a folder), such as a device, FIFO or directory, and a path
    naming the same file as one of `inputs` (paths read by the same command; absent ones are
    skipped). Raises `ValueError` naming the option `name`."""
    path = os.fspath(path)
    if os.path.exists(path):
        if folder and not os.path.isdir(path):
            raise ValueError(f"{name}: {path} exists and is not a folder")
        if not folder and not stat.S_ISREG(os.stat(path).st_mode):
            kind = "a folder" if os.path.isdir(path) else "not a regular file (device, FIFO or socket)"
            raise ValueError(f"{name}: {path} exists and is {kind}; refusing to replace it")
        for inp in inputs:
            if inp is not None and os.path.exists(inp) and os.path.samefile(path, inp):
                raise ValueError(f"{name}: {path} is also an input of this command; "
                                 "writing it would destroy the input")


def atomic_write(path, write) -> None:
    """Call `write(file_object)` on a temporary file beside `path`, then rename it to `path`.

    The file gets mode `0o666 & ~umask` (as `open` would give it). An existing `path`
    that is not a regular file (folder, device, FIFO) is refused with `ValueError`.
    """
    path = os.fspath(path)
    check_output_path(path, "out")
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.basename(path), dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600 whatever the umask
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
