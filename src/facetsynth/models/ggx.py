"""The portable material: glTF 2.0's metallic-roughness BRDF with anisotropic GGX, and its fit to an NDF.

The BRDF is the glTF 2.0 specification's, Appendix B ("BRDF Implementation",
https://registry.khronos.org/glTF/specs/2.0/glTF-2.0.html#appendix-b-brdf-implementation),
with the three material extensions the exporter writes
(https://github.com/KhronosGroup/glTF/tree/main/extensions/2.0/Khronos):

* ``KHR_materials_anisotropy``: alpha = roughness^2 (Appendix B, "Microfacet
  Surfaces"); along the anisotropy direction t (tangent space, the direction
  in which highlights stretch) alpha_t = mix(alpha, 1, strength^2), across it
  (b = n x t) alpha_b = alpha; the distribution is Burley's anisotropic GGX

      D(h) = 1 / (pi alpha_t alpha_b ((h.t)^2/alpha_t^2 + (h.b)^2/alpha_b^2 + (h.n)^2)^2) chi+(h.n)

  and the masking-shadowing term is the height-correlated Smith term of the
  same distribution (Appendix B's G, Heitz 2014), as the extension's
  V_GGX_anisotropic writes it:

      V = G / (4 |n.l| |n.v|) = 1 / (2 (|n.l| |(a_t v.t, a_b v.b, n.v)| + |n.v| |(a_t l.t, a_b l.b, n.l)|))

  (without the sample implementation's clamp to [0, 1], which is not part of
  the BRDF: it only caps V where both directions graze).
* ``KHR_materials_specular`` with ``KHR_materials_ior``: the dielectric BRDF

      fresnel_w = (1 - |v.h|)^5                                  (Schlick)
      f0  = min(((ior - 1)/(ior + 1))^2 specularColor, 1) specular,   f90 = specular
      F   = f0 + (f90 - f0) fresnel_w                             (RGB)
      dielectric = F V D + (1 - max(F.r, F.g, F.b)) baseColor / pi

  (ior 0: f0 from an infinite index, ((ior - 1)/(ior + 1))^2 = 1, per KHR_materials_ior);
* the core metal BRDF and the mix: metal = (baseColor + (1 - baseColor)
  fresnel_w) V D, material = mix(dielectric, metal, metallic).

Everything is reciprocal (|v.h| = |l.h|; D and V are symmetric in l, v),
non-negative, 0 when l or v is at or below the horizon, finite at grazing.

Frames: the sample plane is facetsynth's (normal +z, azimuth from +x towards
+y); the exported quad's tangent is +x and bitangent +y, so an anisotropy
direction at tangent-space angle a is the sample-plane azimuth a.

:func:`fit_ggx_ndf` fits (alpha_x, alpha_y, frame azimuth) of an anisotropic
GGX to tabulated NDFs on a :class:`facetsynth.geometry.grid.DirectionGrid` (moments,
then batched Levenberg-Marquardt on the table, vectorised over points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.grid import DirectionGrid
from .microfacet import half_vector
from ..geometry.plane import PlaneGrid

ALPHA_MIN = 1e-4      # the spec's note: never evaluate alpha = 0; clamp to a small positive value
FIT_ALPHA_RANGE = (2e-3, 1.0)   # the fit's bounds: glTF's alpha_t = mix(alpha, 1, s^2) cannot exceed 1


def dielectric_f0(ior) -> np.ndarray:
    """((ior - 1)/(ior + 1))^2 (Appendix B's fresnel_mix; KHR_materials_ior), 1 for the special value ior = 0."""
    ior = np.asarray(ior, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    return np.where(ior == 0.0, 1.0, f0)


def anisotropic_alphas(roughness, strength) -> tuple[np.ndarray, np.ndarray]:
    """(alpha_t, alpha_b) of KHR_materials_anisotropy: alpha = roughness^2, alpha_t = mix(alpha, 1, strength^2),
    alpha_b = alpha; both floored at :data:`ALPHA_MIN`."""
    alpha = np.asarray(roughness, float) ** 2
    s2 = np.asarray(strength, float) ** 2
    return np.maximum(alpha * (1.0 - s2) + s2, ALPHA_MIN), np.maximum(alpha, ALPHA_MIN)


def roughness_strength(alpha_major, alpha_minor) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`anisotropic_alphas`: (roughness, anisotropy strength) with alpha_t = ``alpha_major``
    and alpha_b = ``alpha_minor`` (alpha_minor <= alpha_major <= 1)."""
    a_min = np.clip(np.asarray(alpha_minor, float), 0.0, 1.0)
    a_max = np.clip(np.asarray(alpha_major, float), a_min, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s2 = np.where(a_min < 1.0, (a_max - a_min) / (1.0 - a_min), 0.0)
    return np.sqrt(a_min), np.sqrt(np.clip(s2, 0.0, 1.0))


def ggx_d(ht, hb, hn, alpha_t, alpha_b) -> np.ndarray:
    """Burley's anisotropic GGX D (KHR_materials_anisotropy) of half vectors in the (t, b, n) frame; 0 for h.n <= 0."""
    q = (ht / alpha_t) ** 2 + (hb / alpha_b) ** 2 + hn * hn
    with np.errstate(divide="ignore", over="ignore"):
        d = 1.0 / (np.pi * alpha_t * alpha_b * q * q)
    return np.where(hn > 0.0, d, 0.0)


def ggx_visibility(lt, lb, ln, vt, vb, vn, alpha_t, alpha_b) -> np.ndarray:
    """The height-correlated Smith visibility V = G / (4 |n.l| |n.v|) of the anisotropic GGX
    (Appendix B's "Specular BRDF", KHR_materials_anisotropy's V_GGX_anisotropic, no clamp).
    Directions in the (t, b, n) frame; 0 where l.n <= 0 or v.n <= 0."""
    ln_a, vn_a = np.abs(ln), np.abs(vn)
    ggx_v = ln_a * np.sqrt((alpha_t * vt) ** 2 + (alpha_b * vb) ** 2 + vn * vn)
    ggx_l = vn_a * np.sqrt((alpha_t * lt) ** 2 + (alpha_b * lb) ** 2 + ln * ln)
    den = ggx_v + ggx_l
    ok = (ln > 0.0) & (vn > 0.0) & (den > 0.0)
    return np.where(ok, 0.5 / np.where(ok, den, 1.0), 0.0)


def _frame_components(d: np.ndarray, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d.t, d.b, d.n) with t = (cos a, sin a, 0), b = n x t = (-sin a, cos a, 0), n = +z."""
    c, s = np.cos(angle), np.sin(angle)
    return c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]


@dataclass
class GltfMaterial:
    """Per-point glTF material parameters on the sample-plane grid (the exported textures, decoded).

    ``anisotropy_angle`` (P,) radians: the direction of increased roughness (alpha_t), counter-clockwise from
    the tangent (+x) towards the bitangent (+y); ``specular_color`` is the effective colour (factor x texture).
    :meth:`eval_index` is :class:`facetsynth.models.svbrdf.SVBRDF`'s interface, so :class:`facetsynth.app.predict.FrameRenderer`
    renders it.
    """

    plane: PlaneGrid
    base_color: np.ndarray           # (P, 3) linear
    roughness: np.ndarray            # (P,)
    anisotropy_strength: np.ndarray  # (P,)
    anisotropy_angle: np.ndarray     # (P,)
    specular: np.ndarray             # (P,)
    specular_color: np.ndarray       # (P, 3) linear
    ior: float = 1.5
    metallic: np.ndarray | None = None   # (P,), None = 0

    def __post_init__(self):
        p = self.plane.rows * self.plane.cols
        for name, shape in (("base_color", (p, 3)), ("roughness", (p,)), ("anisotropy_strength", (p,)),
                            ("anisotropy_angle", (p,)), ("specular", (p,)), ("specular_color", (p, 3)),
                            ("metallic", (p,))):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, float)
                setattr(self, name, value)
                if value.shape != shape:
                    raise ValueError(f"GltfMaterial {name} has shape {value.shape}, expected {shape}")
        self.alpha_t, self.alpha_b = anisotropic_alphas(self.roughness, self.anisotropy_strength)

    @property
    def n_points(self) -> int:
        return self.plane.rows * self.plane.cols

    def point_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell index and on-sample flag of sample-plane points (the SVBRDF's mapping)."""
        from .svbrdf import SVBRDF
        return SVBRDF.point_index(self, points)

    def eval_index(self, index: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """rho (N, 3) in 1/sr at flat point indices (N,), light directions wi (= l) and view directions wo (= v)."""
        index = np.asarray(index, np.intp)
        wi, wo = np.asarray(wi, float), np.asarray(wo, float)
        h = half_vector(wi, wo)
        angle = self.anisotropy_angle[index]
        at, ab = self.alpha_t[index], self.alpha_b[index]
        ht, hb, hn = _frame_components(h, angle)
        lt, lb, ln = _frame_components(wi, angle)
        vt, vb, vn = _frame_components(wo, angle)
        spec = ggx_d(ht, hb, hn, at, ab) * ggx_visibility(lt, lb, ln, vt, vb, vn, at, ab)
        c = 0.5 * (np.abs(np.sum(wi * h, -1)) + np.abs(np.sum(wo * h, -1)))   # |v.h| = |l.h|, symmetric bits
        w = ((1.0 - np.clip(c, 0.0, 1.0)) ** 5)[:, None]
        s = self.specular[index][:, None]
        f0 = np.minimum(dielectric_f0(self.ior) * self.specular_color[index], 1.0) * s
        fresnel = f0 + (s - f0) * w
        base = self.base_color[index]
        rho = fresnel * spec[:, None] + (1.0 - fresnel.max(axis=-1, keepdims=True)) * base / np.pi
        if self.metallic is not None:
            m = self.metallic[index][:, None]
            rho = (1.0 - m) * rho + m * (base + (1.0 - base) * w) * spec[:, None]
        valid = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
        rho = np.where(valid[:, None], rho, 0.0)
        return np.clip(np.nan_to_num(rho, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


# --- the fit -----------------------------------------------------------------------------------------------

def ggx_tables(grid: DirectionGrid, alpha_x, alpha_y, phi) -> np.ndarray:
    """Anisotropic GGX D at the cell centres of ``grid``, (N, n_theta * n_phi): alpha_x along the frame azimuth
    ``phi`` (N,), alpha_y across it (the convention of :func:`facetsynth.models.microfacet.ndf`)."""
    d = grid.directions.reshape(-1, 3)
    angle = np.asarray(phi, float)[:, None]
    ht, hb, hn = _frame_components(d[None], angle)
    return ggx_d(ht, hb, hn, np.asarray(alpha_x, float)[:, None], np.asarray(alpha_y, float)[:, None])


def _moments(tables: np.ndarray, grid: DirectionGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(major, minor eigenvalue, major axis azimuth) of E[(h_x, h_y)(h_x, h_y)^T] under (n.h) D dw (N,)."""
    d = grid.directions.reshape(-1, 3)
    w = tables * (d[:, 2] * grid.solid_angles.ravel())[None]
    total = np.maximum(w.sum(-1), 1e-300)
    cxx, cyy, cxy = ((w @ (d[:, i] * d[:, j])) / total for i, j in ((0, 0), (1, 1), (0, 1)))
    phi = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    mean, half = 0.5 * (cxx + cyy), np.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy ** 2)
    return mean + half, np.maximum(mean - half, 0.0), phi


@dataclass(frozen=True)
class _MomentDictionary:
    """Moments of GGX lobes (alpha_x >= alpha_y, frame 0) on one grid: the fit's starting point."""
    log_alpha: np.ndarray   # (M, 2)
    log_moment: np.ndarray  # (M, 2) log(major), log(minor)

    @classmethod
    def build(cls, grid: DirectionGrid, steps: int = 28) -> "_MomentDictionary":
        a = np.geomspace(*FIT_ALPHA_RANGE, steps)
        ax, ay = np.meshgrid(a, a, indexing="ij")
        keep = ax >= ay
        ax, ay = ax[keep], ay[keep]
        major, minor, _ = _moments(ggx_tables(grid, ax, ay, np.zeros(ax.size)), grid)
        return cls(np.log(np.stack([ax, ay], -1)), np.log(np.maximum(np.stack([major, minor], -1), 1e-30)))

    def start(self, major: np.ndarray, minor: np.ndarray) -> np.ndarray:
        """(N, 2) log alphas of the dictionary lobe nearest in log moments."""
        target = np.log(np.maximum(np.stack([major, minor], -1), 1e-30))
        dist = ((target[:, None, :] - self.log_moment[None]) ** 2).sum(-1)
        return self.log_alpha[np.argmin(dist, axis=1)]


def _model_and_jacobian(p: np.ndarray, d: np.ndarray, fit_scale: bool):
    """c D_ggx at directions d (C, 3) and its derivatives by (log ax, log ay, phi[, log c]); p (N, 4)."""
    ax, ay, phi = np.exp(p[:, 0:1]), np.exp(p[:, 1:2]), p[:, 2:3]
    c, s = np.cos(phi), np.sin(phi)
    hu = c * d[None, :, 0] + s * d[None, :, 1]
    hv = -s * d[None, :, 0] + c * d[None, :, 1]
    hz = d[None, :, 2]
    u2, v2 = (hu / ax) ** 2, (hv / ay) ** 2
    q = u2 + v2 + hz * hz
    m = np.exp(p[:, 3:4]) / (np.pi * ax * ay * q * q) if fit_scale else 1.0 / (np.pi * ax * ay * q * q)
    jac = [m * (-1.0 + 4.0 * u2 / q), m * (-1.0 + 4.0 * v2 / q),
           m * (-4.0 * hu * hv * (1.0 / ax ** 2 - 1.0 / ay ** 2) / q)]
    if fit_scale:
        jac.append(m)
    return m, np.stack(jac, -1)


def fit_ggx_ndf(tables: np.ndarray, grid: DirectionGrid, iterations: int = 12, fit_scale: bool = False,
                dictionary: _MomentDictionary | None = None) -> dict[str, np.ndarray]:
    """Anisotropic GGX lobes fitted to tabulated NDFs (N, n_theta, n_phi) on ``grid``, vectorised over N.

    Minimises sum over cells of Omega_cell (c D_ggx(h_cell) - table)^2 (D at the cell centres, the table's own
    sampling; Omega the cell's solid angle) over (log alpha_x, log alpha_y, frame azimuth) and, with
    ``fit_scale``, the scale c (else c = 1: the lobe keeps GGX's normalisation). Start: the principal axes of
    the table's (h_x, h_y) second moments under (n.h) D dw, and the alphas of the GGX lobe with the nearest
    moments (a dictionary on the same grid); then ``iterations`` batched Levenberg-Marquardt steps.

    Returns alpha_x >= alpha_y (N,) in :data:`FIT_ALPHA_RANGE`, ``phi`` (N,) the azimuth of alpha_x's axis in
    (-pi/2, pi/2], ``scale`` (N,) and ``rel_l2`` (N,): the fit's solid-angle-weighted relative L2 against the table.
    """
    n = tables.shape[0]
    t = np.clip(np.asarray(tables, float).reshape(n, -1), 0.0, None)
    d = grid.directions.reshape(-1, 3)
    sw = grid.solid_angles.ravel()[None]
    dictionary = dictionary or _MomentDictionary.build(grid)
    major, minor, phi0 = _moments(t, grid)
    p = np.zeros((n, 4))
    p[:, :2] = dictionary.start(major, minor)
    p[:, 2] = phi0
    lo, hi = np.log(FIT_ALPHA_RANGE[0]), np.log(FIT_ALPHA_RANGE[1])
    if fit_scale:   # the best scale of the starting lobe (linear least squares)
        m, _ = _model_and_jacobian(p, d, False)
        p[:, 3] = np.log(np.clip((sw * m * t).sum(-1) / np.maximum((sw * m * m).sum(-1), 1e-300), 1e-3, 1e3))
    k = 4 if fit_scale else 3
    model, jac = _model_and_jacobian(p, d, fit_scale)
    cost = (sw * (model - t) ** 2).sum(-1)
    lam = np.full(n, 1e-3)
    for _ in range(iterations):
        r = model - t
        jw = jac[..., :k] * sw[..., None]
        a = np.matmul(jw.transpose(0, 2, 1), jac[..., :k])      # J^T W J and J^T W r as matrix products:
        g = np.matmul(r[:, None, :], jw)[:, 0]                   # einsum's loops took 5 x as long
        diag = np.einsum("nii->ni", a)
        step = -np.linalg.solve(a + (lam[:, None] * np.maximum(diag, 1e-300))[..., None] * np.eye(k),
                                g[..., None])[..., 0]
        trial = p.copy()
        trial[:, :k] += step
        trial[:, :2] = np.clip(trial[:, :2], lo, hi)
        trial_model, trial_jac = _model_and_jacobian(trial, d, fit_scale)
        trial_cost = (sw * (trial_model - t) ** 2).sum(-1)
        better = np.isfinite(trial_cost) & (trial_cost < cost)
        p[better], cost[better] = trial[better], trial_cost[better]
        model[better], jac[better] = trial_model[better], trial_jac[better]
        lam = np.where(better, lam / 4.0, lam * 8.0)
    ax, ay, phi = np.exp(p[:, 0]), np.exp(p[:, 1]), p[:, 2]
    swap = ay > ax
    ax, ay = np.where(swap, ay, ax), np.where(swap, ax, ay)
    phi = np.where(swap, phi + 0.5 * np.pi, phi)
    phi = np.pi / 2 - np.mod(np.pi / 2 - phi, np.pi)          # into (-pi/2, pi/2]
    norm = np.sqrt((sw * t * t).sum(-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(norm > 0, np.sqrt(cost) / norm, 0.0)
    return {"alpha_x": ax, "alpha_y": ay, "phi": phi, "scale": np.exp(p[:, 3]) if fit_scale else np.ones(n),
            "rel_l2": rel}
