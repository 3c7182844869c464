"""Interpolation of a point's light samples in the plane of the lights (paper 002 sec. 4, resampling).

The rig's lights lie in one plane above the sample (the LED array at height
h, scanned along y). Seen from a sample point x, the light direction i meets
that plane at

    X(x, i) = x + (h - x_z) i / i_z,

so the sample of light q sits at the light's own position P_q, the same for
every point. Interpolating the samples linearly over one triangulation of
the light positions (scipy's Delaunay) is therefore the same operation at
every point; only the query X moves with x. Splatting each point's samples
into a grid of directions and filling the gaps with push-pull (Gortler et
al. 1996) is not: where the lights are sparser than the grid (a glossy lobe
at the paper's 480 lights is one or two lights wide), which cells a sample
lands in, and how much push-pull blurs it, depends on where x sits
relative to the LEDs. That made two points of one material get different
partial NDFs, in stripes with the LED pitch (docs/decisions.md,
"Sampling-invariant partial NDFs"). Beyond the lights' convex hull the
caller fills the table by push-pull from the interpolated cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import Delaunay, QhullError

UP = 1e-3   # directions with i_z at or below this never reach the plane of the lights


@dataclass(frozen=True)
class LightTriangulation:
    """A Delaunay triangulation of the lights' (x, y) in their plane z = ``height`` (the median light z)."""

    triangulation: Delaunay
    height: float

    @classmethod
    def from_lights(cls, positions: np.ndarray) -> "LightTriangulation":
        positions = np.asarray(positions, float)
        xy = positions[:, :2]
        problem = (f"the {len(positions)} light(s) do not span an area of their plane (at least 3 lights, not all "
                   "on one line, are needed)")
        if len(xy) < 3 or np.linalg.matrix_rank(xy - xy.mean(axis=0), tol=1e-9) < 2:
            raise ValueError(problem)
        try:
            triangulation = Delaunay(xy)
        except (QhullError, ValueError) as exc:
            raise ValueError(f"{problem}: {str(exc).strip().splitlines()[0]}") from None
        # scipy computes the barycentric transforms on first use and find_simplex reads them without the GIL:
        # computed here, once, so that threads sharing the triangulation never replace them under each other
        triangulation.transform
        return cls(triangulation, float(np.median(positions[:, 2])))

    def hits(self, points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """X(x, i) (P, N, 2) in the lights' plane for points (P, 3) and directions (N, 3), and whether the
        direction reaches the plane at all (i_z > UP) (N,)."""
        up = directions[:, 2] > UP
        t = (self.height - points[:, None, 2]) / np.where(up, directions[:, 2], 1.0)[None]
        return points[:, None, :2] + t[..., None] * directions[None, :, :2], up

    def interpolate(self, values: np.ndarray, valid: np.ndarray, points: np.ndarray,
                    directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point, its light samples ``values`` (P, F) interpolated linearly at ``directions`` (N, 3).

        Invalid samples (``valid`` (P, F) False: saturated, unseen) are left
        out and the remaining barycentric weights renormalised. Returns
        (values (P, N), defined (P, N)): ``defined`` is False beyond the
        lights' hull, for directions that never reach the lights' plane, and
        where every light of the triangle is invalid; there the value is 0.
        """
        n_points, n_dirs = len(points), len(directions)
        xy, up = self.hits(np.asarray(points, float), np.asarray(directions, float))
        simplex = self.triangulation.find_simplex(xy.reshape(-1, 2)).reshape(n_points, n_dirs)
        simplex[:, ~up] = -1
        return _barycentric_sum(np.asarray(values, float), np.asarray(valid, bool), xy, simplex,
                                self.triangulation.transform, self.triangulation.simplices)


@numba.njit(cache=True, nogil=True)
def _barycentric_sum(values: np.ndarray, valid: np.ndarray, xy: np.ndarray, simplex: np.ndarray,
                     transform: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of each point's valid samples (P, F) at its hits ``xy`` (P, N, 2) in the triangles
    ``simplex`` (P, N) (-1: none) of a Delaunay triangulation (scipy's ``transform`` and ``simplices``), the
    barycentric weights of invalid lights dropped and the rest renormalised."""
    n_points, n_dirs = simplex.shape
    out = np.zeros((n_points, n_dirs))
    defined = np.zeros((n_points, n_dirs), np.bool_)
    for a in range(n_points):
        for n in range(n_dirs):
            s = simplex[a, n]
            if s < 0:
                continue
            dx, dy = xy[a, n, 0] - transform[s, 2, 0], xy[a, n, 1] - transform[s, 2, 1]
            b0 = transform[s, 0, 0] * dx + transform[s, 0, 1] * dy
            b1 = transform[s, 1, 0] * dx + transform[s, 1, 1] * dy
            total = value = 0.0
            for k, b in ((0, b0), (1, b1), (2, 1.0 - b0 - b1)):
                light = vertices[s, k]
                if valid[a, light]:
                    total += b
                    value += b * values[a, light]
            if total > 1e-9:
                out[a, n] = value / total
                defined[a, n] = True
    return out, defined
