"""The driver's hardening (protocol v2) under injected faults, against the emulator and the firmware's host build.

A :class:`FaultProxy` sits between the driver and a backend of ``test_rig_conformance`` (whose fixtures are
reused): it serves the driver on a pseudo-terminal of its own and copies lines both ways to the backend's
pseudo-terminal, dropping, garbling or delaying chosen lines on request, or simulating a USB disconnect.
The driver's port path is a **symlink** in a temporary directory: a disconnect closes the proxy's pty (the
driver's reads and writes fail with EIO, as on an unplugged USB adapter), and a new pty appears a little later
and the symlink is repointed to it (a pty's own path cannot be chosen), so the driver reopens "the same port".
Meanwhile the symlink points nowhere, as a device node vanishes when its USB adapter is unplugged.
"""

from __future__ import annotations

import os
import queue
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
# The conformance suite's backends: host_firmware and spawn are fixtures, imported to be used here.
from test_rig_conformance import MAX_STEPS, Backend, SpawnBackend, host_firmware, spawn  # noqa: F401

from facetsynth.rig.driver import PositionError, RigController
from facetsynth.rig.emulator import VirtualController
from facetsynth.rig.protocol import ErrorCode, RigError, RigTimeoutError

TIMEOUT = 0.3  # s, per attempt (the backends answer within milliseconds)
MOTION_TIMEOUT = 0.5  # s; the firmware runs with FIRMWARE_STEP_US=0: motions take no time
RETRIES = 3


@dataclass
class Fault:
    """One injected fault: ``action`` on the next ``count`` lines (``direction`` ``"cmd"`` or ``"reply"``)
    containing ``match``."""

    direction: str
    match: bytes
    action: str  # "drop", "garble", "delay", "disconnect"
    count: float = 1
    delay: float = 0.0
    reset: Callable[[], None] | None = None  # for "disconnect": power-cycle the controller meanwhile
    gap: float = 0.3  # for "disconnect": seconds until the new port appears


class FaultProxy:
    """Copies lines between a driver-side pty (reached through the symlink ``path``) and ``backend_port``."""

    def __init__(self, backend_port: str, path: Path) -> None:
        self.path = path
        self.backend = os.open(backend_port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.faults: list[Fault] = []
        self.log: list[tuple[str, bytes]] = []  # ("cmd" | "reply", line as forwarded, "x" marks a fault)
        self.disconnects = 0
        self._lock = threading.Lock()
        self._master = self._slave = -1
        self._reappear_at: float | None = None
        self._delayed: list[tuple[float, bytes]] = []
        self._captured: queue.Queue[bytes] | None = None
        self._new_pty()
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="fault-proxy", daemon=True)
        self._thread.start()

    def inject(self, direction: str, match: str, action: str, **kw: object) -> Fault:
        fault = Fault(direction, match.encode(), action, **kw)  # type: ignore[arg-type]
        with self._lock:
            self.faults.append(fault)
        return fault

    def ask_backend(self, line: str) -> str:
        """Send ``line`` (unnumbered) to the backend directly; its reply, not forwarded to the driver."""
        self._captured = queue.Queue()
        os.write(self.backend, line.encode() + b"\n")
        try:
            return self._captured.get(timeout=2.0).decode().rstrip("\n")
        finally:
            self._captured = None

    def lines(self, direction: str) -> list[str]:
        with self._lock:
            return [line.decode("ascii", "replace") for d, line in self.log if d == direction]

    def close(self) -> None:
        self._stop = True
        os.write(self._wake_w, b"x")
        self._thread.join(5)
        for fd in (self._master, self._slave, self.backend, self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)

    # -- the thread -------------------------------------------------------------------

    def _new_pty(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self._repoint(Path(os.ttyname(self._slave)))

    def _repoint(self, target: Path) -> None:
        tmp = self.path.with_name(self.path.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(target)
        os.replace(tmp, self.path)  # atomic

    def _disconnect(self, fault: Fault) -> None:
        # First point the port path nowhere: pty numbers are system-wide, and the freed one may be taken by
        # another process's pty (another test run) before ours reappears; the driver must not open that one.
        self._repoint(self.path.with_name(self.path.name + ".unplugged"))
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = -1
        self.disconnects += 1
        if fault.reset is not None:
            fault.reset()
        self._reappear_at = time.monotonic() + fault.gap

    def _fault_for(self, direction: str, line: bytes) -> Fault | None:
        with self._lock:
            for fault in self.faults:
                if fault.direction == direction and fault.count > 0 and fault.match in line:
                    fault.count -= 1
                    return fault
        return None

    def _run(self) -> None:
        bufs = {"cmd": b"", "reply": b""}
        while not self._stop:
            now = time.monotonic()
            if self._reappear_at is not None and now >= self._reappear_at:
                self._reappear_at = None
                self._new_pty()
            for due, data in [d for d in self._delayed if d[0] <= now]:
                self._delayed.remove((due, data))
                self._to_driver(data)
            wakeups = [t for t in [self._reappear_at, *(d for d, _ in self._delayed)] if t is not None]
            wait = max(0.0, min(wakeups) - now) if wakeups else None
            fds = [self._wake_r, self.backend] + ([self._master] if self._master >= 0 else [])
            readable, _, _ = select.select(fds, [], [], wait)
            for fd in readable:
                if fd == self._wake_r:
                    return
                try:
                    chunk = os.read(fd, 4096)
                except (BlockingIOError, OSError):
                    continue  # EIO while the driver has the slave closed
                direction = "cmd" if fd == self._master else "reply"
                bufs[direction] += chunk
                while b"\n" in bufs[direction]:
                    line, _, bufs[direction] = bufs[direction].partition(b"\n")
                    self._line(direction, line + b"\n")

    def _line(self, direction: str, line: bytes) -> None:
        captured = self._captured
        if direction == "reply" and captured is not None:
            captured.put(line)
            return
        fault = self._fault_for(direction, line) if line.strip() else None
        action = fault.action if fault else "pass"
        if action == "garble":  # a non-ASCII byte over the second character: the sequence number's first digit
            line = line[:1] + b"\xb9" + line[2:]
        with self._lock:
            self.log.append((direction, line if action in ("pass", "garble") else b"x " + line))
        if action == "drop":
            return
        if action == "disconnect":
            assert fault is not None
            self._disconnect(fault)
            return
        if direction == "cmd":
            os.write(self.backend, line)
        elif action == "delay":
            assert fault is not None
            self._delayed.append((time.monotonic() + fault.delay, line))
        else:
            self._to_driver(line)

    def _to_driver(self, data: bytes) -> None:
        if self._master >= 0:  # replies to a disconnected driver are lost
            os.write(self._master, data)


# --- fixtures ----------------------------------------------------------------------------


@dataclass
class Setup:
    backend: Backend
    proxy: FaultProxy
    rig: RigController

    def position(self) -> int:
        """The carriage position according to the backend itself (not through the proxy)."""
        controller = self.emulator()
        if controller is not None:
            state = controller.state()
            assert state.homed
            return state.position
        reply = self.proxy.ask_backend("POS?")  # the firmware: asked directly, bypassing the driver
        assert reply.startswith("OK POS "), reply
        return int(reply.split()[2])

    def emulator(self) -> VirtualController | None:
        if self.backend.name != "emulator":
            return None
        return self.backend.power_cycle.__self__  # type: ignore[attr-defined]  # bound VirtualController.reset


@pytest.fixture(params=["emulator", "firmware"])
def setup(request: pytest.FixtureRequest, spawn: SpawnBackend, tmp_path: Path) -> Iterator[Setup]:  # noqa: F811
    backend = spawn(request.param)
    proxy = FaultProxy(backend.port, tmp_path / "ttyRIG")
    rig = RigController.connect(
        str(proxy.path),
        timeout=TIMEOUT,
        motion_timeout=MOTION_TIMEOUT,
        retries=RETRIES,
        reconnect_attempts=20,
        reconnect_delay=0.05,
    )
    try:
        assert rig.sequence and rig.info is not None and rig.info.protocol == 2
        rig.home()
        yield Setup(backend, proxy, rig)
    finally:
        rig.close()
        proxy.close()


def count_executions(setup: Setup, verb: str) -> list[list[str]]:
    """The emulator's executed commands with ``verb`` (replays are not executions), from now on."""
    controller = setup.emulator()
    executed: list[list[str]] = []
    if controller is not None:
        execute = controller._execute

        def counting(words: list[str]) -> str:
            if words[:1] == [verb]:
                executed.append(words)
            return execute(words)

        controller._execute = counting  # type: ignore[method-assign]
    return executed


# --- tests -------------------------------------------------------------------------------


@pytest.mark.parametrize("action", ["drop", "garble"])
def test_lost_or_garbled_move_reply_is_retried_and_moves_once(setup: Setup, action: str) -> None:
    moves = count_executions(setup, "MOVE")
    setup.proxy.inject("reply", "OK POS 480", action)
    assert setup.rig.move_to(480) == 480
    sent = [line for line in setup.proxy.lines("cmd") if "MOVE" in line]
    assert len(sent) == 2 and sent[0] == sent[1]  # the same line, the same number, twice
    assert setup.position() == 480
    if setup.emulator() is not None:
        assert moves == [["MOVE", "480"]]  # executed once; the retry got the stored reply
    assert setup.rig.move_to(960) == 960 and setup.position() == 960  # still in step


@pytest.mark.parametrize("action", ["garble", "drop"])
def test_garbled_or_lost_command_is_retried(setup: Setup, action: str) -> None:
    """A garbled sequence number gets an unnumbered ``ERR 2`` (retried at once), a lost line no reply."""
    setup.proxy.inject("cmd", "LED 7", action)
    start = time.monotonic()
    setup.rig.led_on(7)
    elapsed = time.monotonic() - start
    assert setup.rig.lit_led() == 7
    replies = setup.proxy.lines("reply")
    if action == "garble":
        assert "ERR 2 BAD SEQUENCE NUMBER\n" in replies
        assert elapsed < TIMEOUT  # no waiting for a timeout
    else:
        assert elapsed >= TIMEOUT
    if setup.emulator() is not None:
        assert setup.emulator().state().lit_led == 7  # type: ignore[union-attr]


def test_late_reply_is_discarded_as_stale(setup: Setup) -> None:
    """A reply delayed beyond the timeout: the retry's replayed reply is taken, the late one discarded."""
    moves = count_executions(setup, "MOVE")
    setup.proxy.inject("reply", "OK POS 300", "delay", delay=MOTION_TIMEOUT * 1.5)
    assert setup.rig.move_to(300) == 300
    time.sleep(MOTION_TIMEOUT)  # the late copy arrives now
    for led in (1, 2):
        setup.rig.led_on(led)
        assert setup.rig.lit_led() == led
    assert setup.rig.position() == 300 == setup.position()
    if setup.emulator() is not None:
        assert moves == [["MOVE", "300"]]


def test_timeout_on_every_attempt(setup: Setup) -> None:
    setup.proxy.inject("reply", "OK LED", "drop", count=float("inf"))
    start = time.monotonic()
    with pytest.raises(RigTimeoutError) as info:
        setup.rig.lit_led()
    elapsed = time.monotonic() - start
    message = str(info.value)
    assert str(setup.proxy.path) in message and "'LED?'" in message and f"attempt {RETRIES + 1} of" in message
    assert (info.value.command, info.value.port) == ("LED?", str(setup.proxy.path))
    sent = [line for line in setup.proxy.lines("cmd") if "LED?" in line]
    assert len(sent) == RETRIES + 1 and len(set(sent)) == 1
    assert (RETRIES + 1) * TIMEOUT * 0.9 <= elapsed < (RETRIES + 1) * TIMEOUT + 1.0


def test_err_replies_are_answers_not_retried(setup: Setup) -> None:
    with pytest.raises(RigError) as info:
        setup.rig.move_to(MAX_STEPS + 1)
    assert info.value.code == ErrorCode.OUT_OF_RANGE
    assert len([line for line in setup.proxy.lines("cmd") if "MOVE" in line]) == 1


@pytest.mark.parametrize("reset", [True, False], ids=["controller-reset", "no-reset"])
def test_disconnect_mid_sequence_reconnects_and_rehomes(setup: Setup, reset: bool) -> None:
    rig, proxy = setup.rig, setup.proxy
    assert rig.move_to(480) == 480
    rig.led_on(5)
    proxy.inject("cmd", "MOVE 960", "disconnect", reset=setup.backend.power_cycle if reset else None)
    assert rig.move_to(960) == 960
    assert rig.reconnects == 1 and proxy.disconnects == 1
    assert setup.position() == 960, (proxy.log, rig.reconnects)
    assert rig.lit_led() == 5  # the LEDs the driver had set are restored
    after = proxy.lines("cmd")
    homes = [line for line in after if line.split()[1:] == ["HOME"]]
    assert len(homes) == (2 if reset else 1)  # the session's HOME, and one after the reset
    if setup.emulator() is not None:
        assert setup.emulator().state().lit_led == 5  # type: ignore[union-attr]
    # A query after a disconnect with reset: re-homed and moved back to where the driver had left it.
    proxy.inject("cmd", "POS?", "disconnect", reset=setup.backend.power_cycle)
    assert rig.position() == 960 == setup.position()
    assert rig.reconnects == 2


def test_disconnect_that_does_not_come_back(setup: Setup) -> None:
    rig = setup.rig
    rig.reconnect_attempts, rig.reconnect_delay = 3, 0.05
    setup.proxy.inject("cmd", "LED?", "disconnect", gap=60)
    start = time.monotonic()
    with pytest.raises(RigError, match=rf"{setup.proxy.path}.*'LED\?'.*reopen") as info:
        rig.lit_led()
    assert time.monotonic() - start < 5
    assert info.value.port == str(setup.proxy.path)


def test_stop(setup: Setup) -> None:
    setup.rig.move_to(240)
    setup.rig.led_on(3)
    setup.rig.stop()
    assert setup.rig.lit_led() is None
    with pytest.raises(RigError) as info:
        setup.rig.position()
    assert info.value.code == ErrorCode.NOT_HOMED
    setup.rig.home()
    assert setup.rig.move_to(24) == 24


def test_position_is_asked_after_every_move(setup: Setup) -> None:
    """``POS?`` follows every move."""
    setup.rig.move_to(120)
    cmds = [line.split(" ", 1)[1] for line in setup.proxy.lines("cmd") if line.startswith("@")]
    assert cmds[-2:] == ["MOVE 120\n", "POS?\n"]


@pytest.mark.parametrize("setup", ["emulator"], indirect=True)   # only the emulator's replies can be altered
def test_a_position_that_disagrees_raises(setup: Setup) -> None:
    """A ``POS?`` answer other than the requested position (a garbled-but-valid reply) raises PositionError."""
    controller = setup.emulator()
    handle = controller.handle

    def lying(line: str) -> str:
        reply = handle(line)
        return reply.replace("OK POS 360", "OK POS 359") if "POS?" in line else reply

    controller.handle = lying  # type: ignore[method-assign]
    with pytest.raises(PositionError, match=r"reports position 359 after 'MOVE 360', expected 360"):
        setup.rig.move_to(360)


# --- an absent controller ------------------------------------------------------------------


def test_nonexistent_port_fails_fast(tmp_path: Path) -> None:
    port = str(tmp_path / "ttyNOTHING")
    start = time.monotonic()
    with pytest.raises(RigError, match="ttyNOTHING"):
        RigController.connect(port)
    assert time.monotonic() - start < 1


def test_silent_port_fails_within_the_timeout() -> None:
    """Nothing answers ``ID?``: RigTimeoutError naming the port after one timeout (default 2 s), not after
    every retry."""
    master, slave = os.openpty()
    tty.setraw(slave)
    port = os.ttyname(slave)
    try:
        start = time.monotonic()
        with pytest.raises(RigTimeoutError, match=rf"no rig controller answers on {port}.*'ID\?'"):
            RigController.connect(port)
        assert time.monotonic() - start < 5
    finally:
        os.close(master)
        os.close(slave)
