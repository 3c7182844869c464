"""Camera backends of the real rig (issue 16 item 3): one small interface, two real backends.

A backend takes one frame's exposure bracket (:meth:`CameraBackend.capture`) and stores each exposure in
the capture's folder under its final name only once it is whole (a temporary name in the same folder,
then :func:`os.replace`), so a capture interrupted at any point never leaves a partial file that looks
whole (:mod:`facetsynth.rig.session` journals the frames).

What is stored, by the file the camera delivers:

- RAW (CR2, CR3, NEF, ARW, DNG, RAF, ORF, RW2, PEF ..., anything LibRaw opens): decoded with rawpy
  (:func:`decode_raw`) to LINEAR RGB in [0, 1] and written as EXR (:func:`facetsynth.io.fileio.write_exr`,
  header ``exposure_time``), so that ``value = min(1, time * I)``: the manifest's ``saturation`` is 1.
- 8-bit images (JPEG, 8-bit PNG/TIFF): kept byte for byte (8-bit, the camera's nonlinear tone curve); the
  ``hdr`` stage recovers the camera response from the brackets (:mod:`facetsynth.capture.response`, Debevec and
  Malik 1997) and linearizes them.
- Float images (EXR, float TIFF): written as EXR R, G, B as they are (taken as linear).
- 16-bit integer images (TIFF, PNG): taken as LINEAR (as a raw converter's 16-bit linear export), scaled to
  [0, 1] by 65535 and written as EXR. A 16-bit file with a gamma curve would be misread: export EXR or
  8-bit instead.

Backends (:func:`open_camera` builds one from the rig description's ``camera`` dict): :class:`Gphoto2Camera`
(tethered over USB with libgphoto2) and :class:`WatchFolderCamera` (the camera's own software writes the
files). The virtual rig's camera (``backend: virtual``) is built by :func:`facetsynth.rig.session.open_camera`.
"""

from __future__ import annotations

import fnmatch
import logging
import math
import os
import re
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from time import monotonic, sleep
from typing import Any, Callable, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from ..io.fileio import atomic_path, write_exr

log = logging.getLogger(__name__)

RAW_EXTENSIONS = frozenset(
    ".3fr .ari .arw .bay .cr2 .cr3 .crw .dcr .dng .erf .fff .iiq .k25 .kdc .mef .mos .mrw .nef .nrw .orf "
    ".pef .raf .raw .rw2 .rwl .sr2 .srf .srw .x3f".split())
"""File extensions taken as camera RAW (decoded with rawpy)."""

EIGHT_BIT_EXTENSIONS = frozenset({".jpg", ".jpeg"})
"""Extensions stored as they are without looking inside (JPEG is always 8-bit)."""


class CameraError(RuntimeError):
    """A camera backend failed: one line naming the camera (or file) and the problem."""


@runtime_checkable
class CameraBackend(Protocol):
    """What the rig's capture needs from a camera."""

    def describe(self) -> str:
        """One line naming the camera, e.g. ``"gphoto2: Canon EOS 80D (usb:001,004)"`` (``facetsynth rig check``)."""

    def capture(self, times: Sequence[float], folder: Path, stem: str) -> list[dict]:
        """Take one exposure per time (seconds) into ``folder`` (which exists) as ``f"{stem}_e{k}{ext}"``,
        each written atomically; return ``[{"file": name relative to folder, "time": seconds actually
        used}]``. Raises :class:`CameraError`; never leaves a partial file under a final name."""

    def close(self) -> None:
        """Release the camera."""


# --- conversion of a delivered file --------------------------------------------------------------------

def decode_raw(source: str | os.PathLike | Any) -> np.ndarray:
    """A camera RAW file (a path or a binary file object) as LINEAR RGB (H, W, 3) float32 in [0, 1].

    LibRaw (rawpy) ``postprocess(gamma=(1, 1), no_auto_bright=True, use_camera_wb=True, output_bps=16,
    user_flip=0, output_color=raw, highlight_mode=clip, adjust_maximum_thr=0)``, divided by 65535.
    Applied: the black level subtracted, the camera's as-shot white-balance multipliers (normalised to
    green; nothing else: no auto white balance), AHD demosaicing, scaling so that the sensor's nominal
    white level is 1 (``adjust_maximum_thr=0``: LibRaw's default 0.75 lowers the white level to the
    image's own maximum when that exceeds 75 % of it, which would scale each exposure differently). NOT applied: no
    gamma or tone curve, no auto-brightening, no colour matrix (the RGB is the camera's own primaries, so a
    clipped channel stays exactly at 1 and the hdr stage's saturation test holds; the fit is per channel),
    no rotation (pixels as the sensor reads them, as the calibration's images must be), no denoising, no
    lens corrections. So ``value = min(1, time * I)`` in camera RGB, linear up to the sensor's own
    non-linearity near its white level.
    """
    import rawpy

    if isinstance(source, os.PathLike):
        source = os.fspath(source)
    try:
        with rawpy.imread(source) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, use_camera_wb=True, output_bps=16,
                                  user_flip=0, output_color=rawpy.ColorSpace.raw,
                                  highlight_mode=rawpy.HighlightMode.Clip, adjust_maximum_thr=0.0)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        name = getattr(source, "name", source)
        raise CameraError(f"{name}: not a RAW file LibRaw can decode ({type(exc).__name__}: {exc})") from None
    return (rgb.astype(np.float32) / np.float32(65535.0))[..., :3]


def store_exposure(source: Path, folder: Path, stem: str, time: float) -> str:
    """Store the delivered file ``source`` in ``folder`` as ``stem`` + extension, atomically; return the name.

    RAW -> EXR (:func:`decode_raw`); JPEG and other 8-bit images -> kept byte for byte; float images -> EXR;
    16-bit integer images -> EXR, taken as linear (module docstring). The EXR header has ``exposure_time``.
    """
    source, folder = Path(source), Path(folder)
    ext = source.suffix.lower()
    if ext in RAW_EXTENSIONS:
        name = f"{stem}.exr"
        write_exr(folder / name, {"RGB": decode_raw(str(source))}, {"exposure_time": float(time)},
                  precision="float32")
        return name
    if ext in EIGHT_BIT_EXTENSIONS:
        return _copy(source, folder, f"{stem}{ext}")
    pixels, bits = _read_image(source)
    if bits == 8:
        return _copy(source, folder, f"{stem}{ext}")
    name = f"{stem}.exr"
    write_exr(folder / name, {"RGB": pixels}, {"exposure_time": float(time)}, precision="float32")
    return name


def _copy(source: Path, folder: Path, name: str) -> str:
    """Copy ``source`` to ``folder/name`` atomically."""
    with atomic_path(folder / name, suffix=source.suffix) as tmp:
        shutil.copyfile(source, tmp)
    return name


def _read_image(path: Path) -> tuple[np.ndarray | None, int | None]:
    """An image OpenImageIO reads: (linear RGB float32 (H, W, 3), None) for float and 16-bit integer
    formats, (None, 8) for 8-bit ones (kept as they are)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise CameraError(f"{path}: not an image OpenImageIO can read ({oiio.geterror()})")
    try:
        spec = inp.spec()
        base = spec.format.basetype
        if base in (oiio.UINT8, oiio.INT8):
            return None, 8
        if spec.nchannels < 3 and spec.nchannels != 1:
            raise CameraError(f"{path}: {spec.nchannels} channels, expected RGB or grey")
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    finally:
        inp.close()
    if pixels is None:
        raise CameraError(f"{path}: unreadable image ({oiio.geterror()})")
    pixels = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels)
    pixels = np.repeat(pixels, 3, axis=-1) if spec.nchannels == 1 else pixels[..., :3]
    if not np.isfinite(pixels).all():
        raise CameraError(f"{path}: NaN or Inf pixels")
    return np.ascontiguousarray(pixels), None


def exif_exposure_time(path: Path) -> float | None:
    """The EXIF ``ExposureTime`` (seconds) of an image OpenImageIO reads (JPEG, TIFF, most RAW), else None."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        value = inp.spec().getattribute("ExposureTime")
    finally:
        inp.close()
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None


# --- shutter speeds ------------------------------------------------------------------------------------

_FRACTION = re.compile(r"(\d+(?:\.\d+)?)\s*/\s*(\d+(?:\.\d+)?)")
_SECONDS = re.compile(r"(\d+(?:\.\d+)?)")
_CANON_TENTHS = re.compile(r"(\d+)\"(\d+)")        # 1"3: 1.3 s (Canon)


def parse_shutter_speed(text: str) -> float | None:
    """Seconds of a libgphoto2 shutter-speed choice: ``'1/100'``, ``'1/100s'``, ``'0.0100s'``, ``'1'``,
    ``'30"'``, ``'2.5"'``, ``'1"3'`` (1.3 s), ``'30s'``; None for non-times (``'bulb'``, ``'auto'``, ``'x 1/200'``)."""
    t = text.strip().lower().rstrip("s").rstrip().replace(",", ".")
    for pattern, value in ((_FRACTION, lambda m: float(m[1]) / float(m[2])),
                           (_CANON_TENTHS, lambda m: float(f"{m[1]}.{m[2]}")),
                           (_SECONDS, lambda m: float(m[1]))):
        m = pattern.fullmatch(t.rstrip('"').strip() if pattern is _SECONDS else t)
        if m:
            seconds = value(m)
            return seconds if seconds > 0 else None
    return None


def nearest_choice(choices: Sequence[str], seconds: float) -> tuple[str, float]:
    """The choice nearest to ``seconds`` in stops (log2 ratio), and its time; ValueError when none is a time."""
    times = [(c, parse_shutter_speed(c)) for c in choices]
    times = [(c, t) for c, t in times if t is not None]
    if not times:
        raise ValueError(f"no shutter speed among the choices {list(choices)[:8]}")
    return min(times, key=lambda ct: abs(math.log2(ct[1] / seconds)))


# --- gphoto2 --------------------------------------------------------------------------------------------

class Gphoto2Camera:
    """A camera tethered over USB through libgphoto2 (python-gphoto2).

    ``port``: the libgphoto2 port (``"usb:001,004"``, see ``gphoto2 --auto-detect``); None: the first
    camera found. ``config``: the name of the shutter-speed config widget (``shutterspeed`` on Canon, Nikon,
    Sony). ``delete``: delete each file from the camera's card once stored (failures to delete are logged).
    ``event_timeout_ms``: how long to wait for further files of one capture (RAW+JPEG mode: the RAW is
    kept). For each exposure time the widget is set to the nearest choice in stops and the time actually
    used is recorded; the camera must be in manual (M) exposure mode.
    """

    def __init__(self, port: str | None = None, config: str = "shutterspeed", delete: bool = True,
                 event_timeout_ms: int = 200, camera: Any = None):
        import gphoto2 as gp

        self._gp, self.config, self.delete, self.event_timeout_ms = gp, config, delete, event_timeout_ms
        self._camera = camera if camera is not None else gp.Camera()
        self._name = f"gphoto2 camera at {port or 'the first port'}"
        try:
            if camera is None and port is not None:
                ports = gp.PortInfoList()
                ports.load()
                self._camera.set_port_info(ports[ports.lookup_path(port)])
            if camera is None:
                self._camera.init()
            model = self._camera.get_abilities().model
            path = self._camera.get_port_info().get_path()
        except gp.GPhoto2Error as exc:
            raise CameraError(f"{self._name}: cannot open the camera ({exc}); is it on, connected, and not "
                              "claimed by another program (gvfs, a desktop photo importer)?") from None
        self._name = f"gphoto2: {model} ({path})"

    def describe(self) -> str:
        return self._name

    def shutter_choices(self) -> list[str]:
        """The shutter-speed widget's choices, as the camera names them."""
        widget = self._widget(self._call("read its config", self._camera.get_config))
        return [widget.get_choice(i) for i in range(widget.count_choices())]

    def set_exposure(self, seconds: float) -> float:
        """Set the shutter speed nearest to ``seconds``; return the time it stands for."""
        cfg = self._call("read its config", self._camera.get_config)
        widget = self._widget(cfg)
        choices = [widget.get_choice(i) for i in range(widget.count_choices())]
        try:
            choice, actual = nearest_choice(choices, seconds)
        except ValueError as exc:
            raise CameraError(f"{self._name}: {self.config}: {exc}") from None
        if widget.get_value() != choice:
            widget.set_value(choice)
            self._call(f"set {self.config} to {choice}", self._camera.set_config, cfg)
        if abs(math.log2(actual / seconds)) > 1 / 6:
            log.info("%s: exposure %g s taken as %s (%g s), the nearest the camera offers", self._name,
                     seconds, choice, actual)
        return actual

    def capture(self, times: Sequence[float], folder: Path, stem: str) -> list[dict]:
        folder = Path(folder)
        out = []
        for k, requested in enumerate(times):
            actual = self.set_exposure(float(requested))
            files = self._capture_files()
            raws = [f for f in files if Path(f[1]).suffix.lower() in RAW_EXTENSIONS]
            keep = raws[0] if raws else files[0]
            name = self._download(keep, folder, f"{stem}_e{k}", actual)
            if self.delete:
                for f in files:
                    try:
                        self._camera.file_delete(*f)
                    except self._gp.GPhoto2Error as exc:
                        log.info("%s: could not delete %s/%s from the camera (%s)", self._name, *f, exc)
            out.append({"file": name, "time": actual})
        return out

    def close(self) -> None:
        try:
            self._camera.exit()
        except self._gp.GPhoto2Error as exc:
            log.info("%s: exit: %s", self._name, exc)

    def _capture_files(self) -> list[tuple[str, str]]:
        """Trigger one exposure; the (folder, name) of the files it made on the camera (RAW+JPEG: two)."""
        gp = self._gp
        path = self._call("capture", self._camera.capture, gp.GP_CAPTURE_IMAGE)
        files = [(path.folder, path.name)]
        while True:    # further files of the same shot (RAW+JPEG) arrive as events
            try:
                kind, data = self._camera.wait_for_event(self.event_timeout_ms)
            except gp.GPhoto2Error:
                break
            if kind == gp.GP_EVENT_FILE_ADDED:
                files.append((data.folder, data.name))
            elif kind in (gp.GP_EVENT_TIMEOUT, gp.GP_EVENT_CAPTURE_COMPLETE):
                break
        return files

    def _download(self, file: tuple[str, str], folder: Path, stem: str, time: float) -> str:
        """Download the camera's ``file`` into ``folder`` and store it (:func:`store_exposure`)."""
        gp = self._gp
        camera_file = self._call(f"download {file[0]}/{file[1]}", self._camera.file_get, file[0], file[1],
                                 gp.GP_FILE_TYPE_NORMAL)
        data = bytes(memoryview(camera_file.get_data_and_size()))
        if not data:
            raise CameraError(f"{self._name}: {file[0]}/{file[1]}: the camera sent an empty file")
        ext = Path(file[1]).suffix.lower() or ".jpg"
        # A temporary name (".NAME.PID-TID.tmpEXT", swept by fileio if this process is killed), never published.
        download = folder / f".{stem}.download.{os.getpid()}-{threading.get_ident()}.tmp{ext}"
        try:
            download.write_bytes(data)
            return store_exposure(download, folder, stem, time)
        except CameraError as exc:
            raise CameraError(f"{self._name}: {file[1]}: {exc}") from None
        except OSError as exc:
            raise CameraError(f"{self._name}: {file[1]}: cannot store in {folder} ({exc})") from None
        finally:
            download.unlink(missing_ok=True)

    def _widget(self, cfg):
        try:
            return cfg.get_child_by_name(self.config)
        except self._gp.GPhoto2Error:
            raise CameraError(f"{self._name}: no '{self.config}' config (is the camera in manual mode? set "
                              "camera.config to its shutter-speed setting's name)") from None

    def _call(self, what: str, fn: Callable, *args):
        try:
            return fn(*args)
        except self._gp.GPhoto2Error as exc:
            raise CameraError(f"{self._name}: {what} failed: {exc}") from None


# --- watch folder ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class WatchSettings:
    """How :class:`WatchFolderCamera` waits: ``timeout_s`` for each file, polling every ``poll_s``; a file is
    complete when its size and mtime have not changed for ``settle_s``."""

    timeout_s: float = 60.0
    poll_s: float = 0.05
    settle_s: float = 0.3
    stop_tolerance: float = 1 / 3        # EXIF time vs requested, in stops, beyond which it is an error


class WatchFolderCamera:
    """Files written by the camera's own software (its tethering tool, or a card reader's import) into
    ``folder``: for each requested exposure, the next NEW file matching ``pattern`` (fnmatch, case-insensitive;
    files present when the backend opened, hidden files and files already taken are ignored, oldest first)
    once its size has stopped changing; stored by :func:`store_exposure` (the watched file is left where
    it is, or deleted with ``remove``).

    The exposure time recorded: the file's EXIF ``ExposureTime`` when OpenImageIO finds one (JPEG, TIFF,
    most RAW: the time the camera actually used), else the requested time (the user sets the same bracket
    in the camera's software). An EXIF time more than ``stop_tolerance`` stops from the requested one is a
    CameraError (the software's bracket is not the rig's, or a frame was missed).
    """

    def __init__(self, folder: str | os.PathLike, pattern: str = "*", settings: WatchSettings = WatchSettings(),
                 remove: bool = False):
        self.folder, self.pattern, self.settings, self.remove = Path(folder), pattern, settings, remove
        if not self.folder.is_dir():
            raise CameraError(f"watch folder {self.folder}: not a folder")
        self._taken: set[str] = set(self._candidates())

    def describe(self) -> str:
        return f"watch folder: {self.folder} ({self.pattern})"

    def capture(self, times: Sequence[float], folder: Path, stem: str) -> list[dict]:
        if Path(folder).resolve() == self.folder.resolve():
            raise CameraError(f"watch folder {self.folder}: is also the capture's folder; the stored exposures "
                              "would be taken as new files: watch another folder")
        out = []
        for k, requested in enumerate(times):
            source = self._next_file(k, len(times), float(requested))
            seconds = self._exposure_time(source, float(requested))
            name = store_exposure(source, Path(folder), f"{stem}_e{k}", seconds)
            self._taken.add(source.name)
            if self.remove:
                source.unlink(missing_ok=True)
            out.append({"file": name, "time": seconds})
        return out

    def close(self) -> None:
        pass

    def _candidates(self) -> list[str]:
        pattern = self.pattern.lower()
        try:
            names = os.listdir(self.folder)
        except OSError as exc:
            raise CameraError(f"watch folder {self.folder}: unreadable ({exc})") from None
        return [n for n in names if not n.startswith(".") and fnmatch.fnmatchcase(n.lower(), pattern)]

    def _next_file(self, k: int, n: int, requested: float) -> Path:
        """The oldest new matching file whose size and mtime stayed the same for ``settle_s``."""
        s = self.settings
        deadline = monotonic() + s.timeout_s
        seen: dict[str, tuple[int, int, float]] = {}     # name -> (size, mtime_ns, since when unchanged)
        while True:
            now = monotonic()
            ready = []
            for name in self._candidates():
                if name in self._taken:
                    continue
                try:
                    st = os.stat(self.folder / name)
                except FileNotFoundError:            # renamed away meanwhile (a writer's temporary)
                    continue
                key = (st.st_size, st.st_mtime_ns)
                if name not in seen or seen[name][:2] != key:
                    seen[name] = (*key, now)
                elif st.st_size > 0 and now - seen[name][2] >= s.settle_s:
                    ready.append((st.st_mtime_ns, name))
            if ready:
                return self.folder / min(ready)[1]
            if now > deadline:
                raise CameraError(f"watch folder {self.folder}: no new complete file matching '{self.pattern}' "
                                  f"within {s.timeout_s:g} s (exposure {k + 1} of {n}, {requested:g} s); is the "
                                  "camera's software saving there?")
            sleep(s.poll_s)

    def _exposure_time(self, source: Path, requested: float) -> float:
        exif = exif_exposure_time(source)
        if exif is None:
            return requested
        if abs(math.log2(exif / requested)) > self.settings.stop_tolerance:
            raise CameraError(f"{source}: exposure time {exif:g} s (EXIF), the bracket asks for {requested:g} s: "
                              "set the camera software's bracket to the rig's exposure.times, in order")
        return exif


# --- from the rig description ---------------------------------------------------------------------------

BackendFactory = Callable[[Mapping[str, Any]], CameraBackend]


def _gphoto2(desc: Mapping[str, Any]) -> CameraBackend:
    return Gphoto2Camera(port=desc.get("port"), config=desc.get("config", "shutterspeed"),
                         delete=bool(desc.get("delete", True)))


def _watch(desc: Mapping[str, Any]) -> CameraBackend:
    if "folder" not in desc:
        raise CameraError("camera backend 'watch' needs 'folder' (camera.folder)")
    defaults = WatchSettings()
    settings = WatchSettings(timeout_s=float(desc.get("timeout_s", defaults.timeout_s)),
                             poll_s=float(desc.get("poll_s", defaults.poll_s)),
                             settle_s=float(desc.get("settle_s", defaults.settle_s)))
    return WatchFolderCamera(desc["folder"], desc.get("pattern", "*"), settings, remove=bool(desc.get("remove", False)))


BACKENDS: dict[str, BackendFactory] = {"gphoto2": _gphoto2, "watch": _watch}
"""The built-in backends by name; :func:`open_camera` takes more through ``registry``."""

_open_lock = threading.Lock()


def open_camera(desc: Mapping[str, Any], registry: Mapping[str, BackendFactory] | None = None) -> CameraBackend:
    """The camera backend of a rig description's ``camera`` dict.

    Keys, by ``backend``:

    - ``gphoto2``: ``port`` (libgphoto2 port such as ``"usb:001,004"``; default the first camera),
      ``config`` (shutter-speed widget name, default ``shutterspeed``), ``delete`` (delete files from the
      card once stored, default true).
    - ``watch``: ``folder`` (required: where the camera's software saves), ``pattern`` (fnmatch,
      case-insensitive, default ``*``; e.g. ``*.CR2``), ``timeout_s`` (per file, default 60), ``settle_s``
      (a file is complete once unchanged this long, default 0.3), ``poll_s`` (default 0.05), ``remove``
      (delete the watched file once stored, default false).

    Other keys (``retries``, read by the session) are ignored. ``registry`` adds or overrides backends
    (name -> factory taking the dict). An unknown name is a CameraError naming the known ones.
    """
    backends = {**BACKENDS, **(registry or {})}
    name = desc.get("backend")
    if name not in backends:
        raise CameraError(f"unknown camera backend {name!r} (known: {', '.join(sorted(backends))})")
    with _open_lock:
        return backends[name](desc)
