"""Every rig controller implementation against rig/PROTOCOL.md (version 2), reply line by reply line.

Backends, each served on a pseudo-terminal and spoken to through pyserial (raw lines) or the driver:

- ``emulator``: :class:`facetsynth.rig.emulator.VirtualController` (:class:`PtyServer`).
- ``firmware``: the C firmware (``rig/firmware``) built for the host (``make host``): the protocol, motion
  and state code that runs on the ATmega328P, with the UART on stdin/stdout and the carriage simulated.
  Motions take no time here (``FIRMWARE_STEP_US=0``) except in the tests of motion timing.
- ``simavr``: the AVR image itself (``build/facetsynth-rig.elf``) in simavr (``make simavr``), with the real
  UART and step timing. Marked ``simavr`` and deselected in the unit suite, as it takes about 30 s (every
  ``HOME`` re-approaches the switch at 2.5 mm/s; a full travel is 6 s of simulated time): ``make
  test-firmware`` runs it. Needs Debian's gcc-avr, avr-libc, binutils-avr and libsimavr-dev.

Each test starts from a power-on controller (the firmware processes are started per test). Where the
backends must differ it is because the emulator's motions are instantaneous: input that arrives during a
motion (``STOP``, or anything else) exists only for the firmware, and those tests run on the firmware
backends alone.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import serial

from facetsynth.rig.driver import RigController
from facetsynth.rig import emulator
from facetsynth.rig.emulator import PtyServer, VirtualController
from facetsynth.rig.protocol import ErrorCode, RigError, RigInfo

N_LEDS = 40
MAX_STEPS = 24000
IDENTITY = f"LEDS={N_LEDS} STEPS={MAX_STEPS} STEPS_PER_MM=80 PROTO=2"
OUT_OF_RANGE = f"ERR 3 POSITION OUT OF RANGE 0..{MAX_STEPS}"
LED_OUT_OF_RANGE = f"ERR 3 LED INDEX OUT OF RANGE 0..{N_LEDS - 1}"
NOT_HOMED = "ERR 4 NOT HOMED"
UNKNOWN = "ERR 1 UNKNOWN COMMAND"
UNEXPECTED = "ERR 2 UNEXPECTED ARGUMENT"
BAD_MOVE = "ERR 2 EXPECTED MOVE <steps>"
BAD_LED = "ERR 2 EXPECTED LED <index>|OFF"
BAD_SEQUENCE = "ERR 2 BAD SEQUENCE NUMBER"
TOO_LONG = "ERR 2 LINE TOO LONG"

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "rig" / "firmware"
REPLY_TIMEOUT = 15.0  # s; generous: a full-travel move in simavr takes 3-6 s of wall time
SIMAVR = pytest.param("simavr", marks=pytest.mark.simavr)   # the real step rates: make test-firmware
BACKENDS = ["emulator", "firmware", SIMAVR]
FIRMWARE_BACKENDS = ["firmware", SIMAVR]


def firmware_version() -> str:
    """The version token the C firmware reports (``FW_VERSION`` in config.h)."""
    match = re.search(r'#define FW_VERSION "([^"]+)"', (FIRMWARE_DIR / "config.h").read_text())
    assert match, "FW_VERSION not found in rig/firmware/config.h"
    return match.group(1)


# --- building the firmware ------------------------------------------------------


def _make(target: str, build_dir: Path) -> None:
    result = subprocess.run(
        ["make", "-C", str(FIRMWARE_DIR), target, f"BUILD_DIR={build_dir}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if result.returncode != 0:
        pytest.fail(f"make {target} failed:\n{result.stdout}\n{result.stderr}")


@pytest.fixture(scope="session")
def host_firmware(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``rig-host``, built once per session into a temporary directory."""
    if shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("make and a C compiler (cc) are needed to build the firmware for the host")
    build = tmp_path_factory.mktemp("firmware-host")
    _make("host", build)
    return build / "rig-host"


@pytest.fixture(scope="session")
def simavr_firmware(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """``rig-simavr`` and the AVR image it runs, built once per session."""
    if shutil.which("avr-gcc") is None or shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("avr-gcc is not installed (Debian: gcc-avr avr-libc binutils-avr)")
    if not Path("/usr/include/simavr/sim_avr.h").exists():
        pytest.skip("simavr is not installed (Debian: libsimavr-dev)")
    build = tmp_path_factory.mktemp("firmware-simavr")
    _make("simavr", build)
    return build / "rig-simavr", build / "facetsynth-rig.elf"


# --- backends ----------------------------------------------------------------------


class ControllerProcess:
    """A controller program speaking the protocol on stdin/stdout, served on a pseudo-terminal.

    The program gets the master end as stdin and stdout; ``port`` is the slave end, which this object
    keeps open (as :class:`PtyServer` does) so that clients may open and close it freely.
    :meth:`power_cycle` restarts the program on the same pty; its stderr (``FIRMWARE_TRACE``) goes to
    ``trace_file``.
    """

    def __init__(self, argv: list[str], env: dict[str, str], trace_file: Path) -> None:
        self.argv = argv
        self.env = {**os.environ, "FIRMWARE_TRACE": "1", **env}
        self.trace_file = trace_file
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.process: subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        with open(self.trace_file, "wb") as trace:
            self.process = subprocess.Popen(
                self.argv, stdin=self.master, stdout=self.master, stderr=trace, env=self.env
            )

    def stop(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait(timeout=5)
            self.process = None

    def power_cycle(self) -> None:
        self.stop()
        self.start()

    def trace(self) -> list[str]:
        """The trace lines so far (LED frames, motor enable/disable with the carriage position)."""
        return self.trace_file.read_text().splitlines()

    def close(self) -> None:
        self.stop()
        os.close(self.master)
        os.close(self.slave)


@dataclass
class Backend:
    """One controller implementation, served on ``port`` from power-on."""

    name: str
    version: str
    port: str
    power_cycle: Callable[[], None]
    process: ControllerProcess | None = None

    def trace(self) -> list[str]:
        assert self.process is not None, "only the firmware backends have a trace"
        return self.process.trace()

    def carriage_at_motor_off(self) -> int:
        """The simulated carriage position when the motor driver was last disabled."""
        offs = [line for line in self.trace() if line.startswith("motor off ")]
        assert offs, self.trace()
        return int(offs[-1].rpartition("=")[2])

    def last_led_frame(self) -> str:
        frames = [line for line in self.trace() if line.startswith("leds ")]
        assert frames, self.trace()
        return frames[-1]


SpawnBackend = Callable[..., Backend]


@pytest.fixture
def spawn(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SpawnBackend]:
    """``spawn(name, **env)``: a power-on backend; ``env`` sets ``FIRMWARE_*`` variables of the firmware."""
    cleanups: list[Callable[[], None]] = []

    def make(name: str, **env: str) -> Backend:
        if name == "emulator":
            controller = VirtualController(n_leds=N_LEDS, max_steps=MAX_STEPS, steps_per_mm=80.0)
            server = PtyServer(controller).start()
            cleanups.append(server.close)
            return Backend(name, emulator.FIRMWARE_VERSION, server.port, controller.reset)
        if name == "firmware":
            argv = [str(request.getfixturevalue("host_firmware"))]
            env = {"FIRMWARE_STEP_US": "0", "FIRMWARE_START_STEPS": "2000", **env}
        elif name == "simavr":
            harness, elf = request.getfixturevalue("simavr_firmware")
            argv = [str(harness), str(elf)]
            env = {"FIRMWARE_START_STEPS": "100", **env}  # short homing: simavr runs the real step rates
        else:
            raise ValueError(name)
        process = ControllerProcess(argv, env, tmp_path / f"{name}-{len(cleanups)}.trace")
        cleanups.append(process.close)
        return Backend(name, firmware_version(), process.port, process.power_cycle, process)

    yield make
    for cleanup in reversed(cleanups):
        cleanup()


class Link:
    """Raw protocol lines over pyserial."""

    def __init__(self, port: str) -> None:
        self.serial = serial.Serial(port, baudrate=115200, timeout=REPLY_TIMEOUT)

    def send(self, data: bytes) -> None:
        self.serial.write(data)
        self.serial.flush()

    def reply(self) -> str:
        """The next reply line, without its ``\\n`` (which must be there)."""
        raw = self.serial.readline()
        assert raw.endswith(b"\n"), f"no complete reply line, got {raw!r}"
        return raw[:-1].decode("ascii")

    def ask(self, line: str) -> str:
        self.send(line.encode("ascii") + b"\n")
        return self.reply()

    def asks(self, *lines: str) -> list[str]:
        """The replies to ``lines``, sent one after the other (strict request/reply)."""
        return [self.ask(line) for line in lines]

    def close(self) -> None:
        self.serial.close()


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest, spawn: SpawnBackend) -> Backend:
    return spawn(request.param)


@pytest.fixture(params=FIRMWARE_BACKENDS)
def firmware_backend(request: pytest.FixtureRequest, spawn: SpawnBackend) -> Backend:
    return spawn(request.param)


@pytest.fixture
def link(backend: Backend) -> Iterator[Link]:
    link = Link(backend.port)
    yield link
    link.close()


def open_link(backend: Backend) -> Link:
    return Link(backend.port)


# --- identity, homing, moves, LEDs ------------------------------------------------------


def test_identify(link: Link, backend: Backend) -> None:
    assert link.ask("ID?") == f"OK FACETSYNTH-RIG {backend.version} {IDENTITY}"


def test_power_on_state(link: Link) -> None:
    assert link.asks("LED?", "POS?", "MOVE 10", "MOVE 0") == ["OK LED OFF", NOT_HOMED, NOT_HOMED, NOT_HOMED]


def test_home_and_moves(link: Link) -> None:
    assert link.asks("HOME", "POS?") == ["OK POS 0", "OK POS 0"]
    assert link.asks("MOVE 480", "POS?", "MOVE 007", "MOVE -0", "MOVE 1", "POS?") == [
        "OK POS 480", "OK POS 480", "OK POS 7", "OK POS 0", "OK POS 1", "OK POS 1",
    ]  # fmt: skip
    assert link.asks("MOVE 300", "HOME", "POS?") == ["OK POS 300", "OK POS 0", "OK POS 0"]
    assert link.asks(f"MOVE {MAX_STEPS}", "POS?") == [f"OK POS {MAX_STEPS}", f"OK POS {MAX_STEPS}"]


def test_move_out_of_range_changes_nothing(link: Link) -> None:
    link.asks("HOME", "MOVE 480")
    assert link.asks("MOVE -1", f"MOVE {MAX_STEPS + 1}", "MOVE 99999999999999999999", "MOVE -99999999999") == [
        OUT_OF_RANGE
    ] * 4
    assert link.ask("POS?") == "OK POS 480"


def test_leds(link: Link) -> None:
    assert link.asks("LED 0", "LED?") == ["OK LED 0", "OK LED 0"]  # LEDs need no homing
    assert link.asks(f"LED {N_LEDS - 1}", "LED?") == [f"OK LED {N_LEDS - 1}"] * 2
    assert link.asks(f"LED {N_LEDS}", "LED -1", "LED 0999", "LED?") == [
        LED_OUT_OF_RANGE, LED_OUT_OF_RANGE, LED_OUT_OF_RANGE, f"OK LED {N_LEDS - 1}",
    ]  # fmt: skip
    assert link.asks("LED 007", "LED OFF", "LED?", "LED OFF") == ["OK LED 7", "OK LED OFF", "OK LED OFF", "OK LED OFF"]


# --- errors ----------------------------------------------------------------------------------

BAD_LINES = {
    "FOO": UNKNOWN,
    "home": UNKNOWN,  # case-sensitive
    "Home": UNKNOWN,
    "led 3": UNKNOWN,
    "pos?": UNKNOWN,
    "LED\t3": UNKNOWN,  # only spaces separate tokens
    "POS": UNKNOWN,
    "ID? 1": UNEXPECTED,
    "HOME now": UNEXPECTED,
    "POS? 3": UNEXPECTED,
    "LED? 1": UNEXPECTED,
    "STOP now": UNEXPECTED,
    "MOVE": BAD_MOVE,
    "MOVE x": BAD_MOVE,
    "MOVE 1.5": BAD_MOVE,
    "MOVE +5": BAD_MOVE,
    "MOVE -": BAD_MOVE,
    "MOVE 1e3": BAD_MOVE,
    "MOVE 0x10": BAD_MOVE,
    "MOVE 1 2": BAD_MOVE,
    "LED": BAD_LED,
    "LED off": BAD_LED,
    "LED x": BAD_LED,
    "LED 1 2": BAD_LED,
    "LED OFF 2": BAD_LED,
}


def test_bad_commands_change_nothing(link: Link) -> None:
    link.asks("HOME", "MOVE 240", "LED 5")
    lines = list(BAD_LINES)
    assert dict(zip(lines, link.asks(*lines))) == BAD_LINES
    assert link.asks("POS?", "LED?") == ["OK POS 240", "OK LED 5"]


def test_error_precedence(link: Link) -> None:
    """1 (unknown command) before 2 (bad argument) before 4 (not homed) before 3 (out of range)."""
    assert link.asks("FOO 1 2", "MOVE x", "MOVE 1 2", "POS? 3", "MOVE -1", f"MOVE {MAX_STEPS + 1}") == [
        UNKNOWN, BAD_MOVE, BAD_MOVE, UNEXPECTED, NOT_HOMED, NOT_HOMED,
    ]  # fmt: skip
    assert link.ask(f"LED {N_LEDS}") == LED_OUT_OF_RANGE  # LEDs never need homing
    link.ask("HOME")
    assert link.asks("MOVE -1 2", "MOVE -1", "LED -1 2", "LED -1") == [
        BAD_MOVE, OUT_OF_RANGE, BAD_LED, LED_OUT_OF_RANGE,
    ]  # fmt: skip


def test_bytes_outside_ascii_are_part_of_tokens(link: Link) -> None:
    """Non-ASCII bytes and NUL are no separators, digits or verbs: the token they are in is invalid."""
    replies = []
    for data in (b"LED \xb3\n", b"\xffLED 3\n", b"LED 3\x00\n", b"LED\x003\n", b"@1\xb9 LED 3\n"):
        link.send(data)
        replies.append(link.reply())
    assert replies == [BAD_LED, UNKNOWN, BAD_LED, UNKNOWN, BAD_SEQUENCE]
    assert link.ask("LED?") == "OK LED OFF"


# --- line framing ------------------------------------------------------------------------------


def test_cr_and_blank_lines(link: Link) -> None:
    link.send(b"LED 5\r\n")
    assert link.reply() == "OK LED 5"
    link.send(b"\n\r\n   \n  \r\n\nLED?\n")  # blank lines get no reply: the next line is LED?'s
    assert link.reply() == "OK LED 5"
    link.send(b"LED?\r\r\n")  # only one CR is tolerated
    assert link.reply() == UNKNOWN
    link.send(b"  LED   6  \r\n")  # leading, repeated and trailing spaces
    assert link.reply() == "OK LED 6"


def test_command_split_across_writes(link: Link) -> None:
    link.send(b"LE")
    time.sleep(0.02)
    link.send(b"D 3")
    time.sleep(0.02)
    link.send(b"\n")
    assert link.reply() == "OK LED 3"


def test_line_length_limit(link: Link) -> None:
    """64 bytes including the ``\\n`` (and a ``\\r``, which counts) is the longest line."""
    longest = "LED " + "0" * 58 + "7"
    assert len(longest) + 1 == 64
    assert link.ask(longest) == "OK LED 7"
    assert link.ask(longest + "0") == TOO_LONG
    link.send(longest.encode() + b"\r\n")
    assert link.reply() == TOO_LONG
    assert link.ask("LED " + "1" * 300) == TOO_LONG  # one reply, however long
    assert link.ask("@5 LED " + "1" * 60) == TOO_LONG  # not read, so no prefix echoed
    assert link.ask("LED?") == "OK LED 7"  # framing recovered, nothing changed
    assert link.ask("@5 LED?") == "@5 OK LED 7"  # and the long @5 line was not stored


# --- sequence numbers (v2) ---------------------------------------------------------------------


def test_sequence_prefix_is_echoed(link: Link, backend: Backend) -> None:
    assert link.ask("@1 ID?") == f"@1 OK FACETSYNTH-RIG {backend.version} {IDENTITY}"
    assert link.asks("@0 HOME", "@9999 LED 3", "@0042 LED?", "@12 MOVE -1", "  @13   POS?  ") == [
        "@0 OK POS 0", "@9999 OK LED 3", "@42 OK LED 3", f"@12 {OUT_OF_RANGE}", "@13 OK POS 0",
    ]  # fmt: skip
    assert link.asks("@14", "@15 home", "@16 MOVE x", "@17 STOP now") == [
        "@14 ERR 1 EMPTY COMMAND", f"@15 {UNKNOWN}", f"@16 {BAD_MOVE}", f"@17 {UNEXPECTED}",
    ]  # fmt: skip
    assert link.ask("POS?") == "OK POS 0"  # without a prefix: no echo


def test_repeated_sequence_number_is_not_executed_again(link: Link) -> None:
    link.ask("HOME")
    assert link.ask("@8 MOVE 100") == "@8 OK POS 100"
    assert link.ask("MOVE 200") == "OK POS 200"  # unprefixed: neither uses nor changes the stored reply
    assert link.ask("@8 MOVE 100") == "@8 OK POS 100"  # the retry gets the stored reply ...
    assert link.ask("POS?") == "OK POS 200"  # ... and does not move
    assert link.ask("@8 LED 5") == "@8 OK POS 100"  # only the number is compared
    assert link.ask("LED?") == "OK LED OFF"
    assert link.asks("@9 MOVE 100", "POS?") == ["@9 OK POS 100", "OK POS 100"]  # a new number executes
    assert link.asks("@10 MOVE -5", "@10 MOVE 5", "POS?") == [f"@10 {OUT_OF_RANGE}"] * 2 + ["OK POS 100"]


def test_reset_forgets_the_stored_reply(link: Link, backend: Backend) -> None:
    assert link.asks("@3 LED 4", "@4 HOME") == ["@3 OK LED 4", "@4 OK POS 0"]
    backend.power_cycle()
    link.serial.reset_input_buffer()
    assert link.asks("LED?", "POS?") == ["OK LED OFF", NOT_HOMED]
    assert link.ask("@4 HOME") == "@4 OK POS 0"  # executed, not replayed:
    assert link.ask("POS?") == "OK POS 0"


@pytest.mark.parametrize("line", ["@ LED 3", "@", "@x LED 3", "@-1 LED 3", "@+1 LED 3", "@10000 LED 3",
                                  "@00000 LED 3", "@5LED 3", "@1.5 LED 3", "@@1 LED 3", "  @ LED 3"])  # fmt: skip
def test_malformed_sequence_prefix(link: Link, line: str) -> None:
    assert link.ask("@5 LED 2") == "@5 OK LED 2"
    assert link.ask(line) == BAD_SEQUENCE  # no prefix: none could be read
    assert link.ask("LED?") == "OK LED 2"  # nothing executed
    assert link.ask("@5 LED 6") == "@5 OK LED 2"  # nothing stored: @5 is still the last


# --- STOP (v2) -----------------------------------------------------------------------------------


def test_stop_between_commands(link: Link) -> None:
    assert link.ask("STOP") == "OK STOP"  # valid before the first HOME too
    link.asks("HOME", "MOVE 300", "LED 5")
    assert link.ask("STOP") == "OK STOP"
    assert link.asks("LED?", "POS?", "MOVE 10", "MOVE 300") == ["OK LED OFF", NOT_HOMED, NOT_HOMED, NOT_HOMED]
    assert link.ask("LED 6") == "OK LED 6"  # LEDs work without homing
    assert link.asks("HOME", "POS?", "MOVE 30") == ["OK POS 0", "OK POS 0", "OK POS 30"]
    assert link.asks("@3 STOP", "POS?", "LED?") == ["@3 OK STOP", NOT_HOMED, "OK LED OFF"]


def test_stop_is_never_replayed(link: Link) -> None:
    """A STOP whose number repeats the stored one is executed anyway (and its reply stored)."""
    assert link.ask("@4 LED 2") == "@4 OK LED 2"
    assert link.ask("@4 STOP") == "@4 OK STOP"
    assert link.ask("LED?") == "OK LED OFF"
    assert link.asks("LED 3", "@4 STOP", "LED?") == ["OK LED 3", "@4 OK STOP", "OK LED OFF"]
    assert link.asks("@4 LED 9", "LED?") == ["@4 OK STOP", "OK LED OFF"]


# --- through the driver ------------------------------------------------------------------------------


def test_driver_session(backend: Backend) -> None:
    with RigController.open(backend.port, timeout=REPLY_TIMEOUT) as rig:
        assert rig.identify() == RigInfo(backend.version, N_LEDS, MAX_STEPS, 80.0, protocol=2)
        with pytest.raises(RigError) as info:
            rig.position()
        assert info.value.code == ErrorCode.NOT_HOMED
        rig.home()
        for steps in (480, 960, 0):
            assert rig.move_to(steps) == steps
            for led in (0, 13, N_LEDS - 1):
                rig.led_on(led)
                assert rig.lit_led() == led
            assert rig.position() == steps
        with pytest.raises(RigError) as info:
            rig.move_to(MAX_STEPS + 1)
        assert (info.value.code, info.value.raw) == (ErrorCode.OUT_OF_RANGE, OUT_OF_RANGE)
        with pytest.raises(RigError) as info:
            rig.led_on(N_LEDS)
        assert info.value.code == ErrorCode.OUT_OF_RANGE
        rig.leds_off()
        assert rig.lit_led() is None


# --- firmware only: input during a motion, the simulated carriage --------------------------------------
# The emulator's motions are instantaneous: nothing can arrive during one, so these tests do not apply to it.


@pytest.fixture(params=FIRMWARE_BACKENDS)
def slow_backend(request: pytest.FixtureRequest, spawn: SpawnBackend) -> Backend:
    """A firmware backend whose motions take real time: 250 us per step on the host (a full travel takes
    6 s or more), the real step rates in simavr."""
    if request.param == "firmware":
        return spawn("firmware", FIRMWARE_STEP_US="250", FIRMWARE_START_STEPS="20")
    return spawn(request.param)


def stop_during(link: Link, command: str, stop: str = "STOP", after: float = 0.3) -> list[str]:
    """Send ``command``, then ``stop`` while its motion runs; the two replies."""
    link.send(command.encode() + b"\n")
    time.sleep(after)
    link.send(stop.encode() + b"\n")
    return [link.reply(), link.reply()]


def test_stop_during_move(slow_backend: Backend) -> None:
    link = open_link(slow_backend)
    try:
        assert link.asks("HOME", "LED 3") == ["OK POS 0", "OK LED 3"]
        assert stop_during(link, "@21 MOVE 24000", "@22 STOP") == ["@21 ERR 5 STOPPED", "@22 OK STOP"]
        assert 0 < slow_backend.carriage_at_motor_off() < MAX_STEPS  # stopped part way
        assert slow_backend.last_led_frame() == "leds 00 00 00 00 00"
        assert link.asks("LED?", "POS?", "MOVE 10") == ["OK LED OFF", NOT_HOMED, NOT_HOMED]
        assert link.asks("@21 MOVE 5", "@21 LED 1") == [f"@21 {NOT_HOMED}"] * 2  # replays work as before
        assert link.ask("HOME") == "OK POS 0"
        assert stop_during(link, f"MOVE {MAX_STEPS}") == ["ERR 5 STOPPED", "OK STOP"]
        assert link.ask("POS?") == NOT_HOMED
    finally:
        link.close()


@pytest.mark.parametrize("name", FIRMWARE_BACKENDS)
def test_stop_during_home(spawn: SpawnBackend, name: str) -> None:
    # 4000 steps from the switch: the approach alone takes 1 s or more on either backend.
    backend = spawn(name, FIRMWARE_START_STEPS="4000", **({"FIRMWARE_STEP_US": "250"} if name == "firmware" else {}))
    link = open_link(backend)
    try:
        assert stop_during(link, "@1 HOME", "@2 STOP", after=0.2) == ["@1 ERR 5 STOPPED", "@2 OK STOP"]
        assert 0 < backend.carriage_at_motor_off() < 4000
        assert link.asks("POS?", "MOVE 0") == [NOT_HOMED, NOT_HOMED]
    finally:
        link.close()


def test_other_input_during_a_motion_is_discarded(firmware_backend: Backend) -> None:
    """Everything but a valid STOP line is dropped, also a line that only ends after the motion."""
    link = open_link(firmware_backend)
    try:
        link.ask("HOME")
        # One write: the bytes after MOVE's line arrive while MOVE runs.
        link.send(b"MOVE 2000\nLED 7\nPOS?\nSTOP now\n@x STOP\nstop\n" + b"S" * 100 + b"TOP\nLED")
        assert link.reply() == "OK POS 2000"
        link.send(b" 9\n")  # completes the line begun during the motion: dropped too
        assert link.ask("LED?") == "OK LED OFF"  # the first reply after the motion's
        assert link.ask("POS?") == "OK POS 2000"  # still homed: no STOP was taken
    finally:
        link.close()


@pytest.mark.parametrize("start", [2000, 0, -50], ids=["off-switch", "at-switch", "on-switch"])
def test_steps_match_the_carriage(spawn: SpawnBackend, start: int) -> None:
    """After HOME the firmware's step count is the simulated carriage's position, wherever it started."""
    backend = spawn("firmware", FIRMWARE_START_STEPS=str(start))
    link = open_link(backend)
    try:
        assert link.asks("HOME", "MOVE 480", "MOVE 470", "STOP") == ["OK POS 0", "OK POS 480", "OK POS 470", "OK STOP"]
        assert backend.carriage_at_motor_off() == 470
    finally:
        link.close()


def test_home_fails_without_end_stop(spawn: SpawnBackend) -> None:
    """A carriage beyond the search limit (full travel + 10 %): the switch is never found.
    (Host build only: in simavr the search would take 13 s of simulated time.)"""
    backend = spawn("firmware", FIRMWARE_START_STEPS=str(MAX_STEPS * 2))
    link = open_link(backend)
    try:
        assert link.asks("HOME", "POS?") == ["ERR 4 HOME SWITCH NOT FOUND", NOT_HOMED]
        assert backend.carriage_at_motor_off() == MAX_STEPS * 2 - (MAX_STEPS + MAX_STEPS // 10)  # released
    finally:
        link.close()
