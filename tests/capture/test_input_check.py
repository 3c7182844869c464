"""Issue 15, parts 1 and 2: bad captures never pass ``facetsynth check``, the import stage or ``predict``.

Each test reproduces an input from the issue's "What was seen" list (or its neighbours) on a tiny 4x3
capture and asserts the one-line error: the file, the JSON path of the key, the reason.
"""

import copy
import logging
import math

import numpy as np
import OpenImageIO as oiio
import pytest

from conftest import exposure_files, toy_manifest, write_manifest, write_toy_capture

from facetsynth.app import cli
from facetsynth.capture import manifest
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import write_exr
from facetsynth.stages import hdr
from facetsynth.stages.capture import check_capture

GOOD = toy_manifest([(0, 0.1, 0.04), (0.1, 0, 0.04)])
FILES = exposure_files(GOOD)


@pytest.fixture
def capture(tmp_path):
    """A valid 4x3 capture of two frames of two exposures each; returns its folder."""
    return write_toy_capture(tmp_path / "cap", GOOD)


write = write_manifest


def mutated(folder, mutate):
    """Rewrite the folder's manifest as GOOD changed by ``mutate``; returns the manifest path."""
    data = copy.deepcopy(GOOD)
    mutate(data)
    return write(folder, data)


def check_error(folder, capsys):
    """Run ``facetsynth check`` on ``folder``: it must fail with one line on stderr; returns that line."""
    assert cli.main(["check", str(folder)]) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("facetsynth check: error:")]
    assert len(lines) == 1, err
    return lines[0]


# --- part 1: the manifest's meaning ---------------------------------------------------------------------

BAD_MANIFESTS = [
    # case, mutation, JSON path, reason
    ("NaN light position", lambda d: d["frames"][1]["light"].update(position=[math.nan, 0, 0.04]),
     "frames/1/light/position/0", "nan is not a finite number"),
    ("Inf light position", lambda d: d["frames"][0]["light"].update(position=[0, 0, math.inf]),
     "frames/0/light/position/2", "inf is not a finite number"),
    ("NaN sample width", lambda d: d["sample"].update(width=math.nan), "sample/width", "not a finite number"),
    ("Inf sample height", lambda d: d["sample"].update(height=math.inf), "sample/height", "not a finite number"),
    ("-Inf in t", lambda d: d["camera"].update(t=[0, 0, -math.inf]), "camera/t/2", "not a finite number"),
    ("NaN exposure time", lambda d: d["frames"][0]["exposures"][1].update(time=math.nan),
     "frames/0/exposures/1/time", "not a finite number"),
    ("integer beyond float range", lambda d: d["frames"][0]["light"].update(intensity=[10 ** 400, 1, 1]),
     "frames/0/light/intensity/0", "not a finite number"),
    ("NaN in an unknown field", lambda d: d.update(rig={"temperature": math.nan}), "rig/temperature",
     "not a finite number"),
    ("light below the sample plane", lambda d: d["frames"][1]["light"].update(position=[0, 0, -0.05]),
     "frames/1/light/position/2", "light at z = -0.05 m is not above the sample plane"),
    ("light on the sample plane", lambda d: d["frames"][0]["light"].update(position=[0.2, 0, 0]),
     "frames/0/light/position/2", "not above the sample plane"),
    ("light of zero intensity", lambda d: d["frames"][0]["light"].update(intensity=[0, 0, 0]),
     "frames/0/light/intensity", "every channel is zero"),
    ("negative intensity channel", lambda d: d["frames"][0]["light"].update(intensity=[1, -1, 1]),
     "frames/0/light/intensity/1", "less than the minimum"),
    ("zero exposure time", lambda d: d["frames"][0]["exposures"][0].update(time=0),
     "frames/0/exposures/0/time", "less than or equal to the minimum"),
    ("negative exposure time", lambda d: d["frames"][0]["exposures"][0].update(time=-0.25),
     "frames/0/exposures/0/time", "less than or equal to the minimum"),
    ("negative sample width", lambda d: d["sample"].update(width=-0.1), "sample/width", "less than or equal"),
    ("misspelt saturation", lambda d: d.update(saturaton=d.pop("saturation")), "(top level)",
     "'saturation' is a required property; did you mean 'saturation' for 'saturaton'?; "
     'state "saturation": null for data that were never clipped'),
    ("no saturation", lambda d: d.pop("saturation"), "(top level)",
     "'saturation' is a required property; state \"saturation\": null"),
    ("zero saturation", lambda d: d.update(saturation=0), "saturation", "less than or equal to the minimum"),
    ("saturation as a string", lambda d: d.update(saturation="1.0"), "saturation", "is not of type"),
    ("misspelt sample width", lambda d: d["sample"].update(widht=d["sample"].pop("width")), "sample",
     "'width' is a required property; did you mean 'width' for 'widht'?"),
    ("R not orthonormal beyond the tolerance", lambda d: d["camera"]["R"][0].__setitem__(1, 1e-4), "camera/R",
     "not a rotation matrix (|R R^T - I| up to 0.0001, tolerance 1e-05"),
    ("R a reflection", lambda d: d["camera"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "camera/R",
     "det R = -1, must be +1"),
    ("camera below the sample plane", lambda d: d["camera"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     "camera/t", "the camera centre C = -R^T t = (0, 0, -1) is not above the sample plane"),
    ("camera above the plane looking away", lambda d: d["camera"].update(t=[0, 0, -1],
                                                                          R=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     "camera/t", "the camera looks away from the sample"),
    ("sample centre outside the image", lambda d: d["camera"]["K"][0].__setitem__(2, 40), "camera",
     "the sample's centre projects to (col 40.0, row 1.0), outside the 4x3 image"),
    ("zero focal length", lambda d: d["camera"]["K"][1].__setitem__(1, 0), "camera/K",
     "focal lengths must be positive"),
    ("K not a camera matrix", lambda d: d["camera"]["K"].__setitem__(2, [0, 0, 2]), "camera/K",
     "rows 2 and 3 must be [0, fy, cy] and [0, 0, 1], not [0.0, 100.0, 1.0] and [0.0, 0.0, 2.0]"),
]


@pytest.mark.parametrize("case, mutate, where, reason", BAD_MANIFESTS, ids=[c[0] for c in BAD_MANIFESTS])
def test_bad_manifest_fails_check_with_file_key_and_reason(capture, capsys, case, mutate, where, reason):
    path = mutated(capture, mutate)
    line = check_error(capture, capsys)
    assert f"{path}: invalid capture manifest at '{where}': " in line and reason in line, line


def test_the_import_stage_and_predict_refuse_a_manifest_as_check_does(capture, tmp_path, capsys):
    """One check for all: ``facetsynth check``, the import stage and ``predict`` give the same line."""
    from facetsynth.app.predict import predict
    from facetsynth.stages.capture import Inputs, Outputs, Settings, run
    path = mutated(capture, lambda d: d["frames"][0]["light"].update(position=[0, 0, math.nan]))
    line = check_error(capture, capsys)
    with pytest.raises(InputError) as imported:
        run(Inputs(path=capture), Outputs(capture=tmp_path / "out"),
            Settings(source="import", rig=None, seed=0, noise=False))
    with pytest.raises(InputError) as predicted:
        predict(tmp_path / "no-model", path, tmp_path / "pred", progress=False)
    assert line.endswith(str(imported.value)) and str(imported.value) == str(predicted.value)
    assert not (tmp_path / "out").exists() and not (tmp_path / "pred").exists()


@pytest.mark.parametrize("name, reason", [("frames/0000\x00.exr", "embedded null byte"),
                                          ("x" * 5000, "File name too long")], ids=["NUL byte", "too long"])
def test_a_file_name_that_cannot_be_a_path_is_an_input_error(capture, capsys, name, reason):
    path = mutated(capture, lambda d: d["frames"][0]["exposures"][1].update(file=name))
    line = check_error(capture, capsys)
    assert f"{path}: invalid capture manifest at 'frames/0/exposures/1/file': not a usable file name ({reason})" in line


@pytest.mark.parametrize("mutate", [
    lambda d: d.update(saturation=None),                                    # never clipped: stated
    lambda d: d["camera"]["R"][0].__setitem__(1, 1e-6),                     # R written with 6 decimals
    lambda d: d["sample"].update(width=10.0, height=10.0),                  # a close-up: sample > frame
    lambda d: d["frames"][0]["light"].update(intensity=[0, 0, 2.5]),        # one channel lit
    lambda d: d.update(saturation_margin=0.05, rig={"leds": [1, 2]}),       # unknown fields, one near a key
], ids=["saturation null", "R to 6 decimals", "close-up", "blue light", "unknown fields"])
def test_legitimate_manifests_still_pass(capture, mutate):
    mutated(capture, mutate)
    check_capture(capture)


def test_the_merged_hdr_capture_states_saturation_null(capture, tmp_path):
    """The merged HDR capture is never clipped and says so: ``"saturation": null``, and it reloads."""
    third = {"light": {"position": [-0.1, -0.1, 0.04], "intensity": [1, 1, 1]},   # hdr needs lights spanning an area
             "exposures": [{"file": "frames/0002_e0.exr", "time": 1.0}]}
    write_exr(capture / third["exposures"][0]["file"], {"RGB": np.full((3, 4, 3), 0.2)})
    mutated(capture, lambda d: d["frames"].append(third))
    hdr.run(hdr.Inputs(capture=capture),
            hdr.Outputs(frames=tmp_path / "hdr/frames", manifest=tmp_path / "hdr/manifest.json",
                              metrics=tmp_path / "hdr/metrics.json"))
    assert manifest.load(tmp_path / "hdr/manifest.json")["saturation"] is None


# --- part 2: check reads the pixels as hdr does ---------------------------------------------------------

def test_good_capture_passes_check_with_a_summary(capture, capsys):
    assert cli.main(["check", str(capture)]) == 0
    out = capsys.readouterr().out
    assert "valid capture, 2 frames, 4 exposure files, camera 4x3, saturation 1, 0 warning(s)" in out


def test_truncated_exr_fails_check_naming_the_file(capture, capsys):
    frame = capture / FILES[3]
    frame.write_bytes(frame.read_bytes()[:-40])                # the header reads; the pixels do not
    line = check_error(capture, capsys)
    assert f"{frame.resolve()}: unreadable frame: not a readable OpenEXR image" in line


def test_png_renamed_exr_fails_check_naming_the_file(capture, capsys):
    frame = capture / FILES[1]
    png = capture / "frame.png"
    oiio.ImageBuf(oiio.ImageSpec(4, 3, 3, "uint8")).write(str(png))    # right size, R G B: the header passed
    png.replace(frame)
    line = check_error(capture, capsys)
    assert "manifest.json: exposures mix EXR (" in line and f"and 8-bit images ({frame.resolve()})" in line


def test_nan_pixels_fail_check_with_first_file_and_counts(capture, capsys):
    for name, pixels in ((FILES[1], [(2, 3)]), (FILES[2], [(0, 0), (1, 1)])):
        image = np.full((3, 4, 3), 0.2)
        for row, col in pixels:
            image[row, col, 1] = np.inf if row else np.nan
        write_exr(capture / name, {"RGB": image}, precision="float16")
    line = check_error(capture, capsys)
    assert (f"{(capture / FILES[1]).resolve()}: 1 pixel(s) are NaN or Inf (first at row 2, col 3); "
            "3 such pixel(s) in 2 of 4 exposure files") in line


@pytest.mark.parametrize("damage, message", [
    (lambda f: write_exr(f, {"RGB": np.zeros((4, 4, 3))}), "frame is 4x4, the manifest's camera is 4x3"),
    (lambda f: write_exr(f, {"Y": np.zeros((3, 4))}), "unreadable frame: no R, G, B channels (found: Y)"),
], ids=["wrong size", "no RGB"])
def test_frames_the_hdr_stage_cannot_use_fail_check(capture, capsys, damage, message):
    damage(capture / FILES[0])
    assert f"{(capture / FILES[0]).resolve()}: {message}" in check_error(capture, capsys)


def test_negative_pixels_are_a_warning_with_count_and_first_file(capture, capsys, caplog):
    image = np.full((3, 4, 3), 0.2)
    image[0, :2, 0] = -0.01                                   # 2 pixels
    for name in FILES[2:]:
        write_exr(capture / name, {"RGB": image})
    assert cli.main(["check", str(capture)]) == 0
    out, err = capsys.readouterr()
    assert "1 warning(s)" in out
    assert (f"facetsynth check: warning: {capture}: 4 negative value(s) in 2 of 4 exposure files "
            f"(first: {(capture / FILES[2]).resolve()}); hdr clips them to 0") in err
    with caplog.at_level(logging.WARNING):                    # the import stage logs the same warning
        check_capture(capture)
    assert "4 negative value(s)" in caplog.text


def test_a_dark_frame_is_a_warning_and_all_dark_frames_an_error(capture, capsys):
    for name in FILES[2:]:
        write_exr(capture / name, {"RGB": np.zeros((3, 4, 3))})
    assert cli.main(["check", str(capture)]) == 0
    assert (f"1 of 2 frame(s) are dark, no value above the noise floor (0) in any exposure (first: frame 1, "
            f"{(capture / FILES[2]).resolve()})") in capsys.readouterr().err
    for name in FILES[:2]:
        write_exr(capture / name, {"RGB": np.zeros((3, 4, 3))})
    line = check_error(capture, capsys)
    assert f"{capture}: every frame is dark: no value above the noise floor (0) in any of the 4 exposure files" in line


def test_dark_means_below_the_noise_floor_as_in_hdr(capture, capsys):
    """Values of 0.2 under a read noise of 0.1 (floor 3 sigma = 0.3, as hdr has it) measured nothing."""
    mutated(capture, lambda d: d.update(noise={"read_sigma": 0.1, "shot_gain": 0.0}))
    assert "every frame is dark: no value above the noise floor (0.3)" in check_error(capture, capsys)
