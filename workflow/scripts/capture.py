from facetsynth.stages import capture
from facetsynth.stages.runner import run_stage

run_stage(snakemake, capture.run, source=snakemake.params.source, path=snakemake.input.path,
          out_dir=snakemake.output[0], rig=snakemake.params.rig, seed=snakemake.params.seed,
          noise=snakemake.params.noise, rotation_deg=snakemake.params.rotation_deg,
          threads=snakemake.threads)
