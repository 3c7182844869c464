"""The knobs of the calibration rules (config section ``calibration``), apart from the stage
(:mod:`facetsynth.stages.calibrate`) so that the rule file reads them without importing OpenCV or scipy."""

from __future__ import annotations

from ..stages.settings import StageSettings


class TargetSettings(StageSettings):
    """Config section ``calibration`` (target rendering of a virtual rig)."""

    sample_width: float = 0.10      # metres: the virtual camera's focal length follows the sample width
    intrinsic_views: int = 12       # hand-held checkerboard views (Zhang 2000)
    mirror_heights: tuple = (0.0, 0.025)   # metres: the mirror on the plane, then on a spacer
    mirror_every: int = 3           # every n-th carriage position of the scan for the mirror
    led_radius: float = 0.0015      # metres: the LED emitter disc
    albedo: float = 0.95            # the white reference


class CalibrateSettings(StageSettings):
    """Config section ``calibration`` (fitting)."""

    lens: str = "none"                   # none (ideal pinhole: rectify accepts no distortion), radial, full
    fix_principal_point: bool = True     # keep (W-1)/2, (H-1)/2: a narrow lens does not constrain it
    corner_window: int = 5               # cornerSubPix half-window (px): below half a square's image
    highlight_floor_sigmas: float = 20.0 # a mirror frame's peak must exceed this many read-noise sigmas
    scale_from_carriage: bool = True     # fix the focal length by the carriage's known travel per step (targets.json
                                         # carriage/step_length): a narrow lens leaves f and distance interchangeable
