"""Stage ``hdr``: merge each frame's exposures into one scene-linear EXR (paper 002 sec. 4).

Exposures are EXR (linear exposure values) or, all of them, 8-bit images (JPEG, PNG, TIFF, told by the
pixel format: :func:`facetsynth.io.fileio.exposure_bits`): for those the camera response is recovered from
the capture's brackets (Debevec and Malik 1997, :mod:`facetsynth.capture.response`), the codes linearized with it
and merged with its 8-bit sensor model (code 255 clipped, code 0 the noise floor, quantisation noise); the
manifest's ``saturation`` and ``noise`` are then not used (the linear scale puts clipping at 1).

A manifest that declares the ``transfer`` of its 8-bit exposures (sRGB, linear or a gamma,
:mod:`facetsynth.capture.transfer`) and optionally a ``black_level`` replaces the recovery: the codes are decoded
with it, the black level subtracted (``max(0, L - b) / (1 - b)``: code 255 stays 1), and merged with the
same sensor model (:meth:`facetsynth.capture.response.Response.from_transfer`), so one exposure per frame is
enough (a light dome's one sRGB JPEG per light). A channel at code 255 is clipped: a pixel where every
exposure clipped is flagged ``saturated`` like a clipped HDR value. ``transfer`` on EXR exposures, and a
``black_level`` without a ``transfer``, are InputErrors.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..capture import manifest, plausibility
from ..capture.rectify import sample_pixels
from ..io.errors import InputError
from ..evaluation.hdr import frame_truth_errors, truth_scores
from ..evaluation.truth import check_truth_scene
from ..io.fileio import atomic_dir, exposure_bits, file_key, read_codes, read_exr, read_rgb, write_exr, write_json
from ..io.frames import map_frames
from ..capture.hdr import SensorModel, merge_exposures
from ..geometry.lightplane import LightTriangulation
from ..capture.response import Response, ResponseSettings, recover_response
from ..capture.transfer import Transfer, parse
from .common import RuleFiles, StageSettings, flag_degenerate

log = logging.getLogger(__name__)


class Inputs(RuleFiles):
    """Rule ``hdr``'s input: capture's folder (``manifest.json`` and the exposures)."""
    capture: Path


class Outputs(RuleFiles):
    """Rule ``hdr``'s outputs: the merged frames' folder, their manifest and the stage's figures."""
    frames: Path
    manifest: Path
    metrics: Path


class Settings(StageSettings):
    """The stage's knobs: config ``hdr`` (workflow/schemas/config.schema.yaml)."""
    floor_sigmas: float = 3.0         # exposure values below floor_sigmas x read noise are ignored
    saturation_margin: float = 0.02   # values above (1 - margin) x saturation count as clipped


@dataclass(frozen=True)
class Capture:
    """What the stage reads, checked: the capture's manifest (``_dir``: its folder) and path, the plausibility
    warnings of :func:`load`, the pixels that see the sample, the camera's image shape (H, W, 3), the sensor
    model the merge applies, and for 8-bit exposures their response (None: EXR) with the declared transfer
    (None: recovered from the brackets) and black level."""
    manifest: dict
    path: Path
    warnings: list[str]
    on_sample: np.ndarray
    shape: tuple[int, int, int]
    sensor: SensorModel
    response: Response | None = None
    transfer: Transfer | None = None
    black_level: float = 0.0


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1, *,
        response_settings: ResponseSettings = ResponseSettings()) -> None:
    """Load, merge, write: every frame of the capture ``inputs.capture`` merged into ``outputs.frames/NNNN.exr``,
    an HDR manifest ``outputs.manifest`` and ``outputs.metrics``; for a virtual capture, the merged frames
    scored against the true radiance (:func:`facetsynth.evaluation.hdr.truth_scores`).

    The output manifest describes the merged frames as a capture with one
    exposure of time 1 per frame and no clipping, so it is itself importable.
    Frames get channels R, G, B and ``saturated`` (1 where every exposure clipped); they are merged on
    ``threads`` threads. Negative exposure values are clipped (:class:`Negatives`): their count is
    in the metrics (``negative_values``) and each frame's header, and a WARNING names the first file.
    A run killed at any point resumes in the staging folder, to the same bytes.
    8-bit exposures (module docstring): the recovered or declared curve is in the metrics (``response``),
    a declared transfer and black level also as ``transfer``.
    """
    capture = load(inputs, settings, response_settings)
    merged, warnings = merge(capture, Path(outputs.frames), threads)
    write_manifest(capture.manifest, Path(outputs.frames), Path(outputs.manifest))
    metrics = merge_metrics(capture, merged, warnings)
    scores = truth_scores(merged)
    write_json(outputs.metrics, {"ground_truth": bool(scores), **metrics, **scores})


# ---------------------------------------------------------------------------- load
def load(inputs: Inputs, settings: Settings, response_settings: ResponseSettings = ResponseSettings()) -> Capture:
    """The capture's manifest, refused here if the method cannot use it (:func:`_check_lights`; the plausibility
    checks of ``facetsynth check``, :mod:`facetsynth.capture.plausibility`, for a capture that skipped it: refused
    before it becomes a model, its warnings kept for the metrics), and the sensor model it is merged with
    (:func:`sensor_model`)."""
    capture = manifest.load(inputs.capture)
    path = Path(capture["_dir"]) / "manifest.json"
    _check_lights(capture, path)
    warnings = plausibility.check_geometry(capture, path) + plausibility.duplicate_files(capture)
    check_truth_scene(capture, path)
    on_sample = sample_pixels(manifest.camera(capture), capture["sample"]["width"], capture["sample"]["height"],
                              whole=False)
    shape = (capture["camera"]["height"], capture["camera"]["width"], 3)
    sensor, response, transfer, black_level = sensor_model(capture, path, shape, settings, response_settings)
    return Capture(capture, path, warnings, on_sample, shape, sensor, response, transfer, black_level)


def sensor_model(capture: dict, path: Path, shape: tuple[int, int, int], settings: Settings,
                 response_settings: ResponseSettings) -> tuple[SensorModel, Response | None, Transfer | None, float]:
    """The sensor model of the merge, the 8-bit exposures' response (None for EXR), their declared transfer
    (None: the response recovered from the brackets) and black level. EXR: the manifest's ``saturation`` and
    ``noise``; 8-bit: the response's own model (module docstring). A transfer on EXR exposures is an InputError."""
    noise = capture.get("noise", {})
    sensor = SensorModel(saturation=capture.get("saturation"), read_sigma=noise.get("read_sigma", 0.0),
                         shot_gain=noise.get("shot_gain", 0.0), floor_sigmas=settings.floor_sigmas,
                         saturation_margin=settings.saturation_margin)
    transfer, black_level = _declared_transfer(capture, path)
    if not _eight_bit(capture, path):
        if transfer is not None:
            raise InputError(path, f'"transfer" ({transfer.describe()}) applies to 8-bit exposures only; '
                                   f"these are EXR (linear exposure values, e.g. "
                                   f"{capture['frames'][0]['exposures'][0]['file']}): drop the key")
        return sensor, None, None, black_level
    if transfer is not None:
        response = Response.from_transfer(transfer, black_level)
        log.info("8-bit exposures: declared transfer %s, black level %g", transfer.describe(), black_level)
    else:
        response = _recover_response(capture, shape, path, response_settings)
        log.info("8-bit exposures: camera response recovered (Debevec-Malik 1997; scale from %s)",
                 ", ".join(response.scale_from))
    return response.sensor_model(settings.floor_sigmas), response, transfer, black_level


# ---------------------------------------------------------------------------- merge
def merge(capture: Capture, frames_dir: Path, threads: int = 1) -> tuple[list[Merged], list[str]]:
    """Every frame merged (:func:`merge_frame`) on ``threads`` threads into ``frames_dir``, published whole
    (:func:`facetsynth.io.fileio.atomic_dir`: an interrupted run resumes in its staging folder, to the same
    bytes); returns the frames' figures and the capture's warnings, those of :func:`load` and of the clipping.
    A capture whose every frame is dark, or clipped, is an InputError, and nothing is published."""
    key = {"capture": file_key(capture.path), "sensor": asdict(capture.sensor)}
    if capture.response is not None:
        key["response"] = hashlib.sha256(capture.response.linear.tobytes()).hexdigest()
    with atomic_dir(frames_dir, key) as staging:
        jobs = list(enumerate(capture.manifest["frames"]))
        merged = map_frames(lambda job: merge_frame(capture, *job, staging), jobs, threads, "hdr")
        dark = [q for q, m in enumerate(merged) if m.dark]
        if len(dark) == len(merged):
            raise InputError(capture.path, f"all {len(dark)} frames are dark (no pixel above the sensor's noise "
                                           f"floor, {capture.sensor.noise_floor:g}): nothing was measured; check "
                                           "that the lights fire, the lens is uncovered and the exposures are long "
                                           "enough")
        warnings = capture.warnings + plausibility.check_clipping(
            [m.clipped_on_sample for m in merged], int(capture.on_sample.sum()), capture.manifest, capture.path, "hdr")
    return merged, warnings


def merge_frame(capture: Capture, q: int, frame: dict, staging: Path) -> Merged:
    """Merge frame q into ``staging/NNNN.exr`` (or read it back, if merged before an interruption), and its
    figures, measured on the stored (PXR24-rounded) values as a resumed run reads them back."""
    times = np.array([e["time"] for e in frame["exposures"]])
    out = staging / f"{q:04d}.exr"
    merged_before = _read_merged(out) if out.exists() else None
    if merged_before is None:
        files = [e["file"] for e in frame["exposures"]]
        values = np.stack([_read_exposure(file, capture.shape, capture.response) for file in files])
        merged, saturated = merge_exposures(values, times, capture.sensor)
        write_exr(out, {"RGB": merged, "saturated": saturated.astype(np.float32)},
                  header=_negatives(files, values).header(), precision="float24")
        merged_before = _read_merged(out)
    merged, saturated, negatives = merged_before
    noise_floor = capture.sensor.noise_floor
    # Dark: no pixel above the noise floor in the longest exposure (0 for a noise-free HDR import).
    dark = not (saturated.any() or (merged * times.max() > noise_floor).any())
    return Merged(int(saturated.sum()), negatives, frame_truth_errors(frame, merged, saturated, times, noise_floor),
                  dark, int(np.count_nonzero(saturated & capture.on_sample)))


# ---------------------------------------------------------------------------- write
def write_manifest(capture: dict, frames_dir: Path, manifest_out: Path) -> None:
    """The HDR manifest: the capture's manifest ``capture`` with the merged frames in ``frames_dir`` (one
    exposure of time 1 each, no clipping, no noise; a virtual capture's with their true radiance), its file names
    relative to ``manifest_out``'s folder. The merged frames are linear EXR: the 8-bit exposures' transfer and black
    level do not apply to them."""
    hdr_manifest = {**{k: v for k, v in capture.items() if k not in ("frames", "_dir", "transfer", "black_level")},
                    "saturation": None}
    hdr_manifest["frames"] = [_merged_frame(q, frame, frames_dir, manifest_out)
                              for q, frame in enumerate(capture["frames"])]
    hdr_manifest["noise"] = {"read_sigma": 0.0, "shot_gain": 0.0}
    if "scene" in capture.get("truth", {}):
        hdr_manifest["truth"] = {"scene": os.path.relpath(capture["truth"]["scene"], manifest_out.parent)}
    manifest.save(manifest_out, hdr_manifest)


def _merged_frame(q: int, frame: dict, frames_dir: Path, manifest_out: Path) -> dict:
    """Frame q's entry in the HDR manifest."""
    out_frame = {"light": frame["light"], "exposures": [{"file": f"{frames_dir.name}/{q:04d}.exr", "time": 1.0}]}
    if "radiance" in frame.get("truth", {}):
        out_frame["truth"] = {"radiance": os.path.relpath(frame["truth"]["radiance"], manifest_out.parent)}
    return out_frame


def merge_metrics(capture: Capture, merged: list[Merged], warnings: list[str]) -> dict:
    """The merge's figures of hdr/metrics.json (all but ``ground_truth`` and the truth's): frames, saturated
    pixels, negative values, dark frames (``degenerate``), the warnings (logged), and the 8-bit exposures'
    response."""
    frames, path = capture.manifest["frames"], capture.path
    negatives = Negatives.total([m.negatives for m in merged])
    dark = [q for q, m in enumerate(merged) if m.dark]
    metrics = {"frames": len(merged), "saturated_pixels": sum(m.saturated for m in merged),
               "negative_values": negatives.count, "dark_frames": len(dark)}
    if warnings:
        metrics["warnings"] = warnings
        for warning in warnings:
            log.warning("%s: %s", path, warning)
    if dark:
        flag_degenerate(metrics, f"{len(dark)} of {len(merged)} frames are dark (no pixel above the noise floor; "
                                 f"the first: frame {dark[0]}, {frames[dark[0]]['exposures'][0]['file']}): "
                                 "the fit takes them as measurements of black reflectance in those light "
                                 "directions, which pulls the NDF and ks down there; if those lights did not fire, "
                                 "drop their frames from the manifest (or the .lp) and re-run from hdr", log)
    if negatives.count:
        log.warning("%d exposure values are negative (first in %s): taken as read noise around the black "
                    "level, below the noise floor, and clipped to 0", negatives.count, negatives.first_file)
    if capture.response is not None:
        metrics.update(_response_metrics(capture))
    return metrics


def _response_metrics(capture: Capture) -> dict:
    """The 8-bit exposures' figures: their bits, the declared transfer and black level, the response curve."""
    metrics = {"exposure_bits": 8}
    transfer, black_level = capture.transfer, capture.black_level
    if transfer is not None:
        metrics["transfer"] = {"declared": transfer.to_json(), "description": transfer.describe(),
                               "black_level": black_level}
        method = f"declared transfer: {transfer.describe()}, black level {black_level:g}"
    else:
        method = "Debevec and Malik 1997 (cv2.createCalibrateDebevec)"
    metrics["response"] = {"method": method, "scale_from": list(capture.response.scale_from),
                           "sensor": asdict(capture.sensor), **capture.response.to_json()}
    return metrics


# ---------------------------------------------------------------------------- helpers
def _check_lights(capture: dict, manifest_path: Path) -> None:
    """The method interpolates each point's samples over one triangulation of the lights in their plane
    (:class:`facetsynth.geometry.lightplane.LightTriangulation`, resample): lights that span no area (fewer than 3,
    or all on one line) are an error here, before any frame is merged."""
    try:
        LightTriangulation.from_lights(manifest.lights(capture["frames"]))
    except ValueError as exc:
        raise InputError(manifest_path, f"too few lights for the method: {exc}; capture under lights spread over "
                                        "a plane above the sample (the paper: 20 x 24 = 480)") from None


class Merged(NamedTuple):
    """One merged frame's figures: its saturated pixel count, its exposures' negative values, its relative
    errors against the truth (None without truth, :func:`facetsynth.evaluation.hdr.frame_truth_errors`), whether it is dark, and its
    saturated pixels among those that see the sample (:func:`facetsynth.capture.plausibility.check_clipping`)."""
    saturated: int
    negatives: "Negatives"
    errors: np.ndarray | None
    dark: bool
    clipped_on_sample: int = 0


@dataclass(frozen=True)
class Negatives:
    """Exposure values below 0 (of a frame, or of the capture): how many, and the first file holding one.

    A sensor's read noise around its black level makes dark values negative: they are noise, not
    signal, so the merge keeps clipping them (:func:`facetsynth.capture.hdr.merge_exposures`), but says so.
    """
    count: int = 0
    first_file: str | None = None

    def header(self) -> dict:
        """The merged frame's EXR attributes: a resumed run reads the count back from the frame."""
        return {"negative_values": self.count} | ({"negative_file": self.first_file} if self.count else {})

    @classmethod
    def from_header(cls, header: dict) -> "Negatives":
        return cls(header["negative_values"], header.get("negative_file"))

    @classmethod
    def total(cls, parts: list["Negatives"]) -> "Negatives":
        """The capture's count, and the first file in frame order."""
        return cls(sum(n.count for n in parts), next((n.first_file for n in parts if n.count), None))


def _negatives(files: list[str], values: np.ndarray) -> Negatives:
    """The negative values of a frame's exposures ``values`` (E, H, W, 3) read from ``files``."""
    counts = [int(np.count_nonzero(v < 0)) for v in values]
    return Negatives.total([Negatives(c, f) for c, f in zip(counts, files)])


def _read_merged(path: Path) -> tuple[np.ndarray, np.ndarray, Negatives] | None:
    """A frame merged before an interruption: radiance, saturated mask and its exposures' negative values;
    None for a frame without the count (merged by an older version: merge it again)."""
    channels, header = read_exr(path)
    if "negative_values" not in header:
        return None
    return channels["RGB"], channels["saturated"] > 0, Negatives.from_header(header)


def _read_exposure(file: str, shape: tuple[int, ...], response: Response | None = None) -> np.ndarray:
    """One exposure's linear values: an EXR's as stored, an 8-bit image's codes through ``response``. A file
    whose header declares another size than the camera's is refused before its pixels are read."""
    image = read_rgb(file, shape=shape[:2]) if response is None else read_codes(file, shape[:2])
    if image.shape != shape:
        raise InputError(file, f"frame is {image.shape[1]}x{image.shape[0]}, the manifest's camera is "
                               f"{shape[1]}x{shape[0]}")
    return image if response is None else response.linearize(image)


def _declared_transfer(capture: dict, manifest_path: Path) -> tuple[Transfer | None, float]:
    """The manifest's declared ``transfer`` (None: recover the response from brackets) and ``black_level``
    (0 when absent); a black level without a transfer is an InputError (it would be silently ignored)."""
    black_level = float(capture.get("black_level", 0.0))
    if "transfer" not in capture:
        if black_level:
            raise InputError(manifest_path, f'"black_level" ({black_level:g}) applies to 8-bit exposures with a '
                                            'declared "transfer" only: declare the transfer of the 8-bit exposures '
                                            '(e.g. "transfer": "srgb"), or drop the key')
        return None, black_level
    if not 0.0 <= black_level < 1.0:
        raise InputError(manifest_path, f'"black_level" {black_level:g} is not in [0, 1)')
    try:
        return parse(capture["transfer"]), black_level
    except ValueError as exc:
        raise InputError(manifest_path, f'"transfer": {exc}') from None


def _eight_bit(capture: dict, manifest_path: Path) -> bool:
    """Whether the capture's exposures are 8-bit images (all of them) rather than EXR (all of them)."""
    kinds = {}
    for frame in capture["frames"]:
        for exposure in frame["exposures"]:
            kinds.setdefault(exposure_bits(exposure["file"]), exposure["file"])
            if len(kinds) > 1:
                raise InputError(manifest_path, f"exposures mix EXR ({kinds[None]}) and 8-bit images ({kinds[8]}): "
                                                "convert them to one kind")
    return 8 in kinds


RESPONSE_FRAMES = 8
"""Frames whose brackets the 8-bit camera response is recovered from (evenly spread over the capture)."""


def _recover_response(capture: dict, shape: tuple[int, ...], manifest_path: Path,
                      settings: ResponseSettings) -> Response:
    """The camera response from the brackets of up to RESPONSE_FRAMES frames taken with the capture's most
    common exposure times (:func:`facetsynth.capture.response.recover_response`)."""
    brackets = Counter(tuple(e["time"] for e in f["exposures"]) for f in capture["frames"])
    times = max(brackets, key=brackets.get)
    frames = [f for f in capture["frames"] if tuple(e["time"] for e in f["exposures"]) == times]
    chosen = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, RESPONSE_FRAMES).round().astype(int))]
    stacks = []
    for frame in chosen:
        codes = [read_codes(e["file"], shape[:2]) for e in frame["exposures"]]
        for e, c in zip(frame["exposures"], codes):
            if c.shape != shape:
                raise InputError(e["file"], f"frame is {c.shape[1]}x{c.shape[0]}, the manifest's camera is "
                                            f"{shape[1]}x{shape[0]}")
        stacks.append(np.stack(codes))
    return recover_response(stacks, times, settings, source=str(manifest_path))
