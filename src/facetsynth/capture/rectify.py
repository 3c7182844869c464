"""Rectification: map camera images onto the regular sample-plane grid (paper 002 sec. 4).

The sample plane z = 0 is imaged by the homography H = K [r1 r2 t]; composing
it with the grid's (col, row) -> (x, y) matrix gives the map from rectified
pixels to camera pixels, and OpenImageIO warps each frame with it.
"""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio

from ..geometry.camera import Camera
from ..io.errors import InputError
from ..geometry.plane import PlaneGrid

# OpenCV puts pixel (0, 0)'s centre at (0, 0); OpenImageIO at (0.5, 0.5).
_CV_TO_OIIO = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
# A cell whose filter gave the sample's own pixels less weight than this saw none (its samples are invalid).
MIN_COVER = 1e-3
# Pixel corners this far (relative to the sample's size) beyond its edge count as on it: a dome's capture whose
# image is the sample (rti.lp) puts the outer corners on the edge, up to rounding.
EDGE_SLACK = 1e-9


def rectified_to_camera(camera: Camera, grid: PlaneGrid) -> np.ndarray:
    """3x3 M with (col, row, 1)_camera ~ M (col, row, 1)_rectified (OpenCV pixel centres)."""
    if camera.has_distortion:
        raise InputError(None, "rectify: lens distortion is not supported yet; undistort the frames "
                               "first and set camera/distortion to zeros")
    return camera.plane_homography() @ grid.pixel_to_plane()


def warp_to_plane(image: np.ndarray, camera: Camera, grid: PlaneGrid, filtername: str = "triangle") -> np.ndarray:
    """Resample a camera image (H, W, C) onto the sample-plane grid: (rows, cols, C).

    Cells whose footprint falls outside the image are 0 (see :func:`visible_cells`).
    """
    m = _CV_TO_OIIO @ rectified_to_camera(camera, grid) @ np.linalg.inv(_CV_TO_OIIO)
    src_to_dst = np.linalg.inv(m)
    src = oiio.ImageBuf(np.ascontiguousarray(image, dtype=np.float32))
    roi = oiio.ROI(0, grid.cols, 0, grid.rows, 0, 1, 0, image.shape[-1])
    # OIIO wants a row-vector matrix (the transpose) as float32; float64 arrays give wrong pixels.
    dst = oiio.ImageBufAlgo.warp(src, tuple(src_to_dst.T.astype(np.float32).ravel().tolist()),
                                 filtername=filtername, wrap="black", roi=roi)
    if dst.has_error:
        raise RuntimeError(f"OpenImageIO warp failed: {dst.geterror()}")
    return dst.get_pixels(oiio.FLOAT).reshape(grid.rows, grid.cols, image.shape[-1])


def sample_pixels(camera: Camera, width: float, height: float, whole: bool = True,
                  chunk_rows: int = 512) -> np.ndarray:
    """(H, W) bool: the pixels that see the sample, the ``width`` x ``height`` about the origin of the plane,
    ahead of the camera. ``whole``: all four corners of the pixel on it, so the whole pixel is (the plane's image
    of the rectangle is convex; corners on the edge count, :data:`EDGE_SLACK`): a pixel across the sample's edge
    mixes it with the background and is no measurement of either (issue 29: the demo's far row of points, half
    the truth's kd and ks, was drawn by such pixels). Otherwise the pixel's centre on it (the pixels rectify's
    native resolution counts, and hdr's and capture's statistics read). Computed ``chunk_rows`` rows at a time
    (a 50-megapixel camera's plane points would take 1.2 GB at once)."""
    to_plane = np.linalg.inv(camera.plane_homography())
    offset = 0.5 if whole else 0.0
    slack = EDGE_SLACK * max(width, height) if whole else 0.0      # rounding: on the edge
    cols = np.arange(camera.width + int(whole)) - offset
    out = np.zeros((camera.height, camera.width), bool)
    for start in range(0, camera.height, chunk_rows):
        stop = min(start + chunk_rows, camera.height)
        c, r = np.meshgrid(cols, np.arange(start, stop + int(whole)) - offset)
        points = np.stack([c, r, np.ones_like(c)], axis=-1) @ to_plane.T
        with np.errstate(divide="ignore", invalid="ignore"):
            inside = on_sample(camera, points[..., :2] / points[..., 2:], width, height, slack)
        out[start:stop] = (inside[:-1, :-1] & inside[:-1, 1:] & inside[1:, :-1] & inside[1:, 1:]) if whole else inside
    return out


def on_sample(camera: Camera, xy: np.ndarray, width: float, height: float, slack: float = 0.0) -> np.ndarray:
    """(...) bool: the plane points ``xy`` (..., 2) that a ray of ``camera`` meets ahead of it (every ray of an
    orthographic camera) inside the sample's ``width`` x ``height`` about the origin, widened by ``slack``;
    non-finite points are not."""
    with np.errstate(invalid="ignore", over="ignore"):
        points = np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)
        ahead = True if camera.orthographic else (points @ camera.R.T + camera.t)[..., 2] > 0
        return ahead & (np.abs(xy[..., 0]) <= width / 2 + slack) & (np.abs(xy[..., 1]) <= height / 2 + slack)


def warp_samples(images: list[np.ndarray], weight: np.ndarray, camera: Camera, grid: PlaneGrid,
                 filtername: str = "triangle") -> tuple[list[np.ndarray], np.ndarray]:
    """:func:`warp_to_plane` of the pixels that see the sample alone (``weight`` (H, W), :func:`sample_pixels`),
    renormalised (normalised convolution: the warp of ``image * weight`` over that of ``weight``): a cell at
    the sample's or the image's edge is the filter's average of the sample's pixels, not of the sample, the
    background and the black beyond the image. Returns each image's cells (rows, cols, C) and whether each cell
    saw any such pixel (rows, cols) (cells that did not are 0).

    Several images (H, W, C) seen through one camera go in one warp: OpenImageIO's warp spends its time on each
    cell's filter weights, which every channel shares (at 256^2 cells, 29 ms for one frame's 5 channels, 75 ms
    for 8 frames' 33), and computes each channel alone, so every image's cells are bitwise those of its own
    warp."""
    w = np.asarray(weight, np.float32)[..., None]
    warped = warp_to_plane(np.dstack([image * w for image in images] + [w]), camera, grid, filtername)
    cover = warped[..., -1:]
    seen = cover[..., 0] > MIN_COVER
    bounds = np.cumsum([0] + [image.shape[-1] for image in images])
    return [np.divide(warped[..., a:b], cover, out=np.zeros_like(warped[..., a:b]), where=seen[..., None])
            for a, b in zip(bounds[:-1], bounds[1:])], seen


def visible_cells(camera: Camera, grid: PlaneGrid) -> np.ndarray:
    """(rows, cols) True where a cell's centre projects inside the camera image."""
    uv = camera.project(grid.points3d())
    return ((uv[..., 0] >= -0.5) & (uv[..., 0] <= camera.width - 0.5)
            & (uv[..., 1] >= -0.5) & (uv[..., 1] <= camera.height - 0.5))


def native_resolution(camera: Camera, width: float, height: float) -> int:
    """Grid cells across the sample's width such that the grid has as many cells as camera pixels see the
    sample (``rectify.resolution: auto``): no more points than measured, none fewer. Pixels count when the
    ray through their centre meets the plane, ahead of the camera, inside the sample's width x height.
    Square cells, rows from the aspect (:func:`facetsynth.stages.rectify.run`)."""
    pixels = int(on_sample(camera, camera.pixel_plane_points(1), width, height).sum())
    if pixels == 0:
        raise InputError(None, "rectify.resolution auto: the camera sees no part of the sample "
                               f"({width} x {height} m about the origin): check the manifest's camera")
    return max(1, int(round(np.sqrt(pixels * width / height))))
