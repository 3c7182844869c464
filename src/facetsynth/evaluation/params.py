"""The params stage's model against a virtual capture's truth: eta, ks, and the NDF spread per homogeneous region."""

from __future__ import annotations

import logging

import numpy as np

from .metrics import finite_or_none, spread_about_mean
from ..truth.scene import MaterialMaps, Scene
from ..stages.common import RectifiedCapture
from ..models.svbrdf import SVBRDF
from .truth import analytic_points, median_rel_error, truth_of

log = logging.getLogger(__name__)


def truth_scores(model: SVBRDF, capture: RectifiedCapture) -> dict:
    """eta (absolute error, median over the visible points whose truth is eq. 6, ``MaterialMaps.analytic``:
    a measured or conductor truth's eta and ks are placeholders; and over those whose eta was fitted) and ks
    (median relative error, truth > 0) of the fitted model against a virtual capture's truth, and its NDF
    spread per homogeneous region (:func:`spread_scores`); {} for a real capture."""
    truth = truth_of(capture)
    if truth is None:
        return {}
    on = analytic_points(capture, truth)
    out = {}
    err = np.abs(model.eta - truth.eta)
    out["eta_abs_error_median"] = float(np.median(err[on])) if on.any() else None
    sel = on & model.eta_fitted
    out["eta_abs_error_median_fitted"] = float(np.median(err[sel])) if sel.any() else None
    out["eta_within_0.1_fraction_fitted"] = float((err[sel] <= 0.1).mean()) if sel.any() else None
    out["ks_median_rel_error"] = median_rel_error(model.ks, truth.ks, on)
    log.info("eta |error| median %s (fitted points: %s), ks median rel error %s", out["eta_abs_error_median"],
             out["eta_abs_error_median_fitted"], out["ks_median_rel_error"])
    return {**out, **spread_scores(model, capture, truth)}


def spread_scores(model: SVBRDF, capture: RectifiedCapture, truth: MaterialMaps) -> dict:
    """``ndf_spread`` (:func:`ndf_spread`) of ``model`` per named truth region of a virtual capture, with its
    largest median and definition: the metrics of params, and of refine on the delivered model."""
    names = [r.get("name", f"region{k}") for k, r in enumerate(Scene.load(capture.truth_scene).regions)]
    names = [f"{nm}#{k}" if names.count(nm) > 1 else nm for k, nm in enumerate(names)]
    spread, skipped = ndf_spread(model, truth, names, capture.visible)
    medians = [v["median"] for v in spread.values() if v["median"] is not None]
    for name, v in spread.items():
        log.info("NDF spread in %s: median %s, p90 %s over %d points", name, v["median"], v["p90"], v["points"])
    return {"ndf_spread": spread, "ndf_spread_skipped": skipped,
            "ndf_spread_max_median": float(max(medians)) if medians else None,
            "ndf_spread_definition": (
                "per truth region with one frame everywhere (any material kind): each point's final "
                "normalised eq. 18 NDF on the model's grid against the region's mean NDF, relative L2 solid-angle "
                "weighted over the whole hemisphere grid; median and 90th percentile over <= 2000 evenly strided "
                "points; ndf_spread_max_median = the largest median")}


def ndf_spread(model: SVBRDF, truth: MaterialMaps, names: list[str], visible: np.ndarray,
               max_points: int = 2000) -> tuple[dict, dict]:
    """The spread of the fitted per-point NDFs within each homogeneous truth region.

    For every truth region (``truth.region`` >= 0, any kind of material: the
    spread needs only the region, not its true NDF) whose frame
    azimuth is the same at all its visible points (within 1e-6 rad: one NDF
    everywhere), up to ``max_points`` points (evenly strided) get their final
    normalised eq. 18 NDF on the model's grid (:meth:`SVBRDF.point_ndf`), and
    each its relative L2 about the points' mean NDF, solid-angle weighted over
    the whole hemisphere grid (:func:`facetsynth.evaluation.metrics.spread_about_mean`).
    Returns ({name: {"points", "median", "p90"}}, {name: why skipped}); a
    region whose frame turns (a polar frame: one material at many rotations,
    its NDFs should differ) is skipped and said so.
    """
    spread, skipped = {}, {}
    for r in np.unique(truth.region[truth.region >= 0]):
        name = names[r] if r < len(names) else f"region{int(r)}"
        index = np.flatnonzero(visible & (truth.region == r))
        if index.size == 0:
            skipped[name] = "no visible point"
            continue
        turn = np.angle(np.exp(1j * (truth.phi_frame[index] - truth.phi_frame[index[0]])))
        if np.abs(turn).max() > 1e-6:
            skipped[name] = (f"frame turns across the sample (up to {np.degrees(np.abs(turn).max()):.0f} deg from "
                             "its first point): one material at many rotations, its NDFs differ by design")
            continue
        index = index[:: int(np.ceil(index.size / max_points))]
        err = spread_about_mean(model.point_ndf(index), model.grid.solid_angles)
        err = err[np.isfinite(err)]
        spread[name] = {"points": int(err.size),
                        "median": finite_or_none(np.median(err)) if err.size else None,
                        "p90": finite_or_none(np.quantile(err, 0.9)) if err.size else None}
    return spread, skipped
