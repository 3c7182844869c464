"""Stage ``stencil_fit``: one adaptive highlight stencil model (paper 000) per material cluster.

Each material cluster of the fitted SVBRDF (a k-means cluster of the
``cluster`` stage, paper 002 sec. 5.3) is represented by its representative
point; the SVBRDF at that point is evaluated on the UTIA grid and the stencil
model is fitted to it directly (paper 000 sec. 3), with the number of
anisotropy modes chosen from the data.

For virtual samples the fit is scored against the scene's truth: a single
anisotropic microfacet lobe (alpha_u != alpha_v) is one anisotropy mode with
phi_a = 90 deg - phi_frame (mod 180), since the tight tangent
[cos phi_frame, sin phi_frame, 0] is the stencil axis U(phi_a) =
[sin phi_a, cos phi_a, 0] (paper 000 eq. 2); an isotropic lobe has no mode.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from ..fileio import atomic_dir, write_json
from ..svbrdf import SVBRDF
from ..stencil import fit, model_to_json, to_brdf_explorer
from ..stencil.fit import axis_error_deg
from ..stencil.grid import sample_utia
from ..stencil.model import evaluate_utia
from ..stencil.scores import score_brdf
from .common import RectifiedCapture

log = logging.getLogger(__name__)


def true_axes_deg(alpha_u: np.ndarray, alpha_v: np.ndarray, phi_frame: np.ndarray) -> list[list[float]]:
    """The stencil axes phi_a (deg) that a single microfacet lobe has: none if isotropic."""
    return [[] if np.isclose(au, av, rtol=1e-3) else [float((90.0 - np.rad2deg(pf)) % 180.0)]
            for au, av, pf in zip(alpha_u, alpha_v, phi_frame)]


def fit_clusters(model: SVBRDF, representatives: np.ndarray, members: np.ndarray,
                 truth_axes: list[list[float]] | None = None) -> tuple[list[dict], list[str]]:
    """Fit a stencil model at each cluster's representative point -> (cluster records, BRDF Explorer shaders)."""
    points = model.plane.points3d().reshape(-1, 3)
    clusters, shaders = [], []
    for k, point in enumerate(tqdm(representatives, desc="stencil_fit", unit="cluster")):
        brdf = sample_utia(lambda wi, wo: model.eval_index(np.full(len(wi), point, np.intp), wi, wo))
        t0 = time.perf_counter()
        stencil = fit(brdf)
        seconds = time.perf_counter() - t0
        scores = score_brdf(brdf, evaluate_utia(stencil))
        scores["fit_seconds"] = seconds
        entry = {"cluster": k, "representative": int(point), "xy_m": points[point, :2].tolist(),
                 "points": int(members[k]), "stencil": model_to_json(stencil, scores)}
        if truth_axes is not None:
            entry["true_phi_a_deg"] = truth_axes[k]
        clusters.append(entry)
        shaders.append(to_brdf_explorer(stencil))
    return clusters, shaders


def run(svbrdf_dir: str | Path, labels_path: str | Path, geometry: str | Path, out_dir: str | Path,
        metrics_out: str | Path) -> None:
    model = SVBRDF.load(svbrdf_dir)
    if model.representatives is None:
        raise InputError(svbrdf_dir, "the SVBRDF lists no representatives (material clusters)")
    reps = np.asarray(model.representatives, np.intp)
    labels = np.load(labels_path)
    members = np.bincount(labels[labels >= 0], minlength=len(reps))
    truth = RectifiedCapture.load(geometry).truth()
    truth_axes = None if truth is None else true_axes_deg(truth.alpha_u[reps], truth.alpha_v[reps],
                                                          truth.phi_frame[reps])
    clusters, shaders = fit_clusters(model, reps, members, truth_axes)
    with atomic_dir(out_dir) as tmp:
        (tmp / "shaders").mkdir(exist_ok=True)
        for k, shader in enumerate(shaders):
            (tmp / "shaders" / f"cluster_{k:03d}.brdf").write_text(shader)
        write_json(tmp / "stencil.json", {"svbrdf": str(svbrdf_dir), "clusters": clusters})
    metrics = cluster_metrics(clusters, truth_axes is not None)
    log.info("stencil fit: %s", {k: v for k, v in metrics.items() if not isinstance(v, dict)})
    write_json(metrics_out, metrics)


def cluster_metrics(clusters: list[dict], ground_truth: bool) -> dict:
    """Median scores over clusters, the mode-count histogram and, with truth, axis accuracy."""
    scores = [c["stencil"]["scores"] for c in clusters]
    modes = [c["stencil"]["n_modes"] for c in clusters]
    seconds = [s["fit_seconds"] for s in scores]
    metrics = {"ground_truth": ground_truth, "clusters": len(clusters),
               "mode_counts": {str(n): modes.count(n) for n in sorted(set(modes))},
               "fit_seconds_median": float(np.median(seconds)) if seconds else None}
    for key in ("delta_e", "rmse", "psnr_db", "ssim"):
        metrics[f"{key}_median"] = float(np.median([s[key] for s in scores])) if scores else None
    if ground_truth and clusters:
        right = [c["stencil"]["n_modes"] == len(c["true_phi_a_deg"]) for c in clusters]
        errors = [axis_error_deg([m["phi_a_deg"] for m in c["stencil"]["modes"]], c["true_phi_a_deg"])
                  for c, ok in zip(clusters, right) if ok and c["true_phi_a_deg"]]
        metrics["mode_count_accuracy"] = float(np.mean(right))
        metrics["phi_a_error_deg_median"] = float(np.median(errors)) if errors else None
        metrics["phi_a_error_deg_max"] = float(np.max(errors)) if errors else None
    return metrics
