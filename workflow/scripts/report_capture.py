from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

run_stage(snakemake, figures.write_capture, manifest=snakemake.input.manifest, out=snakemake.output[0],
          sample=snakemake.wildcards.sample, settings=figures.FigureSettings.from_params(snakemake.params))
