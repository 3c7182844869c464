"""Degenerate captures never become a silent model (issue 15, part 3): the first stage that can tell stops
with an error naming the capture, or finishes with a WARNING and ``degenerate`` in its metrics
(docs/decisions.md, "Degenerate captures")."""

import json
import logging
import shutil

import numpy as np
import pytest

from conftest import hdr_outputs, rectify_into

from facetsynth.io.errors import InputError
from facetsynth.io.fileio import read_rgb, write_exr
from facetsynth.stages import hdr, separate
from facetsynth.truth.virtual_rig import VirtualRig, capture


@pytest.fixture(scope="module")
def card(repo, tmp_path_factory):
    """The card on the tiny rig (30 lights on a 6 x 5 grid, 3 exposures each), with sensor noise."""
    return capture(repo / "resources/scenes/card.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"),
                   tmp_path_factory.mktemp("card") / "capture", seed=2, noise=True)


def variant(card, folder, frames=None, darken=()):
    """A copy of the card's capture with only ``frames`` (indices) and the frames ``darken`` all black."""
    shutil.copytree(card, folder)
    data = json.loads((folder / "manifest.json").read_text())
    for q in darken:
        for exposure in data["frames"][q]["exposures"]:
            image = read_rgb(folder / exposure["file"])
            write_exr(folder / exposure["file"], {"RGB": np.zeros_like(image)}, precision="float16")
    if frames is not None:
        data["frames"] = [data["frames"][q] for q in frames]
    (folder / "manifest.json").write_text(json.dumps(data))
    return folder


def run_hdr(folder):
    out = folder.parent / "hdr"
    hdr.run(hdr.Inputs(capture=folder), hdr_outputs(out))
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("frames, lights", [([0], 1), ([0, 1, 2, 3], 4), ([0, 7, 14, 21, 28], 5)])
def test_lights_that_span_no_area_are_an_error_before_any_merge(card, tmp_path, frames, lights):
    """One frame, the first row of four lights, and five lights on the grid's diagonal: the lights cannot be
    triangulated (resample interpolates over that triangulation), so hdr stops, naming the manifest."""
    folder = variant(card, tmp_path / "capture", frames)
    with pytest.raises(InputError) as err:
        run_hdr(folder)
    assert str(err.value) == (f"{folder / 'manifest.json'}: too few lights for the method: the {lights} light(s) do "
                              "not span an area of their plane (at least 3 lights, not all on one line, are needed); "
                              "capture under lights spread over a plane above the sample (the paper: 20 x 24 = 480)")
    assert not (tmp_path / "hdr").exists()


def test_three_lights_around_the_sample_are_enough_for_hdr(card, tmp_path):
    metrics = run_hdr(variant(card, tmp_path / "capture", [0, 5, 27]))
    assert metrics["frames"] == 3 and metrics["dark_frames"] == 0 and "degenerate" not in metrics


def test_all_dark_frames_are_an_error_and_publish_nothing(card, tmp_path):
    folder = variant(card, tmp_path / "capture", darken=range(30))
    with pytest.raises(InputError, match=r"manifest\.json: all 30 frames are dark \(no pixel above the sensor's "
                                         r"noise floor, 0\.00[0-9]+\): nothing was measured"):
        run_hdr(folder)
    assert not (tmp_path / "hdr/frames").exists() and not (tmp_path / "hdr/metrics.json").exists()


def test_some_dark_frames_finish_with_a_warning_and_degenerate(card, tmp_path, caplog):
    folder = variant(card, tmp_path / "capture", darken=(4, 17))
    with caplog.at_level(logging.WARNING, logger="facetsynth.stages.hdr"):
        metrics = run_hdr(folder)
    assert metrics["dark_frames"] == 2
    assert metrics["degenerate"].startswith(f"2 of 30 frames are dark (no pixel above the noise floor; the first: "
                                            f"frame 4, {folder / 'frames/0004_e0.exr'})")
    assert [r.getMessage() for r in caplog.records] == ["DEGENERATE: " + metrics["degenerate"]]


def test_a_noisy_matte_sample_is_flagged_diffuse_only(repo, tmp_path):
    """ks = 0 with sensor noise: the specular residual is noise (0.03-0.07 of the diffuse level), below the
    0.5 a highlight needs, at almost every point; separate says the capture supports only kd. The card, glossy,
    is not flagged (73 % of its points show a highlight)."""
    scene = (repo / "resources/scenes/uniform.yaml").read_text().replace("ks: [0.8, 0.8, 0.8]", "ks: [0, 0, 0]")
    (tmp_path / "matte.yaml").write_text(scene)
    rig = VirtualRig.load(repo / "tests/data/rig-tiny.yaml")
    fractions = {}
    for name, path in (("matte", tmp_path / "matte.yaml"), ("card", repo / "resources/scenes/card.yaml")):
        root = tmp_path / name
        capture(path, rig, root / "capture", seed=2, noise=True)
        run_hdr(root / "capture")
        rectify_into(root / "hdr/manifest.json", root / "rectify", 32)
        separate.run(separate.Inputs(geometry=root / "rectify/geometry.json"),
                     separate.Outputs(kd=root / "kd.exr", specular=root / "specular.npy", valid=root / "valid.npy",
                                      metrics=root / "separate.json"), separate.Settings(heldout_every=0))
        fractions[name] = json.loads((root / "separate.json").read_text())
    assert fractions["matte"]["specular_signal_fraction"] < 0.01                 # measured 0.002 at 64 x 64
    assert fractions["matte"]["degenerate"].startswith("no specular signal: ")
    assert fractions["card"]["specular_signal_fraction"] > 0.5 and "degenerate" not in fractions["card"]
