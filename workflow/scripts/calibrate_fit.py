from facetsynth.stages import calibrate
from facetsynth.stages.runner import run_stage

run_stage(snakemake, calibrate.run_calibrate, targets=snakemake.input.targets, out_file=snakemake.output[0],
          settings=calibrate.CalibrateSettings.from_params(snakemake.params))
