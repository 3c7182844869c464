"""Partial NDF fitting with the azimuth-min constrained shadowing (paper 002 sec. 5.1).

With one view o, the half vectors h of the captured light directions cover
only Omega = {h | refl(o, h) . n > 0} (eq. 10). On Omega the NDF follows from
the resampled specular slice by eq. 11 (F = 1, grazing data excluded)

    D(h) = 4 rho~_s(o, i(h)) (i(h) . n)(o . n) / (S(i(h)) S(o)),   i(h) = refl(o, h),

and S from D by eq. 5. Iterating D and S with D = 0 outside Omega (Ngan et
al. 2005, ``constrained=False``) overestimates S; the paper constrains S to
its minimum over azimuth at each elevation. The confidence W of eq. 12 is
multiplied by the light coverage of i(h) and zeroed where i(h) is grazing.

Eq. 11 is printed with a factor 4 pi; with the paper's own normalisation of D
(integral of (n . h) D = 1) and eq. 6, the factor is 4, used here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np
import scipy.fft

from ..geometry.grid import DirectionGrid, bilinear_at, bilinear_stencil, interpolate, polar_coordinates, turn
from ..models.microfacet import fresnel

# Eq. 5 is smooth in k (sec. 3): it is evaluated on this coarse grid of directions.
SHADOWING_GRID = DirectionGrid(16, 32)


def reflect(o: np.ndarray, h: np.ndarray) -> np.ndarray:
    """refl(o, h) = 2 (h . o) h - o (eq. 10)."""
    return 2.0 * np.sum(h * o, axis=-1, keepdims=True) * h - o


def projected_area_table(ndf: np.ndarray, grid: DirectionGrid, k: np.ndarray) -> np.ndarray:
    """A(k) of eq. 5 for tabulated NDFs (P, T, F) at directions k (K, 3): (P, K).

    A(k) = sum over cells of max(h . k, 0) D(h) dw, with D normalised by the
    caller. K is small (the shadowing grid), so this is one matrix product.
    """
    return _projected_area(ndf.reshape(ndf.shape[0], -1), area_kernel(grid, k))


def area_kernel(grid: DirectionGrid, k: np.ndarray) -> np.ndarray:
    """max(h . k, 0) dw (T*F, K): the weights of :func:`projected_area_table`."""
    h = grid.directions.reshape(-1, 3)
    return np.clip(h @ np.asarray(k, float).T, 0.0, None) * grid.solid_angles.reshape(-1, 1)


def projected_area_on(ndf: np.ndarray, grid: DirectionGrid, shadowing_grid: DirectionGrid) -> np.ndarray:
    """:func:`projected_area_table` (P, Ts*Fs) at the directions of ``shadowing_grid``, its kernel made once per
    pair of grids: refine renormalises tables for every stretch it tries, and making the (T*F, Ts*Fs) kernel
    each time took most of that."""
    return _projected_area(ndf.reshape(ndf.shape[0], -1), _grid_area_kernel(grid, shadowing_grid))


@functools.lru_cache(maxsize=8)
def _grid_area_kernel(grid: DirectionGrid, shadowing_grid: DirectionGrid) -> np.ndarray:
    kernel = area_kernel(grid, shadowing_grid.directions.reshape(-1, 3))
    kernel.flags.writeable = False
    return kernel


def _projected_area(ndf: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """ndf (P, T*F) @ kernel over only the cells some point's D covers (a partial NDF is 0 on about half)."""
    cells = np.flatnonzero(np.any(ndf != 0, axis=0))
    return ndf[:, cells] @ kernel[cells]


@functools.lru_cache(maxsize=8)
def _shadowing_kernel(grid: DirectionGrid) -> tuple[str, np.ndarray | None]:
    """How :func:`shadowing_table` integrates eq. 5 on ``grid``, computed once per grid.

    max(h . k, 0) depends on the azimuths of h and k only through their difference, so for each pair
    of rings (h's, k's) A(k) is a circular correlation along phi: ("fft", the kernel's spectrum (T, Ts,
    F/2 + 1)) when SHADOWING_GRID's sectors fall every m-th of the grid's (n_phi = m x 32: every grid
    :func:`facetsynth.fit.sharpness.grid_resolution` makes), O(T Ts F log F) per point against O(T F Ts Fs)
    for the product with :func:`area_kernel`, which any other grid uses ("dense", None: the kernel is
    :func:`projected_area_on`'s, made once there)."""
    if grid.n_phi % SHADOWING_GRID.n_phi:
        return "dense", None
    m = grid.n_phi // SHADOWING_GRID.n_phi
    lag = (np.arange(grid.n_phi) - (m - 1) / 2) * grid.d_phi         # phi_h - phi_k for h's sector j m + lag
    st, ct = np.sin(grid.theta)[:, None, None], np.cos(grid.theta)[:, None, None]
    sk, ck = np.sin(SHADOWING_GRID.theta)[None, :, None], np.cos(SHADOWING_GRID.theta)[None, :, None]
    kernel = np.clip(st * sk * np.cos(lag) + ct * ck, 0.0, None) * grid.solid_angles[:, :1, None]
    return "fft", np.conj(np.fft.rfft(kernel, axis=-1))


def _shadowing_area(ndf: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """A(k) of eq. 5 (P, Ts*Fs) at SHADOWING_GRID's directions for NDFs (P, T, F), as
    :func:`projected_area_table` (the method: :func:`_shadowing_kernel`)."""
    method, kernel = _shadowing_kernel(grid)
    if method == "dense":
        return projected_area_on(ndf, grid, SHADOWING_GRID)
    spectrum = scipy.fft.rfft(ndf, axis=-1).transpose(2, 0, 1)                       # (f, P, T)
    summed = np.matmul(spectrum, kernel.transpose(2, 0, 1))                          # (f, P, Ts): sum over rings
    return _every_mth_lag(summed, grid.n_phi, grid.n_phi // SHADOWING_GRID.n_phi).transpose(1, 2, 0).reshape(
        len(ndf), -1)


def _every_mth_lag(spectrum: np.ndarray, n: int, m: int) -> np.ndarray:
    """irfft(spectrum, n, axis=0)[::m]: the inverse transform at every m-th lag alone, as the n/m-point transform
    of the spectrum folded onto n/m bins (sampling every m-th lag aliases the bins k, k + n/m, ...); ``spectrum``
    (n/2 + 1, P, K) of a real signal of even length n, m dividing n/2."""
    return scipy.fft.irfft(_folded_bins(spectrum, n, m), n=n // m, axis=0) / m


@numba.njit(cache=True, nogil=True)
def _folded_bins(spectrum: np.ndarray, n: int, m: int) -> np.ndarray:
    """The bins 0 .. n/m/2 of the n bins of ``spectrum`` (n/2 + 1, P, K) folded onto n/m: bin k sums the bins
    k + j n/m, j = 0 .. m - 1, in that order, a bin b beyond n/2 read as conj(spectrum[n - b]) (the spectrum
    of a real signal). Only the bins the n/m-point inverse reads, in one pass: bitwise numpy's sum over the
    whole folded spectrum (which adds the m bins in the same order), without making it."""
    period = n // m
    out = np.empty((period // 2 + 1,) + spectrum.shape[1:], spectrum.dtype)
    for k in range(out.shape[0]):
        for j in range(m):
            b = k + j * period
            mirrored = b > n // 2
            source = spectrum[n - b] if mirrored else spectrum[b]
            for p in range(spectrum.shape[1]):
                for q in range(spectrum.shape[2]):
                    value = np.conj(source[p, q]) if mirrored else source[p, q]
                    out[k, p, q] = value if j == 0 else out[k, p, q] + value
    return out


SHADOWING_METHODS = ("constrained", "unconstrained", "clipped")


def shadowing_method(method: bool | str) -> str:
    """The name of a shadowing method; True and False (the former flag) mean constrained and unconstrained."""
    name = {True: "constrained", False: "unconstrained"}.get(method, method) if isinstance(method, bool) else method
    if name not in SHADOWING_METHODS:
        raise ValueError(f"partial NDF shadowing must be one of {', '.join(SHADOWING_METHODS)}, not {method!r}")
    return name


def shadowing_table(ndf: np.ndarray, grid: DirectionGrid, constrained: bool | str) -> np.ndarray:
    """S(k) on SHADOWING_GRID (P, Ts, Fs) from a partial NDF (eq. 5).

    D is normalised to integral of (n . h) D = 1 over its cells. The method
    (``constrained``, :func:`shadowing_method`): "constrained" (True), S at
    each elevation is its minimum over azimuth (sec. 5.1); "unconstrained"
    (False), eq. 5 on the partial NDF as it is (Ngan et al. 2005);
    "clipped", that S capped at 1, the bound a complete normalised NDF obeys.
    The partial NDF's normalisation over only the cells it covers makes D,
    hence A(k), too large where the missing cells matter, so the constrained
    minimum comes out low (docs/decisions.md, "Partial NDF bias").
    A point with an all-zero NDF gets S = 1.
    """
    method = shadowing_method(constrained)
    k = SHADOWING_GRID.directions.reshape(-1, 3)
    norm = grid.integrate(ndf * grid.directions[..., 2])
    normalised = np.divide(ndf, norm[:, None, None], out=np.zeros_like(ndf), where=norm[:, None, None] > 0)
    area = _shadowing_area(normalised, grid)
    # A full normalised NDF gives S <= 1. A partial one overestimates S where it
    # misses part of eq. 5's domain: that is the bias of the unconstrained method
    # (sec. 5.1), kept unclipped; the cap only keeps the numbers finite.
    s = np.clip(np.divide(k[:, 2], area, out=np.ones_like(area), where=area > 1e-12), 0.0, 1e3)
    s = s.reshape((-1,) + SHADOWING_GRID.shape)
    if method == "constrained":
        s = np.broadcast_to(s.min(axis=-1, keepdims=True), s.shape)
    elif method == "clipped":
        s = np.minimum(s, 1.0)
    return np.ascontiguousarray(s)


@dataclass(frozen=True)
class PartialNDF:
    ndf: np.ndarray          # (P, T, F) D of eq. 11, 0 outside the confident domain
    confidence: np.ndarray   # (P, T, F) W of eq. 12 times light coverage
    iterations: np.ndarray   # (P,) iterations used
    converged: np.ndarray    # (P,) bool


def fit(specular_slice: np.ndarray, coverage: np.ndarray, view: np.ndarray, grid: DirectionGrid,
        constrained: bool = True, grazing_deg: float = 80.0, tol: float = 1e-3, max_iter: int = 30) -> PartialNDF:
    """Fit partial NDFs for a tile of points.

    ``specular_slice`` (P, T, F): rho~_s tabulated over light directions on
    ``grid``; ``coverage`` (P, T, F) in [0, 1]: how well lights sampled each
    light direction; ``view`` (P, 3) or (3,): o per point. The NDF is
    tabulated on the same grid, over half vectors h. Iterates eq. 11 and eq.
    5 until the largest relative change of D is below ``tol`` (or
    ``max_iter``). Light directions steeper than ``grazing_deg`` from the
    normal are excluded (F = 1 is assumed, sec. 5.1).
    """
    n_points = specular_slice.shape[0]
    o = np.ascontiguousarray(np.broadcast_to(np.asarray(view, float), (n_points, 3)))
    flat = (n_points, grid.n_theta * grid.n_phi)
    numerator, w, s_t, s_p = _eq11_terms(np.asarray(specular_slice, float).reshape(flat),
                                         np.asarray(coverage, float).reshape(flat), o,
                                         np.ascontiguousarray(grid.directions.reshape(-1, 3)), grid.n_theta,
                                         grid.n_phi, SHADOWING_GRID.n_theta, SHADOWING_GRID.n_phi,
                                         np.cos(np.radians(grazing_deg)))
    return iterate(numerator, w, (s_t, s_p), o, grid, constrained, tol, max_iter)


@numba.njit(cache=True, nogil=True)
def _eq11_terms(rho: np.ndarray, cover: np.ndarray, o: np.ndarray, h: np.ndarray, n_theta: int, n_phi: int,
                s_theta: int, s_phi: int, cos_grazing: float):
    """Per point and half-vector cell: the numerator of eq. 11, 4 rho~_s(i(h)) (i(h) . n)(o . n); W of eq. 12,
    [(i(h) . n)^(1/2)]_+, times the light coverage at i(h) = refl(o, h) (0 where i(h) is steeper than the
    grazing limit); and i(h)'s cell coordinates on the shadowing grid where W > 0 (0 elsewhere). ``rho``,
    ``cover`` (P, T*F) on the grid of ``h`` (T*F, 3); ``o`` (P, 3). One pass per point: the reflected
    directions differ from point to point (per-point views) and are never stored."""
    n_points, n_cells = rho.shape
    n_theta_ratio, n_phi_ratio = s_theta / n_theta, s_phi / n_phi
    numerator = np.zeros((n_points, n_cells))
    w = np.zeros((n_points, n_cells))
    s_t = np.empty((n_points, n_cells))
    s_p = np.empty((n_points, n_cells))
    for a in range(n_points):
        ox, oy, oz = o[a, 0], o[a, 1], o[a, 2]
        for c in range(n_cells):
            hx, hy, hz = h[c, 0], h[c, 1], h[c, 2]
            two_ho = 2.0 * (hx * ox + hy * oy + hz * oz)
            ix, iy, iz = two_ho * hx - ox, two_ho * hy - oy, two_ho * hz - oz          # eq. 10
            s_t[a, c] = s_p[a, c] = 0.0                  # S is not looked up where W = 0
            if iz > cos_grazing:
                t, p = polar_coordinates(ix, iy, iz, n_theta, n_phi)
                t0, t1, p0, p1, ft, fp = bilinear_stencil(t, p, n_theta, n_phi)     # one for both tables
                cv = min(max(interpolate(cover[a], t0, t1, p0, p1, ft, fp, n_phi), 0.0), 1.0)
                w[a, c] = np.sqrt(max(iz, 0.0)) * cv                                      # eq. 12
                if w[a, c] > 0:
                    numerator[a, c] = 4.0 * interpolate(rho[a], t0, t1, p0, p1, ft, fp, n_phi) * iz * oz
                    s_t[a, c] = (t + 0.5) * n_theta_ratio - 0.5
                    s_p[a, c] = (p + 0.5) * n_phi_ratio - 0.5
    return numerator, w, s_t, s_p


def iterate(numerator: np.ndarray, w: np.ndarray, i_coordinates: tuple[np.ndarray, np.ndarray], o: np.ndarray,
            grid: DirectionGrid, constrained: bool = True, tol: float = 1e-3, max_iter: int = 30) -> PartialNDF:
    """Eqs. 11 and 5 alternated from S = 1: D(h) = numerator(h) / (S(i(h)) S(o)) on the support W > 0.

    ``numerator`` (P, T*F): 4 rho~_s(i(h)) (i(h) . n)(o . n) per half-vector
    cell; ``w`` (P, T*F) the confidence W; ``i_coordinates`` the (t, p)
    coordinates on SHADOWING_GRID of each cell's light direction i(h)
    (P, T*F) each; ``o`` (P, 3) the view. Stops when the largest
    relative change of D is below ``tol`` (or after ``max_iter``).
    """
    n_points = numerator.shape[0]
    support = w > 0
    numerator = np.where(support, numerator, 0.0)
    shape = (n_points,) + grid.shape
    d = numerator.reshape(shape).copy()                                # S = 1: the starting point
    iterations = np.zeros(n_points, int)
    active = np.ones(n_points, bool)
    s_t, s_p = np.broadcast_arrays(*i_coordinates)
    o = np.broadcast_to(o, (n_points, 3))
    flat = d.reshape(n_points, -1)
    for it in range(1, max_iter + 1):
        rows = np.flatnonzero(active)                                  # converged points keep their D
        if rows.size == 0:
            break
        s_table = shadowing_table(d if rows.size == n_points else d[rows], grid, constrained)   # eq. 5 from D
        s_at_o = SHADOWING_GRID.lookup(s_table, o[rows, None, :])[:, 0]
        change = _eq11_update(flat, numerator, rows, s_table.reshape(rows.size, -1), s_t, s_p, s_at_o,
                              *SHADOWING_GRID.shape)
        iterations[rows] = it
        active[rows] = change > tol
    return PartialNDF(ndf=d, confidence=w.reshape(shape), iterations=iterations, converged=~active)


@numba.njit(cache=True, nogil=True)
def _eq11_update(d: np.ndarray, numerator: np.ndarray, rows: np.ndarray, s_table: np.ndarray, s_t: np.ndarray,
                 s_p: np.ndarray, s_at_o: np.ndarray, s_theta: int, s_phi: int) -> np.ndarray:
    """One step of eq. 11 in place for the points ``rows`` of d (P, T*F): D = numerator / (S(i(h)) S(o)),
    0 where the denominator is below 1e-6, with S (R, Ts*Fs) looked up bilinearly at i(h)'s coordinates
    ``s_t``, ``s_p`` (P, T*F). Returns each point's largest change of D relative to its largest value (R,)."""
    change = np.zeros(rows.size)
    for r in range(rows.size):
        a = rows[r]
        largest_change = largest = 0.0
        for c in range(d.shape[1]):
            new = 0.0
            if numerator[a, c] != 0.0:
                denom = bilinear_at(s_table[r], s_t[a, c], s_p[a, c], s_theta, s_phi) * s_at_o[r]
                if denom > 1e-6:
                    new = numerator[a, c] / denom
            largest_change = max(largest_change, abs(new - d[a, c]))
            largest = max(largest, abs(new))
            d[a, c] = new
        change[r] = largest_change / max(largest, 1e-30)
    return change


def pooled_fit(specular: np.ndarray, valid: np.ndarray, light_directions: np.ndarray, views: np.ndarray,
               member_confidence: np.ndarray, view: np.ndarray, grid: DirectionGrid,
               constrained: bool = True, grazing_deg: float = 80.0, tol: float = 1e-3,
               max_iter: int = 30, rotation: np.ndarray | None = None) -> PartialNDF:
    """One partial NDF from the eq. 8 samples of several points of one material (a cluster's members).

    Each point's samples lie at its own half vectors h_q = (i_q + o) / |i_q + o|,
    shifted against every other point's by where it sits under the lights.
    Pooled, they sample the shared NDF far more densely than the lights do
    from any one point (a glossy lobe at the paper's 480 lights is one or
    two lights wide): the numerator of eq. 11, 4 rho~_s (i.n)(o.n), is
    averaged over the samples in each half-vector cell (a bilinear splat
    would blur the peak by a cell; push-pull (Gortler et al. 1996) fills the
    cells no sample falls in) and eqs.
    11 and 5 are iterated for the representative's view ``view`` (S is smooth
    in h; the members' views differ by a few degrees). ``specular`` (M, F)
    rho~_s, ``valid`` (M, F), ``light_directions`` i (M, F, 3), ``views`` (M, 3),
    ``member_confidence`` (M, T, F): the members' W, whose mean is the pooled W.
    ``rotation`` (M,): each member's frame against the representative's
    (:func:`facetsynth.fit.cluster.relative_rotation`, D_x(h) = D(R(phi) h)):
    its samples are turned into the representative's frame first.
    Returns a PartialNDF of one point.
    """
    from .pushpull import push_pull
    wi = np.asarray(light_directions, float)
    o = np.broadcast_to(views[:, None, :], wi.shape)
    h = wi + o
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    w_members = np.asarray(member_confidence, float)
    if rotation is not None:
        h = turn(h, np.asarray(rotation, float)[:, None])
        w_members = np.stack([grid.rotate(wm, -phi) for wm, phi in zip(w_members, rotation)])
    use = np.asarray(valid, bool) & (wi[..., 2] > np.cos(np.radians(grazing_deg)))
    value = 4.0 * np.asarray(specular, float) * np.clip(wi[..., 2], 0.0, None) * np.clip(o[..., 2], 0.0, None)
    t, p = grid.coordinates(h[use])
    cell = (np.clip(np.rint(t), 0, grid.n_theta - 1).astype(np.intp) * grid.n_phi
            + np.rint(p).astype(np.intp) % grid.n_phi)
    size = grid.n_theta * grid.n_phi
    value_sum = np.bincount(cell, value[use], minlength=size).reshape((1,) + grid.shape)
    count = np.bincount(cell, minlength=size).astype(float).reshape((1,) + grid.shape)
    numerator = push_pull(value_sum, count).reshape(1, -1)
    o_ref = np.asarray(view, float).reshape(1, 3)
    i = reflect(o_ref[:, None, :], grid.directions.reshape(1, -1, 3))
    w = np.mean(w_members, axis=0).reshape(1, -1)
    return iterate(numerator, w, SHADOWING_GRID.coordinates(i), o_ref, grid, constrained, tol, max_iter)


def fresnel_cosine(view: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """|o . h| on the grid (..., T, F) for views o (..., 3): the cosine of the Fresnel factor that eq. 11
    (F = 1 assumed) leaves in the partial NDF at each half vector h (for a mirror configuration
    |i . h| = |o . h|)."""
    view = np.asarray(view, float)
    c = np.abs(np.einsum("...k,tpk->...tp", view, grid.directions))
    return c


def recoverable_ndf(ks: np.ndarray, eta: np.ndarray, true_ndf: np.ndarray, view: np.ndarray,
                    grid: DirectionGrid) -> np.ndarray:
    """What eq. 11 recovers from perfect data and the true S: mean(ks) F(|o . h|, eta) D(h).

    The reference for the partial NDF's accuracy: eq. 11 assumes F = 1, so
    the Fresnel factor and the specular albedo stay in D until sec. 5.4.
    ``ks`` (P, 3), ``eta`` (P,), ``true_ndf`` (P, T, F), ``view`` (P, 3).
    """
    c = fresnel_cosine(view, grid)
    return ks.mean(axis=-1)[:, None, None] * fresnel(c, eta[:, None, None]) * true_ndf


def relative_l2(estimate: np.ndarray, reference: np.ndarray, mask: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """Relative L2 error (P,) of tabulated NDFs over the ``mask`` cells (solid-angle weighted).

    Points with no masked cell, or a zero reference there, get NaN (metrics only).
    """
    weight = np.where(mask, grid.solid_angles, 0.0)
    num = np.sum((estimate - reference) ** 2 * weight, axis=(1, 2))
    den = np.sum(reference**2 * weight, axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.nan)
