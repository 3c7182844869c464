"""Reading a calibration targets folder (its ``targets.json`` and images; the layout is in
:mod:`facetsynth.calibration`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..io.errors import InputError
from ..io.fileio import read_frame, read_json

REQUIRED = ("camera", "board", "intrinsics", "pose", "mirror", "white", "leds")


def load_layout(folder: str | Path) -> dict[str, Any]:
    """``targets.json`` of ``folder``, its required sections checked (InputError naming the file)."""
    path = Path(folder) / "targets.json"
    layout = read_json(path)
    if not isinstance(layout, dict):
        raise InputError(path, "targets layout must be a JSON object")
    missing = [k for k in REQUIRED if k not in layout]
    if missing:
        raise InputError(path, f"targets layout lacks {', '.join(missing)} (see facetsynth.calibration)")
    if len(layout["intrinsics"]) < 3:
        raise InputError(path, f"intrinsics: {len(layout['intrinsics'])} board view(s); Zhang's method needs at "
                               "least 3 at different tilts (10-20 recommended)")
    return layout


def read_image(folder: str | Path, file: str, size: tuple[int, int]) -> np.ndarray:
    """A target image as float (H, W, 3): an EXR as stored (linear), another format OpenCV reads as its
    values over the type's maximum (8-bit images only for checkerboards: mirror and white frames must be
    linear). InputError names the file when it is missing, unreadable or not ``size`` = (width, height)."""
    path = Path(folder) / file
    if path.suffix.lower() == ".exr":
        image, _ = read_frame(path)
    else:
        if not path.is_file():
            raise InputError(path, "file not found")
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(path, "not an image OpenCV can read")
        scale = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else 1.0
        image = raw.astype(np.float32) / scale
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=-1)
        else:
            image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB)
    if (image.shape[1], image.shape[0]) != tuple(size):
        raise InputError(path, f"image is {image.shape[1]}x{image.shape[0]}, the camera is {size[0]}x{size[1]}")
    return image
