"""Shared fixtures: small ground-truth captures made by the virtual rig."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# The seven measured RGL BRDFs (CC0), vendored from shared/data/rgl: real reflectance nobody here made.
RGL_DIR = REPO / "resources" / "brdfs" / "rgl"
RGL_FILES = sorted(RGL_DIR.glob("*.bsdf"))
assert len(RGL_FILES) == 7, f"{RGL_DIR}: expected the seven RGL .bsdf files"


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO
