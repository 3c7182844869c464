"""Per-pixel relighting fits of light-dome (RTI) captures.

F training images under known unit light directions l (F, 3) (towards the
light, l_z > 0; frame: x right, y up in the image, z towards the camera) are
fitted per pixel and channel by linear least squares I(l) ~ b(l) . c, with a
fixed basis b of n functions of the light direction. One pseudo-inverse of
the (F, n) design matrix serves every pixel and channel. Models (``KINDS``):

* ``"lambert"`` (n = 3): photometric stereo (Woodham 1980) without the
  max(0, .) clamp in the fit, I = g . l, g = albedo * normal; predicted as
  max(0, g . l).
* ``"ptm"`` (n = 6): Polynomial Texture Map, Malzbender, Gelb, Wolters 2001,
  eq. 2: I = a0 lu^2 + a1 lv^2 + a2 lu lv + a3 lu + a4 lv + a5, with
  (lu, lv) = (l_x, l_y).
* ``"hsh2"`` / ``"hsh3"`` (n = 9 / 16): hemispherical harmonics, Gautron,
  Krivanek, Pattanaik, Bouatouch 2004 (sec. 3, eqs. 3-5), up to degree 2 / 3,
  as used by RTIBuilder and relight. With theta, phi the polar angle and
  azimuth of l (phi from +x towards +y) and the shifted associated Legendre
  functions P~_l^m(x) = P_l^m(2 x - 1) (theta in [0, pi/2] mapped to
  cos(theta') = 2 cos(theta) - 1),

      H_l^m  = sqrt(2) K~_l^m  cos(m phi)   P~_l^m(cos theta)      m > 0
      H_l^0  =         K~_l^0               P~_l^0(cos theta)
      H_l^m  = sqrt(2) K~_l^|m| sin(|m| phi) P~_l^|m|(cos theta)   m < 0

      K~_l^m = sqrt((2 l + 1) (l - |m|)! / (2 pi (l + |m|)!)),

  orthonormal over the upper hemisphere (integral of H_l^m H_l'^m' dw =
  delta_ll' delta_mm'). P_l^m is taken without the Condon-Shortley phase
  (-1)^m, as RTIBuilder/relight do (e.g. H_1^1 = sqrt(6/pi) cos(phi)
  sqrt(cos theta - cos^2 theta)); the sign does not change the fit's
  predictions. Column order: index l^2 + l + m, m = -l..l.

Predictions (:func:`relight`) are clipped at 0. Directions are normalised to
unit length; for the HSH basis cos(theta) is clipped to [0, 1] (the basis is
defined on the upper hemisphere only).
"""

from __future__ import annotations

import math

import numpy as np

from ..evaluation.metrics import relative_l2

__all__ = ["KINDS", "n_coefficients", "basis", "fit", "relight", "heldout_scores"]

KINDS = ("lambert", "ptm", "hsh2", "hsh3")

_N_COEFFICIENTS = {"lambert": 3, "ptm": 6, "hsh2": 9, "hsh3": 16}

# Pixels (columns of the flattened (F, P) value array) processed per block, so
# that float64 temporaries stay near _CHUNK_ELEMENTS entries.
_CHUNK_ELEMENTS = 1 << 22


def _check_kind(kind: str) -> str:
    k = str(kind).lower()
    if k not in _N_COEFFICIENTS:
        raise ValueError(f"unknown RTI fit kind {kind!r}; expected one of {KINDS}")
    return k


def n_coefficients(kind: str) -> int:
    """Number n of basis functions (coefficients per pixel and channel) of ``kind``."""
    return _N_COEFFICIENTS[_check_kind(kind)]


def _unit_directions(directions: np.ndarray) -> np.ndarray:
    """(F, 3) float64 unit vectors; ValueError on a wrong shape or a zero/non-finite row."""
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"light directions must have shape (F, 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm == 0):
        raise ValueError("light directions must be finite and non-zero")
    return d / norm


def _legendre_no_phase(lmax: int, x: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """Associated Legendre P_l^m(x), 0 <= m <= l <= lmax, without the Condon-Shortley phase.

    Standard recurrences: P_m^m = (2m - 1)!! (1 - x^2)^(m/2),
    P_{m+1}^m = x (2m + 1) P_m^m, (l - m) P_l^m = (2l - 1) x P_{l-1}^m - (l + m - 1) P_{l-2}^m.
    """
    s = np.sqrt(np.clip(1.0 - x * x, 0.0, None))
    p: dict[tuple[int, int], np.ndarray] = {}
    pmm = np.ones_like(x)
    for m in range(lmax + 1):
        if m > 0:
            pmm = pmm * (2 * m - 1) * s
        p[m, m] = pmm
        if m + 1 <= lmax:
            p[m + 1, m] = x * (2 * m + 1) * pmm
        for ll in range(m + 2, lmax + 1):
            p[ll, m] = ((2 * ll - 1) * x * p[ll - 1, m] - (ll + m - 1) * p[ll - 2, m]) / (ll - m)
    return p


def hsh_basis(lmax: int, directions: np.ndarray) -> np.ndarray:
    """Real hemispherical harmonics H_l^m (Gautron et al. 2004) of degree <= lmax: (F, (lmax + 1)^2).

    See the module docstring for the formula; column l^2 + l + m holds H_l^m.
    """
    d = _unit_directions(directions)
    cos_theta = np.clip(d[:, 2], 0.0, 1.0)
    phi = np.arctan2(d[:, 1], d[:, 0])
    p = _legendre_no_phase(lmax, 2.0 * cos_theta - 1.0)
    out = np.empty((len(d), (lmax + 1) ** 2))
    for ll in range(lmax + 1):
        for m in range(-ll, ll + 1):
            a = abs(m)
            k = math.sqrt((2 * ll + 1) * math.factorial(ll - a) / (2 * math.pi * math.factorial(ll + a)))
            if m > 0:
                col = math.sqrt(2.0) * k * np.cos(a * phi) * p[ll, a]
            elif m < 0:
                col = math.sqrt(2.0) * k * np.sin(a * phi) * p[ll, a]
            else:
                col = k * p[ll, 0]
            out[:, ll * ll + ll + m] = col
    return out


def basis(kind: str, directions: np.ndarray) -> np.ndarray:
    """Design matrix B (F, n) of ``kind`` at the light directions (F, 3): I ~ B @ c.

    lambert: (l_x, l_y, l_z); ptm: (lu^2, lv^2, lu lv, lu, lv, 1) (Malzbender
    et al. 2001, eq. 2); hsh2 / hsh3: :func:`hsh_basis` of degree 2 / 3.
    """
    k = _check_kind(kind)
    d = _unit_directions(directions)
    if k == "lambert":
        return d.copy()
    if k == "ptm":
        u, v = d[:, 0], d[:, 1]
        return np.stack([u * u, v * v, u * v, u, v, np.ones_like(u)], axis=1)
    return hsh_basis(2 if k == "hsh2" else 3, d)


def _apply(matrix: np.ndarray, values: np.ndarray) -> np.ndarray:
    """matrix (A, B) @ values (B, ...) -> (A, ...) in float64, in blocks of pixels."""
    flat = values.reshape(values.shape[0], -1)
    out = np.empty((matrix.shape[0], flat.shape[1]))
    step = max(1, _CHUNK_ELEMENTS // max(matrix.shape[0], flat.shape[0]))
    for start in range(0, flat.shape[1], step):
        out[:, start:start + step] = matrix @ flat[:, start:start + step].astype(np.float64, copy=False)
    return out.reshape((matrix.shape[0],) + values.shape[1:])


def fit(kind: str, directions: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (n, ...) of ``kind`` for the values (F, ...) under directions (F, 3).

    c = pinv(B) I for every pixel and channel at once (B from :func:`basis`);
    for "lambert" c = g, the albedo-scaled normal. ValueError if F < n (the
    fit would be underdetermined) or the shapes disagree.
    """
    k = _check_kind(kind)
    values = np.asarray(values)
    b = basis(k, directions)
    n = b.shape[1]
    if values.shape[:1] != (b.shape[0],):
        raise ValueError(f"values {values.shape} must have one leading entry per light direction ({b.shape[0]})")
    if b.shape[0] < n:
        raise ValueError(f"{k} fit needs at least {n} light directions (one per coefficient), got F = {b.shape[0]}")
    return _apply(np.linalg.pinv(b), values)


def relight(kind: str, coefficients: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Predicted values (G, ...) = max(0, B(directions) @ coefficients) for coefficients (n, ...)."""
    k = _check_kind(kind)
    coefficients = np.asarray(coefficients)
    b = basis(k, directions)
    if coefficients.shape[:1] != (b.shape[1],):
        raise ValueError(f"{k} coefficients must have shape ({b.shape[1]}, ...), got {coefficients.shape}")
    out = _apply(b, coefficients)
    np.clip(out, 0.0, None, out=out)
    return out


def _as_images(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """values (F, ...) as (F, H, W, C) for :func:`facetsynth.evaluation.metrics.relative_l2`.

    With a mask (H, W), values must be (F, H, W) or (F, H, W, C); without one
    every entry after the frame axis is a pixel.
    """
    if mask is None:
        return values.reshape(values.shape[0], -1, 1, 1)
    mask = np.asarray(mask)
    if values.ndim not in (3, 4) or values.shape[1:3] != mask.shape:
        raise ValueError(f"with a mask {mask.shape}, values must be (F, H, W[, C]), got {values.shape}")
    return values.reshape(values.shape[:3] + (-1,))


def heldout_scores(directions: np.ndarray, values: np.ndarray, heldout: np.ndarray,
                   kinds: tuple[str, ...] = KINDS, mask: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """Relative L2 of each fit on its training frames and on the held-out frames.

    Each kind is fitted (:func:`fit`) to the frames where ``heldout`` (F,) is
    False and relit (:func:`relight`, clipped at 0) at all F directions.
    Scores: ``||pred - truth||_2 / ||truth||_2`` over all pixels (only where
    ``mask`` (H, W) is True; values then (F, H, W[, C])), frames and channels
    of the set (:func:`facetsynth.evaluation.metrics.relative_l2`; NaN for an empty set
    or an all-zero truth). Returns {kind: {"training": ..., "heldout": ...}}.
    """
    values = np.asarray(values)
    heldout = np.asarray(heldout, dtype=bool)
    if heldout.shape != (values.shape[0],):
        raise ValueError(f"heldout must be a bool array of shape ({values.shape[0]},), got {heldout.shape}")
    d = _unit_directions(directions)
    truth = _as_images(values, mask)
    train = ~heldout
    scores: dict[str, dict[str, float]] = {}
    for kind in kinds:
        k = _check_kind(kind)
        pred = _as_images(relight(k, fit(k, d[train], values[train]), d), mask)
        scores[k] = {"training": relative_l2(pred[train], truth[train], mask),
                     "heldout": relative_l2(pred[heldout], truth[heldout], mask)}
    return scores
