from facetsynth.stages import params
from facetsynth.stages.runner import run_stage

i, p = snakemake.input, snakemake.params
run_stage(snakemake, params.run, geometry=i.geometry, kd_path=i.kd, specular=i.specular, valid=i.valid,
          colour=i.colour, representatives=i.representatives, neighbours=i.neighbours, weights=i.weights, rotation=i.rotation,
          ndf=i.ndf, fresnel_cosine=i.fresnel_cosine,
          synthesis_confidence=i.synthesis_confidence, grid_path=i.grid, svbrdf_out=snakemake.output.svbrdf,
          metrics_out=snakemake.output.metrics,
          grazing_deg=p.grazing_deg, eta_min=p.eta_min, eta_max=p.eta_max,
          eta_default=p.eta_default, min_samples=p.min_samples, max_std=p.max_std,
          min_ndf_fraction=p.min_ndf_fraction, max_split_difference=p.max_split_difference,
          material_tolerance=p.material_tolerance, max_eta_interval=p.max_eta_interval,
          threads=snakemake.threads)
