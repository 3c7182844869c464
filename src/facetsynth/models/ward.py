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

The fit (:func:`fit_points`) is Levenberg-Marquardt with an analytic Jacobian,
one point at a time inside a compiled (numba) loop over a tile of points: the
points are independent, so a point's fit does not depend on the tile it is in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numba
import numpy as np

from ..io.errors import InputError
from ..io.fileio import read_exr, read_json, write_exr, write_json
from .microfacet import half_vector, to_local
from ..geometry.plane import PlaneGrid

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


STARTS = ((0.15, 0.3, 0.0), (0.15, 0.3, np.pi / 4))   # (alpha_x, alpha_y, phi): phi 0 and 45 deg cover the quadrant
DIAG_FLOOR = 1e-9     # each entry of LM's damping diagonal is at least this x the largest of diag(J^T J)
FTOL = XTOL = 1e-10   # LM stops when the relative cost change (actual and predicted) or the relative step is below


class WardFits(NamedTuple):
    """Per-point results of :func:`fit_points`, arrays (P,)."""

    ks: np.ndarray
    alpha_x: np.ndarray
    alpha_y: np.ndarray
    phi: np.ndarray       # in [0, pi)
    cost: np.ndarray      # 0.5 sum of squared residuals over the used samples (scipy's convention)
    ok: np.ndarray        # bool: enough signal, and LM converged within max_iterations


def fit_points(rho_s, wi, wo, use=None, starts=STARTS, max_iterations: int = 200) -> WardFits:
    """Levenberg-Marquardt fits of ks, alpha_x, alpha_y, phi to a tile of points at once.

    ``rho_s`` (P, N) are the points' specular samples at directions ``wi``, ``wo`` (P, N, 3) (broadcast);
    ``use`` (P, N) bool marks the samples to fit (default all); samples whose value or directions are NaN or
    Inf are left out as well. Each point is fitted independently, as x = (log ks, log alpha_x, log alpha_y,
    phi) minimising 0.5 sum (exp(x0) ward_specular(wi, wo, ax, ay, phi) - rho_s)^2 over its used samples:
    from each of ``starts`` (ks0 by linear least squares there), LM with an analytic Jacobian, Marquardt's
    damping lambda diag(J^T J) (see :func:`_lm`) with lambda adapted per point from the gain ratio (Nielsen),
    log alpha kept in ``ALPHA_RANGE`` (a step stops at the bound; an alpha on its bound and pushed outwards
    is held), stopping on relative cost change (actual and predicted) or relative step below 1e-10, or
    after ``max_iterations`` trial steps (evaluations; then ok = False); the start with the lowest final
    cost wins. A point with fewer than 5 used samples or no positive one gets ks = 0, alpha 0.3, phi 0,
    cost 0, ok = False. Outputs are always finite.
    """
    rho_s = np.asarray(rho_s, float)
    if rho_s.ndim != 2:
        raise ValueError(f"rho_s must be (points, samples), not {rho_s.shape}")
    shape = rho_s.shape
    # C-contiguous float64 and bool throughout: one compiled signature of the kernel
    rho_s = np.ascontiguousarray(rho_s)
    wi = np.ascontiguousarray(np.broadcast_to(np.asarray(wi, float), shape + (3,)))
    wo = np.ascontiguousarray(np.broadcast_to(np.asarray(wo, float), shape + (3,)))
    use = np.ascontiguousarray(np.broadcast_to(True if use is None else np.asarray(use, bool), shape))
    starts = np.asarray(starts, float).reshape(-1, 3)
    out = np.zeros((6, shape[0]))
    _fit_tile(rho_s, wi, wo, use, starts, *np.log(ALPHA_RANGE), int(max_iterations), FTOL, XTOL, out)
    return WardFits(out[0], out[1], out[2], out[3], out[4], out[5] > 0)


def residual_jacobian(x, rho_s, wi, wo) -> tuple[np.ndarray, np.ndarray]:
    """One point's residual r (N,) and analytic Jacobian dr/dx (N, 4) at x = (log ks, log ax, log ay, phi), as
    :func:`fit_points` computes them (for tests)."""
    rho_s = np.ascontiguousarray(rho_s, float)
    n = rho_s.size
    wi = np.ascontiguousarray(np.broadcast_to(np.asarray(wi, float), (n, 3)))
    wo = np.ascontiguousarray(np.broadcast_to(np.asarray(wo, float), (n, 3)))
    a, b, g, rho, use = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_)
    _prepare(rho_s, wi, wo, np.ones(n, np.bool_), a, b, g, rho, use)
    jac = np.zeros((n, 4))
    f = _lobe_jacobian(np.asarray(x, float), a, b, g, jac)
    return f - rho_s, jac


@numba.njit(cache=True, nogil=True)
def _prepare(rho_s, wi, wo, use_in, a, b, g, rho, use):
    """One point's samples without the parameters: use = use_in where value and directions are finite (rho 0
    elsewhere); the half vector's slopes a = h_x / h_z, b = h_y / h_z (world frame, h_z floored at 1e-6) and
    g = 1 / (4 pi sqrt((i.n)(o.n))) ((i.n)(o.n) floored at 1e-8; g = 0 below the horizon or where not used),
    as in :func:`ward_specular`. Returns the numbers of used and of positive used samples."""
    used = positive = 0
    for n in range(rho_s.size):
        a[n], b[n], g[n], rho[n] = 0.0, 0.0, 0.0, 0.0
        ok = use_in[n] and np.isfinite(rho_s[n])
        for j in range(3):
            ok = ok and np.isfinite(wi[n, j]) and np.isfinite(wo[n, j])
        use[n] = ok
        if not ok:
            continue
        used += 1
        rho[n] = rho_s[n]
        if rho_s[n] > 0:
            positive += 1
        if wi[n, 2] > 0 and wo[n, 2] > 0:
            hx, hy, hz = wi[n, 0] + wo[n, 0], wi[n, 1] + wo[n, 1], wi[n, 2] + wo[n, 2]
            norm = np.sqrt(hx * hx + hy * hy + hz * hz)     # > 0: both directions above the horizon
            inv = 1.0 / (norm * max(hz / norm, 1e-6))
            a[n], b[n] = hx * inv, hy * inv
            g[n] = 1.0 / (4.0 * np.pi * np.sqrt(max(wi[n, 2] * wo[n, 2], 1e-8)))
    return used, positive


@numba.njit(cache=True, nogil=True, inline="always")
def _sample_lobe(a, b, g, c, s, iax2, iay2, scale):
    """One sample's lobe exp(x0) ward_specular, with its half vector's slopes in the point's frame (u, v) and
    the exponent's terms pu = u^2 / ax^2, pv = v^2 / ay^2: (f, u, v, pu, pv). The lobe is 0 below the horizon
    (g = 0) and where its exponent is below -700 (exp < 1e-304)."""
    u, v, pu, pv = c * a + s * b, c * b - s * a, 0.0, 0.0
    f = 0.0
    if g > 0:
        pu, pv = u * u * iax2, v * v * iay2
        if -(pu + pv) > -700.0:
            f = scale * g * np.exp(-(pu + pv))
    return f, u, v, pu, pv


@numba.njit(cache=True, nogil=True)
def _lobe_jacobian(x, a, b, g, jac):
    """exp(x0) ward_specular at x for samples (a, b, g) (:func:`_prepare`); fills jac (N, 4)."""
    iax2, iay2 = np.exp(-2.0 * x[1]), np.exp(-2.0 * x[2])
    scale = np.exp(x[0] - x[1] - x[2])
    c, s = np.cos(x[3]), np.sin(x[3])
    f = np.zeros(a.size)
    for n in range(a.size):
        fn, u, v, pu, pv = _sample_lobe(a[n], b[n], g[n], c, s, iax2, iay2, scale)
        if fn != 0.0:
            f[n] = fn
            jac[n, 0] = fn
            jac[n, 1] = fn * (2.0 * pu - 1.0)
            jac[n, 2] = fn * (2.0 * pv - 1.0)
            jac[n, 3] = -2.0 * fn * u * v * (iax2 - iay2)
    return f


@numba.njit(cache=True, nogil=True)
def _normal_equations(x, a, b, g, rho, use, jtj, jtr):
    """0.5 sum r^2 over the used samples at x; fills J^T J (4, 4) and J^T r (4,) (:func:`_sample_lobe`)."""
    iax2, iay2 = np.exp(-2.0 * x[1]), np.exp(-2.0 * x[2])
    scale = np.exp(x[0] - x[1] - x[2])
    c, s = np.cos(x[3]), np.sin(x[3])
    k = -2.0 * (iax2 - iay2)
    cost = 0.0
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    g0 = g1 = g2 = g3 = 0.0
    for n in range(a.size):
        if not use[n]:
            continue
        f, u, v, pu, pv = _sample_lobe(a[n], b[n], g[n], c, s, iax2, iay2, scale)
        r = f - rho[n]
        cost += r * r
        if f != 0.0:
            j1, j2, j3 = f * (2.0 * pu - 1.0), f * (2.0 * pv - 1.0), f * k * u * v
            a00 += f * f
            a01 += f * j1
            a02 += f * j2
            a03 += f * j3
            a11 += j1 * j1
            a12 += j1 * j2
            a13 += j1 * j3
            a22 += j2 * j2
            a23 += j2 * j3
            a33 += j3 * j3
            g0 += f * r
            g1 += j1 * r
            g2 += j2 * r
            g3 += j3 * r
    jtj[0, 0], jtj[0, 1], jtj[0, 2], jtj[0, 3] = a00, a01, a02, a03
    jtj[1, 0], jtj[1, 1], jtj[1, 2], jtj[1, 3] = a01, a11, a12, a13
    jtj[2, 0], jtj[2, 1], jtj[2, 2], jtj[2, 3] = a02, a12, a22, a23
    jtj[3, 0], jtj[3, 1], jtj[3, 2], jtj[3, 3] = a03, a13, a23, a33
    jtr[0], jtr[1], jtr[2], jtr[3] = g0, g1, g2, g3
    return 0.5 * cost


@numba.njit(cache=True, nogil=True)
def _solve_spd(m, rhs, out):
    """out = m^-1 rhs for a small symmetric positive definite m by Cholesky (m overwritten); False if not."""
    n = rhs.size
    for j in range(n):
        d = m[j, j]
        for k in range(j):
            d -= m[j, k] * m[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        m[j, j] = d
        for i in range(j + 1, n):
            t = m[i, j]
            for k in range(j):
                t -= m[i, k] * m[j, k]
            m[i, j] = t / d
    for i in range(n):
        t = rhs[i]
        for k in range(i):
            t -= m[i, k] * out[k]
        out[i] = t / m[i, i]
    for i in range(n - 1, -1, -1):
        t = out[i]
        for k in range(i + 1, n):
            t -= m[k, i] * out[k]
        out[i] = t / m[i, i]
    return True


@numba.njit(cache=True, nogil=True)
def _damped_step(jtj, jtr, lam, damping, x, lo, hi, m, rhs, step):
    """The LM step (J^T J + lam diag(damping)) step = -J^T r with log alpha (x[1], x[2]) kept in [lo, hi]: an
    alpha on its bound and pushed outwards is held, one the step would carry across its bound stops there and
    the others are solved again with it fixed. False if the system is not positive definite."""
    fixed = np.zeros(4, np.bool_)
    fixed_step = np.zeros(4)
    for j in (1, 2):
        fixed[j] = (x[j] <= lo and jtr[j] > 0.0) or (x[j] >= hi and jtr[j] < 0.0)
    for _ in range(3):
        for i in range(4):
            if fixed[i]:
                for j in range(4):
                    m[i, j] = 0.0
                m[i, i], rhs[i] = 1.0, fixed_step[i]
                continue
            rhs[i] = -jtr[i]
            for j in range(4):
                if fixed[j]:
                    m[i, j] = 0.0
                    rhs[i] -= jtj[i, j] * fixed_step[j]
                else:
                    m[i, j] = jtj[i, j]
            m[i, i] += lam * damping[i]
        if not _solve_spd(m, rhs, step):
            return False
        crossed = False
        for j in (1, 2):
            if not fixed[j] and not lo <= x[j] + step[j] <= hi:
                fixed[j], crossed = True, True
                fixed_step[j] = min(max(x[j] + step[j], lo), hi) - x[j]
        if not crossed:
            break
    return True


@numba.njit(cache=True, nogil=True)
def _lm(x, a, b, g, rho, use, lo, hi, max_iterations, ftol, xtol):
    """LM from x (modified in place) for one point; returns (cost, converged). Every trial step (one
    evaluation of residual and J^T J) counts against ``max_iterations``."""
    jtj, jtr = np.empty((4, 4)), np.empty(4)
    jtj_new, jtr_new = np.empty((4, 4)), np.empty(4)
    m, rhs, step, x_new = np.empty((4, 4)), np.empty(4), np.empty(4), np.empty(4)
    cost = _normal_equations(x, a, b, g, rho, use, jtj, jtr)
    lam, nu = 1e-3, 2.0
    shape, damping = np.zeros(4), np.empty(4)
    for _ in range(max_iterations):
        if not cost > 0.0:
            return cost, True                      # an exact fit
        top = max(jtj[0, 0], jtj[1, 1], jtj[2, 2], jtj[3, 3])
        if not top > 0.0:
            return cost, True                      # the lobe vanishes on every sample: nothing to move
        # Marquardt's damping D: diag(J^T J), with, for the lobe's shape (log alphas, phi), the largest ratio to
        # (J^T J)_00 met so far (MINPACK keeps the largest column norms; as ratios D follows the lobe's amplitude,
        # so a point without signal, whose ks shrinks towards 0, is not held back by its first iterations' D)
        for j in range(1, 4):                      # (J^T J)_00 > 0: every column of J is the lobe times a factor
            shape[j] = max(shape[j], jtj[j, j] / jtj[0, 0])
        damping[0] = max(jtj[0, 0], DIAG_FLOOR * top)
        for j in range(1, 4):
            damping[j] = max(jtj[0, 0] * shape[j], DIAG_FLOOR * top)
        if not _damped_step(jtj, jtr, lam, damping, x, lo, hi, m, rhs, step):
            lam *= nu
            nu *= 2.0
            continue
        step_norm = x_norm = 0.0
        for j in range(4):
            x_new[j] = x[j] + step[j]
            if j == 1 or j == 2:
                x_new[j] = min(max(x_new[j], lo), hi)
            step[j] = x_new[j] - x[j]
            step_norm += step[j] * step[j]
            x_norm += x[j] * x[j]
        predicted = 0.0                            # -step.J^T r - step.J^T J.step / 2
        for i in range(4):
            t = 0.0
            for j in range(4):
                t += jtj[i, j] * step[j]
            predicted -= step[i] * (jtr[i] + 0.5 * t)
        small_step = np.sqrt(step_norm) <= xtol * (np.sqrt(x_norm) + xtol)
        cost_new = _normal_equations(x_new, a, b, g, rho, use, jtj_new, jtr_new)
        actual = cost - cost_new
        if actual > 0.0:
            gain = actual / predicted if predicted > 0.0 else 0.0
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            lam = max(lam, 1e-15)
            nu = 2.0
            small_change = actual <= ftol * cost and predicted <= ftol * cost
            x[:] = x_new
            jtj[:, :] = jtj_new
            jtr[:] = jtr_new
            cost = cost_new
            if small_change or small_step:
                return cost, True
        else:
            if small_step or 0.0 <= predicted <= ftol * cost:   # no descent left at this precision
                return cost, True
            lam *= nu
            nu *= 2.0
    return cost, False


@numba.njit(cache=True, nogil=True)
def _fit_tile(rho_s, wi, wo, use_in, starts, lo, hi, max_iterations, ftol, xtol, out):
    """:func:`fit_points`; out (6, P): ks, alpha_x, alpha_y, phi, cost, ok."""
    n = rho_s.shape[1]
    a, b, g, rho, use = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_)
    x, jac = np.empty(4), np.zeros((n, 4))
    for p in range(rho_s.shape[0]):
        out[0, p], out[1, p], out[2, p], out[3, p], out[4, p], out[5, p] = 0.0, 0.3, 0.3, 0.0, 0.0, 0.0
        used, positive = _prepare(rho_s[p], wi[p], wo[p], use_in[p], a, b, g, rho, use)
        if used < 5 or positive == 0:
            continue
        best = np.inf
        for k in range(starts.shape[0]):
            x[0], x[1], x[2], x[3] = 0.0, np.log(starts[k, 0]), np.log(starts[k, 1]), starts[k, 2]
            lobe = _lobe_jacobian(x, a, b, g, jac)     # ks = 1; 0 where not used
            num = den = 0.0
            for i in range(n):
                num += rho[i] * lobe[i]
                den += lobe[i] * lobe[i]
            x[0] = np.log(max(num / max(den, 1e-30), 1e-6))
            cost, converged = _lm(x, a, b, g, rho, use, lo, hi, max_iterations, ftol, xtol)
            if cost < best and np.isfinite(x).all():
                best = cost
                phi = x[3] % np.pi
                out[0, p], out[1, p], out[2, p] = np.exp(x[0]), np.exp(x[1]), np.exp(x[2])
                out[3, p], out[4, p], out[5, p] = phi if phi < np.pi else 0.0, cost, 1.0 if converged else 0.0


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
