"""Stage ``baseline_ward``: per-point anisotropic Ward fitted by LM to the rectified data (paper 002 Fig. 10)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..fileio import atomic_path, read_exr, write_json
from ..render import light_geometry
from ..ward import WardSVBRDF, fit_point
from .common import TILE_POINTS, RectifiedCapture, part_points, part_records

log = logging.getLogger(__name__)


def run(geometry: str | Path, kd_path: str | Path, specular: str | Path, valid: str | Path, colour: str | Path,
        model_out: str | Path, metrics_out: str | Path, max_nfev: int = 200) -> None:
    """Fit every visible point independently (Goldman et al. 2005 style) and write the Ward model folder."""
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
    """LM fits of the visible points among ``points``; defaults (ks 0, alpha 0.3) elsewhere."""
    spec = np.load(specular, mmap_mode="r")
    ok = np.load(valid, mmap_mode="r")
    view = capture.view_directions(True)
    n = points.stop - points.start
    out = {"ks": np.zeros(n), "alpha_x": np.full(n, 0.3), "alpha_y": np.full(n, 0.3), "phi": np.zeros(n),
           "failed": np.zeros(n, bool)}
    start = time.perf_counter()
    visible = np.flatnonzero(capture.visible[points]) + points.start
    for p in tqdm(visible, desc="baseline_ward: LM per point", unit="point", mininterval=5.0):
        wi, _ = light_geometry(capture.points[p][None], capture.light_positions)
        use = np.asarray(ok[p], bool) & (wi[:, 2] > 0)
        rho_s = np.asarray(spec[p], float)[use].mean(axis=-1)
        fit = fit_point(rho_s, wi[use], np.broadcast_to(view[p], (int(use.sum()), 3)), max_nfev=max_nfev)
        q = p - points.start
        out["ks"][q], out["alpha_x"][q], out["alpha_y"][q], out["phi"][q] = fit.ks, fit.alpha_x, fit.alpha_y, fit.phi
        out["failed"][q] = not fit.ok
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
               info={"fit": "Levenberg-Marquardt per point (scipy least_squares, method lm)",
                     "source": str(specular)}).save(model_out)
    write_json(metrics_out, {"points": n, "fitted_points": int(capture.visible.sum()),
                             "points_not_converged": failed, "fit_seconds": float(fitted["seconds"]),
                             "alpha_x_median": float(np.median(ax[capture.visible])),
                             "alpha_y_median": float(np.median(ay[capture.visible]))})
    log.info("Ward fit of %d points in %.1f s (%d not converged)", int(capture.visible.sum()),
             float(fitted["seconds"]), failed)
