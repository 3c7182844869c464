"""The partial_ndf stage's partial NDFs against a virtual capture's recoverable true NDF."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..fit import partial_ndf
from ..io.fileio import read_json
from ..geometry.grid import DirectionGrid
from ..io.tables import SupportTable
from ..stages.common import RectifiedCapture
from .truth import median_or_none, scored_points, truth_of

VARIANTS = {"constrained": (True, "constrained"), "unconstrained": (True, "unconstrained"),
            "clipped": (True, "clipped"), "centre_view": (False, "constrained")}


def partial_ndf_errors(ndf: np.ndarray, confidence: np.ndarray, view: np.ndarray, maps,
                       grid: DirectionGrid) -> np.ndarray:
    """Relative L2 error of partial NDFs against the recoverable truth over cells with W >= 0.5."""
    true_ndf = maps.take((slice(None), None)).ndf(grid.directions.reshape(1, -1, 3)).reshape(ndf.shape)
    reference = partial_ndf.recoverable_ndf(maps.ks, maps.eta, true_ndf, view, grid)
    return partial_ndf.relative_l2(ndf, reference, confidence >= 0.5, grid)


def variant_errors(geometry: str | Path, slice_path: str | Path, grid_path: str | Path,
                   variants: dict[str, tuple[bool, bool | str]] = VARIANTS, grazing_deg: float = 80.0,
                   tol: float = 1e-3, max_iter: int = 30) -> dict[str, float | None]:
    """Median relative L2 error of each variant (per_point_view, shadowing method) on the scored points of a
    virtual capture's resampled data: how the paper's choices (sec. 5.1, Fig. 5) compare on a scene. A scene
    without analytic truth (measured BRDFs only) has no scored point: every variant is None."""
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    truth = truth_of(capture)
    if truth is None:
        raise ValueError(f"{geometry}: variants are compared against the truth, and this capture has none")
    index = np.flatnonzero(scored_points(capture, truth))
    if index.size == 0:
        return {name: None for name in variants}
    s = np.asarray(SupportTable(slice_path).rows("values")[index], float)
    c = capture.light_coverage(grid)(index)
    maps = truth.take(index)
    result = {}
    for name, (per_point, constrain) in variants.items():
        view = capture.view_directions(per_point, index)
        fit = partial_ndf.fit(s, c, view, grid, constrain, grazing_deg, tol, max_iter)
        result[name] = median_or_none(partial_ndf_errors(fit.ndf, fit.confidence, view, maps, grid))
    return result
