"""The remaining parameters of the model (paper 002 sec. 5.4, eqs. 5, 19, 20).

Given a completed NDF D (issue 4's synthesis, in the partial NDF's scale):

* the specular coefficient ks = integral over the hemisphere of (n . h) D dw_h,
* the normalised NDF D / ks (unit integral of (n . h) D, sec. 3),
* the shadowing term S(k) = (k . n) / A(k) from the normalised NDF by eq. 5,
  stored as its denominator A(k) (the projected area), which stays finite and
  positive at grazing k where S -> 0,
* the relative refraction index eta by Levenberg-Marquardt on eq. 19, with the
  measured Fresnel factor F_m of eq. 20 taken from the grazing samples that
  partial NDF fitting excluded.

Two remarks on eqs. 19-20 as printed:

* Eq. 20 carries the factor 4 pi, like eq. 11. With the paper's own
  normalisation of D and eq. 6 the factor is 4 (docs/decisions.md, partial
  NDF); 4 is used here too, so that F_m = F exactly for data made by eq. 6.
* The partial NDF of eq. 11 assumes F = 1, so the NDF that synthesis completes
  carries a Fresnel factor in every cell: ks D_c(h) = ks_true F(c_ref(h))
  D_true(h), with c_ref(h) = |o . h| of the view (rotated) that cell came from
  (synthesis carries it along, :func:`facetsynth.synthesis.complete`). Eq. 19
  compared with the absolute F_c of eq. 3 then has no solution (F_m ~ 1, F_c
  ~ 0.04-0.3). The fit therefore takes F_m = F_c(c, eta) / F_c(c_ref, eta),
  and D_true = D_c / F_c(c_ref, eta) once eta is known. ``c_ref=None`` is
  eq. 19 as printed, right when D and ks are free of Fresnel (e.g. an
  analytic material).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .grid import DirectionGrid
from .microfacet import fresnel
from .partial_ndf import SHADOWING_GRID, projected_area_table

ETA_BOUNDS = (1.05, 4.0)   # physical range of relative refraction indices fitted (dielectrics, coatings)
ETA_DEFAULT = 1.5          # where the data do not constrain eta


def specular_coefficient(ndf: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """ks = integral over the hemisphere of (n . h) D(h) dw_h (sec. 5.4), for NDFs (..., T, F)."""
    return grid.integrate(np.asarray(ndf, float) * grid.directions[..., 2])


def normalise(ndf: np.ndarray, grid: DirectionGrid) -> tuple[np.ndarray, np.ndarray]:
    """(D / ks, ks) with negative cells clipped to 0 first; an all-zero NDF stays 0 with ks = 0."""
    d = np.clip(np.asarray(ndf, float), 0.0, None)
    ks = specular_coefficient(d, grid)
    scale = np.divide(1.0, ks, out=np.zeros_like(ks), where=ks > 0)
    return d * scale[..., None, None], ks


def projected_area(normalised_ndf: np.ndarray, grid: DirectionGrid,
                   shadowing_grid: DirectionGrid = SHADOWING_GRID) -> np.ndarray:
    """A(k) of eq. 5 (R, Ts, Fs) on ``shadowing_grid`` from normalised NDFs (R, T, F).

    S(k) = (k . n) / A(k). S is smooth (sec. 3), so A is tabulated on a coarse
    grid and interpolated. For an all-zero NDF A = 1 (S(k) = k . n).
    """
    k = shadowing_grid.directions.reshape(-1, 3)
    d = np.asarray(normalised_ndf, float)
    area = projected_area_table(d.reshape((-1,) + grid.shape), grid, k)
    area = np.where(area > 1e-9, area, 1.0)
    return area.reshape(d.shape[:-2] + shadowing_grid.shape)


def shadowing(area: np.ndarray, k: np.ndarray, shadowing_grid: DirectionGrid = SHADOWING_GRID) -> np.ndarray:
    """S(k) = max(k . n, 0) / A(k) (eq. 5) from a tabulated A (..., Ts, Fs) at directions k (..., N, 3)."""
    a = shadowing_grid.lookup(area, k)
    return np.clip(k[..., 2], 0.0, None) / np.maximum(a, 1e-9)


def measured_fresnel(rho_s: np.ndarray, specular_without_fresnel: np.ndarray) -> np.ndarray:
    """F_m of eq. 20: the measured specular rho~_s over the model's ks D S S / (4 (i.n)(o.n)).

    The denominator is what eq. 6 predicts with F = 1 (factor 4, see the module
    note). Where it vanishes F_m is 0 (such samples carry no information on eta
    and should be excluded by the caller).
    """
    den = np.asarray(specular_without_fresnel, float)
    return np.divide(np.asarray(rho_s, float), den, out=np.zeros(np.broadcast_shapes(np.shape(rho_s), den.shape)),
                     where=den > 0)


@dataclass(frozen=True)
class EtaFit:
    eta: float
    constrained: bool      # False: the data did not constrain eta; ``eta`` is the default
    std: float             # standard error of eta from the LM Jacobian (inf when unconstrained)
    samples: int
    rms: float             # rms residual of eq. 19 at the solution
    reason: str = ""


def _model(eta: float, c: np.ndarray, c_ref: np.ndarray | None) -> np.ndarray:
    f = fresnel(c, eta)
    if c_ref is None:
        return f
    return f / np.maximum(fresnel(c_ref, eta), 1e-12)


def fit_eta(f_measured: np.ndarray, c: np.ndarray, c_ref: np.ndarray | None = None,
            weight: np.ndarray | None = None, bounds: tuple[float, float] = ETA_BOUNDS,
            default: float = ETA_DEFAULT, min_samples: int = 8, max_std: float = 0.15) -> EtaFit:
    """eta minimising eq. 19, sum_j w_j |F_c(c_j, eta) / F_c(c_ref_j, eta) - F_m,j|^2, by Levenberg-Marquardt.

    ``c`` = |i . h| of each sample; ``c_ref`` (optional) the cosine at which the
    NDF's scale carries F (module note), None for eq. 19 as printed. ``weight``
    (solid angle of each sample, eq. 19's dw) defaults to 1. eta is bounded to
    ``bounds`` by the change of variable eta = lo + (hi - lo) / (1 + exp(-u))
    (scipy ``least_squares(method="lm")`` has no bounds of its own), started
    from the best of a coarse scan so that LM starts in the right basin. The
    fit counts as unconstrained (``default`` returned) with fewer than
    ``min_samples`` samples, or when the standard error of eta exceeds
    ``max_std`` (the data hardly depend on eta), or at a bound. (Residuals in
    log F were measured too: on pooled pipeline data they bias eta upwards,
    1.91 against 1.81 for a true 1.8, docs/decisions.md.)
    """
    f_m = np.asarray(f_measured, float).ravel()
    c = np.asarray(c, float).ravel()
    cr = None if c_ref is None else np.broadcast_to(np.asarray(c_ref, float).ravel(), c.shape)
    w = np.ones_like(c) if weight is None else np.broadcast_to(np.asarray(weight, float).ravel(), c.shape)
    ok = np.isfinite(f_m) & np.isfinite(c) & (w > 0)
    n = int(ok.sum())
    if n < min_samples:
        return EtaFit(default, False, np.inf, n, np.nan, f"{n} usable grazing samples (< {min_samples})")
    f_m, c, sw = f_m[ok], c[ok], np.sqrt(w[ok])
    cr = None if cr is None else cr[ok]
    lo, hi = bounds

    def eta_of(u):
        return lo + (hi - lo) / (1.0 + np.exp(-u))

    def residual(u):
        return sw * (_model(eta_of(u[0]), c, cr) - f_m)

    scan = np.linspace(lo, hi, 60)[1:-1]
    costs = [np.sum(sw**2 * (_model(e, c, cr) - f_m) ** 2) for e in scan]
    e0 = scan[int(np.argmin(costs))]
    u0 = np.log((e0 - lo) / (hi - e0))
    sol = least_squares(residual, [u0], method="lm", xtol=1e-12, ftol=1e-12)
    eta = float(eta_of(sol.x[0]))
    r = sol.fun
    dof = max(n - 1, 1)
    sigma2 = float(r @ r) / dof
    # d eta / d u at the solution turns the Jacobian in u into one in eta
    deta_du = (eta - lo) * (hi - eta) / (hi - lo)
    j = sol.jac[:, 0] / max(deta_du, 1e-300)
    jtj = float(j @ j)
    std = float(np.sqrt(sigma2 / jtj)) if jtj > 0 else np.inf
    rms = float(np.sqrt(np.mean((r / sw) ** 2)))
    if not np.isfinite(eta) or eta - lo < 1e-3 * (hi - lo) or hi - eta < 1e-3 * (hi - lo):
        return EtaFit(default, False, std, n, rms, f"fit ran to the bound ({eta:.3f})")
    if not std <= max_std:
        return EtaFit(default, False, std, n, rms, f"standard error {std:.3f} > {max_std}")
    return EtaFit(eta, True, std, n, rms)
