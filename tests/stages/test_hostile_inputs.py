"""Issue 32, the input side: captures and config that passed validation and then broke the pipeline.

Each class of the issue gets several instances; every error is one line naming the file, the key (or
line) and the problem, from ``facetsynth check`` and from the ``hdr`` stage alike (a capture that skipped
check is caught before it becomes a model).
"""

from __future__ import annotations

import copy
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from conftest import REPO, exposure_files, hdr_outputs, toy_manifest, write_manifest, write_toy_capture

from facetsynth.app import cli
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import read_exr, read_frame, read_json, read_yaml, write_exr
from facetsynth.stages import hdr

GOOD = toy_manifest([(0, 0.1, 0.04), (0.1, 0, 0.04), (-0.1, -0.1, 0.04)])   # lights spanning an area, as hdr needs
FILES = exposure_files(GOOD)


@pytest.fixture
def toy(tmp_path):
    """A valid 4x3 capture of three frames (lights spanning an area, as hdr needs) of two exposures."""
    return write_toy_capture(tmp_path / "cap", GOOD)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The card on the tiny rig (tests/data/rig-tiny.yaml: 30 lights, 120 x 80, 3 exposures), noise-free."""
    from facetsynth.truth.virtual_rig import VirtualRig, capture
    folder = tmp_path_factory.mktemp("tiny") / "capture"
    capture(REPO / "resources/scenes/card.yaml", VirtualRig.load(REPO / "tests/data/rig-tiny.yaml"), folder,
            seed=2, noise=False)
    return folder


write = write_manifest


def mutated(folder, mutate, base=None):
    data = copy.deepcopy(GOOD if base is None else base)
    mutate(data)
    return write(folder, data)


def variant(tiny, tmp_path, mutate):
    """A copy of the tiny capture's manifest (frames read where they are, truth dropped) changed by ``mutate``."""
    data = json.loads((tiny / "manifest.json").read_text())
    data.pop("truth", None)
    for frame in data["frames"]:
        frame.pop("truth", None)
        for exposure in frame["exposures"]:
            exposure["file"] = str(tiny / exposure["file"])
    mutate(data)
    return write(tmp_path / "variant", data)


def check_error(folder, capsys):
    """``facetsynth check``: exit 1 with one error line (no traceback); returns it."""
    assert cli.main(["check", str(folder)]) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("facetsynth check: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def check_warnings(folder, capsys):
    """``facetsynth check`` passes; returns its warning lines."""
    assert cli.main(["check", str(folder)]) == 0, capsys.readouterr().err
    return [line for line in capsys.readouterr().err.splitlines() if ": warning: " in line]


def hdr_error(folder, out):
    """The hdr stage on ``folder`` must refuse it, publishing nothing; returns the error."""
    with pytest.raises(InputError) as err:
        hdr.run(hdr.Inputs(capture=folder), hdr_outputs(out))
    assert not (out / "frames").exists() and not (out / "manifest.json").exists()
    return str(err.value)


# --- 3. units: the sample against the camera's view, the lights against the sample -------------------------

@pytest.mark.parametrize("size, where, reason", [
    ((100, 0.1), "sample/width", "(1/900 of it, less than 1/500)"),  # width typed in mm: rectify hung
    ((100, 100), "sample", "reaches behind the camera"),
    ((1e6, 1e6), "sample", "reaches behind the camera"),           # resample's IndexError
    ((2, 2), "sample", "times the 9600 pixels that see it"),       # rectify: 80 s instead of 0.14
    ((1e-4, 1e-4), "sample/width", "spans 0.11 pixel(s)"),
], ids=["width 100", "100 x 100", "1e6", "2 m", "0.1 mm"])
def test_a_sample_size_no_camera_view_fits_is_refused_by_check_and_hdr(tiny, tmp_path, capsys, size, where, reason):
    path = variant(tiny, tmp_path, lambda d: d.update(sample={"width": size[0], "height": size[1]}))
    line = check_error(path.parent, capsys)
    assert f"{path}: implausible capture at '{where}': " in line and reason in line, line
    assert reason in hdr_error(path.parent, tmp_path / "hdr")


def test_a_sample_far_wider_than_the_view_of_a_looking_down_camera_is_refused(toy, capsys):
    """The toy camera looks straight down (no part behind it): a width 2500 times its view is a unit slip."""
    path = mutated(toy, lambda d: d["sample"].update(width=100.0))
    line = check_error(toy, capsys)
    assert f"{path}: implausible capture at 'sample/width': the camera sees 0.04 m of the sample's width" in line
    assert "millimetres" in line


def test_a_sample_larger_than_the_view_but_plausible_is_a_warning(tiny, tmp_path, capsys):
    path = variant(tiny, tmp_path, lambda d: d.update(sample={"width": 1.0, "height": 1.0}))
    warnings = check_warnings(path.parent, capsys)
    assert any("the camera sees only 11.1 % of the sample's width" in w for w in warnings), warnings
    assert any("sample/height" in w for w in warnings), warnings


def test_a_sample_covering_few_pixels_is_a_warning(tiny, tmp_path, capsys):
    path = variant(tiny, tmp_path, lambda d: d.update(sample={"width": 0.01, "height": 0.01}))
    warnings = check_warnings(path.parent, capsys)
    assert any("covers only 60 of the image's 9600 pixels" in w for w in warnings), warnings


@pytest.mark.parametrize("scale", [1e5, 1e7])
def test_lights_a_unit_slip_away_are_refused(tiny, tmp_path, capsys, scale):
    def farther(d):
        for frame in d["frames"][3:]:
            frame["light"]["position"] = [scale * v for v in frame["light"]["position"]]
    path = variant(tiny, tmp_path, farther)
    line = check_error(path.parent, capsys)
    assert f"{path}: implausible capture at 'frames/" in line and "/light/position': the light is" in line, line
    assert "sample diagonals" in line and "millimetres" in line
    assert "/light/position': the light is" in hdr_error(path.parent, tmp_path / "hdr")


def test_far_and_near_lights_are_warnings(tiny, tmp_path, capsys):
    def far(d):
        d["frames"][5]["light"]["position"] = [0.0, 30.0, 10.0]              # 224 diagonals
        d["frames"][6]["light"]["position"] = [0.0, 0.0, 0.005]              # 0.035 diagonals
    path = variant(tiny, tmp_path, far)
    warnings = check_warnings(path.parent, capsys)
    assert any("1 light(s) are more than 100 sample diagonals away (the farthest: frames/5/light/position" in w
               for w in warnings), warnings
    assert any("nearer than 0.05 sample diagonals" in w and "frames/6/light/position" in w for w in warnings)


def test_the_tiny_rig_capture_passes_check_without_warnings(tiny, capsys):
    assert check_warnings(tiny, capsys) == []


# --- 4, 11. EXR files: RGBA and extra channels, data windows, declared sizes --------------------------------

def _exr(path, channels, **header):
    exr_header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
    OpenEXR.File(exr_header, {k: np.asarray(v, np.float32) for k, v in channels.items()}).write(str(path))


@pytest.mark.parametrize("extra", [{"A": 1.0}, {"Z": 5.0}, {"A": 1.0, "Z": 5.0}, {"A": 0.5, "Y": 3.0}],
                         ids=["RGBA", "RGB+Z", "RGBA+Z", "RGBA+Y"])
def test_rgb_with_alpha_or_extra_channels_is_read_as_rgb(toy, capsys, extra):
    rgb = {"R": np.full((3, 4), 0.1), "G": np.full((3, 4), 0.2), "B": np.full((3, 4), 0.3)}
    for name in FILES:
        _exr(toy / name, {**rgb, **{k: np.full((3, 4), v) for k, v in extra.items()}})
    frame, _ = read_frame(toy / FILES[0])
    np.testing.assert_allclose(frame[0, 0], [0.1, 0.2, 0.3], rtol=1e-6)
    channels, _ = read_exr(toy / FILES[0])
    assert set(channels) == {"RGB", *extra}
    assert cli.main(["check", str(toy)]) == 0, capsys.readouterr().err
    assert "valid capture, 3 frames" in capsys.readouterr().out


def test_a_layered_rgba_exr_splits_its_alpha(tmp_path):
    _exr(tmp_path / "l.exr", {f"diffuse.{c}": np.full((2, 2), v) for c, v in zip("RGBA", (1, 2, 3, 4))})
    channels, _ = read_exr(tmp_path / "l.exr")
    assert set(channels) == {"diffuse", "diffuse.A"} and channels["diffuse.A"][0, 0] == 4
    assert channels["diffuse"].shape == (2, 2, 3)


def _window(x0, y0, x1, y1):
    return (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))


@pytest.mark.parametrize("data, display", [((10, 10, 13, 12), (0, 0, 3, 2)), ((0, 0, 3, 2), (0, 0, 9, 9)),
                                           ((1, 0, 4, 2), (0, 0, 4, 2))], ids=["offset", "cropped", "shifted"])
def test_an_exr_whose_data_window_is_not_its_image_is_refused(toy, capsys, data, display):
    w, h = data[2] - data[0] + 1, data[3] - data[1] + 1
    _exr(toy / FILES[2], {"R": np.ones((h, w)), "G": np.ones((h, w)), "B": np.ones((h, w))},
         dataWindow=_window(*data), displayWindow=_window(*display))
    line = check_error(toy, capsys)
    assert f"{(toy / FILES[2]).resolve()}: unreadable frame: its pixels (data window ({data[0]}, {data[1]})" in line
    assert "display window" in line


def test_an_exr_offset_as_a_whole_is_read(tmp_path):
    _exr(tmp_path / "o.exr", {"R": np.ones((3, 4)), "G": np.ones((3, 4)), "B": np.ones((3, 4))},
         dataWindow=_window(10, 10, 13, 12), displayWindow=_window(10, 10, 13, 12))
    assert read_frame(tmp_path / "o.exr")[0].shape == (3, 4, 3)


def _declaring(path, width, height):
    """Patch a small EXR's header to declare ``width`` x ``height`` (its data and display windows): a tiny
    file whose pixels a reader would allocate before finding them missing."""
    raw = bytearray(path.read_bytes())
    for name in (b"dataWindow\0box2i\0", b"displayWindow\0box2i\0"):
        at = raw.index(name) + len(name) + 4
        raw[at:at + 16] = struct.pack("<4i", 0, 0, width - 1, height - 1)
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("size", [(12000, 12000), (4, 4000), (40000, 40000), (3, 4)])
def test_a_declared_size_is_refused_from_the_header_before_any_pixel_is_read(toy, capsys, size):
    _declaring(toy / FILES[1], *size)
    line = check_error(toy, capsys)
    assert f"{(toy / FILES[1]).resolve()}: frame is {size[0]}x{size[1]}, the manifest's camera is 4x3" in line


def test_a_declared_size_costs_no_memory(toy):
    _declaring(toy / FILES[1], 12000, 12000)
    # the peak of this process alone: VmHWM starts anew at exec, ru_maxrss keeps the forking parent's peak (a test
    # run late in the suite measured the suite's 1.3 GB)
    code = ("import sys; from facetsynth.io.fileio import read_exposure; from facetsynth.io.errors import "
            "InputError\ntry:\n    read_exposure(sys.argv[1], (3, 4))\nexcept InputError as e:\n    print(e)\n"
            "print(next(int(line.split()[1]) for line in open('/proc/self/status') if line.startswith('VmHWM')))")
    done = subprocess.run([sys.executable, "-c", code, str(toy / FILES[1])], capture_output=True, text=True)
    message, rss_kb = done.stdout.strip().splitlines()
    assert "frame is 12000x12000" in message and "no pixel read" in message
    # the pixels alone would be 1.7 GB; the process measured 0.3 GB
    assert int(rss_kb) < 1_000_000, f"{int(rss_kb) / 1000:.0f} MB"


def test_an_image_beyond_the_memory_limit_is_refused_without_a_shape(toy):
    _declaring(toy / FILES[1], 40000, 40000)
    with pytest.raises(InputError, match=r"declares 40000x40000 pixels of 3 channel\(s\), 17.9 GiB"):
        read_exr(toy / FILES[1])


# --- 5. errors quote a bounded, escaped excerpt only --------------------------------------------------------

def test_a_truth_scene_that_is_another_file_is_refused_without_printing_it(toy, tmp_path, capsys):
    secret = tmp_path / "secret.txt"
    secret.write_text("".join(f"user{i}:x:{i}:{i}:secret line {i}:/home/u{i}:/bin/sh\n" for i in range(200)))
    path = mutated(toy, lambda d: d.update(truth={"scene": str(secret)}))
    line = check_error(toy, capsys)
    assert f"{path}: invalid capture manifest at 'truth/scene': not a scene file: {secret}" in line
    assert "secret line 3" not in line and len(line) < 600, line
    assert "secret line 3" not in hdr_error(toy, tmp_path / "hdr")


def test_etc_passwd_as_the_truth_scene_is_not_printed(toy, capsys):
    mutated(toy, lambda d: d.update(truth={"scene": "/etc/passwd"}))
    line = check_error(toy, capsys)
    assert "'truth/scene'" in line and "daemon" not in line and len(line) < 600, line


@pytest.mark.parametrize("text", ["a: [1, 2\nb: " + "x" * 5000 + "\n", "\tkey: value\n" + "secret\n" * 100,
                                  "name: ok\nregions: {{" + "z" * 3000])
def test_yaml_syntax_errors_give_a_position_not_the_text(tmp_path, text):
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_yaml(path)
    message = str(err.value)
    assert message.startswith(f"{path}: not valid YAML at line ") and "\n" not in message
    assert len(message) < 300 and "x" * 100 not in message and "secret" not in message, message


def test_a_long_value_in_a_manifest_is_quoted_by_an_excerpt(toy, capsys):
    path = mutated(toy, lambda d: d.update(camera="line one\n" + "A" * 10000))
    line = check_error(toy, capsys)
    assert f"{path}: invalid capture manifest at 'camera': 'line one\\nAAA" in line
    assert "A" * 200 not in line and len(line) < 600, line


# --- 6. clipping ------------------------------------------------------------------------------------------

def test_a_capture_clipped_in_every_exposure_is_refused(toy, tmp_path, capsys):
    for name in FILES:
        write_exr(toy / name, {"RGB": np.full((3, 4, 3), 1.0)})
    line = check_error(toy, capsys)
    assert (f"{toy / 'manifest.json'}: every exposure of every frame is clipped (all 12 pixels that see the "
            "sample, in all 3 frames") in line
    assert "every exposure of every frame is clipped" in hdr_error(toy, tmp_path / "hdr")


@pytest.mark.parametrize("value", [1.0, 5.0, 0.985])
def test_a_frame_clipped_in_every_exposure_is_refused(toy, tmp_path, capsys, value):
    for name in FILES[2:4]:
        write_exr(toy / name, {"RGB": np.full((3, 4, 3), value)})
    line = check_error(toy, capsys)
    assert f"{toy / 'manifest.json'}: frame 1 is clipped in every exposure (all 12 pixels" in line
    assert "drop frames/1" in line
    assert "frame 1 is clipped in every exposure" in hdr_error(toy, tmp_path / "hdr")


def test_a_frame_half_clipped_is_a_warning_in_check_and_hdr(toy, tmp_path, capsys):
    image = np.full((3, 4, 3), 0.2)
    image[:, :2] = 1.0                                  # 6 of 12 pixels clipped in both exposures
    for name in FILES[:2]:
        write_exr(toy / name, {"RGB": image})
    warnings = check_warnings(toy, capsys)
    assert any("1 frame(s) have more than 20 % of the sample's pixels clipped in every exposure (the most: "
               "frame 0, 50 %)" in w for w in warnings), warnings
    assert any("16.7 % of the sample's pixels over all 3 frames are clipped" in w for w in warnings), warnings
    hdr.run(hdr.Inputs(capture=toy), hdr_outputs(tmp_path / "hdr"))
    recorded = json.loads((tmp_path / "hdr/metrics.json").read_text())["warnings"]
    assert any("frame 0, 50 %" in w for w in recorded), recorded


def test_a_clipped_pixel_in_one_exposure_only_is_measured(toy, capsys):
    write_exr(toy / FILES[1], {"RGB": np.full((3, 4, 3), 1.0)})       # the long exposure clipped, the short not
    assert check_warnings(toy, capsys) == []


@pytest.mark.parametrize("mutate, where, reason", [
    (lambda d: d["frames"][1]["exposures"][1].update(time=0.25), "frames/1/exposures/1/time",
     "exposure time 0.25 s is that of frames/1/exposures/0 too"),
    (lambda d: d["frames"][0]["exposures"].append({"file": "frames/0000_e0.exr", "time": 4.0}),
     "frames/0/exposures/2/file", "is also frames/0/exposures/0/file: one picture cannot be two exposures"),
    (lambda d: d["frames"][2]["exposures"].append({"file": "./frames/../frames/0002_e1.exr", "time": 2.0}),
     "frames/2/exposures/2/file", "is also frames/2/exposures/1/file"),
], ids=["equal times", "one file twice", "one file by two names"])
def test_equal_times_and_duplicate_files_are_refused(toy, tmp_path, capsys, mutate, where, reason):
    path = mutated(toy, mutate)
    line = check_error(toy, capsys)
    assert f"{path}: invalid capture manifest at '{where}': " in line and reason in line, line
    assert f"'{where}'" in hdr_error(toy, tmp_path / "hdr")


def test_one_file_in_two_frames_is_a_warning(toy, capsys):
    mutated(toy, lambda d: d["frames"][2]["exposures"][0].update(file="frames/0000_e0.exr"))
    warnings = check_warnings(toy, capsys)
    assert any("frames 0 and 2 list the same exposure file" in w for w in warnings), warnings


# --- 7. exposure times no float arithmetic survives ---------------------------------------------------------

@pytest.mark.parametrize("time", [1e-320, 1e-30, 1e-10, 1e10, 1e308])
def test_exposure_times_outside_the_float_range_are_refused_naming_the_key(toy, tmp_path, capsys, time):
    path = mutated(toy, lambda d: d["frames"][2]["exposures"][1].update(time=time))
    line = check_error(toy, capsys)
    assert (f"{path}: invalid capture manifest at 'frames/2/exposures/1/time': exposure time {time:.4g} s is "
            "outside [1e-09, 1e+09] s") in line, line
    assert "'frames/2/exposures/1/time'" in hdr_error(toy, tmp_path / "hdr")


@pytest.mark.parametrize("times", [(1e-9, 1e-8), (1e8, 1e9)])
def test_exposure_times_at_the_ends_of_the_range_merge_finitely(toy, tmp_path, times):
    def set_times(d):
        for frame in d["frames"]:
            for exposure, t in zip(frame["exposures"], times):
                exposure["time"] = t
    mutated(toy, set_times)
    for q in range(3):                       # consistent brackets: radiance 0.2 / t_long
        write_exr(toy / FILES[2 * q], {"RGB": np.full((3, 4, 3), 0.2 * times[0] / times[1])})
    hdr.run(hdr.Inputs(capture=toy), hdr_outputs(tmp_path / "hdr"))
    merged, _ = read_frame(tmp_path / "hdr/frames/0000.exr")
    np.testing.assert_allclose(merged, 0.2 / times[1], rtol=1e-4)


# --- 10. file-system oddities: one line, not a traceback ----------------------------------------------------

def test_a_symlink_loop_among_the_exposures_is_one_line(toy, capsys):
    frames = toy / "frames"
    (frames / "0001_e1.exr").unlink()
    os.symlink("loop-b", frames / "loop-a")
    os.symlink("loop-a", frames / "loop-b")
    os.symlink("loop-a", frames / "0001_e1.exr")
    line = check_error(toy, capsys)
    assert "frames/1/exposures/1/file" in line and "symbolic link loop" in line, line


def test_an_exposure_that_is_a_folder_is_one_line(toy, capsys):
    (toy / FILES[3]).unlink()
    (toy / FILES[3]).mkdir()
    line = check_error(toy, capsys)
    assert f"{(toy / FILES[3]).resolve()}: frame file listed in" in line and "is a folder" in line, line


def test_a_manifest_json_that_is_a_folder_is_one_line(tmp_path, capsys):
    (tmp_path / "cap/manifest.json").mkdir(parents=True)
    line = check_error(tmp_path / "cap", capsys)
    assert f"{tmp_path / 'cap/manifest.json'}: is a folder" in line
    with pytest.raises(InputError, match="is a folder, not a file"):
        read_json(tmp_path / "cap/manifest.json")


def test_a_rig_description_that_is_a_folder_is_one_line(tmp_path, capsys):
    (tmp_path / "rig.yaml").mkdir()
    for command in (["rig", "check", str(tmp_path / "rig.yaml")], ["rig", "capture", str(tmp_path / "rig.yaml"),
                                                                   str(tmp_path / "out")]):
        assert cli.main(command) == 1
        err = capsys.readouterr().err
        assert f"{tmp_path / 'rig.yaml'}: is a folder, not a file" in err and "Traceback" not in err, err
    from facetsynth.truth.virtual_rig import VirtualRig
    with pytest.raises(InputError, match="is a folder"):
        VirtualRig.load(tmp_path / "rig.yaml")


def test_a_binary_file_as_yaml_is_one_line(tmp_path):
    (tmp_path / "scene.yaml").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(InputError, match=r"scene\.yaml: not valid YAML: not UTF-8 text"):
        read_yaml(tmp_path / "scene.yaml")


# --- 10, 11. the workflow's config and sample sheet, before any job -----------------------------------------

@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """The workflow (linked, not copied) with a one-sample sheet."""
    folder = tmp_path_factory.mktemp("wf")
    for part in ("Snakefile", "workflow", "config", "resources", "rig"):
        (folder / part).symlink_to(REPO / part)
    (folder / "sheet.tsv").write_text("sample\tsource\tpath\trig\ndemo\tvirtual\tresources/scenes/demo.yaml\t\n")
    return folder


def dry_run(workdir, *config, timeout=60):
    """A dry run; returns (exit code, its output). Refusals come from workflow/rules/common.smk, before the DAG."""
    done = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--nolock", "--cores", "1",
                           "--config", "samples=sheet.tsv", *config], cwd=workdir, capture_output=True, text=True,
                          timeout=timeout)
    return done.returncode, done.stdout + done.stderr     # snakemake logs to stdout when it is no terminal


@pytest.mark.parametrize("config, message", [
    ("params={eta_min: 5, eta_max: 2}", "params.eta_min (5) must be less than params.eta_max (2)"),
    ("params={eta_default: 4.5}", "params.eta_default (4.5) lies outside [params.eta_min, params.eta_max]"),
    ("cluster={min_representatives: 80}", "cluster.min_representatives (80) exceeds cluster.max_representatives (64)"),
    ("resample={n_theta_range: [32, 16]}", "resample.n_theta_range is [32, 16]: its minimum exceeds its maximum"),
    ("synthesize={overlap: [0.9, 0.5]}", "synthesize.overlap is [0.9, 0.5]"),
    ("validate={views: [{name: a, theta_deg: 30, phi_deg: 0}, {name: a, theta_deg: 40, phi_deg: 0}]}",
     "validate.views: the name 'a' is given to 2 views"),
    ("scatter={tiles: 100000}", "scatter.tiles is 100000, more than 1024 jobs per stage and sample"),
    ("scatter={tiles: 1025}", "scatter.tiles is 1025"),
], ids=["eta bounds", "eta default", "representatives", "n_theta_range", "overlap", "view names", "scatter 1e5",
        "scatter 1025"])
def test_contradicting_config_is_refused_before_any_job(workdir, config, message):
    code, err = dry_run(workdir, config)
    assert code != 0 and f"config: {message}" in err, err[-2000:]
    assert "Building DAG" not in err and "Job stats" not in err


def test_the_shipped_config_still_passes(workdir):
    code, err = dry_run(workdir, "scatter={tiles: 4}", timeout=120)
    assert code == 0, err[-2000:]


@pytest.mark.parametrize("row, message", [
    ("demo\tvirtual\tresources/scenes/demo.yaml\t\tsurplus\n", "1 field(s) beyond the header's 4 columns "
                                                               "(sample, source, path, rig), the first 'surplus'"),
    ("demo\tvirtual\tresources/scenes/demo.yaml\trig/descriptions/tiny.yaml\tx\ty\n", "2 field(s) beyond"),
    ("demo\tvirtual\tresources/scenes\t\n", "path 'resources/scenes' of sample 'demo' is a folder"),
    ("demo\tvirtual\tresources/scenes/demo.yaml\trig/descriptions\n", "rig 'rig/descriptions' of sample 'demo' "
                                                                     "is a folder"),
], ids=["one extra", "two extra", "scene a folder", "rig a folder"])
def test_a_bad_sample_sheet_row_names_the_sheet_and_line(workdir, row, message):
    (workdir / "bad.tsv").write_text("sample\tsource\tpath\trig\n" + row)
    code, err = dry_run(workdir, "samples=bad.tsv")
    assert code != 0 and f"bad.tsv line 2: {message}" in err, err[-2000:]


# --- 11. duplicate keys, absurd BRDF values -----------------------------------------------------------------

@pytest.mark.parametrize("old, new, key", [
    ('"saturation": 1.0', '"saturation": 1.0, "saturation": 1e9', "saturation"),
    ('"width": 4', '"width": 4, "width": 400', "width"),
    ('"time": 0.25', '"time": 0.25, "time": 0.5', "time"),
], ids=["saturation", "camera width", "time"])
def test_a_key_given_twice_in_a_json_manifest_is_refused(toy, capsys, old, new, key):
    text = json.dumps(GOOD)
    assert old in text
    (toy / "manifest.json").write_text(text.replace(old, new, 1))
    line = check_error(toy, capsys)
    assert f"{toy / 'manifest.json'}: not valid JSON: key '{key}' appears twice in one object" in line, line


@pytest.mark.parametrize("text, key, line_no", [
    ("name: a\nsize: [0.1, 0.1]\nname: b\n", "name", 3),
    ("regions:\n  - kd: [0.5, 0.5, 0.5]\n    kd: [0.1, 0.1, 0.1]\n", "kd", 3),
])
def test_a_key_given_twice_in_a_yaml_document_is_refused(tmp_path, text, key, line_no):
    (tmp_path / "doc.yaml").write_text(text)
    with pytest.raises(InputError) as err:
        read_yaml(tmp_path / "doc.yaml")
    assert f"doc.yaml: not valid YAML: key '{key}' appears twice in one mapping (line {line_no}" in str(err.value)


def test_yaml_merge_keys_still_override(tmp_path):
    (tmp_path / "doc.yaml").write_text("base: &b {a: 1, b: 2}\nderived:\n  <<: *b\n  b: 3\n")
    assert read_yaml(tmp_path / "doc.yaml")["derived"] == {"a": 1, "b": 3}


@pytest.mark.parametrize("value", [1e300, 1e7, 1e6 * 1.5])
def test_absurd_brdf_values_are_refused_by_the_stencil_readers(tmp_path, capsys, value):
    from facetsynth.stencil import grid, readers
    brdf = np.full(grid.SHAPE, 0.5)
    brdf[0, 2, 5] = value
    readers.write_utia_bin(tmp_path / "b.bin", brdf)
    with pytest.raises(InputError, match=r"b\.bin: field 'rgb': 288 value\(s\) of 248832 above 1e\+06 1/sr"):
        readers.read_utia_bin(tmp_path / "b.bin")
    assert cli.main(["stencil-fit", str(tmp_path / "b.bin")]) == 1
    assert "above 1e+06 1/sr" in capsys.readouterr().err


def test_an_absurd_merl_file_is_refused(tmp_path):
    from facetsynth.stencil import readers
    table = np.full((3, 90, 90, 180), 0.01)
    table[1, 3, 4, 5] = 1e300
    readers.write_merl_table(tmp_path / "m.binary", table)
    with pytest.raises(InputError, match=r"m\.binary: field 'rgb': 1 value\(s\) of 4374000 above 1e\+06"):
        readers.read_merl_table(tmp_path / "m.binary")


def test_measured_brdfs_stay_within_the_limit():
    from conftest import RGL_FILES
    from facetsynth.stencil import readers
    assert max(float(readers.read_rgl(f).max()) for f in RGL_FILES) < readers.MAX_BRDF / 100
