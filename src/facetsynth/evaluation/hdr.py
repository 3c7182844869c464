"""The hdr stage's merged frames against a virtual capture's true radiance."""

from __future__ import annotations

import logging

import numpy as np

from ..io.fileio import read_rgb
from .metrics import relative_errors

log = logging.getLogger(__name__)


def frame_truth_errors(frame: dict, merged: np.ndarray, saturated: np.ndarray, times: np.ndarray,
                       noise_floor: float) -> np.ndarray | None:
    """A virtual capture's frame: the relative errors of its merged radiance against the true one (None
    without truth), on the pixels above the noise floor in the longest exposure and not clipped in all
    (4096 at most, strided). Taken while the frame is merged, not read back after: the frames are streamed."""
    if "radiance" not in frame.get("truth", {}):
        return None
    truth = read_rgb(frame["truth"]["radiance"])
    above_floor = truth * times.max() > noise_floor
    return relative_errors(merged, truth, above_floor & ~saturated[..., None], sample=4096)


def truth_scores(merged: list) -> dict:
    """The merged frames' (:class:`facetsynth.stages.hdr.Merged`) median relative error against the true
    radiance (:func:`frame_truth_errors`); {} for a real capture."""
    errors = [m.errors for m in merged if m.errors is not None]
    if not errors:
        return {}
    scores = {"median_rel_error": float(np.median(np.concatenate(errors)))}
    log.info("HDR median relative error against the true radiance: %.5f", scores["median_rel_error"])
    return scores
