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
        weights_out: str | Path, metrics_out: str | Path, fraction: float = 0.01, min_representatives: int = 8,
        neighbours: int = 16, radius: float = 5.0, ridge: float = 1e-3, n_init: int = 3, seed: int = 0) -> None:
    """Cluster the visible points' partial NDFs; write labels, representatives, neighbours, weights.

    The number of representatives is ``fraction`` of the visible points (at
    least ``min_representatives``). Invisible points get label -1 and all-zero
    weights; every visible point's weights sum to 1.
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
    wanted = int(max(min_representatives, round(fraction * visible.size)))
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
               "lambda": lam if np.isfinite(lam) else None, "radius_lambda": radius, "k": neighbours,
               "ridge": ridge, "neighbours_used_median": float(np.median(used)),
               "eq18_partial_rel_l2_median": float(np.median(err)) if err.size else None,
               "eq18_partial_rel_l2_p90": float(np.quantile(err, 0.9)) if err.size else None,
               "negative_weight_fraction": float(np.mean(wts[wts != 0] < 0)) if np.any(wts != 0) else 0.0,
               "seconds": round(time.perf_counter() - t0, 2)}
    log.info("cluster metrics: %s", metrics)
    write_json(metrics_out, metrics)
