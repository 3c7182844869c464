"""Stage ``separate``: BRDF samples (eq. 8), diffuse kd (eq. 9), the specular residual (paper 002 sec. 4)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..fileio import HALF, as_half, atomic_path, read_frame, write_exr, write_json
from ..frames import imap, map_frames
from ..render import light_geometry
from ..selfcheck import heldout_lights
from ..separation import brdf_samples, diffuse_level, specular_residual
from .common import RectifiedCapture, StageSettings, flag_degenerate, tiles

log = logging.getLogger(__name__)

# A point shows specular signal when its brightest specular residual is at least SIGNAL_RATIO of its diffuse
# level rho_d (channel means): a highlight half as bright as the diffuse reflection. Sensor noise alone stays far
# below: a matte sample (ks = 0) on the tiny rig with noise gives 0.03-0.07 (1-99 % of points), the glossy card
# 0.14-20 (73 % of points above 0.5), the card under its 4 corner lights alone 0.02-0.76 (5 %).
SIGNAL_RATIO = 0.5
# Fewer points than this fraction with specular signal: a matte sample, or lights that miss every highlight;
# a diffuse-only model is all the capture supports. Black markers, dust and dead pixels stay below it.
MIN_SIGNAL_FRACTION = 0.01
FRAME_BLOCK = 32    # frames read before their samples are written


@dataclass(frozen=True)
class Settings(StageSettings):
    """The stage's knobs: config ``separate`` (workflow/schemas/config.schema.yaml)."""
    threshold: float = 0.05   # eq. 9: samples darker than threshold x the point's average intensity are left out
    lowest: float = 0.03      # eq. 9 averages this fraction of the qualifying samples, those of lowest channel
                              # mean (0: eq. 9's minimum, per channel)
    heldout_every: int = 0    # config selfcheck.heldout_every: every k-th frame's samples are invalid, so that no
                              # later stage sees those lights (facetsynth.selfcheck.heldout_lights; 0: none)


def run(geometry: str | Path, kd_out: str | Path, specular_out: str | Path, valid_out: str | Path,
        metrics_out: str | Path, settings: Settings = Settings(), threads: int = 1) -> None:
    """Per point and light: rho by eq. 8, kd = pi rho_d by eq. 9 (:func:`~facetsynth.separation.diffuse_level`),
    rho~_s = rho - rho_d.

    Writes ``kd`` (EXR on the rectified grid), the specular residual (P, F, 3) in half floats
    (:func:`~facetsynth.fileio.as_half`) and the sample validity (P, F) as memory-mappable .npy
    (frames are streamed in; memory does not grow with the sample size).
    Invalid samples: saturated, a point outside the camera's view, or a light held out for the self-check
    (``settings.heldout_every``). Frames are read on ``threads`` threads.
    """
    capture = RectifiedCapture.load(geometry)
    n_points, n_frames = capture.n_points, len(capture.frame_files)
    with atomic_path(specular_out, suffix=".npy") as tmp_spec, atomic_path(valid_out, suffix=".npy") as tmp_valid:
        # eq. 8's samples in float32 beside the output (a temporary: swept if this process dies), so that
        # eq. 9's kd is not rounded to half floats; the residual goes out in half floats
        scratch = tmp_spec.with_name(tmp_spec.name + ".eq8.npy")
        try:
            kd, signal = _separate(capture, settings, threads, scratch, tmp_spec, tmp_valid)
        finally:
            scratch.unlink(missing_ok=True)
    write_exr(kd_out, {"RGB": kd.reshape(capture.grid.rows, capture.grid.cols, 3)},
              {"quantity": "kd (diffuse albedo), paper 002 eq. 9" + (
                  f" (the mean of the lowest {100 * settings.lowest:g} % of the qualifying samples)"
                  if settings.lowest else "")})

    dark = int((kd.sum(axis=1) == 0).sum())
    metrics = {"ground_truth": capture.truth_scene is not None, "points": n_points, "frames": n_frames,
               "threshold": settings.threshold, "lowest": settings.lowest,
               "heldout_frames": int(heldout_lights(n_frames, settings.heldout_every).sum()),
               "points_without_diffuse_estimate": dark}
    lit = capture.visible & (kd.sum(axis=1) > 0)
    metrics["specular_signal_fraction"] = float(signal[lit].mean()) if lit.any() else 0.0
    if metrics["specular_signal_fraction"] < MIN_SIGNAL_FRACTION:
        flag_degenerate(metrics, f"no specular signal: {100 * metrics['specular_signal_fraction']:.1f} % of the "
                        f"lit points have a highlight of at least {SIGNAL_RATIO} x their diffuse level (needed: "
                        f"{100 * MIN_SIGNAL_FRACTION:.0f} %); the sample is matte under these lights, or the lights "
                        "miss its highlights: only kd is supported by the capture, the specular fit is noise", log)
    truth = capture.truth()
    if truth is not None:
        # Points whose true BRDF is not eq. 6 (measured, coated, ...) have no true kd to score against.
        select = (capture.visible & truth.analytic)[:, None] & (truth.kd > 0)
        metrics["kd_median_rel_error"] = (float(np.median(np.abs(kd - truth.kd)[select] / truth.kd[select]))
                                          if select.any() else None)
        if select.any():
            log.info("kd median relative error %.4f", metrics["kd_median_rel_error"])
    write_json(metrics_out, metrics)


def _separate(capture: RectifiedCapture, settings: Settings, threads: int, scratch: Path, specular_out: Path,
              valid_out: Path) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 8 frame by frame into ``scratch``, then eq. 9 tile by tile into the residual and validity files;
    returns kd (P, 3) and which points show specular signal (P,)."""
    n_points, n_frames = capture.n_points, len(capture.frame_files)
    points = capture.points
    held = heldout_lights(n_frames, settings.heldout_every)
    rho = np.lib.format.open_memmap(scratch, mode="w+", dtype=np.float32, shape=(n_points, n_frames, 3))
    valid = np.lib.format.open_memmap(valid_out, mode="w+", dtype=bool, shape=(n_points, n_frames))

    def frame_samples(q: int) -> tuple[np.ndarray, np.ndarray]:
        radiance, saturated = read_frame(capture.frame_files[q])
        sample, _ = brdf_samples(radiance.reshape(-1, 1, 3), points,
                                 capture.light_positions[q:q + 1], capture.light_intensities[q:q + 1])
        return sample[:, 0].astype(np.float32), capture.visible & ~saturated.ravel() & ~held[q]

    # written FRAME_BLOCK frames at a time as one block of columns: a frame alone would touch every
    # page of the (P, F, 3) file for 12 bytes a point
    block = []
    for q, samples in enumerate(imap(frame_samples, range(n_frames), threads, "separate: eq. 8")):
        block.append(samples)
        if len(block) == FRAME_BLOCK or q == n_frames - 1:
            columns = slice(q + 1 - len(block), q + 1)
            rho[:, columns] = np.stack([s for s, _ in block], axis=1)
            valid[:, columns] = np.stack([v for _, v in block], axis=1)
            block = []
    rho.flush()
    valid.flush()
    kd = np.zeros((n_points, 3))
    signal = np.zeros(n_points, bool)
    residuals = np.lib.format.open_memmap(specular_out, mode="w+", dtype=HALF, shape=(n_points, n_frames, 3))

    def separate_tile(tile: slice) -> None:
        rho_tile = np.asarray(rho[tile], float)
        radiance = _radiance(rho_tile, points[tile], capture)
        rho_d = diffuse_level(rho_tile, radiance, valid[tile], settings.threshold, settings.lowest)
        kd[tile] = np.pi * rho_d
        residual = specular_residual(rho_tile, rho_d)
        residuals[tile] = as_half(residual)
        peak = np.where(valid[tile], residual.mean(axis=-1), 0.0).max(axis=1, initial=0.0)
        diffuse = rho_d.mean(axis=-1)
        signal[tile] = (diffuse > 0) & (peak >= SIGNAL_RATIO * diffuse)

    map_frames(separate_tile, list(tiles(n_points)), threads, "separate: eq. 9", unit="tile")
    residuals.flush()
    del rho, valid, residuals
    return kd, signal


def _radiance(rho: np.ndarray, points: np.ndarray, capture: RectifiedCapture) -> np.ndarray:
    """I = rho (n . i) L / |P - x|^2: eq. 8 read forwards, for the threshold of eq. 9."""
    wi, r2 = light_geometry(points[:, None, :], capture.light_positions[None])
    return rho * (np.clip(wi[..., 2], 0, None) / r2)[..., None] * capture.light_intensities[None]
