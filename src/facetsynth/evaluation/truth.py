"""What a virtual capture's truth is at the rectified points, and the one rule for which points are scored.

A virtual capture (the rig's, or Mitsuba's) names its true scene in rectify's geometry
(:attr:`facetsynth.stages.common.RectifiedCapture.truth_scene`); a real capture has none, and every scorer of
this package returns ``{}`` for it. Which points are scored:

* :func:`analytic_points`: the visible points whose true BRDF is eq. 6, the only ones with a true kd, ks, eta
  and NDF (a measured or conductor truth's are placeholders): kd, ks, eta and F0 are scored on all of them;
* :func:`scored_points`: every k-th of the visible points (k = their count // :data:`METRIC_POINTS`, so about
  :data:`METRIC_POINTS` to twice that) that are analytic: the per-point NDFs (partial, completed), whose truth
  is a table per point, are scored on these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..io.errors import InputError
from ..io.fileio import read_yaml
from ..truth.scene import MaterialMaps, Scene
from ..stages.common import RectifiedCapture

METRIC_POINTS = 1024   # the per-point NDFs are scored on every k-th visible point, k = visible // METRIC_POINTS


def check_truth_scene(capture: dict[str, Any], path: str | Path | None) -> None:
    """A virtual capture's ``truth/scene`` must be a scene file: InputError naming the key otherwise (the
    scene's own error is bounded: never the contents of another file)."""
    scene = capture.get("truth", {}).get("scene")
    if scene is None:
        return
    try:
        document = read_yaml(scene)   # its errors give a line and column, never the text
        if not isinstance(document, dict):
            raise InputError(scene, f"holds {type(document).__name__ if document is not None else 'nothing'}, "
                                    "not a scene (a YAML mapping with name, size and regions)")
        Scene.from_dict(document, scene)
    except InputError as exc:
        raise InputError(path, f"invalid capture manifest at 'truth/scene': not a scene file: {exc}") from None


def truth_of(capture: RectifiedCapture) -> MaterialMaps | None:
    """The true SVBRDF parameters at every point of a virtual capture; None for a real one."""
    if capture.truth_scene is None:
        return None
    return Scene.load(capture.truth_scene).parameters(capture.points[:, :2])


def analytic_points(capture: RectifiedCapture, truth: MaterialMaps) -> np.ndarray:
    """(P,) bool: the visible points whose truth is eq. 6 (on a region, ``MaterialMaps.analytic``): the only
    points where a true kd, ks, eta or NDF exists to score a fit against (a measured or conductor truth's are
    placeholders)."""
    return capture.visible & (truth.region >= 0) & np.asarray(truth.analytic, bool).reshape(capture.visible.shape)
def median_rel_error(fitted: np.ndarray, true: np.ndarray, on: np.ndarray) -> float | None:
    """The median over the points ``on`` of |mean(fitted) - mean(true)| / mean(true), channel means of (P, 3)
    maps, where the truth's mean is > 0; None where no point is left."""
    t = np.asarray(true, float).reshape(-1, 3).mean(axis=1)
    sel = on & (t > 0)
    return float(np.median(np.abs(np.asarray(fitted).mean(axis=1)[sel] - t[sel]) / t[sel])) if sel.any() else None


def scored_points(capture: RectifiedCapture, truth: MaterialMaps | None) -> np.ndarray:
    """(P,) bool: every k-th visible point (k = visible // :data:`METRIC_POINTS`) whose truth is eq. 6
    (:func:`analytic_points`); none without a truth."""
    scored = np.zeros(capture.n_points, bool)
    if truth is None:
        return scored
    visible = np.flatnonzero(capture.visible)
    scored[visible[:: max(1, visible.size // METRIC_POINTS)]] = True
    return scored & analytic_points(capture, truth)


def median_or_none(errors: np.ndarray) -> float | None:
    """The median of the finite ``errors``; None where there is none."""
    values = np.asarray(errors, float)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None
