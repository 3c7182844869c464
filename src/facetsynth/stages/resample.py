"""Stage ``resample``: push-pull of each point's specular samples onto the light-direction grid (sec. 4)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..coverage import LightFootprint
from ..fileio import atomic_path, write_json
from ..grid import DirectionGrid
from ..pushpull import push_pull, splat
from ..render import light_geometry
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)


def run(geometry: str | Path, specular: str | Path, valid: str | Path, slice_out: str | Path,
        coverage_out: str | Path, colour_out: str | Path, grid_out: str | Path,
        n_theta: int = 32, n_phi: int = 128) -> None:
    """Writes, per point: the specular slice rho~_s(i) on the grid (P, T, F) float32
    (channel mean), its light coverage (P, T, F) float16 and the specular
    colour (P, 3) (channel ratios, mean 1), and the grid definition (JSON)."""
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid(n_theta, n_phi)
    spec = np.load(specular, mmap_mode="r")
    ok = np.load(valid, mmap_mode="r")
    footprint = LightFootprint.from_lights(capture.light_positions)
    log.info("lights: %d, spacing %.1f mm, plane z = %.1f mm", len(capture.light_positions),
             1e3 * footprint.spacing, 1e3 * footprint.height)
    points, n = capture.points, capture.n_points
    colour = np.ones((n, 3))
    with atomic_path(slice_out, suffix=".npy") as tmp_slice, atomic_path(coverage_out, suffix=".npy") as tmp_cov:
        table = np.lib.format.open_memmap(tmp_slice, mode="w+", dtype=np.float32, shape=(n,) + grid.shape)
        cover = np.lib.format.open_memmap(tmp_cov, mode="w+", dtype=np.float16, shape=(n,) + grid.shape)
        for tile in tqdm(list(tiles(n)), desc="resample", unit="tile"):
            s = np.asarray(spec[tile], float)
            wi, _ = light_geometry(points[tile][:, None, :], capture.light_positions[None])
            value_sum, weight_sum = splat(grid, wi, s.mean(axis=-1), np.asarray(ok[tile]))
            table[tile] = push_pull(value_sum, weight_sum)
            cover[tile] = footprint.coverage(points[tile], grid.directions.reshape(-1, 3)).reshape((-1,) + grid.shape)
            total = np.where(ok[tile][..., None], s, 0.0).sum(axis=1)
            mean = total.mean(axis=1, keepdims=True)
            colour[tile] = np.divide(total, mean, out=np.ones_like(total), where=mean > 0)
        table.flush()
        cover.flush()
        del table, cover
    with atomic_path(colour_out, suffix=".npy") as tmp:
        np.save(tmp, colour.astype(np.float32))
    write_json(grid_out, grid.to_dict())
