# Configuration and sample-sheet validation: an invalid config or sheet fails
# here, before any job runs, with a message naming the key or the row.

import csv
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

validate(config, "../schemas/config.schema.yaml")


def read_samples(path):
    """The sample sheet as {sample: row}, each row validated against the schema."""
    if not Path(path).is_file():
        raise WorkflowError(f"{path}: sample sheet not found (config key 'samples')")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    samples = {}
    for line, row in enumerate(rows, start=2):
        row = {k: v for k, v in row.items() if k is not None and v not in (None, "")}
        try:
            validate(row, "../schemas/samples.schema.yaml")
        except WorkflowError as e:
            raise WorkflowError(f"{path} line {line}: {e}")
        if row["sample"] in samples:
            raise WorkflowError(f"{path} line {line}: sample '{row['sample']}' appears twice")
        if not Path(row["path"]).exists():
            raise WorkflowError(f"{path} line {line}: path '{row['path']}' of sample '{row['sample']}' does not exist")
        samples[row["sample"]] = row
    if not samples:
        raise WorkflowError(f"{path}: the sample sheet lists no samples")
    return samples


SAMPLE_SHEET = read_samples(config["samples"])
SAMPLES = list(SAMPLE_SHEET)


wildcard_constraints:
    sample="|".join(SAMPLES),


def sample_rig(sample):
    """Rig description of a virtual sample."""
    return SAMPLE_SHEET[sample].get("rig", config["virtual"]["rig"])
