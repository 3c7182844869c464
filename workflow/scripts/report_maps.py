from facetsynth.app import figures
from facetsynth.stages.runner import run_stage

i, o = snakemake.input, snakemake.output
run_stage(snakemake, figures.write_maps, svbrdf=i.svbrdf, geometry=i.geometry, kd_out=o.kd, ks_out=o.ks,
          eta_out=o.eta, sample=snakemake.wildcards.sample)
