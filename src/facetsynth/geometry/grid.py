"""The direction grid: a polar (theta, phi) table over the upper hemisphere.

Used for light directions i (the resampled 2D BRDF slice, paper 002 sec. 4)
and half vectors h (the NDF, sec. 5). Cell (t, p) spans theta in
[t, t+1) * pi / (2 n_theta) and phi in [p, p+1) * 2 pi / n_phi, phi measured
from +x towards +y. The paper uses a hemicube; a polar grid is chosen because
an azimuthal rotation R(phi) (eq. 13) is a cyclic shift along the phi axis:
exact for multiples of the cell width, a linear interpolation between two
shifts otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np


def turn(d: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions (..., 3) turned about the normal by phi (...) radians: R(phi) d, azimuth + phi (eq. 13)."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)


@dataclass(frozen=True)
class DirectionGrid:
    """A polar grid of ``n_theta`` elevation rings x ``n_phi`` azimuth sectors."""

    n_theta: int
    n_phi: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_theta, self.n_phi)

    @property
    def d_theta(self) -> float:
        return 0.5 * np.pi / self.n_theta

    @property
    def d_phi(self) -> float:
        return 2.0 * np.pi / self.n_phi

    @cached_property
    def theta(self) -> np.ndarray:
        """(n_theta,) ring centre elevations."""
        return (np.arange(self.n_theta) + 0.5) * self.d_theta

    @cached_property
    def phi(self) -> np.ndarray:
        """(n_phi,) sector centre azimuths."""
        return (np.arange(self.n_phi) + 0.5) * self.d_phi

    @cached_property
    def directions(self) -> np.ndarray:
        """(n_theta, n_phi, 3) unit directions of the cell centres."""
        st, ct = np.sin(self.theta)[:, None], np.cos(self.theta)[:, None]
        return np.stack(np.broadcast_arrays(st * np.cos(self.phi), st * np.sin(self.phi), ct), axis=-1)

    @cached_property
    def solid_angles(self) -> np.ndarray:
        """(n_theta, n_phi) exact solid angle of each cell; they sum to 2 pi."""
        edges = np.arange(self.n_theta + 1) * self.d_theta
        ring = np.cos(edges[:-1]) - np.cos(edges[1:])
        return np.repeat((ring * self.d_phi)[:, None], self.n_phi, axis=1)

    def integrate(self, f: np.ndarray) -> np.ndarray:
        """Hemisphere integral of a tabulated function f (..., n_theta, n_phi)."""
        return np.einsum("...tp,tp->...", f, self.solid_angles)

    def coordinates(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous cell coordinates (t, p) of directions (..., 3); cell centres are integers.

        Directions below the horizon map to the horizon (theta clamped to pi/2).
        """
        theta = np.arccos(np.clip(d[..., 2], 0.0, 1.0))
        phi = np.arctan2(d[..., 1], d[..., 0]) % (2.0 * np.pi)
        return theta / self.d_theta - 0.5, phi / self.d_phi - 0.5

    def lookup(self, f: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of f (..., n_theta, n_phi) at directions d (..., N, 3) -> (..., N).

        Periodic in phi; theta clamped to the grid's rings (constant extension
        to the pole and the horizon). Leading dims of f and d broadcast.
        """
        return self.bilinear(d)(f)

    def bilinear(self, d: np.ndarray) -> "Bilinear":
        """:meth:`lookup` at directions d (..., N, 3) for any number of tables: the cells and weights once."""
        return self.stencil(*self.coordinates(d))

    def stencil(self, t: np.ndarray, p: np.ndarray) -> "Bilinear":
        """:meth:`bilinear` at continuous cell coordinates (t, p) (:meth:`coordinates`)."""
        t = np.clip(t, 0.0, self.n_theta - 1.0)
        t0 = np.minimum(np.floor(t).astype(np.intp), self.n_theta - 2) if self.n_theta > 1 else np.zeros(t.shape, np.intp)
        ft = t - t0 if self.n_theta > 1 else np.zeros(t.shape)
        p0 = np.floor(p).astype(np.intp)
        fp = p - p0
        p0 %= self.n_phi
        p1 = (p0 + 1) % self.n_phi
        t1 = np.minimum(t0 + 1, self.n_theta - 1)
        cells = np.stack([t0 * self.n_phi + p0, t0 * self.n_phi + p1, t1 * self.n_phi + p0, t1 * self.n_phi + p1])
        return Bilinear(cells, ft, fp)

    def rotate(self, f: np.ndarray, phi: float) -> np.ndarray:
        """f^phi(h) = f(R(phi) h) (eq. 13) for f (..., n_theta, n_phi).

        A cyclic shift by phi / d_phi cells, linearly interpolated between the
        two nearest whole shifts. rotate(rotate(f, a), -a) = f exactly when a
        is a multiple of d_phi.
        """
        shift = phi / self.d_phi
        k = int(np.floor(shift))
        frac = shift - k
        a = np.roll(f, -k, axis=-1)
        return a if frac == 0 else (1 - frac) * a + frac * np.roll(f, -k - 1, axis=-1)

    def to_dict(self) -> dict:
        return {"type": "polar", "n_theta": self.n_theta, "n_phi": self.n_phi,
                "convention": "cell (t, p): theta in [t, t+1)*pi/(2 n_theta), phi in [p, p+1)*2pi/n_phi from +x to +y"}

    @classmethod
    def from_dict(cls, d: dict) -> "DirectionGrid":
        return cls(int(d["n_theta"]), int(d["n_phi"]))


@dataclass(frozen=True)
class Bilinear:
    """Bilinear interpolation on a :class:`DirectionGrid` at fixed directions (:meth:`DirectionGrid.bilinear`):
    an iteration that looks up a changing table at the same directions computes their cells once."""

    cells: np.ndarray   # (4, ..., N) flat cells (t0, p0), (t0, p1), (t1, p0), (t1, p1)
    ft: np.ndarray      # (..., N) weight of the t1 ring
    fp: np.ndarray      # (..., N) weight of the p1 sector

    @property
    def weights(self) -> np.ndarray:
        """(4, ..., N) the bilinear weights of ``cells``."""
        ft, fp = self.ft, self.fp
        return np.stack([(1 - ft) * (1 - fp), (1 - ft) * fp, ft * (1 - fp), ft * fp])

    def __call__(self, f: np.ndarray) -> np.ndarray:
        """f (..., n_theta, n_phi) at the directions (..., N); leading dims broadcast."""
        flat = f.reshape(f.shape[:-2] + (-1,))
        lead = np.broadcast_shapes(flat.shape[:-1], self.ft.shape[:-1])
        flat = np.broadcast_to(flat, lead + flat.shape[-1:])
        a00, a01, a10, a11 = (np.take_along_axis(flat, np.broadcast_to(c, lead + c.shape[-1:]), axis=-1)
                              for c in self.cells)
        ft, fp = self.ft, self.fp
        return (1 - ft) * ((1 - fp) * a00 + fp * a01) + ft * ((1 - fp) * a10 + fp * a11)



@numba.njit(cache=True, nogil=True, inline="always")
def bilinear_stencil(t: float, p: float, n_theta: int, n_phi: int) -> tuple[int, int, int, int, float, float]:
    """:meth:`DirectionGrid.bilinear`'s stencil of one direction, in compiled kernels: at continuous cell
    coordinates (t, p) (:meth:`DirectionGrid.coordinates`), the rings t0, t1 and sectors p0, p1 around it and the
    weights ft of t1 and fp of p1; theta clamped to the rings, phi periodic."""
    t = min(max(t, 0.0), n_theta - 1.0)
    t0 = min(int(np.floor(t)), n_theta - 2) if n_theta > 1 else 0
    ft = t - t0 if n_theta > 1 else 0.0
    t1 = min(t0 + 1, n_theta - 1)
    fp0 = np.floor(p)
    p0 = int(fp0) % n_phi
    p1 = p0 + 1 if p0 + 1 < n_phi else 0
    return t0, t1, p0, p1, ft, p - fp0


@numba.njit(cache=True, nogil=True, inline="always")
def bilinear_at(table: np.ndarray, t: float, p: float, n_theta: int, n_phi: int) -> float:
    """:class:`Bilinear` for one direction, in compiled kernels: ``table`` (n_theta * n_phi,) flat, (t, p) its
    continuous cell coordinates (:func:`bilinear_stencil`)."""
    t0, t1, p0, p1, ft, fp = bilinear_stencil(t, p, n_theta, n_phi)
    return interpolate(table, t0, t1, p0, p1, ft, fp, n_phi)


@numba.njit(cache=True, nogil=True, inline="always")
def interpolate(table: np.ndarray, t0: int, t1: int, p0: int, p1: int, ft: float, fp: float, n_phi: int) -> float:
    """``table`` (n_theta * n_phi,) flat at a :func:`bilinear_stencil`: several tables at one direction share it."""
    return ((1 - ft) * ((1 - fp) * table[t0 * n_phi + p0] + fp * table[t0 * n_phi + p1])
            + ft * ((1 - fp) * table[t1 * n_phi + p0] + fp * table[t1 * n_phi + p1]))


@numba.njit(cache=True, nogil=True, inline="always")
def polar_coordinates(x: float, y: float, z: float, n_theta: int, n_phi: int) -> tuple[float, float]:
    """:meth:`DirectionGrid.coordinates` of one direction, in compiled kernels (bitwise the same: arctan2 lies
    in [-pi, pi], where the float modulo by 2 pi adds 2 pi to a negative angle and is a compiled division)."""
    theta = np.arccos(min(max(z, 0.0), 1.0))
    phi = np.arctan2(y, x)
    if phi < 0.0:
        phi += 2.0 * np.pi
    return theta / (0.5 * np.pi / n_theta) - 0.5, phi / (2.0 * np.pi / n_phi) - 0.5
