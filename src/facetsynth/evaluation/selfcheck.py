"""The self-check: a fit scored against its own capture, without ground truth (issue 29).

Two subsets of a capture's frames, both fixed by the frame count alone so
that every stage (and a user) finds the same ones:

* the **held-out lights**, every ``k``-th frame (from ``k // 2``, interleaved
  with the rest: on a rig whose frames run LED by LED along the array, a
  stride that divides the LED count holds out whole LEDs at every carriage
  position). ``separate`` marks their samples invalid, so no stage after
  ``hdr`` sees them, and the fitted model predicts them;
* the **relit fitting view**, every ``k``-th of the remaining frames: the fit
  relit under lights it was fitted on, i.e. whether it reproduces what it saw.

Scores accumulate frame by frame (memory does not grow with the frame count):
relative L2 sqrt(sum (pred - meas)^2 / sum meas^2) over the pixels that see the sample alone (none across its edge),
every frame and channel of the subset (:func:`facetsynth.evaluation.metrics.relative_l2`
of the stacked frames, with clipped pixels left out per frame); its specular
part, the same of (pred - diffuse) against (meas - diffuse) with diffuse the
model's own kd/pi (n.i) L / r^2 (no truth: the fit's separation of the
diffuse term is what it is scored against); each frame's PSNR with that
frame's peak.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .metrics import frame_psnr


def heldout_lights(n_frames: int, every: int) -> np.ndarray:
    """(F,) bool: the held-out frames, every ``every``-th from ``every // 2`` (``every`` 0: none)."""
    held = np.zeros(int(n_frames), bool)
    if every:
        held[every // 2::every] = True
    return held


def relit_frames(heldout: np.ndarray, every: int) -> np.ndarray:
    """Indices of the fitting frames (not held out) relit by the self-check: every ``every``-th of them."""
    fitting = np.flatnonzero(~np.asarray(heldout, bool))
    return fitting[::max(1, int(every))]


@dataclass
class FrameScores:
    """Sums over the frames of one subset, added to frame by frame (:meth:`add`)."""

    error: float = 0.0          # sum (pred - meas)^2
    signal: float = 0.0         # sum meas^2
    specular: float = 0.0       # sum (meas - diffuse)^2
    pixels: int = 0
    psnr_db: list[float] = field(default_factory=list)     # per frame, its own peak
    frames: list[int] = field(default_factory=list)

    def add(self, frame: int, measured: np.ndarray, predicted: np.ndarray, diffuse: np.ndarray,
            mask: np.ndarray, max_db: float = 100.0) -> None:
        """Score one frame: (H, W, 3) measured, predicted and the model's diffuse radiance over ``mask``
        (H, W) (the sample's pixels that are not clipped in this frame)."""
        meas = np.asarray(measured, float)[mask]
        err = np.asarray(predicted, float)[mask] - meas
        self.error += float(np.sum(err**2))
        self.signal += float(np.sum(meas**2))
        self.specular += float(np.sum((meas - np.asarray(diffuse, float)[mask]) ** 2))
        self.pixels += int(mask.sum())
        self.frames.append(int(frame))
        self.psnr_db.append(float(frame_psnr(np.asarray(measured)[None], np.asarray(predicted)[None], mask,
                                             max_db)[0]))

    @property
    def rel_l2(self) -> float:
        """sqrt(sum (pred - meas)^2 / sum meas^2); NaN without signal."""
        return float(np.sqrt(self.error / self.signal)) if self.signal > 0 else float("nan")

    @property
    def specular_rel_l2(self) -> float:
        """sqrt(sum (pred - meas)^2 / sum (meas - diffuse)^2): the error against the specular signal."""
        return float(np.sqrt(self.error / self.specular)) if self.specular > 0 else float("nan")

    def worst_frame(self) -> int | None:
        """The frame of lowest PSNR (None without a scored frame)."""
        psnr = np.asarray(self.psnr_db)
        ok = np.isfinite(psnr)
        return int(np.asarray(self.frames)[ok][np.argmin(psnr[ok])]) if ok.any() else None
