from facetsynth.stages import stencil_fit
from facetsynth.stages.runner import run_stage

run_stage(snakemake, stencil_fit.run, svbrdf_dir=snakemake.input.svbrdf, labels_path=snakemake.input.labels,
          geometry=snakemake.input.geometry, out_dir=snakemake.output.models, metrics_out=snakemake.output.metrics)
