"""Run a stage from a Snakemake ``script:``: logging to the rule's log, clean errors."""

from __future__ import annotations

import logging
import sys
from types import ModuleType
from typing import Any, Callable

from threadpoolctl import threadpool_limits

from ..io.errors import InputError
from .common import scatter_item


def run_script(snakemake: Any, stage: ModuleType) -> None:
    """A stage module's ``run(inputs, outputs, settings, threads)`` from a Snakemake ``script:``: its
    ``Inputs``, ``Outputs`` and ``Settings`` filled by name from the rule (:class:`facetsynth.stages.settings.RuleFiles`,
    :class:`~facetsynth.stages.settings.StageSettings`), run by :func:`run_stage`; a scatter part's rule
    (the ``{scatteritem}`` wildcard) also passes its ``part``: (part, parts) of
    :func:`~facetsynth.stages.common.scatter_item`."""
    scatter = ({"part": scatter_item(snakemake.wildcards.scatteritem)}
               if "scatteritem" in snakemake.wildcards.keys() else {})
    run_stage(snakemake, stage.run, stage.Inputs.from_rule(snakemake.input), stage.Outputs.from_rule(snakemake.output),
              stage.Settings.from_params(snakemake.params), threads=snakemake.threads, **scatter)


def run_stage(snakemake: Any, stage: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
    """Call ``stage(*args, **kwargs)`` with logging sent to the rule's log file.

    Bad input (InputError) ends the job with one clear line naming the file
    and the problem, in the log and on stderr, instead of a traceback. BLAS
    and OpenMP pools are limited to the rule's ``threads`` (a ``script:``
    job does not get Snakemake's OMP_NUM_THREADS, which only ``shell:`` sets).
    """
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if snakemake.log:
        handlers = [logging.FileHandler(snakemake.log[0], mode="w")]
        sys.stderr = open(snakemake.log[0], "a", buffering=1)  # progress bars (tqdm) go to the log
    logging.basicConfig(level=logging.INFO, handlers=handlers, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log = logging.getLogger(f"facetsynth.{snakemake.rule}")
    try:
        with threadpool_limits(limits=snakemake.threads):      # BLAS keeps to the cores the job was given
            stage(*args, **kwargs)
    except InputError as exc:
        log.error("%s", exc)
        print(f"facetsynth {snakemake.rule}: error: {exc}", file=sys.__stderr__)
        sys.exit(1)
