"""Capture sessions over the pty simulator: full runs, faults, crashes and resumes (no mocks)."""

import fcntl
import hashlib
import json
import os
import subprocess
import sys

import pytest

from jaxrefl.capture.serial import (
    ControllerDisconnected,
    ControllerSilent,
    LinkOptions,
    ProtocolError,
    RigError,
)
from jaxrefl.capture.session import MANIFEST, CaptureError, capture, load_plan, plan_from_json, shell_camera
from jaxrefl.capture.simulator import Faults, Simulator

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LIGHTS = [0, 3, 5, 7, 11, 14, 18, 22, 29, 33, 41, 57]
PLAN = plan_from_json({"lights": LIGHTS})
FAST = LinkOptions(timeout=0.1, retries=3, backoff=0.01)


class Camera:
    """Writes what the controller has lit into the image; counts its calls."""

    def __init__(self, sim):
        self.sim, self.calls = sim, []

    def __call__(self, light, out):
        self.calls.append(light)
        with open(out, "wb") as fh:
            fh.write(f"light={light} lit={self.sim.lit()}\n".encode() + bytes(range(256)))


def check_session(folder, lights=LIGHTS, ext=".png"):
    """Independent check: one verified image per light in plan order, nothing else, no temporaries."""
    with open(os.path.join(folder, MANIFEST)) as fh:
        manifest = json.load(fh)
    images = manifest["images"]
    assert [e["light"] for e in images] == lights
    for e in images:
        data = open(os.path.join(folder, e["file"]), "rb").read()
        assert e["file"] == f"light_{e['light']:03d}{ext}"
        assert hashlib.sha256(data).hexdigest() == e["sha256"] and len(data) == e["bytes"]
        assert data.startswith(f"light={e['light']} lit={e['light']}\n".encode())  # lit when triggered
    assert sorted(os.listdir(folder)) == sorted([e["file"] for e in images] + [MANIFEST, ".lock"])
    assert manifest["complete"] and manifest["plan"]["lights"] == lights
    return manifest


def partial_check(folder, temporaries=False):
    """Mid-session: every manifest entry verifies, no temporary file (unless allowed)."""
    manifest = json.load(open(os.path.join(folder, MANIFEST)))
    for e in manifest["images"]:
        assert hashlib.sha256(open(os.path.join(folder, e["file"]), "rb").read()).hexdigest() == e["sha256"]
    assert temporaries or not [n for n in os.listdir(folder) if n.startswith(".tmp-")]
    return manifest


def test_full_capture_of_12_lights(tmp_path):
    with Simulator(60) as sim:
        cam = Camera(sim)
        summary = capture(PLAN, tmp_path / "s", sim.port, cam, options=FAST)
        assert sim.lit() is None  # dark at the end
    assert summary["captured"] == 12 and summary["complete"] and summary["link"]["retries"] == 0
    assert cam.calls == LIGHTS and sim.lit_log == LIGHTS
    m = check_session(tmp_path / "s")
    assert [s["result"] for s in m["sessions"]] == ["complete"]
    # running it again captures nothing and changes no image
    with Simulator(60) as sim:
        cam2 = Camera(sim)
        again = capture(PLAN, tmp_path / "s", sim.port, cam2, options=FAST)
    assert again["captured"] == 0 and again["recovery"]["entries_verified"] == 12 and cam2.calls == []
    assert check_session(tmp_path / "s")["images"] == m["images"]


def test_garbled_replies_within_the_retry_budget(tmp_path):
    with Simulator(60, Faults(garble_rate=0.25, drop_rate=0.05, corrupt=frozenset({4, 9}), seed=2)) as sim:
        cam = Camera(sim)
        summary = capture(PLAN, tmp_path / "s", sim.port, cam, options=LinkOptions(timeout=0.1, retries=8,
                                                                                   backoff=0.005))
    assert summary["link"]["garbled"] >= 3 and summary["link"]["retryable_errors"] >= 1
    assert cam.calls == LIGHTS
    check_session(tmp_path / "s")


def test_garbled_replies_beyond_the_retry_budget_resume(tmp_path):
    calls, sessions = [], 0
    for seed in range(1, 40):
        with Simulator(60, Faults(garble_rate=0.25, seed=seed)) as sim:
            cam = Camera(sim)
            sessions += 1
            try:
                capture(PLAN, tmp_path / "s", sim.port, cam, options=LinkOptions(timeout=0.05, retries=1,
                                                                                 backoff=0.0))
                calls += cam.calls
                break
            except ProtocolError as exc:
                calls += cam.calls
                assert exc.saved[1] == 12
                partial_check(tmp_path / "s")
    assert sorted(calls) == sorted(LIGHTS)  # every light captured exactly once over all sessions
    m = check_session(tmp_path / "s")
    # sessions that failed on ID never touched the folder
    assert 2 <= len(m["sessions"]) <= sessions and m["sessions"][-1]["result"] == "complete"


def test_silent_controller_then_resume(tmp_path):
    with Simulator(60, Faults(silent_after=20)) as sim:
        cam = Camera(sim)
        with pytest.raises(ControllerSilent) as err:
            capture(PLAN, tmp_path / "s", sim.port, cam, options=FAST)
        first = list(cam.calls)
        saved = err.value.saved[0]
        assert 0 < saved < 12 and saved == len(partial_check(tmp_path / "s")["images"])
        sim.power_cycle(Faults())  # answers again, with its state reset
        summary = capture(PLAN, tmp_path / "s", sim.port, cam, options=FAST)
    assert summary["captured"] == 12 - saved and summary["recovery"]["entries_verified"] == saved
    assert cam.calls == LIGHTS and first == LIGHTS[:len(first)]  # no image lost, none taken twice
    m = check_session(tmp_path / "s")
    assert m["sessions"][0]["result"].startswith("ControllerSilent")


def test_disconnect_halfway_then_resume_with_a_new_controller(tmp_path):
    with Simulator(60, Faults(disconnect_after=25)) as sim:
        cam = Camera(sim)
        with pytest.raises(ControllerDisconnected) as err:
            capture(PLAN, tmp_path / "s", sim.port, cam, options=FAST)
        assert sim.hung_up
    saved = err.value.saved[0]
    assert 3 <= saved <= 9 and saved == len(partial_check(tmp_path / "s")["images"])
    with Simulator(60) as sim2:  # a new controller on a new port
        cam.sim = sim2
        summary = capture(PLAN, tmp_path / "s", sim2.port, cam, options=FAST)
    assert summary["captured"] == 12 - saved
    assert cam.calls == LIGHTS
    m = check_session(tmp_path / "s")
    assert m["sessions"][0]["result"].startswith("ControllerDisconnected")
    assert {e["session"] for e in m["images"]} == {0, 1}


def test_damaged_session_is_repaired_on_resume(tmp_path):
    folder = tmp_path / "s"
    with Simulator(60) as sim:
        capture(PLAN, folder, sim.port, Camera(sim), options=FAST)
    (folder / "light_005.png").write_bytes(b"overwritten")          # hash mismatch
    (folder / "light_029.png").unlink()                            # missing
    (folder / ".tmp-light_033.png").write_bytes(b"half an im")     # a crash while writing
    m = json.loads((folder / MANIFEST).read_text())
    m["images"] = [e for e in m["images"] if e["light"] != 57]     # crash between rename and manifest
    (folder / MANIFEST).write_text(json.dumps(m))
    with Simulator(60) as sim:
        cam = Camera(sim)
        summary = capture(PLAN, folder, sim.port, cam, options=FAST)
    assert summary["recovery"] == {"temporaries_removed": 1, "entries_verified": 9, "entries_dropped": 2,
                                   "orphans_removed": 1}
    assert cam.calls == [5, 29, 57]
    check_session(folder)


def test_camera_failures_leave_the_session_resumable(tmp_path):
    folder = tmp_path / "s"
    with Simulator(60) as sim:
        def failing(light, out):
            if light == 11:
                open(out, "wb").write(b"partial")
                raise OSError("camera unplugged")
            Camera(sim)(light, out)

        with pytest.raises(CaptureError, match="camera: light 11: OSError: camera unplugged") as err:
            capture(PLAN, folder, sim.port, failing, options=FAST)
        assert err.value.saved == (4, 12) and sim.lit() is None  # the light was switched off
        partial_check(folder)
        with pytest.raises(CaptureError, match="no image written"):
            capture(PLAN, folder, sim.port, lambda light, out: None, options=FAST)
        capture(PLAN, folder, sim.port, Camera(sim), options=FAST)
    check_session(folder)


def test_shell_camera(tmp_path):
    cam = shell_camera("printf 'light=%s lit=%s\\n' {light} $JAXREFL_LIGHT > {out}")
    out = tmp_path / "a b.png"  # a path that needs quoting
    cam(7, str(out))
    assert out.read_bytes() == b"light=7 lit=7\n"
    with pytest.raises(CaptureError, match="status 3: nope"):
        shell_camera("echo nope >&2; exit 3; : {out}")(1, str(out))
    with pytest.raises(CaptureError, match="timed out"):
        shell_camera("sleep 5; : {out}", timeout=0.2)(1, str(out))
    with pytest.raises(ValueError, match="camera-cmd"):
        shell_camera("touch x")


def test_plan_formats(tmp_path):
    sel = tmp_path / "sel.json"
    sel.write_text(json.dumps({"selected": [4, 2, 9], "diffuse_only_count": 1}))  # select-lights --json
    assert load_plan(sel).lights == (4, 2, 9)
    assert plan_from_json([1, 0]).lights == (1, 0)
    plan = plan_from_json({"format": "jaxrefl-capture-plan", "version": 1,
                           "lights": [{"index": 2, "position": [0.1, 0.2, 1.0]}, 5]})
    with Simulator(12) as sim:
        capture(plan, tmp_path / "s", sim.port, Camera(sim), options=FAST)
    m = check_session(tmp_path / "s", [2, 5])
    assert m["images"][0]["position"] == [0.1, 0.2, 1.0] and "position" not in m["images"][1]


@pytest.mark.parametrize("obj, msg", [
    ({"lights": []}, "no lights"),
    ({"lights": [1, 1]}, "listed twice"),
    ({"lights": [-1]}, "integer >= 0"),
    ({"lights": [True]}, "integer >= 0"),
    ({"lights": [{"index": 1, "position": [0, 1]}]}, "position"),
    ({"lights": [{"index": 1, "position": [0, 1, float("nan")]}]}, "position"),
    ({"format": "other"}, "format"),
    ({"nothing": 1}, "expected a list"),
])
def test_bad_plans(obj, msg):
    with pytest.raises(ValueError, match=f"plan: .*{msg}"):
        plan_from_json(obj)


def test_bad_input_writes_nothing(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="plan: .* not valid JSON"):
        load_plan(bad)
    with Simulator(12) as sim:
        with pytest.raises(ValueError, match="plan: light 14 is beyond the controller's 12 lights"):
            capture(PLAN, tmp_path / "s", sim.port, Camera(sim), options=FAST)
        with pytest.raises(ValueError, match="ext"):
            capture(PLAN, tmp_path / "s", sim.port, Camera(sim), ext="png")
        assert not (tmp_path / "s").exists()
        first = plan_from_json([1, 2])
        capture(first, tmp_path / "s", sim.port, Camera(sim), options=FAST)
        before = {p.name: p.read_bytes() for p in (tmp_path / "s").iterdir()}
        with pytest.raises(ValueError, match="plan: differs"):
            capture(plan_from_json([1, 3]), tmp_path / "s", sim.port, Camera(sim), options=FAST)
        with pytest.raises(ValueError, match="ext: .*'.png'"):
            capture(first, tmp_path / "s", sim.port, Camera(sim), options=FAST, ext=".tif")
        with open(tmp_path / "s" / ".lock") as fh:  # another capture holds the session
            fcntl.flock(fh, fcntl.LOCK_EX)
            with pytest.raises(ValueError, match="in use"):
                capture(first, tmp_path / "s", sim.port, Camera(sim), options=FAST)
        assert {p.name: p.read_bytes() for p in (tmp_path / "s").iterdir()} == before
    with pytest.raises(RigError, match="port: cannot open"):
        capture(first, tmp_path / "t", str(tmp_path / "no-tty"), Camera(None), options=FAST)
    assert not (tmp_path / "t").exists()


# -- the command line --------------------------------------------------------------------


def jaxrefl(*args):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "jaxrefl.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=120)


CAMERA_CMD = ("printf 'light=%s lit=' {light} > {out}; cat \"$LIT_FILE\" >> {out}; "
              "if [ {light} = 14 ] && [ ! -e \"$CRASH_MARK\" ]; then touch \"$CRASH_MARK\"; kill -9 $PPID; fi; "
              "printf '\\n' >> {out}")


def test_cli_crash_and_silence_then_resume_with_the_same_command(tmp_path, monkeypatch):
    """A real SIGKILL while the camera writes, then a controller that goes silent: the same
    command resumes each time; the camera reads the lit light from a file the test keeps up."""
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"lights": [2, 2]}))
    r = jaxrefl("capture", plan, "--out", tmp_path / "t", "--simulate")
    assert r.returncode == 2 and r.stderr.strip() == "jaxrefl capture: error: plan: lights[1]: light 2 is listed twice"
    assert not (tmp_path / "t").exists()
    plan.write_text(json.dumps({"lights": LIGHTS}))
    lit_file = tmp_path / "lit"
    monkeypatch.setenv("LIT_FILE", str(lit_file))
    monkeypatch.setenv("CRASH_MARK", str(tmp_path / "crashed"))
    with Simulator(60, state_file=str(lit_file)) as sim:
        out = tmp_path / "session"
        cmd = ("capture", plan, "--out", out, "--port", sim.port, "--camera-cmd", CAMERA_CMD, "--timeout", 0.2,
               "--retries", 2, "--backoff", 0.01, "--json")
        r = jaxrefl(*cmd)
        assert r.returncode == -9  # killed mid-image
        assert (out / ".tmp-light_014.png").exists()  # a partial image left behind
        assert len(partial_check(out, temporaries=True)["images"]) == 5
        sim.power_cycle(Faults(silent_after=10))
        r = jaxrefl(*cmd)
        assert r.returncode == 3 and r.stdout == ""
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("jaxrefl capture: error: controller: no answer")
        assert "run the same command to resume" in lines[0]
        assert not (out / ".tmp-light_014.png").exists()
        saved = len(partial_check(out)["images"])
        assert 5 < saved < 12
        sim.power_cycle(Faults())
        r = jaxrefl(*cmd)
        assert r.returncode == 0, r.stderr
        summary = json.loads(r.stdout)
        assert summary["complete"] and summary["captured"] == 12 - saved
    m = check_session(out)
    results = [s["result"] for s in m["sessions"]]
    assert results[0].startswith("ended without a clean exit") and results[1].startswith("ControllerSilent")
    assert results[2] == "complete"


@pytest.mark.slow
def test_cli_simulate(tmp_path):
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps([2, 4, 6]))
    r = jaxrefl("capture", plan, "--out", tmp_path / "s", "--simulate", "disconnect_after=5", "--timeout", 0.1)
    assert r.returncode == 3 and len(r.stderr.strip().splitlines()) == 1 and "lost the line" in r.stderr
    r = jaxrefl("capture", plan, "--out", tmp_path / "s", "--simulate", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["complete"]
    m = json.loads((tmp_path / "s" / MANIFEST).read_text())
    assert [e["light"] for e in m["images"]] == [2, 4, 6] and len(m["sessions"]) == 2
    r = jaxrefl("capture", plan, "--out", tmp_path / "s", "--port", "/dev/null", "--simulate")
    assert r.returncode == 2 and "exactly one of --port and --simulate" in r.stderr
