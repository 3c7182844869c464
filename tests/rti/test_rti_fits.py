"""Per-pixel RTI relighting fits (facetsynth.rti.fits)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facetsynth.rti import fits
from test_rti_lp import spiral_dome   # the .lp tests' golden-angle dome

Z_MIN = 0.15   # the dome's lowest cos(theta)


def _random_dome(count: int, rng: np.random.Generator, z_min: float = 0.15) -> np.ndarray:
    """Directions uniform in cos(theta) in [z_min, 1] and in azimuth."""
    z = rng.uniform(z_min, 1.0, count)
    phi = rng.uniform(0.0, 2 * np.pi, count)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def _hemisphere_quadrature(n_theta: int = 32, n_phi: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Directions (N, 3) and weights (N,) integrating over the upper hemisphere (dw = dcos(theta) dphi).

    Gauss-Legendre in cos(theta) on [0, 1], midpoint rule in phi (exact for
    the trigonometric polynomials of the HSH basis up to degree 3).
    """
    x, w = np.polynomial.legendre.leggauss(n_theta)
    ct, wt = 0.5 * (x + 1), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    c, p = np.meshgrid(ct, phi, indexing="ij")
    s = np.sqrt(1 - c * c)
    d = np.stack([s * np.cos(p), s * np.sin(p), c], axis=-1).reshape(-1, 3)
    return d, np.outer(wt, np.full(n_phi, 2 * np.pi / n_phi)).ravel()


# (1) HSH orthonormality ---------------------------------------------------------------

@pytest.mark.parametrize("kind, n", [("hsh2", 9), ("hsh3", 16)])
def test_hsh_basis_orthonormal_over_hemisphere_by_quadrature(kind, n):
    d, w = _hemisphere_quadrature()
    b = fits.basis(kind, d)
    assert b.shape == (len(d), n)
    gram = b.T @ (b * w[:, None])
    assert np.abs(gram - np.eye(n)).max() < 1e-10


def test_hsh_basis_orthonormal_by_monte_carlo():
    rng = np.random.default_rng(3)
    count = 200_000
    z = rng.uniform(0, 1, count)                       # uniform on the hemisphere: pdf 1 / (2 pi)
    phi = rng.uniform(0, 2 * np.pi, count)
    s = np.sqrt(1 - z * z)
    b = fits.basis("hsh3", np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1))
    gram = 2 * np.pi * b.T @ b / count
    assert np.abs(gram - np.eye(16)).max() < 2e-2


def test_hsh_low_order_terms_match_closed_forms():
    """H_0^0 = 1/sqrt(2 pi), H_1^0 = sqrt(3/(2 pi)) (2 cos(theta) - 1),
    H_1^1 = sqrt(6/pi) cos(phi) sqrt(cos(theta) - cos^2(theta)) (RTIBuilder/relight, no Condon-Shortley phase)."""
    d = spiral_dome(25, Z_MIN)
    ct, phi = d[:, 2], np.arctan2(d[:, 1], d[:, 0])
    b = fits.basis("hsh3", d)
    root = np.sqrt(ct - ct * ct)
    np.testing.assert_allclose(b[:, 0], 1 / math.sqrt(2 * math.pi), rtol=1e-12)
    np.testing.assert_allclose(b[:, 2], math.sqrt(3 / (2 * math.pi)) * (2 * ct - 1), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(b[:, 3], math.sqrt(6 / math.pi) * np.cos(phi) * root, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(b[:, 1], math.sqrt(6 / math.pi) * np.sin(phi) * root, rtol=1e-12, atol=1e-14)


def test_ptm_basis_is_malzbender_eq2():
    d = spiral_dome(7, Z_MIN)
    u, v = d[:, 0], d[:, 1]
    np.testing.assert_allclose(fits.basis("ptm", d),
                               np.stack([u * u, v * v, u * v, u, v, np.ones(7)], axis=1), rtol=0, atol=1e-15)


# (2) each model reproduces its own data -----------------------------------------------

@pytest.mark.parametrize("kind", fits.KINDS)
def test_model_reproduces_data_made_by_its_own_basis(kind):
    rng = np.random.default_rng(11)
    train, test = _random_dome(40, rng), _random_dome(15, rng)
    n = fits.n_coefficients(kind)
    coeffs = rng.normal(0, 1, (n, 4, 5, 3))
    make = lambda d: np.einsum("fn,n...->f...", fits.basis(kind, d), coeffs)  # noqa: E731
    # Shift so every value is positive (the clip at 0 in relight does not act):
    # for lambert a positive constant is not in the span, so use g with a large z.
    if kind == "lambert":
        coeffs[:2] *= 0.1
        coeffs[2] = np.abs(coeffs[2]) + 5.0
    else:
        coeffs[fits.n_coefficients(kind) - 1 if kind == "ptm" else 0] += 20.0
    assert make(train).min() > 0 and make(test).min() > 0
    fitted = fits.fit(kind, train, make(train))
    assert fitted.shape == coeffs.shape
    np.testing.assert_allclose(fits.relight(kind, fitted, test), make(test), rtol=0, atol=1e-8)
    np.testing.assert_allclose(fitted, coeffs, rtol=0, atol=1e-8)


def test_fit_and_relight_chunked_equal_unchunked(monkeypatch):
    rng = np.random.default_rng(5)
    d = _random_dome(30, rng)
    values = rng.uniform(0, 1, (30, 6, 7, 3)).astype(np.float32)
    whole = fits.fit("hsh3", d, values)
    pred = fits.relight("hsh3", whole, d)
    monkeypatch.setattr(fits, "_CHUNK_ELEMENTS", 50)  # blocks of 1-3 pixels
    np.testing.assert_allclose(fits.fit("hsh3", d, values), whole, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fits.relight("hsh3", whole, d), pred, rtol=1e-12, atol=1e-12)
    assert whole.dtype == np.float64 and pred.shape == values.shape


def test_relight_clips_at_zero():
    d = np.array([[0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]])
    g = np.array([[2.0], [0.0], [1.0]])                  # (3, 1): g . l = 2.0 and -0.4
    np.testing.assert_allclose(fits.relight("lambert", g, d), [[2.0], [0.0]])


# (3) lambert recovers albedo * normal -------------------------------------------------

def test_lambert_recovers_albedo_times_normal():
    rng = np.random.default_rng(2)
    lights = _random_dome(25, rng, z_min=0.6)
    normal = np.array([math.sin(0.3) * math.cos(1.0), math.sin(0.3) * math.sin(1.0), math.cos(0.3)])
    albedo = np.array([0.2, 0.5, 0.7])
    assert (lights @ normal).min() > 0                    # every light in front: no clamp
    values = np.clip(lights @ normal, 0, None)[:, None] * albedo      # (F, 3) one pixel, RGB
    g = fits.fit("lambert", lights, values)                # (3 components, 3 channels)
    np.testing.assert_allclose(g, normal[:, None] * albedo[None, :], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(g, axis=0), albedo, rtol=1e-12)


# (4) hsh3 beats ptm on a smooth Blinn-Phong-like capture -------------------------------

def _blinn_phong_capture(lights: np.ndarray) -> np.ndarray:
    """(F, 8, 8, 3): kd (n.l) + ks (n.h)^8 (n.l), view +z, normals tilted up to ~0.26 rad, grey ks 0.3."""
    ty, tx = np.meshgrid(np.linspace(-0.25, 0.25, 8), np.linspace(-0.25, 0.25, 8), indexing="ij")
    n = np.stack([tx, ty, np.ones_like(tx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    kd = np.stack([0.3 + 0.5 * (tx + 0.25), 0.5 + 0.0 * tx, 0.8 - 0.5 * (ty + 0.25)], axis=-1)
    h = lights + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nl = np.clip(np.einsum("fk,hwk->fhw", lights, n), 0, None)
    nh = np.clip(np.einsum("fk,hwk->fhw", h, n), 0, None)
    return kd[None] * nl[..., None] + 0.3 * (nh**8 * nl)[..., None]


def test_hsh3_heldout_error_below_ptm_on_smooth_specular_pixels():
    lights = spiral_dome(40, Z_MIN)
    heldout = np.arange(40) % 4 == 1                     # 10 held out, 30 training
    scores = fits.heldout_scores(lights, _blinn_phong_capture(lights), heldout)
    measured = {k: (scores[k]["training"], scores[k]["heldout"]) for k in fits.KINDS}
    expected = MEASURED_BLINN_PHONG
    for k in fits.KINDS:
        np.testing.assert_allclose(measured[k], expected[k], rtol=1e-3, err_msg=k)
    assert scores["hsh3"]["heldout"] < 0.3 * scores["ptm"]["heldout"]
    assert scores["hsh3"]["heldout"] < scores["hsh2"]["heldout"] < scores["ptm"]["heldout"]


# (training, held-out) relative L2 measured on the capture above (spiral dome, frames 1, 5, 9, ... held out).
MEASURED_BLINN_PHONG = {"lambert": (0.090383, 0.097195), "ptm": (0.074472, 0.090070),
                        "hsh2": (0.016396, 0.023817), "hsh3": (0.0042883, 0.0087559)}


# (5) too few frames -------------------------------------------------------------------

@pytest.mark.parametrize("kind, count", [("lambert", 2), ("ptm", 5), ("hsh2", 8), ("hsh3", 10)])
def test_fewer_frames_than_coefficients_raises(kind, count):
    d = spiral_dome(count, Z_MIN)
    n = fits.n_coefficients(kind)
    with pytest.raises(ValueError, match=rf"{kind} fit needs at least {n} light directions.*F = {count}"):
        fits.fit(kind, d, np.ones((count, 2, 2)))


def test_unknown_kind_and_bad_shapes_raise():
    d = spiral_dome(20, Z_MIN)
    with pytest.raises(ValueError, match="unknown RTI fit kind 'ptm2'"):
        fits.basis("ptm2", d)
    with pytest.raises(ValueError, match="one leading entry per light direction"):
        fits.fit("ptm", d, np.ones((19, 3)))
    with pytest.raises(ValueError, match=r"shape \(F, 3\)"):
        fits.basis("ptm", d[:, :2])


# (6) heldout_scores by hand -----------------------------------------------------------

def test_heldout_scores_match_hand_computation():
    """Lambert on 3 training lights interpolates exactly; the held-out light is computed by hand.

    Lights l1 = (0, 0, 1), l2 = (0.6, 0, 0.8), l3 = (0, 0.6, 0.8); held out
    l4 = (-0.6, 0, 0.8). Pixel a: I = 1, 1, 1 -> g = (1/3, 1/3, 1), prediction at
    l4 = -0.2 + 0.8 = 0.6 against truth 0.8. Pixel b: I = 2, 2, 2 -> prediction
    1.2 against truth 1.0. Pixel c (masked out): I = 1, 1, 1, truth 5 at l4.
    """
    lights = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    values = np.array([[1.0, 2.0, 1.0], [1.0, 2.0, 1.0], [1.0, 2.0, 1.0], [0.8, 1.0, 5.0]]).reshape(4, 1, 3)
    heldout = np.array([False, False, False, True])
    mask = np.array([[True, True, False]])
    s = fits.heldout_scores(lights, values, heldout, kinds=("lambert",), mask=mask)
    assert set(s) == {"lambert"}
    assert s["lambert"]["training"] == pytest.approx(0.0, abs=1e-12)
    assert s["lambert"]["heldout"] == pytest.approx(math.sqrt((0.2**2 + 0.2**2) / (0.8**2 + 1.0**2)), rel=1e-12)
    # only pixel a: 0.2 / 0.8
    only_a = fits.heldout_scores(lights, values[..., None], heldout, kinds=("lambert",),
                                 mask=np.array([[True, False, False]]))
    assert only_a["lambert"]["heldout"] == pytest.approx(0.25, rel=1e-12)
    # no mask: pixel c enters, prediction 0.6 against 5
    full = fits.heldout_scores(lights, values, heldout, kinds=("lambert",))
    assert full["lambert"]["heldout"] == pytest.approx(
        math.sqrt((0.2**2 + 0.2**2 + 4.4**2) / (0.8**2 + 1.0**2 + 5.0**2)), rel=1e-12)


def test_heldout_scores_least_squares_residual_and_clip_by_hand():
    """Lambert on 5 training lights (over-determined) and a held-out prediction clipped at 0.

    Training lights l1 = (0, 0, 1), (+-0.6, 0, 0.8), (0, +-0.6, 0.8) with values
    0, 0 (x+), 2 (x-), 1, 1: B^T B = diag(0.72, 0.72, 3.56), so
    g = (-1.2 / 0.72, 0, 3.2 / 3.56) = (-5/3, 0, gz), gz = 0.899. Predictions:
    gz at l1 (truth 0); -1 + 0.8 gz < 0 at (+0.6, 0, 0.8), clipped to 0 = truth;
    0.8 gz + 1 at (-0.6, 0, 0.8) (truth 2) and 0.8 gz at (0, +-0.6, 0.8) (truth 1),
    so residuals gz, 0, and 0.8 gz - 1 three times; truth norm sqrt(6). Held out
    (0.8, 0, 0.6): g . l = -4/3 + 0.6 gz < 0, clipped to 0 against truth 0.5:
    relative error 1.
    """
    lights = np.array([[0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8], [0, 0.6, 0.8], [0, -0.6, 0.8],
                       [0.8, 0, 0.6]])
    values = np.array([0.0, 0.0, 2.0, 1.0, 1.0, 0.5])[:, None]
    heldout = np.array([False] * 5 + [True])
    gz = 3.2 / 3.56
    np.testing.assert_allclose(fits.fit("lambert", lights[:5], values[:5])[:, 0], [-5 / 3, 0, gz], atol=1e-12)
    s = fits.heldout_scores(lights, values, heldout, kinds=("lambert",))
    assert s["lambert"]["training"] == pytest.approx(math.sqrt(gz**2 + 3 * (0.8 * gz - 1) ** 2) / math.sqrt(6),
                                                     rel=1e-12)
    assert s["lambert"]["heldout"] == pytest.approx(1.0, rel=1e-12)
