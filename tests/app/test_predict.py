"""`facetsynth predict`: frames of a capture manifest rendered from a fitted SVBRDF (DESIGN.md sec. 4)."""

import json

import numpy as np
import pytest

from facetsynth.app import cli
from facetsynth.capture import manifest
from facetsynth.io.fileio import read_rgb
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.evaluation.metrics import image_scores
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.app.predict import predict
from facetsynth.truth.scene import Scene
from facetsynth.models.svbrdf import tabulate_truth
from facetsynth.truth.virtual_rig import VirtualRig, capture

SCENE = """\
name: predict-test
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: left
    where: {rect: {x: [-0.05, 0.0], y: [-0.05, 0.05]}}
    kd: [0.25, 0.10, 0.08]
    ks: [0.6, 0.5, 0.4]
    eta: 1.4
    alpha: [0.2, 0.35]
    frame: {angle_deg: 30}
  - name: right
    where: {rect: {x: [0.0, 0.05], y: [-0.05, 0.05]}}
    kd: [0.08, 0.20, 0.10]
    ks: [0.5, 0.5, 0.5]
    eta: 2.4
    alpha: [0.3, 0.3]
    frame: {angle_deg: 0}
"""


@pytest.fixture(scope="module")
def captured(tmp_path_factory, repo):
    """A tiny noise-free virtual capture and the SVBRDF built from its truth (true NDFs tabulated)."""
    root = tmp_path_factory.mktemp("predict")
    (root / "scene.yaml").write_text(SCENE)
    rig = VirtualRig.load(repo / "tests/data/rig-tiny.yaml")
    capture(root / "scene.yaml", rig, root / "capture", seed=1, noise=False)
    plane = PlaneGrid(0.1, 0.1, 64, 64)
    maps = Scene.load(root / "scene.yaml").parameters(plane.points3d().reshape(-1, 3)[:, :2])
    tabulate_truth(maps, DirectionGrid(32, 128), plane).save(root / "svbrdf")
    return root


def test_predict_on_the_captures_own_manifest_reproduces_the_true_radiance(captured):
    """Consistency: with the true parameters (NDF tabulated on 32 x 128), predict is the virtual rig's renderer."""
    out = predict(captured / "svbrdf", captured / "capture" / "manifest.json", captured / "pred", progress=False)
    m = manifest.load(captured / "capture" / "manifest.json")
    assert len(out["frames"]) == len(m["frames"]) == 30
    pred = np.stack([read_rgb(captured / "pred" / f["exposures"][0]["file"]) for f in out["frames"]])
    truth = np.stack([read_rgb(f["truth"]["radiance"]) for f in m["frames"]])
    mask = np.asarray(truth.max(axis=(0, 3)) > 0)
    scores = image_scores(truth, pred, mask)
    assert scores["psnr_db"] > 45          # measured 49.7 dB (NDF tabulation; truth stored as half floats)
    assert scores["ssim"] > 0.999          # measured 0.99977
    lit = truth > 1e-3 * truth.max()
    assert np.median(np.abs(pred - truth)[lit] / truth[lit]) < 0.002   # measured 6.4e-4
    reloaded = manifest.load(captured / "pred" / "manifest.json")     # the prediction is itself a capture
    assert reloaded["saturation"] is None and reloaded["frames"][0]["exposures"][0]["time"] == 1.0


def test_cli_predict_writes_one_hdr_exr_per_frame(captured, capsys):
    assert cli.main(["predict", str(captured / "svbrdf"), str(captured / "capture"), str(captured / "cli")]) == 0
    assert len(list((captured / "cli" / "frames").glob("*.exr"))) == 30
    assert "30 predicted HDR frame(s)" in capsys.readouterr().out


def test_predict_validates_its_manifest_and_fails_clearly(captured, tmp_path, capsys):
    good = json.loads((captured / "capture" / "manifest.json").read_text())
    bad = dict(good, camera={k: v for k, v in good["camera"].items() if k != "K"})
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    rc = cli.main(["predict", str(captured / "svbrdf"), str(tmp_path / "bad.json"), str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 1 and "bad.json" in err and "camera" in err and "'K'" in err
    assert not (tmp_path / "out").exists()                             # nothing written on a bad manifest
    (tmp_path / "broken.json").write_text("{not json")
    assert cli.main(["predict", str(captured / "svbrdf"), str(tmp_path / "broken.json"), str(tmp_path / "o")]) == 1
    assert "broken.json" in capsys.readouterr().err
    distorted = dict(good, camera=dict(good["camera"], distortion=[0.1, 0, 0, 0, 0]))
    (tmp_path / "distorted.json").write_text(json.dumps(distorted))
    assert cli.main(["predict", str(captured / "svbrdf"), str(tmp_path / "distorted.json"), str(tmp_path / "o")]) == 1
    assert "distortion" in capsys.readouterr().err
    assert cli.main(["predict", str(tmp_path / "no-model"), str(captured / "capture"), str(tmp_path / "o")]) == 1
    assert "model.json" in capsys.readouterr().err


def test_predict_again_into_its_own_folder_keeps_only_the_frames_its_manifest_lists(captured, tmp_path):
    """A second prediction of fewer frames into predict's own folder leaves no frame of the first behind (its
    manifest lists only the new ones); a foreign folder written with --force keeps the user's files."""
    out = tmp_path / "pred"
    predict(captured / "svbrdf", captured / "capture", out, frames=[0, 1, 2], progress=False)
    predict(captured / "svbrdf", captured / "capture", out, frames=[1], progress=False)
    assert sorted(p.name for p in (out / "frames").glob("*.exr")) == ["0001.exr"]
    assert [f["source_frame"] for f in manifest.load(out)["frames"]] == [1]
    foreign = tmp_path / "mine"
    (foreign / "frames").mkdir(parents=True)
    (foreign / "frames" / "0007.exr").write_bytes(b"the user's")
    predict(captured / "svbrdf", captured / "capture", foreign, frames=[1], progress=False, force=True)
    assert (foreign / "frames" / "0007.exr").read_bytes() == b"the user's"
