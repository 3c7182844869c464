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
import os
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..capture import manifest
from ..io.errors import InputError
from ..io.fileio import write_exr
from ..io.outputs import output_folder
from ..fit.normals import to_local
from ..models.render import light_geometry, towards
from ..models.svbrdf import CHUNK, SVBRDF, model_grids, refuse_bad_values

log = logging.getLogger(__name__)
OUTPUTS = ("frames", "manifest.json")    # what predict writes into its output folder, published in this order


BYTES_PER_SUBPIXEL = 384       # FrameRenderer's peak memory per sub-pixel, measured 335 B (the sample filling the frame)
MEMORY_LIMIT_GIB = 16.0        # default limit of that estimate; the environment variable below overrides it
MEMORY_LIMIT_VARIABLE = "FACETSYNTH_MEMORY_LIMIT_GIB"


def memory_limit_gib() -> float:
    """The memory a rendering may use, GiB: ``$FACETSYNTH_MEMORY_LIMIT_GIB`` if set, else MEMORY_LIMIT_GIB."""
    text = os.environ.get(MEMORY_LIMIT_VARIABLE)
    if text is None:
        return MEMORY_LIMIT_GIB
    try:
        limit = float(text)
    except ValueError:
        limit = float("nan")
    if not (np.isfinite(limit) and limit > 0):
        raise InputError(None, f"{MEMORY_LIMIT_VARIABLE} must be a positive number of GiB, got {text!r:.40}")
    return limit


def memory_problem(width: int, height: int, supersample: int) -> str | None:
    """Why rendering a width x height camera at ``supersample`` is refused before any allocation (None when it
    is not): FrameRenderer's memory, BYTES_PER_SUBPIXEL per sub-pixel, would exceed :func:`memory_limit_gib`."""
    need = int(width) * int(height) * int(supersample) ** 2 * BYTES_PER_SUBPIXEL / 2.0 ** 30
    limit = memory_limit_gib()
    if need <= limit:
        return None
    return (f"a {width}x{height} camera at supersample {supersample} needs about {need:.3g} GiB to render, above "
            f"the limit of {limit:g} GiB (set {MEMORY_LIMIT_VARIABLE} to raise it)")


class FrameRenderer:
    """Renders radiance images of one camera from an SVBRDF; the view-dependent terms are computed once."""

    def __init__(self, model, camera, supersample: int = 1):
        if camera.has_distortion:
            raise ValueError("lens distortion is not supported by predict yet (undistort the capture first)")
        too_big = memory_problem(camera.width, camera.height, supersample)
        if too_big:
            raise ValueError(too_big)
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
        with np.errstate(over="ignore"):     # beyond float32: Inf, which predict and render refuse to write
            return image.reshape(self.camera.height, s, self.camera.width, s, 3).mean(axis=(1, 3)).astype(np.float32)


def load_model(path: str | Path):
    """A fitted model folder: the SVBRDF of paper 002 (default) or the Ward baseline (``model: ward``)."""
    from ..io.fileio import read_json
    path = Path(path)
    if not path.is_dir():
        found = "is a file" if path.exists() else "not found"
        raise InputError(path, f"{found}; expected a fitted model folder holding model.json")
    meta = read_json(path / "model.json")
    if not isinstance(meta, dict):
        raise InputError(path / "model.json", f"expected a JSON object, found {type(meta).__name__}")
    if meta.get("model") == "ward":
        return _checked_ward(path, meta)
    return SVBRDF.load(path)


def _checked_ward(path: Path, meta: dict):
    """The Ward baseline folder ``path``, its parameters checked finite and in range (as
    :meth:`SVBRDF.check_values`): InputError naming the file and the count of bad values."""
    from ..models.ward import WardSVBRDF
    model_grids(path / "model.json", dict(meta, grid={"n_theta": 1, "n_phi": 1},
                                          shadowing_grid={"n_theta": 1, "n_phi": 1}))
    try:
        model = WardSVBRDF.load(path)
    except KeyError as exc:
        raise InputError(path / "model.json", f"incomplete Ward model description (no {exc})") from None
    except ValueError as exc:       # a map of another size than the plane grid
        raise InputError(path, f"inconsistent Ward model folder ({str(exc):.200})") from None
    for name, what, values, lowest in (("kd.exr", "kd", model.kd, 0.0), ("ks.exr", "ks", model.ks, 0.0),
                                       ("lobe.exr", "alpha_x", model.alpha_x, None),
                                       ("lobe.exr", "alpha_y", model.alpha_y, None),
                                       ("lobe.exr", "phi", model.phi, None)):
        refuse_bad_values(path / name, what, values, lowest)
    for what, alpha in (("alpha_x", model.alpha_x), ("alpha_y", model.alpha_y)):
        if (alpha <= 0.0).any():
            raise InputError(path / "lobe.exr", f"{int((alpha <= 0.0).sum())} {what} value(s) <= 0: a Ward lobe's "
                                                "width is positive")
    return model


def input_folders(model_dir: str | Path, capture: dict[str, Any]) -> list[Path]:
    """The folders predict reads: the model, the capture, and every folder holding a frame or truth file."""
    folders = {Path(model_dir), Path(capture["_dir"])}
    for frame in capture["frames"]:
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

    The output folder is checked and written by :func:`facetsynth.io.outputs.output_folder`
    once the inputs are read: it may not overlap the model, the capture or a
    frame folder, nor be a non-empty folder predict did not make (unless
    ``force``), nor one another command is writing; the frames and the
    manifest are published only when all are written (a failure or a Ctrl-C
    leaves the old output, or none). Every frame is checked finite before it
    is written.
    """
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise InputError(None, f"supersample must be a positive integer, got {supersample!r}")
    manifest_path = Path(manifest_path)
    m = manifest.load(manifest_path, check_files=False)
    model = load_model(model_dir)
    camera = manifest.camera(m)
    try:
        renderer = FrameRenderer(model, camera, supersample)
    except ValueError as exc:
        raise InputError(manifest_path, str(exc)) from None
    if not renderer.mask.any():
        log.warning("%s: no pixel of this camera sees the sample", manifest_path)
    selected = range(len(m["frames"])) if frames is None else frames
    out_frames = []
    with output_folder(out_dir, "predict", input_dirs=input_folders(model_dir, m), writes=OUTPUTS,
                       force=force) as stage:
        (stage / "frames").mkdir()
        for q in tqdm(selected, desc="predict", unit="frame", disable=not progress):
            light = m["frames"][q]["light"]
            image = _finite_frame(renderer.radiance(manifest.light_point(light), light["intensity"]), q,
                                  manifest_path, model_dir)
            name = f"frames/{q:04d}.exr"
            write_exr(stage / name, {"RGB": image}, {"exposure_time": 1.0, "quantity": "predicted radiance I",
                                                     "source_frame": int(q)})
            out_frames.append({"light": light, "exposures": [{"file": name, "time": 1.0}], "source_frame": int(q)})
        out = {"version": 1, "units": "m", "sample": m["sample"], "camera": m["camera"], "saturation": None,
               "frames": out_frames,
               "prediction": {"model": str(Path(model_dir).resolve()), "manifest": str(manifest_path.resolve()),
                              "supersample": int(supersample)}}
        manifest.save(stage / "manifest.json", out)
    return out
