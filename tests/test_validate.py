"""Held-out validation (paper 002 sec. 6) and the per-point Ward baseline (Fig. 10, Goldman et al. 2005)."""

import json

import numpy as np
import pytest

from facetsynth import manifest
from facetsynth.grid import DirectionGrid
from facetsynth.plane import PlaneGrid
from facetsynth.scene import Scene
from facetsynth.stages import validate
from facetsynth.svbrdf import tabulate_truth
from facetsynth.virtual_rig import VirtualRig
from facetsynth.ward import WardSVBRDF, fit_point, ward_specular

from test_predict import SCENE


def test_ward_lm_recovers_an_anisotropic_ward_lobe():
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(600, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = np.broadcast_to([0.0, -0.866, 0.5], wi.shape)
    truth = 0.7 * ward_specular(wi, wo, 0.12, 0.3, 1.1)
    fit = fit_point(truth, wi, wo)
    assert fit.ok
    assert fit.ks == pytest.approx(0.7, rel=1e-3)
    assert (fit.alpha_x, fit.alpha_y) == pytest.approx((0.12, 0.3), rel=1e-3)
    assert fit.phi == pytest.approx(1.1, abs=1e-3)
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
        validate.heldout_capture(tmp_path / "scene.yaml", repo / "tests/data/rig-tiny.yaml",
                                 tmp_path / "heldout" / name, theta, phi, led_every=2, position_every=2)
    plane = PlaneGrid(0.1, 0.1, 64, 64)
    maps = Scene.load(tmp_path / "scene.yaml").parameters(plane.points3d().reshape(-1, 3)[:, :2])
    tabulate_truth(maps, DirectionGrid(32, 128), plane).save(tmp_path / "svbrdf")
    # a deliberately poor "baseline": the right kd, an isotropic lobe of the wrong width
    p = plane.rows * plane.cols
    WardSVBRDF(plane, maps.kd, maps.ks, np.full(p, 0.5), np.full(p, 0.5), np.zeros(p)).save(tmp_path / "ward")
    (tmp_path / "bench.tsv").write_text("s\th:m:s\tmax_rss\n12.5\t0:00:12\t100\n")
    validate.run(tmp_path / "svbrdf", tmp_path / "ward", {v: tmp_path / "heldout" / v for v in views},
                 tmp_path / "pred", tmp_path / "metrics.json", tmp_path / "images",
                 fit_benchmarks=[tmp_path / "bench.tsv", tmp_path / "missing.tsv"], ward_benchmark=tmp_path / "bench.tsv")
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert set(m["views"]) == set(views)
    for v in m["views"].values():
        assert v["heldout_psnr_db"] > 45 and v["heldout_ssim"] > 0.999       # true parameters: tabulation only
        assert v["baseline_ward_psnr_db"] < v["heldout_psnr_db"] - 10
        assert v["frames"] == len(manifest.load(tmp_path / "heldout" / "paper")["frames"])
    assert m["heldout_psnr_db"] == pytest.approx(np.mean([v["heldout_psnr_db"] for v in m["views"].values()]))
    assert m["fit_seconds"]["ours"] == 12.5 and m["fit_seconds"]["baseline_ward"] == 12.5
    assert "peak" in m["normalisation"]
    assert len(list((tmp_path / "images").glob("*.png"))) == 4


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
