from facetsynth.stages import separate
from facetsynth.stages.runner import run_stage

run_stage(snakemake, separate.run, geometry=snakemake.input.geometry, geometry_out=snakemake.output.geometry,
          normals_out=snakemake.output.normals, kd_out=snakemake.output.kd,
          specular_out=snakemake.output.specular, valid_out=snakemake.output.valid,
          metrics_out=snakemake.output.metrics, settings=separate.Settings.from_params(snakemake.params),
          threads=snakemake.threads)
