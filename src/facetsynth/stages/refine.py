"""Stage ``refine``: every point's kd and ks fitted to its own samples (issue 29; :mod:`facetsynth.refine`).

Inputs: the SVBRDF of ``params`` (NDF mixtures, turns, eta: kept), the
rectified geometry and ``separate``'s samples (the specular residual, its
validity, kd). Output: the fitted SVBRDF folder a user takes away, and
``refine/metrics.json`` with the relative L2 of the model against the samples
it was fitted on (in radiance, rectified: before and after) and, for a
virtual capture, kd and ks against the truth (scored apart from the fit, on
the written model).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..fileio import atomic_dir, read_npy, write_json
from ..frames import map_frames
from ..metrics import finite_or_none
from ..microfacet import fresnel
from ..refine import NormalSums, radiance_weights, solve
from ..render import light_geometry, unit
from ..svbrdf import SVBRDF
from .common import RectifiedCapture, StageSettings, tiles

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Settings(StageSettings):
    """The stage's knobs: config ``refine`` (workflow/schemas/config.schema.yaml)."""
    ridge: float = 1e-3    # weight of the pipeline's kd, ks as a prior, relative to the point's samples


def fit(model: SVBRDF, capture: RectifiedCapture, specular, valid, settings: Settings = Settings(),
        threads: int = 1) -> tuple[SVBRDF, dict]:
    """kd and ks per point by :func:`facetsynth.refine.solve` on the point's valid samples lit from above;
    returns the refined model (NDFs, turns, eta unchanged) and the fit's figures."""
    n = capture.n_points
    a0, b0 = model.kd / np.pi, model.ks
    a, b = a0.copy(), b0.copy()
    before, after, signal = np.zeros(n), np.zeros(n), np.zeros(n)
    views = unit(capture.view_position - capture.points)

    def tile_fit(tile: slice) -> None:
        index = np.arange(tile.start, tile.stop)
        wi, r2 = light_geometry(capture.points[tile][:, None, :], capture.light_positions[None])
        rho_s = np.asarray(specular[tile], np.float32)
        ok = np.asarray(valid[tile], bool) & (wi[..., 2] > 0) & capture.visible[tile][:, None]
        ok &= np.isfinite(rho_s).all(axis=-1)
        pp, ff = np.nonzero(ok)
        if pp.size == 0:
            return
        at = index[pp]
        area_o = model.area_at(index, views[tile])
        spec, c = model.specular_terms(at, wi[pp, ff], views[at], area_o[pp])
        g = spec * fresnel(c, model.eta[at])
        y = rho_s[pp, ff].astype(float) + a0[at]
        u = radiance_weights(wi[pp, ff], r2[pp, ff], capture.light_intensities[ff])
        sums = NormalSums.of(pp, len(index), y, g, u)
        a[tile], b[tile] = solve(sums, a0[tile], b0[tile], settings.ridge)
        before[tile] = sums.sse(a0[tile], b0[tile]).sum(axis=1)
        after[tile] = sums.sse(a[tile], b[tile]).sum(axis=1)
        signal[tile] = sums.uyy.sum(axis=1)

    t0 = time.perf_counter()
    map_frames(tile_fit, list(tiles(n)), threads, "refine: kd, ks per point", unit="tile")
    refined = replace(model, kd=np.pi * a, ks=b)
    total = signal.sum()
    figures = {"fitting_samples_rel_l2_before": finite_or_none(np.sqrt(before.sum() / total)) if total else None,
               "fitting_samples_rel_l2_after": finite_or_none(np.sqrt(after.sum() / total)) if total else None,
               "points_fitted": int((signal > 0).sum()), "ridge": settings.ridge,
               "seconds": round(time.perf_counter() - t0, 2)}
    return refined, figures


def truth_scores(model: SVBRDF, capture: RectifiedCapture) -> dict:
    """kd and ks of the written model against a virtual capture's truth (median relative error over the
    visible points whose truth is eq. 6: ``MaterialMaps.analytic``, kd / ks > 0); {} for a real capture."""
    truth = capture.truth()
    if truth is None:
        return {}
    on = capture.visible & (truth.region >= 0)
    analytic = getattr(truth, "analytic", None)
    if analytic is not None:
        on &= np.asarray(analytic, bool).reshape(on.shape)
    out = {}
    for name, fitted, true in (("kd", model.kd, truth.kd), ("ks", model.ks, truth.ks)):
        t = np.asarray(true, float).reshape(-1, 3).mean(axis=1)
        sel = on & (t > 0)
        err = np.abs(fitted.mean(axis=1)[sel] - t[sel]) / t[sel]
        out[f"{name}_median_rel_error"] = float(np.median(err)) if sel.any() else None
    return out


def run(model: str | Path, geometry: str | Path, specular: str | Path, valid: str | Path,
        svbrdf_out: str | Path, metrics_out: str | Path, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: the refined SVBRDF folder and refine/metrics.json."""
    capture = RectifiedCapture.load(geometry)
    pipeline = SVBRDF.load(model)
    n = capture.n_points
    spec, ok = read_npy(specular, mmap_mode="r"), read_npy(valid, mmap_mode="r")
    for path, a in ((specular, spec), (valid, ok)):
        if a.shape[0] != n:
            from ..errors import InputError
            raise InputError(path, f"has {a.shape[0]} rows, the rectified grid {n} points")
    refined, metrics = fit(pipeline, capture, spec, ok, settings, threads)
    with atomic_dir(svbrdf_out) as staging:
        refined.info = dict(pipeline.info, ks="ks, kd per point: eq. 6 fitted to the point's samples with the "
                                              "pipeline's NDF, turn and eta (facetsynth.refine)")
        refined.save(staging, provenance=dict(pipeline.info.get("provenance", {}), refine=str(model)))
    log.info("relative L2 on the fitting samples (radiance, rectified): %s -> %s (%d points, %.1f s)",
             metrics["fitting_samples_rel_l2_before"], metrics["fitting_samples_rel_l2_after"],
             metrics["points_fitted"], metrics["seconds"])
    truth = truth_scores(refined, capture)
    if truth:
        before = truth_scores(pipeline, capture)
        truth.update({f"{k}_before": v for k, v in before.items()})
        log.info("against the truth: %s", truth)
    write_json(metrics_out, {"ground_truth": capture.truth_scene is not None, **metrics, **truth})
