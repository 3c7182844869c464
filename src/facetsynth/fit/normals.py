"""Shading normals (mesostructure): each point's local frame.

Paper 002 writes eq. 6 in the frame of the sample plane (normal n = +z). Real samples have relief: weave,
grain, brush marks, paint strokes. A per-point shading normal n(x) tilts that frame; the model is eq. 6
evaluated in it, with i and o expressed in the point's frame and the foreshortening n(x) . i:

    I = rho(x, R(x) i, R(x) o) (n(x) . i) L / |P - x|^2,    R(x) n(x) = +z.

R(x) is the smallest rotation taking n(x) to +z (about the axis n x z), so a flat sample (n = +z) keeps
the plane's frame exactly and the anisotropy's azimuth stays measured from the plane's x axis.

Estimation (:func:`estimate`): robust Lambertian photometric stereo, per point.

Woodham (1980, "Photometric method for determining surface orientation from multiple images", Opt. Eng.
19(1)): with the irradiance-normalised radiance b_q = I_q / E_q and the unit light directions l_q, a
Lambertian point gives b_q = (kd/pi) (n . l_q) = g . l_q, linear in g = (kd/pi) n; three or more lights
not in one plane give g by least squares, n = g / |g|, kd/pi = |g|.

Real samples break the linear model in two ways, both one-sided and sparse: highlights (the specular lobe,
b_q >> g . l_q, for lights near the view direction mirrored about n) and shadows (attached: n . l_q <= 0 where the
measurement is 0 instead of the negative g . l_q; cast: the relief hides the light, b_q ~ 0). Rather than
the low-rank / sparse-error formulations (Wu et al. 2010, ACCV, "Robust photometric stereo via low-rank
matrix completion and recovery"; Mukaigawa et al. 2007, JOSA A, "Analysis of photometric factors based on
photometric linearization"), whose per-point iterative SVDs / RANSAC over triplets are too heavy for
200 000 points, we do what the classic shadow-and-highlight rejection does (Coleman & Jain 1982, CGIP 18;
Barsky & Petrou 2003, PAMI 25(10): drop the brightest and darkest samples, then verify against the fit),
as an iteratively trimmed least squares, vectorised over points:

1. seed with the valid samples between the ``lower``-th and ``upper``-th percentile of luminance per point
   (10 % / 50 % by default: the darkest are shadows, the brightest highlights), less those darker than
   ``dark`` x the point's median (shadows, however many);
2. fit g on the luminance (channel mean) by least squares over the inliers: batched 3 x 3 normal
   equations (sum l l^T) g = sum b l, ``np.linalg.solve`` on (P, 3, 3) with a vanishing ridge so no
   batch member is exactly singular;
3. re-select: a valid sample is an inlier if its residual r = b - g . l lies in [-k sigma, k_high sigma],
   sigma = 1.4826 median |r| over the current inliers (a MAD about the fit) kept within [floor, cap] |g|
   (exact data must not make the band vanish, a poor seed must not widen it to everything), and it is lit,
   n . l > ``min_cos`` (attached shadow); the band is tighter above (k_high = 1.5 < k = 3) because
   highlights only add light and a GGX lobe's long tail adds a little to many samples; a point whose
   new set is too small keeps its previous one; repeat 2-3 ``iterations`` times, then fit once more.

This is a trimmed least squares (Rousseeuw's LTS in spirit, with a MAD-scaled band instead of a fixed
fraction), with the same reasoning as the percentile rejection of Coleman & Jain but adaptive to the
number of lights the highlight and the shadows actually cover. Hard 0/1 weights, not an M-estimator's
smooth ones: the outliers here are gross (a highlight is 5-20x the diffuse, a shadow 0), and the
inlier mask is itself an output (:attr:`Normals.inliers`).

The per-channel albedo kd_c / pi is then the least squares of b_q,c on s_q = n . l_q over the inliers,
sum s b_c / sum s^2, clipped at 0.

Guards: a point with fewer than ``min_inliers`` inliers, ill-conditioned lights over its inliers
(det(A) / (tr(A) / 3)^3 < ``min_conditioning``, A = sum l l^T; 1 for isotropic directions, 0 for
coplanar ones), |g| ~ 0 or a normal facing down (n_z <= 0) falls back to the flat normal +z and is
flagged. A normal tilted beyond ``max_tilt_deg`` keeps its azimuth and is clamped to that tilt. Samples
with non-finite values or directions are invalid. Nothing non-finite leaves :func:`estimate`.

What the stage ``separate`` does with it (docs/decisions.md, "Shading normals"):
:func:`photometric_normals` leaves the specular lobe's core out of the fit (LOBE_DEG about the normal);
a point without enough diffuse to tell its normal (:func:`diffuse_enough`: a metal) takes it from its
highlight (:func:`highlight_normals`); :func:`relief_normals` removes a tilt common to the whole sample and
makes a sample flat, exactly, when 95 % of its tilts are below FLAT_TILT_P95_DEG.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.colour import channel_mean
from ..models.microfacet import half_vector

FLAT = np.array([0.0, 0.0, 1.0])

# Photometric stereo leaves out the samples whose half vector lies within LOBE_DEG of the point's normal: the
# specular lobe's core. Trimming alone misses a broad lobe's shoulder, and under an oblique camera that shoulder
# lies on one side: it tilted a flat GGX point (alpha 0.25) by 2-3 deg. Twice: about +z, then about the estimate.
LOBE_DEG = 25.0
# A sample whose shading normals tilt less than this (deg) at their 95th percentile is flat: its normals are +z.
# Estimation noise and the leftover bias of a lobe's shoulder stay below it on the virtual scenes (flat); the
# real reliefs of docs/accuracy.md tilt by 10-30 deg.
FLAT_TILT_P95_DEG = 3.0
MIN_KD, MIN_KD_SHARE = 0.01, 0.1   # diffuse_enough
# Points without enough diffuse (a metal) take their normal from their highlight (highlight_normals) when the
# brightest sample is at least HIGHLIGHT_CONTRAST x their median: the mean half vector of their GLINT_SAMPLES
# brightest samples. A glint is one or two lights wide on a dome of 48, so a handful of samples holds it.
HIGHLIGHT_CONTRAST, GLINT_SAMPLES = 4.0, 3


def shading_frames(normal: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations R with R n = +z, the smallest such (Rodrigues about n x z), for unit normals
    (..., 3) with n_z > -1. n = +z gives the identity exactly."""
    n = np.asarray(normal, float)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    c = 1.0 / (1.0 + z)        # n_z > -1: normals of a surface seen from above
    # R = I + [a]x + [a]x^2 / (1 + cos), a = n x z = (y, -x, 0), cos = z
    R = np.empty(n.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - x * x * c
    R[..., 0, 1] = -x * y * c
    R[..., 0, 2] = -x
    R[..., 1, 0] = -x * y * c
    R[..., 1, 1] = 1 - y * y * c
    R[..., 1, 2] = -y
    R[..., 2, 0] = x
    R[..., 2, 1] = y
    R[..., 2, 2] = z
    return R


def to_local(frames: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Directions v (..., 3) in the frames (..., 3, 3) of :func:`shading_frames` (broadcast over ...)."""
    return (frames @ v[..., None])[..., 0]


# ---------------------------------------------------------------------------------------------------------------
# Estimation: robust photometric stereo on the diffuse part
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NormalSettings:
    """Knobs of :func:`estimate` (see the module's estimation notes); defaults tuned on the tests'
    synthetic relief (48 lights, GGX highlights 5-20x the diffuse, 20 % cast shadows, 1 % noise).

    lower, upper:       luminance percentiles (0-100) of a point's valid samples that seed the fit (10, 50):
                        highlights are few and bright, so the seed stays below the median.
    dark:               the seed also drops samples darker than ``dark`` x the point's median valid
                        luminance (0.1): shadows, however many there are.
    iterations:         trimming iterations after the seed fit (5; 3 give the same numbers in the tests).
    k:                  the band below the fit, in robust standard deviations sigma = 1.4826 median |r|
                        over the inliers (3).
    k_high:             the band above the fit (1.5): highlights only ever add light, and a lobe's tail
                        adds a little to many samples, so the band is one-sided-tight upwards.
    floor, cap:         sigma is kept within [floor, cap] x |g| (|g| = luminance kd/pi; 0.01, 0.1): exact
                        data keeps its samples, and a poor seed cannot widen the band to everything.
    min_cos:            n . l at or below which a sample is an attached shadow, excluded (0.1, ~84 deg).
    min_inliers:        fewer inliers than this: fall back to +z (6).
    min_conditioning:   det(A) / (tr(A)/3)^3 of the inliers' A = sum l l^T below this: fall back (1e-4).
    max_tilt_deg:       normals tilted further from +z are clamped to this tilt, azimuth kept (80).
    chunk:              points per internal block (8192: ~60 MB of float64 temporaries at F = 42, cache
                        friendly; 65536 blocks ran 3-5x slower).
    """

    lower: float = 10.0
    upper: float = 50.0
    dark: float = 0.1
    iterations: int = 5
    k: float = 3.0
    k_high: float = 1.5
    floor: float = 0.01
    cap: float = 0.1
    min_cos: float = 0.1
    min_inliers: int = 6
    min_conditioning: float = 1e-4
    max_tilt_deg: float = 80.0
    chunk: int = 8192


@dataclass(frozen=True)
class Normals:
    """Result of :func:`estimate`: ``normal`` (P, 3) unit, n_z >= cos(max tilt); ``albedo`` (P, 3) kd/pi
    per channel, >= 0; ``inliers`` (P, F) bool, the samples of the final fit (False: invalid, highlight,
    shadow); ``fallback`` (P,) bool, True where the fit was impossible and the normal is +z."""

    normal: np.ndarray
    albedo: np.ndarray
    inliers: np.ndarray
    fallback: np.ndarray


def estimate(samples: np.ndarray, directions: np.ndarray, valid: np.ndarray,
             settings: NormalSettings = NormalSettings()) -> Normals:
    """Per-point shading normals and diffuse albedo by robust photometric stereo (Woodham 1980) with
    iteratively trimmed least squares against highlights and shadows (see the module's estimation notes).

    samples (P, F, 3): b = I / E, irradiance-normalised radiance per point, frame and channel.
    directions (P, F, 3): unit world directions towards the light (z > 0).
    valid (P, F) bool: usable samples; samples or directions with non-finite values, and directions with
    z <= 0, are dropped as well.
    Vectorised over points (blocks of ``settings.chunk``), a few iterations in Python.
    """
    samples = np.asarray(samples)
    directions = np.asarray(directions)
    valid = np.asarray(valid, bool)
    if samples.ndim != 3 or samples.shape[-1] != 3:
        raise ValueError(f"samples must be (P, F, 3), got {samples.shape}")
    P, F = samples.shape[:2]
    if directions.shape != (P, F, 3) or valid.shape != (P, F):
        raise ValueError(f"directions {directions.shape} / valid {valid.shape} do not match "
                         f"samples {samples.shape}")
    normal = np.empty((P, 3))
    albedo = np.empty((P, 3))
    inliers = np.zeros((P, F), bool)
    fallback = np.zeros(P, bool)
    step = max(int(settings.chunk), 1)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):    # huge inputs: outputs are guarded
        for a in range(0, P, step):
            b = slice(a, min(a + step, P))
            normal[b], albedo[b], inliers[b], fallback[b] = _estimate_block(samples[b], directions[b],
                                                                            valid[b], settings)
    return Normals(normal=normal, albedo=albedo, inliers=inliers, fallback=fallback)


def _masked_median(x: np.ndarray, mask: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per-row median (lower middle) of x where mask; 0 for empty rows."""
    s = np.sort(np.where(mask, x, np.inf), axis=1)
    idx = np.maximum(count - 1, 0) // 2
    m = np.take_along_axis(s, idx[:, None], axis=1)[:, 0]
    return np.where(count > 0, m, 0.0)


def _fit(M: np.ndarray, w: np.ndarray):
    """Batched least squares of the luminance y on the directions l over the rows' masks w (P, F), from
    M (P, 9, F) = the products (lx lx, lx ly, lx lz, ly ly, ly lz, lz lz, y lx, y ly, y lz): g (P, 3),
    and the conditioning det(A) / (tr(A)/3)^3 of A = sum l l^T."""
    m = np.matmul(M, w.astype(float)[..., None])[..., 0]            # (P, 9): the masked sums
    A = m[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    tr = m[:, 0] + m[:, 3] + m[:, 5]
    ridge = 1e-12 * tr + (tr <= 0)          # never exactly singular; empty rows solve I g = 0
    g = np.linalg.solve(A + ridge[:, None, None] * np.eye(3), m[:, 6:, None])[..., 0]
    cond = np.linalg.det(A) / np.where(tr > 0, tr / 3.0, 1.0) ** 3
    cond = np.where(np.isfinite(cond), cond, 0.0)
    return g, cond


def _estimate_block(samples, directions, valid, st: NormalSettings):
    b = np.moveaxis(np.asarray(samples, float), -1, 0)      # (3, P, F): components as contiguous planes
    d = np.moveaxis(np.asarray(directions, float), -1, 0)
    b = np.ascontiguousarray(b)
    d = np.ascontiguousarray(d)
    dn = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    ok = valid & np.isfinite(b).all(0) & np.isfinite(dn) & (dn > 0) & (d[2] > 0)
    l = np.where(ok, d / np.where(ok, dn, 1.0), 0.0)        # (3, P, F) unit, 0 where invalid
    b = np.where(ok, b, 0.0)
    y = b.mean(0)
    n_ok = ok.sum(1)
    P, F = y.shape

    def dot(v):                                             # l . v per sample, v (P, 3)
        return l[0] * v[:, 0, None] + l[1] * v[:, 1, None] + l[2] * v[:, 2, None]

    # 1. seed: valid samples between the lower and upper luminance percentiles (ranks of the valid ones)
    order = np.argsort(np.where(ok, y, np.inf), axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(F), (P, F)), axis=1)
    lo = np.floor(st.lower / 100.0 * n_ok).astype(int)
    hi = np.ceil(st.upper / 100.0 * n_ok).astype(int)
    med = _masked_median(y, ok, n_ok)
    inl = ok & (rank >= lo[:, None]) & (rank < hi[:, None]) & (y > st.dark * med[:, None])
    small = inl.sum(1) < st.min_inliers          # too few for a band: seed with every valid sample
    inl[small] = ok[small]

    # 2-3. trimmed least squares on the luminance
    M = np.stack([l[0] * l[0], l[0] * l[1], l[0] * l[2], l[1] * l[1], l[1] * l[2], l[2] * l[2],
                  y * l[0], y * l[1], y * l[2]], axis=1)
    for _ in range(max(int(st.iterations), 0)):
        g, _cond = _fit(M, inl)
        gl = dot(g)
        sres = y - gl
        gnorm = np.sqrt((g * g).sum(1))
        sigma = 1.4826 * _masked_median(np.abs(sres), inl, inl.sum(1))
        band = np.minimum(np.maximum(sigma, st.floor * gnorm), st.cap * gnorm)[:, None]
        lit = gl > st.min_cos * gnorm[:, None]
        new = ok & (sres >= -st.k * band) & (sres <= st.k_high * band) & lit
        keep = new.sum(1) >= st.min_inliers
        inl = np.where(keep[:, None], new, inl)
    g, cond = _fit(M, inl)

    # normal, guards, tilt clamp
    gnorm = np.sqrt((g * g).sum(1))
    scale = np.maximum(np.abs(y).max(1, initial=0.0), 1e-300)
    good = (np.isfinite(g).all(1) & (gnorm > 1e-9 * scale) & (inl.sum(1) >= st.min_inliers)
            & (cond >= st.min_conditioning))
    n = np.where(good[:, None], g / np.where(good, gnorm, 1.0)[:, None], FLAT)
    good &= n[:, 2] > 0
    n = np.where(good[:, None], n, FLAT)
    zmin = np.cos(np.radians(st.max_tilt_deg))
    steep = n[:, 2] < zmin
    if steep.any():
        xy = n[steep, :2]
        xy = xy / np.sqrt((xy * xy).sum(1))[:, None]      # n_z < 1 here so |xy| > 0
        n[steep, :2] = xy * np.sqrt(1.0 - zmin * zmin)
        n[steep, 2] = zmin
    fallback = ~good
    # fallback points: a flat normal, and its lit samples of the inlier set for the albedo
    inl = np.where(fallback[:, None], inl & (l[2] > st.min_cos), inl)

    # per-channel albedo: least squares of b_c on s = n . l over the inliers
    s = dot(n) * inl
    den = (s * s).sum(1)
    num = (b * s).sum(2).T                                  # (P, 3)
    alb = np.where(den[:, None] > 0, num / np.where(den > 0, den, 1.0)[:, None], 0.0)
    alb = np.clip(np.nan_to_num(alb, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    return n, alb, inl, fallback


def photometric_normals(b: np.ndarray, wi: np.ndarray, view: np.ndarray,
                        valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normals (p, 3), luminance albedo kd/pi (p,)) of points from their irradiance-normalised radiance
    b = rho (+z . i) (p, F, 3) (b = (kd/pi) n . i on the diffuse part) by robust photometric stereo
    (:func:`facetsynth.fit.normals.estimate`) away from the specular lobe: LOBE_DEG about the normal, +z first,
    then the estimate (``view`` (p, 3) the points' o)."""
    h = half_vector(wi, view[:, None, :])
    normal = np.broadcast_to(FLAT, view.shape)
    for _ in range(2):
        off_lobe = np.einsum("pfk,pk->pf", h, normal) < np.cos(np.radians(LOBE_DEG))
        found = estimate(b, wi, valid & off_lobe)
        normal = found.normal
    return found.normal, found.albedo.mean(axis=-1)


def highlight_normals(b: np.ndarray, h: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normals (p, 3), highlight contrast (p,)) from the points' highlights: where the diffuse part is too weak
    to tell a normal (a metal), a lobe centred on the normal peaks at h = n, so the normal is the mean half
    vector ``h`` (p, F, 3) of the GLINT_SAMPLES brightest valid samples, weighted by their luminance above the
    point's median. Contrast: the brightest sample's luminance over the median (0 without samples)."""
    lum = np.where(valid, channel_mean(b), np.nan)
    with np.errstate(all="ignore"):
        median = np.nan_to_num(np.nanmedian(lum, axis=1), nan=0.0) if lum.shape[1] else np.zeros(len(lum))
    lum = np.nan_to_num(lum, nan=-np.inf)
    k = min(GLINT_SAMPLES, lum.shape[1])
    if k == 0:
        return np.tile(FLAT, (len(lum), 1)), np.zeros(len(lum))
    top = np.argpartition(-lum, k - 1, axis=1)[:, :k]
    peak = np.take_along_axis(lum, top, axis=1)
    w = np.clip(np.where(np.isfinite(peak), peak, 0.0) - median[:, None], 0.0, None)
    n = np.einsum("pk,pkj->pj", w, np.take_along_axis(h, top[..., None], axis=1))
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    ok = (norm[:, 0] > 0) & (n[:, 2] > 0)
    n = np.where(ok[:, None], n / np.where(norm > 0, norm, 1.0), FLAT)
    contrast = np.where(ok & (median > 0), peak.max(axis=1, initial=0.0) / np.where(median > 0, median, 1.0), 0.0)
    return n, contrast


def diffuse_enough(albedo: np.ndarray) -> np.ndarray:
    """(P,) whether a point's diffuse part is strong enough to tell its normal: luminance kd at least
    MIN_KD, and MIN_KD_SHARE of the sample's 90th percentile (a metal's or a black marker's normal is
    the specular tail's and the noise's, not the surface's)."""
    kd = np.pi * np.asarray(albedo, float)
    return (kd >= MIN_KD) & (kd >= MIN_KD_SHARE * np.percentile(kd, 90))


def relief_normals(normals: np.ndarray, trusted: np.ndarray) -> tuple[np.ndarray, str]:
    """The shading normals of a relief on the plane, and what was done. Points not ``trusted`` (off the
    sample, too little diffuse) get +z. The sample's mean plane is z = 0, so the trusted points' slopes
    (-n_x/n_z, -n_y/n_z) have median 0: a common tilt is a bias of the estimate (a lobe's shoulder, an
    uneven dome), removed. Then, when FLAT_TILT_P95_DEG exceeds the 95th percentile of the tilts, the
    sample is flat: +z everywhere (a model only as complex as the scene)."""
    visible = trusted
    normals = np.where(trusted[:, None], normals, FLAT)
    slope = -normals[:, :2] / normals[:, 2:]
    bias = np.median(slope[visible], axis=0) if visible.any() else np.zeros(2)
    slope[trusted] -= bias
    normals = np.concatenate([-slope, np.ones((len(slope), 1))], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(normals[visible, 2], -1.0, 1.0)))
    p95 = float(np.percentile(tilt, 95)) if tilt.size else 0.0
    removed = f"common tilt {np.degrees(np.arctan(np.hypot(*bias))):.2f} deg removed"
    if p95 < FLAT_TILT_P95_DEG:
        return np.tile(FLAT, (len(normals), 1)), f"flat ({removed}; 95 % of tilts below {p95:.2f} deg < " \
                                                   f"{FLAT_TILT_P95_DEG:g})"
    return normals, f"relief ({removed}; 95th percentile of tilts {p95:.1f} deg)"
