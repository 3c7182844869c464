"""Camera response of 8-bit exposures (Debevec and Malik 1997; issue 16 item 3) and the hdr stage on them.

A known linear radiance is exposed at a 4-exposure bracket two stops apart (value = min(1, t I)),
encoded with a known nonlinear response and quantised to 8 bits; the recovered response must linearize
and merge it back to the radiance. The relative errors measured are printed (pytest -s).
"""

import copy
import json

import cv2
import numpy as np
import pytest

from facetsynth.io.errors import InputError
from facetsynth.io.fileio import exposure_bits, read_frame, write_exr
from facetsynth.capture.hdr import merge_exposures
from facetsynth.capture.response import ResponseSettings, recover_response
from facetsynth.stages import hdr

TIMES = np.array([0.0125, 0.05, 0.2, 0.8])      # 4 exposures, 2 stops apart


def srgb(v):
    """The sRGB transfer curve (IEC 61966-2-1): a gamma-like camera tone curve."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 1e-12), 1 / 2.4) - 0.055)


def srgb_inverse(code):
    c = np.asarray(code, np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def shouldered(v):
    """A film-like curve with a soft shoulder: f(1) = 1 is only reached in the limit."""
    return (1 - np.exp(-4 * np.power(np.clip(v, 0.0, 1.0), 0.6))) / (1 - np.exp(-4))


def encode(radiance, times, curve):
    """The 8-bit bracket (E, H, W, 3) of ``radiance``: codes round(255 f(min(1, t I)))."""
    return np.stack([np.rint(255 * curve(np.minimum(t * radiance, 1.0))).astype(np.uint8) for t in times])


def radiance_image(shape=(64, 64, 3), low=0.02, high=20.0, seed=0):
    """Log-uniform radiance over 3 decades (clipped in the longer exposures, dark in the shortest)."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.uniform(np.log(low), np.log(high), shape))


def rel_errors(estimate, truth):
    err = np.abs(estimate / truth - 1)
    return float(np.median(err)), float(np.percentile(err, 95)), float(err.max())


def test_recovered_response_merges_an_srgb_bracket_to_the_radiance():
    radiance = radiance_image()
    codes = encode(radiance, TIMES, srgb)
    response = recover_response([codes], TIMES)
    assert response.scale_from == ("clipping",) * 3
    assert np.isfinite(response.linear).all() and (np.diff(response.linear, axis=0) >= 0).all()
    z = np.arange(8, 251)
    curve_err = np.abs(response.linear[z] / srgb_inverse(z)[:, None] - 1)
    merged, saturated = merge_exposures(response.linearize(codes), TIMES, response.sensor_model())
    assert np.isfinite(merged).all() and not saturated.any()
    median, p95, worst = rel_errors(merged, radiance)
    scale = np.median(radiance / merged)
    s_median, s_p95, s_worst = rel_errors(scale * merged, radiance)
    print(f"\nsRGB: curve rel. error codes 8..250 median {np.median(curve_err):.4f} max {curve_err.max():.4f}; "
          f"merged radiance rel. error median {median:.4f} p95 {p95:.4f} max {worst:.4f}; global scale "
          f"{scale:.4f}; after it median {s_median:.4f} p95 {s_p95:.4f} max {s_worst:.4f}")
    assert np.median(curve_err) < 0.015 and curve_err.max() < 0.04      # measured 0.0044, 0.0227
    assert median < 0.012 and p95 < 0.03 and worst < 0.05                # measured 0.0055, 0.0196, 0.0348
    assert abs(scale - 1) < 0.015                                        # measured 0.9992


def test_shouldered_curve_is_recovered_up_to_its_clipping_level():
    """A soft shoulder clips at code 255 below exposure 1 (at f^-1(254.5 / 255) = 0.9587): the scale is
    fixed where pixels clip, so the merge is the radiance over that level, and the shape is exact."""
    radiance = radiance_image(seed=1)
    codes = encode(radiance, TIMES, shouldered)
    response = recover_response([codes], TIMES)
    merged, _ = merge_exposures(response.linearize(codes), TIMES, response.sensor_model())
    assert np.isfinite(merged).all()
    clip_level = (-np.log(1 - 254.5 / 255 * (1 - np.exp(-4))) / 4) ** (1 / 0.6)   # f(v) = 254.5 / 255
    scale = np.median(radiance / merged)
    s_median, s_p95, s_worst = rel_errors(scale * merged, radiance)
    print(f"\nshouldered: true clipping level {clip_level:.4f}, recovered {scale:.4f}; after the global scale "
          f"rel. error median {s_median:.4f} p95 {s_p95:.4f} max {s_worst:.4f}")
    assert abs(scale / clip_level - 1) < 0.01                           # measured < 0.0001
    assert s_median < 0.012 and s_p95 < 0.035 and s_worst < 0.07       # measured 0.0072, 0.0236, 0.046


def test_bracket_that_never_clips_takes_its_scale_from_the_power_law():
    radiance = radiance_image(low=0.01, high=1.2)          # t_max I <= 0.96: no pixel clips
    codes = encode(radiance, TIMES, srgb)
    response = recover_response([codes], TIMES)
    assert response.scale_from == ("power law",) * 3
    merged, _ = merge_exposures(response.linearize(codes), TIMES, response.sensor_model())
    median, p95, worst = rel_errors(merged, radiance)
    print(f"\nno clipping: merged rel. error median {median:.4f} p95 {p95:.4f} max {worst:.4f}")
    assert median < 0.015 and worst < 0.06                              # measured 0.0065, 0.042


def test_sensor_noise_before_the_tone_curve_keeps_the_merge_and_its_scale():
    """A smooth scene over 3 decades with shot-like noise (sigma = 0.003 sqrt(t I), about one code at
    mid-grey) added before the sensor clips and the sRGB curve is applied: the clipping level is found
    by the split that misclassifies fewest pixels, so the noise does not move the scale."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:96, 0:96] / 95.0
    log_radiance = np.log(0.02) + np.log(1000) * (0.7 * x + 0.3 * (0.5 + 0.5 * np.sin(6 * y)))
    radiance = np.exp(log_radiance)[..., None] * np.array([1.0, 0.8, 0.6])
    codes = np.stack([np.rint(255 * srgb(np.minimum(t * radiance + 0.003 * np.sqrt(t * radiance)
                                                    * rng.standard_normal(radiance.shape), 1.0))).astype(np.uint8)
                      for t in TIMES])
    response = recover_response([codes], TIMES)
    merged, saturated = merge_exposures(response.linearize(codes), TIMES, response.sensor_model())
    assert np.isfinite(merged).all()
    ok = ~saturated
    median, p95, worst = rel_errors(merged[ok], radiance[ok])
    scale = np.median(radiance[ok] / merged[ok])
    print(f"\nnoisy sRGB: merged rel. error median {median:.4f} p95 {p95:.4f} max {worst:.4f}; scale {scale:.4f}")
    assert median < 0.015 and p95 < 0.04 and abs(scale - 1) < 0.015      # measured 0.0082, 0.0250, 0.9962


def test_sensor_model_clips_only_code_255_and_floors_only_code_0():
    radiance = radiance_image()
    response = recover_response([encode(radiance, TIMES, srgb)], TIMES)
    sensor = response.sensor_model()
    lut = response.linear
    assert (lut[255] >= sensor.clip_level).all() and (lut[254] < sensor.clip_level).all()
    assert (lut[0] <= sensor.noise_floor).all() and (lut[1] > sensor.noise_floor).all()
    assert sensor.read_sigma > 0 and sensor.shot_gain > 0


@pytest.mark.parametrize("times", [[0.2], [0.2, 0.2]])
def test_one_exposure_time_is_a_clear_error(times):
    codes = encode(radiance_image(), times, srgb)
    with pytest.raises(InputError, match=r"cap/manifest.json: .*exposure.* needs a bracket of at least 2"):
        recover_response([codes], times, source="cap/manifest.json")


def test_bracket_covering_too_few_codes_is_a_clear_error():
    """A uniform grey card at a 2-exposure bracket: 2 codes per channel, no curve."""
    codes = encode(np.full((16, 16, 3), 0.5), [0.5, 1.0], srgb)
    with pytest.raises(InputError, match=r"cover \d+% of the 8-bit codes .*too short a bracket"):
        recover_response([codes], [0.5, 1.0], ResponseSettings(), source="cap/manifest.json")


# --- the hdr stage on an 8-bit capture ---------------------------------------------------------------

SIZE = 32
MANIFEST = {
    "version": 1, "units": "m", "sample": {"width": 0.1, "height": 0.1},
    "camera": {"width": SIZE, "height": SIZE, "K": [[300, 0, 15.5], [0, 300, 15.5], [0, 0, 1]],
               "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "t": [0, 0, 1], "distortion": [0, 0, 0, 0, 0]},
    "saturation": 1.0, "frames": [],
}
LIGHTS = [[-0.1, -0.1, 0.1], [0.1, -0.1, 0.1], [-0.1, 0.1, 0.1], [0.1, 0.1, 0.1]]


def write_png(path, codes):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(codes[..., ::-1]))     # OpenCV writes BGR


def eight_bit_capture(folder, curve=srgb, ext=".png"):
    """A 4-light capture of 8-bit exposures (PNG, lossless) with the true radiance of each frame."""
    data = copy.deepcopy(MANIFEST)
    truths = []
    for q, light in enumerate(LIGHTS):
        radiance = radiance_image((SIZE, SIZE, 3), low=0.02 * (q + 1), high=10.0 * (q + 1), seed=10 + q)
        truths.append(radiance)
        write_exr(folder / f"truth/{q:04d}.exr", {"RGB": radiance})
        exposures = []
        for k, (t, codes) in enumerate(zip(TIMES, encode(radiance, TIMES, curve))):
            write_png(folder / f"frames/{q:04d}_e{k}{ext}", codes)
            exposures.append({"file": f"frames/{q:04d}_e{k}{ext}", "time": float(t)})
        data["frames"].append({"light": {"position": light, "intensity": [1, 1, 1]}, "exposures": exposures,
                               "truth": {"radiance": f"truth/{q:04d}.exr"}})
    (folder / "manifest.json").write_text(json.dumps(data))
    return truths


def test_hdr_stage_merges_an_8bit_capture_to_the_true_radiance(tmp_path):
    truths = eight_bit_capture(tmp_path / "cap")
    assert exposure_bits(tmp_path / "cap/frames/0000_e0.png") == 8
    out = tmp_path / "hdr"
    hdr.run(hdr.Inputs(capture=tmp_path / "cap"), hdr.Outputs(
        frames=out / "frames", manifest=out / "manifest.json", metrics=out / "metrics.json"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["exposure_bits"] == 8
    curve = np.array(metrics["response"]["linear"])
    assert curve.shape == (256, 3) and curve[0].tolist() == [0, 0, 0] and curve[255].tolist() == [1, 1, 1]
    errs = []
    for q, truth in enumerate(truths):
        merged, saturated = read_frame(out / f"frames/{q:04d}.exr")
        assert np.isfinite(merged).all()
        ok = ~saturated
        errs.append(np.abs(merged[ok] / truth[ok] - 1).ravel())
    err = np.concatenate(errs)
    print(f"\nhdr stage, 8-bit PNG capture: rel. error median {np.median(err):.4f} p95 "
          f"{np.percentile(err, 95):.4f} max {err.max():.4f}; stage's median_rel_error "
          f"{metrics['median_rel_error']:.4f}; saturated pixels {metrics['saturated_pixels']}")
    assert np.median(err) < 0.012 and np.percentile(err, 95) < 0.03      # measured 0.0041, 0.0126
    assert metrics["median_rel_error"] < 0.012


def test_hdr_stage_refuses_a_capture_mixing_exr_and_8bit(tmp_path):
    eight_bit_capture(tmp_path / "cap")
    data = json.loads((tmp_path / "cap/manifest.json").read_text())
    write_exr(tmp_path / "cap/frames/x.exr", {"RGB": np.full((SIZE, SIZE, 3), 0.5)})
    data["frames"][2]["exposures"][0]["file"] = "frames/x.exr"
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    out = tmp_path / "hdr"
    with pytest.raises(InputError, match=r"manifest.json: exposures mix EXR .*x.exr.* and 8-bit images"):
        hdr.run(hdr.Inputs(capture=tmp_path / "cap"), hdr.Outputs(
            frames=out / "frames", manifest=out / "manifest.json", metrics=out / "metrics.json"))


def test_hdr_stage_8bit_capture_with_one_exposure_is_a_clear_error(tmp_path):
    eight_bit_capture(tmp_path / "cap")
    data = json.loads((tmp_path / "cap/manifest.json").read_text())
    for frame in data["frames"]:
        frame["exposures"] = frame["exposures"][1:2]
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    out = tmp_path / "hdr"
    with pytest.raises(InputError, match=r"manifest.json: 1 exposure\(s\) at 1 distinct time"):
        hdr.run(hdr.Inputs(capture=tmp_path / "cap"), hdr.Outputs(
            frames=out / "frames", manifest=out / "manifest.json", metrics=out / "metrics.json"))
