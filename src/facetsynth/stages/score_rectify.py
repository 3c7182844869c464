"""Stage ``score_rectify``: a virtual capture's rectified frames against its truth (the registration on the
scene's markers, the rectified radiance), in a job of its own beside the fit (issue 31): rectify does not wait
for it, nor does anything after rectify, and a real capture, which has no truth, never runs it. It warps the
frames it scores again, as rectify does (:class:`facetsynth.stages.rectify.FrameWarp`), instead of reading
rectify's, which are deleted once separate has read them: asked for after a fit made without it, it runs alone,
not rectify again and every stage after it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..capture import manifest
from ..evaluation.rectify import truth_scores
from ..geometry.plane import PlaneGrid
from ..io.fileio import read_json, write_json
from .common import RuleFiles, StageSettings
from .rectify import FrameWarp


class Inputs(RuleFiles):
    """Rule ``score_rectify``'s inputs: hdr's manifest (the capture, its frames and its truth) and rectify's
    geometry (the grid)."""
    manifest: Path
    geometry: Path
    frames: Path | None = None     # hdr's merged frames (read through the manifest)


class Outputs(RuleFiles):
    """Rule ``score_rectify``'s output: the scores (JSON)."""
    scores: Path


class Settings(StageSettings):
    """The stage's knobs: config ``rectify.filter``, the warp's, as rectify's."""
    filter: str = "triangle"


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, score, write: :func:`facetsynth.evaluation.rectify.truth_scores` of the frames as rectify warps them
    with ``settings.filter`` ({} but ``ground_truth`` false for a capture without truth)."""
    capture = manifest.load(inputs.manifest)
    camera, geometry = manifest.camera(capture), read_json(inputs.geometry)
    grid = PlaneGrid.from_dict(geometry["grid"])
    warp = FrameWarp(capture, camera, grid, settings.filter)
    scores = truth_scores(capture, camera, grid, np.asarray(geometry["visible"], bool),
                          lambda q: warp([q])[0][0][..., :3])
    write_json(outputs.scores, {"ground_truth": manifest.has_truth(capture), **scores})
