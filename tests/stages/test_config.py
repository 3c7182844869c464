"""Issue 30: a stage's knobs have one default, in its ``Settings``; config/config.yaml is the user's copy of them.

Every stage whose rule passes its config section as ``params`` has a frozen ``Settings`` whose fields are the
config's keys (its own section's, then the keys its rule takes from other sections under their config
names); the defaults must be the values config/config.yaml ships (with its default preset filled in), so
that a stage run from Python and the workflow run with the shipped config fit the same model.
"""

from __future__ import annotations

import importlib
from dataclasses import MISSING, fields
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]

# stage module -> its config section
STAGES = {"hdr": "hdr", "rectify": "rectify", "separate": "separate", "resample": "resample",
          "partial_ndf": "partial_ndf", "cluster": "cluster", "synthesize": "synthesize", "params": "params",
          "refine": "refine", "selfcheck": "selfcheck", "baseline": "baseline"}
# keys a rule takes from another section (or the top level), under that section's name for them
ELSEWHERE = {"seed": (), "material_tolerance": ("params",), "grazing_deg": ("partial_ndf",),
             "heldout_every": ("selfcheck",), "shadowing": ("partial_ndf",), "tolerance": ("partial_ndf",),
             "max_iterations": ("partial_ndf",)}


def shipped_config() -> dict:
    """config/config.yaml with its default preset's knobs filled in where a section leaves them out."""
    config = yaml.safe_load((ROOT / "config/config.yaml").read_text())
    for section, knobs in config["presets"][config["preset"]].items():
        config[section] = {**knobs, **(config.get(section) or {})}    # a section may be all preset (null)
    return config


def as_settings_value(value):
    return tuple(as_settings_value(v) for v in value) if isinstance(value, list) else value


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_settings_defaults_are_the_shipped_config(stage):
    config = shipped_config()
    section = config[STAGES[stage]]
    settings = importlib.import_module(f"facetsynth.stages.{stage}").Settings
    for f in fields(settings):
        if f.name in section:
            shipped = section[f.name]
        else:
            assert f.name in ELSEWHERE, f"{stage}.Settings.{f.name} is no key of config section {STAGES[stage]}"
            node = config
            for key in ELSEWHERE[f.name] + (f.name,):
                node = node[key]
            shipped = node
        assert f.default is not MISSING, f"{stage}.Settings.{f.name} has no default"
        assert f.default == as_settings_value(shipped), \
            f"{stage}.Settings.{f.name} defaults to {f.default!r}, config/config.yaml ships {shipped!r}"


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_every_key_of_the_section_is_a_setting(stage):
    """A key the user can set in the config and no stage reads would be a knob that does nothing."""
    names = {f.name for f in fields(importlib.import_module(f"facetsynth.stages.{stage}").Settings)}
    assert set(shipped_config()[STAGES[stage]]) <= names
