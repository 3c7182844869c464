"""Camera intrinsics and pose from checkerboard images (Zhang 2000, as paper 002 sec. 4).

Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000: each view of a
planar target gives a homography H = K [r1 r2 t] (the plane's z = 0), two constraints on the image of
the absolute conic; three or more views at different tilts fix K, and a non-linear refinement of all
reprojection errors gives K, the lens distortion and each view's pose (OpenCV ``calibrateCamera``).
The rig's pose is then the pose of one board lying on the sample plane at a known placement
(``solvePnP`` with the calibrated K): X_cam = R X + t, the convention of :class:`facetsynth.geometry.camera.Camera`.

Corners: ``findChessboardCorners`` then ``cornerSubPix`` (the saddle point of the intensity, to a few
hundredths of a pixel on a sharp board). A board has ``inner_corners`` = (columns, rows) corners where
four squares meet, ``square`` metres apart; board coordinates (x along columns, y along rows, z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..io.errors import InputError

# The lens models of calibrateCamera this module offers: "none" (an ideal pinhole: what rectify accepts),
# "radial" (k1, k2), "full" (k1, k2, p1, p2, k3).
_FLAGS = {
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "radial": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "full": 0,
}
LENS_MODELS = tuple(_FLAGS)


@dataclass(frozen=True)
class Board:
    """A checkerboard: ``inner_corners`` (columns, rows) and the ``square`` side in metres."""

    inner_corners: tuple[int, int]
    square: float

    def object_points(self) -> np.ndarray:
        """(N, 3) board coordinates of the inner corners, row-major (OpenCV's order), z = 0."""
        cols, rows = self.inner_corners
        gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
        return np.stack([gx.ravel(), gy.ravel(), np.zeros(cols * rows)], axis=-1) * self.square


@dataclass(frozen=True)
class Intrinsics:
    """What :func:`calibrate_intrinsics` found: K, distortion, RMS and per-view reprojection (px)."""

    K: np.ndarray
    distortion: np.ndarray
    rms_px: float
    per_view_px: list[float]


def to_grey(image: np.ndarray) -> np.ndarray:
    """Float32 grey (H, W): the mean of the channels."""
    return (image.mean(axis=-1) if image.ndim == 3 else image).astype(np.float32)


def to_gray8(image: np.ndarray, saturation: float | None) -> np.ndarray:
    """An 8-bit grey image for the corner finder: linear values scaled so that ``saturation`` (or the image's
    99.9th percentile without one) is 255."""
    if image.dtype == np.uint8:
        return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    grey = image.mean(axis=-1) if image.ndim == 3 else image
    top = saturation if saturation else float(np.percentile(grey, 99.9)) or 1.0
    return np.clip(np.rint(grey / top * 255.0), 0, 255).astype(np.uint8)


def find_corners(grey: np.ndarray, board: Board, file: str | Path, window: int = 4,
                 fine: np.ndarray | None = None) -> np.ndarray:
    """Sub-pixel inner corners (N, 2) of ``board`` in an 8-bit image, OpenCV's order; refined on ``fine``
    (the same image as float32 grey, free of 8-bit rounding) when given.

    Raises InputError naming ``file`` when no complete board is found (all corners must be visible).
    ``window``: half-size of cornerSubPix's search window in pixels (below half a square's image).
    """
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, tuple(board.inner_corners), flags=flags)
    if not found:
        raise InputError(file, f"no checkerboard of {board.inner_corners[0]} x {board.inner_corners[1]} inner "
                               "corners found (the whole board must be in view, sharp and evenly lit)")
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    refine = grey if fine is None else np.ascontiguousarray(fine, np.float32)
    corners = cv2.cornerSubPix(refine, corners, (window, window), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)


def calibrate_intrinsics(views: list[np.ndarray], board: Board | list[Board], size: tuple[int, int],
                         lens: str = "none", fix_principal_point: bool = True) -> Intrinsics:
    """K and distortion from the corners (N, 2) of several board views (Zhang 2000, ``calibrateCamera``);
    ``board``: the board of every view, or one per view.

    ``size`` = (width, height). ``fix_principal_point``: keep the principal point at the image centre
    ((W-1)/2, (H-1)/2): a narrow lens (the rig's: a few degrees of field) does not constrain it, and an error
    there is absorbed by the pose's rotation. Square pixels (fixed aspect ratio) always.
    """
    width, height = size
    boards = board if isinstance(board, list) else [board] * len(views)
    obj = [b.object_points().astype(np.float32) for b in boards]
    img = [v.astype(np.float32).reshape(-1, 1, 2) for v in views]
    K0 = cv2.initCameraMatrix2D(obj, img, (width, height), 1.0)
    K0[0, 2], K0[1, 2] = (width - 1) / 2, (height - 1) / 2
    flags = _FLAGS[lens] | cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO
    if fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (width, height), K0, np.zeros(5), flags=flags,
                                                     criteria=criteria)
    per_view = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - i) ** 2, axis=-1)))))
    return Intrinsics(K=np.asarray(K, float), distortion=np.asarray(dist, float).ravel()[:5], rms_px=float(rms),
                      per_view_px=per_view)


def board_to_world(board: Board, origin, x_axis, y_axis) -> np.ndarray:
    """(N, 3) world positions of the corners of a board lying with its corner 0 at ``origin`` and its columns
    and rows running along the unit vectors ``x_axis`` and ``y_axis``."""
    local = board.object_points()
    axes = np.stack([np.asarray(x_axis, float), np.asarray(y_axis, float)])
    return np.asarray(origin, float) + local[:, :2] @ axes


def solve_pose(corners: np.ndarray, world: np.ndarray, K: np.ndarray, distortion: np.ndarray, board: Board,
               prior_centre: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """R, t (X_cam = R X + t) and the RMS reprojection (px) from the corners (N, 2) of a board whose corners
    are at ``world`` (N, 3) (``solvePnP``, iterative, on the calibrated K).

    The corner finder may list a board's rows or columns from either end: the four orders are solved and
    the one whose camera centre is nearest ``prior_centre`` (roughly where the camera is: the rig
    description's) is kept; without a prior, the one with the camera above the plane (z > 0) and the smaller
    reprojection error (a mirrored order puts the camera below the plane).
    """
    cols, rows = board.inner_corners
    grid = corners.reshape(rows, cols, 2)
    best = None
    for order in (grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]):
        order = np.ascontiguousarray(order.reshape(-1, 2))
        ok, rvec, tvec = cv2.solvePnP(world, order, K, distortion, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(world, order, K, distortion, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        t = tvec.ravel()
        proj, _ = cv2.projectPoints(world, rvec, tvec, K, distortion)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - order) ** 2, axis=-1))))
        centre = -R.T @ t
        if prior_centre is not None:
            score = float(np.linalg.norm(centre - prior_centre))
        else:
            score = rms + (1e9 if centre[2] <= 0 else 0.0)
        if best is None or score < best[0]:
            best = (score, R, t, rms)
    if best is None:
        raise InputError(None, "solvePnP found no pose for the board on the sample plane")
    return best[1], best[2], best[3]
