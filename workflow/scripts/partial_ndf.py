from facetsynth.stages import partial_ndf
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, partial_ndf.run, geometry=snakemake.input.geometry, slice_path=snakemake.input.slice,
          coverage_path=snakemake.input.coverage, grid_path=snakemake.input.grid, ndf_out=snakemake.output.ndf,
          confidence_out=snakemake.output.confidence, metrics_out=snakemake.output.metrics,
          per_point_view=p.per_point_view, constrained=p.shadowing, grazing_deg=p.grazing_deg,
          tol=p.tolerance, max_iter=p.max_iterations)
