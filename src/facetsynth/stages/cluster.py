"""Stage ``cluster``: k-means representatives and eq. 18 interpolation weights (paper 002 sec. 5.3).

Points are compared on a coarse grid (:func:`facetsynth.cluster.coarse`),
where the phase of the lights against a glossy lobe averages out; each
representative's partial NDF is then fitted from the pooled samples of its
cluster's members (:func:`facetsynth.partial_ndf.pooled_fit`), which sample the
shared NDF far more densely than the lights sample any one point.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import cluster
from .. import partial_ndf as pndf
from ..fileio import NpyRows, read_exr, read_json, write_json, write_npy
from ..tables import SupportTable
from ..frames import imap
from ..grid import DirectionGrid
from ..partial_ndf import relative_l2
from .common import RectifiedCapture, tiles

log = logging.getLogger(__name__)

POOL_MEMBERS = 2048  # members (evenly strided) whose samples a representative's partial NDF pools
TURN_GAIN = 0.8      # a cluster is one material turning across the sample when turning its points onto its
TURN_SPREAD = 0.5    # representative lowers their eq. 15 distance by 20 % (median) and their turns spread over
                     # more than half a sector (standard deviation): then each point is that representative turned


def run(geometry: str | Path, ndf: str | Path, grid_path: str | Path,
        specular: str | Path | None, valid: str | Path | None,
        labels_out: str | Path, representatives_out: str | Path, neighbours_out: str | Path,
        weights_out: str | Path, rep_ndf_out: str | Path, rep_confidence_out: str | Path, rotation_out: str | Path,
        metrics_out: str | Path,
        representatives: str | int | float = "auto",
        min_representatives: int = 1, max_representatives: int = 64, distortion: float = 0.08, spread: float = 0.15,
        scan_points: int = 2048, neighbours: int = 16, radius: float = 5.0, ridge: float = 1e-3, n_init: int = 3,
        seed: int = 0, constrained: bool = True, grazing_deg: float = 80.0, tol: float = 1e-3,
        max_iter: int = 30, kd: str | Path | None = None, threads: int = 1) -> None:
    """Cluster the visible points' partial NDFs; write labels, representatives, neighbours, weights.

    The number of representatives: ``representatives`` "auto" chooses it from
    the data (:func:`facetsynth.cluster.choose_k`: the smallest k on a
    geometric ladder from ``min_representatives`` to ``max_representatives``
    whose k-means distortion falls below ``distortion`` of the total
    variance, scanned on ``scan_points`` points); an integer >= 1 fixes it;
    a number in (0, 1) is a fraction of the visible points (the paper's 1 %,
    at least ``min_representatives``). ``spread``: a cluster whose points lie
    within this relative L2 of its centre is one material (k stops there).
    Invisible points get label -1 and all-zero weights; every visible point's
    weights sum to 1. Each representative's partial NDF (``rep_ndf_out``,
    ``rep_confidence_out``, (R, T, F)) pools its members' samples
    (``specular``, ``valid`` from ``separate``; eqs. 11 and 5 as in
    ``partial_ndf``: ``constrained``, ``grazing_deg``, ``tol``, ``max_iter``);
    without the samples (None) it is the representative's own partial NDF.
    ``kd`` (``separate``'s map): points are compared by their diffuse albedo
    too (:func:`facetsynth.cluster.with_albedo`), so that two materials of one
    lobe shape stay two (eta and isotropy are decided per material by kd). The partial NDFs are read and
    coarsened on ``threads`` threads.
    """
    t0 = time.perf_counter()
    capture = RectifiedCapture.load(geometry)
    grid = DirectionGrid.from_dict(read_json(grid_path))
    table = SupportTable(ndf)         # partial_ndf's D and W
    d_all, w_all = table.rows("ndf"), table.rows("confidence")
    n = capture.n_points
    visible = np.flatnonzero(capture.visible)
    if visible.size == 0:
        raise ValueError("no visible points to cluster")
    d, w, cgrid = coarse_points(d_all, w_all, visible, grid, threads=threads)
    log.info("points compared on a %d x %d grid (partial NDFs on %d x %d)", *cgrid.shape, *grid.shape)
    domain = cluster.common_domain(w)
    log.info("features on the cells %s", "every point sees (W >= 0.6 at 97 %% of the points): %d of %d" % (
        domain.sum(), domain.size) if domain is not None else "of each point's own domain (no common one)")
    feats = cluster.features(d, w, cgrid, domain)
    if kd is not None:
        channels, _ = read_exr(kd)
        feats = cluster.with_albedo(feats, channels["RGB"].reshape(n, 3)[visible])
    choice = None
    if isinstance(representatives, str) and representatives.strip() != "auto":
        try:                                  # --config passes numbers as strings
            representatives = float(representatives)
        except ValueError:
            pass
    if isinstance(representatives, str):
        if representatives.strip() != "auto":
            raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                             f"not {representatives!r}")
        choice = cluster.choose_k(feats, min_representatives, min(max_representatives, visible.size), distortion,
                                  subsample=scan_points, seed=seed, spread=spread)
        wanted = choice.k
        log.info("representatives: auto, k = %d (%s); distortion / total variance on %d points: %s", wanted,
                 choice.rule, choice.subsample,
                 ", ".join(f"k={k}: {v:.3f}" for k, v in zip(choice.ladder, choice.distortion)))
    elif float(representatives) >= 1:
        wanted = int(representatives)
        log.info("representatives: fixed at %d", wanted)
    elif float(representatives) > 0:
        wanted = int(max(min_representatives, round(float(representatives) * visible.size)))
        log.info("representatives: %g of %d visible points, at least %d: %d", float(representatives),
                 visible.size, min_representatives, wanted)
    else:
        raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                         f"not {representatives!r}")
    result = cluster.kmeans(feats, d, w, cgrid, wanted, seed=seed, n_init=n_init)
    del feats
    reps = result.representatives                      # rows of the visible subset
    log.info("k-means: %d visible points, %d representatives (%d asked, %d distinct NDFs)",
             visible.size, reps.size, wanted, result.distinct)
    if specular is None:
        rows = visible[reps]
        pooled = Pooled(np.asarray(d_all[rows], float), np.asarray(w_all[rows], float), np.ones(reps.size, int))
    else:
        pooled = pooled_representatives(capture, visible, result, d_all, w_all, NpyRows(specular),
                                        NpyRows(valid), grid, constrained, grazing_deg, tol, max_iter)
    rep_d, rep_w, _ = cluster.coarse(pooled.ndf, pooled.confidence, grid)
    if domain is not None:      # eq. 18 compared on the cells every point sees, as k-means (the domain is the rig's)
        w, rep_w = np.broadcast_to(domain, w.shape).astype(float), np.broadcast_to(domain, rep_w.shape).astype(float)
    nbr, wts, lam = cluster.interpolation_weights(d, w, rep_d, rep_w, cgrid, k=neighbours, radius=radius,
                                                  ridge=ridge)
    turns = point_turns(d_all, w_all, visible, result.labels, pooled, grid)
    turned = np.flatnonzero(turns.turned)
    members = np.isin(result.labels, turned)
    nbr[members], wts[members] = result.labels[members, None], 0.0
    wts[members, 0] = 1.0
    point_turn = np.where(members, turns.phi, 0.0)
    log.info("%d of %d clusters turn across the sample (%d points): each point is its representative turned "
             "(eq. 13); turn spread per cluster (deg) %s", turned.size, reps.size, int(members.sum()),
             np.round(np.degrees(turns.spread), 1).tolist())
    # eq. 18 on the partial data: how well the representatives span the points
    err = np.concatenate([relative_l2(np.einsum("nk,nktp->ntp", wts[t], rep_d[nbr[t]]), d[t], w[t] > 0, cgrid)
                          for t in tiles(visible.size)])
    err = err[np.isfinite(err)]
    used = (wts != 0).sum(axis=1)

    labels = np.full(n, -1, np.int32)
    labels[visible] = result.labels
    neighbours_full = np.zeros((n, neighbours), np.int32)
    weights_full = np.zeros((n, neighbours), np.float32)
    neighbours_full[visible], weights_full[visible] = nbr, wts
    write_npy(labels_out, labels)
    write_npy(representatives_out, visible[reps].astype(np.int64))
    write_npy(neighbours_out, neighbours_full)
    write_npy(weights_out, weights_full)
    write_npy(rep_ndf_out, pooled.ndf.astype(np.float32))
    write_npy(rep_confidence_out, pooled.confidence.astype(np.float32))
    rotation = np.zeros(n, np.float32)
    rotation[visible] = point_turn
    write_npy(rotation_out, rotation)
    metrics = {"points": n, "visible_points": int(visible.size), "representatives": int(reps.size),
               "representatives_requested": wanted, "distinct_ndfs": int(result.distinct),
               "representatives_rule": ("auto" if choice is not None else
                                        "fixed" if float(representatives) >= 1 else "fraction"),
               "k_chosen": wanted,
               **({"k_rule": choice.rule, "k_distortion_tolerance": distortion, "k_scan_points": choice.subsample,
                   "k_ladder": choice.ladder, "k_distortion_curve": [round(v, 5) for v in choice.distortion],
                   "k_spread_curve": [round(v, 5) for v in choice.spread],
                   "k_scan_seconds": round(choice.seconds, 2)} if choice is not None else
                  {"representatives_setting": representatives}),
               "lambda": lam if np.isfinite(lam) else None, "radius_lambda": radius, "k": neighbours,
               "ridge": ridge, "neighbours_used_median": float(np.median(used)),
               "eq18_partial_rel_l2_median": float(np.median(err)) if err.size else None,
               "eq18_partial_rel_l2_p90": float(np.quantile(err, 0.9)) if err.size else None,
               "comparison_grid": list(cgrid.shape), "spread_tolerance": spread,
               "pooled_members_median": float(np.median(pooled.members)),
               "turned_clusters": int(turned.size), "turned_points_fraction": float(members.mean()),
               "turn_rule": f"median eq. 15 gain < {TURN_GAIN} and turn spread > {TURN_SPREAD} sector",
               "negative_weight_fraction": float(np.mean(wts[wts != 0] < 0)) if np.any(wts != 0) else 0.0,
               "seconds": round(time.perf_counter() - t0, 2)}
    log.info("cluster metrics: %s", metrics)
    write_json(metrics_out, metrics)


def coarse_points(d_all, w_all, rows: np.ndarray, grid: DirectionGrid, tile: int = 4096, threads: int = 1):
    """:func:`facetsynth.cluster.coarse` of the points ``rows`` of the memory-mapped (P, T, F) tables, a tile
    at a time on ``threads`` threads: memory holds the coarse tables (16 x smaller on the demo's grid), never
    the full ones."""
    blocks = list(imap(lambda t: cluster.coarse(d_all[rows[t]], w_all[rows[t]], grid), list(tiles(rows.size, tile)),
                       threads, "cluster: coarse tables", unit="tile"))
    return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]), blocks[0][2]


@dataclass(frozen=True)
class Pooled:
    ndf: np.ndarray          # (R, T, F) each representative's partial NDF from its members' pooled samples
    confidence: np.ndarray   # (R, T, F)
    members: np.ndarray      # (R,) members pooled


def pooled_representatives(capture: RectifiedCapture, visible: np.ndarray, result, d_all, w_all, specular, valid,
                           grid: DirectionGrid, constrained: bool, grazing_deg: float, tol: float,
                           max_iter: int) -> Pooled:
    """Every cluster's partial NDF from up to POOL_MEMBERS of its members' eq. 8 samples
    (:func:`facetsynth.partial_ndf.pooled_fit`), for its representative's view and, where the cluster turns
    across the sample (TURN_GAIN, TURN_SPREAD), in its frame (each member's turn against it,
    :func:`facetsynth.cluster.relative_rotation`, undone; elsewhere the turns are noise, and undoing
    them would blur the lobe)."""
    views = capture.view_directions(True)
    ndf = np.zeros((len(result.representatives),) + grid.shape)
    conf = np.zeros_like(ndf)
    counts = np.zeros(len(result.representatives), int)
    for c, rep in enumerate(tqdm(result.representatives, desc="cluster: pooled partial NDFs", unit="rep")):
        members = visible[np.flatnonzero(result.labels == c)]
        members = members[:: max(1, int(np.ceil(members.size / POOL_MEMBERS)))]
        w_members = np.asarray(w_all[members], float)
        own = visible[rep]
        turn, gain = cluster.relative_rotation(np.asarray(d_all[members], float), w_members,
                                               np.asarray(d_all[own], float), np.asarray(w_all[own], float), grid,
                                               max_shift=grid.n_phi // 4)
        turning = np.median(gain) < TURN_GAIN and np.std(turn) > TURN_SPREAD * grid.d_phi
        fit = pndf.pooled_fit(np.asarray(specular[members], float).mean(axis=-1), np.asarray(valid[members]),
                              capture.light_directions(members)[0], views[members], w_members,
                              views[own], grid, constrained, grazing_deg, tol, max_iter,
                              rotation=turn if turning else None)
        ndf[c], conf[c], counts[c] = fit.ndf[0], fit.confidence[0], members.size
    return Pooled(ndf, conf, counts)


@dataclass(frozen=True)
class Turns:
    phi: np.ndarray          # (N,) each visible point's turn against its cluster's representative (radians; 0
                             # in a cluster that does not turn)
    spread: np.ndarray       # (R,) standard deviation of the turns within each cluster (radians)
    gain: np.ndarray         # (R,) median eq. 15 distance turned / unturned within each cluster
    turned: np.ndarray       # (R,) bool: the cluster is one material turning across the sample


def point_turns(d_all, w_all, visible: np.ndarray, labels: np.ndarray, pooled: Pooled, grid: DirectionGrid,
                batch: int = 512) -> Turns:
    """Each visible point's turn against its cluster's pooled partial NDF (eq. 13,
    :func:`facetsynth.cluster.relative_rotation`), and which clusters are one material turning across the
    sample (TURN_GAIN, TURN_SPREAD): for those a representative and a per-point turn replace eq. 18's
    mixture of representatives at other turns, which showed as wedges on the demo's turned copper.
    Whether a cluster turns, its spread and gain, are measured on up to POOL_MEMBERS of its members
    (evenly strided); the turns of every member only where it does (elsewhere the turn is 0)."""
    n_rep = len(pooled.ndf)
    phi, gain = np.zeros(len(visible)), np.ones(len(visible))

    def measure(rows: np.ndarray, c: int) -> None:
        for start in range(0, rows.size, batch):
            part = rows[start:start + batch]
            d, w = np.asarray(d_all[visible[part]], float), np.asarray(w_all[visible[part]], float)
            phi[part], gain[part] = cluster.relative_rotation(d, w, pooled.ndf[c], pooled.confidence[c], grid,
                                                              max_shift=grid.n_phi // 4)

    spread, median_gain = np.zeros(n_rep), np.ones(n_rep)
    for c in range(n_rep):
        members = np.flatnonzero(labels == c)
        if members.size == 0:
            continue
        sample = members[:: max(1, int(np.ceil(members.size / POOL_MEMBERS)))]
        measure(sample, c)
        spread[c], median_gain[c] = float(np.std(phi[sample])), float(np.median(gain[sample]))
        if median_gain[c] < TURN_GAIN and spread[c] > TURN_SPREAD * grid.d_phi:
            measure(np.setdiff1d(members, sample, assume_unique=True), c)
        else:
            phi[sample] = 0.0
    turned = (median_gain < TURN_GAIN) & (spread > TURN_SPREAD * grid.d_phi)
    return Turns(phi, spread, median_gain, turned)
