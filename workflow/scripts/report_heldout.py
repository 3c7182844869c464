from pathlib import Path

from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

i, w = snakemake.input, snakemake.wildcards
run_stage(snakemake, figures.write_heldout, view=w.view, heldout=i.heldout,
          predictions=Path(i.predictions) / w.view, svbrdf=i.svbrdf, metrics=i.metrics, out=snakemake.output[0],
          sample=w.sample, settings=figures.FigureSettings.from_params(snakemake.params))
