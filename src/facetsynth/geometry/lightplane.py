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

Directional lights (a light dome's, at infinity) have one direction d_q for
every point: their plane is the plane z = 1 seen from the origin, each light
at its gnomonic projection d_q / d_qz, and every point queries it from the
origin (:func:`light_plane`). Great circles are straight lines there, so the
triangulation interpolates between neighbouring directions as on the sphere.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import Delaunay, QhullError

UP = 1e-3   # directions with i_z at or below this never reach the plane of the lights


def light_plane(lights: np.ndarray) -> tuple[np.ndarray, bool]:
    """The lights (F, 4) homogeneous (:mod:`facetsynth.models.render`) or (F, 3) positions as positions (F, 3) in
    their plane, and whether they are at infinity (directional: d / d_z on the plane z = 1, seen from the
    origin by every point). A capture's lights are all point lights or all directional (ValueError)."""
    lights = np.asarray(lights, float)
    if lights.shape[-1] == 3 or np.all(lights[:, 3] > 0):
        return lights[:, :3], False
    if np.any(lights[:, 3] > 0):
        raise ValueError("the capture mixes point lights and directional lights: they need two planes of lights")
    d = lights[:, :3]
    return d / d[:, 2:3], True


def seen_from(points: np.ndarray, at_infinity: bool) -> np.ndarray:
    """Where each point (..., 3) sees the plane of the lights from: itself, or the origin for lights at infinity."""
    points = np.asarray(points, float)
    return np.zeros_like(points) if at_infinity else points


@dataclass(frozen=True)
class LightTriangulation:
    """A Delaunay triangulation of the lights' (x, y) in their plane z = ``height`` (the median light z)."""

    triangulation: Delaunay
    height: float
    at_infinity: bool = False

    @classmethod
    def from_lights(cls, lights: np.ndarray) -> "LightTriangulation":
        """From the lights (F, 4) homogeneous, or positions (F, 3) (:func:`light_plane`)."""
        positions, at_infinity = light_plane(lights)
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
        return cls(triangulation, float(np.median(positions[:, 2])), at_infinity)

    def hits(self, points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """X(x, i) (P, N, 2) in the lights' plane for points (P, 3) and world directions (N, 3), the same for
        every point, or (P, N, 3), each point's own (a shading frame's directions turned to the world); and
        whether the direction reaches the plane at all (i_z > UP) (1 or P, N)."""
        d = directions if directions.ndim == 3 else directions[None]
        up = d[..., 2] > UP
        points = seen_from(points, self.at_infinity)
        t = (self.height - points[:, None, 2]) / np.where(up, d[..., 2], 1.0)
        return points[:, None, :2] + t[..., None] * d[..., :2], up

    def interpolate(self, values: np.ndarray, valid: np.ndarray, points: np.ndarray,
                    directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point, its light samples ``values`` (P, F) interpolated linearly at ``directions`` (N, 3), or
        each point's own (P, N, 3) (:meth:`hits`).

        Invalid samples (``valid`` (P, F) False: saturated, unseen) are left
        out and the remaining barycentric weights renormalised. Returns
        (values (P, N), defined (P, N)): ``defined`` is False beyond the
        lights' hull, for directions that never reach the lights' plane, and
        where every light of the triangle is invalid; there the value is 0.

        One compiled pass: each hit is computed, located and summed without an array of hits (P, N, 2).
        Its triangle is found by walking from the triangle of the point's previous direction (the grid's
        next cell: a step or none), as scipy's ``find_simplex`` walks from its last query, the same
        triangle as scipy's; a triangulation with degenerate triangles (no barycentric transform) is left
        to ``find_simplex``.
        """
        values, valid = np.asarray(values, float), np.asarray(valid, bool)
        points, directions = np.asarray(points, float), np.asarray(directions, float)
        tri = self.triangulation
        if np.isnan(tri.transform).any():
            xy, up = self.hits(points, directions)
            simplex = tri.find_simplex(xy.reshape(-1, 2)).reshape(xy.shape[:2])
            simplex[~np.broadcast_to(up, simplex.shape)] = -1
            return _barycentric_sum(values, valid, xy, simplex, tri.transform, tri.simplices)
        return _interpolate(values, valid, seen_from(points, self.at_infinity),
                            directions if directions.ndim == 3 else directions[None], self.height,
                            tri.transform, tri.simplices, tri.neighbors, self.bounds)

    @functools.cached_property
    def bounds(self) -> np.ndarray:
        """(x min, y min, x max, y max) of the lights in their plane, widened by 1e-9 of their extent: a hit
        beyond it is beyond the hull without a walk to its edge."""
        low, high = self.triangulation.min_bound, self.triangulation.max_bound
        margin = 1e-9 * float(np.max(high - low))
        return np.concatenate([low - margin, high + margin])


INSIDE = 100 * np.finfo(float).eps    # scipy's find_simplex tolerance on the barycentric coordinates


@numba.njit(cache=True, nogil=True)
def _interpolate(values: np.ndarray, valid: np.ndarray, seen_from: np.ndarray, directions: np.ndarray,
                 height: float, transform: np.ndarray, vertices: np.ndarray,
                 neighbours: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`LightTriangulation.interpolate` for points seen from ``seen_from`` (P, 3) and directions (1 or P,
    N, 3): each hit X = x + (h - x_z) i / i_z (:meth:`LightTriangulation.hits`), its triangle by a visibility
    walk over the triangles' ``neighbours`` (the k-th opposite vertex k; -1 beyond the hull: a Delaunay
    triangulation is convex, so a walk that would leave it started outside; a hit beyond ``bounds`` is not
    walked), and :func:`_barycentric_sum`'s weights."""
    n_points, n_dirs = seen_from.shape[0], directions.shape[1]
    per_point = directions.shape[0] > 1
    out = np.zeros((n_points, n_dirs))
    defined = np.zeros((n_points, n_dirs), np.bool_)
    start = first = 0     # where a walk starts: the triangle of the point's previous direction's hit; for its
    for a in range(n_points):  # first direction, that of the point before
        start = first
        px, py, pz = seen_from[a, 0], seen_from[a, 1], seen_from[a, 2]
        d = directions[a] if per_point else directions[0]
        for n in range(n_dirs):
            if not d[n, 2] > UP:
                continue
            t = (height - pz) / d[n, 2]
            x, y = px + t * d[n, 0], py + t * d[n, 1]
            if not (bounds[0] <= x <= bounds[2] and bounds[1] <= y <= bounds[3]):
                continue
            s = start
            for _ in range(transform.shape[0]):
                dx, dy = x - transform[s, 2, 0], y - transform[s, 2, 1]
                b0 = transform[s, 0, 0] * dx + transform[s, 0, 1] * dy
                b1 = transform[s, 1, 0] * dx + transform[s, 1, 1] * dy
                b2 = 1.0 - b0 - b1
                worst, lowest = 0, b0
                if b1 < lowest:
                    worst, lowest = 1, b1
                if b2 < lowest:
                    worst, lowest = 2, b2
                if lowest >= -INSIDE:
                    break
                s = neighbours[s, worst]
                if s < 0:
                    break
            else:
                s = -1                             # no triangle after as many steps as there are: none
            if s < 0:
                continue
            start = s
            if n == 0:
                first = s
            _weigh(out, defined, values, valid, vertices, a, n, s, b0, b1, b2)
    return out, defined


@numba.njit(cache=True, nogil=True, inline="always")
def _weigh(out, defined, values, valid, vertices, a, n, s, b0, b1, b2) -> None:
    """out[a, n]: point a's valid samples at triangle s's corners, weighted by b0, b1, b2 renormalised over the
    valid ones (defined where their weights sum above 1e-9)."""
    total = value = 0.0
    for k, b in ((0, b0), (1, b1), (2, b2)):
        light = vertices[s, k]
        if valid[a, light]:
            total += b
            value += b * values[a, light]
    if total > 1e-9:
        out[a, n] = value / total
        defined[a, n] = True


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
            _weigh(out, defined, values, valid, vertices, a, n, s, b0, b1, 1.0 - b0 - b1)
    return out, defined
