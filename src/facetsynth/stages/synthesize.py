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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .. import synthesis as syn
from ..cluster import material_groups
from ..errors import InputError
from ..fileio import read_exr, read_json, write_json, write_npy
from ..tables import SupportTable
from ..grid import DirectionGrid
from .common import RectifiedCapture, flag_degenerate, tiles

log = logging.getLogger(__name__)

METRIC_POINTS = 1024   # points scored against the true NDF (every k-th visible point)


def run(geometry: str | Path, ndf: str | Path, grid_path: str | Path,
        representatives: str | Path, neighbours: str | Path, weights: str | Path,
        ndf_out: str | Path, confidence_out: str | Path, cosine_out: str | Path, grid_out: str | Path,
        metrics_out: str | Path,
        search: str = "exact", compare: bool = False, n_regions: int = 20, buckets: int = 32,
        candidates: int = 5, overlap: tuple[float, float] = (0.5, 0.85), max_iterations: int = 12,
        target_coverage: float = 0.96, max_relative_error: float = 0.4, stalled_fraction: float = 0.5,
        max_exemplars: int = 4096, ann_neighbors: int = 30, ann_epsilon: float = 0.2, fill_overlap: float | None = None,
        extend_rings: bool = False, isotropic_threshold: float = 0.13, kd: str | Path | None = None,
        material_tolerance: float = 0.25, seed: int = 0,
        rotations: Sequence[tuple[str | Path, str | Path]] = (),
        rep_ndf: str | Path | None = None, rep_confidence: str | Path | None = None,
        rotation: str | Path | None = None) -> None:
    """Complete every representative's NDF; write ndf (R, T, F), its W before fill, the cosine of the
    Fresnel factor each cell carries (R, T, F; see :func:`facetsynth.synthesis.complete`), grid, metrics.

    Isotropy is a property of the material: representatives are grouped into
    materials by kd (``kd``, :func:`facetsynth.cluster.material_groups`, as in
    ``params``), and a material whose representatives' partial NDFs deviate
    from azimuthal symmetry by less than ``isotropic_threshold`` in the median
    (relative L2, :func:`facetsynth.synthesis.anisotropy`; one
    representative alone is noisy when its lobe is narrower than a ring) is
    isotropic: its representatives are completed by azimuthal symmetry
    (:func:`facetsynth.synthesis.complete_isotropic`), without a search
    (without ``kd`` each representative decides alone). When
    every representative is isotropic no exemplar set or index is built at
    all (``search_skipped``). ``isotropic_threshold`` 0 turns this off.

    ``rotations``: (geometry, partial NDF table) of further captures of the same
    sample turned on the rig (paper 002 sec. 4, last paragraph): their partial
    NDFs join the exemplar set (``max_exemplars`` shared evenly), so that a
    material whose frame is the same everywhere (brushed metal) finds rotated
    exemplars. Their rotation angles need not be known: eq. 14 searches every
    rotation anyway."""
    if search not in ("ann", "exact"):
        raise ValueError(f"synthesize.search must be 'ann' or 'exact', not {search!r}")
    capture = RectifiedCapture.load(geometry)
    grid_dict = read_json(grid_path)
    grid = DirectionGrid.from_dict(grid_dict)
    table = SupportTable(ndf)         # partial_ndf's D and W
    d_all, w_all = table.rows("ndf"), table.rows("confidence")
    reps = np.load(representatives)
    t0 = time.perf_counter()
    view = capture.view_directions(True)
    budget = max(2, max_exemplars // (1 + len(rotations)))
    pool = exemplar_pool(capture, budget)
    sources = [(d_all, w_all, view, pool)]
    for rot_geometry, rot_ndf in rotations:
        rot_capture = RectifiedCapture.load(rot_geometry)
        rot_table = SupportTable(rot_ndf)
        rot_d, rot_w = rot_table.rows("ndf"), rot_table.rows("confidence")
        if rot_d.shape[1:] != grid.shape:
            raise InputError(rot_ndf, f"partial NDFs on a {rot_d.shape[1:]} grid; the sample's grid is {grid.shape} "
                                      "(captures of one sample must share the direction grid: fix n_theta_range)")
        sources.append((rot_d, rot_w, rot_capture.view_directions(True), exemplar_pool(rot_capture, budget)))
    ex_index = np.concatenate([pool] + [np.full(src[3].size, -1) for src in sources[1:]])   # -1: another capture
    ex_view = np.concatenate([src[2][src[3]] for src in sources])
    if rep_ndf is None:      # the representatives' own partial NDFs
        rep_d, rep_w = np.asarray(d_all[reps], float), np.asarray(w_all[reps], float)
    else:                    # pooled from their clusters' members (stage cluster)
        rep_d, rep_w = np.load(rep_ndf).astype(float), np.load(rep_confidence).astype(float)
    stat = syn.anisotropy(rep_d, rep_w, grid)
    if kd is None:
        material = np.arange(len(reps))
    else:
        channels, _ = read_exr(kd)
        material = material_groups(channels["RGB"].reshape(-1, 3)[np.asarray(reps, np.intp)], material_tolerance)
    material_stat = {int(m): float(np.median(stat[material == m])) for m in np.unique(material)}
    isotropic = np.array([material_stat[int(m)] < isotropic_threshold for m in material], bool)
    skip = bool(isotropic.all())
    log.info("isotropy: %d of %d representatives isotropic, %d of %d materials (median relative L2 deviation "
             "from ring means and first azimuthal harmonic per material below %.3f: %s; per representative min %.3f, "
             "median %.3f, max %.3f)%s", isotropic.sum(), len(reps),
             sum(v < isotropic_threshold for v in material_stat.values()), len(material_stat), isotropic_threshold,
             {m: round(v, 3) for m, v in material_stat.items()}, stat.min(initial=np.inf), np.median(stat) if stat.size
             else np.nan, stat.max(initial=-np.inf),
             ": all complete by azimuthal symmetry, no exemplar search" if skip else "")
    ex_w = np.concatenate([np.asarray(src[1][src[3]], np.float32) for src in sources])
    ex_d = None if skip else np.concatenate([np.asarray(src[0][src[3]], np.float32) for src in sources])
    spectra = None if skip else syn.ExemplarSpectra(ex_d, ex_w, grid, ex_index)
    concentration = None if skip else _orientation_concentration(ex_d, ex_w, grid, isotropic_threshold)
    mask = np.median(ex_w > syn.SUPPORT, axis=0) > 0.5           # the view's domain Omega (Fig. 7)
    target = syn.hemisphere_target(mask, grid)
    shifts = syn.region_shifts(mask, grid, n_regions, *overlap)
    prep_seconds = time.perf_counter() - t0
    log.info("%d exemplars x %d rotations; domain %.1f %% of the hemisphere, rotations reach %.1f %%; "
             "%d overlap regions, shifts %s sectors", ex_index.size, grid.n_phi,
             100 * np.sum(mask * grid.solid_angles) / (2 * np.pi),
             100 * np.sum(target * grid.solid_angles) / (2 * np.pi), shifts.size,
             np.unique(np.round(shifts)).astype(int).tolist())

    modes = [search] + ([{"ann": "exact", "exact": "ann"}[search]] if compare else [])
    results = {}
    for mode in modes:
        t1, c1 = time.perf_counter(), time.process_time()
        index = None
        build = 0.0
        if mode == "ann" and not skip:
            if shifts.size == 0:
                log.warning("no rotation gives a %.0f-%.0f %% overlap: ANN search disabled, exact search used",
                            100 * overlap[0], 100 * overlap[1])
            else:
                index = syn.HistogramSearch(ex_d, mask, grid, shifts, buckets=buckets, seed=seed,
                                            n_neighbors=ann_neighbors, epsilon=ann_epsilon)
                build = index.build_seconds
        out = []
        for i, r in enumerate(reps):
            if isotropic[i]:
                out.append(syn.complete_isotropic(rep_d[i], rep_w[i], grid, target, view=view[r]))
                continue
            out.append(syn.complete(rep_d[i], rep_w[i], spectra, ex_d, ex_w,
                                    grid, target, search=index, overlap_range=tuple(overlap),
                                    max_iterations=max_iterations, target_coverage=target_coverage,
                                    max_relative_error=max_relative_error, candidates_per_region=candidates,
                                    fill_overlap=fill_overlap, extend_rings=extend_rings,
                                    view=view[r], exemplars_view=ex_view))
        results[mode] = (out, time.perf_counter() - t1, build, time.process_time() - c1)
        log.info("%s search: %d representatives in %.1f s (index build %.1f s)", mode, len(reps),
                 results[mode][1], build)

    completions = results[search][0]
    table = np.stack([c.ndf for c in completions]).astype(np.float32)
    write_npy(ndf_out, table)
    write_npy(confidence_out, np.stack([c.confidence for c in completions]).astype(np.float32))
    write_npy(cosine_out, np.stack([c.fresnel_cosine for c in completions]).astype(np.float32))
    write_json(grid_out, grid_dict)

    metrics = {"representatives": int(len(reps)), "exemplars": 0 if skip else int(ex_index.size),
               "rotation_captures": len(rotations), "search": search,
               "regions": int(shifts.size), "region_shifts_sectors": np.unique(np.round(shifts)).astype(int).tolist(),
               "overlap_range": list(overlap), "max_relative_error": max_relative_error,
               "domain_fraction_of_hemisphere": float(np.sum(mask * grid.solid_angles) / (2 * np.pi)),
               "reachable_fraction_of_hemisphere": float(np.sum(target * grid.solid_angles) / (2 * np.pi)),
               "reachable_max_theta_deg": float(np.degrees((np.flatnonzero(target[:, 0]).max() + 1) * grid.d_theta))
               if target.any() else 0.0,
               "prepare_seconds": round(prep_seconds, 2),
               "isotropic_threshold": isotropic_threshold,
               "isotropic_representatives": int(isotropic.sum()), "search_skipped": skip,
               "anisotropy": [round(float(x), 4) for x in stat],
               "anisotropy_median": float(np.median(stat)) if stat.size else None,
               "materials": len(material_stat),
               "material_anisotropy": [round(v, 4) for v in material_stat.values()]}
    truth = capture.truth()
    scored = np.zeros(capture.n_points, bool)
    if truth is not None:
        visible = np.flatnonzero(capture.visible)
        scored[visible[:: max(1, visible.size // METRIC_POINTS)]] = True
        scored &= (truth.region >= 0) & truth.analytic   # the true NDF is what is recovered only on eq. 6 points
    nbr, wts = np.load(neighbours, mmap_mode="r"), np.load(weights, mmap_mode="r")
    for mode, (comps, secs, build_s, cpu) in results.items():
        summary = _summary(comps, secs, build_s, stalled_fraction)
        summary["cpu_seconds"] = round(cpu, 2)     # process CPU time: comparable under a loaded machine
        if truth is not None:
            tab = np.stack([c.ndf for c in comps])
            errs = _score(tab, nbr, wts, scored, truth, grid,
                          None if rotation is None else np.load(rotation).astype(float))
            summary["ndf_rel_l2_median"] = float(np.median(errs)) if errs.size else None
            summary["ndf_rel_l2_p90"] = float(np.quantile(errs, 0.9)) if errs.size else None
            summary["scored_points"] = int(errs.size)
        for key, value in summary.items():
            metrics[key + "_" + mode] = value
            if mode == search:
                metrics[key] = value
    metrics["ground_truth"] = truth is not None
    # Rotation diversity is decided from the exemplars' lobe axes: one axis everywhere is insufficient even
    # where broad lobes match themselves at wrong rotations (then few representatives stall), and stalls
    # alone also come from noise (wallpaper with sensor noise: 17 of 32). docs/decisions.md.
    metrics["orientation_concentration"] = concentration
    metrics["insufficient_rotation_diversity"] = bool(concentration is not None
                                                      and concentration >= syn.SINGLE_ORIENTATION)
    stalled = f"{metrics['stalled_representatives']} of {len(reps)} representatives stalled"
    if metrics["insufficient_rotation_diversity"]:
        flag_degenerate(metrics, f"INSUFFICIENT ROTATION DIVERSITY: the anisotropic exemplars' lobe axes all point "
                        f"one way (concentration {concentration:.2f} >= {syn.SINGLE_ORIENTATION:.2f}), so no exemplar "
                        f"shows this material at another rotation; {stalled} (no match within relative error "
                        f"{max_relative_error:.2f}, coverage before fill {metrics['coverage_before_fill']:.2f}). What "
                        "the fit did: the stalled NDFs are push-pull extensions of what this view measured, the others "
                        "completed from the one orientation seen. What it costs: the NDF where no light fell is "
                        "extrapolated, so renders from views far from this camera's are the least reliable part of "
                        "the model; the self-check's held-out lights (same view) do not show it. (Captures of the "
                        "sample turned on the rig, listed with rotation_of = this sample, would join its exemplars.)",
                        log)
    elif metrics["stalled_majority"]:
        flag_degenerate(metrics, f"{stalled} (no exemplar within relative error {max_relative_error:.2f}) although "
                        f"the lobe axes vary (concentration "
                        f"{'n/a' if concentration is None else f'{concentration:.2f}'}): noisy or narrow partial NDFs, "
                        "not missing rotations; their NDFs are push-pull extensions beyond the merged domain.", log)
    log.info("synthesize metrics: %s", {k: v for k, v in metrics.items() if not isinstance(v, list)})
    write_json(metrics_out, metrics)


def _orientation_concentration(ex_d, ex_w, grid: DirectionGrid, isotropic_threshold: float) -> float | None:
    """:func:`facetsynth.synthesis.orientation_concentration` over the exemplars whose partial NDF is
    anisotropic (:func:`facetsynth.synthesis.anisotropy` >= ``isotropic_threshold``); None without any."""
    axes = []
    for t in tiles(len(ex_d), 512):
        d, w = np.asarray(ex_d[t], float), np.asarray(ex_w[t], float)
        axes.append(syn.orientation(d, w, grid)[syn.anisotropy(d, w, grid) >= isotropic_threshold])
    axes = np.concatenate(axes) if axes else np.zeros(0, complex)
    value = syn.orientation_concentration(axes)
    return None if not np.isfinite(value) else value


def exemplar_pool(capture: RectifiedCapture, budget: int) -> np.ndarray:
    """Exemplar points of one capture: its visible points, strided down to at most ``budget``."""
    visible = np.flatnonzero(capture.visible)
    return visible[:: max(1, int(np.ceil(visible.size / budget)))]


def _summary(comps, seconds, build, stalled_fraction) -> dict:
    cov = np.array([c.coverage for c in comps])
    stalled = np.array([c.stalled for c in comps])
    merged = [m for c in comps for m in c.merges if m["merged"]]
    return {"coverage_before_fill": float(np.mean(cov)), "coverage_before_fill_min": float(np.min(cov)),
            "iterations_median": float(np.median([c.iterations for c in comps])),
            "stalled_representatives": int(stalled.sum()),
            "stalled_majority": bool(stalled.mean() >= stalled_fraction),
            "merge_relative_error_median": float(np.median([m["relative_error"] for m in merged])) if merged else None,
            "exact_fallback_iterations": int(sum(c.fallbacks for c in comps)),
            "merges": int(len(merged)),
            "seconds": round(seconds, 2), "index_build_seconds": round(build, 2)}


def _score(table, nbr, wts, scored, truth, grid, rotation=None) -> np.ndarray:
    """Relative L2 (solid-angle weighted, all cells) of sum_k w_k ndf[nbr_k] (turned by the point's
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
