from facetsynth.stages import hdr
from facetsynth.stages.runner import run_stage

run_stage(snakemake, hdr.run, capture_dir=snakemake.input[0], frames_dir=snakemake.output.frames,
          manifest_out=snakemake.output.manifest, metrics_out=snakemake.output.metrics,
          floor_sigmas=snakemake.params.floor_sigmas, saturation_margin=snakemake.params.saturation_margin,
          threads=snakemake.threads)
