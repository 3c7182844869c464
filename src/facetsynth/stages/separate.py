"""Stage ``separate``: shading normals, BRDF samples (eq. 8), diffuse kd (eq. 9), the specular residual (paper
002 sec. 4).

Real samples have relief. Each point's shading normal n(x) comes first, by robust photometric stereo on the
diffuse part (:func:`facetsynth.fit.normals.estimate`: highlights and shadows trimmed); eq. 8 is then read in the
point's frame, rho = I |P - x|^2 / (L n(x) . i), and so is everything after: the stage writes rectify's
geometry with the normals (``separate/geometry.json``), which every later stage reads
(:class:`~facetsynth.stages.common.RectifiedCapture`). Cast shadows, samples far darker than the diffuse
part predicts, are invalid: masked, not fitted.

A capture that states no light intensities (an ``.lp`` without them: ``assumed`` lists ``intensities``) gets
them from its own photos: a robust RGB factor per light from the diffuse part
(:func:`facetsynth.fit.light_factors.estimate`, the mean factor of each channel fixed to 1). The samples are
divided by it, and ``separate/geometry.json`` carries the corrected intensities to every later stage. Held-out
lights are not seen: their factors are their neighbours' on the sphere (fill_from_neighbours).
"""

from __future__ import annotations

import copy
import logging
import os
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..fit import light_factors
from ..evaluation.separate import truth_scores
from ..io.colour import channel_mean
from ..io.fileio import atomic_path, read_frame, read_json, write_exr, write_json, write_npy
from ..io.half import HALF, as_half
from ..io.errors import InputError
from ..io.frames import imap, map_frames
from ..fit.light_factors import Factors, fill_from_neighbours
from ..fit.normals import (FLAT, HIGHLIGHT_CONTRAST, diffuse_enough, highlight_normals, photometric_normals,
                           relief_normals)
from ..models.microfacet import half_vector
from ..models.render import light_geometry, towards
from ..evaluation.selfcheck import heldout_lights
from ..fit.separation import brdf_samples, diffuse_level, specular_residual
from .common import RectifiedCapture, RuleFiles, StageSettings, flag_degenerate, strided, tiles

log = logging.getLogger(__name__)

# A point shows specular signal when its brightest specular residual is at least SIGNAL_RATIO of its diffuse
# level rho_d (channel means): a highlight half as bright as the diffuse reflection. Sensor noise alone stays far
# below: a matte sample (ks = 0) on the tiny rig with noise gives 0.03-0.07 (1-99 % of points), the glossy card
# 0.14-20 (73 % of points above 0.5), the card under its 4 corner lights alone 0.02-0.76 (5 %).
SIGNAL_RATIO = 0.5
# Fewer points than this fraction with specular signal: a matte sample, or lights that miss every highlight;
# a diffuse-only model is all the capture supports. Black markers, dust and dead pixels stay below it.
MIN_SIGNAL_FRACTION = 0.01
FRAME_BLOCK = 32    # frames read before their samples are written, as one contiguous block (FrameBlocks)
# A sample whose luminance is below CAST_SHADOW x what the point's diffuse part predicts, (kd/pi) n . i, lies in a
# cast shadow of the relief (or is occluded): invalid. Sensor noise and the darkest diffuse samples stay above it.
CAST_SHADOW = 0.5
# AUTO_NORMALS: "auto" estimates normals under directional lights (a dome: a top-down camera, lights all round)
# and not on a rig of point lights seen obliquely: there the demo's turned copper, whose anisotropic lobes
# stretch beyond LOBE_DEG, came out tilted by up to 10 deg (95th percentile) on a flat sample
# (docs/decisions.md, "Shading normals"); config true forces them.
FACTOR_POINTS = 20_000   # points the lights' intensity factors are estimated from (evenly strided)
FACTORS_DEFINITION = ("per light, the RGB factor f by which its intensity differs from the nominal one, from the "
                      "photos' diffuse part (b = f kd/pi n.i, robust rank-1 fit; facetsynth.fit.light_factors); the mean "
                      "of each channel's factors over the estimated lights is 1; fallback lights (held out, or too "
                      "few usable points) take their neighbours' on the sphere (facetsynth.fit.light_factors."
                      "fill_from_neighbours); spread: the robust dispersion of a light's ratios")
# n . i below this: the light grazes the point's own facet; eq. 8 would divide by ~0 (invalid, as below the plane)
MIN_COS = 1e-3


class Inputs(RuleFiles):
    """Rule ``separate``'s inputs: rectify's geometry and its frames (read through the geometry's file names)."""
    geometry: Path
    frames: Path | None = None


class Outputs(RuleFiles):
    """Rule ``separate``'s outputs: kd, the specular residual and its validity, the stage's figures; the shading
    normals and rectify's geometry with them (the later stages' geometry; None: not written)."""
    kd: Path
    specular: Path
    valid: Path
    metrics: Path
    geometry: Path | None = None
    normals: Path | None = None


class Settings(StageSettings):
    """The stage's knobs: config ``separate`` (workflow/schemas/config.schema.yaml)."""
    threshold: float = 0.05   # eq. 9: samples darker than threshold x the point's average intensity are left out
    lowest: float = 0.03      # eq. 9 averages this fraction of the qualifying samples, those of lowest channel
                              # mean (0: eq. 9's minimum, per channel)
    heldout_every: int = 10   # config selfcheck.heldout_every: every k-th frame's samples are invalid, so that no
                              # later stage sees those lights (facetsynth.evaluation.selfcheck.heldout_lights; 0: none)
    shading_normals: bool | str = "auto"   # a normal per point (photometric stereo): "auto" for directional lights
                                           # (a dome) only (AUTO_NORMALS), True always, False: the plane's +z


class Separated(NamedTuple):
    """What :func:`fit` returns beside the tables it writes: kd (P, 3), which points show specular signal (P,),
    the shading normals (P, 3) and the lights' estimated intensity factors (None when they were stated)."""
    kd: np.ndarray
    signal: np.ndarray
    normals: np.ndarray
    factors: Factors | None


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, separate, write: per point and light of ``inputs.geometry``, rho by eq. 8, kd = pi rho_d by eq. 9
    (:func:`~facetsynth.fit.separation.diffuse_level`), rho~_s = rho - rho_d; for a virtual capture, kd scored
    against the truth (:func:`facetsynth.evaluation.separate.truth_scores`).

    Writes ``kd`` (EXR on the rectified grid), the specular residual (P, F, 3) in half floats
    (:func:`~facetsynth.io.half.as_half`) and the sample validity (P, F) as bits (P, ceil(F / 8)) uint8
    (:class:`facetsynth.io.fileio.BitRows`), memory-mappable .npy (frames are streamed in; memory does not grow
    with the sample size).
    Invalid samples: saturated, a point outside the camera's view, a light held out for the self-check
    (``settings.heldout_every``), a light at or behind the point's facet, or a cast shadow (CAST_SHADOW).
    Frames are read on ``threads`` threads. ``outputs.normals``: the shading normals (P, 3) float32 .npy;
    ``outputs.geometry``: rectify's geometry with them (the later stages' geometry).
    """
    capture, g = load(inputs)
    settings = replace(settings, shading_normals=uses_normals(settings.shading_normals, capture))
    separated = fit(capture, settings, outputs.specular, outputs.valid, threads,
                    intensities_from=g if estimates_intensities(g) else None)
    write(separated, capture, g, inputs, outputs, settings.lowest)
    write_json(outputs.metrics, {"ground_truth": capture.truth_scene is not None,
                                 **fit_metrics(separated, capture, g, settings), **truth_scores(separated.kd, capture)})


# ---------------------------------------------------------------------------- load
def load(inputs: Inputs) -> tuple[RectifiedCapture, dict]:
    """rectify's geometry: the capture (:class:`~facetsynth.stages.common.RectifiedCapture`) and the file as
    read (written again with the normals, :func:`_write_geometry`)."""
    return RectifiedCapture.load(inputs.geometry), read_json(inputs.geometry)


def estimates_intensities(g: dict) -> bool:
    """Whether the stage estimates the lights' intensities (module docstring): the geometry ``g`` of a capture
    that states none (``assumed`` lists ``intensities``), or names a ``reference_region``."""
    return "reference_region" in g or "intensities" in g.get("assumed", [])


def uses_normals(setting: bool | str, capture: RectifiedCapture) -> bool:
    """Whether the stage estimates shading normals: config ``separate.shading_normals``, "auto" (AUTO_NORMALS)
    for captures whose every light is directional."""
    if setting == "auto":
        return bool(np.all(capture.lights[:, 3] == 0))
    return bool(setting)


# ---------------------------------------------------------------------------- separate
def fit(capture: RectifiedCapture, settings: Settings, specular_out: str | Path, valid_out: str | Path,
        threads: int = 1, intensities_from: dict | None = None) -> Separated:
    """The separation: eq. 8's samples (:func:`eq8_samples`), the shading normals (:func:`shading_normals`,
    with ``settings.shading_normals``), the lights' intensity factors (:func:`_light_factors`; only with
    ``intensities_from``, the geometry of a capture without intensities: from its ``reference_region`` when it
    names one, else from the whole sample), eq. 9 (:func:`eq9_residuals`). The specular residual and the
    validity tables are written as they are made, each whole or not at all, to ``specular_out`` and
    ``valid_out``; eq. 8's samples in float32 beside them (:class:`FrameBlocks`, a temporary: swept if this
    process dies), so that eq. 9's kd is not rounded to half floats."""
    with atomic_path(specular_out, suffix=".npy") as tmp_spec, atomic_path(valid_out, suffix=".npy") as tmp_valid:
        scratch = tmp_spec.with_name(tmp_spec.name + ".eq8")
        try:
            return _separate(capture, settings, threads, scratch, tmp_spec, tmp_valid, intensities_from)
        finally:
            for path in FrameBlocks.files(scratch):
                path.unlink(missing_ok=True)


def _separate(capture: RectifiedCapture, settings: Settings, threads: int, scratch: Path, specular_out: Path,
              valid_out: Path, intensities_from: dict | None = None) -> Separated:
    """:func:`fit` into the files ``scratch`` (eq. 8, :class:`FrameBlocks`), ``specular_out`` and ``valid_out``."""
    samples = eq8_samples(capture, heldout_lights(len(capture.frame_files), settings.heldout_every), scratch,
                          threads)
    n_points = capture.n_points
    normals, albedo = np.tile(FLAT, (n_points, 1)), np.zeros(n_points)
    diffuse = np.zeros(n_points, bool)        # points that tell their normal from the diffuse part
    if settings.shading_normals:
        normals, albedo, diffuse = shading_normals(capture, samples, threads)
    factors = None
    if intensities_from is not None:
        factors = _light_factors(samples, capture, normals, capture.visible & diffuse,
                                 intensities_from.get("reference_region"))
    kd, signal = eq9_residuals(capture, settings, samples, normals, albedo, factors, specular_out, valid_out, threads)
    return Separated(kd, signal, normals, factors)


class FrameBlocks:
    """Eq. 8's samples rho (P, F, 3) float32 and their validity (P, F), kept as blocks of FRAME_BLOCK frames:
    two files, (blocks, P, FRAME_BLOCK, 3) and (blocks, P, FRAME_BLOCK), at ``scratch`` + ".rho.npy" and
    ".valid.npy" (the last block padded).

    - A block of frames is written once, as one contiguous stretch of each file. In (P, F, 3) order a block is
      a block of columns, which touches every page of the file: at 800^2 x 480 each of the 15 blocks dirtied the
      whole 3.7 GB again, and the process wrote 62 GB for it (6.2 GB now, with the outputs).
    - Each :meth:`put` and :meth:`rows` maps the files for the call alone: the pages stay in the page cache, not
      in the process's resident memory, and nothing forces them to the disk (a scratch deleted before the
      kernel writes it back is never written)."""

    def __init__(self, scratch: Path, n_points: int, n_frames: int):
        blocks = -(-n_frames // FRAME_BLOCK)
        self.paths = self.files(scratch)
        for path, dtype, shape in zip(self.paths, (np.float32, bool), ((blocks, n_points, FRAME_BLOCK, 3),
                                                                       (blocks, n_points, FRAME_BLOCK))):
            np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)    # the file made, not mapped on
        self.n_frames = n_frames

    @staticmethod
    def files(scratch: Path) -> tuple[Path, Path]:
        return scratch.with_name(scratch.name + ".rho.npy"), scratch.with_name(scratch.name + ".valid.npy")

    def put(self, first: int, block: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """The samples (P, 3) and validity (P,) of frames ``first``, ``first`` + 1, ... (``first`` starts a block)."""
        k, n = first // FRAME_BLOCK, len(block)
        rho, valid = (np.load(path, mmap_mode="r+") for path in self.paths)
        rho[k, :, :n] = np.stack([s for s, _ in block], axis=1)
        valid[k, :, :n] = np.stack([v for _, v in block], axis=1)

    def rows(self, points) -> tuple[np.ndarray, np.ndarray]:
        """rho (p, F, 3) float32 and validity (p, F) of ``points`` (a slice or indices): copies, read block by
        block."""
        rho, valid = (np.load(path, mmap_mode="r")[:, points] for path in self.paths)
        p = rho.shape[1]
        return (np.array(rho.transpose(1, 0, 2, 3).reshape(p, -1, 3)[:, :self.n_frames]),
                np.array(valid.transpose(1, 0, 2).reshape(p, -1)[:, :self.n_frames]))


def eq8_samples(capture: RectifiedCapture, held: np.ndarray, scratch: Path, threads: int = 1) -> FrameBlocks:
    """Eq. 8 frame by frame, with the plane's normal: rho (P, F, 3) float32 and the samples' validity (P, F):
    visible, not saturated, not a ``held`` light; memory-mapped at ``scratch`` (:class:`FrameBlocks`). Frames
    are read on ``threads`` threads and written FRAME_BLOCK at a time."""
    n_points, n_frames = capture.n_points, len(capture.frame_files)
    points = capture.points
    samples = FrameBlocks(scratch, n_points, n_frames)

    def frame_samples(q: int) -> tuple[np.ndarray, np.ndarray]:
        radiance, saturated = read_frame(capture.frame_files[q])
        sample, _ = brdf_samples(radiance.reshape(-1, 1, 3), points,
                                 capture.lights[q:q + 1], capture.light_intensities[q:q + 1])
        return sample[:, 0].astype(np.float32), capture.visible & ~saturated.ravel() & ~held[q]

    block = []
    for q, frame in enumerate(imap(frame_samples, range(n_frames), threads, "separate: eq. 8")):
        block.append(frame)
        if len(block) == FRAME_BLOCK or q == n_frames - 1:
            samples.put(q + 1 - len(block), block)
            block = []
    return samples


def shading_normals(capture: RectifiedCapture, samples: FrameBlocks, threads: int = 1) -> tuple[np.ndarray, ...]:
    """The shading normals (P, 3) from eq. 8's ``samples`` and their validity, tile by tile on ``threads``
    threads: robust photometric stereo on the diffuse part where it tells (:func:`facetsynth.fit.normals.
    photometric_normals`, ``diffuse``), else the highlights' where they glint (:func:`facetsynth.fit.normals.
    highlight_normals`), then the relief's common tilt removed (:func:`facetsynth.fit.normals.relief_normals`).
    Returns the normals, the diffuse part's albedo (P,) and ``diffuse`` (P,) bool; logged."""
    n_points, points = capture.n_points, capture.points
    normals, albedo = np.tile(FLAT, (n_points, 1)), np.zeros(n_points)
    glints, contrast = np.tile(FLAT, (n_points, 1)), np.zeros(n_points)

    def normal_tile(tile: slice) -> None:
        wi, _ = light_geometry(points[tile][:, None, :], capture.lights[None])
        rho, ok = samples.rows(tile)
        b = np.asarray(rho, float) * np.clip(wi[..., 2], 0.0, None)[..., None]
        view = towards(points[tile], capture.view_point)
        normals[tile], albedo[tile] = photometric_normals(b, wi, view, ok)
        glints[tile], contrast[tile] = highlight_normals(b, half_vector(wi, view[:, None, :]), ok)

    map_frames(normal_tile, list(tiles(n_points)), threads, "separate: shading normals", unit="tile")
    diffuse = diffuse_enough(albedo)
    glinting = contrast >= HIGHLIGHT_CONTRAST
    normals[:] = np.where((~diffuse & glinting)[:, None], glints, normals)
    normals[:], relief = relief_normals(normals, capture.visible & (diffuse | glinting))
    log.info("shading normals from the diffuse part at %.0f %% of the points, from highlights at %.0f %%",
             100 * np.mean(diffuse[capture.visible]), 100 * np.mean((~diffuse & glinting)[capture.visible]))
    log.info("shading normals: %s", relief)
    return normals, albedo, diffuse


def eq9_residuals(capture: RectifiedCapture, settings: Settings, samples: FrameBlocks, normals: np.ndarray,
                  albedo: np.ndarray, factors: Factors | None, specular_out: Path, valid_out: Path,
                  threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 9 tile by tile on ``threads`` threads: eq. 8's ``samples`` divided by the lights' ``factors``
    (if any), re-read in each point's shading frame (with ``settings.shading_normals``: :func:`_in_shading_frame`,
    which also narrows their validity), kd = pi rho_d (:func:`facetsynth.fit.separation.diffuse_level`), the
    specular residual rho - rho_d in half floats into ``specular_out`` (P, F, 3) and the validity into
    ``valid_out`` (P, F) as bits (:class:`facetsynth.io.fileio.BitRows`). Returns kd (P, 3) and which points show
    specular signal (P,): a residual of at least SIGNAL_RATIO x the diffuse level."""
    n_points, n_frames = capture.n_points, len(capture.frame_files)
    points = capture.points
    kd = np.zeros((n_points, 3))
    signal = np.zeros(n_points, bool)
    scale = np.ones((n_frames, 3)) if factors is None else factors.rgb
    residuals = np.lib.format.open_memmap(specular_out, mode="w+", dtype=HALF, shape=(n_points, n_frames, 3))
    valid = np.lib.format.open_memmap(valid_out, mode="w+", dtype=np.uint8,      # as bits: io.fileio.BitRows
                                      shape=(n_points, -(-n_frames // 8)))

    def separate_tile(tile: slice) -> None:
        rho_tile, ok = samples.rows(tile)
        rho_tile = np.asarray(rho_tile, float) / scale[None]
        wi, r2 = light_geometry(points[tile][:, None, :], capture.lights[None])
        cos = np.einsum("pfk,pk->pf", wi, normals[tile])
        if settings.shading_normals:
            rho_tile, ok = _in_shading_frame(rho_tile, wi, cos, albedo[tile], ok)
        valid[tile] = np.packbits(ok, axis=1)
        radiance = rho_tile * (np.clip(cos, 0, None) / r2)[..., None] * (capture.light_intensities * scale)[None]
        rho_d = diffuse_level(rho_tile, radiance, ok, settings.threshold, settings.lowest)
        kd[tile] = np.pi * rho_d
        residual = specular_residual(rho_tile, rho_d)
        residuals[tile] = as_half(residual)
        peak = np.where(ok, channel_mean(residual), 0.0).max(axis=1, initial=0.0)
        diffuse = channel_mean(rho_d)
        signal[tile] = (diffuse > 0) & (peak >= SIGNAL_RATIO * diffuse)

    map_frames(separate_tile, list(tiles(n_points)), threads, "separate: eq. 9", unit="tile")
    residuals.flush()
    valid.flush()
    return kd, signal


# ---------------------------------------------------------------------------- write
def write(separated: Separated, capture: RectifiedCapture, g: dict, inputs: Inputs, outputs: Outputs,
          lowest: float) -> None:
    """The shading normals (``outputs.normals``), rectify's geometry ``g`` with them and the estimated
    intensities (``outputs.geometry``, :func:`_write_geometry`; each None: not written) and kd (EXR on the
    rectified grid; eq. 9 with the ``lowest`` share of the samples, settings.lowest)."""
    if outputs.normals is not None:
        write_npy(outputs.normals, separated.normals.astype(np.float32))
    if outputs.geometry is not None:
        _write_geometry(g, Path(inputs.geometry).parent, outputs.geometry, outputs.normals, separated.factors)
    write_exr(outputs.kd, {"RGB": separated.kd.reshape(capture.grid.rows, capture.grid.cols, 3)},
              {"quantity": "kd (diffuse albedo), paper 002 eq. 9" + (
                  f" (the mean of the lowest {100 * lowest:g} % of the qualifying samples)" if lowest else "")})


def fit_metrics(separated: Separated, capture: RectifiedCapture, g: dict, settings: Settings) -> dict:
    """The separation's figures of separate/metrics.json: the points without a diffuse estimate, the normals'
    tilt, the lights' factors (logged), the fraction of lit points with specular signal (``degenerate`` below
    MIN_SIGNAL_FRACTION)."""
    kd, factors, n_frames = separated.kd, separated.factors, len(capture.frame_files)
    metrics = {"points": capture.n_points, "frames": n_frames, "threshold": settings.threshold,
               "lowest": settings.lowest, "heldout_frames": int(heldout_lights(n_frames, settings.heldout_every).sum()),
               "points_without_diffuse_estimate": int((kd.sum(axis=1) == 0).sum()),
               "shading_normals": settings.shading_normals, **_normal_metrics(separated.normals, capture)}
    if factors is not None:
        metrics["light_factors"] = {"rgb": factors.rgb.round(4).tolist(), "spread": factors.spread.round(4).tolist(),
                                    "fallback": factors.fallback.tolist(), "definition": FACTORS_DEFINITION,
                                    "from": ("the reference region " + str(g["reference_region"])
                                             if "reference_region" in g else "the whole sample's diffuse part")}
        log.info("light factors (estimated, mean 1 per channel): luminance %.3f-%.3f, %d light(s) from their "
                 "neighbours",
                 factors.rgb.mean(axis=1)[~factors.fallback].min(initial=1.0),
                 factors.rgb.mean(axis=1)[~factors.fallback].max(initial=1.0), int(factors.fallback.sum()))
    lit = capture.visible & (kd.sum(axis=1) > 0)
    metrics["specular_signal_fraction"] = float(separated.signal[lit].mean()) if lit.any() else 0.0
    if metrics["specular_signal_fraction"] < MIN_SIGNAL_FRACTION:
        flag_degenerate(metrics, f"no specular signal: {100 * metrics['specular_signal_fraction']:.1f} % of the "
                        f"lit points have a highlight of at least {SIGNAL_RATIO} x their diffuse level (needed: "
                        f"{100 * MIN_SIGNAL_FRACTION:.0f} %); the sample is matte under these lights, or the lights "
                        "miss its highlights: only kd is supported by the capture, the specular fit is noise", log)
    return metrics


# ---------------------------------------------------------------------------- helpers
def _light_factors(samples: FrameBlocks, capture: RectifiedCapture, normals: np.ndarray, trusted: np.ndarray,
                   reference: dict | None = None):
    """The lights' RGB factors (:func:`facetsynth.fit.light_factors.estimate`) from eq. 8's ``samples``
    of evenly strided ``trusted`` points (diffuse enough to have a normal): b = rho (+z . i) against the
    diffuse shading n . i; or, with a ``reference`` box {"x": [x0, x1], "y": [y0, y1]} (metres), from the
    points in it (:func:`facetsynth.fit.light_factors.reference_region`). Only the valid samples take part
    (held-out lights: none; their factors are their neighbours')."""
    if reference is not None:
        x, y = capture.points[:, 0], capture.points[:, 1]
        inside = capture.visible & (x >= reference["x"][0]) & (x <= reference["x"][1]) \
            & (y >= reference["y"][0]) & (y <= reference["y"][1])
        index = strided(np.flatnonzero(inside), FACTOR_POINTS)
        if index.size == 0:
            raise InputError(None, f"the reference region {reference} holds none of the sample's visible points")
    else:
        index = strided(np.flatnonzero(trusted), FACTOR_POINTS)
    if index.size == 0:
        index = strided(np.flatnonzero(capture.visible), FACTOR_POINTS)
    wi, _ = light_geometry(capture.points[index][:, None, :], capture.lights[None])
    rho, ok = samples.rows(index)
    b = np.asarray(rho, float) * np.clip(wi[..., 2], 0.0, None)[..., None]
    shading = np.einsum("pfk,pk->pf", wi, normals[index])
    if reference is not None:
        rgb = light_factors.reference_region(b, shading, ok, np.ones(len(index), bool))
        found = Factors(rgb=rgb, points_used=np.full(len(rgb), len(index)), spread=np.zeros(len(rgb)),
                        fallback=~ok.any(axis=0) | np.all(rgb == 1.0, axis=1))
    else:
        found = light_factors.estimate(b, shading, ok)
    return filled_from_neighbours(found, capture.lights, capture.points[capture.visible].mean(axis=0)
                                  if capture.visible.any() else np.zeros(3))


def filled_from_neighbours(found: Factors, lights: np.ndarray, centre: np.ndarray) -> Factors:
    """``found`` with the fallback (held-out) lights' factors taken from their neighbours on the sphere of
    directions seen from the sample's ``centre`` (3,) (:func:`facetsynth.fit.light_factors.fill_from_neighbours`):
    a directional light's direction, a point light's direction from the centre. ``lights`` (F, 4) homogeneous."""
    directions, _ = light_geometry(np.asarray(centre, float)[None, None, :], np.asarray(lights, float)[None])
    return replace(found, rgb=fill_from_neighbours(directions[0, :, :], found.rgb, found.fallback))


def _in_shading_frame(rho: np.ndarray, wi: np.ndarray, cos: np.ndarray, albedo: np.ndarray,
                      valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8's samples of points (p, F, 3), read with the plane's normal, re-read in each point's shading frame,
    rho = b / (n . i), b = rho (+z . i) (``cos`` (p, F) = n . i); and their validity: samples at or behind the
    point's facet (n . i < MIN_COS) and in cast shadows (luminance below CAST_SHADOW x the diffuse part's
    albedo n . i) are invalid."""
    b = rho * np.clip(wi[..., 2], 0.0, None)[..., None]
    valid = valid & (cos > MIN_COS) & (channel_mean(b) >= CAST_SHADOW * albedo[:, None] * cos)
    return np.where(valid[..., None], b / np.where(valid, cos, 1.0)[..., None], 0.0), valid


def _write_geometry(g: dict, source: Path, geometry_out: str | Path, normals_out: str | Path, factors) -> None:
    """Rectify's geometry ``g`` (read from the folder ``source``) with the shading normals and the estimated
    intensities (``factors``, or None), its file names relative to ``geometry_out``'s folder."""
    g, folder = copy.deepcopy(g), Path(geometry_out).parent
    for q, frame in enumerate(g["frames"]):
        frame["file"] = os.path.relpath(source / frame["file"], folder)
        if factors is not None:
            frame["light"]["intensity"] = (np.asarray(frame["light"]["intensity"], float) * factors.rgb[q]).tolist()
    if factors is not None:
        g["assumed"] = [a for a in g.get("assumed", []) if a != "intensities"]
        g["intensities"] = "estimated per light from the photos' diffuse part (separate/metrics.json light_factors)"
    if "scene" in g.get("truth", {}):
        g["truth"]["scene"] = os.path.relpath(source / g["truth"]["scene"], folder)
    g["normals"] = os.path.relpath(normals_out, folder)
    write_json(geometry_out, g)


def _normal_metrics(normals: np.ndarray, capture: RectifiedCapture) -> dict:
    """The shading normals' tilt from the plane (deg): median and 99th percentile over the visible points."""
    tilt = np.degrees(np.arccos(np.clip(normals[capture.visible, 2], -1.0, 1.0)))
    if tilt.size == 0:
        return {}
    return {"normal_tilt_median_deg": float(np.median(tilt)), "normal_tilt_p99_deg": float(np.percentile(tilt, 99))}
