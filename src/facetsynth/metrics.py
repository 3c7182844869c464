"""Accuracy measures against ground truth (DESIGN.md "Accuracy records")."""

from __future__ import annotations

import numpy as np


def relative_errors(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                    sample: int | None = None) -> np.ndarray:
    """|estimate - truth| / truth over the entries selected by ``mask`` (truth > 0 only).

    ``mask`` broadcasts against the arrays. With ``sample``, at most that many
    entries, evenly strided (deterministic), are returned.
    """
    truth = np.asarray(truth, dtype=np.float64)
    select = truth > 0 if mask is None else np.broadcast_to(mask, truth.shape) & (truth > 0)
    err = np.abs(np.asarray(estimate, dtype=np.float64)[select] - truth[select]) / truth[select]
    if sample is not None and err.size > sample:
        err = err[:: int(np.ceil(err.size / sample))]
    return err


def marker_centroids(image: np.ndarray, expected: np.ndarray, radius: float) -> np.ndarray:
    """Sub-pixel centres (col, row) of dark disc markers near their expected positions.

    ``image`` (rows, cols) is a brightness image; each marker is found in a
    window of 2.5 radii around its expected (col, row) as the centroid of the
    darkness (local background minus value), the background being the median
    of the ring between 1.6 and 2.5 radii. Markers whose window leaves the
    image come back as NaN rows.
    """
    rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    found = np.full((len(expected), 2), np.nan)
    for m, (c0, r0) in enumerate(expected):
        d = np.hypot(cols - c0, rows - r0)
        if c0 - 2.5 * radius < -0.5 or r0 - 2.5 * radius < -0.5 or \
           c0 + 2.5 * radius > image.shape[1] - 0.5 or r0 + 2.5 * radius > image.shape[0] - 0.5:
            continue
        ring = (d >= 1.6 * radius) & (d <= 2.5 * radius)
        background = np.median(image[ring])
        weight = np.where(d <= 1.5 * radius, np.clip(background - image, 0.0, None), 0.0)
        if weight.sum() > 0:
            found[m] = (weight * cols).sum() / weight.sum(), (weight * rows).sum() / weight.sum()
    return found
