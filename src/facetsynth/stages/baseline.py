"""Stage ``baseline_ward``: per-point anisotropic Ward fitted by LM to the rectified data (paper 002 Fig. 10).

Each point is fitted independently; :func:`facetsynth.models.ward.fit_points` fits a tile of them at once. The
config knob ``baseline.max_nfev`` (argument ``max_nfev``) caps the LM iterations (trial steps) per start and
point; it kept its name from the scipy fit it replaced, where it capped function evaluations."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..io.colour import channel_mean
from ..io.fileio import atomic_path, read_exr, write_json
from ..models.ward import WardSVBRDF, fit_points
from .common import TILE_POINTS, RectifiedCapture, RuleFiles, StageSettings, part_points, part_records

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``baseline_ward``'s inputs: separate's geometry, kd, specular samples and their validity, resample's
    specular colour; in the join of scatter parts (``scatter.tiles`` > 1) also the parts' records (None: the
    whole capture, or one part)."""
    geometry: Path
    kd: Path
    specular: Path
    valid: Path
    colour: Path
    records: list[Path] | None = None


class Outputs(RuleFiles):
    """Rule ``baseline_ward``'s outputs: the Ward model folder and the metrics; rule ``baseline_ward_part``'s: its
    ``record`` (the others None)."""
    model: Path | None = None
    metrics: Path | None = None
    record: Path | None = None


class Settings(StageSettings):
    """The stage's knobs: config ``baseline`` (workflow/schemas/config.schema.yaml)."""
    max_nfev: int = 200    # LM iterations (trial steps) per start and point


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1, *,
        part: tuple[int, int] | None = None) -> None:
    """The rule's job: scatter part ``part`` (part, parts) of rule ``baseline_ward_part`` (:func:`run_part`), the
    parts' join (``inputs.records``: :func:`gather`) or the whole capture (:func:`run_whole`); one thread."""
    if part is not None:
        run_part(inputs.geometry, inputs.specular, inputs.valid, *part, record_out=outputs.record,
                 max_nfev=settings.max_nfev)
    elif inputs.records is not None:
        gather(inputs.geometry, inputs.kd, inputs.colour, inputs.specular, records=inputs.records,
               model_out=outputs.model, metrics_out=outputs.metrics)
    else:
        run_whole(inputs.geometry, inputs.kd, inputs.specular, inputs.valid, inputs.colour, model_out=outputs.model,
                  metrics_out=outputs.metrics, max_nfev=settings.max_nfev)


def run_whole(geometry: str | Path, kd_path: str | Path, specular: str | Path, valid: str | Path,
              colour: str | Path, model_out: str | Path, metrics_out: str | Path, max_nfev: int = 200) -> None:
    """The whole capture in one job (``scatter.tiles`` 1): fit every visible point independently (Goldman et al.
    2005 style) and write the Ward model folder."""
    capture = RectifiedCapture.load(geometry)
    fitted = _fit_points(capture, specular, valid, slice(0, capture.n_points), max_nfev)
    _write(capture, kd_path, colour, fitted, specular, model_out, metrics_out)


def run_part(geometry: str | Path, specular: str | Path, valid: str | Path, part: int, parts: int,
             record_out: str | Path, max_nfev: int = 200) -> None:
    """One scatter part (config ``scatter.tiles`` > 1): the fits of :func:`~facetsynth.stages.common.part_points`
    only, as a record (.npz) that :func:`gather` joins; each point's fit does not depend on the others."""
    capture = RectifiedCapture.load(geometry)
    points = part_points(capture.n_points, part, parts, TILE_POINTS)
    fitted = _fit_points(capture, specular, valid, points, max_nfev)
    with atomic_path(record_out, suffix=".npz") as tmp:
        np.savez(tmp, start=points.start, **fitted)


def gather(geometry: str | Path, kd_path: str | Path, colour: str | Path, specular: str | Path,
           records: list[str | Path], model_out: str | Path, metrics_out: str | Path) -> None:
    """The parts' fits joined into the unsplit Ward model and metrics."""
    capture = RectifiedCapture.load(geometry)
    _, fitted = part_records(records)
    if len(fitted["ks"]) != capture.n_points:
        raise ValueError(f"{model_out}: the scatter parts hold {len(fitted['ks'])} points, the capture "
                         f"{capture.n_points}")
    _write(capture, kd_path, colour, fitted, specular, model_out, metrics_out)


def _fit_points(capture: RectifiedCapture, specular, valid, points: slice, max_nfev: int) -> dict:
    """LM fits of the visible points among ``points``, a tile of TILE_POINTS at a time (tiles counted from
    ``points.start``, so a scatter part's tiles are those of the unsplit run); defaults (ks 0, alpha 0.3)
    elsewhere. A point's samples are those valid, finite and lit from above (i.z > 0)."""
    spec = np.load(specular, mmap_mode="r")
    ok = capture.validity(valid)
    view = capture.view_directions(True)
    n = points.stop - points.start
    out = {"ks": np.zeros(n), "alpha_x": np.full(n, 0.3), "alpha_y": np.full(n, 0.3), "phi": np.zeros(n),
           "failed": np.zeros(n, bool)}
    start = time.perf_counter()
    for t0 in tqdm(range(points.start, points.stop, TILE_POINTS), desc="baseline_ward: LM per tile", unit="tile",
                   mininterval=5.0):
        tile = slice(t0, min(t0 + TILE_POINTS, points.stop))
        visible = np.flatnonzero(capture.visible[tile])
        if visible.size == 0:
            continue
        p = visible + t0
        wi, _ = capture.light_directions(p)                                                  # (T, F, 3)
        rho_s = channel_mean(np.asarray(spec[tile], float)[visible])                    # (T, F)
        use = np.asarray(ok[tile], bool)[visible] & (wi[..., 2] > 0) & np.isfinite(rho_s)
        fit = fit_points(rho_s, wi, view[p][:, None], use, max_iterations=max_nfev)
        q = p - points.start
        out["ks"][q], out["alpha_x"][q], out["alpha_y"][q], out["phi"][q] = fit.ks, fit.alpha_x, fit.alpha_y, fit.phi
        out["failed"][q] = ~fit.ok
    out["seconds"] = time.perf_counter() - start
    return out


def _write(capture: RectifiedCapture, kd_path, colour, fitted: dict, specular, model_out, metrics_out) -> None:
    n = capture.n_points
    kd = read_exr(kd_path)[0]["RGB"].reshape(n, 3).astype(float)
    col = np.load(colour).astype(float)
    kd = np.where(capture.visible[:, None], kd, 0.0)
    ks, ax, ay, phi = fitted["ks"], fitted["alpha_x"], fitted["alpha_y"], fitted["phi"]
    failed = int(np.sum(fitted["failed"]))
    WardSVBRDF(capture.grid, kd, ks[:, None] * col, ax, ay, phi,
               info={"fit": "Levenberg-Marquardt per point (facetsynth.models.ward.fit_points: batched over tiles, "
                            "analytic Jacobian, two starts)",
                     "source": str(specular)}).save(model_out)
    write_json(metrics_out, {"points": n, "fitted_points": int(capture.visible.sum()),
                             "points_not_converged": failed, "fit_seconds": float(fitted["seconds"]),
                             "alpha_x_median": float(np.median(ax[capture.visible])),
                             "alpha_y_median": float(np.median(ay[capture.visible]))})
    log.info("Ward fit of %d points in %.1f s (%d not converged)", int(capture.visible.sum()),
             float(fitted["seconds"]), failed)
