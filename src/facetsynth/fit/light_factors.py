"""Per-light RGB intensity factors of a light dome, from the capture itself (self-calibration).

A light-dome (RTI) capture gives the light directions but not their intensities: the LEDs differ in
brightness and colour by a few per cent to tens of per cent. With a directional light q of RGB irradiance
E_q = f_q E_nominal (f_q (3,) the unknown factor), a point x reflects

    I_q(x) = rho(x, i_q, o) (n(x) . i_q) E_q,

and on its diffuse part rho = kd / pi = a(x). The irradiance-normalised sample under the nominal
intensities, b_q = I_q / E_nominal, is then, per channel c,

    b[p, q, c] = f[q, c] a[p, c] s[p, q],        s[p, q] = n(p) . i_q  (``predicted``),

so the ratios r = b / s = f[q, c] a[p, c] form a rank-1 matrix per channel (points x lights) wherever the
point is diffuse, lit and unshadowed. :func:`estimate` factorises it robustly; highlights (r >> f a) and
cast shadows (r << f a) are sparse one-sided outliers, trimmed as in :mod:`facetsynth.fit.normals`:

1. usable samples: valid, finite, s > ``min_predicted`` (0.2: grazing light amplifies every error in s);
   points with at least ``min_lights`` usable samples, at most ``max_points`` of them, evenly strided
   (deterministic);
2. seed by median polish in the log domain (Tukey; log r = log f + log a is a two-way additive table):
   alternately log a[p] = median_q (log r - log f), log f[q] = median_p (log r - log a), ``polish`` times;
3. trimmed least squares, ``iterations`` times: the relative residual e = r / (f a) - 1 is an inlier if
   -k sigma <= e <= k_high sigma in every channel, sigma = 1.4826 median |e| over the point's current
   inliers (a per-point, per-channel MAD) kept within [``floor``, ``cap``]; a point left with fewer than
   ``min_lights`` inliers keeps its previous set. Then, on the inliers (w = 1),

       a[p, c] = sum_q w b f s / sum_q w (f s)^2,      f[q, c] = sum_p w b a s / sum_p w (a s)^2,

   the least squares of b = f a s in one factor with the other fixed (one alternation per iteration);
4. the scale: f a is invariant under f[:, c] -> k_c f[:, c], a[:, c] -> a[:, c] / k_c, one free constant
   per channel. Fixed here: **the mean over lights of each channel's factor is 1**,

       (1 / F') sum_q f[q, c] = 1   for c = R, G, B   (F' = the lights that are not fallbacks),

   so the average light is the nominal (white) one; the mean luminance factor over lights is then 1 as
   well, and kd = pi a keeps both its scale and its colour. The samples are corrected by b / f
   (:func:`correct`).

Lights with fewer than ``min_points`` inlier points (none of which lit any usable point, or a capture with
fewer than ``min_lights`` lights, where no point constrains the ratio between lights) get the factor 1 and
are flagged (:attr:`Factors.fallback`). Nothing non-finite leaves this module.

:func:`reference_region` is the alternative when the user names a white / grey reference region: per
region point its albedo a[p, c] = median over its usable lights of r, then f[q, c] = median over the
region's usable points of r / a, scale fixed the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAD = 1.4826        # MAD -> standard deviation of a normal distribution


@dataclass(frozen=True)
class FactorSettings:
    """Knobs of :func:`estimate` and :func:`reference_region` (see the module's notes).

    min_predicted:  usable samples have s = n . i above this (0.2, ~78 deg from the normal).
    max_points:     at most this many points take part, evenly strided over the eligible ones (20 000).
    min_lights:     a point needs at least this many usable samples (inliers during the trimming) (4).
    min_points:     a light needs at least this many inlier points, else factor 1 and a fallback (20).
    polish:         median-polish rounds of the seed (2).
    iterations:     trimmed least-squares iterations (4).
    k, k_high:      the inlier band below / above the fit in robust standard deviations (3, 1.5; tighter
                    above: highlights only add light, and a lobe's tail adds a little to many samples).
    floor, cap:     the per-point relative sigma is kept within [floor, cap] (0.01, 0.1).
    """

    min_predicted: float = 0.2
    max_points: int = 20_000
    min_lights: int = 4
    min_points: int = 20
    polish: int = 2
    iterations: int = 4
    k: float = 3.0
    k_high: float = 1.5
    floor: float = 0.01
    cap: float = 0.1


@dataclass(frozen=True)
class Factors:
    """Result of :func:`estimate`: ``rgb`` (F, 3) the per-light factors f_q (mean over the non-fallback
    lights of each channel = 1; fallbacks exactly 1); ``points_used`` (F,) int, the inlier points of each
    light's final fit; ``spread`` (F,) the relative robust dispersion of each light's luminance ratios
    b / (f a s) over its usable points (1.4826 MAD about their median; 0 without points);
    ``fallback`` (F,) bool, True where the light had too few points and its factor is 1."""

    rgb: np.ndarray
    points_used: np.ndarray
    spread: np.ndarray
    fallback: np.ndarray


def correct(samples: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Samples (P, F, 3) under the lights' true intensities: b / f_q (``rgb`` (F, 3), all > 0)."""
    return np.asarray(samples) / np.asarray(rgb)[None]


def estimate(samples: np.ndarray, predicted: np.ndarray, valid: np.ndarray,
             settings: FactorSettings = FactorSettings()) -> Factors:
    """Per-light RGB factors f (F, 3) with samples[p, q, c] ~ f[q, c] a[p, c] predicted[p, q] on the
    diffuse inliers (robust rank-1 factorisation per channel; the module's notes give the steps and the
    scale fixed: the mean over lights of each channel's factor is 1).

    samples (P, F, 3): b = I / E_nominal, irradiance-normalised radiance under the nominal intensities.
    predicted (P, F): the point's diffuse shading s = n . i_q (> 0 where lit).
    valid (P, F) bool: usable samples; non-finite samples or predictions are dropped as well.
    """
    st = settings
    b, s, ok = _checked(samples, predicted, valid, st)
    F = b.shape[1]
    rows = _subsample(ok, st)
    b, s = b[rows], s[rows]
    ok = ok[rows] & np.isfinite(b).all(2)
    b = np.where(ok[..., None], b, 0.0)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
        r = np.where(ok[..., None], b / np.where(ok, s, 1.0)[..., None], 0.0)     # (N, F, 3)
        f, a = _polish(r, ok, st)
        inl = ok
        for _ in range(max(int(st.iterations), 0)):
            inl = _trim(r, f, a, ok, inl, st)
            a = _fit_points(b, s, f, inl)
            f = _fit_lights(b, s, a, inl)
        points = inl.sum(0)
        fallback = ~((points >= st.min_points) & np.isfinite(f).all(1) & (f > 0).all(1))
        rgb = _normalise(f, fallback)
        spread = _spread(r, f, a, ok)
    return Factors(rgb=rgb, points_used=points.astype(int), spread=spread,
                   fallback=fallback if F else np.zeros(0, bool))


def reference_region(samples: np.ndarray, predicted: np.ndarray, valid: np.ndarray, mask: np.ndarray,
                     settings: FactorSettings = FactorSettings()) -> np.ndarray:
    """Per-light RGB factors (F, 3) from a white / grey reference region the user names (``mask`` (P,)
    bool): with r = b / s, the region point's albedo a[p, c] = median_q r over its usable lights, and
    f[q, c] = median over the region's usable points of r / a; scale fixed as in :func:`estimate` (the mean
    over lights of each channel's factor is 1). Lights with fewer than ``min_points`` region points, and
    every light when no region point has ``min_lights`` usable samples, get 1. Only ``min_predicted``,
    ``min_lights`` and ``min_points`` of the settings apply (no subsampling: the region is small)."""
    st = settings
    b, s, ok = _checked(samples, predicted, valid, st)
    mask = np.asarray(mask, bool)
    if mask.shape != ok.shape[:1]:
        raise ValueError(f"mask {mask.shape} does not match samples {b.shape}")
    rows = np.flatnonzero(mask & (ok.sum(1) >= st.min_lights))
    b, s = b[rows], s[rows]
    ok = ok[rows] & np.isfinite(b).all(2)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
        r = np.where(ok[..., None], b / np.where(ok, s, 1.0)[..., None], 0.0)
        okc = ok[..., None] & (r > 0)
        a = _masked_median(r, okc, axis=1)                                 # (N, 3)
        okc &= (a > 0)[:, None, :]
        f = _masked_median(r / np.where(a > 0, a, 1.0)[:, None, :], okc, axis=0)   # (F, 3)
        n = okc.all(2).sum(0)
        fallback = ~((n >= st.min_points) & np.isfinite(f).all(1) & (f > 0).all(1))
        return _normalise(f, fallback)


# ---------------------------------------------------------------------------------------------------------------
# Steps
# ---------------------------------------------------------------------------------------------------------------


def _checked(samples, predicted, valid, st: FactorSettings):
    """float arrays b (P, F, 3), s (P, F) and the usable mask: valid, finite, s > min_predicted."""
    b = np.asarray(samples, float)
    s = np.asarray(predicted, float)
    valid = np.asarray(valid, bool)
    if b.ndim != 3 or b.shape[-1] != 3:
        raise ValueError(f"samples must be (P, F, 3), got {b.shape}")
    if s.shape != b.shape[:2] or valid.shape != b.shape[:2]:
        raise ValueError(f"predicted {s.shape} / valid {valid.shape} do not match samples {b.shape}")
    with np.errstate(invalid="ignore"):
        ok = valid & np.isfinite(s) & (s > st.min_predicted)
    return b, s, ok


def _subsample(ok: np.ndarray, st: FactorSettings) -> np.ndarray:
    """Indices of at most ``max_points`` points with >= ``min_lights`` usable samples, evenly strided.
    (Finiteness of the samples is checked on these rows only: the full array may be large.)"""
    rows = np.flatnonzero(ok.sum(1) >= st.min_lights)
    m = max(int(st.max_points), 1)
    if len(rows) > m:
        rows = rows[np.linspace(0, len(rows) - 1, m).round().astype(int)]
    return rows


def _masked_median(x: np.ndarray, mask: np.ndarray, axis: int) -> np.ndarray:
    """Median (lower middle) of x where mask along ``axis`` (removed); 0 where the mask is empty.
    (The axis is moved last and made contiguous: sorting along a strided axis is several times slower.)"""
    x, mask = np.broadcast_arrays(x, mask)
    count = mask.sum(axis)
    if x.shape[axis] == 0:
        return np.zeros(count.shape)
    srt = np.ascontiguousarray(np.moveaxis(np.where(mask, x, np.inf), axis, -1))
    srt.sort(axis=-1)
    m = np.take_along_axis(srt, (np.maximum(count - 1, 0) // 2)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, m, 0.0)


def _polish(r: np.ndarray, ok: np.ndarray, st: FactorSettings):
    """Seed f (F, 3), a (N, 3) by median polish of log r = log f + log a over the usable, positive
    ratios; log f centred per channel (geometric mean 1). Empty rows / columns: factor 1, albedo 0."""
    pos = ok[..., None] & (r > 0)
    lr = np.log(np.where(pos, r, 1.0))
    lf = np.zeros(r.shape[1:])
    la = np.zeros((r.shape[0], 3))
    for _ in range(max(int(st.polish), 1)):
        la = _masked_median(lr - lf[None], pos, axis=1)
        lf = _masked_median(lr - la[:, None], pos, axis=0)
        has = pos.any(0)
        lf -= np.array([lf[has[:, c], c].mean() if has[:, c].any() else 0.0 for c in range(3)])
        lf = np.where(has, lf, 0.0)
    la = _masked_median(lr - lf[None], pos, axis=1)
    a = np.where(pos.any(1), np.exp(la), 0.0)
    return np.exp(lf), a


def _trim(r, f, a, ok, inl, st: FactorSettings) -> np.ndarray:
    """New inlier mask (N, F): the relative residual e = r / (f a) - 1 within [-k sigma, k_high sigma] in
    every channel, sigma the point's clipped MAD over its current inliers; too few: keep the old set."""
    fa = f[None] * a[:, None]                                          # (N, F, 3)
    e = np.where(fa > 0, r / np.where(fa > 0, fa, 1.0) - 1.0, np.inf)
    sigma = MAD * _masked_median(np.abs(e), inl[..., None] & np.isfinite(e), axis=1)      # (N, 3)
    band = np.clip(sigma, st.floor, st.cap)[:, None]
    new = ok & ((e >= -st.k * band) & (e <= st.k_high * band)).all(2)
    keep = new.sum(1) >= st.min_lights
    return np.where(keep[:, None], new, inl)


def _fit_points(b, s, f, inl) -> np.ndarray:
    """a[p, c] = sum_q w b f s / sum_q w (f s)^2 (N, 3); 0 where nothing fits."""
    w = (inl * s)[..., None]                                           # w s (N, F, 1)
    num = (w * b * f[None]).sum(1)
    den = (w * s[..., None] * (f * f)[None]).sum(1)
    return _ratio(num, den)


def _fit_lights(b, s, a, inl) -> np.ndarray:
    """f[q, c] = sum_p w b a s / sum_p w (a s)^2 (F, 3); 0 where nothing fits (a fallback)."""
    w = (inl * s)[..., None]
    num = (w * b * a[:, None]).sum(0)
    den = (w * s[..., None] * (a * a)[:, None]).sum(0)
    return _ratio(num, den)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    q = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.where(np.isfinite(q), q, 0.0)


def _normalise(f: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Fix the scale: each channel's mean over the non-fallback lights is 1; fallbacks are 1."""
    good = ~fallback
    if not good.any():
        return np.ones_like(f)
    mean = f[good].mean(0)
    out = np.where(good[:, None], f / mean[None], 1.0)
    return np.where(np.isfinite(out) & (out > 0), out, 1.0)


def _spread(r, f, a, ok) -> np.ndarray:
    """Per light, 1.4826 MAD of the luminance ratio sum_c r / sum_c f a (the fit's f, a) over its usable
    points, about its median (relative; 0 without points)."""
    fa = (f[None] * a[:, None]).sum(2)
    use = ok & (fa > 0)
    x = np.where(use, r.sum(2) / np.where(use, fa, 1.0), 0.0)
    med = _masked_median(x, use, axis=0)
    out = MAD * _masked_median(np.abs(x - med[None]), use, axis=0)
    return np.where(np.isfinite(out), out, 0.0)


def fill_from_neighbours(directions: np.ndarray, rgb: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """``rgb`` (F, 3) with the ``missing`` lights' factors (F,) bool (held out, or fallbacks) taken from their
    neighbours on the sphere: a local-linear fit of log f over the other lights' directions, weighted by
    exp(-(angle / (2 s))^2), s the median angle between a light and its nearest neighbour (``directions``
    (F, 3) unit), read at the missing light. A dome's factors change steeply from ring to ring (RealRTI:
    0.4 at 11 deg elevation to 1.7 at 75 deg), and a light on the lowest ring has neighbours above it only:
    a weighted mean (the fallback, with weights exp(-(angle / s)^2), where fewer than four lights span the
    neighbourhood) is biased towards them by the slope; the local-linear fit is not (the fresco's held-out
    lights: 0.148 -> 0.127 relative L2, docs/decisions.md). Without any known light, a missing light keeps its
    own factor."""
    rgb = np.array(rgb, float)
    missing = np.asarray(missing, bool)
    known = np.flatnonzero(~missing & np.all(rgb > 0, axis=1))
    if known.size == 0 or not missing.any():
        return rgb
    d = np.asarray(directions, float)
    angle = np.arccos(np.clip(d @ d.T, -1.0, 1.0))
    nearest = np.sort(angle + np.diag(np.full(len(d), np.inf)), axis=1)[:, 0]
    scale = max(float(np.median(nearest)), 1e-3)
    log_f = np.log(rgb[known])
    for q in np.flatnonzero(missing):
        w = np.exp(-(angle[q, known] / scale) ** 2)
        filled = np.exp(w @ log_f / w.sum()) if w.sum() > 0 else rgb[q]
        root = np.sqrt(np.exp(-(angle[q, known] / (2.0 * scale)) ** 2))[:, None]
        design = np.c_[np.ones(known.size), d[known] - d[q]] * root
        if np.linalg.matrix_rank(design, tol=1e-6) == 4:
            filled = np.exp(np.linalg.lstsq(design, log_f * root, rcond=None)[0][0])
        rgb[q] = filled
    return rgb
    d = np.asarray(directions, float)
    angle = np.arccos(np.clip(d @ d.T, -1.0, 1.0))
    nearest = np.sort(angle + np.diag(np.full(len(d), np.inf)), axis=1)[:, 0]
    scale = max(float(np.median(nearest)), 1e-3)
    w = np.exp(-(angle[np.ix_(missing, known)] / scale) ** 2)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    rgb[missing] = w @ rgb[known]
    return rgb
