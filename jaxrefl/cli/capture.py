"""`jaxrefl capture`: one image per planned light through a serial light rig (resumable)."""

from __future__ import annotations

import json
import sys

from ._common import progress


def add_capture(sub):
    p = sub.add_parser("capture", help="one image per planned light through a serial light rig (resumable)")
    p.add_argument("plan", help="plan JSON: {\"lights\": [...]}, a list, or select-lights --json output")
    p.add_argument("--out", required=True, help="session folder (images + manifest.json); rerun to resume")
    p.add_argument("--port", default=None, help="serial device of the light controller, e.g. /dev/ttyUSB0")
    p.add_argument("--simulate", nargs="?", const="", default=None, metavar="FAULTS",
                   help="use a simulated controller on a pty instead of --port; optional faults, e.g. "
                        "garble_rate=0.1,seed=1 or disconnect_after=20")
    p.add_argument("--camera-cmd", default=None,
                   help="shell template: must write the image to {out} (a temporary path) for light {light}; "
                        "with --simulate the default writes a small PNG")
    p.add_argument("--ext", default=".png", help="image file extension")
    p.add_argument("--baud", type=int, default=115200)
    p.add_argument("--timeout", type=float, default=0.5, help="reply timeout per try [s]")
    p.add_argument("--retries", type=int, default=3, help="re-sends after a timeout or garbled reply")
    p.add_argument("--backoff", type=float, default=0.05, help="wait before the first re-send [s], doubling")
    p.add_argument("--settle-timeout", type=float, default=10.0, help="time a positioner may take [s]")
    p.add_argument("--camera-timeout", type=float, default=60.0, help="time the camera command may take [s]")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def run_capture(args) -> int:
    from ..capture.serial import LinkOptions, RigError
    from ..capture.session import CaptureError, capture, load_plan, shell_camera
    from ..capture.simulator import Faults, Simulator

    if (args.port is None) == (args.simulate is None):
        raise ValueError("port: give exactly one of --port and --simulate")
    if args.camera_cmd is None and args.simulate is None:
        raise ValueError("camera-cmd: required with --port")
    plan = load_plan(args.plan)
    options = LinkOptions(baudrate=args.baud, timeout=args.timeout, retries=args.retries, backoff=args.backoff,
                          settle_timeout=args.settle_timeout)
    camera = shell_camera(args.camera_cmd, args.camera_timeout) if args.camera_cmd is not None else None
    sim = Simulator(max(60, max(plan.lights) + 1), Faults.parse(args.simulate)) if args.simulate is not None else None
    try:
        summary = capture(plan, args.out, sim.port if sim else args.port, camera or sim.camera, options=options,
                          ext=args.ext, progress=progress())
    except (RigError, CaptureError, KeyboardInterrupt) as exc:
        saved, total = getattr(exc, "saved", (0, len(plan.lights)))
        print(f"jaxrefl capture: error: {str(exc) or 'interrupted'}; {saved} of {total} images saved in {args.out}, "
              "run the same command to resume", file=sys.stderr)
        return 3
    finally:
        if sim is not None:
            sim.stop()
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{args.out}: {summary['captured']} images captured, {summary['recovery']['entries_verified']} "
              f"already there; {'complete' if summary['complete'] else 'incomplete'}")
    return 0


COMMANDS = {"capture": (add_capture, run_capture)}
