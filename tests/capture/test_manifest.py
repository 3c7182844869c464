"""The capture manifest schema: good and bad manifests, clear errors naming the file."""

import copy

import numpy as np
import pytest

from conftest import toy_manifest, write_manifest

from facetsynth.capture import manifest
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import write_exr

GOOD = toy_manifest([(0, 0.1, 0.04)], times=(0.25,))


@pytest.fixture
def capture(tmp_path):
    write_exr(tmp_path / "frames" / "0000_e0.exr", {"RGB": np.zeros((3, 4, 3))})
    return tmp_path


write = write_manifest


def test_good_manifest_loads_with_absolute_frame_paths_and_unknown_fields(capture):
    data = copy.deepcopy(GOOD)
    data["rig"] = {"name": "someone else's rig"}          # readers accept fields they do not know
    data["frames"][0]["led_index"] = 17
    loaded = manifest.load(write(capture, data))
    assert loaded["frames"][0]["exposures"][0]["file"] == str(capture / "frames" / "0000_e0.exr")
    assert manifest.load(capture)["rig"]["name"] == "someone else's rig"   # the folder works too
    np.testing.assert_allclose(manifest.camera(loaded).centre, [0, 0, 1])
    np.testing.assert_allclose(manifest.lights(loaded["frames"]), [[0, 0.1, 0.04, 1]])


@pytest.mark.parametrize("mutate, where", [
    (lambda d: d.pop("camera"), "(top level)"),
    (lambda d: d.update(version=2), "version"),
    (lambda d: d["camera"].update(K=[[1, 0], [0, 1]]), "camera/K"),
    (lambda d: d["frames"][0]["exposures"][0].update(time=0), "frames/0/exposures/0/time"),
    (lambda d: d["frames"][0]["light"].update(intensity=[1, -1, 1]), "frames/0/light/intensity/1"),
    (lambda d: d.update(frames=[]), "frames"),
    (lambda d: d["camera"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "camera/R"),
])
def test_bad_manifests_are_refused_naming_file_and_key(capture, mutate, where):
    data = copy.deepcopy(GOOD)
    mutate(data)
    path = write(capture, data)
    with pytest.raises(InputError) as err:
        manifest.load(path)
    assert str(path) in str(err.value) and f"'{where}'" in str(err.value)


def test_missing_frame_is_an_error_naming_the_frame(capture):
    data = copy.deepcopy(GOOD)
    data["frames"][0]["exposures"][0]["file"] = "frames/missing.exr"
    with pytest.raises(InputError, match=r"frames/missing\.exr.*missing"):
        manifest.load(write(capture, data))


def test_not_json_is_an_error_naming_the_file(tmp_path):
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(InputError, match="manifest.json: not valid JSON"):
        manifest.load(tmp_path)


def test_published_schema_is_draft_2020_12():
    from facetsynth.io.validation import schema
    assert schema("capture_manifest.schema.json")["$schema"].endswith("2020-12/schema")
