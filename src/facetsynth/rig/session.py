"""A capture on the real rig (paper 002 sec. 4), journaled so that an interrupted one resumes.

The controller (``rig/PROTOCOL.md``, :class:`~facetsynth.rig.driver.RigController`) homes the carriage,
then for every frame of the scan moves it and lights one LED; the camera backend
(:mod:`facetsynth.rig.cameras`) takes the frame's exposure bracket. The manifest's geometry comes from the
rig's calibration (``calibration.json`` of the ``calibrate`` rule): the camera's K, R, t and distortion,
and each frame's light position ``home[led] + steps * step`` and intensity.

What survives a fault (a controller that stops answering, a camera error, a power cut, Ctrl-C):

- The capture is built in a staging folder beside its output (:func:`facetsynth.io.fileio.atomic_dir`),
  moved into place only when every frame is there and the manifest written.
- Every exposure file is written atomically (a temporary name, then a rename), so a file under its final
  name is whole.
- After a frame's files are in place it is appended to ``journal.jsonl`` and the journal is flushed to
  disk (fsync). A frame is taken when, and only when, the journal has no entry for it whose files all
  exist: a rerun with the same rig description and calibration resumes at the next missing frame and
  retakes nothing saved. A line torn by a power cut is ignored (that frame is taken again).
- The driver retries lost or garbled replies and reconnects after a USB disconnect
  (:mod:`facetsynth.rig.driver`); a camera error is retried ``camera.retries`` times. A fault that
  outlasts those stops the capture with the error, LEDs off; running again resumes it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from tqdm import tqdm

from ..capture import manifest
from ..io.errors import InputError
from ..io.fileio import atomic_dir, read_yaml
from ..io.validation import validate
from .driver import RigController
from .protocol import RigError, RigInfo

log = logging.getLogger(__name__)

JOURNAL = "journal.jsonl"


@dataclass(frozen=True)
class ScanPlan:
    """Which (carriage steps, LED) pairs a capture takes, in order (the description's ``scan``)."""

    positions: int
    travel_steps: int
    use_every: int = 1

    def frames(self, n_leds: int) -> list[tuple[int, int]]:
        """(steps, led) of every frame: carriage positions evenly spaced from home, each LED along x in turn."""
        steps = np.rint(np.linspace(0, self.travel_steps, self.positions)).astype(int) if self.positions > 1 else [0]
        return [(int(s), led) for s in steps for led in range(0, n_leds, self.use_every)]


@dataclass(frozen=True)
class RigDescription:
    """A validated rig description (``source: rig``; schema ``rig.schema.json``)."""

    path: Path
    desc: dict[str, Any]

    @classmethod
    def load(cls, path: str | Path) -> "RigDescription":
        desc = read_yaml(path)
        validate(desc, "rig.schema.json", path, "rig description")
        return cls(Path(path), desc)

    @property
    def name(self) -> str:
        return self.desc["name"]

    @property
    def calibration(self) -> Path:
        return Path(self.desc["calibration"])

    @property
    def scan(self) -> ScanPlan:
        return ScanPlan(**self.desc["scan"])

    @property
    def times(self) -> list[float]:
        return [float(t) for t in self.desc["exposure"]["times"]]

    def frames_key(self) -> dict:
        """What the frames depend on: a staging folder taken with another key is not resumed. Not the controller's
        port (a USB adapter may come back under another name), the camera's retries or the calibration (it
        places the lights in the manifest, written at the end, and changes no pixel)."""
        camera = {k: v for k, v in self.desc["camera"].items() if k != "retries"}
        return {"camera": camera, **{k: self.desc.get(k) for k in ("scan", "exposure", "sample")}}

    def connect(self, port: str | None = None) -> RigController:
        """The controller at ``port`` (default: the description's ``controller.port``), identified."""
        c = self.desc["controller"]
        return RigController.connect(port or c["port"], baudrate=c.get("baudrate", 115200),
                                     timeout=c.get("timeout_s", 1.0))


CameraFactory = Callable[[RigDescription, RigController], Any]


def open_camera(rig: RigDescription, driver: RigController):
    """The description's camera backend; the virtual one sees the hardware through ``driver``."""
    desc = rig.desc["camera"]
    if desc["backend"] == "virtual":
        from ..truth.virtual_rig import VirtualCamera, VirtualRig
        for key in ("scene", "rig"):
            if key not in desc:
                raise InputError(rig.path, f"camera backend 'virtual' needs '{key}' (camera.{key})")
        return VirtualCamera(desc["scene"], VirtualRig.load(desc["rig"]), seed=int(desc.get("seed", 0)),
                             noise=bool(desc.get("noise", True)),
                             hardware=lambda: (driver.position(), driver.lit_led()))
    from . import cameras
    return cameras.open_camera(desc)


class Journal:
    """``journal.jsonl``: one JSON line per saved frame, appended and flushed to disk once its files are in place."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.path = self.folder / JOURNAL

    def saved(self) -> dict[int, dict]:
        """The saved frames, {frame index: entry}: entries whose exposure files all exist. A torn last line
        (a power cut while appending) and entries whose files are gone are left out: those frames are taken again."""
        if not self.path.is_file():
            return {}
        saved = {}
        for number, line in enumerate(self.path.read_text().splitlines(), start=1):
            try:
                entry = json.loads(line)
            except ValueError:
                log.warning("%s line %d: torn entry, ignored (its frame is taken again)", self.path, number)
                continue
            if all((self.folder / e["file"]).is_file() for e in entry["exposures"]):
                saved[entry["frame"]] = entry
        return saved

    def record(self, entry: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(entry) + "\n")
            f.flush()
            os.fsync(f.fileno())


def capture(rig: RigDescription, out_dir: str | Path, port: str | None = None,
            camera_factory: CameraFactory = open_camera) -> dict:
    """Capture the rig's scan into the capture folder ``out_dir`` (``manifest.json`` + ``frames/``); resumes an
    interrupted capture of the same description and calibration. Returns the manifest.

    Raises InputError for a bad description or calibration, RigError when the controller fails beyond the
    driver's retries, the camera backend's error when a bracket fails beyond ``camera.retries``.
    """
    from ..calibration.rigfile import RigCalibration
    calibration = RigCalibration.load(rig.calibration)
    key = rig.frames_key()
    out_dir = Path(out_dir)
    with atomic_dir(out_dir, key) as staging, contextlib.closing(rig.connect(port)) as driver:
        frames_dir = staging / "frames"
        frames_dir.mkdir(exist_ok=True)
        journal = Journal(staging)
        info = driver.info
        plan = _check_plan(rig, info, calibration)
        saved = journal.saved()
        if saved:
            log.info("resuming %s: %d of %d frames saved", out_dir, len(saved), len(plan))
        camera = camera_factory(rig, driver)
        try:
            log.info("controller %s on %s; camera %s", info.firmware, port or rig.desc["controller"]["port"],
                     camera.describe())
            _scan(rig, driver, camera, plan, saved, journal, frames_dir)
            truth = camera.truth(staging) if hasattr(camera, "truth") else None
        finally:
            with contextlib.suppress(RigError, OSError):
                driver.leds_off()
            camera.close()
        saved = journal.saved()
        captured = _manifest(rig, calibration, info, plan, saved, truth)
        manifest.save(staging / "manifest.json", captured)
    return captured


def check(rig: RigDescription, port: str | None = None, test_steps: int = 200) -> list[str]:
    """``facetsynth rig check``: the controller's identity, a homing, a test move of ``test_steps`` and back
    (each verified with ``POS?`` by the driver), every LED lit in turn and checked with ``LED?``, then the
    camera backend opened. One line of report per step; the first failure raises (RigError, InputError,
    the camera backend's error)."""
    lines = []
    with contextlib.closing(rig.connect(port)) as driver:
        info = driver.info
        lines.append(f"controller: firmware {info.firmware}, protocol {info.protocol}, {info.n_leds} LEDs, "
                     f"travel {info.max_steps} steps ({info.steps_per_mm:g} steps/mm) on "
                     f"{port or rig.desc['controller']['port']}")
        driver.home()
        move = min(test_steps, info.max_steps)
        driver.move_to(move)
        driver.move_to(0)
        lines.append(f"carriage: homed, moved to {move} steps and back, positions verified")
        try:
            for led in range(info.n_leds):
                driver.led_on(led)
                if driver.lit_led() != led:
                    raise RigError(f"LED {led} was switched on but the controller reports LED {driver.lit_led()}")
        finally:
            driver.leds_off()
        lines.append(f"LEDs: each of the {info.n_leds} lit in turn and confirmed, all off")
        camera = open_camera(rig, driver)
        try:
            lines.append(f"camera: {camera.describe()}")
        finally:
            camera.close()
    return lines


def _check_plan(rig: RigDescription, info: RigInfo, calibration) -> list[tuple[int, int]]:
    """The scan's frames, checked against the controller's identity and the calibration."""
    if rig.scan.travel_steps > info.max_steps:
        raise InputError(rig.path, f"scan.travel_steps {rig.scan.travel_steps} is beyond the controller's travel "
                                   f"({info.max_steps} steps, firmware {info.firmware})")
    if calibration.count != info.n_leds:
        raise InputError(rig.calibration, f"calibrates {calibration.count} LEDs, the controller has {info.n_leds} "
                                          f"(firmware {info.firmware}): calibrate this rig")
    return rig.scan.frames(info.n_leds)


def _scan(rig, driver, camera, plan, saved, journal, frames_dir) -> None:
    """Take every frame of ``plan`` that ``saved`` lacks, journaling each."""
    retries = int(rig.desc["camera"].get("retries", 2))
    driver.home()
    with tqdm(total=len(plan), initial=len(saved), desc="capture", unit="frame") as bar:
        for q, (steps, led) in enumerate(plan):
            if q in saved:
                continue
            if driver.position() != steps:
                driver.move_to(steps)
            driver.led_on(led)
            exposures = _bracket(camera, rig.times, frames_dir, f"{q:04d}", retries)
            journal.record({"frame": q, "led": led, "carriage_steps": steps,
                            "exposures": [{**e, "file": f"frames/{e['file']}"} for e in exposures]})
            bar.update()


def _bracket(camera, times, folder, stem, retries) -> list[dict]:
    """The camera's bracket, taken again up to ``retries`` times after an error."""
    for attempt in range(retries + 1):
        try:
            return camera.capture(times, folder, stem)
        except Exception as exc:   # the backend's error type; the last one propagates
            if attempt == retries:
                raise
            log.warning("frame %s: camera error (%s); taking it again (%d of %d)", stem, exc, attempt + 1, retries)
    raise AssertionError("unreachable")


def _manifest(rig, calibration, info, plan, saved, truth) -> dict:
    """The capture manifest: the calibrated camera and lights, the journal's frames in scan order."""
    missing = [q for q in range(len(plan)) if q not in saved]
    if missing:
        raise RuntimeError(f"{rig.path}: {len(missing)} frame(s) not saved after the scan (first: {missing[0]})")
    camera = calibration.camera()
    frames = []
    for q, (steps, led) in enumerate(plan):
        entry = saved[q]
        frames.append({"light": {"position": calibration.light_position(led, steps).tolist(),
                                 "intensity": calibration.intensity(led).tolist()},
                       "exposures": entry["exposures"], "led": led, "carriage_steps": steps})
    noise = rig.desc.get("noise", {})
    captured = {
        "version": 1, "units": "m",
        "sample": dict(rig.desc["sample"]),
        "camera": {"width": camera.width, "height": camera.height, "K": camera.K.tolist(), "R": camera.R.tolist(),
                   "t": camera.t.tolist(), "distortion": [float(d) for d in camera.distortion]},
        "saturation": rig.desc["exposure"]["saturation"],
        "noise": {"read_sigma": noise.get("read_sigma", 0.0), "shot_gain": noise.get("shot_gain", 0.0)},
        "frames": frames,
        "rig": {"name": rig.name, "firmware": info.firmware, "calibration": str(rig.calibration)},
    }
    if truth:
        captured["truth"] = truth
    return captured
