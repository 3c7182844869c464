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
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from .errors import InputError

MARKER = ".facetsynth-output"


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
        return not any(folder.iterdir())
    except OSError as exc:
        raise InputError(folder, f"cannot list the output folder ({exc.strerror})") from None


def _writable(path: Path) -> Path:
    """``path`` if this process may write in it, else InputError."""
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(path, "output folder is not writable")
    return path
