"""Clustering (eq. 18) and example-based NDF synthesis (paper 002 sec. 5.2-5.3, eqs. 13-17) against analytic NDFs.

The search logic is tested with the exact search (and a brute-force search of
the sec. 5.3 histogram keys); pynndescent (about 24 s of numba compilation per
process) is used in one test only.
"""

from dataclasses import replace

import numpy as np
import pytest

from facetsynth.models import microfacet
from facetsynth.fit import synthesis
from facetsynth.fit.cluster import constrained_least_squares, features, interpolation_weights, kmeans
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.geometry.plane import PlaneGrid

from test_stages import metrics_of, one_material, rig_lights, write_rectified

GRID = DirectionGrid(16, 64)
ALPHA = (0.15, 0.4)
# the knobs these tests were measured with (synthesis.complete's former defaults; the stage's Settings stops at
# target_coverage 0.96): sec. 5.2's 50-85 % overlap, the paper's rule only
KNOBS = synthesis.Knobs(overlap_range=(0.5, 0.85), max_iterations=12, target_coverage=0.99, max_relative_error=0.4,
                        candidates_per_region=5, fill_overlap=None)
ANN = {"buckets": 32, "seed": 0, "n_neighbors": 30, "epsilon": 0.2}   # config synthesize's (and seed)


def single_view_domain(grid: DirectionGrid = GRID) -> np.ndarray:
    """A domain shaped like a single view's Omega: a full cap round the pole, then a lobe narrowing in phi."""
    t = np.degrees(grid.theta)[:, None]
    p = np.degrees(grid.phi)[None, :]
    half = np.clip(150.0 - (t - 15.0) * 3.5, 0.0, 180.0)          # half-width in azimuth, per ring
    gap = np.abs((p - 90.0 + 180.0) % 360.0 - 180.0)
    return ((t <= 15.0) | (gap <= half)) & (t <= 56.0)            # like the rig's: see docs/decisions.md


def ggx_table(frame_rad, grid: DirectionGrid = GRID, alpha=ALPHA) -> np.ndarray:
    frame = np.atleast_1d(np.asarray(frame_rad, float))
    h = grid.directions.reshape(1, -1, 3)
    return microfacet.ndf(h, alpha[0], alpha[1], frame[:, None]).reshape((len(frame),) + grid.shape)


def partial(frames, scale=1.0, grid: DirectionGrid = GRID, alpha=ALPHA):
    """Partial tuples <D, W> (N, T, F) of GGX NDFs at the given frame azimuths, on the single-view domain."""
    mask = single_view_domain(grid)
    d = ggx_table(frames, grid, alpha) * np.reshape(scale, (-1, 1, 1))
    w = np.broadcast_to(mask, d.shape).astype(float)
    return np.where(mask, d, 0.0), w


def normalised(d, grid=GRID):
    return d / grid.integrate(d * grid.directions[..., 2])[..., None, None]


def rel_l2(a, b, mask=None, grid=GRID):
    wgt = grid.solid_angles if mask is None else np.where(mask, grid.solid_angles, 0.0)
    return float(np.sqrt(np.sum((a - b) ** 2 * wgt) / np.sum(b**2 * wgt)))


# ---------------------------------------------------------------------------- eq. 15
def test_distance_is_zero_for_self_scale_invariant_and_symmetric():
    d, w = partial([0.3, 1.2])
    w = w * np.linspace(0.2, 1.0, GRID.n_phi)            # non-uniform confidence
    same = synthesis.distance(d[0], w[0], d[0], w[0], GRID)
    assert same.distance == pytest.approx(0.0, abs=1e-15) and same.relative == pytest.approx(0.0, abs=1e-7)
    ab = synthesis.distance(d[0], w[0], d[1], w[1], GRID).distance
    assert ab > 0
    assert (synthesis.distance(7.5 * d[0], w[0], 0.02 * d[1], w[1], GRID).distance   # s1, s2
            == pytest.approx(ab, rel=1e-12))
    assert synthesis.distance(d[1], w[1], d[0], w[0], GRID).distance == pytest.approx(ab, rel=1e-12)
    # the matrix form (clustering) and the FFT form (every rotation) agree with the direct one
    pair = synthesis.pairwise_distance(d, w, d, w, GRID)
    assert pair[0, 1] == pytest.approx(ab, rel=1e-9) and pair[1, 0] == pytest.approx(ab, rel=1e-9)
    assert abs(pair[0, 0]) < 1e-9 * ab
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    match, frac = spectra.scores(d[0], w[0])
    for k in (0, 5, 17):
        dk, wk = synthesis.rotate_tuple(d[1], w[1], GRID, k)
        direct = synthesis.distance(d[0], w[0], dk, wk, GRID)
        assert match.distance[1, k] == pytest.approx(float(direct.distance), rel=1e-4)
        assert frac[1, k] == pytest.approx(float(direct.overlap / np.sum((wk > 0) * GRID.solid_angles)), abs=1e-5)


def test_empty_overlap_gives_an_infinite_distance_and_no_nan():
    d, w = partial([0.0, 0.0])
    w2 = np.zeros_like(w[1])
    m = synthesis.distance(d[0], w[0], d[1], w2, GRID)
    assert np.isinf(m.distance) and m.s2 == 0 and m.weight == 0
    zero = synthesis.distance(d[0], w[0], np.zeros_like(d[1]), w[1], GRID)       # s2 = 0: all-zero NDF on the overlap
    assert np.isinf(zero.distance)
    assert np.isinf(synthesis.pairwise_distance(d[:1], w[:1], d[1:], w2[None], GRID)).all()
    spectra = synthesis.ExemplarSpectra(np.stack([d[1]]), np.stack([w2]), GRID)
    match, frac = spectra.scores(d[0], w[0])
    assert np.isinf(match.distance).all() and np.all(frac == 0) and not np.isnan(match.distance).any()
    # synthesis with nothing to merge keeps the partial NDF, finite, and says it covered nothing new
    done = synthesis.complete(d[0], w[0], spectra, d[1:], w2[None], GRID, synthesis.hemisphere_target(w[0] > 0, GRID),
                              KNOBS)
    assert done.iterations == 0 and np.isfinite(done.ndf).all() and (done.ndf >= 0).all()
    empty = synthesis.complete(np.zeros_like(d[0]), np.zeros_like(w[0]), spectra, d[1:], w2[None], GRID,
                               synthesis.hemisphere_target(w[0] > 0, GRID), KNOBS)
    assert empty.coverage == 0 and np.all(empty.ndf == 0)


# ---------------------------------------------------------------------------- eqs. 13-14: best match at the right phi
@pytest.mark.parametrize("turn_deg", [40.0, 61.0])
def test_a_partial_ndf_and_its_rotated_copy_are_each_others_best_match(turn_deg):
    """Point b is point a's NDF turned by turn_deg; distractors have other roughness. Exact search."""
    rng = np.random.default_rng(1)
    da, wa = partial([0.4])
    db, wb = partial([0.4 + np.radians(turn_deg)], scale=0.3)
    dx, wx = partial(rng.uniform(0, 2 * np.pi, 6), alpha=(0.3, 0.3))
    d, w = np.concatenate([da, db, dx]), np.concatenate([wa, wb, wx])
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    target = synthesis.hemisphere_target(wa[0] > 0, GRID)
    step = np.degrees(GRID.d_phi)
    for query, other, sign in ((0, 1, +1), (1, 0, -1)):
        done = synthesis.complete(d[query], w[query], spectra, d, w, GRID, target, replace(KNOBS, max_iterations=1),
                                  exclude=query)
        first = done.merges[0]
        assert first["exemplar"] == other and first["merged"]
        # D_b(R(phi) h) = D_a(h) for phi = turn: the shift is turn / d_phi sectors (a: -turn)
        got = (first["shift"] * step - sign * turn_deg + 180.0) % 360.0 - 180.0
        assert abs(got) <= step
        assert first["relative_error"] < 0.05


def test_histogram_keys_find_the_rotated_copy_with_brute_force_search():
    """Sec. 5.3 pruning, brute force over the keys: the same candidate and phi as the exact search."""
    da, wa = partial([0.4])
    db, wb = partial([0.4 + np.radians(50.0)])
    dx, wx = partial(np.linspace(0, 2 * np.pi, 8, endpoint=False), alpha=(0.35, 0.35))
    d, w = np.concatenate([da, db, dx]), np.concatenate([wa, wb, wx])
    mask = wa[0] > 0
    shifts = synthesis.region_shifts(mask, GRID, 20, 0.5, 0.85)
    assert shifts.size == 20 and shifts.min() >= 1
    search = synthesis.HistogramSearch(d, mask, GRID, shifts, **ANN, exact=True)
    assert len(search.regions) == 2 * len(search.shifts)
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    target = synthesis.hemisphere_target(mask, GRID)
    done = synthesis.complete(d[0], w[0], spectra, d, w, GRID, target, replace(KNOBS, max_iterations=1), search=search,
                              exclude=0)
    first = done.merges[0]
    assert first["exemplar"] == 1
    assert abs(first["shift"] * np.degrees(GRID.d_phi) - 50.0) <= np.degrees(GRID.d_phi)


# ---------------------------------------------------------------------------- eqs. 16-17 and the whole synthesis
def test_merge_follows_eqs_16_and_17():
    d = np.array([[2.0, 1.0, 0.0]])
    w = np.array([[1.0, 0.5, 0.0]])
    dc = np.array([[9.0, 4.0, 6.0]])
    wc = np.array([[0.0, 0.5, 1.0]])
    merged, wm = synthesis.merge(d, w, dc, wc, ratio=0.5)
    np.testing.assert_allclose(merged, [[2.0, (0.5 * 1 + 0.5 * 0.5 * 4) / 1.0, 3.0]])
    np.testing.assert_allclose(wm, [[1.0, 0.5, 1.0]])


@pytest.mark.parametrize("options, min_coverage, max_error, max_overall", [
    ({}, 0.83, 0.15, 0.30),                                          # the paper's rule, push-pull: 0.850, 0.120, 0.275
    ({"fill_overlap": 0.95}, 0.93, 0.03, 0.02),                    # the option: 0.948, 0.008, 0.016
])
def test_synthesis_completes_an_anisotropic_ggx_from_rotated_partial_copies(options, min_coverage, max_error,
                                                                            max_overall):
    """64 points share one GGX (0.15, 0.4) with frames turned through every azimuth, seen on one partial
    domain (19 % of the hemisphere, up to 56 deg) at different brightness. The point with frame 0 is completed."""
    frames = np.linspace(0, 2 * np.pi, 64, endpoint=False) + 0.013
    scale = np.random.default_rng(0).uniform(0.3, 1.0, 64)
    d, w = partial(frames, scale=scale)
    mask = w[0] > 0
    target = synthesis.hemisphere_target(mask, GRID)
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    done = synthesis.complete(d[0], w[0], spectra, d, w, GRID, target, replace(KNOBS, **options), exclude=0)
    truth = ggx_table(frames[0])[0]
    cos = GRID.directions[..., 2]

    def on_target(x):   # normalised over the reachable rings: the part synthesis supplies
        return x / GRID.integrate(np.where(target, x * cos, 0.0))

    before = rel_l2(on_target(np.where(mask, d[0], 0.0)), on_target(truth), target)
    after = rel_l2(on_target(done.ndf), on_target(truth), target)
    overall = rel_l2(normalised(done.ndf), normalised(truth))
    print(f"coverage {done.coverage:.3f}, error on reachable rings {before:.3f} -> {after:.3f}, "
          f"all cells {overall:.3f}")
    assert done.coverage >= min_coverage and not done.stalled
    assert 2 <= done.iterations <= 12
    assert after <= max_error and before >= 0.35    # before: the partial NDF alone (0.383)
    assert overall <= max_overall
    covered = done.confidence > 0                    # merged cells: exact up to the point's scale
    ratio = done.ndf[covered] / truth[covered]
    assert np.ptp(ratio) <= 1e-6 * ratio.mean()
    assert np.isfinite(done.ndf).all() and (done.ndf >= 0).all()


def test_the_rings_beyond_reach_continue_a_ggx_lobe_as_ggx():
    """Rotation about the normal cannot reach the rings past the view's last one: they continue each azimuth's
    D^-1/2 line in sin^2 theta (GGX's form, fitted on the outer half of the reachable rings). Anisotropic and
    isotropic GGX cut at
    56 deg come back to rounding; the last ring held instead adds 0.9-1.2 % of their mass (ks = integral of
    (n.h) D carries it). A narrow lobe over a broad one (a measured lobe is not one GGX) keeps its mass beyond
    the reach to 2 % (held: 43 % too much). A table with data on 3 azimuths only, and an empty one, stay finite, non-negative
    and non-increasing past the reach."""
    grid = DirectionGrid(32, 128)
    target = np.broadcast_to((np.degrees(grid.theta) <= 56.0)[:, None], grid.shape)
    last = int(np.flatnonzero(target[:, 0]).max())
    cos = grid.directions[..., 2]
    for alpha in ((0.1, 0.32), (0.2, 0.2)):
        truth = ggx_table([0.3], grid, alpha)[0]
        held = truth.copy()
        held[last + 1:] = held[last]
        made = synthesis.decay_beyond_reach(held, target, grid)
        np.testing.assert_allclose(made, truth, rtol=1e-9)
        assert grid.integrate(held * cos) > 1.008 * grid.integrate(truth * cos)         # the test can fail
    beyond = np.zeros(grid.shape, bool)
    beyond[last + 1:] = True
    two = 0.7 * ggx_table([0.3], grid, (0.05, 0.05))[0] + 0.3 * ggx_table([0.3], grid, (0.4, 0.4))[0]
    held = two.copy()
    held[last + 1:] = held[last]
    mass = [grid.integrate(np.where(beyond, t * cos, 0.0)) for t in (two, held,
                                                                       synthesis.decay_beyond_reach(held, target, grid))]
    assert mass[2] == pytest.approx(mass[0], rel=0.02) and mass[1] > 1.3 * mass[0]   # 0.0207 / 0.0297 / 0.0207
    spot = np.zeros(grid.shape)
    spot[:last + 1, :3] = np.linspace(1.0, 0.1, last + 1)[:, None]                    # data on 3 azimuths only
    for table in (spot, np.zeros(grid.shape), ggx_table([0.0], grid, (0.1, 0.32))[0] * np.where(target, 1.0, 0.0)):
        made = synthesis.decay_beyond_reach(table, target, grid)
        assert np.isfinite(made).all() and (made >= 0).all()
        assert (np.diff(made[last:], axis=0) <= 1e-15).all()
        np.testing.assert_array_equal(made[:last + 1], table[:last + 1])


def test_synthesis_carries_the_cosine_of_the_fresnel_factor_each_cell_holds():
    """Eq. 11 leaves F(|o.h|) in a partial NDF. A cell merged from an exemplar rotated by phi holds that
    exemplar's data at h' = R(phi) h, seen from o: its Fresnel cosine is |o . R(phi) h|. Own cells keep
    |o . h|; cells that both cover hold the eq. 16 weighted mean; every cell ends in [0, 1]."""
    frames = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    d, w = partial(frames)
    o = np.array([0.0, np.sin(np.radians(50.0)), np.cos(np.radians(50.0))])
    views = np.tile(o, (64, 1))
    target = synthesis.hemisphere_target(w[0] > 0, GRID)
    done = synthesis.complete(d[0], w[0], synthesis.ExemplarSpectra(d, w, GRID), d, w, GRID, target,
                              replace(KNOBS, max_iterations=1, refine=False), exclude=0, view=o, exemplars_view=views)
    (merge,) = done.merges
    phi = merge["shift"] * GRID.d_phi
    rz = np.array([[np.cos(phi), -np.sin(phi), 0.0], [np.sin(phi), np.cos(phi), 0.0], [0.0, 0.0, 1.0]])
    h = GRID.directions
    own, theirs = np.abs(h @ o), np.abs((h @ rz.T) @ o)
    _, wc = synthesis.rotate_tuple(d[merge["exemplar"]], w[merge["exemplar"]], GRID, merge["shift"])
    only_own, only_theirs, both = (w[0] > 0) & (wc == 0), (w[0] == 0) & (wc > 0), (w[0] > 0) & (wc > 0)
    assert only_own.sum() > 20 and only_theirs.sum() > 20 and both.sum() > 20
    np.testing.assert_allclose(done.fresnel_cosine[only_own], own[only_own], atol=1e-9)
    np.testing.assert_allclose(done.fresnel_cosine[only_theirs], theirs[only_theirs], atol=1e-9)
    expected = (w[0] * own + wc * theirs) / np.where(both, w[0] + wc, 1.0)
    np.testing.assert_allclose(done.fresnel_cosine[both], expected[both], atol=1e-9)
    assert np.isfinite(done.fresnel_cosine).all() and done.fresnel_cosine.min() >= 0 and done.fresnel_cosine.max() <= 1


def test_one_frame_everywhere_is_reported_not_invented():
    """brushed: every point has the same frame, so no rotated exemplar matches; synthesis stalls."""
    d, w = partial(np.full(32, 0.52), scale=np.linspace(0.5, 1.0, 32), alpha=(0.05, 0.3))
    target = synthesis.hemisphere_target(w[0] > 0, GRID)
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    done = synthesis.complete(d[0], w[0], spectra, d, w, GRID, target, KNOBS, exclude=0)
    assert done.stalled
    assert done.merges[-1]["merged"] is False and done.merges[-1]["relative_error"] > 0.4
    # the only true matches are the half turn (GGX is symmetric under R(pi)): nothing else is merged
    for m in done.merges[:-1]:
        assert m["merged"] and abs(m["shift"] - GRID.n_phi / 2) <= 1 and m["relative_error"] < 0.05
    assert done.iterations <= 1 and done.coverage < 0.85


def test_orientation_concentration_tells_one_lobe_axis_from_rotated_ones():
    """Paper 002 sec. 4: rotation diversity read off the exemplars' lobe axes. The second azimuthal harmonic
    of a single-view partial GGX NDF turns with its frame, once round per half turn of the frame (its axis, mod
    180 deg; the domain makes the rate uneven);
    concentration 1 for one frame everywhere (brushed), far below the stage's SINGLE_ORIENTATION for frames
    spread over 180 deg (wallpaper) and for two perpendicular sets of equal weight (a satin's warp and weft:
    measured 0.33 and 0.25 on this domain, whose shape biases every axis the same way); an isotropic lobe has no
    axis."""
    one, w1 = partial(np.full(24, 0.52), scale=np.linspace(0.5, 1.0, 24))
    spread, w2 = partial(np.linspace(0.0, np.pi, 24, endpoint=False))
    weave, w3 = partial(np.repeat([0.2, 0.2 + np.pi / 2], 12))
    assert synthesis.orientation_concentration(synthesis.orientation(one, w1, GRID)) == pytest.approx(1.0, abs=1e-9)
    single = synthesis.SINGLE_ORIENTATION
    assert synthesis.orientation_concentration(synthesis.orientation(spread, w2, GRID)) < 0.5 * single
    assert synthesis.orientation_concentration(synthesis.orientation(weave, w3, GRID)) < 0.5 * single
    z = synthesis.orientation(spread, w2, GRID)
    turn = np.angle(np.roll(z, -1) / z)                   # frames 7.5 deg apart round a half turn: 2 psi winds
    assert np.degrees(turn.sum()) == pytest.approx(360.0, abs=1e-6) and np.abs(turn).max() < np.pi / 3  # once

    iso, wi = partial([0.0], alpha=(0.3, 0.3))
    assert abs(synthesis.orientation(iso, wi, GRID)[0]) < 1e-3 * abs(synthesis.orientation(one, w1, GRID)[0])
    assert np.isnan(synthesis.orientation_concentration(np.zeros(3, complex)))


# ---------------------------------------------------------------------------- clustering and eq. 18
def test_weights_sum_to_one_and_reproduce_representatives():
    frames = np.linspace(0, np.pi, 40)
    d, w = partial(frames, scale=np.linspace(0.5, 1.0, 40))
    feats = features(d, w, GRID)
    result = kmeans(feats, d, w, GRID, 6, seed=0)
    reps = result.representatives
    assert len(reps) == 6 and len(np.unique(reps)) == 6
    assert all(result.labels[r] == i for i, r in enumerate(reps))
    nbr, wts, lam = interpolation_weights(d, w, d[reps], w[reps], GRID, k=16, rep_rows=reps,
                                          rows=np.arange(len(d)))
    assert nbr.shape == (40, 16) and wts.dtype == np.float32 and lam > 0
    np.testing.assert_allclose(wts.sum(axis=1), 1.0, atol=1e-6)
    for j, r in enumerate(reps):                         # a representative is itself, weight 1
        assert nbr[r, 0] == j and wts[r, 0] == 1.0 and np.all(wts[r, 1:] == 0)
    assert np.all(nbr < len(reps)) and np.all(wts[:, 6:] == 0)   # padding: weight 0
    # the least squares of eq. 18 (no ridge) reproduces a representative exactly
    a = d[reps].reshape(6, -1).T
    np.testing.assert_allclose(constrained_least_squares(a, a[:, 2]), np.eye(6)[2], atol=1e-8)
    # a point halfway between two representatives' NDFs is found as that mix
    mix = 0.3 * d[reps[1]] + 0.7 * d[reps[4]]
    n2, w2, _ = interpolation_weights(mix[None], w[:1], d[reps], w[reps], GRID, k=16, ridge=0.0,
                                      radius=1e9)
    got = np.bincount(n2[0], weights=w2[0], minlength=len(reps))     # padding repeats an index with weight 0
    np.testing.assert_allclose(got, 0.3 * np.eye(6)[1] + 0.7 * np.eye(6)[4], atol=1e-5)


def test_degenerate_kmeans_on_identical_ndfs():
    d, w = partial(np.full(20, 0.3))
    feats = features(d, w, GRID)
    result = kmeans(feats, d, w, GRID, 5, seed=0)
    assert result.distinct == 1 and len(result.representatives) == 1 and np.all(result.labels == 0)
    nbr, wts, lam = interpolation_weights(d, w, d[result.representatives], w[result.representatives],
                                          GRID, rep_rows=result.representatives, rows=np.arange(20))
    assert np.isinf(lam) and np.all(nbr == 0)
    np.testing.assert_allclose(wts.sum(axis=1), 1.0)
    # two identical representatives: a singular eq. 18 system still gives finite weights summing to 1
    sol = constrained_least_squares(np.stack([d[0].ravel(), d[0].ravel()], axis=1), d[0].ravel())
    assert np.isfinite(sol).all() and sol.sum() == pytest.approx(1.0)


# ---------------------------------------------------------------------------- the one pynndescent test
def test_ann_search_completes_like_the_exact_search():
    """Sec. 5.3 with real pynndescent indexes (the suite's only numba compilation)."""
    frames = np.linspace(0, 2 * np.pi, 96, endpoint=False) + 0.02
    d, w = partial(frames, scale=np.random.default_rng(2).uniform(0.3, 1.0, 96))
    mask = w[0] > 0
    target = synthesis.hemisphere_target(mask, GRID)
    spectra = synthesis.ExemplarSpectra(d, w, GRID)
    search = synthesis.HistogramSearch(d, mask, GRID, synthesis.region_shifts(mask, GRID, 20, 0.5, 0.85), **ANN)
    assert all(index is not None for index in search.indexes)
    truth = ggx_table(frames[0])[0]
    cos = GRID.directions[..., 2]

    def on_target(x):
        return x / GRID.integrate(np.where(target, x * cos, 0.0))

    ann = synthesis.complete(d[0], w[0], spectra, d, w, GRID, target, KNOBS, search=search, exclude=0)
    exact = synthesis.complete(d[0], w[0], spectra, d, w, GRID, target, KNOBS, exclude=0)
    e_ann, e_exact = (rel_l2(on_target(c.ndf), on_target(truth), target) for c in (ann, exact))
    print(f"ANN: coverage {ann.coverage:.3f} error {e_ann:.3f}; exact: {exact.coverage:.3f} {e_exact:.3f}")
    assert ann.coverage >= 0.83 and exact.coverage >= 0.83     # the paper's overlap rule: measured 0.870, 0.855
    assert e_ann <= 0.15 and e_exact <= 0.15                  # measured 0.066, 0.133 (holes push-pulled)
    assert all(m["relative_error"] < 0.01 for m in ann.merges)   # only true (rotated) copies merged


# ---------------------------------------------------------------------------- numerical extremes (issue 7, part 2)
SGRID = GRID                                    # DirectionGrid(16, 64), as the extremes tests name it


def ggx_partial(frames, scale=1.0, alpha=(0.15, 0.4), grid=SGRID, max_theta=56.0):
    """Partial tuples <D, W> of GGX NDFs at frame azimuths, on a single-view-like domain (a cap to max_theta
    deg narrowing in phi; the same shape as tests/fit/test_synthesis.py's)."""
    t = np.degrees(grid.theta)[:, None]
    p = np.degrees(grid.phi)[None, :]
    half = np.clip(150.0 - (t - 15.0) * 3.5, 0.0, 180.0)
    gap = np.abs((p - 90.0 + 180.0) % 360.0 - 180.0)
    mask = ((t <= 15.0) | (gap <= half)) & (t <= max_theta)
    frames = np.atleast_1d(np.asarray(frames, float))
    d = microfacet.ndf(grid.directions.reshape(1, -1, 3), alpha[0], alpha[1], frames[:, None]).reshape(
        (len(frames),) + grid.shape) * np.reshape(scale, (-1, 1, 1))
    return np.where(mask, d, 0.0), np.broadcast_to(mask, d.shape).astype(float)


def test_eq15_tiny_overlap_and_extreme_scales():
    """Eq. 15 where s1, s2 -> 0 or the overlap shrinks to one cell. One shared cell: each D divided by its
    own scale over the overlap is 1 / dw there, so the distance is 0 (to rounding, 1e-12) and the overlap is that cell's
    solid angle (direct, matrix and FFT forms agree). NDFs scaled by 1e-6 and 1e6 (a dark and a very bright
    point): the distance is scale-free, direct form to 1e-9, FFT (complex64) within 1e-3 of the direct one.
    Below the TINY scale (1e-32) an NDF counts as empty: distance inf, weights 0, never NaN."""
    d, w = ggx_partial([0.3, 1.2])
    one = np.zeros_like(w)
    one[0, 3, 10] = one[1, 3, 10] = 1.0                      # each domain: one cell, the same one
    one[1, 4, 20] = 0.5                                      # ... and one of its own
    m = synthesis.distance(d[0], one[0], d[1], one[1], SGRID)
    assert m.distance < 1e-12 / SGRID.solid_angles[3, 10] ** 2 and m.relative < 1e-12   # 0 up to rounding
    assert m.overlap == pytest.approx(SGRID.solid_angles[3, 10], rel=1e-12)
    scale = 1.0 / SGRID.solid_angles[3, 10] ** 2
    assert abs(synthesis.pairwise_distance(d[:1], one[:1], d[1:], one[1:], SGRID)[0, 0]) < 1e-9 * scale
    match, frac = synthesis.ExemplarSpectra(d[1:], one[1:], SGRID).scores(d[0], one[0])
    assert abs(match.distance[0, 0]) < 1e-5 * scale and np.isfinite(match.distance[0, 0])
    assert not np.isnan(match.distance).any() and not np.isnan(frac).any()
    base = synthesis.distance(d[0], w[0], d[1], w[1], SGRID)
    spectra_base, _ = synthesis.ExemplarSpectra(d[1:], w[1:], SGRID).scores(d[0], w[0])
    for s1, s2 in ((1e-6, 1.0), (1.0, 1e6), (1e-6, 1e6)):
        m = synthesis.distance(s1 * d[0], w[0], s2 * d[1], w[1], SGRID)
        assert m.distance == pytest.approx(float(base.distance), rel=1e-9)
        fft, _ = synthesis.ExemplarSpectra(s2 * d[1:], w[1:], SGRID).scores(s1 * d[0], w[0])
        assert np.isfinite(fft.distance).all()
        np.testing.assert_allclose(fft.distance, spectra_base.distance, rtol=1e-3, atol=1e-3 * float(base.distance))
    empty = synthesis.distance(1e-32 * d[0], w[0], d[1], w[1], SGRID)
    assert np.isinf(empty.distance) and empty.s1 == 0 and empty.weight == 0 and not np.isnan(empty.relative)


def test_identical_ndfs_everywhere_through_the_stages(tmp_path):
    """Every point has the identical partial NDF (an isotropic GGX, alpha 0.3) and W: the cluster stage
    lowers k to 1 distinct NDF (one representative, weight 1 everywhere, lambda undefined -> null); the
    synthesize stage completes it beyond its own domain (from rotated copies of itself, which are exact
    matches, or by azimuthal symmetry), so on every covered cell the completed NDF equals the true
    isotropic GGX (to the half-float rounding of the stored partial NDFs, 2^-11), and nothing is NaN."""
    from facetsynth.io.fileio import write_json
    from facetsynth.stages import cluster, synthesize
    from facetsynth.io.tables import support_writer
    geometry = write_rectified(tmp_path / "cap", one_material((0.2,) * 3, (0.5,) * 3), PlaneGrid(0.1, 0.1, 5, 5),
                               rig_lights(2, 2))
    d, w = ggx_partial([0.0], scale=0.7, alpha=(0.3, 0.3))
    with support_writer(tmp_path / "partial", (25,) + SGRID.shape, ("ndf", "confidence")) as write:
        write(np.repeat(w, 25, 0) > 0, ndf=np.repeat(d, 25, 0), confidence=np.repeat(w, 25, 0))
    write_json(tmp_path / "grid.json", SGRID.to_dict())
    out = tmp_path / "out"
    cluster.run(cluster.Inputs(geometry=geometry, ndf=tmp_path / "partial", grid=tmp_path / "grid.json"),
         cluster.Outputs(labels=out / "labels.npy",
         representatives=out / "reps.npy", neighbours=out / "nbr.npy", weights=out / "wts.npy",
         rep_ndf=out / "rep_ndf.npy", rep_confidence=out / "rep_conf.npy", rotation=out / "rotation.npy",
         metrics=out / "cluster.json"))
    m = metrics_of(out / "cluster.json")
    assert m["distinct_ndfs"] == 1 and m["representatives"] == 1 and m["lambda"] is None
    wts = np.load(out / "wts.npy")
    assert np.all(np.load(out / "labels.npy") == 0) and np.all(wts[:, 0] == 1) and np.all(wts[:, 1:] == 0)
    synthesize.run(synthesize.Inputs(geometry=geometry, ndf=tmp_path / "partial",
         grid=tmp_path / "grid.json", representatives=out / "reps.npy", neighbours=out / "nbr.npy",
         weights=out / "wts.npy"), synthesize.Outputs(ndf=out / "ndf.npy", confidence=out / "w.npy",
         fresnel_cosine=out / "cos.npy", grid=out / "grid.json", metrics=out / "synth.json"))
    table, conf = np.load(out / "ndf.npy"), np.load(out / "w.npy")
    assert table.shape == (1,) + SGRID.shape and np.isfinite(table).all() and (table >= 0).all()
    covered = conf[0] > 0
    truth = 0.7 * microfacet.ndf(SGRID.directions, 0.3, 0.3, 0.0)
    assert covered.sum() > (w[0] > 0).sum()                  # more than its own domain
    np.testing.assert_allclose(table[0][covered], truth[covered], rtol=2.0 ** -11)


def test_every_turn_of_every_pair_of_complete_ndfs_by_fft_is_eq15_turned_sector_by_sector():
    """turned_pairwise_distance (refine's materials test, one FFT per NDF) against pairwise_distance of each
    NDF turned by rotate_tuple, whole sectors -6 .. 6: equal to 1e-12 of the largest distance, with the
    empty NDF infinite against every other, never NaN; a lobe is 0 from its own turned copy at that turn."""
    grid = DirectionGrid(12, 48)
    rng = np.random.default_rng(3)
    d = rng.random((6,) + grid.shape) ** 3
    d[2] = 0.0                                                          # an empty NDF
    d[4] = np.roll(d[1], -5, axis=-1)                                   # NDF 1 turned by 5 sectors
    full = np.ones(grid.shape)
    fft = synthesis.turned_pairwise_distance(d, grid, 6)
    direct = np.stack([np.stack([synthesis.pairwise_distance(d, np.ones_like(d), t[None], full[None], grid)[:, 0]
                                 for t in (synthesis.rotate_tuple(d[k], full, grid, float(s))[0]
                                           for s in range(-6, 7))], axis=-1) for k in range(len(d))], axis=1)
    assert fft.shape == (6, 6, 13) and not np.isnan(fft).any()
    assert np.array_equal(np.isinf(fft), np.isinf(direct)) and np.isinf(fft[2]).all() and np.isinf(fft[:, 2]).all()
    finite = np.isfinite(direct)
    np.testing.assert_allclose(fft[finite], direct[finite], rtol=0, atol=1e-12 * direct[finite].max())
    assert fft[4, 1, 6 + 5] < 1e-12 * direct[finite].max() and fft[4, 1].min() == fft[4, 1, 11]
