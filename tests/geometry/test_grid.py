"""facetsynth.geometry.grid: the polar direction grid, its bilinear lookup and the compiled forms of both (issue 30:
one implementation per formula, each compiled kernel checked against its numpy form)."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from facetsynth.models import microfacet
from facetsynth.geometry.grid import DirectionGrid, bilinear_at, polar_coordinates, turn


def random_directions(n: int, seed: int = 0, below: bool = False) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    if not below:
        d[:, 2] = np.abs(d[:, 2])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@numba.njit(cache=True)
def _compiled_lookup(table, d, n_theta, n_phi):
    out = np.empty(d.shape[0])
    for k in range(d.shape[0]):
        t, p = polar_coordinates(d[k, 0], d[k, 1], d[k, 2], n_theta, n_phi)
        out[k] = bilinear_at(table, t, p, n_theta, n_phi)
    return out


@pytest.mark.parametrize("shape", [(32, 128), (16, 64), (1, 8)])
def test_compiled_lookup_is_the_numpy_lookup(shape):
    """bilinear_at(polar_coordinates(d)) is DirectionGrid.lookup(d), at the pole, the horizon, below it and at
    the phi seam, to rounding."""
    grid = DirectionGrid(*shape)
    table = np.random.default_rng(1).random(shape)
    d = np.concatenate([random_directions(5000, below=True),
                        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, -1e-12, 0.3], [0.0, 1.0, -0.5]]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(_compiled_lookup(table.ravel(), d, *shape), grid.lookup(table, d),
                               rtol=1e-12, atol=1e-12)
    t, p = grid.coordinates(d)
    tc = np.array([polar_coordinates(*v, *shape) for v in d[:50]])
    np.testing.assert_allclose(tc, np.stack([t[:50], p[:50]], -1), rtol=0, atol=1e-12)


def test_lookup_reproduces_cell_centres_and_linear_functions():
    """At cell centres the lookup returns the table; a function linear in (theta, phi) between centres is
    interpolated exactly; the weights of every direction sum to 1."""
    grid = DirectionGrid(16, 64)
    table = np.random.default_rng(2).random(grid.shape)
    np.testing.assert_allclose(grid.lookup(table, grid.directions.reshape(-1, 3)), table.ravel(), atol=1e-12)
    linear = np.broadcast_to(grid.theta[:, None] * 3.0, grid.shape)       # linear in theta, periodic in phi
    d = random_directions(2000, seed=3)
    theta = np.arccos(d[:, 2])
    inside = (theta > grid.theta[0]) & (theta < grid.theta[-1])
    np.testing.assert_allclose(grid.lookup(linear, d)[inside], 3.0 * theta[inside], atol=1e-9)
    np.testing.assert_allclose(grid.bilinear(d).weights.sum(axis=0), 1.0, atol=1e-12)


def test_solid_angles_integrate_to_two_pi_and_cosine_to_pi():
    grid = DirectionGrid(32, 128)
    for g in (grid, DirectionGrid(7, 9)):
        assert g.solid_angles.sum() == pytest.approx(2 * np.pi, rel=1e-12)
    assert grid.integrate(grid.directions[..., 2]) == pytest.approx(np.pi, rel=1e-3)


def test_rotating_a_tabulated_ndf_is_rotating_its_frame_and_rotates_back():
    """rotate(f, phi)(h) = f(R(phi) h) (eq. 13): exact for whole sectors, linear between them."""
    grid = DirectionGrid(32, 128)

    def table(phi):
        return microfacet.ndf(grid.directions, 0.1, 0.4, phi)

    k = 5
    np.testing.assert_allclose(grid.rotate(table(0.0), k * grid.d_phi), table(-k * grid.d_phi), rtol=1e-9)
    np.testing.assert_array_equal(grid.rotate(grid.rotate(table(0.3), k * grid.d_phi), -k * grid.d_phi), table(0.3))
    d = grid.directions
    f = 1.0 + 0.5 * d[..., 0] + 0.3 * d[..., 1] ** 2 + d[..., 2]     # a fractional turn: linear along phi
    back = grid.rotate(grid.rotate(f, 0.37), -0.37)
    assert np.abs(back - f).max() < 1e-3
    np.testing.assert_allclose(grid.rotate(f, k * grid.d_phi).ravel(),
                               grid.lookup(f, turn(d.reshape(-1, 3), k * grid.d_phi)), atol=1e-9)


# ---------------------------------------------------------------------------- shared direction helpers
# The paper's direction grid and view, and direction constructors: used by the tests of the modules that
# work on directions (test_partial_ndf, test_separation, test_stages, test_svbrdf, test_ward_batched, ...).
GRID = DirectionGrid(32, 128)
O = np.array([0.0, -0.8, 0.6])                  # the paper's view, 53 deg from vertical


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sph(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    t, p = np.broadcast_arrays(t, p)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def upper(rng, n):
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    return unit(d)
