"""The baseline of paper 002 Fig. 10: a per-point anisotropic Ward model fitted by Levenberg-Marquardt.

As in Goldman et al. 2005 and paper 002 sec. 6.2, each point's parameters are
fitted independently to the same rectified data (the per-point BRDF samples
of eq. 8 after the diffuse separation of eq. 9):

    rho(i, o) = kd/pi + ks exp(-tan^2(theta_h) (cos^2(phi_h)/ax^2 + sin^2(phi_h)/ay^2))
                        / (4 pi ax ay sqrt((i.n)(o.n)))

(Ward 1992), with phi_h measured in the point's frame at azimuth ``phi``.
kd is the separation's kd (eq. 9); ks (RGB as scalar x the specular colour),
ax, ay and phi are fitted to the specular residual. The model is reciprocal;
it is 0 where i.n <= 0 or o.n <= 0, and (i.n)(o.n) is floored so that it
stays finite at grazing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from .errors import InputError
from .fileio import read_exr, read_json, write_exr, write_json
from .microfacet import half_vector, to_local
from .plane import PlaneGrid

ALPHA_RANGE = (0.01, 1.5)


def ward_specular(wi, wo, alpha_x, alpha_y, phi):
    """The anisotropic Ward lobe without ks (1/sr); 0 below the horizon."""
    wi, wo = np.asarray(wi, float), np.asarray(wo, float)
    h = to_local(half_vector(wi, wo), phi)
    hz = np.clip(h[..., 2], 1e-6, None)
    e = -((h[..., 0] / alpha_x) ** 2 + (h[..., 1] / alpha_y) ** 2) / (hz * hz)
    cc = np.clip(wi[..., 2] * wo[..., 2], 1e-8, None)
    value = np.exp(np.clip(e, -700, 0)) / (4 * np.pi * alpha_x * alpha_y * np.sqrt(cc))
    return np.where((wi[..., 2] > 0) & (wo[..., 2] > 0), value, 0.0)


@dataclass(frozen=True)
class WardFit:
    ks: float
    alpha_x: float
    alpha_y: float
    phi: float
    cost: float
    ok: bool


def fit_point(rho_s: np.ndarray, wi: np.ndarray, wo: np.ndarray, starts=((0.15, 0.3, 0.0), (0.15, 0.3, np.pi / 4)),
              max_nfev: int = 200) -> WardFit:
    """LM fit of ks, alpha_x, alpha_y, phi to one point's specular samples rho_s (N,) at directions (N, 3).

    Parameters are fitted as log ks, log alpha (positivity) and phi; several
    starts (alpha_x < alpha_y, phi = 0 and 45 deg cover the frame's quadrant),
    the lowest cost wins. A point with no specular signal gets ks = 0. Samples
    whose value or directions are NaN or Inf are dropped.
    """
    rho_s, wi, wo = np.asarray(rho_s, float), np.asarray(wi, float), np.asarray(wo, float)
    finite = np.isfinite(rho_s) & np.isfinite(wi).all(axis=-1) & np.isfinite(wo).all(axis=-1)
    if not finite.all():
        rho_s, wi, wo = rho_s[finite], wi[finite], wo[finite]
    if rho_s.size < 5 or not np.any(rho_s > 0):
        return WardFit(0.0, 0.3, 0.3, 0.0, 0.0, False)
    best = None
    lo, hi = np.log(ALPHA_RANGE)
    for ax0, ay0, p0 in starts:
        lobe = ward_specular(wi, wo, ax0, ay0, p0)
        ks0 = max(float(rho_s @ lobe) / max(float(lobe @ lobe), 1e-30), 1e-6)

        def residual(x):
            ax, ay = np.exp(np.clip(x[1:3], lo, hi))
            return np.exp(x[0]) * ward_specular(wi, wo, ax, ay, x[3]) - rho_s

        sol = least_squares(residual, [np.log(ks0), np.log(ax0), np.log(ay0), p0], method="lm", max_nfev=max_nfev)
        if best is None or sol.cost < best.cost:
            best = sol
    ks = float(np.exp(best.x[0]))
    ax, ay = (float(v) for v in np.exp(np.clip(best.x[1:3], lo, hi)))
    return WardFit(ks, ax, ay, float(np.mod(best.x[3], np.pi)), float(best.cost), bool(best.success))


@dataclass
class WardSVBRDF:
    """Per-point Ward parameters on the plane grid, with the SVBRDF loader's evaluation interface."""

    plane: PlaneGrid
    kd: np.ndarray        # (P, 3)
    ks: np.ndarray        # (P, 3)
    alpha_x: np.ndarray   # (P,)
    alpha_y: np.ndarray   # (P,)
    phi: np.ndarray       # (P,)
    info: dict[str, Any] = field(default_factory=dict)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        rc = (self.plane.rows, self.plane.cols)
        write_exr(path / "kd.exr", {"RGB": self.kd.reshape(rc + (3,))}, {"quantity": "kd"})
        write_exr(path / "ks.exr", {"RGB": self.ks.reshape(rc + (3,))}, {"quantity": "ks (Ward)"})
        write_exr(path / "lobe.exr", {"alpha_x": self.alpha_x.reshape(rc), "alpha_y": self.alpha_y.reshape(rc),
                                      "phi": self.phi.reshape(rc)}, {"quantity": "Ward alpha_x, alpha_y, frame phi (rad)"})
        write_json(path / "model.json", dict(self.info, version=1, model="ward", units="m",
                                             plane_grid=self.plane.to_dict(),
                                             formula="kd/pi + ks exp(-tan^2 th (cos^2 ph/ax^2 + sin^2 ph/ay^2)) "
                                                     "/ (4 pi ax ay sqrt((i.n)(o.n)))"))

    @classmethod
    def load(cls, path: str | Path) -> "WardSVBRDF":
        path = Path(path)
        meta = read_json(path / "model.json")
        if meta.get("model") != "ward":
            raise InputError(path / "model.json", "not a Ward model folder")
        plane = PlaneGrid.from_dict(meta["plane_grid"])
        p = plane.rows * plane.cols
        lobe = read_exr(path / "lobe.exr")[0]
        return cls(plane, read_exr(path / "kd.exr")[0]["RGB"].reshape(p, 3).astype(float),
                   read_exr(path / "ks.exr")[0]["RGB"].reshape(p, 3).astype(float),
                   lobe["alpha_x"].reshape(p).astype(float), lobe["alpha_y"].reshape(p).astype(float),
                   lobe["phi"].reshape(p).astype(float), meta)

    def point_index(self, points):
        from .svbrdf import SVBRDF
        return SVBRDF.point_index(self, points)   # same cell lookup (uses only self.plane)

    def eval_index(self, index, wi, wo) -> np.ndarray:
        spec = ward_specular(wi, wo, self.alpha_x[index], self.alpha_y[index], self.phi[index])
        rho = self.kd[index] / np.pi + self.ks[index] * spec[:, None]
        rho = np.where(((wi[:, 2] > 0) & (wo[:, 2] > 0))[:, None], rho, 0.0)
        return np.clip(np.nan_to_num(rho, nan=0.0, posinf=0.0), 0.0, None)
