"""Stage ``heldout_capture``: a held-out view of a virtual sample, rendered by the virtual rig (paper 002
sec. 6, Figs. 9-10).

The sample's rig with the camera moved to the view's (theta, phi) and a subset
of its lights (:func:`facetsynth.stages.validate.heldout_rig`) renders the
sample's scene, noise-free: its truth radiance is what ``validate`` scores the
predictions against.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..truth import virtual_rig
from ..truth.virtual_rig import VirtualRig
from .common import RuleFiles, StageSettings
from .validate import heldout_rig

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``heldout_capture``'s inputs: the sample's scene and rig description."""
    scene: Path
    rig: Path


class Outputs(RuleFiles):
    """Rule ``heldout_capture``'s output: the held-out capture's folder."""
    capture: Path


class Settings(StageSettings):
    """The stage's knobs: the view (the rule's params, from config ``validate.views``; default the paper's
    Fig. 9 view), config ``validate``'s held-out lights and the top-level ``seed``."""
    theta_deg: float = 50.9     # the camera's angle from vertical ...
    phi_deg: float = -15.3      # ... and its azimuth relative to the fitting camera's (degrees)
    led_every: int = 4          # held-out lights: every 4th LED ...
    position_every: int = 4     # ... at every 4th carriage position
    seed: int = 0               # config seed


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Render a held-out capture (noise-free; its truth radiance is what predictions are scored against)."""
    held = heldout_rig(VirtualRig.load(inputs.rig), settings.theta_deg, settings.phi_deg, settings.led_every,
                       settings.position_every)
    log.info("held-out view theta %.1f deg, phi %+.1f deg (relative), %d lights", settings.theta_deg,
             settings.phi_deg, len(held.scan()))
    virtual_rig.capture(inputs.scene, held, outputs.capture, seed=settings.seed, noise=False)
