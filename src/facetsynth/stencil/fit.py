"""Direct (non-iterative) fit of the stencil model of paper 000 to a BRDF on the UTIA grid.

Steps (paper 000 sec. 3.1 letters in brackets):

1. [A] Axis detection and mode count.  The luminance Y on the high-elevation
   slices (theta_i, theta_v in {60, 75} deg, which include the paper's
   theta_i = 75 / theta_v = 60 cross-section, here for all 48 phi_i) is split
   into its rotation average Y_iso(theta_i, theta_v, phi_v - phi_i) -- exact on
   the UTIA grid -- and the anisotropic residual R = Y - Y_iso.  An isotropic
   BRDF has R = 0.  Each candidate axis phi_a (1 deg steps on [0, 180)) gives a
   ridge kernel K = F(phi_a)^p (eq. 2) with its own rotation average removed,
   so K is orthogonal to every isotropic function.  Greedy matching pursuit:
   take the phi_a with the largest normalised correlation rho = <R, K>/(|K| |Y - mean Y|),
   refine it by a parabola through the three neighbouring candidates, subtract
   the projection, repeat.  **Mode-count criterion:** a mode is accepted while
   rho >= ``RHO_MIN`` (0.10), at most ``MAX_MODES`` (4), candidates within
   ``SEPARATION_DEG`` (20 deg) of an accepted axis are skipped.  Marginal
   candidates (``RHO_CAND`` 0.05 <= rho < 0.10), strongest first, are kept
   only if the whole model refitted with them has a lower BIC,
   2 n log(mean CIEDE2000 error) + 11 log n per mode (a Laplace likelihood of the
   per-sample error Delta E averages; n = 20736 samples, the grid's every
   2nd azimuth of both directions): model selection from the data's fit residual.
2. [B] Width w of each mode from the data: the residual R binned over F of
   the mode (other modes' ridges and the specular neighbourhood excluded);
   w = the F below which the binned ridge excess drops under 10 % of its
   peak (clamped to [0.3, 0.97]).  Support masks as in sec. 3.1 C with
   d_w = 0.15 w.
3. [B, C] Elevation scaling a, b (eq. 3) from one ridge sample per
   (theta_i, theta_v) pair (the maximum of Y on F > 0.97), and shape
   kd, ks, alpha (eq. 4): for each alpha on a log grid, a, b are the linear
   least-squares fit of the normalised ridge intensities ((I - kd0)/max)^(1/alpha)
   and kd, ks the weighted linear least squares of eq. 4 on the support;
   the alpha with the least squared error wins (variable projection on a grid,
   no iterative optimiser).  a, b are normalised so the ridge scale peaks at 1.
4. [D] Colour m_j: linear least squares of each channel on L_j (eq. 5).
5. [E] Background (eq. 7): one level per elevation pair -- the darkest
   sample (the paper's orange dots) with modes, the median of the
   non-specular samples without -- projected on m_bg (the darkest samples'
   mean colour with modes, the non-specular median colour without) and
   fitted by eq. 3's form r (a_r + b_r / cp), a_r + b_r = 1.
6. [F] Specular (eq. 10) with two lobes k H_z^alpha (a + (b + f (1 - k.h)^5) / cp),
   divided by k.h or not, and with modes shaped by the dominant mode's stencil
   F_0^alpha_0 or not (the forms are fitted in turn, each kept if it lowers the
   CIELAB error), fitted to the ratio data / model-without-specular
   on the grid's every 2nd azimuth: variable projection on an alpha grid
   (1 .. 65536), A, B, C >= 0 by weighted linear least squares per alpha
   (cube-root residual), one lobe, then the other given it, alternating
   twice; each lobe's highlight colour by linear least squares (eq. 5's
   colour fit applied to the highlight); then beta_j (eq. 8) by closed-form
   least squares (B_S is linear in each beta), clipped to [0, 1].
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import grid
from .model import (COS_FLOOR, NO_LOBE, Mode, StencilModel, apply_shares, elevation_scale, half_vector,
                    highlight_shares, merge_modes, mode_colour, mode_luminance, specular_scale, stencil, support_mask)

__all__ = ["RHO_MIN", "RHO_CAND", "MODE_PARAMS", "MAX_MODES", "SEPARATION_DEG", "axis_error_deg", "detect_axes", "fit",
           "fit_file"]

RHO_MIN = 0.10
# candidates with RHO_CAND <= rho < RHO_MIN are kept only if they lower the fit's BIC
RHO_CAND = 0.05
# parameters one mode adds (phi_a, w, a, b, kd, ks, alpha, m_rgb, beta) -- the BIC penalty per mode
MODE_PARAMS = 11
MAX_MODES = 4
SEPARATION_DEG = 20.0
KERNEL_POWER = 20.0
DW_RATIO = 0.15
SPEC_EXCLUDE = np.cos(np.deg2rad(25.0))
_CAND = np.deg2rad(np.arange(0.0, 180.0, 1.0))
_ALPHAS = np.geomspace(0.25, 256.0, 22)
_TOP = (4, 5)  # theta indices of 60 and 75 deg
_SPEC_ALPHAS = 2.0 ** np.arange(17)  # 1 .. 65536; H_z^alpha by repeated squaring
# the specular fit uses every SPEC_STRIDE-th azimuth of both directions (speed; mirror pairs kept)
SPEC_STRIDE = 2
_SUBSAMPLE = np.zeros(grid.SHAPE[1:], bool)
_SUBSAMPLE[:, ::SPEC_STRIDE, :, ::SPEC_STRIDE] = True


@lru_cache(maxsize=1)
def _geometry():
    wi, wo = grid.utia_directions()
    h = half_vector(wi, wo)
    cp = np.maximum(wi[..., 2], COS_FLOOR) * np.maximum(wo[..., 2], COS_FLOOR)
    # rotation index: Z[ti, pi, tv, d] = X[ti, pi, tv, (pi + d) % 48]
    pv = (np.arange(48)[:, None] + np.arange(48)[None, :]) % 48
    top = np.ix_(_TOP, range(48), _TOP, range(48))
    hz = h[top][..., :].reshape(-1, 3)  # (9216, 3) in natural layout
    hz = h[np.ix_(_TOP, range(48), _TOP)]  # (2, 48, 2, 48, 3)
    hrot = hz[:, np.arange(48)[:, None], :, pv]  # (48, 48, 2, 2, 3) fancy-index layout
    hrot = np.moveaxis(hrot, (2, 3), (0, 2))    # (2, 48, 2, 48, 3) as [ti, pi, tv, d]
    U = np.stack([np.sin(_CAND), np.cos(_CAND), np.zeros_like(_CAND)], -1)
    K = (1.0 - np.abs(np.einsum("...k,ck->c...", hrot, U))) ** KERNEL_POWER  # (C, 2, 48, 2, 48)
    K = K - K.mean(axis=2, keepdims=True)  # remove the rotation average (mean over phi_i at fixed d)
    K = K.reshape(len(_CAND), -1)
    Kn = np.linalg.norm(K, axis=1)
    kh = np.clip(np.sum(wi * h, -1), COS_FLOOR, 1.0)  # wi . H, floored as in model.specular_lobe
    return dict(wi=wi, wo=wo, h=h, hz=h[..., 2], cp=cp, kh=kh, schlick=(1.0 - kh) ** 5, pv=pv, K=K, Kn=Kn)


def _rotate(X, pv):
    """X (..., 6|2, 48, 6|2, 48) natural -> Z[ti, pi, tv, d] = X[ti, pi, tv, (pi + d) % 48]."""
    Z = X[:, np.arange(48)[:, None], :, pv]      # (48, 48, nti, ntv)
    return np.moveaxis(Z, (2, 3), (0, 2))


def _unrotate(Z, pv):
    X = np.empty_like(Z)
    X[:, np.arange(48)[:, None], :, pv] = np.moveaxis(Z, (0, 2), (2, 3))
    return X


def anisotropic_residual(Y):
    """R = Y - rotation average (exact on the UTIA grid), natural layout."""
    g = _geometry()
    Z = _rotate(Y, g["pv"])
    return _unrotate(Z - Z.mean(axis=1, keepdims=True), g["pv"])


def axis_error_deg(found, truth):
    """Largest angle (deg) between matched axes phi_a (both lists in deg, sorted), modulo 180 deg."""
    return max((abs((f - t + 90.0) % 180.0 - 90.0) for f, t in zip(sorted(found), sorted(truth))), default=0.0)


def detect_axes(Y, rho_min=RHO_MIN):
    """Anisotropy axes phi_a (radians, [0, pi)) and correlations rho >= rho_min, strongest first (step 1)."""
    g = _geometry()
    Yt = np.cbrt(np.maximum(Y[np.ix_(_TOP, range(48), _TOP, range(48))], 0.0))
    Z = _rotate(Yt, g["pv"])
    R = (Z - Z.mean(axis=1, keepdims=True)).reshape(-1)
    norm = np.linalg.norm(Z - Z.mean())
    if not np.isfinite(norm) or norm <= 1e-12 * max(1.0, np.abs(Z).max()):
        return np.zeros(0), np.zeros(0)
    K, Kn = g["K"], g["Kn"]
    axes, rhos = [], []
    blocked = np.zeros(len(_CAND), bool)
    for _ in range(MAX_MODES):  # loop over modes, not samples
        rho = (K @ R) / (Kn * norm)
        rho_b = np.where(blocked, -np.inf, rho)
        j = int(np.argmax(rho_b))
        if rho_b[j] < rho_min:
            break
        y0, y1, y2 = rho[(j - 1) % len(_CAND)], rho[j], rho[(j + 1) % len(_CAND)]
        den = y0 - 2 * y1 + y2
        off = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        phi = (_CAND[j] + np.clip(off, -0.5, 0.5) * (_CAND[1] - _CAND[0])) % np.pi
        axes.append(phi)
        rhos.append(float(rho_b[j]))
        # project out the whole neighbourhood of the ridge (kernels within +-10 deg),
        # so a ridge wider or narrower than the kernel leaves no side lobes
        nb = K[(j + np.arange(-10, 11)) % len(_CAND)]
        coef, *_ = np.linalg.lstsq(nb.T, R, rcond=None)
        R = R - nb.T @ coef
        d = np.abs((np.rad2deg(_CAND - phi) + 90.0) % 180.0 - 90.0)
        blocked |= d < SEPARATION_DEG
    return np.array(axes), np.array(rhos)


def _estimate_width(F, R, valid):
    """w: F below which the binned ridge excess falls under 10 % of its peak (step 2)."""
    edges = np.linspace(0.0, 1.0, 51)
    b = np.clip(np.digitize(F, edges) - 1, 0, 49)
    wts = valid.astype(float)
    b, wts, R = b.ravel(), wts.ravel(), np.asarray(R).ravel()
    cnt = np.bincount(b, wts, 50)
    s = np.bincount(b, wts * R, 50)
    prof = np.where(cnt > 0, s / np.maximum(cnt, 1), np.nan)
    ok = np.isfinite(prof)
    if ok.sum() < 5:
        return 0.7
    centres = 0.5 * (edges[1:] + edges[:-1])
    base = np.nanmedian(np.where(centres < 0.6, prof, np.nan)) if np.any(ok & (centres < 0.6)) else np.nanmin(prof)
    peak = prof[ok][-1]
    if not peak > base:
        return 0.7
    above = np.where(ok, prof - base >= 0.1 * (peak - base), True)
    # last index (from the top) where the profile falls below the 10 % level
    below = np.nonzero(~above)[0]
    w = centres[below[-1]] + 0.01 if below.size else 0.3
    return float(np.clip(w, 0.3, 0.97))


def _per_pair(values, mask, reduce):
    """Reduce values over (phi_i, phi_v) for each (theta_i, theta_v) pair where mask; NaN if empty."""
    v = np.where(mask, values, np.nan).transpose(0, 2, 1, 3).reshape(36, -1)
    out = np.full(36, np.nan)
    has = np.isfinite(v).any(axis=1)
    if has.any():
        out[has] = reduce(v[has], axis=1)
    return out


_CP_PAIR = None


def _pair_cp():
    c = np.maximum(np.cos(grid.THETA), COS_FLOOR)
    return (c[:, None] * c[None, :]).reshape(36)


def _fit_ab(target, cp):
    """Linear least squares of a + b / cp to target (NaNs ignored); (a, b): the 2 x 2 normal equations,
    the mean alone when 1 / cp does not vary."""
    ok = np.isfinite(target)
    if ok.sum() < 2:
        return 1.0, 0.0
    x, y = 1.0 / cp[ok], target[ok]
    xc = x - x.mean()
    sxx = xc @ xc
    if sxx <= 1e-12 * (x @ x):
        return float(y.mean()), 0.0
    b = (xc @ y) / sxx
    return float(y.mean() - b * x.mean()), float(b)


def _fit_mode(phi_a, Y, R, F, W, others, g):
    """Steps 2-4 for one mode: returns a Mode (m filled later) and its support weights."""
    hz, cp = g["hz"], g["cp"]
    valid = (hz < SPEC_EXCLUDE) & ~others
    w = _estimate_width(F, R, valid)
    M = support_mask(F, w, DW_RATIO)
    wts = M * valid
    ridge = (F > 0.97) & valid
    I = _per_pair(Y, ridge, np.nanmax)
    rim = (M > 0) & (F < w) & valid
    kd0 = np.percentile(Y[rim], 5) if rim.any() else 0.0
    In = I - kd0
    pcp = _pair_cp()
    if not np.any(np.isfinite(In)) or np.nanmax(In) <= 0:
        return Mode(float(phi_a), w, 1.0, 0.0, float(kd0), 0.0, 1.0, (1.0, 1.0, 1.0)), M
    In = np.clip(In / np.nanmax(In), 1e-6, None)
    sel = np.flatnonzero(wts > 0.05)
    if sel.size > 20000:
        sel = sel[:: sel.size // 20000 + 1]
    ys, ws, Fs, cps = Y.reshape(-1)[sel], wts.reshape(-1)[sel], F.reshape(-1)[sel], cp.reshape(-1)[sel]
    best = None
    for alpha in _ALPHAS:  # 22 closed-form candidates (variable projection), not samples
        a, b = _fit_ab(In ** (1.0 / alpha), pcp)
        smax = max(a + b / pcp.min(), a + b, 1e-12)
        a, b = a / smax, b / smax
        Ea = np.power(np.maximum(Fs * elevation_scale(a, b, cps), 0.0), alpha)
        # weighted linear least squares of kd + ks Ea (2x2 normal equations)
        s0, s1, s2 = ws.sum(), ws @ Ea, ws @ (Ea * Ea)
        r0, r1 = ws @ ys, ws @ (Ea * ys)
        det = s0 * s2 - s1 * s1
        kd, ks = ((s2 * r0 - s1 * r1) / det, (s0 * r1 - s1 * r0) / det) if det > 1e-12 * s0 * s2 else (r0 / s0, 0.0)
        if ks < 0:
            kd, ks = float(np.average(ys, weights=ws)), 0.0
        err = np.sum(ws * (kd + ks * Ea - ys) ** 2)
        if best is None or err < best[0]:
            best = (err, a, b, kd, ks, alpha)
    _, a, b, kd, ks, alpha = best
    return Mode(float(phi_a), w, float(a), float(b), float(kd), float(ks), float(alpha), (1.0, 1.0, 1.0)), M


def _nnls_normal(G, r):
    """argmin over c >= 0 of c.G.c - 2 c.r for a batch of small problems, ``G (m, n, n)``, ``r (m, n)``,
    n <= 3: the normal equations on every set of columns, the feasible one with the least objective
    (the full set's solution when it is feasible, since it is the unconstrained optimum; the other sets
    are tried only for the problems where it is not)."""
    m, n = r.shape
    best, best_obj = np.zeros((m, n)), np.zeros(m)
    floor = 1e-12 * np.diagonal(G, axis1=1, axis2=2).max(axis=1)    # a column this weak stays at 0
    todo = np.arange(m)
    for cols in _SUBSETS[n]:
        if not todo.size:
            break
        idx = np.array(cols)
        Gt, rt = G[todo], r[todo]
        sub = Gt[:, idx[:, None], idx[None, :]]
        diag = np.diagonal(sub, axis1=1, axis2=2)
        ok = (np.abs(np.linalg.det(sub)) > 1e-12 * np.prod(diag, axis=1)) & np.all(diag > floor[todo, None], axis=1)
        sub = np.where(ok[:, None, None], sub, np.eye(len(idx)))
        c = np.zeros((len(todo), n))
        c[:, idx] = np.linalg.solve(sub, rt[:, idx, None])[..., 0]
        obj = np.einsum("mi,mij,mj->m", c, Gt, c) - 2 * np.einsum("mi,mi->m", c, rt)
        feasible = ok & (c[:, idx].min(axis=1) >= 0)
        better = feasible & (obj < best_obj[todo])
        best[todo[better]], best_obj[todo[better]] = c[better], obj[better]
        if len(cols) == n:                              # solved without constraints: done
            todo = todo[~feasible]
    return best


# column sets, the full one first
_SUBSETS = {n: [tuple(i for i in range(n) if m >> i & 1) for m in range(2 ** n - 1, 0, -1)] for n in (1, 2, 3)}


class _LobeData:
    """What every lobe fit of one eq. 10 fit shares: the ratio t = data / model, its cube root, the weights
    t^(-4/3), the elevation columns (1, 1 / cp, (1 - k.h)^5 / cp) times the lobes' common factor,
    H_z^(2^j) for the 17 alphas (repeated squaring) and the per-sample outer products of the columns."""

    def __init__(self, t, hz, cols):
        self.t, self.ct, self.w, self.cols = t, np.cbrt(t), t ** (-4.0 / 3.0), cols
        self.H = np.empty((len(_SPEC_ALPHAS), len(t)))
        self.H[0] = hz
        for j in range(1, len(self.H)):
            self.H[j] = self.H[j - 1] * self.H[j - 1]
        k = cols.shape[1]
        self.outer = (self.w[:, None, None] * cols[:, :, None] * cols[:, None, :]).reshape(len(t), k * k)

    def lobe(self, p):
        """A fitted lobe (err, alpha, A, B, C) at the samples."""
        return self.H[int(np.log2(p[1]))] * (self.cols @ p[2:])


def _fit_lobe(d, base, near=None):
    """One lobe H_z^alpha (A + (B + C (1 - k.h)^5) / cp) [times the common factor] of eq. 10 added to
    ``base`` to fit the ratio t = data / model of :class:`_LobeData` ``d``.

    Variable projection on the alpha grid: per alpha, A, B, C >= 0 by weighted linear least squares (the
    samples are those above the model, where eq. 10's max is the lobe; weights t^(-4/3): the cube-root
    residual linearised, cf. CIELAB L*), scored by the cube-root error of max(1, base + lobe); all 17
    alphas at once, or the 5 nearest to the alpha ``near`` (a refit).  Returns (err, alpha, A, B, C).
    """
    alphas, H, outer = _SPEC_ALPHAS, d.H, d.outer
    if near is not None:
        j0 = int(np.clip(np.searchsorted(_SPEC_ALPHAS, near), 2, len(_SPEC_ALPHAS) - 3))
        alphas, H = alphas[j0 - 2:j0 + 3], H[j0 - 2:j0 + 3]
    # normal equations of all alphas at once:
    # G[a] = sum_n H[a, n]^2 w_n c_n c_n^T,  r[a] = sum_n H[a, n] w_n (t - base)_n c_n
    k = d.cols.shape[1]
    G = ((H * H) @ outer).reshape(-1, k, k)
    C = _nnls_normal(G, H @ (((d.t - base) * d.w)[:, None] * d.cols))
    pred = base + H * (C @ d.cols.T)                    # (alphas, samples)
    err = np.sum((np.cbrt(np.maximum(pred, 1.0)) - d.ct) ** 2, axis=1)
    j = int(np.argmin(err))
    return (float(err[j]), float(alphas[j]), *(float(x) for x in C[j]))


def _lobe_params(alpha, A, B, C):
    """(k, alpha, a, b, f) with a, b, f scaled so a + (b + f) / cp <= 1 over the grid (k carries the scale)."""
    smax = A + (B + C) / COS_FLOOR ** 2
    return (float(smax), float(alpha), float(A / smax), float(B / smax), float(C / smax)) if smax > 0 else NO_LOBE


def _fit_specular(rgb, B, g, scale):
    """Eq. 10 from the data: two lobes (k, alpha_s, a_s, b_s, f_s) and their highlight colours m_s, m_s2.

    ``rgb``, ``B`` ``(n, 3)``, the geometry ``g`` (hz, cp, kh, schlick) and the lobes' common factor
    ``scale`` (:func:`~facetsynth.stencil.model.specular_scale`) are on the subsampled grid.
    The ratio t = Y / Y(B) where it exceeds 1.02 is fitted by one lobe, then a second lobe
    on the rest, then each again given the other (each by :func:`_fit_lobe`).
    m_s, m_s2: per-channel non-negative linear least squares of data - B on the
    two lobes' shares of the boost (S - 1) Y(B) (:func:`highlight_shares`), where
    S > 1: eq. 5's colour fit applied to the highlight.  Also returns those shares per unit luminance.
    """
    Y, YB = rgb @ grid.LUMA, B @ grid.LUMA
    sel = (Y > 1.02 * YB) & (YB > 1e-12 * max(Y.max(), 1e-300))
    if sel.sum() < 3:
        return NO_LOBE, NO_LOBE, None, None, np.zeros(Y.shape + (2,))
    icp = 1.0 / g["cp"][sel]
    cols = np.stack([np.ones_like(icp), icp, icp * g["schlick"][sel]], 1)
    d = _LobeData(Y[sel] / YB[sel], np.clip(g["hz"][sel], 0.0, 1.0),
                  cols * np.broadcast_to(scale, sel.shape)[sel, None])
    p1 = _fit_lobe(d, 0.0)
    p2 = _fit_lobe(d, d.lobe(p1))
    for _ in range(2):  # two alternations (block coordinate descent over the lobes), alpha near the last one
        p1 = _fit_lobe(d, d.lobe(p2), near=p1[1])
        p2 = _fit_lobe(d, d.lobe(p1), near=p2[1])
    s1, s2 = _lobe_params(*p1[1:]), _lobe_params(*p2[1:])
    shares = highlight_shares(g["hz"], g["cp"], s1, s2, g["kh"], scale)
    X = YB[:, None] * shares                                   # the boost per lobe, (n, 2)
    on = X.sum(-1) > 1e-3 * YB
    if not on.any():
        return s1, s2, None, None, shares
    wt = 1.0 / np.maximum(Y[on], 1e-12 * max(Y.max(), 1e-300)) ** (4.0 / 3.0)
    Xw = X[on] * wt[:, None]
    G, rhs = X[on].T @ Xw, Xw.T @ (rgb[on] - B[on])                # (2, 2), (2, 3)
    cols = _nnls_normal(np.broadcast_to(G, (3, 2, 2)), rhs.T)       # (3 channels, 2 lobes)
    return s1, s2, tuple(float(x) for x in cols[:, 0]), tuple(float(x) for x in cols[:, 1]), shares


def _fit_background(level, m_bg):
    """r, a_r, b_r of P_n = r m_bg (a_r + b_r / cp) from one background level (RGB) per elevation pair.

    Per pair the level is projected on m_bg (eq. 7's linear scaling r), then
    the eq. 3 form a + b / cp is fitted by linear least squares and split as
    r = a + b (the value at normal incidence), a_r + b_r = 1.
    """
    ratio = level @ m_bg / max(m_bg @ m_bg, 1e-300)
    A, B = _fit_ab(ratio, _pair_cp())
    r = A + B
    if not (np.isfinite(r) and r > 0):
        return float(max(np.nanmean(ratio), 0.0)) if np.any(np.isfinite(ratio)) else 0.0, 1.0, 0.0
    return float(r), float(A / r), float(B / r)


def fit(brdf):
    """Fit the stencil model (paper 000, sec. 3) to a BRDF ``(3, 6, 48, 6, 48)`` -> StencilModel."""
    brdf = np.nan_to_num(np.maximum(np.asarray(brdf, float), 0.0))
    if brdf.shape != grid.SHAPE:
        raise ValueError(f"expected a BRDF of shape {grid.SHAPE}, got {brdf.shape}")
    g = _geometry()
    rgb = np.moveaxis(brdf, 0, -1)
    Y = rgb @ grid.LUMA
    axes, rhos = detect_axes(Y, rho_min=RHO_CAND)
    sure = int(np.sum(rhos >= RHO_MIN))
    lab_error = _LabError(rgb)
    model, out = _fit_axes(rgb, Y, axes[:sure], rhos[:sure], g, lab_error)
    if sure < len(axes):
        # marginal candidates (RHO_CAND <= rho < RHO_MIN), strongest first: keep one only if
        # the whole model refitted with it has a lower BIC (CIEDE2000 residual, MODE_PARAMS per mode)
        n = int(_SUBSAMPLE.sum())
        # Laplace likelihood of the per-sample CIEDE2000 error (what Delta E averages): -2 log L = 2 n log(mean e)

        def bic(o):
            return 2 * n * np.log(max(lab_error(o, de2000=True), 1e-300))
        cur = bic(out)
        tried = [dict(phi_a=float(np.rad2deg(axes[j])), rho=float(rhos[j])) for j in range(sure, len(axes))]
        for j in range(sure, len(axes)):
            m2, o2 = _fit_axes(rgb, Y, axes[:j + 1], rhos[:j + 1], g, lab_error,
                               (model.jacobian, model.stencil_highlight and bool(model.modes)))
            fit2 = bic(o2)
            tried[j - sure]["delta_bic"] = float(fit2 + MODE_PARAMS * np.log(n) - cur)
            if tried[j - sure]["delta_bic"] >= 0:
                break
            model, out, cur = m2, o2, fit2
        model.meta["marginal"] = tried
    return model


class _LabError:
    """Mean colour error of the model's RGB on the subsampled grid ``(n, 3)`` against the data there, in
    CIELAB exposure-normalised as in the scores: the Euclidean distance (CIE76, cheap: it compares the
    eq. 10 forms), or with ``de2000`` the CIEDE2000 difference that Delta E averages (the BIC's residual)."""

    def __init__(self, rgb):
        from .scores import ciede2000, exposure, rgb_to_lab
        self._lab, self._de, self._ex = rgb_to_lab, ciede2000, exposure(rgb)
        self._ref = rgb_to_lab(rgb[_SUBSAMPLE] / self._ex)

    def __call__(self, out, de2000=False):
        lab = self._lab(out / self._ex)
        return float(np.mean(self._de(self._ref, lab) if de2000 else np.linalg.norm(lab - self._ref, axis=-1)))


def _fit_axes(rgb, Y, axes, rhos, g, lab_error, form=None):
    """Steps 2-8 for given axes -> (StencilModel, its RGB on the subsampled grid ``(n, 3)``).

    Step 8, the form of eq. 10's lobes, ``(jacobian, stencil_highlight)``: with and without 1 / k.h, the
    one with the lower CIELAB error; then, with modes, the highlight shaped by the dominant mode's stencil,
    kept if it lowers the error further.  ``form`` given (a marginal mode's refit): that form only."""
    R = anisotropic_residual(Y) if len(axes) else None
    Fs = [stencil(g["h"], p) for p in axes]
    ridges = [F > 0.97 for F in Fs]
    modes, Ms = [], []
    for j, phi in enumerate(axes):
        others = np.zeros(Y.shape, bool)
        for k, r in enumerate(ridges):
            if k != j:
                others |= r
        md, M = _fit_mode(phi, Y, R, Fs[j], None, others, g)
        modes.append(md)
        Ms.append(M)
    # colours (eq. 5): per-mode linear fit of RGB on L over the exclusive support
    T = []
    for j, md in enumerate(modes):
        L = np.maximum(mode_luminance(Fs[j], elevation_scale(md.a, md.b, g["cp"]), md.kd, md.ks, md.alpha), 0)
        excl = Ms[j] * (g["hz"] < SPEC_EXCLUDE)
        for k in range(len(modes)):
            if k != j:
                excl = excl * (1 - Ms[k])
        if excl.sum() < 1e-9:
            excl = Ms[j]
        den = np.sum(excl * L * L)
        m = ((excl * L).reshape(-1) @ rgb.reshape(-1, 3)) / den if den > 0 else np.ones(3)
        m = np.maximum(m, 0.0)
        modes[j] = Mode(md.phi_a, md.w, md.a, md.b, md.kd, md.ks, md.alpha, tuple(float(x) for x in m))
        T.append(mode_colour(L, m))
    # order: dominant (brightest ridge) on top
    order = np.argsort([-(md.kd + md.ks) * grid.LUMA @ np.array(md.m) for md in modes]) if modes else []
    modes = [modes[i] for i in order]
    Fs = [Fs[i] for i in order]
    Ms = [Ms[i] for i in order]
    T = [T[i] for i in order]
    rhos = [float(rhos[i]) for i in order]
    # background (eq. 7): one level per elevation pair -- the darkest sample with modes (paper;
    # m_bg is their mean colour, not the bottom mode's), the median of the non-specular
    # samples without -- scaled on m_bg with eq. 3's elevation form
    if modes:
        idx = np.argmin(Y.transpose(0, 2, 1, 3).reshape(36, -1), axis=1)
        level = rgb.transpose(0, 2, 1, 3, 4).reshape(36, -1, 3)[np.arange(36), idx]
        m_bg = level.mean(0)
    else:
        diffuse = g["hz"] < np.cos(np.deg2rad(20.0))
        m_bg = np.median(rgb[diffuse], axis=0)
        level = np.stack([_per_pair(rgb[..., c], diffuse, np.nanmedian) for c in range(3)], -1)
    r, a_r, b_r = _fit_background(level, m_bg)
    bg = (r * np.maximum(elevation_scale(a_r, b_r, g["cp"]), 0.0))[..., None] * m_bg
    # step 6 on the subsampled grid (every SPEC_STRIDE-th azimuth of both directions)
    sub = _SUBSAMPLE
    gs = {key: g[key][sub] for key in ("hz", "cp", "kh", "schlick")}
    if modes:
        gs["top"] = (Fs[0][sub], modes[0].alpha)
    Ts, Mss, bgs = [x[sub] for x in T], [x[sub] for x in Ms], bg[sub]
    Bs = merge_modes(Ts, Mss, [0.0] * max(len(modes) - 1, 0), bgs) * np.ones(bgs.shape)
    fits = {}

    def run(f):
        params, out = _finish(rgb[sub], Ts, Mss, bgs, Bs, gs, f)
        fits[f] = (params, out, lab_error(out))
        return fits[f]
    if form is None:
        form = min([(False, False), (True, False)], key=lambda f: run(f)[2])
        if modes and run((form[0], True))[2] < fits[form][2]:
            form = (form[0], True)
    else:
        run(form)
    (s1, s2, m_s, m_s2, beta), out, _ = fits[form]
    model = StencilModel(
        modes=tuple(modes), beta=tuple(beta), r=r, m_bg=tuple(float(x) for x in m_bg),
        k=s1[0], alpha_s=s1[1], a_s=s1[2], b_s=s1[3], f_s=s1[4], dw_ratio=DW_RATIO,
        k2=s2[0], alpha_s2=s2[1], a_s2=s2[2], b_s2=s2[3], f_s2=s2[4], m_s=m_s, m_s2=m_s2, a_r=a_r, b_r=b_r,
        jacobian=form[0], stencil_highlight=form[1],
        meta={"rho": rhos, "eq10_lab_error": {_FORMS[f]: v[2] for f, v in fits.items()}},
    )
    return model, out


_FORMS = {(False, False): "eq. 10", (True, False): "1 / k.h", (False, True): "stencil",
          (True, True): "1 / k.h, stencil"}


def _finish(rgb, T, Ms, bg, B, g, form):
    """Steps 6-7 on the merged modes ``B`` (beta = 0), all ``(n, ...)`` on the subsampled grid, for the eq. 10
    form ``(jacobian, stencil_highlight)``: the lobes and colours, then beta (eq. 8) by closed-form least
    squares, top interface first (B_S is linear in B) -> (parameters, the model's RGB there)."""
    scale = specular_scale(g["kh"], form[0], g["top"] if form[1] else None)
    s1, s2, m_s, m_s2, shares = _fit_specular(rgb, B, g, scale)
    lin = lambda X: apply_shares(X, shares, m_s, m_s2)  # noqa: E731  (the lobes do not depend on B)
    beta = [0.0] * max(len(T) - 1, 0)
    for j in range(len(beta)):
        b1 = list(beta)
        b1[j] = 1.0
        D = lin(merge_modes(T, Ms, b1, bg) - B)
        den = np.sum(D * D)
        if den > 0:
            beta[j] = float(np.clip(np.sum(D * (rgb - lin(B))) / den, 0.0, 1.0))
            B = merge_modes(T, Ms, beta, bg) * np.ones(B.shape)
    return (s1, s2, m_s, m_s2, beta), np.maximum(lin(B), 0.0)


def fit_file(path):
    """Read a BRDF file (UTIA .bin/.exr, RGL .bsdf, MERL .binary), fit it, score it.

    Returns ``(model, scores)``; scores has delta_e, rmse, psnr_db, ssim and
    fit_seconds (the fit alone; reading/resampling the file is read_seconds).
    """
    from .readers import read_brdf
    from .model import evaluate_utia
    from .scores import score_brdf
    t0 = time.perf_counter()
    brdf = read_brdf(path)
    t1 = time.perf_counter()
    model = fit(brdf)
    t2 = time.perf_counter()
    scores = score_brdf(brdf, evaluate_utia(model))
    scores["fit_seconds"] = t2 - t1
    scores["read_seconds"] = t1 - t0
    scores["source"] = str(Path(path))
    return model, scores
