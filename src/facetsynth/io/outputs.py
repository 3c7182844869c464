"""Output folders of the ``facetsynth`` writers: an output never overwrites an input.

Every command that writes a folder (``predict``, ``stencil-fit --out``,
``stencil-edit --out``) calls :func:`prepare_output_dir` once its inputs are
read and before it writes anything. The rules, in the order they are checked:

1. The output must be a folder: an existing file at that path (or a file
   where one of its parent folders should be) is an error.
2. The output never overlaps an input folder: it may not be, contain, or lie
   inside one (``predict``: the model folder, the capture folder, every folder
   holding a frame file the manifest lists). ``--force`` does not lift this.
3. The output never replaces an input file: for input *files* (a BRDF file,
   a ``stencil.json``) the only check is that none of the names the command
   writes lands on one, so ``stencil-fit x.bin --out .`` is not refused for
   sharing a folder with ``x.bin`` (rule 4 still asks for ``--force`` there),
   but ``stencil-edit fit/stencil.json --out fit`` is, even with ``--force``.
4. An existing non-empty folder is used only if this same command made it
   (it holds the marker file :data:`MARKER` naming the command), or with
   ``--force``.

A folder the command creates, or an empty one it takes over, gets the marker,
a small deterministic JSON file (``{"written_by": "facetsynth predict"}``), so
that running the command again into it needs no ``--force``. A foreign folder
written into with ``--force`` is not marked.

Writing (issue 32), by :func:`output_folder`:

5. One writer at a time: the command holds a lock on the folder (``flock`` of
   the file :data:`LOCK` in it, which names the holder's pid) for as long as it
   writes. A second writer is refused, naming the first; a lock left by a dead
   process holds nothing (the kernel released it) and is taken over.
6. Nothing is published half-written: the command writes into a staging
   folder inside the output folder and moves its files into place only when
   all are written, the last-named of ``writes`` (the manifest, the .gltf)
   last. A full disk, a Ctrl-C or any error removes the staging folder, and
   the folder too if this run created it: the old output stays whole, or there
   is none. A subfolder (``frames/``) replaces the old one whole, except in a
   foreign folder written with ``--force``, where its files are moved in one
   by one and the user's other files stay.

``render`` writes one file, by :func:`refuse_output_file` and
:func:`write_errors`: never the model folder or a file in it, never a file it
read, and an existing file only if ``render`` wrote it (its metadata say so)
or with ``--force``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
from pathlib import Path
from typing import Iterable, Iterator

from .errors import InputError

MARKER = ".facetsynth-output"
LOCK = ".facetsynth-lock"          # held (flock) by the one command writing into the folder
STAGING = ".facetsynth-staging-"   # + pid: the folder a command writes into before publishing


def _marker_text(command: str) -> str:
    return json.dumps({"written_by": f"facetsynth {command}"}) + "\n"


def made_by(folder: Path, command: str) -> bool:
    """Whether ``folder`` carries the marker of ``command`` (a damaged marker counts as foreign)."""
    try:
        return (folder / MARKER).read_text() == _marker_text(command)
    except OSError:
        return False


def _overlap(out: Path, folder: Path) -> str | None:
    """How ``out`` overlaps the input ``folder`` (both resolved): 'is', 'lies inside', 'contains' or None."""
    if out == folder:
        return "is"
    if folder in out.parents:
        return "lies inside"
    if out in folder.parents:
        return "contains"
    return None


def refuse_overlap(out: str | os.PathLike, input_dirs: Iterable[str | os.PathLike] = (),
                   input_files: Iterable[str | os.PathLike] = (), writes: Iterable[str] = ()) -> None:
    """InputError naming ``out`` if it overlaps an input folder, or if writing ``writes`` replaces an input file."""
    target = Path(out).resolve()
    for folder in sorted({Path(d).resolve() for d in input_dirs}):
        how = _overlap(target, folder)
        if how:
            raise InputError(out, f"output folder {how} the input folder {folder}; choose an output folder "
                                  "apart from the inputs")
    files = {Path(f).resolve() for f in input_files}
    for name in writes:
        if (target / name).resolve() in files:
            raise InputError(out, f"writing {name} here would replace the input file {target / name}; "
                                  "choose another output folder")


def _existing_ancestor_file(path: Path) -> Path | None:
    """The first existing non-folder among ``path``'s parents, if any (mkdir would fail on it)."""
    for parent in path.parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def prepare_output_dir(out: str | os.PathLike, command: str, *, input_dirs: Iterable[str | os.PathLike] = (),
                       input_files: Iterable[str | os.PathLike] = (), writes: Iterable[str] = (),
                       force: bool = False) -> Path:
    """Check ``out`` against the rules in the module docstring, create it if needed, return it.

    ``command`` is the subcommand name (``"predict"``); ``input_dirs`` and
    ``input_files`` are what the command read; ``writes`` the names (relative
    to ``out``) it will write; ``force`` lifts only the non-empty-folder rule.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(path, "exists and is a file; the output must be a folder")
    blocker = _existing_ancestor_file(path)
    if blocker is not None:
        raise InputError(path, f"cannot create the output folder: {blocker} is a file")
    refuse_overlap(path, input_dirs, input_files, writes)
    if path.is_dir() and not _is_empty(path):
        if made_by(path, command) or force:
            return _writable(path)
        raise InputError(path, f"output folder is not empty and was not made by facetsynth {command}; "
                               "choose a new or empty folder, or pass --force to write into it")
    try:
        path.mkdir(parents=True, exist_ok=True)
        (path / MARKER).write_text(_marker_text(command))
    except OSError as exc:
        raise InputError(path, f"cannot create the output folder ({exc.strerror})") from None
    return path


def _is_empty(folder: Path) -> bool:
    """Whether ``folder`` holds nothing (InputError if it cannot be listed)."""
    try:
        return not any(p.name != LOCK for p in folder.iterdir())     # a dead writer's lock holds nothing
    except OSError as exc:
        raise InputError(folder, f"cannot list the output folder ({exc.strerror})") from None


def _writable(path: Path) -> Path:
    """``path`` if this process may write in it, else InputError."""
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(path, "output folder is not writable")
    return path


# --- writing: one writer, nothing half-written (rules 5 and 6) ------------------------------------------

def write_error(path: str | os.PathLike, exc: BaseException) -> InputError:
    """An InputError naming ``path`` for a failed write (a full disk, a read-only folder): the system's reason,
    bounded, without the temporary's name."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    reason = re.sub(r' ?"[^"]*"', "", reason)       # OpenEXR names the temporary: not the user's file
    if len(reason) > 200:
        reason = reason[:200] + "..."
    return InputError(path, f"cannot write ({reason}); nothing written")


@contextlib.contextmanager
def write_errors(path: str | os.PathLike) -> Iterator[None]:
    """Turn an OSError (or OpenEXR's RuntimeError for one) raised by the body into :func:`write_error`."""
    try:
        yield
    except (OSError, RuntimeError) as exc:
        raise write_error(path, exc) from None


def _holder(fd: int) -> str:
    """Who holds the lock whose file is open as ``fd``, as its record says (bounded)."""
    try:
        record = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return f"{str(record['command'])[:60]} (process {int(record['pid'])})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another facetsynth command"


@contextlib.contextmanager
def folder_lock(folder: Path, command: str) -> Iterator[None]:
    """Hold the write lock of ``folder`` (rule 5) for the body; InputError naming the holder if another
    process has it. flock is released by the kernel when its holder dies, so a stale lock file is taken over."""
    path = folder / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(folder, f"cannot lock the output folder ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise InputError(folder, f"output folder is being written by {holder}; wait for it to finish, or "
                                     "choose another folder") from None
        if _same_file(fd, path):
            break
        os.close(fd)                    # its last holder removed it after we opened it: lock the new one
    try:
        with contextlib.suppress(OSError):          # the record only names the holder; a full disk may refuse it
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps({"pid": os.getpid(), "command": f"facetsynth {command}"}).encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``fd``."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    fst = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (fst.st_dev, fst.st_ino)


@contextlib.contextmanager
def output_folder(out: str | os.PathLike, command: str, *, input_dirs: Iterable[str | os.PathLike] = (),
                  input_files: Iterable[str | os.PathLike] = (), writes: Iterable[str] = (),
                  force: bool = False) -> Iterator[Path]:
    """Yield a staging folder for the outputs of ``command`` bound for ``out``; publish them on success.

    ``out`` is checked and created by :func:`prepare_output_dir` (rules 1 to 4) and locked (rule 5) while the
    body writes into the staging folder; its files are then moved into ``out`` (rule 6), those named in
    ``writes`` (names relative to ``out``) in that order, after any others. On any exception, Ctrl-C
    included, nothing is published: the staging folder is removed, and ``out`` too when this call created it;
    an OSError (a full disk, a read-only folder) becomes an InputError naming ``out``.
    """
    writes = list(writes)
    created = not os.path.lexists(out)
    folder = prepare_output_dir(out, command, input_dirs=input_dirs, input_files=input_files, writes=writes,
                                force=force)
    with folder_lock(folder, command):
        replace = created or made_by(folder, command)
        staging = folder / f"{STAGING}{os.getpid()}"
        try:
            _remove_staging(folder)
            staging.mkdir()
            yield staging
            _publish(staging, folder, writes, replace)
        except BaseException as exc:
            shutil.rmtree(folder if created else staging, ignore_errors=True)
            if isinstance(exc, (OSError, RuntimeError)):     # OpenEXR reports a failed write as RuntimeError
                raise write_error(out, exc) from None
            raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)


def _remove_staging(folder: Path) -> None:
    """Remove the staging folders killed writers left in ``folder`` (the lock is ours: nobody else writes)."""
    for stale in folder.glob(f"{STAGING}*"):
        shutil.rmtree(stale, ignore_errors=True)


def _publish(staging: Path, folder: Path, writes: list[str], replace: bool) -> None:
    """Move every entry of ``staging`` into ``folder``, the names of ``writes`` last and in that order; a
    subfolder replaces the old one whole when ``replace``, else its files are moved in one by one."""
    names = sorted(p.name for p in staging.iterdir())
    for name in [n for n in names if n not in writes] + [n for n in writes if n in names]:
        source, target = staging / name, folder / name
        if source.is_dir() and target.is_dir() and not target.is_symlink():
            if replace:
                aside = staging.parent / f"{STAGING}{os.getpid()}.replaced"
                os.replace(target, aside)
                os.replace(source, target)
                shutil.rmtree(aside, ignore_errors=True)
            else:
                _merge(source, target)
        else:
            os.replace(source, target)


def _merge(source: Path, target: Path) -> None:
    """Move the files of folder ``source`` into folder ``target``, keeping target's other files."""
    for entry in sorted(source.iterdir()):
        if entry.is_dir() and (target / entry.name).is_dir():
            _merge(entry, target / entry.name)
        else:
            os.replace(entry, target / entry.name)


# --- render: one output file ---------------------------------------------------------------------------

RENDER_SOFTWARE = "facetsynth render"   # the Software metadata of every picture render writes


def written_by_render(path: Path) -> bool:
    """Whether the picture at ``path`` says (Software metadata) that ``facetsynth render`` wrote it."""
    import OpenImageIO as oiio
    image = oiio.ImageInput.open(str(path))
    if image is None:
        oiio.geterror()
        return False
    try:
        return image.spec().getattribute("Software") == RENDER_SOFTWARE
    finally:
        image.close()


def refuse_output_file(out: str | os.PathLike, model_dir: str | os.PathLike, force: bool = False) -> None:
    """InputError naming ``out`` unless ``render`` may write its picture there: never the model folder, a path
    inside it or any file the model folder holds (or links to); never a folder; an existing file only if
    render wrote it (:func:`written_by_render`) or with ``force``."""
    out, model = Path(out), Path(model_dir)
    target, folder = out.resolve(), model.resolve()
    how = _overlap(target, folder)
    if how in ("is", "lies inside"):
        raise InputError(out, f"output {how} the model folder {folder}; write the picture elsewhere")
    read = {p.resolve() for p in model.iterdir()} if model.is_dir() else set()
    if target in read:
        raise InputError(out, f"is the model's input file {target}; write the picture elsewhere")
    if out.is_dir():
        raise InputError(out, "is a folder; give the picture's file name")
    if out.exists() and not force and not written_by_render(out):
        raise InputError(out, "exists and was not written by facetsynth render; choose a new file name, or pass "
                              "--force to replace it")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise InputError(out.parent, "folder is not writable")

