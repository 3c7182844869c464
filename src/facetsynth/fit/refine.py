"""Per-point refinement: eq. 6 read forwards, fitted to each point's own samples (issue 29).

The paper's pipeline (secs. 5.1-5.4) gives every point an NDF (an eq. 18
mixture of completed representative NDFs, turned by the point's eq. 13
rotation), an eta, and ks and kd through clustering and eq. 9. Those are
shared by a cluster or biased by a threshold: ks was constant per cluster
(wedges on the demo's turned copper), and nothing asked the model to
reproduce the samples it was fitted on. With the NDF, shadowing and Fresnel
fixed, eq. 6 is linear in kd and ks per channel,

    rho(x, i, o) = kd(x)/pi + ks(x) g(x, i, o),   g = D(h) F(|i.h|) / (4 A(i) A(o)),

so each point's kd and ks follow from its valid samples by a 2 x 2 least
squares per channel, weighted as the capture weighs them: in radiance,
I = rho (n.i) L / r^2 (eq. 8), the quantity the self-check and the held-out
views score. A small ridge towards the pipeline's values keeps points whose
samples do not constrain ks (no highlight in view) where the pipeline put
them; kd, ks >= 0 (the constrained solution on the boundary otherwise).

Before that, the NDF's one systematic loss is corrected per material: the
completed lobes come out broader than the measurement (the demo's copper: a
26 % larger half-maximum solid angle than the truth, peak 16 % low; every
resampling on the way blurs). :func:`stretch` narrows (s < 1) or widens a
tabulated NDF in slope space, where a microfacet lobe's roughness scales
(Beckmann, GGX); s is chosen by the samples, as eta is (docs/decisions.md,
"The fit reproduces what it saw"). Then each point's NDF turn is searched
(:func:`best_turns`): clusters that shared one frame drew wedges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from ..geometry.grid import bilinear_at, bilinear_stencil


@dataclass(frozen=True)
class NormalSums:
    """Per point and channel the sums of the weighted least squares of rho = a + b g, a = kd/pi, b = ks:
    each (N, 3) (``u`` the sample weights, ``y`` the observed rho)."""
    u: np.ndarray       # sum u
    ug: np.ndarray      # sum u g
    ugg: np.ndarray     # sum u g^2
    uy: np.ndarray      # sum u y
    ugy: np.ndarray     # sum u g y
    uyy: np.ndarray     # sum u y^2

    @classmethod
    def of(cls, point: np.ndarray, n_points: int, y: np.ndarray, g: np.ndarray, u: np.ndarray) -> "NormalSums":
        """Accumulate samples: ``point`` (S,) index in [0, n_points), ``y`` (S, 3) observed rho, ``g`` (S,)
        the specular factor, ``u`` (S, 3) weights."""
        return cls(*_sample_sums(np.asarray(point, np.intp), n_points, np.asarray(y, float), np.asarray(g, float),
                                 np.asarray(u, float)))

    def sse(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(N, 3) weighted sum of squared residuals of rho = a + b g (expanded: no second pass)."""
        out = (self.uyy - 2 * a * self.uy - 2 * b * self.ugy + a * a * self.u + 2 * a * b * self.ug
               + b * b * self.ugg)
        return np.maximum(out, 0.0)


@numba.njit(cache=True, nogil=True)
def _sample_sums(point: np.ndarray, n_points: int, y: np.ndarray, g: np.ndarray, u: np.ndarray) -> np.ndarray:
    """:meth:`NormalSums.of`'s six sums (6, N, 3) in one pass over the samples, each added in the samples' order
    (as numpy's bincount adds them: the same sums to the bit)."""
    out = np.zeros((6, n_points, 3))
    for s in range(point.size):
        x, gs = point[s], g[s]
        for c in range(3):
            us, ys = u[s, c], y[s, c]
            out[0, x, c] += us
            out[1, x, c] += us * gs
            out[2, x, c] += us * gs * gs
            out[3, x, c] += us * ys
            out[4, x, c] += us * gs * ys
            out[5, x, c] += us * ys * ys
    return out


def solve(sums: NormalSums, a0: np.ndarray, b0: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """The non-negative least-squares (a, b) per point and channel, with a ridge towards (a0, b0).

    Minimises sum u (y - a - b g)^2 + lam ((a - a0)^2 + (b - b0)^2 s), lam = ridge x sum u (the prior
    counts as ``ridge`` of the point's samples), s = sum u g^2 / sum u (b's own scale). Where the samples
    do not constrain b (no g > 0: no highlight in view), b keeps b0 and a fits the samples given it. Where the
    unconstrained optimum has a < 0 or b < 0, the best with that one at 0 is taken (the 2-variable NNLS:
    the optimum with both at 0 is never better than one of these, as sum u y >= 0 when y >= 0). A point
    without samples (sum u = 0) keeps (a0, b0).
    """
    lam = ridge * sums.u
    s = np.divide(sums.ugg, sums.u, out=np.zeros_like(sums.u), where=sums.u > 0)
    m11, m12, m22 = sums.u + lam, sums.ug, sums.ugg + lam * s
    r1, r2 = sums.uy + lam * a0, sums.ugy + lam * s * b0
    det = m11 * m22 - m12 * m12
    ok = det > 1e-12 * np.maximum(m11 * m22, 1e-300)
    safe = np.where(ok, det, 1.0)
    # singular (no g > 0 among the samples: ks unconstrained): b stays b0, a fits the samples given it
    a_given_b0 = np.divide(r1 - m12 * b0, m11, out=a0.copy(), where=m11 > 0)
    a = np.where(ok, (m22 * r1 - m12 * r2) / safe, a_given_b0)
    b = np.where(ok, (m11 * r2 - m12 * r1) / safe, b0)
    # boundary solutions: b = 0 (a alone) and a = 0 (b alone)
    a_only = np.divide(r1, m11, out=np.zeros_like(r1), where=m11 > 0)
    b_only = np.divide(r2, m22, out=np.zeros_like(r2), where=m22 > 0)
    neg_b, neg_a = b < 0, a < 0
    a = np.where(neg_b, np.maximum(a_only, 0.0), a)
    b = np.where(neg_b, 0.0, b)
    b = np.where(neg_a & ~neg_b, np.maximum(b_only, 0.0), b)
    a = np.where(neg_a & ~neg_b, 0.0, a)
    empty = sums.u <= 0
    return np.where(empty, a0, a), np.where(empty, b0, b)


def radiance_weights(wi: np.ndarray, r2: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """u = ((n.i) L / r^2)^2 per sample and channel (..., 3): least squares on rho weighted by u is least
    squares on the radiance I = rho (n.i) L / r^2 of eq. 8."""
    e = np.clip(wi[..., 2], 0.0, None) / r2
    return (e[..., None] * intensity) ** 2


@numba.njit(cache=True, nogil=True)
def gather_samples(points, lights, frames, ok, rho):
    """A tile's samples in one compiled pass: of points (N, 3) under homogeneous lights (F, 4) (eq. 8's
    geometry, as :func:`facetsynth.models.render.light_geometry` makes it), the samples ``ok`` (N, F) lit
    from above in the point's shading frame (``frames`` (N, 3, 3), :func:`facetsynth.fit.normals.shading_frames`;
    empty: the plane's) whose residual ``rho`` (N, F, 3) float32 is finite (its three channels' float32 sum).
    Returns (point (S,), light (S,), i (S, 3) local, |P - x|^2 (S,) (1 for a light at infinity), rho (S, 3)
    float64), in (point, light) order."""
    n, f = ok.shape
    keep = np.zeros((n, f), np.bool_)
    wi = np.empty((n, f, 3))
    r2 = np.empty((n, f))
    count = 0
    for a in range(n):
        for b in range(f):
            if not ok[a, b]:
                continue
            w = lights[b, 3]
            dx, dy, dz = (lights[b, 0] - w * points[a, 0], lights[b, 1] - w * points[a, 1],
                          lights[b, 2] - w * points[a, 2])
            d2 = dx * dx + dy * dy + dz * dz
            norm = np.sqrt(d2)
            ix, iy, iz = dx / norm, dy / norm, dz / norm
            if frames.shape[0]:
                m = frames[a]
                ix, iy, iz = (m[0, 0] * ix + m[0, 1] * iy + m[0, 2] * iz, m[1, 0] * ix + m[1, 1] * iy + m[1, 2] * iz,
                              m[2, 0] * ix + m[2, 1] * iy + m[2, 2] * iz)
            if iz > 0 and np.isfinite(rho[a, b, 0] + rho[a, b, 1] + rho[a, b, 2]):
                keep[a, b] = True
                wi[a, b, 0], wi[a, b, 1], wi[a, b, 2] = ix, iy, iz
                r2[a, b] = d2 if w > 0 else 1.0
                count += 1
    point, light = np.empty(count, np.intp), np.empty(count, np.intp)
    i_out, r2_out, rho_out = np.empty((count, 3)), np.empty(count), np.empty((count, 3))
    s = 0
    for a in range(n):
        for b in range(f):
            if keep[a, b]:
                point[s], light[s], r2_out[s] = a, b, r2[a, b]
                for c in range(3):
                    i_out[s, c] = wi[a, b, c]
                    rho_out[s, c] = rho[a, b, c]
                s += 1
    return point, light, i_out, r2_out, rho_out


def stretch(table: np.ndarray, grid, s: float) -> np.ndarray:
    """The NDF tables (..., T, F) on ``grid`` stretched in slope space by ``s`` (Heitz 2014, sec. 5: the
    slope distribution P(m) = D(h) cos^4(theta_h), m = tan(theta_h) (cos phi, sin phi), scaled to
    P(m / s) / s^2): D_s(theta, phi) = D(theta', phi) cos^4(theta') / cos^4(theta), tan(theta') =
    tan(theta) / s, bilinear on the grid. GGX and Beckmann of roughness alpha become exactly those of
    s alpha (up to the normalisation, left to the caller: :func:`facetsynth.fit.params.normalise`); s = 1
    returns the tables."""
    if s == 1.0:
        return np.asarray(table, float)
    d = grid.directions
    theta = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
    source = np.arctan(np.tan(theta) / s)
    phi = np.arctan2(d[..., 1], d[..., 0])
    src = np.stack([np.sin(source) * np.cos(phi), np.sin(source) * np.sin(phi), np.cos(source)], -1)
    jacobian = (np.cos(source) / np.cos(theta)) ** 4
    return grid.lookup(np.asarray(table, float), src.reshape(-1, 3)).reshape(np.shape(table)) * jacobian


@numba.njit(cache=True, nogil=True)
def _turn_error(t, p, denom, r, u, table, s0, s1, k, urr, n_theta, n_phi):
    """:func:`best_turns`' error of one candidate turned by ``k`` sectors (k may be fractional) for the samples
    s0:s1 of one point, after its best ks >= 0."""
    ugr = 0.0
    ugg = 0.0
    for s in range(s0, s1):
        g = bilinear_at(table, t[s], p[s] + k, n_theta, n_phi) * denom[s]
        ugr += u[s] * g * r[s]
        ugg += u[s] * g * g
    return urr - ugr * ugr / ugg if (ugg > 0.0 and ugr > 0.0) else urr


@numba.njit(cache=True, nogil=True)
def _turn_errors(t, p, denom, r, u, table, s0, s1, window, urr, n_theta, n_phi, errors):
    """:func:`_turn_error` of every whole turn k = -window .. window into ``errors`` (2 window + 1,), in one
    pass over the samples: a whole turn moves a sample's bilinear stencil by k sectors and keeps its weights,
    so each sample reads the 2 window + 2 sectors of its two rings once."""
    n = 2 * window + 1
    ugr = np.zeros(n)
    ugg = np.zeros(n)
    for s in range(s0, s1):
        t0, t1, p0, _, ft, fp = bilinear_stencil(t[s], p[s] - window, n_theta, n_phi)
        a, b = t0 * n_phi, t1 * n_phi
        w00, w01, w10, w11 = (1 - ft) * (1 - fp), (1 - ft) * fp, ft * (1 - fp), ft * fp
        us, rs, ds = u[s], r[s], denom[s]
        lo0, lo1 = table[a + p0], table[b + p0]
        q = p0
        for k in range(n):
            q = q + 1 if q + 1 < n_phi else 0
            hi0, hi1 = table[a + q], table[b + q]
            g = (w00 * lo0 + w01 * hi0 + w10 * lo1 + w11 * hi1) * ds
            ugr[k] += us * g * rs
            ugg[k] += us * g * g
            lo0, lo1 = hi0, hi1
    for k in range(n):
        errors[k] = urr - ugr[k] * ugr[k] / ugg[k] if (ugg[k] > 0.0 and ugr[k] > 0.0) else urr


@numba.njit(cache=True, nogil=True, parallel=True)
def best_turns(offsets, t, p, denom, r, u, candidates, tables, n_theta, n_phi, window):
    """For each point the representative and turn whose NDF best explains its specular samples.

    Point x owns samples offsets[x]:offsets[x + 1] (luminance): ``r`` the specular residual, ``u`` its weight,
    (``t``, ``p``) the half vector's continuous cell coordinates in the point's current frame
    (:meth:`DirectionGrid.coordinates` after the point's turn), ``denom`` F / (4 A(i) A(o)) of the current
    model. A candidate is a representative of ``candidates`` (N, K) (-1: none) turned by k sectors, |k| <=
    ``window``: g = D_rep(t, p + k) denom, i.e. the turn grows by k d_phi (eq. 13's R(phi) adds phi to the
    azimuth). Its error after the best ks >= 0 is sum u r^2 - max(0, sum u g r)^2 / sum u g^2 (eq. 6 with kd
    fixed: the lobe's samples decide the shape). The best whole sector is then refined to a fraction of one:
    the vertex of the parabola through its error and its two neighbours', kept where its own error is lower
    (a turned material's frame turns continuously: whole sectors of 2.8 deg drew the demo's radial streaks).
    Returns (error (N,), representative (N,), k (N,), in sectors); a point without samples or candidates gets
    (inf, -1, 0).
    """
    n = offsets.size - 1
    best = np.full(n, np.inf)
    rep_out = np.full(n, -1, np.int64)
    k_out = np.zeros(n)
    for x in numba.prange(n):
        s0, s1 = offsets[x], offsets[x + 1]
        if s1 <= s0:
            continue
        urr = 0.0
        for s in range(s0, s1):
            urr += u[s] * r[s] * r[s]
        errors = np.empty(2 * window + 1)
        best_errors = np.full(2 * window + 1, np.inf)
        for j in range(candidates.shape[1]):
            rep = candidates[x, j]
            if rep < 0:
                continue
            _turn_errors(t, p, denom, r, u, tables[rep], s0, s1, window, urr, n_theta, n_phi, errors)
            for k in range(-window, window + 1):
                if errors[k + window] < best[x]:
                    best[x], rep_out[x], k_out[x] = errors[k + window], rep, k
            if rep_out[x] == rep:
                best_errors[:] = errors
        rep = rep_out[x]
        i = int(k_out[x]) + window
        if rep < 0 or i == 0 or i == 2 * window:
            continue
        e0, e1, e2 = best_errors[i - 1], best_errors[i], best_errors[i + 1]
        curvature = e0 - 2.0 * e1 + e2
        if curvature <= 0.0:
            continue
        k = k_out[x] + min(max(0.5 * (e0 - e2) / curvature, -0.5), 0.5)
        err = _turn_error(t, p, denom, r, u, tables[rep], s0, s1, k, urr, n_theta, n_phi)
        if err < best[x]:
            best[x], k_out[x] = err, k
    return best, rep_out, k_out


def table_normal_equations(cells: np.ndarray, weights: np.ndarray, coef: np.ndarray, r: np.ndarray,
                           u: np.ndarray, n_cells: int) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The normal equations (``m`` sparse (C, C), ``v`` (C,)) of sum u (r - coef D(h))^2 over the C cell values
    D of one table, for a batch of samples; batches add up (m1 + m2, v1 + v2).

    Eq. 6 read forwards for the NDF: with kd, ks, eta and A(k) fixed, a sample's specular residual
    r = rho - kd/pi is ks F/(4 A(i) A(o)) D(h), linear in the table through the bilinear lookup of h:
    D(h) = sum_j w_j D[cell_j]. ``cells``, ``weights`` (S, 4) the lookup of every sample's h (in its point's
    frame, turned as the point is), ``coef``, ``r``, ``u`` (S, 3) per channel ks F / (4 A(i) A(o)), the
    residual and the sample weight. The channels share the lookup: m = sum_s q_s w w^T with
    q = sum_c u_c coef_c^2, v = sum_s (sum_c u_c coef_c r_c) w. ``m`` couples only the cells of one sample's
    stencil, so it is built sparse (a dense (C, C) was 0.68 GB on 48 x 192)."""
    q = np.sum(u * coef * coef, axis=-1)
    p = np.sum(u * coef * r, axis=-1)
    cells = np.asarray(cells, np.int64)
    k = cells.shape[1]
    rows = np.repeat(cells, k, axis=1).ravel()            # (s, a, b) -> cells[s, a]
    cols = np.tile(cells, (1, k)).ravel()                  # (s, a, b) -> cells[s, b]
    values = (q[:, None, None] * weights[:, :, None] * weights[:, None, :]).ravel()
    m = sparse.coo_matrix((values, (rows, cols)), shape=(n_cells, n_cells)).tocsr()   # duplicates summed
    v = np.bincount(cells.ravel(), weights=(p[:, None] * weights).ravel(), minlength=n_cells)
    return m, v


def azimuthal_differences(n_theta: int, n_phi: int) -> sparse.csr_matrix:
    """L (C, C), C = n_theta n_phi: D^T L D = sum of (D[t, p + 1] - D[t, p])^2, the squared steps between
    neighbouring sectors around each ring of a table on the polar grid (periodic in phi). Cell index
    t n_phi + p, as :meth:`facetsynth.geometry.grid.DirectionGrid.bilinear` numbers them. Around the rings
    only: a dome's lights lie on rings of elevation, and a held-out light falls between the azimuths of its
    ring's neighbours; across the rings the table is the lobe's profile, which a metal's sharp highlight
    needs unblurred (the coin: docs/decisions.md, "the tables interpolate between the lights")."""
    index = np.arange(n_theta * n_phi).reshape(n_theta, n_phi)
    pairs = np.stack([index.ravel(), np.roll(index, -1, axis=1).ravel()], axis=1)
    rows = np.repeat(np.arange(len(pairs)), 2)
    d = sparse.csr_matrix((np.tile([1.0, -1.0], len(pairs)), (rows, pairs.ravel())),
                          shape=(len(pairs), n_theta * n_phi))
    return (d.T @ d).tocsr()


def half_turn_fold(n_theta: int, n_phi: int) -> sparse.csr_matrix:
    """P (C, C/2), C = n_theta n_phi: a table D = P x whose cells (t, p) and (t, p + n_phi/2) share one value
    x, i.e. a lobe that a half turn maps onto itself, D(h) = D(R(pi) h) (n_phi even)."""
    index = np.arange(n_theta * n_phi).reshape(n_theta, n_phi)
    half = (index // n_phi) * (n_phi // 2) + (index % n_phi) % (n_phi // 2)
    return sparse.csr_matrix((np.ones(index.size), (index.ravel(), half.ravel())),
                             shape=(index.size, index.size // 2))


def solve_table(m: sparse.spmatrix, v: np.ndarray, prior: np.ndarray, ridge: float,
                smooth: float = 0.0, shape: tuple[int, int] | None = None, half_turn: bool = False) -> np.ndarray:
    """The table (C,) minimising the normal equations' error plus lam_j (D_j - prior_j)^2 per cell, plus
    ``smooth`` x floor x the squared steps between neighbouring sectors of each ring
    (:func:`azimuthal_differences` on the grid of ``shape``, (n_theta, n_phi)), clipped at 0.

    lam_j = ridge x (M_jj + floor), floor = the mean of the observed M_jj: a cell the samples see a lot
    follows them, one they barely see (or not at all) keeps ``prior`` (the completed NDF: "keeping the
    completed NDF where the view saw nothing", issue 29). The smoothness term is what makes the table between
    the lights' half vectors an interpolation of what they saw rather than whatever fits each light's own
    cells (issue 35: on a light dome, the held-out lights fall between them). ``m`` couples only cells
    that share a sample's bilinear stencil (at most 9 per cell), so the system is solved sparse (SuperLU):
    the dense solve was O(C^3), 4.5 s per table on 40 x 160, and on 48 x 192 21 s against the sparse
    solve's 0.9 s.

    ``half_turn``: the table is point-symmetric, D(h) = D(R(pi) h) (:func:`half_turn_fold`): the normal
    equations are folded so that the samples of both halves measure one value per pair of cells. A brushed
    metal's lobe is; a material whose frame turns across the sample (the Mitsuba copper) has points at turns
    phi and phi + pi on either side of a line through its centre, and a table that was not symmetric there (3 %
    relative L2) drew the line as a step in their kd and ks."""
    diag = m.diagonal().copy()
    seen = diag > 0
    floor = float(diag[seen].mean()) if seen.any() else 1.0
    lam = ridge * (diag + floor)
    a = m + sparse.diags(lam)
    if smooth > 0:
        a = a + smooth * floor * azimuthal_differences(*shape)
    b = v + lam * prior
    if half_turn:
        fold = half_turn_fold(*shape)
        table = fold @ spsolve(sparse.csc_matrix(fold.T @ a @ fold), fold.T @ b)
    else:
        table = spsolve(sparse.csc_matrix(a), b)
    return np.clip(np.where(np.isfinite(table), table, prior), 0.0, None)   # a non-finite cell keeps the prior


def owned_kd(kd: np.ndarray, owner: np.ndarray, representatives: np.ndarray) -> np.ndarray:
    """(R, 3): each representative's kd as the median over the points it owns (``owner`` (P,): each point's
    representative of largest eq. 18 weight; ``kd`` (P, 3)); the representative's own point's
    (``representatives`` (R,) point numbers) where it owns none. What groups representatives into materials:
    one point's kd is one point's separation, and the ggx-tiles capture's representative 9 had kd 0.117 (its
    4681 points' median 0.150) and ks 0, so its points stayed a material of their own (issue 29)."""
    kd = np.asarray(kd, float)
    out = kd[np.asarray(representatives, np.intp)]
    owner = np.asarray(owner, np.intp)
    for k in np.unique(owner):
        out[k] = np.median(kd[owner == k], axis=0)
    return out
