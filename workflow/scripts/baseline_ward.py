from facetsynth.stages import baseline
from facetsynth.stages.runner import run_stage

i = snakemake.input
run_stage(snakemake, baseline.run, geometry=i.geometry, kd_path=i.kd, specular=i.specular, valid=i.valid,
          colour=i.colour, model_out=snakemake.output.model, metrics_out=snakemake.output.metrics,
          max_nfev=snakemake.params.max_nfev)
