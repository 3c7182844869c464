"""Crash hygiene (issue 15, part 6) and negative exposure values (issue 15).

A job killed with SIGKILL cannot clean up. These tests kill the ``hdr`` and ``partial_ndf`` stages in a
subprocess at chosen points (mid-write of a file: its temporary written, not renamed; and between
files), rerun the stage in-process on the same paths, and check that the outputs and metrics are those
of an uninterrupted run byte for byte, and that no temporary file is left anywhere.

The capture: the demo scene on the tiny test rig (30 frames of 3 exposures, 120 x 80, sensor noise on),
with negative values written into two exposures (:data:`NEGATIVES`); rectified to 16 x 16 points for
``partial_ndf``, which runs in tiles of 64 points (4 tiles) on an 8 x 32 direction grid.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import hdr_outputs, rectify_into

from facetsynth.io.fileio import read_exr, write_exr

# (frame, exposure, pixels made negative, channels): 10 pixels x 3 channels + 5 pixels x 1 channel.
NEGATIVES = [(1, 2, 10, 3), (4, 0, 5, 1)]
NEGATIVE_COUNT = 35
TILE_POINTS = 64

# Runs a stage, killing the process with SIGKILL on the k-th call of a function. With "truncate", the
# file that call is given (os.replace's source: a finished temporary) is first cut to half its size, as a
# kill mid-write would leave it.
KILL_ON_CALL = """
import importlib, json, os, signal, sys
from pathlib import Path
spec = json.loads(sys.argv[1])
owner = importlib.import_module(spec["owner"])
original, calls = getattr(owner, spec["name"]), []

def kill_on_call(*args, **kwargs):
    calls.append(None)
    if len(calls) == spec["call"]:
        if spec["truncate"]:
            Path(args[0]).write_bytes(Path(args[0]).read_bytes()[: Path(args[0]).stat().st_size // 2])
        os.kill(os.getpid(), signal.SIGKILL)
    return original(*args, **kwargs)

setattr(owner, spec["name"], kill_on_call)
stage = importlib.import_module(spec["stage"])
vars(stage).update(spec["globals"])
kwargs = {k: getattr(stage, v["class"])(**{f: Path(p) for f, p in v["files"].items()}) if isinstance(v, dict) else v
          for k, v in spec["kwargs"].items()}     # a stage's Inputs, Outputs: rebuilt from their paths
getattr(stage, spec["function"])(**kwargs)
"""


def run_killed(stage: str, function: str, kwargs: dict, root: Path, owner: str, name: str, call: int,
               left: list[str], truncate: bool = False, stage_globals: dict | None = None) -> None:
    """Run ``stage.function(**kwargs)`` in a subprocess killed on the ``call``-th call of ``owner.name``;
    check that the kill left the files ``left`` (globs under ``root``): it happened where intended."""
    spec = {"stage": stage, "function": function, "kwargs": {k: rule_files(v) for k, v in kwargs.items()},
            "owner": owner, "name": name, "call": call, "truncate": truncate, "globals": stage_globals or {}}
    done = subprocess.run([sys.executable, "-c", KILL_ON_CALL, json.dumps(spec)], capture_output=True, text=True)
    assert done.returncode == -signal.SIGKILL, done.stderr[-2000:]
    for pattern in left:
        assert list(root.glob(pattern)), f"the kill left no {pattern}"


def rule_files(value) -> str | dict:
    """A keyword argument of a stage as JSON: a path as text, a stage's ``Inputs`` or ``Outputs`` as its class
    name and its paths (KILL_ON_CALL rebuilds it)."""
    if dataclasses.is_dataclass(value):
        return {"class": type(value).__name__,
                "files": {f.name: str(getattr(value, f.name)) for f in dataclasses.fields(value)
                          if getattr(value, f.name) is not None}}
    return str(value)


def temporaries(root: Path) -> list[Path]:
    return sorted(root.rglob("*.tmp*"))


def assert_same_files(got: Path, expected: Path) -> None:
    """The same files (hidden ones too) under both folders, byte for byte."""
    names = sorted(p.relative_to(expected) for p in expected.rglob("*") if p.is_file())
    assert sorted(p.relative_to(got) for p in got.rglob("*") if p.is_file()) == names
    for name in names:
        assert (got / name).read_bytes() == (expected / name).read_bytes(), name


def pndf_paths(root: Path) -> dict:
    return {"ndf_out": root / "partial_ndf/ndf", "metrics_out": root / "partial_ndf/metrics.json"}


@pytest.fixture(scope="module")
def work(tmp_path_factory, repo):
    """The capture with negative values, and an uninterrupted run of every stage up to ``partial_ndf``
    in ``ref``: its hdr and partial_ndf outputs are the references, its resample outputs the inputs of
    the partial_ndf runs."""
    from facetsynth.stages import hdr, partial_ndf, resample, separate
    from facetsynth.truth.virtual_rig import VirtualRig, capture
    root = tmp_path_factory.mktemp("crash")
    capture(repo / "resources/scenes/demo.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"),
            root / "capture", seed=2, noise=True)
    for q, e, pixels, channels in NEGATIVES:
        file = root / f"capture/frames/{q:04d}_e{e}.exr"
        image, header = read_exr(file)
        rgb = image["RGB"]
        rgb[0, :pixels, :channels] = -0.003          # read noise below a black level
        write_exr(file, {"RGB": rgb}, {"exposure_time": header["exposure_time"]}, precision="float16")
    ref = root / "ref"
    hdr.run(hdr.Inputs(capture=root / "capture"), hdr_outputs(ref / "hdr"))
    rectify_into(ref / "hdr/manifest.json", ref / "rectify", 16)
    inputs = {"geometry": ref / "rectify/geometry.json", "slice_path": ref / "resample/slice",
              "grid_path": ref / "resample/grid.json"}
    separate.run(separate.Inputs(geometry=inputs["geometry"]),
                 separate.Outputs(kd=ref / "separate/kd.exr", specular=ref / "separate/specular.npy",
                                  valid=ref / "separate/valid.npy", metrics=ref / "separate/metrics.json"),
                 separate.Settings(heldout_every=0))
    resample.run_whole(geometry=inputs["geometry"], specular=ref / "separate/specular.npy",
                       valid=ref / "separate/valid.npy", slice_out=inputs["slice_path"],
                       colour_out=ref / "resample/colour.npy", grid_out=inputs["grid_path"],
                       metrics_out=ref / "resample/metrics.json", settings=resample.Settings(n_theta_range=(8, 8)))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(partial_ndf, "TILE_POINTS", TILE_POINTS)
        partial_ndf.run_whole(**inputs, **pndf_paths(ref))
    return {"root": root, "ref": ref, "pndf_inputs": inputs}


def test_hdr_counts_negative_exposure_values_and_warns(work, tmp_path, caplog):
    """Negative values (read noise around a black level) are still clipped, but no longer silently: the
    count goes to the metrics and a WARNING names it and the first file."""
    from facetsynth.stages import hdr
    with caplog.at_level(logging.WARNING, logger="facetsynth.stages.hdr"):
        hdr.run(hdr.Inputs(capture=work["root"] / "capture"), hdr_outputs(tmp_path / "hdr"))
    metrics = json.loads((tmp_path / "hdr/metrics.json").read_text())
    assert metrics["negative_values"] == NEGATIVE_COUNT
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert f"{NEGATIVE_COUNT} exposure values are negative" in warnings[0] and "0001_e2.exr" in warnings[0]
    for q in (1, 4):
        assert read_exr(tmp_path / f"hdr/frames/{q:04d}.exr")[0]["RGB"].min() >= 0     # clipped


def test_hdr_without_negative_values_reports_zero_and_does_not_warn(tmp_path, repo, caplog):
    from facetsynth.stages import hdr
    from facetsynth.truth.virtual_rig import VirtualRig, capture
    capture(repo / "resources/scenes/demo.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"),
            tmp_path / "capture", seed=2, noise=True)
    with caplog.at_level(logging.WARNING, logger="facetsynth.stages.hdr"):
        hdr.run(hdr.Inputs(capture=tmp_path / "capture"), hdr_outputs(tmp_path / "hdr"))
    assert json.loads((tmp_path / "hdr/metrics.json").read_text())["negative_values"] == 0
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]


# hdr, with threads=1, calls os.replace once per frame (0000 .. 0029), then to publish the frames folder,
# then for the manifest and the metrics.
HDR_KILLS = {
    # frame 0004's temporary in the staging folder, half written; frames 0000-0003 done (the resumed run
    # reads them back, frame 0001's negative values too).
    "mid-write of frame 0004": dict(owner="os", name="replace", call=5, truncate=True,
                                    left=["hdr/.frames.partial/.0004.exr.*.tmp.exr", "hdr/.frames.partial/0003.exr"]),
    # between frames: 0000-0007 done, nothing being written.
    "between frames 0007 and 0008": dict(owner="facetsynth.stages.hdr", name="write_exr", call=9,
                                         left=["hdr/.frames.partial/0007.exr"]),
    # the frames folder published, the manifest's temporary half written beside it.
    "mid-write of the manifest": dict(owner="os", name="replace", call=32, truncate=True,
                                      left=["hdr/frames/0029.exr", "hdr/.manifest.json.*.tmp"]),
}


@pytest.mark.parametrize("kill", HDR_KILLS, ids=list(HDR_KILLS))
def test_hdr_rerun_after_sigkill_is_bitwise_an_uninterrupted_run(work, tmp_path, kill):
    from facetsynth.stages import hdr
    root = work["root"] / tmp_path.name       # beside ref: the manifest's relative paths to the capture match
    kwargs = {"inputs": hdr.Inputs(capture=work["root"] / "capture"), "outputs": hdr_outputs(root / "hdr")}
    run_killed("facetsynth.stages.hdr", "run", kwargs, root, **HDR_KILLS[kill])
    hdr.run(**kwargs)
    assert temporaries(root) == []
    assert_same_files(root / "hdr", work["ref"] / "hdr")


# partial_ndf writes its support table (facetsynth.io.tables) tile by tile into a staging folder, renames the
# mask, then writes the offsets and table.json, publishes the folder, then writes the metrics.
PNDF_KILLS = {
    # in the third tile: the staged D and W values and the mask's temporary (two tiles) written.
    "mid-write of the table": dict(owner="facetsynth.fit.partial_ndf", name="fit", call=3,
                                   left=["partial_ndf/.ndf.partial/ndf.npy", "partial_ndf/.ndf.partial/.mask.npy.*.tmp.npy"]),
    # every file of the table staged (mask, offsets, table.json renamed into place), the folder not published.
    "before the table is published": dict(owner="os", name="replace", call=4,
                                          left=["partial_ndf/.ndf.partial/table.json"]),
}


@pytest.mark.parametrize("kill", PNDF_KILLS, ids=list(PNDF_KILLS))
def test_partial_ndf_rerun_after_sigkill_is_bitwise_an_uninterrupted_run(work, tmp_path, kill, monkeypatch):
    from facetsynth.stages import partial_ndf
    kwargs = {**work["pndf_inputs"], **pndf_paths(tmp_path)}
    run_killed("facetsynth.stages.partial_ndf", "run_whole", kwargs, tmp_path, **PNDF_KILLS[kill],
               stage_globals={"TILE_POINTS": TILE_POINTS})
    monkeypatch.setattr(partial_ndf, "TILE_POINTS", TILE_POINTS)
    partial_ndf.run_whole(**kwargs)
    assert temporaries(tmp_path) == []
    assert_same_files(tmp_path / "partial_ndf", work["ref"] / "partial_ndf")
