from facetsynth.stages import calibrate
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, calibrate.run_targets, rig=p.rig, out_dir=snakemake.output[0], seed=p.seed, noise=p.noise,
          settings=calibrate.TargetSettings.from_params(p))
