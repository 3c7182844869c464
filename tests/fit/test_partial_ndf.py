"""facetsynth.fit.partial_ndf (eqs. 5, 10-12) and its stage at the numerical extremes (issue 7, part 2): the view in
the sample plane, a very rough lobe, the iteration cut short, float32 against float64 runs (push-pull, partial NDF,
k-means, synthesis and the eta fit), and the stage's scatter parts. The common cases are in
tests/fit/test_reflectance.py."""

import numpy as np
import pytest

from facetsynth.fit import cluster, params
from facetsynth.models import microfacet
from facetsynth.io import tables
from facetsynth.fit import partial_ndf
from facetsynth.fit import synthesis
from facetsynth.fit.pushpull import push_pull, splat

from test_grid import GRID, O, sph, upper
from test_params import C_GRAZING
from test_stages import metrics_of
from test_synthesis import SGRID, ggx_partial


def test_eq11_view_in_the_plane_gives_an_empty_partial_ndf():
    """A view exactly in the sample plane (o.n = 0; eq. 11's factor (o.n) vanishes): every D is 0 (no
    information), finite, converged at once; a view 0.01 deg above the plane stays finite and non-negative."""
    full = np.ones((1,) + GRID.shape)
    rng = np.random.default_rng(0)
    d = upper(rng, 500)[None]
    for elevation, expect_zero in ((0.0, True), (0.01, False)):
        view = np.array([0.0, -1.0, 0.0]) if elevation == 0 else sph(90.0 - elevation, -90.0)
        slice_ = push_pull(*splat(GRID, d, microfacet.rho(d, view, np.zeros(3), np.full(3, 0.6), 1.6, 0.2, 0.3,
                                                          0.0).mean(-1)))
        fit = partial_ndf.fit(slice_, full, view, GRID)
        assert np.isfinite(fit.ndf).all() and np.isfinite(fit.confidence).all() and (fit.ndf >= 0).all()
        if expect_zero:
            assert np.all(fit.ndf == 0) and fit.converged.all() and fit.iterations[0] == 1


def analytic_slice(ks, eta, alpha_u, alpha_v, phi, view=O, grid=GRID):
    rho = microfacet.rho(grid.directions, view, np.zeros(3), np.full(3, ks), eta, alpha_u, alpha_v, phi)
    return rho.mean(axis=-1)[None]


def test_partial_ndf_of_a_very_rough_lobe():
    """Alpha = 1 (a broad NDF: most of its mass lies outside the view's domain Omega, and eq. 5's shadowing
    is strong): the partial NDF from an exact slice is finite, non-negative and converged, and matches
    mean(ks) F D on W >= 0.5 within 0.35 relative L2 (measured 0.28, against 0.05-0.08 for alpha 0.1-0.3 in
    test_reflectance: S of eq. 5 from a partial NDF that misses most of a broad lobe is biased; stated)."""
    full = np.ones((1,) + GRID.shape)
    fit = partial_ndf.fit(analytic_slice(0.6, 1.6, 1.0, 1.0, 0.0), full, O, GRID)
    assert fit.converged.all() and np.isfinite(fit.ndf).all() and (fit.ndf >= 0).all()
    true_ndf = microfacet.ndf(GRID.directions, 1.0, 1.0, 0.0)[None]
    ref = partial_ndf.recoverable_ndf(np.full((1, 3), 0.6), np.array([1.6]), true_ndf, O[None], GRID)
    err = partial_ndf.relative_l2(fit.ndf, ref, fit.confidence >= 0.5, GRID)[0]
    assert err < 0.35


def test_partial_ndf_iteration_cut_short():
    """The eq. 5 / eq. 11 iteration stopped before it converges (max_iter = 1, and 0) returns its last
    iterate, finite and non-negative, flagged converged = False with the iterations used; with its budget
    it converges, and the one-step iterate is 1-10 % (relative L2) from the converged NDF."""
    full = np.ones((1,) + GRID.shape)
    slice_ = analytic_slice(0.6, 1.6, 0.2, 0.4, 0.5)
    done = partial_ndf.fit(slice_, full, O, GRID)
    assert done.converged.all() and done.iterations[0] > 1
    for max_iter in (0, 1):
        cut = partial_ndf.fit(slice_, full, O, GRID, max_iter=max_iter)
        assert not cut.converged.any() and cut.iterations[0] == max_iter
        assert np.isfinite(cut.ndf).all() and (cut.ndf >= 0).all()
    one = partial_ndf.fit(slice_, full, O, GRID, max_iter=1)
    err = partial_ndf.relative_l2(one.ndf, done.ndf, done.confidence > 0, GRID)[0]
    assert 0.01 < err < 0.1                                  # measured 0.046


# ============================================================================ float32 versus float64
def test_float32_and_float64_runs_agree():
    """The same scene's data in float32 and in float64 (the pipeline stores float32 tensors): push-pull and
    the partial NDF agree to 1e-5 (relative to the largest value), k-means gives the same clusters, synthesis
    makes the same merges (exemplar and shift) with NDFs within 1e-4, and the eta fit agrees to 1e-5."""
    rng = np.random.default_rng(8)
    d = upper(rng, 600)[None].repeat(3, 0)
    values = np.stack([microfacet.rho(d[0], O, np.zeros(3), np.full(3, 0.6), eta, a, b, p).mean(-1)
                       for eta, a, b, p in ((1.3, 0.1, 0.3, 0.0), (2.5, 0.2, 0.2, 0.0), (1.6, 0.05, 0.4, 1.0))])
    sums = {dt: splat(GRID, d.astype(dt), values.astype(dt)) for dt in (np.float32, np.float64)}
    slices = {dt: push_pull(*s) for dt, s in sums.items()}
    peak = np.abs(slices[np.float64]).max()
    assert np.abs(slices[np.float32] - slices[np.float64]).max() < 1e-5 * peak
    full = np.ones((3,) + GRID.shape)
    fits = {dt: partial_ndf.fit(slices[np.float64].astype(dt), full.astype(dt), O.astype(dt), GRID) for dt in slices}
    a, b = fits[np.float32].ndf, fits[np.float64].ndf
    assert np.isfinite(a).all() and np.abs(a - b).max() < 1e-5 * np.abs(b).max()
    # clustering and synthesis on rotated copies of one anisotropic GGX
    frames = np.linspace(0, 2 * np.pi, 32, endpoint=False) + 0.013
    pd, pw = ggx_partial(frames, scale=np.random.default_rng(0).uniform(0.3, 1.0, 32))
    runs = {}
    for dt in (np.float32, np.float64):
        dd, ww = pd.astype(dt), pw.astype(dt)
        km = cluster.kmeans(cluster.features(dd, ww, SGRID), dd, ww, SGRID, 4, seed=0)
        spectra = synthesis.ExemplarSpectra(dd, ww, SGRID)
        done = synthesis.complete(dd[0], ww[0], spectra, dd, ww, SGRID, synthesis.hemisphere_target(ww[0] > 0, SGRID),
                                  synthesis.Knobs(overlap_range=(0.5, 0.85), max_iterations=12, target_coverage=0.99,
                                            max_relative_error=0.4, candidates_per_region=5, fill_overlap=None),
                                  exclude=0)
        runs[dt] = (km, done)
    (k32, c32), (k64, c64) = runs[np.float32], runs[np.float64]
    np.testing.assert_array_equal(k32.labels, k64.labels)
    assert [(m["exemplar"], m["shift"]) for m in c32.merges] == [(m["exemplar"], m["shift"]) for m in c64.merges]
    assert len(c64.merges) >= 2
    assert np.abs(c32.ndf - c64.ndf).max() < 1e-4 * c64.ndf.max()
    f_m = microfacet.fresnel(C_GRAZING, 1.9) * (1 + 0.02 * np.random.default_rng(1).standard_normal(C_GRAZING.size))
    e32 = params.fit_eta(f_m.astype(np.float32), C_GRAZING.astype(np.float32))
    e64 = params.fit_eta(f_m, C_GRAZING)
    assert e32.constrained and e64.constrained and abs(e32.eta - e64.eta) < 1e-5


def test_partial_ndf_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """scatter.tiles > 1 (issue 14): the parts (whole tiles of points) and their join give the unsplit
    run's partial NDFs bit for bit and the same metrics; tiles of 64 points give 4 tiles on these 256, and
    6 parts leave two empty."""
    from facetsynth.stages.partial_ndf import Settings, gather, run_part, run_whole
    monkeypatch.setattr("facetsynth.stages.partial_ndf.TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], slice_path=f["resample/slice"],
                  grid_path=f["resample/grid.json"])
    settings = Settings(per_point_view=True)
    run_whole(**inputs, ndf_out=tmp_path / "ndf", metrics_out=tmp_path / "m.json", settings=settings)
    from facetsynth.stages.common import part_points
    assert [part_points(256, k, 6, 64) for k in range(6)] == [slice(0, 64), slice(64, 128), slice(128, 192),
                                                              slice(192, 256), slice(256, 256), slice(256, 256)]
    assert part_points(200, 3, 4, 64) == slice(192, 200) and part_points(1000, 1, 2) == slice(512, 1000)
    with pytest.raises(ValueError):
        part_points(256, 6, 6)
    parts = [tmp_path / f"part{k}" for k in range(6)]
    for k in (3, 0, 5, 1, 4, 2):                      # any order
        run_part(**inputs, part=k, parts=6, ndf_out=parts[k] / "ndf", record_out=parts[k] / "record.npz",
                 settings=settings)
    shuffled = [parts[k] for k in (2, 0, 5, 4, 1, 3)]
    gather(f["geometry"], f["resample/grid.json"], [p / "ndf" for p in shuffled],
           [p / "record.npz" for p in shuffled], tmp_path / "joined", tmp_path / "joined.json", settings)
    for name in ("table.json", "mask.npy", "offsets.npy", "ndf.npy", "confidence.npy"):
        assert (tmp_path / "joined" / name).read_bytes() == (tmp_path / "ndf" / name).read_bytes(), name
    assert metrics_of(tmp_path / "joined.json") == metrics_of(tmp_path / "m.json")
    assert len(tables.SupportTable(tmp_path / "ndf")) == 256 and len(tables.SupportTable(parts[5] / "ndf")) == 0
