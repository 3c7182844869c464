from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

run_stage(snakemake, figures.write_stencils, svbrdf=snakemake.input.svbrdf, models=snakemake.input.models,
          out_dir=snakemake.output[0], sample=snakemake.wildcards.sample)
