"""The workflow on a real SLURM cluster (issue 14 part 3): ``make test-cluster``, run by .ci/run.

A single-node cluster on localhost (:mod:`slurm_local`: Debian's slurmctld, slurmd and munge) runs two
small samples through ``--workflow-profile profiles/slurm`` (snakemake-executor-plugin-slurm), their
resampling and partial NDFs split into 4 jobs each (``scatter.tiles``); every output must equal an
unsplit local run's bit for bit, the metrics up to their timings. Measured: about 110 s
through SLURM against 16 s locally (job start latency), 452 files compared.
"""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facetsynth.io.fileio import read_exr

from slurm_local import local_slurm, missing

pytestmark = pytest.mark.cluster

SAMPLES = ("sample\tsource\tpath\trig\n"
           "demo\tvirtual\tresources/scenes/demo.yaml\trig/descriptions/tiny.yaml\n"
           "card\tvirtual\tresources/scenes/card.yaml\trig/descriptions/tiny.yaml\n")
TARGETS = ["results/demo/svbrdf", "results/card/svbrdf"]


def workdir(repo: Path, dest: Path) -> Path:
    dest.mkdir(parents=True)
    for part in ("Snakefile", "workflow", "config", "resources", "rig", "profiles"):
        (shutil.copytree if (repo / part).is_dir() else shutil.copy)(repo / part, dest / part)
    shutil.copy(repo / "tests/data/rig-tiny.yaml", dest / "rig/descriptions/tiny.yaml")
    (dest / "config/samples.tsv").write_text(SAMPLES)
    (dest / "small.yaml").write_text("preset: fast\n")
    (dest / "tiles.yaml").write_text("scatter: {tiles: 4}\n")    # 32 x 32 points: 4 tiles of 256, one per job
    return dest


def run(wd: Path, *args: str, configs: tuple[str, ...] = ("small.yaml",)) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snakemake", *TARGETS, *args,
                           "--configfile", "config/config.yaml", *configs],
                          cwd=wd, capture_output=True, text=True)


def without_timings(x):
    """A JSON record with every key that names a duration (``*seconds*``) left out."""
    if isinstance(x, dict):
        return {k: without_timings(v) for k, v in x.items() if "seconds" not in k}
    if isinstance(x, list):
        return [without_timings(v) for v in x]
    return x


def same_file(a: Path, b: Path) -> bool:
    if a.suffix == ".npy":
        x, y = np.load(a), np.load(b)
        return x.shape == y.shape and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)
    if a.suffix == ".exr":            # the pixels: headers may carry the writer's provenance
        (ca, _), (cb, _) = read_exr(a), read_exr(b)
        return ca.keys() == cb.keys() and all(np.array_equal(ca[k], cb[k], equal_nan=True) for k in ca)
    if a.suffix == ".json":
        return without_timings(json.loads(a.read_text())) == without_timings(json.loads(b.read_text()))
    return a.read_bytes() == b.read_bytes()


def test_two_samples_through_slurm_equal_a_local_run(repo, tmp_path):
    assert not missing(), f"run tests/cluster/install.sh first: {missing()} missing"
    local = workdir(repo, tmp_path / "local")
    done = run(local, "--cores", "2")
    assert done.returncode == 0, done.stderr[-3000:]

    cluster = workdir(repo, tmp_path / "slurm")
    with local_slurm(tmp_path / "slurm-state") as pids:
        done = run(cluster, "--workflow-profile", "profiles/slurm", configs=("small.yaml", "tiles.yaml"))
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-3000:] + "\n" + "\n".join(
        p.read_text()[-1500:] for p in (tmp_path / "slurm-state").glob("*.log"))
    for pid in pids:                                    # every daemon the test started is gone
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text()

    # every rule but capture (a localrule: it drives the rig) ran as a SLURM job, once per sample; partial_ndf
    # and resample as 4 part jobs each and their joins (scatter.tiles 4), against one job each locally
    submitted = re.findall(r"has been submitted with SLURM jobid \d+ \(log: \S*/slurm_logs/rule_(\w+)/", log)
    rules = ("hdr", "rectify", "separate", "resample", "partial_ndf", "cluster", "synthesize", "params", "refine")
    assert sorted(submitted) == sorted(list(rules) * 2 + ["partial_ndf_part", "resample_part"] * 8), submitted

    compared, differ = 0, []
    for a in sorted((local / "results").rglob("*")):
        rel = a.relative_to(local / "results")
        if a.is_dir() or {"benchmarks", "logs"} & set(rel.parts):
            continue
        b = cluster / "results" / rel
        compared += 1
        if not b.exists() or not same_file(a, b):
            differ.append(str(rel))
    assert compared > 400 and not differ, differ[:20]
