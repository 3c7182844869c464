"""Declared transfer functions of 8-bit exposures (facetsynth.capture.transfer) and the hdr stage on captures of one
8-bit exposure per frame (a light dome's one sRGB JPEG per light). The errors measured are printed
(pytest -s)."""

import copy
import json

import numpy as np
import OpenImageIO as oiio
import pytest

from facetsynth.capture import manifest
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import read_frame, write_exr
from facetsynth.capture.response import Response
from facetsynth.stages import hdr
from facetsynth.capture.transfer import Transfer, decode, parse, table
from test_response import LIGHTS, MANIFEST, SIZE   # the bracket tests' 8-bit capture: camera and lights

# --- the transfer functions ---------------------------------------------------------------------------


@pytest.mark.parametrize("code, linear", [(0, 0.0), (10, 0.0030353), (128, 0.2158605), (255, 1.0),
                                          (11, 0.0033465), (188, 0.5028865), (64, 0.0512695)])
def test_srgb_decode_matches_iec_61966_2_1(code, linear):
    """Known values of the sRGB decode (IEC 61966-2-1): the linear segment below V = 0.04045 (code 10 is
    on it, code 11 above it), the power segment above."""
    assert decode(np.array([code], np.uint8), "srgb")[0] == pytest.approx(linear, abs=5e-8)


def test_srgb_decode_is_continuous_monotone_and_ends_at_0_and_1():
    lut = table("srgb")
    assert lut[0] == 0.0 and lut[255] == 1.0 and (np.diff(lut) > 0).all()
    # The two segments meet at V = 0.04045 (to the standard's 4 digits: 0.0031308 either way).
    v = 0.04045
    assert v / 12.92 == pytest.approx(((v + 0.055) / 1.055) ** 2.4, rel=1e-4)


def test_linear_and_gamma_decode():
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    np.testing.assert_allclose(decode(codes, "linear"), codes / 255.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(decode(codes, {"gamma": 2.2}), (codes / 255.0) ** 2.2, rtol=1e-12)
    assert decode(codes, {"gamma": 2.2}).shape == codes.shape
    assert decode(np.array([[255]], np.uint8), {"gamma": 0.45})[0, 0] == 1.0


def test_black_level_is_subtracted_and_code_255_stays_1():
    b = 0.02
    lut = table("srgb", black_level=b)
    assert lut[255] == 1.0 and lut[0] == 0.0
    raw = table("srgb")
    np.testing.assert_allclose(lut, np.maximum(raw - b, 0) / (1 - b))
    assert (lut[raw <= b] == 0).all() and (lut[raw > b] > 0).all()
    with pytest.raises(ValueError, match="black level"):
        table("srgb", black_level=1.0)


def test_parse_and_describe():
    assert parse("srgb") == Transfer("srgb") and "IEC 61966-2-1" in parse("srgb").describe()
    assert parse({"gamma": 2.2}).describe() == "gamma 2.2 ((code / 255) ^ 2.2)"
    for value in ("srgb", "linear", {"gamma": 1.8}):
        assert parse(parse(value).to_json()) == parse(value)
    for bad in ("rec709", {"gamma": 0}, {"gamma": -1}, {"gama": 2.2}, 2.2, None):
        with pytest.raises(ValueError):
            parse(bad)
    with pytest.raises(ValueError, match="0..255"):
        decode(np.array([256]), "srgb")
    with pytest.raises(AttributeError):                 # frozen
        parse("srgb").kind = "linear"


def test_declared_response_sensor_model_clips_only_255_and_floors_only_black():
    for transfer, b in (("srgb", 0.0), ("linear", 0.0), ({"gamma": 2.2}, 0.0), ("srgb", 0.05)):
        response = Response.from_transfer(parse(transfer), b)
        sensor = response.sensor_model()
        lut = response.linear[:, 0]
        assert lut[255] >= sensor.clip_level > lut[254]
        assert (lut[lut > 0] > sensor.noise_floor).all() and sensor.noise_floor >= 0


# --- the hdr stage on one 8-bit exposure per frame -----------------------------------------------------

TIME = 0.5


def encode(linear, transfer):
    """The continuous code 255 f(L) of linear values L in [0, 1] (the inverse of the decode)."""
    v = np.clip(linear, 0.0, 1.0)
    if transfer == "srgb":
        return 255 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 1e-12), 1 / 2.4) - 0.055)
    if transfer == "linear":
        return 255 * v
    return 255 * v ** (1 / transfer["gamma"])


def write_8bit(path, codes):
    """An 8-bit R G B image with OpenImageIO (PNG lossless; JPEG at quality 100)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = oiio.ImageSpec(codes.shape[1], codes.shape[0], 3, "uint8")
    if path.suffix == ".jpg":
        spec.attribute("Compression", "jpeg:100")
        spec.attribute("jpeg:subsampling", "4:4:4")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(codes)), oiio.geterror()
    out.close()


def radiance_image(seed, low=0.004, high=2.6):
    """Log-uniform radiance: at TIME, exposure values 0.002 .. 1.3 (about 5 % clipped, a few at code 0
    in the linear and gamma codings)."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.uniform(np.log(low), np.log(high), (SIZE, SIZE, 3)))


def smooth_radiance_image(seed, low=0.004, high=2.6):
    """Radiance varying smoothly (log-linear ramps, JPEG-friendly) over the range of :func:`radiance_image`."""
    y, x = np.mgrid[0:SIZE, 0:SIZE] / (SIZE - 1)
    ramps = np.stack([x, y, (x + y) / 2], axis=-1)[..., np.roll([0, 1, 2], seed)]
    return np.exp(np.log(low) + np.log(high / low) * ramps)


def one_shot_capture(folder, transfer, black_level=0.0, ext=".png", times=(TIME,), image=radiance_image):
    """A 4-light capture of 8-bit exposures at ``times`` encoded with ``transfer``, black at linear
    ``black_level``: code = round(255 f(b + (1 - b) min(1, t I))), a black 4 x 4 corner (I = 0) in each.
    Returns the true radiance and codes (each frame's (E, H, W, 3))."""
    data = copy.deepcopy(MANIFEST)
    data["transfer"] = transfer
    if black_level:
        data["black_level"] = black_level
    truths, codes = [], []
    for q, light in enumerate(LIGHTS):
        radiance = image(20 + q)
        radiance[:4, :4] = 0.0
        truths.append(radiance)
        write_exr(folder / f"truth/{q:04d}.exr", {"RGB": radiance})
        exposures, frame_codes = [], []
        for k, t in enumerate(times):
            value = black_level + (1 - black_level) * np.minimum(t * radiance, 1.0)
            c = np.rint(encode(value, transfer)).astype(np.uint8)
            write_8bit(folder / f"frames/{q:04d}_{k}{ext}", c)
            exposures.append({"file": f"frames/{q:04d}_{k}{ext}", "time": t})
            frame_codes.append(c)
        codes.append(np.stack(frame_codes))
        data["frames"].append({"light": {"position": light, "intensity": [1, 1, 1]}, "exposures": exposures,
                               "truth": {"radiance": f"truth/{q:04d}.exr"}})
    (folder / "manifest.json").write_text(json.dumps(data))
    return truths, codes


def run_stage(tmp_path, capture="cap", out="hdr"):
    out = tmp_path / out
    hdr.run(hdr.Inputs(capture=tmp_path / capture),
            hdr.Outputs(frames=out / "frames", manifest=out / "manifest.json", metrics=out / "metrics.json"))
    return out, json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("transfer", ["srgb", "linear", {"gamma": 2.2}])
def test_hdr_stage_recovers_one_8bit_exposure_per_frame_with_a_declared_transfer(tmp_path, transfer):
    """No bracket: each frame's one exposure decoded with the declared transfer is the radiance to within
    the 8-bit quantisation (half a code), code 255 flagged saturated, code 0 at 0."""
    truths, codes = one_shot_capture(tmp_path / "cap", transfer)
    out, metrics = run_stage(tmp_path)
    assert metrics["exposure_bits"] == 8 and metrics["transfer"]["declared"] == transfer
    assert metrics["transfer"]["black_level"] == 0.0 and metrics["response"]["scale_from"] == ["transfer"] * 3
    code_err, rel_bright = [], []
    for q, truth in enumerate(truths):
        merged, saturated = read_frame(out / f"frames/{q:04d}.exr")
        c = codes[q][0]
        np.testing.assert_array_equal(saturated, (c == 255).any(axis=-1))
        ok = (c < 255) & (c > 0) & ~saturated[..., None]
        # Half a code, in code units (plus the stored frame's float24 rounding, relative 2^-16).
        code_err.append(np.abs(encode(TIME * merged[ok], transfer) - encode(TIME * truth[ok], transfer)))
        bright = ok & (TIME * truth > 0.25)
        assert (merged[:4, :4] == 0).all() and (c[:4, :4] == 0).all()
        rel_bright.append(np.abs(merged[bright] / truth[bright] - 1))
        assert (merged[c == 0] == 0).all()
        clip_level = Response.from_transfer(parse(transfer)).sensor_model().clip_level
        assert np.allclose(merged[c == 255], clip_level / TIME, rtol=1e-4)
    code_err, rel_bright = np.concatenate(code_err), np.concatenate(rel_bright)
    print(f"\n{transfer}: |code error| max {code_err.max():.4f} (bound 0.5); rel. error of exposure values "
          f"> 0.25: median {np.median(rel_bright):.5f} max {rel_bright.max():.5f}; stage median_rel_error "
          f"{metrics['median_rel_error']:.5f}; saturated pixels {metrics['saturated_pixels']}")
    assert code_err.max() <= 0.5 + 0.005          # + the float24 rounding: 255 * 2^-16 = 0.004 at most
    assert np.median(rel_bright) < 0.004 and rel_bright.max() < 0.0085     # half a code at 0.25: 0.0079..0.0081
    assert metrics["saturated_pixels"] > 0
    # The output is a linear HDR capture: no transfer, no black level; loadable and merged again as EXR.
    hdr_manifest = manifest.load(out / "manifest.json")
    assert "transfer" not in hdr_manifest and "black_level" not in hdr_manifest
    assert hdr_manifest["saturation"] is None
    assert all(len(f["exposures"]) == 1 and f["exposures"][0]["time"] == 1.0 for f in hdr_manifest["frames"])


def test_hdr_stage_subtracts_the_black_level(tmp_path):
    b = 0.03
    truths, codes = one_shot_capture(tmp_path / "cap", "srgb", black_level=b)
    out, metrics = run_stage(tmp_path)
    assert metrics["transfer"] == {"declared": "srgb", "description": "sRGB (IEC 61966-2-1:1999)",
                                   "black_level": b}
    errs = []
    for q, truth in enumerate(truths):
        merged, saturated = read_frame(out / f"frames/{q:04d}.exr")
        bright = ~saturated[..., None] & (TIME * truth > 0.25) & (TIME * truth < 0.95)
        errs.append(np.abs(merged[bright] / truth[bright] - 1))
        # Codes at or below black are 0 (the noise floor), not negative; the black corner among them.
        at_black = table("srgb")[codes[q][0]] <= b
        assert at_black[:4, :4].all() and (merged[at_black] == 0).all() and merged.min() == 0.0
    err = np.concatenate(errs)
    print(f"\nblack level {b}: rel. error of exposure values 0.25..0.95 median {np.median(err):.5f} "
          f"max {err.max():.5f}; stage median_rel_error {metrics['median_rel_error']:.5f}")
    assert np.median(err) < 0.004 and err.max() < 0.009     # half a code at 0.25, over 1 - b: 0.0087
    assert metrics["negative_values"] == 0


def test_hdr_stage_ignoring_the_black_level_would_be_biased(tmp_path):
    """The same capture without its black level: dark values off by far more than the quantisation."""
    truths, _ = one_shot_capture(tmp_path / "cap", "srgb", black_level=0.03)
    data = json.loads((tmp_path / "cap/manifest.json").read_text())
    del data["black_level"]
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    out, metrics = run_stage(tmp_path)
    assert metrics["median_rel_error"] > 0.05


def test_hdr_stage_merges_several_exposures_with_a_declared_transfer(tmp_path):
    """Two exposures two stops apart: merged like a bracket; saturated only where both clip."""
    times = (0.5, 2.0)
    truths, codes = one_shot_capture(tmp_path / "cap", "srgb", times=times)
    out, metrics = run_stage(tmp_path)
    errs = []
    for q, truth in enumerate(truths):
        merged, saturated = read_frame(out / f"frames/{q:04d}.exr")
        np.testing.assert_array_equal(saturated, (codes[q] == 255).all(axis=0).any(axis=-1))
        ok = ~saturated[..., None] & (0.5 * truth > 0.05)
        errs.append(np.abs(merged[ok] / truth[ok] - 1))
    err = np.concatenate(errs)
    print(f"\nsRGB, 2 exposures: rel. error (short exposure value > 0.05) median {np.median(err):.5f} "
          f"max {err.max():.5f}; saturated pixels {metrics['saturated_pixels']}")
    assert np.median(err) < 0.004 and err.max() < 0.015
    assert 0 < metrics["saturated_pixels"] < sum(int((c[1] == 255).any(axis=-1).sum()) for c in codes)


def test_hdr_stage_reads_one_srgb_jpeg_per_light(tmp_path):
    """JPEG (quality 100, 4:4:4) of a smooth scene: within the compression's error (a code or so)."""
    truths, _ = one_shot_capture(tmp_path / "cap", "srgb", ext=".jpg", image=smooth_radiance_image)
    out, metrics = run_stage(tmp_path)
    errs = []
    for q, truth in enumerate(truths):
        merged, saturated = read_frame(out / f"frames/{q:04d}.exr")
        bright = ~saturated[..., None] & (TIME * truth > 0.25)
        errs.append(np.abs(merged[bright] / truth[bright] - 1))
    err = np.concatenate(errs)
    print(f"\nsRGB JPEG q100 4:4:4: rel. error of exposure values > 0.25 median {np.median(err):.5f} max "
          f"{err.max():.5f}; stage median_rel_error {metrics['median_rel_error']:.5f}")
    assert metrics["transfer"]["declared"] == "srgb" and metrics["saturated_pixels"] > 0
    assert np.median(err) < 0.006 and metrics["median_rel_error"] < 0.02


def test_8bit_capture_without_transfer_still_needs_a_bracket_and_names_the_transfer_key(tmp_path):
    one_shot_capture(tmp_path / "cap", "srgb")
    data = json.loads((tmp_path / "cap/manifest.json").read_text())
    del data["transfer"]
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r'manifest.json: 1 exposure\(s\) at 1 distinct time.* needs a bracket of '
                                         r'at least 2 .*declare "transfer": "srgb" in the manifest for sRGB photos'):
        run_stage(tmp_path)


def test_declared_transfer_on_exr_exposures_is_refused(tmp_path):
    data = copy.deepcopy(MANIFEST)
    data["transfer"] = "srgb"
    for q, light in enumerate(LIGHTS):
        write_exr(tmp_path / f"cap/frames/{q:04d}.exr", {"RGB": radiance_image(q) * TIME})
        data["frames"].append({"light": {"position": light, "intensity": [1, 1, 1]},
                               "exposures": [{"file": f"frames/{q:04d}.exr", "time": TIME}]})
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"cap/manifest.json: \"transfer\" \(sRGB.*\) applies to 8-bit exposures "
                                         r"only"):
        run_stage(tmp_path)
    del data["transfer"]
    data["black_level"] = 0.01
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"cap/manifest.json: \"black_level\" \(0.01\) applies to 8-bit exposures "
                                         r"with a declared \"transfer\" only"):
        run_stage(tmp_path)
    data["black_level"] = 0
    (tmp_path / "cap/manifest.json").write_text(json.dumps(data))
    run_stage(tmp_path)                                   # an explicit black level 0 is the default
