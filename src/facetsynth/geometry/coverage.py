"""Which light directions a capture sampled, per sample point (used in W, paper 002 eq. 12).

The rig's lights lie in a plane above the sample (the LED array at height h,
sec. 4); a point x saw light from direction i when the ray from x along i
meets that plane near a light position. The footprint of the lights is
rasterised once per capture as a distance map (directional lights: on the
plane z = 1 seen from the origin, :func:`facetsynth.geometry.lightplane.light_plane`); coverage is 1 within 0.75
light spacings of a light (every point inside the array), falling to 0 at
1.25 spacings. Captures whose lights are not near one plane are measured at
the lights' median height: an approximation, stated in the stage's log.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from .lightplane import light_plane, seen_from


@dataclass(frozen=True)
class LightFootprint:
    distance: np.ndarray   # (rows, cols) distance to the nearest light, metres
    origin: np.ndarray     # (x, y) of raster cell (0, 0)
    pitch: float           # raster cell size, metres
    height: float          # plane of the lights, z
    spacing: float         # median nearest-neighbour distance between lights
    at_infinity: bool = False

    @classmethod
    def from_lights(cls, lights: np.ndarray) -> "LightFootprint":
        """From the lights (F, 4) homogeneous, or positions (F, 3)."""
        positions, at_infinity = light_plane(lights)
        xy = positions[:, :2]
        spacing = float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1])) if len(xy) > 1 else 0.01
        spacing = max(spacing, 1e-4)
        pitch = spacing / 4
        origin = xy.min(axis=0) - 2 * spacing
        shape = np.ceil((xy.max(axis=0) + 2 * spacing - origin) / pitch).astype(int) + 1
        lit = np.ones((shape[1], shape[0]), bool)
        cols, rows = np.round((xy - origin) / pitch).astype(int).T
        lit[rows, cols] = False
        return cls(distance_transform_edt(lit) * pitch, origin, pitch, float(np.median(positions[:, 2])), spacing,
                   at_infinity)

    def coverage(self, points: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Coverage in [0, 1] of world directions (N, 3), or each point's own (P, N, 3), seen from points
        (P, 3): (P, N)."""
        directions = np.asarray(directions, float)
        return _coverage(self.distance, self.origin, self.pitch, self.height, self.spacing,
                         seen_from(points, self.at_infinity),
                         directions if directions.ndim == 3 else directions[None])

    def on_grid(self, points: np.ndarray, grid, frames: np.ndarray | None = None) -> np.ndarray:
        """Coverage of the directions of a :class:`facetsynth.geometry.grid.DirectionGrid` seen from points (P, 3):
        (P, T, F); with shading ``frames`` (P, 3, 3) (:func:`facetsynth.fit.normals.shading_frames`) the grid is
        each point's own frame's, turned to the world first."""
        return self.coverage(points, world_grid(grid, frames)).reshape((-1,) + grid.shape)


def world_grid(grid, frames: np.ndarray | None = None) -> np.ndarray:
    """The grid's directions (N, 3), or with shading ``frames`` (P, 3, 3) each point's grid turned to the world,
    R^T d (P, N, 3)."""
    directions = grid.directions.reshape(-1, 3)
    return directions if frames is None else directions @ frames    # sum_j d_j R_ji (a stacked matmul: 15 x einsum)


def read_around(covered: np.ndarray) -> np.ndarray:
    """Cells (P, T, F) bool within one cell of a ``covered`` one (phi periodic, theta clamped): every cell a
    bilinear lookup (:func:`facetsynth.geometry.grid.bilinear_at`) with a covered corner of nonzero weight reads. A
    slice is kept there (:mod:`facetsynth.io.tables`): eq. 11 reads it only where W, which carries the
    coverage, is positive."""
    around = covered | np.roll(covered, 1, axis=-1) | np.roll(covered, -1, axis=-1)
    out = around.copy()
    out[:, 1:] |= around[:, :-1]
    out[:, :-1] |= around[:, 1:]
    return out


@numba.njit(cache=True, nogil=True)
def _coverage(distance: np.ndarray, origin: np.ndarray, pitch: float, height: float, spacing: float,
              points: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Per point and direction (``directions`` (1 or P, N, 3): shared, or each point's): where the ray meets the
    lights' plane, the distance map there (linear interpolation; beyond the raster: infinitely far), as coverage
    1 within 0.75 spacings, 0 beyond 1.25."""
    rows, cols = distance.shape
    out = np.zeros((points.shape[0], directions.shape[1]))
    shared = directions.shape[0] == 1
    for a in range(points.shape[0]):
        d = directions[0] if shared else directions[a]
        for n in range(directions.shape[1]):
            dz = d[n, 2]
            if dz <= 1e-3:                                   # never reaches the plane
                continue
            t = (height - points[a, 2]) / dz
            col = (points[a, 0] + t * d[n, 0] - origin[0]) / pitch
            row = (points[a, 1] + t * d[n, 1] - origin[1]) / pitch
            if not (0.0 <= row <= rows - 1 and 0.0 <= col <= cols - 1):
                continue
            r0, c0 = min(int(row), rows - 2), min(int(col), cols - 2)
            fr, fc = row - r0, col - c0
            dist = ((1 - fr) * ((1 - fc) * distance[r0, c0] + fc * distance[r0, c0 + 1])
                    + fr * ((1 - fc) * distance[r0 + 1, c0] + fc * distance[r0 + 1, c0 + 1]))
            out[a, n] = min(max((1.25 * spacing - dist) / (0.5 * spacing), 0.0), 1.0)
    return out
