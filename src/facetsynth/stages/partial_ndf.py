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

METRIC_POINTS = 1024  # points on which the accuracy against the truth is measured


def run(geometry: str | Path, slice_path: str | Path, coverage_path: str | Path, grid_path: str | Path,
        ndf_out: str | Path, confidence_out: str | Path, metrics_out: str | Path, per_point_view: bool = False,
        constrained: bool | str = True, grazing_deg: float = 80.0, tol: float = 1e-3, max_iter: int = 30) -> None:
    """Fit every point's partial NDF, in tiles of points over memory-mapped tensors.

    For virtual captures, accuracy is measured against
    :func:`facetsynth.partial_ndf.recoverable_ndf` over cells with W >= 0.5,
    on the points :func:`scored_points` picks. The other shadowing method and
    view model are compared on the same points by :func:`variant_errors`
    (a test, not every run: it fits the points again per variant).
    """
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    table = np.load(slice_path, mmap_mode="r")
    cover = np.load(coverage_path, mmap_mode="r")
    n = capture.n_points
    truth = capture.truth()
    scored = scored_points(capture, truth)
    errors = []
    iterations, converged = np.zeros(n, int), np.zeros(n, bool)
    views = capture.view_directions(per_point_view)
    with atomic_path(ndf_out, suffix=".npy") as tmp_ndf, atomic_path(confidence_out, suffix=".npy") as tmp_w:
        ndf = np.lib.format.open_memmap(tmp_ndf, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        weight = np.lib.format.open_memmap(tmp_w, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        for tile in tqdm(list(tiles(n)), desc="partial_ndf", unit="tile"):
            s, c = np.asarray(table[tile], float), np.asarray(cover[tile], float)
            view = views[tile]
            fit = pndf.fit(s, c, view, grid, constrained, grazing_deg, tol, max_iter)
            ndf[tile], weight[tile] = fit.ndf, fit.confidence
            iterations[tile], converged[tile] = fit.iterations, fit.converged
            pick = scored[tile]
            if pick.any():
                errors.append(_errors(fit.ndf[pick], fit.confidence[pick], view[pick],
                                      truth.take(np.flatnonzero(pick) + tile.start), grid))
        ndf.flush()
        weight.flush()
        del ndf, weight

    metrics = {"ground_truth": truth is not None, "points": n, "grid": grid.to_dict(),
               "method": pndf.shadowing_method(constrained),
               "view": "per_point" if per_point_view else "centre",
               "iterations_median": float(np.median(iterations)), "iterations_max": int(iterations.max()),
               "converged_fraction": float(converged.mean()), "grazing_deg": grazing_deg, "tolerance": tol}
    if truth is not None:
        metrics["scored_points"] = int(scored.sum())
        metrics["ndf_rel_l2_median"] = _median(errors)
        log.info("partial NDF relative L2 against the truth, median: %s", metrics["ndf_rel_l2_median"])
    write_json(metrics_out, metrics)


def scored_points(capture: RectifiedCapture, truth) -> np.ndarray:
    """Every k-th visible point on the truth's sample (at most METRIC_POINTS); none without a truth."""
    scored = np.zeros(capture.n_points, bool)
    if truth is not None:
        scored[:: max(1, capture.n_points // METRIC_POINTS)] = True
        scored &= capture.visible & (truth.region >= 0) & truth.analytic   # true NDF known: eq. 6 points
    return scored


VARIANTS = {"constrained": (True, "constrained"), "unconstrained": (True, "unconstrained"),
            "clipped": (True, "clipped"), "centre_view": (False, "constrained")}


def variant_errors(geometry: str | Path, slice_path: str | Path, coverage_path: str | Path, grid_path: str | Path,
                   variants: dict[str, tuple[bool, bool | str]] = VARIANTS, grazing_deg: float = 80.0,
                   tol: float = 1e-3, max_iter: int = 30) -> dict[str, float | None]:
    """Median relative L2 error of each variant (per_point_view, shadowing method) on the scored points of a
    virtual capture's resampled data: how the paper's choices (sec. 5.1, Fig. 5) compare on a scene. A scene
    without analytic truth (measured BRDFs only) has no scored point: every variant is None."""
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    truth = capture.truth()
    if truth is None:
        raise ValueError(f"{geometry}: variants are compared against the truth, and this capture has none")
    index = np.flatnonzero(scored_points(capture, truth))
    if index.size == 0:
        return {name: None for name in variants}
    s = np.asarray(np.load(slice_path, mmap_mode="r")[index], float)
    c = np.asarray(np.load(coverage_path, mmap_mode="r")[index], float)
    maps = truth.take(index)
    result = {}
    for name, (per_point, constrain) in variants.items():
        view = capture.view_directions(per_point)[index]
        fit = pndf.fit(s, c, view, grid, constrain, grazing_deg, tol, max_iter)
        result[name] = _median([_errors(fit.ndf, fit.confidence, view, maps, grid)])
    return result


def _errors(ndf: np.ndarray, confidence: np.ndarray, view: np.ndarray, maps, grid: DirectionGrid) -> np.ndarray:
    """Relative L2 error of partial NDFs against the recoverable truth over cells with W >= 0.5."""
    true_ndf = maps.take((slice(None), None)).ndf(grid.directions.reshape(1, -1, 3)).reshape(ndf.shape)
    reference = pndf.recoverable_ndf(maps.ks, maps.eta, true_ndf, view, grid)
    return pndf.relative_l2(ndf, reference, confidence >= 0.5, grid)


def _median(errors: list[np.ndarray]) -> float | None:
    values = np.concatenate(errors) if errors else np.zeros(0)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None
