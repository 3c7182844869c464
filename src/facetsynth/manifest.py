"""The capture manifest (DESIGN.md sec. 4): reading, validation, writing.

A capture is a folder holding ``manifest.json`` and frame files; the manifest
is validated against the published JSON schema
(``facetsynth/schemas/capture_manifest.schema.json``) on every read. Frame
paths are relative to the manifest's folder or absolute.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .camera import Camera
from .errors import InputError
from .fileio import read_json, write_json
from .validation import validate as validate_schema


def validate(manifest: Any, path: str | Path | None = None) -> None:
    """Raise InputError naming the file and the offending key if invalid."""
    validate_schema(manifest, "capture_manifest.schema.json", path, "capture manifest")
    K = np.asarray(manifest["camera"]["K"], dtype=float)
    if K[2, 2] == 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, "invalid capture manifest at 'camera/K': focal lengths must be positive")
    R = np.asarray(manifest["camera"]["R"], dtype=float)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(path, "invalid capture manifest at 'camera/R': not a rotation matrix")


def load(path: str | Path, check_files: bool = True) -> dict[str, Any]:
    """Read and validate a manifest; resolve every frame path to an absolute one.

    ``path`` is the manifest file or the capture folder holding ``manifest.json``.
    With ``check_files`` every exposure file must exist (InputError names the
    first missing one). The returned dict carries ``_dir`` (the capture folder).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "manifest.json"
    manifest = read_json(path)
    validate(manifest, path)
    folder = path.parent.resolve()
    for frame in manifest["frames"]:
        for exposure in frame["exposures"]:
            exposure["file"] = str((folder / exposure["file"]).resolve())
            if check_files and not Path(exposure["file"]).is_file():
                raise InputError(exposure["file"], f"frame file listed in {path} is missing")
        if "truth" in frame and "radiance" in frame["truth"]:
            frame["truth"]["radiance"] = str((folder / frame["truth"]["radiance"]).resolve())
    if "truth" in manifest and "scene" in manifest["truth"]:
        manifest["truth"]["scene"] = str((folder / manifest["truth"]["scene"]).resolve())
    manifest["_dir"] = str(folder)
    return manifest


def save(path: str | Path, manifest: dict[str, Any]) -> None:
    """Validate and write a manifest atomically (private ``_`` keys dropped)."""
    clean = {k: v for k, v in manifest.items() if not k.startswith("_")}
    validate(clean, path)
    write_json(path, clean)


def camera(manifest: dict[str, Any]) -> Camera:
    """The manifest's camera."""
    cam = manifest["camera"]
    return Camera(width=cam["width"], height=cam["height"], K=np.asarray(cam["K"], float),
                  R=np.asarray(cam["R"], float), t=np.asarray(cam["t"], float),
                  distortion=np.asarray(cam.get("distortion", [0.0] * 5), float))


def light_positions(manifest: dict[str, Any]) -> np.ndarray:
    """(F, 3) light positions P_q in metres, world frame."""
    return np.array([f["light"]["position"] for f in manifest["frames"]], dtype=float)


def light_intensities(manifest: dict[str, Any]) -> np.ndarray:
    """(F, 3) RGB light intensities L_q."""
    return np.array([f["light"]["intensity"] for f in manifest["frames"]], dtype=float)


def has_truth(manifest: dict[str, Any]) -> bool:
    """Whether the capture is virtual and carries its ground truth."""
    return "scene" in manifest.get("truth", {})
