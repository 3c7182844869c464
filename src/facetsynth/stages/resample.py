"""Stage ``resample``: each point's specular samples onto the light-direction grid (sec. 4).

Linear interpolation over one triangulation of the lights' positions
(:mod:`facetsynth.geometry.lightplane`: the same at every point, so two points of one
material get the same slice wherever they sit under the LEDs), push-pull
(Gortler et al. 1996, as the paper) only beyond the lights' hull.

The grid's resolution follows the sharpness of the measured lobes
(:mod:`facetsynth.fit.sharpness`): it is decided here, from the data, and
recorded with its reason in ``resample/metrics.json``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..geometry.coverage import LightFootprint, read_around, world_grid
from ..io.colour import channel_mean
from ..io.fileio import NpyRows, atomic_path, write_json, write_npy
from ..io.frames import imap
from ..geometry.grid import DirectionGrid
from ..models.microfacet import half_vector
from ..geometry.lightplane import LightTriangulation
from ..fit.pushpull import push_pull
from ..fit.sharpness import grid_resolution, lobe_widths
from ..io.tables import join_tables, support_writer
from .common import TILE_POINTS, RectifiedCapture, RuleFiles, StageSettings, part_points, part_records, tiles

log = logging.getLogger(__name__)


SHARPNESS_POINTS = 1024    # points (every k-th visible one) whose lobes decide the grid


def measured_sharpness(capture: RectifiedCapture, spec, ok, grazing_deg: float) -> dict:
    """Median narrow and broad lobe half-widths (deg) over up to SHARPNESS_POINTS visible points that have a
    resolved specular lobe (:func:`facetsynth.fit.sharpness.lobe_widths`; lights beyond ``grazing_deg``
    excluded, as in eq. 11)."""
    visible = np.flatnonzero(capture.visible)
    idx = visible[:: max(1, visible.size // SHARPNESS_POINTS)]
    wi, _ = capture.light_directions(idx)
    o = np.broadcast_to(capture.view_directions(True, idx)[:, None, :], wi.shape)
    use = np.asarray(ok[idx], bool) & (wi[..., 2] > np.cos(np.radians(grazing_deg)))
    value = np.where(use, channel_mean(np.asarray(spec[idx], float)) * 4.0 * wi[..., 2] * o[..., 2], 0.0)
    narrow, broad, _ = lobe_widths(half_vector(wi, o), value)
    peak = value.max(axis=1)
    lobed = np.isfinite(narrow) & (peak > 0.1 * np.quantile(peak, 0.9))     # drops markers and diffuse points
    return {"points_measured": int(idx.size), "points_with_a_lobe": int(lobed.sum()),
            "narrow_half_width_deg": float(np.median(narrow[lobed])) if lobed.any() else None,
            "broad_half_width_deg": float(np.median(broad[lobed])) if lobed.any() else None}


class Inputs(RuleFiles):
    """Rule ``resample``'s inputs: separate's geometry, specular samples and their validity; in the join of scatter
    parts (``scatter.tiles`` > 1) also the parts' slices and records (None: the whole capture, or one part)."""
    geometry: Path
    specular: Path
    valid: Path
    slice: list[Path] | None = None
    records: list[Path] | None = None


class Outputs(RuleFiles):
    """Rule ``resample``'s outputs: the slices' folder, the specular colour, the grid and the metrics; rule
    ``resample_part``'s: its points' slices and its ``record`` (the others None)."""
    slice: Path
    colour: Path | None = None
    grid: Path | None = None
    metrics: Path | None = None
    record: Path | None = None


class Settings(StageSettings):
    """The stage's knobs: config ``resample`` and ``partial_ndf.grazing_deg`` (workflow/schemas/config.schema.yaml)."""
    cells_per_lobe: float = 1.3               # elevation rings per narrow lobe half-width
    n_theta_range: tuple[int, int] = (16, 48)  # [min, max] rings
    grazing_deg: float = 80.0                 # lights beyond it are left out of the lobe widths (as in eq. 11)

    def direction_grid(self, capture: RectifiedCapture, spec, ok) -> tuple[DirectionGrid, dict]:
        """The grid the measured lobes ask for, and the metrics saying why (the same in every scatter part:
        it is decided on the same evenly strided points of the whole capture)."""
        sharpness = measured_sharpness(capture, spec, ok, self.grazing_deg)
        narrow = sharpness["narrow_half_width_deg"]
        n_theta, n_phi = grid_resolution(np.nan if narrow is None else narrow, self.cells_per_lobe,
                                         tuple(self.n_theta_range))
        reason = ("no resolved specular lobe: the coarsest grid" if narrow is None else
                  f"narrow lobe half-width {narrow:.2f} deg (median of {sharpness['points_with_a_lobe']} points) x "
                  f"{self.cells_per_lobe} rings per half-width, n_theta in {list(self.n_theta_range)}")
        return DirectionGrid(n_theta, n_phi), {**sharpness, "n_theta": n_theta, "n_phi": n_phi,
                                               "cells_per_lobe": self.cells_per_lobe,
                                               "n_theta_range": list(self.n_theta_range), "reason": reason,
                                               "ring_width_deg": 90.0 / n_theta}


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1, *,
        part: tuple[int, int] | None = None) -> None:
    """The rule's job: scatter part ``part`` (part, parts) of rule ``resample_part`` (:func:`run_part`), the parts'
    join (``inputs.records``: :func:`gather`) or the whole capture (:func:`run_whole`)."""
    if part is not None:
        run_part(inputs.geometry, inputs.specular, inputs.valid, *part, slice_out=outputs.slice,
                 record_out=outputs.record, settings=settings, threads=threads)
    elif inputs.records is not None:
        gather(inputs.geometry, inputs.specular, inputs.valid, slice_parts=inputs.slice, records=inputs.records,
               slice_out=outputs.slice, colour_out=outputs.colour, grid_out=outputs.grid,
               metrics_out=outputs.metrics, settings=settings)
    else:
        run_whole(inputs.geometry, inputs.specular, inputs.valid, slice_out=outputs.slice, colour_out=outputs.colour,
                  grid_out=outputs.grid, metrics_out=outputs.metrics, settings=settings, threads=threads)


def run_whole(geometry: str | Path, specular: str | Path, valid: str | Path, slice_out: str | Path,
              colour_out: str | Path, grid_out: str | Path, metrics_out: str | Path,
              settings: Settings = Settings(), threads: int = 1) -> None:
    """The whole capture in one job (``scatter.tiles`` 1). Writes, per point: the specular slice rho~_s(i) on
    the grid (P, T, F) (channel mean; a :mod:`facetsynth.io.tables` support table, kept within a cell of the
    directions the lights covered, where eq. 11 reads it) and the specular colour (P, 3) (channel ratios,
    mean 1), the grid definition (JSON) and the metrics (the measured lobe widths and the grid they chose).
    The coverage itself (in W, eq. 12) is geometry: :class:`facetsynth.geometry.coverage.LightFootprint`
    gives it where it is used."""
    capture = RectifiedCapture.load(geometry)
    spec, ok = NpyRows(specular), capture.validity(valid)
    grid, metrics = settings.direction_grid(capture, spec, ok)
    log.info("direction grid %d x %d: %s", grid.n_theta, grid.n_phi, metrics["reason"])
    colour = _resample_points(capture, grid, spec, ok, slice(0, capture.n_points), slice_out, threads)
    write_npy(colour_out, colour.astype(np.float32))
    write_json(grid_out, grid.to_dict())
    write_json(metrics_out, metrics)


def run_part(geometry: str | Path, specular: str | Path, valid: str | Path, part: int, parts: int,
             slice_out: str | Path, record_out: str | Path,
             settings: Settings = Settings(), threads: int = 1) -> None:
    """One scatter part (``scatter.tiles`` > 1): the slices of :func:`part_points` only, and a
    record (.npz: the points' specular colour) that :func:`gather` joins."""
    capture = RectifiedCapture.load(geometry)
    spec, ok = NpyRows(specular), capture.validity(valid)
    grid, _ = settings.direction_grid(capture, spec, ok)
    points = part_points(capture.n_points, part, parts, TILE_POINTS)
    colour = _resample_points(capture, grid, spec, ok, points, slice_out, threads)
    with atomic_path(record_out, suffix=".npz") as tmp:
        np.savez(tmp, start=points.start, colour=colour)


def gather(geometry: str | Path, specular: str | Path, valid: str | Path, slice_parts: list,
           records: list, slice_out: str | Path, colour_out: str | Path,
           grid_out: str | Path, metrics_out: str | Path, settings: Settings = Settings()) -> None:
    """The scatter parts joined into the unsplit outputs, bit for bit."""
    capture = RectifiedCapture.load(geometry)
    grid, metrics = settings.direction_grid(capture, NpyRows(specular), capture.validity(valid))
    order, fitted = part_records(records)
    join_tables([slice_parts[k] for k in order], slice_out, capture.n_points)
    write_npy(colour_out, fitted["colour"].astype(np.float32))
    write_json(grid_out, grid.to_dict())
    write_json(metrics_out, metrics)


def _resample_points(capture: RectifiedCapture, grid: DirectionGrid, spec, ok, points: slice, slice_out,
                     threads: int = 1) -> np.ndarray:
    """The slices of ``points`` (whole tiles) into a (len, T, F) support table, tiles on ``threads``
    threads; returns their colour."""
    lights = LightTriangulation.from_lights(capture.lights)
    footprint = LightFootprint.from_lights(capture.lights)
    n = points.stop - points.start
    colour = np.ones((n, 3))
    shape = (n,) + grid.shape

    def resample_tile(local: slice) -> tuple[np.ndarray, np.ndarray]:
        tile = slice(points.start + local.start, points.start + local.stop)
        s, valid = np.asarray(spec[tile], float), ok[tile]
        xyz, directions = capture.points[tile], world_grid(grid, capture.frames(tile))
        value, defined = lights.interpolate(channel_mean(s), valid, xyz, directions)
        table = push_pull((value * defined).reshape((-1,) + grid.shape), defined.reshape((-1,) + grid.shape).astype(float))
        total = np.where(valid[..., None], s, 0.0).sum(axis=1)
        mean = total.mean(axis=1, keepdims=True)
        colour[local] = np.divide(total, mean, out=np.ones_like(total), where=mean > 0)
        covered = footprint.coverage(xyz, directions).reshape((-1,) + grid.shape) > 0    # LightFootprint.on_grid
        return read_around(covered), table

    with support_writer(slice_out, shape) as write_slice:
        for kept, table in imap(resample_tile, list(tiles(n)), threads, "resample", unit="tile"):
            write_slice(kept, values=table)
    return colour
