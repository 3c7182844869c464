"""``facetsynth render`` (a tone-mapped preview of a fitted model) and ``facetsynth inspect`` (a sample's state)."""

import json

import numpy as np
import OpenImageIO as oiio
import pytest

from facetsynth.app.cli import main
from facetsynth.io.fileio import read_rgb
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.app.preview import PreviewSettings, display_encode, mirror_light, preview_camera, render_preview
from facetsynth.truth.scene import MaterialMaps
from facetsynth.app.summary import summarise
from facetsynth.models.svbrdf import tabulate_truth

PLANE = PlaneGrid(0.08, 0.06, 8, 6)
P = PLANE.rows * PLANE.cols
KD = np.array([0.6, 0.3, 0.1])


@pytest.fixture(scope="module")
def model_dirs(tmp_path_factory):
    """Two fitted-SVBRDF folders on the same plane: a pure Lambertian one and a glossy isotropic GGX one."""
    root = tmp_path_factory.mktemp("models")
    out = {}
    for name, ks in (("lambert", 0.0), ("glossy", 0.8)):
        maps = MaterialMaps(kd=np.tile(KD, (P, 1)), ks=np.full((P, 3), ks), eta=np.full(P, 1.5),
                            alpha_u=np.full(P, 0.1), alpha_v=np.full(P, 0.1), phi_frame=np.zeros(P),
                            region=np.zeros(P, int))
        tabulate_truth(maps, DirectionGrid(16, 64), PLANE).save(root / name)
        out[name] = root / name
    return out


def test_the_preview_camera_frames_the_sample_centred():
    for theta, phi in ((0.0, 0.0), (30.0, 0.0), (60.0, -75.0)):
        cam = preview_camera(PLANE.width, PLANE.height, theta, phi, 256)
        centre = cam.project(np.zeros(3))
        assert np.allclose(centre, [127.5, 127.5], atol=1e-9)
        corners = cam.project(np.array([[sx * PLANE.width / 2, sy * PLANE.height / 2, 0.0]
                                        for sx in (-1, 1) for sy in (-1, 1)]))
        assert np.all((corners > 0) & (corners < 255)), (theta, phi, corners)
        assert np.degrees(np.arccos(cam.centre[2] / np.linalg.norm(cam.centre))) == pytest.approx(theta)


def test_the_default_light_mirrors_the_view_about_the_normal():
    cam = preview_camera(PLANE.width, PLANE.height, 40.0, 25.0, 64)
    light = mirror_light(PLANE.width, PLANE.height, 40.0, 25.0)
    h = light / np.linalg.norm(light) + cam.centre / np.linalg.norm(cam.centre)
    assert np.allclose(h / np.linalg.norm(h), [0.0, 0.0, 1.0], atol=1e-12)


def test_a_lambertian_sample_renders_kd_over_pi_cos_over_r2(model_dirs, tmp_path):
    """The linear (.exr) preview against the pixel model read by hand: I = kd/pi (n.i) L / r^2 at the centre."""
    light = (0.01, -0.02, 0.1)
    done = render_preview(model_dirs["lambert"], tmp_path / "p.exr",
                          PreviewSettings(theta_deg=20.0, light=light, intensity=2.0, size=64, supersample=1))
    image = read_rgb(tmp_path / "p.exr")
    cam = preview_camera(PLANE.width, PLANE.height, 20.0, 0.0, 64)
    # pixel (32, 32)'s centre sees a point near the sample centre: evaluate the pixel model there exactly
    xy = cam.pixel_plane_points(1)[32, 32]
    d = np.asarray(light) - np.array([xy[0], xy[1], 0.0])
    r2 = d @ d
    expected = KD / np.pi * (d[2] / np.sqrt(r2)) * 2.0 / r2
    assert np.allclose(image[32, 32], expected, rtol=1e-5)
    assert done["sample_pixels"] == int((image.max(axis=-1) > 0).sum())
    assert np.isfinite(image).all() and image[0, 0].max() == 0.0   # the corner is off the sample: black


def test_the_png_is_the_display_encoded_exposed_radiance(model_dirs, tmp_path):
    settings = PreviewSettings(theta_deg=35.0, phi_deg=10.0, size=48, supersample=1, exposure_ev=3.0)
    render_preview(model_dirs["glossy"], tmp_path / "p.exr", settings)
    render_preview(model_dirs["glossy"], tmp_path / "p.png", settings)
    radiance = read_rgb(tmp_path / "p.exr")
    png = oiio.ImageInput.open(str(tmp_path / "p.png"))
    pixels = png.read_image(oiio.UINT8)
    png.close()
    assert pixels.shape == (48, 48, 3)
    assert np.array_equal(pixels, display_encode(radiance * 8.0))
    # sRGB's encoding of a mid linear value (IEC 61966-2-1): 0.2 -> 0.4845 -> 124
    assert display_encode(np.full((1, 1, 3), 0.2, np.float32))[0, 0, 0] == 124
    # the default (mirror) light puts the highlight near the sample centre, the image centre (the half vector is
    # the normal there; 1/r^2 and n.i pull the radiance peak a few pixels towards the light); the corners are dim
    peak = np.unravel_index(np.argmax(radiance.max(axis=-1)), radiance.shape[:2])
    assert np.hypot(peak[0] - 23.5, peak[1] - 23.5) < 6, peak
    lit = radiance[radiance.max(axis=-1) > 0].max(axis=-1)
    assert lit.max() > 1.5 * np.percentile(lit, 10)


def test_auto_exposure_maps_the_lit_sample_near_white(model_dirs, tmp_path):
    done = render_preview(model_dirs["glossy"], tmp_path / "p.png", PreviewSettings(size=48, supersample=1))
    png = oiio.ImageInput.open(str(tmp_path / "p.png"))
    pixels = png.read_image(oiio.UINT8)
    png.close()
    sample = pixels.max(axis=-1)[pixels.max(axis=-1) > 0]
    assert np.percentile(sample, 99.5) >= 250 and np.median(sample) > 40
    assert done["exposure_scale"] > 0


@pytest.mark.parametrize("argv, text", [
    (["--view", "95", "0"], "--view theta must be in [0, 90)"),
    (["--light", "0", "0", "-0.1"], "--light z must be above the sample"),
    (["--size", "4"], "--size must be from 16 to 4096"),
    (["-o", "PREVIEW.bmpx"], "unknown picture type"),
])
def test_render_refuses_bad_arguments_in_one_line(model_dirs, tmp_path, capsys, argv, text):
    args = ["render", str(model_dirs["glossy"]), *argv]
    if "-o" not in argv:
        args += ["-o", str(tmp_path / "p.png")]
    else:
        args[args.index("PREVIEW.bmpx")] = str(tmp_path / "p.bmpx")
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert text in err and "\n" not in err


def test_render_cli_writes_a_picture(model_dirs, tmp_path, capsys):
    assert main(["render", str(model_dirs["glossy"]), "--view", "30", "45", "--size", "32",
                 "-o", str(tmp_path / "p.png")]) == 0
    assert "32x32" in capsys.readouterr().out and (tmp_path / "p.png").stat().st_size > 100


def test_inspect_lists_stages_figures_and_warnings(tmp_path, capsys):
    sample = tmp_path / "results" / "linen"
    for stage, metrics in (("hdr", {"frames": 480, "saturated_pixels": 12, "dark_frames": 0}),
                           ("rectify", {"cols": 168, "rows": 160, "resolution_rule": "auto"}),
                           ("separate", {"specular_signal_fraction": 0.004,
                                         "degenerate": "no specular signal at 99 % of the points"})):
        (sample / stage).mkdir(parents=True)
        (sample / stage / "metrics.json").write_text(json.dumps(metrics))
    (sample / "truth").mkdir()                     # rule score_rectify's scores, beside the fit (issue 31)
    (sample / "truth" / "rectify.json").write_text(json.dumps({"ground_truth": True, "registration_error_px": 0.071}))
    (sample / "logs").mkdir()
    (sample / "logs" / "hdr.log").write_text("2026-12-03 01:00:00,000 INFO facetsynth.stages.hdr: merged\n"
                                             "2026-12-03 01:00:01,000 WARNING facetsynth.stages.hdr: 3 dark "
                                             "frames\n" * 2)
    lines = summarise(sample)
    assert lines[0] == f"{sample}: 3 of 14 stages done"
    assert any(line.split() == ["hdr", "done:", "frames", "480,", "saturated", "pixels", "12,", "dark", "frames",
                                "0"] for line in lines)
    assert any("168x160 points (auto), registration 0.07 px" in line for line in lines)
    assert any(line.split()[:2] == ["capture", "-"] for line in lines)
    assert "2 warning(s):" in lines
    assert "  separate: degenerate: no specular signal at 99 % of the points" in lines
    assert "  hdr: facetsynth.stages.hdr: 3 dark frames" in lines   # the repeated line once
    assert main(["inspect", str(sample)]) == 0
    assert capsys.readouterr().out.splitlines() == lines


def test_inspect_names_a_folder_that_is_not_a_sample(tmp_path, capsys):
    assert main(["inspect", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert str(tmp_path) in err and "holds no stage output" in err
    assert main(["inspect", str(tmp_path / "nope")]) == 1
    assert "not a folder" in capsys.readouterr().err
