"""Issue 14: the compiled and batched paths that make the paper's scale fast, against the plain
computations they replace (scipy's map_coordinates, the dense eq. 5 integral, numpy's lstsq, Delaunay
barycentric weights, the frame-at-a-time separation)."""

import json

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from facetsynth.fit import cluster
from facetsynth.io import tables
from facetsynth.geometry.coverage import LightFootprint
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.geometry.lightplane import LightTriangulation
from facetsynth.fit.partial_ndf import (SHADOWING_GRID, _shadowing_area, _shadowing_kernel, projected_area_on,
                                       projected_area_table)

from test_stages import one_material, rig_lights, write_rectified
from test_sampling_invariance import paper_lights


@pytest.mark.parametrize("grid", [DirectionGrid(16, 64), DirectionGrid(24, 96), DirectionGrid(32, 128),
                                  DirectionGrid(12, 48)])
def test_shadowing_area_by_fft_equals_the_dense_integral(grid):
    """A(k) of eq. 5 at the shadowing grid's directions: the circular correlation along phi (grids with
    n_phi a multiple of 32) and the dense product (any other grid, here 12 x 48) give the integral
    sum max(h . k, 0) D(h) dw to 1e-12 of its largest value, for partial NDFs that are 0 on half the cells."""
    rng = np.random.default_rng(3)
    d = rng.random((6,) + grid.shape) * (rng.random((6,) + grid.shape) > 0.5)
    d[0] = 0.0                                                       # an all-zero NDF stays all zero
    dense = projected_area_table(d, grid, SHADOWING_GRID.directions.reshape(-1, 3))
    fast = _shadowing_area(d, grid)
    assert _shadowing_kernel(grid)[0] == ("dense" if grid.n_phi % 32 else "fft")
    assert np.abs(fast - dense).max() <= 1e-12 * np.abs(dense).max()
    assert np.all(fast[0] == 0.0) or np.abs(fast[0]).max() < 1e-15


def test_the_folded_spectrum_is_numpys_fold_of_every_bin_to_the_bit():
    """_every_mth_lag folds only the bins its n/m-point inverse reads, in one compiled pass: bitwise the
    inverse of numpy's fold of all n bins (the spectrum mirrored to n bins, summed over the m aliases), and
    the every-m-th lag of the full inverse to 1e-12, for the grids' ratios m = 2, 3, 5 and a random spectrum
    of a real signal that is 0 on half its samples."""
    import scipy.fft
    from facetsynth.fit.partial_ndf import _every_mth_lag
    rng = np.random.default_rng(5)
    for n, m in [(64, 2), (96, 3), (160, 5)]:
        x = rng.random((7, 4, n)) * (rng.random((7, 4, n)) > 0.5)
        spectrum = np.ascontiguousarray(scipy.fft.rfft(x, axis=-1).transpose(2, 0, 1))      # (n/2 + 1, 7, 4)
        full = np.concatenate([spectrum, np.conj(spectrum[-2:0:-1])])
        folded = full.reshape((m, n // m) + full.shape[1:]).sum(axis=0)
        reference = scipy.fft.irfft(folded[: n // m // 2 + 1], n=n // m, axis=0) / m
        np.testing.assert_array_equal(_every_mth_lag(spectrum, n, m), reference)
        every_mth = scipy.fft.irfft(spectrum, n=n, axis=0)[::m]
        assert np.abs(_every_mth_lag(spectrum, n, m) - every_mth).max() <= 1e-12 * np.abs(every_mth).max()


def test_the_kernel_made_once_gives_the_same_areas_to_the_bit():
    """projected_area_on (refine renormalises every stretch it tries) reuses one read-only kernel per pair of
    grids, and its A(k) is projected_area_table's at the shadowing grid's directions, bitwise, on a second call
    too."""
    grid = DirectionGrid(24, 96)
    rng = np.random.default_rng(4)
    d = rng.random((5,) + grid.shape) * (rng.random((5,) + grid.shape) > 0.5)
    dense = projected_area_table(d, grid, SHADOWING_GRID.directions.reshape(-1, 3))
    for _ in range(2):
        np.testing.assert_array_equal(projected_area_on(d, grid, SHADOWING_GRID), dense)
    from facetsynth.fit.partial_ndf import _grid_area_kernel
    kernel = _grid_area_kernel(grid, SHADOWING_GRID)
    assert kernel is _grid_area_kernel(DirectionGrid(24, 96), SHADOWING_GRID) and not kernel.flags.writeable


def test_coverage_kernel_equals_scipy_map_coordinates():
    """The compiled coverage (one pass per point and direction) against the distance map read by scipy's
    map_coordinates (order 1, constant mode, infinitely far beyond the raster): equal to 1e-12, for points
    on and off the sample plane and directions that miss the lights or never reach their plane."""
    footprint = LightFootprint.from_lights(paper_lights())
    grid = DirectionGrid(16, 64)
    directions = np.concatenate([grid.directions.reshape(-1, 3), [[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]]])
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.2, 0.2, 40), rng.uniform(-0.1, 0.3, 40), rng.uniform(-0.01, 0.02, 40)])
    up = directions[:, 2] > 1e-3
    t = np.where(up, (footprint.height - points[:, None, 2]) / np.where(up, directions[:, 2], 1.0), 0.0)
    hit = points[:, None, :2] + t[..., None] * directions[:, :2]
    col, row = ((hit - footprint.origin) / footprint.pitch).transpose(2, 0, 1)
    dist = map_coordinates(footprint.distance, [row.ravel(), col.ravel()], order=1, mode="constant",
                           cval=np.inf).reshape(row.shape)
    reference = np.where(up, np.clip((1.25 * footprint.spacing - dist) / (0.5 * footprint.spacing), 0, 1), 0)
    got = footprint.coverage(points, directions)
    assert 0.1 < (got > 0).mean() < 0.9                             # both sides of the footprint's edge
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-12)
    assert np.all(got[:, -1] == 0.0)                                 # parallel to the plane: never reaches it


def dome_lights() -> np.ndarray:
    """A light dome's directions (at infinity, homogeneous w = 0) down to 12 deg of elevation."""
    g = DirectionGrid(8, 16).directions.reshape(-1, 3)
    g = g[g[:, 2] > 0.2]
    return np.column_stack([g, np.zeros(len(g))])


@pytest.mark.parametrize("lights, own_directions", [("paper", False), ("paper", True), ("dome", False)])
def test_light_plane_interpolation_equals_scipy_barycentric_weights(lights, own_directions):
    """Per point and direction: scipy's Delaunay point location and its own barycentric transform,
    weights of invalid lights dropped and the rest renormalised, against the compiled walk and sum (1e-12);
    on the paper's point lights with one set of directions or each point's own (a tilted shading frame's),
    and on a dome's lights at infinity. Points in scattered order: long walks, from inside the hull to
    hits beyond it."""
    lights = paper_lights() if lights == "paper" else dome_lights()
    tri = LightTriangulation.from_lights(lights)
    rng = np.random.default_rng(5)
    points = np.column_stack([rng.uniform(-0.05, 0.05, 12), rng.uniform(0.05, 0.15, 12), np.zeros(12)])
    directions = DirectionGrid(16, 64).directions.reshape(-1, 3)
    if own_directions:
        tilted = directions[None] + np.column_stack([rng.uniform(-0.3, 0.3, (12, 2)), np.zeros(12)])[:, None] \
            * directions[None, :, 2:]
        directions = tilted / np.linalg.norm(tilted, axis=-1, keepdims=True)
    values = rng.random((12, len(lights)))
    valid = rng.random((12, len(lights))) > 0.2
    got, defined = tri.interpolate(values, valid, points, directions)
    xy, up = tri.hits(points, directions)
    want, want_defined = np.zeros(got.shape), np.zeros(got.shape, bool)
    for a in range(len(points)):
        simplex = tri.triangulation.find_simplex(xy[a])
        for n in np.flatnonzero((simplex >= 0) & up[min(a, len(up) - 1)]):
            s = simplex[n]
            b = tri.triangulation.transform[s, :2] @ (xy[a, n] - tri.triangulation.transform[s, 2])
            weights = np.append(b, 1 - b.sum()) * valid[a, tri.triangulation.simplices[s]]
            if weights.sum() > 1e-9:
                want[a, n] = weights @ values[a, tri.triangulation.simplices[s]] / weights.sum()
                want_defined[a, n] = True
    np.testing.assert_array_equal(defined, want_defined)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert 0.05 < defined.mean() < 0.95


def test_batched_constrained_least_squares_equals_lstsq_per_system():
    """Eq. 18's weights for many points at once (pseudo-inverse of each KKT system) against numpy's lstsq
    of each system alone, with and without the ridge, including a singular system (two identical
    representatives: the minimum-norm solution, equal weights) and sum(w) = 1 throughout."""
    rng = np.random.default_rng(6)
    a = rng.random((7, 40, 3))
    a[3, :, 2] = a[3, :, 1]                                          # identical representatives
    b = rng.random((7, 40))
    for ridge in (0.0, 1e-3):
        got = cluster.constrained_least_squares(a, b, ridge)
        for i in range(len(a)):
            ata = a[i].T @ a[i]
            if ridge > 0:
                ata = ata + ridge * np.trace(ata) / 3 * np.eye(3)
            kkt = np.block([[2 * ata, np.ones((3, 1))], [np.ones((1, 3)), np.zeros((1, 1))]])
            want = np.linalg.lstsq(kkt, np.append(2 * a[i].T @ b[i], 1.0), rcond=None)[0][:3]
            np.testing.assert_allclose(got[i], want / want.sum(), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got.sum(axis=1), 1.0, rtol=1e-12)
        assert abs(got[3, 1] - got[3, 2]) < 1e-9                     # the singular system splits evenly


def test_separation_in_frame_blocks_equals_one_frame_at_a_time(tmp_path, monkeypatch):
    """separate reads the frames in blocks on threads and writes them as blocks of columns: the outputs are
    bit for bit those of one frame at a time on one thread."""
    from facetsynth.geometry.plane import PlaneGrid
    from facetsynth.stages import separate
    geometry = write_rectified(tmp_path / "cap", one_material((0.2, 0.3, 0.4), (0.5,) * 3), PlaneGrid(0.1, 0.1, 9, 9),
                               rig_lights(5, 4))
    outputs = {}
    for name, block, threads in (("one", 1, 1), ("blocks", 7, 2)):
        monkeypatch.setattr(separate, "FRAME_BLOCK", block)
        out = tmp_path / name
        separate.run(separate.Inputs(geometry=geometry),
                     separate.Outputs(kd=out / "kd.exr", specular=out / "spec.npy", valid=out / "valid.npy",
                                      metrics=out / "m.json"), separate.Settings(heldout_every=0), threads=threads)
        outputs[name] = [np.load(out / f) for f in ("spec.npy", "valid.npy")]
    for a, b in zip(outputs["one"], outputs["blocks"]):
        np.testing.assert_array_equal(a, b)
    assert outputs["one"][0].shape == (81, 33, 3) and outputs["one"][0].any()


def test_frame_blocks_write_each_block_as_one_stretch_and_read_back_points_rows(tmp_path, monkeypatch):
    """separate's scratch (FrameBlocks) holds eq. 8's samples block of frames after block of frames, each block
    one contiguous (P, FRAME_BLOCK, ...) stretch of its file (a block of columns of a (P, F, 3) table touched
    every page at each block); rows() gives any points' (p, F, 3) and (p, F), the last block's padding cut."""
    from facetsynth.stages import separate
    monkeypatch.setattr(separate, "FRAME_BLOCK", 4)
    rng = np.random.default_rng(8)
    rho = rng.random((13, 10, 3)).astype(np.float32)
    valid = rng.random((13, 10)) > 0.3
    blocks = separate.FrameBlocks(tmp_path / "x.eq8", 13, 10)
    for first in (8, 0, 4):                                            # any order; the last block holds 2 frames
        frames = range(first, min(first + 4, 10))
        blocks.put(first, [(rho[:, q], valid[:, q]) for q in frames])
    on_disk = np.load(separate.FrameBlocks.files(tmp_path / "x.eq8")[0], mmap_mode="r")
    assert on_disk.shape == (3, 13, 4, 3)
    np.testing.assert_array_equal(on_disk[1], rho[:, 4:8])            # frames 4-7 of every point, in one stretch
    for points in (slice(0, 13), slice(3, 9), np.array([12, 0, 5])):
        got_rho, got_valid = blocks.rows(points)
        np.testing.assert_array_equal(got_rho, rho[points])
        np.testing.assert_array_equal(got_valid, valid[points])


def test_tiles_on_threads_equal_one_thread(tmp_path):
    """resample and partial_ndf with their tiles on 2 threads write the same bytes as on one, run after run."""
    from facetsynth.geometry.plane import PlaneGrid
    from facetsynth.stages import partial_ndf, resample, separate
    geometry = write_rectified(tmp_path / "cap", one_material((0.2, 0.3, 0.4), (0.5,) * 3), PlaneGrid(0.1, 0.1, 32, 32),
                               rig_lights(9, 8))
    separate.run(separate.Inputs(geometry=geometry),
                 separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "spec.npy", valid=tmp_path / "valid.npy",
                                  metrics=tmp_path / "s.json"), separate.Settings(heldout_every=0))
    runs = []
    for threads in (1, 2, 2, 2):
        out = tmp_path / f"run{len(runs)}"
        resample.run_whole(geometry, tmp_path / "spec.npy", tmp_path / "valid.npy", out / "slice",
                           out / "colour.npy", out / "grid.json", out / "r.json", threads=threads)
        partial_ndf.run_whole(geometry, out / "slice", out / "grid.json", out / "ndf", out / "p.json",
                              partial_ndf.Settings(per_point_view=True), threads=threads)
        runs.append([tables.load(out / "slice"), np.load(out / "colour.npy"), tables.load(out / "ndf", "ndf"),
                     tables.load(out / "ndf", "confidence")])
    assert runs[0][0].shape[0] == 1024 and runs[0][2].any()
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)


def test_one_light_triangulation_shared_by_threads():
    """Two threads interpolating through one fresh triangulation get what one thread gets, 20 times out of 20.
    scipy computes a Delaunay's barycentric transforms on first use and find_simplex reads them without the
    GIL; computed by two threads at once, one read the array the other replaced: wrong slices (7 runs in 20
    here, 1 in 2 on the card scene) until LightTriangulation computed them when it is built."""
    from concurrent.futures import ThreadPoolExecutor
    lights = rig_lights(40, 50)                                      # 2013 lights: a transform worth racing for
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(-0.05, 0.05, 512), rng.uniform(0.05, 0.15, 512), np.zeros(512)])
    values, valid = rng.random((512, len(lights))), np.ones((512, len(lights)), bool)
    directions = DirectionGrid(24, 96).directions.reshape(-1, 3)
    reference = LightTriangulation.from_lights(lights).interpolate(values, valid, points, directions)[0]
    halves = [slice(0, 256), slice(256, 512)]
    for _ in range(20):
        tri = LightTriangulation.from_lights(lights)
        with ThreadPoolExecutor(2) as pool:
            parts = list(pool.map(lambda s: tri.interpolate(values[s], valid[s], points[s], directions)[0], halves))
        np.testing.assert_array_equal(np.concatenate(parts), reference)


def test_the_slice_kept_on_its_support_gives_the_partial_ndfs_of_the_whole_slice(tmp_path, monkeypatch):
    """resample keeps each point's slice only within a cell of the light directions its lights covered
    (coverage.read_around): every cell eq. 11's bilinear lookups read where W > 0. The partial NDFs fitted
    from it are those fitted from the whole slice, bit for bit, on a rig whose lights cover a part of the
    hemisphere."""
    from facetsynth.geometry.plane import PlaneGrid
    from facetsynth.stages import partial_ndf, resample, separate
    geometry = write_rectified(tmp_path / "cap", one_material((0.2, 0.3, 0.4), (0.5,) * 3, alpha=(0.15, 0.3)),
                               PlaneGrid(0.1, 0.1, 16, 16), rig_lights(9, 8))
    separate.run(separate.Inputs(geometry=geometry),
                 separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "spec.npy", valid=tmp_path / "valid.npy",
                                  metrics=tmp_path / "s.json"), separate.Settings(heldout_every=0))
    fitted = []
    for name in ("support", "whole"):
        out = tmp_path / name
        if name == "whole":
            monkeypatch.setattr(resample, "read_around", lambda covered: np.ones_like(covered))
        resample.run_whole(geometry, tmp_path / "spec.npy", tmp_path / "valid.npy", out / "slice", out / "colour.npy",
                           out / "grid.json", out / "r.json")
        partial_ndf.run_whole(geometry, out / "slice", out / "grid.json", out / "ndf", out / "p.json",
                              partial_ndf.Settings(per_point_view=True))
        fitted.append((tables.load(out / "ndf", "ndf"), tables.load(out / "ndf", "confidence"),
                       json.loads((out / "slice/table.json").read_text())["stored_fraction"]))
    (d, w, kept), (d_all, w_all, everything) = fitted
    assert everything == 1.0 and 0.2 < kept < 0.9 and (w > 0).mean() > 0.1
    np.testing.assert_array_equal(d, d_all)
    np.testing.assert_array_equal(w, w_all)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_channel_mean_is_numpys_mean_over_the_channels_to_the_bit(dtype):
    """io.colour.channel_mean (the three channels added in order, the per-point tables' luminance in separate,
    resample, cluster, params and refine) against numpy's mean over the last axis it replaced: equal to the
    bit, dtype included, with NaN and both infinities among the channels, on (N, 3) and (P, F, 3)."""
    from facetsynth.io.colour import channel_mean
    rng = np.random.default_rng(11)
    for shape in ((5000, 3), (40, 120, 3)):
        v = (rng.standard_normal(shape) * 10.0 ** rng.integers(-6, 6, shape)).astype(dtype)
        v.flat[::97], v.flat[::151], v.flat[::203] = np.inf, np.nan, -np.inf
        got = channel_mean(v)
        assert got.dtype == v.mean(axis=-1).dtype
        np.testing.assert_array_equal(got, v.mean(axis=-1))
