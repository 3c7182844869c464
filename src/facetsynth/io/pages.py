"""numpy's arrays on the kernel's small pages unless the user says otherwise.

numpy asks Linux for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on
every large array, on kernels >= 4.6, unless ``NUMPY_MADVISE_HUGEPAGE`` says
otherwise; the variable is read once, when numpy is imported. On a virtual
machine a huge page's first touch can cost milliseconds: on the project's
2-core one, the fresco's fit from its photos took 206 s with them and 154 s
without (docs/speed.md, "Huge pages"). On bare metal the difference is small either
way, so every process facetsynth starts sets the variable to 0 where the user
has not set it: a user who wants huge pages exports NUMPY_MADVISE_HUGEPAGE=1.
"""

from __future__ import annotations

import os

VARIABLE = "NUMPY_MADVISE_HUGEPAGE"


def small_pages() -> None:
    """Set NUMPY_MADVISE_HUGEPAGE=0 where it is unset: numpy imported after this (in this process or in
    any process it starts, such as a Snakemake job) allocates on small pages."""
    os.environ.setdefault(VARIABLE, "0")
