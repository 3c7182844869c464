"""Host-side driver for the rig controller (protocol: ``rig/PROTOCOL.md``).

:class:`RigController` is the one driver for both the real controller on a
serial port and the virtual controller on a pseudo-terminal
(:mod:`facetsynth.rig.emulator`). Every command waits for its reply; a
missing reply, an ``ERR`` reply or a malformed reply raises
:class:`~facetsynth.rig.protocol.RigError` (or a subclass).

With a protocol version 2 controller (``PROTO=2`` in the reply to ``ID?``)
the driver hardens the link (see :class:`RigController`): every command
carries a sequence number ``@<n>`` that the reply must echo; lost, garbled
or stale replies are retried under the same number (the controller replays
its stored reply instead of executing again); a USB disconnect is survived
by reopening the port and restoring the controller's state; and every move
is verified with ``POS?``. Use :meth:`RigController.connect` to open a port
and check that a controller answers there.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol, Self, TypeVar

import serial

from . import protocol
from .protocol import (BAUDRATE, MAX_SEQUENCE, ErrorCode, ErrReply, OkReply, ProtocolError, RigError, RigInfo,
                       RigTimeoutError)

__all__ = ["SerialLike", "RigController", "RigInfo", "RigError", "PositionError"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

try:  # pyserial lets termios.error (not an OSError) escape from flush() / reset_input_buffer() on POSIX
    import termios

    _IO_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # pragma: no cover - Windows
    _IO_ERRORS = (serial.SerialException, OSError)

DEFAULT_TIMEOUT = 2.0
"""Seconds to wait for the reply to a non-motion command."""
DEFAULT_MOTION_TIMEOUT = 60.0
"""Seconds to wait for the reply to ``HOME`` / ``MOVE`` (sent after the motion ends)."""
DEFAULT_RETRIES = 3
"""Times a command is sent again after a timeout or a garbled / mismatching reply (protocol v2)."""
DEFAULT_RECONNECT_ATTEMPTS = 5
"""Times the driver tries to reopen a port that failed with an I/O error (protocol v2)."""
DEFAULT_RECONNECT_DELAY = 0.5
"""Seconds to wait before each attempt to reopen the port."""


class PositionError(RigError):
    """The carriage is not where it was sent (``POS?`` after a move disagrees)."""


class _Retry(Exception):
    """Internal: this attempt failed in a way a resend of the same number may fix."""

    def __init__(self, error: RigError) -> None:
        super().__init__(str(error))
        self.error = error


class _Disconnected(Exception):
    """Internal: the port raised an I/O error (e.g. the USB adapter was unplugged)."""

    def __init__(self, error: RigError) -> None:
        super().__init__(str(error))
        self.error = error


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
        sequence: Whether to send sequence prefixes ``@<n>`` (protocol v2).
            ``None`` (default): from the moment :meth:`identify` reports a
            version 2 controller; before that, and with a version 1
            controller, commands go unprefixed and are sent once.
        retries: With sequence prefixes, how often a command is sent again
            after a timeout, an unparseable reply or a reply that does not
            echo its number.
        reopen: Returns the same port opened anew; used to reconnect after an
            I/O error (set by :meth:`open` / :meth:`connect`; ``None``: an
            I/O error is final).
        reconnect_attempts: Attempts to reopen the port after an I/O error.
        reconnect_delay: Seconds to wait before each attempt.

    **Sequence numbers and retries** (protocol v2). Every command is sent as
    ``@<n> <command>``, ``n`` cycling through 0..9999, and only a reply
    starting with ``@<n>`` is taken as its answer: replies with another or no
    number are stale (e.g. late answers to an earlier attempt) and are
    discarded while the driver keeps reading until the timeout. On a
    timeout, a garbled reply, or an unnumbered ``ERR`` (the controller could
    not read the number, so it executed nothing), the *same* line with the
    *same* number is sent again, up to ``retries`` times. This is safe for
    every command, ``MOVE`` and ``HOME`` included: the controller does not
    execute a repeated number again but replays the reply it stored, so a
    carriage whose reply was lost moves once. (``STOP`` is always executed,
    which is harmless.) ``ERR`` replies that echo the number are answers and
    are raised at once, never retried. After the last attempt the last error
    is raised (:class:`~facetsynth.rig.protocol.RigTimeoutError` naming port
    and command after timeouts). The first numbered exchange of a session is
    an extra ``ID?``, so that a number the controller stored in an earlier
    session cannot be mistaken for a retry.

    **Reconnecting** (protocol v2, ports opened with :meth:`open` /
    :meth:`connect`). If the port raises an I/O error (USB adapter unplugged
    and plugged in again), the driver closes it and reopens the same path,
    waiting ``reconnect_delay`` before each of at most
    ``reconnect_attempts`` tries. The controller may have been reset
    meanwhile (LEDs off, not homed, stored reply forgotten), so the driver
    then restores what it had established: it sends a lone ``\\n`` (drops a
    partial line) and ``ID?``; if it had homed the controller (and no
    ``STOP`` since) and ``POS?`` now answers ``ERR 4``, it sends ``HOME`` and,
    unless the interrupted command is a ``MOVE``, moves back to the last
    verified position; if it had set the LEDs and ``LED?`` disagrees, it sets
    them again (unless the interrupted command sets them itself). Then the
    interrupted command is sent again under a new number (all commands of the
    protocol are absolute, so executing one twice is harmless). Nothing else
    is restored (there is no other controller state). Each reconnection
    counts as one of the ``retries``. Reopening goes by path: name the port by
    one that stays with the adapter (``/dev/serial/by-id/...``), as another
    device may take ``/dev/ttyUSB0`` while this one is unplugged.

    **Verified moves.** :meth:`home` and :meth:`move_to` ask ``POS?`` after
    the motion and raise :class:`PositionError` if the controller reports
    another position.

    Thread-safe: exchanges are serialised by a lock (so :meth:`stop` waits
    for a command in progress on another thread).
    """

    def __init__(
        self,
        port: SerialLike,
        *,
        name: str | None = None,
        motion_timeout: float | None = DEFAULT_MOTION_TIMEOUT,
        sequence: bool | None = None,
        retries: int = DEFAULT_RETRIES,
        reopen: Callable[[], SerialLike] | None = None,
        reconnect_attempts: int = DEFAULT_RECONNECT_ATTEMPTS,
        reconnect_delay: float = DEFAULT_RECONNECT_DELAY,
    ) -> None:
        if retries < 0 or reconnect_attempts < 0 or reconnect_delay < 0:
            raise ValueError("retries, reconnect_attempts and reconnect_delay must not be negative")
        self._serial: SerialLike | None = port
        self.port_name: str = name or str(getattr(port, "port", None) or port)
        self.motion_timeout = motion_timeout
        self.sequence = sequence
        self.retries = retries
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_delay = reconnect_delay
        self._reopen = reopen
        self._lock = threading.RLock()
        self._next_seq = 0
        self._synced = False
        # What the driver established on the controller (restored after a reconnect).
        self._homed = False
        self._position: int | None = None
        self._lit_known = False
        self._lit: int | None = None
        self.reconnects = 0
        """Number of times the port was reopened after an I/O error."""

    @classmethod
    def open(
        cls,
        port: str,
        baudrate: int = BAUDRATE,
        timeout: float = DEFAULT_TIMEOUT,
        *,
        motion_timeout: float | None = DEFAULT_MOTION_TIMEOUT,
        sequence: bool | None = None,
        retries: int = DEFAULT_RETRIES,
        reconnect_attempts: int = DEFAULT_RECONNECT_ATTEMPTS,
        reconnect_delay: float = DEFAULT_RECONNECT_DELAY,
    ) -> Self:
        """Open ``port`` (device path or pyserial URL such as ``loop://``), 8N1.

        Nothing is sent: :meth:`connect` also checks that a controller answers.

        Raises:
            RigError: if the port cannot be opened.
        """

        def reopen() -> SerialLike:
            return _open_serial(port, baudrate, timeout)

        return cls(
            reopen(),
            name=port,
            motion_timeout=motion_timeout,
            sequence=sequence,
            retries=retries,
            reopen=reopen,
            reconnect_attempts=reconnect_attempts,
            reconnect_delay=reconnect_delay,
        )

    @classmethod
    def connect(
        cls,
        port: str,
        baudrate: int = BAUDRATE,
        timeout: float = DEFAULT_TIMEOUT,
        *,
        motion_timeout: float | None = DEFAULT_MOTION_TIMEOUT,
        retries: int = DEFAULT_RETRIES,
        reconnect_attempts: int = DEFAULT_RECONNECT_ATTEMPTS,
        reconnect_delay: float = DEFAULT_RECONNECT_DELAY,
    ) -> Self:
        """Open ``port`` and identify the controller there (``ID?``).

        The identification is sent once, after a lone ``\\n`` that drops any
        partial line; only a garbled reply is retried, so an absent or silent
        controller is reported after about ``timeout`` seconds rather than
        after all retries. A version 2 controller is then driven with
        sequence numbers, retries and reconnection (see the class). The
        identity is in :attr:`info`.

        Raises:
            RigError: naming the port, if it cannot be opened or nothing
                there answers ``ID?`` like a rig controller within ``timeout``
                (:class:`~facetsynth.rig.protocol.RigTimeoutError` for
                silence).
        """
        rig = cls.open(
            port,
            baudrate,
            timeout,
            motion_timeout=motion_timeout,
            retries=retries,
            reconnect_attempts=reconnect_attempts,
            reconnect_delay=reconnect_delay,
        )
        try:
            rig._probe()
        except BaseException:
            rig.close()
            raise
        return rig

    # -- commands ------------------------------------------------------------

    info: RigInfo | None = None
    """The identity from the last :meth:`identify` (``None`` before)."""

    def identify(self) -> RigInfo:
        """Firmware version and rig dimensions (``ID?``).

        With ``sequence=None``, a version 2 controller switches the driver to
        sequence numbers from here on.
        """
        command = protocol.cmd_identify()
        with self._lock:
            info = self._parse(protocol.parse_identity, self._command(command), command)
            self._adopt(info)
            return info

    def home(self) -> None:
        """Drive the carriage to the home end stop; position becomes 0 (``HOME``), verified with ``POS?``."""
        with self._lock:
            self._home()

    def move_to(self, steps: int) -> int:
        """Move the carriage to absolute position ``steps``; returns the position reached (verified with ``POS?``).

        Raises:
            PositionError: if ``POS?`` after the move reports another position.
        """
        command = protocol.cmd_move(steps)
        with self._lock:
            position = self._parse(protocol.parse_position, self._command(command, motion=True), command)
            self._expect(position == steps, command, f"reached position {position}, expected {steps}")
            self._verify_position(steps, command)
            return position

    def position(self) -> int:
        """Carriage position in steps from the home end stop (``POS?``)."""
        command = protocol.cmd_position()
        with self._lock:
            return self._parse(protocol.parse_position, self._command(command), command)

    def led_on(self, index: int) -> None:
        """Light exactly LED ``index`` (0-based); all others go off."""
        command = protocol.cmd_led(index)
        with self._lock:
            lit = self._parse(protocol.parse_led, self._command(command), command)
            self._expect(lit == index, command, f"controller reports LED {lit}, expected {index}")
            self._lit_known, self._lit = True, index

    def leds_off(self) -> None:
        """Switch all LEDs off."""
        command = protocol.cmd_leds_off()
        with self._lock:
            lit = self._parse(protocol.parse_led, self._command(command), command)
            self._expect(lit is None, command, f"controller reports LED {lit} lit, expected all off")
            self._lit_known, self._lit = True, None

    def lit_led(self) -> int | None:
        """Index of the lit LED, or ``None`` if all are off (``LED?``)."""
        command = protocol.cmd_lit_led()
        with self._lock:
            return self._parse(protocol.parse_led, self._command(command), command)

    def stop(self) -> None:
        """Emergency stop (``STOP``, v2): LEDs off, motor released, controller not homed.

        Call :meth:`home` before the next move. Sent between commands (the
        driver's motions block while they run, holding the lock).
        """
        command = protocol.cmd_stop()
        with self._lock:
            reply = self._command(command)
            self._expect(reply.words == ("STOP",), command, f"reply {reply.raw!r}, expected 'OK STOP'")
            self._homed, self._position = False, None
            self._lit_known, self._lit = True, None

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

    def _adopt(self, info: RigInfo) -> None:
        """Note the identity; switch to sequence numbers for a v2 controller (``sequence=None``)."""
        self.info = info
        if self.sequence is None and info.protocol >= 2:
            self.sequence = True
            log.debug("%s: protocol %d controller, using sequence numbers", self.port_name, info.protocol)

    def _probe(self) -> None:
        """``ID?`` once after a lone newline (see :meth:`connect`); garbled replies are retried."""
        command = protocol.cmd_identify()
        with self._lock:
            ser = self._port(command)
            try:
                ser.write(b"\n")
            except _IO_ERRORS as exc:
                raise self._io_error(command, exc) from exc
            for attempt in range(self.retries + 1):
                try:
                    reply = self._exchange(command)
                    info = self._parse(protocol.parse_identity, reply, command)
                except RigTimeoutError as exc:
                    raise RigTimeoutError(
                        f"no rig controller answers on {self.port_name}: {exc} (connected and powered?)",
                        raw=exc.raw,
                        command=command,
                        port=self.port_name,
                    ) from exc
                except ProtocolError:
                    if attempt == self.retries:
                        raise
                    log.warning("%s: garbled reply to %r, retrying", self.port_name, command)
                    continue
                self._adopt(info)
                return

    def _io_error(self, command: str, exc: BaseException) -> RigError:
        """The error for an I/O failure of the port during ``command``."""
        return RigError(f"I/O error on rig controller port {self.port_name} during {command!r}: {exc}",
                        command=command, port=self.port_name)

    def _error(self, reply: ErrReply, command: str) -> RigError:
        """The error for an ``ERR`` reply; its ``raw`` is the reply without the sequence prefix."""
        body = protocol.split_sequence(reply.raw)[1].lstrip(" ") if reply.seq is not None else reply.raw
        return dataclasses.replace(reply, raw=body).to_error(command=command, port=self.port_name)

    def _port(self, command: str) -> SerialLike:
        """The open port, or :class:`RigError` if the driver was closed."""
        ser = self._serial
        if ser is None:
            raise RigError(f"rig controller on {self.port_name} is closed", command=command, port=self.port_name)
        return ser

    def _take_seq(self) -> int:
        """The next sequence number (0..9999, cycling)."""
        seq = self._next_seq
        self._next_seq = (seq + 1) % (MAX_SEQUENCE + 1)
        return seq

    def _command(self, command: str, *, motion: bool = False, reconnect: bool = True) -> OkReply:
        """Execute ``command``; its ``OK`` reply, or the error for an ``ERR`` reply.

        Protocol v1 (no sequence numbers): one unprefixed exchange. Protocol
        v2: numbered, with retries and reconnection (see the class;
        ``reconnect=False`` during a restore: :meth:`_transact`).
        """
        if not self.sequence:
            return self._exchange(command, motion=motion)
        reply = self._transact(command, motion=motion, reconnect=reconnect)
        if isinstance(reply, ErrReply):
            raise self._error(reply, command)
        return reply

    def _transact(self, command: str, *, motion: bool = False, reconnect: bool = True) -> OkReply | ErrReply:
        """The reply (``OK`` or ``ERR``) echoing the number ``command`` was sent under, with retries.

        With ``reconnect=False`` (during a restore) an I/O error propagates
        as :class:`_Disconnected`.
        """
        if not self._synced:
            self._synced = True  # before the exchange: it must not recurse
            seq = self._take_seq()
            try:
                self._retrying(seq, protocol.cmd_identify(), motion=False, reconnect=reconnect)
            except BaseException:
                self._synced = False
                raise
            log.debug("%s: sequence numbers in step (@%d)", self.port_name, seq)
        return self._retrying(self._take_seq(), command, motion=motion, reconnect=reconnect)

    def _retrying(self, seq: int, command: str, *, motion: bool, reconnect: bool) -> OkReply | ErrReply:
        """Send ``@seq command`` until its reply arrives, at most ``1 + retries`` times."""
        attempt = 0
        lost: RigError | None = None  # set after an I/O error: reconnect before the next attempt
        while True:
            try:
                if lost is not None:
                    self._reconnect(command, lost)
                    lost = None
                    seq = self._take_seq()  # the restore used numbers in between: the old one would not replay
                return self._attempt(seq, command, motion=motion, attempt=attempt)
            except _Retry as failure:
                error = failure.error
            except _Disconnected as failure:
                if not reconnect:
                    raise
                if self._reopen is None:
                    raise failure.error from failure
                error = lost = failure.error
            attempt += 1
            if attempt > self.retries:
                raise error
            log.warning("%s: %s; retry %d of %d", self.port_name, error, attempt, self.retries)

    def _attempt(self, seq: int | None, command: str, *, motion: bool, attempt: int) -> OkReply | ErrReply:
        """Send ``@seq command`` once; the reply echoing ``seq``. ``seq`` None (protocol v1): ``command``
        unprefixed, and the first reply line is its answer.

        Raises:
            _Retry: on a timeout, a garbled reply, or an unnumbered ``ERR``
                (the controller could not read the line).
            _Disconnected: on an I/O error of the port.
        """
        line = command if seq is None else protocol.with_sequence(seq, command)
        data = protocol.encode_line(line)
        ser = self._port(command)
        tries = "" if seq is None else f" (attempt {attempt + 1} of {self.retries + 1})"
        base_timeout = getattr(ser, "timeout", None)
        limit = base_timeout
        if motion and self.motion_timeout is not None and hasattr(ser, "timeout"):
            limit = max(self.motion_timeout, base_timeout or 0.0)
        start = time.monotonic()
        raw = b""
        try:
            reset = getattr(ser, "reset_input_buffer", None)
            if reset is not None:
                reset()  # drop stale bytes, e.g. a reply that came after a timeout
            ser.write(data)
            flush = getattr(ser, "flush", None)
            if flush is not None:
                flush()
            while True:
                if limit is not None and hasattr(ser, "timeout"):
                    remaining = limit - (time.monotonic() - start)
                    if remaining <= 0:
                        raw = b""
                        break
                    ser.timeout = remaining  # type: ignore[attr-defined]
                raw = ser.readline()
                log.debug("%s > %r < %r (%.1f ms)", self.port_name, line, raw, 1e3 * (time.monotonic() - start))
                if not raw.endswith(b"\n"):
                    break  # timeout
                try:
                    reply = protocol.parse_reply(raw.decode("ascii"))
                except (UnicodeDecodeError, ProtocolError) as exc:
                    raise _Retry(
                        ProtocolError(
                            f"garbled reply from rig controller on {self.port_name} to {line!r}{tries}: {raw!r}",
                            raw=raw.decode("ascii", "replace"),
                            command=command,
                            port=self.port_name,
                        )
                    ) from exc
                if reply.seq == seq:
                    return reply
                if seq is None:  # a v1 exchange sends no number, so expects none back
                    raise _Retry(
                        ProtocolError(
                            f"rig controller on {self.port_name} answered {command!r} with a sequence prefix: {raw!r}",
                            raw=reply.raw,
                            command=command,
                            port=self.port_name,
                        )
                    )
                if reply.seq is None and isinstance(reply, ErrReply):
                    # ERR 2 BAD SEQUENCE NUMBER / LINE TOO LONG, ERR 1 for a mangled '@': nothing was executed.
                    raise _Retry(
                        ProtocolError(
                            f"rig controller on {self.port_name} could not read {line!r}{tries}: {reply.raw!r}",
                            raw=reply.raw,
                            command=command,
                            port=self.port_name,
                        )
                    )
                log.debug("%s: discarding stale reply %r while waiting for @%d", self.port_name, raw, seq)
        except serial.SerialTimeoutException as exc:
            raise _Retry(
                RigTimeoutError(
                    f"timed out writing {line!r} to rig controller on {self.port_name}{tries}",
                    command=command,
                    port=self.port_name,
                )
            ) from exc
        except _IO_ERRORS as exc:
            raise _Disconnected(self._io_error(command, exc)) from exc
        finally:
            if hasattr(ser, "timeout") and self._serial is ser:
                try:
                    ser.timeout = base_timeout  # type: ignore[attr-defined]
                except (*_IO_ERRORS, ValueError):
                    pass
        partial = f" (partial reply {raw!r})" if raw else ""
        within = f" within {limit:g} s" if isinstance(limit, (int, float)) else ""
        raise _Retry(
            RigTimeoutError(
                f"no reply from rig controller on {self.port_name} to {command!r}"
                f"{'' if seq is None else f' (sent as {line!r})'}{within}"
                f"{tries}{partial}",
                raw=raw.decode("ascii", "replace") or None,
                command=command,
                port=self.port_name,
            )
        )

    def _reconnect(self, command: str, cause: RigError) -> None:
        """Close the failed port, reopen the same path, restore the controller's state."""
        assert self._reopen is not None
        log.warning("%s: %s; reconnecting", self.port_name, cause)
        old, self._serial = self._serial, None
        if old is not None:
            try:
                old.close()
            except _IO_ERRORS:
                pass
        last: BaseException | None = None
        for _ in range(self.reconnect_attempts):
            time.sleep(self.reconnect_delay)
            try:
                self._serial = self._reopen()
                break
            except (RigError, *_IO_ERRORS, ValueError) as exc:
                last = exc
        else:
            raise RigError(
                f"lost the rig controller on {self.port_name} during {command!r} ({cause}) and could not "
                f"reopen the port in {self.reconnect_attempts} attempts: {last}",
                command=command,
                port=self.port_name,
            ) from last
        self.reconnects += 1
        self._restore(command)  # an I/O error here (_Disconnected) makes the caller reconnect again

    def _restore(self, command: str) -> None:
        """After a reopen: bring a possibly reset controller back to what the driver had established."""
        ser = self._port(command)
        try:
            ser.write(b"\n")  # drop a partial line the controller may hold
        except _IO_ERRORS as exc:
            raise _Disconnected(RigError(f"I/O error on {self.port_name} after reconnecting: {exc}")) from exc
        verb = command.split(" ", 1)[0]
        ident = protocol.cmd_identify()
        info = self._parse(protocol.parse_identity, self._restore_ok(ident, command), ident)
        self.info = info
        if self._homed and verb not in ("HOME", "STOP"):
            reply = self._transact(protocol.cmd_position(), reconnect=False)
            if isinstance(reply, ErrReply) and reply.code == ErrorCode.NOT_HOMED:
                log.warning("%s: controller was reset; homing again before %r", self.port_name, command)
                target = self._position
                self._home(reconnect=False)
                if verb != "MOVE" and target:
                    move = protocol.cmd_move(target)
                    self._restore_ok(move, command, motion=True)
                    self._verify_position(target, move, reconnect=False)
            elif isinstance(reply, ErrReply):
                raise self._error(reply, protocol.cmd_position())
        if self._lit_known and verb not in ("LED", "STOP"):
            lit = protocol.parse_led(self._restore_ok(protocol.cmd_lit_led(), command))
            if lit != self._lit:
                log.warning("%s: LEDs were reset; setting them again before %r", self.port_name, command)
                fix = protocol.cmd_leds_off() if self._lit is None else protocol.cmd_led(self._lit)
                self._restore_ok(fix, command)

    def _restore_ok(self, step: str, command: str, *, motion: bool = False) -> OkReply:
        """One exchange of a restore: its ``OK`` reply, else an error naming both commands."""
        reply = self._transact(step, motion=motion, reconnect=False)
        if isinstance(reply, ErrReply):
            error = self._error(reply, step)
            raise RigError(
                f"could not restore the rig controller on {self.port_name} after reconnecting during "
                f"{command!r}: {error}",
                code=reply.code,
                raw=reply.raw,
                command=step,
                port=self.port_name,
            )
        return reply

    def _home(self, *, reconnect: bool = True) -> None:
        """``HOME`` then ``POS?``; the driver notes the controller homed at 0 (lock held)."""
        command = protocol.cmd_home()
        reply = self._command(command, motion=True, reconnect=reconnect)
        position = self._parse(protocol.parse_position, reply, command)
        self._expect(position == 0, command, f"home position {position}, expected 0")
        self._homed, self._position = True, 0
        self._verify_position(0, command, reconnect=reconnect)

    def _verify_position(self, expected: int, command: str, *, reconnect: bool = True) -> None:
        """Ask ``POS?`` after ``command``; :class:`PositionError` unless it reports ``expected``."""
        query = protocol.cmd_position()
        reply = self._command(query, reconnect=reconnect)
        actual = self._parse(protocol.parse_position, reply, query)
        if actual != expected:
            self._position = None
            raise PositionError(
                f"rig controller on {self.port_name} reports position {actual} after {command!r}, expected {expected}",
                raw=reply.raw,
                command=command,
                port=self.port_name,
            )
        self._position = expected

    def _exchange(self, command: str, *, motion: bool = False) -> OkReply:
        """Protocol v1: send ``command`` once, unprefixed; its ``OK`` reply, or the error for ``ERR``."""
        with self._lock:
            try:
                reply = self._attempt(None, command, motion=motion, attempt=0)
            except (_Retry, _Disconnected) as failure:
                raise failure.error from failure.__cause__
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


def _open_serial(port: str, baudrate: int, timeout: float) -> serial.SerialBase:
    """Open ``port`` 8N1 without flow control; :class:`RigError` naming the port if that fails."""
    try:
        return serial.serial_for_url(
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
