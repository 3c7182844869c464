from facetsynth.stages import export
from facetsynth.stages.runner import run_script

run_script(snakemake, export)
