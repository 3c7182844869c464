from facetsynth.stages import rectify
from facetsynth.stages.runner import run_stage

run_stage(snakemake, rectify.run, hdr_manifest=snakemake.input.manifest, frames_dir=snakemake.output.frames,
          geometry_out=snakemake.output.geometry, metrics_out=snakemake.output.metrics,
          resolution=snakemake.params.resolution, filtername=snakemake.params.filter,
          threads=snakemake.threads)
