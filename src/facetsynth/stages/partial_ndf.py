"""Stage ``partial_ndf``: partial NDF D and confidence W per point (paper 002 sec. 5.1, eqs. 5, 10-12)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..fit import partial_ndf
from ..io.fileio import atomic_path, read_json, write_json
from ..io.frames import imap
from ..geometry.grid import DirectionGrid
from ..io.tables import SupportTable, join_tables, support_writer
from ..evaluation.partial_ndf import partial_ndf_errors
from ..evaluation.truth import median_or_none, scored_points, truth_of
from .common import TILE_POINTS, RectifiedCapture, RuleFiles, StageSettings, part_points, part_records, tiles

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``partial_ndf``'s inputs: separate's geometry, resample's slices and grid; in the join of scatter parts
    (``scatter.tiles`` > 1) also the parts' NDF tables and records (None: the whole capture, or one part)."""
    geometry: Path
    slice: Path
    grid: Path
    ndf: list[Path] | None = None
    records: list[Path] | None = None


class Outputs(RuleFiles):
    """Rule ``partial_ndf``'s outputs: the NDF table (D and W) and the metrics; rule ``partial_ndf_part``'s: its
    points' NDF table and its ``record`` (no metrics)."""
    ndf: Path
    metrics: Path | None = None
    record: Path | None = None


class Settings(StageSettings):
    """The stage's knobs: config ``partial_ndf`` (workflow/schemas/config.schema.yaml)."""
    per_point_view: bool = True           # o(x) per point, or the paper's view at the sample centre
    shadowing: bool | str = "constrained"  # S of eq. 5: :func:`facetsynth.fit.partial_ndf.shadowing_method`
    grazing_deg: float = 80.0             # light directions steeper than this are excluded
    tolerance: float = 1e-3               # stop when D changes by less than this (relative)
    max_iterations: int = 30

    def fit(self, slice_: np.ndarray, coverage: np.ndarray, view: np.ndarray,
            grid: DirectionGrid) -> partial_ndf.PartialNDF:
        return partial_ndf.fit(slice_, coverage, view, grid, self.shadowing, self.grazing_deg, self.tolerance,
                               self.max_iterations)


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1, *,
        part: tuple[int, int] | None = None) -> None:
    """The rule's job: scatter part ``part`` (part, parts) of rule ``partial_ndf_part`` (:func:`run_part`), the
    parts' join (``inputs.records``: :func:`gather`) or the whole capture (:func:`run_whole`)."""
    if part is not None:
        run_part(inputs.geometry, inputs.slice, inputs.grid, *part, ndf_out=outputs.ndf, record_out=outputs.record,
                 settings=settings, threads=threads)
    elif inputs.records is not None:
        gather(inputs.geometry, inputs.grid, ndf_parts=inputs.ndf, records=inputs.records, ndf_out=outputs.ndf,
               metrics_out=outputs.metrics, settings=settings)
    else:
        run_whole(inputs.geometry, inputs.slice, inputs.grid, ndf_out=outputs.ndf, metrics_out=outputs.metrics,
                  settings=settings, threads=threads)


def run_whole(geometry: str | Path, slice_path: str | Path, grid_path: str | Path, ndf_out: str | Path,
              metrics_out: str | Path, settings: Settings = Settings(), threads: int = 1) -> None:
    """The whole capture in one job (``scatter.tiles`` 1): fit every point's partial NDF, in tiles of points over
    memory-mapped tensors, on ``threads`` threads. ``ndf_out``: a :mod:`facetsynth.io.tables` support table of D
    (channel ``ndf``) and W (``confidence``) on each point's W > 0.

    For virtual captures, accuracy is measured against
    :func:`facetsynth.fit.partial_ndf.recoverable_ndf` over cells with W >= 0.5,
    on the points :func:`facetsynth.evaluation.truth.scored_points` picks. The other shadowing method and
    view model are compared on the same points by :func:`facetsynth.evaluation.partial_ndf.variant_errors`
    (a test, not every run: it fits the points again per variant).
    """
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    fitted = _fit_points(capture, grid, slice_path, slice(0, capture.n_points), ndf_out, settings, threads)
    write_json(metrics_out, _metrics(capture, grid, fitted, settings))


def run_part(geometry: str | Path, slice_path: str | Path, grid_path: str | Path,
             part: int, parts: int, ndf_out: str | Path, record_out: str | Path,
             settings: Settings = Settings(), threads: int = 1) -> None:
    """One scatter part (``scatter.tiles`` > 1): the partial NDFs of :func:`part_points` only, and a record
    (.npz: the points' iterations, convergence and scored errors) that :func:`gather` turns into the
    metrics of an unsplit run."""
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    points = part_points(capture.n_points, part, parts, TILE_POINTS)
    fitted = _fit_points(capture, grid, slice_path, points, ndf_out, settings, threads)
    with atomic_path(record_out, suffix=".npz") as tmp:
        np.savez(tmp, start=points.start, **fitted)


def gather(geometry: str | Path, grid_path: str | Path, ndf_parts: list[str | Path], records: list[str | Path],
           ndf_out: str | Path, metrics_out: str | Path, settings: Settings = Settings()) -> None:
    """The scatter parts joined into the unsplit outputs (streamed part by part) and the unsplit metrics."""
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    order, fitted = part_records(records)
    join_tables([ndf_parts[k] for k in order], ndf_out, capture.n_points)
    write_json(metrics_out, _metrics(capture, grid, fitted, settings))


def _fit_points(capture: RectifiedCapture, grid: DirectionGrid, slice_path, points: slice, ndf_out,
                settings: Settings, threads: int = 1) -> dict:
    """Fit the partial NDFs of ``points`` (a slice of the capture's points, whole tiles) into a (len, T, F)
    support table, tiles on ``threads`` threads; returns the points' iterations, convergence and the
    scored points' errors."""
    table, coverage = SupportTable(slice_path).rows("values"), capture.light_coverage(grid)
    truth = truth_of(capture)
    scored = scored_points(capture, truth)
    n = points.stop - points.start
    errors = []
    iterations, converged = np.zeros(n, int), np.zeros(n, bool)
    views = capture.view_directions(settings.per_point_view)
    shape = (n,) + grid.shape

    def fit_tile(local: slice) -> tuple[slice, slice, partial_ndf.PartialNDF]:
        tile = slice(points.start + local.start, points.start + local.stop)
        return local, tile, settings.fit(np.asarray(table[tile], float), coverage(tile), views[tile], grid)

    with support_writer(ndf_out, shape, ("ndf", "confidence")) as write:
        for local, tile, fit in imap(fit_tile, list(tiles(n, TILE_POINTS)), threads, "partial_ndf", unit="tile"):
            view = views[tile]
            write(fit.confidence > 0, ndf=fit.ndf, confidence=fit.confidence)
            iterations[local], converged[local] = fit.iterations, fit.converged
            pick = scored[tile]
            if pick.any():
                errors.append(partial_ndf_errors(fit.ndf[pick], fit.confidence[pick], view[pick],
                                                 truth.take(np.flatnonzero(pick) + tile.start), grid))
    return {"iterations": iterations, "converged": converged,
            "errors": np.concatenate(errors) if errors else np.zeros(0)}


def _metrics(capture: RectifiedCapture, grid: DirectionGrid, fitted: dict, settings: Settings) -> dict:
    truth = truth_of(capture)
    iterations, converged = fitted["iterations"], fitted["converged"]
    metrics = {"ground_truth": truth is not None, "points": capture.n_points, "grid": grid.to_dict(),
               "method": partial_ndf.shadowing_method(settings.shadowing),
               "view": "per_point" if settings.per_point_view else "centre",
               "iterations_median": float(np.median(iterations)), "iterations_max": int(iterations.max()),
               "converged_fraction": float(converged.mean()), "grazing_deg": settings.grazing_deg,
               "tolerance": settings.tolerance}
    if truth is not None:
        metrics["scored_points"] = int(scored_points(capture, truth).sum())
        metrics["ndf_rel_l2_median"] = median_or_none(fitted["errors"])
        log.info("partial NDF relative L2 against the truth, median: %s", metrics["ndf_rel_l2_median"])
    return metrics
