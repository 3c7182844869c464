"""Baseline: the anisotropic BRDF model of Kurt, Szirmay-Kalos and Krivanek 2010,
two lobes, fitted as in paper 000 sec. 4.2.

    fr = kd/pi + sum_l ks_l F_l(h.k) D_l(h) / (4 (k.h) ((n.k1)(n.k2))^alpha_l)
    D(h) = exp(-tan^2 th_h (cos^2 ph_h / mx^2 + sin^2 ph_h / my^2)) / (pi mx my cos^4 th_h)
    F(c) = f0 + (1 - f0)(1 - c)^5                                    (Schlick)

Per lobe f0, mx, my, alpha (fitted to luminance) and ks RGB; kd RGB global
(7 per lobe + 3 = 17, paper 000 Tab. 1).  The lobe frame is the sample frame.
Fit: scipy.optimize.least_squares (method 'trf', bounded, max 40 evaluations,
every 2nd azimuth of the UTIA grid) on cube-root
luminance residuals (dynamic-range compression, stated choice), then kd, ks
per channel by non-negative linear least squares with the lobe shapes fixed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, nnls

from . import grid

__all__ = ["KurtModel", "LobeGeometry", "kurt_evaluate", "kurt_evaluate_utia", "fit_kurt"]


@dataclass(frozen=True)
class KurtModel:
    kd: tuple              # RGB
    ks: tuple              # (n_lobes, 3)
    lobes: tuple           # ((f0, mx, my, alpha), ...)


@dataclass(frozen=True)
class LobeGeometry:
    """What a lobe's shape takes from the directions alone, computed once for every lobe and every step of a
    fit: the half vector's tan^2 th_h and its cos^2 ph_h, cos^4 th_h, (1 - k.h)^5, 4 (k.h), (n.k1)(n.k2), and
    where both directions are above the horizon."""
    tan2: np.ndarray
    cos2_phi: np.ndarray
    cos4: np.ndarray
    schlick: np.ndarray
    four_kh: np.ndarray
    cos_io: np.ndarray
    above: np.ndarray

    @classmethod
    def of(cls, wi, wo) -> "LobeGeometry":
        h = wi + wo
        h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
        ci, co = np.maximum(wi[..., 2], 1e-6), np.maximum(wo[..., 2], 1e-6)
        ch = np.clip(h[..., 2], 1e-6, 1.0)
        kh = np.clip(np.sum(wi * h, -1), 1e-6, 1.0)
        sh2 = np.maximum(1 - ch * ch, 0.0)
        r2 = h[..., 0] ** 2 + h[..., 1] ** 2
        c2 = np.where(r2 > 0, h[..., 0] ** 2 / np.maximum(r2, 1e-300), 0.5)
        return cls(tan2=sh2 / (ch * ch), cos2_phi=c2, cos4=ch ** 4, schlick=(1 - kh) ** 5, four_kh=4 * kh,
                   cos_io=ci * co, above=(wi[..., 2] > 0) & (wo[..., 2] > 0))

    def lobe(self, f0, mx, my, alpha) -> np.ndarray:
        """One lobe's shape F D / (4 (k.h) ((n.k1)(n.k2))^alpha), ``(...)``; zero below the horizon."""
        e = np.minimum(self.tan2 * (self.cos2_phi / mx ** 2 + (1 - self.cos2_phi) / my ** 2), 700.0)
        D = np.exp(-e) / (np.pi * mx * my * self.cos4)
        F = f0 + (1 - f0) * self.schlick
        return np.where(self.above, F * D / (self.four_kh * self.cos_io ** alpha), 0.0)


def kurt_evaluate(model, wi, wo):
    wi, wo = np.broadcast_arrays(np.asarray(wi, float), np.asarray(wo, float))
    out = np.asarray(model.kd, float) / np.pi * np.ones(wi.shape[:-1] + (1,))
    geometry = LobeGeometry.of(wi, wo)
    for ks, lobe in zip(model.ks, model.lobes):
        out = out + geometry.lobe(*lobe)[..., None] * np.asarray(ks, float)
    return np.nan_to_num(np.where(geometry.above[..., None], np.maximum(out, 0.0), 0.0))


def kurt_evaluate_utia(model):
    wi, wo = grid.utia_directions()
    return np.moveaxis(kurt_evaluate(model, wi, wo), -1, 0)


def fit_kurt(brdf, n_lobes=2, max_nfev=40, phi_stride=2):
    """Fit the two-lobe Kurt model to a UTIA-grid BRDF -> (KurtModel, seconds)."""
    t0 = time.perf_counter()
    wi, wo = grid.utia_directions()
    # drop the duplicated theta = 0 azimuths (keep phi index 0 there)
    keep = np.ones(grid.SHAPE[1:], bool)
    keep[0, 1:] = False
    keep[:, :, 0, 1:] = False
    # the LM fit uses every phi_stride-th azimuth (speed); the linear colour fit too
    sub = np.zeros(grid.N_PHI, bool)
    sub[::phi_stride] = True
    keep &= sub[None, :, None, None] & sub[None, None, None, :]
    wi, wo = wi[keep], wo[keep]
    rgb = np.moveaxis(np.asarray(brdf, float), 0, -1)[keep]
    Y = np.maximum(rgb @ grid.LUMA, 0.0)
    Yc = np.cbrt(Y)
    kd0 = np.pi * np.percentile(Y, 10)
    x0 = [kd0]
    lo, hi = [0.0], [np.inf]
    rough = [0.08, 0.35, 0.6][:n_lobes]
    for r in rough:
        x0 += [max(Y.max() - kd0 / np.pi, 1e-3) * 0.05, 0.05, r, r, 0.5]
        lo += [0.0, 0.0, 0.005, 0.005, 0.0]
        hi += [np.inf, 1.0, 2.0, 2.0, 1.0]

    def lobes_of(x):
        return [tuple(x[1 + 5 * i + 1:1 + 5 * i + 5]) for i in range(n_lobes)]

    geometry = LobeGeometry.of(wi, wo)      # the directions' part of every lobe, once for the whole fit

    def resid(x):
        f = x[0] / np.pi + sum(x[1 + 5 * i] * geometry.lobe(*lb) for i, lb in enumerate(lobes_of(x)))
        return np.cbrt(np.maximum(f, 0.0)) - Yc

    sol = least_squares(resid, np.array(x0), bounds=(lo, hi), method="trf", max_nfev=max_nfev,
                        x_scale="jac")
    lobes = lobes_of(sol.x)
    A = np.stack([np.full(len(Y), 1 / np.pi)] + [geometry.lobe(*lb) for lb in lobes], 1)
    sw = 1.0 / np.maximum(np.cbrt(Y) ** 2, 1e-3)  # relative weighting, matches the cube-root fit
    coefs = np.array([nnls(A * sw[:, None], rgb[:, c] * sw, maxiter=200)[0] for c in range(3)])  # 3 channels
    model = KurtModel(kd=tuple(float(v) for v in coefs[:, 0]),
                      ks=tuple(tuple(float(v) for v in coefs[:, 1 + i]) for i in range(n_lobes)),
                      lobes=tuple(tuple(float(v) for v in lb) for lb in lobes))
    return model, time.perf_counter() - t0
