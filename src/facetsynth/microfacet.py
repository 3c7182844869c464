"""Microfacet SVBRDF model of Wang et al. 2008, section 3 (eqs. 2-6).

    rho(x, i, o) = kd/pi + ks * D(h) S(i) S(o) F(i, o) / (4 (i.n)(o.n))      (eq. 6)

with the unpolarised Cook-Torrance Fresnel term F (eq. 3), a normalised
microfacet normal distribution D,

    integral over {h.n > 0} of (n.h) D(h) dw_h = 1,

and the directional shadowing term derived from D (eq. 5, after Ashikhmin et
al. 2000)

    S(k) = (k.n) / A(k),   A(k) = integral over {h.n > 0, h.k > 0} of (h.k) D(h) dw_h.

A(k) is the projected area of the microsurface seen from k.  With the
normalisation above, eq. 5 is exactly Smith's uncorrelated masking function
G1 (Heitz 2014: A(k) = cos(theta_k) (1 + Lambda(k))), so GGX and Beckmann
have closed forms (:func:`projected_area`); any other (e.g. tabulated) NDF
goes through the quadrature :func:`projected_area_numerical`.

Conventions
-----------
* Directions are unit 3-vectors, arrays of shape ``(..., 3)``, in the
  sample-plane frame: normal n = +z, azimuth phi measured from +x towards +y.
* ``phi_frame`` is the azimuth of the material's local u axis (thread / brush
  direction); ``alpha_u`` is the roughness along u, ``alpha_v`` along v.
* All scalar parameters broadcast against the leading ``...`` dimensions.
  Angles in radians.  BRDF values in 1/sr, without the cosine factor.
* Inputs may be float32 or float64; everything is computed and returned in
  float64.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

__all__ = [
    "half_vector",
    "to_local",
    "ndf",
    "projected_area",
    "shadowing",
    "projected_area_numerical",
    "ndf_normalisation_numerical",
    "fresnel",
    "rho",
]

_KINDS = ("ggx", "beckmann")
_INV_SQRT_PI = 1.0 / np.sqrt(np.pi)

# Quadrature layout of projected_area_numerical: theta panels with
# breakpoints 0, _THETA_GRADE_MIN * 2**j (j = 0, 1, ...) and pi/2.
_THETA_GRADE_MIN = 2.5e-4
# Gauss-Legendre order of the equal phi panels.
_PHI_ORDER = 8


def _f64(x):
    return np.asarray(x, dtype=np.float64)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _check_kind(kind: str) -> str:
    k = str(kind).lower()
    if k not in _KINDS:
        raise ValueError(f"unknown NDF kind {kind!r}; expected one of {_KINDS}")
    return k


# --------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------
def half_vector(wi, wo):
    """Half-angle vector h = (i + o) / |i + o| of eq. 2.

    Returns a unit vector of shape ``broadcast(wi, wo)``.  Where i + o vanishes
    (i = -o, h undefined) the surface normal n = (0, 0, 1) is returned; the
    BRDF is zero there anyway because one of the two directions lies on or
    below the horizon.  The sum is symmetric, so ``half_vector(a, b)`` and
    ``half_vector(b, a)`` are bitwise identical.
    """
    s = _f64(wi) + _f64(wo)
    ss = _dot(s, s)
    ok = ss > np.finfo(np.float64).tiny
    inv = 1.0 / np.sqrt(np.where(ok, ss, 1.0))
    n = np.array([0.0, 0.0, 1.0])
    return np.where(ok[..., None], s * inv[..., None], n)


def to_local(v, phi_frame):
    """Rotate directions about +z by ``-phi_frame`` (section 3 frame convention).

    The result is expressed in the material's local frame (u, v, n) whose u
    axis lies at azimuth ``phi_frame`` in the sample plane, so a direction at
    azimuth ``phi`` ends up at local azimuth ``phi - phi_frame``.  The z
    component is unchanged.  ``phi_frame`` broadcasts against ``v[..., 0]``.
    """
    return _rotate(v, _frame(phi_frame))


def _frame(phi_frame):
    """(cos, sin) of the frame azimuth: computed once where several directions go to one frame."""
    p = _f64(phi_frame)
    return np.cos(p), np.sin(p)


def _rotate(v, frame):
    v = _f64(v)
    c, s = frame
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    xl = c * x + s * y
    yl = c * y - s * x
    xl, yl, z = np.broadcast_arrays(xl, yl, z)
    return np.stack([xl, yl, z], axis=-1)


# --------------------------------------------------------------------------
# normal distribution function
# --------------------------------------------------------------------------
def ndf(h, alpha_u, alpha_v, phi_frame=0.0, kind="ggx"):
    """Anisotropic microfacet NDF D(h) (the D of eqs. 2, 5 and 6).

    ``kind="ggx"`` (Trowbridge-Reitz)::

        D = 1 / (pi au av (hu^2/au^2 + hv^2/av^2 + hz^2)^2)

    ``kind="beckmann"``::

        D = exp(-(hu^2/au^2 + hv^2/av^2) / hz^2) / (pi au av hz^4)

    where (hu, hv, hz) = ``to_local(h, phi_frame)``.  Both are normalised as
    the paper requires: integral over the upper hemisphere of (n.h) D dw = 1.
    D = 0 for h.n <= 0.  Beckmann is evaluated in the log domain, so it is
    finite (and underflows to 0) as h.n -> 0.  alphas must be > 0.
    """
    return _ndf_local(to_local(h, phi_frame), alpha_u, alpha_v, _check_kind(kind))


def _ndf_local(hl, alpha_u, alpha_v, kind):
    """:func:`ndf` of half vectors already in the local frame."""
    au = _f64(alpha_u)
    av = _f64(alpha_v)
    hx, hy, hz = hl[..., 0], hl[..., 1], hl[..., 2]
    up = hz > 0.0
    hz_s = np.where(up, hz, 1.0)
    q = (hx / au) ** 2 + (hy / av) ** 2  # = tan^2(theta_h) / alpha(phi_h)^2 * hz^2
    with np.errstate(over="ignore", divide="ignore", invalid="ignore", under="ignore"):
        if kind == "ggx":
            den = q + hz_s * hz_s
            d = 1.0 / (np.pi * au * av * den * den)
        else:
            logd = -q / (hz_s * hz_s) - np.log(np.pi * au * av) - 4.0 * np.log(hz_s)
            d = np.exp(logd)
    return np.where(up, d, 0.0)


# --------------------------------------------------------------------------
# shadowing (eq. 5)
# --------------------------------------------------------------------------
def projected_area(k, alpha_u, alpha_v, phi_frame=0.0, kind="ggx"):
    """Projected microsurface area A(k), the denominator of eq. 5, in closed form.

    With c = |k.n| and alpha_k^2 sin^2(theta_k) = au^2 ku^2 + av^2 kv^2 (local
    frame at azimuth ``phi_frame``):

    * GGX:       A = (c + sqrt(c^2 + alpha_k^2 sin^2 theta_k)) / 2
    * Beckmann:  A = c (1 + Lambda),  Lambda = (erf(a) - 1)/2 + exp(-a^2)/(2 a sqrt(pi)),
      a = c / (alpha_k sin theta_k), evaluated as
      A = c (1 + erf(a))/2 + alpha_k sin(theta_k) exp(-a^2) / (2 sqrt(pi)).

    Both forms are sums of non-negative terms (no cancellation), equal 1 at
    k = n and stay finite and strictly positive at grazing incidence, where
    A -> alpha_k / 2 (GGX) or alpha_k / (2 sqrt(pi)) (Beckmann).

    Below the horizon (k.n < 0) we use |k.n| semantics: A(k) is the value at
    the mirrored direction (kx, ky, |kz|), which is positive and continuous
    across the horizon.  (The literal integral of eq. 5 for a downward k
    would be the smaller area c * Lambda, which vanishes at k = -n.)  S and
    rho are defined to be 0 there in any case.
    """
    return _projected_area_local(to_local(k, phi_frame), alpha_u, alpha_v, _check_kind(kind))


def _projected_area_local(kl, alpha_u, alpha_v, kind):
    """:func:`projected_area` of directions already in the local frame."""
    au = _f64(alpha_u)
    av = _f64(alpha_v)
    c = np.abs(kl[..., 2])
    q = (au * kl[..., 0]) ** 2 + (av * kl[..., 1]) ** 2  # alpha_k^2 sin^2(theta_k)
    if kind == "ggx":
        return 0.5 * (c + np.sqrt(c * c + q))
    sq = np.sqrt(q)
    pos = sq > 0.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        a = np.where(pos, c / np.where(pos, sq, 1.0), np.inf)
        tail = np.where(pos, sq * np.exp(-a * a) * (0.5 * _INV_SQRT_PI), 0.0)
    return 0.5 * c * (1.0 + erf(a)) + tail


def shadowing(k, alpha_u, alpha_v, phi_frame=0.0, kind="ggx"):
    """Directional shadowing term S(k) = max(k.n, 0) / A(k) of eq. 5.

    Uses the closed-form :func:`projected_area` (equal to Smith's G1).
    S(n) = 1, S -> 0 at grazing, S = 0 for k.n <= 0.
    """
    kz = _f64(k)[..., 2]
    a = projected_area(k, alpha_u, alpha_v, phi_frame, kind)
    return np.maximum(kz, 0.0) / a


# --------------------------------------------------------------------------
# eq. 5 by quadrature, for any NDF
# --------------------------------------------------------------------------
def _gauss_legendre(n):
    x, w = np.polynomial.legendre.leggauss(int(n))
    return x, w


def _composite_gauss_legendre(n, order):
    """Nodes/weights on [-1, 1]: max(1, n // order) equal panels of ``order`` GL nodes."""
    panels = max(1, int(n) // int(order))
    x, w = _gauss_legendre(order)
    edges = np.linspace(-1.0, 1.0, panels + 1)
    half = 0.5 * (edges[1:] - edges[:-1])
    mid = 0.5 * (edges[1:] + edges[:-1])
    return (mid[:, None] + half[:, None] * x).ravel(), (half[:, None] * w).ravel()


def _theta_breakpoints():
    grade = _THETA_GRADE_MIN * 2.0 ** np.arange(64)
    grade = grade[grade < 0.5 * np.pi]
    return np.concatenate([[0.0], grade, [0.5 * np.pi]])


def _projected_area_block(k, ndf_fn, n_theta, n_phi):
    """Quadrature of eq. 5 for a flat block of directions k, shape (M, 3)."""
    kx, ky = k[:, 0], k[:, 1]
    kz = np.abs(k[:, 2])
    rxy = np.hypot(kx, ky)
    norm = np.sqrt(rxy * rxy + kz * kz)
    sin_tk = rxy / norm
    cos_tk = kz / norm
    phi_k = np.arctan2(ky, kx)

    # theta breakpoints: fixed graded set plus the per-k split t*.
    fixed = _theta_breakpoints()
    t_star = np.arctan2(cos_tk, sin_tk)  # pi/2 - theta_k, in [0, pi/2]
    bps = np.sort(
        np.concatenate([np.broadcast_to(fixed, (k.shape[0], fixed.size)), t_star[:, None]], axis=1),
        axis=1,
    )
    lo, hi = bps[:, :-1], bps[:, 1:]  # (M, P)
    xt, wt = _gauss_legendre(n_theta)
    u, wu = 0.5 * (xt + 1.0), 0.5 * wt  # Gauss-Legendre on [0, 1]
    width = (hi - lo)[..., None]
    # Just above t*, the ring integral behaves like (t - t*)^(3/2); on the
    # panel starting at t* use t = lo + width u^2, which makes it smooth.
    after = (lo == t_star[:, None])[..., None]
    t = lo[..., None] + width * np.where(after, u * u, u)  # (M, P, n_theta)
    w_t = width * np.where(after, 2.0 * u * wu, wu)
    t = t.reshape(k.shape[0], -1)  # (M, T)
    w_t = w_t.reshape(k.shape[0], -1)
    st, ct = np.sin(t), np.cos(t)

    # phi arc where h.k > 0 on the ring theta_h = t: |p - phi_k| < half_arc.
    num = ct * cos_tk[:, None]
    den = st * sin_tk[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(den > 0.0, -num / np.where(den > 0.0, den, 1.0), -np.inf)
    half_arc = np.arccos(np.clip(x, -1.0, 1.0))  # (M, T), in [0, pi]

    xp, wp = _composite_gauss_legendre(n_phi, _PHI_ORDER)
    p = phi_k[:, None, None] + half_arc[..., None] * xp  # (M, T, n_phi)
    w = (w_t * st * half_arc)[..., None] * wp  # sin(t) dt dphi

    st3 = st[..., None]
    h = np.stack([st3 * np.cos(p), st3 * np.sin(p), np.broadcast_to(ct[..., None], p.shape)], axis=-1)
    kk = np.stack([kx / norm, ky / norm, cos_tk], axis=-1)  # mirrored, unit
    hk = np.maximum(_dot(h, kk[:, None, None, :]), 0.0)
    d = _f64(ndf_fn(h))
    return np.sum(w * hk * d, axis=(-2, -1))


def projected_area_numerical(k, ndf_fn, n_theta=16, n_phi=256):
    """Eq. 5's projected area A(k) by deterministic quadrature, for ANY NDF.

    A(k) = integral over {h.n > 0, h.k > 0} of (h.k) D(h) dw_h, with D given
    as a vectorised callable ``ndf_fn(h) -> D`` for ONE distribution (h of
    shape ``(..., 3)``, arbitrary leading dims; D must be 0 for h.n <= 0 or
    is only ever called with h.n > 0).  Below the horizon, k is mirrored to
    (kx, ky, |kz|) as in :func:`projected_area`.

    Quadrature (spherical coordinates about n, h = (sin t cos p, sin t sin p, cos t)):

    * theta: composite Gauss-Legendre, ``n_theta`` nodes per panel, on
      panels graded geometrically towards the pole (breakpoints 0,
      2.5e-4 * 2^j, pi/2: 14 panels) so lobes as sharp as alpha = 0.005
      are resolved, plus one extra breakpoint at t* = pi/2 - theta_k, where
      the ring {theta_h = t} starts to be cut by the great circle h.k = 0.
    * phi: on each ring only the arc where h.k > 0,
      |p - phi_k| < arccos(-cot(t) cot(theta_k)), is integrated, with
      ``n_phi`` nodes (equal panels of 8-point Gauss-Legendre).

    Both boundaries of the integration domain (h.n = 0 and h.k = 0) are
    therefore cell boundaries; on the theta panel starting at t*, where the
    ring integral behaves like (t - t*)^(3/2), the substitution
    t = t* + width u^2 removes the singularity.  The integrand is then smooth
    on every cell and the rule converges spectrally.  Measured relative
    error with the defaults (n_theta=16, n_phi=256; 15 x 16 x 256 ~ 61k NDF
    evaluations per k), GGX and Beckmann, alpha in [0.005, 1], theta_k in
    [0, 90] deg: <= 2e-7 for anisotropy ratio alpha_max/alpha_min <= 10
    (1e-15 for isotropic sharp lobes), ~3e-4 for ratio 20.  Sharply
    anisotropic lobes are narrow in phi: use n_phi >= ~25 x ratio
    (n_phi=512 gives <= 5e-6 at ratio 20, 3e-5 at 30).

    Work is done in blocks of directions to bound memory (~2e6 nodes per
    block).  Returns an array of shape ``k.shape[:-1]``.
    """
    k = _f64(k)
    shape = k.shape[:-1]
    kf = k.reshape(-1, 3)
    nodes_per_k = (_theta_breakpoints().size) * int(n_theta) * max(1, int(n_phi) // _PHI_ORDER) * _PHI_ORDER
    block = max(1, 2_000_000 // nodes_per_k)
    out = np.concatenate(
        [_projected_area_block(kf[s : s + block], ndf_fn, n_theta, n_phi) for s in range(0, kf.shape[0], block)]
        or [np.zeros(0)]
    )
    return out.reshape(shape)


def ndf_normalisation_numerical(ndf_fn, n_theta=16, n_phi=256):
    """Integral over the upper hemisphere of (n.h) D(h) dw_h (section 3; should be 1).

    Same quadrature as :func:`projected_area_numerical` (this is A(n)).
    Returns a float.
    """
    return float(projected_area_numerical(np.array([0.0, 0.0, 1.0]), ndf_fn, n_theta, n_phi))


# --------------------------------------------------------------------------
# Fresnel (eq. 3)
# --------------------------------------------------------------------------
def fresnel(cos_ih, eta):
    """Unpolarised dielectric Fresnel reflectance of eq. 3 (Cook and Torrance 1981).

        F = (g - c)^2 / (2 (g + c)^2) * (1 + (c (g + c) - 1)^2 / (c (g - c) + 1)^2),
        g^2 = eta^2 + c^2 - 1,  c = |i.h|.

    g - c is evaluated as (eta^2 - 1) / (g + c) to avoid cancellation, so
    F -> 0 smoothly as eta -> 1 (F = 0 at eta = 1 for every c, including
    c = 0, where the eq. 3 limit is otherwise ambiguous), F -> 1 as c -> 0
    for eta > 1, and F(c = 1) = ((eta - 1)/(eta + 1))^2.  For eta < 1 and
    g^2 <= 0 (total internal reflection) F = 1.  Never NaN for finite input.
    """
    c = np.clip(np.abs(_f64(cos_ih)), 0.0, 1.0)
    eta = _f64(eta)
    d = (eta - 1.0) * (eta + 1.0)  # eta^2 - 1
    g2 = d + c * c
    tir = g2 < 0.0
    g = np.sqrt(np.where(tir, 0.0, g2))
    s = g + c
    pos = s > 0.0
    s_safe = np.where(pos, s, 1.0)
    gm = d / s_safe  # g - c
    r = np.where(pos, gm / s_safe, 0.0)  # (g - c)/(g + c)
    t = (c * s - 1.0) / (c * gm + 1.0)  # c*gm + 1 = c g - c^2 + 1 >= c g >= 0, > 0 unless TIR
    with np.errstate(invalid="ignore", divide="ignore"):
        f = 0.5 * r * r * (1.0 + t * t)
    return np.where(tir, 1.0, np.where(pos, np.minimum(f, 1.0), 0.0))


# --------------------------------------------------------------------------
# full model (eq. 6)
# --------------------------------------------------------------------------
def rho(wi, wo, kd, ks, eta, alpha_u, alpha_v, phi_frame=0.0, kind="ggx"):
    """Full SVBRDF of eq. 6 (eqs. 1-5 combined), shape ``(..., 3)``, in 1/sr.

        rho = kd/pi + ks * D(h) S(i) S(o) F / (4 (i.n)(o.n))

    evaluated in the equivalent, stable form (S(k)/(k.n) = 1/A(k), eq. 5)

        rho = kd/pi + ks * D(h) F(|i.h|, eta) / (4 A(i) A(o)),

    which has no 0/0 at grazing.  rho = 0 (all channels, diffuse included)
    where i.n <= 0 or o.n <= 0.  ``kd`` and ``ks`` are RGB arrays ``(..., 3)``;
    ``eta``, ``alpha_u``, ``alpha_v``, ``phi_frame`` broadcast over ``...``.
    Reciprocity rho(i, o) = rho(o, i) holds bitwise (h and c = |i.h| are
    computed symmetrically).
    """
    wi = _f64(wi)
    wo = _f64(wo)
    kd = _f64(kd)
    ks = _f64(ks)
    h = half_vector(wi, wo)
    c = 0.5 * (np.abs(_dot(wi, h)) + np.abs(_dot(wo, h)))
    kind = _check_kind(kind)
    frame = _frame(phi_frame)                      # one cos / sin for the three directions
    d = _ndf_local(_rotate(h, frame), alpha_u, alpha_v, kind)
    f = fresnel(c, eta)
    a_i = _projected_area_local(_rotate(wi, frame), alpha_u, alpha_v, kind)
    a_o = _projected_area_local(_rotate(wo, frame), alpha_u, alpha_v, kind)
    spec = d * f / (4.0 * (a_i * a_o))
    valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
    out = kd * (1.0 / np.pi) + ks * spec[..., None]
    return np.where(valid[..., None], out, 0.0)
