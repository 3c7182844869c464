"""HDR merge (paper 002 sec. 4) against known radiance."""

import json

import numpy as np
import pytest

from conftest import hdr_outputs

from facetsynth.capture.hdr import SensorModel, merge_exposures
from facetsynth.models.render import expose

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


def test_hdr_stage_on_two_threads_writes_what_one_thread_writes(tmp_path, repo):
    """The hdr stage merges frames on a thread pool: the frames, the manifest and the accuracy record
    are those of the serial merge (the tiny rig, sensor noise on)."""
    from facetsynth.io.fileio import read_frame
    from facetsynth.stages import hdr
    from facetsynth.truth.virtual_rig import VirtualRig, capture

    capture(repo / "resources/scenes/demo.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"),
            tmp_path / "capture", seed=2, noise=True)
    out = {}
    for threads in (1, 2):
        d = tmp_path / f"hdr{threads}"
        hdr.run(hdr.Inputs(capture=tmp_path / "capture"), hdr_outputs(d), threads=threads)
        out[threads] = d
    for q in (0, 17, 29):
        one, two = read_frame(out[1] / f"frames/{q:04d}.exr"), read_frame(out[2] / f"frames/{q:04d}.exr")
        np.testing.assert_array_equal(one[0], two[0])
        np.testing.assert_array_equal(one[1], two[1])
    assert (out[1] / "metrics.json").read_text() == (out[2] / "metrics.json").read_text()
    assert (out[1] / "manifest.json").read_text().replace("hdr1", "hdr2") == (out[2] / "manifest.json").read_text()
    assert 0 < json.loads((out[2] / "metrics.json").read_text())["median_rel_error"] < 0.03


@pytest.mark.parametrize("saturation, times", [(65535.0, [1e-4, 1e-2, 1.0]), (1.0, [1.0, 30.0, 900.0])])
def test_merge_is_exact_at_sensor_count_scale_and_long_exposures(saturation, times):
    """The merge works in float32: 16-bit counts with a 1e-4 s exposure, and exposures of 15 min, with a
    noise-free sensor (variance floor only) stay finite and exact."""
    times = np.array(times)
    sensor = SensorModel(saturation=saturation)
    radiance = np.logspace(-3, 0, 300).reshape(10, 10, 3) * saturation / times.min() * 0.5
    values = np.stack([expose(radiance, t, saturation) for t in times])
    merged, saturated = merge_exposures(values, times, sensor)
    assert np.isfinite(merged).all() and not saturated.any()
    np.testing.assert_allclose(merged, radiance, rtol=1e-6)


# ---------------------------------------------------------------------------- numerical extremes (issue 7, part 2)
def test_hdr_merge_treats_nan_and_inf_readings_as_unusable():
    """A NaN or +Inf exposure reading (a dead or hot sensor value) is unusable, like a clipped one: the
    pixel is merged from its other exposures exactly as if that reading were absent. A pixel with no
    finite reading at all gets the clipped pixel's finite lower bound and the saturated flag, so later
    stages exclude it. The merge never returns NaN or Inf."""
    from facetsynth.capture.hdr import SensorModel, merge_exposures
    times = np.array([0.01, 0.1, 1.0])
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    values = np.array([0.004, 0.04, 0.4])[:, None, None, None] * np.ones((3, 1, 4, 3))
    reference, _ = merge_exposures(values, times, sensor)
    np.testing.assert_allclose(reference, 0.4, rtol=1e-6)
    bad = values.copy()
    bad[1, 0, 0, 0] = np.nan                  # pixel 0: NaN in the middle exposure
    bad[2, 0, 1, 1] = np.inf                  # pixel 1: Inf in the longest
    bad[:, 0, 2, 2] = np.nan                  # pixel 2: no finite reading in any exposure
    merged, saturated = merge_exposures(bad, times, sensor)
    assert np.isfinite(merged).all()
    without_middle, _ = merge_exposures(values[[0, 2], :, :1], times[[0, 2]], sensor)
    without_longest, _ = merge_exposures(values[:2, :, 1:2], times[:2], sensor)
    np.testing.assert_allclose(merged[0, 0, 0], without_middle[0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(merged[0, 1, 1], without_longest[0, 0, 1], rtol=1e-6)
    np.testing.assert_allclose(merged[0, 3], reference[0, 3], rtol=0)   # an untouched pixel is unchanged
    assert merged[0, 2, 2] == pytest.approx(sensor.clip_level / times.min())
    assert saturated[0, 2] and not saturated[0, 0] and not saturated[0, 1] and not saturated[0, 3]
