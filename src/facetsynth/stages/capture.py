"""Stage ``capture``: a virtual capture, an import, or the real rig (paper 002 sec. 4)."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture import manifest, plausibility
from ..truth import virtual_rig
from ..capture.rectify import sample_pixels
from ..io.errors import InputError
from ..evaluation.truth import check_truth_scene
from ..io.fileio import atomic_dir, read_exposure
from ..io.frames import map_frames
from ..capture.hdr import SensorModel
from ..rig import session
from ..rig.session import RigDescription
from ..truth.virtual_rig import VirtualRig
from .common import RuleFiles, StageSettings

log = logging.getLogger(__name__)

CHECK_THREADS = min(4, os.cpu_count() or 1)
"""Threads reading a capture's exposures in :func:`inspect_capture` (EXR decoding releases the GIL)."""


class Inputs(RuleFiles):
    """Rule ``capture``'s inputs: the sample sheet's ``path`` (a scene, a capture folder, an ``.lp`` file or a rig
    description), the files it names (``sources``) and, for a virtual sample, its rig description."""
    path: Path
    sources: list[Path] | None = None
    rig: Path | None = None


class Outputs(RuleFiles):
    """Rule ``capture``'s output: the capture folder (``manifest.json`` + frames)."""
    capture: Path


class Settings(StageSettings):
    """The rule's params: the sample sheet's ``source`` and ``rotation_deg``, the sample's rig description,
    config ``seed`` and ``virtual.noise``."""
    source: str = "virtual"         # virtual, import, lp or rig
    rig: str | Path | None = None   # the virtual rig's description (virtual samples)
    seed: int = 0                   # config seed: the virtual sensor's noise
    noise: bool = True              # config virtual.noise: sensor noise in a virtual capture
    rotation_deg: float = 0.0       # the virtual scene turned by this


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Produce the capture folder ``outputs.capture`` (``manifest.json`` + frames) for one sample: a virtual
    scene ``inputs.path`` turned by ``settings.rotation_deg`` on the virtual rig ``settings.rig``, its frames
    rendered on ``threads`` threads; a capture folder made elsewhere (``import``) or a light dome's ``.lp`` file
    (``lp``, its photos read where they are); or the real rig of the description ``inputs.path``
    (:mod:`facetsynth.rig.session`: resumes an interrupted capture)."""
    path, out_dir = inputs.path, outputs.capture
    if settings.source == "virtual":
        log.info("virtual capture of scene %s turned by %g deg with rig %s (seed %d, noise %s)", path,
                 settings.rotation_deg, settings.rig, settings.seed, settings.noise)
        virtual_rig.capture(path, VirtualRig.load(settings.rig), out_dir, seed=settings.seed, noise=settings.noise,
                            rotation_deg=settings.rotation_deg, threads=threads)
    elif settings.source in ("import", "lp"):
        import_capture(path, out_dir)
    else:
        session.capture(RigDescription.load(path), out_dir)


def check_capture(path: str | Path) -> dict:
    """Validate a capture folder (:func:`inspect_capture`), log its warnings, return the loaded manifest."""
    capture, warnings = inspect_capture(path)
    for warning in warnings:
        log.warning("%s: %s", path, warning)
    return capture


def inspect_capture(path: str | Path) -> tuple[dict, list[str]]:
    """Validate a capture folder as the pipeline will read it: the loaded manifest and the warnings.

    The manifest goes through :func:`facetsynth.capture.manifest.load` (schema and meaning); every exposure's
    pixels are read with the reader the ``hdr`` stage uses (:func:`facetsynth.io.fileio.read_exposure`: an
    EXR's values, an 8-bit image's codes), on threads. Errors (InputError, one line naming the file): a
    file that is not a readable EXR or 8-bit image with R, G, B of the camera's size; a NaN or Inf pixel (``hdr`` refuses them); every frame dark (nothing
    measured). Warnings, as the data still merge and fit: negative values (``hdr`` clips them to 0; a
    few are read noise around a subtracted black level, many say the black level is wrong) and dark
    frames (a light that did not fire, or lights nothing the camera sees; the other frames still fit).
    Dark is as ``hdr`` has it: no value of any exposure above the sensor's noise floor (3 read-noise
    sigmas of the manifest's ``noise``, the ``hdr`` default; 0 for noise-free data).
    Plausibility (:mod:`facetsynth.capture.plausibility`, issue 32; ``hdr`` checks the same): the sample's size
    against the camera's view of it and the lights' distances against the sample, before any pixel is
    read; a virtual capture's ``truth/scene``; clipping per frame and over the capture.
    """
    capture = manifest.load(path)
    source = Path(path) / "manifest.json" if Path(path).is_dir() else Path(path)
    warnings = plausibility.check_geometry(capture, source) + plausibility.duplicate_files(capture)
    check_truth_scene(capture, source)
    on_sample = sample_pixels(manifest.camera(capture), capture["sample"]["width"], capture["sample"]["height"],
                              whole=False)
    shape = (capture["camera"]["height"], capture["camera"]["width"], 3)
    floor = SensorModel(read_sigma=capture.get("noise", {}).get("read_sigma", 0.0)).noise_floor

    def read_frame(frame: dict) -> tuple[list[ExposureStats], int]:
        """A frame's exposures' stats, and its sample pixels clipped in every exposure."""
        stats, clipped = [], None
        for e in frame["exposures"]:
            s, c = _read_exposure(e["file"], shape, floor, capture)
            stats.append(s)
            clipped = c if clipped is None else clipped & c
        return stats, int(np.count_nonzero(clipped.any(axis=-1) & on_sample))

    read = map_frames(read_frame, capture["frames"], CHECK_THREADS, "check")
    per_frame = [stats for stats, _ in read]
    exposures = [stats for frame in per_frame for stats in frame]
    _refuse_nonfinite(exposures)
    _refuse_mixed_kinds(exposures, capture["_dir"])
    warnings += plausibility.check_clipping([c for _, c in read], int(on_sample.sum()), capture, source)
    negative = [s for s in exposures if s.negative]
    if negative:
        warnings.append(f"{sum(s.negative for s in negative)} negative value(s) in {len(negative)} of "
                        f"{len(exposures)} exposure files (first: {negative[0].file}); hdr clips them to 0")
    dark = [q for q, frame in enumerate(per_frame) if not any(s.lit for s in frame)]
    if len(dark) == len(per_frame):
        raise InputError(path, f"every frame is dark: no value above the noise floor ({floor:g}) in any of the "
                               f"{len(exposures)} exposure files; nothing was measured")
    if dark:
        warnings.append(f"{len(dark)} of {len(per_frame)} frame(s) are dark, no value above the noise floor "
                        f"({floor:g}) in any exposure (first: frame {dark[0]}, "
                        f"{capture['frames'][dark[0]]['exposures'][0]['file']})")
    if capture.get("assumed"):
        warnings.append(assumed_note(capture["assumed"], capture.get("source", {}).get("lp")))
    return capture, warnings


def assumed_note(assumed: list[str], lp: str | None) -> str:
    """What a capture (an ``.lp``) did not say and the pipeline assumes (:mod:`facetsynth.rti.lp`)."""
    said = {"camera": "an orthographic camera looking straight down", "pixel_size_mm": "0.1 mm per pixel",
            "intensities": "light intensities estimated per light from the photos",
            "transfer": "sRGB photos", "black_level": "black level 0"}
    where = f" in {Path(lp).with_suffix('.yaml').name} beside the .lp" if lp else ""
    return ("assumed, as the capture does not say: " + "; ".join(said.get(a, a) for a in assumed)
            + f" (override{where})")


@dataclass(frozen=True)
class ExposureStats:
    """What :func:`inspect_capture` found in one exposure file's pixels."""

    file: str
    bits: int | None                         # 8: an 8-bit image's codes; None: an EXR's linear values
    nonfinite: int                           # pixels with a NaN or Inf channel
    first_nonfinite: tuple[int, int] | None  # (row, col) of the first
    negative: int                            # negative values (channels) of finite pixels
    lit: bool                                # some value above the noise floor


def _read_exposure(file: str, shape: tuple[int, int, int], floor: float,
                   capture: dict) -> tuple[ExposureStats, np.ndarray]:
    """Read one exposure as ``hdr`` does; count its non-finite pixels and negative values, and whether some
    value is above the noise ``floor``; with its (H, W, 3) clipped values (:func:`plausibility.clip_level`).
    A file of another size than the camera's is refused from its header, before its pixels are read."""
    try:
        rgb, bits = read_exposure(file, shape[:2])
    except InputError as exc:
        if exc.problem.startswith("frame is "):
            raise InputError(file, exc.problem.split(" (the file's header")[0]) from None
        raise InputError(file, f"unreadable frame: {exc.problem}") from None
    if rgb.shape != shape:
        raise InputError(file, f"frame is {rgb.shape[1]}x{rgb.shape[0]}, the manifest's camera is "
                               f"{shape[1]}x{shape[0]}")
    return _stats(file, rgb, bits, floor), ~(rgb < plausibility.clip_level(capture, bits))


def _stats(file: str, rgb: np.ndarray, bits: int | None, floor: float) -> ExposureStats:
    """One exposure's :class:`ExposureStats`."""
    lowest, highest = float(rgb.min()), float(rgb.max())   # NaN if any pixel is NaN: the fast path is all finite
    if np.isfinite(lowest) and np.isfinite(highest):
        negative = 0 if lowest >= 0 else int((rgb < 0).sum())
        return ExposureStats(file=file, bits=bits, nonfinite=0, first_nonfinite=None, negative=negative, lit=highest > floor)
    finite = np.isfinite(rgb).all(axis=-1)
    bad = np.argwhere(~finite)
    return ExposureStats(file=file, bits=bits, nonfinite=len(bad), first_nonfinite=(int(bad[0][0]), int(bad[0][1])),
                         negative=int((rgb[finite] < 0).sum()), lit=bool((rgb[finite] > floor).any()))


def _refuse_mixed_kinds(exposures: list[ExposureStats], folder: str) -> None:
    """InputError when some exposures are EXR and others 8-bit images (``hdr`` merges one kind), naming one of each."""
    first = {}
    for s in exposures:
        first.setdefault(s.bits, s.file)
    if len(first) > 1:
        raise InputError(Path(folder) / "manifest.json", f"exposures mix EXR ({first[None]}) and 8-bit images "
                                                         f"({first[8]}): convert them to one kind")


def _refuse_nonfinite(exposures: list[ExposureStats]) -> None:
    """InputError naming the first exposure file with a NaN or Inf pixel, with the counts."""
    bad = [s for s in exposures if s.nonfinite]
    if bad:
        first = bad[0]
        row, col = first.first_nonfinite
        raise InputError(first.file, f"{first.nonfinite} pixel(s) are NaN or Inf (first at row {row}, col {col}); "
                                     f"{sum(s.nonfinite for s in bad)} such pixel(s) in {len(bad)} of "
                                     f"{len(exposures)} exposure files")


def import_capture(path: str | Path, out_dir: str | Path) -> None:
    """Validate a capture made elsewhere and publish its manifest with absolute frame paths."""
    capture = check_capture(path)
    log.info("imported %d frames from %s", len(capture["frames"]), path)
    with atomic_dir(out_dir) as staging:
        manifest.save(staging / "manifest.json", capture)
