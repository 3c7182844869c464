# Held-out views (paper 002 sec. 6, Figs. 9-10): the virtual rig renders captures from views not
# used for fitting; the fitted SVBRDF and the per-point Ward baseline predict them (the code path
# of `facetsynth predict`); results/{sample}/validate/metrics.json scores both.
# Input function virtual_scene: common.smk.

HELDOUT_VIEWS = {v["name"]: v for v in config["validate"]["views"]}


wildcard_constraints:
    view="|".join(HELDOUT_VIEWS),


rule heldout_capture:
    input:
        unpack(virtual_scene),
    output:
        capture=directory("results/{sample}/validate/heldout/{view}"),
    log:
        "results/{sample}/logs/heldout_capture_{view}.log",
    benchmark:
        "results/{sample}/benchmarks/heldout_capture_{view}.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        theta_deg=lambda wc: HELDOUT_VIEWS[wc.view]["theta_deg"],
        phi_deg=lambda wc: HELDOUT_VIEWS[wc.view]["phi_deg"],
        led_every=config["validate"]["led_every"],
        position_every=config["validate"]["position_every"],
        seed=config["seed"],
    script:
        "../scripts/heldout_capture.py"


BASELINE_INPUTS = {
    "geometry": "results/{sample}/separate/geometry.json",
    "kd": "results/{sample}/separate/kd.exr",
    "specular": "results/{sample}/separate/specular.npy",
    "valid": "results/{sample}/separate/valid.npy",
    "colour": "results/{sample}/resample/specular_colour.npy",
}


rule baseline_ward:  # all points; with scatter.tiles > 1 the join of baseline_ward_part's fits (bitwise the same)
    input:
        **BASELINE_INPUTS,
        **scatter_parts(records="results/{{sample}}/baseline/parts/{scatteritem}.npz"),
    output:
        model=directory("results/{sample}/baseline/ward"),
        metrics="results/{sample}/baseline/metrics.json",
    log:
        "results/{sample}/logs/baseline_ward.log",
    benchmark:
        "results/{sample}/benchmarks/baseline_ward.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        max_nfev=config["baseline"]["max_nfev"],
    script:
        "../scripts/baseline_ward.py"


use rule baseline_ward as baseline_ward_part with:  # one part's per-point fits; unused at scatter.tiles 1
    input:
        **BASELINE_INPUTS,
    output:
        record=temp("results/{sample}/baseline/parts/{scatteritem}.npz"),
    log:
        "results/{sample}/logs/baseline_ward/{scatteritem}.log",
    benchmark:
        "results/{sample}/benchmarks/baseline_ward/{scatteritem}.tsv"


rule validate:
    input:
        svbrdf="results/{sample}/svbrdf",
        params_metrics="results/{sample}/params/metrics.json",
        ward="results/{sample}/baseline/ward",
        heldout=expand("results/{{sample}}/validate/heldout/{view}", view=list(HELDOUT_VIEWS)),
        # the held-out truth's rig: its supersampling renders the truth's diffuse term for the specular score
        rig=lambda wc: virtual_scene(wc)["rig"],
    output:
        metrics="results/{sample}/validate/metrics.json",
        images=directory("results/{sample}/validate/images"),
        predictions=directory("results/{sample}/validate/predictions"),
    log:
        "results/{sample}/logs/validate.log",
    benchmark:
        "results/{sample}/benchmarks/validate.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    params:
        views=list(HELDOUT_VIEWS),
        # the fitting stages of each method (Snakemake benchmark: files, read when this job runs)
        fit_benchmarks=lambda wc: [
            f"results/{wc.sample}/benchmarks/{s}.tsv"
            for s in ("partial_ndf", "cluster", "synthesize", "params", "refine")
        ],
        ward_benchmark=lambda wc: f"results/{wc.sample}/benchmarks/baseline_ward.tsv",
        images_per_view=config["validate"]["images_per_view"],
    script:
        "../scripts/validate.py"


rule selfcheck:
    input:
        svbrdf="results/{sample}/svbrdf",
        manifest="results/{sample}/hdr/manifest.json",
        frames="results/{sample}/hdr/frames",
        geometry="results/{sample}/separate/geometry.json",  # the lights' intensities as the fit saw them
        capture="results/{sample}/capture",  # 8-bit exposures with a declared transfer: HSH 3 on their codes
    output:
        metrics="results/{sample}/selfcheck/metrics.json",
        images=report(
            directory("results/{sample}/selfcheck/images"),
            patterns=["{subset}_worst.png"],
            caption="../report/selfcheck.rst",
            category="{sample}",
            subcategory="5 held-out views",
            labels={"figure": "self-check", "subset": "{subset}"},
        ),
    log:
        "results/{sample}/logs/selfcheck.log",
    benchmark:
        "results/{sample}/benchmarks/selfcheck.tsv"
    threads: 1
    resources:
        mem_mb=1000,
    params:
        **config["selfcheck"],
    script:
        "../scripts/selfcheck.py"
