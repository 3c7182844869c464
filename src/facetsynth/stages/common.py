"""What the per-point stages share: the rectified capture's geometry, tiling, truth."""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..fileio import read_json
from ..plane import PlaneGrid
from ..scene import MaterialMaps, Scene

TILE_POINTS = 256  # points per tile: bounds the memory of every per-point stage


class StageSettings:
    """Base of a stage's frozen settings dataclass: one field per key of its config section."""

    @classmethod
    def from_params(cls, params):
        """From a rule's ``params`` (the config section's keys)."""
        return cls(**{f.name: getattr(params, f.name) for f in fields(cls)})


@dataclass(frozen=True)
class RectifiedCapture:
    """``rectify/geometry.json``: the grid, the points, the lights, the view."""

    folder: Path
    grid: PlaneGrid
    visible: np.ndarray            # (P,) bool
    light_positions: np.ndarray    # (F, 3)
    light_intensities: np.ndarray  # (F, 3)
    view_position: np.ndarray      # (3,) camera centre V
    frame_files: list[Path]
    truth_scene: Path | None

    @classmethod
    def load(cls, path: str | Path) -> "RectifiedCapture":
        path = Path(path)
        g = read_json(path)
        truth = g.get("truth", {}).get("scene")
        return cls(folder=path.parent, grid=PlaneGrid.from_dict(g["grid"]),
                   visible=np.asarray(g["visible"], bool).ravel(),
                   light_positions=np.array([f["light"]["position"] for f in g["frames"]], float),
                   light_intensities=np.array([f["light"]["intensity"] for f in g["frames"]], float),
                   view_position=np.asarray(g["view_position"], float),
                   frame_files=[path.parent / f["file"] for f in g["frames"]],
                   truth_scene=None if truth is None else (path.parent / truth).resolve())

    @property
    def points(self) -> np.ndarray:
        """(P, 3) world positions of the points, row-major over the grid."""
        return self.grid.points3d().reshape(-1, 3)

    @property
    def n_points(self) -> int:
        return self.grid.rows * self.grid.cols

    def view_directions(self, per_point: bool) -> np.ndarray:
        """o per point (P, 3): exact per-point view, or the paper's view at the sample centre."""
        if per_point:
            d = self.view_position - self.points
        else:
            d = np.broadcast_to(self.view_position, (self.n_points, 3))
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def truth(self) -> MaterialMaps | None:
        """The true SVBRDF parameters at every point, for virtual captures."""
        if self.truth_scene is None:
            return None
        return Scene.load(self.truth_scene).parameters(self.points[:, :2])


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
