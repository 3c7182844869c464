"""Host-side driver for the rig controller (protocol: ``rig/PROTOCOL.md``).

:class:`RigController` is the one driver for both the real controller on a
serial port and the virtual controller on a pseudo-terminal
(:mod:`facetsynth.rig.emulator`). Every command waits for its reply; a
missing reply, an ``ERR`` reply or a malformed reply raises
:class:`~facetsynth.rig.protocol.RigError` (or a subclass).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol, Self, TypeVar

import serial

from . import protocol
from .protocol import (
    BAUDRATE,
    ErrReply,
    OkReply,
    ProtocolError,
    RigError,
    RigInfo,
    RigTimeoutError,
)

__all__ = ["SerialLike", "RigController", "RigInfo", "RigError"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

DEFAULT_TIMEOUT = 2.0
"""Seconds to wait for the reply to a non-motion command."""
DEFAULT_MOTION_TIMEOUT = 60.0
"""Seconds to wait for the reply to ``HOME`` / ``MOVE`` (sent after the motion ends)."""


class SerialLike(Protocol):
    """What the driver needs from a port (``serial.Serial`` satisfies it).

    ``readline`` returns the bytes up to and including ``b"\\n"``, or what
    arrived before the timeout (possibly ``b""``). If the object also has a
    writable ``timeout`` attribute and ``reset_input_buffer()``, the driver
    uses them (longer timeout for motion; discarding stale input).
    """

    def write(self, data: bytes, /) -> int | None: ...

    def readline(self) -> bytes: ...

    def close(self) -> None: ...


class RigController:
    """The rig controller: LED array on a motorised carriage.

    Args:
        port: An open serial-like object (see :class:`SerialLike`).
        name: Port name used in messages (default: ``port.port`` if present).
        motion_timeout: Reply timeout for ``HOME`` / ``MOVE``, applied if
            ``port`` has a ``timeout`` attribute; ``None`` keeps the port's.

    Thread-safe: exchanges are serialised by a lock.
    """

    def __init__(
        self,
        port: SerialLike,
        *,
        name: str | None = None,
        motion_timeout: float | None = DEFAULT_MOTION_TIMEOUT,
    ) -> None:
        self._serial: SerialLike | None = port
        self.port_name: str = name or str(getattr(port, "port", None) or port)
        self.motion_timeout = motion_timeout
        self._lock = threading.Lock()

    @classmethod
    def open(
        cls,
        port: str,
        baudrate: int = BAUDRATE,
        timeout: float = DEFAULT_TIMEOUT,
        *,
        motion_timeout: float | None = DEFAULT_MOTION_TIMEOUT,
    ) -> Self:
        """Open ``port`` (device path or pyserial URL such as ``loop://``), 8N1.

        Raises:
            RigError: if the port cannot be opened.
        """
        try:
            ser = serial.serial_for_url(
                port,
                baudrate=baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                xonxoff=False,
                rtscts=False,
                timeout=timeout,
                write_timeout=timeout,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise RigError(f"cannot open rig controller port {port}: {exc}", port=port) from exc
        return cls(ser, name=port, motion_timeout=motion_timeout)

    # -- commands ------------------------------------------------------------

    def identify(self) -> RigInfo:
        """Firmware version and rig dimensions (``ID?``)."""
        command = protocol.cmd_identify()
        return self._parse(protocol.parse_identity, self._exchange(command), command)

    def home(self) -> None:
        """Drive the carriage to the home end stop; position becomes 0 (``HOME``)."""
        command = protocol.cmd_home()
        position = self._parse(protocol.parse_position, self._exchange(command, motion=True), command)
        self._expect(position == 0, command, f"home position {position}, expected 0")

    def move_to(self, steps: int) -> int:
        """Move the carriage to absolute position ``steps``; returns the position reached."""
        command = protocol.cmd_move(steps)
        position = self._parse(protocol.parse_position, self._exchange(command, motion=True), command)
        self._expect(position == steps, command, f"reached position {position}, expected {steps}")
        return position

    def position(self) -> int:
        """Carriage position in steps from the home end stop (``POS?``)."""
        command = protocol.cmd_position()
        return self._parse(protocol.parse_position, self._exchange(command), command)

    def led_on(self, index: int) -> None:
        """Light exactly LED ``index`` (0-based); all others go off."""
        command = protocol.cmd_led(index)
        lit = self._parse(protocol.parse_led, self._exchange(command), command)
        self._expect(lit == index, command, f"controller reports LED {lit}, expected {index}")

    def leds_off(self) -> None:
        """Switch all LEDs off."""
        command = protocol.cmd_leds_off()
        lit = self._parse(protocol.parse_led, self._exchange(command), command)
        self._expect(lit is None, command, f"controller reports LED {lit} lit, expected all off")

    def lit_led(self) -> int | None:
        """Index of the lit LED, or ``None`` if all are off (``LED?``)."""
        command = protocol.cmd_lit_led()
        return self._parse(protocol.parse_led, self._exchange(command), command)

    # -- lifetime ------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has been called."""
        return self._serial is None

    def close(self) -> None:
        """Close the port (idempotent). The LEDs are left as they are."""
        with self._lock:
            ser, self._serial = self._serial, None
        if ser is not None:
            ser.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.port_name!r}{', closed' if self.closed else ''})"

    # -- the exchange --------------------------------------------------------

    def _exchange(self, command: str, *, motion: bool = False) -> OkReply:
        """Send ``command``, wait for its reply line, return it if ``OK``."""
        data = protocol.encode_line(command)
        with self._lock:
            ser = self._serial
            if ser is None:
                raise RigError(f"rig controller on {self.port_name} is closed", command=command, port=self.port_name)
            timeout = getattr(ser, "timeout", None)
            use_motion_timeout = motion and self.motion_timeout is not None and hasattr(ser, "timeout")
            if use_motion_timeout:
                ser.timeout = max(self.motion_timeout, timeout or 0.0)  # type: ignore[attr-defined]
            start = time.monotonic()
            try:
                reset = getattr(ser, "reset_input_buffer", None)
                if reset is not None:
                    reset()  # drop stale bytes, e.g. a reply that came after a timeout
                ser.write(data)
                flush = getattr(ser, "flush", None)
                if flush is not None:
                    flush()
                raw = ser.readline()
            except serial.SerialTimeoutException as exc:
                raise RigTimeoutError(
                    f"timed out writing {command!r} to rig controller on {self.port_name}",
                    command=command,
                    port=self.port_name,
                ) from exc
            except (serial.SerialException, OSError) as exc:
                raise RigError(
                    f"I/O error on rig controller port {self.port_name} during {command!r}: {exc}",
                    command=command,
                    port=self.port_name,
                ) from exc
            finally:
                waited = getattr(ser, "timeout", None)
                if use_motion_timeout:
                    ser.timeout = timeout  # type: ignore[attr-defined]
            elapsed = time.monotonic() - start
        log.debug("%s > %r < %r (%.1f ms)", self.port_name, command, raw, 1e3 * elapsed)

        if not raw.endswith(b"\n"):
            partial = f" (partial reply {raw!r})" if raw else ""
            limit = f" within {waited:g} s" if isinstance(waited, (int, float)) else ""
            raise RigTimeoutError(
                f"no reply from rig controller on {self.port_name} to {command!r}{limit}{partial}",
                raw=raw.decode("ascii", "replace") or None,
                command=command,
                port=self.port_name,
            )
        try:
            text = raw.decode("ascii")
            reply = protocol.parse_reply(text)
        except (UnicodeDecodeError, ProtocolError) as exc:
            raise ProtocolError(
                f"bad reply from rig controller on {self.port_name} to {command!r}: {raw!r}",
                raw=raw.decode("ascii", "replace"),
                command=command,
                port=self.port_name,
            ) from exc
        if reply.seq is not None:  # this driver sends no sequence prefixes (protocol v2), so expects none back
            raise ProtocolError(
                f"rig controller on {self.port_name} answered {command!r} with a sequence prefix: {raw!r}",
                raw=reply.raw,
                command=command,
                port=self.port_name,
            )
        if isinstance(reply, ErrReply):
            raise reply.to_error(command=command, port=self.port_name)
        return reply

    def _parse(self, parse: Callable[[OkReply], _T], reply: OkReply, command: str) -> _T:
        """Apply a reply parser, naming port and command on failure."""
        try:
            return parse(reply)
        except ProtocolError as exc:
            raise ProtocolError(
                f"unexpected reply from rig controller on {self.port_name} to {command!r}: {reply.raw!r}",
                raw=reply.raw,
                command=command,
                port=self.port_name,
            ) from exc

    def _expect(self, condition: bool, command: str, what: str) -> None:
        """Raise :class:`ProtocolError` unless the reply matched the request."""
        if not condition:
            raise ProtocolError(
                f"rig controller on {self.port_name} answered {command!r} inconsistently: {what}",
                command=command,
                port=self.port_name,
            )
