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
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src/facetsynth"

FIT_CORE = ["hdr", "response", "transfer", "rectify", "plane", "camera", "separation", "normals", "light_factors",
            "pushpull", "sharpness", "coverage", "lightplane", "grid", "partial_ndf", "cluster", "synthesis",
            "params", "refine", "svbrdf", "microfacet", "tables", "fileio"]
FIT_STAGES = ["stages.common", "stages.hdr", "stages.rectify", "stages.separate", "stages.resample",
              "stages.partial_ndf", "stages.cluster", "stages.synthesize", "stages.params", "stages.refine"]
TRUTH = {"scene", "virtual_rig", "mitsuba_capture", "mitsuba_relief", "ward", "rig"}


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
    bad = {m for m in reachable(module) if m.split(".")[0] in TRUTH}
    assert not bad, f"facetsynth.{module} imports {sorted(bad)}"


@pytest.mark.parametrize("module", FIT_STAGES)
def test_fit_stages_reach_the_truth_only_through_the_evaluation_package(module):
    bad = {m for m in reachable(module, skip="evaluation") if m.split(".")[0] in TRUTH}
    assert not bad, f"facetsynth.{module} imports {sorted(bad)} outside facetsynth.evaluation"


def test_the_rule_sees_imports():
    """The walk finds what a module imports (so that the rule above cannot pass by seeing nothing)."""
    assert "scene" in reachable("virtual_rig")
    assert "grid" in reachable("partial_ndf") and "grid" in reachable("stages.refine")
    assert "scene" in reachable("stages.validate") and "scene" in reachable("evaluation.truth")
    assert "evaluation.refine" in reachable("stages.refine", skip="evaluation")
    assert "scene" in reachable("stages.refine") and "scene" not in reachable("stages.refine", skip="evaluation")
