"""The RTI community's light file (``.lp``) as a capture manifest (DESIGN.md sec. 4).

A light dome (RTIBuilder, relight, the RealRTI dataset) writes one photo per light and a text file::

    48
    image00.jpg 0.1318 0.8498 0.5103
    image01.jpg -0.1109 0.8637 0.4916
    ...

the number of lights, then per photo its file (relative to the ``.lp``'s folder) and the direction
towards the light, a (nearly) unit vector in the image's frame: x to the right of the image, y to its
top, z towards the camera (RTIBuilder's highlight detection on a reflective sphere, and relight's
``Dome``: "the origin is the centre of the image, Z is up"). No intensities, no camera, no scale.

What the pipeline assumes for what the file does not say, each stated here, in the log and in the
manifest's ``assumed`` field, and each overridable in a side file ``<stem>.yaml`` beside the ``.lp``
(keys below):

* camera (``camera``): orthographic, looking straight down, the image's top towards world +y (the
  dome's distant camera; the lights are directional, so only the view's direction matters);
* pixel size on the object (``pixel_size_mm``, default 0.1): the sample's width in metres is that
  times the image width. Nothing in the fit depends on it (directional lights and an orthographic
  camera have no length in them); it labels the report's axes and sizes exports;
* light intensities (``intensities``: one [r, g, b] per light, default white 1): irradiance at normal
  incidence, in units of the photos' linear values. Without them the stage ``separate`` estimates a factor
  per light from the photos (:mod:`facetsynth.fit.light_factors`): from the whole sample's diffuse part, or
  from a white or grey box the user names, ``reference: [col0, row0, col1, row1]`` (photo pixels; the
  manifest's ``reference_region``, on the plane);
* the photos' transfer function (``transfer``, default ``srgb``: JPEG and 8-bit PNG are sRGB-encoded
  as cameras and RTI tools write them; ``linear`` or ``{gamma: G}`` otherwise) and ``black_level``
  (default 0);
* ``saturation``: 8-bit codes of 255 are clipped (the hdr stage masks them).

World frame: x right, y up in the image, z up out of the sample: the ``.lp`` directions are world
directions as they are.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..io.errors import InputError
from ..io.fileio import read_yaml
from ..capture import transfer

HORIZON_TOLERANCE = 0.05
"""Lights calibrated this far below the horizon (z of the unit direction, about 3 deg) are taken as
grazing (:data:`GRAZING_Z`): a dome's lowest ring sits on the horizon and its sphere calibration scatters
by a degree or two (RealRTI item7 has one light at z = -0.0012). Further below is an error."""

GRAZING_Z = 1e-3
"""z given to a light calibrated at or just below the horizon: grazing, so the stages' grazing cut-offs
(eq. 11's 80 deg) leave it out of the fit wherever the sample is flat."""

PIXEL_SIZE_MM = 0.1
"""Default size of an image pixel on the object (mm): only labels lengths (module docstring)."""

SIDE_KEYS = {"pixel_size_mm", "intensities", "transfer", "black_level", "camera", "reference"}


def read(path: str | Path) -> tuple[list[str], np.ndarray]:
    """(file names as written, unit directions (F, 3)) of an ``.lp`` file; InputError naming the file and
    the line for anything else: a count that is not a positive integer, fewer or more lines than it says,
    a line without a file and three numbers, a direction that is not finite, zero, or below the sample
    (z < -:data:`HORIZON_TOLERANCE`; between that and 0 it is raised to :data:`GRAZING_Z`)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the light file: {getattr(exc, 'strerror', None) or exc}") from None
    numbered = [(k + 1, line.strip()) for k, line in enumerate(lines) if line.strip()]
    if not numbered:
        raise InputError(path, "empty light file: expected the number of lights on line 1")
    first, count = numbered[0]
    if not count.isdecimal() or int(count) == 0:    # not isdigit: '²' is a digit that int() refuses
        raise InputError(path, f"line {first}: expected the number of lights (a positive integer), got {count!r:.40}")
    entries = numbered[1:]
    if len(entries) != int(count):
        raise InputError(path, f"line {first} says {int(count)} lights, but {len(entries)} light line(s) follow")
    files, directions = [], []
    for number, line in entries:
        files.append(_file(path, number, line))
        directions.append(_direction(path, number, line))
    return files, np.array(directions)


def _file(path: Path, number: int, line: str) -> str:
    """The file name of a light line (it may contain spaces: the last three fields are the direction)."""
    fields = line.rsplit(None, 3)
    if len(fields) != 4:
        raise InputError(path, f"line {number}: expected 'FILE x y z', got {line!r:.60}")
    return fields[0]


def _direction(path: Path, number: int, line: str) -> list[float]:
    """The unit direction of a light line."""
    try:
        d = [float(v) for v in line.rsplit(None, 3)[1:]]
    except ValueError:
        raise InputError(path, f"line {number}: the direction must be three numbers, got {line!r:.60}") from None
    norm = math.hypot(*d) if all(map(math.isfinite, d)) else float("nan")   # hypot: no overflow of v * v
    if not norm > 1e-9:
        raise InputError(path, f"line {number}: the direction {d} is not a finite, nonzero vector")
    d = [v / norm for v in d]
    if not d[2] >= -HORIZON_TOLERANCE:
        raise InputError(path, f"line {number}: the light direction {d} is below the sample (z must be > 0: "
                               "x right, y up in the image, z towards the camera)")
    if d[2] < GRAZING_Z:          # on the horizon within calibration error: grazing
        flat = math.hypot(d[0], d[1])
        d = [d[0] / flat * math.sqrt(1 - GRAZING_Z**2), d[1] / flat * math.sqrt(1 - GRAZING_Z**2), GRAZING_Z]
    return d


def side_file(path: str | Path) -> Path:
    """The optional side file of an ``.lp``: ``<stem>.yaml`` in its folder."""
    path = Path(path)
    return path.with_suffix(".yaml")


def options(path: str | Path, n_lights: int) -> dict[str, Any]:
    """The side file's settings (module docstring), {} without one; InputError naming the side file for
    unknown keys, intensities that are not n_lights x 3 finite numbers >= 0, a pixel size that is not a
    finite number > 0, a black level that is not a number in [0, 1), or a transfer that is not one."""
    side = side_file(path)
    if not side.is_file():
        return {}
    found = read_yaml(side) or {}
    if not isinstance(found, dict):
        raise InputError(side, f"expected a mapping of {sorted(SIDE_KEYS)}, found {type(found).__name__}")
    unknown = set(found) - SIDE_KEYS
    if unknown:
        raise InputError(side, f"unknown key(s) {sorted(map(str, unknown))}; known: {sorted(SIDE_KEYS)}")
    intensities = found.get("intensities")
    if intensities is not None:
        try:
            values = np.asarray(intensities, float)
        except (TypeError, ValueError):      # ragged, or not numbers
            values = None
        if values is None or values.shape != (n_lights, 3):
            got = f"shape {values.shape}" if values is not None else f"{str(intensities)!r:.60}"
            raise InputError(side, f"intensities: expected one [r, g, b] per light ({n_lights} x 3), got {got}")
        if not (np.isfinite(values).all() and (values >= 0).all()):
            raise InputError(side, "intensities: every value must be a finite number >= 0")
    for key, low, high in (("pixel_size_mm", 0.0, math.inf), ("black_level", 0.0, 1.0)):
        value = found.get(key)
        if key in found and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                 and (low < value < high or key == "black_level" and value == low)):
            limits = "a finite number > 0" if key == "pixel_size_mm" else "a number in [0, 1)"
            raise InputError(side, f"{key} must be {limits}, got {str(value)!r:.40}")
    reference = found.get("reference")
    if "reference" in found and not (isinstance(reference, list) and len(reference) == 4
                                     and all(isinstance(v, int) and not isinstance(v, bool) for v in reference)
                                     and reference[0] < reference[2] and reference[1] < reference[3]):
        raise InputError(side, f"reference must be a box of photo pixels [col0, row0, col1, row1] with col0 < col1 "
                               f"and row0 < row1, got {str(reference)!r:.60}")
    if "transfer" in found:
        try:
            transfer.parse(found["transfer"])
        except (TypeError, ValueError) as exc:
            raise InputError(side, f"transfer: {exc}") from None
    return found


def _plane_box(cam: dict[str, Any], box: list[int]) -> dict[str, list[float]]:
    """A box of photo pixels [col0, row0, col1, row1] (pixel edges: col0 - 0.5 .. col1 - 0.5) as the box it covers
    on the sample plane, {"x": [x0, x1], "y": [y0, y1]} in metres (the camera's plane homography, inverted)."""
    from ..capture.manifest import camera
    H = np.linalg.inv(camera({"camera": cam}).plane_homography())
    corners = np.array([[box[0] - 0.5, box[1] - 0.5, 1.0], [box[2] - 0.5, box[3] - 0.5, 1.0]]) @ H.T
    xy = corners[:, :2] / corners[:, 2:]
    return {"x": sorted(xy[:, 0].tolist()), "y": sorted(xy[:, 1].tolist())}


def manifest(path: str | Path, image_size: tuple[int, int]) -> dict[str, Any]:
    """The capture manifest of an ``.lp`` file whose photos are ``image_size`` (width, height) pixels:
    directional lights, an orthographic top-down camera, and the stated defaults (module docstring),
    with ``assumed`` listing what was assumed rather than read. Frame files stay where they are
    (relative to the ``.lp``'s folder)."""
    path = Path(path)
    files, directions = read(path)
    side = options(path, len(files))
    width, height = image_size
    pixel_m = float(side.get("pixel_size_mm", PIXEL_SIZE_MM)) / 1000.0
    if not pixel_m > 0:
        raise InputError(side_file(path), f"pixel_size_mm must be > 0, got {side['pixel_size_mm']}")
    intensities = np.asarray(side.get("intensities", np.ones((len(files), 3))), float)
    scale = 1.0 / pixel_m
    camera = side.get("camera", {"projection": "orthographic", "width": width, "height": height,
                                 "K": [[scale, 0.0, (width - 1) / 2], [0.0, scale, (height - 1) / 2], [0, 0, 1]],
                                 "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "t": [0, 0, 1]})
    assumed = [key for key, default in (("camera", "orthographic, top-down"),
                                        ("pixel_size_mm", PIXEL_SIZE_MM), ("intensities", "white, 1"),
                                        ("transfer", "srgb"), ("black_level", 0))
               if key not in side]
    return {"version": 1, "units": "m", "sample": {"width": width * pixel_m, "height": height * pixel_m},
            "camera": camera, "saturation": 1.0, "transfer": side.get("transfer", "srgb"),
            "black_level": float(side.get("black_level", 0.0)),
            "frames": [{"light": {"direction": d.tolist(), "intensity": i.tolist()},
                        "exposures": [{"file": f, "time": 1.0}]}
                       for f, d, i in zip(files, directions, intensities)],
            **({"reference_region": _plane_box(camera, side["reference"])} if "reference" in side else {}),
            "source": {"lp": str(path.resolve()),
                       "side_file": str(side_file(path)) if side_file(path).is_file() else None},
            "assumed": assumed}
