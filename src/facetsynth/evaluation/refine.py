"""The refine stage's model against a virtual capture's truth: kd, ks, ks F0 and the NDF spread."""

from __future__ import annotations

import numpy as np

from ..models.microfacet import fresnel
from ..stages.common import RectifiedCapture
from ..models.svbrdf import SVBRDF
from .params import spread_scores
from .truth import analytic_points, median_rel_error, truth_of


def truth_scores(model: SVBRDF, capture: RectifiedCapture) -> dict:
    """kd, ks and ks F0 (ks F(eta) at normal incidence: ks and eta trade against each other, their product is
    what a view measures best) of the written model against a virtual capture's truth (median relative
    error over the visible points whose truth is eq. 6: ``MaterialMaps.analytic``, truth > 0) and its NDF spread per
    homogeneous region (:func:`facetsynth.evaluation.params.spread_scores`); {} for a real capture."""
    truth = truth_of(capture)
    if truth is None:
        return {}
    on = analytic_points(capture, truth)
    f0 = np.ones(1)      # ks F(eta) at normal incidence: the specular reflectance a renderer's F0 takes (eq. 3)
    f0_fitted = model.ks * fresnel(f0, model.eta)[:, None]
    f0_true = np.asarray(truth.ks, float).reshape(-1, 3) * fresnel(f0, np.asarray(truth.eta, float).ravel())[:, None]
    out = {f"{name}_median_rel_error": median_rel_error(fitted, true, on)
           for name, fitted, true in (("kd", model.kd, truth.kd), ("ks", model.ks, truth.ks),
                                      ("ks_f0", f0_fitted, f0_true))}
    return {**out, **spread_scores(model, capture, truth)}
