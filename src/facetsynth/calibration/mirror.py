"""LED positions from their highlights in a flat mirror at known heights (paper 002 sec. 4 geometry).

A front-surface mirror lies on the sample plane (z = 0) and then on a spacer of known height h (its
surface at z = h, normal +z). With LED ``led`` lit and the carriage at ``steps``, the camera sees the LED's
mirror image: the camera ray through the highlight's centroid hits the mirror at P and, reflected
(d' = d - 2 (d.n) n), passes through the LED. Rays from two mirror heights, or from several carriage
positions, meet at the LED: with the LED at home[led] + steps * step (a straight carriage), every ray
gives two linear equations (I - d d^T)(home[led] + steps * step - P) = 0, and all of them are solved
together in least squares for every LED's home and the one shared step vector.

Why a flat mirror and not a mirror sphere: at the rig's scale (camera 1 m away, a few arc-minutes per
pixel) a flat mirror images the LED at the camera's full angular resolution (a pixel is about 0.05 mm at
the LED), where a sphere of 1-2 cm demagnifies the whole hemisphere into a few dozen pixels (a pixel is
several millimetres at the LED). The flat mirror only shows the LEDs whose mirror direction over the
sample reaches the camera; those are the lights that make the sample's highlights, where geometry errors
matter most. LEDs it never shows keep the straight-array line fit through the others (``extrapolated``).

The camera is the calibrated one (:mod:`.checkerboard`), distortion included (rays from undistorted
points).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from ..geometry.camera import Camera


@dataclass(frozen=True)
class Highlight:
    """A highlight's intensity-weighted centroid (col, row) in pixels, its peak value and pixel count."""

    centre: np.ndarray
    peak: float
    pixels: int


def find_highlight(image: np.ndarray, floor: float, threshold: float = 0.1, border: int = 2) -> Highlight | None:
    """The brightest blob of a (H, W[, 3]) linear image: its centroid over the connected pixels above
    ``threshold`` * peak (weights: value minus that level). None when the peak is below ``floor`` (the LED's
    image is not in view) or the blob reaches within ``border`` pixels of the image edge (cut off: a biased
    centroid)."""
    grey = image.mean(axis=-1) if image.ndim == 3 else image
    peak = float(grey.max())
    if peak < floor:
        return None
    level = threshold * peak
    labels, _ = ndimage.label(grey > level)
    row, col = np.unravel_index(int(np.argmax(grey)), grey.shape)
    blob = labels == labels[row, col]
    rows, cols = np.nonzero(blob)
    h, w = grey.shape
    if rows.min() < border or cols.min() < border or rows.max() >= h - border or cols.max() >= w - border:
        return None
    weight = grey[rows, cols] - level
    centre = np.array([np.sum(cols * weight), np.sum(rows * weight)]) / weight.sum()
    return Highlight(centre=centre, peak=peak, pixels=int(blob.sum()))


def pixel_rays(camera: Camera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays (origin = the camera centre (3,), unit directions (N, 3)) through pixels (N, 2) (col, row),
    undistorted with the camera's lens model."""
    pts = cv2.undistortPoints(np.asarray(pixels, np.float64).reshape(-1, 1, 2), camera.K,
                              np.asarray(camera.distortion, float)).reshape(-1, 2)
    d = np.concatenate([pts, np.ones((len(pts), 1))], axis=-1) @ camera.R
    return camera.centre, d / np.linalg.norm(d, axis=-1, keepdims=True)


def reflected_rays(camera: Camera, pixels: np.ndarray, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets a horizontal mirror at z = height (N, 3), and its reflected unit
    direction (N, 3): the line the LED lies on."""
    centre, d = pixel_rays(camera, pixels)
    s = (np.asarray(heights, float) - centre[2]) / d[:, 2]
    hit = centre + s[:, None] * d
    return hit, d * np.array([1.0, 1.0, -1.0])


@dataclass(frozen=True)
class LedFit:
    """LED positions fitted from rays: home (count, 3), step (3,), per-ray distances (m), which LEDs were
    seen (and fitted) and which were extrapolated along the array."""

    home: np.ndarray
    step: np.ndarray
    ray_distance: np.ndarray
    seen: np.ndarray
    extrapolated: list[int]


def fit_leds(count: int, leds: np.ndarray, steps: np.ndarray, origins: np.ndarray, directions: np.ndarray,
             min_angle_deg: float = 0.5, prior_home: np.ndarray | None = None) -> LedFit:
    """Least-squares LED homes and the shared carriage step from rays (origins, unit directions (N, 3)) that
    pass through LED ``leds[k]`` at carriage ``steps[k]``.

    Each ray adds (I - d d^T)(home + steps step) = (I - d d^T) P. An LED is fitted when its rays are not all
    parallel (spread above ``min_angle_deg``); the others get the straight line a + led b fitted through the
    fitted homes (the array is straight and evenly pitched), or, given ``prior_home`` (count, 3) (the rig
    description's), their prior position moved as the fitted LEDs moved on average from theirs (a rigid
    shift of the array: extrapolating a line far beyond the LEDs it was fitted to multiplies its slope's error).
    """
    leds = np.asarray(leds, int)
    steps = np.asarray(steps, float)
    seen = np.zeros(count, bool)
    for led in np.unique(leds):
        d = directions[leds == led]
        spread = np.degrees(np.arccos(np.clip(np.abs(d @ d.T), -1.0, 1.0))).max() if len(d) > 1 else 0.0
        seen[led] = spread > min_angle_deg
    index = -np.ones(count, int)
    index[seen] = np.arange(seen.sum())
    use = seen[leds]
    n_unknown = 3 * seen.sum() + 3
    scale = max(float(np.abs(steps).max()), 1.0)     # steps in units of the largest: a well-scaled system
    rows_a, rows_b = [], []
    for led, s, p, d in zip(leds[use], steps[use], origins[use], directions[use]):
        proj = np.eye(3) - np.outer(d, d)
        a = np.zeros((3, n_unknown))
        a[:, 3 * index[led]:3 * index[led] + 3] = proj
        a[:, -3:] = proj * (s / scale)
        rows_a.append(a)
        rows_b.append(proj @ p)
    solution, *_ = np.linalg.lstsq(np.concatenate(rows_a), np.concatenate(rows_b), rcond=None)
    step = solution[-3:] / scale
    home = np.full((count, 3), np.nan)
    home[seen] = solution[:-3].reshape(-1, 3)
    extrapolated = [int(i) for i in np.flatnonzero(~seen)]
    if extrapolated and prior_home is not None:
        prior_home = np.asarray(prior_home, float)
        home[~seen] = prior_home[~seen] + np.mean(home[seen] - prior_home[seen], axis=0)
    elif extrapolated:
        fitted = np.flatnonzero(seen)
        design = np.stack([np.ones(len(fitted)), fitted], axis=-1)
        line, *_ = np.linalg.lstsq(design, home[fitted], rcond=None)
        home[~seen] = np.stack([np.ones(len(extrapolated)), extrapolated], axis=-1) @ line
    position = home[leds[use]] + steps[use, None] * step
    offset = position - origins[use]
    dist = np.linalg.norm(offset - np.sum(offset * directions[use], axis=-1, keepdims=True) * directions[use],
                          axis=-1)
    return LedFit(home=home, step=step, ray_distance=dist, seen=seen, extrapolated=extrapolated)
