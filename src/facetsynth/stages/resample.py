"""Stage ``resample``: each point's specular samples onto the light-direction grid (sec. 4).

Linear interpolation over one triangulation of the lights' positions
(:mod:`facetsynth.lightplane`: the same at every point, so two points of one
material get the same slice wherever they sit under the LEDs), push-pull
(Gortler et al. 1996, as the paper) only beyond the lights' hull.

The grid's resolution follows the sharpness of the measured lobes
(:mod:`facetsynth.sharpness`): it is decided here, from the data, and
recorded with its reason in ``resample/metrics.json``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..coverage import LightFootprint
from ..fileio import atomic_path, write_json
from ..grid import DirectionGrid
from ..microfacet import half_vector
from ..lightplane import LightTriangulation
from ..pushpull import push_pull
from ..render import light_geometry
from ..sharpness import grid_resolution, lobe_widths
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)


SHARPNESS_POINTS = 1024    # points (every k-th visible one) whose lobes decide the grid


def measured_sharpness(capture: RectifiedCapture, spec, ok, grazing_deg: float) -> dict:
    """Median narrow and broad lobe half-widths (deg) over up to SHARPNESS_POINTS visible points that have a
    resolved specular lobe (:func:`facetsynth.sharpness.lobe_widths`; lights beyond ``grazing_deg``
    excluded, as in eq. 11)."""
    visible = np.flatnonzero(capture.visible)
    idx = visible[:: max(1, visible.size // SHARPNESS_POINTS)]
    wi, _ = light_geometry(capture.points[idx][:, None, :], capture.light_positions[None])
    o = np.broadcast_to(capture.view_directions(True)[idx][:, None, :], wi.shape)
    use = np.asarray(ok[idx], bool) & (wi[..., 2] > np.cos(np.radians(grazing_deg)))
    value = np.where(use, np.asarray(spec[idx], float).mean(axis=-1) * 4.0 * wi[..., 2] * o[..., 2], 0.0)
    narrow, broad, _ = lobe_widths(half_vector(wi, o), value)
    peak = value.max(axis=1)
    lobed = np.isfinite(narrow) & (peak > 0.1 * np.quantile(peak, 0.9))     # drops markers and diffuse points
    return {"points_measured": int(idx.size), "points_with_a_lobe": int(lobed.sum()),
            "narrow_half_width_deg": float(np.median(narrow[lobed])) if lobed.any() else None,
            "broad_half_width_deg": float(np.median(broad[lobed])) if lobed.any() else None}


def run(geometry: str | Path, specular: str | Path, valid: str | Path, slice_out: str | Path,
        coverage_out: str | Path, colour_out: str | Path, grid_out: str | Path, metrics_out: str | Path,
        cells_per_lobe: float = 1.3, n_theta_range: tuple[int, int] = (16, 32), grazing_deg: float = 80.0) -> None:
    """Writes, per point: the specular slice rho~_s(i) on the grid (P, T, F) float32
    (channel mean), its light coverage (P, T, F) float16 and the specular
    colour (P, 3) (channel ratios, mean 1), the grid definition (JSON) and the
    metrics (the measured lobe widths and the grid they chose)."""
    capture = RectifiedCapture.load(geometry)
    spec = np.load(specular, mmap_mode="r")
    ok = np.load(valid, mmap_mode="r")
    sharpness = measured_sharpness(capture, spec, ok, grazing_deg)
    narrow = sharpness["narrow_half_width_deg"]
    n_theta, n_phi = grid_resolution(np.nan if narrow is None else narrow, cells_per_lobe, tuple(n_theta_range))
    grid = DirectionGrid(n_theta, n_phi)
    reason = (f"no resolved specular lobe: the coarsest grid" if narrow is None else
              f"narrow lobe half-width {narrow:.2f} deg (median of {sharpness['points_with_a_lobe']} points) x "
              f"{cells_per_lobe} rings per half-width, n_theta in {list(n_theta_range)}")
    log.info("direction grid %d x %d: %s", n_theta, n_phi, reason)
    footprint = LightFootprint.from_lights(capture.light_positions)
    log.info("lights: %d, spacing %.1f mm, plane z = %.1f mm", len(capture.light_positions),
             1e3 * footprint.spacing, 1e3 * footprint.height)
    lights = LightTriangulation.from_lights(capture.light_positions)
    directions = grid.directions.reshape(-1, 3)
    points, n = capture.points, capture.n_points
    colour = np.ones((n, 3))
    with atomic_path(slice_out, suffix=".npy") as tmp_slice, atomic_path(coverage_out, suffix=".npy") as tmp_cov:
        table = np.lib.format.open_memmap(tmp_slice, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        cover = np.lib.format.open_memmap(tmp_cov, mode="w+", dtype=np.float16, shape=(n,) + grid.shape)
        for tile in tqdm(list(tiles(n)), desc="resample", unit="tile"):
            s = np.asarray(spec[tile], float)
            value, defined = lights.interpolate(s.mean(axis=-1), ok[tile], points[tile], directions)
            table[tile] = push_pull((value * defined).reshape((-1,) + grid.shape),
                                    defined.reshape((-1,) + grid.shape).astype(float))
            cover[tile] = footprint.coverage(points[tile], directions).reshape((-1,) + grid.shape)
            total = np.where(ok[tile][..., None], s, 0.0).sum(axis=1)
            mean = total.mean(axis=1, keepdims=True)
            colour[tile] = np.divide(total, mean, out=np.ones_like(total), where=mean > 0)
        table.flush()
        cover.flush()
        del table, cover
    with atomic_path(colour_out, suffix=".npy") as tmp:
        np.save(tmp, colour.astype(np.float32))
    write_json(grid_out, grid.to_dict())
    write_json(metrics_out, {**sharpness, "n_theta": n_theta, "n_phi": n_phi, "cells_per_lobe": cells_per_lobe,
                             "n_theta_range": list(n_theta_range), "reason": reason,
                             "ring_width_deg": 90.0 / n_theta})
