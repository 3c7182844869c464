"""HDR assembly: merge an exposure bracket into scene-linear radiance (paper 002 sec. 4).

The camera's response is linear (values are t I clipped at the saturation
level), so the merge is an inverse-variance weighted mean of the per-exposure
estimates v_e / t_e over the exposures that are neither saturated nor at the
noise floor (Debevec and Malik 1997 with a linear response; the weights follow
the sensor noise model var(v) = read_sigma^2 + shot_gain v).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """What the merge needs to know about the sensor."""

    saturation: float | None = None   # clipping level of exposure values; None: never clips
    read_sigma: float = 0.0           # std. dev. of the read noise, in exposure units
    shot_gain: float = 0.0            # shot-noise variance per unit value
    floor_sigmas: float = 3.0         # values below floor_sigmas * read_sigma are noise floor
    saturation_margin: float = 0.02   # values above (1 - margin) * saturation count as saturated

    @property
    def noise_floor(self) -> float:
        return self.floor_sigmas * self.read_sigma

    @property
    def clip_level(self) -> float:
        return np.inf if self.saturation is None else (1.0 - self.saturation_margin) * self.saturation


def merge_exposures(values: np.ndarray, times: np.ndarray, sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """Merge exposures (E, ..., C) taken with ``times`` (E,) into radiance (..., C).

    Usable exposures are those neither clipped nor at the noise floor. They are
    combined with inverse-variance weights t^2 / var(v), the variance taken at
    a first-pass estimate I0 = sum(v) / sum(t) (weights from each noisy value
    itself would bias the merge low). A pixel whose longest unclipped exposure
    is at the noise floor is dark: it keeps that exposure's estimate, so a
    noise spike in a short exposure cannot pose as signal.

    A NaN or +Inf reading (a dead or hot sensor value) is unusable like a
    clipped one: the pixel is merged from its other exposures.

    Returns (radiance, saturated): ``saturated`` (...) is True where every
    exposure of some channel clipped (or was NaN / Inf); there the radiance is
    the lower bound clip level / t_min. Never NaN.
    """
    values = np.asarray(values, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64).reshape((-1,) + (1,) * (values.ndim - 1))
    unclipped = values < sensor.clip_level
    usable = unclipped & (values > sensor.noise_floor)

    # The longest unclipped exposure of each pixel decides whether it is dark.
    all_clipped = ~unclipped.any(axis=0)
    longest = np.argmax(np.where(unclipped, times, -np.inf), axis=0)
    longest_value = np.take_along_axis(values, longest[None], axis=0)[0]
    longest_time = times.ravel()[longest]
    dark = ~all_clipped & (longest_value <= sensor.noise_floor)
    usable &= ~dark

    first_pass = np.divide(np.where(usable, values, 0.0).sum(axis=0), np.where(usable, times, 0.0).sum(axis=0),
                           out=np.zeros(values.shape[1:]), where=usable.any(axis=0))
    variance = sensor.read_sigma**2 + sensor.shot_gain * times * first_pass + 1e-30
    weight = np.where(usable, times**2 / variance, 0.0)
    weight_sum = weight.sum(axis=0)
    merged = np.divide((weight * np.where(usable, values, 0.0) / times).sum(axis=0), weight_sum,
                       out=np.zeros(values.shape[1:]), where=weight_sum > 0)

    lower_bound = sensor.clip_level / times.min() if sensor.saturation is not None else 0.0
    fallback = np.where(all_clipped, lower_bound, np.clip(longest_value / longest_time, 0.0, None))
    radiance = np.where(weight_sum > 0, merged, fallback)
    return radiance.astype(np.float32), all_clipped.any(axis=-1)
