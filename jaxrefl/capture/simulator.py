"""A simulated light-rig controller on a real pseudo-terminal, with fault injection.

`Simulator` opens a pty pair (`os.openpty`), puts it in raw mode and serves the
line protocol of `jaxrefl.capture.serial` on the master end from a thread; the host
opens `sim.port` (the slave device path) with pyserial exactly as it would open
`/dev/ttyUSB0`. Faults (`Faults`) are injected per request, counted 1, 2, ... in
arrival order: replies garbled in transit (a flipped character, a line cut short
before its LF, line noise in front), replies dropped, requests that arrive
garbled (answered E01), a controller that stops answering, one that hangs up the
line (closes its pty end: the host's reads and writes fail), a faulty lamp (E06)
and a positioner that needs `settle` seconds after SEL (E04 meanwhile).

Dry run from a shell:

    python3 -m jaxrefl.capture.simulator --lights 12 --faults garble_rate=0.1,seed=1

prints the port to give `jaxrefl capture --port` and serves until interrupted.
`jaxrefl capture --simulate [FAULTS]` starts one in-process instead.
"""

from __future__ import annotations

import argparse
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass

from .serial import MAX_LINE, PROTOCOL_VERSION, ProtocolError, encode_reply, parse_request

__all__ = ["Faults", "Simulator"]

_SETS = ("garble", "drop", "corrupt", "lamp_fail")
_INTS = ("silent_after", "disconnect_after", "seed")
_FLOATS = ("garble_rate", "drop_rate", "settle", "latency")


@dataclass(frozen=True)
class Faults:
    """What goes wrong. Sets hold request ordinals (1-based, in arrival order), except
    `lamp_fail`, which holds light indices. `silent_after` / `disconnect_after`: answer
    that many requests, then ignore all / hang up. Rates draw from a `seed`ed generator.
    `settle` [s]: positioner travel time after SEL; `latency` [s]: delay of every reply."""

    garble: frozenset = frozenset()
    drop: frozenset = frozenset()
    corrupt: frozenset = frozenset()
    lamp_fail: frozenset = frozenset()
    garble_rate: float = 0.0
    drop_rate: float = 0.0
    silent_after: int | None = None
    disconnect_after: int | None = None
    settle: float = 0.0
    latency: float = 0.0
    seed: int = 0

    @classmethod
    def parse(cls, text: str) -> Faults:
        """From `key=value,...`; sets as `+`-separated integers, e.g.
        `garble=3+8,drop_rate=0.1,disconnect_after=20` ('' = no faults)."""
        kwargs = {}
        for item in filter(None, (t.strip() for t in text.split(","))):
            key, eq, value = item.partition("=")
            try:
                if not eq:
                    raise ValueError("expected key=value")
                if key in _SETS:
                    kwargs[key] = frozenset(int(v) for v in value.split("+") if v)
                elif key in _INTS:
                    kwargs[key] = int(value)
                elif key in _FLOATS:
                    kwargs[key] = float(value)
                    if not 0 <= kwargs[key] < float("inf") or (key.endswith("rate") and kwargs[key] > 1):
                        raise ValueError("out of range")
                else:
                    raise ValueError(f"unknown fault (known: {', '.join(_SETS + _INTS + _FLOATS)})")
            except ValueError as exc:
                raise ValueError(f"simulate: {item!r}: {exc}") from None
        return cls(**kwargs)


class Simulator:
    """The controller of `lights` lights served on a pty; `port` is the device path.

    Inspect `lit()` (the light that is on, or None), `log` (received request lines,
    decoded), `lit_log` (the light index each time a light went on) and `received`;
    with `state_file`, the lit light's index (empty when dark) is kept in that file,
    so an external dry-run camera command can check it.
    `power_cycle(faults)` resets the controller's state and faults (a silent one
    answers again); `hang_up()` (or `stop()`) ends the thread and closes the line.
    """

    def __init__(self, lights: int = 60, faults: Faults = Faults(), name: str = "LIGHTRIG-SIM", fw: str = "1.0",
                 state_file: str | None = None):
        if lights < 1:
            raise ValueError(f"lights: must be >= 1, got {lights}")
        self.lights, self.name, self.fw, self.state_file = lights, name, fw, state_file
        self._published = ()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no CR/LF translation, even before the host configures it
        self.port = os.ttyname(self._slave)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.log: list[str] = []
        self.lit_log: list[int] = []
        self.received = 0
        self.hung_up = False
        self.power_cycle(faults)
        self._thread = threading.Thread(target=self._serve, name=f"rig-sim {self.port}", daemon=True)
        self._thread.start()

    # -- control from the test / CLI side --

    def power_cycle(self, faults: Faults | None = None) -> None:
        """Reset the state (nothing selected, all off); replace the faults if given."""
        with self._lock:
            if faults is not None:
                self.faults = faults
                self._rng = random.Random(faults.seed)
                self._base = self.received  # ordinals in the new faults count from here
            self._sel, self._on, self._ready_at = None, False, 0.0
            self._publish()

    def lit(self):
        """Index of the light that is on, or None."""
        with self._lock:
            return self._sel if self._on else None

    def hang_up(self) -> None:
        """Close the controller's end of the line for good (the host sees a disconnect)."""
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=5)
        with self._lock:
            self._close()

    stop = hang_up

    def _close(self) -> None:
        if not self.hung_up:
            self.hung_up = True
            os.close(self._master)
            os.close(self._slave)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def camera(self, light: int, out: str) -> None:
        """A dry-run camera: writes a small grey PNG to `out` if `light` is the one lit, else raises."""
        lit = self.lit()
        if lit != light:
            raise RuntimeError(f"simulated camera: light {light} should be lit, the controller has {lit}")
        import numpy as np
        from matplotlib.image import imsave

        level = np.uint8(40 + (light * 37) % 200)
        imsave(out, np.full((8, 8, 3), level, np.uint8), format="png")

    # -- the controller --

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set() and not self.hung_up:
            try:
                ready, _, _ = select.select([self._master], [], [], 0.02)
                if not ready:
                    continue
                buf += os.read(self._master, 4096)
            except (OSError, ValueError):  # closed under us by hang_up
                return
            while b"\n" in buf and not self.hung_up:
                line, _, buf = buf.partition(b"\n")
                self._handle(line)
            if len(buf) >= MAX_LINE and not self.hung_up:  # no LF in sight: answer overflow and resynchronise
                buf = b""
                self._send(encode_reply(0, error="E07"))

    def _handle(self, line: bytes) -> None:
        with self._lock:
            self.received += 1
            n = self.received - self._base
            f = self.faults
            self.log.append(line.decode("ascii", "replace"))
            if f.disconnect_after is not None and n > f.disconnect_after:
                self._close()
                return
            if f.silent_after is not None and n > f.silent_after:
                return
            if n in f.corrupt:
                i = len(line) // 2  # mid-line: the seq usually survives, so the E01 reaches the host
                line = line[:i] + bytes([line[i] ^ 0x01]) + line[i + 1:] if line else b"?"
            reply = self._reply(line)
            self._publish()
            if n in f.drop or (f.drop_rate and self._rng.random() < f.drop_rate):
                return
            if n in f.garble or (f.garble_rate and self._rng.random() < f.garble_rate):
                reply = _garble(reply, n)
        if f.latency:
            time.sleep(f.latency)
        self._send(reply)

    def _reply(self, line: bytes) -> bytes:
        first = line.split(b" ", 1)[0]
        seq = int(first) if first.isdigit() and len(first) <= 5 and int(first) <= 65535 else 0
        if len(line) + 1 > MAX_LINE:
            return encode_reply(seq, error="E07")
        try:
            seq, verb, args = parse_request(line)
        except ProtocolError:
            return encode_reply(seq, error="E01")
        except ValueError:
            return encode_reply(seq, error="E02")
        now = time.monotonic()
        sel = "-" if self._sel is None else str(self._sel)
        if verb == "ID":
            return encode_reply(seq, {"id": self.name, "fw": self.fw, "lights": self.lights,
                                      "proto": PROTOCOL_VERSION})
        if verb == "STAT":
            return encode_reply(seq, {"sel": sel, "on": int(self._on), "ready": int(now >= self._ready_at),
                                      "lights": self.lights})
        if verb == "OFF":
            self._on = False
            return encode_reply(seq, {"sel": sel, "on": 0})
        if verb == "SEL":
            k = args[0]
            if k >= self.lights:
                return encode_reply(seq, error="E03")
            if self._sel != k:
                self._on, self._sel, self._ready_at = False, k, now + self.faults.settle
            return encode_reply(seq, {"sel": k, "ready": int(now >= self._ready_at)})
        # ON
        if self._sel is None:
            return encode_reply(seq, error="E05")
        if now < self._ready_at:
            return encode_reply(seq, error="E04")
        if self._sel in self.faults.lamp_fail:
            return encode_reply(seq, error="E06")
        if not self._on:
            self.lit_log.append(self._sel)
        self._on = True
        return encode_reply(seq, {"sel": sel, "on": 1})

    def _publish(self) -> None:
        """Rewrite `state_file` (atomically) with the lit light's index, or nothing when dark."""
        lit = self._sel if self._on else None
        if self.state_file is None or self._published == (lit,):
            return
        tmp = f"{self.state_file}.tmp"
        with open(tmp, "w") as fh:
            fh.write("" if lit is None else str(lit))
        os.replace(tmp, self.state_file)
        self._published = (lit,)

    def _send(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except OSError:  # hung up meanwhile
            pass


def _garble(reply: bytes, n: int) -> bytes:
    """Damage a reply in one of three ways, chosen by the request ordinal."""
    kind = n % 3
    if kind == 0:  # one character changed: the checksum fails
        i = len(reply) // 2
        return reply[:i] + bytes([reply[i] ^ 0x04]) + reply[i + 1:]
    if kind == 1:  # cut short: no LF arrives
        return reply[: max(1, len(reply) - 4)]
    return b"\x00\xff#" + reply  # line noise in front


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m jaxrefl.capture.simulator", description=__doc__.splitlines()[0])
    parser.add_argument("--lights", type=int, default=60)
    parser.add_argument("--faults", default="", help="e.g. garble_rate=0.1,seed=1 or disconnect_after=20")
    parser.add_argument("--state-file", default=None, help="keep the lit light's index in this file")
    args = parser.parse_args(argv)
    sim = Simulator(args.lights, Faults.parse(args.faults), state_file=args.state_file)
    print(sim.port, flush=True)
    try:
        while not sim.hung_up:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    sim.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

