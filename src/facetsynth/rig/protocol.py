"""The rig controller's line protocol (see ``rig/PROTOCOL.md``), without I/O.

Pure functions that format commands and parse replies into small
dataclasses, shared by the host driver (:mod:`facetsynth.rig.driver`) and
the virtual controller (:mod:`facetsynth.rig.emulator`).

Command strings returned here carry no line terminator; :func:`encode_line`
adds it. Protocol version 2 adds sequence prefixes (:func:`split_sequence`,
:func:`with_sequence`), ``STOP`` (:func:`cmd_stop`) and error code 5.
"""

from __future__ import annotations

import operator
import re
from dataclasses import dataclass
from enum import IntEnum

__all__ = [
    "BAUDRATE",
    "TERMINATOR",
    "MAX_COMMAND_LENGTH",
    "MAX_REPLY_LENGTH",
    "IDENT_PREFIX",
    "PROTOCOL_VERSION",
    "MAX_SEQUENCE",
    "ErrorCode",
    "RigError",
    "RigTimeoutError",
    "ProtocolError",
    "RigInfo",
    "OkReply",
    "ErrReply",
    "cmd_identify",
    "cmd_home",
    "cmd_move",
    "cmd_position",
    "cmd_led",
    "cmd_leds_off",
    "cmd_lit_led",
    "cmd_stop",
    "encode_line",
    "parse_int",
    "split_words",
    "split_sequence",
    "with_sequence",
    "format_ok",
    "format_err",
    "format_identity",
    "parse_reply",
    "parse_identity",
    "parse_position",
    "parse_led",
]

BAUDRATE = 115200
"""Line speed; framing is 8N1 without flow control."""
TERMINATOR = "\n"
"""Terminates every command and every reply."""
MAX_COMMAND_LENGTH = 64
"""Longest command line in bytes, terminator included."""
MAX_REPLY_LENGTH = 128
"""Longest reply line in bytes, terminator included."""
IDENT_PREFIX = "FACETSYNTH-RIG"
"""First word after ``OK`` in the reply to ``ID?``."""
PROTOCOL_VERSION = 2
"""Protocol version implemented here, reported as ``PROTO=`` by ``ID?`` (absent: version 1)."""
MAX_SEQUENCE = 9999
"""Largest sequence number of an ``@<n>`` prefix (1 to 4 decimal digits)."""

_INT_RE = re.compile(r"-?[0-9]+")
_SEQUENCE_RE = re.compile(r"@([0-9]{1,4})")


class ErrorCode(IntEnum):
    """Codes carried by ``ERR <code> <message>`` replies."""

    UNKNOWN_COMMAND = 1
    BAD_ARGUMENT = 2
    OUT_OF_RANGE = 3
    NOT_HOMED = 4
    STOPPED = 5
    """(v2) A ``HOME``/``MOVE`` aborted by ``STOP`` (firmware only)."""


class RigError(Exception):
    """Anything that went wrong talking to the rig controller.

    Raised as is for an ``ERR`` reply, in which case :attr:`code` holds the
    controller's error code. Subclasses cover timeouts and malformed replies.

    Attributes:
        code: The controller's error code (``None`` unless it sent ``ERR``).
        raw: The raw reply line, if any was received.
        command: The command that was being executed, if known.
        port: The port name, if known.
    """

    def __init__(
        self,
        message: str,
        *,
        code: int | None = None,
        raw: str | None = None,
        command: str | None = None,
        port: str | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.raw = raw
        self.command = command
        self.port = port


class RigTimeoutError(RigError):
    """No complete reply line arrived within the timeout."""


class ProtocolError(RigError):
    """A reply that does not follow the protocol (or does not match the command)."""


@dataclass(frozen=True)
class RigInfo:
    """The controller's identity, as reported by ``ID?``.

    Attributes:
        firmware: Version token (the emulator's ends in ``-virtual``).
        n_leds: LEDs in the array.
        max_steps: Largest valid carriage position in steps.
        steps_per_mm: Motor steps per millimetre of carriage travel.
        protocol: Protocol version (``PROTO=``; 1 for a controller that does
            not report one, which knows neither sequence prefixes nor ``STOP``).
    """

    firmware: str
    n_leds: int
    max_steps: int
    steps_per_mm: float
    protocol: int = 1


@dataclass(frozen=True)
class OkReply:
    """A successful reply: the words after ``OK``.

    ``seq`` is the number of an ``@<n>`` prefix (``None`` without one); ``raw``
    is the whole line, prefix included.
    """

    words: tuple[str, ...]
    raw: str
    seq: int | None = None


@dataclass(frozen=True)
class ErrReply:
    """A failure reply ``ERR <code> <message>`` (``seq``, ``raw``: as for :class:`OkReply`)."""

    code: int
    message: str
    raw: str
    seq: int | None = None

    def to_error(self, command: str | None = None, port: str | None = None) -> RigError:
        """The :class:`RigError` describing this reply."""
        where = f" on {port}" if port else ""
        what = f"{command!r}" if command else "command"
        try:
            name = ErrorCode(self.code).name
        except ValueError:
            name = "UNKNOWN_ERROR"
        return RigError(
            f"rig controller{where} rejected {what}: ERR {self.code} ({name}) {self.message}",
            code=self.code,
            raw=self.raw,
            command=command,
            port=port,
        )


# --- commands ---------------------------------------------------------------


def _require_int(value: int, what: str) -> int:
    """``value`` as a Python int; integer-like types (e.g. numpy ints) accepted."""
    if isinstance(value, bool):
        raise TypeError(f"{what} must be an integer, got bool")
    try:
        return operator.index(value)
    except TypeError:
        raise TypeError(f"{what} must be an integer, got {type(value).__name__}") from None


def cmd_identify() -> str:
    """``ID?``: ask for firmware version and rig dimensions."""
    return "ID?"


def cmd_home() -> str:
    """``HOME``: drive the carriage to the home end stop (position 0)."""
    return "HOME"


def cmd_move(steps: int) -> str:
    """``MOVE <steps>``: absolute carriage move in motor steps."""
    return f"MOVE {_require_int(steps, 'steps')}"


def cmd_position() -> str:
    """``POS?``: ask for the carriage position in steps."""
    return "POS?"


def cmd_led(index: int) -> str:
    """``LED <index>``: light exactly LED ``index`` (0-based)."""
    return f"LED {_require_int(index, 'LED index')}"


def cmd_leds_off() -> str:
    """``LED OFF``: switch all LEDs off."""
    return "LED OFF"


def cmd_lit_led() -> str:
    """``LED?``: ask which LED is lit."""
    return "LED?"


def cmd_stop() -> str:
    """``STOP`` (v2): emergency stop; LEDs off, motor released, not homed."""
    return "STOP"


def encode_line(text: str, limit: int = MAX_COMMAND_LENGTH) -> bytes:
    """A command (or, with ``limit=MAX_REPLY_LENGTH``, a reply) as bytes on
    the wire, terminator appended.

    Raises:
        ValueError: if ``text`` is not ASCII, contains a line break or is
            longer than ``limit`` bytes with its terminator.
    """
    if "\n" in text or "\r" in text:
        raise ValueError(f"line must not contain a line break: {text!r}")
    data = (text + TERMINATOR).encode("ascii")
    if len(data) > limit:
        raise ValueError(f"line too long ({len(data)} bytes): {text!r}")
    return data


def parse_int(token: str) -> int | None:
    """A protocol integer (decimal, optional ``-``), or ``None`` if malformed."""
    return int(token) if _INT_RE.fullmatch(token) else None


def split_words(line: str) -> list[str]:
    """The tokens of a command line: only the space character separates them."""
    return [word for word in line.split(" ") if word]


def split_sequence(line: str) -> tuple[int | None, str]:
    """Split an optional ``@<n>`` sequence prefix (v2) off a line.

    Returns ``(n, rest)`` for a prefixed line (``rest`` may be empty) and
    ``(None, line)`` for a line whose first token does not start with ``@``.

    Raises:
        ValueError: if the first token starts with ``@`` but is not ``@``
            followed by 1 to 4 decimal digits (``@``, ``@x``, ``@10000``).
    """
    stripped = line.lstrip(" ")
    if not stripped.startswith("@"):
        return None, line
    token, _, rest = stripped.partition(" ")
    match = _SEQUENCE_RE.fullmatch(token)
    if match is None:
        raise ValueError(f"malformed sequence prefix {token!r}")
    return int(match.group(1)), rest


def with_sequence(seq: int | None, text: str) -> str:
    """``text`` with the prefix ``@<seq> `` (v2), or unchanged if ``seq`` is ``None``."""
    if seq is None:
        return text
    seq = _require_int(seq, "sequence number")
    if not 0 <= seq <= MAX_SEQUENCE:
        raise ValueError(f"sequence number {seq} outside 0..{MAX_SEQUENCE}")
    return f"@{seq} {text}"


# --- replies: formatting (controller side) -----------------------------------


def format_ok(*words: object) -> str:
    """``OK <words...>`` (no terminator)."""
    return " ".join(["OK", *(str(w) for w in words)])


def format_err(code: ErrorCode | int, message: str) -> str:
    """``ERR <code> <message>`` (no terminator)."""
    return f"ERR {int(code)} {message}"


def format_identity(info: RigInfo) -> str:
    """The reply to ``ID?`` for ``info`` (``PROTO=`` from version 2 on)."""
    if not info.firmware or any(c.isspace() for c in info.firmware):
        raise ValueError(f"firmware version must be one non-empty token: {info.firmware!r}")
    fields = [f"LEDS={info.n_leds}", f"STEPS={info.max_steps}", f"STEPS_PER_MM={info.steps_per_mm:g}"]
    if info.protocol >= 2:
        fields.append(f"PROTO={info.protocol}")
    return format_ok(IDENT_PREFIX, info.firmware, *fields)


# --- replies: parsing (host side) --------------------------------------------


def parse_reply(raw: str) -> OkReply | ErrReply:
    """Classify one reply line (terminator optional) as OK or ERR.

    A sequence prefix ``@<n> `` (v2) is split off into the reply's ``seq``.

    Raises:
        ProtocolError: if the line is neither a well-formed ``OK`` nor ``ERR``
            (with an optional well-formed prefix).
    """
    line = raw.rstrip("\r\n")
    try:
        seq, body = split_sequence(line)
    except ValueError as exc:
        raise ProtocolError(f"malformed sequence prefix in reply: {line!r}", raw=line) from exc
    words = body.split()
    if words and words[0] == "OK":
        return OkReply(words=tuple(words[1:]), raw=line, seq=seq)
    if words and words[0] == "ERR":
        parts = body.split(None, 2)
        code = parse_int(parts[1]) if len(parts) > 1 else None
        if code is None:
            raise ProtocolError(f"malformed ERR reply: {line!r}", raw=line)
        return ErrReply(code=code, message=parts[2] if len(parts) > 2 else "", raw=line, seq=seq)
    raise ProtocolError(f"reply is neither OK nor ERR: {line!r}", raw=line)


def parse_identity(reply: OkReply) -> RigInfo:
    """The :class:`RigInfo` in a reply to ``ID?`` (unknown ``KEY=VALUE`` ignored).

    Raises:
        ProtocolError: if the reply is not a valid identity line.
    """
    words = reply.words
    if len(words) < 2 or words[0] != IDENT_PREFIX:
        raise ProtocolError(f"not a rig identity reply: {reply.raw!r}", raw=reply.raw)
    fields: dict[str, str] = {}
    for word in words[2:]:
        key, sep, value = word.partition("=")
        if not sep:
            raise ProtocolError(f"malformed identity field {word!r}: {reply.raw!r}", raw=reply.raw)
        fields[key] = value
    try:
        n_leds = parse_int(fields["LEDS"])
        max_steps = parse_int(fields["STEPS"])
        steps_per_mm = float(fields["STEPS_PER_MM"])
    except (KeyError, ValueError) as exc:
        raise ProtocolError(f"identity reply lacks a valid field ({exc}): {reply.raw!r}", raw=reply.raw) from exc
    version = parse_int(fields.get("PROTO", "1"))
    if (
        n_leds is None
        or max_steps is None
        or version is None
        or n_leds < 1
        or max_steps < 0
        or not steps_per_mm > 0
        or version < 1
    ):
        raise ProtocolError(f"identity reply has invalid values: {reply.raw!r}", raw=reply.raw)
    return RigInfo(
        firmware=words[1], n_leds=n_leds, max_steps=max_steps, steps_per_mm=steps_per_mm, protocol=version
    )


def parse_position(reply: OkReply) -> int:
    """The carriage position in steps from ``OK POS <steps>``.

    Raises:
        ProtocolError: if the reply is not a position.
    """
    words = reply.words
    steps = parse_int(words[1]) if len(words) == 2 and words[0] == "POS" else None
    if steps is None:
        raise ProtocolError(f"expected 'OK POS <steps>', got {reply.raw!r}", raw=reply.raw)
    return steps


def parse_led(reply: OkReply) -> int | None:
    """The lit LED from ``OK LED <index>`` / ``OK LED OFF`` (``None`` = all off).

    Raises:
        ProtocolError: if the reply is not an LED state.
    """
    words = reply.words
    if len(words) == 2 and words[0] == "LED":
        if words[1] == "OFF":
            return None
        index = parse_int(words[1])
        if index is not None and index >= 0:
            return index
    raise ProtocolError(f"expected 'OK LED <index>|OFF', got {reply.raw!r}", raw=reply.raw)
