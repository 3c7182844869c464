"""Stage ``cluster``: k-means representatives and eq. 18 interpolation weights (paper 002 sec. 5.3).

Points are compared on a coarse grid (:func:`facetsynth.fit.cluster.coarse`),
where the phase of the lights against a glossy lobe averages out; each
representative's partial NDF is then fitted from the pooled samples of its
cluster's members (:func:`facetsynth.fit.partial_ndf.pooled_fit`), which sample the
shared NDF far more densely than the lights sample any one point.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..fit import cluster
from ..fit import partial_ndf
from ..io.colour import channel_mean
from ..io.fileio import NpyRows, read_exr, read_json, write_json, write_npy
from ..io.tables import SupportTable
from ..io.frames import imap, map_frames
from ..geometry.grid import DirectionGrid
from ..fit.partial_ndf import relative_l2
from .common import RectifiedCapture, RuleFiles, StageSettings, tiles

log = logging.getLogger(__name__)

POOL_MEMBERS = 2048  # members (evenly strided) whose samples a representative's partial NDF pools
TURN_GAIN = 0.8      # a cluster is one material turning across the sample when turning its points onto its
TURN_SPREAD = 0.5    # representative lowers their eq. 15 distance by 20 % (median) and their turns spread over
                     # more than half a sector (standard deviation): then each point is that representative turned


class Inputs(RuleFiles):
    """Rule ``cluster``'s inputs: separate's geometry, partial_ndf's tables and resample's grid; separate's
    samples (without them, None, each representative's partial NDF is its own) and kd map (None: points are
    compared by their partial NDFs alone)."""
    geometry: Path
    ndf: Path
    grid: Path
    specular: Path | None = None
    valid: Path | None = None
    kd: Path | None = None


class Outputs(RuleFiles):
    """Rule ``cluster``'s outputs: per point its cluster, eq. 18 neighbours and weights and turn; the
    representatives, their pooled partial NDFs; the stage's figures."""
    labels: Path
    representatives: Path
    neighbours: Path
    weights: Path
    rep_ndf: Path
    rep_confidence: Path
    rotation: Path
    metrics: Path


class Settings(StageSettings):
    """The stage's knobs: config ``cluster``, the top-level ``seed`` and ``partial_ndf``'s eqs. 11 and 5 for
    the pooled representative partial NDFs (workflow/schemas/config.schema.yaml)."""
    representatives: str | int | float = "auto"   # auto, a count >= 1 or a fraction in (0, 1) of the visible points
    distortion: float = 0.08         # auto: smallest k whose k-means distortion <= this x total variance ...
    spread: float = 0.15             # ... or whose clusters each lie within this relative L2 of their centre
    min_representatives: int = 1     # auto: the k ladder from this ...
    max_representatives: int = 64    # ... to this
    scan_points: int = 2048          # auto: points (evenly strided) the k scan clusters
    neighbours: int = 16             # k nearest representatives per point (eq. 18)
    radius_lambda: float = 5.0       # drop neighbours farther than this x lambda
    ridge: float = 1e-3              # Tikhonov term of the eq. 18 least squares
    n_init: int = 3                  # k-means restarts
    seed: int = 0                    # config seed: k-means and the k scan
    shadowing: bool | str = "constrained"  # config partial_ndf: S of eq. 5, :func:`facetsynth.fit.partial_ndf.shadowing_method`
    grazing_deg: float = 80.0        # config partial_ndf: light directions steeper than this are excluded
    tolerance: float = 1e-3          # config partial_ndf: eq. 11 stops when D changes by less than this
    max_iterations: int = 30         # config partial_ndf


@dataclass(frozen=True)
class Points:
    """The visible points' partial NDFs, full (memory-mapped) and on the coarse grid they are compared on."""
    capture: RectifiedCapture
    grid: DirectionGrid             # the partial NDFs' grid
    d_all: object                   # (P, T, F) D of every point (:class:`facetsynth.io.tables.SupportRows`)
    w_all: object                   # (P, T, F) W
    visible: np.ndarray             # (N,) the visible points
    d: np.ndarray                   # (N, t, f) their D on the coarse grid
    w: np.ndarray                   # (N, t, f) their W on it
    cgrid: DirectionGrid            # the coarse grid
    domain: np.ndarray | None       # (t, f) the cells every point sees (:func:`facetsynth.fit.cluster.common_domain`)
    kd: np.ndarray | None           # (N, 3) their diffuse albedo (None: not compared by it)


@dataclass(frozen=True)
class Count:
    """How many representatives k-means is asked for, and why."""
    wanted: int
    rule: str                       # auto, fixed or fraction
    setting: str | int | float      # config ``representatives`` (a number given as a string read as one)
    choice: cluster.KChoice | None  # the auto scan (None: fixed or fraction)


@dataclass(frozen=True)
class Fit:
    """The stage's result on the visible points (rows of ``Points.visible``)."""
    count: Count
    result: cluster.Clustering      # k-means: labels, representatives (rows), distinct NDFs
    pooled: Pooled                  # each representative's partial NDF
    neighbours: np.ndarray          # (N, k) eq. 18 neighbour representatives
    weights: np.ndarray             # (N, k) eq. 18 weights (a turned cluster's points: 1 on their own)
    lam: float                      # lambda: smallest distance between representatives
    turns: Turns                    # each point's turn against its representative, per cluster whether it turns
    turned_points: np.ndarray       # (N,) bool: the point is its representative turned
    rotation: np.ndarray            # (N,) its turn (radians; 0 elsewhere)
    eq18_error: np.ndarray          # finite eq. 18 relative L2 against the partial data, per point


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: cluster the visible points' partial NDFs; labels, representatives, neighbours,
    weights, the representatives' partial NDFs, the points' turns and cluster/metrics.json.

    The number of representatives (:func:`representative_count`): ``representatives`` "auto" chooses it
    from the data (:func:`facetsynth.fit.cluster.choose_k`: the smallest k on a geometric ladder from
    ``min_representatives`` to ``max_representatives`` whose k-means distortion falls below ``distortion``
    of the total variance, scanned on ``scan_points`` points); an integer >= 1 fixes it; a number in (0, 1)
    is a fraction of the visible points (the paper's 1 %, at least ``min_representatives``). ``spread``: a
    cluster whose points lie within this relative L2 of its centre is one material (k stops there).
    Invisible points get label -1 and all-zero weights; every visible point's weights sum to 1. Each
    representative's partial NDF pools its members' samples (``inputs.specular``, ``inputs.valid`` from
    ``separate``; eqs. 11 and 5 as in ``partial_ndf``: ``shadowing``, ``grazing_deg``, ``tolerance``,
    ``max_iterations``); without the samples (None) it is the representative's own partial NDF.
    ``inputs.kd`` (``separate``'s map): points are compared by their diffuse albedo too
    (:func:`facetsynth.fit.cluster.with_albedo`), so that two materials of one lobe shape stay two (eta and
    isotropy are decided per material by kd). The partial NDFs are read and coarsened on ``threads``
    threads.
    """
    t0 = time.perf_counter()
    points = load(inputs, threads)
    specular = None if inputs.specular is None else NpyRows(inputs.specular)
    valid = None if inputs.valid is None else points.capture.validity(inputs.valid)
    fitted = fit(points, specular, valid, settings, threads)
    write(outputs, points, fitted)
    metrics = {**fit_metrics(points, fitted, settings), "seconds": round(time.perf_counter() - t0, 2)}
    log.info("cluster metrics: %s", metrics)
    write_json(outputs.metrics, metrics)


def load(inputs: Inputs, threads: int = 1) -> Points:
    """The capture, its partial NDF tables (memory-mapped), the visible points' on the coarse grid (read on
    ``threads`` threads), the cells every point sees and the points' kd."""
    capture = RectifiedCapture.load(inputs.geometry)
    grid = DirectionGrid.from_dict(read_json(inputs.grid))
    table = SupportTable(inputs.ndf)         # partial_ndf's D and W
    d_all, w_all = table.rows("ndf"), table.rows("confidence")
    visible = np.flatnonzero(capture.visible)
    if visible.size == 0:
        raise ValueError("no visible points to cluster")
    d, w, cgrid = coarse_points(d_all, w_all, visible, grid, threads=threads)
    log.info("points compared on a %d x %d grid (partial NDFs on %d x %d)", *cgrid.shape, *grid.shape)
    domain = cluster.common_domain(w)
    log.info("features on the cells %s", "every point sees (W >= 0.6 at 97 %% of the points): %d of %d" % (
        domain.sum(), domain.size) if domain is not None else "of each point's own domain (no common one)")
    kd = None
    if inputs.kd is not None:
        channels, _ = read_exr(inputs.kd)
        kd = channels["RGB"].reshape(capture.n_points, 3)[visible]
    return Points(capture, grid, d_all, w_all, visible, d, w, cgrid, domain, kd)


def fit(points: Points, specular, valid, settings: Settings, threads: int = 1) -> Fit:
    """k-means representatives (:func:`kmeans_clusters`), their partial NDFs (pooled from the members'
    samples ``specular``, ``valid`` where given, :func:`pooled_representatives`), eq. 18 neighbours and
    weights, and the clusters that turn across the sample (:func:`point_turns`): their points are their
    representative turned. Clusters are pooled and turned on ``threads`` threads."""
    count, result = kmeans_clusters(points, settings)
    visible, grid = points.visible, points.grid
    if specular is None:
        rows = visible[result.representatives]
        pooled = Pooled(np.asarray(points.d_all[rows], float), np.asarray(points.w_all[rows], float),
                        np.ones(result.representatives.size, int))
    else:
        pooled = pooled_representatives(points.capture, visible, result, points.d_all, points.w_all, specular,
                                        valid, grid, settings, threads)
    rep_d, rep_w, _ = cluster.coarse(pooled.ndf, pooled.confidence, grid)
    d, w = points.d, points.w
    if points.domain is not None:   # eq. 18 compared on the cells every point sees, as k-means (the rig's domain)
        w = np.broadcast_to(points.domain, w.shape).astype(float)
        rep_w = np.broadcast_to(points.domain, rep_w.shape).astype(float)
    nbr, wts, lam = cluster.interpolation_weights(d, w, rep_d, rep_w, points.cgrid, k=settings.neighbours,
                                                  radius=settings.radius_lambda, ridge=settings.ridge)
    turns = point_turns(points.d_all, points.w_all, visible, result.labels, pooled, grid, threads=threads)
    turned = np.flatnonzero(turns.turned)
    members = np.isin(result.labels, turned)
    nbr[members], wts[members] = result.labels[members, None], 0.0
    wts[members, 0] = 1.0
    log.info("%d of %d clusters turn across the sample (%d points): each point is its representative turned "
             "(eq. 13); turn spread per cluster (deg) %s", turned.size, result.representatives.size,
             int(members.sum()), np.round(np.degrees(turns.spread), 1).tolist())
    return Fit(count, result, pooled, nbr, wts, lam, turns, members, np.where(members, turns.phi, 0.0),
               eq18_errors(d, w, rep_d, nbr, wts, points.cgrid, threads))


def kmeans_clusters(points: Points, settings: Settings) -> tuple[Count, cluster.Clustering]:
    """The points' eq. 15 features (with their kd where given), how many representatives
    (:func:`representative_count`) and k-means on them; the features are dropped on return."""
    feats = cluster.features(points.d, points.w, points.cgrid, points.domain)
    if points.kd is not None:
        feats = cluster.with_albedo(feats, points.kd)
    count = representative_count(feats, points.visible.size, settings)
    result = cluster.kmeans(feats, points.d, points.w, points.cgrid, count.wanted, seed=settings.seed,
                            n_init=settings.n_init)
    log.info("k-means: %d visible points, %d representatives (%d asked, %d distinct NDFs)",
             points.visible.size, result.representatives.size, count.wanted, result.distinct)
    return count, result


def representative_count(feats: np.ndarray, n_visible: int, settings: Settings) -> Count:
    """How many representatives, from ``settings.representatives``: "auto" (the k scan,
    :func:`facetsynth.fit.cluster.choose_k`), a count >= 1, or a fraction in (0, 1) of the ``n_visible`` points
    (at least ``min_representatives``); a number given as a string (--config) is read as one."""
    representatives = settings.representatives
    if isinstance(representatives, str) and representatives.strip() != "auto":
        try:                                  # --config passes numbers as strings
            representatives = float(representatives)
        except ValueError:
            pass
    if isinstance(representatives, str):
        if representatives.strip() != "auto":
            raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                             f"not {representatives!r}")
        choice = cluster.choose_k(feats, settings.min_representatives, min(settings.max_representatives, n_visible),
                                  settings.distortion, subsample=settings.scan_points, seed=settings.seed,
                                  spread=settings.spread)
        log.info("representatives: auto, k = %d (%s); distortion / total variance on %d points: %s", choice.k,
                 choice.rule, choice.subsample,
                 ", ".join(f"k={k}: {v:.3f}" for k, v in zip(choice.ladder, choice.distortion)))
        return Count(choice.k, "auto", representatives, choice)
    if float(representatives) >= 1:
        log.info("representatives: fixed at %d", int(representatives))
        return Count(int(representatives), "fixed", representatives, None)
    if float(representatives) > 0:
        wanted = int(max(settings.min_representatives, round(float(representatives) * n_visible)))
        log.info("representatives: %g of %d visible points, at least %d: %d", float(representatives),
                 n_visible, settings.min_representatives, wanted)
        return Count(wanted, "fraction", representatives, None)
    raise ValueError(f"cluster.representatives must be 'auto', a count >= 1 or a fraction in (0, 1), "
                     f"not {representatives!r}")


def eq18_errors(d: np.ndarray, w: np.ndarray, rep_d: np.ndarray, nbr: np.ndarray, wts: np.ndarray,
                cgrid: DirectionGrid, threads: int = 1) -> np.ndarray:
    """Eq. 18 on the partial data: each point's mixture of its neighbours' coarse NDFs against its own D
    (relative L2 on its W > 0), the finite ones: how well the representatives span the points (a tile of
    points at a time on ``threads`` threads)."""
    err = np.concatenate(map_frames(
        lambda t: relative_l2(np.einsum("nk,nktp->ntp", wts[t], rep_d[nbr[t]]), d[t], w[t] > 0, cgrid),
        list(tiles(len(d))), threads, "cluster: eq. 18 errors", unit="tile"))
    return err[np.isfinite(err)]


def write(outputs: Outputs, points: Points, fitted: Fit) -> None:
    """The per-point arrays over every point (invisible ones: label -1, no neighbours, zero weights and turn),
    the representatives' points and their partial NDFs."""
    n, visible = points.capture.n_points, points.visible
    labels = np.full(n, -1, np.int32)
    labels[visible] = fitted.result.labels
    neighbours_full = np.zeros((n, fitted.neighbours.shape[1]), np.int32)
    weights_full = np.zeros((n, fitted.neighbours.shape[1]), np.float32)
    neighbours_full[visible], weights_full[visible] = fitted.neighbours, fitted.weights
    write_npy(outputs.labels, labels)
    write_npy(outputs.representatives, visible[fitted.result.representatives].astype(np.int64))
    write_npy(outputs.neighbours, neighbours_full)
    write_npy(outputs.weights, weights_full)
    write_npy(outputs.rep_ndf, fitted.pooled.ndf.astype(np.float32))
    write_npy(outputs.rep_confidence, fitted.pooled.confidence.astype(np.float32))
    rotation = np.zeros(n, np.float32)
    rotation[visible] = fitted.rotation
    write_npy(outputs.rotation, rotation)


def fit_metrics(points: Points, fitted: Fit, settings: Settings) -> dict:
    """cluster/metrics.json's figures (but the stage's seconds): the counts, how k was chosen, eq. 18's
    lambda, neighbours and error on the partial data, the pooling and the turned clusters."""
    count, result, wts, err = fitted.count, fitted.result, fitted.weights, fitted.eq18_error
    choice, lam = count.choice, fitted.lam
    used = (wts != 0).sum(axis=1)
    return {"points": points.capture.n_points, "visible_points": int(points.visible.size),
            "representatives": int(result.representatives.size),
            "representatives_requested": count.wanted, "distinct_ndfs": int(result.distinct),
            "representatives_rule": count.rule,
            "k_chosen": count.wanted,
            **({"k_rule": choice.rule, "k_distortion_tolerance": settings.distortion,
                "k_scan_points": choice.subsample,
                "k_ladder": choice.ladder, "k_distortion_curve": [round(v, 5) for v in choice.distortion],
                "k_spread_curve": [round(v, 5) for v in choice.spread],
                "k_scan_seconds": round(choice.seconds, 2)} if choice is not None else
               {"representatives_setting": count.setting}),
            "lambda": lam if np.isfinite(lam) else None, "radius_lambda": settings.radius_lambda,
            "k": settings.neighbours,
            "ridge": settings.ridge, "neighbours_used_median": float(np.median(used)),
            "eq18_partial_rel_l2_median": float(np.median(err)) if err.size else None,
            "eq18_partial_rel_l2_p90": float(np.quantile(err, 0.9)) if err.size else None,
            "comparison_grid": list(points.cgrid.shape), "spread_tolerance": settings.spread,
            "pooled_members_median": float(np.median(fitted.pooled.members)),
            "turned_clusters": int(fitted.turns.turned.sum()),
            "turned_points_fraction": float(fitted.turned_points.mean()),
            "turn_rule": f"median eq. 15 gain < {TURN_GAIN} and turn spread > {TURN_SPREAD} sector",
            "negative_weight_fraction": float(np.mean(wts[wts != 0] < 0)) if np.any(wts != 0) else 0.0}


def coarse_points(d_all, w_all, rows: np.ndarray, grid: DirectionGrid, tile: int = 4096, threads: int = 1):
    """:func:`facetsynth.fit.cluster.coarse` of the points ``rows`` of the memory-mapped (P, T, F) tables, a tile
    at a time on ``threads`` threads: memory holds the coarse tables (16 x smaller on the demo's grid), never
    the full ones. ``d_all``, ``w_all``: support table channels (:class:`facetsynth.io.tables.SupportRows`), summed
    where they are stored (``sector_sums``: bitwise numpy's sums of the dense rows) when the grid coarsens."""
    sectors = 4 * cluster.COARSE_RINGS

    def summed(t: slice):
        return cluster.coarse_sums(d_all.sector_sums(rows[t], sectors), w_all.sector_sums(rows[t], sectors), grid)

    def dense(t: slice):
        return cluster.coarse(d_all[rows[t]], w_all[rows[t]], grid)

    blocks = list(imap(summed if cluster.coarsens(grid) else dense, list(tiles(rows.size, tile)), threads,
                       "cluster: coarse tables", unit="tile"))
    return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]), blocks[0][2]


@dataclass(frozen=True)
class Pooled:
    ndf: np.ndarray          # (R, T, F) each representative's partial NDF from its members' pooled samples
    confidence: np.ndarray   # (R, T, F)
    members: np.ndarray      # (R,) members pooled


def pooled_representatives(capture: RectifiedCapture, visible: np.ndarray, result, d_all, w_all, specular, valid,
                           grid: DirectionGrid, settings: Settings, threads: int = 1) -> Pooled:
    """Every cluster's partial NDF from up to POOL_MEMBERS of its members' eq. 8 samples
    (:func:`facetsynth.fit.partial_ndf.pooled_fit`: ``settings.shadowing``, ``grazing_deg``, ``tolerance``,
    ``max_iterations``), for its representative's view and, where the cluster turns
    across the sample (TURN_GAIN, TURN_SPREAD), in its frame (each member's turn against it,
    :func:`facetsynth.fit.cluster.relative_rotation`, undone; elsewhere the turns are noise, and undoing
    them would blur the lobe). Clusters in parallel on ``threads`` threads."""
    views = capture.view_directions(True)
    ndf = np.zeros((len(result.representatives),) + grid.shape)
    conf = np.zeros_like(ndf)
    counts = np.zeros(len(result.representatives), int)

    def pool(c: int) -> None:
        rep = result.representatives[c]
        members = visible[np.flatnonzero(result.labels == c)]
        members = members[:: max(1, int(np.ceil(members.size / POOL_MEMBERS)))]
        w_members = np.asarray(w_all[members], float)
        own = visible[rep]
        turn, gain = cluster.relative_rotation(np.asarray(d_all[members], float), w_members,
                                               np.asarray(d_all[own], float), np.asarray(w_all[own], float), grid,
                                               max_shift=grid.n_phi // 4)
        turning = np.median(gain) < TURN_GAIN and np.std(turn) > TURN_SPREAD * grid.d_phi
        pooled = partial_ndf.pooled_fit(channel_mean(np.asarray(specular[members], float)),
                                        np.asarray(valid[members]), capture.light_directions(members)[0],
                                        views[members], w_members, views[own], grid, settings.shadowing,
                                        settings.grazing_deg, settings.tolerance, settings.max_iterations,
                                        rotation=turn if turning else None)
        ndf[c], conf[c], counts[c] = pooled.ndf[0], pooled.confidence[0], members.size

    map_frames(pool, range(len(result.representatives)), threads, "cluster: pooled partial NDFs", unit="rep")
    return Pooled(ndf, conf, counts)


@dataclass(frozen=True)
class Turns:
    phi: np.ndarray          # (N,) each visible point's turn against its cluster's representative (radians; 0
                             # in a cluster that does not turn)
    spread: np.ndarray       # (R,) standard deviation of the turns within each cluster (radians)
    gain: np.ndarray         # (R,) median eq. 15 distance turned / unturned within each cluster
    turned: np.ndarray       # (R,) bool: the cluster is one material turning across the sample


def point_turns(d_all, w_all, visible: np.ndarray, labels: np.ndarray, pooled: Pooled, grid: DirectionGrid,
                batch: int = 512, threads: int = 1) -> Turns:
    """Each visible point's turn against its cluster's pooled partial NDF (eq. 13,
    :func:`facetsynth.fit.cluster.relative_rotation`), and which clusters are one material turning across the
    sample (TURN_GAIN, TURN_SPREAD): for those a representative and a per-point turn replace eq. 18's
    mixture of representatives at other turns, which showed as wedges on the demo's turned copper.
    Whether a cluster turns, its spread and gain, are measured on up to POOL_MEMBERS of its members
    (evenly strided); the turns of every member only where it does (elsewhere the turn is 0). Each cluster's
    sample, then the turning clusters' other members, in batches of ``batch`` points on ``threads`` threads
    (at 800^2 one turning cluster holds most of the points: by clusters, one thread measured them all)."""
    n_rep = len(pooled.ndf)
    phi, gain = np.zeros(len(visible)), np.ones(len(visible))
    members = [np.flatnonzero(labels == c) for c in range(n_rep)]
    samples = [m[:: max(1, int(np.ceil(m.size / POOL_MEMBERS)))] for m in members]

    def measure(job: tuple[int, np.ndarray]) -> None:
        c, part = job
        d, w = np.asarray(d_all[visible[part]], float), np.asarray(w_all[visible[part]], float)
        phi[part], gain[part] = cluster.relative_rotation(d, w, pooled.ndf[c], pooled.confidence[c], grid,
                                                          max_shift=grid.n_phi // 4)

    def batches(c: int, rows: np.ndarray) -> list[tuple[int, np.ndarray]]:
        return [(c, rows[start:start + batch]) for start in range(0, rows.size, batch)]

    map_frames(measure, [job for c in range(n_rep) for job in batches(c, samples[c])], threads,
               "cluster: turns within clusters", unit="batch")
    spread = np.array([float(np.std(phi[s])) if s.size else 0.0 for s in samples])
    median_gain = np.array([float(np.median(gain[s])) if s.size else 1.0 for s in samples])
    turned = (median_gain < TURN_GAIN) & (spread > TURN_SPREAD * grid.d_phi)
    for c in np.flatnonzero(~turned):
        phi[samples[c]] = 0.0
    rest = [job for c in np.flatnonzero(turned)
            for job in batches(c, np.setdiff1d(members[c], samples[c], assume_unique=True))]
    map_frames(measure, rest, threads, "cluster: turns of the turning clusters' points", unit="batch")
    return Turns(phi, spread, median_gain, turned)
