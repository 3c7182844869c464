"""Pure editing functions on a fitted StencilModel (paper 000, sec. 5.1, Fig. 16).

Each returns a new model; the input is never modified.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["shift_phi_a", "set_width", "swap_mode_colours", "set_mode_colour"]


def _check(model, i):
    if not 0 <= i < len(model.modes):
        raise IndexError(f"mode {i} out of range (model has {len(model.modes)} modes)")


def _with_mode(model, i, **changes):
    modes = list(model.modes)
    modes[i] = replace(modes[i], **changes)
    return replace(model, modes=tuple(modes))


def shift_phi_a(model, mode, delta):
    """Rotate the anisotropy axis of ``mode`` by ``delta`` radians (Fig. 16 a, b); kept in [0, pi)."""
    _check(model, mode)
    return _with_mode(model, mode, phi_a=float((model.modes[mode].phi_a + delta) % np.pi))


def set_width(model, mode, w):
    """Set the support width w of ``mode`` (Fig. 16 c); larger w narrows the highlight support."""
    _check(model, mode)
    if not 0.0 < w < 1.0:
        raise ValueError(f"w must be in (0, 1), got {w}")
    return _with_mode(model, mode, w=float(w))


def swap_mode_colours(model, i, j, channels=(0, 1, 2)):
    """Swap the colour parameters m of modes i and j in the given channels (Fig. 16 d)."""
    _check(model, i)
    _check(model, j)
    mi, mj = list(model.modes[i].m), list(model.modes[j].m)
    for c in channels:
        mi[c], mj[c] = mj[c], mi[c]
    return _with_mode(_with_mode(model, i, m=tuple(mi)), j, m=tuple(mj))


def set_mode_colour(model, mode, m):
    """Replace m of ``mode`` (the Fig. 13 colour edit)."""
    _check(model, mode)
    m = tuple(float(v) for v in m)
    if len(m) != 3 or min(m) < 0:
        raise ValueError("m must be three non-negative values")
    return _with_mode(model, mode, m=m)
