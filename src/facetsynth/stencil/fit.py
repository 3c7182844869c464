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
   ``SEPARATION_DEG`` (10 deg) of an accepted axis are skipped.
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
5. [E] Background r (eq. 7): linear scale between the darkest sample of
   each elevation pair and m of the bottom mode.  beta_j (eq. 8) by
   closed-form least squares (B is linear in each beta), clipped to [0, 1].
6. [F] Specular (eq. 10): a_s, b_s (= a_0, b_0 with modes), and k, alpha_s
   from a log-linear least-squares fit of the ratio data / model-without-
   specular where it exceeds 1.
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import grid
from .model import (COS_FLOOR, Mode, StencilModel, elevation_scale, half_vector, merge_modes,
                    mode_colour, mode_luminance, specular_factor, stencil, support_mask)

__all__ = ["RHO_MIN", "MAX_MODES", "SEPARATION_DEG", "axis_error_deg", "detect_axes", "fit", "fit_file"]

RHO_MIN = 0.10
MAX_MODES = 4
SEPARATION_DEG = 20.0
KERNEL_POWER = 20.0
DW_RATIO = 0.15
SPEC_EXCLUDE = np.cos(np.deg2rad(25.0))
_CAND = np.deg2rad(np.arange(0.0, 180.0, 1.0))
_ALPHAS = np.geomspace(0.25, 256.0, 22)
_TOP = (4, 5)  # theta indices of 60 and 75 deg


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
    return dict(wi=wi, wo=wo, h=h, hz=h[..., 2], cp=cp, pv=pv, K=K, Kn=Kn)


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


def detect_axes(Y):
    """Anisotropy axes phi_a (radians, [0, pi)) and correlations rho, strongest first (step 1)."""
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
        if rho_b[j] < RHO_MIN:
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
    """Linear least squares of a + b / cp to target (NaNs ignored); (a, b)."""
    ok = np.isfinite(target)
    if ok.sum() < 2:
        return 1.0, 0.0
    A = np.stack([np.ones(ok.sum()), 1.0 / cp[ok]], 1)
    (a, b), *_ = np.linalg.lstsq(A, target[ok], rcond=None)
    return float(a), float(b)


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
        A = np.stack([np.ones_like(Ea), Ea], 1) * np.sqrt(ws)[:, None]
        coef, *_ = np.linalg.lstsq(A, ys * np.sqrt(ws), rcond=None)
        kd, ks = coef
        if ks < 0:
            kd, ks = float(np.average(ys, weights=ws)), 0.0
        err = np.sum(ws * (kd + ks * Ea - ys) ** 2)
        if best is None or err < best[0]:
            best = (err, a, b, kd, ks, alpha)
    _, a, b, kd, ks, alpha = best
    return Mode(float(phi_a), w, float(a), float(b), float(kd), float(ks), float(alpha), (1.0, 1.0, 1.0)), M


def _fit_specular(Ydata, Bl, hz, cp, a_s, b_s):
    """k, alpha_s of eq. 10 by log-linear least squares on samples where data / model > 1."""
    s = elevation_scale(a_s, b_s, cp)
    q = Ydata / np.maximum(Bl, 1e-12)
    sel = (q > 1.02) & (s > 1e-6) & (hz > SPEC_EXCLUDE) & (Bl > 1e-9)
    if sel.sum() < 3:
        return 0.0, 1.0
    lq = np.log(q[sel])
    lh = np.log(hz[sel])
    if np.ptp(lh) < 1e-3:
        # every boosted sample sits at the same H_z (e.g. only exact mirror pairs):
        # alpha_s is not identifiable; take a delta-like lobe that spares the neighbours.
        alpha_s = 1000.0
        return float(np.exp(np.average(lq - np.log(s[sel]) - alpha_s * lh))), alpha_s
    A = np.stack([np.ones(sel.sum()), np.log(hz[sel])], 1)
    rhs = lq - np.log(s[sel])
    wt = np.sqrt(lq)
    (lk, alpha_s), *_ = np.linalg.lstsq(A * wt[:, None], rhs * wt, rcond=None)
    alpha_s = float(np.clip(alpha_s, 0.0, 1e4))
    if alpha_s == 0.0:
        lk = float(np.average(rhs, weights=wt))
    return float(np.exp(min(lk, 700.0))), alpha_s


def fit(brdf):
    """Fit the stencil model (paper 000, sec. 3) to a BRDF ``(3, 6, 48, 6, 48)`` -> StencilModel."""
    brdf = np.nan_to_num(np.maximum(np.asarray(brdf, float), 0.0))
    if brdf.shape != grid.SHAPE:
        raise ValueError(f"expected a BRDF of shape {grid.SHAPE}, got {brdf.shape}")
    g = _geometry()
    rgb = np.moveaxis(brdf, 0, -1)
    Y = rgb @ grid.LUMA
    axes, rhos = detect_axes(Y)
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
    Ms = [Ms[i] for i in order]
    T = [T[i] for i in order]
    rhos = [float(rhos[i]) for i in order]
    # background (eq. 7)
    if modes:
        m_bg = np.array(modes[-1].m)
        idx = np.argmin(Y.transpose(0, 2, 1, 3).reshape(36, -1), axis=1)
        dark = rgb.transpose(0, 2, 1, 3, 4).reshape(36, -1, 3)[np.arange(36), idx]
        r = float(max(np.sum(dark @ m_bg) / (36 * max(m_bg @ m_bg, 1e-300)), 0.0))
        a_s, b_s = modes[0].a, modes[0].b
    else:
        diffuse = g["hz"] < np.cos(np.deg2rad(20.0))
        m_bg = np.median(rgb[diffuse], axis=0)
        r = 1.0
        pk = _per_pair(Y, np.ones(Y.shape, bool), np.nanmax)
        a_s, b_s = _fit_ab(pk / max(np.nanmax(pk), 1e-300), _pair_cp())
        smax = max(a_s + b_s / _pair_cp().min(), a_s + b_s, 1e-12)
        a_s, b_s = a_s / smax, b_s / smax
    bg = r * m_bg
    beta = [0.0] * max(len(modes) - 1, 0)
    B = merge_modes(T, Ms, beta, bg) * np.ones(Y.shape + (1,))
    k, alpha_s = _fit_specular(Y, B @ grid.LUMA, g["hz"], g["cp"], a_s, b_s)
    S = specular_factor(g["hz"], g["cp"], k, alpha_s, a_s, b_s)[..., None]
    # beta (eq. 8) by closed-form least squares, top interface first
    for j in range(len(beta)):
        b1 = list(beta)
        b1[j] = 1.0
        D = (merge_modes(T, Ms, b1, bg) - B) * S
        den = np.sum(D * D)
        if den > 0:
            beta[j] = float(np.clip(np.sum(D * (rgb - B * S)) / den, 0.0, 1.0))
            B = merge_modes(T, Ms, beta, bg) * np.ones(Y.shape + (1,))
    return StencilModel(
        modes=tuple(modes), beta=tuple(beta), r=r, m_bg=tuple(float(x) for x in m_bg),
        k=k, alpha_s=alpha_s, a_s=float(a_s), b_s=float(b_s), dw_ratio=DW_RATIO,
        meta={"rho": rhos},
    )


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
