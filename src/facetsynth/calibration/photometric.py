"""LED intensities from a diffuse white reference (paper 002 sec. 4, eq. 8 read backwards).

A Lambertian reference of known albedo a lies on the sample plane (z = 0). Lit by a point light of
intensity L at P, a point x of it has radiance (eq. 8 with rho = a / pi)

    I(x) = (a / pi) cos(theta_i) L / |P - x|^2,    cos(theta_i) = (P - x)_z / |P - x|,

in the units of the capture manifest. Each pixel that sees the reference therefore gives
L = I(x) / ((a / pi) cos(theta_i) / |P - x|^2) with x from the calibrated camera (the pixel's ray meets
z = 0) and P the calibrated LED position; the LED's intensity is the median over the pixels (robust to a
speck of dust, a saturated or a dark pixel). Relative to each other these fix the LEDs' differences; the
absolute scale is the reference's albedo's.
"""

from __future__ import annotations

import numpy as np

from ..geometry.camera import Camera


def plane_points(camera: Camera) -> np.ndarray:
    """(H, W, 3) point of the plane z = 0 each pixel centre sees (lens distortion included)."""
    from .mirror import pixel_rays

    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    centre, d = pixel_rays(camera, np.stack([cols.ravel(), rows.ravel()], axis=-1).astype(float))
    s = -centre[2] / d[:, 2]
    return (centre + s[:, None] * d).reshape(camera.height, camera.width, 3)


def shading(points: np.ndarray, light: np.ndarray, albedo: float) -> np.ndarray:
    """(a / pi) cos(theta_i) / r^2 at plane points (..., 3) lit from ``light`` (eq. 8 with L = 1)."""
    d = np.asarray(light, float) - points
    r2 = np.sum(d * d, axis=-1)
    return albedo / np.pi * np.clip(d[..., 2], 0.0, None) / np.sqrt(r2) / r2


def led_intensity(image: np.ndarray, time: float, points: np.ndarray, light: np.ndarray, albedo: float,
                  floor: float, saturation: float | None, mask: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """RGB intensity (3,) of one LED from an exposure (H, W, 3) of ``time`` of the white reference, and the
    number of pixels used: the median of value / (time * shading) over the pixels (within ``mask``) whose
    every channel is above ``floor`` and below ``saturation``."""
    s = shading(points, light, albedo)
    ok = (image.min(axis=-1) > floor) & (s > 0)
    if saturation:
        ok &= image.max(axis=-1) < 0.98 * saturation
    if mask is not None:
        ok &= mask
    if not ok.any():
        return np.full(3, np.nan), 0
    return np.median(image[ok] / (time * s[ok, None]), axis=0), int(ok.sum())
