"""Stage ``score_refine``: a virtual capture's fitted SVBRDF against its truth (kd, ks, ks F0 and the NDF spread per
region; :func:`facetsynth.evaluation.refine.truth_scores`), the refined model's and, for comparison, the pipeline's
it started from, in a job of its own beside the fit (issue 31): nothing of the fit waits for it, and a real
capture, which has no truth, never runs it."""

from __future__ import annotations

import logging
from pathlib import Path

from ..evaluation.refine import truth_scores
from ..io.fileio import write_json
from ..models.svbrdf import SVBRDF
from .common import RectifiedCapture, RuleFiles, StageSettings

log = logging.getLogger(__name__)

COMPARED = ("kd_median_rel_error", "ks_median_rel_error", "ks_f0_median_rel_error", "ndf_spread_max_median")


class Inputs(RuleFiles):
    """Rule ``score_refine``'s inputs: separate's geometry (the capture and its truth), params' SVBRDF (the
    pipeline's) and refine's (the fitted one)."""
    geometry: Path
    pipeline: Path
    svbrdf: Path


class Outputs(RuleFiles):
    """Rule ``score_refine``'s output: the scores (JSON)."""
    scores: Path


class Settings(StageSettings):
    """The stage's knobs: none."""


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, score, write: the refined model's truth scores, and the pipeline's of :data:`COMPARED` as
    ``NAME_before`` ({} but ``ground_truth`` false for a capture without truth)."""
    capture = RectifiedCapture.load(inputs.geometry)
    scores = truth_scores(SVBRDF.load(inputs.svbrdf), capture)
    if scores:
        before = truth_scores(SVBRDF.load(inputs.pipeline), capture)
        scores.update({f"{k}_before": before[k] for k in COMPARED})
        log.info("against the truth: kd %s, ks %s, largest NDF spread %s (the pipeline's: %s, %s, %s)",
                 *(scores.get(k) for k in COMPARED if k != "ks_f0_median_rel_error"),
                 *(scores.get(f"{k}_before") for k in COMPARED if k != "ks_f0_median_rel_error"))
    write_json(outputs.scores, {"ground_truth": capture.truth_scene is not None, **scores})
