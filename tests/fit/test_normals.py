"""Shading normals: the frames (shading_frames, to_local) and robust photometric stereo (estimate)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from facetsynth.fit.normals import NormalSettings, Normals, estimate, shading_frames, to_local

Z = np.array([0.0, 0.0, 1.0])
PLAIN = NormalSettings(lower=0.0, upper=100.0, dark=0.0, iterations=0)   # Woodham's least squares on every valid sample


def dome(n_rings=4, per_ring=12, elev=(15.0, 75.0)):
    """48 directional lights: rings at elevations 15..75 deg, azimuths staggered ring to ring."""
    out = []
    for r, e in enumerate(np.radians(np.linspace(*elev, n_rings))):
        az = 2 * np.pi * (np.arange(per_ring) + 0.5 * (r % 2)) / per_ring
        out.append(np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.full(per_ring, np.sin(e))], -1))
    return np.concatenate(out)


def random_normals(rng, P, max_tilt_deg):
    t = np.arccos(rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0, P))
    a = rng.uniform(0, 2 * np.pi, P)
    return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], -1)


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


def lambertian(normal, albedo, lights):
    """b = (kd/pi) max(n.l, 0): (P, F, 3), with directions (P, F, 3)."""
    P = len(normal)
    d = np.broadcast_to(lights, (P,) + lights.shape).copy()
    cos = np.maximum(np.einsum("pfi,pi->pf", d, normal), 0.0)
    return cos[..., None] * albedo[:, None, :], d


def ggx_specular(normal, d, alpha, view=Z):
    """Specular part of b = rho (n.i) for ks = 1, F = G = 1: D(h) / (4 (n.o)) with GGX D, (P, F)."""
    h = d + view
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    hn = np.einsum("pfi,pi->pf", h, normal)
    ln = np.einsum("pfi,pi->pf", d, normal)
    vn = normal @ view
    D = alpha**2 / (np.pi * ((alpha**2 - 1) * hn**2 + 1) ** 2) * (hn > 0)
    return np.where(ln > 0, D / (4 * vn[:, None]), 0.0)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


# --- 1. frames ----------------------------------------------------------------------------------------------------

def test_shading_frames(rng):
    n = random_normals(rng, 500, 89.0)
    R = shading_frames(n)
    np.testing.assert_allclose(np.einsum("pij,pj->pi", R, n), np.broadcast_to(Z, n.shape), atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.array_equal(shading_frames(Z), np.eye(3))
    u, v = rng.normal(size=(2, 500, 3))
    lu, lv = to_local(R, u), to_local(R, v)
    np.testing.assert_allclose(np.sum(lu * lv, -1), np.sum(u * v, -1), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(lu, axis=-1), np.linalg.norm(u, axis=-1), atol=1e-12)


# --- 2-5. estimation -----------------------------------------------------------------------------------------------

def relief(rng, P=2000, max_tilt=40.0):
    n = random_normals(rng, P, max_tilt)
    albedo = rng.uniform(0.05, 0.3, (P, 3))
    b, d = lambertian(n, albedo, dome())
    return n, albedo, b, d


def noisy(rng, b, level=0.01):
    """1 % Gaussian sensor noise, relative to the signal."""
    return b * (1.0 + level * rng.normal(size=b.shape))


def all_valid(b):
    return np.ones(b.shape[:2], bool)


def test_lambertian_relief(rng):
    """2. Exact Lambertian relief up to 40 deg tilt, attached shadows included: exact normals and albedo."""
    n, albedo, b, d = relief(rng)
    got = estimate(b, d, all_valid(b))
    assert isinstance(got, Normals)
    err = angle_deg(got.normal, n)
    print(f"lambertian: median {np.median(err):.2g} max {err.max():.2g} deg, "
          f"albedo {np.abs(got.albedo / albedo - 1).max():.2g}")
    assert not got.fallback.any()
    assert np.median(err) < 0.2 and err.max() < 1.0      # measured: 0 and 1e-6 deg
    np.testing.assert_allclose(got.albedo, albedo, rtol=0.01)
    # attached shadows (b = 0 where n.l <= 0) are never inliers
    assert not (got.inliers & (np.einsum("pfi,pi->pf", d, n) <= 0)).any()


def test_specular_highlights(rng):
    """3. GGX highlights 5-20x the diffuse (roughness 0.2, alpha = roughness^2 as in facetsynth.models.ggx), 1 %
    noise: the trimmed fit stays within a degree or two; Woodham's plain least squares does not."""
    n, albedo, b, d = relief(rng)
    diffuse = b.mean(-1)
    spec = ggx_specular(n, d, alpha=0.2**2)
    ratio = np.where(diffuse > 0, spec / np.where(diffuse > 0, diffuse, 1.0), 0.0)
    ks = rng.uniform(5.0, 20.0, len(n)) / ratio.max(1)          # the brightest highlight is 5-20x its diffuse
    b = noisy(rng, b + (ks[:, None] * spec)[..., None])
    got = estimate(b, d, all_valid(b))
    plain = estimate(b, d, all_valid(b), PLAIN)
    err, err_plain = angle_deg(got.normal, n), angle_deg(plain.normal, n)
    print(f"specular: median {np.median(err):.2f} p99 {np.percentile(err, 99):.2f} max {err.max():.2f} deg; "
          f"plain LS median {np.median(err_plain):.2f} deg; albedo median rel. error "
          f"{np.median(np.abs(got.albedo / albedo - 1)):.3f}")
    assert not got.fallback.any()
    assert np.median(err) < 1.0                     # measured 0.4
    assert np.percentile(err, 99) < 3.0             # measured 1.1
    assert np.median(err_plain) > 10.0              # measured 24
    assert np.median(err_plain) > 10 * np.median(err)
    # the highlights are the samples left out: each point's brightest-relative sample is no inlier
    hl = (ks[:, None] * spec) > diffuse
    assert not (got.inliers & hl).any()
    assert np.median(np.abs(got.albedo / albedo - 1)) < 0.04   # measured 0.02 (the lobe's tail)


def test_cast_shadows(rng):
    """4. A fifth of each point's low-elevation samples (below 40 deg) in cast shadow (1 % of their value),
    1 % noise."""
    n, albedo, b, d = relief(rng)
    low = d[..., 2] < np.sin(np.radians(40.0))
    k = int(round(0.2 * low[0].sum()))
    pick = np.argsort(np.where(low, rng.random(low.shape), 2.0), axis=1)[:, :k]
    cast = np.zeros_like(low)
    np.put_along_axis(cast, pick, True, axis=1)
    b = noisy(rng, np.where(cast[..., None], 0.01 * b, b))
    got = estimate(b, d, all_valid(b))
    err = angle_deg(got.normal, n)
    err_plain = angle_deg(estimate(b, d, all_valid(b), PLAIN).normal, n)
    print(f"cast shadows: median {np.median(err):.2f} max {err.max():.2f} deg; plain LS median "
          f"{np.median(err_plain):.2f} deg")
    assert not got.fallback.any()
    assert np.median(err) < 0.5 and err.max() < 2.0     # measured 0.08 and 0.3
    assert np.median(err_plain) > 2.0                   # measured 5
    assert not (got.inliers & cast).any()


def test_flat_with_noise(rng):
    """5. A flat Lambertian sample, 48 lights, 1 % noise: every normal within 0.5 deg of +z."""
    P = 4000
    albedo = rng.uniform(0.05, 0.3, (P, 3))
    b, d = lambertian(np.tile(Z, (P, 1)), albedo, dome())
    got = estimate(noisy(rng, b), d, all_valid(b))
    err = angle_deg(got.normal, Z)
    print(f"flat: median {np.median(err):.3f} max {err.max():.3f} deg")
    assert not got.fallback.any()
    assert err.max() < 0.5                              # measured 0.06 median, 0.3 max
    np.testing.assert_allclose(got.albedo, albedo, rtol=0.02)


def test_steep_normal_clamped(rng):
    """A normal tilted beyond max_tilt_deg keeps its azimuth, at that tilt."""
    n = np.array([[np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))]])
    b, d = lambertian(n, np.full((1, 3), 0.2), dome())
    got = estimate(b, d, all_valid(b), NormalSettings(max_tilt_deg=45.0))
    np.testing.assert_allclose(got.normal[0], [np.sin(np.radians(45)), 0.0, np.cos(np.radians(45))], atol=1e-12)
    assert not got.fallback[0]


def test_degenerate_inputs(rng):
    """6. Nothing non-finite leaves estimate; impossible fits fall back to +z, flagged."""
    n, albedo, b, d = relief(rng, P=8)
    F = b.shape[1]
    valid = all_valid(b)
    b = b.copy()
    valid[0] = False                       # 0: all invalid
    b[1] = 0.0                             # 1: all zero
    valid[2] = False
    valid[2, 40] = True                    # 2: one valid light
    b[3] = np.nan                          # 3: NaN everywhere, marked valid
    b[4, :5] = np.inf                      # 4: a few NaN / Inf samples marked valid: dropped, the rest fits
    b[4, 5:8, 1] = np.nan
    dz = d.copy()
    dz[5] = d[5, 7]                        # 5: every frame the same light: rank 1
    az = np.radians(30.0)
    e = np.radians(np.linspace(15, 75, F))
    dz[6] = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], -1)   # 6: coplanar lights
    b[7] = 1e300                           # 7: huge values: finite out
    got = estimate(b, dz, valid)
    for a in (got.normal, got.albedo):
        assert np.isfinite(a).all()
    assert (got.albedo >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(got.normal, axis=1), 1.0)
    bad = [0, 1, 2, 3, 5, 6]
    assert got.fallback[bad].all() and not got.fallback[4]
    assert np.array_equal(got.normal[bad], np.tile(Z, (len(bad), 1)))
    assert not got.inliers[0].any() and not got.inliers[3].any()
    assert not got.inliers[4, :8].any()
    assert angle_deg(got.normal[4], n[4]) < 1e-3
    assert (got.normal[:, 2] >= np.cos(np.radians(80.0)) - 1e-12).all()
    # empty input, float32 input, directions given unnormalised
    empty = estimate(np.zeros((0, F, 3)), np.zeros((0, F, 3)), np.zeros((0, F), bool))
    assert empty.normal.shape == (0, 3) and empty.inliers.shape == (0, F)
    n2, _, b2, d2 = relief(rng, P=16)
    got32 = estimate(b2.astype(np.float32), 3.0 * d2.astype(np.float32), all_valid(b2))
    assert angle_deg(got32.normal, n2).max() < 0.01
    # blocks are independent: any chunk size gives the same answer
    small = estimate(b, dz, valid, NormalSettings(chunk=3))
    for a, c in zip((got.normal, got.albedo, got.inliers, got.fallback),
                    (small.normal, small.albedo, small.inliers, small.fallback)):
        np.testing.assert_array_equal(a, c)


def test_a_flat_normal_map_is_the_plane_frame(rng):
    """separate writes +z normals for a flat sample (and under point lights, where `auto` estimates none): the
    capture then gives no shading frames, so no stage turns every direction by the identity, and the directions
    are bitwise those of a capture without normals; one tilted point turns them all into frames."""
    from facetsynth.geometry.plane import PlaneGrid
    from facetsynth.stages.common import RectifiedCapture
    grid = PlaneGrid(0.05, 0.05, 4, 3)
    lights = np.column_stack([rng.uniform(-0.2, 0.2, (7, 2)), rng.uniform(0.1, 0.3, 7), np.ones(7)])
    plain = RectifiedCapture(folder=None, grid=grid, visible=np.ones(12, bool), lights=lights,
                             light_intensities=np.ones((7, 3)), view_point=np.array([0.1, -0.2, 0.5, 1.0]),
                             frame_files=[], truth_scene=None)
    flat = dataclasses.replace(plain, normals=np.tile([0.0, 0.0, 1.0], (12, 1)))
    index = np.arange(2, 9)
    assert plain.frames(index) is None and flat.frames(index) is None and not flat.tilted
    np.testing.assert_array_equal(flat.light_directions(index)[0], plain.light_directions(index)[0])
    np.testing.assert_array_equal(flat.view_directions(True, index), plain.view_directions(True, index))
    normals = flat.normals.copy()
    normals[5] = [0.1, 0.0, np.sqrt(0.99)]
    tilted = dataclasses.replace(plain, normals=normals)
    assert tilted.tilted and tilted.frames(index).shape == (7, 3, 3)
    wi = tilted.light_directions(index)[0]
    np.testing.assert_allclose(wi[3], to_local(shading_frames(normals[5]), plain.light_directions(index)[0][3]),
                               atol=1e-15)
    np.testing.assert_array_equal(wi[:3], plain.light_directions(index)[0][:3])     # +z points: the identity
