"""Capture sessions: one image per planned light through a serial light rig, resumable.

**Plan** (JSON): the lights to capture, in order. Any of

    {"format": "jaxrefl-capture-plan", "version": 1,
     "lights": [3, 17, {"index": 42, "position": [0.1, 0.05, 1.2]}]}
    {"selected": [3, 17, 42], ...}          (the output of `jaxrefl select-lights --json`)
    [3, 17, 42]

Indices are the controller's light numbers (0-based, distinct); a `position`
[m], when given, is copied into the manifest for later stages.

**Session folder** (`--out`): `light_003.png`, ... (one per planned light,
`light_{index:03d}{ext}`), `manifest.json`, and `.lock` (held while a capture
runs). **Manifest** (JSON, rewritten atomically after every image):
`format` "jaxrefl-capture-manifest", `version` 1, `plan` (`lights`,
`positions`, `sha256` of the plan), `ext`, `created`, `updated`, `complete`,
`images` (plan order; each `light`, `order`, `file`, `bytes`, `sha256`,
`time` ISO 8601 UTC, `session`, optional `position`) and `sessions` (one per
run: `started`, `ended`, `port`, `controller`, `captured`, `result`, `link`
retry counters, `recovery`).

Per light: select it and wait until ready, switch it on, trigger the camera,
which writes the image to a temporary `.tmp-light_003.png` in the folder; the
file is fsynced, hashed and renamed into place, the manifest entry is written
(atomically), and the light goes off. **Resume** (same command again): temporary
`.tmp-*` files are removed, every manifest entry is verified (file present,
size and sha256 equal) and kept, entries that fail and image files without an
entry (a crash between rename and manifest write) are removed, and the lights
still missing are captured. A session refuses a different plan or `ext`.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shlex
import signal
import subprocess
import time
from dataclasses import dataclass
from datetime import datetime, timezone

from ..scan.io import atomic_write, folder_lock
from .serial import LightController, LinkOptions, RigError

__all__ = ["Plan", "CaptureError", "load_plan", "plan_from_json", "shell_camera", "image_name", "capture",
           "MANIFEST"]

PLAN_FORMAT = "jaxrefl-capture-plan"
MANIFEST_FORMAT = "jaxrefl-capture-manifest"
MANIFEST = "manifest.json"
TMP_PREFIX = ".tmp-"
_EXT = re.compile(r"\.[A-Za-z0-9]{1,8}")


class CaptureError(RuntimeError):
    """The camera failed (command exit status, timeout, no file); the capture can be resumed."""


# -- plan ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """Lights to capture in order, `positions` a matching tuple of `(x, y, z)` [m] or None."""

    lights: tuple
    positions: tuple

    def to_json(self) -> dict:
        return {"lights": list(self.lights), "positions": [None if p is None else list(p) for p in self.positions]}

    @property
    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.to_json(), sort_keys=True).encode()).hexdigest()


def plan_from_json(obj) -> Plan:
    """A `Plan` from parsed JSON (see the module docstring); ValueError naming `plan` otherwise."""
    if isinstance(obj, dict):
        if obj.get("format", PLAN_FORMAT) != PLAN_FORMAT or obj.get("version", 1) != 1:
            raise ValueError(f"plan: unsupported format {obj.get('format')!r} version {obj.get('version')!r}")
        items = obj.get("lights", obj.get("selected"))
    else:
        items = obj
    if not isinstance(items, list):
        raise ValueError("plan: expected a list of lights, an object with 'lights', or select-lights --json output")
    if not items:
        raise ValueError("plan: no lights to capture")
    lights, positions = [], []
    for i, item in enumerate(items):
        index, position = (item.get("index"), item.get("position")) if isinstance(item, dict) else (item, None)
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise ValueError(f"plan: lights[{i}]: index must be an integer >= 0, got {index!r}")
        if index in lights:
            raise ValueError(f"plan: lights[{i}]: light {index} is listed twice")
        if position is not None:
            ok = isinstance(position, list) and len(position) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) < float("inf") for v in position)
            if not ok:
                raise ValueError(f"plan: lights[{i}]: position must be 3 finite numbers [m], got {position!r}")
            position = tuple(float(v) for v in position)
        lights.append(index)
        positions.append(position)
    return Plan(tuple(lights), tuple(positions))


def load_plan(path) -> Plan:
    """Read and validate a plan file."""
    with open(path, encoding="utf-8") as fh:
        try:
            obj = json.load(fh)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"plan: {path} is not valid JSON ({exc})") from None
    return plan_from_json(obj)


def image_name(light: int, ext: str) -> str:
    return f"light_{light:03d}{ext}"


# -- camera ----------------------------------------------------------------------------


def shell_camera(template: str, timeout: float = 60.0):
    """A camera callback `(light, out_path)` running a shell command.

    `{out}` in `template` becomes the (quoted) path the command must write the image
    to, `{light}` the light index; both are also in the environment as
    `JAXREFL_OUT` and `JAXREFL_LIGHT`. A non-zero exit or `timeout` [s] raises
    CaptureError (the whole process group is killed on timeout).
    """
    if "{out}" not in template:
        raise ValueError("camera-cmd: must contain {out}, the path the image is to be written to")
    if not timeout > 0:
        raise ValueError(f"camera-timeout: must be > 0, got {timeout}")

    def camera(light: int, out: str) -> None:
        cmd = template.replace("{out}", shlex.quote(out)).replace("{light}", str(int(light)))
        env = dict(os.environ, JAXREFL_OUT=out, JAXREFL_LIGHT=str(int(light)))
        proc = subprocess.Popen(cmd, shell=True, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            _, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise CaptureError(f"camera: light {light}: command timed out after {timeout} s") from None
        if proc.returncode != 0:
            last = (err.decode(errors="replace").strip().splitlines() or [""])[-1]
            raise CaptureError(f"camera: light {light}: command exited with status {proc.returncode}"
                               + (f": {last}" if last else ""))

    return camera


# -- session ---------------------------------------------------------------------------


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _sha256(path) -> tuple[str, int]:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())
        digest = hashlib.file_digest(fh, "sha256").hexdigest()
        return digest, fh.tell()


def _fsync_dir(folder) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # not possible on every platform; the renames are still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _read_manifest(folder, plan: Plan, ext: str):
    """The existing manifest (checked against `plan` and `ext`), or None."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.exists(path):
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            manifest = json.load(fh)
        ok = manifest.get("format") == MANIFEST_FORMAT and manifest.get("version") == 1
        images, sessions, plan_sha = manifest["images"], manifest["sessions"], manifest["plan"]["sha256"]
        ok = ok and isinstance(images, list) and isinstance(sessions, list)
        ok = ok and all(isinstance(e, dict) and {"light", "file", "sha256", "bytes"} <= e.keys()
                        and isinstance(e["light"], int) for e in images)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"manifest: {path} is unreadable ({exc}); use another --out") from None
    if not ok:
        raise ValueError(f"manifest: {path} is not a version 1 capture manifest")
    if plan_sha != plan.sha256:
        raise ValueError(f"plan: differs from the plan session {folder} was started with; use another --out")
    if manifest.get("ext") != ext:
        raise ValueError(f"ext: session {folder} was started with {manifest.get('ext')!r}, not {ext!r}")
    return manifest


def _recover(folder, plan: Plan, manifest: dict, ext: str) -> dict:
    """Make the folder agree with the manifest: drop temporaries, unverifiable entries and
    orphan images. Returns counts; `manifest["images"]` keeps the verified entries."""
    report = {"temporaries_removed": 0, "entries_verified": 0, "entries_dropped": 0, "orphans_removed": 0}
    for name in os.listdir(folder):
        if name.startswith(TMP_PREFIX):
            os.unlink(os.path.join(folder, name))
            report["temporaries_removed"] += 1
    kept = []
    for entry in manifest["images"]:
        path = os.path.join(folder, str(entry["file"]))
        good = (entry["light"] in plan.lights and entry["file"] == image_name(entry["light"], ext)
                and entry["light"] not in {e["light"] for e in kept} and os.path.isfile(path)
                and os.path.getsize(path) == entry["bytes"] and _sha256(path)[0] == entry["sha256"])
        if good:
            kept.append(entry)
        else:
            report["entries_dropped"] += 1
            if entry["file"] == image_name(entry["light"], ext) and os.path.isfile(path):
                os.unlink(path)
    manifest["images"] = kept
    report["entries_verified"] = len(kept)
    done = {e["light"] for e in kept}
    for light in plan.lights:
        path = os.path.join(folder, image_name(light, ext))
        if light not in done and os.path.lexists(path):
            os.unlink(path)
            report["orphans_removed"] += 1
    return report


def capture(plan: Plan, folder, port: str, camera, *, options: LinkOptions = LinkOptions(), ext: str = ".png",
            progress: bool = False) -> dict:
    """Capture (or resume capturing) one image per light of `plan` into `folder`.

    **Arguments:** `plan` a `Plan`; `folder` the session folder (created);
    `port` the controller's serial device; `camera(light, out_path)` writes
    one image to `out_path` (e.g. `shell_camera(...)`); `options` link timing.

    **Returns:** a summary dict (`captured` this run, `recovery`, `complete`, `link`,
    `seconds`, ...). Raises ValueError on bad input (nothing written), `RigError`
    or `CaptureError` when the rig or camera fails: the session is left
    consistent and the same call resumes it; the exception's `saved` attribute
    is `(images saved, images planned)`.
    """
    t0 = time.perf_counter()
    if not isinstance(ext, str) or not _EXT.fullmatch(ext):
        raise ValueError(f"ext: must be a dot and 1-8 letters or digits, got {ext!r}")
    folder = os.fspath(folder)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise ValueError(f"out: {folder} exists and is not a folder")
    manifest = _read_manifest(folder, plan, ext) if os.path.isdir(folder) else None
    try:
        return _capture(plan, folder, port, camera, options, ext, progress, manifest, t0)
    except (RigError, CaptureError, KeyboardInterrupt) as exc:
        if not hasattr(exc, "saved"):  # failed before the session started: count what the manifest holds
            exc.saved = (len(manifest["images"]) if manifest else 0, len(plan.lights))
        raise


def _capture(plan, folder, port, camera, options, ext, progress, manifest, t0) -> dict:
    with LightController(port, options) as ctl:
        ident = ctl.identify()
        n = int(ident["lights"])
        beyond = [k for k in plan.lights if k >= n]
        if beyond:
            raise ValueError(f"plan: light {beyond[0]} is beyond the controller's {n} lights (0-{n - 1})")
        os.makedirs(folder, exist_ok=True)
        with folder_lock(folder, f"out: session {folder} is in use by another capture"):
            manifest = _read_manifest(folder, plan, ext)  # again, under the lock
            if manifest is None:
                manifest = {"format": MANIFEST_FORMAT, "version": 1, "plan": {**plan.to_json(), "sha256": plan.sha256},
                            "ext": ext, "created": _now(), "updated": None, "complete": False, "images": [],
                            "sessions": []}
            for s in manifest["sessions"]:
                if s.get("result") == "running":
                    s["result"] = "ended without a clean exit (crash or kill)"
            recovery = _recover(folder, plan, manifest, ext)
            session = {"started": _now(), "ended": None, "port": port, "controller": ident, "captured": 0,
                       "result": "running", "link": ctl.stats, "recovery": recovery}
            manifest["sessions"].append(session)
            _write_manifest(folder, manifest, plan)
            try:
                _run(plan, folder, ctl, camera, manifest, session, ext, progress)
                session["result"] = "complete"
            except BaseException as exc:
                session["result"] = f"{type(exc).__name__}: {exc}"
                if not isinstance(exc, RigError):
                    try:  # the link still works: leave the rig dark
                        ctl.off()
                    except RigError:
                        pass
                if isinstance(exc, (RigError, CaptureError, KeyboardInterrupt)):
                    exc.saved = (len(manifest["images"]), len(plan.lights))
                raise
            finally:
                session["ended"] = _now()
                _write_manifest(folder, manifest, plan)
    return {"out": folder, "lights": len(plan.lights), "captured": session["captured"],
            "complete": manifest["complete"], "recovery": recovery, "controller": ident, "link": dict(ctl.stats),
            "seconds": time.perf_counter() - t0}


def _run(plan, folder, ctl, camera, manifest, session, ext, progress) -> None:
    done = {e["light"] for e in manifest["images"]}
    todo = [(i, k) for i, k in enumerate(plan.lights) if k not in done]
    if progress:
        from tqdm import tqdm

        todo = tqdm(todo, desc="capture", unit="image", initial=len(done), total=len(plan.lights))
    ctl.off()
    for order, light in todo:
        name = image_name(light, ext)
        tmp, final = os.path.join(folder, TMP_PREFIX + name), os.path.join(folder, name)
        if os.path.lexists(tmp):
            os.unlink(tmp)
        ctl.select(light)
        ctl.on(light)
        try:
            try:
                camera(light, tmp)
            except CaptureError:
                raise
            except Exception as exc:
                raise CaptureError(f"camera: light {light}: {type(exc).__name__}: {exc}") from exc
            if not os.path.isfile(tmp) or os.path.getsize(tmp) == 0:
                raise CaptureError(f"camera: light {light}: no image written to {tmp}")
            digest, size = _sha256(tmp)
            os.replace(tmp, final)
            _fsync_dir(folder)
        finally:
            if os.path.lexists(tmp):
                os.unlink(tmp)
        entry = {"light": light, "order": order, "file": name, "bytes": size, "sha256": digest, "time": _now(),
                 "session": len(manifest["sessions"]) - 1}
        if plan.positions[order] is not None:
            entry["position"] = list(plan.positions[order])
        manifest["images"].append(entry)
        session["captured"] += 1
        _write_manifest(folder, manifest, plan)
        ctl.off()


def _write_manifest(folder, manifest: dict, plan: Plan) -> None:
    order = {k: i for i, k in enumerate(plan.lights)}
    manifest["images"].sort(key=lambda e: order[e["light"]])
    manifest["complete"] = len(manifest["images"]) == len(plan.lights)
    manifest["updated"] = _now()
    text = json.dumps(manifest, indent=1).encode()
    atomic_write(os.path.join(folder, MANIFEST), lambda fh: fh.write(text))
    _fsync_dir(folder)
