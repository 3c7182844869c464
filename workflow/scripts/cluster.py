from facetsynth.stages import cluster
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, cluster.run, geometry=snakemake.input.geometry, ndf=snakemake.input.ndf,
          grid_path=snakemake.input.grid,
          specular=snakemake.input.specular, valid=snakemake.input.valid, kd=snakemake.input.kd,
          labels_out=snakemake.output.labels, representatives_out=snakemake.output.representatives,
          neighbours_out=snakemake.output.neighbours, weights_out=snakemake.output.weights,
          rep_ndf_out=snakemake.output.rep_ndf, rep_confidence_out=snakemake.output.rep_confidence,
          rotation_out=snakemake.output.rotation,
          metrics_out=snakemake.output.metrics, representatives=p.representatives,
          distortion=p.distortion, spread=p.spread, min_representatives=p.min_representatives,
          max_representatives=p.max_representatives, scan_points=p.scan_points,
          neighbours=p.neighbours, radius=p.radius_lambda, ridge=p.ridge, n_init=p.n_init, seed=p.seed,
          constrained=p.partial_ndf["shadowing"], grazing_deg=p.partial_ndf["grazing_deg"], threads=snakemake.threads,
          tol=p.partial_ndf["tolerance"], max_iter=p.partial_ndf["max_iterations"])
