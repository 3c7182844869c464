from facetsynth.stages import validate
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, validate.heldout_capture, scene=snakemake.input.scene, rig=snakemake.input.rig,
          out_dir=snakemake.output[0], theta_deg=p.theta_deg, phi_deg=p.phi_deg, led_every=p.led_every,
          position_every=p.position_every, seed=p.seed)
