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
  (synthesis carries it along, :func:`facetsynth.fit.synthesis.complete`). Eq. 19
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

from ..geometry.grid import DirectionGrid
from ..models.microfacet import fresnel
from .partial_ndf import SHADOWING_GRID, projected_area_on

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
    d = np.asarray(normalised_ndf, float)
    area = projected_area_on(d.reshape((-1,) + grid.shape), grid, shadowing_grid)
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


# --- eta's profile-likelihood interval (issue 13 item 6) ----------------------------------

CHI2_1_95 = 3.841458820694124   # chi-square quantile, 1 degree of freedom, 0.95 (scipy.stats.chi2.ppf(0.95, 1))


@dataclass(frozen=True)
class EtaInterval:
    """The profile-likelihood interval of eta on eqs. 19-20 (:func:`eta_profile`)."""

    lo: float
    hi: float
    best: float            # eta minimising the residual sum of squares over [eta_min, eta_max]
    rss_min: float         # RSS at ``best``
    threshold: float       # RSS(eta) <= threshold inside the interval
    samples: int           # residuals in the RSS
    units: int             # n of the threshold: independent units (samples, or the groups given)
    open_below: bool       # the interval reaches eta_min (the data allow every eta down to the bound)
    open_above: bool       # ... eta_max
    reason: str = ""

    @property
    def width(self) -> float:
        return self.hi - self.lo

    def identifiable(self, max_width: float) -> bool:
        """True only when the interval is narrower than ``max_width`` and closed inside the bounds."""
        return bool(self.width < max_width and not self.open_below and not self.open_above)


def eta_rss(eta: np.ndarray, f_measured: np.ndarray, c: np.ndarray, c_ref: np.ndarray | None = None,
            weight: np.ndarray | None = None, block: int = 16) -> np.ndarray:
    """Eq. 19's residual sum of squares RSS(eta) = sum_j w_j (F_c(c_j, eta) / F_c(c_ref_j, eta) - F_m,j)^2.

    ``eta`` (G,) values; the samples (N,) as :func:`fit_eta` takes them
    (``c_ref`` None: eq. 19 as printed). Vectorised over ``block`` values of
    eta at a time (memory G x N). Eq. 19 as used here has no free parameter
    besides eta (ks and D come from sec. 5.4 and eq. 20, not from this fit), so
    this is the profile of eta: nothing to optimise out at each eta.
    """
    eta = np.atleast_1d(np.asarray(eta, float))
    f_m = np.asarray(f_measured, float)[None]
    c = np.asarray(c, float)[None]
    cr = None if c_ref is None else np.asarray(c_ref, float)[None]
    w = np.ones(c.shape) if weight is None else np.asarray(weight, float)[None]
    out = np.empty(eta.shape)
    for a in range(0, eta.size, block):
        e = eta[a:a + block, None]
        out[a:a + block] = np.sum(w * (_model(e, c, cr) - f_m) ** 2, axis=1)
    return out


def eta_profile(f_measured: np.ndarray, c: np.ndarray, c_ref: np.ndarray | None = None,
                weight: np.ndarray | None = None, bounds: tuple[float, float] = ETA_BOUNDS,
                groups: np.ndarray | None = None, chi2: float = CHI2_1_95, n_grid: int = 241) -> EtaInterval:
    """The 95 % profile-likelihood interval of eta from eqs. 19-20.

    RSS(eta) (:func:`eta_rss`) is evaluated on ``n_grid`` values spanning
    ``bounds`` and minimised (grid, then a bounded scalar search around the
    best grid value). With Gaussian residuals of unknown variance, estimated at
    the optimum as RSS_min / (n - p), the likelihood-ratio test at level 0.95
    keeps every eta with

        RSS(eta) <= RSS_min (1 + chi2_1(0.95) / (n - p)),   p = 1 (eta: eq. 19's only free parameter).

    n is the number of independent units: the samples (``groups`` None), or
    the number of distinct ``groups`` labels (N,) when samples share errors
    (the samples of one representative NDF share its error at the grazing
    half vectors: the residuals' scale is then set by the groups, and n = the
    groups' count is the design-effect correction of the test). The interval is
    the hull of the accepted set (conservative if RSS has several minima), its
    ends found where RSS crosses the threshold (Brent's method between grid
    values); an end that reaches a bound is marked open. With n - p < 1 or no
    usable sample the interval is the whole of ``bounds`` (nothing known).
    """
    from scipy.optimize import brentq, minimize_scalar

    lo_b, hi_b = float(bounds[0]), float(bounds[1])
    f_m = np.asarray(f_measured, float).ravel()
    c = np.asarray(c, float).ravel()
    cr = None if c_ref is None else np.broadcast_to(np.asarray(c_ref, float).ravel(), c.shape)
    w = np.ones_like(c) if weight is None else np.broadcast_to(np.asarray(weight, float).ravel(), c.shape)
    ok = np.isfinite(f_m) & np.isfinite(c) & (w > 0)
    if cr is not None:
        ok &= np.isfinite(cr)
    n = int(ok.sum())
    units = n if groups is None else int(np.unique(np.asarray(groups).ravel()[ok]).size)
    if units - 1 < 1:
        return EtaInterval(lo_b, hi_b, float("nan"), float("nan"), float("nan"), n, units, True, True,
                           f"{units} independent unit(s): eta not constrained")
    f_m, c, w = f_m[ok], c[ok], w[ok]
    cr = None if cr is None else cr[ok]

    def rss(e):
        return float(eta_rss(np.array([e]), f_m, c, cr, w)[0])

    grid = np.linspace(lo_b, hi_b, n_grid)
    profile = eta_rss(grid, f_m, c, cr, w)
    i = int(np.argmin(profile))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    res = minimize_scalar(rss, bounds=(a, b), method="bounded", options={"xatol": 1e-6 * (hi_b - lo_b)})
    best, rss_min = (float(res.x), float(res.fun)) if res.fun < profile[i] else (float(grid[i]), float(profile[i]))
    threshold = rss_min * (1.0 + chi2 / (units - 1))
    accepted = np.flatnonzero(profile <= threshold)
    inner_lo = min(best, grid[accepted].min()) if accepted.size else best
    inner_hi = max(best, grid[accepted].max()) if accepted.size else best

    def end(inner, outer_candidates):
        """The crossing between the inner point and the nearest grid value outside (None: reaches the bound)."""
        if outer_candidates.size == 0:
            return None
        outer = float(outer_candidates[-1] if outer_candidates[-1] < inner else outer_candidates[0])
        f_out, f_in = rss(outer) - threshold, rss(inner) - threshold
        if f_out <= 0:
            return outer
        if f_in >= 0:
            return float(inner)
        return float(brentq(lambda e: rss(e) - threshold, min(inner, outer), max(inner, outer), xtol=1e-7))

    lo = end(inner_lo, grid[grid < inner_lo])
    hi = end(inner_hi, grid[grid > inner_hi])
    return EtaInterval(lo_b if lo is None else lo, hi_b if hi is None else hi, best, rss_min, threshold, n, units,
                       lo is None, hi is None)
