from facetsynth.stages import refine
from facetsynth.stages.runner import run_stage

i, o = snakemake.input, snakemake.output
run_stage(snakemake, refine.run, model=i.model, geometry=i.geometry, specular=i.specular, valid=i.valid,
          svbrdf_out=o.svbrdf, metrics_out=o.metrics, settings=refine.Settings.from_params(snakemake.params),
          threads=snakemake.threads)
