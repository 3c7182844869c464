"""Issue 29: the per-point refinement (facetsynth.refine) and the self-check's subsets and scores
(facetsynth.selfcheck), against known answers."""

from __future__ import annotations

import numpy as np
import pytest

from facetsynth.refine import NormalSums, radiance_weights, solve
from facetsynth.selfcheck import FrameScores, heldout_lights, relit_frames


def _samples(rng, n_points=40, per_point=200, a=None, b=None, noise=0.0):
    point = np.repeat(np.arange(n_points), per_point)
    g = rng.gamma(0.5, 2.0, point.size)                      # a lobe: mostly small, a few large
    a = rng.uniform(0.02, 0.3, (n_points, 3)) if a is None else a
    b = rng.uniform(0.1, 1.0, (n_points, 3)) if b is None else b
    y = a[point] + b[point] * g[:, None] + noise * rng.standard_normal((point.size, 3))
    u = rng.uniform(0.5, 2.0, (point.size, 3))
    return point, g, y, u, a, b


def test_solve_recovers_kd_and_ks_from_exact_samples():
    rng = np.random.default_rng(0)
    point, g, y, u, a, b = _samples(rng)
    sums = NormalSums.of(point, len(a), y, g, u)
    fa, fb = solve(sums, np.zeros_like(a), np.zeros_like(b), ridge=0.0)
    np.testing.assert_allclose(fa, a, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fb, b, rtol=1e-9)
    np.testing.assert_allclose(sums.sse(fa, fb), 0.0, atol=1e-9)


def test_solve_is_the_weighted_least_squares_under_noise_and_its_sse_is_exact():
    rng = np.random.default_rng(1)
    point, g, y, u, a, b = _samples(rng, n_points=5, noise=0.02)
    sums = NormalSums.of(point, 5, y, g, u)
    fa, fb = solve(sums, a, b, ridge=0.0)
    for p in range(5):
        sel = point == p
        for c in range(3):
            w = np.sqrt(u[sel, c])
            design = np.stack([np.ones(sel.sum()), g[sel]], -1) * w[:, None]
            ref, *_ = np.linalg.lstsq(design, y[sel, c] * w, rcond=None)
            assert fa[p, c] == pytest.approx(ref[0], rel=1e-8, abs=1e-12)
            assert fb[p, c] == pytest.approx(ref[1], rel=1e-8)
            direct = np.sum(u[sel, c] * (y[sel, c] - fa[p, c] - fb[p, c] * g[sel]) ** 2)
            assert sums.sse(fa, fb)[p, c] == pytest.approx(direct, rel=1e-6)


def test_solve_keeps_kd_and_ks_non_negative_with_the_best_boundary_solution():
    rng = np.random.default_rng(2)
    # a matte point (ks = 0) whose noise pulls the unconstrained ks below 0, and a black one with a lobe
    point, g, y, u, _, _ = _samples(rng, n_points=2, a=np.array([[0.2] * 3, [0.0] * 3]),
                                    b=np.array([[0.0] * 3, [0.5] * 3]), noise=0.01)
    y[point == 0] -= 0.004 * g[point == 0, None]
    y[point == 1] -= 0.003
    sums = NormalSums.of(point, 2, y, g, u)
    fa, fb = solve(sums, np.zeros((2, 3)), np.zeros((2, 3)), ridge=0.0)
    assert (fa >= 0).all() and (fb >= 0).all()
    sel = point == 0
    np.testing.assert_allclose(fb[0], 0.0)
    np.testing.assert_allclose(fa[0], (u[sel] * y[sel]).sum(0) / u[sel].sum(0), rtol=1e-10)
    sel = point == 1
    np.testing.assert_allclose(fa[1], 0.0)
    np.testing.assert_allclose(fb[1], (u[sel] * g[sel, None] * y[sel]).sum(0) / (u[sel] * g[sel, None] ** 2).sum(0),
                               rtol=1e-10)


def test_the_ridge_keeps_the_prior_where_the_samples_do_not_constrain_ks():
    rng = np.random.default_rng(3)
    point, g, y, u, a, b = _samples(rng, n_points=3)
    g[point == 1] = 0.0                                   # no highlight in view: ks unconstrained
    y[point == 1] = a[1]
    u[point == 2] = 0.0                                   # no valid sample at all
    sums = NormalSums.of(point, 3, y, g, u)
    prior_a, prior_b = np.full((3, 3), 0.5), np.full((3, 3), 0.7)
    fa, fb = solve(sums, prior_a, prior_b, ridge=1e-3)
    np.testing.assert_allclose(fb[1], 0.7)                # kept: nothing says otherwise
    np.testing.assert_allclose(fa[1], (a[1] + 1e-3 * 0.5) / (1 + 1e-3), rtol=1e-9)   # kd follows its samples
    np.testing.assert_allclose(fa[2], 0.5)
    np.testing.assert_allclose(fb[2], 0.7)
    np.testing.assert_allclose(fb[0], b[0], rtol=2e-3)    # a point with a lobe barely feels the prior


def test_radiance_weights_make_rho_residuals_radiance_residuals():
    wi = np.array([[0.0, 0.6, 0.8], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    r2 = np.array([0.04, 0.01, 0.02])
    u = radiance_weights(wi, r2, np.array([0.3, 0.2, 0.1]))
    np.testing.assert_allclose(u[0], (0.8 / 0.04 * np.array([0.3, 0.2, 0.1])) ** 2)
    np.testing.assert_allclose(u[2], 0.0)                 # grazing: no radiance, no weight


def test_heldout_lights_are_interleaved_and_relit_frames_avoid_them():
    held = heldout_lights(1360, 10)
    assert held.sum() == 136 and np.flatnonzero(held)[:3].tolist() == [5, 15, 25]
    relit = relit_frames(held, 8)
    assert not held[relit].any() and relit.size == int(np.ceil(1224 / 8))
    assert not heldout_lights(30, 0).any()
    assert relit_frames(heldout_lights(30, 0), 1).size == 30


def test_frame_scores_against_known_errors():
    rng = np.random.default_rng(4)
    measured = rng.uniform(0.1, 1.0, (2, 6, 5, 3))
    diffuse = 0.5 * measured
    mask = np.ones((6, 5), bool)
    mask[0, 0] = False
    scores = FrameScores()
    for q in range(2):
        scores.add(q, measured[q], 1.1 * measured[q], diffuse[q], mask)
    assert scores.rel_l2 == pytest.approx(0.1, rel=1e-12)             # 10 % too bright everywhere
    assert scores.specular_rel_l2 == pytest.approx(0.2, rel=1e-12)    # the error against half the signal
    exact = FrameScores()
    exact.add(7, measured[0], measured[0], diffuse[0], mask)
    assert exact.rel_l2 == 0.0 and exact.psnr_db == [100.0] and exact.worst_frame() == 7
    dark = FrameScores()
    dark.add(3, np.zeros((6, 5, 3)), np.zeros((6, 5, 3)), np.zeros((6, 5, 3)), mask)
    assert np.isnan(dark.rel_l2) and dark.worst_frame() is None       # no light: no score, not a perfect one
