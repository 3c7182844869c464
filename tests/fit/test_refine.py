"""Issue 29: the per-point refinement (facetsynth.fit.refine) and the self-check's subsets and scores
(facetsynth.evaluation.selfcheck), against known answers."""

from __future__ import annotations

import numpy as np
import pytest

from facetsynth.fit.cluster import material_groups
from facetsynth.fit.refine import NormalSums, owned_kd, radiance_weights, solve
from facetsynth.evaluation.selfcheck import FrameScores, heldout_lights, relit_frames


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


def test_points_without_any_sample_keep_the_prior():
    """A tile whose points have no valid sample (found by the SLURM test's 32 x 32 tiny capture): float sums
    of zero, and the prior returned."""
    sums = NormalSums.of(np.zeros(0, np.intp), 4, np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    assert sums.u.dtype == float and not sums.u.any()
    a, b = solve(sums, np.full((4, 3), 0.1), np.full((4, 3), 0.6), ridge=1e-3)
    np.testing.assert_array_equal(a, 0.1)
    np.testing.assert_array_equal(b, 0.6)


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


# --- the NDF's stretch and turn (issue 29) ----------------------------------------------------------------

from facetsynth.models import microfacet  # noqa: E402
from facetsynth.geometry.grid import DirectionGrid  # noqa: E402
from facetsynth.fit.params import normalise  # noqa: E402
from facetsynth.fit.refine import _turn_error, _turn_errors, best_turns, stretch  # noqa: E402
from facetsynth.stages.refine import ladder_minimum  # noqa: E402


def _ggx_table(grid, alpha_u, alpha_v, phi=0.0):
    d = grid.directions.reshape(-1, 3)
    return microfacet.ndf(d, alpha_u, alpha_v, phi).reshape(grid.shape)


def test_stretch_maps_one_ggx_lobe_onto_another_of_scaled_roughness():
    """GGX is a function of tan(theta_h) / alpha: stretching alpha 0.3's table by 0.5 is alpha 0.15's
    (normalised; the grid's bilinear lookup is the only error: 1.5 % relative L2 on 64 x 256)."""
    grid = DirectionGrid(64, 256)
    wide, narrow = (normalise(_ggx_table(grid, a, a), grid)[0] for a in (0.3, 0.15))
    made, _ = normalise(stretch(wide, grid, 0.5), grid)
    w = grid.solid_angles
    assert np.sqrt(np.sum((made - narrow) ** 2 * w) / np.sum(narrow**2 * w)) < 0.02
    assert np.sqrt(np.sum((wide - narrow) ** 2 * w) / np.sum(narrow**2 * w)) > 0.5   # the test can fail
    np.testing.assert_array_equal(stretch(wide, grid, 1.0), wide)


def test_ladder_minimum_finds_the_minimum_between_the_best_rungs_neighbours():
    """An asymmetric error in log eta with its minimum at 1.8, on refine's eta ladder: the bounded search finds
    it to 0.5 % where the parabola through the best three rungs (1.4, 1.7, 2.1) puts it at 1.74; at the
    ladder's end, and on a flat error, the ladder's own best (the first of equals) stays."""
    ladder = np.array([1.2, 1.4, 1.7, 2.1, 2.7, 3.5])

    def error(v):
        x = np.log(v / 1.8)
        return 1.0 + x * x + 1.5 * x ** 3

    value, err = ladder_minimum(ladder, error(ladder), error)
    assert value == pytest.approx(1.8, rel=0.005) and err == pytest.approx(error(value))
    x, y = np.log(ladder[1:4]), error(ladder[1:4])
    vertex = np.exp(x[1] - 0.5 * ((x[1] - x[0]) ** 2 * (y[1] - y[2]) - (x[1] - x[2]) ** 2 * (y[1] - y[0]))
                    / ((x[1] - x[0]) * (y[1] - y[2]) - (x[1] - x[2]) * (y[1] - y[0])))
    assert abs(vertex - 1.8) > 0.05                                   # 1.743: the parabola's bias the search removes
    rising = lambda v: np.log(v)                                       # noqa: E731
    assert ladder_minimum(ladder, rising(ladder), rising) == (1.2, pytest.approx(np.log(1.2)))
    flat = lambda v: 1.0                                               # noqa: E731
    assert ladder_minimum(ladder, np.ones(ladder.size), flat) == (1.2, 1.0)


def test_best_turns_finds_the_representative_and_turn_that_made_the_samples():
    """Samples made by representative 1 turned by 3 sectors (plus a constant denominator): the compiled
    search returns exactly that candidate and a zero error; its error equals a numpy evaluation."""
    grid = DirectionGrid(16, 64)
    tables = np.stack([_ggx_table(grid, 0.1, 0.4, a) for a in (0.0, 0.5, 1.2)]).reshape(3, -1)
    rng = np.random.default_rng(5)
    n_points, per = 3, 300
    h = rng.normal(size=(n_points * per, 3))
    h[:, 2] = np.abs(h[:, 2]) + 1.0
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    t, p = grid.coordinates(h)
    denom = rng.uniform(0.5, 1.5, h.shape[0])
    u = rng.uniform(0.5, 2.0, h.shape[0])
    k_true, rep_true, ks = [3, -2, 0], [1, 2, 0], [0.7, 0.2, 1.3]
    r = np.concatenate([ks[x] * grid.lookup(tables[rep_true[x]].reshape(grid.shape),
                                            np.stack([np.cos(np.arctan2(h[s, 1], h[s, 0]) + k_true[x] * grid.d_phi)
                                                      * np.hypot(h[s, 0], h[s, 1]),
                                                      np.sin(np.arctan2(h[s, 1], h[s, 0]) + k_true[x] * grid.d_phi)
                                                      * np.hypot(h[s, 0], h[s, 1]), h[s, 2]], -1))
                        * denom[s] for x, s in enumerate(np.split(np.arange(h.shape[0]), n_points))])
    offsets = np.arange(n_points + 1) * per
    candidates = np.array([[0, 1, -1], [0, 1, 2], [0, 2, 1]], np.int64)
    err, rep, k = best_turns(offsets, t, p, denom, r, u, candidates, tables, grid.n_theta, grid.n_phi, 4)
    assert rep.tolist() == rep_true and k.tolist() == k_true
    np.testing.assert_allclose(err, 0.0, atol=1e-9 * np.sum(u * r * r))
    # no candidate or no sample: no choice
    err, rep, k = best_turns(np.array([0, 0, per]), t[:per], p[:per], denom[:per], r[:per], u[:per],
                             np.array([[0, 1], [-1, -1]], np.int64), tables, grid.n_theta, grid.n_phi, 2)
    assert rep.tolist() == [-1, -1] and np.isinf(err).all()


def test_best_turns_finds_a_turn_between_whole_sectors():
    """Samples of an analytic GGX lobe (alpha 0.1 x 0.4) turned by 2.4 sectors of a 32 x 128 grid (3.4 deg),
    searched with the lobe's table: the turn comes out 2.4 to 0.1 sector (whole sectors alone: 2, the demo's
    radial streaks), with a lower error than at 2 sectors."""
    grid = DirectionGrid(32, 128)
    table = _ggx_table(grid, 0.1, 0.4).reshape(1, -1)
    rng = np.random.default_rng(7)
    h = rng.normal(size=(2000, 3))
    h[:, 2] = np.abs(h[:, 2]) + 2.0
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    t, p = grid.coordinates(h)
    k_true = 2.4
    phi = np.arctan2(h[:, 1], h[:, 0]) + k_true * grid.d_phi
    turned = np.stack([np.cos(phi) * np.hypot(h[:, 0], h[:, 1]), np.sin(phi) * np.hypot(h[:, 0], h[:, 1]), h[:, 2]], -1)
    r = 0.8 * microfacet.ndf(turned, 0.1, 0.4, 0.0)
    u, denom = np.ones(h.shape[0]), np.ones(h.shape[0])
    offsets = np.array([0, h.shape[0]])
    err, rep, k = best_turns(offsets, t, p, denom, r, u, np.array([[0]], np.int64), table, grid.n_theta,
                             grid.n_phi, 4)
    assert rep.tolist() == [0] and k[0] == pytest.approx(k_true, abs=0.1)
    whole, _, k_whole = best_turns(offsets, t, p, denom, r, u, np.array([[0]], np.int64), table, grid.n_theta,
                                   grid.n_phi, 2)     # 2.4 is beyond a window of 2: the window's end, whole
    assert k_whole[0] == 2 and err[0] < 0.5 * whole[0]


@pytest.mark.parametrize("tilted", [False, True])
def test_the_compiled_gather_is_the_samples_written_in_numpy(tilted):
    """refine's samples of a tile in one compiled pass (fit.refine.gather_samples) against the numpy it replaced
    (light_geometry, the shading frames, the masks): the same samples in the same order, i and |P - x|^2 equal
    (to rounding under tilted frames, whose matrix product numpy orders its own way), rho to the bit; point and
    directional lights, lights at and below a point's horizon, non-finite residuals dropped."""
    from facetsynth.fit.normals import shading_frames, to_local
    from facetsynth.fit.refine import gather_samples
    from facetsynth.models.render import light_geometry
    rng = np.random.default_rng(8)
    n, f = 40, 30
    points = np.c_[rng.uniform(-0.05, 0.05, (n, 2)), np.zeros(n)]
    lights = np.c_[rng.uniform(-0.3, 0.3, (f, 2)), rng.uniform(-0.02, 0.3, f), np.ones(f)]
    lights[:5] = np.c_[rng.normal(size=(5, 3)), np.zeros(5)]             # directional
    lights[:5, :3] /= np.linalg.norm(lights[:5, :3], axis=1, keepdims=True)
    normal = np.c_[rng.normal(0, 0.3, (n, 2)), np.ones(n)] if tilted else np.tile([0.0, 0.0, 1.0], (n, 1))
    frames = shading_frames(normal / np.linalg.norm(normal, axis=1, keepdims=True))
    ok = rng.uniform(size=(n, f)) < 0.7
    rho = rng.uniform(0, 1, (n, f, 3)).astype(np.float32)
    rho[0, 3, 1], rho[2, 4, 0] = np.inf, np.nan
    pp, ff, wi, r2, got = gather_samples(points, lights, frames if tilted else np.empty((0, 3, 3)), ok, rho)
    i, d2 = light_geometry(points[:, None, :], lights[None])
    i = to_local(frames[:, None], i) if tilted else i
    keep = ok & (i[..., 2] > 0) & np.isfinite(rho.sum(axis=-1))
    assert 0 < keep.sum() < ok.sum()                                     # some lights below the horizon
    np.testing.assert_array_equal(np.c_[pp, ff], np.argwhere(keep))
    np.testing.assert_allclose(wi, i[keep], rtol=0, atol=1e-15)
    np.testing.assert_allclose(r2, np.where(lights[ff, 3] > 0, d2[keep], 1.0), rtol=1e-15)
    np.testing.assert_array_equal(got, rho[keep])


def test_every_whole_turn_in_one_pass_equals_each_turn_alone():
    """best_turns reads each sample's two rings once for all 2 window + 1 whole turns (fit.refine._turn_errors,
    4.7 x faster on refine's tiles); each turn's error equals the one pass per turn it replaced
    (_turn_error) to rounding: across phi's wrap, beyond the first and last ring (clamped), with samples
    whose g is 0."""
    grid = DirectionGrid(12, 40)
    table = np.random.default_rng(2).uniform(0.0, 3.0, grid.n_theta * grid.n_phi)
    table[:grid.n_phi] = 0.0                               # a ring of zeros: some g = 0
    rng = np.random.default_rng(4)
    n, window = 500, 10
    t = rng.uniform(-1.0, grid.n_theta + 0.5, n)
    p = rng.uniform(-0.5, grid.n_phi - 0.5, n)
    p[:50] = rng.uniform(-0.5, 0.5, 50)                   # at the wrap
    denom, r, u = rng.uniform(0.5, 1.5, n), rng.uniform(0.0, 2.0, n), rng.uniform(0.5, 2.0, n)
    urr = float(np.sum(u * r * r))
    errors = np.empty(2 * window + 1)
    _turn_errors(t, p, denom, r, u, table, 0, n, window, urr, grid.n_theta, grid.n_phi, errors)
    alone = [_turn_error(t, p, denom, r, u, table, 0, n, k, urr, grid.n_theta, grid.n_phi)
             for k in range(-window, window + 1)]
    np.testing.assert_allclose(errors, alone, rtol=1e-12)
    assert np.ptp(alone) > 0.03 * urr                      # the turns differ: the test can fail


def test_a_table_fitted_to_samples_of_turned_points_recovers_the_lobe_between_one_points_samples():
    """Samples of one GGX lobe (alpha 0.1 x 0.3, ks 0.7, a known denominator) at points turned to 16
    azimuths, each point seeing the same 40 half vectors in the world: in the table's frame they fall at
    16 x 40 places. The table fitted to them (eq. 6 read forwards for D) matches the truth's best bilinear
    table to 2 % where the samples reach, while a prior 3 x too wide is what it started from (the test can
    fail); cells no sample reaches keep the prior exactly."""
    from facetsynth.geometry.grid import turn
    from facetsynth.fit.refine import solve_table, table_normal_equations
    grid = DirectionGrid(16, 64)
    truth = _ggx_table(grid, 0.1, 0.3).ravel()
    prior = _ggx_table(grid, 0.3, 0.9).ravel()
    rng = np.random.default_rng(3)
    h = rng.normal(size=(40, 3)) * [0.25, 0.25, 1.0]
    h[:, 2] = np.abs(h[:, 2])
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    turns = np.repeat(np.arange(16) * 2 * np.pi / 16, h.shape[0])
    local = turn(np.tile(h, (16, 1)), turns)
    look = grid.bilinear(local)
    cells, w = look.cells.T, look.weights.T
    coef = np.tile(rng.uniform(0.5, 1.5, (local.shape[0], 1)), (1, 3)) * [0.7, 0.6, 0.5]
    r = coef * np.sum(truth[cells] * w, axis=-1)[:, None]
    m, v = 0, 0
    for half in np.array_split(np.arange(r.shape[0]), 2):        # batches add up
        batch_m, batch_v = table_normal_equations(cells[half], w[half], coef[half], r[half], np.ones_like(r[half]),
                                                  truth.size)
        m, v = m + batch_m, v + batch_v
    fitted = solve_table(m, v, prior, 1e-6)
    seen = m.diagonal() > 0.05 * m.diagonal().max()
    assert seen.sum() > 100
    err = np.sqrt(np.sum((fitted - truth)[seen] ** 2) / np.sum(truth[seen] ** 2))
    assert err < 0.02
    assert np.sqrt(np.sum((prior - truth)[seen] ** 2) / np.sum(truth[seen] ** 2)) > 0.5
    unseen = np.flatnonzero(m.diagonal() == 0)
    np.testing.assert_allclose(fitted[unseen], np.clip(prior[unseen], 0, None), rtol=1e-9, atol=1e-12)
    # the samples' own error after the fit is what the least squares promise: below that of the truth's table
    # plus nothing (exact samples of a bilinear table: zero)
    pred = coef * np.sum(fitted[cells] * w, axis=-1)[:, None]
    assert np.sqrt(np.sum((pred - r) ** 2) / np.sum(r ** 2)) < 1e-3


def test_materials_group_representatives_by_the_kd_of_the_points_they_own():
    """A representative whose own point's separation is off (kd 0.117 where its points have 0.150, as on the
    Mitsuba ggx-tiles capture) is grouped with the material its points belong to; by its own point's kd it
    would be a material of its own (log distance 0.25 > log(1.25))."""
    kd = np.full((9, 3), 0.15)
    kd[6:] = 0.05                                       # a darker material
    kd[4] = 0.117                                       # representative 1's own point
    owner = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
    representatives = np.array([0, 4, 7])
    owned = owned_kd(kd, owner, representatives)
    np.testing.assert_allclose(owned, [[0.15] * 3, [0.15] * 3, [0.05] * 3])
    assert material_groups(owned, 0.25).tolist() == [0, 0, 1]
    own = material_groups(kd[representatives], 0.25)
    assert own[0] != own[1]                             # what grouping by the representatives' own kd did
    lonely = owned_kd(kd, np.zeros(9, np.intp), representatives)   # representatives 1, 2 own no point
    np.testing.assert_allclose(lonely[1:], kd[representatives[1:]])


def test_the_fits_figure_scores_every_model_against_the_same_samples(extreme_run):
    """refine's figure on the fitting samples keeps the observations where separate left them (its residual
    plus separate's kd): a model with kd 0.05 too high scores worse, and the kd, ks fit scores better. Before,
    the observations moved with the model's kd, so the wrong kd scored as well as the right one, and on a
    dome's leaf the fit's figure rose 0.129 -> 0.168 while the fit had lowered its error."""
    from dataclasses import replace
    from facetsynth.io.fileio import read_npy
    from facetsynth.stages.common import RectifiedCapture
    from facetsynth.stages.refine import Settings, kd_ks, samples_rel_l2
    from facetsynth.models.svbrdf import SVBRDF
    capture = RectifiedCapture.load(extreme_run["geometry"])
    model = SVBRDF.load(extreme_run["svbrdf"])
    spec, ok = read_npy(extreme_run["separate/specular.npy"]), capture.validity(extreme_run["separate/valid.npy"])
    before = samples_rel_l2(model, capture, spec, ok, model.kd)
    wrong = samples_rel_l2(replace(model, kd=model.kd + 0.05), capture, spec, ok, model.kd)
    a, b, _ = kd_ks(model, capture, spec, ok, Settings())
    fitted = samples_rel_l2(replace(model, kd=np.pi * a, ks=b), capture, spec, ok, model.kd)
    assert wrong > 1.2 * before and fitted < before


def test_one_eta_per_material_gives_each_materials_points_their_median(extreme_run):
    """Params' eta drifts across a material (the eq. 18 mixture of its representatives'): before the samples
    choose, each material's visible points take their median, and nothing else changes."""
    from dataclasses import replace
    from facetsynth.stages.common import RectifiedCapture
    from facetsynth.stages.refine import Settings, material_points, materials, one_eta_per_material
    from facetsynth.models.svbrdf import SVBRDF
    capture = RectifiedCapture.load(extreme_run["geometry"])
    model = SVBRDF.load(extreme_run["svbrdf"])
    drift = replace(model, eta=1.4 + 0.2 * np.linspace(0.0, 1.0, model.n_points))
    settings = Settings()
    made = one_eta_per_material(drift, capture, settings)
    material, owner = materials(drift, settings)
    touched = np.zeros(model.n_points, bool)
    for m in np.unique(material):
        points, _ = material_points(capture, owner, np.flatnonzero(material == m), 1)
        if points.size:
            assert np.all(made.eta[points] == np.median(drift.eta[points]))
            touched[points] = True
    assert touched.any() and np.ptp(drift.eta[touched]) > 0.05
    np.testing.assert_array_equal(made.eta[~touched], drift.eta[~touched])
    np.testing.assert_array_equal(made.ks, drift.ks)


def test_the_sparse_table_solve_is_the_dense_one():
    """The table's normal equations are built and solved sparse (they couple only neighbouring cells): on random
    half vectors on 16 x 64 they equal the equations written out dense sample by sample, and the solve equals
    the dense solve of the same system to round-off (measured 5e-15 relative); the ridge keeps unseen cells at
    the prior."""
    from facetsynth.geometry.grid import DirectionGrid
    from facetsynth.fit.refine import solve_table, table_normal_equations
    rng = np.random.default_rng(3)
    grid = DirectionGrid(16, 64)
    n_cells = grid.n_theta * grid.n_phi
    h = rng.normal(size=(5000, 3))
    h[:, 2] = 3 * np.abs(h[:, 2]) + 2          # near the pole: the outer rings see no sample
    look = grid.bilinear(h / np.linalg.norm(h, axis=1, keepdims=True))
    coef, r, u = rng.uniform(0.1, 1, (5000, 3)), rng.uniform(0, 1, (5000, 3)), rng.uniform(0.5, 1, (5000, 3))
    m, v = table_normal_equations(look.cells.T, look.weights.T, coef, r, u, n_cells)
    cells, w = look.cells.T, look.weights.T        # the normal equations written out dense, sample by sample
    q, p = np.sum(u * coef * coef, axis=-1), np.sum(u * coef * r, axis=-1)
    dense_m, dense_v = np.zeros((n_cells, n_cells)), np.zeros(n_cells)
    for s in range(cells.shape[0]):
        np.add.at(dense_m, (cells[s][:, None], cells[s][None, :]), q[s] * np.outer(w[s], w[s]))
        np.add.at(dense_v, cells[s], p[s] * w[s])
    assert np.allclose(m.toarray(), dense_m, rtol=1e-12, atol=0) and np.allclose(v, dense_v, rtol=1e-12, atol=0)
    prior = rng.uniform(0, 1, n_cells)
    diag = np.diag(dense_m)
    lam = 0.01 * (diag + diag[diag > 0].mean())
    dense = np.clip(np.linalg.solve(dense_m + np.diag(lam), dense_v + lam * prior), 0, None)
    fitted = solve_table(m, v, prior, 0.01)
    assert np.abs(fitted - dense).max() <= 1e-10 * np.abs(dense).max()
    unseen = diag == 0
    assert unseen.any() and np.allclose(fitted[unseen], prior[unseen])


def test_azimuthal_differences_sum_the_squared_steps_around_each_ring():
    """Issue 35: D^T L D is the sum of (D[t, p + 1] - D[t, p])^2 around each ring (periodic); a table that
    changes only from ring to ring has no steps."""
    from facetsynth.fit.refine import azimuthal_differences
    rng = np.random.default_rng(3)
    table = rng.random((5, 12))
    by_hand = np.sum((np.roll(table, -1, axis=1) - table) ** 2)
    flat = table.ravel()
    assert flat @ (azimuthal_differences(5, 12) @ flat) == pytest.approx(by_hand, rel=1e-12)
    rings = np.repeat(rng.random(5), 12)                                      # a function of theta alone
    assert np.abs(azimuthal_differences(5, 12) @ rings).max() < 1e-12


def test_the_smoothness_term_interpolates_between_the_cells_the_samples_saw():
    """Issue 35: a lobe around the ring seen only on every other sector. Without the smoothness term the unseen
    sectors keep the prior (0 here); with it each comes out within 0.02 of its seen neighbours' mean (linear
    interpolation: 0.076 below the sine at its peak), and the seen ones stay within 0.02 of the data."""
    from scipy import sparse
    from facetsynth.fit.refine import solve_table
    n_theta, n_phi = 4, 16
    truth = np.tile(1.0 + np.sin(2 * np.pi * np.arange(n_phi) / n_phi), (n_theta, 1)).ravel()
    seen = (np.arange(n_theta * n_phi) % 2) == 0
    m = sparse.diags(seen.astype(float) * 100.0).tocsr()
    v = m @ truth
    prior = np.zeros(n_theta * n_phi)
    plain = solve_table(m, v, prior, 1e-3)
    smooth = solve_table(m, v, prior, 1e-3, 0.05, (n_theta, n_phi))
    assert np.abs(plain[~seen]).max() < 1e-9 and np.abs(plain[seen] - truth[seen]).max() < 5e-3
    table = smooth.reshape(n_theta, n_phi)
    between = 0.5 * (np.roll(table, 1, axis=1) + np.roll(table, -1, axis=1))
    assert np.abs(table - between)[:, 1::2].max() < 0.02                        # the unseen: interpolated
    assert np.abs(smooth[seen] - truth[seen]).max() < 0.025                      # the seen: still the data


def test_one_lobe_turned_is_one_material_whatever_kd_the_separation_left():
    """The Mitsuba copper (no diffuse term, its frame turning around the centre) came out of separate with kd
    0.017 to 0.10 by cluster; grouped by kd it was four materials, each with its own eta, stretch and NDF,
    drawn as wedges. Complete anisotropic NDFs that are one lobe turned (whole sectors here: distance 0 to
    round-off) are one material; another roughness (0.25 eq. 15 distance at its best turn) stays apart unless
    kd joins it; isotropic lobes of one gloss are joined by kd alone (the RTI fresco's pigments)."""
    from facetsynth.fit.cluster import materials, self_distances, turned_distances
    from facetsynth.geometry.grid import DirectionGrid
    from facetsynth.models import microfacet
    grid = DirectionGrid(24, 96)
    turns = np.radians([0.0, 30.0, 67.5, 90.0, 150.0])
    lobes = [microfacet.ndf(grid.directions, 0.15, 0.35, t) for t in turns]
    lobes += [microfacet.ndf(grid.directions, 0.08, 0.08, 0.0)] * 3            # a glossier, isotropic lobe
    d = np.stack(lobes)
    dist = turned_distances(d, grid)
    np.testing.assert_allclose(dist[:5, :5], 0.0, atol=1e-9)
    assert dist[5, :5].min() > 0.2 and np.all(dist == dist.T)
    quarter = self_distances(d, grid, 0.25)
    assert quarter[:5].min() > 0.1 and quarter[5:].max() < 1e-9
    np.testing.assert_allclose(self_distances(d, grid, 0.5), 0.0, atol=1e-9)  # GGX: a half turn maps it onto itself
    kd = np.array([[0.017] * 3, [0.10] * 3, [0.05] * 3, [0.08] * 3, [0.033] * 3,
                   [0.5] * 3, [0.2] * 3, [0.5, 0.2, 0.1]])
    assert len(np.unique(material_groups(kd, 0.25)[:5])) >= 4                 # what kd alone made of the copper
    assert materials(kd, d, grid, 0.25, 0.05).tolist() == [0, 0, 0, 0, 0, 1, 2, 3]
    kd[5] = kd[1]                                            # the same kd: the glossy one joins the copper
    assert materials(kd, d, grid, 0.25, 0.05).tolist() == [0, 0, 0, 0, 0, 0, 1, 2]


def test_a_half_turn_symmetric_table_is_measured_by_both_halves():
    """A point-symmetric lobe D(h) = D(R(pi) h), seen by samples that cover one half of the table each in a
    different place (the Mitsuba copper's points at turns phi and phi + pi): folded, every cell gets the truth
    from whichever half saw it (to 1e-6), and the two halves are equal; unfolded, each half keeps the prior
    where it saw nothing (the step in kd and ks across the copper's centre)."""
    from scipy import sparse
    from facetsynth.fit.refine import half_turn_fold, solve_table
    n_theta, n_phi = 4, 16
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    truth = np.outer(np.linspace(2, 1, n_theta), 1.0 + 0.5 * np.cos(2 * phi)).ravel()   # a half turn maps it
    fold = half_turn_fold(n_theta, n_phi)
    np.testing.assert_array_equal(np.asarray(fold.sum(axis=0)).ravel(), 2.0)
    np.testing.assert_allclose(fold @ (fold.T @ truth) / 2, truth, rtol=1e-12)
    cell = np.arange(n_theta * n_phi)
    seen = ((cell % n_phi) < n_phi // 2) == (cell // n_phi % 2 == 0)          # rings alternate which half
    m = sparse.diags(seen * 100.0).tocsr()
    v = m @ truth
    prior = np.zeros(truth.size)
    folded = solve_table(m, v, prior, 1e-9, shape=(n_theta, n_phi), half_turn=True)
    np.testing.assert_allclose(folded, truth, rtol=1e-6)
    table = folded.reshape(n_theta, n_phi)
    np.testing.assert_array_equal(table, np.roll(table, n_phi // 2, axis=1))
    plain = solve_table(m, v, prior, 1e-9)
    assert np.abs(plain[~seen]).max() < 1e-6 and np.abs(plain[seen] - truth[seen]).max() < 1e-6


def test_a_table_is_folded_only_where_its_points_turn_widely():
    """The copper's points turn all the way round (mean resultant length 0); a table whose points keep one frame
    within +-25 deg (the Mitsuba tiles and quadrants) or one turned by 180 deg as a whole is not folded; evenly
    over a quarter turn is the edge (0.90)."""
    from facetsynth.stages.refine import turned_widely
    rng = np.random.default_rng(4)
    assert turned_widely(rng.uniform(-np.pi, np.pi, 1000))
    assert turned_widely(np.radians(rng.uniform(-80, 110, 1000)))                     # the copper's, measured
    assert not turned_widely(np.radians(rng.uniform(-25, 25, 1000)))
    assert not turned_widely(np.full(50, np.pi))
    assert not turned_widely(np.radians(np.linspace(-44, 44, 1001)))
    assert turned_widely(np.radians(np.linspace(-46, 46, 1001)))
    assert not turned_widely(np.zeros(0))
