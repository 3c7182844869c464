"""Stage ``rectify``: every HDR frame onto the regular sample-plane grid (paper 002 sec. 4)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..capture import manifest
from ..io.fileio import atomic_dir, file_key, read_frame, write_exr, write_json
from ..io.frames import map_frames
from ..io.errors import InputError
from ..geometry.camera import Camera
from ..geometry.plane import PlaneGrid
from ..capture.rectify import native_resolution, sample_pixels, visible_cells, warp_samples
from .common import RuleFiles, StageSettings

log = logging.getLogger(__name__)

WARP_FRAMES = 8   # frames warped together (capture.rectify.warp_samples): at 256^2, 29 -> 9 ms a frame


class Inputs(RuleFiles):
    """Rule ``rectify``'s inputs: hdr's merged frames (read through the manifest) and their manifest."""
    manifest: Path
    frames: Path | None = None


class Outputs(RuleFiles):
    """Rule ``rectify``'s outputs: the rectified frames' folder, the geometry and the stage's figures."""
    frames: Path
    geometry: Path
    metrics: Path


class Settings(StageSettings):
    """The stage's knobs: config ``rectify`` (workflow/schemas/config.schema.yaml; ``resolution`` from the preset)."""
    resolution: int | str = "auto"   # grid cells across the sample width; auto: as many as camera pixels see it
    filter: str = "triangle"         # OpenImageIO warp filter


def run(inputs: Inputs, outputs: Outputs, settings: Settings = Settings(), threads: int = 1) -> None:
    """Load, warp, write: every HDR frame of ``inputs.manifest`` onto a ``settings.resolution``-cell-wide grid
    over the sample. A virtual capture's registration and rectified radiance are scored against its truth by
    rule ``score_rectify`` (:mod:`facetsynth.stages.score_rectify`), beside the fit.

    ``resolution`` "auto": the grid with as many cells as camera pixels see the sample
    (:func:`facetsynth.capture.rectify.native_resolution`), logged; ``resolution_rule`` in the metrics says which.

    Writes ``outputs.frames/NNNN.exr`` (R, G, B, ``saturated``: 1 where a clipped pixel or no pixel of the sample
    alone reached the cell, i.e. no valid sample), and
    ``outputs.geometry`` (JSON): the grid and its (row, col) -> (x, y) mapping, the
    camera position (the view point V), the lights, the frame files and the
    ``visible`` cells. Cells are square; rows follow from the sample's aspect. Frames are warped on
    ``threads`` threads.
    """
    capture = manifest.load(inputs.manifest)
    camera = manifest.camera(capture)
    grid, rule = plane_grid(capture, camera, settings.resolution, inputs.manifest)
    visible = visible_cells(camera, grid)
    frames = warp_frames(capture, camera, grid, settings.filter, Path(outputs.frames), inputs.manifest, threads)
    write_geometry(capture, camera, grid, visible, frames, Path(outputs.geometry))
    metrics = {"ground_truth": manifest.has_truth(capture), "cols": grid.cols, "rows": grid.rows,
               "resolution_rule": rule, "visible_fraction": float(visible.mean())}
    write_json(outputs.metrics, metrics)


def plane_grid(capture: dict, camera: Camera, resolution: int | str, manifest_path: Path) -> tuple[PlaneGrid, str]:
    """The grid over the sample, ``resolution`` cells across (square cells, rows from the sample's aspect), and
    the rule that chose it: "fixed", or "auto" (as many cells as camera pixels see the sample, logged; a
    camera that cannot tell is an InputError naming the HDR ``manifest_path``)."""
    width, height = capture["sample"]["width"], capture["sample"]["height"]
    rule = "fixed"
    if resolution == "auto":
        try:
            resolution, rule = native_resolution(camera, width, height), "auto"
        except InputError as error:
            raise InputError(manifest_path, error.problem) from None
        log.info("resolution auto: %d cells across, as many cells as camera pixels see the sample", resolution)
    return PlaneGrid(width, height, cols=resolution, rows=max(1, int(round(resolution * height / width)))), rule


def warp_frames(capture: dict, camera: Camera, grid: PlaneGrid, filtername: str, frames_dir: Path, manifest_path: Path,
                threads: int = 1) -> list[dict]:
    """Every HDR frame warped onto ``grid`` from the pixels that see the sample alone (OpenImageIO filter
    ``filtername``, :func:`facetsynth.capture.rectify.warp_samples`, WARP_FRAMES frames in one warp; a cell that
    saw none is marked ``saturated``: no valid sample) into ``frames_dir/NNNN.exr`` on ``threads`` threads, published
    whole (:func:`facetsynth.io.fileio.atomic_dir`: an interrupted run resumes, skipping the frames already
    warped); returns each frame's geometry entry (its file, relative to the geometry's folder, and light)."""
    key = {"hdr": file_key(manifest_path), "grid": grid.to_dict(), "filter": filtername, "weights": "sample pixels"}
    warp = FrameWarp(capture, camera, grid, filtername)
    with atomic_dir(frames_dir, key) as staging:

        def rectify_frames(batch: list[int]) -> None:
            todo = [q for q in batch if not (staging / f"{q:04d}.exr").exists()]   # the others: before an interruption
            if not todo:
                return
            warped, seen = warp(todo)
            for q, cells in zip(todo, warped):
                invalid = (cells[..., 3] > 0) | ~seen
                write_exr(staging / f"{q:04d}.exr", {"RGB": cells[..., :3], "saturated": invalid.astype(np.float32)},
                          precision="float24")

        n = len(capture["frames"])
        map_frames(rectify_frames, [list(range(q, min(q + WARP_FRAMES, n))) for q in range(0, n, WARP_FRAMES)],
                   threads, "rectify", unit="batch")
    return [{"file": f"{frames_dir.name}/{q:04d}.exr", "light": frame["light"]}
            for q, frame in enumerate(capture["frames"])]


class FrameWarp:
    """HDR frames of ``capture`` (hdr's manifest) warped onto ``grid`` from the pixels that see the sample alone
    (:func:`facetsynth.capture.rectify.warp_samples`, OpenImageIO filter ``filtername``): what rectify writes,
    and what rule ``score_rectify`` scores without rectify's frames (deleted once separate has them)."""

    def __init__(self, capture: dict, camera: Camera, grid: PlaneGrid, filtername: str):
        self.capture, self.camera, self.grid, self.filtername = capture, camera, grid, filtername
        self.on_sample = sample_pixels(camera, capture["sample"]["width"],
                                       capture["sample"]["height"]).astype(np.float32)

    def __call__(self, frames: list[int]) -> tuple[list[np.ndarray], np.ndarray]:
        """The frames ``frames`` (indices) in one warp: each (rows, cols, 4) R, G, B and the warped ``saturated``
        mask, and which cells saw a pixel of the sample (rows, cols); every frame's cells bitwise its own warp's."""
        images = [np.dstack(read_frame(self.capture["frames"][q]["exposures"][0]["file"])) for q in frames]
        return warp_samples(images, self.on_sample, self.camera, self.grid, self.filtername)


def write_geometry(capture: dict, camera: Camera, grid: PlaneGrid, visible: np.ndarray, frames: list[dict],
                   geometry_out: Path) -> None:
    """rectify/geometry.json: the grid, the view point, the ``visible`` cells, the frames, what the capture
    assumed, its reference region, its camera, and a virtual capture's true scene (relative to
    ``geometry_out``'s folder)."""
    geometry = {"grid": grid.to_dict(), "view_point": camera.view_point.tolist(),
                "visible": visible.astype(int).tolist(), "frames": frames, "assumed": capture.get("assumed", []),
                **({"reference_region": capture["reference_region"]} if "reference_region" in capture else {}),
                "camera": {k: capture["camera"][k] for k in ("width", "height", "K", "R", "t", "projection")
                           if k in capture["camera"]}}
    if manifest.has_truth(capture):
        geometry["truth"] = {"scene": os.path.relpath(capture["truth"]["scene"], geometry_out.parent)}
    write_json(geometry_out, geometry)


