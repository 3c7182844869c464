"""Stage ``synthesize``: complete the representatives' NDFs (paper 002 sec. 5.2-5.3).

The exemplar set is the visible points' partial NDFs (strided down to at most
``max_exemplars``) at every rotation (eq. 13). Each representative is
completed by :func:`facetsynth.fit.synthesis.complete`, with the ANN search of
sec. 5.3 (``search: ann``) or the exact search (``search: exact``); with
``compare`` the other mode is run too and both are recorded (keys suffixed
``_ann`` and ``_exact``; the unsuffixed keys are the written mode's). The
per-point complete NDF is never stored: it is sum_k weights[x, k]
ndf[neighbours[x, k]] (eq. 18, from the ``cluster`` stage). For a virtual
capture the completed NDFs are scored against the true ones
(:func:`facetsynth.evaluation.synthesize.truth_scores`, apart from the fit).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..fit import synthesis
from ..fit.cluster import material_groups
from ..io.errors import InputError
from ..io.fileio import read_exr, read_json, write_json, write_npy
from ..geometry.grid import DirectionGrid
from ..io.tables import SupportTable
from ..evaluation.synthesize import truth_scores
from .common import RectifiedCapture, RuleFiles, StageSettings, flag_degenerate, tiles

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``synthesize``'s inputs: the geometry, kd, partial NDFs and direction grid of the sample, the
    cluster stage's representatives (their pooled partial NDFs, the points' eq. 18 neighbours, weights and
    turns), and the geometry and partial NDFs of the sample's turned captures (sec. 4; lists, maybe empty)."""
    geometry: Path
    ndf: Path
    grid: Path
    representatives: Path
    neighbours: Path
    weights: Path
    kd: Path | None = None                # None: each representative is its own material
    rep_ndf: Path | None = None           # None: the representatives' own partial NDFs
    rep_confidence: Path | None = None
    rotation: Path | None = None          # None: the points' NDFs are not turned (scores only)
    rotation_geometry: tuple = ()
    rotation_ndf: tuple = ()


class Outputs(RuleFiles):
    """Rule ``synthesize``'s outputs: the completed NDFs (R, T, F), their W before push-pull, the cosine
    of the Fresnel factor each cell carries, the grid and the stage's figures."""
    ndf: Path
    confidence: Path
    fresnel_cosine: Path
    grid: Path
    metrics: Path


class Settings(StageSettings):
    """The stage's knobs: config ``synthesize`` (workflow/schemas/config.schema.yaml)."""
    search: str = "exact"             # exact: every exemplar at every rotation (FFT); ann: sec. 5.3's pruning
    compare: bool = False             # also run the other search mode and record it (_ann, _exact keys)
    n_regions: int = 20               # sampled overlap regions Omega(phi_i) (sec. 5.3's n_phi)
    buckets: int = 32                 # histogram buckets per region (sec. 5.3's m)
    candidates: int = 5               # ANN matches per region
    overlap: tuple = (0.5, 0.85)      # a candidate overlaps the current domain by this share of its own (sec. 5.2)
    target_coverage: float = 0.96     # stop when this fraction of the reachable hemisphere is covered
    max_relative_error: float = 0.4   # a best match less similar than this (eq. 15, relative) is not merged
    stalled_fraction: float = 0.5     # stalled_majority when this fraction of representatives stalls
    ann_neighbors: int = 30           # pynndescent graph degree
    ann_epsilon: float = 0.2          # pynndescent search breadth
    fill_overlap: float | None = None   # relaxed upper overlap bound for the last holes; None: the paper's rule
    isotropic_threshold: float = 0.13   # a material this close to azimuthal symmetry: completed by symmetry; 0: off
    max_exemplars: int = 4096         # (preset) exemplar points: the visible points, strided down to this many
    max_iterations: int = 12          # (preset) merges per representative at most
    seed: int = 0                     # config seed: the ANN indexes' random state
    material_tolerance: float = 0.25  # config params.material_tolerance: representatives' kd within it: one material

    def knobs(self) -> synthesis.Knobs:
        """The knobs of :func:`facetsynth.fit.synthesis.complete`."""
        return synthesis.Knobs(overlap_range=tuple(self.overlap), max_iterations=self.max_iterations,
                               target_coverage=self.target_coverage, max_relative_error=self.max_relative_error,
                               candidates_per_region=self.candidates, fill_overlap=self.fill_overlap)


@dataclass(frozen=True)
class Source:
    """One capture's share of the exemplar set (eq. 13): its partial NDF rows (D, W), the view o of every
    point, and its exemplar points."""
    d: Any
    w: Any
    view: np.ndarray      # (P, 3)
    points: np.ndarray    # (N,)


@dataclass(frozen=True)
class Data:
    """What the stage reads: the direction grid, the representatives (points (R,), partial NDFs (R, T, F),
    kd (R, 3) or None) and the exemplar sources, this capture's first."""
    grid: DirectionGrid
    representatives: np.ndarray
    rep_d: np.ndarray
    rep_w: np.ndarray
    rep_kd: np.ndarray | None
    sources: list[Source]


@dataclass(frozen=True)
class Exemplars:
    """The exemplar set (eq. 13, every rotation scored at once): D (float32, None when no representative is
    searched), W, the view of each exemplar, its point (-1: a turned capture's)."""
    d: np.ndarray | None
    w: np.ndarray
    view: np.ndarray
    index: np.ndarray


@dataclass(frozen=True)
class Prepared:
    """What every completion shares: which representatives are isotropic (and the statistics that said
    so), the exemplar set and its spectra, the view's domain Omega (Fig. 7), the reachable target, the
    overlap regions' shifts (sec. 5.3)."""
    anisotropy: np.ndarray
    material_anisotropy: dict
    isotropic: np.ndarray
    exemplars: Exemplars
    spectra: synthesis.ExemplarSpectra | None
    concentration: float | None
    mask: np.ndarray
    target: np.ndarray
    shifts: np.ndarray
    seconds: float

    @property
    def skip(self) -> bool:
        """Every representative isotropic: no exemplar set or search at all."""
        return bool(self.isotropic.all())


@dataclass(frozen=True)
class Run:
    """One search mode's completions and its times (wall, index build, process CPU)."""
    completions: list
    seconds: float
    build_seconds: float
    cpu_seconds: float


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, fit, write: the completed NDFs and synthesize/metrics.json; for a virtual capture, the scores
    against the true NDFs (:func:`facetsynth.evaluation.synthesize.truth_scores`). ``threads``: BLAS's (eq. 15's scores), which the runner
    limits."""
    if settings.search not in ("ann", "exact"):
        raise ValueError(f"synthesize.search must be 'ann' or 'exact', not {settings.search!r}")
    capture = RectifiedCapture.load(inputs.geometry)
    grid_dict = read_json(inputs.grid)
    data = load(inputs, capture, DirectionGrid.from_dict(grid_dict), settings.max_exemplars)
    runs, metrics = fit(data, settings)
    write(outputs, runs[settings.search].completions, grid_dict)
    tables = {mode: [c.ndf for c in done.completions] for mode, done in runs.items()}
    metrics.update(by_mode(truth_scores(capture, data.grid, tables, inputs.neighbours, inputs.weights,
                                        inputs.rotation), settings.search))
    metrics["ground_truth"] = capture.truth_scene is not None
    log.info("synthesize metrics: %s", {k: v for k, v in metrics.items() if not isinstance(v, list)})
    write_json(outputs.metrics, metrics)


# ---------------------------------------------------------------------------- load
def load(inputs: Inputs, capture: RectifiedCapture, grid: DirectionGrid, max_exemplars: int) -> Data:
    """The representatives and the exemplar sources: this capture's visible points and those of its turned
    captures (paper 002 sec. 4, last paragraph; ``max_exemplars`` shared evenly), so that a material whose
    frame is the same everywhere (brushed metal) finds rotated exemplars. Their rotation angles need not
    be known: eq. 14 searches every rotation anyway."""
    table = SupportTable(inputs.ndf)         # partial_ndf's D and W
    d_all, w_all = table.rows("ndf"), table.rows("confidence")
    reps = np.load(inputs.representatives)
    budget = max(2, max_exemplars // (1 + len(inputs.rotation_geometry)))
    sources = [Source(d_all, w_all, capture.view_directions(True), exemplar_pool(capture, budget))]
    sources += [turned_source(g, ndf, grid, budget) for g, ndf in zip(inputs.rotation_geometry, inputs.rotation_ndf)]
    if inputs.rep_ndf is None:      # the representatives' own partial NDFs
        rep_d, rep_w = np.asarray(d_all[reps], float), np.asarray(w_all[reps], float)
    else:                           # pooled from their clusters' members (stage cluster)
        rep_d, rep_w = np.load(inputs.rep_ndf).astype(float), np.load(inputs.rep_confidence).astype(float)
    rep_kd = None if inputs.kd is None else read_exr(inputs.kd)[0]["RGB"].reshape(-1, 3)[np.asarray(reps, np.intp)]
    return Data(grid, reps, rep_d, rep_w, rep_kd, sources)


def turned_source(geometry: Path, ndf: Path, grid: DirectionGrid, budget: int) -> Source:
    """The exemplar source of a capture of the same sample turned on the rig."""
    capture = RectifiedCapture.load(geometry)
    table = SupportTable(ndf)
    d, w = table.rows("ndf"), table.rows("confidence")
    if d.shape[1:] != grid.shape:
        raise InputError(ndf, f"partial NDFs on a {d.shape[1:]} grid; the sample's grid is {grid.shape} "
                              "(captures of one sample must share the direction grid: fix n_theta_range)")
    return Source(d, w, capture.view_directions(True), exemplar_pool(capture, budget))


def exemplar_pool(capture: RectifiedCapture, budget: int) -> np.ndarray:
    """Exemplar points of one capture: its visible points, strided down to at most ``budget``."""
    visible = np.flatnonzero(capture.visible)
    return visible[:: max(1, int(np.ceil(visible.size / budget)))]


# ---------------------------------------------------------------------------- fit
def fit(data: Data, settings: Settings) -> tuple[dict[str, Run], dict]:
    """Every representative completed in the written search mode (and, with ``compare``, the other):
    the runs by mode and the fit's figures."""
    prepared = prepare(data, settings)
    modes = [settings.search] + ([{"ann": "exact", "exact": "ann"}[settings.search]] if settings.compare else [])
    runs = {mode: complete_all(mode, data, prepared, settings) for mode in modes}
    return runs, fit_metrics(data, prepared, runs, settings)


def prepare(data: Data, settings: Settings) -> Prepared:
    """Isotropy per material (:func:`isotropy`), the exemplar set and its spectra (none when every
    representative is isotropic), the view's domain Omega (cells inside the domain of most exemplars,
    Fig. 7), what rotations reach of the hemisphere, and the overlap regions' shifts (sec. 5.3)."""
    t0, grid = time.perf_counter(), data.grid
    stat, material_stat, isotropic = isotropy(data, settings)
    skip = bool(isotropic.all())
    exemplars = exemplar_set(data.sources, skip)
    spectra = None if skip else synthesis.ExemplarSpectra(exemplars.d, exemplars.w, grid, exemplars.index)
    concentration = None if skip else orientation_concentration(exemplars, grid, settings.isotropic_threshold)
    mask = np.median(exemplars.w > synthesis.SUPPORT, axis=0) > 0.5           # the view's domain Omega (Fig. 7)
    target = synthesis.hemisphere_target(mask, grid)
    shifts = synthesis.region_shifts(mask, grid, settings.n_regions, *settings.overlap)
    log.info("%d exemplars x %d rotations; domain %.1f %% of the hemisphere, rotations reach %.1f %%; "
             "%d overlap regions, shifts %s sectors", exemplars.index.size, grid.n_phi,
             100 * hemisphere_fraction(mask, grid), 100 * hemisphere_fraction(target, grid), shifts.size,
             np.unique(np.round(shifts)).astype(int).tolist())
    return Prepared(stat, material_stat, isotropic, exemplars, spectra, concentration, mask, target, shifts,
                    time.perf_counter() - t0)


def isotropy(data: Data, settings: Settings) -> tuple[np.ndarray, dict, np.ndarray]:
    """Isotropy is a property of the material: representatives are grouped into materials by kd
    (:func:`facetsynth.fit.cluster.material_groups`, as in ``params``; without kd each representative decides
    alone), and a material whose representatives' partial NDFs deviate from azimuthal symmetry by less
    than ``isotropic_threshold`` in the median (relative L2, :func:`facetsynth.fit.synthesis.anisotropy`; one
    representative alone is noisy when its lobe is narrower than a ring) is isotropic: its representatives
    are completed by azimuthal symmetry (:func:`facetsynth.fit.synthesis.complete_isotropic`), without a
    search. Returns each representative's statistic, each material's median, and the isotropic ones."""
    stat = synthesis.anisotropy(data.rep_d, data.rep_w, data.grid)
    material = (np.arange(len(data.representatives)) if data.rep_kd is None
                else material_groups(data.rep_kd, settings.material_tolerance))
    threshold = settings.isotropic_threshold
    material_stat = {int(m): float(np.median(stat[material == m])) for m in np.unique(material)}
    isotropic = np.array([material_stat[int(m)] < threshold for m in material], bool)
    log.info("isotropy: %d of %d representatives isotropic, %d of %d materials (median relative L2 deviation "
             "from ring means and first azimuthal harmonic per material below %.3f: %s; per representative min %.3f, "
             "median %.3f, max %.3f)%s", isotropic.sum(), len(data.representatives),
             sum(v < threshold for v in material_stat.values()), len(material_stat), threshold,
             {m: round(v, 3) for m, v in material_stat.items()}, stat.min(initial=np.inf), np.median(stat) if stat.size
             else np.nan, stat.max(initial=-np.inf),
             ": all complete by azimuthal symmetry, no exemplar search" if isotropic.all() else "")
    return stat, material_stat, isotropic


def exemplar_set(sources: list[Source], skip: bool) -> Exemplars:
    """The exemplar points' partial NDFs of every source, joined (D only when some representative is
    searched: ``skip`` False)."""
    index = np.concatenate([sources[0].points] + [np.full(s.points.size, -1) for s in sources[1:]])
    view = np.concatenate([s.view[s.points] for s in sources])
    w = np.concatenate([np.asarray(s.w[s.points], np.float32) for s in sources])
    d = None if skip else np.concatenate([np.asarray(s.d[s.points], np.float32) for s in sources])
    return Exemplars(d, w, view, index)


def orientation_concentration(exemplars: Exemplars, grid: DirectionGrid, isotropic_threshold: float) -> float | None:
    """:func:`facetsynth.fit.synthesis.orientation_concentration` over the exemplars whose partial NDF is
    anisotropic (:func:`facetsynth.fit.synthesis.anisotropy` >= ``isotropic_threshold``); None without any."""
    axes = []
    for t in tiles(len(exemplars.d), 512):
        d, w = np.asarray(exemplars.d[t], float), np.asarray(exemplars.w[t], float)
        axes.append(synthesis.orientation(d, w, grid)[synthesis.anisotropy(d, w, grid) >= isotropic_threshold])
    axes = np.concatenate(axes) if axes else np.zeros(0, complex)
    value = synthesis.orientation_concentration(axes)
    return None if not np.isfinite(value) else value


def complete_all(mode: str, data: Data, prepared: Prepared, settings: Settings) -> Run:
    """Every representative completed with search ``mode``: isotropic ones by azimuthal symmetry, the others
    by :func:`facetsynth.fit.synthesis.complete` (sec. 5.2; ``ann``: sec. 5.3's index, :func:`ann_index`)."""
    t0, c0 = time.perf_counter(), time.process_time()
    index = ann_index(prepared, data.grid, settings) if mode == "ann" and not prepared.skip else None
    build = 0.0 if index is None else index.build_seconds
    knobs, ex = settings.knobs(), prepared.exemplars
    out = []
    for i, r in enumerate(data.representatives):
        view = data.sources[0].view[r]
        if prepared.isotropic[i]:
            out.append(synthesis.complete_isotropic(data.rep_d[i], data.rep_w[i], data.grid, prepared.target,
                                                    view=view))
        else:
            out.append(synthesis.complete(data.rep_d[i], data.rep_w[i], prepared.spectra, ex.d, ex.w, data.grid,
                                          prepared.target, knobs, search=index, view=view, exemplars_view=ex.view))
    done = Run(out, time.perf_counter() - t0, build, time.process_time() - c0)
    log.info("%s search: %d representatives in %.1f s (index build %.1f s)", mode, len(out), done.seconds, build)
    return done


def ann_index(prepared: Prepared, grid: DirectionGrid, settings: Settings) -> synthesis.HistogramSearch | None:
    """Sec. 5.3's histogram keys and pynndescent indexes over the overlap regions; None (the exact search)
    when no rotation overlaps as ``overlap`` asks."""
    if prepared.shifts.size == 0:
        log.warning("no rotation gives a %.0f-%.0f %% overlap: ANN search disabled, exact search used",
                    100 * settings.overlap[0], 100 * settings.overlap[1])
        return None
    return synthesis.HistogramSearch(prepared.exemplars.d, prepared.mask, grid, prepared.shifts,
                                     buckets=settings.buckets, seed=settings.seed, n_neighbors=settings.ann_neighbors,
                                     epsilon=settings.ann_epsilon)


def hemisphere_fraction(cells: np.ndarray, grid: DirectionGrid) -> float:
    """The fraction of the hemisphere (2 pi sr) that ``cells`` (T, F) bool cover."""
    return float(np.sum(cells * grid.solid_angles) / (2 * np.pi))


def fit_metrics(data: Data, prepared: Prepared, runs: dict[str, Run], settings: Settings) -> dict:
    """The fit's figures: the exemplar set and domain, isotropy, each mode's completions (:func:`summary`;
    by :func:`by_mode`), and rotation diversity (:func:`flag_rotation_diversity`)."""
    grid, target, shifts, stat = data.grid, prepared.target, prepared.shifts, prepared.anisotropy
    metrics = {"representatives": int(len(data.representatives)),
               "exemplars": 0 if prepared.skip else int(prepared.exemplars.index.size),
               "rotation_captures": len(data.sources) - 1, "search": settings.search,
               "regions": int(shifts.size), "region_shifts_sectors": np.unique(np.round(shifts)).astype(int).tolist(),
               "overlap_range": list(settings.overlap), "max_relative_error": settings.max_relative_error,
               "domain_fraction_of_hemisphere": hemisphere_fraction(prepared.mask, grid),
               "reachable_fraction_of_hemisphere": hemisphere_fraction(target, grid),
               "reachable_max_theta_deg": float(np.degrees((np.flatnonzero(target[:, 0]).max() + 1) * grid.d_theta))
               if target.any() else 0.0,
               "prepare_seconds": round(prepared.seconds, 2),
               "isotropic_threshold": settings.isotropic_threshold,
               "isotropic_representatives": int(prepared.isotropic.sum()), "search_skipped": prepared.skip,
               "anisotropy": [round(float(x), 4) for x in stat],
               "anisotropy_median": float(np.median(stat)) if stat.size else None,
               "materials": len(prepared.material_anisotropy),
               "material_anisotropy": [round(v, 4) for v in prepared.material_anisotropy.values()]}
    metrics.update(by_mode({mode: summary(done, settings.stalled_fraction) for mode, done in runs.items()},
                           settings.search))
    flag_rotation_diversity(metrics, prepared.concentration, settings.max_relative_error)
    return metrics


def summary(done: Run, stalled_fraction: float) -> dict:
    """One mode's completions: coverage before fill, iterations, stalls, merges and their relative error
    (eq. 15), the exact search's stand-ins, times."""
    comps = done.completions
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
            "seconds": round(done.seconds, 2), "index_build_seconds": round(done.build_seconds, 2),
            "cpu_seconds": round(done.cpu_seconds, 2)}    # process CPU time: comparable under a loaded machine


def by_mode(figures: dict[str, dict], search: str) -> dict:
    """Each mode's figures under keys suffixed ``_ann`` or ``_exact``; the written mode's (``search``) also
    unsuffixed."""
    out = {}
    for mode, values in figures.items():
        for key, value in values.items():
            out[f"{key}_{mode}"] = value
            if mode == search:
                out[key] = value
    return out


def flag_rotation_diversity(metrics: dict, concentration: float | None, max_relative_error: float) -> None:
    """``orientation_concentration`` and ``insufficient_rotation_diversity`` in ``metrics``, and a
    DEGENERATE warning for it or for a majority of stalled representatives. Rotation diversity is decided
    from the exemplars' lobe axes: one axis everywhere is insufficient even where broad lobes match
    themselves at wrong rotations (then few representatives stall), and stalls alone also come from noise
    (wallpaper with sensor noise: 17 of 32). docs/decisions.md."""
    metrics["orientation_concentration"] = concentration
    metrics["insufficient_rotation_diversity"] = bool(concentration is not None
                                                      and concentration >= synthesis.SINGLE_ORIENTATION)
    stalled = f"{metrics['stalled_representatives']} of {metrics['representatives']} representatives stalled"
    if metrics["insufficient_rotation_diversity"]:
        flag_degenerate(metrics, f"INSUFFICIENT ROTATION DIVERSITY: the anisotropic exemplars' lobe axes all point "
                        f"one way (concentration {concentration:.2f} >= {synthesis.SINGLE_ORIENTATION:.2f}), so no "
                        f"exemplar shows this material at another rotation; {stalled} (no match within relative error "
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


# ---------------------------------------------------------------------------- write
def write(outputs: Outputs, completions: list, grid_dict: dict) -> None:
    """ndf (R, T, F), its W before fill, the cosine of the Fresnel factor each cell carries (see
    :func:`facetsynth.fit.synthesis.complete`), all float32, and the direction grid."""
    write_npy(outputs.ndf, np.stack([c.ndf for c in completions]).astype(np.float32))
    write_npy(outputs.confidence, np.stack([c.confidence for c in completions]).astype(np.float32))
    write_npy(outputs.fresnel_cosine, np.stack([c.fresnel_cosine for c in completions]).astype(np.float32))
    write_json(outputs.grid, grid_dict)



