"""A quick look at a fitted model: one view, one point light, a tone-mapped picture (``facetsynth render``).

The camera looks at the sample centre from elevation ``theta`` (from the
normal) and azimuth ``phi`` (from the sample's +x axis), at a distance that
fits the sample in the frame; the pixel model is predict's (eq. 8 read
forwards: I = rho (n.i) L / |P - x|^2), so a preview is one predicted frame
from a camera no capture had. The radiance is exposed so that the 99.5th
percentile of the lit sample maps to white (or by ``exposure_ev``), then
encoded for display by OpenImageIO's colour management (linear Rec.709 to
sRGB). Writing ``.exr`` keeps the scene-linear radiance instead.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry.camera import Camera
from ..io.errors import InputError
from ..io.fileio import atomic_path, write_exr
from ..io.outputs import RENDER_SOFTWARE, refuse_output_file, write_errors

WHITE_PERCENTILE = 99.5   # auto exposure: this percentile of the sample's radiance maps to 1
MAX_EXPOSURE_EV = 64      # --exposure range, +-EV: 2^64 = 1.8e19, far beyond any radiance's dynamic range
MAX_INTENSITY = 1e12      # --intensity, W/sr: a 100 W lamp is about 10 W/sr; float32 radiance stays finite


@dataclass(frozen=True)
class PreviewSettings:
    """What ``facetsynth render`` draws: the view, the light, the picture."""

    theta_deg: float = 30.0
    phi_deg: float = 0.0
    light: tuple[float, float, float] | None = None       # metres, sample-plane frame (z up); None: mirror_light
    intensity: float = 1.0                                 # radiant intensity of the light (W/sr), RGB white
    size: int = 512                                        # pixels across
    supersample: int = 2                                   # sub-pixels per pixel side (box filter)
    exposure_ev: float | None = None                       # None: auto (WHITE_PERCENTILE); else 2^ev scale

    def __post_init__(self):
        for name, value in (("--view theta", self.theta_deg), ("--view phi", self.phi_deg),
                            ("--intensity", self.intensity), *((("--light",) + (v,)) for v in self.light or ())):
            if not np.isfinite(value):
                raise InputError(None, f"{name} must be finite, got {value!r}")
        if not 0.0 <= self.theta_deg < 90.0:
            raise InputError(None, f"--view theta must be in [0, 90) degrees (from the normal), got "
                                   f"{self.theta_deg:g}")
        if self.light is not None and self.light[2] <= 0.0:
            raise InputError(None, f"--light z must be above the sample (z > 0 m), got {self.light[2]:g}")
        if not 16 <= self.size <= 4096:
            raise InputError(None, f"--size must be from 16 to 4096 pixels, got {self.size}")
        if not 0.0 < self.intensity <= MAX_INTENSITY:
            raise InputError(None, f"--intensity must be above 0 and at most {MAX_INTENSITY:g} W/sr, got "
                                   f"{self.intensity:g}")
        if self.exposure_ev is not None and not abs(self.exposure_ev) <= MAX_EXPOSURE_EV:
            raise InputError(None, f"--exposure must be from -{MAX_EXPOSURE_EV} to {MAX_EXPOSURE_EV} EV, got "
                                   f"{self.exposure_ev:g}")


def preview_camera(width: float, height: float, theta_deg: float, phi_deg: float, size: int) -> Camera:
    """A square camera looking at the centre of a width x height sample from (theta, phi).

    Distance 3 sample diagonals (a mild perspective, as on a rig); the
    focal length frames the diagonal with a 10 % margin.
    """
    diagonal = float(np.hypot(width, height))
    distance = 3.0 * diagonal
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    position = distance * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    focal = size * distance / (1.1 * diagonal)
    # looking straight down, world up is degenerate: use +y (the top of the rectified maps) instead
    up = (0.0, 1.0, 0.0) if theta_deg < 1e-3 else (0.0, 0.0, 1.0)
    return Camera.look_at(position, (0.0, 0.0, 0.0), size, size, focal, up=up)


def mirror_light(width: float, height: float, theta_deg: float, phi_deg: float) -> np.ndarray:
    """The default light: the camera's direction mirrored about the normal, 2 sample diagonals away, so that
    the highlight lies on the sample."""
    t, p = np.radians(theta_deg), np.radians(phi_deg + 180.0)
    return 2.0 * float(np.hypot(width, height)) * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p),
                                                             np.cos(t)])


def exposure_scale(radiance: np.ndarray, mask: np.ndarray, exposure_ev: float | None) -> float:
    """The factor applied before display encoding: 2^ev, or 1 / the WHITE_PERCENTILE of the lit sample."""
    if exposure_ev is not None:
        return float(2.0 ** exposure_ev)
    lit = radiance[mask].max(axis=-1)
    lit = lit[lit > 0]
    if lit.size == 0:
        return 1.0
    return float(1.0 / np.percentile(lit, WHITE_PERCENTILE))


def display_encode(radiance: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear Rec.709 in [0, 1] to 8-bit sRGB, by OpenImageIO's colour management."""
    import OpenImageIO as oiio
    buf = oiio.ImageBuf(np.ascontiguousarray(np.clip(radiance, 0.0, 1.0), dtype=np.float32))
    buf = oiio.ImageBufAlgo.colorconvert(buf, "Linear Rec.709 (sRGB)", "sRGB Encoded Rec.709 (sRGB)")
    return np.round(np.clip(buf.get_pixels(oiio.FLOAT), 0.0, 1.0) * 255.0).astype(np.uint8)


def render_preview(model_dir: str | Path, out: str | Path, settings: PreviewSettings, force: bool = False) -> dict:
    """Render ``settings``' view of the fitted model in ``model_dir`` to ``out`` (.png, .jpg, .tif or .exr).

    ``out`` follows :func:`facetsynth.io.outputs.refuse_output_file`: never the model folder, a file in it or
    inside it; an existing file only if render wrote it, or with ``force``. The picture is written to a
    temporary and renamed when complete: a full disk or a read-only folder is an InputError naming ``out``,
    and leaves the old picture (if any) as it was.
    """
    from .predict import FrameRenderer, load_model
    out = Path(out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr"):
        raise InputError(out, "unknown picture type; write .png, .jpg, .tif or .exr")
    if not out.parent.is_dir():
        raise InputError(out.parent, "folder not found; create it first")
    model = load_model(model_dir)
    refuse_output_file(out, model_dir, force)
    camera = preview_camera(model.plane.width, model.plane.height, settings.theta_deg, settings.phi_deg,
                            settings.size)
    try:
        renderer = FrameRenderer(model, camera, settings.supersample)
    except ValueError as exc:
        raise InputError(None, f"--size {settings.size}: {exc}") from None
    light = (mirror_light(model.plane.width, model.plane.height, settings.theta_deg, settings.phi_deg)
             if settings.light is None else np.asarray(settings.light, float))
    radiance = _finite(renderer.radiance(light, np.full(3, settings.intensity)), model_dir)
    scale = exposure_scale(radiance, renderer.sample_mask, settings.exposure_ev)
    with write_errors(out), atomic_path(out, suffix=out.suffix) as tmp:
        if out.suffix.lower() == ".exr":
            write_exr(tmp, {"RGB": radiance}, {"quantity": "predicted radiance I (facetsynth render)",
                                               "software": RENDER_SOFTWARE})
        else:
            _write_picture(out, tmp, display_encode(radiance * scale))
    lit = radiance[renderer.sample_mask]
    return {"file": str(out), "width": camera.width, "height": camera.height, "light": light.tolist(),
            "sample_pixels": int(renderer.sample_mask.sum()), "exposure_scale": scale,
            "max_radiance": float(lit.max()) if lit.size else 0.0}


def _finite(radiance: np.ndarray, model_dir: str | Path) -> np.ndarray:
    """``radiance`` if every pixel is finite (float32: a huge kd or ks times the light can overflow), else
    InputError naming the model."""
    bad = ~np.isfinite(radiance).all(axis=-1)
    if bad.any():
        raise InputError(model_dir, f"{int(bad.sum())} rendered pixel(s) overflow to Inf (parameters too large for "
                                    "float32 radiance at this intensity); picture not written")
    return radiance


PIL_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF"}
SOFTWARE_TAG = 0x0131   # TIFF and Exif tag "Software"


def _write_picture(out: Path, tmp: Path, pixels: np.ndarray) -> None:
    """Write 8-bit sRGB ``pixels`` to ``tmp`` in ``out``'s format, marked as render's (Software metadata).

    Encoded in memory (Pillow), then written by Python: a full disk is an OSError here (OpenImageIO's writers
    report one only through geterror, and its PNG writer left a truncated file with exit 0)."""
    from PIL import Image, PngImagePlugin
    image, buffer = Image.fromarray(np.ascontiguousarray(pixels), "RGB"), io.BytesIO()
    form = PIL_FORMATS[out.suffix.lower()]
    if form == "PNG":
        info = PngImagePlugin.PngInfo()
        info.add_text("Software", RENDER_SOFTWARE)
        image.save(buffer, form, pnginfo=info)
    else:
        exif = Image.Exif()
        exif[SOFTWARE_TAG] = RENDER_SOFTWARE
        image.save(buffer, form, exif=exif, **({"quality": 95} if form == "JPEG" else {}))
    tmp.write_bytes(buffer.getvalue())
