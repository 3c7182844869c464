"""Issue 13, done-when: fits that describe the material, not the rig, at the paper's 480 lights.

Each scene is captured by the virtual rig (default noise) and run through the whole workflow; these are
the slow tests (`make test-scenes`: 20-24 min on 2 cores in all), run by CI after the unit suite.

- uniform: one GGX material (alpha 0.12) at 1360 and 480 lights: at most 8 representatives (measured 1 at
  both), per-point NDF spread at the noise level (measured 0.0: every point has the one representative).
- rgl-quadrants at 480 lights: four measured RGL BRDFs (not eq. 6), held-out relative L2 and the
  within-region spread of the fitted NDFs.
- ggx-tiles at 480 lights: one anisotropic GGX at sixteen orientations, the same.
Before issue 13 (push-pull slices, k-means on each point's own domain, eq. 18 with the representatives'
own partial NDFs): uniform 64 representatives at both densities; docs/decisions.md has the figures.
"""

import json

import pytest

from test_workflow import make_workdir, snakemake

pytestmark = pytest.mark.scenes

# Held-out relative L2 (every view) and the largest within-region median NDF spread at 480 lights, at the
# default native resolution (168 x 168), measured 2026-12-02 (views paper / theta30): rgl-quadrants 0.300 /
# 0.680 (Ward 0.368 / 0.803), spread 0.086; ggx-tiles 0.123 / 0.094 (Ward 0.537 / 0.876), spread 0.105.
# Before eq. 9 averaged its lowest samples and an unconstrained eta kept the default (the same day):
# rgl-quadrants 0.312 / 0.690, ggx-tiles 0.212 / 0.168 with spread 0.245 (docs/decisions.md, "Diffuse level
# under noise"). Since issue 29's refine (2026-12-05, session 41, this test's config: every light fitted):
# rgl-quadrants 0.153 / 0.460 (Ward 0.368 / 0.803), ggx-tiles 0.054 / 0.045 (Ward 0.537 / 0.876); the spreads
# (params') unchanged. Bounds about 15 % above the largest view; issue 13's target of 0.10 is met by the tiles
# on both views.
RGL_REL_L2, RGL_SPREAD = 0.53, 0.10
TILES_REL_L2, TILES_SPREAD = 0.063, 0.12

RIG_480 = "rig/descriptions/paper-480.yaml"
SHEET = (f"uniform\tvirtual\tresources/scenes/uniform.yaml\t\n"
         f"uniform-480\tvirtual\tresources/scenes/uniform.yaml\t{RIG_480}\n"
         f"rgl-quadrants-480\tvirtual\tresources/scenes/rgl-quadrants.yaml\t{RIG_480}\n"
         f"ggx-tiles-480\tvirtual\tresources/scenes/ggx-tiles.yaml\t{RIG_480}\n")


@pytest.fixture(scope="module")
def scenes(repo, tmp_path_factory):
    """The scenes fitted on all their lights: the figures below are claims at 480 lights. With issue 29's
    self-check holding 48 of them out (the default), uniform-480 splits into 3 representatives (NDF spread
    0.072) and the tiles' pipeline spread rises to 0.29 (0.17 after refine), while the held-out views improve
    (docs/decisions.md, "The fit reproduces what it saw"; docs/accuracy.md measures the default)."""
    workdir = make_workdir(repo, tmp_path_factory.mktemp("scenes"), SHEET, resolution=None)   # native: 168 x 168
    targets = ["results/uniform/params/metrics.json", "results/uniform-480/params/metrics.json",
               "results/rgl-quadrants-480/validate/metrics.json", "results/ggx-tiles-480/validate/metrics.json"]
    done = snakemake(workdir, *targets, "--config", "selfcheck={heldout_every: 0, relit_every: 8}")
    assert done.returncode == 0, done.stderr[-3000:]
    return workdir


def metrics(workdir, sample, stage):
    return json.loads((workdir / "results" / sample / stage / "metrics.json").read_text())


@pytest.mark.parametrize("sample", ["uniform", "uniform-480"])
def test_one_material_gets_few_representatives_and_one_ndf_everywhere(scenes, sample):
    clustered = metrics(scenes, sample, "cluster")
    assert clustered["representatives"] <= 8
    spread = metrics(scenes, sample, "params")["ndf_spread"]["uniform"]
    assert spread["median"] <= 0.02 and spread["p90"] <= 0.05


@pytest.mark.parametrize("sample, rel_l2, spread, beats_ward", [
    ("rgl-quadrants-480", RGL_REL_L2, RGL_SPREAD, True),     # measured BRDFs: ahead of Ward at native resolution
    ("ggx-tiles-480", TILES_REL_L2, TILES_SPREAD, True)])
def test_held_out_views_and_region_spread_at_480_lights(scenes, sample, rel_l2, spread, beats_ward):
    validate = metrics(scenes, sample, "validate")
    for view in validate["views"].values():
        assert view["heldout_rel_l2"] <= rel_l2
        if beats_ward:
            assert view["heldout_rel_l2"] < view["baseline_ward_rel_l2"]
    regions = metrics(scenes, sample, "params")["ndf_spread"]
    assert len(regions) == (4 if sample.startswith("rgl") else 16)
    assert max(r["median"] for r in regions.values()) <= spread

