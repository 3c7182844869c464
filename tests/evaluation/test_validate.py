"""Held-out validation (paper 002 sec. 6) and the per-point Ward baseline (Fig. 10, Goldman et al. 2005)."""

import json

import numpy as np
import pytest

from facetsynth.capture import manifest
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.truth.scene import Scene
from facetsynth.stages import heldout_capture, validate
from facetsynth.models.svbrdf import tabulate_truth
from facetsynth.truth.virtual_rig import VirtualRig
from facetsynth.models.ward import WardSVBRDF, fit_points, ward_specular

from test_predict import SCENE


def test_ward_lm_recovers_an_anisotropic_ward_lobe():
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(600, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = np.broadcast_to([0.0, -0.866, 0.5], wi.shape)
    truth = 0.7 * ward_specular(wi, wo, 0.12, 0.3, 1.1)
    fit = fit_points(truth[None], wi[None], wo[None])
    fit = type(fit)(*(f[0] for f in fit))               # the one point
    assert fit.ok
    assert fit.ks == pytest.approx(0.7, rel=1e-3)
    # (alpha_x, alpha_y, phi) and (alpha_y, alpha_x, phi + pi/2) are the same lobe; LM may land on either
    ax, ay, phi = fit.alpha_x, fit.alpha_y, fit.phi
    if ax > ay:
        ax, ay, phi = ay, ax, phi - np.pi / 2
    assert (ax, ay) == pytest.approx((0.12, 0.3), rel=1e-3)
    assert np.angle(np.exp(2j * (phi - 1.1))) / 2 == pytest.approx(0.0, abs=1e-3)     # phi modulo pi
    np.testing.assert_allclose(fit.ks * ward_specular(wi, wo, fit.alpha_x, fit.alpha_y, fit.phi), truth, rtol=1e-6)
    assert np.array_equal(ward_specular(wi, wo, 0.12, 0.3, 1.1), ward_specular(wo, wi, 0.12, 0.3, 1.1))


def test_heldout_rig_moves_the_camera_and_thins_the_lights(repo):
    rig = VirtualRig.load(repo / "rig/descriptions/virtual-demo.yaml")
    held = validate.heldout_rig(rig, 50.9, -15.3, 4, 4)
    cam = held.camera(0.1)
    o = cam.centre / np.linalg.norm(cam.centre)
    assert np.degrees(np.arccos(o[2])) == pytest.approx(50.9, abs=1e-6)
    assert np.degrees(np.arctan2(o[1], o[0])) == pytest.approx(-90 - 15.3, abs=1e-6)
    assert len(held.scan()) == 10 * 9 and len(rig.scan()) == 1360


def test_validate_scores_heldout_views_and_writes_side_by_side_images(tmp_path, repo):
    (tmp_path / "scene.yaml").write_text(SCENE)
    views = {"paper": (50.9, -15.3), "theta30": (30.0, 20.0)}
    for name, (theta, phi) in views.items():
        heldout_capture.run(heldout_capture.Inputs(tmp_path / "scene.yaml", repo / "tests/data/rig-tiny.yaml"),
                            heldout_capture.Outputs(tmp_path / "heldout" / name),
                            heldout_capture.Settings(theta, phi, led_every=2, position_every=2))
    plane = PlaneGrid(0.1, 0.1, 64, 64)
    maps = Scene.load(tmp_path / "scene.yaml").parameters(plane.points3d().reshape(-1, 3)[:, :2])
    tabulate_truth(maps, DirectionGrid(32, 128), plane).save(tmp_path / "svbrdf")
    # a deliberately poor "baseline": the right kd, an isotropic lobe of the wrong width
    p = plane.rows * plane.cols
    WardSVBRDF(plane, maps.kd, maps.ks, np.full(p, 0.5), np.full(p, 0.5), np.zeros(p)).save(tmp_path / "ward")
    (tmp_path / "bench.tsv").write_text("s\th:m:s\tmax_rss\n12.5\t0:00:12\t100\n")
    validate.run(validate.Inputs(tmp_path / "svbrdf", [tmp_path / "heldout" / v for v in views], ward=tmp_path / "ward"),
                 validate.Outputs(tmp_path / "metrics.json", tmp_path / "images", tmp_path / "pred"),
                 validate.Settings(views=tuple(views), fit_benchmarks=(tmp_path / "bench.tsv", tmp_path / "missing.tsv"),
                                   ward_benchmark=tmp_path / "bench.tsv"))
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert set(m["views"]) == set(views)
    for v in m["views"].values():
        assert v["heldout_psnr_db"] > 45 and v["heldout_ssim"] > 0.999       # true parameters: tabulation only
        assert v["baseline_ward_psnr_db"] < v["heldout_psnr_db"] - 10
        assert v["frames"] == len(manifest.load(tmp_path / "heldout" / "paper")["frames"])
        assert set(v["heldout_rel_l2_regions"]) <= {r["name"] for r in Scene.load(tmp_path / "scene.yaml").regions}
        assert max(v["heldout_rel_l2_regions"].values()) < 0.05 < min(v["baseline_ward_rel_l2_regions"].values())
    assert m["heldout_psnr_db"] == pytest.approx(np.mean([v["heldout_psnr_db"] for v in m["views"].values()]))
    assert m["fit_seconds"]["ours"] == 12.5 and m["fit_seconds"]["baseline_ward"] == 12.5
    assert "peak" in m["normalisation"]
    assert len(list((tmp_path / "images").glob("*.png"))) == 4
    # the scores that do not hide faults (issue 13 item 4): finite, beside today's, for both models
    for v in m["views"].values():
        for prefix in ("heldout_", "baseline_ward_"):
            for key in TRUSTED_KEYS:
                assert np.isfinite(v[prefix + key]), prefix + key
        assert v["specular_pixels"] > 0.5 * v["sample_pixels"]        # every point of this scene is analytic
        assert v["heldout_rel_l2"] < 0.006 and v["heldout_specular_rel_l2"] < 0.012   # measured <= 0.0028, 0.0060
        assert v["baseline_ward_rel_l2"] > 5 * v["heldout_rel_l2"]
        assert v["baseline_ward_specular_rel_l2"] > v["baseline_ward_rel_l2"]       # the lobe is where it fails
        assert v["heldout_frame_psnr_worst_db"] <= v["heldout_frame_psnr_median_db"]
    for key in TRUSTED_KEYS:
        assert m["heldout_" + key] == pytest.approx(np.mean([v["heldout_" + key] for v in m["views"].values()]))
    assert "heldout_rel_l2" in m["normalisation"] and "that frame's largest" in m["normalisation"]


TRUSTED_KEYS = ("rel_l2", "specular_rel_l2", "frame_psnr_median_db", "frame_psnr_worst_db")


def test_relative_l2_against_hand_computed_values():
    from facetsynth.evaluation.metrics import relative_l2
    truth = np.zeros((2, 2, 2, 3))
    truth[0, 0, 0] = [3.0, 0.0, 0.0]
    truth[1, 1, 1] = [0.0, 4.0, 0.0]
    pred = truth.copy()
    pred[0, 0, 0, 0] = 2.0                       # error 1 where truth is 3
    pred[1, 0, 1, 2] = 1.0                       # error 1 on a pixel left out by the mask below
    assert relative_l2(pred, truth) == pytest.approx(np.sqrt(2 / 25))
    mask = np.array([[True, False], [False, True]])
    assert relative_l2(pred, truth, mask) == pytest.approx(np.sqrt(1 / 25))
    # the specular part: a reference (the diffuse truth) subtracted from both
    reference = np.full_like(truth, 0.5)
    # (truth - 0.5)^2 summed over the two masked pixels, two frames, three channels:
    # frame 0: [2.5, -.5, -.5] -> 6.75 and 0.75; frame 1: 0.75 and [-.5, 3.5, -.5] -> 12.75; total 21
    assert relative_l2(pred, truth, mask, reference) == pytest.approx(np.sqrt(1 / 21))
    assert relative_l2(truth, truth, mask) == 0.0
    # nothing to be relative to: empty mask, zero truth -> NaN, and the stage writes None, never NaN
    assert np.isnan(relative_l2(pred, truth, np.zeros((2, 2), bool)))
    assert np.isnan(relative_l2(pred, np.zeros_like(truth)))
    assert relative_l2(np.zeros_like(truth), np.zeros_like(truth)) == 0.0


def test_frame_psnr_against_hand_computed_values():
    from facetsynth.evaluation.metrics import finite_or_none, frame_psnr
    truth = np.zeros((4, 1, 2, 3))
    truth[0, 0, 0] = 2.0                          # peak 2
    truth[1, 0, 1] = 0.5                          # peak 0.5: its own peak, not the view's
    truth[3, 0, 0] = 1.0
    pred = truth.copy()
    pred[0, 0, 1, 0] = 0.2                        # mse = 0.04 / 6
    pred[1] += 0.05                               # mse = 0.0025
    psnr = frame_psnr(truth, pred)
    assert psnr[0] == pytest.approx(20 * np.log10(2 / np.sqrt(0.04 / 6)))
    assert psnr[1] == pytest.approx(20 * np.log10(0.5 / 0.05))
    assert np.isnan(psnr[2])                      # no light on the sample: no score
    assert psnr[3] == 100.0                       # exact: capped
    masked = frame_psnr(truth, pred, np.array([[True, False]]))
    assert masked[0] == 100.0 and np.isnan(masked[1])          # frame 1's light falls outside the mask
    assert np.isnan(frame_psnr(truth, pred, np.zeros((1, 2), bool))).all()
    assert finite_or_none(np.nan) is None and finite_or_none(np.inf) is None and finite_or_none(2) == 2.0
    # the stage's summary: median and worst over the lit frames only, None when no frame is lit
    scores = validate.trusted_scores(truth, pred, np.ones((1, 2), bool))
    lit = psnr[[0, 1, 3]]
    assert scores["heldout_frame_psnr_median_db"] == pytest.approx(np.median(lit))
    assert scores["heldout_frame_psnr_worst_db"] == pytest.approx(lit.min())
    dark = validate.trusted_scores(np.zeros_like(truth), pred, np.ones((1, 2), bool))
    assert dark["heldout_frame_psnr_median_db"] is None and dark["heldout_rel_l2"] is None
    assert dark["heldout_specular_rel_l2"] is None


def test_spread_about_mean_against_hand_computed_values():
    from facetsynth.evaluation.metrics import spread_about_mean
    tables = np.array([[1.0, 3.0], [3.0, 1.0]])                   # mean [2, 2]
    weight = np.array([1.0, 3.0])
    expected = np.sqrt((1 * 1 + 3 * 1) / (1 * 4 + 3 * 4))
    np.testing.assert_allclose(spread_about_mean(tables, weight), [expected, expected])
    np.testing.assert_allclose(spread_about_mean(np.ones((5, 3, 4)), np.ones((3, 4))), 0.0)
    assert spread_about_mean(np.zeros((0, 2)), weight).shape == (0,)
    assert np.isnan(spread_about_mean(np.zeros((2, 2)), weight)).all()


def test_diffuse_truth_is_the_rigs_render_of_the_diffuse_term(repo, tmp_path):
    """With ks = 0 the truth is its diffuse term: diffuse_truth must equal the virtual rig's own render."""
    from facetsynth.models.render import radiance
    scene = Scene.from_dict({"name": "matte", "size": [0.1, 0.1], "regions": [
        {"name": "a", "where": {"all": True}, "kd": [0.3, 0.2, 0.1], "ks": [0.0, 0.0, 0.0], "eta": 1.5,
         "alpha": [0.2, 0.2], "frame": {"angle_deg": 0}}]})
    rig = validate.heldout_rig(VirtualRig.load(repo / "tests/data/rig-tiny.yaml"), 50.9, -15.3, 8, 2)
    camera = rig.camera(0.1)
    lights = np.array([[0.0, 0.05, 0.04], [0.03, 0.1, 0.04]])
    intensity = np.array([[0.3, 0.3, 0.3], [0.2, 0.3, 0.4]])
    for s in (1, 2):
        diffuse, analytic, _ = validate.diffuse_truth(scene, camera, lights, intensity, supersample=s)
        xy = camera.pixel_plane_points(s)
        on = scene.on_sample(xy)
        maps = scene.parameters(xy[on])
        points = np.concatenate([xy[on], np.zeros((on.sum(), 1))], -1)
        for q in range(2):
            image = np.zeros(on.shape + (3,))
            image[on] = radiance(points, maps.rho, lights[q], intensity[q], camera.centre)
            expected = image.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3))
            np.testing.assert_allclose(diffuse[q], expected, rtol=1e-5, atol=1e-9)
        assert analytic.sum() > 0 and (analytic <= on.reshape(camera.height, s, camera.width, s).all(axis=(1, 3))).all()


def test_region_scores_say_which_material_holds_the_error(repo):
    """Two halves: the region map follows the scene (pixels straddling the edge are -1), and a prediction that
    is exact on one half and twice the truth on the other scores 0 and 1 there."""
    half = {"kd": [0.3, 0.2, 0.1], "ks": [0.0, 0.0, 0.0], "eta": 1.5, "alpha": [0.2, 0.2], "frame": {"angle_deg": 0}}
    scene = Scene.from_dict({"name": "halves", "size": [0.1, 0.1], "regions": [
        {"name": "left", "where": {"rect": {"x": [-0.05, 0.0], "y": [-0.05, 0.05]}}, **half},
        {"name": "right", "where": {"rect": {"x": [0.0, 0.05], "y": [-0.05, 0.05]}}, **half}]})
    camera = validate.heldout_rig(VirtualRig.load(repo / "tests/data/rig-tiny.yaml"), 30.0, 10.0, 8, 2).camera(0.1)
    lights, intensity = np.array([[0.0, 0.05, 0.04]]), np.array([[0.3, 0.3, 0.3]])
    diffuse, analytic, region = validate.diffuse_truth(scene, camera, lights, intensity, supersample=2)
    x = camera.pixel_plane_points(1)[..., 0]
    on = analytic & (diffuse[0].max(axis=-1) > 0)
    assert (region[on & (x < -0.002)] == 0).all() and (region[on & (x > 0.002)] == 1).all()
    assert (region[~scene.on_sample(camera.pixel_plane_points(1))] == -1).all()
    assert (region[on] == -1).sum() > 0            # the sub-pixels of the pixels on the edge disagree
    prediction = np.where((region == 1)[None, ..., None], 2.0 * diffuse, diffuse)
    scores = validate.region_scores(diffuse.astype(float), prediction.astype(float), on, region, ["left", "right"])
    assert scores == pytest.approx({"left": 0.0, "right": 1.0}, abs=1e-6)


def test_new_rules_build_their_jobs_and_a_bad_config_is_refused(repo, tmp_path):
    """Dry runs: the baseline and held-out captures need only existing stages; params/validate are wired."""
    from test_workflow import make_workdir, snakemake
    wd = make_workdir(repo, tmp_path / "wf", "demo\tvirtual\tresources/scenes/demo.yaml\t\n")
    done = snakemake(wd, "-n", "results/demo/baseline/metrics.json", "results/demo/validate/heldout/paper")
    assert done.returncode == 0, done.stderr[-2000:]
    for rule in ("baseline_ward", "heldout_capture", "capture", "separate", "resample"):
        assert f"rule {rule}:" in done.stdout + done.stderr
    (wd / "bad.yaml").write_text("validate:\n  views: [{name: paper, theta_deg: 95, phi_deg: 0}]\n"
                                 "  led_every: 4\n  position_every: 4\n  images_per_view: 2\n")
    bad = snakemake(wd, "-n", "--configfile", "config/config.yaml", "bad.yaml")
    assert bad.returncode != 0 and "theta_deg" in bad.stdout + bad.stderr


@pytest.mark.parametrize("calibration_error", [False, True])
def test_diffuse_truth_reproduces_a_matte_heldout_capture(repo, tmp_path, calibration_error):
    """A matte scene (ks = 0) is all diffuse: the stage's diffuse truth must be the held-out truth itself, also
    when the rig's true camera pose and LEDs differ from the calibration its manifest records."""
    import yaml

    from facetsynth.io.fileio import read_rgb
    desc = yaml.safe_load((repo / "tests/data/rig-tiny.yaml").read_text())
    if calibration_error:
        desc["calibration_error"] = {"led_intensity": 0.05, "led_position_m": 0.002, "camera_rotation_deg": 0.3,
                                     "seed": 2}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(desc))
    (tmp_path / "matte.yaml").write_text(
        "name: matte\nsize: [0.1, 0.1]\nregions:\n  - name: a\n    where: {all: true}\n"
        "    kd: [0.3, 0.2, 0.1]\n    ks: [0.0, 0.0, 0.0]\n    eta: 1.5\n    alpha: [0.2, 0.2]\n"
        "    frame: {angle_deg: 0}\n")
    heldout_capture.run(heldout_capture.Inputs(tmp_path / "matte.yaml", tmp_path / "rig.yaml"),
                        heldout_capture.Outputs(tmp_path / "held"),
                        heldout_capture.Settings(40.0, 10.0, led_every=4, position_every=4))
    m = manifest.load(tmp_path / "held", check_files=False)
    assert ("calibration" in m["truth"]) == calibration_error
    truth = np.stack([read_rgb(f["truth"]["radiance"]) for f in m["frames"]]).astype(float)
    diffuse, analytic, _ = validate.diffuse_truth(Scene.load(m["truth"]["scene"]), *validate.true_rig(m), 1)
    inside = analytic & (truth.max(axis=(0, 3)) > 0)
    assert inside.sum() > 1000
    np.testing.assert_allclose(diffuse[:, inside], truth[:, inside], rtol=2e-3)       # truth stored as half floats
    nominal, _, _ = validate.diffuse_truth(Scene.load(m["truth"]["scene"]), manifest.camera(m),
                                        manifest.lights(m["frames"]), manifest.light_intensities(m["frames"]), 1)
    if calibration_error:      # the nominal rig would leave a residual "specular" part where there is none
        assert np.abs(nominal[:, inside] - truth[:, inside]).max() > 0.01 * truth[:, inside].max()
