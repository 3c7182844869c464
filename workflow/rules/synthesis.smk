# Clustering and example-based NDF synthesis (paper 002 sec. 5.2-5.3): k-means representatives
# and eq. 18 interpolation weights; completion of the representatives' NDFs from rotated,
# overlapping partial NDFs (eqs. 13-17) with the ANN search pruning of sec. 5.3.


rule cluster:
    input:
        geometry="results/{sample}/separate/geometry.json",
        ndf="results/{sample}/partial_ndf/ndf",
        grid="results/{sample}/resample/grid.json",
        specular="results/{sample}/separate/specular.npy",
        valid="results/{sample}/separate/valid.npy",
        kd="results/{sample}/separate/kd.exr",
    output:
        labels="results/{sample}/cluster/labels.npy",
        representatives="results/{sample}/cluster/representatives.npy",
        neighbours="results/{sample}/cluster/neighbours.npy",
        weights="results/{sample}/cluster/weights.npy",
        rep_ndf="results/{sample}/cluster/representative_ndf.npy",
        rep_confidence="results/{sample}/cluster/representative_confidence.npy",
        rotation="results/{sample}/cluster/rotation.npy",
        metrics="results/{sample}/cluster/metrics.json",
    log:
        "results/{sample}/logs/cluster.log",
    benchmark:
        "results/{sample}/benchmarks/cluster.tsv"
    threads: 2  # coarse tables read on threads; k-means and eq. 15 in BLAS
    resources:
        mem_mb=5000,  # make bench-scale: 4.9 GB peak at 800^2
    params:
        **config["cluster"],
        seed=config["seed"],
        shadowing=config["partial_ndf"]["shadowing"],  # eqs. 11 and 5 for the pooled representative partial NDFs
        grazing_deg=config["partial_ndf"]["grazing_deg"],
        tolerance=config["partial_ndf"]["tolerance"],
        max_iterations=config["partial_ndf"]["max_iterations"],
    script:
        "../scripts/cluster.py"


rule synthesize:
    input:
        unpack(rotation_inputs),
        geometry="results/{sample}/separate/geometry.json",
        kd="results/{sample}/separate/kd.exr",
        ndf="results/{sample}/partial_ndf/ndf",
        grid="results/{sample}/resample/grid.json",
        representatives="results/{sample}/cluster/representatives.npy",
        rep_ndf="results/{sample}/cluster/representative_ndf.npy",
        rep_confidence="results/{sample}/cluster/representative_confidence.npy",
        rotation="results/{sample}/cluster/rotation.npy",
        neighbours="results/{sample}/cluster/neighbours.npy",
        weights="results/{sample}/cluster/weights.npy",
    output:
        ndf="results/{sample}/synthesize/ndf.npy",
        confidence="results/{sample}/synthesize/confidence.npy",
        fresnel_cosine="results/{sample}/synthesize/fresnel_cosine.npy",
        grid="results/{sample}/synthesize/grid.json",
        metrics="results/{sample}/synthesize/metrics.json",
    log:
        "results/{sample}/logs/synthesize.log",
    benchmark:
        "results/{sample}/benchmarks/synthesize.tsv"
    threads: 2  # eq. 15 scores in BLAS
    resources:
        mem_mb=4000,
    params:
        **config["synthesize"],
        seed=config["seed"],
        material_tolerance=config["params"]["material_tolerance"],
    script:
        "../scripts/synthesize.py"
