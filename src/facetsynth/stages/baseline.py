"""Stage ``baseline_ward``: per-point anisotropic Ward fitted by LM to the rectified data (paper 002 Fig. 10)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..fileio import read_exr, write_json
from ..render import light_geometry
from ..ward import WardSVBRDF, fit_point
from .common import RectifiedCapture

log = logging.getLogger(__name__)


def run(geometry: str | Path, kd_path: str | Path, specular: str | Path, valid: str | Path, colour: str | Path,
        model_out: str | Path, metrics_out: str | Path, max_nfev: int = 200) -> None:
    """Fit every visible point independently (Goldman et al. 2005 style) and write the Ward model folder."""
    capture = RectifiedCapture.load(geometry)
    n = capture.n_points
    kd = read_exr(kd_path)[0]["RGB"].reshape(n, 3).astype(float)
    col = np.load(colour).astype(float)
    spec = np.load(specular, mmap_mode="r")
    ok = np.load(valid, mmap_mode="r")
    points = capture.points
    view = capture.view_directions(True)
    ks, ax, ay, phi = np.zeros(n), np.full(n, 0.3), np.full(n, 0.3), np.zeros(n)
    failed = 0
    start = time.perf_counter()
    for p in tqdm(np.flatnonzero(capture.visible), desc="baseline_ward: LM per point", unit="point",
                  mininterval=5.0):
        wi, _ = light_geometry(points[p][None], capture.light_positions)
        use = np.asarray(ok[p], bool) & (wi[:, 2] > 0)
        rho_s = np.asarray(spec[p], float)[use].mean(axis=-1)
        fit = fit_point(rho_s, wi[use], np.broadcast_to(view[p], (int(use.sum()), 3)), max_nfev=max_nfev)
        ks[p], ax[p], ay[p], phi[p] = fit.ks, fit.alpha_x, fit.alpha_y, fit.phi
        failed += not fit.ok
    seconds = time.perf_counter() - start
    kd = np.where(capture.visible[:, None], kd, 0.0)
    WardSVBRDF(capture.grid, kd, ks[:, None] * col, ax, ay, phi,
               info={"fit": "Levenberg-Marquardt per point (scipy least_squares, method lm)",
                     "source": str(specular)}).save(model_out)
    write_json(metrics_out, {"points": n, "fitted_points": int(capture.visible.sum()),
                             "points_not_converged": int(failed), "fit_seconds": seconds,
                             "alpha_x_median": float(np.median(ax[capture.visible])),
                             "alpha_y_median": float(np.median(ay[capture.visible]))})
    log.info("Ward fit of %d points in %.1f s (%d not converged)", int(capture.visible.sum()), seconds, failed)
