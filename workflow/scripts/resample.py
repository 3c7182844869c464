from facetsynth.stages import resample
from facetsynth.stages.runner import run_stage

run_stage(snakemake, resample.run, geometry=snakemake.input.geometry, specular=snakemake.input.specular,
          valid=snakemake.input.valid, slice_out=snakemake.output.slice, coverage_out=snakemake.output.coverage,
          colour_out=snakemake.output.colour, grid_out=snakemake.output.grid, metrics_out=snakemake.output.metrics,
          cells_per_lobe=snakemake.params.cells_per_lobe, n_theta_range=tuple(snakemake.params.n_theta_range),
          grazing_deg=snakemake.params.grazing_deg)
