"""The separate stage's kd against a virtual capture's true kd."""

from __future__ import annotations

import logging

import numpy as np

from ..stages.common import RectifiedCapture
from .truth import analytic_points, truth_of

log = logging.getLogger(__name__)


def truth_scores(kd: np.ndarray, capture: RectifiedCapture) -> dict:
    """kd's median relative error against a virtual capture's truth, over the visible points whose true BRDF is
    eq. 6 (:func:`facetsynth.evaluation.truth.analytic_points`: measured, coated, ... have no true kd) and
    channels with a true kd > 0 (None: no such point); {} for a real capture."""
    truth = truth_of(capture)
    if truth is None:
        return {}
    select = analytic_points(capture, truth)[:, None] & (truth.kd > 0)
    scores = {"kd_median_rel_error": (float(np.median(np.abs(kd - truth.kd)[select] / truth.kd[select]))
                                      if select.any() else None)}
    if select.any():
        log.info("kd median relative error %.4f", scores["kd_median_rel_error"])
    return scores
