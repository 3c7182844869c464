# Remaining parameters (paper 002 sec. 5.4): ks, normalised NDF, shadowing (eq. 5), eta by
# Levenberg-Marquardt on eqs. 19-20 -> results/{sample}/params/svbrdf/; then refine makes that model reproduce
# its own samples (issue 29: one NDF per material, its eta and stretch, each point's NDF turn, kd and ks per
# point; facetsynth.stages.refine) -> the fitted SVBRDF folder results/{sample}/svbrdf/.
# Inputs from cluster and synthesize (issue 4); reachable as a target only.


rule params:
    input:
        geometry="results/{sample}/separate/geometry.json",
        kd="results/{sample}/separate/kd.exr",
        specular="results/{sample}/separate/specular.npy",
        valid="results/{sample}/separate/valid.npy",
        colour="results/{sample}/resample/specular_colour.npy",
        representatives="results/{sample}/cluster/representatives.npy",
        neighbours="results/{sample}/cluster/neighbours.npy",
        weights="results/{sample}/cluster/weights.npy",
        rotation="results/{sample}/cluster/rotation.npy",
        ndf="results/{sample}/synthesize/ndf.npy",
        fresnel_cosine="results/{sample}/synthesize/fresnel_cosine.npy",
        synthesis_confidence="results/{sample}/synthesize/confidence.npy",
        grid="results/{sample}/synthesize/grid.json",
    output:
        svbrdf=directory("results/{sample}/params/svbrdf"),  # the pipeline's model: refine's start
        metrics="results/{sample}/params/metrics.json",
    log:
        "results/{sample}/logs/params.log",
    benchmark:
        "results/{sample}/benchmarks/params.tsv"
    threads: 2  # tiles of points in parallel
    resources:
        mem_mb=3500,  # make bench-scale: 2.3 GB peak at 800^2 (3.2 GB in an earlier run)
    params:
        **config["params"],
        grazing_deg=config["partial_ndf"]["grazing_deg"],
    script:
        "../scripts/params.py"


rule refine:
    input:
        model="results/{sample}/params/svbrdf",
        geometry="results/{sample}/separate/geometry.json",
        specular="results/{sample}/separate/specular.npy",
        valid="results/{sample}/separate/valid.npy",
    output:
        svbrdf=directory("results/{sample}/svbrdf"),
        metrics="results/{sample}/refine/metrics.json",
    log:
        "results/{sample}/logs/refine.log",
    benchmark:
        "results/{sample}/benchmarks/refine.tsv"
    threads: 2  # tiles of points in parallel
    resources:
        mem_mb=1500,  # demo, 168^2 points x 1360 lights: 0.8 GB peak (tiles of points: does not grow with P)
    params:
        **config["refine"],
        material_tolerance=config["params"]["material_tolerance"],  # materials as params groups them
    script:
        "../scripts/refine.py"


rule score_refine:  # a virtual sample's fitted SVBRDF against its truth, beside the fit
    input:
        geometry="results/{sample}/separate/geometry.json",
        pipeline="results/{sample}/params/svbrdf",
        svbrdf="results/{sample}/svbrdf",
    output:
        scores="results/{sample}/truth/refine.json",
    log:
        "results/{sample}/logs/score_refine.log",
    benchmark:
        "results/{sample}/benchmarks/score_refine.tsv"
    threads: 1
    resources:
        mem_mb=1000,  # demo, 168^2 points (two models scored): 0.3 GB peak, 7 s
    script:
        "../scripts/score_refine.py"
