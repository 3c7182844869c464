"""Stage ``capture``: a virtual capture, an import, or the real rig (paper 002 sec. 4)."""

from __future__ import annotations

import logging
from pathlib import Path

import OpenImageIO as oiio

from .. import manifest as manifest_io
from ..errors import InputError
from ..fileio import atomic_dir
from ..virtual_rig import VirtualRig, capture as virtual_capture

log = logging.getLogger(__name__)


def run(source: str, path: str | Path, out_dir: str | Path, rig: str | Path, seed: int, noise: bool,
        rotation_deg: float = 0.0, threads: int = 1) -> None:
    """Produce the capture folder ``out_dir`` (``manifest.json`` + frames) for one sample (a virtual scene
    turned by ``rotation_deg`` on the rig, its frames rendered on ``threads`` threads)."""
    if source == "virtual":
        log.info("virtual capture of scene %s turned by %g deg with rig %s (seed %d, noise %s)", path, rotation_deg,
                 rig, seed, noise)
        virtual_capture(path, VirtualRig.load(rig), out_dir, seed=seed, noise=noise, rotation_deg=rotation_deg,
                        threads=threads)
    elif source == "import":
        import_capture(path, out_dir)
    else:
        raise InputError(path, "source 'rig' needs the real-rig camera backend, which is not built yet "
                               "(DESIGN.md sec. 7); capture with your own software and use source 'import'")


def check_capture(path: str | Path) -> dict:
    """Validate a capture folder: its manifest, and every exposure file's header.

    Every exposure file must exist and be an image of the camera's size with
    R, G, B channels; the pixels themselves are read (and checked) by ``hdr``.
    Returns the loaded manifest.
    """
    manifest = manifest_io.load(path)
    width, height = manifest["camera"]["width"], manifest["camera"]["height"]
    for frame in manifest["frames"]:
        for exposure in frame["exposures"]:
            _check_frame_header(exposure["file"], width, height)
    return manifest


def import_capture(path: str | Path, out_dir: str | Path) -> None:
    """Validate a capture made elsewhere and publish its manifest with absolute frame paths."""
    manifest = check_capture(path)
    log.info("imported %d frames from %s", len(manifest["frames"]), path)
    with atomic_dir(out_dir) as staging:
        manifest_io.save(staging / "manifest.json", manifest)


def _check_frame_header(file: str, width: int, height: int) -> None:
    image = oiio.ImageInput.open(file)
    if image is None:
        raise InputError(file, f"unreadable frame ({oiio.geterror().strip() or 'unknown format'})")
    spec = image.spec()
    image.close()
    if (spec.width, spec.height) != (width, height):
        raise InputError(file, f"frame is {spec.width}x{spec.height}, the manifest's camera is {width}x{height}")
    missing = {"R", "G", "B"} - set(spec.channelnames)
    if missing:
        raise InputError(file, f"frame has no {'/'.join(sorted(missing))} channel(s)")
