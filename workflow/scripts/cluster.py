from facetsynth.stages import cluster
from facetsynth.stages.runner import run_stage

p = snakemake.params
run_stage(snakemake, cluster.run, geometry=snakemake.input.geometry, ndf=snakemake.input.ndf,
          confidence=snakemake.input.confidence, grid_path=snakemake.input.grid,
          labels_out=snakemake.output.labels, representatives_out=snakemake.output.representatives,
          neighbours_out=snakemake.output.neighbours, weights_out=snakemake.output.weights,
          metrics_out=snakemake.output.metrics, representatives=p.representatives,
          distortion=p.distortion, min_representatives=p.min_representatives,
          max_representatives=p.max_representatives, scan_points=p.scan_points,
          neighbours=p.neighbours, radius=p.radius_lambda, ridge=p.ridge, n_init=p.n_init, seed=p.seed)
