"""Stage ``hdr``: merge each frame's exposures into one scene-linear EXR (paper 002 sec. 4).

Exposures are EXR (linear exposure values) or, all of them, 8-bit images (JPEG, PNG, TIFF, told by the
pixel format: :func:`facetsynth.fileio.exposure_bits`): for those the camera response is recovered from
the capture's brackets (Debevec and Malik 1997, :mod:`facetsynth.response`), the codes linearized with it
and merged with its 8-bit sensor model (code 255 clipped, code 0 the noise floor, quantisation noise); the
manifest's ``saturation`` and ``noise`` are then not used (the linear scale puts clipping at 1).

A manifest that declares the ``transfer`` of its 8-bit exposures (sRGB, linear or a gamma,
:mod:`facetsynth.transfer`) and optionally a ``black_level`` replaces the recovery: the codes are decoded
with it, the black level subtracted (``max(0, L - b) / (1 - b)``: code 255 stays 1), and merged with the
same sensor model (:meth:`facetsynth.response.Response.from_transfer`), so one exposure per frame is
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

from .. import manifest as manifest_io
from .. import plausibility
from ..errors import InputError
from ..fileio import atomic_dir, exposure_bits, file_key, read_codes, read_exr, read_rgb, write_exr, write_json
from ..frames import map_frames
from ..hdr import SensorModel, merge_exposures
from ..lightplane import LightTriangulation
from ..metrics import relative_errors
from ..response import Response, ResponseSettings, recover_response
from ..transfer import Transfer, parse as parse_transfer
from .common import RuleFiles, StageSettings, flag_degenerate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Inputs(RuleFiles):
    """Rule ``hdr``'s input: capture's folder (``manifest.json`` and the exposures)."""
    capture: Path


@dataclass(frozen=True)
class Outputs(RuleFiles):
    """Rule ``hdr``'s outputs: the merged frames' folder, their manifest and the stage's figures."""
    frames: Path
    manifest: Path
    metrics: Path


@dataclass(frozen=True)
class Settings(StageSettings):
    """The stage's knobs: config ``hdr`` (workflow/schemas/config.schema.yaml)."""
    floor_sigmas: float = 3.0         # exposure values below floor_sigmas x read noise are ignored
    saturation_margin: float = 0.02   # values above (1 - margin) x saturation count as clipped


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1, *,
        response_settings: ResponseSettings = ResponseSettings()) -> None:
    """Load, merge, write: every frame of the capture ``inputs.capture`` merged into ``outputs.frames/NNNN.exr``,
    an HDR manifest ``outputs.manifest`` and ``outputs.metrics``.

    The output manifest describes the merged frames as a capture with one
    exposure of time 1 per frame and no clipping, so it is itself importable.
    Frames get channels R, G, B and ``saturated`` (1 where every exposure clipped); they are merged on
    ``threads`` threads. Negative exposure values are clipped (:class:`Negatives`): their count is
    in the metrics (``negative_values``) and each frame's header, and a WARNING names the first file.
    A run killed at any point resumes in the staging folder, to the same bytes.
    8-bit exposures (module docstring): the recovered or declared curve is in the metrics (``response``),
    a declared transfer and black level also as ``transfer``.
    """
    capture = manifest_io.load(inputs.capture)
    manifest_path = Path(capture["_dir"]) / "manifest.json"
    _check_lights(capture, manifest_path)
    # The plausibility checks of ``facetsynth check`` (:mod:`facetsynth.plausibility`), for a capture that
    # skipped it: refused here, before it becomes a model; its warnings logged and kept in the metrics.
    warnings = plausibility.check_geometry(capture, manifest_path) + plausibility.duplicate_files(capture)
    plausibility.check_truth_scene(capture, manifest_path)
    on_sample = plausibility.sample_pixels(capture)
    noise = capture.get("noise", {})
    sensor = SensorModel(saturation=capture.get("saturation"), read_sigma=noise.get("read_sigma", 0.0),
                         shot_gain=noise.get("shot_gain", 0.0), floor_sigmas=settings.floor_sigmas,
                         saturation_margin=settings.saturation_margin)
    shape = (capture["camera"]["height"], capture["camera"]["width"], 3)
    response = None
    transfer, black_level = _declared_transfer(capture, manifest_path)
    if _eight_bit(capture, manifest_path):
        if transfer is not None:
            response = Response.from_transfer(transfer, black_level)
            log.info("8-bit exposures: declared transfer %s, black level %g", transfer.describe(), black_level)
        else:
            response = _recover_response(capture, shape, manifest_path, response_settings)
            log.info("8-bit exposures: camera response recovered (Debevec-Malik 1997; scale from %s)",
                     ", ".join(response.scale_from))
        sensor = response.sensor_model(settings.floor_sigmas)
    elif transfer is not None:
        raise InputError(manifest_path, f'"transfer" ({transfer.describe()}) applies to 8-bit exposures only; '
                                        f"these are EXR (linear exposure values, e.g. "
                                        f"{capture['frames'][0]['exposures'][0]['file']}): drop the key")
    frames_dir, manifest_out = Path(outputs.frames), Path(outputs.manifest)
    key = {"capture": file_key(manifest_path), "sensor": asdict(sensor)}
    if response is not None:
        key["response"] = hashlib.sha256(response.linear.tobytes()).hexdigest()
    with atomic_dir(frames_dir, key) as staging:

        def merge_frame(job: tuple[int, dict]) -> Merged:
            """Merge frame q (or read it back, if merged before an interruption)."""
            q, frame = job
            times = np.array([e["time"] for e in frame["exposures"]])
            out = staging / f"{q:04d}.exr"
            merged_before = _read_merged(out) if out.exists() else None
            if merged_before is None:
                files = [e["file"] for e in frame["exposures"]]
                values = np.stack([_read_exposure(file, shape, response) for file in files])
                merged, saturated = merge_exposures(values, times, sensor)
                write_exr(out, {"RGB": merged, "saturated": saturated.astype(np.float32)},
                          header=_negatives(files, values).header(), precision="float24")
                # Metrics from the stored (PXR24-rounded) values, as a resumed run reads them back.
                merged_before = _read_merged(out)
            merged, saturated, negatives = merged_before
            out_frame = {"light": frame["light"], "exposures": [{"file": f"{frames_dir.name}/{q:04d}.exr", "time": 1.0}]}
            errors = None
            if "radiance" in frame.get("truth", {}):
                truth = read_rgb(frame["truth"]["radiance"])
                # Pixels above the noise floor in the longest exposure, not clipped in all.
                above_floor = truth * times.max() > sensor.noise_floor
                errors = relative_errors(merged, truth, above_floor & ~saturated[..., None], sample=4096)
                out_frame["truth"] = {"radiance": os.path.relpath(frame["truth"]["radiance"], manifest_out.parent)}
            # Dark: no pixel above the noise floor in the longest exposure (0 for a noise-free HDR import).
            dark = not (saturated.any() or (merged * times.max() > sensor.noise_floor).any())
            return Merged(out_frame, int(saturated.sum()), negatives, errors, dark,
                          int(np.count_nonzero(saturated & on_sample)))

        per_frame = map_frames(merge_frame, list(enumerate(capture["frames"])), threads, "hdr")
        dark = [q for q, m in enumerate(per_frame) if m.dark]
        if len(dark) == len(per_frame):
            raise InputError(manifest_path, f"all {len(dark)} frames are dark (no pixel above the sensor's noise "
                                            f"floor, {sensor.noise_floor:g}): nothing was measured; check that "
                                            "the lights fire, the lens is uncovered and the exposures are long "
                                            "enough")
        warnings += plausibility.check_clipping([m.clipped_on_sample for m in per_frame], int(on_sample.sum()),
                                                capture, manifest_path, "hdr")
    frames = [m.frame for m in per_frame]
    saturated_total = sum(m.saturated for m in per_frame)
    negatives = Negatives.total([m.negatives for m in per_frame])
    errors = [m.errors for m in per_frame if m.errors is not None]
    # The merged frames are linear EXR: the 8-bit exposures' transfer and black level do not apply to them.
    hdr_manifest = {**{k: v for k, v in capture.items() if k not in ("frames", "_dir", "transfer", "black_level")},
                    "saturation": None}
    hdr_manifest["frames"] = frames
    hdr_manifest["noise"] = {"read_sigma": 0.0, "shot_gain": 0.0}
    if "scene" in capture.get("truth", {}):
        hdr_manifest["truth"] = {"scene": os.path.relpath(capture["truth"]["scene"], manifest_out.parent)}
    manifest_io.save(manifest_out, hdr_manifest)

    metrics = {"ground_truth": bool(errors), "frames": len(frames), "saturated_pixels": saturated_total,
               "negative_values": negatives.count, "dark_frames": len(dark)}
    if warnings:
        metrics["warnings"] = warnings
        for warning in warnings:
            log.warning("%s: %s", manifest_path, warning)
    if dark:
        flag_degenerate(metrics, f"{len(dark)} of {len(frames)} frames are dark (no pixel above the noise floor; "
                                 f"the first: frame {dark[0]}, {capture['frames'][dark[0]]['exposures'][0]['file']}): "
                                 "the fit takes them as measurements of black reflectance in those light "
                                 "directions, which pulls the NDF and ks down there; if those lights did not fire, "
                                 "drop their frames from the manifest (or the .lp) and re-run from hdr", log)
    if negatives.count:
        log.warning("%d exposure values are negative (first in %s): taken as read noise around the black "
                    "level, below the noise floor, and clipped to 0", negatives.count, negatives.first_file)
    if response is not None:
        metrics["exposure_bits"] = 8
        if transfer is not None:
            metrics["transfer"] = {"declared": transfer.to_json(), "description": transfer.describe(),
                                   "black_level": black_level}
            method = f"declared transfer: {transfer.describe()}, black level {black_level:g}"
        else:
            method = "Debevec and Malik 1997 (cv2.createCalibrateDebevec)"
        metrics["response"] = {"method": method, "scale_from": list(response.scale_from),
                               "sensor": asdict(sensor), **response.to_json()}
    if errors:
        metrics["median_rel_error"] = float(np.median(np.concatenate(errors)))
        log.info("HDR median relative error against the true radiance: %.5f", metrics["median_rel_error"])
    write_json(outputs.metrics, metrics)


def _check_lights(capture: dict, manifest_path: Path) -> None:
    """The method interpolates each point's samples over one triangulation of the lights in their plane
    (:class:`facetsynth.lightplane.LightTriangulation`, resample): lights that span no area (fewer than 3,
    or all on one line) are an error here, before any frame is merged."""
    try:
        LightTriangulation.from_lights(manifest_io.lights(capture["frames"]))
    except ValueError as exc:
        raise InputError(manifest_path, f"too few lights for the method: {exc}; capture under lights spread over "
                                        "a plane above the sample (the paper: 20 x 24 = 480)") from None


class Merged(NamedTuple):
    """One merged frame: its manifest entry, saturated pixel count, its exposures' negative values, its
    relative errors against the truth (None without truth), whether it is dark, and its saturated pixels
    among those that see the sample (:func:`facetsynth.plausibility.check_clipping`)."""
    frame: dict
    saturated: int
    negatives: "Negatives"
    errors: np.ndarray | None
    dark: bool
    clipped_on_sample: int = 0


@dataclass(frozen=True)
class Negatives:
    """Exposure values below 0 (of a frame, or of the capture): how many, and the first file holding one.

    A sensor's read noise around its black level makes dark values negative: they are noise, not
    signal, so the merge keeps clipping them (:func:`facetsynth.hdr.merge_exposures`), but says so.
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
        return parse_transfer(capture["transfer"]), black_level
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
    common exposure times (:func:`facetsynth.response.recover_response`)."""
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
