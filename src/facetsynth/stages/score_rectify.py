"""Stage ``score_rectify``: a virtual capture's rectified frames against its truth (the registration on the
scene's markers, the rectified radiance), in a job of its own beside the fit (issue 31): rectify does not wait
for it, nor does anything after rectify, and a real capture, which has no truth, never runs it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..capture import manifest
from ..evaluation.rectify import truth_scores
from ..geometry.plane import PlaneGrid
from ..io.fileio import read_json, write_json
from .common import RuleFiles, StageSettings


class Inputs(RuleFiles):
    """Rule ``score_rectify``'s inputs: hdr's manifest (the capture and its truth), rectify's geometry and
    frames."""
    manifest: Path
    geometry: Path
    frames: Path


class Outputs(RuleFiles):
    """Rule ``score_rectify``'s output: the scores (JSON)."""
    scores: Path


class Settings(StageSettings):
    """The stage's knobs: none."""


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, score, write: :func:`facetsynth.evaluation.rectify.truth_scores` of the rectified frames ({} but
    ``ground_truth`` false for a capture without truth)."""
    capture = manifest.load(inputs.manifest)
    geometry = read_json(inputs.geometry)
    scores = truth_scores(capture, manifest.camera(capture), PlaneGrid.from_dict(geometry["grid"]),
                          np.asarray(geometry["visible"], bool), Path(inputs.frames))
    write_json(outputs.scores, {"ground_truth": manifest.has_truth(capture), **scores})
