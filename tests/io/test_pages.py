"""numpy on small pages and freed memory kept for reuse in every process facetsynth starts, unless the user
says otherwise (facetsynth.io.pages)."""

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from facetsynth.io.pages import MALLOC, TUNABLES, VARIABLE

PROBE = "import facetsynth.app.cli, numpy; print(numpy._core.multiarray._get_madvise_hugepage())"
CHILD = "import facetsynth.app.cli, os, subprocess, sys; subprocess.run([sys.executable, '-c', sys.argv[1]])"
# a tile's four tables of 16 MiB each filled, freed and filled again 10 times: the page faults of the refills
REFILL = """
import resource, numpy
tables = [numpy.ones(2 << 20) for _ in range(4)]
del tables
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    tables = [numpy.ones(2 << 20) for _ in range(4)]
    del tables
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def environment(**given):
    env = {k: v for k, v in os.environ.items() if k not in (VARIABLE, TUNABLES)}
    env.update({k: v for k, v in given.items() if v is not None})
    return env


@pytest.mark.parametrize("given, expected", [(None, "False"), ("1", "True"), ("0", "False")])
def test_the_command_allocates_on_small_pages_unless_the_user_sets_the_variable(given, expected):
    out = subprocess.run([sys.executable, "-c", PROBE], env=environment(NUMPY_MADVISE_HUGEPAGE=given),
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected


@pytest.mark.parametrize("given, expected", [
    (None, MALLOC),
    ("glibc.pthread.rseq=0", "glibc.pthread.rseq=0:" + MALLOC),          # other tunables kept, malloc's added
    ("glibc.malloc.arena_max=2", "glibc.malloc.arena_max=2"),            # the user's malloc settings win
])
def test_the_commands_jobs_reuse_freed_memory_unless_the_user_tunes_malloc(given, expected):
    probe = f"import os; print(os.environ.get('{TUNABLES}'))"
    out = subprocess.run([sys.executable, "-c", CHILD, probe], env=environment(GLIBC_TUNABLES=given),
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc",
                    reason="needs glibc: GLIBC_TUNABLES sets its malloc (musl's and macOS's ignore it)")
def test_a_freed_table_is_refilled_without_fresh_pages():
    """The settings take effect in a started job. With glibc's defaults the 10 refills of four 16 MiB tables
    fault in most of their 163840 fresh pages (4 KiB): the threshold rises to a freed table's size, but the
    heap's free top beyond twice that (32 MiB) goes back to the kernel; with the heap kept, none."""
    faults = {}
    for name, tunables in (("default", None), ("kept", MALLOC)):
        env = environment(GLIBC_TUNABLES=tunables, NUMPY_MADVISE_HUGEPAGE="0")
        out = subprocess.run([sys.executable, "-c", REFILL], env=env, capture_output=True, text=True, check=True)
        faults[name] = int(out.stdout)
    assert faults["kept"] < 100 and faults["default"] > 10 * 4 * 4096 / 2, faults


def test_the_workflow_calls_it_before_its_jobs_start():
    """Snakemake's jobs inherit the environment of the Snakemake process that parsed the Snakefile."""
    common = Path(__file__).resolve().parents[2] / "workflow" / "rules" / "common.smk"
    assert "\nmemory_defaults()" in common.read_text()
