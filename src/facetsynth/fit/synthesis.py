"""Example-based microfacet synthesis: NDF completion from rotated partial NDFs (paper 002 sec. 5.2-5.3).

A partial NDF tuple Psi = <D, W> lives on a :class:`~facetsynth.geometry.grid.DirectionGrid`;
its domain is Omega = {h | W(h) > 0}. The exemplar set (eq. 13) holds every
exemplar point's tuple rotated by every azimuth. On the polar grid a rotation
by k sectors is a cyclic shift (``grid.rotate``), so eq. 15 for *all* integer
shifts of a candidate at once is a set of circular cross-correlations along
phi, computed with FFTs (:class:`ExemplarSpectra`): the exact search scores
every exemplar at every whole-sector rotation.

Synthesis of one NDF (:func:`complete`) starts from Psi_0 = Psi and merges, at
each iteration, the best exemplar (eq. 14) whose domain overlaps the current
one by 50-85 % (of the exemplar's domain), by eqs. 16-17, until the azimuthal
sweep of the domain is covered. Leftover holes are filled by push-pull.

Search pruning (sec. 5.3, :class:`HistogramSearch`): for n_phi = 20 relative
rotations phi_i in the range where a rotated domain overlaps its original by
50-85 %, the overlap region Omega(phi_i) = Omega cap R(phi_i) Omega; in it a
32-bucket histogram of each exemplar's D; one pynndescent index per region
(and per sense of rotation); 5 best matches per region; then phi chosen for
each match by minimising eq. 14 with the full distance of eq. 15 (over all
whole-sector rotations, then below a sector). Choices where the paper is
silent, and measurements: docs/decisions.md.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..geometry.grid import DirectionGrid
from .partial_ndf import fresnel_cosine
from .pushpull import push_pull

log = logging.getLogger(__name__)

SUPPORT = 1e-6      # W above this is inside the domain Omega
# Orientation concentration (:func:`orientation_concentration`) of the anisotropic exemplars at and above which
# a sample has a single lobe axis, whatever the stalls say (measured over the exemplars: brushed at alpha 0.04-0.12
# across the brush 0.93-0.96, turned captures added 0.14-0.20; satin's two thread directions 0.32, wallpaper 0.17,
# demo 0.05; docs/decisions.md).
SINGLE_ORIENTATION = 0.85
TINY = 1e-30


# ----------------------------------------------------------------------------
# eq. 15: the overlap-normalised distance
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Match:
    """eq. 15 between two tuples: distance, the scales s1, s2, overlap areas (sr)."""

    distance: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    overlap: np.ndarray      # solid angle of Omega_cap
    weight: np.ndarray       # integral of sqrt(W1 W2) over Omega_cap (eq. 15's denominator)
    relative: np.ndarray     # sqrt(distance / mean of (D1/s1)^2 and (D2/s2)^2 over Omega_cap): 0 .. sqrt(2)


def _assemble(num, ref, s1, s2, den, overlap) -> Match:
    """Eq. 15 from its parts: ``num`` = int_cap sqrt(W1 W2) |D1/s1 - D2/s2|^2, ``ref`` = the same of the mean
    of (D1/s1)^2 and (D2/s2)^2, the scales, ``den`` = int_cap sqrt(W1 W2) and the overlap's solid angle. An
    empty overlap or a zero scale gives an infinite distance."""
    ok = (den > TINY) & (s1 > TINY) & (s2 > TINY) & (overlap > 0)
    num = np.maximum(num, 0.0)
    dist = np.where(ok, num / np.where(ok, den, 1.0), np.inf)
    rel = np.where(ok & (ref > 0), np.sqrt(num / np.where(ref > 0, ref, 1.0)), np.inf)
    return Match(distance=dist, s1=np.where(ok, s1, 0.0), s2=np.where(ok, s2, 0.0), overlap=overlap,
                 weight=np.where(ok, den, 0.0), relative=rel)


def _finish(a11, a12, a22, s1, s2, den, ref1, ref2, overlap) -> Match:
    """Eq. 15 from the integrals of D1^2, D1 D2 and D2^2 weighted by sqrt(W1 W2) (:func:`_assemble`)."""
    s1s, s2s = np.where(s1 > TINY, s1, 1.0), np.where(s2 > TINY, s2, 1.0)
    num = a11 / s1s**2 - 2.0 * a12 / (s1s * s2s) + a22 / s2s**2
    return _assemble(num, 0.5 * (ref1 / s1s**2 + ref2 / s2s**2), s1, s2, den, overlap)


def distance(d1: np.ndarray, w1: np.ndarray, d2: np.ndarray, w2: np.ndarray, grid: DirectionGrid) -> Match:
    """Eq. 15 between tuples <d1, w1> and <d2, w2> (..., T, F), broadcasting over leading dims.

    dist = int_cap sqrt(W1 W2) |D1/s1 - D2/s2|^2 dw / int_cap sqrt(W1 W2) dw, with
    s_k = int_cap D_k dw and cap = {W1 W2 > 0}. Zero for a tuple and itself,
    invariant to scaling D1 or D2, symmetric. Empty overlap: infinite.
    """
    cap = (w1 > SUPPORT) & (w2 > SUPPORT)
    om = grid.solid_angles
    a = np.where(cap, np.sqrt(np.clip(w1, 0, None) * np.clip(w2, 0, None)), 0.0) * om
    s1 = np.sum(np.where(cap, d1, 0.0) * om, axis=(-2, -1))
    s2 = np.sum(np.where(cap, d2, 0.0) * om, axis=(-2, -1))
    overlap = np.sum(cap * om, axis=(-2, -1))
    den = np.sum(a, axis=(-2, -1))
    s1s, s2s = np.where(s1 > TINY, s1, 1.0), np.where(s2 > TINY, s2, 1.0)
    e1, e2 = d1 / s1s[..., None, None], d2 / s2s[..., None, None]
    num = np.sum(a * (e1 - e2) ** 2, axis=(-2, -1))
    ref = 0.5 * np.sum(a * (e1**2 + e2**2), axis=(-2, -1))
    return _assemble(num, ref, s1, s2, den, overlap)


def pairwise_distance(d1: np.ndarray, w1: np.ndarray, d2: np.ndarray, w2: np.ndarray,
                      grid: DirectionGrid) -> np.ndarray:
    """Eq. 15 between every tuple of set 1 (N1, T, F) and set 2 (N2, T, F): (N1, N2).

    Every integral of eq. 15 factors into a matrix product (sqrt(W1 W2) =
    sqrt(W1) sqrt(W2)); computed in float64. Empty overlaps: inf.
    """
    w1 = np.asarray(w1).reshape(len(w1), -1)
    cells = np.flatnonzero(np.any(w1 > SUPPORT, axis=0))   # every integral is 0 where no tuple of set 1 has W
    om = grid.solid_angles.reshape(-1)[cells]

    def parts(d, w):
        d = np.asarray(d, float).reshape(len(d), -1)[:, cells]
        w = np.clip(np.asarray(w, float).reshape(len(w), -1)[:, cells], 0.0, None)
        m = (w > SUPPORT).astype(float)
        sw = np.sqrt(w) * m
        return d, m, sw

    a_d, a_m, a_sw = parts(d1, w1)
    b_d, b_m, b_sw = parts(d2, w2)
    s1 = (a_d * a_m) @ (b_m * om).T
    s2 = (a_m * om) @ (b_d * b_m).T
    overlap = (a_m * om) @ b_m.T
    den = (a_sw * om) @ b_sw.T
    a11 = (a_sw * a_d**2 * om) @ b_sw.T
    a12 = (a_sw * a_d * om) @ (b_sw * b_d).T
    a22 = (a_sw * om) @ (b_sw * b_d**2).T
    return _finish(a11, a12, a22, s1, s2, den, a11, a22, overlap).distance


def turned_pairwise_distance(d: np.ndarray, grid: DirectionGrid, max_shift: int) -> np.ndarray:
    """:func:`pairwise_distance` between complete NDFs (W = 1 on every cell) ``d`` (R, T, F) and each of them
    turned (eq. 13) by -max_shift .. max_shift whole sectors: (R, R, 2 max_shift + 1), [j, k, s] = d_j
    against d_k turned by s - max_shift.

    With the whole domain in the overlap only the cross term of eq. 15 moves with the turn, and it is a
    circular cross-correlation along phi: every turn of every pair from one FFT per NDF."""
    d = np.asarray(d, float)
    om = grid.solid_angles
    spectra = np.fft.rfft(d, axis=-1)                                               # (R, T, nf)
    cross = np.fft.irfft(np.einsum("jtf,t,ktf->jkf", np.conj(spectra), om[:, 0], spectra), n=grid.n_phi,
                         axis=-1)                                                   # (R, R, F): every lag
    a12 = cross[..., np.arange(-max_shift, max_shift + 1) % grid.n_phi]
    s, squares = np.sum(d * om, axis=(1, 2)), np.sum(d**2 * om, axis=(1, 2))
    area = np.full(a12.shape, om.sum())
    a11, a22 = squares[:, None, None], squares[None, :, None]
    return _finish(a11, a12, a22, s[:, None, None], s[None, :, None], area, a11, a22, area).distance


# ----------------------------------------------------------------------------
# eq. 13-15 for every whole-sector rotation: circular cross-correlation by FFT
# ----------------------------------------------------------------------------
class ExemplarSpectra:
    """FFTs along phi of an exemplar set's eq. 15 factors, for scoring all rotations at once.

    For a query <Dq, Wq> and exemplar x rotated by k sectors (D_x^k[t, p] =
    D_x[t, p + k], i.e. ``grid.rotate(D_x, k * d_phi)``), every integral of
    eq. 15 is sum_t sum_p q[t, p] c_x[t, p + k]: a circular cross-correlation,
    conj(FFT q) * FFT c_x summed over rings. Memory: 5 complex64 arrays of
    (N, T, F/2 + 1).
    """

    def __init__(self, d: np.ndarray, w: np.ndarray, grid: DirectionGrid, index: np.ndarray | None = None):
        self.grid = grid
        self.index = np.arange(len(d)) if index is None else np.asarray(index)
        n = len(d)
        nf = grid.n_phi // 2 + 1
        self.spectra = np.empty((5, nf, n, grid.n_theta), np.complex64)   # frequency-major for batched matmul
        self.area = np.empty(n)
        om = grid.solid_angles
        for start in range(0, n, 256):
            sl = slice(start, min(start + 256, n))
            dd, ww = np.asarray(d[sl], float), np.clip(np.asarray(w[sl], float), 0.0, None)
            m = (ww > SUPPORT).astype(float)
            sw = np.sqrt(ww) * m
            dm = dd * m
            for j, arr in enumerate((m, dm, sw, sw * dd, sw * dd**2)):
                self.spectra[j, :, sl, :] = np.fft.rfft(arr, axis=-1).transpose(2, 0, 1)
            self.area[sl] = np.sum(m * om, axis=(1, 2))

    def __len__(self) -> int:
        return len(self.area)

    def scores(self, dq: np.ndarray, wq: np.ndarray, rows: np.ndarray | None = None) -> tuple[Match, np.ndarray]:
        """Eq. 15 between query <dq, wq> (T, F) and every exemplar (or ``rows``) at every shift k.

        Returns (Match with arrays (N, F), overlap fraction (N, F) = area of
        Omega_q cap Omega_x^k / area of Omega_x).
        """
        om = self.grid.solid_angles
        wq = np.clip(np.asarray(wq, float), 0.0, None)
        dq = np.asarray(dq, float)
        m = (wq > SUPPORT).astype(float)
        sw = np.sqrt(wq) * m
        q = np.stack([m * om, dq * m * om, sw * om, sw * dq * om, sw * dq**2 * om])     # (5, T, F)
        qf = np.conj(np.fft.rfft(q, axis=-1)).transpose(2, 1, 0).astype(np.complex64)  # (nf, T, 5)
        spec = self.spectra if rows is None else self.spectra[:, :, rows, :]
        n_phi = self.grid.n_phi

        def corr(c_index, q_index):
            out = np.matmul(spec[c_index], qf[:, :, q_index])                   # (nf, N, len(q_index))
            return np.fft.irfft(out, n=n_phi, axis=0).transpose(1, 2, 0)        # (N, len(q), F)

        c_m = corr(0, [0, 1])          # overlap area, S1
        s2 = corr(1, [0])[:, 0]
        c_sw = corr(2, [2, 4])         # den, A11
        a12 = corr(3, [3])[:, 0]
        a22 = corr(4, [2])[:, 0]
        overlap, s1 = c_m[:, 0], c_m[:, 1]
        den, a11 = c_sw[:, 0], c_sw[:, 1]
        # float32 spectra: tiny negative round-off where the true value is 0
        scale = max(np.abs(overlap).max(initial=0.0), 1e-12)
        overlap = np.where(overlap > 1e-4 * scale / max(len(om), 1), overlap, 0.0)
        match = _finish(a11, a12, a22, s1, s2, den, a11, a22, overlap)
        area = self.area if rows is None else self.area[rows]
        fraction = overlap / np.where(area > 0, area, np.inf)[:, None]
        return match, fraction


# ----------------------------------------------------------------------------
# eqs. 16-17: merge
# ----------------------------------------------------------------------------
def merge(d: np.ndarray, w: np.ndarray, dc: np.ndarray, wc: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge an aligned candidate <dc, wc> into <d, w> (eqs. 16-17); ratio = s1 / s2.

    D' = (W D + (s1/s2) Wc Dc) / (W + Wc) where W + Wc > 0 (D kept elsewhere),
    W' = max(W, Wc).
    """
    total = w + wc
    merged = np.divide(w * d + ratio * wc * dc, total, out=np.array(d, dtype=float, copy=True), where=total > 0)
    return merged, np.maximum(w, wc)


def rotate_tuple(d: np.ndarray, w: np.ndarray, grid: DirectionGrid, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """<D, W> rotated by ``shift`` sectors (eq. 13): D(R(phi) h) with phi = shift * d_phi.

    The domain of a fractionally rotated W is the intersection of the two
    whole shifts it blends (no partial support leaks into empty cells).
    """
    phi = shift * grid.d_phi
    dr, wr = grid.rotate(d, phi), grid.rotate(w, phi)
    if shift != np.floor(shift):
        k = int(np.floor(shift))
        inside = (np.roll(w, -k, axis=-1) > SUPPORT) & (np.roll(w, -k - 1, axis=-1) > SUPPORT)
        wr = np.where(inside, wr, 0.0)
    return dr, wr


# ----------------------------------------------------------------------------
# the common domain and its rotations (sec. 5.3, Fig. 7c-d)
# ----------------------------------------------------------------------------
def overlap_curve(mask: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """f(k) = area(Omega cap Omega shifted by k sectors) / area(Omega), k = 0 .. n_phi - 1."""
    om = grid.solid_angles
    m = mask.astype(float)
    area = np.sum(m * om)
    if area <= 0:
        return np.zeros(grid.n_phi)
    spec = np.fft.rfft(m, axis=-1)
    c = np.fft.irfft(np.sum(np.conj(spec * om[:, :1]) * spec, axis=0), n=grid.n_phi)
    return np.clip(c / area, 0.0, 1.0)


def region_shifts(mask: np.ndarray, grid: DirectionGrid, n_regions: int, lo: float, hi: float) -> np.ndarray:
    """n_regions shifts (sectors, positive = counter-clockwise extension) with overlap in [lo, hi].

    Uniformly sampled between the smallest and largest whole shift in 1 .. n_phi/2
    whose overlap fraction lies in [lo, hi]; empty if there is none.
    """
    f = overlap_curve(mask, grid)
    k = np.arange(1, grid.n_phi // 2 + 1)
    ok = k[(f[k] >= lo) & (f[k] <= hi)]
    if ok.size == 0:
        return np.zeros(0)
    return np.linspace(ok.min(), ok.max(), n_regions)


def hemisphere_target(masks: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """Omega_+ as far as rotations can reach: every cell of a ring that some domain touches.

    A single view never sees half vectors near the horizon, and rotation about
    the normal cannot move a half vector's elevation: those rings are outside
    what synthesis can complete (push-pull extends to them).
    """
    rings = np.any(masks, axis=tuple(range(masks.ndim - 2)) + (-1,))
    return np.broadcast_to(rings[:, None], grid.shape)


def hold_beyond_reach(table: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(..., T, F) tables with every ring past the last ring of ``target`` set to that ring's values
    (per azimuth). Push-pull alone fills those rings from whichever coarse level first holds data, which
    depends on where the level boundaries fall: on a 24-ring grid that was the average of the whole
    lobe (demo: NDF error 0.69 against 0.15 on 32 rings, where a level boundary sits at 45 deg)."""
    rings = np.flatnonzero(np.any(target, axis=-1))
    if rings.size == 0 or rings.max() >= table.shape[-2] - 1:
        return table
    last = int(rings.max())
    out = np.array(table, dtype=float, copy=True)
    out[..., last + 1:, :] = out[..., last:last + 1, :]
    return out


def decay_beyond_reach(ndf: np.ndarray, target: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """Continue (..., T, F) NDFs past the last ring of ``target`` with a GGX-shaped decay, per azimuth.

    A GGX lobe (isotropic or, along any one azimuth, anisotropic) has D^(-1/2) linear in sin^2 theta:
    D = 1 / (pi a_x a_y (sin^2 theta q(phi) + cos^2 theta)^2). Per azimuth the line is fitted (least
    squares) to the outer half of the reachable rings (theta at least half the last one's, D > 0) and
    continued from the last reachable ring's value, its slope clamped >= 0 (D non-increasing); an azimuth
    with fewer than two such rings takes the median relative slope of the table's others (none: the last
    ring held). The outer rings, not the lobe's core: a measured lobe is not one GGX, and its tail follows
    its broad part (the Mitsuba quadrants' satin: a line through the core cut its mass beyond 50 deg from
    0.066 to 0.013 and doubled its held-out lights' error).

    Rotation about the normal cannot move a half vector's elevation, so synthesis leaves those rings
    empty, yet they carry mass that ks = integral (n.h) D (sec. 5.4) and A(k) (eq. 5) count: the last ring
    held to the horizon put 7.6 % of the demo copper's mass beyond 45 deg (truth 5.2 %: ks 1.10 x the
    truth), a log-linear extension 2.6 % of the paint's (truth 4.6 %: ks 0.95 x).
    """
    rings = np.flatnonzero(np.any(target, axis=-1))
    if rings.size == 0 or rings.max() >= grid.n_theta - 1:
        return np.asarray(ndf, float)
    last = int(rings.max())
    d = np.clip(np.asarray(ndf, float), 0.0, None)
    x = np.sin(grid.theta) ** 2                                      # (T,)
    outer = grid.theta[:last + 1] >= 0.5 * grid.theta[last]
    use = (d[..., :last + 1, :] > 0) & outer[:, None]                 # (..., L+1, F)
    y = np.where(use, np.maximum(d[..., :last + 1, :], TINY) ** -0.5, 0.0)
    xs = np.broadcast_to(x[:last + 1, None], use.shape)
    n = use.sum(axis=-2)
    sx, sy = (use * xs).sum(axis=-2), y.sum(axis=-2)
    sxx, sxy = (use * xs * xs).sum(axis=-2), (y * xs).sum(axis=-2)
    den = n * sxx - sx * sx
    ok = (n >= 2) & (den > 1e-12)
    slope = np.where(ok, (n * sxy - sx * sy) / np.where(ok, den, 1.0), 0.0)
    y_last = np.maximum(d[..., last, :], TINY) ** -0.5
    relative = np.maximum(slope, 0.0) / y_last                       # per unit sin^2 theta, in units of y_last
    fallback = np.ma.filled(np.ma.median(np.ma.masked_array(relative, ~ok), axis=-1), 0.0)   # the other azimuths
    relative = np.where(ok, relative, np.asarray(fallback)[..., None])
    tail = y_last[..., None, :] * (1.0 + relative[..., None, :] * (x[last + 1:, None] - x[last]))
    out = d.copy()
    out[..., last + 1:, :] = np.where(d[..., last:last + 1, :] > 0, tail ** -2.0, 0.0)
    return out


# ----------------------------------------------------------------------------
# sec. 5.3 search pruning: histograms of D over sampled overlap regions, one ANN index each
# ----------------------------------------------------------------------------
class HistogramSearch:
    """n_phi overlap regions Omega(phi_i), 32-bucket histograms, one pynndescent index per region.

    Regions are built for both senses of rotation: +phi_i extends a domain
    piece counter-clockwise, -phi_i clockwise (the side of the first piece,
    needed for the periodic wrap). The histogram of a tuple over a region:
    solid-angle weighted counts of D / mean(D) over the region's cells in
    ``buckets`` buckets over [0, ``top``] (values above go to the last
    bucket), normalised to sum 1. The paper buckets D over [0, 1]; here D
    carries the specular albedo and Fresnel factor, so it is divided by its
    mean over the region first, which makes the key scale invariant like
    eq. 15. ``top`` is the 99th percentile of those values over the exemplars.
    ``exact=True`` replaces the ANN indexes by a brute-force search of the
    same keys (for tests; the stage's exact mode bypasses the histograms).
    """

    def __init__(self, d: np.ndarray, mask: np.ndarray, grid: DirectionGrid, shifts: np.ndarray,
                 *, buckets: int, seed: int, n_neighbors: int, epsilon: float, exact: bool = False):
        self.grid, self.buckets, self.exact, self.epsilon = grid, buckets, exact, epsilon
        shifts = np.unique(np.round(np.asarray(shifts, float)).astype(int))
        self.shifts = shifts
        # region in the exemplar's frame: +s: Omega cap (Omega - s); -s: Omega cap (Omega + s)
        self.regions = [(sign, int(s), mask & np.roll(mask, -sign * int(s), axis=-1))
                        for sign in (+1, -1) for s in shifts]
        om = grid.solid_angles
        d = np.asarray(d, np.float32)
        tops = []
        for _, _, region in self.regions:
            vals = d[:, region].astype(float)
            if vals.size:
                vals = vals / np.maximum(np.mean(vals, axis=1, keepdims=True), TINY)
                tops.append(np.quantile(vals, 0.99))
        self.top = float(max(max(tops) if tops else 1.0, 1e-6))
        self.keys = [self.histogram(d[:, region], om[region]) for _, _, region in self.regions]
        self.indexes = []
        self.build_seconds = 0.0
        if not exact:
            from pynndescent import NNDescent
            t0 = time.perf_counter()
            for keys in self.keys:
                index = None
                if len(keys) > 8:
                    index = NNDescent(keys, metric="euclidean", n_neighbors=min(n_neighbors, len(keys) - 1),
                                      random_state=seed, low_memory=True)
                    index.prepare()
                self.indexes.append(index)
            self.build_seconds = time.perf_counter() - t0

    def histogram(self, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(N, buckets) float32 histograms of rows of values (N, C) with cell weights (C,)."""
        values = np.asarray(values, float)
        if values.ndim == 1:
            values = values[None]
        n = len(values)
        out = np.zeros((n, self.buckets), np.float32)
        if values.shape[1] == 0:
            return out
        v = values / np.maximum(np.mean(values, axis=1, keepdims=True), TINY)
        b = np.clip((v / self.top * self.buckets).astype(np.intp), 0, self.buckets - 1)
        b += np.arange(n)[:, None] * self.buckets
        out = np.bincount(b.ravel(), weights=np.broadcast_to(weights, b.shape).ravel(),
                          minlength=n * self.buckets).reshape(n, self.buckets)
        out /= np.maximum(out.sum(axis=1, keepdims=True), TINY)
        return out.astype(np.float32)

    def query(self, d_current: np.ndarray, upper: float, lower: float, k: int = 5) -> list[tuple[int, int]]:
        """Candidates (exemplar row, predicted whole shift) extending the covered arc at either end.

        A piece merged with shift c has domain Omega - c (sectors); the arc
        covered so far runs from the piece at position ``lower`` to the one at
        ``upper`` (position = -c). An exemplar extending the upper end by
        s_i has shift c = -upper - s_i, and its overlap with that piece is,
        in its own frame, Omega cap (Omega - s_i); the lower end likewise with
        c = -lower + s_i. The current NDF is read on that region in the query
        frame (D_q[u - c]) and its histogram looked up in the region's index.
        """
        out = []
        om = self.grid.solid_angles
        for i, (sign, s, region) in enumerate(self.regions):
            if not region.any():
                continue
            c = int(round(-upper - s)) if sign > 0 else int(round(-lower + s))
            dq = np.roll(d_current, c, axis=-1)[region]
            key = self.histogram(dq, om[region])
            if self.exact or self.indexes[i] is None:
                dist = np.sum((self.keys[i] - key) ** 2, axis=1)
                best = np.argsort(dist, kind="stable")[:k]
            else:
                best = self.indexes[i].query(key, k=min(k, len(self.keys[i])), epsilon=self.epsilon)[0][0]
            out.extend((int(b), c % self.grid.n_phi) for b in best)
        return out


# ----------------------------------------------------------------------------
# completion of one NDF
# ----------------------------------------------------------------------------
@dataclass
class Completion:
    ndf: np.ndarray                  # (T, F) after push-pull
    confidence: np.ndarray           # (T, F) W after the last merge (before push-pull)
    coverage: float                  # fraction of the target covered before push-pull
    iterations: int
    stalled: bool                    # stopped because the best match was too dissimilar (not merged)
    merges: list = field(default_factory=list)   # dicts: exemplar, shift, relative_error, overlap, merged
    fallbacks: int = 0               # ANN iterations that fell back to the exact search
    fresnel_cosine: np.ndarray | None = None   # (T, F) cosine of the Fresnel factor each cell carries


@dataclass(frozen=True)
class Knobs:
    """What :func:`complete` merges and stops by (sec. 5.2-5.3). No defaults: the synthesize stage's
    ``Settings`` (config ``synthesize``) holds them."""
    overlap_range: tuple[float, float]   # a candidate's domain overlaps the current one by this share of its own
    max_iterations: int                  # merges at most
    target_coverage: float               # stop once this fraction of the target is covered
    max_relative_error: float            # a best match less similar (eq. 15, relative) stalls the synthesis
    candidates_per_region: int           # ANN matches per overlap region (sec. 5.3)
    fill_overlap: float | None           # the upper overlap bound relaxed to this for the last holes; None: off
    refine: bool = True                  # the best whole-sector shift refined below a sector (tests: off)


def _refine(ed: np.ndarray, ew: np.ndarray, shift: int, d, w, grid, lo: float, hi: float) -> tuple[float, Match, float]:
    """Sub-sector phi minimising eq. 14 around whole shift ``shift`` (golden section on [k-1, k+1])."""
    def score(s):
        dc, wc = rotate_tuple(ed, ew, grid, s)
        m = distance(d, w, dc, wc, grid)
        area = np.sum((wc > SUPPORT) * grid.solid_angles)
        frac = float(m.overlap / area) if area > 0 else 0.0
        return (float(m.distance) if lo <= frac <= hi else np.inf), m, frac

    best = (float(shift),) + score(float(shift))
    a, b = shift - 1.0, shift + 1.0
    g = (np.sqrt(5) - 1) / 2
    x1, x2 = b - g * (b - a), a + g * (b - a)
    f1, f2 = score(x1), score(x2)
    for _ in range(6):
        if f1[0] <= f2[0]:
            b, x2, f2 = x2, x1, f1
            x1 = b - g * (b - a)
            f1 = score(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + g * (b - a)
            f2 = score(x2)
    for x, f in ((x1, f1), (x2, f2)):
        if f[0] < best[1]:
            best = (x,) + f
    return best[0], best[2], best[3]


def ring_means(values: np.ndarray, w: np.ndarray, grid: DirectionGrid) -> tuple[np.ndarray, np.ndarray]:
    """W dw-weighted mean of ``values`` (..., T, F) over the domain cells of each theta ring.

    Returns (means (..., T), covered (..., T) bool: rings the domain touches;
    the mean of an untouched ring is 0).
    """
    w = np.clip(np.asarray(w, float), 0.0, None)
    ww = np.where(w > SUPPORT, w, 0.0) * grid.solid_angles
    total = ww.sum(axis=-1)
    covered = total > 0
    means = np.sum(ww * np.asarray(values, float), axis=-1) / np.where(covered, total, 1.0)
    return np.where(covered, means, 0.0), covered


def _ring_harmonics(d: np.ndarray, w: np.ndarray, grid: DirectionGrid, order: int):
    """Per theta ring, the W dw-weighted least-squares fit of D (..., T, F) on the ring's domain cells by
    a + sum_k (b_k cos(k phi) + c_k sin(k phi)), k = 1 .. ``order``. Returns (coefficients (..., T, n) in
    the order 1, cos phi, sin phi, cos 2 phi, ..., the basis (F, n), the weights W dw (..., T, F)); a
    small ridge keeps rings with fewer than n domain cells solvable."""
    w = np.clip(np.asarray(w, float), 0.0, None)
    ww = np.where(w > SUPPORT, w, 0.0) * grid.solid_angles
    ph = grid.phi
    basis = np.stack([np.ones_like(ph)] + [f(k * ph) for k in range(1, order + 1) for f in (np.cos, np.sin)], -1)
    n = basis.shape[1]
    a = (ww @ (basis[:, :, None] * basis[:, None, :]).reshape(-1, n * n)).reshape(ww.shape[:-1] + (n, n))
    b = (ww * np.asarray(d, float)) @ basis          # matrix products: einsum's loops took twice as long
    a = a + (1e-9 * np.trace(a, axis1=-2, axis2=-1)[..., None, None] + 1e-300) * np.eye(n)
    return np.linalg.solve(a, b[..., None])[..., 0], basis, ww


def anisotropy(d: np.ndarray, w: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """Relative L2 deviation (...,) of a partial NDF from azimuthal symmetry, over its domain.

    Per theta ring, D is fitted on the ring's domain cells (weights W dw) by
    a + b cos(phi) + c sin(phi): its ring mean plus the first azimuthal
    harmonic. The statistic is sqrt(int_Omega W (D - fit)^2 dw / int_Omega
    W D^2 dw). 0 for an isotropic NDF whatever its domain; an anisotropic
    microfacet NDF (D(h) = D(R(pi) h): GGX, Beckmann, Ward) varies with
    2 phi and higher harmonics, which the fit cannot absorb on rings the
    domain covers all round. The first harmonic is left out because what a
    single view adds along a ring (the Fresnel factor of eq. 11, shadowing,
    the shift of a narrow resampled highlight) varies mostly with the
    azimuth relative to the view's. An empty or all-zero tuple gives inf.
    Measured values and the threshold: docs/decisions.md.
    """
    d = np.asarray(d, float)
    coefficients, basis, ww = _ring_harmonics(d, w, grid, order=1)
    fit = coefficients @ basis.T
    num = np.sum(ww * (d - fit) ** 2, axis=(-2, -1))
    den = np.sum(ww * d**2, axis=(-2, -1))
    return np.where(den > TINY, np.sqrt(num / np.where(den > TINY, den, 1.0)), np.inf)


def orientation(d: np.ndarray, w: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """The second azimuthal harmonic (...,) complex of partial NDFs (..., T, F) over their domains.

    Per theta ring, D is fitted on the ring's domain cells (weights W dw) by
    a + b cos(phi) + c sin(phi) + e cos(2 phi) + f sin(2 phi); the result is
    sum over rings of (e + i f) x the ring's domain weight. Its angle is
    2 psi, psi the azimuth of the lobe's axis (mod 180 deg: a microfacet NDF
    is symmetric under R(pi)); its modulus grows with the anisotropy. The
    view's own domain biases psi by the same amount at every point of a
    capture, so psi compares points of one capture (and of captures of the
    same rig turned, paper 002 sec. 4). An empty tuple gives 0.
    """
    c, _, ww = _ring_harmonics(d, w, grid, order=2)
    return np.sum((c[..., 3] + 1j * c[..., 4]) * ww.sum(axis=-1), axis=-1)


def orientation_concentration(z: np.ndarray) -> float:
    """|mean of z / |z||| over tuples' second harmonics z (:func:`orientation`): 1 when every lobe's axis
    is the same (no rotation diversity: brushed metal), near 0 when the axes are spread (wallpaper) or
    come in two perpendicular sets (a satin's warp and weft). nan without a tuple of nonzero z."""
    z = np.asarray(z, complex).ravel()
    z = z[np.abs(z) > 0]
    return float(np.abs(np.mean(z / np.abs(z)))) if z.size else float("nan")


def complete_isotropic(d0: np.ndarray, w0: np.ndarray, grid: DirectionGrid, target: np.ndarray, *,
                       view: np.ndarray | None = None, min_ring_coverage: float = 1 / 3) -> Completion:
    """Complete an isotropic partial NDF <d0, w0> (T, F) by azimuthal symmetry: no exemplar search.

    Every ring whose cells the domain covers by at least ``min_ring_coverage``
    gets its ring mean (:func:`ring_means`, weights W dw) at every azimuth;
    the profile continues past the last such ring by :func:`decay_beyond_reach`
    (GGX-shaped, non-increasing). On rings the domain only grazes
    (a narrow arc at its edge, grazing light) the partial NDF of a rough
    material falls far below the true one; their ring means would carry
    that bias round the whole ring (card, 340-light rig: 0.59 -> 0.21,
    docs/decisions.md). The confidence is the ring mean of W on the rings
    used. With ``view`` the cosine |o . h| of the Fresnel factor
    (:func:`facetsynth.fit.partial_ndf.fresnel_cosine`) is averaged per ring the
    same way (push-pull beyond).
    """
    w0 = np.clip(np.asarray(w0, float), 0.0, None)
    r, touched = ring_means(d0, w0, grid)
    covered = touched & (np.mean(w0 > SUPPORT, axis=-1) >= min_ring_coverage)
    if not covered.any():
        covered = touched
    wr, _ = ring_means(w0, w0, grid)
    w = np.broadcast_to(np.where(covered, wr, 0.0)[:, None], grid.shape).copy()
    d = np.broadcast_to(r[:, None], grid.shape).copy()
    full = np.broadcast_to(covered[:, None], grid.shape).astype(float)    # the ring means are kept as they are:
    filled = push_pull(full * d, full)                                     # push-pull only fills the other rings
    filled = np.where(np.isfinite(filled), np.maximum(filled, 0.0), 0.0)
    filled = decay_beyond_reach(filled, full > 0, grid)
    cosine = None
    if view is not None:
        c, _ = ring_means(fresnel_cosine(view, grid), w0, grid)
        cosine = np.broadcast_to(c[:, None], grid.shape)
        cosine = np.clip(np.nan_to_num(push_pull(full * cosine, full), nan=0.0), 0.0, 1.0)
    return Completion(ndf=filled, confidence=w, coverage=coverage(w, target, grid), iterations=0, stalled=False,
                      merges=[], fallbacks=0, fresnel_cosine=cosine)


def complete(d0: np.ndarray, w0: np.ndarray, spectra: ExemplarSpectra, exemplars_d: np.ndarray,
             exemplars_w: np.ndarray, grid: DirectionGrid, target: np.ndarray, knobs: Knobs, *,
             search: HistogramSearch | None = None, exclude: int | None = None,
             view: np.ndarray | None = None, exemplars_view: np.ndarray | None = None) -> Completion:
    """Complete one partial NDF <d0, w0> (T, F) by iterative synthesis (sec. 5.2).

    Each iteration merges (eqs. 16-17) the exemplar and rotation minimising eq. 14 against the current
    tuple among those whose domain overlaps the current one as ``knobs.overlap_range`` asks
    (:func:`next_match`: the exact search, or the ANN candidates of ``search``, sec. 5.3). A best match
    whose relative error (``Match.relative``) exceeds ``knobs.max_relative_error`` is not merged: the
    synthesis stops (stalled) rather than merge dissimilar data. It ends when ``knobs.target_coverage`` of
    ``target`` is covered, after ``knobs.max_iterations`` merges, or when no candidate overlaps as the rule
    asks; holes and the rings beyond the reach of rotation are then filled (:func:`fill_holes`). ``exclude``:
    an exemplar row not to use at all (tests: the query itself).

    With ``view`` (the query's view o, (3,)) and ``exemplars_view`` (N, 3), the cosine |o . h| of the
    Fresnel factor that eq. 11 leaves in each cell is carried along: rotated with each merged exemplar and
    merged with the weights of eq. 16 (``Completion.fresnel_cosine``), so that sec. 5.4 can divide the
    right F out of every cell (docs/decisions.md).
    """
    d, w = np.asarray(d0, float).copy(), np.clip(np.asarray(w0, float), 0.0, None).copy()
    cosine = None if view is None else fresnel_cosine(view, grid)
    merges, stalled, fallbacks, iterations = [], False, 0, 0
    arc = (0.0, 0.0)    # positions (sectors, unwrapped) of the pieces at the upper and lower end of the covered arc
    while iterations < knobs.max_iterations and coverage(w, target, grid) < knobs.target_coverage:
        found, fell_back = next_match(d, w, spectra, exemplars_d, exemplars_w, knobs, search, arc, exclude)
        fallbacks += fell_back
        if found is None:
            break       # nothing overlaps as the rule asks: the domain is as complete as merging can make it
        row, bound, s, m, f = found
        record = {"exemplar": row, "shift": s, "relative_error": float(m.relative), "overlap": f}
        if not np.isfinite(m.distance) or float(m.relative) > knobs.max_relative_error:
            stalled = True
            merges.append({**record, "merged": False})
            break
        dc, wc = rotate_tuple(np.asarray(exemplars_d[row], float), np.asarray(exemplars_w[row], float), grid, s)
        if cosine is not None:
            cosine_c = grid.rotate(fresnel_cosine(exemplars_view[row], grid), s * grid.d_phi)
            cosine = merge(cosine, w, cosine_c, wc, 1.0)[0]
        d, w = merge(d, w, dc, wc, float(m.s1 / m.s2))
        merges.append({**record, "merged": True, "fill": bound > knobs.overlap_range[1]})
        iterations += 1
        arc = extend_arc(arc, s, grid.n_phi)
    ndf, cosine = fill_holes(d, w, cosine, target, grid)
    return Completion(ndf=ndf, confidence=w, coverage=coverage(w, target, grid), iterations=iterations,
                      stalled=stalled, merges=merges, fallbacks=fallbacks, fresnel_cosine=cosine)


def coverage(w: np.ndarray, target: np.ndarray, grid: DirectionGrid) -> float:
    """The fraction (by solid angle) of ``target`` inside the domain Omega = {W > 0} of ``w`` (T, F)."""
    om = grid.solid_angles
    return float(np.sum(((w > SUPPORT) & target) * om)) / max(float(np.sum(target * om)), TINY)


def next_match(d: np.ndarray, w: np.ndarray, spectra: ExemplarSpectra, exemplars_d: np.ndarray,
               exemplars_w: np.ndarray, knobs: Knobs, search: HistogramSearch | None, arc: tuple[float, float],
               exclude: int | None) -> tuple[tuple | None, bool]:
    """One iteration's match, (row, overlap bound used, shift, Match, overlap fraction) or None
    (:func:`best_match`, then :func:`aligned_match`), and whether the exact search stood in for ``search``:
    where the ANN candidates hold no acceptable match, the iteration is searched exhaustively, so that a
    stall always means that no exemplar at all matches."""
    def found(use_search):
        choice = best_match(d, w, spectra, knobs, use_search, arc, exclude)
        return None if choice is None else aligned_match(choice, exemplars_d, exemplars_w, d, w, spectra.grid, knobs)

    result = found(search)
    if search is not None and (result is None or not float(result[3].relative) <= knobs.max_relative_error):
        return found(None), True        # inf and nan miss
    return result, False


def best_match(d: np.ndarray, w: np.ndarray, spectra: ExemplarSpectra, knobs: Knobs,
               search: HistogramSearch | None, arc: tuple[float, float],
               exclude: int | None) -> tuple[int, int, float] | None:
    """The best acceptable (row, whole shift, upper overlap bound used) under eq. 14, or None.

    The exact search (``search`` None) scores every exemplar at every whole-sector shift; with ``search``,
    its candidates (``knobs.candidates_per_region`` per overlap region, at both ends of the covered ``arc``:
    the periodic wrap, sec. 5.3) are each scored at every whole-sector rotation (eq. 14 minimised over phi
    for each candidate). A candidate's domain must overlap the current one by ``knobs.overlap_range``
    (fraction of the exemplar's domain); where none does, the upper bound is relaxed to
    ``knobs.fill_overlap`` (thin holes in the outer rings, which no candidate can extend by 15 % of its
    domain; None: the paper's rule only, docs/decisions.md)."""
    if search is None:
        rows = np.arange(len(spectra))
        match, frac = spectra.scores(d, w)
    else:
        rows = np.unique([r for r, _ in search.query(d, *arc, knobs.candidates_per_region)]).astype(int)
        if rows.size == 0:
            return None
        match, frac = spectra.scores(d, w, rows)
    lo, hi = knobs.overlap_range
    allowed = (frac >= lo) & np.isfinite(match.distance)
    if exclude is not None:
        allowed[rows == exclude] = False
    fill = knobs.fill_overlap
    for bound in (hi, fill) if fill and fill > hi else (hi,):
        cost = np.where(allowed & (frac <= bound), match.distance, np.inf)
        if cost.size and np.isfinite(cost.min()):
            i, shift = divmod(int(np.argmin(cost)), spectra.grid.n_phi)
            return int(rows[i]), int(shift), bound
    return None


def aligned_match(choice: tuple[int, int, float], exemplars_d: np.ndarray, exemplars_w: np.ndarray,
                  d: np.ndarray, w: np.ndarray, grid: DirectionGrid,
                  knobs: Knobs) -> tuple[int, float, float, Match, float]:
    """The chosen exemplar's (row, bound, shift s (sectors), eq. 15 Match, overlap fraction) against <d, w>:
    its whole shift refined below a sector (:func:`_refine`, eq. 14) unless ``knobs.refine`` is off."""
    row, shift, bound = choice
    ed, ew = np.asarray(exemplars_d[row], float), np.asarray(exemplars_w[row], float)
    if knobs.refine:
        return (row, bound) + _refine(ed, ew, shift, d, w, grid, knobs.overlap_range[0], bound)
    dc, wc = rotate_tuple(ed, ew, grid, float(shift))
    m = distance(d, w, dc, wc, grid)
    return row, bound, float(shift), m, float(m.overlap / max(np.sum((wc > SUPPORT) * grid.solid_angles), TINY))


def extend_arc(arc: tuple[float, float], s: float, n_phi: int) -> tuple[float, float]:
    """The covered arc's (upper, lower) ends after a merge with shift ``s``: the merged piece's domain sits
    at position -s, and it extends the nearer end (sec. 5.3's search looks past both)."""
    upper, lower = arc
    position = (-s) % n_phi
    up, down = (position - upper) % n_phi, (lower - position) % n_phi
    return (upper + up, lower) if up <= down else (upper, lower - down)


def fill_holes(d: np.ndarray, w: np.ndarray, cosine: np.ndarray | None, target: np.ndarray,
               grid: DirectionGrid) -> tuple[np.ndarray, np.ndarray | None]:
    """The completed NDF and Fresnel cosine: holes filled by push-pull (weights W), non-negative and finite;
    the rings beyond the reach of rotation (``target``) by :func:`decay_beyond_reach` (the cosine: the last
    ring held, :func:`hold_beyond_reach`)."""
    ndf = push_pull(w * d, w)
    ndf = np.where(np.isfinite(ndf), np.maximum(ndf, 0.0), 0.0)
    ndf = decay_beyond_reach(ndf, target, grid)
    if cosine is not None:
        cosine = hold_beyond_reach(np.clip(np.nan_to_num(push_pull(w * cosine, w), nan=0.0), 0.0, 1.0), target)
    return ndf, cosine
