"""BRDF samples and diffuse/specular separation (paper 002 sec. 4, eqs. 8-9)."""

from __future__ import annotations

import numpy as np

from .render import light_geometry


def brdf_samples(radiance: np.ndarray, points: np.ndarray, light_positions: np.ndarray,
                 light_intensities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8: rho(x, i_q(x), o) = I_q(x) / ((n . i_q(x)) L_q |P_q - x|^2).

    ``radiance`` (P, Q, 3) at points (P, 3) under lights (Q, 3) of intensity
    (Q, 3). Each point has its own light direction i_q(x) = (P_q - x)/|P_q - x|.
    Returns (rho (P, Q, 3), light directions (P, Q, 3)). Where n . i <= 0 (a
    light at or below the sample plane) rho is 0.
    """
    wi, r2 = light_geometry(points[:, None, :], light_positions[None, :, :])
    cos_i = wi[..., 2]
    scale = np.divide(r2, cos_i, out=np.zeros_like(r2), where=cos_i > 1e-6)
    irradiance_free = np.divide(radiance, light_intensities[None], out=np.zeros(radiance.shape),
                                where=light_intensities[None] > 0)
    return irradiance_free * scale[..., None], wi


def diffuse_minimum(rho: np.ndarray, radiance: np.ndarray, valid: np.ndarray, threshold: float = 0.05) -> np.ndarray:
    """Eq. 9: rho_d(x) = min_q { rho(x, i_q, o) | I_q(x) > threshold * I_avg(x) }, per channel.

    I is the channel mean of the radiance; I_avg its mean over the valid
    samples of the point. A sample whose rho or radiance is NaN or Inf counts
    as invalid. A point with no qualifying sample (fully dark, or no valid
    sample) gets rho_d = 0. Returns (P, 3); kd = pi rho_d.
    """
    valid = valid & np.isfinite(rho).all(axis=-1) & np.isfinite(radiance).all(axis=-1)
    intensity = radiance.mean(axis=-1)
    n_valid = valid.sum(axis=1)
    average = np.divide(np.where(valid, intensity, 0.0).sum(axis=1), n_valid,
                        out=np.zeros(n_valid.shape), where=n_valid > 0)
    qualifies = valid & (intensity > threshold * average[:, None]) & (average[:, None] > 0)
    minimum = np.where(qualifies[..., None], rho, np.inf).min(axis=1)
    return np.where(np.isfinite(minimum), minimum, 0.0)


def specular_residual(rho: np.ndarray, rho_d: np.ndarray) -> np.ndarray:
    """The scaled specular measurement rho~_s = rho - rho_d = ks rho_s (sec. 4), clipped at 0."""
    return np.clip(rho - rho_d[:, None, :], 0.0, None)
