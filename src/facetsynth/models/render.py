"""The pixel model of DESIGN.md sec. 4: paper 002 eq. 8 read forwards.

A point x of the sample plane lit by a point light at P with intensity L and
seen from a camera at C has radiance

    I = rho(x, i, o) (n . i) L / |P - x|^2,   i = (P - x)/|P - x|,  o = (C - x)/|C - x|

and an exposure of time t records min(saturation, t I) plus sensor noise.

Lights and cameras are homogeneous points (X, w): a point light or a pinhole
camera is (P, 1); a directional light or an orthographic camera is (d, 0),
d the direction towards it, at infinity (the convention of OpenGL's light
positions). A directional light's L is its irradiance at normal incidence and
|P - x|^2 is replaced by 1: I = rho(x, i, o) (n . i) L, i = d/|d| everywhere.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

BRDF = Callable[[np.ndarray, np.ndarray], np.ndarray]


def unit(v: np.ndarray) -> np.ndarray:
    """Normalise vectors along the last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def homogeneous(point: np.ndarray) -> np.ndarray:
    """(..., 4) homogeneous points: (..., 3) positions get w = 1; (..., 4) are returned as they are."""
    point = np.asarray(point, float)
    if point.shape[-1] == 4:
        return point
    return np.concatenate([point, np.ones(point.shape[:-1] + (1,))], axis=-1)


def light_geometry(points: np.ndarray, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions i (..., 3) from points (..., 3) towards a homogeneous light or camera (..., 4) (or a
    position (..., 3)), and the squared distances |P - x|^2 (...) of eq. 8: 1 for a light at infinity."""
    light = homogeneous(light)
    w = light[..., 3:]
    d = light[..., :3] - w * points
    r2 = np.sum(d * d, axis=-1)
    return d / np.sqrt(r2)[..., None], np.where(w[..., 0] > 0, r2, 1.0)


def towards(points: np.ndarray, view_point: np.ndarray) -> np.ndarray:
    """Unit directions o (..., 3) from points towards a camera, a homogeneous point (4,) (or a centre (3,))."""
    return light_geometry(points, view_point)[0]


def radiance(points: np.ndarray, brdf: BRDF, light: np.ndarray, light_intensity: np.ndarray,
             view_point: np.ndarray) -> np.ndarray:
    """Radiance I (..., 3) leaving sample points (..., 3) toward the camera (eq. 8 forwards), for a homogeneous
    light and camera (:func:`light_geometry`).

    ``brdf(wi, wo)`` returns rho (..., 3) in 1/sr for the same points.
    """
    wi, r2 = light_geometry(points, light)
    wo = towards(points, view_point)
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
