"""What the per-point stages share: the rectified capture's geometry, tiling, scatter parts."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..capture import manifest
from ..io.errors import InputError
from ..io.fileio import BitRows, read_json
from ..fit.normals import shading_frames, to_local
from ..geometry.coverage import LightFootprint
from ..geometry.grid import DirectionGrid
from ..geometry.plane import PlaneGrid
from ..models.render import light_geometry, towards
from .settings import RuleFiles, StageSettings  # noqa: F401 (the stages import their bases from here)

log = logging.getLogger(__name__)

TILE_POINTS = 256  # points per tile: bounds the memory of every per-point stage


class ModelOutputs(RuleFiles):
    """The outputs of the rules that write the SVBRDF (``params``: the pipeline's, refine's start; ``refine``: the
    fitted one a user takes away): its folder and the fit's figures."""
    svbrdf: Path
    metrics: Path


@dataclass(frozen=True)
class RectifiedCapture:
    """``rectify/geometry.json``: the grid, the points, the lights, the view; and ``separate/geometry.json``, the
    same with each point's shading normal (:mod:`facetsynth.fit.normals`). With normals, every direction the
    stages get (:meth:`light_directions`, :meth:`view_directions`) is in the point's shading frame, so that
    each stage's eq. 6 is the point's own, and i.z is n(x) . i."""

    folder: Path
    grid: PlaneGrid
    visible: np.ndarray            # (P,) bool
    lights: np.ndarray             # (F, 4) homogeneous: (P, 1) point lights, (d, 0) directional
    light_intensities: np.ndarray  # (F, 3)
    view_point: np.ndarray         # (4,) homogeneous: (V, 1) the camera centre, (o, 0) orthographic
    frame_files: list[Path]
    truth_scene: Path | None
    normals: np.ndarray | None = None   # (P, 3) unit shading normals, world frame; None: the plane's +z

    @classmethod
    def load(cls, path: str | Path) -> "RectifiedCapture":
        path = Path(path)
        g = read_json(path)
        if "view_point" not in g:
            raise InputError(path, "a geometry file of an older facetsynth (no 'view_point'): re-run from rectify "
                                   "(snakemake --forcerun rectify)")
        truth = g.get("truth", {}).get("scene")
        return cls(folder=path.parent, grid=PlaneGrid.from_dict(g["grid"]),
                   visible=np.asarray(g["visible"], bool).ravel(),
                   lights=manifest.lights(g["frames"]),
                   light_intensities=manifest.light_intensities(g["frames"]),
                   view_point=np.asarray(g["view_point"], float),
                   frame_files=[path.parent / f["file"] for f in g["frames"]],
                   truth_scene=None if truth is None else (path.parent / truth).resolve(),
                   normals=None if "normals" not in g else np.load(path.parent / g["normals"]).astype(float))

    @cached_property
    def points(self) -> np.ndarray:
        """(P, 3) world positions of the points, row-major over the grid (made once: every tile of every
        stage indexes it; read-only, as it is shared)."""
        points = self.grid.points3d().reshape(-1, 3)
        points.flags.writeable = False
        return points

    @property
    def n_points(self) -> int:
        return self.grid.rows * self.grid.cols

    def view_directions(self, per_point: bool, index=slice(None)) -> np.ndarray:
        """o (p, 3) of the points ``index`` (default all): exact per point, or the paper's view at the sample
        centre."""
        points = self.points[index]
        o = towards(points if per_point else np.zeros_like(points), self.view_point)
        frames = self.frames(index)
        return o if frames is None else to_local(frames, o)

    def frames(self, index) -> np.ndarray | None:
        """The shading frames (p, 3, 3) of the points ``index`` (:func:`facetsynth.fit.normals.shading_frames`), None
        without normals, or when every normal is +z (a flat sample's: the frames would be the identity, exactly,
        and every stage would turn every direction by it): the world's directions of a point's grid are R^T d."""
        return None if not self.tilted else shading_frames(self.normals[index])

    @cached_property
    def tilted(self) -> bool:
        """Whether any point's shading normal differs from +z."""
        return self.normals is not None and bool(np.any(self.normals[:, :2] != 0))

    def validity(self, path: str | Path) -> BitRows:
        """separate's ``valid.npy``: whether each of the points' eq. 8 samples is valid, (P, F) bool read by rows
        (:class:`facetsynth.io.fileio.BitRows`); InputError naming the file if it is not this capture's."""
        return BitRows(path, len(self.frame_files), self.n_points, "sample validity")

    def light_coverage(self, grid: DirectionGrid):
        """``coverage(points)``: (len, T, F) how well the capture's lights sampled each grid direction from
        each of ``points`` (point indices), as W of eq. 12 needs it (:class:`LightFootprint`)."""
        footprint = LightFootprint.from_lights(self.lights)
        if footprint.at_infinity:
            log.info("directional lights: %d, spacing %.3f on their gnomonic plane z = 1", len(self.lights),
                     footprint.spacing)
        else:
            log.info("lights: %d, spacing %.1f mm, plane z = %.1f mm", len(self.lights), 1e3 * footprint.spacing,
                     1e3 * footprint.height)
        return lambda points: footprint.on_grid(self.points[points], grid, self.frames(points))

    def light_directions(self, index) -> tuple[np.ndarray, np.ndarray]:
        """i (p, F, 3) and |P - x|^2 (p, F) (1 for directional lights) of the points ``index``, eq. 8."""
        wi, r2 = light_geometry(self.points[index][:, None, :], self.lights[None])
        frames = self.frames(index)
        return (wi if frames is None else to_local(frames[:, None], wi)), r2


def part_points(n: int, part: int, parts: int, size: int = TILE_POINTS) -> slice:
    """The points of scatter part ``part`` of ``parts`` (0-based, config ``scatter.tiles``): whole tiles of
    ``size`` points, contiguous, so that every tile is processed exactly as in one unsplit run (per-point stages
    then join bitwise into its result; docs/decisions.md, "On a cluster"). Parts past the last tile are empty."""
    if not 0 <= part < parts:
        raise ValueError(f"scatter part {part} of {parts} does not exist")
    groups = np.array_split(np.arange(-(-n // size)), parts)[part]
    if groups.size == 0:
        return slice(n, n)
    return slice(int(groups[0]) * size, min(n, (int(groups[-1]) + 1) * size))


def scatter_item(item: str) -> tuple[int, int]:
    """(part, parts), part 0-based, of Snakemake's ``{scatteritem}`` wildcard "k-of-n"."""
    k, n = (int(x) for x in item.split("-of-"))
    return k - 1, n


def part_records(records: list) -> tuple[np.ndarray, dict]:
    """Scatter parts' records (.npz, each with the ``start`` of its points) in point order: the order of
    ``records`` by start, and every per-point array concatenated in that order (the ``start`` and any
    scalar, e.g. seconds, summed)."""
    loaded = [dict(np.load(r)) for r in records]
    order = np.argsort([int(record["start"]) for record in loaded], kind="stable")
    joined = {key: (np.concatenate([loaded[k][key] for k in order]) if loaded[0][key].ndim
                    else np.sum([loaded[k][key] for k in order]))
              for key in loaded[0] if key != "start"} if loaded else {}
    return order, joined


def flag_degenerate(metrics: dict, reason: str, log: logging.Logger) -> None:
    """A condition that still allows a weaker model (issue 15; docs/decisions.md, "Degenerate captures"): a
    WARNING in the stage's log and ``degenerate`` in its metrics (several reasons joined by "; "), never a
    silent model."""
    log.warning("DEGENERATE: %s", reason)
    metrics["degenerate"] = "; ".join(filter(None, [metrics.get("degenerate"), reason]))


def strided(index: np.ndarray, at_most: int) -> np.ndarray:
    """At most ``at_most`` entries of ``index``, evenly strided from its first (all when it has no more)."""
    return index[::max(1, -(-index.size // at_most))]


def tiles(n: int, size: int = TILE_POINTS):
    """Slices covering range(n) in tiles of ``size``."""
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))
