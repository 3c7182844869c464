from facetsynth.stages import resample
from facetsynth.stages.runner import run_script

run_script(snakemake, resample)
