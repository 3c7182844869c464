"""NDF clustering and interpolation weights (paper 002 sec. 5.3, "NDF Clustering", eq. 18).

k-means (scikit-learn) over the partial NDFs picks a small set of
representatives whose NDFs are completed by synthesis; every point's NDF is
then a linear combination of its neighbour representatives (eq. 18). The
distances are eq. 15's (:func:`facetsynth.fit.synthesis.pairwise_distance`).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.sparse.csgraph import connected_components

from ..geometry.grid import DirectionGrid
from .synthesis import SUPPORT, TINY, pairwise_distance, rotate_tuple, turned_pairwise_distance

log = logging.getLogger(__name__)


COARSE_RINGS = 8   # the clustering grid: 8 rings x 32 sectors (11.25 deg cells)


def coarse(d: np.ndarray, w: np.ndarray, grid: DirectionGrid,
           rings: int = COARSE_RINGS) -> tuple[np.ndarray, np.ndarray, DirectionGrid]:
    """Partial NDFs <D, W> (N, T, F) averaged over blocks of cells to a ``rings`` x 4 ``rings`` grid.

    A point's partial NDF depends on where its samples fall relative to the
    lobe: at the paper's light densities a glossy lobe is one or two lights
    wide, and its interpolated shape changes with the point's place under
    the LEDs. Over cells several light spacings wide, that phase averages out
    and what remains is the material's: clustering and eq. 18 compare points
    on this grid (docs/decisions.md, "Sampling-invariant partial NDFs").
    D is averaged with solid-angle weights, W plainly; a grid that does not
    divide into the coarse one is returned as it is.
    """
    if not coarsens(grid, rings):
        return np.asarray(d, float), np.asarray(w, float), grid
    n, sectors = len(d), 4 * rings
    # sectors first (om is constant along a ring), then rings; accumulated in float64 without a float64 copy
    d_sums, w_sums = (np.asarray(x).reshape(n, grid.n_theta, sectors, -1).sum(axis=-1, dtype=float) for x in (d, w))
    return coarse_sums(d_sums, w_sums, grid, rings)


def coarsens(grid: DirectionGrid, rings: int = COARSE_RINGS) -> bool:
    """Whether :func:`coarse` averages ``grid`` onto ``rings`` x 4 ``rings`` cells (else it keeps it)."""
    return not (grid.n_theta % rings or grid.n_phi % (4 * rings) or grid.n_theta <= rings)


def coarse_sums(d_sums: np.ndarray, w_sums: np.ndarray, grid: DirectionGrid,
                rings: int = COARSE_RINGS) -> tuple[np.ndarray, np.ndarray, DirectionGrid]:
    """:func:`coarse` from the sums (N, T, 4 ``rings``) of D and W over each ring's runs of cells, float64 (what
    :meth:`facetsynth.io.tables.SupportTable.sector_sums` reads from a stored table)."""
    bt, bp = grid.n_theta // rings, grid.n_phi // (4 * rings)
    n = len(d_sums)
    om = grid.solid_angles
    area = om.reshape(rings, bt, 4 * rings, bp).sum(axis=(1, 3))
    dc = (d_sums * om[:, :1]).reshape(n, rings, bt, 4 * rings).sum(axis=2) / area
    wc = w_sums.reshape(n, rings, bt, 4 * rings).sum(axis=2) / (bt * bp)
    return dc, wc, DirectionGrid(rings, 4 * rings)


def common_domain(w: np.ndarray, fraction: float = 0.97, level: float = 0.6) -> np.ndarray | None:
    """Cells (T, F) where at least ``fraction`` of the points have W >= ``level``; None if there are none."""
    domain = np.mean(np.asarray(w) >= level, axis=0) >= fraction
    return domain if domain.any() else None


def relative_rotation(d: np.ndarray, w: np.ndarray, d_ref: np.ndarray, w_ref: np.ndarray, grid: DirectionGrid,
                      max_shift: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """The azimuth phi (N,) by which each tuple <d, w> (N, T, F) is the reference <d_ref, w_ref> (T, F) turned:
    D(h) ~ D_ref(R(phi) h) (eq. 13), the eq. 15 distance minimised over whole-sector shifts up to
    ``max_shift`` either way, refined by a parabola through the best shift and its neighbours; and the
    gain (N,): the best whole-shift distance over the unturned one (1: turning explains nothing).

    A cluster of a material whose frame turns across the sample (the demo's turned copper, 45
    representatives for 360 deg) spans several degrees of rotation; pooling its members' samples
    without undoing it would blur the lobe. An isotropic material has a flat distance curve, and
    any phi it gets turns it onto itself.
    """
    shifts = np.arange(-max_shift, max_shift + 1)
    dist = shifted_distances(d, w, d_ref, w_ref, grid, max_shift)
    best = np.argmin(dist, axis=1)
    shift = shifts[best].astype(float)
    inner = (best > 0) & (best < shifts.size - 1)
    rows = np.flatnonzero(inner & np.isfinite(dist[np.arange(len(d)), best]))
    if rows.size:
        lo, mid, hi = (dist[rows, best[rows] + k] for k in (-1, 0, 1))
        curve = lo - 2.0 * mid + hi
        ok = np.isfinite(curve) & (curve > TINY)
        shift[rows[ok]] += np.clip(0.5 * (lo - hi)[ok] / curve[ok], -0.5, 0.5)
    unturned = dist[:, max_shift]
    best_dist = dist[np.arange(len(d)), best]
    gain = np.divide(best_dist, unturned, out=np.ones(len(d)), where=np.isfinite(unturned) & (unturned > TINY))
    return shift * grid.d_phi, gain


ALBEDO_WEIGHT = 0.7    # kd that differ by 25 % (params.material_tolerance) are 0.16 apart, past cluster.spread
ALBEDO_CLIP = 0.5      # log kd deviations bounded: cells half on a black marker must not split a material


def shifted_distances(d: np.ndarray, w: np.ndarray, d_ref: np.ndarray, w_ref: np.ndarray, grid: DirectionGrid,
                      max_shift: int) -> np.ndarray:
    """(N, 2 max_shift + 1): eq. 15's distance of each tuple <d, w> (N, T, F) to the reference turned by
    -max_shift .. max_shift whole sectors (inf where there is no overlap)."""
    turned = [rotate_tuple(d_ref, w_ref, grid, float(s)) for s in range(-max_shift, max_shift + 1)]
    dist = pairwise_distance(d, w, np.stack([t[0] for t in turned]), np.stack([t[1] for t in turned]), grid)
    return np.where(np.isfinite(dist), dist, np.inf)


def with_albedo(feats: np.ndarray, kd: np.ndarray, weight: float = ALBEDO_WEIGHT, clip: float = ALBEDO_CLIP) -> np.ndarray:
    """NDF features (N, K) with the diffuse albedo appended: weight x (log kd - its median, within
    +-clip) x the features' median norm (3 columns). eq. 15 is scale-free in D, so materials of one
    lobe shape and another kd (the card's papers) would otherwise be one cluster; centred and bounded,
    the albedo adds little to a uniform material's spread (choose_k's sum of squares). Measured k
    (uniform 480 / 1360 lights, rgl-quadrants, ggx-tiles, demo): without the albedo 1 / 1 / 2 / 6 / 6;
    weight 1.35 unbounded 4 / 4 / 3 / 8 / 6; 0.7 within +-0.5: 1 / 1 / 4 / 6 / 8."""
    log_kd = np.log(np.clip(np.asarray(kd, float), 1e-3, None))
    norm = float(np.median(np.linalg.norm(feats, axis=1))) if len(feats) else 1.0
    extra = weight * norm * np.clip(log_kd - np.median(log_kd, axis=0), -clip, clip)
    return np.concatenate([feats, extra.astype(feats.dtype)], axis=1)


def features(d: np.ndarray, w: np.ndarray, grid: DirectionGrid, domain: np.ndarray | None = None) -> np.ndarray:
    """k-means features (N, T*F) float32: sqrt(W dw) D / s, s = integral of D over the domain.

    Their squared Euclidean distance approximates the numerator of eq. 15
    (the scale s taken over each tuple's own domain rather than the overlap,
    which is nearly the same domain for points seen from one view). With a
    ``domain`` (T, F) (:func:`common_domain`), every point is compared on the
    same cells with W = 1 there: the domain each point sees moves with its
    place under the lights and the camera, and is not the material's.
    """
    d = np.asarray(d, float)
    w = np.clip(np.asarray(w, float), 0.0, None)
    if domain is not None:
        w = np.broadcast_to(np.asarray(domain, float), d.shape)
    m = w > SUPPORT
    om = grid.solid_angles
    s = np.sum(np.where(m, d, 0.0) * om, axis=(-2, -1))
    f = np.where(m, np.sqrt(w * om) * d, 0.0) / np.where(s > TINY, s, 1.0)[:, None, None]
    return f.reshape(len(f), -1).astype(np.float32)


@dataclass(frozen=True)
class Clustering:
    labels: np.ndarray           # (N,) cluster of each input row
    representatives: np.ndarray  # (R,) input row of each cluster's representative
    n_requested: int             # clusters asked for
    distinct: int                # distinct feature rows (bounds the useful number of clusters)


KMEANS_POINTS = 32768
"""k-means fits its centres on at most this many points (evenly strided), then assigns every point: the demo
(168 x 168) fits on all of its points, as before."""


def kmeans(feats: np.ndarray, d: np.ndarray, w: np.ndarray, grid: DirectionGrid, n_clusters: int,
           seed: int = 0, n_init: int = 3, batch: bool = False) -> Clustering:
    """k-means over ``feats`` (N, K); each cluster's representative is its member nearest the centre (eq. 15).

    The centre, as a tuple for eq. 15, is the members' mean normalised D
    (D / s) with their mean W. The centres are fitted on at most KMEANS_POINTS
    evenly strided points and every point is then assigned to its nearest
    (a 310 x 310 dome capture at 64 clusters: 30 s on all points, docs/decisions.md,
    "Light-dome (RTI) captures"). If there are fewer distinct NDFs than clusters
    (degenerate data, e.g. identical partial NDFs) the number of clusters is
    lowered to the number of distinct rows; empty clusters are dropped.
    """
    from sklearn.cluster import KMeans, MiniBatchKMeans

    n = len(feats)
    rounded = np.round(feats / max(float(np.abs(feats).max()), TINY), 6)
    distinct = len(np.unique(rounded, axis=0))
    k = int(max(1, min(n_clusters, distinct, n)))
    if k == 1:
        labels = np.zeros(n, int)
    else:
        algo = (MiniBatchKMeans(n_clusters=k, random_state=seed, n_init=n_init, batch_size=4096) if batch
                else KMeans(n_clusters=k, random_state=seed, n_init=n_init))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # "fewer distinct clusters" is handled below
            if n <= KMEANS_POINTS:
                labels = algo.fit_predict(feats)
            else:
                labels = algo.fit(feats[:: -(-n // KMEANS_POINTS)]).predict(feats)
    reps, new_labels = [], np.full(n, -1, int)
    om = grid.solid_angles
    for c in np.unique(labels):
        members = np.flatnonzero(labels == c)
        dm, wm = np.asarray(d[members], float), np.clip(np.asarray(w[members], float), 0.0, None)
        mask = wm > SUPPORT
        s = np.sum(np.where(mask, dm, 0.0) * om, axis=(1, 2))
        centre_d = np.mean(dm / np.where(s > TINY, s, 1.0)[:, None, None], axis=0)
        centre_w = np.mean(wm, axis=0)
        dist = pairwise_distance(dm, wm, centre_d[None], centre_w[None], grid)[:, 0]
        dist = np.where(np.isfinite(dist), dist, np.inf)
        new_labels[members] = len(reps)
        reps.append(int(members[int(np.argmin(dist))]))
    return Clustering(labels=new_labels, representatives=np.asarray(reps, np.int64), n_requested=int(n_clusters),
                      distinct=distinct)


def k_ladder(k_min: int, k_max: int, ratio: float = 2 ** 0.5) -> list[int]:
    """Cluster counts on a geometric ladder from ``k_min`` to ``k_max`` (both included)."""
    k_min, k_max = max(1, int(k_min)), max(1, int(k_max))
    if k_max <= k_min:
        return [k_min]
    n = int(np.ceil(np.log(k_max / k_min) / np.log(ratio)))
    return sorted({int(round(k_min * ratio**i)) for i in range(n)} | {k_min, k_max})


@dataclass(frozen=True)
class KChoice:
    k: int                       # chosen number of clusters
    ladder: list                 # k scanned
    distortion: list             # within-cluster distortion / total variance at each k (eq. 15 features)
    rule: str                    # how k was chosen, in words
    subsample: int               # rows the scan clustered
    seconds: float = 0.0         # time the scan took
    spread: list = ()            # RMS relative L2 of the rows from their cluster centres at each k


def choose_k(feats: np.ndarray, k_min: int, k_max: int, tolerance: float, subsample: int = 2048,
             seed: int = 0, components: int = 64, spread: float = 0.0) -> KChoice:
    """The smallest k on a geometric ladder whose k-means distortion falls below ``tolerance``, or whose
    clusters are each one material: points within ``spread`` (relative L2, RMS over the points) of their
    centre.

    Distortion: sum over rows of |f - centre(f)|^2 (the features' squared
    distance approximates eq. 15's numerator) over the total variance sum
    |f - mean|^2, on an evenly strided ``subsample`` of the rows. For speed
    the scan clusters a PCA projection onto ``components`` dimensions, then
    scores each partition in the full feature space. eq. 15 is not rotation
    invariant, so one material seen in many frames (a turned disc) counts
    as many shapes. If no k up to ``k_max`` reaches the tolerance, k_max.

    The spread test is absolute: sum |f - centre(f)|^2 / sum |f|^2 <=
    spread^2. Without it a uniform material never stops (its total variance
    is all noise and sampling, which k-means splits as readily as
    materials) and goes to ``k_max``.
    """
    from sklearn.cluster import KMeans
    from sklearn.decomposition import PCA

    t0 = time.perf_counter()
    x = np.asarray(feats[:: max(1, int(np.ceil(len(feats) / subsample)))], np.float64)
    n = len(x)
    ladder = [k for k in k_ladder(k_min, k_max) if k <= n] or [max(1, min(k_min, n))]
    rule = (f"smallest k on the ladder {ladder[0]}..{ladder[-1]} (ratio sqrt 2) whose k-means distortion "
            f"/ total variance <= {tolerance:g} or / sum of squares <= {spread:g}^2 (else {ladder[-1]})")
    total = float(np.sum((x - x.mean(axis=0)) ** 2))
    energy = float(np.sum(x * x))
    if total <= TINY:
        return KChoice(k=ladder[0], ladder=ladder[:1], distortion=[0.0], rule=rule, subsample=n,
                       seconds=time.perf_counter() - t0, spread=[0.0])
    y = x
    if x.shape[1] > components and n > components:
        y = PCA(n_components=components, random_state=seed, svd_solver="randomized").fit_transform(x)
    curve, spreads = [], []
    chosen = ladder[-1]
    for k in ladder:
        if k == 1:
            labels = np.zeros(n, int)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                labels = KMeans(n_clusters=k, random_state=seed, n_init=1).fit_predict(y)
        within = 0.0
        for c in np.unique(labels):
            m = x[labels == c]
            within += float(np.sum((m - m.mean(axis=0)) ** 2))
        curve.append(within / total)
        spreads.append(float(np.sqrt(within / max(energy, TINY))))
        if curve[-1] <= tolerance or spreads[-1] <= spread:
            chosen = k
            break
    return KChoice(k=int(chosen), ladder=ladder[:len(curve)], distortion=curve, rule=rule, subsample=n,
                   seconds=time.perf_counter() - t0, spread=spreads)


def constrained_least_squares(a: np.ndarray, b: np.ndarray, ridge: float = 0.0) -> np.ndarray:
    """w minimising |A w - b|^2 + ridge tr(A^T A)/k |w|^2 subject to sum(w) = 1 (eq. 18 augmented).

    ``a`` (..., C, k), ``b`` (..., C): any number of systems at once. Solved
    through the KKT system by its pseudo-inverse (the least-squares solution
    of numpy's ``lstsq``, with its cut-off), so a singular system (identical
    representatives) still gives a finite solution (the minimum-norm one).
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    k = a.shape[-1]
    ata = np.swapaxes(a, -1, -2) @ a
    if ridge > 0:
        scale = np.maximum(np.trace(ata, axis1=-2, axis2=-1) / k, TINY)
        ata = ata + ridge * scale[..., None, None] * np.eye(k)
    kkt = np.zeros(a.shape[:-2] + (k + 1, k + 1))
    kkt[..., :k, :k] = 2.0 * ata
    kkt[..., :k, k] = kkt[..., k, :k] = 1.0
    rhs = np.concatenate([2.0 * np.einsum("...ck,...c->...k", a, b), np.ones(a.shape[:-2] + (1,))], axis=-1)
    sol = (np.linalg.pinv(kkt, rcond=np.finfo(float).eps * (k + 1)) @ rhs[..., None])[..., :k, 0]
    total = sol.sum(axis=-1, keepdims=True)
    good = np.all(np.isfinite(sol), axis=-1, keepdims=True) & (np.abs(total) > TINY)
    return np.where(good, sol / np.where(good, total, 1.0), 1.0 / k)


def interpolation_weights(d: np.ndarray, w: np.ndarray, rep_d: np.ndarray, rep_w: np.ndarray, grid: DirectionGrid,
                          k: int = 16, radius: float = 5.0, ridge: float = 1e-3,
                          rep_rows: np.ndarray | None = None, rows: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray, float]:
    """Eq. 18: neighbour representatives and weights for points <d, w> (N, T, F).

    Neighbours: the ``k`` nearest representatives under eq. 15, dropping
    those farther than ``radius`` * lambda (lambda: the smallest eq. 15
    distance between two representatives); the nearest is always kept.
    Weights: least squares of D (cells weighted by W dw) on the neighbours'
    partial NDFs with sum(w) = 1 (a small ``ridge`` keeps nearly collinear
    neighbours from getting huge opposite weights). A point that is itself a
    representative (``rows[i] == rep_rows[j]``) gets weight 1 on it.
    Returns (neighbours (N, k) int32, weights (N, k) float32, lambda);
    padding entries repeat the nearest representative with weight 0.
    """
    n_rep = len(rep_d)
    lam = np.inf
    if n_rep > 1:
        rr = pairwise_distance(rep_d, rep_w, rep_d, rep_w, grid)
        np.fill_diagonal(rr, np.inf)
        lam = float(np.min(rr))
    limit = radius * lam if np.isfinite(lam) and lam > 0 else np.inf
    n = len(d)
    neighbours = np.zeros((n, k), np.int32)
    weights = np.zeros((n, k), np.float32)
    om = grid.solid_angles.reshape(-1)
    rep_flat = np.asarray(rep_d, float).reshape(n_rep, -1)
    for start in range(0, n, 256):
        block = np.arange(start, min(start + 256, n))
        dd, ww = np.asarray(d[block], float), np.asarray(w[block], float)
        dist = pairwise_distance(dd, ww, rep_d, rep_w, grid)
        dist = np.where(np.isfinite(dist), dist, np.inf)
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        # the neighbours within the radius are a prefix of the sorted ones; the nearest is always kept
        count = np.maximum(1, np.sum(np.take_along_axis(dist, order, axis=1) <= limit, axis=1))
        neighbours[block] = order[:, :1]                   # padding: the nearest, with weight 0
        neighbours[block, :order.shape[1]] = np.where(np.arange(order.shape[1]) < count[:, None], order, order[:, :1])
        cw = np.sqrt(np.clip(ww, 0.0, None).reshape(len(block), -1) * om)
        for size in np.unique(count):
            g = np.flatnonzero(count == size)
            if size == 1:
                weights[block[g], 0] = 1.0
                continue
            a = rep_flat[order[g, :size]].transpose(0, 2, 1) * cw[g, :, None]          # (G, cells, size)
            weights[block[g], :size] = constrained_least_squares(a, dd[g].reshape(len(g), -1) * cw[g], ridge)
    if rep_rows is not None and rows is not None:          # a representative is its own neighbour
        where = {int(r): j for j, r in enumerate(rep_rows)}
        for row, r in enumerate(np.asarray(rows)):
            if int(r) in where:
                neighbours[row], weights[row] = where[int(r)], 0.0
                weights[row, 0] = 1.0
    return neighbours, weights, lam


def material_groups(kd_rep: np.ndarray, tolerance: float) -> np.ndarray:
    """Materials (R,) int labels: representatives whose diffuse albedos kd (R, 3) agree within
    ``tolerance`` in every channel on a log scale (complete linkage, scipy), i.e. the same material at
    other rotations. eta is a property of the material (sec. 3: the facets share one refraction index),
    and one representative's grazing samples constrain it too weakly (docs/decisions.md)."""
    kd_rep = np.asarray(kd_rep, float)
    if len(kd_rep) < 2:
        return np.zeros(len(kd_rep), np.intp)
    features = np.log(np.clip(kd_rep, 1e-3, None))
    tree = linkage(features, method="complete", metric="chebyshev")
    return fcluster(tree, t=np.log1p(tolerance), criterion="distance").astype(np.intp) - 1


def turned_distances(d: np.ndarray, grid: DirectionGrid) -> np.ndarray:
    """(R, R): eq. 15's distance between complete NDFs ``d`` (R, T, F) after the best whole-sector turn of one
    onto the other (:func:`facetsynth.fit.synthesis.turned_pairwise_distance`, up to a quarter turn either way:
    a lobe that a half turn maps onto itself needs no more), the smaller of the two directions."""
    out = turned_pairwise_distance(d, grid, grid.n_phi // 4).min(axis=-1)
    return np.minimum(out, out.T)


def joined(groups: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """Labels (R,) of the connected components of ``groups`` (R,) int labels joined wherever ``linked`` (R, R)
    bool holds, numbered in order of first appearance."""
    same = (groups[:, None] == groups[None, :]) | linked
    _, labels = connected_components(sparse.csr_matrix(same), directed=False)
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(np.argsort(first))
    return order[labels].astype(np.intp)


def self_distances(d: np.ndarray, grid: DirectionGrid, turn: float) -> np.ndarray:
    """(R,): eq. 15's relative distance of each complete NDF ``d`` (R, T, F) to itself turned by ``turn`` of a
    full turn (a quarter: how far from isotropic; a half: how far from point-symmetric)."""
    d = np.asarray(d, float)
    full = np.ones((1,) + grid.shape)
    turned = np.stack([rotate_tuple(t, full[0], grid, grid.n_phi * turn)[0] for t in d])
    return np.array([pairwise_distance(d[k:k + 1], full, turned[k:k + 1], full, grid)[0, 0]
                     for k in range(len(d))])


def materials(kd_rep: np.ndarray, d: np.ndarray, grid: DirectionGrid, kd_tolerance: float,
              ndf_distance: float) -> np.ndarray:
    """Materials (R,) int labels of representatives with kd (R, 3) and complete NDFs ``d`` (R, T, F): one where
    their kd agree within ``kd_tolerance`` (:func:`material_groups`), or where both NDFs are anisotropic (a
    quarter turn moves them by ``ndf_distance`` or more) and one turned is the other within ``ndf_distance``
    (:func:`turned_distances`).

    kd alone split a material whose frame turns across the sample: the separation leaves part of a rough lobe
    in kd, more or less as the lobe's axis lies to the lights (the Mitsuba copper, no diffuse term: kd 0.017 to
    0.10 by cluster, four materials, each with its own eta, stretch and NDF, drawn as wedges). That bias needs a
    lobe whose axis turns; isotropic lobes are left to kd, as pigments of one gloss may differ in eta (on the
    RTI fresco, joining them too changed nothing: 0.065 / 0.114 either way)."""
    turned = self_distances(d, grid, 0.25) >= ndf_distance
    linked = (turned_distances(d, grid) < ndf_distance) & turned[:, None] & turned[None]
    return joined(material_groups(kd_rep, kd_tolerance), linked)
