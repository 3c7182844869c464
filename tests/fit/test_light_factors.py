"""Per-light RGB factors of a light dome (light_factors.estimate, reference_region)."""

from __future__ import annotations

import numpy as np
import pytest

from facetsynth.fit.light_factors import Factors, FactorSettings, correct, estimate, reference_region
from test_normals import dome, random_normals   # the same synthetic dome and relief as the normals' tests

Z = np.array([0.0, 0.0, 1.0])



def ggx_specular(normal, lights, alpha):
    """D(h) / (4 (n.o)) with GGX D, view +z, (P, F); 0 where unlit."""
    h = lights + Z
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    hn = normal @ h.T
    ln = normal @ lights.T
    D = alpha**2 / (np.pi * ((alpha**2 - 1) * hn**2 + 1) ** 2) * (hn > 0)
    return np.where(ln > 0, D / (4 * normal[:, 2:3]), 0.0)


def unit_mean(f):
    """The module's scale: each channel's mean over lights is 1."""
    return f / f.mean(0)


def capture(rng, P=4000, factors=None, highlights=True, shadows=True, noise=0.01):
    """Synthetic relief (normals up to 30 deg, random RGB albedo kd/pi in [0.05, 0.3]) under the 48-light
    dome with per-light RGB factors (default uniform in [0.8, 1.2]): GGX highlights (alpha 0.04, the
    brightest 5-10x its diffuse), a fifth of each point's low-light (< 40 deg) samples in cast shadow
    (1 % of their value), relative Gaussian noise. Returns samples b = I / E_nominal (P, F, 3), the
    diffuse shading s = n . l (P, F), the true factors (F, 3) and the albedo (P, 3)."""
    lights = dome()
    F = len(lights)
    f = rng.uniform(0.8, 1.2, (F, 3)) if factors is None else np.broadcast_to(factors, (F, 3))
    n = random_normals(rng, P, 30.0)
    albedo = rng.uniform(0.05, 0.3, (P, 3))
    s = np.maximum(n @ lights.T, 0.0)
    radiance = albedo[:, None, :] * s[..., None]
    if highlights:
        spec = ggx_specular(n, lights, 0.2**2)
        diffuse = radiance.mean(-1)
        ratio = np.where(diffuse > 0, spec / np.where(diffuse > 0, diffuse, 1.0), 0.0)
        ks = rng.uniform(5.0, 10.0, P) / ratio.max(1)
        radiance = radiance + (ks[:, None] * spec)[..., None]
    if shadows:
        low = np.broadcast_to(lights[:, 2] < np.sin(np.radians(40.0)), (P, F))
        k = int(round(0.2 * low[0].sum()))
        pick = np.argsort(np.where(low, rng.random(low.shape), 2.0), axis=1)[:, :k]
        cast = np.zeros((P, F), bool)
        np.put_along_axis(cast, pick, True, axis=1)
        radiance = np.where(cast[..., None], 0.01 * radiance, radiance)
    b = radiance * f[None] * (1.0 + noise * rng.normal(size=radiance.shape))
    return b, s, np.asarray(f, float), albedo


def rel_err(got, f):
    return np.abs(got / unit_mean(f) - 1).max()


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def test_recovers_factors(rng):
    """Factors in [0.8, 1.2] recovered to 2 % (each channel's mean over lights fixed to 1) through highlights,
    cast shadows and 1 % noise; a naive median of ratios without the trimming is not as good."""
    b, s, f, _ = capture(rng)
    valid = np.ones(s.shape, bool)
    got = estimate(b, s, valid)
    assert isinstance(got, Factors)
    err = rel_err(got.rgb, f)
    seed = rel_err(estimate(b, s, valid, FactorSettings(iterations=0)).rgb, f)
    print(f"factors: max rel. error {err:.4f} (median polish only {seed:.4f}); "
          f"spread median {np.median(got.spread):.4f}")
    assert err < 0.02                                   # measured 0.005 (the GGX tail; 0.0006 without)
    assert not got.fallback.any()
    np.testing.assert_allclose(got.rgb.mean(0), 1.0, rtol=1e-12)
    assert (got.points_used > 1000).all()
    assert np.isfinite(got.spread).all() and (got.spread > 0).all()
    # the corrected samples are the capture under the nominal lights: factors of 1
    again = estimate(correct(b, got.rgb), s, valid)
    assert np.abs(again.rgb - 1).max() < 0.002


def test_white_lights(rng):
    """All factors truly 1: within 0.5 % of 1 under cast shadows and 1 % noise. The GGX highlights' long tail
    (a few 0.1 % to a few % of the diffuse on many samples, more on the high lights, which lie nearer the
    mirror of the view for most normals) is indistinguishable from a brighter light: with them the error
    grows to ~0.5 % (high rings up, middle rings down), still far inside the 2 % of the requirement."""
    b, s, f, _ = capture(rng, factors=np.ones(3), highlights=False)
    got = estimate(b, s, np.ones(s.shape, bool))
    err = np.abs(got.rgb - 1).max()
    b, s, f, _ = capture(rng, factors=np.ones(3))
    err_hl = np.abs(estimate(b, s, np.ones(s.shape, bool)).rgb - 1).max()
    print(f"white lights: max |f - 1| {err:.4f}, with GGX highlights {err_hl:.4f}")
    assert err < 0.005                                  # measured 0.0008
    assert err_hl < 0.01                                # measured 0.005
    assert not got.fallback.any()


def test_invalid_and_unlit_samples_ignored(rng):
    """Invalid samples, NaN / Inf values and grazing or unlit predictions (s <= 0.2) do not take part."""
    b, s, f, _ = capture(rng, P=3000)
    valid = rng.random(s.shape) > 0.3
    b = b.copy()
    b[~valid] = np.nan
    b[0, :5] = np.inf
    valid[0, :5] = True
    s2 = s.copy()
    s2[s <= 0.2] = -5.0                                 # nonsense where not lit enough: ignored
    got = estimate(b, s2, valid)
    assert np.isfinite(got.rgb).all() and not got.fallback.any()
    assert rel_err(got.rgb, f) < 0.02


def test_subsampling_deterministic(rng):
    b, s, f, _ = capture(rng, P=3000)
    valid = np.ones(s.shape, bool)
    st = FactorSettings(max_points=1000)
    one, two = estimate(b, s, valid, st), estimate(b, s, valid, st)
    assert np.array_equal(one.rgb, two.rgb)
    assert one.points_used.max() <= 1000
    assert rel_err(one.rgb, f) < 0.02


def test_reference_region(rng):
    """A grey reference region (uniform albedo, flat) under the same lights, highlights, shadows and noise:
    the median-based factors to 2 %."""
    b, s, f, albedo = capture(rng)
    P = len(s)
    mask = np.zeros(P, bool)
    mask[:800] = True
    lights = dome()
    flat = np.maximum(np.broadcast_to(lights[:, 2], (800, len(lights))), 0.0)
    b = b.copy()
    s = s.copy()
    b[:800] = 0.18 * flat[..., None] * f[None] * (1.0 + 0.01 * rng.normal(size=(800, len(lights), 3)))
    s[:800] = flat
    got = reference_region(b, s, np.ones(s.shape, bool), mask)
    err = rel_err(got, f)
    print(f"reference region: max rel. error {err:.4f}")
    assert got.shape == f.shape and err < 0.02          # measured 0.0013
    np.testing.assert_allclose(got.mean(0), 1.0, rtol=1e-12)


def test_degenerate_inputs(rng):
    """No valid samples, one light, an empty region, huge values: finite factors of 1, flagged."""
    b, s, f, _ = capture(rng, P=200)
    F = s.shape[1]
    none = estimate(b, s, np.zeros(s.shape, bool))
    assert np.array_equal(none.rgb, np.ones((F, 3))) and none.fallback.all()
    assert np.array_equal(none.points_used, np.zeros(F, int)) and np.isfinite(none.spread).all()

    one = estimate(b[:, :1], s[:, :1], np.ones((200, 1), bool))
    assert np.array_equal(one.rgb, np.ones((1, 3))) and one.fallback.all()

    dark = estimate(np.zeros_like(b), s, np.ones(s.shape, bool))   # all-black capture
    assert np.isfinite(dark.rgb).all() and dark.fallback.all()

    huge = estimate(np.full_like(b, 1e300), s, np.ones(s.shape, bool))
    assert np.isfinite(huge.rgb).all() and np.isfinite(huge.spread).all()

    few = np.zeros(s.shape, bool)
    few[:, 3] = True                                    # light 3 alone on every point: no ratio to others
    few[:5] = True                                      # five complete points: too few for any light
    got = estimate(b, s, few)
    assert np.array_equal(got.rgb, np.ones((F, 3))) and got.fallback.all()

    assert np.array_equal(reference_region(b, s, np.ones(s.shape, bool), np.zeros(200, bool)), np.ones((F, 3)))
    assert np.array_equal(reference_region(b, s, np.zeros(s.shape, bool), np.ones(200, bool)), np.ones((F, 3)))

    empty = estimate(np.zeros((0, F, 3)), np.zeros((0, F)), np.zeros((0, F), bool))
    assert empty.fallback.all() and np.array_equal(empty.rgb, np.ones((F, 3)))

    with pytest.raises(ValueError):
        estimate(b, s[:, :3], np.ones(s.shape, bool))
