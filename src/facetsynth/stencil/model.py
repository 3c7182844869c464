"""The adaptive highlight-stencil BRDF model of paper 000 (Filip et al.), sec. 3.

Per anisotropy mode j (ordered from the top/dominant mode, j = 0, to the
bottom one):

* stencil (eq. 2)       F_j = 1 - |H . U(phi_a)|,   U(phi_a) = [sin phi_a, cos phi_a, 0]
* elevation (eq. 3)     E_j = F_j (a_j + b_j / (cos th_i cos th_v))
* shape (eq. 4)         L_j = kd_j + ks_j E_j^alpha_j
* colour (eq. 5)        T_j = m_j max(0, L_j)
* support mask          M_j = smoothstep(w_j - d_w, w_j + d_w, F_j),  d_w = dw_ratio * w_j
* merging (eqs. 7-9, generalised to n modes, bottom-up)
      P_n = r m_bg max(0, a_r + b_r / (cos th_i cos th_v))  (background; eq. 3's elevation
                                                             scaling on eq. 7's r, a_r + b_r = 1)
      P_j = (1 - M_j) P_{j+1} + M_j [(1 - beta_j) T_j + beta_j T_{j+1}]
  (beta_j blends mode j with the mode below; the bottom mode has no beta.)
* specular (eq. 10)     S = max(1, l_1 + l_2),  l = k H_z^alpha_s (a_s + (b_s + f_s (1 - k.h)^5) / cp) [/ k.h]
                        B_S = P_0 S                              (eq. 10, m_s = None)
                        B_S = P_0 + (S - 1) Y(P_0) (l_1 m_s + l_2 m_s2) / (l_1 + l_2)
                                                                 (coloured highlights)
  with cp = cos th_i cos th_v, k.h = cos of the half angle (wi . H), Y the
  Rec. 709 luminance; the division by k.h only with ``jacobian``, and with
  ``stencil_highlight`` both lobes are multiplied by F_0^alpha_0, the
  dominant mode's stencil and exponent (eqs. 2, 4), so the highlight follows
  that mode's axis.  The defaults (k2 = 0, f_s = f_s2 = 0, jacobian and
  stencil_highlight False, m_s = None, a_r = 1, b_r = 0) are the paper's
  equations; the second lobe, the Schlick term f_s (1 - k.h)^5 (Schlick
  1994, the Fresnel factor of a microfacet lobe), the Jacobian 1 / k.h (the
  half-vector density's, as in the lobes of Kurt et al. and
  Ashikhmin-Shirley), the stencil-shaped highlight, the highlight colours
  and the background's elevation scaling are the fit's extensions
  (docs/stencil.md: what each costs).
* retro-reflection (sec. 5.1): a mode with ``retro=True`` computes its H from
  (-wi_x, -wi_y, wi_z), i.e. phi_i + pi.

Directions are unit ``(..., 3)`` vectors with normal +z; the model is zero
when either direction is at or below the horizon.  The cosine product in
eq. 3 is floored at ``COS_FLOOR**2`` so grazing angles stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Tuple

import numpy as np

from .grid import LUMA

__all__ = [
    "COS_FLOOR", "Mode", "StencilModel", "half_vector", "axis_vector", "stencil",
    "elevation_scale", "mode_luminance", "mode_colour", "support_mask", "merge_modes",
    "NO_LOBE", "specular_lobe", "specular_scale", "specular_factor", "lobes", "highlight_shares", "highlight_basis",
    "apply_shares", "apply_specular",
    "background", "evaluate", "evaluate_utia",
]

COS_FLOOR = np.cos(np.deg2rad(85.0))
# an absent specular lobe (k, alpha_s, a_s, b_s, f_s)
NO_LOBE = (0.0, 1.0, 1.0, 0.0, 0.0)


@dataclass(frozen=True)
class Mode:
    """One anisotropy mode (paper 000, sec. 3.2: phi_a, w, a, b, 3 x m, kd, ks, alpha)."""
    phi_a: float              # radians, axis U = [sin phi_a, cos phi_a, 0]
    w: float                  # support width threshold on F (0 wide .. 1 narrow)
    a: float
    b: float
    kd: float
    ks: float
    alpha: float
    m: Tuple[float, float, float]
    retro: bool = False


@dataclass(frozen=True)
class StencilModel:
    """All parameters of the model (paper 000, Tab. 1, plus the stated extras)."""
    modes: Tuple[Mode, ...]
    beta: Tuple[float, ...]               # len(modes) - 1 values (0 if < 2 modes)
    r: float                              # background scale, eq. 7
    m_bg: Tuple[float, float, float]      # background colour basis (m of the bottom mode)
    k: float                              # specular, eq. 10
    alpha_s: float
    a_s: float = 1.0                      # specular elevation scaling (paper: a_0, b_0; fitted since issue 18)
    b_s: float = 0.0
    dw_ratio: float = 0.15                # d_w = dw_ratio * w (paper: 0.1-0.2)
    k2: float = 0.0                       # second (broad) specular lobe of eq. 10
    alpha_s2: float = 1.0
    a_s2: float = 1.0
    b_s2: float = 0.0
    m_s: Optional[Tuple[float, float, float]] = None   # highlight colours of the lobes; None: eq. 10
    m_s2: Optional[Tuple[float, float, float]] = None
    a_r: float = 1.0                      # background elevation scaling (eq. 3 form on r)
    b_r: float = 0.0
    f_s: float = 0.0                      # Schlick term of each lobe (0: eq. 10)
    f_s2: float = 0.0
    jacobian: bool = False                # lobes divided by k.h (False: eq. 10)
    stencil_highlight: bool = False       # lobes times F_0^alpha_0 of the dominant mode (False: eq. 10)
    meta: dict = field(default_factory=dict, compare=False)

    def with_modes(self, modes):
        return replace(self, modes=tuple(modes))


def half_vector(wi, wo, retro=False):
    """H = (wi + wo)/|wi + wo|; with ``retro`` wi is first rotated by pi about the normal."""
    wi = np.asarray(wi, float)
    if retro:
        wi = wi * np.array([-1.0, -1.0, 1.0])
    h = wi + np.asarray(wo, float)
    n = np.linalg.norm(h, axis=-1, keepdims=True)
    return np.where(n > 1e-12, h / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0]))


def axis_vector(phi_a):
    """U(phi_a) = [sin phi_a, cos phi_a, 0] (eq. 2)."""
    phi_a = np.asarray(phi_a, float)
    return np.stack([np.sin(phi_a), np.cos(phi_a), np.zeros_like(phi_a)], -1)


def stencil(h, phi_a):
    """Highlight stencil F = 1 - |H . U(phi_a)| (eq. 2)."""
    u = axis_vector(phi_a)
    return 1.0 - np.abs(np.sum(np.asarray(h, float) * u, -1))


def _cos_product(wi, wo):
    ci = np.maximum(np.asarray(wi, float)[..., 2], COS_FLOOR)
    co = np.maximum(np.asarray(wo, float)[..., 2], COS_FLOOR)
    return ci * co


def elevation_scale(a, b, cos_product):
    """a + b / (cos th_i cos th_v) (eq. 3), cos product floored at COS_FLOOR**2."""
    return a + b / np.maximum(cos_product, COS_FLOOR ** 2)


def mode_luminance(F, scale, kd, ks, alpha):
    """L = kd + ks E^alpha with E = F * scale (eqs. 3-4); E clamped to >= 0 before the power."""
    E = np.maximum(F * scale, 0.0)
    return kd + ks * np.power(E, alpha)


def mode_colour(L, m):
    """T_i = m_i max(0, L) (eq. 5); returns ``(..., 3)``."""
    return np.maximum(L, 0.0)[..., None] * np.asarray(m, float)


def support_mask(F, w, dw_ratio=0.15):
    """Smooth support mask M: 0 for F <= w - d_w, 1 for F >= w + d_w, smoothstep between.

    Paper 000 writes the two cases the other way round, but its smoothstep
    f(x) = y^2 (3 - 2y), y = (x - w + d_w)/(2 d_w), rises with x = F and the
    text says the mask surrounds the highlight centres (F = 1) with w = 1
    "extremely narrow": the orientation used here.  d_w = 0 gives a step.
    """
    dw = dw_ratio * w
    if dw <= 0:
        return (np.asarray(F) >= w).astype(float)
    y = np.clip((np.asarray(F, float) - w + dw) / (2 * dw), 0.0, 1.0)
    return y * y * (3.0 - 2.0 * y)


def merge_modes(T, M, beta, background):
    """Eqs. 7-9 generalised: T ``(n, ..., 3)``, M ``(n, ...)``, beta ``(n-1,)``, background ``(3,)`` or ``(..., 3)``.

    Bottom-up: P = background; for j = n-1 .. 0:
    P = (1 - M_j) P + M_j [(1 - beta_j) T_j + beta_j T_{j+1}]  (beta_{n-1} = 0).
    """
    bg = np.asarray(background, float)
    n = len(T)
    if n == 0:
        return bg
    P = bg
    for j in range(n - 1, -1, -1):  # loop over modes (n <= 4), not samples
        bj = beta[j] if j < n - 1 else 0.0
        top = T[j] if bj == 0 else (1 - bj) * T[j] + bj * T[j + 1]
        P = (1 - M[j])[..., None] * P + M[j][..., None] * top
    return P


def specular_lobe(hz, cos_product, lobe, kh=1.0, scale=1.0):
    """One lobe of eq. 10's max, ``lobe = (k, alpha_s, a_s, b_s[, f_s])``:
    k H_z^alpha_s max(0, a_s + (b_s + f_s (1 - k.h)^5) / cp) times ``scale`` (:func:`specular_scale`).

    ``kh`` = wi . H, floored at COS_FLOOR; kh = 1 (the default) leaves out the Schlick term.
    """
    k, alpha_s, a_s, b_s, f_s = tuple(lobe) + (0.0,) * (5 - len(lobe))
    kh = np.clip(kh, COS_FLOOR, 1.0)
    s = np.maximum(elevation_scale(a_s, b_s + f_s * (1.0 - kh) ** 5, cos_product), 0.0)
    return k * np.power(np.clip(hz, 0.0, 1.0), alpha_s) * s * scale


def specular_scale(kh, jacobian=False, top=None):
    """The factor both eq. 10 lobes share: 1 / k.h (k.h floored at COS_FLOOR) with ``jacobian``, times
    F_0^alpha_0 with ``top = (F_0, alpha_0)``, the dominant mode's stencil and exponent (eqs. 2, 4)."""
    scale = 1.0 / np.clip(kh, COS_FLOOR, 1.0) if jacobian else 1.0
    if top is not None:
        scale = scale * np.power(np.clip(top[0], 0.0, 1.0), top[1])
    return scale


def specular_factor(hz, cos_product, lobe1, lobe2=NO_LOBE, kh=1.0, scale=1.0):
    """S = max(1, l_1 + l_2), the sum of the lobes (eq. 10; the second lobe is zero with k2 = 0)."""
    return np.maximum(1.0, specular_lobe(hz, cos_product, lobe1, kh, scale)
                      + specular_lobe(hz, cos_product, lobe2, kh, scale))


def lobes(model):
    """The model's two eq. 10 lobes as ``(k, alpha_s, a_s, b_s, f_s)`` tuples."""
    return ((model.k, model.alpha_s, model.a_s, model.b_s, model.f_s),
            (model.k2, model.alpha_s2, model.a_s2, model.b_s2, model.f_s2))


def highlight_shares(hz, cos_product, lobe1, lobe2, kh=1.0, scale=1.0):
    """Eq. 10's boost per unit luminance, split between the lobes in proportion l_1 : l_2,
    ``(..., 2)``: (S - 1) l_i / (l_1 + l_2).  They sum to S - 1 and do not depend on B."""
    l1 = specular_lobe(hz, cos_product, lobe1, kh, scale)
    l2 = specular_lobe(hz, cos_product, lobe2, kh, scale)
    tot = l1 + l2
    f = (np.maximum(tot, 1.0) - 1.0) / np.maximum(tot, 1e-30)
    return np.stack([f * l1, f * l2], -1)


def highlight_basis(B, hz, cos_product, lobe1, lobe2, kh=1.0, scale=1.0):
    """The boost (S - 1) Y(B) of eq. 10 split between the lobes in proportion l_1 : l_2, ``(..., 2)``."""
    return (np.asarray(B, float) @ LUMA)[..., None] * highlight_shares(hz, cos_product, lobe1, lobe2, kh, scale)


def apply_shares(B, shares, m_s=None, m_s2=None):
    """Eq. 10 from :func:`highlight_shares`: B S = B (1 + sum of the shares) without highlight colours (m_s
    None), else B + Y(B) (share_1 m_s + share_2 m_s2).  Linear in B; ``B (..., 3)``."""
    B = np.asarray(B, float)
    if m_s is None:
        return B * (1.0 + shares.sum(-1))[..., None]
    m_s2 = m_s if m_s2 is None else m_s2
    colour = shares[..., :1] * np.asarray(m_s, float) + shares[..., 1:] * np.asarray(m_s2, float)
    return B + (B @ LUMA)[..., None] * colour


def apply_specular(B, hz, cos_product, lobe1, lobe2=NO_LOBE, m_s=None, m_s2=None, kh=1.0, scale=1.0):
    """Eq. 10.  Without highlight colours (m_s None) B_S = B S, as in the paper; with them the
    boost (S - 1) Y(B) is split between the lobes (:func:`highlight_basis`) and each share takes
    its lobe's colour: B_S = B + X_1 m_s + X_2 m_s2.  Linear in B; ``B (..., 3)``.
    """
    return apply_shares(B, highlight_shares(hz, cos_product, lobe1, lobe2, kh, scale), m_s, m_s2)


def background(model, cos_product):
    """P_n = r m_bg max(0, a_r + b_r / cp) (eq. 7 with eq. 3's elevation scaling), ``(..., 3)``."""
    s = np.maximum(elevation_scale(model.a_r, model.b_r, cos_product), 0.0)
    return (model.r * s)[..., None] * np.asarray(model.m_bg, float)


def mode_terms(model, wi, wo):
    """Per mode (F, M, T) stacked: ``(n, ...)``, ``(n, ...)``, ``(n, ..., 3)``."""
    cp = _cos_product(wi, wo)
    Fs, Ms, Ts = [], [], []
    for md in model.modes:
        F = stencil(half_vector(wi, wo, md.retro), md.phi_a)
        L = mode_luminance(F, elevation_scale(md.a, md.b, cp), md.kd, md.ks, md.alpha)
        Fs.append(F)
        Ms.append(support_mask(F, md.w, model.dw_ratio))
        Ts.append(mode_colour(L, md.m))
    return Fs, Ms, Ts


def evaluate(model, wi, wo):
    """The fitted BRDF B_S(wi, wo) ``(..., 3)`` in 1/sr (eqs. 2-10); zero below the horizon."""
    wi, wo = np.broadcast_arrays(np.asarray(wi, float), np.asarray(wo, float))
    F, M, T = mode_terms(model, wi, wo)
    cp = _cos_product(wi, wo)
    B = merge_modes(T, M, model.beta, background(model, cp)) * np.ones(wi.shape[:-1] + (1,))
    h = half_vector(wi, wo)
    kh = np.sum(wi * h, -1)
    top = (F[0], model.modes[0].alpha) if model.stencil_highlight and model.modes else None
    out = apply_specular(B, h[..., 2], cp, *lobes(model), model.m_s, model.m_s2, kh=kh,
                         scale=specular_scale(kh, model.jacobian, top))
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    out = np.where(ok[..., None], np.maximum(out, 0.0), 0.0)
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


def evaluate_utia(model):
    """The model on the UTIA grid, ``(3, 6, 48, 6, 48)``."""
    from .grid import utia_directions
    wi, wo = utia_directions()
    return np.moveaxis(evaluate(model, wi, wo), -1, 0)
