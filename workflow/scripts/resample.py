from facetsynth.stages import resample
from facetsynth.stages.runner import run_stage

run_stage(snakemake, resample.run, geometry=snakemake.input.geometry, specular=snakemake.input.specular,
          valid=snakemake.input.valid, slice_out=snakemake.output.slice, coverage_out=snakemake.output.coverage,
          colour_out=snakemake.output.colour, grid_out=snakemake.output.grid,
          n_theta=snakemake.params.n_theta, n_phi=snakemake.params.n_phi)
