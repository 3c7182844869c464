"""The virtual rig: pixel model of DESIGN.md sec. 4 and capture through the serial driver."""

import numpy as np
import pytest

from facetsynth.capture import manifest
from facetsynth.models import microfacet
from facetsynth.io.fileio import read_rgb
from facetsynth.truth.scene import Scene
from facetsynth.truth.virtual_rig import VirtualRig, capture


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory, repo):
    out = tmp_path_factory.mktemp("capture") / "demo"
    rig = VirtualRig.load(repo / "tests/data/rig-tiny.yaml")
    capture(repo / "resources/scenes/demo.yaml", rig, out, seed=3, noise=False)
    return out, rig


def test_scan_covers_the_paper_geometry(repo):
    rig = VirtualRig.load(repo / "rig/descriptions/virtual.yaml")
    scan = rig.scan()
    assert len(scan) == 40 * 34                      # 40 LEDs, 0.6 cm steps over 20 cm
    first, last = rig.led_position(0, scan[0][0]), rig.led_position(39, scan[-1][0])
    np.testing.assert_allclose(first, [-0.117, 0.20, 0.04])
    np.testing.assert_allclose(last, [0.117, 0.002, 0.04], atol=1e-12)
    camera = rig.camera(0.1)
    theta = np.degrees(np.arccos(camera.centre[2] / np.linalg.norm(camera.centre)))
    assert np.linalg.norm(camera.centre) == pytest.approx(1.0) and theta == pytest.approx(53.13, abs=0.01)


def test_manifest_is_valid_and_lights_follow_the_controller(tiny_capture):
    out, rig = tiny_capture
    m = manifest.load(out)
    assert len(m["frames"]) == len(rig.scan()) == 30
    for frame, (steps, led) in zip(m["frames"], rig.scan()):
        assert (frame["carriage_steps"], frame["led"]) == (steps, led)
        np.testing.assert_allclose(frame["light"]["position"], rig.led_position(led, steps))
    intensities = manifest.light_intensities(m["frames"])
    assert 0.15 < intensities.min() and intensities.max() < 0.45 and intensities.std() > 0   # per-LED variation
    assert manifest.has_truth(m) and m["rig"]["firmware"].endswith("-virtual")


def test_pixels_follow_the_pixel_model_against_an_independent_evaluation(tiny_capture):
    """value = min(saturation, t I), I = rho (n.i) L / |P - x|^2 with rho of eq. 6, per pixel."""
    out, _ = tiny_capture
    m = manifest.load(out)
    camera, scene = manifest.camera(m), Scene.load(m["truth"]["scene"])
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(10, 70, 40), rng.integers(10, 110, 40)
    for q in (0, 13, 29):
        frame = m["frames"][q]
        truth = read_rgb(frame["truth"]["radiance"])
        P, L = np.array(frame["light"]["position"]), np.array(frame["light"]["intensity"])
        for r, c in zip(rows, cols):
            # Independent ray-plane intersection through the pixel centre.
            ray = camera.R.T @ np.linalg.solve(camera.K, [c, r, 1.0])
            x = camera.centre - camera.centre[2] / ray[2] * ray
            wi, wo = (P - x) / np.linalg.norm(P - x), (camera.centre - x) / np.linalg.norm(camera.centre - x)
            p = scene.parameters(x[None, :2])
            rho = microfacet.rho(wi, wo, p.kd[0], p.ks[0], p.eta[0], p.alpha_u[0], p.alpha_v[0], p.phi_frame[0])
            expected = rho * wi[2] * L / np.sum((P - x) ** 2)
            np.testing.assert_allclose(truth[r, c], expected, rtol=1e-3, atol=1e-7)   # stored as half floats
            for exposure in frame["exposures"]:
                value = read_rgb(exposure["file"])[r, c]
                # Stored as half floats, as a camera delivers: relative precision 2^-11.
                np.testing.assert_allclose(value, np.minimum(1.0, exposure["time"] * expected), rtol=1e-3, atol=1e-7)


def test_off_sample_pixels_see_black_and_markers_are_black(tiny_capture):
    out, _ = tiny_capture
    m = manifest.load(out)
    camera, scene = manifest.camera(m), Scene.load(m["truth"]["scene"])
    xy = camera.pixel_plane_points()
    truth = read_rgb(m["frames"][10]["truth"]["radiance"])
    assert np.all(truth[~scene.on_sample(xy)] == 0)
    assert np.all(truth[scene.marker_mask(xy)] == 0)
    assert np.all(truth[scene.on_sample(xy) & ~scene.marker_mask(xy)].sum(-1) > 0)


def test_noise_is_seeded_and_reproducible_on_any_number_of_threads(tmp_path, repo):
    """Each frame has its own noise stream (seed, frame): frames rendered on 2 threads are the frames
    rendered on 1, bit for bit, and so is their manifest; another seed gives other noise."""
    rig = VirtualRig.load(repo / "tests/data/rig-tiny.yaml")
    a = capture(repo / "resources/scenes/card.yaml", rig, tmp_path / "a", seed=5, noise=True, threads=1)
    b = capture(repo / "resources/scenes/card.yaml", rig, tmp_path / "b", seed=5, noise=True, threads=2)
    c = capture(repo / "resources/scenes/card.yaml", rig, tmp_path / "c", seed=6, noise=True, threads=2)
    for e in ("0007_e2.exr", "0020_e1.exr"):
        np.testing.assert_array_equal(read_rgb(a / "frames" / e), read_rgb(b / "frames" / e))
        assert not np.array_equal(read_rgb(a / "frames" / e), read_rgb(c / "frames" / e))
    assert (a / "manifest.json").read_text() == (b / "manifest.json").read_text()
    noisy, clean = read_rgb(a / "frames/0007_e2.exr"), np.minimum(1.0, read_rgb(a / "truth/radiance_0007.exr"))
    assert 0 < np.abs(noisy - clean).mean() < 0.02
