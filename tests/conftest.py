"""Shared fixtures: small ground-truth captures made by the virtual rig."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# The seven measured RGL BRDFs (CC0), vendored from shared/data/rgl: real reflectance nobody here made.
RGL_DIR = REPO / "resources" / "brdfs" / "rgl"
RGL_FILES = sorted(RGL_DIR.glob("*.bsdf"))
assert len(RGL_FILES) == 7, f"{RGL_DIR}: expected the seven RGL .bsdf files"


def hdr_outputs(folder: Path):
    """hdr's outputs in ``folder`` as the workflow lays them out: frames/, manifest.json, metrics.json."""
    from facetsynth.stages import hdr
    return hdr.Outputs(frames=folder / "frames", manifest=folder / "manifest.json", metrics=folder / "metrics.json")


def tiny_truth_model(root: Path, repo: Path, cells: int, rings: int):
    """test_predict's SCENE captured noise-free by the test rig (30 frames) into ``root``/capture, and the SVBRDF
    of its truth on a ``cells`` x ``cells`` plane grid and a ``rings`` x 4 ``rings`` direction grid in
    ``root``/svbrdf; returns the model."""
    from facetsynth.grid import DirectionGrid
    from facetsynth.plane import PlaneGrid
    from facetsynth.scene import Scene
    from facetsynth.svbrdf import tabulate_truth
    from facetsynth.virtual_rig import VirtualRig, capture
    from test_predict import SCENE
    (root / "scene.yaml").write_text(SCENE)
    capture(root / "scene.yaml", VirtualRig.load(repo / "tests/data/rig-tiny.yaml"), root / "capture", seed=1,
            noise=False)
    plane = PlaneGrid(0.1, 0.1, cells, cells)
    maps = Scene.load(root / "scene.yaml").parameters(plane.points3d().reshape(-1, 3)[:, :2])
    model = tabulate_truth(maps, DirectionGrid(rings, 4 * rings), plane)
    model.save(root / "svbrdf")
    return model


def rectify_into(manifest: Path, folder: Path, resolution: int | str) -> dict:
    """rectify of the hdr ``manifest`` into ``folder`` (frames/, geometry.json, metrics.json) at ``resolution``;
    returns its metrics."""
    import json

    from facetsynth.stages import rectify
    rectify.run(rectify.Inputs(manifest=manifest),
                rectify.Outputs(frames=folder / "frames", geometry=folder / "geometry.json",
                                metrics=folder / "metrics.json"), rectify.Settings(resolution=resolution))
    return json.loads((folder / "metrics.json").read_text())


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


def pytest_collection_modifyitems(items):
    """A test that uses ``demo_run`` is a whole-workflow test: it runs with the scene tests (make test-scenes)."""
    for item in items:
        if "demo_run" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.scenes)


@pytest.fixture(scope="session")
def demo_run(repo, tmp_path_factory):
    """The default demo sample, noise-free, through the whole default workflow (validate, stencil_fit, the
    report's figures, the exports): one run (about 4 min) shared by the workflow, report and export tests, which
    are therefore scene tests (``pytest_collection_modifyitems``)."""
    from test_workflow import NOISE_FREE, make_workdir, snakemake
    workdir = make_workdir(repo, tmp_path_factory.mktemp("wf"), "demo\tvirtual\tresources/scenes/demo.yaml\t\n",
                           resolution=None)
    (workdir / "noise-free.yaml").write_text("virtual:\n  noise: false\n")
    done = snakemake(workdir, *NOISE_FREE)
    assert done.returncode == 0, done.stderr[-3000:]
    return workdir
