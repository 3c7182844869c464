"""Half floats: the dtype of the per-point tensors between stages (docs/decisions.md, "Disk at the paper's
scale"), and the cast to them.

numpy's clip and cast to float16 take 5-6 ns a value here (the cast is done one value at a time in software);
resample and partial_ndf cast every tile they write. :func:`as_half` makes the same bits (IEEE round to nearest,
ties to even, straight from the double: no double rounding through float32) in one compiled pass, saturated as
numpy's clip would, at 2.5 ns a value (docs/decisions.md, "Half floats cast in one compiled pass").
"""

from __future__ import annotations

import numba
import numpy as np

HALF = np.float16
LARGEST = float(np.finfo(HALF).max)           # 65504
# the float64 value of every half float's bits (uint16): compiled kernels read half floats through it (numba has
# no float16), exactly numpy's cast
HALF_VALUES = np.arange(1 << 16, dtype=np.uint16).view(HALF).astype(np.float64)
HALF_VALUES.flags.writeable = False


def as_half(values: np.ndarray) -> np.ndarray:
    """``values`` as half floats, saturated at the largest finite half (+-65504) rather than overflowing to
    Inf: relative rounding 2^-11, far below a capture's noise; BRDF values stay below the limit, a
    mirror-like peak is saturated, never infinite. NaN stays NaN. Bitwise numpy's
    ``np.clip(values, -65504, 65504).astype(np.float16)``."""
    v = np.ascontiguousarray(values, dtype=np.float64)
    out = np.empty(v.shape, np.uint16)
    flat = v.reshape(-1)
    _half_bits(flat, flat.view(np.uint64), out.reshape(-1))
    return out.view(HALF)


@numba.njit(cache=True, nogil=True)
def _half_bits(values: np.ndarray, bits: np.ndarray, out: np.ndarray) -> None:
    """The half-float bits (uint16) of float64 ``values`` (their bits ``bits``, uint64), saturated at +-65504:
    numpy's ``npy_doublebits_to_halfbits`` (numpy/_core/src/npymath/halffloat.cpp) below the overflow it never
    reaches here."""
    for k in range(values.size):
        x = values[k]
        if x > LARGEST:
            out[k] = 0x7BFF
            continue
        if x < -LARGEST:
            out[k] = 0xFBFF
            continue
        b = bits[k]
        sign = np.uint16((b >> np.uint64(48)) & np.uint64(0x8000))
        exponent = b & np.uint64(0x7FF0000000000000)
        significand = b & np.uint64(0x000FFFFFFFFFFFFF)
        if exponent == np.uint64(0x7FF0000000000000):              # NaN (Inf is saturated above)
            h = np.uint64(0x7C00) + (significand >> np.uint64(42))
            out[k] = sign + np.uint16(h + np.uint64(1) if h == np.uint64(0x7C00) else h)
        elif exponent <= np.uint64(0x3F00000000000000):            # a half subnormal, or zero
            if exponent < np.uint64(0x3E60000000000000):           # below half the smallest subnormal
                out[k] = sign
                continue
            s = (np.uint64(0x0010000000000000) + significand) << ((exponent >> np.uint64(52)) - np.uint64(998))
            if (s & np.uint64(0x003FFFFFFFFFFFFF)) != np.uint64(0x0010000000000000):   # not a tie to even
                s += np.uint64(0x0010000000000000)
            out[k] = sign + np.uint16(s >> np.uint64(53))
        else:                                                      # a normal half
            h_exponent = (exponent - np.uint64(0x3F00000000000000)) >> np.uint64(42)
            if (significand & np.uint64(0x000007FFFFFFFFFF)) != np.uint64(0x0000020000000000):
                significand += np.uint64(0x0000020000000000)
            out[k] = sign + np.uint16((significand >> np.uint64(42)) + h_exponent)
