"""The pixel model of DESIGN.md sec. 4: paper 002 eq. 8 read forwards.

A point x of the sample plane lit by a point light at P with intensity L and
seen from a camera at C has radiance

    I = rho(x, i, o) (n . i) L / |P - x|^2,   i = (P - x)/|P - x|,  o = (C - x)/|C - x|

and an exposure of time t records min(saturation, t I) plus sensor noise.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

BRDF = Callable[[np.ndarray, np.ndarray], np.ndarray]


def unit(v: np.ndarray) -> np.ndarray:
    """Normalise vectors along the last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def light_geometry(points: np.ndarray, light_position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Light directions i (..., 3) and squared distances |P - x|^2 (...) (eq. 8)."""
    d = np.asarray(light_position, float) - points
    r2 = np.sum(d * d, axis=-1)
    return d / np.sqrt(r2)[..., None], r2


def radiance(points: np.ndarray, brdf: BRDF, light_position: np.ndarray, light_intensity: np.ndarray,
             camera_centre: np.ndarray) -> np.ndarray:
    """Radiance I (..., 3) leaving sample points (..., 3) toward the camera (eq. 8 forwards).

    ``brdf(wi, wo)`` returns rho (..., 3) in 1/sr for the same points.
    """
    wi, r2 = light_geometry(points, light_position)
    wo = unit(np.asarray(camera_centre, float) - points)
    cos_i = np.clip(wi[..., 2], 0.0, None)
    return brdf(wi, wo) * (cos_i / r2)[..., None] * np.asarray(light_intensity, float)


def expose(radiance_image: np.ndarray, time: float, saturation: float | None = None,
           read_sigma: float = 0.0, shot_gain: float = 0.0,
           rng: np.random.Generator | None = None) -> np.ndarray:
    """One exposure: t I plus shot and read noise, clipped to [0, saturation].

    Noise model: var = read_sigma^2 + shot_gain * t I (Gaussian approximation).
    """
    value = time * radiance_image
    if rng is not None and (read_sigma > 0 or shot_gain > 0):
        sigma = np.sqrt(read_sigma**2 + shot_gain * np.clip(value, 0, None))
        value = value + sigma * rng.standard_normal(value.shape, dtype=np.result_type(value.dtype, np.float32))
    return np.clip(value, 0.0, saturation)
