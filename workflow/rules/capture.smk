# capture: virtual rig, import of frames captured elsewhere, or the real rig.
# Writes results/{sample}/capture/ (manifest.json + frames); paper 002 sec. 4.
# Input function capture_inputs: common.smk.


# On a cluster (profiles/slurm) capture runs on the submitting host: it drives the rig's hardware.
localrules:
    capture,


rule capture:
    input:
        unpack(capture_inputs),
    output:
        capture=directory("results/{sample}/capture"),
    log:
        "results/{sample}/logs/capture.log",
    benchmark:
        "results/{sample}/benchmarks/capture.tsv"
    threads: 2  # frames in parallel (facetsynth.io.frames)
    resources:
        mem_mb=2000,
    params:
        source=lambda wc: SAMPLE_SHEET[wc.sample]["source"],
        rig=lambda wc: sample_rig(wc.sample),
        seed=config["seed"],
        noise=config["virtual"]["noise"],
        rotation_deg=lambda wc: float(SAMPLE_SHEET[wc.sample].get("rotation_deg", 0.0)),
    script:
        "../scripts/capture.py"
