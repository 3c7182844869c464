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
        return cls(triangulation, float(np.median(positions[:, 2])))

    def hits(self, points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """X(x, i) (P, N, 2) in the lights' plane for points (P, 3) and directions (N, 3), and whether the
        direction reaches the plane at all (i_z > UP) (N,)."""
        up = directions[:, 2] > UP
        t = (self.height - points[:, None, 2]) / np.where(up, directions[:, 2], 1.0)[None]
        return points[:, None, :2] + t[..., None] * directions[None, :, :2], up

    def barycentric(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Light indices (M, 3), barycentric weights (M, 3) and inside-the-hull mask (M,) of points xy (M, 2)."""
        tri = self.triangulation
        simplex = tri.find_simplex(xy)
        inside = simplex >= 0
        s = np.where(inside, simplex, 0)
        transform = tri.transform[s]                                         # (M, 3, 2)
        b = np.einsum("mij,mj->mi", transform[:, :2], xy - transform[:, 2])
        weights = np.concatenate([b, 1.0 - b.sum(axis=1, keepdims=True)], axis=1)
        return tri.simplices[s], np.where(inside[:, None], weights, 0.0), inside

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
        vertices, weights, inside = self.barycentric(xy.reshape(-1, 2))
        vertices = vertices.reshape(n_points, n_dirs, 3)
        weights = weights.reshape(n_points, n_dirs, 3)
        rows = np.arange(n_points)[:, None, None]
        ok = np.asarray(valid, bool)[rows, vertices]
        w = np.where(ok, weights, 0.0)
        total = w.sum(axis=-1)
        defined = inside.reshape(n_points, n_dirs) & up[None] & (total > 1e-9)
        value = np.einsum("pnk,pnk->pn", w, np.asarray(values, float)[rows, vertices])
        return np.where(defined, value / np.where(defined, total, 1.0), 0.0), defined
