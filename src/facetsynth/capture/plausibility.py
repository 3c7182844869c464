"""Plausibility of a capture: what its schema cannot see, checked by ``facetsynth check`` and ``hdr`` alike.

A manifest can be valid and still describe no capture this pipeline can fit (issue 32): a sample width
typed in millimetres (rectify then hangs: the warp's cost follows the sample's image, which a 1000 times
larger sample makes a million times larger, or unbounded when the sample reaches behind the camera), lights
a thousand times too far (kd comes out a million times too bright), every exposure clipped (nothing
measured). The thresholds are measured on the captures this repository makes and imports, and stated in
docs/decisions.md, "Hostile input: captures and config (issue 32)"; docs/capture.md lists them.

Geometry is taken without lens distortion (rectify refuses a distorted camera anyway). Errors are
InputErrors naming the manifest and the key; warnings are strings the caller prints (check) or logs (hdr).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import manifest
from ..io.errors import InputError
from .rectify import sample_pixels

# --- the sample against the camera's view of it ---------------------------------------------------------

SEEN_WARNING = 0.25
"""Warn when the camera sees less than this share of the sample's width or height (through its centre):
the fit covers only the part in view. The test fixtures' 4 x 3 pixel camera sees 0.3 of its 0.1 m sample."""

SEEN_ERROR = 1 / 500
"""Refuse when the camera sees less than this share of the sample's width or height: a length typed in
millimetres is 1000 times too large, so a sample that filled half the view or more lands below 1/500.
The largest legitimate ratio measured: the fixtures' close-up, a 10 m sample seen over 1/333 of its height."""

IMAGE_COST_RATIO = 1000.0
IMAGE_COST_PIXELS = 1e7
"""Refuse when the whole sample's image (in view or not) covers more than IMAGE_COST_RATIO times the
pixels that see it, and more than IMAGE_COST_PIXELS pixels: rectify's warp costs in proportion to it.
Measured on the tiny rig (30 frames, 120 x 80): a 0.1 m sample 0.14 s (7e3 pixels, ratio 1), 1 m 1.3 s
(1e6, ratio 103), 2 m 80 s (2.2e7, ratio 2250), 100 m hung (the sample reaches behind the camera)."""

MIN_PIXELS_ACROSS = 2.0
"""Refuse a sample that spans fewer pixels than this across its width or height: nothing to fit."""

FILL_WARNING = 0.01
"""Warn when the sample covers less than this share of the image (a size typed in too small a unit, or
a camera far too wide): the captures here fill 0.6 (virtual rigs, sample_fill 0.9) to 1 (a dome's .lp)."""

# --- the lights against the sample -----------------------------------------------------------------------

LIGHT_FAR_WARNING = 100.0
LIGHT_FAR_ERROR = 1e4
LIGHT_NEAR_WARNING = 0.05
"""A point light's distance from the sample's centre in sample diagonals: every rig here puts its lights
0.28 to 1.5 diagonals away (tests/data/rig-tiny.yaml, rig/descriptions/*.yaml, the fixtures' 0.76).
Beyond 100 diagonals a light is near-directional (state its direction instead, and check its intensity's
units: the radiance falls with the distance squared); beyond 1e4 it is a unit slip (a light within 10
diagonals typed in millimetres): kd would come out 1e6 times too bright. Nearer than 0.05 diagonals the
light sits on the sample (a position typed in too small a unit)."""

# --- clipping ---------------------------------------------------------------------------------------------

CLIPPED_FRAME_WARNING = 0.20
CLIPPED_CAPTURE_WARNING = 0.05
"""Warn when more than these shares of the sample's pixels are clipped in every exposure, in one frame or
over the whole capture (clipped pixels give a lower bound only). Measured on the tiny rig's virtual
captures: a conductor's mirror highlight clips up to 6.4 % of a frame's pixels and 1.0 % of the capture's;
card, coated, demo, brushed and satin at most 0.5 %. A frame (or capture) whose every sample pixel is
clipped is an error: it measured nothing, and taken as a lower bound it shifted ks by 15 %."""

DEFAULT_SATURATION_MARGIN = 0.02
"""check's clip level: values above (1 - margin) x saturation, config hdr.saturation_margin's default."""


def _implausible(path: str | Path | None, where: str, problem: str) -> InputError:
    return InputError(path, f"implausible capture at '{where}': {problem}")


@dataclass(frozen=True)
class AxisView:
    """The camera's view of one of the sample's axes, the line through its centre along x or y."""

    length: float            # the sample's extent along the axis (m)
    low: float               # the part of the line in view: [low, high] (m; infinite where unbounded)
    high: float
    pixels: float            # pixels the sample's part in view spans along the axis

    @property
    def seen(self) -> float:
        """The share of the sample's extent in view."""
        half = self.length / 2
        return max(0.0, min(self.high, half) - max(self.low, -half)) / self.length

    @property
    def footprint(self) -> float:
        return self.high - self.low


def _axis_view(H: np.ndarray, axis: int, length: float, width: int, height: int) -> AxisView:
    """The interval of the line s * e_axis (s in metres) that projects inside the image, in front of the
    camera: each image border (and the camera's principal plane) is a linear inequality in s."""
    a, b = H[:, axis], H[:, 2]          # homogeneous pixel of s e_axis: s a + b
    low, high = -math.inf, math.inf
    # each constraint: alpha s + beta >= 0
    rows = [(a[2], b[2]),                                           # depth w > 0
            (a[0] - (-0.5) * a[2], b[0] - (-0.5) * b[2]),           # u >= -0.5
            ((width - 0.5) * a[2] - a[0], (width - 0.5) * b[2] - b[0]),     # u <= W - 0.5
            (a[1] - (-0.5) * a[2], b[1] - (-0.5) * b[2]),           # v >= -0.5
            ((height - 0.5) * a[2] - a[1], (height - 0.5) * b[2] - b[1])]   # v <= H - 0.5
    for alpha, beta in rows:
        if alpha > 0:
            low = max(low, -beta / alpha)
        elif alpha < 0:
            high = min(high, -beta / alpha)
    half = length / 2
    ends = np.array([max(low, -half), min(high, half)])
    points = np.zeros((2, 3))
    points[:, 2] = 1.0
    points[:, axis] = ends
    uvw = points @ H.T
    with np.errstate(all="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:]
    pixels = float(np.hypot(*(uv[1] - uv[0]))) if ends[1] > ends[0] else 0.0
    return AxisView(length=length, low=low, high=high, pixels=pixels if math.isfinite(pixels) else 0.0)


def check_geometry(capture: dict[str, Any], path: str | Path | None) -> list[str]:
    """The sample's size against the camera's view of it, and the lights' distances against the sample:
    InputError for what cannot be a capture, the warnings for what is doubtful."""
    warnings = _sample_against_view(capture, path)
    warnings += _lights_against_sample(capture, path)
    return warnings


def _sample_against_view(capture: dict[str, Any], path: str | Path | None) -> list[str]:
    camera = manifest.camera(capture)
    w, h = float(capture["sample"]["width"]), float(capture["sample"]["height"])
    H = camera.plane_homography()
    size = f"{w:.4g} x {h:.4g} m"
    corners = np.array([[sx * w / 2, sy * h / 2, 0.0] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    if not camera.orthographic:
        depth = (corners @ camera.R.T + camera.t)[:, 2]
        if depth.min() <= 0:
            k = int(np.argmin(depth))
            raise _implausible(path, "sample", f"the sample ({size} about the origin) reaches behind the "
                                                   f"camera: its corner ({corners[k, 0]:.4g}, {corners[k, 1]:.4g}) "
                                                   f"m is at depth {depth[k]:.3g} m; no camera sees that (a "
                                                   "size typed in millimetres instead of metres?)")
    views = {"width": _axis_view(H, 0, w, camera.width, camera.height),
             "height": _axis_view(H, 1, h, camera.width, camera.height)}
    for name, view in views.items():
        if view.seen < SEEN_ERROR:
            raise _implausible(path, f"sample/{name}", f"the camera sees {view.footprint:.3g} m of the sample's "
                                                       f"{name} of {view.length:.4g} m through its centre "
                                                       f"(1/{1 / max(view.seen, 1e-300):.3g} of it, less than "
                                                       f"1/{1 / SEEN_ERROR:g}): a size typed in millimetres "
                                                       "instead of metres?")
        if view.pixels < MIN_PIXELS_ACROSS:
            raise _implausible(path, f"sample/{name}", f"the sample's {name} of {view.length:.4g} m spans "
                                                       f"{view.pixels:.2g} pixel(s) in the image (fewer than "
                                                       f"{MIN_PIXELS_ACROSS:g}): nothing to fit; a size typed in "
                                                       "too small a unit?")
    mask = sample_pixels(camera, w, h, whole=False)
    on_sample = int(mask.sum())
    uv = camera.project(corners)
    x, y = uv[:, 0], uv[:, 1]
    image_area = 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
    if image_area > IMAGE_COST_PIXELS and image_area > IMAGE_COST_RATIO * max(on_sample, 1):
        raise _implausible(path, "sample", f"the whole sample ({size}) would span {image_area:.3g} pixels in the "
                                           f"image plane, {image_area / max(on_sample, 1):.3g} times the "
                                           f"{on_sample} pixels that see it (more than {IMAGE_COST_RATIO:g} times "
                                           f"and {IMAGE_COST_PIXELS:g} pixels): rectify would spend hours "
                                           "warping what no pixel saw; a size typed in millimetres instead "
                                           "of metres?")
    warnings = []
    for name, view in views.items():
        if view.seen < SEEN_WARNING:
            warnings.append(f"the camera sees only {100 * view.seen:.3g} % of the sample's {name} ({view.footprint:.3g} m "
                            f"of {view.length:.4g} m, sample/{name}): the fit covers the part in view only; "
                            "state the size of the part in view (or check the unit: metres)")
    fill = on_sample / mask.size
    if fill < FILL_WARNING:
        warnings.append(f"the sample ({size}) covers only {on_sample} of the image's {mask.size} pixels "
                        f"({100 * fill:.2g} %): check its size's unit (metres) and the camera")
    return warnings


def _lights_against_sample(capture: dict[str, Any], path: str | Path | None) -> list[str]:
    w, h = float(capture["sample"]["width"]), float(capture["sample"]["height"])
    diagonal = math.hypot(w, h)
    points = [(q, np.asarray(f["light"]["position"], float)) for q, f in enumerate(capture["frames"])
              if "position" in f["light"]]
    if not points:
        return []
    distances = np.array([np.linalg.norm(p) for _, p in points]) / diagonal
    far, near = int(np.argmax(distances)), int(np.argmin(distances))
    q_far, q_near = points[far][0], points[near][0]
    if distances[far] > LIGHT_FAR_ERROR:
        raise _implausible(path, f"frames/{q_far}/light/position", f"the light is {distances[far]:.3g} sample "
                                                                   f"diagonals ({diagonal:.3g} m) from the sample's "
                                                                   f"centre, more than {LIGHT_FAR_ERROR:g}: its "
                                                                   "radiance would be 1/distance^2 of nothing; a "
                                                                   "position typed in millimetres instead of "
                                                                   "metres? (a light that far is directional: "
                                                                   "state its direction)")
    warnings = []
    n_far = int(np.sum(distances > LIGHT_FAR_WARNING))
    if n_far:
        warnings.append(f"{n_far} light(s) are more than {LIGHT_FAR_WARNING:g} sample diagonals away (the farthest: "
                        f"frames/{q_far}/light/position, {distances[far]:.3g} diagonals of {diagonal:.3g} m): "
                        "check the positions' unit (metres) and the intensities; a light that far is directional")
    n_near = int(np.sum(distances < LIGHT_NEAR_WARNING))
    if n_near:
        warnings.append(f"{n_near} light(s) are nearer than {LIGHT_NEAR_WARNING:g} sample diagonals to the sample's "
                        f"centre (the nearest: frames/{q_near}/light/position, {distances[near]:.3g} diagonals of "
                        f"{diagonal:.3g} m): check the positions' unit (metres) and the sample's size")
    return warnings


def duplicate_files(capture: dict[str, Any]) -> list[str]:
    """A warning when one exposure file is listed by two frames (two lights cannot give one picture)."""
    first: dict[str, int] = {}
    for q, frame in enumerate(capture["frames"]):
        for exposure in frame["exposures"]:
            r = first.setdefault(exposure["file"], q)
            if r != q:
                return [f"frames {r} and {q} list the same exposure file {exposure['file']}: two lights cannot "
                        "give one picture"]
    return []


# --- clipping ---------------------------------------------------------------------------------------------

def clip_level(capture: dict[str, Any], bits: int | None, margin: float = DEFAULT_SATURATION_MARGIN) -> float:
    """The value from which an exposure value counts as clipped, as hdr has it: code 255 for an 8-bit image,
    (1 - margin) x saturation for an EXR, never (inf) for data stated never clipped."""
    if bits == 8:
        return 254.5
    saturation = capture.get("saturation")
    return math.inf if saturation is None else (1.0 - margin) * saturation


def clipped_pixels(values: list[np.ndarray], level: float) -> np.ndarray:
    """(H, W) bool: the pixels with a channel at or above ``level`` (or NaN / Inf) in every exposure of a frame,
    as :func:`facetsynth.capture.hdr.merge_exposures` flags them saturated."""
    all_clipped = None
    for v in values:
        clipped = ~(v < level)
        all_clipped = clipped if all_clipped is None else all_clipped & clipped
    return all_clipped.any(axis=-1)


def check_clipping(clipped: list[int], on_sample: int, capture: dict[str, Any], path: str | Path | None,
                   stage: str = "check") -> list[str]:
    """``clipped[q]``: frame q's sample pixels clipped in every exposure, of ``on_sample``. InputError when a
    frame is clipped entirely (every frame: the capture), the warnings above the thresholds."""
    if not clipped or on_sample <= 0:
        return []
    shares = np.asarray(clipped, float) / on_sample
    full = np.flatnonzero(shares >= 1.0)
    frames = capture["frames"]
    if len(full) == len(frames):
        raise InputError(path, f"every exposure of every frame is clipped (all {on_sample} pixels that see the "
                               f"sample, in all {len(frames)} frames, at or above the clip level of the manifest's "
                               f"saturation {capture.get('saturation')}): nothing was measured; shorten the "
                               "exposures or check 'saturation'")
    if len(full):
        q = int(full[0])
        raise InputError(path, f"frame {q} is clipped in every exposure (all {on_sample} pixels that see the "
                               f"sample; {len(full)} such frame(s), first file {frames[q]['exposures'][0]['file']}): "
                               "it measured nothing but a lower bound, which would bias the fit; add a shorter "
                               f"exposure, or drop frames/{q} from the manifest")
    warnings = []
    worst = int(np.argmax(shares))
    many = np.flatnonzero(shares > CLIPPED_FRAME_WARNING)
    if len(many):
        warnings.append(f"{len(many)} frame(s) have more than {100 * CLIPPED_FRAME_WARNING:g} % of the sample's "
                        f"pixels clipped in every exposure (the most: frame {worst}, {100 * shares[worst]:.3g} %): "
                        "those pixels give a lower bound only; add a shorter exposure")
    total = float(shares.mean())
    if total > CLIPPED_CAPTURE_WARNING:
        warnings.append(f"{100 * total:.3g} % of the sample's pixels over all {len(frames)} frames are clipped in every "
                        f"exposure (more than {100 * CLIPPED_CAPTURE_WARNING:g} %): the fit sees a lower bound "
                        "there; add a shorter exposure")
    return warnings
