"""Accuracy measures against ground truth (DESIGN.md "Accuracy records")."""

from __future__ import annotations

import numpy as np


def relative_errors(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                    sample: int | None = None) -> np.ndarray:
    """|estimate - truth| / truth over the entries selected by ``mask`` (truth > 0 only).

    ``mask`` broadcasts against the arrays. With ``sample``, at most that many
    entries, evenly strided (deterministic), are returned.
    """
    truth = np.asarray(truth, dtype=np.float64)
    select = truth > 0 if mask is None else np.broadcast_to(mask, truth.shape) & (truth > 0)
    err = np.abs(np.asarray(estimate, dtype=np.float64)[select] - truth[select]) / truth[select]
    if sample is not None and err.size > sample:
        err = err[:: int(np.ceil(err.size / sample))]
    return err


def marker_centroids(image: np.ndarray, expected: np.ndarray, radius: float) -> np.ndarray:
    """Sub-pixel centres (col, row) of dark disc markers near their expected positions.

    ``image`` (rows, cols) is a brightness image; each marker is found in a
    window of 2.5 radii around its expected (col, row) as the centroid of the
    darkness (local background minus value), the background being the median
    of the ring between 1.6 and 2.5 radii. Markers whose window leaves the
    image come back as NaN rows.
    """
    rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    found = np.full((len(expected), 2), np.nan)
    for m, (c0, r0) in enumerate(expected):
        d = np.hypot(cols - c0, rows - r0)
        if c0 - 2.5 * radius < -0.5 or r0 - 2.5 * radius < -0.5 or \
           c0 + 2.5 * radius > image.shape[1] - 0.5 or r0 + 2.5 * radius > image.shape[0] - 0.5:
            continue
        ring = (d >= 1.6 * radius) & (d <= 2.5 * radius)
        background = np.median(image[ring])
        weight = np.where(d <= 1.5 * radius, np.clip(background - image, 0.0, None), 0.0)
        if weight.sum() > 0:
            found[m] = (weight * cols).sum() / weight.sum(), (weight * rows).sum() / weight.sum()
    return found


# --- image comparison (held-out views, paper 002 sec. 6) ----------------------------

def ssim_map(x: np.ndarray, y: np.ndarray, sigma: float = 1.5, data_range: float = 1.0) -> np.ndarray:
    """Per-pixel SSIM (Wang et al. 2004: Gaussian window sigma, K1 0.01, K2 0.03) of two single-channel images."""
    from scipy.ndimage import gaussian_filter

    x, y = np.asarray(x, float), np.asarray(y, float)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    f = lambda a: gaussian_filter(a, sigma, truncate=3.5)  # noqa: E731
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def image_scores(truth: np.ndarray, prediction: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """RMSE, PSNR and SSIM of predicted against true radiance over the sample's pixels.

    ``truth``, ``prediction`` (F, H, W, 3) linear radiance of the F frames of
    one view; ``mask`` (H, W) the sample's pixels. Normalisation (stated in
    every metrics file): peak = the largest true radiance over the view's
    sample pixels (all frames, all channels);

    * ``rmse``: root mean square error over sample pixels, frames and
      channels, in radiance units; ``rmse_normalised`` = rmse / peak;
    * ``psnr_db`` = 20 log10(peak / rmse);
    * ``ssim``: SSIM (Wang et al. 2004: Gaussian window sigma 1.5, K1 0.01,
      K2 0.03) of the channel-mean images divided by peak (data range 1),
      averaged over the sample's pixels and then over frames.
    """
    truth = np.asarray(truth, float)
    prediction = np.asarray(prediction, float)
    m = np.broadcast_to(mask, truth.shape[1:3])
    t, p = truth[:, m], prediction[:, m]
    peak = float(t.max()) if t.size else 0.0
    rmse = float(np.sqrt(np.mean((p - t) ** 2))) if t.size else float("nan")
    psnr = float(20 * np.log10(peak / rmse)) if rmse > 0 and peak > 0 else float("inf")
    scale = max(peak, 1e-30)
    ssims = [float(ssim_map(truth[q].mean(axis=-1) / scale, prediction[q].mean(axis=-1) / scale)[m].mean())
             for q in range(truth.shape[0])]
    return {"rmse": rmse, "rmse_normalised": rmse / peak if peak > 0 else float("nan"), "psnr_db": psnr,
            "ssim": float(np.mean(ssims)) if ssims else float("nan"), "peak": peak}


# --- scores a user can trust (issue 13 item 4) ----------------------------------------

def relative_l2(prediction: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                reference: np.ndarray | None = None) -> float:
    """Relative L2 error sqrt(sum (prediction - truth)^2 / sum (truth - reference)^2) over masked pixels.

    ``prediction``, ``truth`` (..., H, W, C) images (e.g. (F, H, W, 3): every
    frame of a view); ``mask`` (H, W) the pixels scored (default all); every
    frame and channel of a selected pixel enters both sums. ``reference``
    (same shape, default 0) is subtracted from both images first, so that
    ``reference`` = the true diffuse term kd/pi (n.i) L / r^2 (eq. 8 forwards)
    scores the specular part alone: (prediction - reference) against
    (truth - reference). Returns NaN when nothing is selected or the
    denominator is 0 (no signal to be relative to), 0 when both sums are 0.
    """
    truth = np.asarray(truth, float)
    prediction = np.asarray(prediction, float)
    m = np.ones(truth.shape[-3:-1], bool) if mask is None else np.broadcast_to(np.asarray(mask, bool),
                                                                               truth.shape[-3:-1])
    t = truth[..., m, :]
    if t.size == 0:
        return float("nan")
    signal = t if reference is None else t - np.asarray(reference, float)[..., m, :]
    num = float(np.sum((prediction[..., m, :] - t) ** 2))
    den = float(np.sum(signal**2))
    if den > 0:
        return float(np.sqrt(num / den))
    return 0.0 if num == 0 else float("nan")


def frame_psnr(truth: np.ndarray, prediction: np.ndarray, mask: np.ndarray | None = None,
               max_db: float = 100.0) -> np.ndarray:
    """PSNR (F,) of each frame over the masked pixels, with that frame's own peak.

    ``truth``, ``prediction`` (F, H, W, C); ``mask`` (H, W). For frame q:
    peak_q = max of truth[q] over the masked pixels (all channels), rmse_q over
    the masked pixels and channels, psnr_q = 20 log10(peak_q / rmse_q), capped
    at ``max_db`` (an exact prediction: rmse 0). A frame with no masked pixel
    or peak_q <= 0 (no light on the sample) is NaN: no score, not a perfect
    one; callers summarise over the finite frames.
    """
    truth = np.asarray(truth, float)
    prediction = np.asarray(prediction, float)
    m = np.ones(truth.shape[1:3], bool) if mask is None else np.broadcast_to(np.asarray(mask, bool),
                                                                            truth.shape[1:3])
    t, p = truth[:, m], prediction[:, m]
    out = np.full(truth.shape[0], np.nan)
    if t.shape[1] == 0:
        return out
    peak = t.reshape(len(t), -1).max(axis=1)
    rmse = np.sqrt(np.mean((p - t).reshape(len(t), -1) ** 2, axis=1))
    lit = peak > 0
    floor = peak * 10 ** (-max_db / 20)             # rmse below this scores max_db
    with np.errstate(divide="ignore", invalid="ignore"):
        out[lit] = 20 * np.log10(peak[lit] / np.maximum(rmse[lit], floor[lit]))
    return out


def spread_about_mean(tables: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Relative L2 (N,) of each table about the mean table, weighted: sqrt(sum w (x_n - m)^2 / sum w m^2).

    ``tables`` (N, ...) e.g. per-point NDFs (N, T, F) on a direction grid;
    ``weight`` (...) e.g. the grid's solid angles (the hemisphere integral
    of the squared difference, as :func:`facetsynth.fit.partial_ndf.relative_l2`).
    The spread of a homogeneous region's fitted NDFs: 0 when every point has
    the same NDF. An all-zero mean gives NaN (nothing to be relative to);
    no table gives an empty array.
    """
    x = np.asarray(tables, float)
    if x.shape[0] == 0:
        return np.zeros(0)
    w = np.broadcast_to(np.asarray(weight, float), x.shape[1:])
    mean = x.mean(axis=0)
    den = float(np.sum(w * mean**2))
    if not den > 0:
        return np.full(x.shape[0], np.nan)
    axes = tuple(range(1, x.ndim))
    return np.sqrt(np.sum(w * (x - mean) ** 2, axis=axes) / den)


def finite_or_none(value) -> float | None:
    """A float for a metrics file: None where the value is missing, NaN or infinite (no NaN/Inf in JSON)."""
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None
