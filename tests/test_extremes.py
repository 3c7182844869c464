"""Numerical extremes (issue 7, part 2): every stage, and the pipeline on small scenes, at the edges.

Each test states the expected behaviour in its docstring and checks it against
a ground truth (an analytic value, or the scene's truth) with a stated
tolerance, besides finiteness. Items of the issue's list that existing tests
already cover are not repeated here; the list says where each item is tested.

Item -> where tested ("here": this module):

- grazing light/view: eq. 8 (light at / in the plane: rho = 0)
    -> tests/test_reflectance.py::test_separation_edge_cases_are_finite_and_stated
- grazing light/view: eq. 8 close to (not at) grazing, exact inverse
    -> here: test_eq8_inverts_the_pixel_model_up_to_grazing
- grazing view: eq. 11 at 89.9 deg (finite)
    -> tests/test_reflectance.py::test_partial_ndf_edge_cases_pure_diffuse_grazing_and_a_sharp_lobe
- grazing view: eq. 11 with the view in the plane (D = 0)
    -> here: test_eq11_view_in_the_plane_gives_an_empty_partial_ndf
- grazing: eq. 6 / A(k) / S(k) at theta -> 90 deg
    -> tests/test_microfacet.py::test_edge_grazing_incidence
    -> tests/test_microfacet.py::test_shadowing_values
- grazing: the fitted SVBRDF at i.n = 0, 1e-9
    -> tests/test_svbrdf.py::test_grazing_below_horizon_off_sample_and_degenerate_directions
- grazing: eq. 20 (F_m) at 89.5-89.99 deg light
    -> here: test_eq20_measured_fresnel_at_grazing_light
- grazing: paper 000 eq. 3 (cos product floored), model at 89.9999 deg
    -> tests/stencil/test_stencil_model_fit.py::test_eq3_4_5_hand_cases (eq. 3 alone)
    -> here: test_stencil_model_is_bounded_and_continuous_at_grazing
- eta near 1 and large; Fresnel at grazing (eq. 3 itself)
    -> tests/test_microfacet.py::test_fresnel_limits
    -> tests/test_microfacet.py::test_fresnel_vs_sp_equations
- eta near 1 / 3.8 / beyond the bound / = 1 in the LM fit (eq. 19)
    -> here: test_eta_fit_at_the_extremes_of_eta
- Fresnel at grazing in eq. 19 (all samples at c = 0: no information)
    -> here: test_eta_fit_on_samples_all_at_grazing_keeps_the_default
- near-mirror lobe (alpha 0.02) between sparse lights, partial NDF
    -> tests/test_reflectance.py::test_partial_ndf_edge_cases_pure_diffuse_grazing_and_a_sharp_lobe
- near-mirror lobe: eq. 6 at alpha 0.005
    -> tests/test_microfacet.py::test_edge_sharp_and_rough_lobes
- near-mirror lobe narrower than a grid cell: tabulated model, eq. 5
    -> here: test_lobe_narrower_than_a_cell_keeps_its_energy_and_eq5
- near-mirror lobe: eq. 9 kd exact between the lights
    -> here: test_eq9_near_mirror_and_very_rough_lobes
- very rough lobe (alpha 1): eq. 9 bias, stated exactly
    -> here: test_eq9_near_mirror_and_very_rough_lobes
- very rough lobe (alpha 1): partial NDF accuracy
    -> here: test_partial_ndf_of_a_very_rough_lobe
- very rough lobe (alpha 1): fitted SVBRDF against eq. 6
    -> here: test_very_rough_tabulated_model_matches_eq6
- purely diffuse: eq. 11 gives D = 0
    -> tests/test_reflectance.py::test_partial_ndf_edge_cases_pure_diffuse_grazing_and_a_sharp_lobe
- purely diffuse / purely specular, the whole pipeline
    -> here: test_pipeline_* (scene with a ks = 0 and a kd = 0 quadrant)
- purely diffuse everywhere: cluster, params, model = kd / pi
    -> here: test_all_diffuse_sample_gives_a_lambertian_model
- dark pixels (HDR)
    -> tests/test_hdr.py::test_dark_pixels_stay_finite_and_dark
- fully dark point (eq. 9: kd = 0)
    -> tests/test_reflectance.py::test_separation_edge_cases_are_finite_and_stated
- saturated pixels (HDR flag and lower bound)
    -> tests/test_hdr.py::test_all_exposures_clipped_gives_flagged_lower_bound
- saturated pixels through separate (invalid, kd from the other frames)
    -> here: test_saturated_and_nan_samples_are_invalid_and_kd_comes_from_the_rest
    -> here: test_pipeline_hdr_and_separation
- NaN / Inf in an exposure (merge)
    -> here: test_hdr_merge_treats_nan_and_inf_readings_as_unusable
- NaN / Inf in a captured frame file (clear error)
    -> tests/test_workflow.py::test_bad_frames_fail_with_one_clear_line_naming_the_file
- NaN in a rectified frame (separate: clear error)
    -> here: test_separate_stage_refuses_a_nan_frame_naming_the_pixel
- NaN / Inf samples in eq. 9 (pure function)
    -> here: test_saturated_and_nan_samples_are_invalid_and_kd_comes_from_the_rest
- a sample of a single pixel, through every per-point stage
    -> here: test_single_point_sample_runs_every_stage
- tiles with no valid point
    -> here: test_tiles_with_no_visible_point
- empty overlap / s2 = 0 in eq. 15
    -> tests/test_synthesis.py::test_empty_overlap_gives_an_infinite_distance_and_no_nan
- tiny overlaps / tiny and huge scales in eq. 15 (direct, matrix, FFT)
    -> here: test_eq15_tiny_overlap_and_extreme_scales
- identical NDFs (k-means, function level)
    -> tests/test_synthesis.py::test_degenerate_kmeans_on_identical_ndfs
- identical NDFs through the cluster and synthesize stages
    -> here: test_identical_ndfs_everywhere_through_the_stages
- LM that does not converge (eta, eq. 19)
    -> here: test_eta_fit_on_noise_is_unconstrained
- LM that does not converge (Ward baseline)
    -> here: test_ward_lm_that_does_not_converge_and_bad_samples
- iteration of eqs. 5/11 that does not converge
    -> here: test_partial_ndf_iteration_cut_short
- float32 inputs of eq. 6
    -> tests/test_microfacet.py::test_float32_inputs_compute_in_float64
- float32 versus float64 runs of the same scene
    -> here: test_float32_and_float64_runs_agree
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import hdr_outputs, rectify_into

from facetsynth import cluster, microfacet, params, tables
from facetsynth import partial_ndf as pndf
from facetsynth import synthesis as syn
from facetsynth.grid import DirectionGrid
from facetsynth.plane import PlaneGrid
from facetsynth.pushpull import push_pull, splat
from facetsynth.scene import MaterialMaps
from facetsynth.separation import brdf_samples, diffuse_level, specular_residual

REPO = Path(__file__).resolve().parents[1]
GRID = DirectionGrid(32, 128)
O = np.array([0.0, -0.8, 0.6])                  # the paper's view, 53 deg from vertical


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sph(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    t, p = np.broadcast_arrays(t, p)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def upper(rng, n):
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    return unit(d)


# ============================================================================ the whole pipeline, small scenes
EXTREME_SCENE = """\
name: extremes
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: diffuse-only
    where: {rect: {x: [-0.05, 0.0], y: [0.0, 0.05]}}
    kd: [0.40, 0.30, 0.20]
    ks: [0.0, 0.0, 0.0]
    eta: 1.5
    alpha: [0.3, 0.3]
    frame: {angle_deg: 0}
  - name: mirror-metal
    where: {rect: {x: [0.0, 0.05], y: [0.0, 0.05]}}
    kd: [0.0, 0.0, 0.0]
    ks: [0.9, 0.7, 0.5]
    eta: 3.5
    alpha: [0.02, 0.02]
    frame: {angle_deg: 0}
  - name: rough-eta-near-1
    where: {rect: {x: [-0.05, 0.0], y: [-0.05, 0.0]}}
    kd: [0.10, 0.20, 0.30]
    ks: [0.5, 0.5, 0.5]
    eta: 1.05
    alpha: [1.0, 1.0]
    frame: {angle_deg: 0}
  - name: glossy
    where: {rect: {x: [0.0, 0.05], y: [-0.05, 0.0]}}
    kd: [0.2, 0.2, 0.2]
    ks: [0.6, 0.6, 0.6]
    eta: 1.6
    alpha: [0.15, 0.3]
    frame: {angle_deg: 30}
"""


def run_per_point_stages(root: Path, geometry: Path, n_theta: int = 32,
                         min_representatives: int = 8) -> dict[str, Path]:
    """separate -> resample -> partial_ndf -> cluster -> synthesize -> params, in-process, into ``root``;
    the direction grid has ``n_theta`` rings (a resample stage that chooses its grid from the data is
    pinned to it)."""
    from facetsynth.stages import cluster as st_cluster, params as st_params, partial_ndf as st_pndf
    from facetsynth.stages import resample as st_resample, separate as st_separate, synthesize as st_synth
    f = {"geometry": geometry}
    for stage, names in {"separate": ("kd.exr", "specular.npy", "valid.npy", "metrics.json"),
                         "resample": ("slice", "specular_colour.npy", "grid.json",
                                      "metrics.json"),
                         "partial_ndf": ("ndf", "metrics.json"),
                         "cluster": ("labels.npy", "representatives.npy", "neighbours.npy", "weights.npy",
                                     "representative_ndf.npy", "representative_confidence.npy", "rotation.npy",
                                     "metrics.json"),
                         "synthesize": ("ndf.npy", "confidence.npy", "cosine.npy", "grid.json", "metrics.json"),
                         "params": ("metrics.json",)}.items():
        for n in names:
            f[f"{stage}/{n}"] = root / stage / n
    f["svbrdf"] = root / "svbrdf"
    st_separate.run(st_separate.Inputs(geometry=geometry),
                    st_separate.Outputs(kd=f["separate/kd.exr"], specular=f["separate/specular.npy"],
                                        valid=f["separate/valid.npy"], metrics=f["separate/metrics.json"]),
                    st_separate.Settings(heldout_every=0))
    st_resample.run(geometry=geometry, specular=f["separate/specular.npy"], valid=f["separate/valid.npy"],
         slice_out=f["resample/slice"],
         colour_out=f["resample/specular_colour.npy"], grid_out=f["resample/grid.json"],
         metrics_out=f["resample/metrics.json"], settings=st_resample.Settings(n_theta_range=(n_theta, n_theta)))
    st_pndf.run(geometry=geometry, slice_path=f["resample/slice"],
         grid_path=f["resample/grid.json"], ndf_out=f["partial_ndf/ndf"],
         metrics_out=f["partial_ndf/metrics.json"],
         settings=st_pndf.Settings(per_point_view=True))
    st_cluster.run(st_cluster.Inputs(geometry=geometry, ndf=f["partial_ndf/ndf"],
         grid=f["resample/grid.json"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"],
         kd=f["separate/kd.exr"]),
         st_cluster.Outputs(labels=f["cluster/labels.npy"],
         representatives=f["cluster/representatives.npy"], neighbours=f["cluster/neighbours.npy"],
         weights=f["cluster/weights.npy"], rep_ndf=f["cluster/representative_ndf.npy"],
         rep_confidence=f["cluster/representative_confidence.npy"], rotation=f["cluster/rotation.npy"],
         metrics=f["cluster/metrics.json"]),
         st_cluster.Settings(min_representatives=min_representatives, n_init=1))
    st_synth.run(st_synth.Inputs(geometry=geometry, ndf=f["partial_ndf/ndf"],
         grid=f["resample/grid.json"], representatives=f["cluster/representatives.npy"],
         neighbours=f["cluster/neighbours.npy"], weights=f["cluster/weights.npy"],
         rep_ndf=f["cluster/representative_ndf.npy"], rep_confidence=f["cluster/representative_confidence.npy"]),
         st_synth.Outputs(ndf=f["synthesize/ndf.npy"], confidence=f["synthesize/confidence.npy"],
         fresnel_cosine=f["synthesize/cosine.npy"], grid=f["synthesize/grid.json"],
         metrics=f["synthesize/metrics.json"]))
    st_params.run(st_params.Inputs(geometry=geometry, kd=f["separate/kd.exr"], specular=f["separate/specular.npy"],
         valid=f["separate/valid.npy"], colour=f["resample/specular_colour.npy"],
         representatives=f["cluster/representatives.npy"], neighbours=f["cluster/neighbours.npy"],
         weights=f["cluster/weights.npy"], ndf=f["synthesize/ndf.npy"], fresnel_cosine=f["synthesize/cosine.npy"],
         synthesis_confidence=f["synthesize/confidence.npy"],
         grid=f["synthesize/grid.json"], rotation=f["cluster/rotation.npy"]),
         st_params.Outputs(svbrdf=f["svbrdf"], metrics=f["params/metrics.json"]))
    return f


def metrics_of(path: Path) -> dict:
    return json.loads(Path(path).read_text())


@pytest.fixture(scope="module")
def extreme_run(tmp_path_factory):
    """The four-quadrant extremes scene (ks = 0; kd = 0 with a near-mirror alpha 0.02 metal-like eta 3.5
    lobe; alpha 1 with eta 1.05; an anisotropic glossy one), noise-free, captured by the virtual rig on
    the sparse test rig (340 lights; camera 120 x 80), merged, rectified to 16 x 16 cells, then every
    per-point stage on a 16 x 64 direction grid."""
    from facetsynth.stages import hdr
    from facetsynth.virtual_rig import VirtualRig, capture
    root = tmp_path_factory.mktemp("extremes")
    (root / "scene.yaml").write_text(EXTREME_SCENE)
    rig = (REPO / "tests/data/rig-sparse.yaml").read_text().replace("width: 240", "width: 120")
    (root / "rig.yaml").write_text(rig.replace("height_px: 160", "height_px: 80"))   # a quarter of the pixels
    capture(root / "scene.yaml", VirtualRig.load(root / "rig.yaml"), root / "capture", seed=1, noise=False)
    hdr.run(hdr.Inputs(capture=root / "capture"), hdr_outputs(root / "hdr"))
    rectify_into(root / "hdr/manifest.json", root / "rectify", 16)
    files = run_per_point_stages(root, root / "rectify/geometry.json", n_theta=16)
    files["root"] = root
    return files


def interior_truth(geometry: Path):
    """The rectified capture, the true maps at its points, and the cells away from material edges."""
    from facetsynth.stages.common import RectifiedCapture
    from facetsynth.stages.rectify import _near_edges
    cap = RectifiedCapture.load(geometry)
    truth = cap.truth()
    region = truth.region.reshape(cap.grid.rows, cap.grid.cols)
    border = np.ones(region.shape, bool)
    border[1:-1, 1:-1] = False                         # the warp filter mixes the background into the outer cells
    interior = (~_near_edges(region) & ~border).ravel() & cap.visible & (truth.region >= 0)
    return cap, truth, interior


def test_pipeline_hdr_and_separation(extreme_run):
    """The mirror lobe saturates every exposure at some pixels (HDR flags them, rectify carries the flag,
    separate marks those samples invalid); kd of eq. 9 is exact where there is no specular (ks = 0), ~0
    where there is no diffuse (kd = 0, the near-mirror tail between lights is tiny), and every tensor is finite."""
    from facetsynth.fileio import read_exr
    hdr = metrics_of(extreme_run["root"] / "hdr/metrics.json")
    assert hdr["saturated_pixels"] > 0 and hdr["median_rel_error"] < 1e-3
    cap, truth, interior = interior_truth(extreme_run["geometry"])
    valid = np.load(extreme_run["separate/valid.npy"])
    spec = np.load(extreme_run["separate/specular.npy"])
    kd = read_exr(extreme_run["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert np.isfinite(spec).all() and (spec >= 0).all() and np.isfinite(kd).all()
    mirror = truth.region == 1
    assert (~valid[mirror]).any() and valid[interior & ~mirror].all()   # saturated: the mirror quadrant, and
                                                                        # the cells the warp filter mixes with it
    diffuse = interior & (truth.region == 0)
    rel = np.abs(kd[diffuse] - truth.kd[diffuse]) / truth.kd[diffuse]
    assert rel.max() < 0.015       # measured 1.2 % everywhere: cell averaging at the grazing light eq. 9 picks
    assert kd[interior & mirror].max() < 0.01
    assert (spec[diffuse] / (truth.kd[diffuse][:, None] / np.pi)).max() < 0.02   # ks = 0: the 1.2 % above
    assert "degenerate" not in metrics_of(extreme_run["separate/metrics.json"])   # one matte quadrant of four


def test_pipeline_model_is_finite_and_predicts_the_capture(extreme_run):
    """The fitted SVBRDF of the extremes scene is finite and non-negative everywhere (grazing, below the
    horizon included; 0 at i.n = 0 and below); eta stays in its range. Against the true radiance of every
    7th frame, relative rms per quadrant (interior cells): ks = 0 within 1 %; the
    anisotropic glossy one within 25 %; the near-mirror metal (alpha 0.02, narrower than the light spacing
    and the 16 x 64 grid) loses its peak: within 1.05, i.e. no overshoot (the prediction is never worse than
    predicting nothing); alpha 1 / eta 1.05 within 2 %. Stated: on the ks = 0 quadrant the model's ks is not 0 (the 1.2 % rectification
    residual looks like a broad lobe, and ks is that lobe's scale over F(c, eta) ~ 0.04), but its radiance
    is right to 1 %."""
    from facetsynth.render import light_geometry
    from facetsynth.svbrdf import SVBRDF
    cap, truth, interior = interior_truth(extreme_run["geometry"])
    model = SVBRDF.load(extreme_run["svbrdf"])
    assert np.isfinite(model.eta).all() and model.eta.min() >= 1.05 and model.eta.max() <= 4.0
    rng = np.random.default_rng(0)
    n = 4000
    index = rng.integers(0, cap.n_points, n)
    wi, wo = upper(rng, n), upper(rng, n)
    wi[:500, 2] = 0.0                                                   # exactly grazing
    wi[500:1000, 2] = 1e-9
    wi[1000:1500, 2] *= -1                                              # below the horizon
    rho = model.eval_index(index, unit(wi), unit(wo))
    assert np.isfinite(rho).all() and (rho >= 0).all()
    assert np.all(rho[:500] == 0) and np.all(rho[1000:1500] == 0)
    # the capture's own frames: predicted against the true radiance at the rectified points
    pts = cap.points
    o = cap.view_directions(True)
    q = np.arange(0, len(cap.lights), 7)
    li, r2 = light_geometry(pts[:, None, :], cap.lights[q][None])
    irr = (np.clip(li[..., 2], 0, None) / r2)[..., None] * cap.light_intensities[q][None]
    idx = np.repeat(np.arange(cap.n_points), len(q))
    pred = model.eval_index(idx, li.reshape(-1, 3), np.repeat(o, len(q), 0)).reshape(irr.shape) * irr
    true = truth.take((slice(None), None)).rho(li, o[:, None, :]) * irr
    # measured 0.005, 0.994, 0.017, 0.24 (0.003, 0.99, 0.002, 0.19 when every representative kept its own
    # partial NDF and weight 1 on itself, before issue 13's pooled representatives and coarse eq. 18)
    for region, bound in ((0, 0.01), (1, 1.05), (2, 0.02), (3, 0.25)):
        sel = interior & (truth.region == region)
        err = np.sqrt(np.mean((pred[sel] - true[sel]) ** 2)) / np.sqrt(np.mean(true[sel] ** 2))
        assert np.isfinite(err) and err < bound


# ============================================================================ hand-built rectified captures
def rig_lights(n_x=11, n_y=9, height=0.04):
    """Lights like the rig's LED array (y from 0 to 0.2 m, 4 cm up), plus a far ring for grazing light."""
    xs, ys = np.meshgrid(np.linspace(-0.1, 0.1, n_x), np.linspace(0.0, 0.2, n_y))
    grid = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, height)], -1)
    az = np.radians(np.linspace(30, 150, 13))
    ring = np.stack([0.4 * np.cos(az), 0.4 * np.sin(az), np.full(az.size, 0.03)], -1)
    return np.concatenate([grid, ring])


def write_rectified(folder: Path, scene_text: str, plane: PlaneGrid, lights: np.ndarray,
                    visible: np.ndarray | None = None, damage=None) -> Path:
    """A rectified capture made directly from the scene's truth (exact radiance at the cell centres):
    geometry.json and one EXR per light. ``damage(q, rgb, saturated)`` may alter frame q in place."""
    from facetsynth.fileio import write_exr, write_json
    from facetsynth.render import radiance
    from facetsynth.scene import Scene
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.yaml").write_text(scene_text)
    p = plane.rows * plane.cols
    visible = np.ones(p, bool) if visible is None else np.asarray(visible, bool)
    view = np.array([0.0, -0.52, 0.9])                     # the rig's camera (60 deg), 1 m from the centre
    pts = plane.points3d()
    maps = Scene.load(folder / "scene.yaml").parameters(pts[..., :2])
    frames = []
    for q, light in enumerate(lights):
        rgb = radiance(pts, maps.rho, light, np.full(3, 0.3), view).astype(np.float32)
        rgb[~visible.reshape(plane.rows, plane.cols)] = 0.0
        saturated = np.zeros(rgb.shape[:2], np.float32)
        if damage is not None:
            damage(q, rgb, saturated)
        write_exr(folder / f"frames/{q:04d}.exr", {"RGB": rgb, "saturated": saturated})
        frames.append({"file": f"frames/{q:04d}.exr",
                       "light": {"position": light.tolist(), "intensity": [0.3, 0.3, 0.3]}})
    write_json(folder / "geometry.json", {"grid": plane.to_dict(), "visible": visible.astype(int).tolist(),
                                          "frames": frames, "view_point": [*view.tolist(), 1.0],
                                          "truth": {"scene": "scene.yaml"}})
    return folder / "geometry.json"


def eq9_truth(kd, ks, lights, point=np.zeros(3), eta=1.5, alpha=(0.2, 0.3), angle=20.0, lowest=0.03):
    """kd that eq. 9 must give for a point of ``one_material`` (written out: of the true rho at the lights
    whose radiance exceeds 5 % of the mean, the mean of the round(lowest x n) (at least one) with the smallest
    channel mean, the stage's default ``separate.lowest``, times pi; the specular tail there is its bias)."""
    view = np.array([0.0, -0.52, 0.9])
    wi = lights - point
    r2 = np.sum(wi**2, -1)
    wi = wi / np.sqrt(r2)[:, None]
    rho = microfacet.rho(wi, unit(view - point), np.array(kd, float), np.array(ks, float), eta, alpha[0], alpha[1],
                         np.radians(angle))
    intensity = (rho * (np.clip(wi[:, 2], 0, None) / r2)[:, None] * 0.3).mean(axis=1)
    qualifying = rho[intensity > 0.05 * intensity.mean()]
    m = max(1, int(np.round(lowest * len(qualifying))))
    return np.pi * qualifying[np.argsort(qualifying.mean(axis=1))[:m]].mean(axis=0)


def one_material(kd, ks, eta=1.5, alpha=(0.2, 0.3), angle=20.0, name="m") -> str:
    return f"""\
name: {name}
ndf: ggx
size: [0.10, 0.10]
regions:
  - name: all
    where: {{all: true}}
    kd: {list(kd)}
    ks: {list(ks)}
    eta: {eta}
    alpha: {list(alpha)}
    frame: {{angle_deg: {angle}}}
"""


def test_all_diffuse_sample_gives_a_lambertian_model(tmp_path):
    """Purely diffuse (ks = 0) everywhere: eq. 9 gives kd exactly; the specular residual and the partial
    NDFs are float32 rounding noise (<= 1e-7, relative 1e-7 of kd / pi). Stated: cluster and synthesize
    run on that noise (eq. 15 is scale-free, so noise looks like 36 distinct NDFs), but params turns it
    into ks <= 1e-5, so the model is Lambertian (rho = kd / pi to 1e-5) in every direction pair, and eta
    keeps the default (no specular signal at grazing)."""
    from facetsynth.fileio import read_exr
    from facetsynth.svbrdf import SVBRDF
    kd = (0.45, 0.25, 0.05)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0, 0, 0)), PlaneGrid(0.1, 0.1, 6, 6), rig_lights())
    f = run_per_point_stages(tmp_path, geometry, n_theta=16)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    np.testing.assert_allclose(got, np.tile(kd, (36, 1)), rtol=1e-5)          # float32 frames
    assert np.all(np.load(f["separate/specular.npy"]) <= 1e-7)          # measured 1.5e-8
    separated = metrics_of(f["separate/metrics.json"])                  # never a silent model (issue 15)
    assert separated["specular_signal_fraction"] == 0.0
    assert separated["degenerate"].startswith("no specular signal: 0.0 % of the lit points")
    assert np.all(tables.load(f["partial_ndf/ndf"], "ndf") <= 1e-6)            # measured 3.2e-8
    model = SVBRDF.load(f["svbrdf"])                                    # ks measured 2.9e-6
    assert np.all(model.ks <= 1e-5) and not model.eta_fitted.any()
    rng = np.random.default_rng(1)
    idx = rng.integers(0, 36, 3000)
    rho = model.eval_index(idx, upper(rng, 3000), upper(rng, 3000))
    np.testing.assert_allclose(rho, np.tile(kd, (3000, 1)) / np.pi, rtol=1e-5, atol=1e-7)


def test_single_point_sample_runs_every_stage(tmp_path):
    """A sample of a single rectified cell: every per-point stage runs (k-means with one point, synthesis
    with one exemplar, eta with one representative); kd is exact, the model finite, and it predicts the
    point's own frames within 15 % rms (one partial NDF, completed only from its own rotations)."""
    from facetsynth.fileio import read_exr
    from facetsynth.render import light_geometry
    from facetsynth.svbrdf import SVBRDF
    kd, ks = (0.2, 0.3, 0.1), (0.6, 0.6, 0.6)
    lights = rig_lights(21, 17)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, ks, alpha=(0.25, 0.25)), PlaneGrid(0.1, 0.1, 1, 1),
                               lights)
    f = run_per_point_stages(tmp_path, geometry)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert got.shape == (1, 3)
    np.testing.assert_allclose(got[0], eq9_truth(kd, ks, lights, alpha=(0.25, 0.25)), rtol=1e-5)
    assert np.all(got[0] > kd) and np.all(got[0] - kd < 0.01)    # eq. 9's bias: the specular tail, stated
    assert metrics_of(f["cluster/metrics.json"])["representatives"] == 1
    model = SVBRDF.load(f["svbrdf"])
    assert np.isfinite(model.ndf).all() and np.isfinite(model.area).all() and model.area.min() > 0
    o = unit(np.array([0.0, -0.52, 0.9]))
    wi, _ = light_geometry(np.zeros((1, 3)), lights)
    pred = model.eval_index(np.zeros(len(lights), np.intp), wi, np.tile(o, (len(lights), 1)))
    true = microfacet.rho(wi, o, np.array(kd), np.array(ks), 1.5, 0.25, 0.25, np.radians(20.0))
    err = np.sqrt(np.mean((pred - true) ** 2) / np.mean(true**2))
    assert np.isfinite(pred).all() and err < 0.15                      # measured 0.082


def test_tiles_with_no_visible_point(tmp_path):
    """272 points, the first tile of 256 not visible: invisible points get kd = 0, label -1, zero weights,
    ks = 0 and a model that is 0; the 16 visible points of the second tile get kd exactly."""
    from facetsynth.fileio import read_exr
    from facetsynth.svbrdf import SVBRDF
    plane = PlaneGrid(0.1, 0.1, 16, 17)
    visible = np.zeros(272, bool)
    visible[256:] = True
    kd = (0.3, 0.2, 0.1)
    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0.5, 0.5, 0.5), alpha=(0.3, 0.3)), plane,
                               rig_lights(), visible)
    f = run_per_point_stages(tmp_path, geometry, n_theta=16, min_representatives=2)
    got = read_exr(f["separate/kd.exr"])[0]["RGB"].reshape(-1, 3)
    assert np.all(got[:256] == 0)
    expected = [eq9_truth(kd, (0.5,) * 3, rig_lights(), pt, alpha=(0.3, 0.3))
                for pt in plane.points3d().reshape(-1, 3)[256:]]
    np.testing.assert_allclose(got[256:], expected, rtol=1e-5)
    assert not np.load(f["separate/valid.npy"])[:256].any()
    for name, channel in (("resample/slice", "values"), ("partial_ndf/ndf", "ndf"), ("partial_ndf/ndf", "confidence")):
        assert np.isfinite(tables.load(f[name], channel)).all()
    labels, weights = np.load(f["cluster/labels.npy"]), np.load(f["cluster/weights.npy"])
    assert np.all(labels[:256] == -1) and np.all(weights[:256] == 0) and np.all(labels[256:] >= 0)
    np.testing.assert_allclose(weights[256:].sum(axis=1), 1.0, atol=1e-5)
    model = SVBRDF.load(f["svbrdf"])
    assert np.all(model.ks[:256] == 0) and np.all(model.kd[:256] == 0)
    rng = np.random.default_rng(2)
    idx = rng.integers(0, 272, 2000)
    rho = model.eval_index(idx, upper(rng, 2000), upper(rng, 2000))
    assert np.isfinite(rho).all() and np.all(rho[idx < 256] == 0) and np.all(rho[idx >= 256] > 0)


def test_separate_stage_refuses_a_nan_frame_naming_the_pixel(tmp_path):
    """A NaN (or Inf) in a rectified frame is bad input: separate fails with an InputError naming the
    file and the first bad pixel, and writes nothing."""
    from facetsynth.errors import InputError
    from facetsynth.stages import separate

    def damage(q, rgb, saturated):
        if q == 3:
            rgb[2, 1, 0] = np.nan
        if q == 5:
            rgb[0, 0, 2] = np.inf

    geometry = write_rectified(tmp_path / "cap", one_material((0.2,) * 3, (0.5,) * 3), PlaneGrid(0.1, 0.1, 4, 4),
                               rig_lights(3, 3), damage=damage)
    with pytest.raises(InputError, match=r"0003\.exr.*1 pixel\(s\) are NaN or Inf \(first at row 2, col 1\)"):
        separate.run(separate.Inputs(geometry=geometry),
                     separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "s.npy", valid=tmp_path / "v.npy",
                                      metrics=tmp_path / "m.json"), separate.Settings(heldout_every=0))
    assert not (tmp_path / "kd.exr").exists() and not (tmp_path / "s.npy").exists()


def test_saturated_and_nan_samples_are_invalid_and_kd_comes_from_the_rest(tmp_path):
    """Eq. 9 with bad samples. (a) In the stage, a pixel flagged saturated in the rectified frame is an
    invalid sample and its point's kd comes from the other frames, exactly. (b) In the pure function, a
    NaN or Inf sample (even one passed as valid) is treated as invalid: kd is what the other samples give."""
    from facetsynth.fileio import read_exr
    from facetsynth.stages import separate
    kd = (0.3, 0.2, 0.1)

    def damage(q, rgb, saturated):
        if q % 2 == 0:                              # half the frames clip at cell (1, 1): a wrong, huge value
            rgb[1, 1] = 1e3
            saturated[1, 1] = 1.0

    geometry = write_rectified(tmp_path / "cap", one_material(kd, (0.4,) * 3), PlaneGrid(0.1, 0.1, 3, 3),
                               rig_lights(5, 5), damage=damage)
    separate.run(separate.Inputs(geometry=geometry),
                 separate.Outputs(kd=tmp_path / "kd.exr", specular=tmp_path / "s.npy", valid=tmp_path / "v.npy",
                                  metrics=tmp_path / "m.json"), separate.Settings(heldout_every=0))
    got = read_exr(tmp_path / "kd.exr")[0]["RGB"].reshape(-1, 3)
    valid = np.load(tmp_path / "v.npy")
    assert valid[4, 1::2].all() and not valid[4, 0::2].any() and valid[[0, 1, 2, 3, 5, 6, 7, 8]].all()
    pts = PlaneGrid(0.1, 0.1, 3, 3).points3d().reshape(-1, 3)
    lights = rig_lights(5, 5)
    expected = np.array([eq9_truth(kd, (0.4,) * 3, lights, pt) for pt in pts])
    expected[4] = eq9_truth(kd, (0.4,) * 3, lights[1::2], pts[4])       # cell (1, 1): the odd frames only
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    # (b) the pure function
    rng = np.random.default_rng(4)
    lights = np.column_stack([rng.uniform(-0.1, 0.1, 60), rng.uniform(0.0, 0.2, 60), np.full(60, 0.04)])
    points = np.zeros((1, 3))
    wi, r2 = (lights[None] - points[:, None]), None
    r2 = np.sum(wi**2, -1)
    wi = wi / np.sqrt(r2)[..., None]
    rho = microfacet.rho(wi, O, np.array(kd), np.full(3, 0.5), 1.5, 0.1, 0.3, 0.0)
    radiance = rho * (wi[..., 2] / r2)[..., None] * 0.3
    samples, _ = brdf_samples(radiance, points, lights, np.full((60, 3), 0.3))
    clean = diffuse_level(samples, radiance, np.ones((1, 60), bool))
    keep = np.ones((1, 60), bool)
    keep[0, [7, 30]] = False
    reference = diffuse_level(samples[:, keep[0]], radiance[:, keep[0]], np.ones((1, 58), bool))
    bad_s, bad_r = samples.copy(), radiance.copy()
    bad_s[0, 7], bad_r[0, 7] = np.nan, np.nan
    bad_s[0, 30, 1], bad_r[0, 30, 1] = np.inf, np.inf
    got = diffuse_level(bad_s, bad_r, np.ones((1, 60), bool))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, reference, rtol=1e-12)
    np.testing.assert_allclose(got, clean, rtol=0.05)                 # and close to the clean data's kd
    residual = specular_residual(bad_s, got)
    assert np.all(residual[:, keep[0]] >= 0) and np.isfinite(residual[:, keep[0]]).all()


def test_hdr_merge_treats_nan_and_inf_readings_as_unusable():
    """A NaN or +Inf exposure reading (a dead or hot sensor value) is unusable, like a clipped one: the
    pixel is merged from its other exposures exactly as if that reading were absent. A pixel with no
    finite reading at all gets the clipped pixel's finite lower bound and the saturated flag, so later
    stages exclude it. The merge never returns NaN or Inf."""
    from facetsynth.hdr import SensorModel, merge_exposures
    times = np.array([0.01, 0.1, 1.0])
    sensor = SensorModel(saturation=1.0, read_sigma=1e-3, shot_gain=1e-4)
    values = np.array([0.004, 0.04, 0.4])[:, None, None, None] * np.ones((3, 1, 4, 3))
    reference, _ = merge_exposures(values, times, sensor)
    np.testing.assert_allclose(reference, 0.4, rtol=1e-6)
    bad = values.copy()
    bad[1, 0, 0, 0] = np.nan                  # pixel 0: NaN in the middle exposure
    bad[2, 0, 1, 1] = np.inf                  # pixel 1: Inf in the longest
    bad[:, 0, 2, 2] = np.nan                  # pixel 2: no finite reading in any exposure
    merged, saturated = merge_exposures(bad, times, sensor)
    assert np.isfinite(merged).all()
    without_middle, _ = merge_exposures(values[[0, 2], :, :1], times[[0, 2]], sensor)
    without_longest, _ = merge_exposures(values[:2, :, 1:2], times[:2], sensor)
    np.testing.assert_allclose(merged[0, 0, 0], without_middle[0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(merged[0, 1, 1], without_longest[0, 0, 1], rtol=1e-6)
    np.testing.assert_allclose(merged[0, 3], reference[0, 3], rtol=0)   # an untouched pixel is unchanged
    assert merged[0, 2, 2] == pytest.approx(sensor.clip_level / times.min())
    assert saturated[0, 2] and not saturated[0, 0] and not saturated[0, 1] and not saturated[0, 3]


def test_eq8_inverts_the_pixel_model_up_to_grazing():
    """Eq. 8 divides by n.i: for lights from 80 to 89.99 deg (n.i down to 1.7e-4) it still inverts the
    pixel model exactly (rtol 1e-9); below n.i = 1e-6 (here 89.99995 deg) it returns 0 by statement, not a
    huge quotient of rounding errors."""
    theta = np.array([80.0, 89.0, 89.9, 89.99, 89.99995])
    lights = 0.1 * sph(theta, 70.0)
    points = np.zeros((1, 3))
    wi = unit(lights)[None]
    rho = microfacet.rho(wi, O, np.array([0.2, 0.1, 0.3]), np.full(3, 0.6), 1.5, 0.1, 0.3, 0.2)
    intensity = np.full((len(theta), 3), 0.3)
    radiance = rho * (wi[..., 2] / 0.01)[..., None] * intensity[None]
    samples, directions = brdf_samples(radiance, points, lights, intensity)
    assert np.isfinite(samples).all()
    np.testing.assert_allclose(samples[0, :4], rho[0, :4], rtol=1e-9)
    assert np.all(samples[0, 4] == 0)
    np.testing.assert_allclose(directions[0], wi[0], atol=1e-15)


def test_eq11_view_in_the_plane_gives_an_empty_partial_ndf():
    """A view exactly in the sample plane (o.n = 0; eq. 11's factor (o.n) vanishes): every D is 0 (no
    information), finite, converged at once; a view 0.01 deg above the plane stays finite and non-negative."""
    full = np.ones((1,) + GRID.shape)
    rng = np.random.default_rng(0)
    d = upper(rng, 500)[None]
    for elevation, expect_zero in ((0.0, True), (0.01, False)):
        view = np.array([0.0, -1.0, 0.0]) if elevation == 0 else sph(90.0 - elevation, -90.0)
        slice_ = push_pull(*splat(GRID, d, microfacet.rho(d, view, np.zeros(3), np.full(3, 0.6), 1.6, 0.2, 0.3,
                                                          0.0).mean(-1)))
        fit = pndf.fit(slice_, full, view, GRID)
        assert np.isfinite(fit.ndf).all() and np.isfinite(fit.confidence).all() and (fit.ndf >= 0).all()
        if expect_zero:
            assert np.all(fit.ndf == 0) and fit.converged.all() and fit.iterations[0] == 1


def test_eq20_measured_fresnel_at_grazing_light():
    """Eq. 20 for lights at 89.5-89.99 deg: F_m = rho_s / (ks D / (4 A(i) A(o))) from the tabulated true
    model is finite and overestimates F(c, eta) by 0-20 % in the lobe (measured 9-15 %). Stated limitation:
    A(k) is tabulated on the 16 x 32 shadowing grid, whose last ring is at 87.2 deg, and held constant
    beyond it, while the true A falls to alpha/2 at 90 deg; so A(i) is too large and F_m too high there.
    Exactly at 90 deg the model's factor is 0 and F_m = 0, which the caller excludes."""
    from facetsynth.svbrdf import tabulate_truth
    maps = MaterialMaps(kd=np.zeros((1, 3)), ks=np.full((1, 3), 0.8), eta=np.array([1.5]), alpha_u=np.array([0.25]),
                        alpha_v=np.array([0.4]), phi_frame=np.array([0.5]), region=np.zeros(1, int))
    model = tabulate_truth(maps, GRID, PlaneGrid(0.1, 0.1, 1, 1))
    wi = sph(np.repeat([89.5, 89.9, 89.99, 90.0], 72), np.tile(np.arange(0, 360, 5), 4))
    wo = np.broadcast_to(O, wi.shape)
    rho_s = microfacet.rho(wi, wo, np.zeros(3), np.full(3, 0.8), 1.5, 0.25, 0.4, 0.5).mean(-1)
    spec, c = model.specular_terms(np.zeros(len(wi), np.intp), wi, wo)
    f_m = params.measured_fresnel(rho_s, 0.8 * spec)
    assert np.isfinite(f_m).all()
    at_90 = wi[:, 2] == 0
    assert np.all(f_m[at_90] == 0) and np.all(spec[at_90] == 0)
    lobe = ~at_90 & (model.ndf_at(np.zeros(len(wi), np.intp), microfacet.half_vector(wi, wo)) >= 0.05 * model.ndf.max())
    ratio = f_m[lobe] / microfacet.fresnel(c[lobe], 1.5)
    assert lobe.sum() >= 30 and ratio.min() >= 1.0 and ratio.max() < 1.2


@pytest.mark.parametrize("jacobian", [False, True])
def test_stencil_model_is_bounded_and_continuous_at_grazing(jacobian):
    """Paper 000 eq. 3 divides by cos th_i cos th_v; the model floors each cosine at cos 85 deg, so at
    theta -> 90 deg (cosines 1e-12 .. 1e-3) the value is finite, non-negative, below the analytic bound
    max_j m_j (kd_j + ks_j (a_j + b_j / cos^2 85)^alpha_j) max(1, k (a_s + (b_s + f_s) / cos^2 85) / kh_min),
    and continuous (identical for cosines 1e-12 and 1e-9 up to the change of H).  With ``jacobian`` the
    eq. 10 lobe is also divided by k.h, which at the grazing mirror pair goes to 0: floored at cos 85 deg."""
    from dataclasses import replace
    from facetsynth.stencil.model import COS_FLOOR, Mode, StencilModel, evaluate
    modes = (Mode(0.3, 0.6, 0.4, 0.05, 0.1, 0.8, 2.0, (0.9, 0.6, 0.3)),
             Mode(1.6, 0.7, 0.2, 0.10, 0.05, 0.5, 3.0, (0.2, 0.5, 0.9)))
    model = StencilModel(modes=modes, beta=(0.3,), r=0.05, m_bg=(0.2, 0.5, 0.9), k=2.0, alpha_s=20.0,
                         a_s=0.4, b_s=0.05)
    if jacobian:
        model = replace(model, f_s=0.02, jacobian=True)
    floor = COS_FLOOR**2
    bound = max(max(md.m) * (md.kd + md.ks * (md.a + md.b / floor) ** md.alpha) for md in modes)
    lobe_max = model.k * (model.a_s + (model.b_s + model.f_s) / floor) / (COS_FLOOR if jacobian else 1.0)
    bound = max(bound, model.r * max(model.m_bg)) * max(1.0, lobe_max)
    phis = np.arange(0, 360, 7.5)
    values = {}
    for c in (1e-12, 1e-9, 1e-3):
        s = np.sqrt(1 - c * c)
        wi = np.stack([s * np.cos(np.radians(phis)), s * np.sin(np.radians(phis)), np.full(phis.size, c)], -1)
        wo = np.stack([-wi[:, 0], -wi[:, 1], wi[:, 2]], -1)            # the mirror direction, also grazing
        values[c] = np.concatenate([evaluate(model, wi, wo), evaluate(model, wi, sph(np.full(phis.size, 40.0), phis))])
        assert np.isfinite(values[c]).all() and (values[c] >= 0).all() and values[c].max() <= bound * (1 + 1e-12)
    np.testing.assert_allclose(values[1e-12], values[1e-9], rtol=1e-6, atol=1e-12)
    assert values[1e-3].max() > 0


# ============================================================================ eta, Fresnel, Levenberg-Marquardt
C_GRAZING = np.linspace(0.02, 0.5, 60)         # |i.h| of grazing samples


def test_eta_fit_at_the_extremes_of_eta():
    """Eq. 19 (as printed) on exact F: eta = 1.08 (near 1: F is tiny except at grazing) and 3.8 (metal-like)
    are recovered to 1e-3; eta = 6 lies beyond the bound 4.0, the fit runs to the bound and the default is
    kept and said; eta = 1 (no interface) gives F = 0, the fit runs to the lower bound, default kept."""
    for eta in (1.08, 3.8):
        fit = params.fit_eta(microfacet.fresnel(C_GRAZING, eta), C_GRAZING)
        assert fit.constrained and fit.eta == pytest.approx(eta, abs=1e-3) and np.isfinite(fit.std)
    beyond = params.fit_eta(microfacet.fresnel(C_GRAZING, 6.0), C_GRAZING, default=1.55)
    assert not beyond.constrained and beyond.eta == 1.55 and "bound" in beyond.reason
    none = params.fit_eta(microfacet.fresnel(C_GRAZING, 1.0), C_GRAZING, default=1.55)
    assert not none.constrained and none.eta == 1.55 and "bound" in none.reason
    # the ratio model of the pipeline (F at c over F at c_ref), near 1 and large
    for eta in (1.08, 3.8):
        c_ref = np.full(C_GRAZING.size, 0.6)
        f = microfacet.fresnel(C_GRAZING, eta) / microfacet.fresnel(0.6, eta)
        fit = params.fit_eta(f, C_GRAZING, c_ref)
        assert fit.constrained and fit.eta == pytest.approx(eta, abs=1e-3)


def test_eta_fit_on_samples_all_at_grazing_keeps_the_default():
    """Fresnel at grazing: at c = |i.h| -> 0, F -> 1 for every eta (F = 1 - O(c)), so samples all at
    c <= 1e-6, measured to 1e-4 (far better than the pipeline's F_m), carry no usable information on eta:
    the standard error is huge, the fit is unconstrained and keeps the default; everything finite."""
    c = np.linspace(0.0, 1e-6, 40)
    noise = 1 + 1e-4 * np.random.default_rng(2).standard_normal(40)
    fit = params.fit_eta(microfacet.fresnel(c, 2.0) * noise, c, default=1.45)
    assert not fit.constrained and fit.eta == 1.45 and fit.samples == 40
    assert np.isfinite(fit.rms) and fit.rms < 2e-4 and fit.std > 1.0


def test_eta_fit_on_noise_is_unconstrained():
    """LM on data that no eta explains (F_m log-normal, independent of c; and F_m with NaN / Inf entries
    mixed in): the fit ends without a trusted minimum, reports it unconstrained and keeps the default;
    the NaN / Inf samples are dropped (counted out of ``samples``), nothing non-finite leaves the fit."""
    rng = np.random.default_rng(3)
    f_m = np.exp(rng.normal(0.0, 1.5, C_GRAZING.size))
    fit = params.fit_eta(f_m, C_GRAZING, default=1.45)
    assert not fit.constrained and fit.eta == 1.45 and np.isfinite(fit.rms)
    good = microfacet.fresnel(C_GRAZING, 2.2)
    bad = good.copy()
    bad[[3, 9]] = np.nan
    bad[17] = np.inf
    fit = params.fit_eta(bad, C_GRAZING)
    assert fit.samples == C_GRAZING.size - 3 and fit.constrained and fit.eta == pytest.approx(2.2, abs=1e-3)


def test_ward_lm_that_does_not_converge_and_bad_samples():
    """The per-point Ward baseline's LM. Cut short (max_iterations = 3) it reports ok = False with finite
    parameters inside the alpha range and phi in [0, pi); given its full budget it recovers the lobe
    (ks, alphas to 1e-3). A NaN or Inf sample is dropped, not propagated: the fit equals the fit without it."""
    from facetsynth import ward
    rng = np.random.default_rng(5)
    wi, wo = upper(rng, 300), np.broadcast_to(O, (300, 3))
    truth = (0.5, 0.1, 0.3, 0.4)
    rho_s = truth[0] * ward.ward_specular(wi, wo, *truth[1:])

    def fit(rho, i, o, **kw):
        return type(f := ward.fit_points(rho[None], i[None], o[None], **kw))(*(v[0] for v in f))

    full = fit(rho_s, wi, wo)
    assert full.ok
    np.testing.assert_allclose([full.ks, full.alpha_x, full.alpha_y], truth[:3], rtol=1e-3)
    short = fit(rho_s, wi, wo, max_iterations=3)
    lo, hi = ward.ALPHA_RANGE
    assert not short.ok and np.isfinite([short.ks, short.alpha_x, short.alpha_y, short.phi, short.cost]).all()
    assert lo <= short.alpha_x <= hi and lo <= short.alpha_y <= hi and 0 <= short.phi < np.pi
    bad = rho_s.copy()
    bad[10], bad[20] = np.nan, np.inf
    got = fit(bad, wi, wo)
    keep = np.ones(300, bool)
    keep[[10, 20]] = False
    ref = fit(rho_s[keep], wi[keep], wo[keep])
    np.testing.assert_allclose([got.ks, got.alpha_x, got.alpha_y, got.phi], [ref.ks, ref.alpha_x, ref.alpha_y, ref.phi],
                               rtol=1e-9)


# ============================================================================ near-mirror and very rough lobes
def one_point_maps(alpha_u, alpha_v, phi=0.0, eta=1.5, kd=0.0, ks=0.8):
    return MaterialMaps(kd=np.full((1, 3), kd), ks=np.full((1, 3), ks), eta=np.array([eta]),
                        alpha_u=np.array([alpha_u]), alpha_v=np.array([alpha_v]), phi_frame=np.array([phi]),
                        region=np.zeros(1, int))


@pytest.mark.parametrize("alpha", [0.01, 0.02])
def test_lobe_narrower_than_a_cell_keeps_its_energy_and_eq5(alpha):
    """A near-mirror NDF (alpha 0.01-0.02: most of its mass inside the first ring, 2.8 deg) tabulated on the
    32 x 128 grid: the table is renormalised, so integral (n.h) D = 1 exactly (ks is kept) though the peak
    is lost; eq. 5 from it gives A(k) = closed-form Smith within 1 % up to 75 deg (all microfacets near n);
    the model is finite and non-negative at the mirror direction and at grazing."""
    from facetsynth.svbrdf import tabulate_truth
    model = tabulate_truth(one_point_maps(alpha, alpha), GRID, PlaneGrid(0.1, 0.1, 1, 1))
    assert GRID.integrate(model.ndf[0].astype(float) * GRID.directions[..., 2]) == pytest.approx(1.0, abs=1e-6)
    assert params.specular_coefficient(model.ndf[0], GRID) == pytest.approx(1.0, abs=1e-6)
    k = sph(np.array([0.0, 20.0, 45.0, 60.0, 75.0]), 30.0)
    area = model.area_at(np.zeros(len(k), np.intp), k)
    np.testing.assert_allclose(area, microfacet.projected_area(k, alpha, alpha), rtol=0.01)
    wi = sph(np.array([30.0, 60.0, 89.9, 90.0]), 0.0)
    wi[3] = [1.0, 0.0, 0.0]                               # exactly in the plane
    wo = wi * [-1, -1, 1]
    rho = model.eval_index(np.zeros(4, np.intp), wi, wo)
    assert np.isfinite(rho).all() and (rho >= 0).all() and np.all(rho[3] == 0) and np.all(rho[:3] > 0)


def test_eq9_near_mirror_and_very_rough_lobes():
    """Eq. 9's minimum over lights. A near-mirror lobe (alpha 0.01) narrower than the light spacing hits
    few lights, so kd is exact up to the far GGX tail (2e-5 absolute). A very rough lobe (alpha 1) adds
    specular to every light: kd is over-estimated by exactly the smallest specular value among the
    qualifying lights (the stated bias)."""
    rng = np.random.default_rng(6)
    lights = np.column_stack([rng.uniform(-0.1, 0.1, 150), rng.uniform(0.0, 0.2, 150), np.full(150, 0.04)])
    points = np.zeros((1, 3))
    wi = unit(lights)[None]
    r2 = np.sum(lights**2, -1)[None]
    kd = np.array([0.3, 0.2, 0.1])
    intensity = np.full((150, 3), 0.3)
    for alpha in (0.01, 1.0):
        spec = microfacet.rho(wi, O, np.zeros(3), np.full(3, 0.7), 1.5, alpha, alpha, 0.0)
        rho = kd / np.pi + spec
        radiance = rho * (wi[..., 2] / r2)[..., None] * intensity[None]
        samples, _ = brdf_samples(radiance, points, lights, intensity)
        rho_d = diffuse_level(samples, radiance, np.ones((1, 150), bool))
        mean_i = radiance.mean(-1)
        qualifying = mean_i > 0.05 * mean_i.mean()
        expected = kd / np.pi + spec[qualifying].min(axis=0)
        np.testing.assert_allclose(rho_d[0], expected, rtol=1e-9)
        if alpha == 0.01:
            assert np.all(np.pi * rho_d[0] - kd < 2e-5)         # measured 1.0e-5: the far GGX tail
        else:
            assert np.all(np.pi * rho_d[0] - kd > 0.005)       # the bias is real: measured 0.009 in kd


def analytic_slice(ks, eta, alpha_u, alpha_v, phi, view=O, grid=GRID):
    rho = microfacet.rho(grid.directions, view, np.zeros(3), np.full(3, ks), eta, alpha_u, alpha_v, phi)
    return rho.mean(axis=-1)[None]


def test_partial_ndf_of_a_very_rough_lobe():
    """Alpha = 1 (a broad NDF: most of its mass lies outside the view's domain Omega, and eq. 5's shadowing
    is strong): the partial NDF from an exact slice is finite, non-negative and converged, and matches
    mean(ks) F D on W >= 0.5 within 0.35 relative L2 (measured 0.28, against 0.05-0.08 for alpha 0.1-0.3 in
    test_reflectance: S of eq. 5 from a partial NDF that misses most of a broad lobe is biased; stated)."""
    full = np.ones((1,) + GRID.shape)
    fit = pndf.fit(analytic_slice(0.6, 1.6, 1.0, 1.0, 0.0), full, O, GRID)
    assert fit.converged.all() and np.isfinite(fit.ndf).all() and (fit.ndf >= 0).all()
    true_ndf = microfacet.ndf(GRID.directions, 1.0, 1.0, 0.0)[None]
    ref = pndf.recoverable_ndf(np.full((1, 3), 0.6), np.array([1.6]), true_ndf, O[None], GRID)
    err = pndf.relative_l2(fit.ndf, ref, fit.confidence >= 0.5, GRID)[0]
    assert err < 0.35


def test_very_rough_tabulated_model_matches_eq6():
    """Alpha 1 (and an anisotropic 1 x 0.5 lobe): the tabulated model equals eq. 6 with a median relative
    error below 1e-3 (3e-3) and at most 2e-3 (3 %) while both directions are within 85 deg of the normal;
    beyond, up to 10 % (15 %) (stated: A(k) is held constant beyond the shadowing
    grid's last ring, 87.2 deg, where the true A keeps falling)."""
    from facetsynth.svbrdf import tabulate_truth
    rng = np.random.default_rng(7)
    wi, wo = upper(rng, 20000), upper(rng, 20000)
    for au, av, med, inner_max, all_max in ((1.0, 1.0, 1e-3, 2e-3, 0.1), (1.0, 0.5, 3e-3, 0.03, 0.15)):
        maps = one_point_maps(au, av, phi=0.7, kd=0.0)
        model = tabulate_truth(maps, GRID, PlaneGrid(0.1, 0.1, 1, 1))
        rho = model.eval_index(np.zeros(20000, np.intp), wi, wo)[:, 0]
        truth = maps.take(np.zeros(20000, np.intp)).rho(wi, wo)[:, 0]
        rel = np.abs(rho - truth) / truth
        inner = np.minimum(wi[:, 2], wo[:, 2]) > np.cos(np.radians(85.0))
        assert np.isfinite(rho).all() and np.median(rel) < med        # measured 6.5e-4, 2.2e-3
        assert rel[inner].max() < inner_max and rel.max() < all_max    # measured 1.1e-3, 2.0e-2; 8.7e-2, 0.12


# ============================================================================ eq. 15, k-means, iteration limits
SGRID = DirectionGrid(16, 64)


def ggx_partial(frames, scale=1.0, alpha=(0.15, 0.4), grid=SGRID, max_theta=56.0):
    """Partial tuples <D, W> of GGX NDFs at frame azimuths, on a single-view-like domain (a cap to max_theta
    deg narrowing in phi; the same shape as tests/test_synthesis.py's)."""
    t = np.degrees(grid.theta)[:, None]
    p = np.degrees(grid.phi)[None, :]
    half = np.clip(150.0 - (t - 15.0) * 3.5, 0.0, 180.0)
    gap = np.abs((p - 90.0 + 180.0) % 360.0 - 180.0)
    mask = ((t <= 15.0) | (gap <= half)) & (t <= max_theta)
    frames = np.atleast_1d(np.asarray(frames, float))
    d = microfacet.ndf(grid.directions.reshape(1, -1, 3), alpha[0], alpha[1], frames[:, None]).reshape(
        (len(frames),) + grid.shape) * np.reshape(scale, (-1, 1, 1))
    return np.where(mask, d, 0.0), np.broadcast_to(mask, d.shape).astype(float)


def test_eq15_tiny_overlap_and_extreme_scales():
    """Eq. 15 where s1, s2 -> 0 or the overlap shrinks to one cell. One shared cell: each D divided by its
    own scale over the overlap is 1 / dw there, so the distance is 0 (to rounding, 1e-12) and the overlap is that cell's
    solid angle (direct, matrix and FFT forms agree). NDFs scaled by 1e-6 and 1e6 (a dark and a very bright
    point): the distance is scale-free, direct form to 1e-9, FFT (complex64) within 1e-3 of the direct one.
    Below the TINY scale (1e-32) an NDF counts as empty: distance inf, weights 0, never NaN."""
    d, w = ggx_partial([0.3, 1.2])
    one = np.zeros_like(w)
    one[0, 3, 10] = one[1, 3, 10] = 1.0                      # each domain: one cell, the same one
    one[1, 4, 20] = 0.5                                      # ... and one of its own
    m = syn.distance(d[0], one[0], d[1], one[1], SGRID)
    assert m.distance < 1e-12 / SGRID.solid_angles[3, 10] ** 2 and m.relative < 1e-12   # 0 up to rounding
    assert m.overlap == pytest.approx(SGRID.solid_angles[3, 10], rel=1e-12)
    scale = 1.0 / SGRID.solid_angles[3, 10] ** 2
    assert abs(syn.pairwise_distance(d[:1], one[:1], d[1:], one[1:], SGRID)[0, 0]) < 1e-9 * scale
    match, frac = syn.ExemplarSpectra(d[1:], one[1:], SGRID).scores(d[0], one[0])
    assert abs(match.distance[0, 0]) < 1e-5 * scale and np.isfinite(match.distance[0, 0])
    assert not np.isnan(match.distance).any() and not np.isnan(frac).any()
    base = syn.distance(d[0], w[0], d[1], w[1], SGRID)
    spectra_base, _ = syn.ExemplarSpectra(d[1:], w[1:], SGRID).scores(d[0], w[0])
    for s1, s2 in ((1e-6, 1.0), (1.0, 1e6), (1e-6, 1e6)):
        m = syn.distance(s1 * d[0], w[0], s2 * d[1], w[1], SGRID)
        assert m.distance == pytest.approx(float(base.distance), rel=1e-9)
        fft, _ = syn.ExemplarSpectra(s2 * d[1:], w[1:], SGRID).scores(s1 * d[0], w[0])
        assert np.isfinite(fft.distance).all()
        np.testing.assert_allclose(fft.distance, spectra_base.distance, rtol=1e-3, atol=1e-3 * float(base.distance))
    empty = syn.distance(1e-32 * d[0], w[0], d[1], w[1], SGRID)
    assert np.isinf(empty.distance) and empty.s1 == 0 and empty.weight == 0 and not np.isnan(empty.relative)


def test_identical_ndfs_everywhere_through_the_stages(tmp_path):
    """Every point has the identical partial NDF (an isotropic GGX, alpha 0.3) and W: the cluster stage
    lowers k to 1 distinct NDF (one representative, weight 1 everywhere, lambda undefined -> null); the
    synthesize stage completes it beyond its own domain (from rotated copies of itself, which are exact
    matches, or by azimuthal symmetry), so on every covered cell the completed NDF equals the true
    isotropic GGX (to the half-float rounding of the stored partial NDFs, 2^-11), and nothing is NaN."""
    from facetsynth.fileio import write_json
    from facetsynth.stages import cluster as st_cluster, synthesize as st_synth
    from facetsynth.tables import support_writer
    geometry = write_rectified(tmp_path / "cap", one_material((0.2,) * 3, (0.5,) * 3), PlaneGrid(0.1, 0.1, 5, 5),
                               rig_lights(2, 2))
    d, w = ggx_partial([0.0], scale=0.7, alpha=(0.3, 0.3))
    with support_writer(tmp_path / "partial", (25,) + SGRID.shape, ("ndf", "confidence")) as write:
        write(np.repeat(w, 25, 0) > 0, ndf=np.repeat(d, 25, 0), confidence=np.repeat(w, 25, 0))
    write_json(tmp_path / "grid.json", SGRID.to_dict())
    out = tmp_path / "out"
    st_cluster.run(st_cluster.Inputs(geometry=geometry, ndf=tmp_path / "partial", grid=tmp_path / "grid.json"),
         st_cluster.Outputs(labels=out / "labels.npy",
         representatives=out / "reps.npy", neighbours=out / "nbr.npy", weights=out / "wts.npy",
         rep_ndf=out / "rep_ndf.npy", rep_confidence=out / "rep_conf.npy", rotation=out / "rotation.npy",
         metrics=out / "cluster.json"))
    m = metrics_of(out / "cluster.json")
    assert m["distinct_ndfs"] == 1 and m["representatives"] == 1 and m["lambda"] is None
    wts = np.load(out / "wts.npy")
    assert np.all(np.load(out / "labels.npy") == 0) and np.all(wts[:, 0] == 1) and np.all(wts[:, 1:] == 0)
    st_synth.run(st_synth.Inputs(geometry=geometry, ndf=tmp_path / "partial",
         grid=tmp_path / "grid.json", representatives=out / "reps.npy", neighbours=out / "nbr.npy",
         weights=out / "wts.npy"), st_synth.Outputs(ndf=out / "ndf.npy", confidence=out / "w.npy",
         fresnel_cosine=out / "cos.npy", grid=out / "grid.json", metrics=out / "synth.json"))
    table, conf = np.load(out / "ndf.npy"), np.load(out / "w.npy")
    assert table.shape == (1,) + SGRID.shape and np.isfinite(table).all() and (table >= 0).all()
    covered = conf[0] > 0
    truth = 0.7 * microfacet.ndf(SGRID.directions, 0.3, 0.3, 0.0)
    assert covered.sum() > (w[0] > 0).sum()                  # more than its own domain
    np.testing.assert_allclose(table[0][covered], truth[covered], rtol=2.0 ** -11)


def test_partial_ndf_iteration_cut_short():
    """The eq. 5 / eq. 11 iteration stopped before it converges (max_iter = 1, and 0) returns its last
    iterate, finite and non-negative, flagged converged = False with the iterations used; with its budget
    it converges, and the one-step iterate is 1-10 % (relative L2) from the converged NDF."""
    full = np.ones((1,) + GRID.shape)
    slice_ = analytic_slice(0.6, 1.6, 0.2, 0.4, 0.5)
    done = pndf.fit(slice_, full, O, GRID)
    assert done.converged.all() and done.iterations[0] > 1
    for max_iter in (0, 1):
        cut = pndf.fit(slice_, full, O, GRID, max_iter=max_iter)
        assert not cut.converged.any() and cut.iterations[0] == max_iter
        assert np.isfinite(cut.ndf).all() and (cut.ndf >= 0).all()
    one = pndf.fit(slice_, full, O, GRID, max_iter=1)
    err = pndf.relative_l2(one.ndf, done.ndf, done.confidence > 0, GRID)[0]
    assert 0.01 < err < 0.1                                  # measured 0.046


# ============================================================================ float32 versus float64
def test_float32_and_float64_runs_agree():
    """The same scene's data in float32 and in float64 (the pipeline stores float32 tensors): push-pull and
    the partial NDF agree to 1e-5 (relative to the largest value), k-means gives the same clusters, synthesis
    makes the same merges (exemplar and shift) with NDFs within 1e-4, and the eta fit agrees to 1e-5."""
    rng = np.random.default_rng(8)
    d = upper(rng, 600)[None].repeat(3, 0)
    values = np.stack([microfacet.rho(d[0], O, np.zeros(3), np.full(3, 0.6), eta, a, b, p).mean(-1)
                       for eta, a, b, p in ((1.3, 0.1, 0.3, 0.0), (2.5, 0.2, 0.2, 0.0), (1.6, 0.05, 0.4, 1.0))])
    sums = {dt: splat(GRID, d.astype(dt), values.astype(dt)) for dt in (np.float32, np.float64)}
    slices = {dt: push_pull(*s) for dt, s in sums.items()}
    peak = np.abs(slices[np.float64]).max()
    assert np.abs(slices[np.float32] - slices[np.float64]).max() < 1e-5 * peak
    full = np.ones((3,) + GRID.shape)
    fits = {dt: pndf.fit(slices[np.float64].astype(dt), full.astype(dt), O.astype(dt), GRID) for dt in slices}
    a, b = fits[np.float32].ndf, fits[np.float64].ndf
    assert np.isfinite(a).all() and np.abs(a - b).max() < 1e-5 * np.abs(b).max()
    # clustering and synthesis on rotated copies of one anisotropic GGX
    frames = np.linspace(0, 2 * np.pi, 32, endpoint=False) + 0.013
    pd, pw = ggx_partial(frames, scale=np.random.default_rng(0).uniform(0.3, 1.0, 32))
    runs = {}
    for dt in (np.float32, np.float64):
        dd, ww = pd.astype(dt), pw.astype(dt)
        km = cluster.kmeans(cluster.features(dd, ww, SGRID), dd, ww, SGRID, 4, seed=0)
        spectra = syn.ExemplarSpectra(dd, ww, SGRID)
        done = syn.complete(dd[0], ww[0], spectra, dd, ww, SGRID, syn.hemisphere_target(ww[0] > 0, SGRID),
                            syn.Knobs(overlap_range=(0.5, 0.85), max_iterations=12, target_coverage=0.99,
                                      max_relative_error=0.4, candidates_per_region=5, fill_overlap=None,
                                      extend_rings=False), exclude=0)
        runs[dt] = (km, done)
    (k32, c32), (k64, c64) = runs[np.float32], runs[np.float64]
    np.testing.assert_array_equal(k32.labels, k64.labels)
    assert [(m["exemplar"], m["shift"]) for m in c32.merges] == [(m["exemplar"], m["shift"]) for m in c64.merges]
    assert len(c64.merges) >= 2
    assert np.abs(c32.ndf - c64.ndf).max() < 1e-4 * c64.ndf.max()
    f_m = microfacet.fresnel(C_GRAZING, 1.9) * (1 + 0.02 * np.random.default_rng(1).standard_normal(C_GRAZING.size))
    e32 = params.fit_eta(f_m.astype(np.float32), C_GRAZING.astype(np.float32))
    e64 = params.fit_eta(f_m, C_GRAZING)
    assert e32.constrained and e64.constrained and abs(e32.eta - e64.eta) < 1e-5


def test_partial_ndf_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """scatter.tiles > 1 (issue 14): the parts (whole tiles of points) and their join give the unsplit
    run's partial NDFs bit for bit and the same metrics; tiles of 64 points give 4 tiles on these 256, and
    6 parts leave two empty."""
    from facetsynth.stages import partial_ndf as st_pndf
    monkeypatch.setattr(st_pndf, "TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], slice_path=f["resample/slice"],
                  grid_path=f["resample/grid.json"])
    settings = st_pndf.Settings(per_point_view=True)
    st_pndf.run(**inputs, ndf_out=tmp_path / "ndf", metrics_out=tmp_path / "m.json", settings=settings)
    from facetsynth.stages.common import part_points
    assert [part_points(256, k, 6, 64) for k in range(6)] == [slice(0, 64), slice(64, 128), slice(128, 192),
                                                              slice(192, 256), slice(256, 256), slice(256, 256)]
    assert part_points(200, 3, 4, 64) == slice(192, 200) and part_points(1000, 1, 2) == slice(512, 1000)
    with pytest.raises(ValueError):
        part_points(256, 6, 6)
    parts = [tmp_path / f"part{k}" for k in range(6)]
    for k in (3, 0, 5, 1, 4, 2):                      # any order
        st_pndf.run_part(**inputs, part=k, parts=6, ndf_out=parts[k] / "ndf", record_out=parts[k] / "record.npz",
                         settings=settings)
    shuffled = [parts[k] for k in (2, 0, 5, 4, 1, 3)]
    st_pndf.gather(f["geometry"], f["resample/grid.json"], [p / "ndf" for p in shuffled],
                   [p / "record.npz" for p in shuffled], tmp_path / "joined", tmp_path / "joined.json", settings)
    for name in ("table.json", "mask.npy", "offsets.npy", "ndf.npy", "confidence.npy"):
        assert (tmp_path / "joined" / name).read_bytes() == (tmp_path / "ndf" / name).read_bytes(), name
    assert metrics_of(tmp_path / "joined.json") == metrics_of(tmp_path / "m.json")
    assert len(tables.SupportTable(tmp_path / "ndf")) == 256 and len(tables.SupportTable(parts[5] / "ndf")) == 0


def test_resample_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """resample in 3 parts of whole tiles (64 points: 2, 1 and 1 tiles of the 256 points), joined in any
    order: the unsplit run's slices, colour, grid and metrics, bit for bit (every part decides the
    same grid from the same strided points)."""
    from facetsynth.stages import resample
    monkeypatch.setattr(resample, "TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"])
    names = ("slice", "colour.npy", "grid.json", "metrics.json")
    resample.run(**inputs, **{k: tmp_path / "whole" / n for k, n in zip(
        ("slice_out", "colour_out", "grid_out", "metrics_out"), names)})
    parts = [tmp_path / f"part{k}" for k in range(3)]
    for k in (1, 2, 0):
        resample.run_part(**inputs, part=k, parts=3, slice_out=parts[k] / "slice", record_out=parts[k] / "record.npz")
    shuffled = [parts[k] for k in (2, 0, 1)]
    resample.gather(**inputs, slice_parts=[p / "slice" for p in shuffled],
                    records=[p / "record.npz" for p in shuffled],
                    **{k: tmp_path / "joined" / n for k, n in zip(
                        ("slice_out", "colour_out", "grid_out", "metrics_out"), names)})
    for name in ("slice/table.json", "slice/mask.npy", "slice/offsets.npy", "slice/values.npy") + names[1:]:
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "joined" / name).read_bytes(), name
    assert len(tables.SupportTable(parts[0] / "slice")) == 128


def test_ward_baseline_scatter_parts_join_bitwise_into_the_unsplit_run(extreme_run, tmp_path, monkeypatch):
    """The per-point Ward fits (the slowest per-point stage: 915 s at the demo's native 168 x 168) in 3 parts of
    whole tiles (64 points: 2, 1 and 1 tiles of the 256 points), joined in any order: the same model folder, bit
    for bit, and the same metrics but the time."""
    from facetsynth.stages import baseline
    monkeypatch.setattr(baseline, "TILE_POINTS", 64)
    f = extreme_run
    inputs = dict(geometry=f["geometry"], specular=f["separate/specular.npy"], valid=f["separate/valid.npy"])
    baseline.run(**inputs, kd_path=f["separate/kd.exr"], colour=f["resample/specular_colour.npy"],
                 model_out=tmp_path / "whole", metrics_out=tmp_path / "whole.json")
    for k in range(3):
        baseline.run_part(**inputs, part=k, parts=3, record_out=tmp_path / f"part{k}.npz")
    baseline.gather(f["geometry"], f["separate/kd.exr"], f["resample/specular_colour.npy"], f["separate/specular.npy"],
                    [tmp_path / f"part{k}.npz" for k in (2, 0, 1)], tmp_path / "joined", tmp_path / "joined.json")
    for a in sorted((tmp_path / "whole").iterdir()):
        assert a.read_bytes() == (tmp_path / "joined" / a.name).read_bytes(), a.name
    whole, joined = metrics_of(tmp_path / "whole.json"), metrics_of(tmp_path / "joined.json")
    assert whole.pop("fit_seconds") > 0 and joined.pop("fit_seconds") > 0 and whole == joined
