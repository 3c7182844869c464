"""Stage ``synthesize``: complete the representatives' NDFs (paper 002 sec. 5.2-5.3).

The exemplar set is the visible points' partial NDFs (strided down to at most
``max_exemplars``) at every rotation (eq. 13). Each representative is
completed by :func:`facetsynth.synthesis.complete`, with the ANN search of
sec. 5.3 (``search: ann``) or the exact search (``search: exact``); with
``compare`` the other mode is run too and both are recorded (keys suffixed
``_ann`` and ``_exact``; the unsuffixed keys are the written mode's). The
per-point complete NDF is never stored: it is sum_k weights[x, k]
ndf[neighbours[x, k]] (eq. 18, from the ``cluster`` stage).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from .. import synthesis as syn
from ..fileio import read_json, write_json, write_npy
from ..grid import DirectionGrid
from ..microfacet import fresnel
from ..synthesis import TINY
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)

METRIC_POINTS = 1024   # points scored against the true NDF (every k-th visible point)


def run(geometry: str | Path, ndf: str | Path, confidence: str | Path, grid_path: str | Path,
        representatives: str | Path, neighbours: str | Path, weights: str | Path,
        ndf_out: str | Path, confidence_out: str | Path, grid_out: str | Path, metrics_out: str | Path,
        search: str = "exact", compare: bool = False, n_regions: int = 20, buckets: int = 32,
        candidates: int = 5, overlap: tuple[float, float] = (0.5, 0.85), max_iterations: int = 12,
        target_coverage: float = 0.96, max_relative_error: float = 0.4, stalled_fraction: float = 0.5,
        max_exemplars: int = 4096, ann_neighbors: int = 30, ann_epsilon: float = 0.2, fill_overlap: float | None = None,
        extend_rings: bool = False, fresnel_eta: float | None = None, seed: int = 0) -> None:
    """Complete every representative's NDF; write ndf (R, T, F), its W before fill, grid, metrics."""
    if search not in ("ann", "exact"):
        raise ValueError(f"synthesize.search must be 'ann' or 'exact', not {search!r}")
    capture = RectifiedCapture.load(geometry)
    grid_dict = read_json(grid_path)
    grid = DirectionGrid.from_dict(grid_dict)
    d_all = np.load(ndf, mmap_mode="r")
    w_all = np.load(confidence, mmap_mode="r")
    reps = np.load(representatives)
    visible = np.flatnonzero(capture.visible)
    pool = visible[:: max(1, int(np.ceil(visible.size / max_exemplars)))]
    t0 = time.perf_counter()
    view = capture.view_directions(True)
    ex_d = np.asarray(d_all[pool], np.float32) * _fresnel_factor(view[pool], grid, fresnel_eta)
    ex_w = np.asarray(w_all[pool], np.float32)
    spectra = syn.ExemplarSpectra(ex_d, ex_w, grid, pool)
    mask = np.median(ex_w > syn.SUPPORT, axis=0) > 0.5           # the view's domain Omega (Fig. 7)
    target = syn.hemisphere_target(mask, grid)
    shifts = syn.region_shifts(mask, grid, n_regions, *overlap)
    prep_seconds = time.perf_counter() - t0
    log.info("%d exemplars x %d rotations; domain %.1f %% of the hemisphere, rotations reach %.1f %%; "
             "%d overlap regions, shifts %s sectors", pool.size, grid.n_phi,
             100 * np.sum(mask * grid.solid_angles) / (2 * np.pi),
             100 * np.sum(target * grid.solid_angles) / (2 * np.pi), shifts.size,
             np.unique(np.round(shifts)).astype(int).tolist())

    modes = [search] + ([{"ann": "exact", "exact": "ann"}[search]] if compare else [])
    results = {}
    for mode in modes:
        t1, c1 = time.perf_counter(), time.process_time()
        index = None
        build = 0.0
        if mode == "ann":
            if shifts.size == 0:
                log.warning("no rotation gives a %.0f-%.0f %% overlap: ANN search disabled, exact search used",
                            100 * overlap[0], 100 * overlap[1])
            else:
                index = syn.HistogramSearch(ex_d, mask, grid, shifts, buckets=buckets, seed=seed,
                                            n_neighbors=ann_neighbors, epsilon=ann_epsilon)
                build = index.build_seconds
        out = []
        for r in reps:
            d_rep = np.asarray(d_all[r], float) * _fresnel_factor(view[[r]], grid, fresnel_eta)[0]
            out.append(syn.complete(d_rep, np.asarray(w_all[r], float), spectra, ex_d, ex_w,
                                    grid, target, search=index, overlap_range=tuple(overlap),
                                    max_iterations=max_iterations, target_coverage=target_coverage,
                                    max_relative_error=max_relative_error, candidates_per_region=candidates,
                                    fill_overlap=fill_overlap, extend_rings=extend_rings))
        results[mode] = (out, time.perf_counter() - t1, build, time.process_time() - c1)
        log.info("%s search: %d representatives in %.1f s (index build %.1f s)", mode, len(reps),
                 results[mode][1], build)

    completions = results[search][0]
    table = np.stack([c.ndf for c in completions]).astype(np.float32)
    write_npy(ndf_out, table)
    write_npy(confidence_out, np.stack([c.confidence for c in completions]).astype(np.float32))
    write_json(grid_out, grid_dict)

    metrics = {"representatives": int(len(reps)), "exemplars": int(pool.size), "search": search,
               "regions": int(shifts.size), "region_shifts_sectors": np.unique(np.round(shifts)).astype(int).tolist(),
               "overlap_range": list(overlap), "max_relative_error": max_relative_error,
               "domain_fraction_of_hemisphere": float(np.sum(mask * grid.solid_angles) / (2 * np.pi)),
               "reachable_fraction_of_hemisphere": float(np.sum(target * grid.solid_angles) / (2 * np.pi)),
               "reachable_max_theta_deg": float(np.degrees((np.flatnonzero(target[:, 0]).max() + 1) * grid.d_theta))
               if target.any() else 0.0,
               "prepare_seconds": round(prep_seconds, 2)}
    truth = capture.truth()
    scored = np.zeros(capture.n_points, bool)
    if truth is not None:
        scored[visible[:: max(1, visible.size // METRIC_POINTS)]] = True
        scored &= truth.region >= 0
    nbr, wts = np.load(neighbours, mmap_mode="r"), np.load(weights, mmap_mode="r")
    for mode, (comps, secs, build_s, cpu) in results.items():
        summary = _summary(comps, secs, build_s, stalled_fraction)
        summary["cpu_seconds"] = round(cpu, 2)     # process CPU time: comparable under a loaded machine
        if truth is not None:
            tab = np.stack([c.ndf for c in comps])
            errs = _score(tab, nbr, wts, scored, truth, grid)
            summary["ndf_rel_l2_median"] = float(np.median(errs)) if errs.size else None
            summary["ndf_rel_l2_p90"] = float(np.quantile(errs, 0.9)) if errs.size else None
            summary["scored_points"] = int(errs.size)
        for key, value in summary.items():
            metrics[key + "_" + mode] = value
            if mode == search:
                metrics[key] = value
    metrics["ground_truth"] = truth is not None
    if metrics["insufficient_rotation_diversity"]:
        log.warning("INSUFFICIENT ROTATION DIVERSITY: %d of %d representatives could not be completed from "
                    "rotated exemplars (no exemplar matched within relative error %.2f); their NDFs are only "
                    "push-pull extensions of the partial data (coverage before fill %.2f). Capture the sample "
                    "at further rotations (paper 002 sec. 4).", metrics["stalled_representatives"], len(reps),
                    max_relative_error, metrics["coverage_before_fill"])
    log.info("synthesize metrics: %s", {k: v for k, v in metrics.items() if not isinstance(v, list)})
    write_json(metrics_out, metrics)


def _fresnel_factor(view: np.ndarray, grid: DirectionGrid, eta: float | None) -> np.ndarray:
    """F(|o.n|, eta) / F(|o.h|, eta) per cell (N, T, F) float32: moves the partial NDF's Fresnel factor
    (eq. 11 assumes F = 1) to its value at h = n. Ones when eta is None."""
    if eta is None:
        return np.ones((len(view),) + grid.shape, np.float32)
    h = grid.directions.reshape(1, -1, 3)
    c = np.abs(np.sum(h * view[:, None, :], axis=-1))
    f = fresnel(np.abs(view[:, 2:3]), eta) / np.maximum(fresnel(c, eta), TINY)
    return f.reshape((len(view),) + grid.shape).astype(np.float32)


def _summary(comps, seconds, build, stalled_fraction) -> dict:
    cov = np.array([c.coverage for c in comps])
    stalled = np.array([c.stalled for c in comps])
    merged = [m for c in comps for m in c.merges if m["merged"]]
    return {"coverage_before_fill": float(np.mean(cov)), "coverage_before_fill_min": float(np.min(cov)),
            "iterations_median": float(np.median([c.iterations for c in comps])),
            "stalled_representatives": int(stalled.sum()),
            "insufficient_rotation_diversity": bool(stalled.mean() >= stalled_fraction),
            "merge_relative_error_median": float(np.median([m["relative_error"] for m in merged])) if merged else None,
            "exact_fallback_iterations": int(sum(c.fallbacks for c in comps)),
            "merges": int(len(merged)),
            "seconds": round(seconds, 2), "index_build_seconds": round(build, 2)}


def _score(table, nbr, wts, scored, truth, grid) -> np.ndarray:
    """Relative L2 (solid-angle weighted, all cells) of sum_k w_k ndf[nbr_k] against the true NDF, both
    normalised to integral (n.h) D = 1 on the grid."""
    h = grid.directions
    cos = h[..., 2]
    errs = []
    idx = np.flatnonzero(scored)
    for t in tiles(idx.size):
        p = idx[t]
        est = np.einsum("nk,nktp->ntp", np.asarray(wts[p], float), table[np.asarray(nbr[p])])
        ref = truth.take((p, None)).ndf(h.reshape(1, -1, 3)).reshape(est.shape)
        est = est / np.where(np.abs(grid.integrate(est * cos)) > 0, grid.integrate(est * cos), 1.0)[:, None, None]
        ref = ref / grid.integrate(ref * cos)[:, None, None]
        num, den = grid.integrate((est - ref) ** 2), grid.integrate(ref**2)
        errs.append(np.sqrt(num / den))
    errs = np.concatenate(errs) if errs else np.zeros(0)
    return errs[np.isfinite(errs)]
