"""The sRGB transfer function (IEC 61966-2-1): glTF's colour textures and the report's pictures.

(``facetsynth render`` encodes through OpenImageIO's colour management instead; the two agree to 8 bits:
tests/app/test_preview_inspect.py.)
"""

from __future__ import annotations

import numpy as np


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (clipped; NaN and Inf read as 0)."""
    x = np.clip(np.nan_to_num(np.asarray(linear, float), nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear [0, 1] (clipped)."""
    y = np.clip(np.asarray(encoded, float), 0.0, 1.0)
    return np.where(y <= 0.04045, y / 12.92, np.power((y + 0.055) / 1.055, 2.4))


def channel_mean(v: np.ndarray) -> np.ndarray:
    """The mean of the three channels of ``v`` (..., 3) (float32 or float64): ``v.mean(axis=-1)`` to the bit
    (numpy adds the three in order and divides by 3), written out: a reduction over an axis of three is numpy's
    slow path, 4 x slower on the per-point tables (P, F, 3)."""
    return (v[..., 0] + v[..., 1] + v[..., 2]) / 3
