"""Stage ``stencil_fit``: one adaptive highlight stencil model (paper 000) per material cluster.

Each material cluster of the fitted SVBRDF (a k-means cluster of the
``cluster`` stage, paper 002 sec. 5.3) is represented by its representative
point; the SVBRDF at that point is evaluated on the UTIA grid and the stencil
model is fitted to it directly (paper 000 sec. 3), with the number of
anisotropy modes chosen from the data.

Beside it the two-lobe Kurt et al. 2010 baseline (paper 000 sec. 4.2,
:func:`facetsynth.stencil.kurt.fit_kurt`) is fitted to the same UTIA-grid
samples; both are scored (Delta E, RMSE, PSNR, SSIM) against the SVBRDF they
were fitted to, with both fit times.

For virtual samples both are also scored against the scene's true BRDF at the
representative point (sampled on the same grid), as is the fitted SVBRDF
itself, and the axes are checked: a single anisotropic microfacet lobe
(alpha_u != alpha_v) is one anisotropy mode with phi_a = 90 deg - phi_frame
(mod 180), since the tight tangent [cos phi_frame, sin phi_frame, 0] is the
stencil axis U(phi_a) = [sin phi_a, cos phi_a, 0] (paper 000 eq. 2); an
isotropic lobe has no mode.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..io.errors import InputError
from ..evaluation.truth import truth_of
from ..io.fileio import atomic_dir, write_json
from ..truth.scene import MaterialMaps
from ..models.svbrdf import SVBRDF
from ..stencil import fit, model_to_json, to_brdf_explorer
from ..stencil.fit import axis_error_deg
from ..stencil.grid import sample_utia
from ..stencil.kurt import fit_kurt, kurt_evaluate_utia
from ..stencil.model import evaluate_utia
from ..stencil.scores import score_brdf
from .common import RectifiedCapture, RuleFiles, StageSettings, strided

log = logging.getLogger(__name__)

# The Kurt baseline is a comparison, and its fit costs 1-8 s per cluster (as much as the stencil fits): it is
# fitted to at most this many clusters, evenly strided (every cluster of the demo's 11; 16 of the 45 that
# `auto` gives the tiny card under noise).
KURT_CLUSTERS = 16


class Inputs(RuleFiles):
    """Rule ``stencil_fit``'s inputs: the fitted SVBRDF folder, cluster's labels, separate's geometry (the truth
    of a virtual capture)."""
    svbrdf: Path
    labels: Path
    geometry: Path


class Outputs(RuleFiles):
    """Rule ``stencil_fit``'s outputs: the models folder (stencil.json, the BRDF Explorer shaders) and the
    stage's figures."""
    models: Path
    metrics: Path


class Settings(StageSettings):
    """The stage's knobs: none (the stencil fit chooses its anisotropy modes from the data)."""


def true_axes_deg(alpha_u: np.ndarray, alpha_v: np.ndarray, phi_frame: np.ndarray) -> list[list[float]]:
    """The stencil axes phi_a (deg) that a single microfacet lobe has: none if isotropic."""
    return [[] if np.isclose(au, av, rtol=1e-3) else [float((90.0 - np.rad2deg(pf)) % 180.0)]
            for au, av, pf in zip(alpha_u, alpha_v, phi_frame)]


_SCORES = ("delta_e", "rmse", "psnr_db", "ssim")


def _scores(reference, test):
    sc = score_brdf(reference, test)
    return {k: float(sc[k]) for k in _SCORES}


def fit_clusters(model: SVBRDF, representatives: np.ndarray, members: np.ndarray,
                 truth_axes: list[list[float]] | None = None,
                 truth: MaterialMaps | None = None, kurt_at_most: int = KURT_CLUSTERS) -> tuple[list[dict], list[str]]:
    """Fit a stencil model at each cluster's representative point, and the Kurt baseline at up to
    ``kurt_at_most`` of them (evenly strided from the first; 0: none) -> (cluster records, BRDF Explorer
    shaders).  ``truth``: the true maps at the representatives (virtual samples), index k for cluster k."""
    points = model.plane.points3d().reshape(-1, 3)
    compared = set(strided(np.arange(len(representatives)), kurt_at_most).tolist()) if kurt_at_most > 0 else set()
    clusters, shaders = [], []
    for k, point in enumerate(tqdm(representatives, desc="stencil_fit", unit="cluster")):
        kurt = k in compared
        brdf = sample_utia(lambda wi, wo: model.eval_index(np.full(len(wi), point, np.intp), wi, wo))
        t0 = time.perf_counter()
        stencil = fit(brdf)
        seconds = time.perf_counter() - t0
        stencil_brdf = evaluate_utia(stencil)
        scores = _scores(brdf, stencil_brdf)
        scores["fit_seconds"] = seconds
        entry = {"cluster": k, "representative": int(point), "xy_m": points[point, :2].tolist(),
                 "points": int(members[k]), "stencil": model_to_json(stencil, scores)}
        if kurt:
            kurt_model, kurt_seconds = fit_kurt(brdf)
            kurt_brdf = kurt_evaluate_utia(kurt_model)
            entry["kurt"] = {"scores": dict(_scores(brdf, kurt_brdf), fit_seconds=float(kurt_seconds)),
                             "kd": list(kurt_model.kd), "ks": [list(v) for v in kurt_model.ks],
                             "lobes_f0_mx_my_alpha": [list(v) for v in kurt_model.lobes]}
        if truth_axes is not None:
            entry["true_phi_a_deg"] = truth_axes[k]
        if truth is not None:
            true_k = truth.take(np.array([k]))
            true_brdf = sample_utia(lambda wi, wo: np.broadcast_to(true_k.rho(wi, wo), wi.shape))
            entry["vs_truth"] = {"stencil": _scores(true_brdf, stencil_brdf), "svbrdf": _scores(true_brdf, brdf)}
            if kurt:
                entry["vs_truth"]["kurt"] = _scores(true_brdf, kurt_brdf)
        clusters.append(entry)
        shaders.append(to_brdf_explorer(stencil))
    return clusters, shaders


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: a stencil model and the Kurt baseline per material cluster, the models folder and
    stencil_fit/metrics.json."""
    svbrdf_dir = inputs.svbrdf
    model = SVBRDF.load(svbrdf_dir)
    if model.representatives is None:
        raise InputError(svbrdf_dir, "the SVBRDF lists no representatives (material clusters)")
    reps = np.asarray(model.representatives, np.intp)
    labels = np.load(inputs.labels)
    members = np.bincount(labels[labels >= 0], minlength=len(reps))
    truth = truth_of(RectifiedCapture.load(inputs.geometry))
    truth_axes = None if truth is None else true_axes_deg(truth.alpha_u[reps], truth.alpha_v[reps],
                                                          truth.phi_frame[reps])
    clusters, shaders = fit_clusters(model, reps, members, truth_axes, None if truth is None else truth.take(reps))
    with atomic_dir(outputs.models) as tmp:
        (tmp / "shaders").mkdir(exist_ok=True)
        for k, shader in enumerate(shaders):
            (tmp / "shaders" / f"cluster_{k:03d}.brdf").write_text(shader)
        write_json(tmp / "stencil.json", {"svbrdf": str(svbrdf_dir), "clusters": clusters})
    metrics = cluster_metrics(clusters, truth_axes is not None)
    log.info("stencil fit: %s", {k: v for k, v in metrics.items() if not isinstance(v, dict)})
    write_json(outputs.metrics, metrics)


def _median(values):
    return float(np.median(values)) if len(values) else None


def cluster_metrics(clusters: list[dict], ground_truth: bool) -> dict:
    """Median scores over clusters for the stencil model (``delta_e_median`` ...) and the Kurt
    baseline (``kurt_delta_e_median`` ..., over the ``kurt_clusters`` it was fitted to) against the fitted
    SVBRDF, both fit times, the share of those clusters where the stencil's Delta E is at most Kurt's, the
    mode-count histogram and, with truth, both models' (and the SVBRDF's) median scores against the true BRDF
    and the axis accuracy."""
    scores = [c["stencil"]["scores"] for c in clusters]
    kurt = [c["kurt"]["scores"] for c in clusters if "kurt" in c]
    stencil_vs_kurt = [c["stencil"]["scores"]["delta_e"] <= c["kurt"]["scores"]["delta_e"]
                       for c in clusters if "kurt" in c]
    modes = [c["stencil"]["n_modes"] for c in clusters]
    metrics = {"ground_truth": ground_truth, "clusters": len(clusters), "kurt_clusters": len(kurt),
               "mode_counts": {str(n): modes.count(n) for n in sorted(set(modes))},
               "fit_seconds_median": _median([s["fit_seconds"] for s in scores]),
               "kurt_fit_seconds_median": _median([s["fit_seconds"] for s in kurt])}
    for key in _SCORES:
        metrics[f"{key}_median"] = _median([s[key] for s in scores])
        metrics[f"kurt_{key}_median"] = _median([s[key] for s in kurt])
    metrics["stencil_delta_e_at_most_kurt"] = float(np.mean(stencil_vs_kurt)) if stencil_vs_kurt else None
    truths = [c["vs_truth"] for c in clusters if "vs_truth" in c]
    if truths:
        metrics["vs_truth"] = {who: {f"{key}_median": _median([t[who][key] for t in truths if who in t])
                                     for key in _SCORES} for who in ("stencil", "kurt", "svbrdf")}
    if ground_truth and clusters:
        right = [c["stencil"]["n_modes"] == len(c["true_phi_a_deg"]) for c in clusters]
        errors = [axis_error_deg([m["phi_a_deg"] for m in c["stencil"]["modes"]], c["true_phi_a_deg"])
                  for c, ok in zip(clusters, right) if ok and c["true_phi_a_deg"]]
        metrics["mode_count_accuracy"] = float(np.mean(right))
        metrics["phi_a_error_deg_median"] = float(np.median(errors)) if errors else None
        metrics["phi_a_error_deg_max"] = float(np.max(errors)) if errors else None
    return metrics
