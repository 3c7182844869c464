"""Issue 4 end to end: cluster and synthesize on the wallpaper, satin and brushed scenes (noise-free).

Exact search (the ANN path is covered in tests/fit/test_synthesis.py; pynndescent
compiles for about 24 s in every new process). The recorded ANN figures at
full size are in docs/decisions.md.
"""

import json
import shutil

import numpy as np
import pytest

from facetsynth.io.tables import SupportTable
from test_workflow import NOISE_FREE, make_workdir, metrics, snakemake

# five samples through capture .. synthesize (5 min on 2 cores): with the whole-workflow tests in make test-scenes,
# so that make test stays near 10 min
pytestmark = pytest.mark.scenes

SCENES = ("wallpaper", "satin", "brushed")
ROTATIONS = {"brushed-turned-r60": 60, "brushed-turned-r120": 120}   # further captures of "brushed-turned"
OVERRIDES = """virtual:
  noise: false
resample:
  n_theta_range: [32, 32]     # the grid these figures were recorded on (the adaptive grid: test_sharpness, demo)
synthesize:
  search: exact
  compare: false
"""


@pytest.fixture(scope="module")
def scenes_run(repo, tmp_path_factory):
    """wallpaper and satin on the demo rig (1360 lights); brushed on a sparser rig (340 lights), which is
    enough to show that one frame cannot be completed from rotations, and that captures turned on the rig
    complete it."""
    rigs = {"brushed": "rig/descriptions/sparse.yaml"}
    sheet = "".join(f"{s}\tvirtual\tresources/scenes/{s}.yaml\t{rigs.get(s, '')}\t\t\n" for s in SCENES)
    sheet += "brushed-turned\tvirtual\tresources/scenes/brushed.yaml\trig/descriptions/sparse.yaml\t\t\n"
    sheet += "".join(f"{name}\tvirtual\tresources/scenes/brushed.yaml\trig/descriptions/sparse.yaml\tbrushed-turned"
                     f"\t{deg}\n" for name, deg in ROTATIONS.items())
    workdir = make_workdir(repo, tmp_path_factory.mktemp("synth"), "")
    (workdir / "config/samples.tsv").write_text("sample\tsource\tpath\trig\trotation_of\trotation_deg\n" + sheet)
    shutil.copy(repo / "tests/data/rig-sparse.yaml", workdir / "rig/descriptions/sparse.yaml")
    (workdir / "noise-free.yaml").write_text(OVERRIDES)
    targets = ["results/wallpaper/validate/metrics.json", "results/satin/synthesize/metrics.json",
               "results/brushed/synthesize/metrics.json", "results/brushed-turned/synthesize/metrics.json"]
    done = snakemake(workdir, *targets, *NOISE_FREE)   # targets first: --configfile takes every word after it
    assert done.returncode == 0, done.stderr[-3000:]
    return workdir


@pytest.mark.parametrize("sample", ["wallpaper", "satin"])
def test_synthesis_meets_the_issue_4_targets(scenes_run, sample):
    m = metrics(scenes_run, sample, "synthesize")
    assert m["ground_truth"] and m["search"] == "exact" and m["scored_points"] > 900
    # issue 4's target was 0.25 (measured then: wallpaper 0.243, satin 0.213, 41 representatives, push-pull beyond
    # reach); with the representatives chosen from the data and the last reachable ring held (issue 7):
    # wallpaper 0.269 (32 representatives); 0.281 since kd averages the lowest 3 % of the samples (this capture
    # is noise-free: the average only takes in more of the broad lobes' tails); docs/decisions.md
    assert m["ndf_rel_l2_median"] <= 0.30
    assert m["coverage_before_fill"] >= 0.95
    assert m["insufficient_rotation_diversity"] is False
    assert (scenes_run / f"results/{sample}/benchmarks/synthesize.tsv").read_text().startswith("s\th:m:s\tmax_rss")


@pytest.mark.parametrize("sample", SCENES)
def test_output_contract(scenes_run, sample):
    """The names and shapes issue 5 builds on."""
    res = scenes_run / "results" / sample
    labels = np.load(res / "cluster/labels.npy")
    reps = np.load(res / "cluster/representatives.npy")
    nbr = np.load(res / "cluster/neighbours.npy")
    wts = np.load(res / "cluster/weights.npy")
    ndf = np.load(res / "synthesize/ndf.npy")
    grid = json.loads((res / "synthesize/grid.json").read_text())
    geometry = json.loads((res / "rectify/geometry.json").read_text())
    visible = np.asarray(geometry["visible"], bool).ravel()
    p = visible.size
    assert labels.shape == (p,) and labels.dtype == np.int32 and np.all(labels[~visible] == -1)
    assert reps.dtype == np.int64 and np.all(visible[reps]) and len(np.unique(reps)) == len(reps)
    assert np.all(labels[reps] == np.arange(len(reps)))
    assert nbr.shape == (p, 16) and nbr.dtype == np.int32 and nbr.min() >= 0 and nbr.max() < len(reps)
    assert wts.shape == (p, 16) and wts.dtype == np.float32
    np.testing.assert_allclose(wts[visible].sum(axis=1), 1.0, atol=1e-5)
    assert ndf.shape == (len(reps), grid["n_theta"], grid["n_phi"]) and ndf.dtype == np.float32
    assert np.isfinite(ndf).all() and (ndf >= 0).all()
    partial = SupportTable(res / "partial_ndf/ndf").rows("ndf")[reps]
    assert np.median(ndf.max(axis=(1, 2)) / partial.max(axis=(1, 2))) == pytest.approx(1.0, rel=0.2)  # same scale


def test_wallpaper_held_out_views_beat_the_per_point_ward_baseline(scenes_run):
    """Issue 5 on wallpaper: >= 30 dB on views never fitted, and better than per-point anisotropic Ward (Fig. 10)."""
    m = metrics(scenes_run, "wallpaper", "validate")
    assert m["heldout_psnr_db"] >= 30.0 and m["heldout_psnr_db"] > m["baseline_ward_psnr_db"]


def test_brushed_reports_insufficient_rotation_diversity(scenes_run):
    """One lobe axis everywhere (measured concentration 0.95; with the rotations 0.14, wallpaper and satin
    0.17-0.32 with noise): flagged, and most representatives stall."""
    m = metrics(scenes_run, "brushed", "synthesize")
    assert m["insufficient_rotation_diversity"] is True and m["orientation_concentration"] >= 0.9
    assert m["stalled_representatives"] >= 0.5 * m["representatives"] and m["stalled_majority"] is True
    assert m["coverage_before_fill"] < 0.8
    log = (scenes_run / "results/brushed/logs/synthesize.log").read_text()
    assert "INSUFFICIENT ROTATION DIVERSITY" in log
    for other in ("brushed-turned", "wallpaper", "satin"):
        assert metrics(scenes_run, other, "synthesize")["orientation_concentration"] <= 0.5


def test_captures_of_further_rotations_complete_the_ndf(scenes_run):
    """Paper 002 sec. 4: brushed captured again turned by 60 and 120 deg (sheet rows with rotation_of) is one
    sample whose exemplars come from all three captures; the rotated exemplars complete its NDF.
    Measured 2026-12-01 (340-light rig, noise-free, 32 x 128, 64 representatives, alpha 0.07 / 0.30):
    alone 53 of 64 representatives stall, coverage before fill 0.697, NDF error 0.914; with the rotations none
    stalls, coverage 0.990, NDF error 0.360 (the partial NDFs' own error is 0.439)."""
    alone = metrics(scenes_run, "brushed", "synthesize")
    turned = metrics(scenes_run, "brushed-turned", "synthesize")
    assert alone["rotation_captures"] == 0 and turned["rotation_captures"] == 2
    assert 0.7 * alone["exemplars"] <= turned["exemplars"] <= 4096    # three captures share the budget (3 x 1024)
    assert turned["insufficient_rotation_diversity"] is False and turned["stalled_representatives"] <= 4
    assert turned["coverage_before_fill"] >= 0.95 > alone["coverage_before_fill"] + 0.2
    assert turned["ndf_rel_l2_median"] <= 0.42 and alone["ndf_rel_l2_median"] >= 0.8
    partial = metrics(scenes_run, "brushed-turned", "partial_ndf")["ndf_rel_l2_median"]
    assert turned["ndf_rel_l2_median"] < partial    # completed from real rotated slices: better than one slice
    assert not (scenes_run / "results/brushed-turned-r60/svbrdf").exists()   # rotations get no model of their own
