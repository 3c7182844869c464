"""Which light directions a capture sampled, per sample point (used in W, paper 002 eq. 12).

The rig's lights lie in a plane above the sample (the LED array at height h,
sec. 4); a point x saw light from direction i when the ray from x along i
meets that plane near a light position. The footprint of the lights is
rasterised once per capture as a distance map; coverage is 1 within 0.75
light spacings of a light (every point inside the array), falling to 0 at
1.25 spacings. Captures whose lights are not near one plane are measured at
the lights' median height: an approximation, stated in the stage's log.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, map_coordinates
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class LightFootprint:
    distance: np.ndarray   # (rows, cols) distance to the nearest light, metres
    origin: np.ndarray     # (x, y) of raster cell (0, 0)
    pitch: float           # raster cell size, metres
    height: float          # plane of the lights, z
    spacing: float         # median nearest-neighbour distance between lights

    @classmethod
    def from_lights(cls, positions: np.ndarray) -> "LightFootprint":
        xy = positions[:, :2]
        spacing = float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1])) if len(xy) > 1 else 0.01
        spacing = max(spacing, 1e-4)
        pitch = spacing / 4
        origin = xy.min(axis=0) - 2 * spacing
        shape = np.ceil((xy.max(axis=0) + 2 * spacing - origin) / pitch).astype(int) + 1
        lit = np.ones((shape[1], shape[0]), bool)
        cols, rows = np.round((xy - origin) / pitch).astype(int).T
        lit[rows, cols] = False
        return cls(distance_transform_edt(lit) * pitch, origin, pitch, float(np.median(positions[:, 2])), spacing)

    def coverage(self, points: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Coverage in [0, 1] of directions (..., N, 3) seen from points (..., 3): (..., N)."""
        up = directions[..., 2] > 1e-3
        t = np.where(up, (self.height - points[..., None, 2]) / np.where(up, directions[..., 2], 1.0), 0.0)
        hit = points[..., None, :2] + t[..., None] * directions[..., :2]
        col, row = ((hit - self.origin) / self.pitch).transpose(-1, *range(hit.ndim - 1))
        dist = map_coordinates(self.distance, [row.ravel(), col.ravel()], order=1, mode="constant",
                               cval=np.inf).reshape(row.shape)
        return np.where(up, np.clip((1.25 * self.spacing - dist) / (0.5 * self.spacing), 0.0, 1.0), 0.0)
