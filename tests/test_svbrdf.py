"""The fitted SVBRDF folder and its loader: eq. 6 with tabulated NDFs (DESIGN.md sec. 4)."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import facetsynth
from facetsynth.errors import InputError
from facetsynth.grid import DirectionGrid
from facetsynth.plane import PlaneGrid
from facetsynth.scene import MaterialMaps
from facetsynth.svbrdf import SVBRDF, tabulate_truth

PLANE = PlaneGrid(0.1, 0.08, 5, 4)
P = PLANE.rows * PLANE.cols


def random_maps(seed=0):
    rng = np.random.default_rng(seed)
    return MaterialMaps(kd=rng.uniform(0.05, 0.5, (P, 3)), ks=rng.uniform(0.2, 1.0, (P, 3)),
                        eta=rng.uniform(1.2, 3.0, P), alpha_u=rng.uniform(0.15, 0.5, P),
                        alpha_v=rng.uniform(0.15, 0.5, P), phi_frame=rng.uniform(0, np.pi, P),
                        region=np.zeros(P, int))


def upper(rng, n):
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def truth_model():
    maps = random_maps()
    return maps, tabulate_truth(maps, DirectionGrid(32, 128), PLANE)


def test_eval_with_the_true_tabulated_ndf_equals_eq6(truth_model):
    """The loader's only error against microfacet.rho is the NDF's tabulation (32 x 128, A on 16 x 32)."""
    maps, model = truth_model
    rng = np.random.default_rng(1)
    n = 20000
    index = rng.integers(0, P, n)
    points = PLANE.points3d().reshape(-1, 3)[index]
    wi, wo = upper(rng, n), upper(rng, n)
    rho = model.eval(points, wi, wo)
    truth = maps.take(index).rho(wi, wo)
    rel = np.abs(rho - truth) / truth
    assert np.median(rel) < 1e-3            # measured 2.3e-4
    assert np.percentile(rel, 99) < 0.05    # measured 0.03: tails of sharp lobes between cells
    spec_rel = np.abs((rho - truth)[:, 0]) / (truth[:, 0] - maps.kd[index, 0] / np.pi)
    assert np.median(spec_rel) < 0.01       # the specular part alone, measured 2.8e-3


def test_eval_broadcasts_over_points_and_directions(truth_model):
    _, model = truth_model
    rng = np.random.default_rng(2)
    points = PLANE.points3d()                                 # (rows, cols, 3)
    wi = upper(rng, 7)[:, None, None, :]                       # (7, 1, 1, 3)
    wo = np.array([0.0, -0.5, 0.8])
    out = model.eval(points, wi, wo)
    assert out.shape == (7, PLANE.rows, PLANE.cols, 3)
    np.testing.assert_allclose(out[3, 2, 1], model.eval(points[2, 1], wi[3, 0, 0], wo), rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(-1.0, 1.0), st.floats(0, 2 * np.pi), st.floats(0, 2 * np.pi),
       st.floats(-0.05, 0.05), st.floats(-0.04, 0.04), st.floats(0.0, 1.0))
def test_eval_is_reciprocal_non_negative_and_finite(truth_model_cached, zi, zo, pi_, po, x, y, mix):
    """Property test: including grazing (z = 0) and below-horizon directions."""
    model = truth_model_cached
    wi = np.array([np.sqrt(1 - zi * zi) * np.cos(pi_), np.sqrt(1 - zi * zi) * np.sin(pi_), zi])
    wo = np.array([np.sqrt(1 - zo * zo) * np.cos(po), np.sqrt(1 - zo * zo) * np.sin(po), zo])
    point = np.array([x, y, 0.0])
    a, b = model.eval(point, wi, wo), model.eval(point, wo, wi)
    assert np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_array_equal(a, b)
    if zi <= 0 or zo <= 0:
        assert (a == 0).all()


@pytest.fixture(scope="module")
def truth_model_cached(truth_model):
    return truth_model[1]


def test_grazing_below_horizon_off_sample_and_degenerate_directions(truth_model):
    _, model = truth_model
    centre = np.zeros(3)
    graze = np.array([1.0, 0.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    assert np.isfinite(model.eval(centre, graze, up)).all()
    assert (model.eval(centre, graze, up) == 0).all()                     # i.n = 0: no light arrives
    tiny = np.array([1.0, 0.0, 1e-9])
    assert np.isfinite(model.eval(centre, tiny, tiny)).all()
    assert (model.eval(centre, -up, up) == 0).all()                       # i = -o
    assert (model.eval(np.array([0.2, 0.0, 0.0]), up, up) == 0).all()     # off the sample
    assert np.isfinite(model.eval(centre, np.zeros(3), up)).all()          # a zero vector is not a direction


def test_folder_round_trip_and_clear_errors(truth_model, tmp_path):
    _, model = truth_model
    model.save(tmp_path / "svbrdf", provenance={"test": True})
    names = {p.name for p in (tmp_path / "svbrdf").iterdir()}
    assert {"kd.exr", "ks.exr", "eta.exr", "ndf.npy", "projected_area.npy", "neighbours.npy", "weights.npy",
            "representatives.npy", "model.json"} <= names
    loaded = facetsynth.SVBRDF.load(tmp_path / "svbrdf")
    rng = np.random.default_rng(3)
    pts = PLANE.points3d().reshape(-1, 3)
    wi, wo = upper(rng, P), upper(rng, P)
    np.testing.assert_allclose(loaded.eval(pts, wi, wo), model.eval(pts, wi, wo), rtol=1e-6)
    (tmp_path / "svbrdf" / "weights.npy").unlink()
    with pytest.raises(InputError, match="weights.npy"):
        SVBRDF.load(tmp_path / "svbrdf")
    with pytest.raises(InputError, match="model.json"):
        SVBRDF.load(tmp_path / "nothing-here")


def test_eq18_mixture_of_representatives_is_the_mixture_of_ndfs(truth_model):
    """A point mixing two representatives evaluates the mixed NDF and the mixed A of eq. 5."""
    maps, model = truth_model
    mixed = SVBRDF(plane=PLANE, grid=model.grid, kd=model.kd, ks=model.ks, eta=model.eta, ndf=model.ndf,
                   area=model.area, neighbours=np.stack([model.neighbours[:, 0], np.roll(model.neighbours[:, 0], 1)], 1),
                   weights=np.tile([0.3, 0.7], (P, 1)))
    rng = np.random.default_rng(4)
    wi, wo = upper(rng, 50), upper(rng, 50)
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    idx = np.full(50, 5)
    d = mixed.ndf_at(idx, h)
    expected = 0.3 * model.ndf_at(idx, h) + 0.7 * model.ndf_at(idx - 1, h)
    np.testing.assert_allclose(d, expected, rtol=1e-12)
    a, b = mixed.eval_index(idx, wi, wo), mixed.eval_index(idx, wo, wi)
    np.testing.assert_array_equal(a, b)
