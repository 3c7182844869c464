"""A virtual rig controller: the firmware's behaviour in Python.

:class:`VirtualController` is the protocol's state machine
(``rig/PROTOCOL.md``): :meth:`VirtualController.handle` maps one command
line to one reply line without any I/O. :class:`PtyServer` (or the
:func:`virtual_port` context manager) serves it on a pseudo-terminal, so the
host talks to it through :class:`facetsynth.rig.driver.RigController` exactly
as it would to the real controller on a serial port.

The virtual camera reads the rig state (carriage position, lit LED) through
:meth:`VirtualController.state`, which returns an immutable snapshot taken
under the controller's lock.

Protocol version 2 (sequence prefixes with replay, ``STOP``) is implemented
too. Motions are instantaneous here: the reply to ``HOME``/``MOVE`` is sent at
once, so ``STOP`` only ever arrives between commands and ``ERR 5 STOPPED``
(a motion aborted by ``STOP``, see the C firmware in ``rig/firmware/``) never
occurs.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import tty
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from .protocol import (MAX_COMMAND_LENGTH, MAX_REPLY_LENGTH, PROTOCOL_VERSION, ErrorCode, RigInfo, encode_line,
                       format_err, format_identity, format_ok, parse_int, split_sequence, split_words, with_sequence)

__all__ = ["ControllerState", "VirtualController", "PtyServer", "virtual_port"]

log = logging.getLogger(__name__)

DEFAULT_N_LEDS = 40
"""LEDs in the array (Wang et al. 2008, sec. 4)."""
DEFAULT_STEPS_PER_MM = 80.0
"""Motor steps per millimetre of carriage travel (1.8 deg motor, 16x microstepping, 40 mm/rev belt)."""
DEFAULT_MAX_STEPS = 24000
"""Full carriage travel in steps (300 mm at the default steps/mm)."""
FIRMWARE_VERSION = "0.1.0-virtual"
"""Version token the virtual controller reports to ``ID?``."""


@dataclass(frozen=True)
class ControllerState:
    """Immutable snapshot of the controller's state.

    Attributes:
        homed: Whether ``HOME`` has run since the last reset or ``STOP``.
        position: Carriage position in motor steps from the home end
            stop (meaningless, and 0, while not homed).
        lit_led: Index of the lit LED, or ``None`` when all LEDs are off.
        revision: Incremented on every state change; lets a reader detect
            that something moved or switched.
    """

    homed: bool
    position: int
    lit_led: int | None
    revision: int


class VirtualController:
    """The rig controller firmware, emulated.

    Thread-safe: :meth:`handle`, :meth:`reset` and :meth:`state` may be called
    from any thread.
    """

    def __init__(
        self,
        n_leds: int = DEFAULT_N_LEDS,
        max_steps: int = DEFAULT_MAX_STEPS,
        steps_per_mm: float = DEFAULT_STEPS_PER_MM,
        firmware: str = FIRMWARE_VERSION,
    ) -> None:
        if n_leds < 1 or max_steps < 0 or not steps_per_mm > 0:
            raise ValueError("need n_leds >= 1, max_steps >= 0, steps_per_mm > 0")
        self.info = RigInfo(
            firmware=firmware,
            n_leds=n_leds,
            max_steps=max_steps,
            steps_per_mm=float(steps_per_mm),
            protocol=PROTOCOL_VERSION,
        )
        format_identity(self.info)  # validates the firmware token
        self._lock = threading.Lock()
        self._homed = False
        self._position = 0
        self._lit: int | None = None
        self._revision = 0
        # Sequence number and reply of the last prefixed command (v2 replay).
        self._last_seq: int | None = None
        self._last_reply = ""

    # -- conveniences --------------------------------------------------------

    @property
    def n_leds(self) -> int:
        """LEDs in the array."""
        return self.info.n_leds

    @property
    def max_steps(self) -> int:
        """Largest valid carriage position in steps."""
        return self.info.max_steps

    @property
    def steps_per_mm(self) -> float:
        """Motor steps per millimetre of carriage travel."""
        return self.info.steps_per_mm

    def state(self) -> ControllerState:
        """A consistent snapshot of homed flag, position and lit LED."""
        with self._lock:
            return ControllerState(self._homed, self._position, self._lit, self._revision)

    def reset(self) -> None:
        """Power-on reset: all LEDs off, position forgotten (not homed), stored sequence reply forgotten."""
        with self._lock:
            self._homed = False
            self._position = 0
            self._lit = None
            self._revision += 1
            self._last_seq = None
            self._last_reply = ""

    def serve_pty(self) -> PtyServer:
        """Start serving this controller on a new pseudo-terminal.

        Returns the running :class:`PtyServer`; use it as a context manager
        or call :meth:`PtyServer.close`. Its ``port`` is the device path to
        open with the driver.
        """
        return PtyServer(self).start()

    # -- the state machine ---------------------------------------------------

    def handle(self, line: str) -> str:
        """Execute one command line and return its reply line (no terminator).

        ``line`` may carry its ``\\n`` / ``\\r\\n``. The line-framing layer
        (:class:`PtyServer`) drops blank lines without calling this; if one is
        passed anyway it is an unknown command.

        A line with a sequence prefix ``@<n>`` is answered with the same
        prefix; if ``n`` repeats the number of the last prefixed command, that
        command's reply is returned again without executing anything (except
        for ``STOP``, which always runs).
        """
        line = line.removesuffix("\n").removesuffix("\r")
        if len(line.encode("ascii", "replace")) + 1 > MAX_COMMAND_LENGTH:
            return format_err(ErrorCode.BAD_ARGUMENT, "LINE TOO LONG")
        try:
            seq, body = split_sequence(line)
        except ValueError:
            return format_err(ErrorCode.BAD_ARGUMENT, "BAD SEQUENCE NUMBER")
        words = split_words(body)
        with self._lock:
            if seq is None:
                return self._execute(words)
            if seq == self._last_seq and words[:1] != ["STOP"]:
                return self._last_reply  # a retry: not executed again
            reply = with_sequence(seq, self._execute(words))
            self._last_seq, self._last_reply = seq, reply
            return reply

    # Helpers below run with self._lock held.

    def _execute(self, words: list[str]) -> str:
        """The reply to one command, its words without a sequence prefix."""
        if not words:
            return format_err(ErrorCode.UNKNOWN_COMMAND, "EMPTY COMMAND")
        verb, args = words[0], words[1:]
        if verb == "ID?":
            return _no_args(args) or format_identity(self.info)
        if verb == "HOME":
            return _no_args(args) or self._home()
        if verb == "MOVE":
            return self._move(args)
        if verb == "POS?":
            return _no_args(args) or self._require_homed() or format_ok("POS", self._position)
        if verb == "LED":
            return self._led(args)
        if verb == "LED?":
            return _no_args(args) or format_ok("LED", "OFF" if self._lit is None else self._lit)
        if verb == "STOP":
            return _no_args(args) or self._stop()
        return format_err(ErrorCode.UNKNOWN_COMMAND, "UNKNOWN COMMAND")

    def _require_homed(self) -> str | None:
        if not self._homed:
            return format_err(ErrorCode.NOT_HOMED, "NOT HOMED")
        return None

    def _home(self) -> str:
        self._homed = True
        self._position = 0
        self._revision += 1
        return format_ok("POS", 0)

    def _move(self, args: list[str]) -> str:
        steps = parse_int(args[0]) if len(args) == 1 else None
        if steps is None:
            return format_err(ErrorCode.BAD_ARGUMENT, "EXPECTED MOVE <steps>")
        error = self._require_homed()
        if error:
            return error
        if not 0 <= steps <= self.info.max_steps:
            return format_err(ErrorCode.OUT_OF_RANGE, f"POSITION OUT OF RANGE 0..{self.info.max_steps}")
        if steps != self._position:
            self._position = steps
            self._revision += 1
        return format_ok("POS", steps)

    def _stop(self) -> str:
        """Emergency stop: LEDs off, position no longer trusted (motions are instantaneous here)."""
        if self._homed or self._position != 0 or self._lit is not None:
            self._homed = False
            self._position = 0
            self._lit = None
            self._revision += 1
        return format_ok("STOP")

    def _led(self, args: list[str]) -> str:
        if len(args) == 1 and args[0] == "OFF":
            lit: int | None = None
        else:
            index = parse_int(args[0]) if len(args) == 1 else None
            if index is None:
                return format_err(ErrorCode.BAD_ARGUMENT, "EXPECTED LED <index>|OFF")
            if not 0 <= index < self.info.n_leds:
                return format_err(ErrorCode.OUT_OF_RANGE, f"LED INDEX OUT OF RANGE 0..{self.info.n_leds - 1}")
            lit = index
        if lit != self._lit:
            self._lit = lit
            self._revision += 1
        return format_ok("LED", "OFF" if lit is None else lit)


def _no_args(args: list[str]) -> str | None:
    """An ``ERR 2`` reply if a command that takes no argument got some."""
    if args:
        return format_err(ErrorCode.BAD_ARGUMENT, "UNEXPECTED ARGUMENT")
    return None


class PtyServer:
    """Serves a :class:`VirtualController` on a pseudo-terminal.

    The slave end (``port``, e.g. ``/dev/pts/7``) is put in raw mode and
    kept open for the server's lifetime, so clients may open and close it
    freely; a daemon thread reads command lines from the master end and
    writes one reply per line. :meth:`close` stops the thread (via a
    self-pipe) and closes every descriptor.
    """

    def __init__(self, controller: VirtualController) -> None:
        self.controller = controller
        self.port: str = ""
        self._master = -1
        self._slave = -1
        self._stop_r = -1
        self._stop_w = -1
        self._thread: threading.Thread | None = None

    def start(self) -> PtyServer:
        """Open the pty pair and start the serving thread; returns ``self``."""
        if self._thread is not None:
            raise RuntimeError("PtyServer already started")
        self._master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)
            self.port = os.ttyname(self._slave)
            os.set_blocking(self._master, False)
            self._stop_r, self._stop_w = os.pipe()
        except BaseException:
            self._close_fds()
            raise
        self._thread = threading.Thread(target=self._serve, name=f"virtual-rig {self.port}", daemon=True)
        self._thread.start()
        log.debug("virtual rig controller serving on %s", self.port)
        return self

    def close(self) -> None:
        """Stop the serving thread and close both pty ends (idempotent)."""
        if self._thread is not None:
            try:
                os.write(self._stop_w, b"x")
            except OSError:
                pass
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():  # pragma: no cover - would be a bug
                log.error("virtual rig thread on %s did not stop", self.port)
            self._thread = None
        self._close_fds()

    def __enter__(self) -> PtyServer:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_fds(self) -> None:
        for name in ("_master", "_slave", "_stop_r", "_stop_w"):
            fd = getattr(self, name)
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, -1)

    def _serve(self) -> None:
        """Thread body: frame lines from the master end, reply to each."""
        buf = bytearray()
        overflow = False
        while True:
            readable, _, _ = select.select([self._master, self._stop_r], [], [])
            if self._stop_r in readable:
                return
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError:  # EIO: no slave open; cannot happen while we hold it
                return
            buf += chunk
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) >= MAX_COMMAND_LENGTH:
                        overflow = True  # discard up to the next newline
                        buf.clear()
                    break
                raw = bytes(buf[:nl])
                del buf[: nl + 1]
                if overflow or nl + 1 > MAX_COMMAND_LENGTH:
                    overflow = False
                    reply = format_err(ErrorCode.BAD_ARGUMENT, "LINE TOO LONG")
                else:
                    text = raw.decode("ascii", errors="replace")  # handle() drops one "\r"
                    if not text.removesuffix("\r").strip(" "):  # blank: only spaces count
                        continue
                    reply = self.controller.handle(text)
                if not self._write_all(encode_line(reply, limit=MAX_REPLY_LENGTH)):
                    return

    def _write_all(self, data: bytes) -> bool:
        """Write ``data`` to the master end; ``False`` if asked to stop first."""
        view = memoryview(data)
        while view:
            readable, writable, _ = select.select([self._stop_r], [self._master], [])
            if readable:
                return False
            try:
                view = view[os.write(self._master, view) :]
            except BlockingIOError:
                continue
        return True


@contextmanager
def virtual_port(controller: VirtualController) -> Iterator[str]:
    """Serve ``controller`` on a pseudo-terminal; yields the port to open.

    On exit the serving thread is stopped and both pty ends are closed.
    """
    with PtyServer(controller) as server:
        yield server.port
