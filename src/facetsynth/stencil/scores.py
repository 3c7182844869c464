"""Image scores of paper 000 (sec. 4.2) on the 288x288 unwrapped BRDF image.

Normalisation (stated): both images are divided by s = the 99th percentile of
the reference's Rec. 709 luminance (exposure), so the reference's bright
1 % may exceed 1.

* delta_e: mean CIEDE2000 over pixels.  Linear Rec. 709/sRGB RGB -> CIE XYZ
  (IEC 61966-2-1 matrix, D65) -> CIELAB with white D65 (Xn, Yn, Zn) =
  (0.95047, 1, 1.08883), on the exposure-normalised linear images (unclipped).
* rmse, psnr_db, ssim: on the display images sRGB_OETF(clip(lin / s, 0, 1)),
  values in [0, 1]; PSNR = 20 log10(1 / RMSE) (capped at 100 dB); SSIM of
  Wang et al. 2004 on the display luminance, Gaussian window sigma 1.5
  (truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03, L = 1.
"""

from __future__ import annotations

import numpy as np

from ..evaluation.metrics import ssim_map
from . import grid

__all__ = ["SRGB_TO_XYZ", "WHITE_D65", "exposure", "srgb_oetf", "rgb_to_lab", "ciede2000",
           "delta_e", "rmse", "psnr", "ssim", "score_images", "score_brdf"]

SRGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]])
WHITE_D65 = np.array([0.95047, 1.0, 1.08883])


def exposure(ref_img):
    s = np.percentile(np.asarray(ref_img, float) @ grid.LUMA, 99.0)
    return float(s) if s > 0 else 1.0


def srgb_oetf(x):
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def rgb_to_lab(rgb):
    xyz = np.asarray(rgb, float) @ SRGB_TO_XYZ.T / WHITE_D65
    d = 6.0 / 29.0
    f = np.where(xyz > d ** 3, np.cbrt(np.maximum(xyz, 0)), xyz / (3 * d * d) + 4.0 / 29.0)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def ciede2000(lab1, lab2):
    """CIEDE2000 colour difference (Sharma et al. 2005), kL = kC = kH = 1."""
    L1, a1, b1 = np.moveaxis(np.asarray(lab1, float), -1, 0)
    L2, a2, b2 = np.moveaxis(np.asarray(lab2, float), -1, 0)
    C1, C2 = np.hypot(a1, b1), np.hypot(a2, b2)
    Cb7 = ((C1 + C2) / 2) ** 7
    G = 0.5 * (1 - np.sqrt(Cb7 / (Cb7 + 25.0 ** 7)))
    a1p, a2p = (1 + G) * a1, (1 + G) * a2
    C1p, C2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.degrees(np.arctan2(b1, a1p)) % 360
    h2p = np.degrees(np.arctan2(b2, a2p)) % 360
    dLp, dCp = L2 - L1, C2p - C1p
    dh = h2p - h1p
    dh = np.where(dh > 180, dh - 360, np.where(dh < -180, dh + 360, dh))
    dh = np.where(C1p * C2p == 0, 0.0, dh)
    dHp = 2 * np.sqrt(C1p * C2p) * np.sin(np.radians(dh / 2))
    Lbp, Cbp = (L1 + L2) / 2, (C1p + C2p) / 2
    hs = h1p + h2p
    hbp = np.where(np.abs(h1p - h2p) > 180, np.where(hs < 360, hs + 360, hs - 360), hs) / 2
    hbp = np.where(C1p * C2p == 0, hs, hbp)
    T = (1 - 0.17 * np.cos(np.radians(hbp - 30)) + 0.24 * np.cos(np.radians(2 * hbp))
         + 0.32 * np.cos(np.radians(3 * hbp + 6)) - 0.20 * np.cos(np.radians(4 * hbp - 63)))
    dtheta = 30 * np.exp(-(((hbp - 275) / 25) ** 2))
    Cbp7 = Cbp ** 7
    RC = 2 * np.sqrt(Cbp7 / (Cbp7 + 25.0 ** 7))
    SL = 1 + 0.015 * (Lbp - 50) ** 2 / np.sqrt(20 + (Lbp - 50) ** 2)
    SC = 1 + 0.045 * Cbp
    SH = 1 + 0.015 * Cbp * T
    RT = -np.sin(np.radians(2 * dtheta)) * RC
    return np.sqrt((dLp / SL) ** 2 + (dCp / SC) ** 2 + (dHp / SH) ** 2 + RT * (dCp / SC) * (dHp / SH))


def delta_e(ref_lin, test_lin):
    return float(np.mean(ciede2000(rgb_to_lab(ref_lin), rgb_to_lab(test_lin))))


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2)))


def psnr(a, b, peak=1.0):
    e = rmse(a, b)
    return 100.0 if e <= peak * 1e-5 else float(20 * np.log10(peak / e))


def ssim(x, y, sigma=1.5, L=1.0):
    """Mean SSIM (Wang et al. 2004) of two single-channel images in [0, L]."""
    return float(np.mean(ssim_map(x, y, sigma, L)))


def score_images(ref_img, test_img):
    """Scores of two 288x288x3 linear unwrapped images -> dict."""
    ref = np.nan_to_num(np.asarray(ref_img, float))
    tst = np.nan_to_num(np.asarray(test_img, float))
    s = exposure(ref)
    rl, tl = ref / s, tst / s
    rd, td = srgb_oetf(rl), srgb_oetf(tl)
    return {"delta_e": delta_e(rl, tl), "rmse": rmse(rd, td), "psnr_db": psnr(rd, td),
            "ssim": ssim(rd @ grid.LUMA, td @ grid.LUMA), "exposure": s}


def score_brdf(ref_brdf, test_brdf):
    """Scores of two UTIA-grid BRDFs ``(3, 6, 48, 6, 48)`` on their unwrapped images."""
    return score_images(grid.unwrap(ref_brdf), grid.unwrap(test_brdf))
