"""The rectify stage's frames against a virtual capture's true scene: registration and radiance."""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..capture import manifest
from ..geometry.camera import Camera
from .metrics import marker_centroids, relative_errors
from ..geometry.plane import PlaneGrid
from ..models.render import radiance
from ..truth.scene import Scene

log = logging.getLogger(__name__)


def truth_scores(capture: dict, camera: Camera, grid: PlaneGrid, visible: np.ndarray,
                 rectified: Callable[[int], np.ndarray]) -> dict:
    """A virtual capture's rectified frames (``rectified(q)``: frame q's R, G, B on ``grid``, (rows, cols, 3))
    against its true scene (:func:`_accuracy`): the registration error on the markers and the radiance error,
    logged; {} for a real capture."""
    if not manifest.has_truth(capture):
        return {}
    scores = _accuracy(Scene.load(capture["truth"]["scene"]), grid, camera.view_point, capture, rectified, visible)
    log.info("registration error %.3f px (max %.3f), radiance median rel. error %.4f",
             scores["registration_error_px"], scores["registration_error_px_max"], scores["radiance_median_rel_error"])
    return scores


def _accuracy(scene: Scene, grid: PlaneGrid, view: np.ndarray, capture: dict, rectified: Callable[[int], np.ndarray],
              visible: np.ndarray) -> dict:
    """Registration error on the scene's markers; radiance error against the truth on the grid; on 64 frames
    (evenly strided)."""
    maps = scene.parameters(grid.cell_centres())
    points = grid.points3d()
    interior = visible & ~_near_edges(maps.region)
    stride = max(1, len(capture["frames"]) // 64)
    luminance, errors = [], []
    for q in range(0, len(capture["frames"]), stride):
        light = capture["frames"][q]["light"]
        rgb = rectified(q)
        luminance.append(rgb.mean(axis=-1))
        truth = radiance(points, maps.rho, manifest.light_point(light), light["intensity"], view)
        errors.append(relative_errors(rgb, truth, interior[..., None] & (truth > 1e-3 * truth.max())))
    background = np.median(np.stack(luminance), axis=0)
    expected = grid.to_pixel(scene.marker_positions[:, 0], scene.marker_positions[:, 1])
    radius_px = scene.marker_radius / grid.cell_size[0]
    found = marker_centroids(background, expected, radius_px)
    distance = np.hypot(*(found - expected).T)
    distance = distance[np.isfinite(distance)]
    return {"registration_error_px": float(distance.mean()) if distance.size else None,
            "registration_error_px_max": float(distance.max()) if distance.size else None,
            "markers_found": int(distance.size),
            "radiance_median_rel_error": float(np.median(np.concatenate(errors)))}


def _near_edges(region: np.ndarray) -> np.ndarray:
    """Cells within one cell of a material edge or marker, where resampling blurs the truth."""
    edge = np.zeros(region.shape, dtype=bool)
    edge[1:, :] |= region[1:, :] != region[:-1, :]
    edge[:-1, :] |= region[1:, :] != region[:-1, :]
    edge[:, 1:] |= region[:, 1:] != region[:, :-1]
    edge[:, :-1] |= region[:, 1:] != region[:, :-1]
    return edge
