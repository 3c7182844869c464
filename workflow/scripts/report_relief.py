from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

i = snakemake.input
run_stage(snakemake, figures.write_relief, geometry=i.geometry, separate_metrics=i.metrics,
          out=snakemake.output[0], sample=snakemake.wildcards.sample)
