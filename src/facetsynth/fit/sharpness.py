"""The sharpness of the measured specular lobes, and the direction grid it calls for (issue 7).

The paper tabulates NDFs on a hemicube whose resolution was chosen per
material (128 x 128 for brushed aluminium, sec. 6). Here the polar direction
grid follows the data: each point's specular samples, brought to the scale of
D by eq. 11 (rho_s 4 (i.n)(o.n), F = 1 and S ~ 1 near the peak), are above
half their maximum on a region of half vectors. In slope space (h_x / h_z,
h_y / h_z, where microfacet distributions are elliptic) half the region's
width along a direction u (max - min of s . u over the samples inside, / 2)
is the ellipse's support function; its minimum and maximum over u are the
narrow and broad half-widths. Widths, not second moments: the lights sample
half vectors with a density that varies across the lobe (dw_h = dw_i /
4 (i.h), and a plane of lights), which biases moments but not widths. The
samples inside lie within the boundary, so the widths are low by up to one
light spacing (in half-vector slope, about half the lights' angular
spacing). For a GGX lobe the half maximum lies at tan(theta_h) ~
sqrt(sqrt(2) - 1) alpha = 0.644 alpha along each axis (exactly as alpha -> 0).

The narrow half-width is what a grid must resolve: the grid gets
``cells_per_lobe`` elevation rings per narrow half-width (median over the
sample's points), rounded to a multiple of 8 and bounded; azimuth sectors are
4 x the rings (square cells at 45 deg).
"""

from __future__ import annotations

import numpy as np

HALF_MAX = 0.5
EXTENT_DIRECTIONS = 36  # directions u (5 deg apart) along which the half-maximum region's extent is measured
RING_STEP = 8           # n_theta is a multiple of this (n_phi = 4 n_theta stays a multiple of 32)


def lobe_widths(h: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Narrow and broad half-widths at half maximum (degrees) of each point's lobe.

    ``h`` (P, N, 3) unit half vectors of the samples, ``value`` (P, N) the
    samples on D's scale (0 where invalid). Returns (narrow (P,), broad (P,),
    samples above half maximum (P,)); a point with fewer than 3 samples above
    half maximum, or no positive sample, gets NaN widths (its lobe is not
    resolved by the lights, or it has no specular part).
    """
    h = np.asarray(h, float)
    value = np.asarray(value, float)
    peak = value.max(axis=1)
    inside = (value >= HALF_MAX * peak[:, None]) & (peak[:, None] > 0) & (h[..., 2] > 1e-3)
    slope = h[..., :2] / np.maximum(h[..., 2:3], 1e-3)                         # (P, N, 2)
    angles = np.linspace(0.0, np.pi, EXTENT_DIRECTIONS, endpoint=False)
    extents = []
    for a in angles:
        along = slope @ [np.cos(a), np.sin(a)]
        hi = np.max(np.where(inside, along, -np.inf), axis=1)
        lo = np.min(np.where(inside, along, np.inf), axis=1)
        extents.append(np.where(np.isfinite(hi - lo), 0.5 * (hi - lo), 0.0))
    extents = np.stack(extents, axis=1)                                         # (P, directions)
    narrow = np.degrees(np.arctan(extents.min(axis=1)))
    broad = np.degrees(np.arctan(extents.max(axis=1)))
    n = inside.sum(axis=1)
    resolved = n >= 3
    return np.where(resolved, narrow, np.nan), np.where(resolved, broad, np.nan), n


def grid_resolution(narrow_deg: float, cells_per_lobe: float, n_theta_range: tuple[int, int]) -> tuple[int, int]:
    """(n_theta, n_phi) with ``cells_per_lobe`` rings per narrow half-width, n_theta a multiple of 8 within
    ``n_theta_range``; a NaN or non-positive width (no resolved lobe: a diffuse sample) takes the lower bound."""
    lo, hi = int(n_theta_range[0]), int(n_theta_range[1])
    if not (np.isfinite(narrow_deg) and narrow_deg > 0):
        n_theta = lo
    else:
        n_theta = RING_STEP * int(round(cells_per_lobe * 90.0 / narrow_deg / RING_STEP))
    n_theta = int(np.clip(n_theta, lo, hi))
    return n_theta, 4 * n_theta
