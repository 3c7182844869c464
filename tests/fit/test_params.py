"""Remaining parameters (paper 002 sec. 5.4): ks, normalised NDF, eq. 5 shadowing, eta by LM on eqs. 19-20."""

import numpy as np
import pytest

from facetsynth.models import microfacet
from facetsynth.fit import params
from facetsynth.geometry.grid import DirectionGrid
from facetsynth.fit.partial_ndf import SHADOWING_GRID
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.truth.scene import MaterialMaps
from facetsynth.models.svbrdf import tabulate_truth

GRID = DirectionGrid(32, 128)
O = np.array([0.0, -np.sin(np.radians(60)), np.cos(np.radians(60))])   # the rig's view, 60 deg from vertical
ALPHA = (0.25, 0.4, 0.5)                                                # alpha_u, alpha_v, frame azimuth


def grazing_lights(n_theta=9, n_phi=72, lo=80.0, hi=88.0):
    """Light directions steeper than the partial NDF's grazing_deg (80): the data eq. 19 uses."""
    t, p = np.meshgrid(np.radians(np.linspace(lo, hi, n_theta)), np.linspace(0, 2 * np.pi, n_phi, endpoint=False))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)


def analytic_material(eta):
    return MaterialMaps(kd=np.zeros((1, 3)), ks=np.full((1, 3), 0.8), eta=np.array([eta]),
                        alpha_u=np.array([ALPHA[0]]), alpha_v=np.array([ALPHA[1]]), phi_frame=np.array([ALPHA[2]]),
                        region=np.zeros(1, int))


def measured_fresnel_samples(eta, ndf_carries_fresnel_at=None):
    """(F_m, c, c_ref) of eq. 20 for the grazing samples of an analytic GGX material seen from O.

    The measured rho_s comes from the closed-form eq. 6; the model's D, S and ks
    from the NDF tabulated on GRID (ks and D as sec. 5.4 computes them). With
    ``ndf_carries_fresnel_at`` = c_ref, the tabulated NDF is scaled by F(c_ref)
    as the partial NDF of eq. 11 (F = 1 assumed) carries it.
    """
    maps = analytic_material(eta)
    wi = grazing_lights()
    wo = np.broadcast_to(O, wi.shape)
    rho_s = maps.rho(wi, wo).mean(axis=-1)                       # kd = 0: the specular part
    model = tabulate_truth(maps, GRID, PlaneGrid(0.1, 0.1, 1, 1))
    index = np.zeros(len(wi), np.intp)
    spec, c = model.specular_terms(index, wi, wo)
    ks = 0.8
    c_ref = None
    if ndf_carries_fresnel_at is not None:
        c_ref = np.full(len(wi), ndf_carries_fresnel_at)
        ks = ks * microfacet.fresnel(ndf_carries_fresnel_at, eta)
    d = model.ndf_at(index, microfacet.half_vector(wi, wo))
    lobe = d >= 0.05 * model.ndf.max()
    f_m = params.measured_fresnel(rho_s, ks * spec)
    return f_m[lobe], c[lobe], None if c_ref is None else c_ref[lobe]


def test_ks_normalisation_and_shadowing_from_a_tabulated_ndf():
    table = 0.37 * microfacet.ndf(GRID.directions, *ALPHA)
    normalised, ks = params.normalise(table, GRID)
    assert ks == pytest.approx(0.37, rel=2e-3)                    # sec. 5.4: ks = integral (n.h) D
    assert params.specular_coefficient(normalised, GRID) == pytest.approx(1.0, rel=1e-12)
    area = params.projected_area(normalised, GRID)
    k = SHADOWING_GRID.directions.reshape(-1, 3)
    truth = microfacet.projected_area(k, *ALPHA).reshape(SHADOWING_GRID.shape)
    np.testing.assert_allclose(area, truth, rtol=0.01)            # eq. 5 vs closed-form Smith
    s = params.shadowing(area, k)
    np.testing.assert_allclose(s, microfacet.shadowing(k, *ALPHA), atol=0.01)


@pytest.mark.parametrize("eta", [1.2, 1.5, 2.0, 2.5, 3.0])
def test_eta_recovery_on_an_analytic_material_eq19_as_printed(eta):
    """NDF and ks free of Fresnel: F_m of eq. 20 is F of eq. 3, LM finds eta."""
    f_m, c, _ = measured_fresnel_samples(eta)
    assert len(f_m) > 40 and c.max() < 0.5                          # grazing samples only
    fit = params.fit_eta(f_m, c)
    assert fit.constrained and fit.samples == len(f_m)
    assert fit.eta == pytest.approx(eta, abs=0.015)                  # measured: <= 0.011 (D tabulated on 32 x 128)


@pytest.mark.parametrize("eta", [1.2, 1.6, 2.2, 3.0])
def test_eta_recovery_when_the_ndf_scale_carries_fresnel_at_the_lobe(eta):
    """The pipeline's case (module note): ks D carries F(|o.n|); the ratio model recovers eta."""
    f_m, c, c_ref = measured_fresnel_samples(eta, ndf_carries_fresnel_at=O[2])
    fit = params.fit_eta(f_m, c, c_ref)
    assert fit.constrained
    assert fit.eta == pytest.approx(eta, abs=0.005)                  # measured: <= 0.0014
    # the printed eq. 19 cannot explain such data: its residual is far larger
    assert params.fit_eta(f_m, c).rms > 20 * fit.rms


def test_eta_with_noise_stays_close_and_unconstrained_data_fall_back_to_the_default():
    rng = np.random.default_rng(0)
    f_m, c, _ = measured_fresnel_samples(1.8)
    noisy = f_m * (1 + 0.05 * rng.standard_normal(f_m.shape))
    fit = params.fit_eta(noisy, c)
    assert fit.constrained and abs(fit.eta - 1.8) < 0.1 and fit.std < 0.05
    few = params.fit_eta(f_m[:3], c[:3], default=1.55)             # too few grazing samples
    assert not few.constrained and few.eta == 1.55 and "samples" in few.reason
    flat = params.fit_eta(np.full(40, 1.0), np.full(40, 0.4))      # F = 1 at c = 0.4: no eta in range explains it
    assert not flat.constrained and flat.eta == params.ETA_DEFAULT
    lo, hi = params.ETA_BOUNDS
    assert params.fit_eta(f_m, c, bounds=(lo, hi)).eta <= hi


# --- the params stage on a stand-in for issue 4's outputs -------------------------------
# The stand-in makes one representative per region with weight 1 and tabulates the
# region's TRUE NDF as its "completed" NDF, in the partial NDF's scale (times mean ks
# and a Fresnel factor, as eq. 11 leaves it), with the cosine of that Fresnel factor
# per cell as synthesis records it. It tests the stage's plumbing and eta fit, not synthesis.

STANDIN_SCENE = """\
name: standin
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: low-eta
    where: {rect: {x: [-0.05, 0.0], y: [-0.05, 0.05]}}
    kd: [0.2, 0.1, 0.1]
    ks: [0.6, 0.5, 0.4]
    eta: 1.35
    alpha: [0.25, 0.4]
    frame: {angle_deg: 20}
  - name: high-eta
    where: {rect: {x: [0.0, 0.05], y: [-0.05, 0.05]}}
    kd: [0.1, 0.2, 0.1]
    ks: [0.5, 0.5, 0.5]
    eta: 2.6
    alpha: [0.3, 0.3]
    frame: {angle_deg: 0}
"""


def write_standin(folder, fresnel_in_ndf="lobe"):
    """A rectified capture (geometry.json, separate/resample outputs) and cluster/synthesize stand-ins.

    ``fresnel_in_ndf``: "lobe", the NDF carries F at |o.n| in every cell (as if synthesis had brought every
    cell from a view at that cosine); "own", F(|o.h|) of the capture's own view everywhere (no synthesis).
    """
    from facetsynth.io.fileio import write_exr, write_json
    from facetsynth.models.render import light_geometry
    from facetsynth.truth.scene import Scene
    from facetsynth.stages.common import RectifiedCapture

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.yaml").write_text(STANDIN_SCENE)
    plane = PlaneGrid(0.1, 0.1, 8, 8)
    view = np.array([0.0, -0.866, 0.5])
    # the rig's lights (y from 0 to 0.2 m, 4 cm up) plus a low ring on the far side: grazing coverage
    xs, ys = np.meshgrid(np.linspace(-0.1, 0.1, 9), np.linspace(0.0, 0.2, 9))
    rig = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.04)], -1)
    az = np.radians(np.linspace(30, 150, 25))
    ring = np.concatenate([np.stack([0.5 * np.cos(az), 0.5 * np.sin(az), np.full(az.size, z)], -1)
                           for z in (0.02, 0.04, 0.06, 0.08)])
    lights = np.concatenate([rig, ring])
    frames = [{"light": {"position": p.tolist(), "intensity": [1.0, 1.0, 1.0]}, "file": f"frames/{q:04d}.exr"}
              for q, p in enumerate(lights)]
    write_json(folder / "geometry.json", {"grid": plane.to_dict(), "visible": [True] * 64, "frames": frames,
                                          "view_point": [*view.tolist(), 1.0], "truth": {"scene": "scene.yaml"}})
    capture = RectifiedCapture.load(folder / "geometry.json")
    truth = Scene.load(folder / "scene.yaml").parameters(capture.points[:, :2])
    wi, _ = light_geometry(capture.points[:, None, :], lights[None])
    o = capture.view_directions(True)
    rho = truth.take((slice(None), None)).rho(wi, o[:, None, :])
    np.save(folder / "specular.npy", (rho - truth.kd[:, None, :] / np.pi).astype(np.float32))
    np.save(folder / "valid.npy", np.ones(rho.shape[:2], bool))
    np.save(folder / "colour.npy", (truth.ks / truth.ks.mean(1, keepdims=True)).astype(np.float32))
    write_exr(folder / "kd.exr", {"RGB": truth.kd.reshape(8, 8, 3)})
    # two representatives per region (corner points; each owns half the region's rows): eta's interval
    # needs at least two independent units, and a material of one keeps the default
    reps = np.array([0, 56, 7, 63])
    region = truth.region
    nb = np.zeros((64, 16), np.int32)
    nb[:, 0] = 2 * (region != 0) + (np.arange(64) >= 32)
    w = np.zeros((64, 16), np.float32)
    w[:, 0] = 1.0
    np.save(folder / "representatives.npy", reps)
    np.save(folder / "neighbours.npy", nb)
    np.save(folder / "weights.npy", w)
    h = GRID.directions.reshape(1, -1, 3)
    rt = truth.take(reps)
    d = rt.take((slice(None), None)).ndf(h)                                    # (2, T*F)
    if fresnel_in_ndf == "lobe":
        cosine = np.broadcast_to(o[reps, 2][:, None], d.shape)
    else:                                                                      # eq. 11 from the own view, everywhere
        cosine = np.abs(np.sum(h * o[reps][:, None, :], -1))
    f = microfacet.fresnel(cosine, rt.eta[:, None])
    shape = (len(reps),) + GRID.shape
    np.save(folder / "ndf.npy", (rt.ks.mean(1)[:, None] * f * d).reshape(shape).astype(np.float32))
    np.save(folder / "fresnel_cosine.npy", cosine.reshape(shape).astype(np.float32))
    np.save(folder / "confidence.npy", np.ones(shape, np.float32))        # every cell synthesized
    write_json(folder / "grid.json", GRID.to_dict())
    return folder, truth


def run_params(folder, **settings):
    from facetsynth.stages.params import Inputs, Outputs, Settings, run
    run(Inputs(geometry=folder / "geometry.json", kd=folder / "kd.exr", specular=folder / "specular.npy",
               valid=folder / "valid.npy", colour=folder / "colour.npy",
               representatives=folder / "representatives.npy", neighbours=folder / "neighbours.npy",
               weights=folder / "weights.npy", ndf=folder / "ndf.npy",
               fresnel_cosine=folder / "fresnel_cosine.npy",
               synthesis_confidence=folder / "confidence.npy", grid=folder / "grid.json"),
        Outputs(svbrdf=folder / "svbrdf", metrics=folder / "metrics.json"), Settings(**settings))
    import json
    return json.loads((folder / "metrics.json").read_text())


def test_params_stage_recovers_eta_and_ks_per_region_from_grazing_data(tmp_path):
    from facetsynth.models.svbrdf import SVBRDF
    folder, truth = write_standin(tmp_path / "lobe")
    metrics = run_params(folder)
    model = SVBRDF.load(folder / "svbrdf")
    assert metrics["materials"] == 2 and metrics["representatives_eta_fitted"] == 4 and model.eta_fitted.all()
    assert np.abs(model.eta - truth.eta).max() < 0.05                     # measured 0.01
    assert metrics["eta_abs_error_median"] < 0.03
    np.testing.assert_allclose(model.ks, truth.ks, rtol=0.03)            # D / F(cosine, eta): the physical ks
    np.testing.assert_allclose(model.kd, truth.kd, rtol=1e-5)
    assert metrics["grazing_samples"] > 100


def test_params_stage_keeps_the_default_where_the_ndf_holds_its_own_views_fresnel(tmp_path):
    """An NDF that carries F(|o.h|) of the capture's own view in every cell explains the grazing samples
    for any eta (c = |i.h| = |o.h|): eta is not identifiable, and the stage says so rather than fit noise."""
    folder, truth = write_standin(tmp_path / "own", fresnel_in_ndf="own")
    metrics = run_params(folder, eta_default=1.45)
    assert metrics["representatives_eta_fitted"] == 0
    assert all(not r["constrained"] and r["reason"] for r in metrics["per_material"])


def test_params_stage_without_grazing_coverage_keeps_and_records_the_default(tmp_path):
    """No light beyond grazing_deg: eta is not constrained; the default is kept and recorded."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.svbrdf import SVBRDF
    folder, truth = write_standin(tmp_path / "nograzing")
    metrics = run_params(folder, grazing_deg=89.9, eta_default=1.45)
    model = SVBRDF.load(folder / "svbrdf")
    assert metrics["representatives_eta_fitted"] == 0 and metrics["points_eta_fitted_fraction"] == 0.0
    assert not model.eta_fitted.any()
    np.testing.assert_allclose(model.eta, 1.45, rtol=1e-7)           # float32 EXR
    assert all("samples" in r["reason"] for r in metrics["per_material"])
    assert (read_exr(folder / "svbrdf" / "eta.exr")[0]["eta_fitted"] == 0).all()
    assert model.info["eta"]["default"] == 1.45


def test_negative_eq18_weights_give_a_valid_model(tmp_path):
    """Eq. 18's least-squares weights may be negative; the model's mixtures must stay non-negative NDFs
    with A(k) > 0 (regression: a signed mixture gave A(k) = -0.7 and unbounded rho on wallpaper)."""
    from facetsynth.stages.common import RectifiedCapture
    from facetsynth.stages.params import build_model
    folder, truth = write_standin(tmp_path / "neg")
    capture = RectifiedCapture.load(folder / "geometry.json")
    table = np.load(folder / "ndf.npy").astype(float)
    nb = np.zeros((64, 3), int)
    nb[:, 1] = 1
    w = np.tile([1.9, -1.2, 0.3], (64, 1))                        # sums to 1, one weight negative
    model, ks_pt, ks_rep = build_model(table, GRID, nb, w, truth.kd, np.ones((64, 3)), capture)
    assert (model.weights >= 0).all()
    np.testing.assert_allclose(model.weights.sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(ks_pt, np.clip((w * ks_rep[nb]).sum(1), 0, None))   # eq. 18's ks
    rng = np.random.default_rng(5)
    k = rng.normal(size=(64 * 50, 3))
    k[:, 2] = np.abs(k[:, 2])
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    index = np.repeat(np.arange(64), 50)
    assert model.area_at(index, k).min() > 0.05
    rho = model.eval_index(index, k, k[::-1])
    assert np.isfinite(rho).all() and (rho >= 0).all() and rho.max() < 100


# --- eta's profile-likelihood interval (issue 13 item 6) ---------------------------------

def ratio_samples(n, c_range, c_ref=0.6, eta=1.8, noise=0.05, seed=0):
    """Synthetic eq. 19-20 data in the pipeline's form: F_m = F(c, eta) / F(c_ref, eta) x (1 + noise N(0, 1))."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(*c_range, n)
    cr = np.full(n, c_ref)
    f_m = microfacet.fresnel(c, eta) / microfacet.fresnel(cr, eta) * (1 + noise * rng.standard_normal(n))
    return f_m, c, cr


def test_eta_rss_is_eq19s_sum_of_squares():
    f_m, c, cr = ratio_samples(50, (0.3, 0.5))
    w = np.linspace(0.5, 1.5, 50)
    for eta in (1.3, 2.2):
        expected = np.sum(w * (microfacet.fresnel(c, eta) / microfacet.fresnel(cr, eta) - f_m) ** 2)
        assert params.eta_rss([eta], f_m, c, cr, w)[0] == pytest.approx(expected, rel=1e-12)
    assert params.eta_rss([1.8], microfacet.fresnel(c, 1.8), c)[0] == pytest.approx(0.0, abs=1e-20)


def test_eta_interval_covers_the_truth_and_shrinks_with_more_and_grazier_samples():
    """5 % multiplicative noise on F_m, truth 1.8: the 95 % interval covers it (in 95 % of draws), holds the LM fit,
    and narrows with 10 x the samples and with grazier light (the F ratio varies more with eta there)."""
    base = params.eta_profile(*ratio_samples(200, (0.35, 0.47)))
    more = params.eta_profile(*ratio_samples(2000, (0.35, 0.47)))
    grazier = params.eta_profile(*ratio_samples(200, (0.10, 0.30)))
    for iv in (base, more, grazier):
        assert iv.lo < 1.8 < iv.hi and iv.identifiable(0.2) and not (iv.open_below or iv.open_above)
        assert iv.threshold == pytest.approx(iv.rss_min * (1 + params.CHI2_1_95 / (iv.units - 1)))
    assert more.width < 0.5 * base.width and grazier.width < 0.7 * base.width   # measured 0.007 / 0.012 / 0.024
    fit = params.fit_eta(*ratio_samples(200, (0.35, 0.47)))
    assert base.lo < fit.eta < base.hi and base.best == pytest.approx(fit.eta, abs=1e-4)
    assert base.width == pytest.approx(2 * 1.96 * fit.std, rel=0.15)      # near-quadratic profile: the Wald interval
    # the ends lie on the threshold
    f_m, c, cr = ratio_samples(200, (0.35, 0.47))
    np.testing.assert_allclose(params.eta_rss([base.lo, base.hi], f_m, c, cr), base.threshold, rtol=1e-5)
    covered = [params.eta_profile(*ratio_samples(150, (0.3, 0.47), seed=s)).lo < 1.8 <
               params.eta_profile(*ratio_samples(150, (0.3, 0.47), seed=s)).hi for s in range(40)]
    assert np.mean(covered) >= 0.85                                                  # nominal 0.95


def test_eta_interval_is_wide_where_the_data_do_not_constrain_eta():
    """Near-normal samples only: F(c) / F(c_ref) hardly depends on eta (c ~ c_ref): wide, not identifiable."""
    near_normal = params.eta_profile(*ratio_samples(200, (0.9, 1.0), c_ref=0.95))
    assert near_normal.width > 1.0 and not near_normal.identifiable(0.2)           # measured [1.12, 4.0]
    # groups: samples sharing an error are one unit; with one unit nothing is known
    f_m, c, cr = ratio_samples(200, (0.35, 0.47))
    one = params.eta_profile(f_m, c, cr, groups=np.zeros(200, int), bounds=(1.1, 3.0))
    assert (one.lo, one.hi, one.units) == (1.1, 3.0, 1) and not one.identifiable(0.2) and one.reason
    few = params.eta_profile(f_m, c, cr, groups=np.arange(200) % 3)
    many = params.eta_profile(f_m, c, cr)
    assert few.units == 3 and few.width > 2 * many.width                       # fewer independent units: wider
    none = params.eta_profile(np.zeros(0), np.zeros(0))
    assert (none.lo, none.hi) == params.ETA_BOUNDS and not none.identifiable(0.2)
    nan = params.eta_profile(np.full(10, np.nan), np.full(10, 0.4))
    assert nan.samples == 0 and not nan.identifiable(0.2)
    # data that want eta beyond the bound: the interval reaches it, open, and is not identifiable however narrow
    beyond = params.eta_profile(microfacet.fresnel(c, 6.0) / microfacet.fresnel(cr, 6.0), c, cr)
    assert beyond.open_above and beyond.hi == params.ETA_BOUNDS[1] and not beyond.identifiable(10.0)


def test_params_stage_records_eta_intervals_and_the_ndf_spread(tmp_path):
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.svbrdf import SVBRDF
    folder, truth = write_standin(tmp_path / "lobe")
    metrics = run_params(folder, max_eta_interval=0.2)
    model = SVBRDF.load(folder / "svbrdf")
    assert metrics["max_eta_interval"] == 0.2 and "chi2_1(0.95)" in metrics["eta_interval_method"]
    for record in metrics["per_material"]:
        lo, hi = record["eta_interval"]
        assert lo <= record["eta"] <= hi and record["eta_interval_width"] == pytest.approx(hi - lo)
        assert record["eta_interval_units"] == 2 and record["eta_identifiable"]   # two representatives, noise-free
    assert metrics["materials_eta_identifiable"] == 2     # measured [1.334, 1.367] (1.35), [2.502, 2.678] (2.6)
    channels = read_exr(folder / "svbrdf" / "eta.exr")[0]
    assert {"eta", "eta_fitted", "eta_lo", "eta_hi"} <= set(channels)
    assert model.eta_lo.shape == model.eta.shape and (model.eta_lo <= model.eta_hi).all()
    assert model.info["eta"]["intervals"]["per_material"][0]["interval"] == metrics["per_material"][0]["eta_interval"]
    # two regions, each one frame and two representatives of its true NDF, each point one of them with weight 1:
    # every point has the region's NDF, to the float32 tables' rounding (measured 2.8e-8)
    assert set(metrics["ndf_spread"]) == {"low-eta", "high-eta"} and metrics["ndf_spread_skipped"] == {}
    for v in metrics["ndf_spread"].values():
        assert v["points"] == 32 and v["median"] < 1e-6 and v["p90"] < 1e-6
    assert metrics["ndf_spread_max_median"] < 1e-6
    assert "nan" not in (folder / "metrics.json").read_text().lower()
    assert "infinity" not in (folder / "metrics.json").read_text().lower()


def test_params_stage_interval_unit_sets_n_of_the_test(tmp_path):
    """Grazing samples with 2 % noise: counted per sample, per point or per representative the interval covers
    the truth, and it widens as the units get fewer (the unit changes n of the test, nothing else)."""
    from facetsynth.stages.params import fit_eta
    from facetsynth.models.svbrdf import SVBRDF
    folder, truth = write_standin(tmp_path / "lobe")
    run_params(folder)
    model = SVBRDF.load(folder / "svbrdf")
    w18 = np.load(folder / "weights.npy").astype(float)
    samples = {"point": np.repeat(np.arange(64), 20), "f_m": np.ones(64 * 20), "c": np.full(64 * 20, 0.4),
               "c_ref": None}
    c = np.random.default_rng(3).uniform(0.1, 0.45, samples["c"].size)
    eta_true = np.where(truth.region[samples["point"]] == 0, 1.35, 2.6)
    samples.update(c=c, f_m=microfacet.fresnel(c, eta_true) * (1 + 0.02 * np.random.default_rng(4).standard_normal(c.size)))
    material = np.array([0, 0, 1, 1])
    widths = {}
    for unit in ("sample", "point", "representative"):
        eta, fitted, records, eta_rep, interval_rep = fit_eta(model, w18, samples, material, (1.05, 4.0), 1.5,
                                                              8, 0.15, 0.1, 0.2, interval_unit=unit)
        for r, true_eta in zip(records, (1.35, 2.6)):
            assert r["eta_interval"][0] < true_eta < r["eta_interval"][1], unit
        widths[unit] = [r["eta_interval_width"] for r in records]
        np.testing.assert_allclose(interval_rep[:, 0], [records[m]["eta_interval"][0] for m in material])
    for r in (0, 1):      # fewer units, a wider interval (n - 1 = 639, 31, 1 per material); measured widths
        # 0.003 / 0.014 / 0.076 (eta 1.35) and 0.021 / 0.098 / 0.54 (eta 2.6)
        assert 3 * widths["sample"][r] < widths["point"][r] < 0.2
        assert 3 * widths["point"][r] < widths["representative"][r]


def test_params_stage_keeps_eta_where_it_is_not_identifiable_and_says_so(tmp_path):
    """No grazing light: the default is kept as before, and the interval (the whole range) tells the user."""
    from facetsynth.models.svbrdf import SVBRDF
    folder, truth = write_standin(tmp_path / "nograzing")
    metrics = run_params(folder, grazing_deg=89.9, eta_default=1.45, eta_min=1.1, eta_max=3.5)
    model = SVBRDF.load(folder / "svbrdf")
    np.testing.assert_allclose(model.eta, 1.45, rtol=1e-7)
    for r in metrics["per_material"]:
        assert r["eta_interval"] == [1.1, 3.5] and not r["eta_identifiable"] and r["eta_interval_reason"]
    np.testing.assert_allclose(model.eta_lo, 1.1, rtol=1e-7)
    np.testing.assert_allclose(model.eta_hi, 3.5, rtol=1e-7)


def test_ndf_spread_skips_turning_frames_and_scores_a_constant_one():
    """A polar frame is one material at many rotations (skipped, said so); a constant frame is scored, and
    a point whose NDF differs from the rest shows in the spread."""
    from facetsynth.truth.scene import Scene
    from facetsynth.evaluation.params import ndf_spread
    scene = Scene.from_dict({"name": "two", "size": [0.1, 0.1], "regions": [
        {"name": "turned", "where": {"rect": {"x": [-0.05, 0.0], "y": [-0.05, 0.05]}}, "kd": [0.2, 0.2, 0.2],
         "ks": [0.5, 0.5, 0.5], "eta": 1.5, "alpha": [0.1, 0.3], "frame": {"polar": [0.0, 0.0]}},
        {"name": "straight", "where": {"rect": {"x": [0.0, 0.05], "y": [-0.05, 0.05]}}, "kd": [0.2, 0.2, 0.2],
         "ks": [0.5, 0.5, 0.5], "eta": 1.5, "alpha": [0.2, 0.2], "frame": {"angle_deg": 10}}]})
    plane = PlaneGrid(0.1, 0.1, 8, 8)
    maps = scene.parameters(plane.points3d().reshape(-1, 3)[:, :2])
    model = tabulate_truth(maps, DirectionGrid(16, 64), plane)
    visible = np.ones(64, bool)
    spread, skipped = ndf_spread(model, maps, ["turned", "straight"], visible)
    spread_all = spread
    assert set(spread) == {"straight"} and "turns" in skipped["turned"]
    assert spread["straight"] == {"points": 32, "median": 0.0, "p90": 0.0}
    # one point of the straight region given the turned region's first NDF: the spread sees it
    straight = np.flatnonzero(maps.region == 1)
    odd = model.neighbours.copy()
    odd[straight[0]] = model.neighbours[np.flatnonzero(maps.region == 0)[0]]
    changed = type(model)(**{**{f: getattr(model, f) for f in ("plane", "grid", "kd", "ks", "eta", "ndf", "area",
                                                               "weights")}, "neighbours": odd})
    spread, _ = ndf_spread(changed, maps, ["turned", "straight"], visible, max_points=8)
    assert spread["straight"]["points"] == 8 and spread["straight"]["p90"] > 0.1
    # any material kind counts (a measured region has no true NDF, but its fitted NDFs still should agree)
    import dataclasses
    marked = dataclasses.replace(maps, analytic=maps.region == 0)
    assert ndf_spread(model, marked, ["turned", "straight"], visible)[0] == spread_all
    spread, skipped = ndf_spread(model, maps, ["turned", "straight"], ~(maps.region == 1))
    assert spread == {} and "no visible point" in skipped["straight"]


def test_svbrdf_folder_without_eta_interval_still_loads(tmp_path):
    """Backward compatibility: a folder written before the interval channels loads with eta_lo = eta_hi = None;
    one written with them round-trips."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.models.svbrdf import SVBRDF
    plane = PlaneGrid(0.1, 0.1, 2, 2)
    model = tabulate_truth(MaterialMaps(kd=np.full((4, 3), 0.1), ks=np.full((4, 3), 0.5), eta=np.full(4, 1.5),
                                        alpha_u=np.full(4, 0.2), alpha_v=np.full(4, 0.3), phi_frame=np.zeros(4),
                                        region=np.zeros(4, int)), DirectionGrid(8, 32), plane)
    model.save(tmp_path / "old")
    assert set(read_exr(tmp_path / "old" / "eta.exr")[0]) == {"eta", "eta_fitted"}
    old = SVBRDF.load(tmp_path / "old")
    assert old.eta_lo is None and old.eta_hi is None
    model.eta_lo, model.eta_hi = np.full(4, 1.4), np.full(4, 1.7)
    model.save(tmp_path / "new")
    new = SVBRDF.load(tmp_path / "new")
    np.testing.assert_allclose(new.eta_lo, 1.4, rtol=1e-7)
    np.testing.assert_allclose(new.eta_hi, 1.7, rtol=1e-7)
    x = np.array([[0.01, 0.01, 0.0]])
    wi, wo = np.array([[0.3, 0.0, 0.954]]), np.array([[-0.3, 0.1, 0.949]])
    np.testing.assert_array_equal(old.eval(x, wi, wo), new.eval(x, wi, wo))
    with pytest.raises(ValueError):
        SVBRDF(**{**{f: getattr(model, f) for f in ("plane", "grid", "kd", "ks", "eta", "ndf", "area", "neighbours",
                                                     "weights")}, "eta_lo": np.ones(3)})


def test_a_material_whose_eta_interval_is_the_whole_range_keeps_the_default():
    """A material of one representative (the points on a black marker, say) is one independent unit: the 95 %
    interval of eta is all of [eta_min, eta_max] and its LM fit is noise. It keeps the default, saying why;
    before, its fit (1.14 on ggx-tiles' markers) was divided out of its NDF, made that representative's ks 3.7,
    and eq. 18's negative weights took its neighbours' ks to 0.2 for 0.7. A material of three representatives
    whose samples agree keeps its fit."""
    from types import SimpleNamespace
    from facetsynth.stages.params import fit_eta
    rng = np.random.default_rng(3)
    owner = np.repeat([0, 1, 2, 3], [10, 10, 10, 10])                  # points -> representatives
    model = SimpleNamespace(ndf=np.zeros((4, 1, 1)), neighbours=owner[:, None], n_points=owner.size)
    point = np.repeat(np.arange(owner.size), 30)
    c = rng.uniform(0.12, 0.35, point.size)
    c_ref = np.full(point.size, 0.9)
    eta_true = np.where(owner[point] == 3, 1.2, 1.8)
    f_m = microfacet.fresnel(c, eta_true) / microfacet.fresnel(c_ref, eta_true)
    f_m = f_m * (1 + 0.02 * rng.standard_normal(point.size)) * (1 + 0.05 * rng.standard_normal(4))[owner[point]]
    samples = {"point": point, "f_m": f_m, "c": c, "c_ref": c_ref}
    eta, fitted, records, eta_rep, _ = fit_eta(model, np.ones((owner.size, 1)), samples, np.array([0, 0, 0, 1]),
                                              (1.05, 4.0), 1.5, 8, 0.15)
    assert records[0]["constrained"] and abs(records[0]["eta"] - 1.8) < 0.1
    assert not records[1]["constrained"] and records[1]["eta"] == 1.5 and eta_rep[3] == 1.5
    assert records[1]["eta_interval_open"] == [True, True] and "do not constrain" in records[1]["reason"]
    assert abs(records[1]["fitted_eta"] - 1.2) < 0.1                  # the fit is recorded, not used
    assert np.all(eta[owner == 3] == 1.5) and not fitted[owner == 3].any() and fitted[owner < 3].all()


# ---------------------------------------------------------------------------- numerical extremes (issue 7, part 2)
C_GRAZING = np.linspace(0.02, 0.5, 60)         # |i.h| of grazing samples


def test_eta_fit_at_the_extremes_of_eta():
    """Eq. 19 (as printed) on exact F: eta = 1.08 (near 1: F is tiny except at grazing) and 3.8 (metal-like)
    are recovered to 1e-3; eta = 6 lies beyond the bound 4.0, the fit runs to the bound and the default is
    kept and said; eta = 1 (no interface) gives F = 0, the fit runs to the lower bound, default kept."""
    for eta in (1.08, 3.8):
        fit = params.fit_eta(microfacet.fresnel(C_GRAZING, eta), C_GRAZING)
        assert fit.constrained and fit.eta == pytest.approx(eta, abs=1e-3) and np.isfinite(fit.std)
    beyond = params.fit_eta(microfacet.fresnel(C_GRAZING, 6.0), C_GRAZING, default=1.55)
    assert not beyond.constrained and beyond.eta == 1.55 and "bound" in beyond.reason
    none = params.fit_eta(microfacet.fresnel(C_GRAZING, 1.0), C_GRAZING, default=1.55)
    assert not none.constrained and none.eta == 1.55 and "bound" in none.reason
    # the ratio model of the pipeline (F at c over F at c_ref), near 1 and large
    for eta in (1.08, 3.8):
        c_ref = np.full(C_GRAZING.size, 0.6)
        f = microfacet.fresnel(C_GRAZING, eta) / microfacet.fresnel(0.6, eta)
        fit = params.fit_eta(f, C_GRAZING, c_ref)
        assert fit.constrained and fit.eta == pytest.approx(eta, abs=1e-3)


def test_eta_fit_on_samples_all_at_grazing_keeps_the_default():
    """Fresnel at grazing: at c = |i.h| -> 0, F -> 1 for every eta (F = 1 - O(c)), so samples all at
    c <= 1e-6, measured to 1e-4 (far better than the pipeline's F_m), carry no usable information on eta:
    the standard error is huge, the fit is unconstrained and keeps the default; everything finite."""
    c = np.linspace(0.0, 1e-6, 40)
    noise = 1 + 1e-4 * np.random.default_rng(2).standard_normal(40)
    fit = params.fit_eta(microfacet.fresnel(c, 2.0) * noise, c, default=1.45)
    assert not fit.constrained and fit.eta == 1.45 and fit.samples == 40
    assert np.isfinite(fit.rms) and fit.rms < 2e-4 and fit.std > 1.0


def test_eta_fit_on_noise_is_unconstrained():
    """LM on data that no eta explains (F_m log-normal, independent of c; and F_m with NaN / Inf entries
    mixed in): the fit ends without a trusted minimum, reports it unconstrained and keeps the default;
    the NaN / Inf samples are dropped (counted out of ``samples``), nothing non-finite leaves the fit."""
    rng = np.random.default_rng(3)
    f_m = np.exp(rng.normal(0.0, 1.5, C_GRAZING.size))
    fit = params.fit_eta(f_m, C_GRAZING, default=1.45)
    assert not fit.constrained and fit.eta == 1.45 and np.isfinite(fit.rms)
    good = microfacet.fresnel(C_GRAZING, 2.2)
    bad = good.copy()
    bad[[3, 9]] = np.nan
    bad[17] = np.inf
    fit = params.fit_eta(bad, C_GRAZING)
    assert fit.samples == C_GRAZING.size - 3 and fit.constrained and fit.eta == pytest.approx(2.2, abs=1e-3)
