from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

i = snakemake.input
run_stage(snakemake, figures.write_ndf, svbrdf=i.svbrdf, partial=i.partial, partial_grid=i.grid,
          geometry=i.geometry, out=snakemake.output[0], sample=snakemake.wildcards.sample,
          settings=figures.FigureSettings.from_params(snakemake.params))
