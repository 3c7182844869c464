"""facetsynth.fit.separation (eqs. 8-9) and the separate stage at the numerical extremes (issue 7, part 2): eq. 8 up
to grazing light, eq. 9 with near-mirror and very rough lobes, saturated and NaN / Inf samples, a NaN frame. The
common cases are in tests/fit/test_reflectance.py."""

import numpy as np
import pytest

from facetsynth.models import microfacet
from facetsynth.geometry.plane import PlaneGrid
from facetsynth.fit.separation import brdf_samples, diffuse_level, specular_residual
from facetsynth.stages.common import RectifiedCapture

from test_grid import O, sph, unit
from test_stages import eq9_truth, one_material, rig_lights, write_rectified


def test_separate_stage_refuses_a_nan_frame_naming_the_pixel(tmp_path):
    """A NaN (or Inf) in a rectified frame is bad input: separate fails with an InputError naming the
    file and the first bad pixel, and writes nothing."""
    from facetsynth.io.errors import InputError
    from facetsynth.stages import separate

    def damage(q, rgb, saturated):
        if q == 3:
            rgb[2, 1, 0] = np.nan
        if q == 5:
            rgb[0, 0, 2] = np.inf

    geometry = write_rectified(tmp_path / "cap", one_material((0.2,) * 3, (0.5,) * 3), PlaneGrid(0.1, 0.1, 4, 4),
                               rig_lights(3, 3), damage=damage)
    with pytest.raises(InputError, match=r"0003\.exr.*1 pixel\(s\) are NaN or Inf \(first at row 2, col 1\)"):
        separate.run(separate.Inputs(geometry=geometry),
                     separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "s.npy", valid=tmp_path / "v.npy",
                                      metrics=tmp_path / "m.json"), separate.Settings(heldout_every=0))
    assert not (tmp_path / "kd.exr").exists() and not (tmp_path / "s.npy").exists()


def test_saturated_and_nan_samples_are_invalid_and_kd_comes_from_the_rest(tmp_path):
    """Eq. 9 with bad samples. (a) In the stage, a pixel flagged saturated in the rectified frame is an
    invalid sample and its point's kd comes from the other frames, exactly. (b) In the pure function, a
    NaN or Inf sample (even one passed as valid) is treated as invalid: kd is what the other samples give."""
    from facetsynth.io.fileio import read_exr
    from facetsynth.stages import separate
    kd = (0.3, 0.2, 0.1)

    def damage(q, rgb, saturated):
        if q % 2 == 0:                              # half the frames clip at cell (1, 1): a wrong, huge value
            rgb[1, 1] = 1e3
            saturated[1, 1] = 1.0

    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0.4,) * 3), PlaneGrid(0.1, 0.1, 3, 3),
                               rig_lights(5, 5), damage=damage)
    separate.run(separate.Inputs(geometry=geometry),
                 separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "s.npy", valid=tmp_path / "v.npy",
                                  metrics=tmp_path / "m.json"), separate.Settings(heldout_every=0))
    got = read_exr(tmp_path / "kd.exr")[0]["RGB"].reshape(-1, 3)
    valid = RectifiedCapture.load(geometry).validity(tmp_path / "v.npy")[:]
    assert valid[4, 1::2].all() and not valid[4, 0::2].any() and valid[[0, 1, 2, 3, 5, 6, 7, 8]].all()
    pts = PlaneGrid(0.1, 0.1, 3, 3).points3d().reshape(-1, 3)
    lights = rig_lights(5, 5)
    expected = np.array([eq9_truth(kd, (0.4,) * 3, lights, pt) for pt in pts])
    expected[4] = eq9_truth(kd, (0.4,) * 3, lights[1::2], pts[4])       # cell (1, 1): the odd frames only
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    # (b) the pure function
    rng = np.random.default_rng(4)
    lights = np.column_stack([rng.uniform(-0.1, 0.1, 60), rng.uniform(0.0, 0.2, 60), np.full(60, 0.04)])
    points = np.zeros((1, 3))
    wi, r2 = (lights[None] - points[:, None]), None
    r2 = np.sum(wi**2, -1)
    wi = wi / np.sqrt(r2)[..., None]
    rho = microfacet.rho(wi, O, np.array(kd), np.full(3, 0.5), 1.5, 0.1, 0.3, 0.0)
    radiance = rho * (wi[..., 2] / r2)[..., None] * 0.3
    samples, _ = brdf_samples(radiance, points, lights, np.full((60, 3), 0.3))
    clean = diffuse_level(samples, radiance, np.ones((1, 60), bool))
    keep = np.ones((1, 60), bool)
    keep[0, [7, 30]] = False
    reference = diffuse_level(samples[:, keep[0]], radiance[:, keep[0]], np.ones((1, 58), bool))
    bad_s, bad_r = samples.copy(), radiance.copy()
    bad_s[0, 7], bad_r[0, 7] = np.nan, np.nan
    bad_s[0, 30, 1], bad_r[0, 30, 1] = np.inf, np.inf
    got = diffuse_level(bad_s, bad_r, np.ones((1, 60), bool))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, reference, rtol=1e-12)
    np.testing.assert_allclose(got, clean, rtol=0.05)                 # and close to the clean data's kd
    residual = specular_residual(bad_s, got)
    assert np.all(residual[:, keep[0]] >= 0) and np.isfinite(residual[:, keep[0]]).all()


def test_eq8_inverts_the_pixel_model_up_to_grazing():
    """Eq. 8 divides by n.i: for lights from 80 to 89.99 deg (n.i down to 1.7e-4) it still inverts the
    pixel model exactly (rtol 1e-9); below n.i = 1e-6 (here 89.99995 deg) it returns 0 by statement, not a
    huge quotient of rounding errors."""
    theta = np.array([80.0, 89.0, 89.9, 89.99, 89.99995])
    lights = 0.1 * sph(theta, 70.0)
    points = np.zeros((1, 3))
    wi = unit(lights)[None]
    rho = microfacet.rho(wi, O, np.array([0.2, 0.1, 0.3]), np.full(3, 0.6), 1.5, 0.1, 0.3, 0.2)
    intensity = np.full((len(theta), 3), 0.3)
    radiance = rho * (wi[..., 2] / 0.01)[..., None] * intensity[None]
    samples, directions = brdf_samples(radiance, points, lights, intensity)
    assert np.isfinite(samples).all()
    np.testing.assert_allclose(samples[0, :4], rho[0, :4], rtol=1e-9)
    assert np.all(samples[0, 4] == 0)
    np.testing.assert_allclose(directions[0], wi[0], atol=1e-15)


def test_eq9_near_mirror_and_very_rough_lobes():
    """Eq. 9's minimum over lights. A near-mirror lobe (alpha 0.01) narrower than the light spacing hits
    few lights, so kd is exact up to the far GGX tail (2e-5 absolute). A very rough lobe (alpha 1) adds
    specular to every light: kd is over-estimated by exactly the smallest specular value among the
    qualifying lights (the stated bias)."""
    rng = np.random.default_rng(6)
    lights = np.column_stack([rng.uniform(-0.1, 0.1, 150), rng.uniform(0.0, 0.2, 150), np.full(150, 0.04)])
    points = np.zeros((1, 3))
    wi = unit(lights)[None]
    r2 = np.sum(lights**2, -1)[None]
    kd = np.array([0.3, 0.2, 0.1])
    intensity = np.full((150, 3), 0.3)
    for alpha in (0.01, 1.0):
        spec = microfacet.rho(wi, O, np.zeros(3), np.full(3, 0.7), 1.5, alpha, alpha, 0.0)
        rho = kd / np.pi + spec
        radiance = rho * (wi[..., 2] / r2)[..., None] * intensity[None]
        samples, _ = brdf_samples(radiance, points, lights, intensity)
        rho_d = diffuse_level(samples, radiance, np.ones((1, 150), bool))
        mean_i = radiance.mean(-1)
        qualifying = mean_i > 0.05 * mean_i.mean()
        expected = kd / np.pi + spec[qualifying].min(axis=0)
        np.testing.assert_allclose(rho_d[0], expected, rtol=1e-9)
        if alpha == 0.01:
            assert np.all(np.pi * rho_d[0] - kd < 2e-5)         # measured 1.0e-5: the far GGX tail
        else:
            assert np.all(np.pi * rho_d[0] - kd > 0.005)       # the bias is real: measured 0.009 in kd
