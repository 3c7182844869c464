"""Stage ``refine``: the fitted SVBRDF made to reproduce its own samples (issue 29; :mod:`facetsynth.fit.refine`).

Inputs: the SVBRDF of ``params`` (the paper's pipeline: the initialisation),
the rectified geometry and ``separate``'s samples (the specular residual, its
validity). Every choice is made by the squared radiance error the model leaves
on the samples it was fitted on (eq. 6 read forwards): one NDF per material,
eta and the NDF's stretch per material, each point's NDF turn, kd and ks per
point (:func:`fit`). Output: the fitted SVBRDF folder a user takes away, and
``refine/metrics.json``: the model's relative L2 against those samples before
and after, and each choice. A virtual capture's kd and ks against the truth are
rule ``score_refine``'s (:mod:`facetsynth.stages.score_refine`), beside the fit.
"""

from __future__ import annotations

import logging
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar
from scipy import sparse

from ..io.colour import channel_mean
from ..io.errors import InputError
from ..io.fileio import atomic_dir, read_npy, write_json
from ..io.frames import imap, map_frames
from ..evaluation.metrics import finite_or_none
from ..fit import cluster
from ..fit.cluster import relative_rotation, self_distances
from ..fit.synthesis import pairwise_distance, rotate_tuple
from ..fit.params import normalise, projected_area
from ..fit.refine import (NormalSums, best_turns, gather_samples, owned_kd, radiance_weights, solve, solve_table,
                          stretch, table_normal_equations)

from ..models.svbrdf import SVBRDF
from .common import TILE_POINTS, ModelOutputs, RectifiedCapture, RuleFiles, StageSettings, strided, tiles

log = logging.getLogger(__name__)


FIGURE_POINTS = 4096   # points (evenly strided) the fit's own figures are measured on


class Inputs(RuleFiles):
    """Rule ``refine``'s inputs: params' SVBRDF folder, separate's geometry and samples."""
    model: Path
    geometry: Path
    specular: Path
    valid: Path


Outputs = ModelOutputs      # rule refine's outputs: the fitted SVBRDF folder and the fit's figures


class Settings(StageSettings):
    """The stage's knobs: config ``refine`` (workflow/schemas/config.schema.yaml)."""
    ridge: float = 1e-3               # weight of the pipeline's kd, ks as a prior, relative to the point's samples
    ndf_ridge: float = 0.01           # each NDF table fitted to its points' samples; the completed table weighs as
                                      # this share of a cell's samples (0: the tables as synthesised)
    ndf_points: int = 4096            # points (evenly strided) of a table that fit it
    ndf_smooth: float = 0.3           # ... with the steps between neighbouring sectors of each ring weighing as
                                      # this share of a cell's samples (0: none)
    eta: tuple = (1.2, 1.4, 1.7, 2.1, 2.7, 3.5, 5.0, 8.0)   # the etas tried per material; (): none
    stretch: tuple = (0.6, 0.7, 0.8, 0.9, 1.0, 1.1)   # the NDF stretches tried per material; (): none
    material_points: int = 300        # points (evenly strided) of a material that choose its eta and stretch
    material_margin: float = 0.005    # a choice replaces the pipeline's where it lowers their error by this share
    material_tolerance: float = 0.25  # config params.material_tolerance: representatives' kd within it: one material
    share_distance: float = 0.05      # a material's representatives within this of its main one turned: that one
    share_candidates: int = 3         # the representatives of most points tried as a material's main one
    turn_window_deg: float = 22.5     # each point's NDF: its best representative turned within this either way (0: off)
    turn_margin: float = 0.01         # ... taken where it lowers the point's specular error by more than this share


def point_sums(model: SVBRDF, capture: RectifiedCapture, specular, valid, index: np.ndarray,
               separated_kd: np.ndarray | None = None) -> NormalSums:
    """The normal sums of :func:`facetsynth.fit.refine.solve` at points ``index`` (sorted) from their valid samples
    lit from above (i.z > 0), rho = separate's residual + kd/pi, weighted in radiance; a tile of points at a
    time (TILE_POINTS: the (points, frames, 3) temporaries stay small). ``separated_kd`` (P, 3): the kd that
    separate's residual was taken against (default the model's: the pipeline's model carries it; a model
    whose kd was refitted must be given the pipeline's, or the samples move with the fit)."""
    if index.size > TILE_POINTS:
        parts = [point_sums(model, capture, specular, valid, index[t], separated_kd) for t in tiles(index.size)]
        return NormalSums(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(NormalSums)))
    pp, _, wi, u, rho_s, views = samples(capture, specular, valid, index)
    _, _, d, denom = specular_factors(model, index, pp, wi, views)
    return sums_of(model, index, pp, d, denom, u, rho_s, views, separated_kd)


def sums_of(model: SVBRDF, index: np.ndarray, pp, d, denom, u, rho_s, views,
            separated_kd: np.ndarray | None = None) -> NormalSums:
    """:func:`point_sums` of samples already gathered (:func:`samples`' rows ``pp`` of ``index``, ...) whose
    D(h) ``d`` and F / (4 A(i) A(o)) ``denom`` are known (:func:`specular_factors`)."""
    at = index[pp]
    g = np.where(views[pp, 2] > 0.0, d * denom, 0.0)       # i.z > 0 already (samples)
    kd = model.kd if separated_kd is None else separated_kd
    return NormalSums.of(pp, len(index), rho_s + kd[at] / np.pi, g, u)


def samples(capture: RectifiedCapture, specular, valid, index: np.ndarray) -> tuple[np.ndarray, ...]:
    """The valid samples of points ``index`` lit from above (i.z > 0), finite: (row in ``index`` (S,), frame
    (S,), i (S, 3), radiance weights u (S, 3), the specular residual rho - kd/pi (S, 3), and the view o of
    every point of ``index`` (N, 3))."""
    frames = capture.frames(index)
    ok = np.asarray(valid[index], bool) & capture.visible[index][:, None]
    pp, ff, wi, r2, rho_s = gather_samples(capture.points[index], capture.lights,
                                           np.empty((0, 3, 3)) if frames is None else frames, ok,
                                           np.asarray(specular[index], np.float32))
    u = radiance_weights(wi, r2, capture.light_intensities[ff])
    return pp, ff, wi, u, rho_s, capture.view_directions(True, index)


def stretched(model: SVBRDF, s: np.ndarray) -> SVBRDF:
    """``model`` with each representative's NDF stretched by its s (R,) (:func:`facetsynth.fit.refine.stretch`),
    renormalised, and eq. 5's A(k) made anew from it (the others' tables as they were)."""
    ndf, area = model.ndf.copy(), model.area.copy()
    change = np.flatnonzero(np.asarray(s) != 1.0)
    if change.size:
        normalised, _ = normalise(np.stack([stretch(model.ndf[k], model.grid, float(s[k])) for k in change]),
                                  model.grid)
        ndf[change] = normalised
        area[change] = projected_area(normalised, model.grid, model.shadowing_grid)
    return replace(model, ndf=ndf, area=area)


def isotropic(model: SVBRDF, tolerance: float) -> np.ndarray:
    """(R,) bool: representatives whose NDF turned by a quarter is itself within ``tolerance``
    (:func:`facetsynth.fit.cluster.self_distances`): their turn is meaningless, and they get none."""
    return self_distances(model.ndf, model.grid, 0.25) < tolerance


def materials(model: SVBRDF, settings: Settings) -> tuple[np.ndarray, np.ndarray]:
    """The material of every representative (R,) (:func:`facetsynth.fit.cluster.materials`: kd within
    ``material_tolerance``, as params groups them, or one anisotropic NDF turned within ``share_distance``) and
    every point's representative of largest eq. 18 weight (P,)."""
    owner = model.neighbours[np.arange(model.n_points), np.argmax(model.weights, axis=1)]
    reps = (np.arange(model.ndf.shape[0]) if model.representatives is None
            else np.asarray(model.representatives, np.intp))
    return cluster.materials(owned_kd(model.kd, owner, reps), model.ndf, model.grid, settings.material_tolerance,
                             settings.share_distance), owner


def share_representatives(model: SVBRDF, capture: RectifiedCapture, specular, valid,
                          settings: Settings) -> tuple[SVBRDF, list]:
    """One NDF per material, turned point by point: every representative of a material (:func:`materials`) whose
    completed NDF is the material's main one turned, within ``settings.share_distance`` (eq. 15's relative
    distance after the best turn, :func:`facetsynth.fit.cluster.relative_rotation` over a half turn), hands its
    points to it with that turn added to theirs. Synthesis completes each representative on its own, each
    normalisation carries its own error, and ks made up for it cluster by cluster: steps in ks at every
    cluster border of one material (the demo's copper: nine representatives, one NDF turned; issue 29). An
    isotropic main NDF (turning it a quarter changes it by less than ``share_distance``) passes on no turn.

    The samples choose: each of the ``share_candidates`` representatives of most points is tried as the
    main one, on up to ``material_points`` of the material's points, each turned as :func:`choose_turns`
    would, scored by its squared error (:func:`fitted_error`); the best is taken where it is at most
    ``material_margin`` above the pipeline's mixtures' (one NDF is the simpler model: a tie goes to it).
    The representative of most points need not be the one to share (ggx-tiles: representative 9, its own
    point's ks 0, 0.11-0.17 from every other)."""
    material, owner = materials(model, settings)
    flat = isotropic(model, settings.share_distance)
    grid, d = model.grid, model.ndf.astype(float)
    full = np.ones(grid.shape)
    neighbours, weights = model.neighbours.copy(), model.weights.astype(float).copy()
    rotation = np.zeros(model.n_points) if model.rotation is None else model.rotation.astype(float)
    counts = np.bincount(owner[capture.visible], minlength=len(d))
    records = []

    def shared_with(main: int, members: np.ndarray) -> tuple[tuple[np.ndarray, ...], list[dict]]:
        """The mixtures, weights and turns with the members within share_distance of ``main`` handed to it,
        and a record of each."""
        phi, _ = relative_rotation(d[members], np.ones_like(d[members]), d[main], full, grid,
                                   max_shift=grid.n_phi // 4)
        nb, w, rot = neighbours.copy(), weights.copy(), rotation.copy()
        shared = []
        for j, turn_j in zip(members, phi):
            turned, conf = rotate_tuple(d[main], full, grid, turn_j / grid.d_phi)
            gap = float(pairwise_distance(d[j:j + 1], full[None], turned[None], conf[None], grid)[0, 0])
            if j == main or gap >= settings.share_distance:
                continue
            points = np.flatnonzero(owner == j)
            rot[points] += 0.0 if flat[main] else turn_j
            shared.append({"representative": int(j), "turn_deg": round(float(np.degrees(turn_j)), 2),
                           "distance": round(gap, 5), "points": int(points.size)})
        if shared:      # every point of main and of the members it took, main's own too (their mixtures held
            # shared members: the copper's blob of 53 points on representative 9's table, fitted alone), on main alone
            points = np.flatnonzero(np.isin(owner, [main] + [r["representative"] for r in shared]))
            nb[points], w[points] = main, 0.0
            w[points, 0] = 1.0
        return (nb, w, rot), shared

    for m in np.unique(material):
        members = np.flatnonzero(material == m)
        if members.size < 2:
            continue
        _, index = material_points(capture, owner, members, settings.material_points)

        def error(candidate: SVBRDF) -> float:
            """The squared error on the material's sample of points, each turned as choose_turns would."""
            turned, _ = choose_turns(candidate, capture, specular, valid, settings, points=index)
            return fitted_error(turned, capture, specular, valid, index, settings.ridge)

        tried = []
        for main in members[np.argsort(-counts[members], kind="stable")][:settings.share_candidates]:
            arrays, shared = shared_with(main, members)
            if shared:
                trial = replace(model, neighbours=arrays[0], weights=arrays[1], rotation=arrays[2])
                tried.append((error(trial), int(main), arrays, shared))
        if not tried:
            continue
        pipeline = error(model)
        best, main, arrays, shared = min(tried, key=lambda t: t[0])
        taken = best <= (1.0 + settings.material_margin) * pipeline
        if taken:
            neighbours, weights, rotation = arrays
        records.append({"material": int(m), "main": main, "isotropic": bool(flat[main]), "shared": shared,
                        "taken": bool(taken), "sse_relative": round(best / max(pipeline, 1e-300), 4),
                        "tried": {t[1]: round(t[0] / max(pipeline, 1e-300), 4) for t in tried}})
        log.info("material %d: %d of its %d other representatives are its main one (%d)%s turned: %s; squared "
                 "error after the turn search %.4f of the pipeline's (main ones tried: %s): %s", m, len(shared),
                 members.size - 1, main, " (isotropic: not)" if flat[main] else "",
                 [(r["representative"], r["turn_deg"], r["distance"]) for r in shared], records[-1]["sse_relative"],
                 records[-1]["tried"], "taken" if taken else "NOT taken")
    return replace(model, neighbours=neighbours, weights=weights, rotation=rotation), records


def material_points(capture: RectifiedCapture, owner: np.ndarray, members: np.ndarray,
                    at_most: int) -> tuple[np.ndarray, np.ndarray]:
    """The visible points of a material (whose largest eq. 18 weight is one of its representatives
    ``members``), and at most ``at_most`` of them, evenly strided: the ones its choices are scored on."""
    points = np.flatnonzero(capture.visible & np.isin(owner, members))
    return points, strided(points, at_most)


def fitted_error(model: SVBRDF, capture: RectifiedCapture, specular, valid, index: np.ndarray,
                 ridge: float) -> float:
    """The squared radiance error left at ``index`` by the points' kd, ks fit (:func:`facetsynth.fit.refine.solve`)."""
    sums = point_sums(model, capture, specular, valid, index)
    a, b = solve(sums, model.kd[index] / np.pi, model.ks[index], ridge)
    return float(sums.sse(a, b).sum())


def choose_per_material(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings, what: str,
                        ladder, apply, threads: int = 1) -> tuple[SVBRDF, list[dict]]:
    """One parameter per material (:func:`materials`,
    a point belonging to its largest eq. 18 weight's), chosen by the samples: each value of ``ladder`` is
    tried on up to ``settings.material_points`` of the material's points (evenly strided), scored by the
    squared radiance error left by their kd, ks fit, and the minimum between the best one's neighbours
    taken (:func:`ladder_minimum`); it replaces the pipeline's value where it lowers that error by
    more than ``settings.material_margin`` (elsewhere the samples do not tell the values apart, and the
    pipeline's stays). ``apply(model, representatives, points, value)`` is the model with the value set. The
    ladder's values are tried on ``threads`` threads. Returns the model with every material's choice and a
    record per material."""
    material, owner = materials(model, settings)
    ladder = np.asarray(sorted(ladder), float)
    records = []
    for m in np.unique(material) if ladder.size else []:
        members = np.flatnonzero(material == m)
        points, index = material_points(capture, owner, members, settings.material_points)
        if index.size == 0:
            continue

        def error(trial: SVBRDF) -> float:
            return fitted_error(trial, capture, specular, valid, index, settings.ridge)

        def error_at(value: float) -> float:
            return error(apply(model, members, points, value))

        current = error(model)
        sse = np.array(map_frames(error_at, list(ladder), threads, f"refine: {what} of material {m}", unit="value"))
        best, best_sse = ladder_minimum(ladder, sse, error_at)
        chosen = apply(model, members, points, best)
        taken = best_sse < (1.0 - settings.material_margin) * current
        if taken:
            model = chosen
        records.append({"material": int(m), "representatives": members.tolist(), "points": int(index.size),
                        what: best, "taken": bool(taken), "ladder": ladder.tolist(),
                        "sse_relative": (sse / max(current, 1e-300)).round(4).tolist(),
                        "sse_relative_chosen": round(best_sse / max(current, 1e-300), 4)})
        log.info("material %d (%d representatives): %s %.3f %s (squared error on %d points, relative to the "
                 "pipeline's: %s over %s; chosen %.4f)", m, members.size, what, best,
                 "taken" if taken else "NOT taken (no better than the pipeline's)", index.size,
                 records[-1]["sse_relative"], ladder.tolist(), records[-1]["sse_relative_chosen"])
    return model, records


def ladder_minimum(ladder: np.ndarray, sse: np.ndarray, error) -> tuple[float, float]:
    """(value, error) of the smallest ``error(value)`` between the neighbours of the best of ``ladder``
    (ascending, errors ``sse``): bounded Brent in log (the ladders are ratios), to 0.5 %; the ladder's own best
    where nothing between is lower. The parabola through the ladder's best three it replaced was biased by their
    spacing: the demo copper's eta 1.855 from 1.4 / 1.7 / 2.1, where the samples' minimum is at 1.81-1.82 (the
    truth 1.8), and ks followed F0: 0.085 from the truth against 0.047."""
    k = int(np.argmin(sse))
    lo, hi = np.log(ladder[max(k - 1, 0)]), np.log(ladder[min(k + 1, ladder.size - 1)])
    if hi <= lo:
        return float(ladder[k]), float(sse[k])
    found = minimize_scalar(lambda x: error(float(np.exp(x))), bounds=(lo, hi), method="bounded",
                            options={"xatol": 0.005})
    if found.fun < sse[k]:
        return float(np.exp(found.x)), float(found.fun)
    return float(ladder[k]), float(sse[k])


def one_eta_per_material(model: SVBRDF, capture: RectifiedCapture, settings: Settings) -> SVBRDF:
    """``model`` with each material's visible points at the median of their eta: the pipeline's eta made one
    per material before the samples choose theirs (:func:`choose_per_material`), so that where they do not
    choose, a material still has one. Params gives a point the eq. 18 mixture of its representatives' eta,
    which drifts across a material: the demo's paint from 1.506 to 1.467 top to bottom with a step at its
    middle row, and ks made up for it (a seam across the disc in the ks map, 0.332 to 0.363)."""
    material, owner = materials(model, settings)
    eta = model.eta.copy()
    for m in np.unique(material):
        points, _ = material_points(capture, owner, np.flatnonzero(material == m), 1)
        if points.size:
            eta[points] = np.median(eta[points])
    return replace(model, eta=eta)


def with_eta(model: SVBRDF, representatives: np.ndarray, points: np.ndarray, eta: float) -> SVBRDF:
    """``model`` with eta = ``eta`` at ``points`` (one material's)."""
    out = model.eta.copy()
    out[points] = eta
    fitted = np.zeros(model.n_points, bool) if model.eta_fitted is None else model.eta_fitted.copy()
    fitted[points] = True           # the samples constrained it
    return replace(model, eta=out, eta_fitted=fitted)


def with_stretch(model: SVBRDF, representatives: np.ndarray, points: np.ndarray, s: float) -> SVBRDF:
    """``model`` with the NDFs of ``representatives`` stretched by s (:func:`stretched`)."""
    factors = np.ones(model.ndf.shape[0])
    factors[representatives] = s
    return stretched(model, factors)


def specular_factors(model: SVBRDF, index: np.ndarray, pp: np.ndarray, i: np.ndarray,
                     views: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per sample (:func:`samples`: rows ``pp`` of ``index``, lights ``i``, the points' ``views``): the continuous
    cell coordinates (t, p) of its half vector in its point's turned frame, D(h), and eq. 6's
    F(c) / (4 A(i) A(o)): the specular factor without ks and D (:meth:`SVBRDF.sample_terms`), each (S,)."""
    t, p, d, f, area_i = model.sample_terms(index[pp], i, views[pp])
    return t, p, d, f / (4.0 * area_i * model.area_at(index, views)[pp])


def choose_turns(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings,
                 threads: int = 1, points: np.ndarray | None = None) -> tuple[SVBRDF, dict]:
    """Each point's NDF as the one representative, turned within ``turn_window_deg`` (whole sectors, then a
    fraction of one), that best explains its specular samples (:func:`facetsynth.fit.refine.best_turns`; candidates: the anisotropic
    representatives of its eq. 18 mixture of its own material; a point whose NDF is one isotropic
    representative gets no turn), where that lowers its error by more than ``turn_margin`` against
    the pipeline's mixture and turn; elsewhere (an isotropic lobe: every turn fits alike) the pipeline's NDF
    stays. A cluster's points shared one frame unless the cluster turned as a whole: at its borders the
    lobe's axis stepped (the demo's wedges, the Mitsuba copper's blocks, issue 29). ``points``: only these
    (sorted; default all)."""
    window = int(round(np.radians(settings.turn_window_deg) / model.grid.d_phi))
    if window <= 0:
        return model, {"turned_points": 0}
    n = capture.n_points
    rotation = np.zeros(n) if model.rotation is None else model.rotation.astype(float)
    neighbours, weights = model.neighbours.copy(), model.weights.astype(float).copy()
    gain = np.zeros(n)
    tables = model._ndf_flat
    material, owner = materials(model, settings)
    flat = isotropic(model, settings.share_distance)
    rotation[flat[owner] & (weights.max(axis=1) >= 1.0)] = 0.0     # one isotropic NDF: no turn field

    def tile_turns(index: np.ndarray) -> None:
        nb = model.neighbours[index]
        same = material[nb] == material[owner[index]][:, None]       # the point's own material, turnable
        candidates = np.where((model.weights[index] != 0) & same & ~flat[nb], nb, -1).astype(np.int64)
        turnable = (candidates >= 0).any(axis=1)        # an isotropic material's points: nothing to search
        index, candidates = index[turnable], candidates[turnable]
        if index.size == 0:
            return
        pp, _, i, u, rho_s, views = samples(capture, specular, valid, index)
        if pp.size == 0:
            return
        t, p, d, denom = specular_factors(model, index, pp, i, views)
        r, u = channel_mean(rho_s), channel_mean(u)
        g0 = d * denom
        ugr, ugg = (np.bincount(pp, v, minlength=index.size) for v in (u * g0 * r, u * g0 * g0))
        urr = np.bincount(pp, u * r * r, minlength=index.size)
        current = urr - np.divide(np.clip(ugr, 0, None) ** 2, ugg, out=np.zeros_like(ugg), where=ugg > 0)
        offsets = np.searchsorted(pp, np.arange(index.size + 1))
        err, rep, k = best_turns(offsets, t, p, denom, r, u, candidates, tables, model.grid.n_theta,
                                 model.grid.n_phi, window)
        better = (rep >= 0) & (err < (1.0 - settings.turn_margin) * current)
        rows = index[better]
        neighbours[rows] = 0
        neighbours[rows, 0] = rep[better]
        weights[rows] = 0.0
        weights[rows, 0] = 1.0
        rotation[rows] += k[better] * model.grid.d_phi
        gain[rows] = err[better] / np.maximum(current[better], 1e-300)

    points = np.arange(n) if points is None else np.asarray(points, np.intp)
    map_frames(tile_turns, [points[t] for t in tiles(points.size)], threads, "refine: each point's NDF turn",
               unit="tile")
    turned = gain > 0
    record = {"turned_points": int(turned.sum()), "turned_fraction": float(turned[capture.visible].mean())
              if capture.visible.any() else 0.0, "window_sectors": window,
              "specular_error_ratio_median": finite_or_none(np.median(gain[turned])) if turned.any() else None}
    log.info("NDF turns: %d points (%.0f %% of the visible) take a representative turned within +-%d sectors; "
             "their specular error falls to %s of the pipeline's (median)", record["turned_points"],
             100 * record["turned_fraction"], window, record["specular_error_ratio_median"])
    return replace(model, neighbours=neighbours, weights=weights, rotation=rotation), record


def fit(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings = Settings(),
        threads: int = 1) -> tuple[SVBRDF, dict]:
    """The pipeline's model made to reproduce its samples, in this order: one NDF per material
    (:func:`share_representatives`); one eta per material (:func:`one_eta_per_material`), then the samples'
    eta and the NDF's stretch, per material (:func:`choose_per_material`);
    each point's NDF turn (:func:`choose_turns`); every table that points use alone, fitted to their samples
    (:func:`refit_tables`), and each point's turn again against them; kd and ks per point
    (:func:`facetsynth.fit.refine.solve`).
    Returns the refined model and the fit's figures."""
    t0 = time.perf_counter()
    start = model
    model, shared = share_representatives(model, capture, specular, valid, settings)
    model = one_eta_per_material(model, capture, settings)
    model, etas = choose_per_material(model, capture, specular, valid, settings, "eta", settings.eta, with_eta,
                                      threads)
    model, stretches = choose_per_material(model, capture, specular, valid, settings, "stretch", settings.stretch,
                                           with_stretch, threads)
    model, turns = choose_turns(model, capture, specular, valid, settings, threads)
    model, tables = refit_tables(model, capture, specular, valid, settings, threads)
    if tables:      # the turns again, against the tables the samples made (ggx-tiles' held-out lights 0.071 -> 0.064)
        model, turns["after_tables"] = choose_turns(model, capture, specular, valid, settings, threads)
    a, b, fitted = kd_ks(model, capture, specular, valid, settings, threads)
    a0, b0 = model.kd / np.pi, model.ks
    bad = ~(np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1))   # never seen; never written either
    if bad.any():
        log.warning("%d point(s) with a non-finite kd or ks fit keep the pipeline's", int(bad.sum()))
        a[bad], b[bad] = a0[bad], b0[bad]
    refined = replace(model, kd=np.pi * a, ks=b)
    figures = {**{f"fitting_samples_rel_l2_{when}": samples_rel_l2(m, capture, specular, valid, start.kd)
                  for when, m in (("before", start), ("after", refined))},
               "fitting_samples_points": FIGURE_POINTS, "points_fitted": int(fitted.sum()), "ridge": settings.ridge,
               "shared": shared, "eta": etas, "stretch": stretches, "turns": turns, "tables": tables,
               "seconds": round(time.perf_counter() - t0, 2)}
    return refined, figures


def kd_ks(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings,
          threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """kd/pi and ks per point (P, 3) each (:func:`facetsynth.fit.refine.solve`, the model's own as the prior), and
    (P,) whether the point had samples."""
    n = capture.n_points
    a0, b0 = model.kd / np.pi, model.ks
    a, b = a0.copy(), b0.copy()
    fitted = np.zeros(n, bool)

    def tile_fit(tile: slice) -> None:
        sums = point_sums(model, capture, specular, valid, np.arange(tile.start, tile.stop))
        a[tile], b[tile] = solve(sums, a0[tile], b0[tile], settings.ridge)
        fitted[tile] = sums.u.sum(axis=1) > 0

    map_frames(tile_fit, list(tiles(n)), threads, "refine: kd, ks per point", unit="tile")
    return a, b, fitted


def turned_widely(turns: np.ndarray) -> bool:
    """Whether points at ``turns`` (radians) spread wider than evenly over a quarter turn (their mean resultant
    length below sin(pi/4) / (pi/4) = 0.90): a frame that turns across the sample, whose points at phi and
    phi + pi read the two halves of one table. :func:`refit_tables` folds such a table where a half turn maps
    it onto itself (the Mitsuba copper: 0.63). The turns of a table that keeps one frame lie within +-25 deg
    (the Mitsuba tiles and quadrants: 0.97-1.00), and folding theirs lost what a measured BRDF's table holds
    beyond eq. 6 (the quadrants' satin, 0.035 from its half turn: held-out lights 0.086 -> 0.091)."""
    return bool(turns.size > 0
                and abs(np.mean(np.exp(1j * np.asarray(turns, float)))) < np.sin(np.pi / 4) / (np.pi / 4))


def refit_tables(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings,
                 threads: int = 1) -> tuple[SVBRDF, list[dict]]:
    """Every NDF table that points use alone (eq. 18 weight 1, after :func:`share_representatives` and
    :func:`choose_turns`: one per material) fitted to the samples of up to ``settings.ndf_points`` of them
    (evenly strided), each sample read in its point's turned frame, with the points' kd, ks (fitted to their
    samples first, :func:`facetsynth.fit.refine.solve`), eta and A(k) fixed
    (:func:`facetsynth.fit.refine.table_normal_equations`, :func:`facetsynth.fit.refine.solve_table`: the
    completed table is the prior where the samples say little); renormalised, and A(k) made anew. One
    point's samples leave gaps between its lights' half vectors, which synthesis filled by interpolation;
    the points of a table turn it, so together they measure it densely (issue 29: the held-out lights). Tiles
    on ``threads`` threads."""
    if settings.ndf_ridge <= 0:
        return model, []
    grid, n = model.grid, capture.n_points
    n_cells = grid.n_theta * grid.n_phi
    rotation = np.zeros(n) if model.rotation is None else model.rotation.astype(float)
    alone = model.weights.max(axis=1) >= 1.0
    table_of = model.neighbours[np.arange(n), np.argmax(model.weights, axis=1)]
    ndf, area = model.ndf.copy(), model.area.copy()
    symmetric = self_distances(model.ndf, model.grid, 0.5) < settings.share_distance    # a half turn maps it
    records = []
    for k in np.unique(table_of[alone & capture.visible]):
        points = np.flatnonzero(alone & capture.visible & (table_of == k))
        index = strided(points, settings.ndf_points)
        folded = bool(symmetric[k]) and turned_widely(rotation[points])

        def equations(tile: slice, index=index) -> tuple[sparse.csr_matrix, np.ndarray]:
            idx = index[tile]
            pp, _, i, u, rho_s, views = samples(capture, specular, valid, idx)
            t, p, d, denom = specular_factors(model, idx, pp, i, views)     # once: the sums and the lookup
            a, b = solve(sums_of(model, idx, pp, d, denom, u, rho_s, views), model.kd[idx] / np.pi, model.ks[idx],
                         settings.ridge)
            at = idx[pp]
            look = grid.stencil(t, p)
            r = rho_s + model.kd[at] / np.pi - a[pp]      # the samples' rho (point_sums' y) less kd/pi
            return table_normal_equations(look.cells.T, look.weights.T, b[pp] * denom[:, None], r, u, n_cells)

        m, v = sparse.csr_matrix((n_cells, n_cells)), np.zeros(n_cells)
        for tile_m, tile_v in imap(equations, list(tiles(index.size)), threads, f"refine: NDF table {k}",
                                   unit="tile"):      # in order: the sums are those of one thread
            m, v = m + tile_m, v + tile_v
        table = solve_table(m, v, model.ndf[k].astype(float).ravel(), settings.ndf_ridge, settings.ndf_smooth,
                            grid.shape, half_turn=folded).reshape(grid.shape)
        normalised, _ = normalise(table[None], grid)
        ndf[k] = normalised[0]
        area[k] = projected_area(normalised, grid, model.shadowing_grid)[0]
        records.append({"table": int(k), "points": int(points.size), "fitted_on": int(index.size),
                        "folded": folded})
        log.info("NDF table %d fitted to the samples of %d of its %d points", k, index.size, points.size)
    return replace(model, ndf=ndf, area=area), records


def samples_rel_l2(model: SVBRDF, capture: RectifiedCapture, specular, valid,
                   separated_kd: np.ndarray) -> float | None:
    """sqrt(sum u (rho - model)^2 / sum u rho^2) over the valid samples of up to FIGURE_POINTS visible points
    (evenly strided): the model against the samples it was fitted on, in radiance (u of
    :func:`facetsynth.fit.refine.radiance_weights`), on the rectified grid; rho = separate's residual +
    ``separated_kd``/pi (the pipeline's kd: the samples stay where they were whatever kd the model has)."""
    index = strided(np.flatnonzero(capture.visible), FIGURE_POINTS)
    if index.size == 0:
        return None
    sums = point_sums(model, capture, specular, valid, index, separated_kd)
    total = float(sums.uyy.sum())
    err = float(sums.sse(model.kd[index] / np.pi, model.ks[index]).sum())
    return finite_or_none(np.sqrt(err / total)) if total > 0 else None


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: the refined SVBRDF folder and refine/metrics.json."""
    capture = RectifiedCapture.load(inputs.geometry)
    pipeline = SVBRDF.load(inputs.model)
    n = capture.n_points
    spec, ok = read_npy(inputs.specular, mmap_mode="r"), capture.validity(inputs.valid)
    if spec.shape[0] != n:
        raise InputError(inputs.specular, f"has {spec.shape[0]} rows, the rectified grid {n} points")
    refined, metrics = fit(pipeline, capture, spec, ok, settings, threads)
    with atomic_dir(outputs.svbrdf) as staging:
        refined.info = dict(pipeline.info, ks="ks, kd per point: eq. 6 fitted to the point's samples "
                                              "(facetsynth.stages.refine)",
                            refine={"eta_per_material": [{k: r[k] for k in ("material", "eta", "taken")}
                                                         for r in metrics["eta"]],
                                    "stretch_per_material": [{k: r[k] for k in ("material", "stretch", "taken")}
                                                             for r in metrics["stretch"]],
                                    "note": "eta's intervals (eta.exr eta_lo, eta_hi; eta.intervals) are params' "
                                            "eq. 19 fit, before refine chose eta by the samples"})
        refined.save(staging, provenance=dict(pipeline.info.get("provenance", {}), refine=str(inputs.model)))
    log.info("relative L2 on the fitting samples (radiance, rectified, %d points): %s -> %s (%d points fitted, "
             "%.1f s)", FIGURE_POINTS, metrics["fitting_samples_rel_l2_before"],
             metrics["fitting_samples_rel_l2_after"], metrics["points_fitted"], metrics["seconds"])
    write_json(outputs.metrics, {"ground_truth": capture.truth_scene is not None, **metrics})
