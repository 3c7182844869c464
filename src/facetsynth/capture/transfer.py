"""Declared transfer functions of 8-bit exposures: how a code maps to a linear value.

A capture manifest may declare the ``transfer`` of its 8-bit exposures (JPEG, PNG, TIFF) instead of
leaving the hdr stage to recover the camera response from brackets (:mod:`facetsynth.capture.response`); one
exposure per frame is then enough (a light dome's one sRGB JPEG per light). With ``V = code / 255``:

- ``"srgb"``: the sRGB electro-optical transfer function of IEC 61966-2-1:1999 (sec. 5.2, eq. 5-6):
  ``L = V / 12.92`` for ``V <= 0.04045``, ``L = ((V + 0.055) / 1.055) ** 2.4`` above;
- ``"linear"``: ``L = V``;
- ``{"gamma": G}``: ``L = V ** G`` (G > 0).

Every transfer maps code 0 to 0 and code 255 to 1 exactly, and is non-decreasing. The functions here
are pure and vectorised (a 256-entry lookup table per transfer).

``black_level`` (the manifest's, a linear value in [0, 1)): the value black decodes to, subtracted and
the rest rescaled so that code 255 stays 1 (the clipping level, as the recovered response has it):
``L' = max(0, L - b) / (1 - b)``. Codes decoding at or below ``b`` are 0, the noise floor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

LEVELS = 256

SRGB_STANDARD = "IEC 61966-2-1:1999"


@dataclass(frozen=True)
class Transfer:
    """A declared transfer function: ``kind`` "srgb", "linear" or "gamma" (with ``gamma``)."""

    kind: str
    gamma: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("srgb", "linear", "gamma"):
            raise ValueError(f"unknown transfer {self.kind!r}: expected \"srgb\", \"linear\" or {{\"gamma\": G}}")
        if self.kind == "gamma":
            if not (isinstance(self.gamma, (int, float)) and not isinstance(self.gamma, bool)
                    and np.isfinite(self.gamma) and self.gamma > 0):
                raise ValueError(f"transfer gamma must be a finite number > 0, not {self.gamma!r}")
        elif self.gamma is not None:
            raise ValueError(f"transfer {self.kind!r} takes no gamma")

    def describe(self) -> str:
        """One line for logs and metrics."""
        if self.kind == "srgb":
            return f"sRGB ({SRGB_STANDARD})"
        if self.kind == "linear":
            return "linear (code / 255)"
        return f"gamma {self.gamma:g} ((code / 255) ^ {self.gamma:g})"

    def to_json(self) -> str | dict:
        """The manifest value this transfer was parsed from (:func:`parse` of it gives it back)."""
        return {"gamma": self.gamma} if self.kind == "gamma" else self.kind

    def linear(self, v: np.ndarray) -> np.ndarray:
        """The linear value of ``v`` = code / 255, any real in [0, 1] (a per-pixel fit's prediction of a code,
        not only the 256 codes): the module docstring's functions."""
        v = np.asarray(v, dtype=np.float64)
        if self.kind == "srgb":
            return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
        if self.kind == "linear":
            return v
        return v ** float(self.gamma)


def parse(value: Any) -> Transfer:
    """The Transfer of a manifest's ``transfer`` value: "srgb", "linear" or {"gamma": G}; ValueError otherwise."""
    if isinstance(value, Transfer):
        return value
    if isinstance(value, str):
        if value in ("srgb", "linear"):
            return Transfer(value)
        raise ValueError(f"unknown transfer {value!r}: expected \"srgb\", \"linear\" or {{\"gamma\": G}}")
    if isinstance(value, dict) and set(value) == {"gamma"}:
        return Transfer("gamma", value["gamma"])
    raise ValueError(f"transfer {value!r:.60}: expected \"srgb\", \"linear\" or {{\"gamma\": G}}")


def table(transfer: Transfer | Any, black_level: float = 0.0) -> np.ndarray:
    """The linear value (float64) of each code 0..255, the black level subtracted (module docstring):
    ``max(0, L - b) / (1 - b)``: non-decreasing, 0 at code 0, 1 at code 255."""
    return linearise(np.arange(LEVELS, dtype=np.float64) / (LEVELS - 1), transfer, black_level)


def linearise(v: np.ndarray, transfer: Transfer | Any, black_level: float = 0.0) -> np.ndarray:
    """:func:`table` at any ``v`` = code / 255, clipped to [0, 1]: the linear value of a prediction made in
    code values (an RTI tool's per-pixel fit, :mod:`facetsynth.rti.fits`)."""
    b = float(black_level)
    if not 0.0 <= b < 1.0:
        raise ValueError(f"black level {black_level!r} is not in [0, 1)")
    lin = parse(transfer).linear(np.clip(v, 0.0, 1.0))
    return lin if b == 0.0 else np.maximum(lin - b, 0.0) / (1.0 - b)


def decode(codes: np.ndarray, transfer: Transfer | Any, black_level: float = 0.0) -> np.ndarray:
    """Linear values (float64, in [0, 1]) of 8-bit ``codes`` (any shape, uint8 or integers 0..255) under
    ``transfer`` (a Transfer or a manifest value), less ``black_level`` (module docstring)."""
    codes = np.asarray(codes)
    if codes.dtype != np.uint8:
        if not np.issubdtype(codes.dtype, np.integer):
            raise ValueError(f"8-bit codes must be integers, not {codes.dtype}")
        if codes.size and (codes.min() < 0 or codes.max() > LEVELS - 1):
            raise ValueError(f"8-bit codes must be in 0..255, found {codes.min()}..{codes.max()}")
    return table(transfer, black_level)[codes.astype(np.intp, copy=False)]
