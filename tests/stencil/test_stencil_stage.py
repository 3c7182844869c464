"""Stage stencil_fit: one stencil model per material cluster of a fitted SVBRDF (paper 000 on paper 002's output).

The SVBRDF here is the scenes' truth tabulated on the direction grid
(`svbrdf.tabulate_truth`, one representative per distinct NDF): the limit of
a perfect synthesis, so what is tested is the bridge SVBRDF -> UTIA grid ->
stencil fit and its scoring against the truth, not the synthesis.
"""

import numpy as np
import pytest

from facetsynth.geometry.grid import DirectionGrid
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.truth.scene import Scene
from facetsynth.stages.stencil_fit import cluster_metrics, fit_clusters, true_axes_deg
from facetsynth.stencil.fit import axis_error_deg
from facetsynth.models.svbrdf import tabulate_truth

PLANE = PlaneGrid(0.1, 0.1, 16, 16)


def truth_svbrdf(repo, scene):
    maps = Scene.load(repo / f"resources/scenes/{scene}.yaml").parameters(PLANE.points3d().reshape(-1, 3)[:, :2])
    model = tabulate_truth(maps, DirectionGrid(32, 128), PLANE)
    reps = np.asarray(model.representatives)
    members = np.bincount(model.neighbours[:, 0], minlength=len(reps))
    return model, reps, members, true_axes_deg(maps.alpha_u[reps], maps.alpha_v[reps], maps.phi_frame[reps]), \
        maps.take(reps)


def test_true_axes_follow_the_tight_tangent():
    assert true_axes_deg(np.array([0.1, 0.2]), np.array([0.3, 0.2]), np.deg2rad([30.0, 10.0])) == [[60.0], []]
    assert axis_error_deg([179.0], [1.0]) == pytest.approx(2.0)      # axes are modulo 180 deg
    assert axis_error_deg([], []) == 0.0


@pytest.mark.parametrize("scene, clusters, modes", [("satin", 2, {"1": 2}), ("card", 4, {"0": 4})])
def test_one_model_per_material_with_the_true_mode_count_and_axis(repo, scene, clusters, modes):
    """satin: two thread directions, one mode each, at phi_a 90 and 0 deg; card: isotropic, no mode."""
    model, reps, members, truth, maps = truth_svbrdf(repo, scene)
    # the Kurt baseline (1-8 s per cluster) on satin's two clusters only
    records, shaders = fit_clusters(model, reps, members, truth, maps, kurt_at_most=2 if scene == "satin" else 0)
    metrics = cluster_metrics(records, ground_truth=True)
    assert metrics["clusters"] == clusters and metrics["mode_counts"] == modes
    assert metrics["mode_count_accuracy"] == 1.0
    if scene == "satin":
        assert metrics["phi_a_error_deg_max"] < 4.0                  # issue 6: microfacet lobes within 4 deg
    assert all(s.startswith("analytic") for s in shaders) and len(shaders) == clusters
    assert sum(r["points"] for r in records) == PLANE.rows * PLANE.cols
    for r in records:
        sc = r["stencil"]["scores"]
        assert all(np.isfinite(sc[k]) for k in ("delta_e", "rmse", "psnr_db", "ssim", "fit_seconds"))
        assert sc["ssim"] > 0.5
        assert set(r["vs_truth"]) == ({"stencil", "svbrdf", "kurt"} if scene == "satin" else {"stencil", "svbrdf"})
        assert r["vs_truth"]["svbrdf"]["psnr_db"] > 30      # the tabulated truth is close to the truth
    if scene == "satin":    # issue 18: both models' scores and fit times for every cluster, and their medians
        for r in records:
            assert all(np.isfinite(r["kurt"]["scores"][k]) for k in ("delta_e", "psnr_db", "fit_seconds"))
        assert metrics["kurt_delta_e_median"] > 0 and metrics["kurt_fit_seconds_median"] > 0
        assert 0 <= metrics["stencil_delta_e_at_most_kurt"] <= 1 and metrics["kurt_clusters"] == 2
        assert metrics["vs_truth"]["kurt"]["delta_e_median"] > 0


def test_the_kurt_comparison_covers_the_clusters_it_was_fitted_to():
    """The Kurt baseline is fitted to at most KURT_CLUSTERS clusters (a comparison; 1-8 s each): its medians and
    the share where the stencil's Delta E is at most Kurt's are over those clusters alone."""
    def record(stencil_de, kurt_de=None):
        scores = {"delta_e": stencil_de, "rmse": 0.1, "psnr_db": 30.0, "ssim": 0.9, "fit_seconds": 0.1}
        r = {"stencil": {"scores": scores, "n_modes": 0}}
        if kurt_de is not None:
            r["kurt"] = {"scores": dict(scores, delta_e=kurt_de, fit_seconds=2.0)}
        return r
    metrics = cluster_metrics([record(1.0, 2.0), record(9.0), record(3.0, 2.0), record(9.0), record(1.0, 1.5)],
                              ground_truth=False)
    assert (metrics["clusters"], metrics["kurt_clusters"]) == (5, 3)
    assert metrics["stencil_delta_e_at_most_kurt"] == pytest.approx(2 / 3)
    assert metrics["kurt_delta_e_median"] == 2.0 and metrics["delta_e_median"] == 3.0
    assert cluster_metrics([record(1.0)], ground_truth=False)["stencil_delta_e_at_most_kurt"] is None
