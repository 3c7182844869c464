"""Issue 7 part 3, a model only as complex as the scene requires (docs/decisions.md, "Adaptive model size").

(A) isotropic representatives are completed by azimuthal symmetry, without a search;
(B) the number of representatives follows the diversity of the partial NDFs.
"""

import json

import numpy as np
import pytest

from facetsynth.fit import cluster
from facetsynth.models import microfacet
from facetsynth.fit import synthesis
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.fit.partial_ndf import fresnel_cosine
from test_synthesis import rel_l2, single_view_domain
from test_workflow import make_workdir, metrics, snakemake

GRID = DirectionGrid(16, 64)
THRESHOLD = 0.13     # config.yaml synthesize.isotropic_threshold


def ggx(alpha, frame=0.0, grid=GRID):
    h = grid.directions.reshape(1, -1, 3)
    return microfacet.ndf(h, alpha[0], alpha[1], np.array([[frame]])).reshape(grid.shape)


def on_domain(d, grid=GRID):
    mask = single_view_domain(grid)
    return np.where(mask, d, 0.0), mask.astype(float)


# ---------------------------------------------------------------------------- (A) isotropy
def test_isotropy_statistic_on_analytic_ggx():
    d, w = on_domain(ggx((0.2, 0.2)))
    assert synthesis.anisotropy(d, w, GRID) < 1e-6 < THRESHOLD
    for frame in (0.0, 0.4, 1.1, 2.0):
        d, w = on_domain(ggx((0.1, 0.3), frame))
        assert synthesis.anisotropy(d, w, GRID) > 2 * THRESHOLD
    assert np.isinf(synthesis.anisotropy(np.zeros(GRID.shape), w, GRID))       # no data: never isotropic


def test_isotropic_completion_recovers_the_ndf_and_carries_the_fresnel_cosine():
    truth = ggx((0.2, 0.2))
    d, w = on_domain(truth)
    target = synthesis.hemisphere_target(w > 0, GRID)
    view = np.array([np.sin(0.6), 0.0, np.cos(0.6)])
    c = synthesis.complete_isotropic(d, w, GRID, target, view=view)
    assert c.iterations == 0 and not c.merges and 0.5 < c.coverage <= 1.0
    used = np.mean(w > 0, axis=1) >= 1 / 3                                   # rings the domain covers by a third
    np.testing.assert_allclose(c.ndf[used], truth[used], rtol=1e-9)         # at every azimuth
    assert np.all(np.ptp(c.ndf, axis=1) < 1e-9 * c.ndf.max())                # a ring profile everywhere
    assert np.all(np.diff(c.ndf[:, 0])[~used[1:]] <= 0)                      # extended, non-increasing
    assert rel_l2(c.ndf, truth) < 1e-6                                       # GGX-shaped beyond: exact
    assert np.all(np.ptp(c.fresnel_cosine, axis=1) < 1e-9)
    cos = fresnel_cosine(view, GRID)
    ring = np.flatnonzero(used)[3]
    inside = w[ring] > 0
    assert c.fresnel_cosine[ring, 0] == pytest.approx(np.mean(cos[ring, inside]))   # equal W and dw on a ring


# ---------------------------------------------------------------------------- (B) number of representatives
def test_k_follows_the_number_of_distinct_ndf_shapes():
    """Three GGX shapes at a fixed frame, 200 points each with 5 % multiplicative noise: k = 3 on the ladder
    2, 3, 4, 6, ..., 64; two shapes: k = 2; one frame turned through 360 deg (eq. 15 is not rotation invariant):
    many representatives."""
    rng = np.random.default_rng(1)
    shapes = [ggx((0.1, 0.1)), ggx((0.1, 0.4), 0.3), ggx((0.35, 0.6), 1.2)]

    def feats(tables):
        d, w = np.array([on_domain(t)[0] for t in tables]), np.array([on_domain(t)[1] for t in tables])
        d = d * (1 + 0.05 * rng.standard_normal(d.shape))
        return cluster.features(d, w, GRID)

    three = feats([shapes[i % 3] for i in range(600)])
    assert cluster.choose_k(three, 2, 64, 0.08, subsample=600).k == 3
    two = feats([shapes[i % 2] for i in range(400)])
    assert cluster.choose_k(two, 2, 64, 0.08, subsample=400).k == 2
    turned = feats([ggx((0.1, 0.4), f) for f in np.linspace(0, 2 * np.pi, 400, endpoint=False)])
    choice = cluster.choose_k(turned, 2, 64, 0.08, subsample=400)
    assert choice.k >= 8 and choice.distortion[-1] <= 0.08 and choice.distortion == sorted(choice.distortion,
                                                                                             reverse=True)


# ---------------------------------------------------------------------------- the card scene end to end
@pytest.fixture(scope="module")
def card_run(repo, tmp_path_factory):
    """card (four isotropic quadrants) with the defaults — the demo rig, sensor noise, the grid chosen from the
    lobes (24 x 96 here), representatives from the data — up to synthesize, on all its lights: the figures
    below are synthesis's (holding out issue 29's 10 % raises the card's NDF error 0.261 -> 0.326: its broad
    lobes' partial NDFs thin out; docs/decisions.md "The fit reproduces what it saw")."""
    workdir = make_workdir(repo, tmp_path_factory.mktemp("card"), "card\tvirtual\tresources/scenes/card.yaml\t\n")
    done = snakemake(workdir, "results/card/synthesize/metrics.json", "--config",
                     "selfcheck={heldout_every: 0, relit_every: 8}")
    assert done.returncode == 0, done.stderr[-3000:]
    return workdir


def test_card_runs_no_synthesis_search_and_loses_nothing(card_run, tmp_path):
    """Every card material is isotropic (median statistic per material below the threshold), so no exemplar
    set is built and nothing is searched; completing by symmetry is better than the exact search on the same
    representatives (measured 2026-11-23: 4 materials at 0.099 / 0.038 / 0.044 / 0.044, 8 representatives,
    NDF error 0.147 by symmetry against 0.311 searched; 2026-12-02: 0.261)."""
    from facetsynth.stages import synthesize

    m = metrics(card_run, "card", "synthesize")
    assert m["isotropic_threshold"] == THRESHOLD and len(m["anisotropy"]) == m["representatives"]
    assert m["materials"] == 4 and max(m["material_anisotropy"]) < THRESHOLD
    assert m["search_skipped"] is True and m["exemplars"] == 0 and m["merges"] == 0
    assert m["isotropic_representatives"] == m["representatives"]
    assert "all complete by azimuthal symmetry, no exemplar search" in \
        (card_run / "results/card/logs/synthesize.log").read_text()
    res = card_run / "results/card"
    searched = tmp_path / "metrics.json"
    synthesize.run(synthesize.Inputs(geometry=res / "rectify/geometry.json", ndf=res / "partial_ndf/ndf",
                                     grid=res / "resample/grid.json", representatives=res / "cluster/representatives.npy",
                                     neighbours=res / "cluster/neighbours.npy", weights=res / "cluster/weights.npy",
                                     rep_ndf=res / "cluster/representative_ndf.npy",
                                     rep_confidence=res / "cluster/representative_confidence.npy"),
                   synthesize.Outputs(ndf=tmp_path / "ndf.npy", confidence=tmp_path / "confidence.npy",
                                      fresnel_cosine=tmp_path / "cosine.npy", grid=tmp_path / "grid.json",
                                      metrics=searched),
                   synthesize.Settings(isotropic_threshold=0.0))
    s = json.loads(searched.read_text())
    assert s["search_skipped"] is False and s["isotropic_representatives"] == 0 and s["merges"] > 0
    assert m["ndf_rel_l2_median"] <= s["ndf_rel_l2_median"] + 0.01
    # 0.174 with eq. 9's minimum, 0.261 since kd averages the lowest 3 % (separate.lowest): the broad lobes'
    # tails (alpha 0.3, 0.6) raise kd and thin the partial NDFs; held-out radiance unchanged (docs/decisions.md,
    # "Diffuse level under noise")
    assert m["ndf_rel_l2_median"] <= 0.28


def test_card_needs_fewer_representatives_than_demo(card_run):
    """Four isotropic materials: fewer representatives than demo (41 at 1 %, 45 chosen by the same rule)."""
    m = metrics(card_run, "card", "cluster")
    assert m["representatives_rule"] == "auto" and m["k_chosen"] == m["representatives_requested"]
    assert m["k_chosen"] < 41
    assert (m["k_distortion_curve"][-1] <= m["k_distortion_tolerance"] or m["k_spread_curve"][-1] <= m["spread_tolerance"]
            or m["k_chosen"] == m["k_ladder"][-1])
    assert "representatives: auto" in (card_run / "results/card/logs/cluster.log").read_text()
