"""Where the memory of every process facetsynth starts comes from, unless the user says otherwise.

Both settings are read once, when a process starts (or imports numpy), so they
are set in the environment of the process that starts the others: the
Snakemake process whose jobs inherit it, the ``facetsynth`` command, the test
suite. On the project's 2-core virtual machine the first touch of a fresh page
is slow, and the stages allocate their per-tile tables again for every tile
(docs/speed.md, "Huge pages"; docs/decisions.md, "Freed memory kept for
reuse"). Neither changes a number: the outputs are bitwise the same.

- numpy asks Linux for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on
  every large array, on kernels >= 4.6, unless ``NUMPY_MADVISE_HUGEPAGE`` says
  otherwise. A huge page's first touch can cost milliseconds: the fresco's fit
  from its photos took 206 s with them and 154 s without. Set to 0 where the
  user has not set it; a user who wants huge pages exports it as 1.
- glibc's malloc serves an allocation above its mmap threshold with fresh pages
  from the kernel and returns them on free (and trims the heap's free top
  beyond its trim threshold), so a tile's tables of a few MB to 32 MB were
  faulted in again for every tile. ``GLIBC_TUNABLES`` (glibc's documented
  interface, ignored by other C libraries) raises the threshold to glibc's
  largest, 32 MiB, and the trim threshold to 1 GiB: freed tables are reused.
  rectify..refine at 128^2 x 480 lights: 65.5 s -> 57.3 s. Set only where the
  user has set no malloc tunable; one that has keeps theirs.
"""

from __future__ import annotations

import os

VARIABLE = "NUMPY_MADVISE_HUGEPAGE"
TUNABLES = "GLIBC_TUNABLES"
MALLOC = "glibc.malloc.mmap_threshold=33554432:glibc.malloc.trim_threshold=1073741824"


def memory_defaults() -> None:
    """numpy on small pages (NUMPY_MADVISE_HUGEPAGE=0) and freed memory kept for reuse (glibc's malloc tunables),
    where the user has not set them, for every process started after this (such as a Snakemake job) and for
    numpy imported after this in this process."""
    os.environ.setdefault(VARIABLE, "0")
    given = os.environ.get(TUNABLES, "")
    if "glibc.malloc." not in given:
        os.environ[TUNABLES] = f"{given}:{MALLOC}" if given else MALLOC
