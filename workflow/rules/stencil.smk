# Adaptive highlight stencils (paper 000): one compact, editable model per material cluster
# of the fitted SVBRDF, fitted on the UTIA grid; parameters (JSON), BRDF Explorer shaders, scores.


rule stencil_fit:
    input:
        svbrdf="results/{sample}/svbrdf",
        labels="results/{sample}/cluster/labels.npy",
        geometry="results/{sample}/separate/geometry.json",
    output:
        models=directory("results/{sample}/stencil_fit/models"),
        metrics="results/{sample}/stencil_fit/metrics.json",
    log:
        "results/{sample}/logs/stencil_fit.log",
    benchmark:
        "results/{sample}/benchmarks/stencil_fit.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../scripts/stencil_fit.py"
