"""The synthesize stage's completed NDFs (eq. 18 mixtures at the points) against a virtual capture's true NDFs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry.grid import DirectionGrid
from ..stages.common import RectifiedCapture, tiles
from .truth import scored_points, truth_of


def truth_scores(capture: RectifiedCapture, grid: DirectionGrid, tables: dict[str, list], neighbours: Path,
                 weights: Path, rotation: Path | None) -> dict:
    """Each search mode's completed NDFs (``tables``: {mode: its R tables (T, F)}, stacked only for a virtual
    capture; with cluster's eq. 18 ``neighbours``, ``weights`` and ``rotation`` files) against a virtual
    capture's true ones (:func:`ndf_errors` on
    :func:`facetsynth.evaluation.truth.scored_points`): median and 90th percentile relative L2, points scored;
    {} for a real capture."""
    truth = truth_of(capture)
    if truth is None:
        return {}
    scored = scored_points(capture, truth)
    nbr, wts = np.load(neighbours, mmap_mode="r"), np.load(weights, mmap_mode="r")
    turns = None if rotation is None else np.load(rotation).astype(float)
    out = {}
    for mode, table in tables.items():
        errs = ndf_errors(np.stack(table), nbr, wts, scored, truth, grid, turns)   # stacked only for a truth
        out[mode] = {"ndf_rel_l2_median": float(np.median(errs)) if errs.size else None,
                     "ndf_rel_l2_p90": float(np.quantile(errs, 0.9)) if errs.size else None,
                     "scored_points": int(errs.size)}
    return out


def ndf_errors(table, nbr, wts, scored, truth, grid, rotation=None) -> np.ndarray:
    """Relative L2 (solid-angle weighted, all cells) of sum_k w_k ndf[nbr_k] (eq. 18; turned by the point's
    ``rotation``, where the cluster stage gave one) against the true NDF, both normalised to integral
    (n.h) D = 1 on the grid."""
    h = grid.directions
    cos = h[..., 2]
    errs = []
    idx = np.flatnonzero(scored)
    for t in tiles(idx.size):
        p = idx[t]
        est = np.einsum("nk,nktp->ntp", np.asarray(wts[p], float), table[np.asarray(nbr[p])])
        if rotation is not None:
            est = np.stack([grid.rotate(e, phi) for e, phi in zip(est, rotation[p])])
        ref = truth.take((p, None)).ndf(h.reshape(1, -1, 3)).reshape(est.shape)
        est = est / np.where(np.abs(grid.integrate(est * cos)) > 0, grid.integrate(est * cos), 1.0)[:, None, None]
        ref = ref / grid.integrate(ref * cos)[:, None, None]
        num, den = grid.integrate((est - ref) ** 2), grid.integrate(ref**2)
        errs.append(np.sqrt(num / den))
    errs = np.concatenate(errs) if errs else np.zeros(0)
    return errs[np.isfinite(errs)]
