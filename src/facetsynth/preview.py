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

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import InputError
from .fileio import atomic_path, write_exr

WHITE_PERCENTILE = 99.5   # auto exposure: this percentile of the sample's radiance maps to 1


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
        if not 0.0 <= self.theta_deg < 90.0:
            raise InputError(None, f"--view theta must be in [0, 90) degrees (from the normal), got "
                                   f"{self.theta_deg:g}")
        if self.light is not None and self.light[2] <= 0.0:
            raise InputError(None, f"--light z must be above the sample (z > 0 m), got {self.light[2]:g}")
        if not 16 <= self.size <= 4096:
            raise InputError(None, f"--size must be from 16 to 4096 pixels, got {self.size}")


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


def render_preview(model_dir: str | Path, out: str | Path, settings: PreviewSettings) -> dict:
    """Render ``settings``' view of the fitted model in ``model_dir`` to ``out`` (.png, .jpg, .tif or .exr)."""
    from .predict import FrameRenderer, load_model
    out = Path(out)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr"):
        raise InputError(out, "unknown picture type; write .png, .jpg, .tif or .exr")
    if not out.parent.is_dir():
        raise InputError(out.parent, "folder not found; create it first")
    model = load_model(model_dir)
    camera = preview_camera(model.plane.width, model.plane.height, settings.theta_deg, settings.phi_deg,
                            settings.size)
    renderer = FrameRenderer(model, camera, settings.supersample)
    light = (mirror_light(model.plane.width, model.plane.height, settings.theta_deg, settings.phi_deg)
             if settings.light is None else np.asarray(settings.light, float))
    radiance = renderer.radiance(light, np.full(3, settings.intensity))
    scale = exposure_scale(radiance, renderer.sample_mask, settings.exposure_ev)
    with atomic_path(out, suffix=out.suffix) as tmp:
        if out.suffix.lower() == ".exr":
            write_exr(tmp, {"RGB": radiance}, {"quantity": "predicted radiance I (facetsynth render)"})
        else:
            import OpenImageIO as oiio
            pixels = display_encode(radiance * scale)
            image = oiio.ImageOutput.create(str(out))
            if image is None or not image.open(str(tmp), oiio.ImageSpec(camera.width, camera.height, 3,
                                                                        oiio.UINT8)):
                raise InputError(out, f"cannot write the picture ({oiio.geterror()})")
            image.write_image(pixels)
            image.close()
    lit = radiance[renderer.sample_mask]
    return {"file": str(out), "width": camera.width, "height": camera.height, "light": light.tolist(),
            "sample_pixels": int(renderer.sample_mask.sum()), "exposure_scale": scale,
            "max_radiance": float(lit.max()) if lit.size else 0.0}
