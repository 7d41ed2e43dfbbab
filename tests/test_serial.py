"""The light-rig line protocol and its driver, over the simulator on a real pty (no mocks)."""

import time

import pytest
import serial as pyserial
from hypothesis import given
from hypothesis import strategies as st

from jaxrefl.capture.serial import (
    ControllerDisconnected,
    ControllerError,
    ControllerSilent,
    LightController,
    LinkOptions,
    ProtocolError,
    RigError,
    crc,
    encode_reply,
    encode_request,
    parse_reply,
    parse_request,
)
from jaxrefl.capture.simulator import Faults, Simulator

FAST = LinkOptions(timeout=0.1, retries=3, backoff=0.01, settle_timeout=1.0, poll=0.01)


@pytest.fixture
def sim():
    s = Simulator(12)
    yield s
    s.stop()


def raw_exchange(port, line: bytes, timeout=1.0) -> bytes:
    """Send raw bytes with plain pyserial and return the raw reply line."""
    with pyserial.Serial(port, 115200, timeout=timeout) as ser:
        ser.write(line)
        return ser.read_until(b"\n")


# -- framing, exactly as documented ------------------------------------------------------


def test_crc_is_ccitt_false_and_documented_lines_match():
    assert crc(b"123456789") == "29B1"  # the standard check value of CRC-16/CCITT-FALSE
    assert encode_request(1, "ID") == b"1 ID*E74F\n"
    assert encode_request(2, "SEL", 5) == b"2 SEL 5*DC4D\n"
    assert encode_request(3, "SEL", 99) == b"3 SEL 99*E235\n"
    assert encode_reply(1, {"id": "LIGHTRIG", "fw": "1.0", "lights": 12, "proto": 1}) == \
        b"1 OK id=LIGHTRIG fw=1.0 lights=12 proto=1*BB31\n"
    assert encode_reply(2, {"sel": 5, "ready": 1}) == b"2 OK sel=5 ready=1*10C1\n"
    assert encode_reply(3, error="E03") == b"3 ERR E03 range*1F7C\n"
    assert parse_reply(b"3 ERR E03 range*1F7C\r").code == "E03"  # CR before LF is ignored


@given(seq=st.integers(0, 65535), verb=st.sampled_from(["ID", "ON", "OFF", "STAT", "SEL"]),
       arg=st.integers(0, 99999), pos=st.integers(0, 200), xor=st.integers(1, 255))
def test_requests_round_trip_and_any_changed_byte_is_caught(seq, verb, arg, pos, xor):
    args = (arg,) if verb == "SEL" else ()
    line = encode_request(seq, verb, *args)
    assert parse_request(line[:-1]) == (seq, verb, args)
    i = pos % (len(line) - 1)  # any byte but the LF
    bad = line[:i] + bytes([line[i] ^ xor]) + line[i + 1:-1]
    with pytest.raises((ProtocolError, ValueError)):
        parse_request(bad)


@pytest.mark.parametrize("line", [b"", b"1 ID", b"1 ID*e74f", b"1 ID*E74E", b"\x001 ID*E74F",
                                  b"1 OK " + b"a=b " * 30 + b"*0000", b"x ID*" + crc(b"x ID").encode()])
def test_garbled_lines_are_rejected(line):
    with pytest.raises(ProtocolError):
        parse_reply(line)


def test_bad_requests_are_value_errors():
    with pytest.raises(ValueError, match="verb"):
        encode_request(1, "FOO")
    with pytest.raises(ValueError, match="verb"):
        encode_request(1, "SEL")
    with pytest.raises(ValueError, match="seq"):
        encode_request(70000, "ID")
    with pytest.raises(ValueError, match="timeout"):
        LinkOptions(timeout=0)


# -- the simulator speaks the documented bytes ----------------------------------------------


def test_simulator_answers_the_documented_exchange(sim):
    assert raw_exchange(sim.port, b"1 ID*E74F\n") == encode_reply(
        1, {"id": "LIGHTRIG-SIM", "fw": "1.0", "lights": 12, "proto": 1})
    assert raw_exchange(sim.port, b"2 SEL 5*DC4D\n") == b"2 OK sel=5 ready=1*10C1\n"
    assert raw_exchange(sim.port, b"3 SEL 99*E235\n") == b"3 ERR E03 range*1F7C\n"
    assert raw_exchange(sim.port, b"4 SEL 5*DC4D\n") == encode_reply(4, error="E01")  # crc of another line
    assert raw_exchange(sim.port, b"5 FOO*" + crc(b"5 FOO").encode() + b"\n") == encode_reply(5, error="E02")
    assert raw_exchange(sim.port, b"#" * 100) == encode_reply(0, error="E07")


# -- driver --------------------------------------------------------------------------------


def test_driver_switches_lights(sim):
    with LightController(sim.port, FAST) as c:
        assert c.identify()["lights"] == "12"
        assert c.select(7) == {"sel": "7", "ready": "1"} and sim.lit() is None
        c.on(7)
        assert sim.lit() == 7 and c.status()["on"] == "1"
        c.select(2)  # selecting another light switches the lit one off
        assert sim.lit() is None
        c.on(2)
        c.off()
        assert sim.lit() is None and sim.lit_log == [7, 2]
        with pytest.raises(ControllerError) as err:
            c.select(12)
        assert err.value.code == "E03" and c.stats["retries"] == 0  # not retried
        assert c.stats["timeouts"] == c.stats["garbled"] == 0


@pytest.mark.parametrize("faults, counter", [
    (Faults(garble=frozenset({3})), "garbled"),        # a character changed
    (Faults(garble=frozenset({4})), "garbled"),        # cut short: no LF
    (Faults(garble=frozenset({5})), "garbled"),        # line noise in front
    (Faults(drop=frozenset({2, 3})), "timeouts"),      # no reply, twice
    (Faults(corrupt=frozenset({2})), "retryable_errors"),  # request garbled -> E01
])
def test_driver_recovers_from_a_bad_line(faults, counter):
    with Simulator(12, faults) as sim, LightController(sim.port, FAST) as c:
        for k in range(5):
            c.select(k)
            c.on(k)
        assert sim.lit_log == [0, 1, 2, 3, 4]
        assert c.stats[counter] >= 1 and c.stats["retries"] >= 1


def test_driver_skips_a_late_reply_to_an_earlier_request():
    once = LinkOptions(timeout=0.05, retries=0)
    with Simulator(12, Faults(latency=0.3)) as sim, LightController(sim.port, once) as c:
        with pytest.raises(ControllerSilent):
            c.status()
        sim.power_cycle(Faults())
        c.options = LinkOptions(timeout=1.0, retries=0)
        assert c.select(3)["sel"] == "3"  # the late STAT reply arrives first and is skipped
        assert c.stats["stale"] == 1


def test_silent_controller_is_detected_after_retries_with_backoff():
    o = LinkOptions(timeout=0.05, retries=3, backoff=0.02)
    with Simulator(12, Faults(silent_after=2)) as sim, LightController(sim.port, o) as c:
        c.identify()
        c.select(1)
        t0 = time.perf_counter()
        with pytest.raises(ControllerSilent, match="no answer to .* in 4 tries"):
            c.on(1)
        elapsed = time.perf_counter() - t0
        assert elapsed >= 4 * 0.05 + 0.02 * (1 + 2 + 4)
        assert sim.log[-4:] == [sim.log[-1]] * 4  # the same line (same seq) re-sent
        sim.power_cycle(Faults())  # answers again, but forgot its state
        with pytest.raises(ControllerError, match="E05"):
            c.on(1)
        c.select(1)
        c.on(1)
        assert sim.lit() == 1


def test_disconnect_is_reported_at_once():
    with Simulator(12, Faults(disconnect_after=3)) as sim, LightController(sim.port, LinkOptions(timeout=2.0)) as c:
        c.identify()
        c.select(0)
        c.on(0)
        t0 = time.perf_counter()
        with pytest.raises(ControllerDisconnected, match="lost the line"):
            c.off()
        assert time.perf_counter() - t0 < 1.0 and sim.hung_up  # no waiting out the timeout
        with pytest.raises(ControllerDisconnected):
            c.status()


def test_positioner_settles_before_the_light_goes_on():
    with Simulator(12, Faults(settle=0.15)) as sim, LightController(sim.port, FAST) as c:
        t0 = time.perf_counter()
        assert c.select(4)["ready"] == "1"
        assert time.perf_counter() - t0 >= 0.15
        c.on(4)
        assert sim.lit() == 4
    with Simulator(12, Faults(settle=5.0)) as sim, \
            LightController(sim.port, LinkOptions(timeout=0.1, retries=1, backoff=0.01, settle_timeout=0.2)) as c:
        with pytest.raises(RigError, match="not ready"):
            c.select(4)
        with pytest.raises(ControllerError, match="E04 busy"):  # still moving: retried, then given up
            c.on(4)
        assert c.stats["retryable_errors"] == 2


def test_lamp_fault_and_port_errors():
    with Simulator(12, Faults(lamp_fail=frozenset({6}))) as sim:
        with LightController(sim.port, FAST) as c:
            c.select(6)
            with pytest.raises(ControllerError, match="E06 lamp"):
                c.on(6)
            with pytest.raises(ControllerDisconnected, match="port: cannot open"):
                LightController(sim.port, FAST)  # a second driver on the same port
    with pytest.raises(ControllerDisconnected, match="port: cannot open /nonexistent/tty"):
        LightController("/nonexistent/tty", FAST)


def test_fault_spec_parsing():
    f = Faults.parse("garble=3+8,drop_rate=0.25,disconnect_after=20,settle=0.1,seed=4")
    assert f.garble == {3, 8} and f.drop_rate == 0.25 and f.disconnect_after == 20 and f.seed == 4
    assert Faults.parse("") == Faults()
    for bad in ("garble", "wobble=1", "drop_rate=2", "silent_after=x"):
        with pytest.raises(ValueError, match="simulate"):
            Faults.parse(bad)


def test_random_faults_are_reproducible():
    logs = []
    for _ in range(2):
        with Simulator(12, Faults(garble_rate=0.3, drop_rate=0.1, seed=7)) as sim, \
                LightController(sim.port, LinkOptions(timeout=0.2, retries=8, backoff=0.0)) as c:
            for k in range(6):
                c.select(k)
            logs.append((len(sim.log), dict(c.stats)))
    assert logs[0] == logs[1] and logs[0][1]["retries"] > 0
