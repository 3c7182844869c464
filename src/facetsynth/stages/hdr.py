"""Stage ``hdr``: merge each frame's exposures into one scene-linear EXR (paper 002 sec. 4)."""

from __future__ import annotations

import logging
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import manifest as manifest_io
from ..errors import InputError
from ..fileio import atomic_dir, file_key, read_frame, read_rgb, write_exr, write_json
from ..frames import map_frames
from ..hdr import SensorModel, merge_exposures
from ..metrics import relative_errors

log = logging.getLogger(__name__)


def run(capture_dir: str | Path, frames_dir: str | Path, manifest_out: str | Path, metrics_out: str | Path,
        floor_sigmas: float = 3.0, saturation_margin: float = 0.02, threads: int = 1) -> None:
    """Merge every frame; write ``frames_dir/NNNN.exr``, an HDR manifest and metrics.

    The output manifest describes the merged frames as a capture with one
    exposure of time 1 per frame and no clipping, so it is itself importable.
    Frames get channels R, G, B and ``saturated`` (1 where every exposure clipped); they are merged on
    ``threads`` threads.
    """
    capture = manifest_io.load(capture_dir)
    noise = capture.get("noise", {})
    sensor = SensorModel(saturation=capture.get("saturation"), read_sigma=noise.get("read_sigma", 0.0),
                         shot_gain=noise.get("shot_gain", 0.0), floor_sigmas=floor_sigmas,
                         saturation_margin=saturation_margin)
    shape = (capture["camera"]["height"], capture["camera"]["width"], 3)
    frames_dir, manifest_out = Path(frames_dir), Path(manifest_out)
    key = {"capture": file_key(Path(capture["_dir"]) / "manifest.json"), "sensor": asdict(sensor)}
    with atomic_dir(frames_dir, key) as staging:

        def merge_frame(job: tuple[int, dict]) -> tuple[dict, int, np.ndarray | None]:
            """Merge frame q (or read it back, if merged before an interruption): its manifest entry, its
            saturated pixel count and its relative errors against the truth (None without truth)."""
            q, frame = job
            times = np.array([e["time"] for e in frame["exposures"]])
            out = staging / f"{q:04d}.exr"
            if out.exists():
                merged, saturated = read_frame(out)
            else:
                values = np.stack([_read_exposure(e["file"], shape) for e in frame["exposures"]])
                merged, saturated = merge_exposures(values, times, sensor)
                write_exr(out, {"RGB": merged, "saturated": saturated.astype(np.float32)}, precision="float24")
            out_frame = {"light": frame["light"], "exposures": [{"file": f"{frames_dir.name}/{q:04d}.exr", "time": 1.0}]}
            errors = None
            if "radiance" in frame.get("truth", {}):
                truth = read_rgb(frame["truth"]["radiance"])
                # Pixels above the noise floor in the longest exposure, not clipped in all.
                above_floor = truth * times.max() > sensor.noise_floor
                errors = relative_errors(merged, truth, above_floor & ~saturated[..., None], sample=4096)
                out_frame["truth"] = {"radiance": os.path.relpath(frame["truth"]["radiance"], manifest_out.parent)}
            return out_frame, int(saturated.sum()), errors

        per_frame = map_frames(merge_frame, list(enumerate(capture["frames"])), threads, "hdr")
    frames = [frame for frame, _, _ in per_frame]
    saturated_total = sum(count for _, count, _ in per_frame)
    errors = [e for _, _, e in per_frame if e is not None]
    hdr_manifest = {k: v for k, v in capture.items() if k not in ("frames", "saturation", "_dir")}
    hdr_manifest["frames"] = frames
    hdr_manifest["noise"] = {"read_sigma": 0.0, "shot_gain": 0.0}
    if "scene" in capture.get("truth", {}):
        hdr_manifest["truth"] = {"scene": os.path.relpath(capture["truth"]["scene"], manifest_out.parent)}
    manifest_io.save(manifest_out, hdr_manifest)

    metrics = {"ground_truth": bool(errors), "frames": len(frames), "saturated_pixels": saturated_total}
    if errors:
        metrics["median_rel_error"] = float(np.median(np.concatenate(errors)))
        log.info("HDR median relative error against the true radiance: %.5f", metrics["median_rel_error"])
    write_json(metrics_out, metrics)


def _read_exposure(file: str, shape: tuple[int, ...]) -> np.ndarray:
    image = read_rgb(file)
    if image.shape != shape:
        raise InputError(file, f"frame is {image.shape[1]}x{image.shape[0]}, the manifest's camera is "
                               f"{shape[1]}x{shape[0]}")
    return image
