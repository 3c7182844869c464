"""File I/O shared by all stages: EXR images, JSON/YAML documents, .npy tensors.

Every writer is atomic (DESIGN.md sec. 4): data goes to a temporary name in the
destination folder and is renamed into place only when complete, so a crash
never leaves a half-written file that looks whole. Readers turn every failure
into an :class:`~facetsynth.io.errors.InputError` that names the file.

A job killed mid-write (SIGKILL, out of memory, a cluster's time limit) cannot
clean up: its temporaries (``.NAME.PID-TID.tmpSUFFIX``, PID the writing
process) are removed, once process PID is gone, by the next process that
writes in the same folder or resumes the same staging folder.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import shutil
import stat
import threading
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
import OpenEXR
import yaml

from .errors import InputError, excerpt

PathLike = str | os.PathLike

log = logging.getLogger(__name__)

# The temporary name of atomic_path: ".NAME.PID-TID.tmpSUFFIX" beside the file NAME.
_TEMPORARY = re.compile(r"\..+\.(?P<pid>\d+)-\d+\.tmp.*")
_swept: set[str] = set()   # the folders this process has cleared of stale temporaries


@contextlib.contextmanager
def atomic_path(path: PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is untouched.
    ``suffix`` keeps the extension for writers that look at it. The first write
    of a process into a folder removes the temporaries that killed writers
    left there (:func:`remove_stale_temporaries`), those of ``path`` included.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _sweep_once(path.parent)
    # Unique per process and thread; named, not created (mkstemp's extra file creation cost 0.3 ms a
    # file in folders of thousands of frames): the writer creates it.
    tmp = path.parent / f".{path.name}.{os.getpid()}-{threading.get_ident()}.tmp{suffix}"
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_dir(path: PathLike, key: Any = None) -> Iterator[Path]:
    """Yield a staging folder beside ``path``; move it to ``path`` when complete.

    An existing ``path`` is replaced only after the new folder is complete.
    On an exception the staging folder (``.NAME.partial``) is kept, so nothing
    computed is lost: a later run with the same ``key`` (a JSON-able record of
    the inputs and parameters) resumes in it, and writers skip the files that
    are already there (each was written atomically, so each is whole). A
    different key starts afresh. Temporaries of a killed run are removed on
    resuming, and the folder is never published with a temporary in it.

    The old ``path`` is moved aside (``.NAME.replaced``) before the new one
    takes its place and deleted after, so a kill while publishing never
    leaves a half-deleted folder under the published name.
    """
    path = Path(path)
    staging = path.parent / f".{path.name}.partial"
    replaced = path.parent / f".{path.name}.replaced"
    key_file = staging / ".stage-key.json"
    key_text = json.dumps(key, sort_keys=True, default=_json_default)
    if replaced.exists():                  # left by a run killed while publishing
        shutil.rmtree(replaced)
    if staging.exists() and not (key is not None and key_file.is_file() and key_file.read_text() == key_text):
        shutil.rmtree(staging)
    remove_stale_temporaries(staging.rglob(".*.tmp*"))
    staging.mkdir(parents=True, exist_ok=True)
    key_file.write_text(key_text)
    yield staging
    left = [p for p in staging.rglob(".*.tmp*") if _temporary_writer(p) is not None]
    if left:
        raise RuntimeError(f"{path}: not published: {len(left)} temporary file(s) still in {staging} "
                           f"(first: {left[0].name}), a writer is still running")
    key_file.unlink()
    if path.exists():
        os.replace(path, replaced)
    os.replace(staging, path)
    shutil.rmtree(replaced, ignore_errors=True)


def _sweep_once(folder: Path) -> None:
    """Remove the stale temporaries in ``folder`` at this process's first write there.

    Once per folder, not per write: listing a folder of 3000 frames costs 1.2 ms, which at every write
    would make writing a folder of frames quadratic. A job killed while this process writes in the
    same folder leaves its temporaries to the next process that writes there.
    """
    key = os.path.abspath(folder)
    if key not in _swept:
        remove_stale_temporaries(folder.glob(".*.tmp*"))
        _swept.add(key)


def remove_stale_temporaries(files: Iterable[Path]) -> None:
    """Delete those of ``files`` that are :func:`atomic_path` temporaries whose writing process is gone:
    left by a killed job, they would never be renamed into place. A live process's temporary (a
    concurrent writer's) stays."""
    for file in files:
        pid = _temporary_writer(file)
        if pid is not None and not _process_alive(pid):
            log.info("removing %s, a temporary left by process %d, which is gone", file, pid)
            file.unlink(missing_ok=True)


def _temporary_writer(file: Path) -> int | None:
    """The pid in the name of an :func:`atomic_path` temporary, else None."""
    match = _TEMPORARY.fullmatch(file.name)
    return None if match is None else int(match["pid"])


def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (signal 0 checks without signalling).

    A pid is only known on the machine that wrote it: a temporary written on another cluster node
    counts as stale when its pid is free here.
    """
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:                 # another user's process
        return True
    return True


def file_key(*paths: PathLike) -> list:
    """(path, size, mtime) of files, to key a resumable stage on its inputs."""
    return [(str(p), os.stat(p).st_size, os.stat(p).st_mtime_ns) for p in map(Path, paths)]


# --- EXR ---------------------------------------------------------------------------

def write_exr(path: PathLike, channels: dict[str, np.ndarray], header: dict[str, Any] | None = None,
              precision: str = "float32") -> None:
    """Write named channels to an EXR file atomically.

    ``channels`` maps names to (H, W) arrays, or to (H, W, 3) arrays which
    OpenEXR stores as ``NAME.R/G/B`` (``"RGB"`` becomes plain R, G, B).
    ``header`` holds extra attributes (numbers, strings, 3x3 arrays).
    ``precision``: ``"float32"``, lossless 32-bit floats (model parameters);
    ``"float24"``, 32-bit floats stored with PXR24 compression, which keeps
    the float32 range and rounds the mantissa to 15 bits (relative error
    <= 2^-16 = 1.5e-5, far below any sensor's noise; on noisy frames 40 %
    smaller and 1.5x faster to write than ZIP), for measured radiance;
    ``"float16"``, half floats, as a camera delivers its exposures.
    """
    dtype, compression = _PRECISIONS[precision]
    data = {name: np.ascontiguousarray(a, dtype=dtype) for name, a in channels.items()}
    # OpenEXR adds dataWindow to the dict it is given: always pass a fresh one.
    hdr = {"compression": compression, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    with atomic_path(path, suffix=".exr") as tmp:
        OpenEXR.File(hdr, data).write(str(tmp))


_PRECISIONS = {"float32": (np.float32, OpenEXR.ZIP_COMPRESSION),
               "float24": (np.float32, OpenEXR.PXR24_COMPRESSION),
               "float16": (np.float16, OpenEXR.ZIP_COMPRESSION)}


MAX_IMAGE_BYTES = 4 << 30
"""The most memory an image's pixels may take once read as float32 (4 GiB: a 100-megapixel frame's R, G, B
and a mask, twice the largest camera in use here): a file whose header declares more is refused before
any pixel is read (docs/decisions.md, "Hostile input: captures and config (issue 32)")."""


def exr_header(path: PathLike) -> dict[str, Any]:
    """An EXR file's header, read without its pixels; InputError naming the file when it is missing, a folder
    or not an OpenEXR image."""
    path = Path(path)
    _require_file(path)
    try:
        return dict(OpenEXR.File(str(path), header_only=True).header())
    except Exception as exc:  # OpenEXR raises bare RuntimeErrors on damaged files
        raise InputError(path, f"not a readable OpenEXR image ({excerpt(str(exc))})") from None


def exr_size(path: PathLike, header: dict[str, Any] | None = None) -> tuple[int, int]:
    """(width, height) an EXR file declares (its data window); InputError when the data window is not its
    display window (pixels offset or cropped within the image: read as if at the origin they would be
    misplaced)."""
    path = Path(path)
    header = exr_header(path) if header is None else header
    try:
        (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in header["dataWindow"])
        display = header.get("displayWindow")
        shown = None if display is None else tuple(tuple(int(v) for v in corner) for corner in display)
    except (KeyError, TypeError, ValueError):
        raise InputError(path, "not a readable OpenEXR image (no data window in its header)") from None
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if width <= 0 or height <= 0:
        raise InputError(path, f"not a readable OpenEXR image (empty data window ({x0}, {y0})-({x1}, {y1}))")
    if shown is not None and shown != ((x0, y0), (x1, y1)):
        (dx0, dy0), (dx1, dy1) = shown
        raise InputError(path, f"its pixels (data window ({x0}, {y0})-({x1}, {y1})) are not its image (display "
                               f"window ({dx0}, {dy0})-({dx1}, {dy1})): an offset or cropped EXR would be read "
                               "misplaced; write the whole image (crop or pad it to its display window)")
    return width, height


def _refuse_large(path: Path, width: int, height: int, channels: int) -> None:
    """InputError when ``channels`` float32 channels of width x height would take more than MAX_IMAGE_BYTES."""
    if 4 * width * height * channels > MAX_IMAGE_BYTES:
        raise InputError(path, f"declares {width}x{height} pixels of {channels} channel(s), "
                               f"{4 * width * height * channels / 2**30:.3g} GiB as float32: more than the "
                               f"{MAX_IMAGE_BYTES / 2**30:g} GiB an image may take; refused before reading it")


def read_exr(path: PathLike, shape: tuple[int, int] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read every channel of an EXR file as float32 arrays, and its header.

    R, G, B come back together as ``"RGB"`` (H, W, 3); other channels by name: an RGBA file's alpha as
    ``"A"`` (``NAME.R/G/B/A`` layers likewise as ``NAME.RGB`` and ``NAME.A``), a depth as ``"Z"``.
    The header is read first (:func:`exr_size`): a data window offset from the display window, or a
    declared size beyond :data:`MAX_IMAGE_BYTES` (or, with ``shape`` (height, width), any size but
    that one) is refused before a pixel is read. Raises InputError naming the file when it is missing
    or unreadable.
    """
    path = Path(path)
    header = exr_header(path)
    width, height = exr_size(path, header)
    if shape is not None and (height, width) != tuple(shape[:2]):
        raise InputError(path, f"frame is {width}x{height}, the manifest's camera is {shape[1]}x{shape[0]} "
                               "(the file's header; no pixel read)")
    _refuse_large(path, width, height, max(1, len(header.get("channels", ()))))
    try:
        f = OpenEXR.File(str(path))
        channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
        header = dict(f.header())
    except Exception as exc:  # OpenEXR raises bare RuntimeErrors on damaged files
        raise InputError(path, f"not a readable OpenEXR image ({excerpt(str(exc))})") from None
    for name in [n for n, a in channels.items() if a.ndim == 3 and a.shape[-1] == 4]:
        rgba = channels.pop(name)     # R, G, B, A read as one: "RGBA", or a layer's "NAME" (NAME.R/G/B/A)
        rgb_name, alpha_name = ("RGB", "A") if name == "RGBA" else (name, f"{name}.A")
        channels[rgb_name], channels[alpha_name] = rgba[..., :3], rgba[..., 3]
    return channels, header


def read_rgb(path: PathLike, require_finite: bool = True, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read the R, G, B channels of an EXR image as a (H, W, 3) float32 array (``shape``: :func:`read_exr`)."""
    return read_frame(path, require_finite, shape)[0]


def read_frame(path: PathLike, require_finite: bool = True,
               shape: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read an HDR frame: R, G, B (H, W, 3) and its ``saturated`` mask (H, W) bool.

    Channels beyond R, G, B and ``saturated`` (alpha, depth, layers) are ignored. The mask is all False
    when the file has no ``saturated`` channel. With ``require_finite``, a NaN or Inf pixel is an
    InputError naming the pixel. ``shape`` (height, width): any other declared size is an InputError
    before a pixel is read.
    """
    channels, _ = read_exr(path, shape)
    if "RGB" not in channels:
        found = ", ".join(excerpt(name, 20) for name in sorted(channels)[:12])
        raise InputError(path, f"no R, G, B channels (found: {found}{', ...' if len(channels) > 12 else ''})")
    rgb = channels["RGB"]
    if require_finite and not np.isfinite(rgb).all():
        bad = np.argwhere(~np.isfinite(rgb).all(axis=-1))
        row, col = bad[0]
        raise InputError(path, f"{len(bad)} pixel(s) are NaN or Inf (first at row {row}, col {col})")
    saturated = channels.get("saturated", np.zeros(rgb.shape[:2], np.float32)) > 0
    return rgb, saturated


# --- 8-bit exposures ----------------------------------------------------------------

_EXR_MAGIC = b"\x76\x2f\x31\x01"


def exposure_bits(path: PathLike) -> int | None:
    """How an exposure file stores its values: None for OpenEXR (linear exposure values), 8 for an 8-bit
    image (JPEG, PNG, TIFF: a camera's nonlinear codes, linearized by the hdr stage's recovered response,
    :mod:`facetsynth.capture.response`). Decided by the pixel format (OpenImageIO), not the name; any other format
    is an InputError naming the file, as are a folder or a symlink loop in its place."""
    path = Path(path)
    _require_file(path)
    try:
        with open(path, "rb") as f:
            if f.read(4) == _EXR_MAGIC:
                return None
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except OSError as exc:
        raise InputError(path, f"unreadable ({exc.strerror})") from None
    spec = _oiio_spec(path)
    import OpenImageIO as oiio
    if spec.format.basetype == oiio.UINT8:
        return 8
    raise InputError(path, f"a {spec.format} {spec.nchannels}-channel image: exposures are OpenEXR (linear) or "
                           "8-bit images (JPEG, PNG, TIFF)")


def read_codes(path: PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """An 8-bit image's codes as (H, W, 3) uint8 (a grey image repeated in R, G, B; alpha dropped). The size
    its header declares is checked before its pixels are read: beyond :data:`MAX_IMAGE_BYTES`, or (with
    ``shape``, (height, width)) any other size, is an InputError."""
    import OpenImageIO as oiio

    path = Path(path)
    _require_file(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"not a readable image ({excerpt(oiio.geterror().strip() or 'unknown format')})")
    try:
        spec = inp.spec()
        if shape is not None and (spec.height, spec.width) != tuple(shape[:2]):
            raise InputError(path, f"frame is {spec.width}x{spec.height}, the manifest's camera is "
                                   f"{shape[1]}x{shape[0]} (the file's header; no pixel read)")
        if 4 * spec.width * spec.height * max(3, spec.nchannels) > MAX_IMAGE_BYTES:
            raise InputError(path, f"declares {spec.width}x{spec.height} pixels: more than the "
                                   f"{MAX_IMAGE_BYTES / 2**30:g} GiB an image may take; refused before reading it")
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.UINT8)
    finally:
        inp.close()
    if pixels is None or spec.nchannels not in (1, 3, 4):
        raise InputError(path, f"unreadable 8-bit image ({spec.nchannels} channels; "
                               f"{excerpt(oiio.geterror().strip())})")
    pixels = np.asarray(pixels, np.uint8).reshape(spec.height, spec.width, spec.nchannels)
    return np.ascontiguousarray(np.repeat(pixels, 3, axis=-1) if spec.nchannels == 1 else pixels[..., :3])


def read_exposure(path: PathLike, shape: tuple[int, int] | None = None) -> tuple[np.ndarray, int | None]:
    """An exposure file's values as (H, W, 3) float32 and its bits (:func:`exposure_bits`): an EXR's linear
    values (NaN / Inf kept), or an 8-bit image's codes 0..255 (NOT linear: see :mod:`facetsynth.capture.response`).
    With ``shape`` (height, width), a file of another size is refused from its header, before its pixels
    are read."""
    bits = exposure_bits(path)
    if bits is None:
        return read_frame(path, require_finite=False, shape=shape)[0], None
    return read_codes(path, shape).astype(np.float32), bits


def _require_file(path: Path) -> None:
    """InputError naming ``path`` unless it is a file (or a link to one): a folder, a symlink loop or a
    missing file each said so in one line."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(path, "a symbolic link loop, not a file") from None
        raise InputError(path, f"unreadable ({exc.strerror})") from None
    except ValueError as exc:   # a NUL byte in the name
        raise InputError(path, f"not a usable file name ({exc})") from None
    if stat.S_ISDIR(mode):
        raise InputError(path, "is a folder, not a file")
    if not stat.S_ISREG(mode):
        raise InputError(path, "not a regular file")


def _oiio_spec(path: Path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"not a readable image: neither OpenEXR nor a format OpenImageIO reads "
                               f"({oiio.geterror().strip() or 'unknown format'})")
    try:
        return inp.spec()
    finally:
        inp.close()


# --- JSON / YAML / npy -------------------------------------------------------------

def write_json(path: PathLike, data: Any) -> None:
    """Write a JSON document atomically (2-space indent, numpy scalars converted)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_json(path: PathLike) -> Any:
    """Read a JSON document; InputError names the file on failure, a key given twice in one object
    included (Python's json would keep the last silently)."""
    path = Path(path)
    _require_file(path)
    try:
        return json.loads(_read_text(path), object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not valid JSON: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except RecursionError:
        raise InputError(path, "not valid JSON: nested too deeply") from None
    except _DuplicateKey as exc:
        raise InputError(path, f"not valid JSON: key '{excerpt(exc.key)}' appears twice in one object "
                               "(which value is meant?)") from None


class _DuplicateKey(ValueError):
    """A key given twice in one JSON object or YAML mapping."""

    def __init__(self, key: Any, line: int | None = None):
        super().__init__(key)
        self.key, self.line = key, line


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """json's object_pairs_hook: the object as a dict, or _DuplicateKey for a key given twice."""
    seen: dict[str, Any] = {}
    for key, value in pairs:
        if key in seen:
            raise _DuplicateKey(key)
        seen[key] = value
    return seen


def _read_text(path: Path) -> str:
    """A text file's contents; InputError for a file that cannot be read (missing, a folder, no permission)."""
    try:
        return path.read_text()
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a file") from None
    except UnicodeDecodeError:
        raise
    except OSError as exc:
        raise InputError(path, f"unreadable ({exc.strerror or exc})") from None


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping (YAML 1.2 forbids it; PyYAML keeps
    the last silently). Merge keys (``<<``) still override, as YAML defines them."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:     # an unhashable key: SafeLoader names it
                    continue
                if duplicate:
                    raise _DuplicateKey(key, key_node.start_mark.line + 1)
        return super().construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:map", _UniqueKeyLoader.construct_yaml_map)


def read_yaml(path: PathLike) -> Any:
    """Read a YAML document; InputError names the file on failure (a key given twice in one mapping
    included). A syntax error is reported by its line, column and problem, never by echoing the file."""
    path = Path(path)
    _require_file(path)
    try:
        return yaml.load(_read_text(path), Loader=_UniqueKeyLoader)
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not valid YAML: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except _DuplicateKey as exc:
        raise InputError(path, f"not valid YAML: key '{excerpt(exc.key)}' appears twice in one mapping "
                               f"(line {exc.line}; which value is meant?)") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise InputError(path, f"not valid YAML{where}: {excerpt(exc.problem or exc.context or 'syntax error')}"
                         ) from None
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({excerpt(exc)})") from None
    except RecursionError:
        raise InputError(path, "not valid YAML: nested too deeply") from None


def read_npy(path: PathLike, mmap_mode: str | None = None) -> np.ndarray:
    """Read a .npy tensor (memory-mapped with ``mmap_mode``); InputError names the file on failure."""
    path = Path(path)
    try:
        return np.load(path, mmap_mode=mmap_mode)
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except Exception as exc:
        raise InputError(path, f"not a readable .npy tensor ({exc})") from None


class NpyRows:
    """A .npy tensor read by rows (``rows[index]``, any numpy index on the first axis), each read through a
    memory map opened and closed for it: the pages read stay in the page cache, where the kernel reclaims
    them, instead of counting in this process's resident memory for as long as one map of the whole file
    lives (the cluster stage's peak RSS was the partial NDF files it had read: docs/decisions.md, "At the
    paper's scale")."""

    def __init__(self, path: PathLike):
        self.path = Path(path)
        table = read_npy(self.path, mmap_mode="r")
        self.shape, self.dtype = table.shape, table.dtype
        del table

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> np.ndarray:
        table = np.load(self.path, mmap_mode="r")
        rows = np.array(table[index])
        del table                      # unmapped here: its pages leave this process's resident set
        return rows


class BitRows(NpyRows):
    """A (P, F) bool table kept as bits (``numpy.packbits`` along F: a (P, ceil(F / 8)) uint8 .npy, 8 x smaller:
    separate's sample validity, 0.31 -> 0.04 GB at 800^2 x 480), read by rows as :class:`NpyRows` reads a
    tensor: ``rows[index]`` bool (n, F). ``count`` is F, which the packed width rounds up. A (P, F) bool .npy
    (as facetsynth wrote it before) is read as it is. InputError names the file whose shape fits neither."""

    def __init__(self, path: PathLike, count: int, rows: int | None = None, what: str = "bit table"):
        super().__init__(path)
        self.packed, nbytes = self.dtype == np.uint8, -(-count // 8)
        if (len(self.shape) != 2 or self.dtype not in (np.uint8, np.bool_)
                or self.shape[1] != (nbytes if self.packed else count) or rows is not None and self.shape[0] != rows):
            n = "P" if rows is None else rows
            raise InputError(self.path, f"{what}: a {self.dtype} tensor of shape {self.shape}, expected "
                                        f"({n}, {nbytes}) uint8 bits or ({n}, {count}) bool")
        self.shape, self.dtype = (self.shape[0], count), np.dtype(bool)

    def __getitem__(self, index) -> np.ndarray:
        rows = super().__getitem__(index)
        return np.unpackbits(rows, axis=-1, count=self.shape[1]).view(bool) if self.packed else rows


@contextlib.contextmanager
def npy_writer(path: PathLike, dtype, shape: tuple[int, ...]) -> Iterator[Callable[[np.ndarray], None]]:
    """Write a .npy tensor of ``shape`` atomically, row blocks in order: yields ``write(block)``, which
    appends ``block`` (n, *shape[1:]). The bytes are np.save's; the pages written go to the page cache,
    not into this process's resident memory as a writable memory map's would. Raises ValueError when the
    blocks do not fill ``shape`` exactly."""
    dtype = np.dtype(dtype)
    written = 0
    with atomic_path(path, suffix=".npy") as tmp, open(tmp, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                                                 "shape": tuple(shape)})

        def write(block: np.ndarray) -> None:
            nonlocal written
            block = np.ascontiguousarray(block, dtype=dtype)
            if block.shape[1:] != tuple(shape[1:]) or written + len(block) > shape[0]:
                raise ValueError(f"{path}: a block of shape {block.shape} does not fit the tensor {tuple(shape)} "
                                 f"after {written} rows")
            f.write(block.tobytes())
            written += len(block)

        yield write
        if written != shape[0]:
            raise ValueError(f"{path}: {written} rows written of {shape[0]}")


def write_npy(path: PathLike, array: np.ndarray) -> None:
    """Write a .npy tensor atomically; later stages can memory-map it."""
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, array)
