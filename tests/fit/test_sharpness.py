"""Lobe sharpness from the samples, and the direction grid it calls for (facetsynth.fit.sharpness, issue 7)."""

import numpy as np
import pytest

from facetsynth.models import microfacet
from facetsynth.fit.sharpness import grid_resolution, lobe_widths


def ggx_samples(alpha_u, alpha_v, phi_frame, n_lights=300, view_theta_deg=50.0):
    """Half vectors of a dense grid of light directions seen from one view, and D there (one point)."""
    t = np.radians(view_theta_deg)
    o = np.array([0.0, -np.sin(t), np.cos(t)])
    x, y = np.meshgrid(np.linspace(-2.0, 2.0, n_lights), np.linspace(-2.0, 2.0, n_lights))
    wi = np.stack([x.ravel(), y.ravel() + np.tan(t), np.full(x.size, 1.0)], -1)   # lights round the mirror direction
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    h = microfacet.half_vector(wi, np.broadcast_to(o, wi.shape))
    return h[None], microfacet.ndf(h, alpha_u, alpha_v, phi_frame)[None]


@pytest.mark.parametrize("alpha_u, alpha_v, phi", [(0.1, 0.1, 0.0), (0.1, 0.32, 0.0), (0.32, 0.1, 0.7),
                                                   (0.05, 0.25, 1.2)])
def test_half_widths_of_a_ggx_lobe_are_its_half_maximum_ellipse(alpha_u, alpha_v, phi):
    """GGX (with eq. 1's cos^4) is at half maximum where tan^2 = (sqrt 2 - 1) / (1/alpha^2 - sqrt 2) along
    each axis: with lights about 0.4 deg apart (in half-vector slope) the narrow half-width comes out within
    3 %, the broad one within 8 % (its far edge is sampled where the lights' half vectors crowd)."""
    h, d = ggx_samples(alpha_u, alpha_v, phi)
    narrow, broad, n = lobe_widths(h, d)
    a, b = sorted((alpha_u, alpha_v))
    alpha = np.array([a, b])
    expected = np.degrees(np.arctan(np.sqrt((np.sqrt(2) - 1) / (1 / alpha**2 - np.sqrt(2)))))
    assert n[0] >= 10
    np.testing.assert_allclose(narrow[0], expected[0], rtol=0.03)      # measured <= 1.5 %: what the grid uses
    np.testing.assert_allclose(broad[0], expected[1], rtol=0.08)       # measured <= 6 %


def test_no_lobe_gives_nan_widths_and_the_coarsest_grid():
    """A diffuse point (no specular sample) and a lobe narrower than the lights (one sample above half
    maximum) are not resolved: NaN widths, and the grid takes its lower bound."""
    h, d = ggx_samples(0.2, 0.2, 0.0)
    zero = np.zeros_like(d)
    spike = np.zeros_like(d)
    spike[0, 100] = 1.0
    narrow, broad, n = lobe_widths(np.concatenate([h, h]), np.concatenate([zero, spike]))
    assert np.isnan(narrow).all() and np.isnan(broad).all() and list(n) == [0, 1]
    assert grid_resolution(float(narrow[0]), 1.3, (16, 64)) == (16, 64)


def test_sharper_lobes_get_finer_grids_within_bounds():
    """cells_per_lobe rings per narrow half-width, a multiple of 8, n_phi = 4 n_theta, clipped to the range."""
    assert grid_resolution(3.7, 1.3, (16, 64)) == (32, 128)         # the demo's copper (alpha 0.10)
    assert grid_resolution(2.5, 1.3, (16, 64)) == (48, 192)         # satin's weft (alpha 0.07)
    assert grid_resolution(1.0, 1.3, (16, 64)) == (64, 256)         # clipped
    assert grid_resolution(20.0, 1.3, (16, 64)) == (16, 64)         # clipped
    sizes = [grid_resolution(w, 1.3, (8, 128))[0] for w in (1.0, 2.0, 4.0, 8.0)]
    assert sizes == sorted(sizes, reverse=True) and len(set(sizes)) == 4
