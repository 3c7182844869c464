# capture: virtual rig, import of frames captured elsewhere, or the real rig.
# Writes results/{sample}/capture/ (manifest.json + frames); paper 002 sec. 4.


def capture_inputs(wildcards):
    row = SAMPLE_SHEET[wildcards.sample]
    inputs = {"path": row["path"], "sources": source_files(row)}
    if row["source"] == "virtual":
        inputs["rig"] = sample_rig(wildcards.sample)
    return inputs


# On a cluster (profiles/slurm) capture runs on the submitting host: it drives the rig's hardware.
localrules:
    capture,


rule capture:
    input:
        unpack(capture_inputs),
    output:
        capture=directory("results/{sample}/capture"),
    params:
        source=lambda wc: SAMPLE_SHEET[wc.sample]["source"],
        rig=lambda wc: sample_rig(wc.sample),
        seed=config["seed"],
        noise=config["virtual"]["noise"],
        rotation_deg=lambda wc: float(SAMPLE_SHEET[wc.sample].get("rotation_deg", 0.0)),
    log:
        "results/{sample}/logs/capture.log",
    benchmark:
        "results/{sample}/benchmarks/capture.tsv"
    threads: 2   # frames in parallel (facetsynth.frames)
    resources:
        mem_mb=2000,
    script:
        "../scripts/capture.py"
