"""The UTIA BRDF sampling grid and the 288x288 unwrapping of paper 000, Fig. 1.

The UTIA database samples a BRDF at theta = 0, 15, ..., 75 deg (6 elevations)
and phi = 0, 7.5, ..., 352.5 deg (48 azimuths) for both the illumination
(i) and the view (v) direction.  Arrays are ``(3, 6, 48, 6, 48)`` as
``[channel, theta_i, phi_i, theta_v, phi_v]``, linear RGB, 1/sr, no cosine.

The unwrapped image (paper 000, Fig. 1 right) is 288x288x3: row
``48 * theta_i_index + phi_i_index``, column ``48 * theta_v_index +
phi_v_index`` -- illumination elevations stacked vertically, view
elevations side by side horizontally.

Directions: unit 3-vectors, normal +z, azimuth from +x towards +y.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = [
    "N_THETA", "N_PHI", "SHAPE", "THETA", "PHI", "LUMA",
    "sph_to_dir", "utia_directions", "sample_utia", "unwrap", "wrap", "luminance",
]

N_THETA = 6
N_PHI = 48
SHAPE = (3, N_THETA, N_PHI, N_THETA, N_PHI)
THETA = np.deg2rad(15.0 * np.arange(N_THETA))
PHI = np.deg2rad(7.5 * np.arange(N_PHI))
# Rec. 709 / sRGB luminance weights of linear RGB.
LUMA = np.array([0.2126, 0.7152, 0.0722])


def sph_to_dir(theta, phi):
    """Unit direction(s) ``(..., 3)`` from elevation theta and azimuth phi (radians)."""
    theta = np.asarray(theta, float)
    phi = np.asarray(phi, float)
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)), axis=-1)


@lru_cache(maxsize=1)
def utia_directions():
    """``(wi, wo)``, each ``(6, 48, 6, 48, 3)``: the UTIA grid directions (read-only)."""
    ti, pi_, tv, pv = np.meshgrid(THETA, PHI, THETA, PHI, indexing="ij")
    wi = sph_to_dir(ti, pi_)
    wo = sph_to_dir(tv, pv)
    wi.setflags(write=False)
    wo.setflags(write=False)
    return wi, wo


def sample_utia(brdf_eval):
    """Any BRDF on the UTIA grid: ``brdf_eval(wi, wo)`` (N, 3) x (N, 3) -> rho (N, 3) gives ``(3, 6, 48, 6, 48)``.

    How a tabulated or analytic BRDF (a point of a fitted SVBRDF, a microfacet
    model) is brought to the grid on which the stencil model is fitted and scored.
    """
    wi, wo = utia_directions()
    rho = np.asarray(brdf_eval(wi.reshape(-1, 3), wo.reshape(-1, 3)), float)
    if rho.shape != (wi[..., 0].size, 3):
        raise ValueError(f"brdf_eval returned shape {rho.shape}, expected ({wi[..., 0].size}, 3)")
    return np.ascontiguousarray(np.moveaxis(rho.reshape(wi.shape[:-1] + (3,)), -1, 0))


def unwrap(brdf):
    """``(3, 6, 48, 6, 48)`` -> the ``(288, 288, 3)`` image of paper 000, Fig. 1."""
    brdf = np.asarray(brdf)
    if brdf.shape != SHAPE:
        raise ValueError(f"expected a BRDF of shape {SHAPE}, got {brdf.shape}")
    return np.ascontiguousarray(brdf.transpose(1, 2, 3, 4, 0).reshape(288, 288, 3))


def wrap(image):
    """Inverse of :func:`unwrap`: ``(288, 288, 3)`` -> ``(3, 6, 48, 6, 48)``."""
    image = np.asarray(image)
    if image.shape != (288, 288, 3):
        raise ValueError(f"expected a 288x288x3 image, got {image.shape}")
    return np.ascontiguousarray(image.reshape(N_THETA, N_PHI, N_THETA, N_PHI, 3).transpose(4, 0, 1, 2, 3))


def luminance(rgb, axis=0):
    """Rec. 709 luminance of linear RGB along ``axis`` (channel axis)."""
    rgb = np.moveaxis(np.asarray(rgb, float), axis, -1)
    return rgb @ LUMA
