"""The calibrated rig file ``calibration.json`` (schema ``rig_calibration.schema.json``) and its loader.

A frame lit by LED ``led`` with the carriage ``steps`` motor steps from home has its light at
home[led] + steps * step (a straight carriage: the same displacement per step for every LED) and the
intensity intensity[led], in the radiance units of the capture manifest (I = rho cos L / r^2). The camera
follows :class:`facetsynth.geometry.camera.Camera` (X_cam = R X + t, OpenCV's lens model).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry.camera import Camera
from ..io.errors import InputError
from ..io.fileio import read_json, write_json
from ..io.validation import validate


@dataclass(frozen=True)
class RigCalibration:
    """A validated ``calibration.json``."""

    data: dict[str, Any]

    @classmethod
    def load(cls, path: str | Path) -> "RigCalibration":
        """Read and validate; InputError names the file and the problem."""
        data = read_json(path)
        validate(data, "rig_calibration.schema.json", path, "rig calibration")
        leds = data["leds"]
        if len(leds["home"]) != leds["count"] or len(leds["intensity"]) != leds["count"]:
            raise InputError(path, f"rig calibration: leds/home and leds/intensity must list leds/count = "
                                   f"{leds['count']} LEDs (found {len(leds['home'])} and {len(leds['intensity'])})")
        return cls(data)

    def save(self, path: str | Path) -> None:
        """Validate and write atomically."""
        validate(self.data, "rig_calibration.schema.json", path, "rig calibration")
        write_json(path, self.data)

    @property
    def count(self) -> int:
        return int(self.data["leds"]["count"])

    def camera(self) -> Camera:
        c = self.data["camera"]
        return Camera(int(c["width"]), int(c["height"]), np.asarray(c["K"], float), np.asarray(c["R"], float),
                      np.asarray(c["t"], float), np.asarray(c["distortion"], float))

    def light_position(self, led: int, steps: int) -> np.ndarray:
        """World position (3,) of LED ``led`` with the carriage at ``steps`` from home: home[led] + steps * step."""
        self._check(led)
        leds = self.data["leds"]
        return np.asarray(leds["home"][led], float) + float(steps) * np.asarray(leds["step"], float)

    def intensity(self, led: int) -> np.ndarray:
        """RGB intensity (3,) of LED ``led``."""
        self._check(led)
        return np.asarray(self.data["leds"]["intensity"][led], float)

    def _check(self, led: int) -> None:
        if not 0 <= led < self.count:
            raise InputError(None, f"rig calibration: LED {led} is not one of its {self.count} LEDs")
