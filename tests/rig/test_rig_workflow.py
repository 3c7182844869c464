"""Issue 16, done-when: calibrate from rendered targets, capture through the firmware with injected faults,
resume, fit; the result equals an uninterrupted capture's (``make test-scenes``).

Both workflows run the sample sheet's ``rig`` source: the rig description names the firmware's host build on
a pseudo-terminal as the controller, the virtual camera of the demo rig with calibration error (its frames
come from the rig's true geometry, which its calibration only approximates), and the calibration the
workflow's ``calibrate`` rule makes from the targets ``calibration_targets`` renders. The faulted run's
controller is reached through a :class:`FaultProxy`: the USB adapter is unplugged mid-scan while the
controller loses power, for longer than the driver waits (the capture job fails); then one LED's replies are
lost more often than the driver retries (it fails again); the third run finishes. Snakemake's own rerun
resumes from the staging folder each time.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import pytest
import yaml
from test_rig_conformance import host_firmware, spawn  # noqa: F401
from test_rig_faults import FaultProxy
from test_workflow import make_workdir, metrics, snakemake

pytestmark = pytest.mark.scenes

TRUTH_RIG = "rig/descriptions/virtual-demo-calibration-error.yaml"
CALIBRATION = "results/calibration/virtual-demo-calibration-error/calibration.json"
SCAN = {"positions": 12, "travel_steps": 4000, "use_every": 2}   # 12 carriage positions x 20 LEDs = 240 frames
FRAMES = 240
TARGETS = ["results/rigdemo/svbrdf", "results/rigdemo/validate/metrics.json"]


def rig_workdir(repo: Path, dest: Path, port: str) -> Path:
    workdir = make_workdir(repo, dest, "rigdemo\trig\tcfg/rig.yaml\t\n")
    (workdir / "cfg").mkdir()
    (workdir / "cfg/rig.yaml").write_text(yaml.safe_dump({
        "name": "rehearsal", "controller": {"port": port, "timeout_s": 0.5},
        "camera": {"backend": "virtual", "scene": "resources/scenes/demo.yaml", "rig": TRUTH_RIG, "seed": 0},
        "calibration": CALIBRATION, "sample": {"width": 0.1, "height": 0.1}, "scan": SCAN,
        "exposure": {"times": [0.01, 0.1, 1.0], "saturation": 1.0},
        "noise": {"read_sigma": 0.001, "shot_gain": 0.0001}}))
    return workdir


def digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_capture_resumed_after_faults_fits_the_model_of_an_uninterrupted_one(repo, tmp_path, spawn):  # noqa: F811
    clean = rig_workdir(repo, tmp_path / "clean", spawn("firmware").port)
    done = snakemake(clean, *TARGETS)
    assert done.returncode == 0, done.stderr[-3000:]

    backend = spawn("firmware")
    proxy = FaultProxy(backend.port, tmp_path / "ttyRIG")
    try:
        faulted = rig_workdir(repo, tmp_path / "faulted", str(proxy.path))
        staging = faulted / "results/rigdemo/.capture.partial"
        proxy.inject("reply", "OK POS 1091", "garble")                  # absorbed: the driver retries
        proxy.inject("cmd", "LED 24", "disconnect", gap=6.0, reset=backend.power_cycle)   # frame 12
        first = snakemake(faulted, *TARGETS)
        log = faulted / "results/rigdemo/logs/capture.log"
        assert first.returncode != 0 and "lost the rig controller on" in log.read_text()
        assert len((staging / "journal.jsonl").read_text().splitlines()) == 12
        while "unplugged" in str(proxy.path.resolve()) or not proxy.path.resolve().exists():
            time.sleep(0.1)                                              # the adapter comes back
        proxy.inject("reply", "OK LED 30", "drop", count=4)             # beyond 3 retries: frame 15 fails
        second = snakemake(faulted, *TARGETS)
        assert second.returncode != 0 and "LED 30" in log.read_text()
        assert len((staging / "journal.jsonl").read_text().splitlines()) == 15
        third = snakemake(faulted, *TARGETS)
        assert third.returncode == 0, third.stderr[-3000:]
    finally:
        proxy.close()

    capture = json.loads((faulted / "results/rigdemo/capture/manifest.json").read_text())
    assert len(capture["frames"]) == FRAMES
    journal = [json.loads(line) for line in (faulted / "results/rigdemo/capture/journal.jsonl").read_text().splitlines()]
    assert sorted(entry["frame"] for entry in journal) == list(range(FRAMES))   # none lost, none taken twice
    for part in ("capture/frames", "svbrdf"):
        assert digests(faulted / "results/rigdemo" / part) == digests(clean / "results/rigdemo" / part), part
    assert metrics(faulted, "rigdemo", "validate")["views"] == metrics(clean, "rigdemo", "validate")["views"]
