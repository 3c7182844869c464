"""HDR assembly: merge an exposure bracket into scene-linear radiance (paper 002 sec. 4).

The camera's response is linear (values are t I clipped at the saturation
level), so the merge is an inverse-variance weighted mean of the per-exposure
estimates v_e / t_e over the exposures that are neither saturated nor at the
noise floor (Debevec and Malik 1997 with a linear response; the weights follow
the sensor noise model var(v) = read_sigma^2 + shot_gain v). 8-bit exposures are linearized first with
the camera response recovered from the brackets (:mod:`facetsynth.capture.response`), or with the transfer
function the manifest declares (:mod:`facetsynth.capture.transfer`), which also gives their sensor model
(clipping at code 255, quantisation noise).
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
    clipped one: the pixel is merged from its other exposures. A negative
    reading is below the noise floor, and a dark pixel's estimate is clipped
    to 0: the radiance is never negative.

    Returns (radiance, saturated): ``saturated`` (...) is True where every
    exposure of some channel clipped (or was NaN / Inf); there the radiance is
    the lower bound clip level / t_min. Never NaN.
    """
    values = np.asarray(values, dtype=np.float32)
    times = np.asarray(times, dtype=np.float64).ravel()
    clip, floor = sensor.clip_level, sensor.noise_floor
    # One pass per exposure (a bracket has a handful), shortest first, so that the last unclipped
    # exposure seen is the longest. float32 throughout: the merge is a weighted mean of at most E
    # estimates v / t (relative rounding ~1e-7), far below any sensor's noise.
    shape = values.shape[1:]
    unclipped_any = np.zeros(shape, bool)
    longest_value = np.zeros(shape, np.float32)
    longest_time = np.ones(shape, np.float32)
    usable = np.empty(values.shape, bool)
    for e in np.argsort(times, kind="stable"):
        v = values[e]
        unclipped = v < clip                # NaN and +Inf readings are never usable
        usable[e] = unclipped & (v > floor)
        unclipped_any |= unclipped
        np.copyto(longest_value, v, where=unclipped)
        np.copyto(longest_time, np.float32(times[e]), where=unclipped)
    all_clipped = ~unclipped_any
    # The longest unclipped exposure of each pixel decides whether it is dark.
    usable &= all_clipped | (longest_value > floor)

    used = np.where(usable, values, np.float32(0.0))          # (E, ...), 0 where unusable
    time_sum = np.tensordot(times.astype(np.float32), usable, axes=1)
    first_pass = np.divide(used.sum(axis=0), time_sum, out=np.zeros(shape, np.float32), where=time_sum > 0)
    weight_sum, weighted = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    # Inverse-variance weights (t / t_max)^2 / var(v); the variance floor keeps a noise-free sensor's
    # weights finite in float32 (any weights merge exact values exactly).
    for e, t in enumerate(times):
        variance = np.maximum(np.float32(sensor.read_sigma**2) + np.float32(sensor.shot_gain * t) * first_pass,
                              np.float32(1e-20))
        weight = np.where(usable[e], np.float32((t / times.max()) ** 2) / variance, np.float32(0.0))
        weight_sum += weight
        weighted += weight * used[e] * np.float32(1.0 / t)
    merged = np.divide(weighted, weight_sum, out=np.zeros(shape, np.float32), where=weight_sum > 0)

    lower_bound = clip / times.min() if sensor.saturation is not None else 0.0
    # Negative values (read noise around a black level) are noise, not signal: below the noise floor
    # they are never averaged in, and a dark pixel's estimate is clipped to 0, since radiance cannot be
    # negative. The hdr stage counts them and warns (stages.hdr.Negatives).
    fallback = np.where(all_clipped, np.float32(lower_bound), np.clip(longest_value / longest_time, 0.0, None))
    radiance = np.where(weight_sum > 0, merged, fallback)
    return radiance.astype(np.float32), all_clipped.any(axis=-1)
