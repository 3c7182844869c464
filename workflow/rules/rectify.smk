# rectify: map every HDR frame onto the regular sample-plane grid (paper 002 sec. 4).


rule rectify:
    input:
        frames="results/{sample}/hdr/frames",
        manifest="results/{sample}/hdr/manifest.json",
    output:
        # read by separate alone: deleted once it has them (--notemp keeps them; a forced separate runs rectify
        # again). At 800^2 x 480 they were 1.9 of the 10.2 GB rectify..refine left on disk
        frames=temp(directory("results/{sample}/rectify/frames")),
        geometry="results/{sample}/rectify/geometry.json",
        metrics="results/{sample}/rectify/metrics.json",
    log:
        "results/{sample}/logs/rectify.log",
    benchmark:
        "results/{sample}/benchmarks/rectify.tsv"
    threads: 2  # frames in parallel (facetsynth.io.frames)
    resources:
        mem_mb=2000,
    params:
        resolution=config["rectify"]["resolution"],
        filter=config["rectify"]["filter"],
    script:
        "../scripts/rectify.py"


rule score_rectify:  # a virtual sample's registration and rectified radiance against its truth, beside the fit
    input:
        frames="results/{sample}/hdr/frames",  # warped again, as rectify does, for the frames it scores
        manifest="results/{sample}/hdr/manifest.json",
        geometry="results/{sample}/rectify/geometry.json",
    output:
        scores="results/{sample}/truth/rectify.json",
    log:
        "results/{sample}/logs/score_rectify.log",
    benchmark:
        "results/{sample}/benchmarks/score_rectify.tsv"
    threads: 1
    resources:
        mem_mb=1000,  # demo, 168^2 points x 1360 frames (64 of them scored): 210 MB peak, 6.9 s
    params:
        filter=config["rectify"]["filter"],
    script:
        "../scripts/score_rectify.py"
