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
    "smith_lambda",
    "masking_shadowing",
    "fresnel_conductor",
    "conductor_equivalent_eta",
    "CONDUCTORS",
    "rho_extended",
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
def _terms(wi, wo, kd, ks, phi_frame, kind):
    """What eq. 6 and its variants share: float64 inputs, h, c = |i.h| (computed symmetrically, so
    reciprocity holds bitwise), the checked NDF kind and the material frame (one cos / sin for the
    three directions)."""
    wi, wo, kd, ks = _f64(wi), _f64(wo), _f64(kd), _f64(ks)
    h = half_vector(wi, wo)
    c = 0.5 * (np.abs(_dot(wi, h)) + np.abs(_dot(wo, h)))
    return wi, wo, kd, ks, h, c, _check_kind(kind), _frame(phi_frame)


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
    wi, wo, kd, ks, h, c, kind, frame = _terms(wi, wo, kd, ks, phi_frame, kind)
    d = _ndf_local(_rotate(h, frame), alpha_u, alpha_v, kind)
    f = fresnel(c, eta)
    a_i = _projected_area_local(_rotate(wi, frame), alpha_u, alpha_v, kind)
    a_o = _projected_area_local(_rotate(wo, frame), alpha_u, alpha_v, kind)
    spec = d * f / (4.0 * (a_i * a_o))
    valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
    out = kd * (1.0 / np.pi) + ks * spec[..., None]
    return np.where(valid[..., None], out, 0.0)


# --------------------------------------------------------------------------
# truth outside eq. 6: the virtual rig's other materials (docs/decisions.md,
# "Truth outside eq. 6"). The pipeline fits eq. 6; these are what it meets.
# --------------------------------------------------------------------------
# Complex indices n + i k (relative to air) per linear RGB channel: the RGB
# table of conductors of the Yocto/GL renderer (yocto_shading.h,
# conductor_eta, entries "Cu" and "Au"), RGB reductions of measured spectral
# optical constants as renderers use them (the copper values are also the
# defaults of pbrt's "metal" material in Yocto/GL's pbrt loader). Normal-incidence reflectance
# ((n-1)^2+k^2)/((n+1)^2+k^2): copper (0.952, 0.620, 0.511), gold (0.967, 0.802, 0.324).
CONDUCTORS = {
    "copper": ((0.2004376970, 0.9240334304, 1.1022119527), (3.9129485033, 2.4528477015, 2.1421879552)),
    "gold": ((0.1431189557, 0.3749570432, 1.4424785571), (3.9831604247, 2.3857207478, 1.6032152899)),
}


def _excess_area_local(kl, alpha_u, alpha_v, kind):
    """|k.n| Lambda(k) = A(k) - |k.n| >= 0 of directions in the local frame, without cancellation.

    GGX:       A - c = q / (2 (sqrt(c^2 + q) + c)),  q = alpha_k^2 sin^2(theta_k)
    Beckmann:  A - c = sqrt(q) exp(-a^2) / (2 sqrt(pi)) - c erfc(a) / 2,  a = c / sqrt(q)
    (:func:`projected_area` minus c; Heitz 2014 eqs. 72 and 86 times c.)
    """
    from scipy.special import erfc
    au = _f64(alpha_u)
    av = _f64(alpha_v)
    c = np.abs(kl[..., 2])
    q = (au * kl[..., 0]) ** 2 + (av * kl[..., 1]) ** 2
    if kind == "ggx":
        den = np.sqrt(c * c + q) + c
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(den > 0.0, 0.5 * q / np.where(den > 0.0, den, 1.0), 0.0)
    sq = np.sqrt(q)
    pos = sq > 0.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        a = np.where(pos, c / np.where(pos, sq, 1.0), np.inf)
        tail = np.where(pos, sq * np.exp(-a * a) * (0.5 * _INV_SQRT_PI), 0.0)
    return np.maximum(tail - 0.5 * c * erfc(a), 0.0)


def smith_lambda(k, alpha_u, alpha_v, phi_frame=0.0, kind="ggx"):
    """Smith's Lambda(k) of the (anisotropic) GGX or Beckmann NDF (Heitz 2014, eqs. 72 and 86).

    GGX: Lambda = (-1 + sqrt(1 + alpha_k^2 tan^2 theta_k)) / 2;  Beckmann:
    Lambda = (erf(a) - 1)/2 + exp(-a^2)/(2 a sqrt(pi)), a = 1/(alpha_k tan theta_k);
    alpha_k^2 = alpha_u^2 cos^2 phi_k + alpha_v^2 sin^2 phi_k (local azimuth).
    Related to eq. 5 by A(k) = |k.n| (1 + Lambda(k)), so S(k) = G1(k) = 1/(1 + Lambda(k)).
    Lambda(n) = 0, Lambda -> inf at grazing (returned as inf for k.n = 0), |k.n| semantics below
    the horizon as :func:`projected_area`.
    """
    kl = to_local(k, phi_frame)
    e = _excess_area_local(kl, alpha_u, alpha_v, _check_kind(kind))
    c = np.abs(kl[..., 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(c > 0.0, e / np.where(c > 0.0, c, 1.0), np.inf)


def masking_shadowing(wi, wo, alpha_u, alpha_v, phi_frame=0.0, kind="ggx", correlated=True):
    """Smith's masking-shadowing term G2(i, o) (Heitz 2014, sec. 6).

    ``correlated=True``: the height-correlated form  G2 = 1 / (1 + Lambda(i) + Lambda(o))  (Heitz 2014
    eq. 99); ``False``: the separable form of eq. 5,  G2 = G1(i) G1(o) = S(i) S(o).  Computed with
    E(k) = |k.n| Lambda(k) as  G2 = c_i c_o / (c_i c_o + c_o E(i) + c_i E(o)), finite at grazing.
    Always G1(i) G1(o) <= G2_correlated <= min(G1(i), G1(o)), with equality when i or o is n.
    0 where i.n <= 0 or o.n <= 0.
    """
    kind = _check_kind(kind)
    frame = _frame(phi_frame)
    wi, wo = _f64(wi), _f64(wo)
    li, lo = _rotate(wi, frame), _rotate(wo, frame)
    ci, co = np.abs(li[..., 2]), np.abs(lo[..., 2])
    ei = _excess_area_local(li, alpha_u, alpha_v, kind)
    eo = _excess_area_local(lo, alpha_u, alpha_v, kind)
    if correlated:
        den = ci * co + co * ei + ci * eo
    else:
        den = (ci + ei) * (co + eo)
    valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0) & (den > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(valid, ci * co / np.where(valid, den, 1.0), 0.0)


def fresnel_conductor(cos_ih, n, k):
    """Exact unpolarised Fresnel reflectance of a conductor, complex index n + i k, from air.

    With c = |i.h|, s^2 = 1 - c^2 and (Born and Wolf; the form of PBRT v3's FrConductor)

        t0 = n^2 - k^2 - s^2,   a^2 + b^2 = sqrt(t0^2 + 4 n^2 k^2),   a = sqrt((a^2 + b^2 + t0) / 2)
        Rs = (a^2 + b^2 - 2 a c + c^2) / (a^2 + b^2 + 2 a c + c^2)
        Rp = Rs (c^2 (a^2 + b^2) - 2 a c s^2 + s^4) / (c^2 (a^2 + b^2) + 2 a c s^2 + s^4)
        F  = (Rs + Rp) / 2

    (Rp's usual sin(theta) tan(theta) form multiplied through by c^2, so c = 0 needs no tan).
    F(c = 1) = ((n - 1)^2 + k^2) / ((n + 1)^2 + k^2), F -> 1 at grazing (c -> 0).
    ``cos_ih`` broadcasts against ``n[..., 0]``; ``n``, ``k`` are (..., 3) per RGB channel (any
    trailing size); the result has the broadcast shape of ``cos_ih[..., None]`` and ``n``.
    """
    c = np.clip(np.abs(_f64(cos_ih)), 0.0, 1.0)[..., None]
    n, k = _f64(n), _f64(k)
    s2 = 1.0 - c * c
    t0 = n * n - k * k - s2
    ab = np.sqrt(t0 * t0 + 4.0 * n * n * k * k)
    a = np.sqrt(np.maximum(0.5 * (ab + t0), 0.0))
    c2 = c * c
    rs_den = ab + 2.0 * a * c + c2
    rp_num = c2 * ab - 2.0 * a * c * s2 + s2 * s2
    rp_den = c2 * ab + 2.0 * a * c * s2 + s2 * s2
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = np.where(rs_den > 0.0, (ab - 2.0 * a * c + c2) / np.where(rs_den > 0.0, rs_den, 1.0), 1.0)
        rp = rs * np.where(rp_den > 0.0, rp_num / np.where(rp_den > 0.0, rp_den, 1.0), 1.0)
    return np.clip(0.5 * (rs + rp), 0.0, 1.0)


def conductor_equivalent_eta(n, k):
    """The dielectric eta with the conductor's channel-mean normal-incidence reflectance F0:
    eta = (1 + sqrt(F0)) / (1 - sqrt(F0)) (eq. 3 at c = 1 inverted). A placeholder for the
    scalar eta map of a conductor region (its true Fresnel is :func:`fresnel_conductor`)."""
    n, k = _f64(n), _f64(k)
    f0 = np.mean(((n - 1.0) ** 2 + k * k) / ((n + 1.0) ** 2 + k * k), axis=-1)
    r = np.sqrt(np.clip(f0, 0.0, 1.0 - 1e-12))
    return (1.0 + r) / (1.0 - r)


def rho_extended(wi, wo, kd, ks, eta, alpha_u, alpha_v, phi_frame=0.0, kind="ggx", *,
                 correlated=None, conductor=None, coat=None):
    """Eq. 6 with the virtual rig's departures from it, per point, shape ``(..., 3)``, in 1/sr.

    Base lobe (eq. 6 with two options)::

        rho_b = kd/pi + ks * D(h) F G2 / (4 (i.n)(o.n))

    * ``correlated`` (bool, ``(...)``): G2 is the height-correlated Smith term
      1/(1 + Lambda(i) + Lambda(o)) (Heitz 2014 eq. 99) where True, eq. 5's S(i) S(o) elsewhere
      (evaluated as in :func:`rho`, 1/(4 A(i) A(o))).
    * ``conductor`` (complex, ``(..., 3)``): F is the exact conductor Fresnel
      :func:`fresnel_conductor` with n + i k per RGB channel where the row is non-zero, eq. 3 with
      ``eta`` where it is all zero. ``ks`` still multiplies (1 for a bare metal).

    Clear coat, ``coat`` = ``(..., 3)`` rows (eta_c, alpha_c, w), w in [0, 1] (w = 0: no coat)::

        rho = w D_c(h) F(|i.h|, eta_c) / (4 A_c(i) A_c(o))
              + (1 - w F(i.n, eta_c)) (1 - w F(o.n, eta_c)) rho_b

    a white isotropic GGX specular lobe (alpha_c, eq. 5 shadowing) of the coat's dielectric
    surface, over the base attenuated by the coat's Fresnel transmission in and out at the
    macro normal (no refraction of the base lobe, no inter-reflection: a simple, reciprocal,
    energy-bounded layer). Reciprocal and non-negative in every case; 0 (all channels) where
    i.n <= 0 or o.n <= 0. With every option off it equals :func:`rho` bit for bit.
    """
    wi, wo, kd, ks, h, c, kind, frame = _terms(wi, wo, kd, ks, phi_frame, kind)
    li, lo = _rotate(wi, frame), _rotate(wo, frame)
    d = _ndf_local(_rotate(h, frame), alpha_u, alpha_v, kind)
    a_i = _projected_area_local(li, alpha_u, alpha_v, kind)
    a_o = _projected_area_local(lo, alpha_u, alpha_v, kind)
    den = 4.0 * (a_i * a_o)                     # 4 (i.n)(o.n) / (S(i) S(o)), eq. 5 (as in rho)
    if correlated is not None:
        ci, co = np.abs(li[..., 2]), np.abs(lo[..., 2])
        corr = ci * co + co * _excess_area_local(li, alpha_u, alpha_v, kind) \
            + ci * _excess_area_local(lo, alpha_u, alpha_v, kind)
        corr = np.maximum(corr, np.finfo(np.float64).tiny)   # both directions at the horizon: no Inf
        den = np.where(np.asarray(correlated, bool), 4.0 * corr, den)
    f = fresnel(c, eta)[..., None]
    if conductor is not None:
        cond = np.asarray(conductor, dtype=np.complex128)
        metal = np.any(cond != 0, axis=-1)
        f = np.where(metal[..., None], fresnel_conductor(c, cond.real, cond.imag), f)
    spec = d[..., None] * f / den[..., None]   # the order of rho's d * f / (4 A A): equal bits
    out = kd * (1.0 / np.pi) + ks * spec
    if coat is not None:
        coat = _f64(coat)
        eta_c, alpha_c, w = coat[..., 0], coat[..., 1], coat[..., 2]
        on = w > 0
        alpha_c = np.where(on, alpha_c, 1.0)
        dc = _ndf_local(_rotate(h, frame), alpha_c, alpha_c, "ggx")
        ac_i = _projected_area_local(li, alpha_c, alpha_c, "ggx")
        ac_o = _projected_area_local(lo, alpha_c, alpha_c, "ggx")
        eta_c = np.where(on, eta_c, 1.0)
        lobe = w * dc * fresnel(c, eta_c) / (4.0 * (ac_i * ac_o))
        t_i = 1.0 - w * fresnel(wi[..., 2], eta_c)
        t_o = 1.0 - w * fresnel(wo[..., 2], eta_c)
        out = out * (t_i * t_o)[..., None] + lobe[..., None]
    valid = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
    return np.where(valid[..., None], out, 0.0)
