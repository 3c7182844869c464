"""numpy on small pages in every process facetsynth starts, unless the user asks for huge pages."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from facetsynth.io.pages import VARIABLE

PROBE = "import facetsynth.app.cli, numpy; print(numpy._core.multiarray._get_madvise_hugepage())"


@pytest.mark.parametrize("given, expected", [(None, "False"), ("1", "True"), ("0", "False")])
def test_the_command_allocates_on_small_pages_unless_the_user_sets_the_variable(given, expected):
    env = {k: v for k, v in os.environ.items() if k != VARIABLE}
    if given is not None:
        env[VARIABLE] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected


def test_the_workflow_calls_it_before_its_jobs_start():
    """Snakemake's jobs inherit the environment of the Snakemake process that parsed the Snakefile."""
    common = Path(__file__).resolve().parents[2] / "workflow" / "rules" / "common.smk"
    assert "\nsmall_pages()" in common.read_text()
