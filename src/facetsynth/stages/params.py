"""Stage ``params``: ks, normalised NDF, shadowing, eta (paper 002 sec. 5.4) -> the fitted SVBRDF folder.

Inputs: the completed representative NDFs of ``synthesize`` (in the partial
NDF's scale), the eq. 18 neighbours and weights of ``cluster``, kd of
``separate``, the per-point specular samples (``separate/specular.npy``,
``valid.npy``) whose grazing part partial NDF fitting excluded, the specular
colour of ``resample`` and the rectified geometry. Output: the folder
described in :mod:`facetsynth.models.svbrdf` and ``params/metrics.json``: the eq. 19
fit's figures per material and, for a virtual capture, eta, ks and the NDF
spread against the truth (:func:`facetsynth.evaluation.params.truth_scores`, apart from the fit, on the
written model).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..fit import params
from ..fit.cluster import material_groups
from ..io.colour import channel_mean
from ..io.errors import InputError
from ..io.fileio import atomic_dir, read_exr, read_json, read_npy, write_json
from ..io.frames import map_frames
from ..geometry.grid import DirectionGrid
from ..evaluation.metrics import finite_or_none
from ..models.microfacet import fresnel, half_vector
from ..models.svbrdf import SVBRDF
from ..fit.synthesis import SUPPORT
from ..evaluation.params import truth_scores
from .common import ModelOutputs, RectifiedCapture, RuleFiles, StageSettings, tiles

log = logging.getLogger(__name__)


def _load(path, shape0=None, what=""):
    """A memory-mapped .npy tensor whose first axis has ``shape0`` rows (InputError naming ``what`` if not)."""
    a = read_npy(path, mmap_mode="r")
    if shape0 is not None and a.shape[0] != shape0:
        raise InputError(path, f"{what} has {a.shape[0]} rows, expected {shape0}")
    return a


def mixture(ks_rep: np.ndarray, neighbours: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point (eq. 18): D(x) = sum w18 D_rep, so ks(x) = sum w18 ks_rep and the normalised NDF's
    mixture weights are w18 ks_rep / ks(x). Returns (ks (P,), mixture weights (P, K)).

    Eq. 18's least-squares weights may be negative; a mixture with negative
    weights can make D and eq. 5's A(k) negative somewhere (measured: A down
    to -0.7 on wallpaper, i.e. unbounded rho). The model's mixture weights are
    therefore the non-negative part of w18 ks_rep, renormalised to sum 1 (a
    convex mixture of normalised NDFs is a normalised NDF with A(k) > 0); ks(x)
    is the eq. 18 value, clipped at 0.
    """
    contrib = weights * ks_rep[neighbours]
    ks_pt = np.clip(contrib.sum(axis=1), 0.0, None)
    positive = np.clip(contrib, 0.0, None)
    total = positive.sum(axis=1, keepdims=True)
    mix = np.divide(positive, total, out=np.clip(weights, 0.0, None), where=total > 0)
    return ks_pt, mix


def build_model(ndf: np.ndarray, grid: DirectionGrid, neighbours: np.ndarray, weights: np.ndarray,
                kd: np.ndarray, colour: np.ndarray, capture: RectifiedCapture,
                representatives: np.ndarray | None = None,
                rotation: np.ndarray | None = None) -> tuple[SVBRDF, np.ndarray, np.ndarray]:
    """The SVBRDF before eta: ks (sec. 5.4), normalised NDFs, A(k) (eq. 5), per-point mixtures.

    Returns (model with eta = default and ks in the NDF's scale times colour,
    per-point scalar ks (P,), per-representative ks (R,)).
    """
    normalised, ks_rep = params.normalise(ndf, grid)
    area = params.projected_area(normalised, grid)
    nb = np.asarray(neighbours, np.intp)
    w18 = np.asarray(weights, float)
    if nb.min() < 0 or nb.max() >= len(ks_rep):
        raise ValueError(f"neighbour indices outside [0, {len(ks_rep)})")
    ks_pt, mix = mixture(ks_rep, nb, w18)
    ks_pt = np.where(capture.visible, ks_pt, 0.0)
    kd = np.where(capture.visible[:, None], kd, 0.0)
    model = SVBRDF(plane=capture.grid, grid=grid, kd=kd, ks=ks_pt[:, None] * colour,
                   eta=np.full(len(ks_pt), params.ETA_DEFAULT), ndf=normalised.astype(np.float32),
                   area=area.astype(np.float32), neighbours=nb, weights=mix,
                   representatives=representatives, eta_fitted=np.zeros(len(ks_pt), bool), rotation=rotation,
                   normal=capture.normals)
    return model, ks_pt, ks_rep


def grazing_fresnel(model: SVBRDF, ks_pt: np.ndarray, capture: RectifiedCapture, specular, valid,
                    grazing_deg: float, min_ndf_fraction: float, cosine: np.ndarray,
                    covered: np.ndarray, threads: int = 1) -> dict[str, np.ndarray]:
    """F_m of eq. 20 for every grazing sample (light steeper than ``grazing_deg``) of every visible point.

    ``model`` holds the NDFs as synthesis left them (carrying F, eq. 11) and
    ``cosine`` (R, T, F) the cosine of the Fresnel factor each of their cells
    carries. Returns flat arrays over samples: ``point``, ``f_m``, ``c`` =
    |i.h|, ``c_ref`` = the cosine the model's NDF carries at the sample's h
    (the eq. 18 mixture of ``cosine``, weighted by each representative's D
    there), ``rho_s``. Only samples whose half vector lies in the lobe (D(h) >=
    ``min_ndf_fraction`` x the point's largest D) are kept: elsewhere the
    specular signal, and so F_m, is noise; and only where the NDF was
    measured or synthesized (``covered`` (R, T, F) bool, the synthesis domain
    before push-pull, for at least half of the mixture's weight): push-pull's
    extrapolation is no basis for eq. 20. Tiles of points run on ``threads`` threads.
    """
    cos_g = np.cos(np.radians(grazing_deg))
    peak = model.ndf.reshape(model.ndf.shape[0], -1).max(axis=1)
    carried = (model.ndf * cosine).reshape(model.ndf.shape[0], -1).astype(float)
    covered = np.asarray(covered, float).reshape(model.ndf.shape[0], -1)
    keys = ("point", "f_m", "c", "c_ref", "rho_s")

    def tile_samples(tile: slice) -> dict[str, np.ndarray]:
        wi, _ = capture.light_directions(tile)                                            # (p, F, 3)
        ok = np.asarray(valid[tile], bool) & (wi[..., 2] > 0) & (wi[..., 2] < cos_g)
        ok &= capture.visible[tile][:, None] & (ks_pt[tile][:, None] > 0)
        pp, ff = np.nonzero(ok)
        if pp.size == 0:
            return {}
        index = pp + tile.start
        o = capture.view_directions(True, index)
        i = wi[pp, ff]
        h = half_vector(i, o)
        spec, c = model.specular_terms(index, i, o)
        d_peak = np.sum(model.weights[index] * peak[model.neighbours[index]], axis=1)
        d_here = model.ndf_at(index, h)
        c_ref = np.clip(model.mixture(carried, model.grid, index, h) / np.maximum(d_here, 1e-300), 0.0, 1.0)
        lobe = (d_here >= min_ndf_fraction * d_peak) & (model.mixture(covered, model.grid, index, h) >= 0.5)
        rho_s = channel_mean(np.asarray(specular[tile], float)[pp, ff])
        f_m = params.measured_fresnel(rho_s, ks_pt[index] * spec)
        keep = lobe & (spec > 0)
        return {k: v[keep] for k, v in zip(keys, (index, f_m, c, c_ref, rho_s))}

    found = [t for t in map_frames(tile_samples, list(tiles(capture.n_points)), threads, "params: grazing samples",
                                   unit="tile") if t]
    return {k: (np.concatenate([t[k] for t in found]) if found else np.zeros(0)) for k in keys}


# Grazing samples (evenly strided) per material that eq. 19 is fitted on: a native-resolution sample has
# millions, and eta's interval counts representatives, not samples (INTERVAL_UNIT).
ETA_SAMPLES = 200_000
# The independent units of eta's interval (params.eta_profile's n): the samples of one representative share its
# NDF's error at the grazing half vectors (docs/decisions.md "Metrics a user trusts; eta's interval").
INTERVAL_UNIT = "representative"
INTERVAL_METHOD = ("profile likelihood of eq. 19 (linear residuals, as fitted): RSS(eta) on 241 values of "
                   "[eta_min, eta_max] (eta is eq. 19's only free parameter: nothing else to profile out), "
                   "95 %: RSS(eta) <= RSS_min (1 + chi2_1(0.95) / (n - 1)), chi2_1(0.95) = 3.841, the residual "
                   "variance estimated at the optimum; n = the material's representatives with grazing samples "
                   "(a representative's samples share its NDF's error), ends by Brent's method; "
                   "eta_identifiable: width < max_eta_interval and neither end at a bound")


def fit_eta(model: SVBRDF, w18: np.ndarray, samples: dict[str, np.ndarray], material: np.ndarray, bounds,
            default: float, min_samples: int, max_std: float, max_split_difference: float = 0.1,
            max_eta_interval: float = 0.2, interval_unit: str = INTERVAL_UNIT) -> tuple:
    """eta per material by LM (eq. 19) on the grazing samples of its points (up to ETA_SAMPLES, evenly
    strided; a point belongs to the material of its largest eq. 18 weight's representative); every
    representative of the material takes it, and each point the eq. 18 mixture of its representatives' eta.

    The standard error of one fit assumes independent residuals, but the
    NDF's errors are shared by a point's samples; so the fit is repeated on
    the samples of the even and of the odd points, and eta counts as
    unconstrained (default kept) when the halves disagree by more than
    ``max_split_difference``. Each material also gets the 95 % profile-likelihood
    interval of eta (:func:`facetsynth.fit.params.eta_profile`, its independent
    units the material's representatives (``interval_unit`` "representative"),
    points ("point") or samples ("sample")) and ``eta_identifiable`` (width <
    ``max_eta_interval``, closed inside the bounds). An interval open at both
    bounds (every eta fits the samples: a material of one representative,
    such as the points on a black marker) keeps the default: its fitted eta,
    divided out of the NDF, would scale that representative's ks by up to
    10 x and, through eq. 18's negative weights, its neighbours' ks too
    (ggx-tiles at native resolution: ks 0.19 for 0.7). Returns (eta (P,),
    fitted (P,) bool, per-material records, eta per representative (R,),
    interval per representative (R, 2)). ``samples["c_ref"]`` None: eq. 19 as printed (no
    Fresnel factor in the NDF, e.g. an analytic material).
    """
    n_rep = model.ndf.shape[0]
    owner = model.neighbours[np.arange(model.n_points), np.argmax(w18, axis=1)]
    sample_material = material[owner[samples["point"]]] if samples["point"].size else np.zeros(0, np.intp)
    eta_rep, ok_rep, records = np.full(n_rep, default), np.zeros(n_rep, bool), []
    interval_rep = np.tile(np.asarray(bounds, float), (n_rep, 1))
    kw = dict(bounds=bounds, default=default, min_samples=min_samples, max_std=max_std)
    unit_of_sample = {"representative": owner[samples["point"]] if samples["point"].size else None,
                      "point": samples["point"], "sample": None}[interval_unit]
    for m in np.unique(material):
        sel = np.flatnonzero(sample_material == m)
        sel = sel[:: max(1, int(np.ceil(sel.size / ETA_SAMPLES)))]
        c_ref = None if samples["c_ref"] is None else samples["c_ref"][sel]
        res = params.fit_eta(samples["f_m"][sel], samples["c"][sel], c_ref, **kw)
        interval = params.eta_profile(samples["f_m"][sel], samples["c"][sel], c_ref, bounds=bounds,
                                      groups=None if unit_of_sample is None else unit_of_sample[sel])
        record = {"material": int(m), "representatives": np.flatnonzero(material == m).tolist(), "eta": res.eta,
                  "constrained": res.constrained, "std": finite_or_none(res.std), "samples": res.samples,
                  "reason": res.reason,
                  "eta_interval": [interval.lo, interval.hi], "eta_interval_width": interval.width,
                  "eta_identifiable": interval.identifiable(max_eta_interval),
                  "eta_interval_open": [interval.open_below, interval.open_above],
                  "eta_interval_units": interval.units, "eta_profile_best": finite_or_none(interval.best)}
        if interval.reason:
            record["eta_interval_reason"] = interval.reason
        interval_rep[material == m] = interval.lo, interval.hi
        if res.constrained and interval.open_below and interval.open_above:
            res = params.EtaFit(default, False, res.std, res.samples, res.rms,
                                f"the 95 % interval of eta is all of [{bounds[0]}, {bounds[1]}] ({interval.units} "
                                "independent unit(s)): the samples do not constrain it")
            record.update(eta=default, constrained=False, fitted_eta=record["eta"], reason=res.reason)
        if res.constrained:
            halves = []
            for parity in (0, 1):
                part = samples["point"][sel] % 2 == parity
                half = params.fit_eta(samples["f_m"][sel][part], samples["c"][sel][part],
                                      None if c_ref is None else c_ref[part], **kw)
                halves.append(half.eta if half.constrained else np.nan)
            record["eta_halves"] = [finite_or_none(h) for h in halves]
            if not np.all(np.isfinite(halves)) or abs(halves[0] - halves[1]) > max_split_difference:
                res = params.EtaFit(default, False, res.std, res.samples, res.rms,
                                    f"even/odd points disagree: eta {halves[0]:.3f} / {halves[1]:.3f}")
                record.update(eta=default, constrained=False, fitted_eta=record["eta"], reason=res.reason)
        eta_rep[material == m], ok_rep[material == m] = res.eta, res.constrained
        log.info("material %d: eta %.3f (%s), 95 %% interval [%.3f, %.3f] (%d independent units), %s",
                 m, res.eta, "fitted" if res.constrained else "default: " + res.reason, interval.lo, interval.hi,
                 interval.units, "identifiable" if record["eta_identifiable"] else "NOT identifiable")
        records.append(record)
    total = w18.sum(axis=1)
    eta = np.where(np.abs(total) > 1e-6, np.sum(w18 * eta_rep[model.neighbours], axis=1) / np.where(
        np.abs(total) > 1e-6, total, 1.0), default)                    # points without weights keep the default
    eta = np.clip(eta, *bounds)
    fitted = ok_rep[owner]
    return eta, fitted, records, eta_rep, interval_rep


class Inputs(RuleFiles):
    """Rule ``params``'s inputs: separate's geometry, kd and samples, resample's specular colour, cluster's
    representatives and eq. 18 neighbours and weights (and each point's NDF turn), synthesize's completed
    NDFs, the Fresnel cosine they carry, their confidence and their grid."""
    geometry: Path
    kd: Path
    specular: Path
    valid: Path
    colour: Path
    representatives: Path
    neighbours: Path
    weights: Path
    ndf: Path
    fresnel_cosine: Path
    synthesis_confidence: Path
    grid: Path
    rotation: Path | None = None      # cluster's turn of each point's NDF; None: none


Outputs = ModelOutputs      # rule params's outputs: the pipeline's SVBRDF folder (refine's start), the figures


class Settings(StageSettings):
    """The stage's knobs: config ``params`` and ``partial_ndf.grazing_deg`` (workflow/schemas/config.schema.yaml)."""
    eta_min: float = params.ETA_BOUNDS[0]     # eta is bounded to [eta_min, eta_max] in eq. 19's LM fit
    eta_max: float = params.ETA_BOUNDS[1]
    eta_default: float = params.ETA_DEFAULT   # kept where the grazing samples do not constrain eta
    material_tolerance: float = 0.25       # representatives' kd within it: one material, one eta
    min_samples: int = 8                   # grazing samples a material needs for an eta fit
    max_std: float = 0.15                  # a fit with a larger standard error of eta counts as unconstrained
    min_ndf_fraction: float = 0.05         # grazing samples used: half vector in the lobe (D >= this x the peak)
    max_split_difference: float = 0.1      # eta of the even and the odd points must agree within it
    max_eta_interval: float = 0.2          # eta identifiable: its 95 % interval narrower than this
    grazing_deg: float = 80.0              # config partial_ndf.grazing_deg: lights beyond it are eq. 20's samples

    @property
    def bounds(self) -> tuple[float, float]:
        return self.eta_min, self.eta_max


@dataclass(frozen=True)
class Tables:
    """The stage's inputs read and checked against the rectified grid (P points) and the representatives
    (R): the completed NDFs (R, T, F) in the partial NDF's scale, the Fresnel cosine they carry (R, T, F),
    where synthesis measured or synthesized them (``covered``, (R, T, F) bool), eq. 18's neighbours and
    weights (P, K), kd and the specular colour (P, 3), the samples (memory-mapped) and each point's turn."""
    grid: DirectionGrid
    representatives: np.ndarray
    ndf: np.ndarray
    cosine: np.ndarray
    covered: np.ndarray
    neighbours: np.ndarray
    weights: np.ndarray
    kd: np.ndarray
    colour: np.ndarray
    specular: np.ndarray
    valid: np.ndarray
    rotation: np.ndarray | None


def load(inputs: Inputs, capture: RectifiedCapture) -> Tables:
    """The stage's inputs (:class:`Tables`); an InputError names a file whose shape does not fit."""
    n = capture.n_points
    grid = DirectionGrid.from_dict(read_json(inputs.grid))
    reps = np.asarray(_load(inputs.representatives))
    table = np.asarray(_load(inputs.ndf, len(reps), "the completed NDF table"), float)
    if table.shape[1:] != grid.shape:
        raise InputError(inputs.ndf, f"NDF table {table.shape[1:]} does not match its grid {grid.shape}")
    cosine = np.asarray(_load(inputs.fresnel_cosine, len(reps), "the Fresnel cosine table"), float)
    if cosine.shape != table.shape:
        raise InputError(inputs.fresnel_cosine, f"shape {cosine.shape} does not match the NDF table {table.shape}")
    covered = np.asarray(_load(inputs.synthesis_confidence, len(reps), "the synthesis confidence"), float) > SUPPORT
    channels, _ = read_exr(inputs.kd)
    return Tables(grid=grid, representatives=reps, ndf=table, cosine=cosine, covered=covered,
                  neighbours=np.asarray(_load(inputs.neighbours, n, "neighbours")),
                  weights=np.asarray(_load(inputs.weights, n, "weights"), float),
                  kd=channels["RGB"].reshape(n, 3).astype(float),
                  colour=np.asarray(_load(inputs.colour, n, "specular colour"), float),
                  specular=_load(inputs.specular, n, "specular samples"),
                  valid=capture.validity(inputs.valid),
                  rotation=None if inputs.rotation is None else np.asarray(_load(inputs.rotation, n, "rotation"),
                                                                           float))


def fit_model(t: Tables, capture: RectifiedCapture, settings: Settings, threads: int = 1) -> tuple[SVBRDF, dict]:
    """ks, the normalised NDFs and A(k) (sec. 5.4, eq. 5) of the NDFs as synthesis left them; F_m of eq. 20
    on their grazing samples (:func:`grazing_fresnel`); eta per material by eq. 19 (:func:`fit_eta`); then
    the model made anew from the NDFs divided by the Fresnel factor they carry (:func:`fresnel_free`).
    Returns the model (eta, its fitted flag and interval per point, ``info``) and the fit's figures."""
    carrying, ks_pt, ks_rep = build_model(t.ndf, t.grid, t.neighbours, t.weights, t.kd, t.colour, capture,
                                          t.representatives, t.rotation)
    log.info("%d representatives, ks median %.4g; %d points", len(t.representatives), float(np.median(ks_rep)),
             capture.n_points)
    samples = grazing_fresnel(carrying, ks_pt, capture, t.specular, t.valid, settings.grazing_deg,
                              settings.min_ndf_fraction, t.cosine, t.covered, threads)
    log.info("%d grazing samples (lights beyond %.0f deg) in the lobes", samples["f_m"].size, settings.grazing_deg)
    material = material_groups(t.kd[t.representatives.astype(np.intp)], settings.material_tolerance)
    log.info("%d materials by kd (tolerance %.2f)", material.max() + 1, settings.material_tolerance)
    eta, fitted, records, eta_rep, interval_rep = fit_eta(carrying, t.weights, samples, material, settings.bounds,
                                                          settings.eta_default, settings.min_samples,
                                                          settings.max_std, settings.max_split_difference,
                                                          settings.max_eta_interval)
    model = fresnel_free(t, capture, eta_rep)
    model.eta, model.eta_fitted = eta, fitted & capture.visible
    owner = t.neighbours[np.arange(capture.n_points), np.argmax(t.weights, axis=1)]   # a point's interval: its
    model.eta_lo, model.eta_hi = interval_rep[owner, 0], interval_rep[owner, 1]      # material's (as eta_fitted)
    model.info = eta_info(model, material, records, capture, settings)
    return model, fit_metrics(model, samples, records, capture, settings)


def fresnel_free(t: Tables, capture: RectifiedCapture, eta_rep: np.ndarray) -> SVBRDF:
    """The model of the NDFs without the Fresnel factor they carry, D = D_c / F(cosine, eta) (eqs. 3, 11), with
    each representative's eta: its ks, normalised NDFs and A(k) free of Fresnel (:func:`build_model`)."""
    free = t.ndf / np.maximum(fresnel(t.cosine, eta_rep[:, None, None]), 1e-6)
    model, _, _ = build_model(free, t.grid, t.neighbours, t.weights, t.kd, t.colour, capture, t.representatives,
                              t.rotation)
    return model


def eta_info(model: SVBRDF, material: np.ndarray, records: list[dict], capture: RectifiedCapture,
             settings: Settings) -> dict:
    """The model's ``info`` (model.json): how eta was fitted (eq. 19), its intervals, and what ks is."""
    return {"eta": {"bounds": list(settings.bounds), "default": settings.eta_default, "materials": material.tolist(),
                    "fitted_fraction": float(model.eta_fitted[capture.visible].mean()),
                    "grazing_deg": settings.grazing_deg,
                    "intervals": {"method": INTERVAL_METHOD, "max_width": settings.max_eta_interval,
                                  "per_material": [{"material": r["material"], "eta": r["eta"],
                                                    "interval": r["eta_interval"],
                                                    "identifiable": r["eta_identifiable"]}
                                                   for r in records],
                                  "maps": "eta.exr channels eta_lo, eta_hi: the interval of the "
                                          "material of the point's largest eq. 18 weight"}},
            "ks": "ks = integral (n.h) D (sec. 5.4) x specular colour, D free of the Fresnel factor"}


def fit_metrics(model: SVBRDF, samples: dict[str, np.ndarray], records: list[dict], capture: RectifiedCapture,
                settings: Settings) -> dict:
    """The fit's figures of params/metrics.json: eq. 19's samples, materials and their eta fits."""
    return {"points": capture.n_points, "representatives": model.ndf.shape[0],
            "grazing_samples": int(samples["f_m"].size), "materials": len(records),
            "materials_eta_fitted": int(sum(r["constrained"] for r in records)),
            "representatives_eta_fitted": int(sum(len(r["representatives"]) for r in records if r["constrained"])),
            "points_eta_fitted_fraction": model.info["eta"]["fitted_fraction"],
            "eta_default": settings.eta_default, "eta_bounds": list(settings.bounds),
            "eta_median": float(np.median(model.eta[capture.visible])) if capture.visible.any() else None,
            "eta_interval_method": INTERVAL_METHOD, "max_eta_interval": settings.max_eta_interval,
            "materials_eta_identifiable": int(sum(r["eta_identifiable"] for r in records)),
            "per_material": records[:200]}


def write(model: SVBRDF, inputs: Inputs, outputs: Outputs) -> None:
    """The SVBRDF folder (:mod:`facetsynth.models.svbrdf`), whole or not at all."""
    with atomic_dir(outputs.svbrdf) as staging:
        model.save(staging, provenance={"ndf": str(inputs.ndf), "neighbours": str(inputs.neighbours),
                                        "geometry": str(inputs.geometry)})


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: the pipeline's SVBRDF folder and params/metrics.json (then scored against the truth
    of a virtual capture, :func:`facetsynth.evaluation.params.truth_scores`, apart from the fit).

    Eq. 11 assumes F = 1, so the synthesized NDFs carry a Fresnel factor whose
    cosine synthesis carried along per cell (``fresnel_cosine``); eq. 19
    compares F_c(|i.h|) / F_c(that cosine) with F_m, and the NDFs are divided
    by F(cosine, eta) once eta is known, so that the model's D and ks are free
    of Fresnel and eq. 6 applies F(|i . h|, eta) at any view.
    """
    capture = RectifiedCapture.load(inputs.geometry)
    model, metrics = fit_model(load(inputs, capture), capture, settings, threads)
    write(model, inputs, outputs)
    write_json(outputs.metrics, {"ground_truth": capture.truth_scene is not None, **metrics,
                                 **truth_scores(model, capture)})


