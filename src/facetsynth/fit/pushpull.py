"""Push-pull interpolation of scattered samples on the direction grid (Gortler et al. 1996).

Paper 002 sec. 4 resamples each point's scattered specular samples onto a
uniform grid of light directions with push-pull, as Lawrence et al. 2006 do.
Samples are splatted bilinearly into the finest level; *pull* builds a
pyramid by summing 2 x 2 children with weights clamped to 1; *push* fills each
level from the next coarser one where its own weight is below 1. Periodic in
phi. Vectorised over any leading dimensions (points).
"""

from __future__ import annotations

import numba
import numpy as np

from ..geometry.grid import DirectionGrid


def splat(grid: DirectionGrid, directions: np.ndarray, values: np.ndarray,
          valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear splat of samples (P, Q) at directions (P, Q, 3) into (P, T, F) sums.

    Returns (weighted value sum, weight sum). Invalid samples (``valid`` False)
    and samples below the horizon are dropped.
    """
    n_points = values.shape[0]
    t, p = grid.coordinates(directions)
    keep = directions[..., 2] > 0
    if valid is not None:
        keep &= valid
    t = np.clip(t, 0.0, grid.n_theta - 1.0)
    t0 = np.floor(t).astype(np.intp)
    p0 = np.floor(p).astype(np.intp)
    ft, fp = t - t0, p - p0
    value_sum = np.zeros((n_points, grid.n_theta * grid.n_phi))
    weight_sum = np.zeros_like(value_sum)
    rows = np.broadcast_to(np.arange(n_points)[:, None], values.shape)
    for dt, wt in ((0, 1 - ft), (1, ft)):
        for dp, wp in ((0, 1 - fp), (1, fp)):
            w = np.where(keep, wt * wp, 0.0)
            cell = np.minimum(t0 + dt, grid.n_theta - 1) * grid.n_phi + (p0 + dp) % grid.n_phi
            np.add.at(weight_sum, (rows, cell), w)
            np.add.at(value_sum, (rows, cell), w * np.where(keep, values, 0.0))
    shape = (n_points,) + grid.shape
    return value_sum.reshape(shape), weight_sum.reshape(shape)


def push_pull(value_sum: np.ndarray, weight_sum: np.ndarray) -> np.ndarray:
    """Fill a (..., T, F) table from splatted sums; every cell gets a finite value.

    Where there is no sample at all (a zero weight everywhere) the result is 0.
    """
    weight = np.minimum(weight_sum, 1.0)
    value = np.divide(value_sum, weight_sum, out=np.zeros_like(value_sum), where=weight_sum > 0)
    if value.shape[-2] == 1 and value.shape[-1] == 1:
        return value
    coarse = push_pull(_pool(weight * value), _pool(weight))
    return _push(weight, value, coarse)


def _pool(a: np.ndarray) -> np.ndarray:
    """Sum 2 x 2 children; an odd last ring or sector is summed alone (padded with zeros): a coarse
    cell's children are exactly fine cells 2j and 2j + 1, whatever the size."""
    if a.shape[-2] > 1:
        if a.shape[-2] % 2:
            a = np.concatenate([a, np.zeros_like(a[..., -1:, :])], axis=-2)
        a = a[..., 0::2, :] + a[..., 1::2, :]
    if a.shape[-1] > 1:
        if a.shape[-1] % 2:
            a = np.concatenate([a, np.zeros_like(a[..., :1])], axis=-1)
        a = a[..., 0::2] + a[..., 1::2]
    return a


def _push(weight: np.ndarray, value: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """weight value + (1 - weight) coarse, the coarse level (..., m_T, m_F) linearly interpolated to the fine
    one's cells (:func:`_axis_weights`: theta clamped, then phi periodic), in one compiled pass per point."""
    shape = value.shape
    points = (-1,) + shape[-2:]
    out = _push_points(np.broadcast_to(weight, shape).reshape(points), value.reshape(points),
                       coarse.reshape((-1,) + coarse.shape[-2:]),
                       *_axis_weights(coarse.shape[-2], shape[-2], periodic=False),
                       *_axis_weights(coarse.shape[-1], shape[-1], periodic=True))
    return out.reshape(shape)


def _axis_weights(m: int, n: int, periodic: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation along an axis from the level :func:`_pool` made (m = ceil(n / 2) cells, coarse
    cell j over fine cells 2j, 2j + 1) back to n cells: per fine cell, its two coarse cells and the second's
    weight (m = n: the cell itself)."""
    if m == n:
        return np.arange(n), np.arange(n), np.zeros(n)
    if m != (n + 1) // 2:
        raise ValueError(f"push-pull level of {m} cells does not pool {n}")
    x = (np.arange(n) + 0.5) / 2 - 0.5              # fine cell centres in coarse coordinates
    if not periodic:
        x = np.clip(x, 0.0, m - 1.0)
    i0 = np.floor(x).astype(np.intp)
    f = x - i0
    i1 = i0 + 1
    if periodic:
        i0, i1 = i0 % m, i1 % m
    else:
        i1 = np.minimum(i1, m - 1)
    return i0, i1, f


@numba.njit(cache=True, nogil=True)
def _push_points(weight: np.ndarray, value: np.ndarray, coarse: np.ndarray, t0: np.ndarray, t1: np.ndarray,
                 ft: np.ndarray, p0: np.ndarray, p1: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """:func:`_push` on (P, T, F) levels: the coarse level interpolated along theta, then phi, and blended."""
    n_points, n_theta, n_phi = value.shape
    out = np.empty_like(value)
    rings = np.empty((n_theta, coarse.shape[2]))
    for a in range(n_points):
        for i in range(n_theta):
            for k in range(coarse.shape[2]):
                rings[i, k] = (1 - ft[i]) * coarse[a, t0[i], k] + ft[i] * coarse[a, t1[i], k]
        for i in range(n_theta):
            for j in range(n_phi):
                up = (1 - fp[j]) * rings[i, p0[j]] + fp[j] * rings[i, p1[j]]
                out[a, i, j] = weight[a, i, j] * value[a, i, j] + (1.0 - weight[a, i, j]) * up
    return out
