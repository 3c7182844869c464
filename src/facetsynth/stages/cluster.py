"""Stage ``cluster``: k-means representatives and eq. 18 interpolation weights (paper 002 sec. 5.3)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from .. import cluster
from ..fileio import read_json, write_json, write_npy
from ..grid import DirectionGrid
from ..partial_ndf import relative_l2
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)


def run(geometry: str | Path, ndf: str | Path, confidence: str | Path, grid_path: str | Path,
        labels_out: str | Path, representatives_out: str | Path, neighbours_out: str | Path,
        weights_out: str | Path, metrics_out: str | Path, representatives: str | int | float = "auto",
        min_representatives: int = 8, max_representatives: int = 64, distortion: float = 0.08,
        scan_points: int = 2048, neighbours: int = 16, radius: float = 5.0, ridge: float = 1e-3, n_init: int = 3,
        seed: int = 0) -> None:
    """Cluster the visible points' partial NDFs; write labels, representatives, neighbours, weights.

    The number of representatives: ``representatives`` "auto" chooses it from
    the data (:func:`facetsynth.cluster.choose_k`: the smallest k on a
    geometric ladder from ``min_representatives`` to ``max_representatives``
    whose k-means distortion falls below ``distortion`` of the total
    variance, scanned on ``scan_points`` points); an integer >= 1 fixes it;
    a number in (0, 1) is a fraction of the visible points (the paper's 1 %,
    at least ``min_representatives``). Invisible points get label -1 and
    all-zero weights; every visible point's weights sum to 1.
    """
    t0 = time.perf_counter()
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    d_all = np.load(ndf, mmap_mode="r")
    w_all = np.load(confidence, mmap_mode="r")
    n = capture.n_points
    visible = np.flatnonzero(capture.visible)
    if visible.size == 0:
        raise ValueError("no visible points to cluster")
    d = np.asarray(d_all[visible], np.float32)
    w = np.asarray(w_all[visible], np.float32)
    feats = cluster.features(d, w, grid)
    choice = None
    if isinstance(representatives, str) and representatives.strip() != "auto":
        try:                                  # --config passes numbers as strings
            representatives = float(representatives)
        except ValueError:
            pass
    if isinstance(representatives, str):
        if representatives.strip() != "auto":
            raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                             f"not {representatives!r}")
        choice = cluster.choose_k(feats, min_representatives, min(max_representatives, visible.size), distortion,
                                  subsample=scan_points, seed=seed)
        wanted = choice.k
        log.info("representatives: auto, k = %d (%s); distortion / total variance on %d points: %s", wanted,
                 choice.rule, choice.subsample,
                 ", ".join(f"k={k}: {v:.3f}" for k, v in zip(choice.ladder, choice.distortion)))
    elif float(representatives) >= 1:
        wanted = int(representatives)
        log.info("representatives: fixed at %d", wanted)
    elif float(representatives) > 0:
        wanted = int(max(min_representatives, round(float(representatives) * visible.size)))
        log.info("representatives: %g of %d visible points, at least %d: %d", float(representatives),
                 visible.size, min_representatives, wanted)
    else:
        raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                         f"not {representatives!r}")
    result = cluster.kmeans(feats, d, w, grid, wanted, seed=seed, n_init=n_init)
    del feats
    reps = result.representatives                      # rows of the visible subset
    log.info("k-means: %d visible points, %d representatives (%d asked, %d distinct NDFs)",
             visible.size, reps.size, wanted, result.distinct)
    nbr, wts, lam = cluster.interpolation_weights(d, w, d[reps], w[reps], grid, k=neighbours, radius=radius,
                                                  ridge=ridge, rep_rows=reps, rows=np.arange(visible.size))
    # eq. 18 on the partial data: how well the representatives span the points
    rep_d = d[reps]
    err = np.concatenate([relative_l2(np.einsum("nk,nktp->ntp", wts[t], rep_d[nbr[t]]), d[t], w[t] > 0, grid)
                          for t in tiles(visible.size)])
    err = err[np.isfinite(err)]
    used = (wts != 0).sum(axis=1)

    labels = np.full(n, -1, np.int32)
    labels[visible] = result.labels
    neighbours_full = np.zeros((n, neighbours), np.int32)
    weights_full = np.zeros((n, neighbours), np.float32)
    neighbours_full[visible], weights_full[visible] = nbr, wts
    write_npy(labels_out, labels)
    write_npy(representatives_out, visible[reps].astype(np.int64))
    write_npy(neighbours_out, neighbours_full)
    write_npy(weights_out, weights_full)
    metrics = {"points": n, "visible_points": int(visible.size), "representatives": int(reps.size),
               "representatives_requested": wanted, "distinct_ndfs": int(result.distinct),
               "representatives_rule": ("auto" if choice is not None else
                                        "fixed" if float(representatives) >= 1 else "fraction"),
               "k_chosen": wanted,
               **({"k_rule": choice.rule, "k_distortion_tolerance": distortion, "k_scan_points": choice.subsample,
                   "k_ladder": choice.ladder, "k_distortion_curve": [round(v, 5) for v in choice.distortion],
                   "k_scan_seconds": round(choice.seconds, 2)} if choice is not None else
                  {"representatives_setting": representatives}),
               "lambda": lam if np.isfinite(lam) else None, "radius_lambda": radius, "k": neighbours,
               "ridge": ridge, "neighbours_used_median": float(np.median(used)),
               "eq18_partial_rel_l2_median": float(np.median(err)) if err.size else None,
               "eq18_partial_rel_l2_p90": float(np.quantile(err, 0.9)) if err.size else None,
               "negative_weight_fraction": float(np.mean(wts[wts != 0] < 0)) if np.any(wts != 0) else 0.0,
               "seconds": round(time.perf_counter() - t0, 2)}
    log.info("cluster metrics: %s", metrics)
    write_json(metrics_out, metrics)
