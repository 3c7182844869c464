"""Camera model, sample-plane grid and rectification against known geometry."""

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from facetsynth.geometry.camera import Camera
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.capture.rectify import rectified_to_camera, sample_pixels, visible_cells, warp_samples, warp_to_plane
from facetsynth.io.errors import InputError


def warp_sample(image, weight, camera, grid, filtername="triangle"):
    """warp_samples of one image: its cells and the cells that saw the sample."""
    (cells,), seen = warp_samples([image], weight, camera, grid, filtername)
    return cells, seen


@pytest.fixture
def camera():
    # The paper's geometry: 1.0 m away, 0.6 m above the sample centre.
    return Camera.look_at([0.0, -0.8, 0.6], [0.0, 0.0, 0.0], 240, 160, focal_px=0.9 * 240 / 0.1)


def test_look_at_puts_the_target_at_the_principal_point(camera):
    np.testing.assert_allclose(camera.project(np.zeros(3)), [119.5, 79.5], atol=1e-9)
    np.testing.assert_allclose(camera.centre, [0.0, -0.8, 0.6], atol=1e-12)
    # +x of the world is image right; the far edge (+y) is image up.
    right, far = camera.project(np.array([[0.01, 0, 0], [0, 0.01, 0]]))
    assert right[0] > 119.5 and far[1] < 79.5


def test_plane_homography_matches_projection(camera):
    xy = np.random.default_rng(0).uniform(-0.05, 0.05, (100, 2))
    uv1 = np.column_stack([xy, np.ones(100)]) @ camera.plane_homography().T
    np.testing.assert_allclose(uv1[:, :2] / uv1[:, 2:], camera.project(np.column_stack([xy, np.zeros(100)])),
                               atol=1e-9)


def test_pixel_plane_points_invert_projection(camera):
    xy = camera.pixel_plane_points()
    uv = camera.project(np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1))
    cc, rr = np.meshgrid(np.arange(240), np.arange(160))
    np.testing.assert_allclose(uv, np.stack([cc, rr], -1), atol=1e-6)


def test_plane_grid_mapping_round_trip_and_orientation():
    grid = PlaneGrid(0.10, 0.08, cols=50, rows=40)
    np.testing.assert_allclose(grid.to_plane(0, 0), [-0.049, 0.039])        # top-left cell centre
    np.testing.assert_allclose(grid.to_plane(49, 39), [0.049, -0.039])      # bottom-right
    xy = np.random.default_rng(1).uniform(-0.04, 0.04, (20, 2))
    np.testing.assert_allclose(grid.to_plane(*grid.to_pixel(xy[:, 0], xy[:, 1]).T), xy, atol=1e-12)


def test_warp_reproduces_a_smooth_plane_function(camera):
    grid = PlaneGrid(0.1, 0.1, 64, 64)
    def f(xy):
        return np.stack([10 * xy[..., 0] + 1, 20 * xy[..., 1] + 3, np.sin(60 * xy[..., 0]) + 2], -1)

    rectified = warp_to_plane(f(camera.pixel_plane_points()), camera, grid)
    truth = f(grid.cell_centres())
    assert visible_cells(camera, grid).all()
    err = np.abs(rectified - truth)
    dx, dy = grid.cell_size
    assert err[..., 0].max() / 10 < 0.03 * dx   # position error along x, under 0.03 cells
    assert err[..., 1].max() / 20 < 0.05 * dy   # along y (foreshortened by the 53 deg view)
    assert err[..., 2].max() < 2e-3


def test_cells_outside_the_image_are_reported_and_black(camera):
    grid = PlaneGrid(0.3, 0.3, 30, 30)   # larger than the camera's field of view
    visible = visible_cells(camera, grid)
    assert 0 < visible.mean() < 1
    rectified = warp_to_plane(np.ones((160, 240, 3)), camera, grid)
    assert np.isfinite(rectified).all()
    # Away from the image border (one cell of filter support), outside cells are black.
    dilated = binary_dilation(visible, np.ones((5, 5), bool))
    assert np.all(rectified[~dilated] == 0)


def test_cells_at_the_samples_edge_average_the_samples_pixels_alone(camera):
    """A 0.1 m sample of radiance 2 on a background of 0.5, pixels across its edge mixed by their coverage (16 x 16
    sub-pixels), at native resolution: every cell, the edge rows and columns too, is 2 to 0.5 %. The plain warp
    mixes the edge pixels and the background into them (the demo's far row of points had half the truth's kd and
    ks: the test can fail)."""
    width, s = 0.1, 16
    xy = camera.pixel_plane_points(s)
    inside = (np.abs(xy) <= width / 2).all(axis=-1).reshape(160, s, 240, s).mean(axis=(1, 3))
    image = np.repeat((0.5 + 1.5 * inside)[..., None], 3, axis=-1)
    weight = sample_pixels(camera, width, width)
    assert set(np.unique(weight)) == {0.0, 1.0} and np.all(inside[weight == 1] == 1)
    assert np.all(weight[(inside > 0) & (inside < 1)] == 0)      # no pixel across the edge is taken
    grid = PlaneGrid(width, width, 168, 168)
    cells, seen = warp_sample(image, weight, camera, grid)
    assert seen.all()
    np.testing.assert_allclose(cells, 2.0, rtol=5e-3)
    plain = warp_to_plane(image, camera, grid)
    assert plain[0].min() < 1.8 and plain[:, 0].min() < 1.8
    # a cell no sample pixel reaches: 0 and not seen
    cells, seen = warp_sample(image, np.zeros_like(weight), camera, grid)
    assert not seen.any() and np.all(cells == 0)


def test_frames_warped_together_are_each_frames_own_warp_to_the_bit(camera):
    """rectify warps WARP_FRAMES frames in one OpenImageIO warp (their channels side by side, the sample's weight
    once): each frame's cells and the cells that saw the sample are bitwise those of its own warp, for
    frames of 4 and 3 channels (RGB and the saturated mask, RGB alone) under the filters rectify offers."""
    rng = np.random.default_rng(5)
    images = [rng.random((160, 240, c)).astype(np.float32) for c in (4, 3, 4)]
    images[2][..., 3] = rng.random((160, 240)) > 0.9                    # a saturated mask of 0 and 1
    weight = sample_pixels(camera, 0.1, 0.1)
    grid = PlaneGrid(0.14, 0.14, 96, 96)                                 # beyond the sample: cells that see none
    for filtername in ("triangle", "box", "gaussian"):
        together, seen = warp_samples(images, weight, camera, grid, filtername)
        for image, cells in zip(images, together):
            alone, seen_alone = warp_sample(image, weight, camera, grid, filtername)
            assert cells.shape == (96, 96, image.shape[-1])
            np.testing.assert_array_equal(cells, alone)
            np.testing.assert_array_equal(seen, seen_alone)
        assert seen.any() and not seen.all()


def test_sample_pixels_whole_and_by_centre_in_chunks(camera):
    """One function counts the pixels on the sample two ways: ``whole`` (every corner on it: rectify's weights,
    the self-check's mask) and by the pixel's centre (rectify's native resolution, hdr's and capture's statistics);
    the whole pixels are a subset of the centres', short of them by about one ring of edge pixels, and computing
    them a few rows at a time changes nothing."""
    width = 0.1
    whole, centre = sample_pixels(camera, width, width), sample_pixels(camera, width, width, whole=False)
    assert whole.dtype == bool and not (whole & ~centre).any()
    xy = camera.pixel_plane_points(1)[..., :2]
    np.testing.assert_array_equal(centre, (np.abs(xy) <= width / 2).all(axis=-1))
    ring = centre.sum() - whole.sum()
    assert 0 < ring < 2 * (centre.any(axis=0).sum() + centre.any(axis=1).sum())
    for rows in (1, 7):
        np.testing.assert_array_equal(sample_pixels(camera, width, width, chunk_rows=rows), whole)
        np.testing.assert_array_equal(sample_pixels(camera, width, width, whole=False, chunk_rows=rows), centre)


def test_a_camera_that_sees_only_the_sample_takes_every_pixel():
    """A dome's capture (rti.lp's stated default: orthographic, top-down, the image the sample, 0.1 mm pixels):
    every pixel sees the sample alone, its outer corners on the edge up to rounding, and every cell of the native
    grid is seen (at first the outer rows of pixels fell outside by rounding: 619 of the leaf's 96 100 points had
    no sample)."""
    width, height, pixel = 310, 200, 1e-4
    camera = Camera(width, height, np.array([[1 / pixel, 0, (width - 1) / 2], [0, 1 / pixel, (height - 1) / 2],
                                             [0, 0, 1]]), np.diag([1.0, -1.0, -1.0]), np.array([0, 0, 1.0]),
                    projection="orthographic")
    assert sample_pixels(camera, width * pixel, height * pixel).all()
    cells, seen = warp_sample(np.full((height, width, 3), 0.7), np.ones((height, width)), camera,
                              PlaneGrid(width * pixel, height * pixel, width, height))
    assert seen.all()
    np.testing.assert_allclose(cells, 0.7, rtol=1e-6)


def test_distorted_camera_is_refused_with_a_clear_error(camera):
    distorted = Camera(camera.width, camera.height, camera.K, camera.R, camera.t, np.array([0.1, 0, 0, 0, 0]))
    with pytest.raises(InputError, match="distortion"):
        rectified_to_camera(distorted, PlaneGrid(0.1, 0.1, 8, 8))


def nadir_camera(pixels: int = 80, focal: float = 500.0, distance: float = 1.0, x: float = 0.0) -> Camera:
    """A camera straight above the plane: one pixel covers distance / focal metres."""
    K = np.array([[focal, 0.0, (pixels - 1) / 2], [0.0, focal, (pixels - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(pixels, pixels, K, np.diag([1.0, -1.0, -1.0]), np.array([-x, 0.0, distance]), np.zeros(5))


def test_native_resolution_has_as_many_cells_as_pixels_see_the_sample(camera):
    from facetsynth.capture.rectify import native_resolution
    flat = nadir_camera()                                    # 2 mm per pixel: a 0.1 m sample is 50 pixels wide
    assert native_resolution(flat, 0.1, 0.1) == 50
    assert native_resolution(flat, 0.1, 0.05) == 50          # half the rows, the same cells across
    assert native_resolution(nadir_camera(focal=1000.0), 0.1, 0.1) == 80   # 100 px wide, cut by the 80 px image
    # the demo camera: 216 px across in x, foreshortened by about cos(53 deg) in y: sqrt(216 x 130)
    assert 160 <= native_resolution(camera, 0.1, 0.1) <= 172
    with pytest.raises(InputError, match="sees no part of the sample"):
        native_resolution(nadir_camera(x=5.0), 0.1, 0.1)
