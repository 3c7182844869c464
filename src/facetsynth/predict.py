"""Prediction: render the frames a capture manifest describes from a fitted SVBRDF (DESIGN.md sec. 4).

Each pixel sees the sample-plane point through its centre (the camera's
plane homography, as the virtual rig renders); that point's radiance under
the frame's light is the pixel model read forwards (eq. 8),

    I = rho(x, i, o) (n . i) L / |P - x|^2,

written as scene-linear HDR (no exposure, no clipping, no noise): one EXR per
frame with channels R, G, B, plus a capture manifest describing the predicted
frames (one exposure of time 1 each), so that a prediction is itself a
capture. Pixels off the sample are 0.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from . import manifest as manifest_io
from .errors import InputError
from .fileio import write_exr
from .outputs import made_by, prepare_output_dir
from .normals import to_local
from .render import light_geometry, towards
from .svbrdf import CHUNK, SVBRDF

log = logging.getLogger(__name__)


class FrameRenderer:
    """Renders radiance images of one camera from an SVBRDF; the view-dependent terms are computed once."""

    def __init__(self, model, camera, supersample: int = 1):
        if camera.has_distortion:
            raise ValueError("lens distortion is not supported by predict yet (undistort the capture first)")
        self.model, self.camera, self.s = model, camera, int(supersample)
        xy = camera.pixel_plane_points(self.s)                       # (H s, W s, 2)
        points = np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)
        in_front = (points @ camera.R.T + camera.t)[..., 2] > 0       # the ray meets the plane ahead of the camera
        index, inside = model.point_index(xy)
        self.mask = inside & in_front
        self.points = points[self.mask]
        self.index = index[self.mask]
        self.wo = towards(self.points, camera.view_point)
        # shading normals (SVBRDF models that have them): directions in each point's frame, n(x) . i as the cosine
        self.frames = model.frames(self.index) if getattr(model, "normal", None) is not None else None
        if self.frames is not None:
            self.wo = to_local(self.frames, self.wo)
        # the camera is fixed: eq. 5's A(x, o) is computed once per pixel (SVBRDF models)
        self.area_o = model.area_at(self.index, self.wo) if hasattr(model, "area_at") else None

    @property
    def sample_mask(self) -> np.ndarray:
        """(H, W) pixels whose every sub-pixel sees the sample."""
        s = self.s
        m = self.mask.reshape(self.camera.height, s, self.camera.width, s)
        return m.all(axis=(1, 3))

    def radiance(self, light, light_intensity, diffuse_only: bool = False) -> np.ndarray:
        """(H, W, 3) float32 radiance I of the frame under a homogeneous light (4,) or a point light's position
        (3,), box-filtered over sub-pixels; ``diffuse_only``: the model's diffuse term kd/pi (n.i) L / r^2
        alone."""
        wi, r2 = light_geometry(self.points, light)
        if self.frames is not None:
            wi = to_local(self.frames, wi)
        value = np.zeros((len(self.index), 3))
        for a in range(0, len(self.index), CHUNK):
            sl = slice(a, a + CHUNK)
            if diffuse_only:
                value[sl] = self.model.kd[self.index[sl]] / np.pi
            elif self.area_o is None:
                value[sl] = self.model.eval_index(self.index[sl], wi[sl], self.wo[sl])
            else:
                value[sl] = self.model.eval_index(self.index[sl], wi[sl], self.wo[sl], self.area_o[sl])
        value *= (np.clip(wi[:, 2], 0.0, None) / r2)[:, None] * np.asarray(light_intensity, float)
        image = np.zeros(self.mask.shape + (3,))
        image[self.mask] = value
        s = self.s
        return image.reshape(self.camera.height, s, self.camera.width, s, 3).mean(axis=(1, 3)).astype(np.float32)


def load_model(path: str | Path):
    """A fitted model folder: the SVBRDF of paper 002 (default) or the Ward baseline (``model: ward``)."""
    from .fileio import read_json
    path = Path(path)
    if not path.is_dir():
        found = "is a file" if path.exists() else "not found"
        raise InputError(path, f"{found}; expected a fitted model folder holding model.json")
    meta = read_json(path / "model.json")
    if not isinstance(meta, dict):
        raise InputError(path / "model.json", f"expected a JSON object, found {type(meta).__name__}")
    if meta.get("model") == "ward":
        from .ward import WardSVBRDF
        try:
            return WardSVBRDF.load(path)
        except KeyError as exc:
            raise InputError(path / "model.json", f"incomplete Ward model description (no {exc})") from None
    return SVBRDF.load(path)


def input_folders(model_dir: str | Path, manifest: dict[str, Any]) -> list[Path]:
    """The folders predict reads: the model, the capture, and every folder holding a frame or truth file."""
    folders = {Path(model_dir), Path(manifest["_dir"])}
    for frame in manifest["frames"]:
        folders.update(Path(e["file"]).parent for e in frame["exposures"])
        if "radiance" in frame.get("truth", {}):
            folders.add(Path(frame["truth"]["radiance"]).parent)
    return sorted(folders)


def _finite_frame(image: np.ndarray, q: int, manifest_path: Path, model_dir: str | Path) -> np.ndarray:
    """``image`` if every pixel is finite, else InputError naming the manifest, the frame and the model.

    The manifest's numbers are checked finite when it is read and the models
    return finite values, so this is the last guard: nothing non-finite is
    ever written as a prediction.
    """
    bad = ~np.isfinite(image).all(axis=-1)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise InputError(manifest_path, f"frame {q}: {int(bad.sum())} predicted pixel(s) are NaN or Inf (first "
                                        f"at row {row}, col {col}) with the model {model_dir}; frame not written")
    return image


def predict(model_dir: str | Path, manifest_path: str | Path, out_dir: str | Path, supersample: int = 1,
            frames: list[int] | None = None, progress: bool = True, force: bool = False) -> dict[str, Any]:
    """Render every frame (or the listed ``frames``) of ``manifest_path`` from the SVBRDF in ``model_dir``.

    Writes ``out_dir/frames/NNNN.exr`` (NNNN the frame's index in the
    manifest) and ``out_dir/manifest.json``; returns that manifest. The
    manifest is validated against the published schema (InputError naming the
    file on a bad one); its frame files need not exist (a manifest can describe
    views never captured).

    The output folder is checked by :func:`facetsynth.outputs.prepare_output_dir`
    once the inputs are read: it may not overlap the model, the capture or a
    frame folder, nor be a non-empty folder predict did not make (unless
    ``force``). Every frame is checked finite before it is written.
    """
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise InputError(None, f"supersample must be a positive integer, got {supersample!r}")
    manifest_path = Path(manifest_path)
    m = manifest_io.load(manifest_path, check_files=False)
    model = load_model(model_dir)
    camera = manifest_io.camera(m)
    try:
        renderer = FrameRenderer(model, camera, supersample)
    except ValueError as exc:
        raise InputError(manifest_path, str(exc)) from None
    if not renderer.mask.any():
        log.warning("%s: no pixel of this camera sees the sample", manifest_path)
    selected = range(len(m["frames"])) if frames is None else frames
    out_dir = prepare_output_dir(out_dir, "predict", input_dirs=input_folders(model_dir, m), force=force)
    (out_dir / "frames").mkdir(exist_ok=True)
    out_frames = []
    for q in tqdm(selected, desc="predict", unit="frame", disable=not progress):
        light = m["frames"][q]["light"]
        image = _finite_frame(renderer.radiance(manifest_io.light_point(light), light["intensity"]), q,
                              manifest_path, model_dir)
        name = f"frames/{q:04d}.exr"
        write_exr(out_dir / name, {"RGB": image}, {"exposure_time": 1.0, "quantity": "predicted radiance I",
                                                   "source_frame": int(q)})
        out_frames.append({"light": light, "exposures": [{"file": name, "time": 1.0}], "source_frame": int(q)})
    out = {"version": 1, "units": "m", "sample": m["sample"], "camera": m["camera"], "saturation": None,
           "frames": out_frames,
           "prediction": {"model": str(Path(model_dir).resolve()), "manifest": str(manifest_path.resolve()),
                          "supersample": int(supersample)}}
    manifest_io.save(out_dir / "manifest.json", out)
    if made_by(out_dir, "predict"):   # its own folder: frames of an earlier prediction the manifest no longer lists
        written = {out_dir / f["exposures"][0]["file"] for f in out_frames}
        for stale in sorted(set((out_dir / "frames").glob("*.exr")) - written):
            stale.unlink()
    return out
