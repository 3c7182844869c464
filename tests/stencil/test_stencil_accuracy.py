"""Issue 18: the stencil fit is at least as accurate as the two-lobe Kurt baseline on measured RGL BRDFs,
and the extended eq. 10 / eq. 7 terms are recovered from data they generated."""

import importlib
from dataclasses import replace

import numpy as np
import pytest

from conftest import RGL_DIR
from facetsynth.stencil import kurt, model, readers, scores
from facetsynth.stencil.fit import RHO_CAND, RHO_MIN, axis_error_deg, fit


# Kurt fits take 1-2.5 s each on these (the benchmark runs all seven); measured 2026-12-03 (stencil / Kurt
# Delta E): 1.60 / 2.06, 4.50 / 5.29, 3.67 / 5.27, 2.92 / 4.42; colodur_napoli 1.67 / 1.58 (+6 %, within 10 %).
@pytest.mark.parametrize("name, stencil_de", [("vch_golden_yellow_rgb", 1.60), ("cc_ibiza_sunset_rgb", 4.50),
                                              ("cc_iris_purple_gem_rgb", 3.67), ("satin_rosaline_rgb", 2.92),
                                              ("colodur_napoli_4f_rgb", 1.67)])
def test_stencil_delta_e_at_most_kurt_on_rgl(name, stencil_de):
    b = readers.read_rgl(RGL_DIR / f"{name}.bsdf")
    m = fit(b)
    st = scores.score_brdf(b, model.evaluate_utia(m))
    km, _ = kurt.fit_kurt(b)
    ku = scores.score_brdf(b, kurt.kurt_evaluate_utia(km))
    # issue 18: at most Kurt's, or within 10 % with the reason measured (colodur: docs/stencil.md)
    assert st["delta_e"] <= (1.10 if name.startswith("colodur") else 1.0) * ku["delta_e"]
    assert st["delta_e"] == pytest.approx(stencil_de, abs=0.02)     # the fit is deterministic
    assert len(m.modes) == 0 and m.m_s is not None and m.k2 > 0
    # eq. 10 divided by k.h fits these real materials better; colodur needs it most (1.86 without)
    assert m.jacobian == (name != "vch_golden_yellow_rgb")


def test_ggx_three_lobes_third_mode_kept_by_bic_and_beats_kurt():
    """The third axis (rho 0.086 < RHO_MIN) is kept because it lowers the fit's BIC (issue 18);
    measured 2026-12-03: stencil 8.41 (11.77 with 2 modes) vs Kurt 10.20."""
    from facetsynth.stencil.benchmark import anisotropic_cases
    b = anisotropic_cases()["GGX 3 lobes at 0/60/120 deg"]
    m = fit(b)
    assert len(m.modes) == 3
    assert axis_error_deg([float(np.rad2deg(md.phi_a)) for md in m.modes], [30.0, 90.0, 150.0]) < 2.0
    marg = m.meta["marginal"]
    assert len(marg) == 1 and RHO_CAND <= marg[0]["rho"] < RHO_MIN and marg[0]["delta_bic"] < 0
    st = scores.score_brdf(b, model.evaluate_utia(m))
    km, _ = kurt.fit_kurt(b)
    ku = scores.score_brdf(b, kurt.kurt_evaluate_utia(km))
    assert st["delta_e"] <= ku["delta_e"]
    assert st["delta_e"] == pytest.approx(8.41, abs=0.02)
    assert not m.jacobian             # rendered by a microfacet model without 1 / k.h
    assert m.stencil_highlight        # the highlight shaped by the dominant mode's stencil lowers the error


def test_bic_rejects_weak_candidates_that_do_not_help(monkeypatch):
    """With the candidate floor lowered to 0.01 the stretched satin's weak axes (rho 0.023, 0.011) are
    tried and rejected by the BIC; the model and its Delta E stay those of the zero-mode fit (3.27)."""
    from facetsynth.stencil.benchmark import anisotropic_cases
    b = anisotropic_cases()["satin_rosaline stretched x4 at 20/110 deg"]
    # the module, not the package's attribute facetsynth.stencil.fit (the function it re-exports)
    monkeypatch.setattr(importlib.import_module("facetsynth.stencil.fit"), "RHO_CAND", 0.01)
    m = fit(b)
    assert len(m.modes) == 0
    marg = m.meta["marginal"]
    assert marg and marg[0]["rho"] < RHO_MIN and marg[0]["delta_bic"] > 0
    assert scores.score_brdf(b, model.evaluate_utia(m))["delta_e"] == pytest.approx(3.27, abs=0.02)


def truth_model():
    """Zero modes, elevation-scaled background, a sharp white and a broad coloured lobe (eqs. 3, 7, 10)."""
    return model.StencilModel(modes=(), beta=(), r=0.2, m_bg=(0.8, 0.3, 0.1), k=400.0, alpha_s=512.0, a_s=0.0,
                              b_s=model.COS_FLOOR ** 2, k2=4.0, alpha_s2=16.0, a_s2=1.0, b_s2=0.0,
                              m_s=(1.0, 1.0, 1.0), m_s2=(1.4, 0.9, 0.5), a_r=1.1, b_r=-0.1)


def test_extended_terms_recovered_from_their_own_output():
    truth = truth_model()
    b = model.evaluate_utia(truth)
    m = fit(b)
    lobes = sorted([(m.alpha_s, m.k, m.a_s, m.b_s, m.m_s), (m.alpha_s2, m.k2, m.a_s2, m.b_s2, m.m_s2)])
    (al_b, k_b, a_b, b_b, col_b), (al_s, k_s, a_s, b_s, col_s) = lobes
    assert (al_b, al_s) == (16.0, 512.0)                               # alpha grid 2^n: exact
    assert k_b * (a_b + b_b) == pytest.approx(4.0, rel=0.03)            # broad lobe at normal incidence
    assert k_s * (a_s + b_s) == pytest.approx(400.0 * model.COS_FLOOR ** 2, rel=0.05)   # sharp lobe, 3.04
    np.testing.assert_allclose(col_b, truth.m_s2, rtol=0.03)
    np.testing.assert_allclose(col_s, truth.m_s, rtol=0.07)
    np.testing.assert_allclose(m.r * np.array(m.m_bg), truth.r * np.array(truth.m_bg), rtol=0.02)
    assert (m.a_r, m.b_r) == pytest.approx((truth.a_r, truth.b_r), abs=0.02)
    assert scores.score_brdf(b, model.evaluate_utia(m))["delta_e"] < 0.6   # 0.56 measured


def test_jacobian_and_schlick_chosen_from_their_own_output():
    """A truth whose lobes are divided by k.h and carry a Schlick term: the fit picks the Jacobian form,
    the broad lobe's alpha and its value at normal incidence (k.h = 1 there); one without: it does not."""
    C2 = model.COS_FLOOR ** 2
    plain = replace(truth_model(), a_r=1.05, b_r=-0.05)      # background > 0 at 75/75 deg (1.1 - 0.1/cp is not)
    for truth, de in ((plain, 0.30), (replace(plain, jacobian=True, b_s=0.5 * C2, f_s=4 * C2), 0.43)):
        b = model.evaluate_utia(truth)
        m = fit(b)
        assert m.jacobian == truth.jacobian
        broad = min(model.lobes(m), key=lambda lobe: lobe[1])
        assert broad[1] == 16.0 and broad[0] * (broad[2] + broad[3]) == pytest.approx(4.0, rel=0.05)
        assert scores.score_brdf(b, model.evaluate_utia(m))["delta_e"] == pytest.approx(de, abs=0.03)


@pytest.mark.parametrize("shaped, de", [(False, 0.54), (True, 0.49)])
def test_stencil_highlight_chosen_from_its_own_output(shaped, de):
    """One mode at 30 deg, eq. 10's lobes with or without the dominant mode's stencil F_0^alpha_0: the fit
    picks the form that made the data.  (On the two-mode synthetic the self-fit is too poor, Delta E ~15,
    for the choice to be right: "Missing" in docs/stencil.md.)"""
    from facetsynth.stencil.benchmark import _synth
    truth = replace(_synth((30,)), stencil_highlight=shaped)
    b = model.evaluate_utia(truth)
    m = fit(b)
    assert len(m.modes) == 1 and m.stencil_highlight == shaped and not m.jacobian
    assert scores.score_brdf(b, model.evaluate_utia(m))["delta_e"] == pytest.approx(de, abs=0.03)


def test_paper_defaults_are_eq10():
    """With m_s None and k2 = 0 the specular term is eq. 10 exactly: B_S = B max(1, k H_z^alpha (a + b/cp))."""
    B = np.array([[0.2, 0.1, 0.05]])
    S = model.specular_factor(np.array([0.99]), np.array([0.5]), (3.0, 50.0, 0.5, 0.25))
    np.testing.assert_allclose(model.apply_specular(B, np.array([0.99]), np.array([0.5]), (3.0, 50.0, 0.5, 0.25)),
                               B * S[:, None], rtol=1e-14)
    assert S[0] == pytest.approx(max(1.0, 3.0 * 0.99 ** 50 * (0.5 + 0.25 / 0.5)))
    # coloured: the boost (S - 1) Y(B) takes m_s's colour, B itself is kept
    got = model.apply_specular(B, np.array([1.0]), np.array([1.0]), (3.0, 1.0, 1.0, 0.0), m_s=(1.0, 0.5, 0.0))
    np.testing.assert_allclose(got, B + 2.0 * (B @ [0.2126, 0.7152, 0.0722])[:, None] * [1.0, 0.5, 0.0])
