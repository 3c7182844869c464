"""HDR merge (paper 002 sec. 4) against known radiance."""

import numpy as np
import pytest

from facetsynth.hdr import SensorModel, merge_exposures
from facetsynth.render import expose

TIMES = np.array([0.01, 0.1, 1.0])


def bracket(radiance, sensor, rng=None):
    return np.stack([expose(radiance, t, sensor.saturation, sensor.read_sigma, sensor.shot_gain, rng) for t in TIMES])


def test_noise_free_merge_is_exact_over_the_dynamic_range():
    radiance = np.logspace(-4, 1.9, 600).reshape(20, 10, 3)  # 1e-4 .. 80: 5.9 decades
    sensor = SensorModel(saturation=1.0)
    merged, saturated = merge_exposures(bracket(radiance, sensor), TIMES, sensor)
    assert not saturated.any()
    np.testing.assert_allclose(merged, radiance, rtol=1e-6)


def test_all_exposures_clipped_gives_flagged_lower_bound():
    sensor = SensorModel(saturation=1.0)
    radiance = np.full((2, 2, 3), 500.0)
    merged, saturated = merge_exposures(bracket(radiance, sensor), TIMES, sensor)
    assert saturated.all()
    np.testing.assert_allclose(merged, sensor.clip_level / TIMES.min())


def test_dark_pixels_stay_finite_and_dark():
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    radiance = np.zeros((8, 8, 3))
    merged, saturated = merge_exposures(bracket(radiance, sensor, np.random.default_rng(1)), TIMES, sensor)
    assert np.isfinite(merged).all() and not saturated.any()
    assert np.abs(merged).max() < 5 * sensor.noise_floor  # noise-floor values, longest exposure


def test_noisy_merge_is_unbiased_and_inverse_variance_weighted():
    rng = np.random.default_rng(7)
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    radiance = np.full((200, 200, 3), 0.5)  # usable in the 0.1 s and 1 s exposures
    values = bracket(radiance, sensor, rng)
    merged, _ = merge_exposures(values, TIMES, sensor)
    # Predicted std. dev. of the optimal combination of the two usable exposures.
    var = [(sensor.read_sigma**2 + sensor.shot_gain * t * 0.5) / t**2 for t in TIMES[1:]]
    predicted = np.sqrt(1.0 / np.sum(1.0 / np.array(var)))
    assert abs(merged.mean() - 0.5) < 3 * predicted / np.sqrt(merged.size) + 1e-5
    assert abs(merged.std() / predicted - 1.0) < 0.03
    naive = np.mean(values[1:] / TIMES[1:, None, None, None], axis=0)
    assert merged.std() < 0.75 * naive.std()


def test_bracket_order_does_not_matter():
    rng = np.random.default_rng(3)
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    radiance = np.logspace(-3, 1.5, 300).reshape(10, 10, 3)
    values = bracket(radiance, sensor, rng)
    shuffled = [2, 0, 1]
    a, _ = merge_exposures(values, TIMES, sensor)
    b, _ = merge_exposures(values[shuffled], TIMES[shuffled], sensor)
    np.testing.assert_allclose(a, b, rtol=1e-6)


def test_noise_spike_in_a_short_exposure_of_a_dark_pixel_is_ignored():
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    values = np.array([0.02, 0.0005, 0.001]).reshape(3, 1, 1)   # spike at t = 0.01, dark at 0.1 and 1
    merged, _ = merge_exposures(values, TIMES, sensor)
    assert merged.item() == pytest.approx(0.001)   # the longest exposure's reading, not 0.02 / 0.01 = 2
