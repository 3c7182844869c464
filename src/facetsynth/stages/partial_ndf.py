"""Stage ``partial_ndf``: partial NDF D and confidence W per point (paper 002 sec. 5.1, eqs. 5, 10-12)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import partial_ndf as pndf
from ..fileio import atomic_path, read_json, write_json
from ..grid import DirectionGrid
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)

METRIC_POINTS = 1024  # points on which the accuracy of every variant is measured


def run(geometry: str | Path, slice_path: str | Path, coverage_path: str | Path, grid_path: str | Path,
        ndf_out: str | Path, confidence_out: str | Path, metrics_out: str | Path, per_point_view: bool = False,
        constrained: bool = True, grazing_deg: float = 80.0, tol: float = 1e-3, max_iter: int = 30) -> None:
    """Fit every point's partial NDF, in tiles of points over memory-mapped tensors.

    For virtual captures, accuracy is measured against
    :func:`facetsynth.partial_ndf.recoverable_ndf` over cells with W >= 0.5,
    on every k-th point (at most METRIC_POINTS), where the other shadowing
    method and the other view model are also run: all figures are on the
    same points.
    """
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    table = np.load(slice_path, mmap_mode="r")
    cover = np.load(coverage_path, mmap_mode="r")
    n = capture.n_points
    truth = capture.truth()
    variants = {"_constrained": (per_point_view, True), "_unconstrained": (per_point_view, False),
                "_centre_view": (False, constrained), "_per_point_view": (True, constrained)}
    scored = np.zeros(n, bool)
    if truth is not None:
        scored[:: max(1, n // METRIC_POINTS)] = True
        scored &= capture.visible & (truth.region >= 0)
    errors = {name: [] for name in variants}
    iterations, converged = np.zeros(n, int), np.zeros(n, bool)
    with atomic_path(ndf_out, suffix=".npy") as tmp_ndf, atomic_path(confidence_out, suffix=".npy") as tmp_w:
        ndf = np.lib.format.open_memmap(tmp_ndf, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        weight = np.lib.format.open_memmap(tmp_w, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        for tile in tqdm(list(tiles(n)), desc="partial_ndf", unit="tile"):
            s, c = np.asarray(table[tile], float), np.asarray(cover[tile], float)
            fit = pndf.fit(s, c, capture.view_directions(per_point_view)[tile], grid, constrained,
                           grazing_deg, tol, max_iter)
            ndf[tile], weight[tile] = fit.ndf, fit.confidence
            iterations[tile], converged[tile] = fit.iterations, fit.converged
            pick = scored[tile]
            if pick.any():
                _score_variants(errors, variants, s[pick], c[pick], truth.take(np.flatnonzero(scored[tile]) + tile.start),
                                capture, np.flatnonzero(pick) + tile.start, grid, grazing_deg, tol, max_iter,
                                own=((per_point_view, constrained), fit.ndf[pick], fit.confidence[pick]))
        ndf.flush()
        weight.flush()
        del ndf, weight

    metrics = {"ground_truth": truth is not None, "points": n, "grid": grid.to_dict(),
               "method": "constrained" if constrained else "unconstrained",
               "view": "per_point" if per_point_view else "centre",
               "iterations_median": float(np.median(iterations)), "iterations_max": int(iterations.max()),
               "converged_fraction": float(converged.mean()), "grazing_deg": grazing_deg, "tolerance": tol}
    if truth is not None:
        metrics["scored_points"] = int(scored.sum())
        for name, values in errors.items():
            values = np.concatenate(values)
            values = values[np.isfinite(values)]
            metrics["ndf_rel_l2_median" + name] = float(np.median(values)) if values.size else None
        chosen = "_constrained" if constrained else "_unconstrained"
        metrics["ndf_rel_l2_median"] = metrics["ndf_rel_l2_median" + chosen]
        log.info("partial NDF relative L2, median: %s",
                 {k: round(v, 4) for k, v in metrics.items() if k.startswith("ndf_") and v is not None})
    write_json(metrics_out, metrics)


def _score_variants(errors, variants, s, c, maps, capture, index, grid, grazing_deg, tol, max_iter, own) -> None:
    """Each variant's error on the scored points; ``own`` = ((per_point, constrained), D, W) of the stage's
    own fit, which the variants that match it reuse instead of fitting again."""
    true_ndf = maps.take((slice(None), None)).ndf(grid.directions.reshape(1, -1, 3)).reshape(s.shape)
    own_variant, own_ndf, own_confidence = own
    for name, (per_point, constrain) in variants.items():
        view = capture.view_directions(per_point)[index]
        if (per_point, constrain) == own_variant:
            ndf, confidence = own_ndf, own_confidence
        else:
            fit = pndf.fit(s, c, view, grid, constrain, grazing_deg, tol, max_iter)
            ndf, confidence = fit.ndf, fit.confidence
        reference = pndf.recoverable_ndf(maps.ks, maps.eta, true_ndf, view, grid)
        errors[name].append(pndf.relative_l2(ndf, reference, confidence >= 0.5, grid))
