"""The bases of a stage's ``Inputs``, ``Outputs`` and ``Settings``: frozen dataclasses filled by name from a rule.

Plain dataclasses and nothing else, so that the workflow's rule files can read a stage's settings (their
fields and defaults) when Snakemake parses them, without importing numpy, scipy or numba: every
``snakemake`` command parses every rule file, and a cluster job does it again.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import ClassVar, dataclass_transform


@dataclass_transform(frozen_default=True)
class FrozenFields:
    """Base whose every subclass is a frozen dataclass, without a decorator of its own: a stage's ``Inputs``,
    ``Outputs`` and ``Settings`` are declared as their fields alone."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        dataclass(frozen=True)(cls)


class StageSettings(FrozenFields):
    """Base of a stage's frozen settings dataclass: one field per key of its config section (and of the keys
    its rule takes from other sections, under their config names); the defaults are the config's
    (tests/stages/test_config.py checks config/config.yaml against them). ``MEASURED`` names the fields that are
    no config keys (measured defaults the rule does not pass); every other field must come from the rule."""

    MEASURED: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_params(cls, params):
        """From a rule's ``params`` (the config section's keys); lists become tuples (a frozen settings object).
        A field missing from the rule raises (a user's setting would be ignored), but a ``MEASURED`` one."""
        return cls(**{f.name: _frozen(getattr(params, f.name)) for f in fields(cls)
                      if f.name not in cls.MEASURED or hasattr(params, f.name)})


def _frozen(value):
    return tuple(_frozen(v) for v in value) if isinstance(value, list) else value


class RuleFiles(FrozenFields):
    """Base of a stage's ``Inputs`` and ``Outputs`` frozen dataclasses: one field per named file of its rule
    (a list of paths for a named list); a field with a default may be missing from the rule."""

    @classmethod
    def from_rule(cls, files):
        """From a rule's ``input`` or ``output`` (Snakemake's named list), by name."""
        named = dict(files.items())
        return cls(**{f.name: _path(named[f.name]) for f in fields(cls) if f.name in named})


def _path(value):
    return [Path(v) for v in value] if isinstance(value, (list, tuple)) else Path(value)
