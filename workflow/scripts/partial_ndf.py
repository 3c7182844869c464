from facetsynth.stages import partial_ndf
from facetsynth.stages.runner import run_script

run_script(snakemake, partial_ndf)
