"""The capture manifest (DESIGN.md sec. 4): reading, validation, writing.

A capture is a folder holding ``manifest.json`` and frame files; the manifest
is validated against the published JSON schema
(``facetsynth/schemas/capture_manifest.schema.json``) and for its meaning
(:func:`validate`: finite numbers, a rotation, lights above the sample, the
camera in front of it) on every read. Frame paths are relative to the
manifest's folder or absolute.
"""

from __future__ import annotations

import difflib
import errno
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry.camera import Camera
from ..io.errors import InputError, excerpt
from ..io.fileio import read_json, write_json
from ..io import validation


ROTATION_TOLERANCE = 1e-5
"""Largest entry of |R R^T - I| accepted in ``camera/R``: loose enough for an R written with 6
decimals (rounding error <= 3e-6), tight enough to be a rotation to far below a pixel."""

NEVER_CLIPPED_HINT = 'state "saturation": null for data that were never clipped'

EXPOSURE_TIME_RANGE = (1e-9, 1e9)
"""Exposure times (s) the merge's arithmetic survives, and every shutter does: 1 ns to 31 years. The merge
works in float32 (1 / t, v / t, (t / t_max)^2, the shot noise t v): at 1e-320 s a frame came out NaN, at
1e308 s dark; within this range every term stays a normal float32 for values up to 1e20
(docs/decisions.md, "Hostile input: captures and config (issue 32)")."""


def validate(manifest: Any, path: str | Path | None = None) -> None:
    """Check a manifest's schema and meaning; raise InputError naming the file and the key's JSON path.

    The one check of a capture manifest: ``facetsynth check``, the capture/import stage, ``hdr`` and
    ``predict`` all read manifests through :func:`load`, so they can never disagree. Beyond the schema:
    every number is finite; ``camera/K`` is [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0;
    ``camera/R`` is a rotation (every entry of R R^T - I within :data:`ROTATION_TOLERANCE`, det R = +1);
    the camera is in front of the sample (its centre C = -R^T t has z > 0, and the sample's centre,
    the origin, is in front of it: t_z > 0; an orthographic camera looks down: r3_z < 0) and the origin
    projects inside the image (the whole sample need not: a close-up is legitimate); every light (its
    position, or a directional light's direction) is strictly above the sample plane (z > 0) and its
    intensity is not all zero; every exposure time within :data:`EXPOSURE_TIME_RANGE` and a frame's times
    distinct (and, on :func:`load`, a frame's files distinct). ``saturation`` is required: a number > 0, or null for data that were
    never clipped. A missing required key names any close match among the keys beside it.
    """
    _check_finite(manifest, path)
    try:
        validation.validate(manifest, "capture_manifest.schema.json", path, "capture manifest")
    except InputError as exc:
        raise InputError(path, exc.problem + _missing_key_hint(manifest, exc.problem)) from None
    with np.errstate(all="ignore"):    # finite values near 1e308 overflow to inf or NaN, which the checks refuse
        _check_camera(manifest["camera"], path)
    for q, frame in enumerate(manifest["frames"]):
        _check_light(frame["light"], f"frames/{q}/light", path)
        _check_times(frame["exposures"], f"frames/{q}/exposures", path)


def _check_times(exposures: list[dict[str, Any]], where: str, path: str | Path | None) -> None:
    """Each exposure time within :data:`EXPOSURE_TIME_RANGE`, and a frame's times distinct (a bracket of
    equal times is one exposure listed twice, or a time typed wrong: the merge would weigh them wrongly)."""
    low, high = EXPOSURE_TIME_RANGE
    seen: dict[float, int] = {}
    for e, exposure in enumerate(exposures):
        t = exposure["time"]
        if not low <= t <= high:
            raise _invalid(path, f"{where}/{e}/time", f"exposure time {t:.4g} s is outside [{low:g}, {high:g}] s, "
                                                      "the range the HDR merge's float arithmetic survives (a "
                                                      "time in other units than seconds?)")
        if t in seen:
            raise _invalid(path, f"{where}/{e}/time", f"exposure time {t:g} s is that of {where}/{seen[t]} too: a "
                                                      "frame's exposures need distinct times (one picture listed "
                                                      "twice, or a time typed wrong?)")
        seen[t] = e


def _invalid(path: str | Path | None, where: str, problem: str) -> InputError:
    """The one-line error for the value at JSON path ``where``."""
    return InputError(path, f"invalid capture manifest at '{where}': {problem}")


def _check_finite(document: Any, path: str | Path | None) -> None:
    """Every number in the document is finite (Python's json reads NaN, Infinity and 1e999 as floats)."""
    stack: list[tuple[tuple, Any]] = [((), document)]
    while stack:                       # iterative: a deeply nested unknown field cannot overflow the stack
        keys, value = stack.pop()
        if isinstance(value, dict):
            stack.extend(((*keys, k), v) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend(((*keys, i), v) for i, v in reversed(list(enumerate(value))))
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and not _finite(value):
            where = "/".join(map(str, keys)) or "(top level)"
            raise _invalid(path, where, f"{value!r:.40} is not a finite number")


def _finite(value: int | float) -> bool:
    """Whether a JSON number is finite as a float (an integer beyond 1.8e308 is not)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _missing_key_hint(manifest: Any, problem: str) -> str:
    """For a missing required key: a close match among the keys beside it ("did you mean"), and for
    ``saturation`` how to state never-clipped data. Empty for any other problem."""
    found = re.search(r"at '([^']*)': '([^']+)' is a required property", problem)
    if not found:
        return ""
    where, key = found.groups()
    parent = manifest
    try:
        for part in [] if where == "(top level)" else where.split("/"):
            parent = parent[int(part)] if isinstance(parent, list) else parent[part]
        typos = difflib.get_close_matches(key, [k for k in parent if isinstance(k, str)], n=1, cutoff=0.75)
    except (KeyError, IndexError, ValueError, TypeError):
        typos = []
    hints = [f"did you mean '{key}' for '{typo}'?" for typo in typos]
    if key == "saturation":
        hints.append(NEVER_CLIPPED_HINT)
    return "".join(f"; {hint}" for hint in hints)


def _check_camera(cam: dict[str, Any], path: str | Path | None) -> None:
    """K, R, and the camera's place: in front of the sample, with the sample's centre in the image."""
    K = np.asarray(cam["K"], dtype=float)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise _invalid(path, "camera/K", "focal lengths must be positive")
    if K[1, 0] != 0 or list(K[2]) != [0, 0, 1]:
        raise _invalid(path, "camera/K", f"not a camera matrix: its rows 2 and 3 must be [0, fy, cy] and "
                                         f"[0, 0, 1], not {K[1].tolist()} and {K[2].tolist()}")
    R = np.asarray(cam["R"], dtype=float)
    deviation, det = float(np.abs(R @ R.T - np.eye(3)).max()), float(np.linalg.det(R))
    if not (deviation <= ROTATION_TOLERANCE and det > 0):      # written so that NaN fails
        raise _invalid(path, "camera/R", f"not a rotation matrix (|R R^T - I| up to {deviation:.2g}, tolerance "
                                         f"{ROTATION_TOLERANCE:g}; det R = {det:.3g}, must be +1)")
    t = np.asarray(cam["t"], dtype=float)
    centre = -R.T @ t
    if cam.get("projection") == "orthographic":
        if not R[2, 2] < 0:
            raise _invalid(path, "camera/R", f"the orthographic camera looks along {_xyz(R[2])}, not down at the "
                                             "sample (its third row r3 needs z < 0)")
    elif not centre[2] > 0:
        raise _invalid(path, "camera/t", f"the camera centre C = -R^T t = {_xyz(centre)} is not above the "
                                         "sample plane (z = 0, normal +z): it needs z > 0")
    elif not t[2] > 0:
        raise _invalid(path, "camera/t", f"the camera looks away from the sample: the sample's centre lies "
                                         f"at depth t_z = {t[2]:.4g} m (needs > 0)")
    col, row = _camera(cam).project(np.zeros(3))
    if not (-0.5 <= col <= cam["width"] - 0.5 and -0.5 <= row <= cam["height"] - 0.5):
        raise _invalid(path, "camera", f"the sample's centre projects to (col {col:.1f}, row {row:.1f}), "
                                       f"outside the {cam['width']}x{cam['height']} image")


def _check_light(light: dict[str, Any], where: str, path: str | Path | None) -> None:
    """A light strictly above the sample plane (a directional one: from above it), with some intensity."""
    if "direction" in light:
        if not light["direction"][2] > 0:
            raise _invalid(path, f"{where}/direction/2", f"a directional light towards {_xyz(light['direction'])} "
                                                        "is not above the sample plane: it needs z > 0")
    elif not light["position"][2] > 0:
        raise _invalid(path, f"{where}/position/2", f"light at z = {light['position'][2]:.4g} m is not above the "
                                                   "sample plane (z = 0, normal +z): it needs z > 0")
    if not any(light["intensity"]):
        raise _invalid(path, f"{where}/intensity", "every channel is zero (a light must emit)")


def _xyz(v: np.ndarray) -> str:
    """A 3-vector as ``(x, y, z)`` with 4 significant digits."""
    return "(" + ", ".join(f"{x + 0.0:.4g}" for x in v) + ")"   # + 0.0: no "-0"


def load(path: str | Path, check_files: bool = True) -> dict[str, Any]:
    """Read and validate a manifest; resolve every frame path to an absolute one.

    ``path`` is the manifest file, the capture folder holding ``manifest.json``, or a light dome's ``.lp``
    file (:mod:`facetsynth.rti.lp`: directional lights, an orthographic camera, stated defaults). With
    ``check_files`` every exposure file must exist (InputError names the
    first missing one). The returned dict carries ``_dir`` (the capture folder).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "manifest.json"
    if path.is_dir():
        raise InputError(path, "is a folder, not a manifest file")
    manifest = _read_lp(path) if path.suffix.lower() == ".lp" else read_json(path)
    validate(manifest, path)
    folder = path.parent.resolve()
    for q, frame in enumerate(manifest["frames"]):
        listed: dict[str, int] = {}
        for e, exposure in enumerate(frame["exposures"]):
            where = f"frames/{q}/exposures/{e}/file"
            exposure["file"] = _resolve(folder, exposure["file"], where, path)
            if exposure["file"] in listed:
                raise _invalid(path, where, f"the file {exposure['file']} is also frames/{q}/exposures/"
                                            f"{listed[exposure['file']]}/file: one picture cannot be two exposures")
            listed[exposure["file"]] = e
            if check_files:
                _check_file(exposure["file"], path)
        if "truth" in frame and "radiance" in frame["truth"]:
            frame["truth"]["radiance"] = _resolve(folder, frame["truth"]["radiance"], f"frames/{q}/truth/radiance",
                                                  path)
    if "truth" in manifest and "scene" in manifest["truth"]:
        manifest["truth"]["scene"] = _resolve(folder, manifest["truth"]["scene"], "truth/scene", path)
    manifest["_dir"] = str(folder)
    return manifest


def _check_file(file: str, manifest_path: Path) -> None:
    """InputError unless the exposure ``file`` is a file: missing, a folder or a symlink loop said so."""
    if Path(file).is_file():
        return
    if Path(file).is_dir():
        raise InputError(file, f"frame file listed in {manifest_path} is a folder, not a file")
    if os.path.lexists(file):
        raise InputError(file, f"frame file listed in {manifest_path} is not a readable file (a broken link?)")
    raise InputError(file, f"frame file listed in {manifest_path} is missing")


def _read_lp(path: Path) -> dict[str, Any]:
    """The manifest of an ``.lp`` light file, its camera the size of its first photo."""
    from ..io.fileio import _oiio_spec
    from ..rti import lp
    files, _ = lp.read(path)
    first = _resolve(path.parent.resolve(), files[0], "frames/0/exposures/0/file", path)
    if not Path(first).is_file():
        raise InputError(first, f"photo listed on line 2 of {path} is missing")
    spec = _oiio_spec(Path(first))
    return lp.manifest(path, (spec.width, spec.height))


def _resolve(folder: Path, name: str, where: str, path: Path) -> str:
    """The absolute path of a file the manifest names (relative to its folder), or InputError when the
    name cannot be a path on this system (a NUL byte, a name too long)."""
    try:
        resolved = (folder / name).resolve()
        resolved.is_file()                     # raises OSError for a name too long
    except RuntimeError:                       # Python < 3.13: resolve() on a symlink loop
        raise _invalid(path, where, f"{folder / name} is a symbolic link loop, not a file") from None
    except (ValueError, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno == errno.ELOOP:
            raise _invalid(path, where, f"{folder / name} is a symbolic link loop, not a file") from None
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise _invalid(path, where, f"not a usable file name ({excerpt(reason)})") from None
    return str(resolved)


def save(path: str | Path, manifest: dict[str, Any]) -> None:
    """Validate and write a manifest atomically (private ``_`` keys dropped)."""
    clean = {k: v for k, v in manifest.items() if not k.startswith("_")}
    validate(clean, path)
    write_json(path, clean)


def camera(manifest: dict[str, Any]) -> Camera:
    """The manifest's camera."""
    return _camera(manifest["camera"])


def _camera(cam: dict[str, Any]) -> Camera:
    """The camera of a manifest's ``camera`` entry."""
    return Camera(width=cam["width"], height=cam["height"], K=np.asarray(cam["K"], float),
                  R=np.asarray(cam["R"], float), t=np.asarray(cam["t"], float),
                  distortion=np.asarray(cam.get("distortion", [0.0] * 5), float),
                  projection=cam.get("projection", "perspective"))


def light_point(light: dict[str, Any]) -> np.ndarray:
    """A manifest light as a homogeneous point (4,) (:mod:`facetsynth.models.render`): (P, 1) for a point light,
    (d / |d|, 0) for a directional one."""
    if "direction" in light:
        d = np.asarray(light["direction"], float)
        return np.append(d / np.linalg.norm(d), 0.0)
    return np.append(np.asarray(light["position"], float), 1.0)


def lights(frames: list[dict[str, Any]]) -> np.ndarray:
    """(F, 4) homogeneous lights of a manifest's (or a geometry file's) ``frames``."""
    return np.array([light_point(f["light"]) for f in frames]).reshape(-1, 4)


def light_intensities(frames: list[dict[str, Any]]) -> np.ndarray:
    """(F, 3) RGB light intensities L_q of a manifest's ``frames`` (W/sr; a directional light's: W/m^2)."""
    return np.array([f["light"]["intensity"] for f in frames], dtype=float).reshape(-1, 3)


def has_truth(manifest: dict[str, Any]) -> bool:
    """Whether the capture is virtual and carries its ground truth."""
    return "scene" in manifest.get("truth", {})
