"""Rig controller protocol: state machine, driver over a real pty, failure paths."""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Iterator

import numpy as np
import pytest
import serial

from facetsynth.rig import protocol
from facetsynth.rig.driver import RigController
from facetsynth.rig.emulator import ControllerState, PtyServer, VirtualController, virtual_port
from facetsynth.rig.protocol import ErrorCode, ErrReply, OkReply, ProtocolError, RigError, RigInfo, RigTimeoutError

N_LEDS = 40
MAX_STEPS = 24000
STEPS_PER_MM = 80.0
LED_PITCH_STEPS = int(6.0 * STEPS_PER_MM)  # one LED pitch of carriage travel


@pytest.fixture
def controller() -> VirtualController:
    return VirtualController(n_leds=N_LEDS, max_steps=MAX_STEPS, steps_per_mm=STEPS_PER_MM)


@pytest.fixture
def homed(controller: VirtualController) -> VirtualController:
    assert controller.handle("HOME") == "OK POS 0"
    return controller


@pytest.fixture
def rig(controller: VirtualController) -> Iterator[RigController]:
    with virtual_port(controller) as port, RigController.open(port, timeout=1.0) as rig:
        yield rig


@pytest.fixture
def silent_port() -> Iterator[str]:
    """A pty whose other end never answers."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def err_code(reply: str) -> int:
    parsed = protocol.parse_reply(reply)
    assert isinstance(parsed, ErrReply), reply
    return parsed.code


# --- the state machine (no I/O) ----------------------------------------------


def test_reset_state(controller: VirtualController) -> None:
    state = controller.state()
    assert state == ControllerState(homed=False, position=0, lit_led=None, revision=0)
    assert controller.handle("LED?") == "OK LED OFF"


def test_identify(controller: VirtualController) -> None:
    reply = controller.handle("ID?")
    assert reply == "OK FACETSYNTH-RIG 0.1.0-virtual LEDS=40 STEPS=24000 STEPS_PER_MM=80 PROTO=2"
    parsed = protocol.parse_reply(reply)
    assert isinstance(parsed, OkReply)
    assert protocol.parse_identity(parsed) == RigInfo("0.1.0-virtual", N_LEDS, MAX_STEPS, STEPS_PER_MM, protocol=2)


def test_home_move_position(controller: VirtualController) -> None:
    assert controller.handle("HOME\n") == "OK POS 0"
    assert controller.state().homed
    assert controller.handle("MOVE 480\r\n") == "OK POS 480"
    assert controller.handle("POS?") == "OK POS 480"
    assert controller.handle("MOVE 0") == "OK POS 0"
    assert controller.handle(f"MOVE {MAX_STEPS}") == f"OK POS {MAX_STEPS}"
    assert controller.handle("HOME") == "OK POS 0"
    assert controller.state().position == 0


def test_leds(controller: VirtualController) -> None:
    assert controller.handle("LED 0") == "OK LED 0"  # LEDs do not need homing
    assert controller.handle("LED?") == "OK LED 0"
    assert controller.handle(f"LED {N_LEDS - 1}") == f"OK LED {N_LEDS - 1}"
    assert controller.state().lit_led == N_LEDS - 1  # exactly one LED lit
    assert controller.handle("LED OFF") == "OK LED OFF"
    assert controller.handle("LED?") == "OK LED OFF"
    assert controller.state().lit_led is None


def test_reset_switches_leds_off_and_unhomes(homed: VirtualController) -> None:
    homed.handle("MOVE 100")
    homed.handle("LED 3")
    homed.reset()
    state = homed.state()
    assert (state.homed, state.lit_led) == (False, None)
    assert err_code(homed.handle("POS?")) == ErrorCode.NOT_HOMED


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("FOO", ErrorCode.UNKNOWN_COMMAND),
        ("home", ErrorCode.UNKNOWN_COMMAND),  # case-sensitive
        ("led 3", ErrorCode.UNKNOWN_COMMAND),
        ("", ErrorCode.UNKNOWN_COMMAND),
        ("ID? 1", ErrorCode.BAD_ARGUMENT),
        ("HOME now", ErrorCode.BAD_ARGUMENT),
        ("MOVE", ErrorCode.BAD_ARGUMENT),
        ("MOVE x", ErrorCode.BAD_ARGUMENT),
        ("MOVE 1.5", ErrorCode.BAD_ARGUMENT),
        ("MOVE +5", ErrorCode.BAD_ARGUMENT),
        ("MOVE 1 2", ErrorCode.BAD_ARGUMENT),
        ("POS? 3", ErrorCode.BAD_ARGUMENT),
        ("LED", ErrorCode.BAD_ARGUMENT),
        ("LED off", ErrorCode.BAD_ARGUMENT),
        ("LED 1 2", ErrorCode.BAD_ARGUMENT),
        ("LED? 1", ErrorCode.BAD_ARGUMENT),
        ("MOVE " + "1" * 70, ErrorCode.BAD_ARGUMENT),  # line too long
        ("MOVE -1", ErrorCode.OUT_OF_RANGE),
        (f"MOVE {MAX_STEPS + 1}", ErrorCode.OUT_OF_RANGE),
        ("LED -1", ErrorCode.OUT_OF_RANGE),
        (f"LED {N_LEDS}", ErrorCode.OUT_OF_RANGE),
    ],
)
def test_errors_when_homed(homed: VirtualController, line: str, code: ErrorCode) -> None:
    before = homed.state()
    assert err_code(homed.handle(line)) == code
    assert homed.state() == before  # a failed command changes nothing


@pytest.mark.parametrize(
    ("line", "code"),
    [
        ("MOVE 10", ErrorCode.NOT_HOMED),
        ("MOVE -1", ErrorCode.NOT_HOMED),  # not homed is reported before out of range
        ("POS?", ErrorCode.NOT_HOMED),
        ("MOVE x", ErrorCode.BAD_ARGUMENT),  # bad argument before not homed
    ],
)
def test_errors_before_home(controller: VirtualController, line: str, code: ErrorCode) -> None:
    assert err_code(controller.handle(line)) == code
    assert controller.state() == ControllerState(False, 0, None, 0)


# --- pure protocol helpers ---------------------------------------------------


def test_command_formatting() -> None:
    assert protocol.cmd_move(480) == "MOVE 480"
    assert protocol.cmd_led(7) == "LED 7"
    assert protocol.cmd_led(np.int64(7)) == "LED 7"  # scan plans may hold numpy ints
    assert protocol.encode_line(protocol.cmd_leds_off()) == b"LED OFF\n"
    with pytest.raises(TypeError):
        protocol.cmd_move(1.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        protocol.cmd_led(True)
    with pytest.raises(ValueError):
        protocol.encode_line("LED 1\nLED 2")


def test_reply_parsing() -> None:
    err = protocol.parse_reply("ERR 3 POSITION OUT OF RANGE 0..24000\n")
    assert err == ErrReply(3, "POSITION OUT OF RANGE 0..24000", "ERR 3 POSITION OUT OF RANGE 0..24000")
    assert err.to_error("MOVE -1", "/dev/x").code == 3
    ok = protocol.parse_reply("OK FACETSYNTH-RIG 2.0 LEDS=20 STEPS=100 STEPS_PER_MM=12.5 TEMP=31")
    assert isinstance(ok, OkReply)
    assert protocol.parse_identity(ok) == RigInfo("2.0", 20, 100, 12.5)  # unknown fields ignored
    assert protocol.parse_led(OkReply(("LED", "OFF"), "OK LED OFF")) is None
    for bad in ["", "HELLO", "ERR x oops", "ok POS 1"]:
        with pytest.raises(ProtocolError):
            protocol.parse_reply(bad)
    for words in [("POS",), ("POS", "x"), ("LED", "3")]:
        with pytest.raises(ProtocolError):
            protocol.parse_position(OkReply(words, " ".join(words)))
    with pytest.raises(ProtocolError):
        protocol.parse_identity(OkReply(("FACETSYNTH-RIG", "1.0", "LEDS=40"), "OK ..."))


def test_sequence_helpers() -> None:
    """Protocol v2: the ``@<n>`` prefix, its echo in replies, ``STOP`` and ``PROTO=``."""
    assert protocol.split_sequence("@12 MOVE 480") == (12, "MOVE 480")
    assert protocol.split_sequence("  @0007   LED?") == (7, "  LED?")
    assert protocol.split_sequence("@9999") == (9999, "")
    assert protocol.split_sequence("MOVE 480") == (None, "MOVE 480")
    for bad in ["@", "@ LED?", "@x LED?", "@-1 LED?", "@10000 LED?", "@5LED?", "@1.5"]:
        with pytest.raises(ValueError):
            protocol.split_sequence(bad)
    assert protocol.with_sequence(12, "OK POS 480") == "@12 OK POS 480"
    assert protocol.with_sequence(None, "OK POS 480") == "OK POS 480"
    with pytest.raises(ValueError):
        protocol.with_sequence(10000, "STOP")
    assert protocol.cmd_stop() == "STOP"
    assert protocol.split_words("  LED   3 ") == ["LED", "3"]
    assert protocol.split_words("LED\t3") == ["LED\t3"]  # only spaces separate
    ok = protocol.parse_reply("@7 OK POS 3\n")
    assert ok == OkReply(("POS", "3"), "@7 OK POS 3", seq=7)
    assert protocol.parse_reply("@8 ERR 5 STOPPED") == ErrReply(5, "STOPPED", "@8 ERR 5 STOPPED", seq=8)
    assert protocol.parse_reply("OK STOP") == OkReply(("STOP",), "OK STOP")
    with pytest.raises(ProtocolError):
        protocol.parse_reply("@x OK POS 3")
    v2 = protocol.parse_reply("OK FACETSYNTH-RIG 1.0.0 LEDS=40 STEPS=24000 STEPS_PER_MM=80 PROTO=2")
    assert isinstance(v2, OkReply)
    assert protocol.parse_identity(v2) == RigInfo("1.0.0", 40, 24000, 80.0, protocol=2)
    info = RigInfo("1.0.0", 40, 24000, 80.0)
    assert info.protocol == 1 and "PROTO" not in protocol.format_identity(info)  # v1 identity unchanged
    with pytest.raises(ProtocolError):
        words = ("FACETSYNTH-RIG", "1", "LEDS=1", "STEPS=1", "STEPS_PER_MM=1", "PROTO=x")
        protocol.parse_identity(OkReply(words, "OK ..."))
    assert ErrorCode.STOPPED == 5


def test_sequence_replay_in_the_state_machine(homed: VirtualController) -> None:
    assert homed.handle("@3 MOVE 100") == "@3 OK POS 100"
    assert homed.handle("MOVE 200") == "OK POS 200"
    before = homed.state()
    assert homed.handle("@3 MOVE 100") == "@3 OK POS 100"  # replayed, not executed
    assert homed.state() == before
    assert homed.handle("@3 STOP") == "@3 OK STOP"  # STOP always runs
    state = homed.state()
    assert (state.homed, state.position, state.lit_led) == (False, 0, None)
    assert state.revision == before.revision + 1
    assert homed.handle("@x STOP") == "ERR 2 BAD SEQUENCE NUMBER"
    homed.reset()
    assert homed.handle("@3 HOME") == "@3 OK POS 0"  # reset forgot the stored reply
    assert homed.state().homed


# --- the driver against the emulator over a real pty -------------------------


def test_identify_over_pty(rig: RigController) -> None:
    assert rig.identify() == RigInfo("0.1.0-virtual", N_LEDS, MAX_STEPS, STEPS_PER_MM, protocol=2)


def test_mini_scan(rig: RigController, controller: VirtualController) -> None:
    """Home, then at 3 carriage positions light 4 LEDs each, one per frame."""
    rig.home()
    assert rig.position() == 0
    assert controller.state().homed
    leds = [0, 13, 26, 39]
    for k in range(3):
        target = k * LED_PITCH_STEPS
        assert rig.move_to(target) == target
        for led in leds:
            rig.led_on(led)
            state = controller.state()
            assert (state.position, state.lit_led) == (target, led)
            assert rig.lit_led() == led
        assert rig.position() == target
    rig.leds_off()
    assert rig.lit_led() is None
    assert controller.state().lit_led is None


def test_err_replies_raise(rig: RigController, controller: VirtualController) -> None:
    with pytest.raises(RigError, match=r"'MOVE 480'.*ERR 4") as info:
        rig.move_to(480)
    assert info.value.code == ErrorCode.NOT_HOMED
    assert info.value.command == "MOVE 480"
    assert info.value.raw == "ERR 4 NOT HOMED"
    rig.home()
    with pytest.raises(RigError) as info:
        rig.move_to(MAX_STEPS + 1)
    assert info.value.code == ErrorCode.OUT_OF_RANGE
    with pytest.raises(RigError) as info:
        rig.led_on(N_LEDS)
    assert info.value.code == ErrorCode.OUT_OF_RANGE
    assert rig.position() == 0  # the link is still in step after errors
    assert controller.state().lit_led is None


def test_line_framing_over_pty(controller: VirtualController) -> None:
    """Blank lines get no reply; CRLF is accepted; over-long lines get ERR 2."""
    with virtual_port(controller) as port, serial.Serial(port, timeout=1.0) as ser:
        ser.write(b"\n\r\n  \nID?\r\n")
        assert ser.readline().startswith(b"OK FACETSYNTH-RIG ")
        ser.write(b"LED " + b"7" * 100 + b"\nLED 5\n")
        assert ser.readline() == b"ERR 2 LINE TOO LONG\n"
        assert ser.readline() == b"OK LED 5\n"
        ser.write(b"LE")  # a command split across writes
        time.sleep(0.01)
        ser.write(b"D?\n")
        assert ser.readline() == b"OK LED 5\n"


def test_virtual_port_releases_fds_and_thread(controller: VirtualController) -> None:
    fds_before = set(os.listdir("/proc/self/fd"))
    threads_before = set(threading.enumerate())
    for _ in range(3):
        with virtual_port(controller) as port, RigController.open(port) as rig:
            rig.led_on(1)
    assert set(threading.enumerate()) == threads_before
    assert set(os.listdir("/proc/self/fd")) == fds_before
    server = controller.serve_pty()
    assert os.path.exists(server.port)
    server.close()
    server.close()  # idempotent
    assert set(os.listdir("/proc/self/fd")) == fds_before


def test_concurrent_state_reads(rig: RigController, controller: VirtualController) -> None:
    """The camera may poll state() while the driver talks to the rig."""
    rig.home()
    seen: list[ControllerState] = []
    stop = threading.Event()

    def camera() -> None:
        while not stop.is_set():
            seen.append(controller.state())
            time.sleep(0.0005)      # a camera polls; a loop without a pause starved the port's thread of the GIL
                                    # on a loaded machine (a 1 s timeout of the rig, session 44)

    reader = threading.Thread(target=camera)
    reader.start()
    try:
        for led in range(10):
            rig.led_on(led)
    finally:
        stop.set()
        reader.join()
    assert seen and all(s.lit_led is None or 0 <= s.lit_led < 10 for s in seen)
    assert [s.revision for s in seen] == sorted(s.revision for s in seen)


# --- failure paths -----------------------------------------------------------


def test_timeout_names_port_and_command(silent_port: str) -> None:
    timeout = 0.3
    with RigController.open(silent_port, timeout=timeout) as rig:
        start = time.monotonic()
        with pytest.raises(RigTimeoutError, match="'LED\\?'") as info:
            rig.lit_led()
        elapsed = time.monotonic() - start
    assert isinstance(info.value, RigError)
    assert silent_port in str(info.value)
    assert info.value.command == "LED?"
    assert timeout * 0.9 <= elapsed < timeout + 1.0


def test_stale_input_is_discarded() -> None:
    """A late reply left over from a timed-out command is not taken as the next reply."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with RigController.open(os.ttyname(slave), timeout=1.0) as rig:
            os.write(master, b"OK LED 9\n")  # stale
            time.sleep(0.05)

            def answer() -> None:
                received = b""
                while not received.endswith(b"\n"):
                    received += os.read(master, 64)
                assert received == b"LED?\n"
                os.write(master, b"OK LED OFF\n")

            responder = threading.Thread(target=answer)
            responder.start()
            assert rig.lit_led() is None
            responder.join()
    finally:
        os.close(master)
        os.close(slave)


def test_motion_timeout_applies_to_moves(silent_port: str) -> None:
    with RigController.open(silent_port, timeout=0.1, motion_timeout=0.4) as rig:
        start = time.monotonic()
        with pytest.raises(RigTimeoutError, match="'HOME'"):
            rig.home()
        assert time.monotonic() - start >= 0.35
        assert rig._serial.timeout == 0.1  # type: ignore[union-attr]  # restored


class ScriptedPort:
    """A serial-like object replying from a script (for malformed replies)."""

    def __init__(self, *replies: bytes) -> None:
        self.replies = list(replies)
        self.written: list[bytes] = []
        self.port = "scripted"

    def write(self, data: bytes) -> int:
        self.written.append(data)
        return len(data)

    def readline(self) -> bytes:
        return self.replies.pop(0) if self.replies else b""

    def close(self) -> None:
        pass


def test_partial_reply_is_a_timeout() -> None:
    rig = RigController(ScriptedPort(b"OK PO"))
    with pytest.raises(RigTimeoutError, match=r"scripted.*'POS\?'.*partial"):
        rig.position()


@pytest.mark.parametrize(
    ("reply", "call"),
    [
        (b"HELLO\n", lambda rig: rig.position()),
        (b"OK LED 3\n", lambda rig: rig.position()),  # answer to another command
        (b"@7 OK POS 3\n", lambda rig: rig.position()),  # a prefix the driver did not send
        (b"OK POS 479\n", lambda rig: rig.move_to(480)),  # did not reach target
        (b"OK LED 2\n", lambda rig: rig.led_on(3)),
        (b"OK LED 2\n", lambda rig: rig.leds_off()),
        (b"OK POS \xff\n", lambda rig: rig.position()),
        (b"OK FACETSYNTH-RIG 1 LEDS=x STEPS=1 STEPS_PER_MM=1\n", lambda rig: rig.identify()),
    ],
)
def test_malformed_replies(reply: bytes, call) -> None:
    port = ScriptedPort(reply)
    with pytest.raises(ProtocolError, match="scripted") as info:
        call(RigController(port))
    assert info.value.command is not None
    assert port.written and port.written[0].endswith(b"\n")


def test_closed_and_unopenable() -> None:
    rig = RigController(ScriptedPort(b"OK LED OFF\n"))
    assert rig.lit_led() is None
    rig.close()
    rig.close()
    with pytest.raises(RigError, match="closed"):
        rig.lit_led()
    with pytest.raises(RigError, match="/nonexistent/tty"):
        RigController.open("/nonexistent/tty")


def test_pty_server_start_twice_fails(controller: VirtualController) -> None:
    with PtyServer(controller) as server:
        with pytest.raises(RuntimeError):
            server.start()
