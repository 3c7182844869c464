"""BRDF samples and diffuse/specular separation (paper 002 sec. 4, eqs. 8-9)."""

from __future__ import annotations

import numpy as np

from ..io.colour import channel_mean
from ..models.render import light_geometry


def brdf_samples(radiance: np.ndarray, points: np.ndarray, lights: np.ndarray,
                 light_intensities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8: rho(x, i_q(x), o) = I_q(x) |P_q - x|^2 / ((n . i_q(x)) L_q).

    ``radiance`` (P, Q, 3) at points (P, 3) under homogeneous lights (Q, 4) (or positions (Q, 3);
    :func:`facetsynth.models.render.light_geometry`: |P_q - x|^2 is 1 for a directional light) of intensity
    (Q, 3). Each point has its own light direction i_q(x) = (P_q - x)/|P_q - x|.
    Returns (rho (P, Q, 3), light directions (P, Q, 3)). Where n . i <= 0 (a
    light at or below the sample plane) rho is 0.
    """
    wi, r2 = light_geometry(points[:, None, :], np.asarray(lights, float)[None])
    cos_i = wi[..., 2]
    scale = np.divide(r2, cos_i, out=np.zeros_like(r2), where=cos_i > 1e-6)
    irradiance_free = np.divide(radiance, light_intensities[None], out=np.zeros(radiance.shape),
                                where=light_intensities[None] > 0)
    return irradiance_free * scale[..., None], wi


def diffuse_level(rho: np.ndarray, radiance: np.ndarray, valid: np.ndarray, threshold: float = 0.05,
                  lowest: float = 0.0) -> np.ndarray:
    """Eq. 9: rho_d(x) = min_q { rho(x, i_q, o) | I_q(x) > threshold * I_avg(x) }, per channel; with
    ``lowest`` > 0, the mean of the m of those samples whose channel mean is smallest instead, m = max(1,
    round(lowest * n)) of the point's n qualifying samples.

    The minimum of n noisy samples lies about sigma sqrt(2 ln n) below the
    diffuse level (480 samples: 3.5 sigma), and sigma of a rectified point
    depends on where it falls between camera pixels. Averaging the lowest few
    per cent removes most of that bias and takes in more of the specular tail
    those samples carry; choosing them on the channel mean, one set for all
    channels, keeps each channel's own noise out of the choice.
    docs/decisions.md, "Diffuse level under noise" (config ``separate.lowest``).
    I is the channel mean of the radiance; I_avg its mean over the valid
    samples of the point. A sample whose rho or radiance is NaN or Inf counts
    as invalid. A point with no qualifying sample (fully dark, or no valid
    sample) gets rho_d = 0. Returns (P, 3); kd = pi rho_d.
    """
    if not 0.0 <= lowest <= 1.0:
        raise ValueError(f"lowest must be a fraction in [0, 1], not {lowest}")
    intensity, rho_mean = channel_mean(radiance), channel_mean(rho)
    valid = valid & np.isfinite(rho_mean) & np.isfinite(intensity)     # the mean of a NaN or Inf channel is not finite
    n_valid = valid.sum(axis=1)
    average = np.divide(np.where(valid, intensity, 0.0).sum(axis=1), n_valid,
                        out=np.zeros(n_valid.shape), where=n_valid > 0)
    qualifies = valid & (intensity > threshold * average[:, None]) & (average[:, None] > 0)
    if lowest == 0.0 or rho.shape[1] == 0:
        minimum = np.where(qualifies[..., None], rho, np.inf).min(axis=1, initial=np.inf)
        return np.where(np.isfinite(minimum), minimum, 0.0)
    n = qualifies.sum(axis=1)
    m = np.clip(np.round(lowest * n), 1, None).astype(np.intp)                    # (P,) <= n where n >= 1
    k = int(m.max())
    key = np.where(qualifies, rho_mean, np.inf)
    order = np.argpartition(key, k - 1, axis=1)[:, :k] if k < key.shape[1] else np.arange(key.shape[1])[None]
    order = np.take_along_axis(order, np.argsort(np.take_along_axis(key, order, axis=1), axis=1), axis=1)
    taken = (np.arange(k)[None, :] < m[:, None]) & np.isfinite(np.take_along_axis(key, order, axis=1))
    level = np.where(taken[..., None], np.take_along_axis(rho, order[..., None], axis=1), 0.0).sum(axis=1)
    return np.where(n[:, None] > 0, level / m[:, None], 0.0)


def specular_residual(rho: np.ndarray, rho_d: np.ndarray) -> np.ndarray:
    """The scaled specular measurement rho~_s = rho - rho_d = ks rho_s (sec. 4), clipped at 0."""
    return np.clip(rho - rho_d[:, None, :], 0.0, None)
