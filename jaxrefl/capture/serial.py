"""Serial light rig: the controller's ASCII line protocol and a pyserial driver.

The controller switches (or moves a positioner to) one of `n` numbered lights.
Light `k` (0-based, the index of the plan / `select-lights` candidate) is a
fixed lamp or a preset position the controller owns; the host only sends indices.

## Line protocol, version 1

Serial framing: 8N1, 115200 baud by default, no flow control. Every message is
one line of printable ASCII (0x20-0x7E) ended by LF (a CR before the LF is
ignored), at most 80 bytes including the terminator. Tokens are separated by one
space. The host sends a request and waits for the reply before sending another.

```
request = seq SP verb *(SP arg) "*" crc LF
reply   = seq SP "OK" *(SP key "=" value) "*" crc LF
        / seq SP "ERR" SP code SP reason "*" crc LF
seq     = 1*5DIGIT      ; decimal 0-65535, chosen by the host, echoed in the reply
verb    = "ID" / "SEL" / "ON" / "OFF" / "STAT"
arg     = 1*5DIGIT      ; SEL's light index
key     = 1*ALPHA       ; lowercase
value   = 1*(ALPHA / DIGIT / "." / "-" / "_")
code    = "E" 2DIGIT
reason  = 1*(ALPHA / DIGIT / "_")   ; lowercase, informative only
crc     = 4HEXDIG       ; uppercase
```

`crc` is CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no
reflection, no final XOR; check value 0x29B1 for the nine bytes `123456789`)
of every byte before the `*`. Python: `binascii.crc_hqx(body, 0xFFFF)`.
Example exchange (the host's seq counts 1, 2, ...; seq 0 is the controller's
"unknown"):

```
host -> 1 ID*E74F        controller -> 1 OK id=LIGHTRIG fw=1.0 lights=12 proto=1*BB31
host -> 2 SEL 5*DC4D     controller -> 2 OK sel=5 ready=1*10C1
host -> 3 SEL 99*E235    controller -> 3 ERR E03 range*1F7C
```

Verbs (every verb is idempotent, so a host may re-send the same line):

| request | reply fields | meaning |
|---|---|---|
| `ID` | `id fw lights proto` | identify: name, firmware, number of lights `n`, protocol version (1) |
| `SEL k` | `sel ready` | select light `k` (0 <= k < n), the lit one going off; a positioner answers `ready=0` and moves (poll `STAT`) |
| `ON` | `sel on` | switch the selected light on (`on=1`) |
| `OFF` | `sel on` | switch every light off (`on=0`); the selection stays |
| `STAT` | `sel on ready lights` | state; `sel=-` when nothing is selected |

Error codes (`ERR code reason`):

| code | reason | host action |
|---|---|---|
| `E01` | `checksum` | the request arrived garbled: re-send it (retry) |
| `E02` | `syntax` | unknown verb, bad argument count or a malformed line: bug, give up |
| `E03` | `range` | light index outside `0 .. n-1`: give up |
| `E04` | `busy` | still moving: wait and retry |
| `E05` | `nosel` | `ON` with no light selected: give up (the controller may have reset) |
| `E06` | `lamp` | lamp or positioner fault: give up, needs a person |
| `E07` | `overflow` | line longer than 80 bytes: give up |

A line whose checksum fails is answered `E01` with seq as received when its
first token is a number, else seq 0. A controller never sends unsolicited lines.

Host behaviour (`LightController`): each request gets a fresh seq (1-65535,
wrapping); a reply with another seq is stale (an answer to an earlier, timed-out
try) and is skipped. A try fails on silence for `timeout` seconds, on a garbled
reply (bad checksum, grammar, no LF) and on `E01`/`E04`; the host then waits
`backoff * 2**i` seconds (try `i` = 0, 1, ...), drops unread input and re-sends
the same line, `retries` times. When every try met silence the controller is
declared silent (`ControllerSilent`); a port that fails to read or write
(unplugged, hung up) raises `ControllerDisconnected` at once.
"""

from __future__ import annotations

import binascii
import re
import time
from dataclasses import dataclass, field

import serial

__all__ = [
    "MAX_LINE",
    "PROTOCOL_VERSION",
    "ERROR_CODES",
    "RETRYABLE",
    "Reply",
    "RigError",
    "ProtocolError",
    "ControllerError",
    "ControllerSilent",
    "ControllerDisconnected",
    "LinkOptions",
    "LightController",
    "crc",
    "frame",
    "unframe",
    "encode_request",
    "parse_request",
    "encode_reply",
    "parse_reply",
]

MAX_LINE = 80
PROTOCOL_VERSION = 1
VERBS = {"ID": 0, "SEL": 1, "ON": 0, "OFF": 0, "STAT": 0}  # verb -> number of arguments
ERROR_CODES = {"E01": "checksum", "E02": "syntax", "E03": "range", "E04": "busy", "E05": "nosel",
               "E06": "lamp", "E07": "overflow"}
RETRYABLE = frozenset({"E01", "E04"})

_SEQ = re.compile(rb"\d{1,5}")
_ARG = re.compile(rb"\d{1,5}")
_FIELD = re.compile(rb"([a-z]+)=([A-Za-z0-9._-]+)")
_CODE = re.compile(rb"E\d\d")
_REASON = re.compile(rb"[a-z0-9_]+")


class RigError(RuntimeError):
    """The rig failed (controller or link); the capture can be resumed."""


class ProtocolError(RigError):
    """A line broke the grammar or its checksum (garbled in transit)."""


class ControllerError(RigError):
    """The controller answered `ERR code reason` with a code not worth retrying."""

    def __init__(self, code: str, reason: str, request: str):
        super().__init__(f"controller: {code} {reason} (request {request!r})")
        self.code, self.reason, self.request = code, reason, request


class ControllerSilent(RigError):
    """No reply at all through every try."""


class ControllerDisconnected(RigError):
    """The serial port failed to open, read or write (unplugged, hung up)."""


# -- framing ---------------------------------------------------------------------------


def crc(body: bytes) -> str:
    """CRC-16/CCITT-FALSE of `body` as four uppercase hex digits."""
    return f"{binascii.crc_hqx(body, 0xFFFF):04X}"


def frame(body: str) -> bytes:
    """`body` + `*` + crc + LF, checked against the protocol's character set and length."""
    raw = body.encode("ascii")
    line = raw + b"*" + crc(raw).encode() + b"\n"
    if len(line) > MAX_LINE or any(c < 0x20 or c > 0x7E for c in raw):
        raise ValueError(f"line: not a protocol line: {body!r}")
    return line


def unframe(line: bytes) -> list[bytes]:
    """Tokens of one received line (without LF); raises ProtocolError on a bad line or checksum."""
    line = line.rstrip(b"\r")
    if len(line) + 1 > MAX_LINE:
        raise ProtocolError(f"line longer than {MAX_LINE} bytes")
    body, star, check = line.rpartition(b"*")
    if not star or any(c < 0x20 or c > 0x7E for c in line):
        raise ProtocolError(f"malformed line {line[:MAX_LINE]!r}")
    if check != crc(body).encode():
        raise ProtocolError(f"checksum mismatch in {line!r}")
    tokens = body.split(b" ")
    if not tokens or not _SEQ.fullmatch(tokens[0]) or int(tokens[0]) > 65535:
        raise ProtocolError(f"bad sequence number in {line!r}")
    return tokens


def encode_request(seq: int, verb: str, *args: int) -> bytes:
    """One request line, e.g. `encode_request(2, "SEL", 5) == b"2 SEL 5*DC4D\\n"`."""
    if verb not in VERBS or len(args) != VERBS[verb]:
        raise ValueError(f"verb: unknown verb or wrong argument count: {verb} {args}")
    if not 0 <= seq <= 65535 or any(not 0 <= int(a) <= 99999 for a in args):
        raise ValueError(f"seq: out of range in {seq} {verb} {args}")
    return frame(" ".join([str(seq), verb, *(str(int(a)) for a in args)]))


def parse_request(line: bytes) -> tuple[int, str, tuple[int, ...]]:
    """`(seq, verb, args)` of a request line; ProtocolError when garbled, ValueError('E02')
    when well framed but not a valid request."""
    tokens = unframe(line)
    seq, verb, args = int(tokens[0]), (tokens[1] if len(tokens) > 1 else b"").decode(), tokens[2:]
    if verb not in VERBS or len(args) != VERBS[verb] or not all(_ARG.fullmatch(a) for a in args):
        raise ValueError("E02")
    return seq, verb, tuple(int(a) for a in args)


@dataclass(frozen=True)
class Reply:
    """A parsed reply: `ok`, `fields` (str -> str) when OK, `code`/`reason` when ERR."""

    seq: int
    ok: bool
    fields: dict = field(default_factory=dict)
    code: str = ""
    reason: str = ""


def encode_reply(seq: int, fields: dict | None = None, error: str | None = None) -> bytes:
    """An `OK key=value ...` reply, or `ERR code reason` when `error` (a code) is given."""
    if error is not None:
        return frame(f"{seq} ERR {error} {ERROR_CODES[error]}")
    return frame(" ".join([str(seq), "OK", *(f"{k}={v}" for k, v in (fields or {}).items())]))


def parse_reply(line: bytes) -> Reply:
    """Parse one reply line; ProtocolError when garbled or off-grammar."""
    tokens = unframe(line)
    seq = int(tokens[0])
    if len(tokens) >= 2 and tokens[1] == b"OK":
        pairs = [_FIELD.fullmatch(t) for t in tokens[2:]]
        if not all(pairs):
            raise ProtocolError(f"bad field in {line!r}")
        return Reply(seq, True, {m[1].decode(): m[2].decode() for m in pairs})
    if len(tokens) == 4 and tokens[1] == b"ERR" and _CODE.fullmatch(tokens[2]) and _REASON.fullmatch(tokens[3]):
        return Reply(seq, False, code=tokens[2].decode(), reason=tokens[3].decode())
    raise ProtocolError(f"neither OK nor ERR: {line!r}")


# -- driver ------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinkOptions:
    """Timing of the link [s]: `timeout` per try, `retries` extra tries, back-off base,
    `settle_timeout` for a positioner to report ready, `poll` interval while it moves."""

    baudrate: int = 115200
    timeout: float = 0.5
    retries: int = 3
    backoff: float = 0.05
    settle_timeout: float = 10.0
    poll: float = 0.02

    def __post_init__(self):
        for name in ("timeout", "settle_timeout", "poll"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name.replace('_', '-')}: must be > 0, got {getattr(self, name)}")
        if self.retries < 0 or self.backoff < 0 or self.baudrate <= 0:
            raise ValueError(f"retries/backoff/baudrate: must be >= 0, got {self.retries}, {self.backoff}, "
                             f"{self.baudrate}")


class LightController:
    """Driver for a controller speaking the protocol above over `port` (pyserial).

    Use as a context manager. Methods return the reply fields as a dict of strings;
    they raise `ControllerError`, `ControllerSilent`, `ControllerDisconnected` or
    `ProtocolError` (all `RigError`). `stats` counts tries, timeouts, garbled and
    stale lines, controller-side retries (E01/E04) over the driver's life.
    """

    def __init__(self, port: str, options: LinkOptions = LinkOptions()):
        self.port, self.options = port, options
        self.stats = {"requests": 0, "retries": 0, "timeouts": 0, "garbled": 0, "stale": 0, "retryable_errors": 0}
        self._seq = 0
        self._buf = b""
        try:
            self._ser = serial.Serial(port, options.baudrate, timeout=options.timeout, write_timeout=options.timeout,
                                      exclusive=True)  # a second driver on the same port fails to open
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ControllerDisconnected(f"port: cannot open {port}: {exc}") from None
        try:
            self._reset_input()
        except ControllerDisconnected:
            self.close()
            raise

    def close(self) -> None:
        try:
            self._ser.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- verbs --

    def identify(self) -> dict:
        """`{"id", "fw", "lights", "proto"}` (strings); checks the protocol version."""
        f = self.request("ID").fields
        if f.get("proto") != str(PROTOCOL_VERSION) or not f.get("lights", "").isdigit():
            raise ProtocolError(f"controller: unsupported identity {f} (need proto={PROTOCOL_VERSION}, lights=<n>)")
        return f

    def status(self) -> dict:
        return self.request("STAT").fields

    def select(self, light: int) -> dict:
        """Select `light` and wait (polling STAT) until the controller reports it ready."""
        f = self.request("SEL", light).fields
        deadline = time.monotonic() + self.options.settle_timeout
        while not (f.get("sel") == str(light) and f.get("ready") == "1"):
            if f.get("sel") != str(light):
                raise RigError(f"controller: selected light {light} but it reports sel={f.get('sel')}")
            if time.monotonic() > deadline:
                raise RigError(f"controller: light {light} not ready after {self.options.settle_timeout} s")
            time.sleep(self.options.poll)
            f = self.status()
        return f

    def on(self, light: int | None = None) -> dict:
        """Switch the selected light on; with `light`, check it is the one lit."""
        f = self.request("ON").fields
        if f.get("on") != "1" or (light is not None and f.get("sel") != str(light)):
            raise RigError(f"controller: asked for light {light} on, it reports sel={f.get('sel')} on={f.get('on')}")
        return f

    def off(self) -> dict:
        f = self.request("OFF").fields
        if f.get("on") != "0":
            raise RigError(f"controller: asked for all lights off, it reports on={f.get('on')}")
        return f

    # -- transport --

    def request(self, verb: str, *args: int) -> Reply:
        """Send one request with retries; the OK reply, or raise (see the module docstring)."""
        self._seq = self._seq % 65535 + 1
        line = encode_request(self._seq, verb, *args)
        text = line[: line.index(b"*")].decode()
        self.stats["requests"] += 1
        o = self.options
        silent, last, refused = True, "", None
        for attempt in range(o.retries + 1):
            if attempt:
                self.stats["retries"] += 1
                time.sleep(o.backoff * 2 ** (attempt - 1))
                self._reset_input()
            self._write(line)
            outcome = self._await(self._seq, time.monotonic() + o.timeout)
            if isinstance(outcome, Reply):
                if outcome.ok:
                    return outcome
                if outcome.code not in RETRYABLE:
                    raise ControllerError(outcome.code, outcome.reason, text)
                self.stats["retryable_errors"] += 1
                silent, last, refused = False, f"{outcome.code} {outcome.reason}", outcome
            else:
                silent, last, refused = silent and outcome == "timeout", outcome, None
        tries = o.retries + 1
        if refused is not None:  # it answered every time, with "try again" last
            raise ControllerError(refused.code, refused.reason, f"{text}, {tries} tries")
        if silent:
            raise ControllerSilent(f"controller: no answer to {text!r} in {tries} tries "
                                   f"({o.timeout} s each) on {self.port}")
        raise ProtocolError(f"controller: no valid answer to {text!r} in {tries} tries; last: {last}")

    def _await(self, seq: int, deadline: float):
        """The reply to `seq` before `deadline`, or "timeout" / a description of garbage."""
        while True:
            raw = self._read_line(deadline)
            if raw is None:
                self.stats["timeouts"] += 1
                return "timeout"
            try:
                reply = parse_reply(raw)
            except ProtocolError as exc:
                self.stats["garbled"] += 1
                return f"garbled reply ({exc})"
            if reply.seq == seq:
                return reply
            self.stats["stale"] += 1

    def _read_line(self, deadline: float):
        """Bytes of one line (LF stripped) or None at the deadline (a partial line stays buffered)."""
        while b"\n" not in self._buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or len(self._buf) > 4 * MAX_LINE:
                if self._buf:  # a partial or endless line: garbage, hand it over to be rejected
                    raw, self._buf = self._buf, b""
                    return raw
                return None
            try:
                self._ser.timeout = remaining
                self._buf += self._ser.read(max(1, self._ser.in_waiting))
            except (serial.SerialException, OSError) as exc:
                raise self._lost(exc) from None
        raw, _, self._buf = self._buf.partition(b"\n")
        return raw

    def _write(self, line: bytes) -> None:
        try:
            self._ser.write(line)
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None

    def _lost(self, exc) -> ControllerDisconnected:
        return ControllerDisconnected(f"controller: lost the line on {self.port} ({exc})")

    def _reset_input(self) -> None:
        self._buf = b""
        try:
            self._ser.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None
