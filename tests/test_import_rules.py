"""Issue 30: the fit never imports the virtual rig, the scenes' truth or another renderer.

The modules a fit runs (:data:`FIT_CORE`) are read as source (no import executed) and every ``facetsynth``
module they import, directly or through another, is collected; none may be one of :data:`TRUTH`. What
scores a fit against a truth (:mod:`facetsynth.evaluation`, the validate stage) imports the truth;
the functions that fit must not, so that a real capture's fit cannot depend on a virtual capture's truth.
The fit's stages (:data:`FIT_STAGES`) call the evaluation package after they have written their outputs:
what they import outside it must not reach the truth either.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src/facetsynth"

TRUTH = {"truth", "rig", "models.ward"}      # packages and modules: the scenes, the virtual rig and Mitsuba's
                                             # captures, the rig's hardware, the Ward baseline
FIT_PACKAGES = ["capture", "geometry", "models", "fit", "io"]
FIT_CORE = sorted(f"{package}.{path.stem}" for package in FIT_PACKAGES
                  for path in (PACKAGE / package).glob("*.py")
                  if path.stem != "__init__" and f"{package}.{path.stem}" not in TRUTH)
FIT_STAGES = ["stages.common", "stages.hdr", "stages.rectify", "stages.separate", "stages.resample",
              "stages.partial_ndf", "stages.cluster", "stages.synthesize", "stages.params", "stages.refine"]


def is_truth(module: str) -> bool:
    return any(module == t or module.startswith(t + ".") for t in TRUTH)


def module_file(name: str) -> Path:
    path = PACKAGE / (name.replace(".", "/") + ".py")
    return path if path.exists() else PACKAGE / name.replace(".", "/") / "__init__.py"


def facetsynth_imports(name: str) -> set[str]:
    """The facetsynth modules (dotted, relative to the package) that module ``name`` imports."""
    tree = ast.parse(module_file(name).read_text())
    package = name.rsplit(".", 1)[0] if "." in name else ""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".") if package else []
                base = parts[:len(parts) - (node.level - 1)] if node.level > 1 else parts
                prefix = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("facetsynth"):
                prefix = node.module[len("facetsynth"):].lstrip(".")
            else:
                continue
            for alias in node.names:
                candidate = f"{prefix}.{alias.name}".strip(".")
                found.add(candidate if module_file(candidate).exists() else prefix)
        elif isinstance(node, ast.Import):
            found |= {a.name[len("facetsynth."):] for a in node.names if a.name.startswith("facetsynth.")}
    return {m for m in found if m and module_file(m).exists()}


def reachable(name: str, skip: str | None = None) -> set[str]:
    """The facetsynth modules ``name`` imports, directly or through another; not through package ``skip``."""
    seen, todo = set(), [name]
    while todo:
        current = todo.pop()
        for m in facetsynth_imports(current) - seen:
            seen.add(m)
            if skip is None or m.split(".")[0] != skip:
                todo.append(m)
    return seen


@pytest.mark.parametrize("module", FIT_CORE)
def test_fit_core_never_imports_the_truth(module):
    bad = {m for m in reachable(module) if is_truth(m)}
    assert not bad, f"facetsynth.{module} imports {sorted(bad)}"


@pytest.mark.parametrize("module", FIT_STAGES)
def test_fit_stages_reach_the_truth_only_through_the_evaluation_package(module):
    bad = {m for m in reachable(module, skip="evaluation") if is_truth(m)}
    assert not bad, f"facetsynth.{module} imports {sorted(bad)} outside facetsynth.evaluation"


def test_the_rule_sees_imports():
    """The walk finds what a module imports (so that the rule above cannot pass by seeing nothing)."""
    assert len(FIT_CORE) >= 30 and "fit.refine" in FIT_CORE and "models.ward" not in FIT_CORE
    assert "truth.scene" in reachable("truth.virtual_rig")
    assert "geometry.grid" in reachable("fit.partial_ndf") and "geometry.grid" in reachable("stages.refine")
    assert "truth.scene" in reachable("stages.validate") and "truth.scene" in reachable("evaluation.truth")
    assert "evaluation.refine" in reachable("stages.score_refine", skip="evaluation")
    assert "truth.scene" in reachable("stages.score_refine")
    assert "truth.scene" not in reachable("stages.score_refine", skip="evaluation")
    assert "truth.scene" not in reachable("stages.refine")     # its truth is scored beside it (issue 31)


RULE_FILES = sorted((PACKAGE.parents[1] / "workflow").glob("**/*.smk")) + [PACKAGE.parents[1] / "Snakefile"]
HEAVY = ("numpy", "scipy", "numba", "cv2", "OpenImageIO", "matplotlib", "sklearn")


def test_parsing_the_rules_imports_no_numerical_library():
    """Issue 31: every ``snakemake`` command parses every rule file (a cluster job parses them again), so what
    they import at parse (their unindented imports) must not pull in numpy, scipy or numba (the calibration
    stage's did: 0.6 s of a 2.3 s dry run). Imported in a fresh interpreter; input functions import lazily."""
    found = sorted({m for path in RULE_FILES
                    for m in re.findall(r"^(?:from|import)\s+(facetsynth[\w.]*)", path.read_text(), re.M)})
    assert {"facetsynth.io.errors", "facetsynth.io.pages"} <= set(found)     # the walk sees the rule files' imports
    code = (f"import sys\nfor m in {found!r}:\n    __import__(m)\n"
            f"print(sorted(h for h in {HEAVY!r} if h in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env={**os.environ, "PYTHONPATH": str(PACKAGE.parent)})
    assert done.stdout.strip() == "[]", f"{found} import {done.stdout.strip()}"
