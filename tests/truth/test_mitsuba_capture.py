"""An independent renderer (issue 13 item 3): Mitsuba 3 renders a capture the project's model did not render.

(a) geometry: the Mitsuba sensor made from a manifest camera images 3D points where
    :class:`facetsynth.geometry.camera.Camera` projects them; (b) radiometry: a Lambertian plane, and an anisotropic
    GGX material inside the project's model family, rendered by Mitsuba equal the pixel model of DESIGN.md
    sec. 4 (:func:`facetsynth.models.render.radiance`); (c) end to end: a Mitsuba capture of an anisotropic copper
    conductor (Mitsuba's own conductor Fresnel and Smith shadowing: outside eq. 6) is imported by the
    workflow, fitted, and ``facetsynth predict`` is scored against a held-out view that Mitsuba also renders.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install mitsuba, or the test extra): "
                                      "the independent-renderer tests need it")

from facetsynth.app import cli
from facetsynth.capture import manifest
from facetsynth.models import microfacet  # noqa: E402
from facetsynth.truth import mitsuba_capture  # noqa: E402
from facetsynth.geometry.camera import Camera  # noqa: E402
from facetsynth.io.fileio import read_rgb  # noqa: E402
from facetsynth.evaluation.metrics import marker_centroids  # noqa: E402
from facetsynth.models.render import radiance  # noqa: E402
from facetsynth.truth.scene import Scene  # noqa: E402
from facetsynth.stages.capture import check_capture  # noqa: E402
from facetsynth.stages.validate import _to_png, side_by_side  # noqa: E402
from facetsynth.truth.virtual_rig import VirtualRig  # noqa: E402

RIG = Path(__file__).parents[1] / "data" / "rig-mitsuba.yaml"
SIZE = (0.10, 0.10)
# The test material: the anisotropic GGX (alpha_u 0.15, alpha_v 0.35) as Mitsuba's rough copper
# conductor (complex Fresnel, no diffuse term), its u axis along circles about the centre (lathe-turned).
COPPER = mitsuba_capture.EXAMPLE_BSDF
HELDOUT_VIEW = (50.9, -15.3)          # config.yaml validate.views 'paper', phi relative to the fitting camera
# Held-out relative L2 of the fit over the sample pixels (all frames pooled), measured 2026-12-02: 0.275 with
# issue 13's sampling-invariant fit (pooled representatives, each point of a turning cluster its representative
# turned); 0.319 before, at commits 66c7d9f and cdb8eed (the Ward baseline: 0.296; the project's own renderer
# given the same copper, rig and preset: 0.46, Ward 0.32). The whole disc as one representative gave 0.225 here
# but 0.246 against 0.101 on the demo, so it was not kept (docs/decisions.md). The bound is 0.275 plus 16 %;
# the target is 0.10 (not met).
MAX_HELDOUT_REL_L2 = 0.32


@pytest.fixture(scope="module")
def rig() -> VirtualRig:
    return VirtualRig.load(RIG)


def _plane(tmp_path: Path, frame=0.0) -> Path:
    return mitsuba_capture.write_plane_mesh(tmp_path / "sample.ply", SIZE[0], SIZE[1], frame)


def _plane_points(camera: Camera) -> np.ndarray:
    xy = camera.pixel_plane_points(1)
    return np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)


# --- (a) geometry --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shift", [(0.0, 0.0), (-6.3, 4.2)], ids=["centred", "off-centre-principal-point"])
def test_mitsuba_images_points_where_the_manifest_camera_projects_them(rig, tmp_path, shift):
    """A small emissive sphere off the plane and the four black markers on it land within 0.1 px of
    Camera.project (measured: at most 0.06 px; the brief's bound is 0.5 px)."""
    import mitsuba as mi
    base = rig.camera(SIZE[0])
    K = base.K.copy()
    K[0, 2] += shift[0]
    K[1, 2] += shift[1]
    camera = Camera(base.width, base.height, K, base.R, base.t)
    for point in ([0.021, -0.013, 0.03], [-0.03, 0.02, 0.0]):
        scene = {"type": "scene", "integrator": {"type": "direct"},
                 "sensor": mitsuba_capture.sensor_dict(camera, spp=256),
                 "dot": {"type": "sphere", "center": point, "radius": 0.0008,
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}}
        image = np.array(mi.render(mi.load_dict(scene)))[..., 0]
        rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
        found = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
        assert np.hypot(*(found - camera.project(np.array(point)))) < 0.1
    # the markers, on a white plane lit almost uniformly from far above
    lit = mitsuba_capture.Renderer(mitsuba_capture.scene_dict(camera, {"type": "diffuse"}, _plane(tmp_path),
                                                              spp=64)).render([0.0, 0.0, 100.0], [1e4] * 3)
    centres = np.array(mitsuba_capture.DEMO_MARKERS["positions"])
    expected = camera.project(np.c_[centres, np.zeros(len(centres))])
    found = marker_centroids(lit.mean(axis=-1), expected, mitsuba_capture.DEMO_MARKERS["radius"] * camera.K[0, 0])
    assert np.isfinite(found).all()                       # every marker's window inside the image
    assert np.hypot(*(found - expected).T).max() < 0.1


def test_sensor_rejects_what_a_perspective_sensor_cannot_be(rig):
    base = rig.camera(SIZE[0])
    K = base.K.copy()
    K[1, 1] *= 1.01
    with pytest.raises(ValueError, match="square pixels"):
        mitsuba_capture.sensor_dict(Camera(base.width, base.height, K, base.R, base.t))
    with pytest.raises(ValueError, match="distortion"):
        mitsuba_capture.sensor_dict(Camera(base.width, base.height, base.K, base.R, base.t,
                                           np.array([0.1, 0, 0, 0, 0])))


# --- (b) radiometry ------------------------------------------------------------------------------------------

def test_lambertian_plane_matches_the_pixel_model(rig, tmp_path):
    """Mitsuba's point light (intensity per steradian) and diffuse BSDF give I = rho (n.i) L / r^2: median
    relative error over the sample pixels 1e-3 at 32 spp (bound 1 %), under rig lights near and far."""
    camera = rig.camera(SIZE[0])
    albedo = np.array([0.7, 0.5, 0.3])
    renderer = mitsuba_capture.Renderer(mitsuba_capture.scene_dict(
        camera, {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo.tolist()}}, _plane(tmp_path),
        spp=32))
    mask = mitsuba_capture.sample_pixels(camera, SIZE)
    plan = rig.scan()
    for steps, led in (plan[0], plan[len(plan) // 2], plan[-1]):
        light, intensity = rig.led_position(led, steps), np.array([0.3, 0.25, 0.2])
        truth = radiance(_plane_points(camera), lambda wi, wo: np.broadcast_to(albedo / np.pi, wi.shape),
                         light, intensity, camera.centre)
        image = renderer.render(light, intensity)
        rel = np.abs(image[mask] / truth[mask] - 1.0)
        assert np.median(rel) < 0.01
        assert np.percentile(rel, 95) < 0.03


def test_anisotropic_ggx_and_its_tangent_frame_match_the_model(rig, tmp_path):
    """Inside eq. 6's family (GGX, Smith shadowing, dielectric Fresnel as a k = 0 conductor, diffuse base)
    Mitsuba and facetsynth.models.microfacet.rho agree to 0.3 % (relative L1 over the sample): the mesh's texture
    coordinates put the BSDF's u axis at the frame azimuth (the mirrored frame is 10-40 % off)."""
    camera = rig.camera(SIZE[0])
    kd, ks, eta, au, av = np.array([0.2, 0.1, 0.05]), np.array([0.75, 0.5, 0.38]), 1.8, 0.1, 0.3
    w = 0.75   # blendbsdf: (1 - w) diffuse + w conductor, each reflectance <= 1
    bsdf = {"type": "blendbsdf", "weight": w,
            "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": (kd / (1 - w)).tolist()}},
            "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha_u": au, "alpha_v": av,
                       "eta": eta, "k": 0.0, "specular_reflectance": {"type": "rgb", "value": (ks / w).tolist()}}}
    renderer = mitsuba_capture.Renderer(mitsuba_capture.scene_dict(camera, bsdf, _plane(tmp_path, 30.0), spp=32))
    mask = mitsuba_capture.sample_pixels(camera, SIZE)
    points = _plane_points(camera)
    for light in ([0.01, 0.05, 0.04], [-0.03, 0.0, 0.04], [0.0, -0.05, 0.04]):
        image = renderer.render(light, [0.3] * 3)

        def rel_l1(phi_deg):
            model = radiance(points, lambda wi, wo: microfacet.rho(wi, wo, kd, ks, eta, au, av, np.radians(phi_deg)),
                             np.array(light), [0.3] * 3, camera.centre)
            return np.abs(image[mask] - model[mask]).sum() / model[mask].sum()

        assert rel_l1(30.0) < 0.006
        assert rel_l1(-30.0) > 0.05


RGL_QUADRANTS = Path(__file__).parents[2] / "resources" / "scenes" / "rgl-quadrants.yaml"


def test_scene_regions_read_the_measured_quadrants_and_refuse_what_they_cannot_render(tmp_path):
    regions = mitsuba_capture.scene_regions(RGL_QUADRANTS)
    assert regions["size"] == SIZE and regions["markers"] == mitsuba_capture.DEMO_MARKERS
    rects = {r["name"]: r["rect"] for r in regions["regions"]}       # the yaml's +-0.06 rects clipped to the sample
    assert rects == {"satin-rosaline": [[-0.05, 0.0], [0.0, 0.05]], "vch-golden-yellow": [[0.0, 0.05], [0.0, 0.05]],
                     "colodur-napoli": [[-0.05, 0.0], [-0.05, 0.0]], "paper-white": [[0.0, 0.05], [-0.05, 0.0]]}
    assert all(r["bsdf"]["type"] == "measured" and Path(r["bsdf"]["filename"]).is_file() for r in regions["regions"])
    half = mitsuba_capture.measured_bsdf(regions["regions"][0]["bsdf"]["filename"], 0.5)
    assert half["type"] == "blendbsdf" and half["weight"] == 0.5 and half["bsdf_1"]["type"] == "measured"
    with pytest.raises(ValueError, match="scale"):
        mitsuba_capture.measured_bsdf(regions["regions"][0]["bsdf"]["filename"], 2.0)
    text = RGL_QUADRANTS.read_text().replace("../brdfs", str(RGL_QUADRANTS.parents[1] / "brdfs"))
    overlapping = tmp_path / "overlap.yaml"
    overlapping.write_text(text.replace("x: [0.0, 0.06], y: [0.0, 0.06]", "x: [-0.01, 0.06], y: [0.0, 0.06]"))
    with pytest.raises(ValueError, match="overlap"):
        mitsuba_capture.scene_regions(overlapping)
    with pytest.raises(ValueError, match="not a rect with a measured file"):
        mitsuba_capture.scene_regions(RGL_QUADRANTS.parent / "ggx-tiles.yaml")


def test_measured_quadrants_match_the_virtual_rigs_model_of_the_same_files(rig, tmp_path):
    """Mitsuba's ``measured`` BSDF, one mesh per quadrant of rgl-quadrants, against the virtual rig's model of
    the same scene (:class:`facetsynth.truth.scene.Scene`, its RGLBRDF port box-filtered over 4 x 4 sub-pixels) under
    three rig lights: relative L1 per quadrant and light at most 0.5 % (measured 0.07-0.48 %; bound 1 %) with
    the camera in the files' incident slot, where Mitsuba puts it (``si.wi``). The virtual rig puts the light
    there (docs/decisions.md, "Argument order"), and is 0.7-22 % off by the files' non-reciprocity (largest:
    golden-yellow vinyl 22 %, satin 21 %, paper 0.7-4.5 %): asserted above 10 %, so the slot is the one."""
    camera = rig.camera(SIZE[0])
    regions = mitsuba_capture.scene_regions(RGL_QUADRANTS)
    plys = [mitsuba_capture.write_plane_mesh(tmp_path / f"{k}.ply", *SIZE, r["frame"], rect=r["rect"])
            for k, r in enumerate(regions["regions"])]
    renderer = mitsuba_capture.Renderer(mitsuba_capture.scene_dict(camera, regions["regions"], plys, regions["markers"],
                                                                   spp=32))
    s = 4
    xy = camera.pixel_plane_points(s)
    points = np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)
    maps = Scene.load(RGL_QUADRANTS).parameters(xy)
    quadrant = maps.region.reshape(camera.height, s, camera.width, s)
    mask = mitsuba_capture.sample_pixels(camera, SIZE, regions["markers"])
    plan = rig.scan()
    worst = {"swapped": 0.0, "rig's slot": 0.0}
    for steps, led in (plan[0], plan[len(plan) // 2], plan[-1]):
        light, intensity = rig.led_position(led, steps), np.array([0.3, 0.25, 0.2])
        image = renderer.render(light, intensity)

        def box(model):   # the pixel's mean over its sub-pixels, as Mitsuba's box filter
            return radiance(points, model, light, intensity, camera.centre).reshape(
                camera.height, s, camera.width, s, 3).mean(axis=(1, 3))

        swapped, rigs = box(lambda wi, wo: maps.rho(wo, wi)), box(maps.rho)
        for k, r in enumerate(regions["regions"]):
            inside = mask & (quadrant == k).all(axis=(1, 3))
            assert inside.sum() > 0.15 * mask.sum()

            def rel_l1(model):
                return np.abs(image[inside] - model[inside]).sum() / model[inside].sum()

            worst = {"swapped": max(worst["swapped"], rel_l1(swapped)),
                     "rig's slot": max(worst["rig's slot"], rel_l1(rigs))}
    assert worst["swapped"] < 0.01, worst
    assert worst["rig's slot"] > 0.10, worst


# --- (c) end to end: import, fit, predict a held-out Mitsuba view ---------------------------------------------

def _workdir(repo: Path, dest: Path, capture: Path) -> Path:
    """A copy of the workflow whose sample sheet imports ``capture`` as sample 'mitsuba'; the fast preset."""
    dest.mkdir(parents=True)
    for part in ("Snakefile", "workflow", "config", "resources", "rig"):
        src = repo / part
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dest / part)
    (dest / "config/samples.tsv").write_text(f"sample\tsource\tpath\trig\nmitsuba\timport\t{capture}\t\n")
    (dest / "fast.yaml").write_text("preset: fast\n")   # rectify.resolution 32 and the fast direction grids
    return dest


@pytest.fixture(scope="module")
def fitted(repo, rig, tmp_path_factory):
    """Mitsuba renders the fitting capture (340 lights) and the held-out view (25 lights); the workflow
    imports the first and fits it; `facetsynth predict` renders the held-out view from the fit."""
    root = tmp_path_factory.mktemp("mitsuba")
    fit = mitsuba_capture.render_capture(rig, COPPER, root / "capture", SIZE, frame="turned", spp=8, seed=3)
    held = mitsuba_capture.render_capture(rig, COPPER, root / "heldout", SIZE, frame="turned", spp=8, seed=3,
                                          view=HELDOUT_VIEW, led_every=4, position_every=4)
    workdir = _workdir(repo, root / "wf", root / "capture")
    done = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "results/mitsuba/svbrdf",
                           "--configfile", "config/config.yaml", "fast.yaml"],
                          cwd=workdir, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert cli.main(["predict", str(workdir / "results/mitsuba/svbrdf"), str(root / "heldout/manifest.json"),
                     str(root / "predicted")]) == 0
    return {"root": root, "fit": fit, "held": held, "workdir": workdir}


def test_a_mitsuba_capture_is_a_valid_foreign_capture(fitted):
    fit, held, root = fitted["fit"], fitted["held"], fitted["root"]
    assert len(fit["frames"]) == 340 and len(held["frames"]) == 25
    for m in (fit, held):
        assert m["saturation"] is None and "truth" not in m                # HDR, never clipped; no ground truth
        assert m["provenance"]["renderer"].startswith("Mitsuba 3") and m["provenance"]["bsdf"] == COPPER
        assert all(f["exposures"] == [{"file": f"frames/{q:04d}.exr", "time": 1.0}] for q, f in enumerate(m["frames"]))
    check_capture(root / "capture")                                       # what `facetsynth check` runs
    cam = manifest.camera(manifest.load(root / "heldout"))
    theta = np.degrees(np.arccos(cam.centre[2] / np.linalg.norm(cam.centre)))
    fit_cam = manifest.camera(manifest.load(root / "capture"))
    dphi = np.degrees(np.arctan2(cam.centre[1], cam.centre[0]) - np.arctan2(fit_cam.centre[1], fit_cam.centre[0]))
    assert theta == pytest.approx(HELDOUT_VIEW[0], abs=1e-6) and dphi == pytest.approx(HELDOUT_VIEW[1], abs=1e-6)
    params = json.loads((fitted["workdir"] / "results/mitsuba/params/metrics.json").read_text())
    assert params["ground_truth"] is False


def test_the_fit_predicts_a_held_out_mitsuba_view(fitted):
    """The issue's figure: relative L2 of the predicted radiance over the held-out view's sample pixels
    (every sub-pixel on the sample, off the markers), all frames pooled. Writes truth | prediction |
    4 x difference of the brightest frame (scaled by its peak, pixels shown 4 x 4) to
    heldout_side_by_side.png beside the captures."""
    from facetsynth.stages.validate import _to_png, side_by_side
    root = fitted["root"]
    held = manifest.load(root / "heldout")
    camera = manifest.camera(held)
    mask = mitsuba_capture.sample_pixels(camera, SIZE, held["provenance"]["markers"])
    truth = np.stack([read_rgb(f["exposures"][0]["file"]) for f in held["frames"]]).astype(float)
    predicted = np.stack([read_rgb(root / f"predicted/frames/{q:04d}.exr")
                          for q in range(len(held["frames"]))]).astype(float)
    t, p = truth[:, mask], predicted[:, mask]
    rel_l2 = float(np.sqrt(((p - t) ** 2).sum() / (t ** 2).sum()))
    q = int(np.argmax(t.sum(axis=(1, 2))))
    _to_png(root / "heldout_side_by_side.png",
            side_by_side(truth[q] * mask[..., None], predicted[q] * mask[..., None], None,
                         float(t[q].max())).repeat(4, axis=0).repeat(4, axis=1))
    print(f"held-out relative L2 {rel_l2:.4f} over {mask.sum()} pixels x {len(truth)} frames; "
          f"image {root / 'heldout_side_by_side.png'}")
    assert mask.sum() > 0.6 * camera.width * camera.height
    assert rel_l2 < MAX_HELDOUT_REL_L2


# --- (d) issue 29: the paper's light density at native resolution, the self-check against Mitsuba ------------

PAPER_480 = Path(__file__).parents[2] / "rig" / "descriptions" / "paper-480.yaml"
# Issue 29's scenes rendered by Mitsuba at the paper's light density (paper-480: 480 lights, the demo camera),
# fitted by the default workflow at native resolution (168 x 168), every 10th light held out:
# - "copper": the turned anisotropic GGX copper (a conductor: its Fresnel is outside eq. 6).
# - "tiles": ggx-tiles' layout (4 x 4 tiles at 16 turns, 11.25 deg apart) of one anisotropic GGX, alpha
#   0.10 x 0.30, with a dielectric Fresnel (roughconductor, eta 1.5, k 0: the dielectric's reflectance) over
#   a Lambertian kd 0.15 (blendbsdf, half each: ks 0.5): the model's own family, rendered by another renderer.
# Measured 2026-12-05, session 41 (relit fitting view / held-out lights / the paper's held-out view):
# copper 0.041 / 0.069 / 0.040 (2026-12-04, before the tables were fitted to the samples: 0.099 / 0.137 / 0.110);
# tiles 0.032 / 0.057 / 0.032 (session 40: 0.049 / 0.074 / 0.049, before refine grouped materials by their
# points' kd and let the samples choose the NDF they share). Session 42 (rectify averages the pixels that see the
# sample alone, refine turns to a fraction of a sector): copper 0.047 / 0.075 / 0.031, tiles 0.036 / 0.057 /
# 0.021 (the held-out views better by a third). The self-check then scored every pixel whose centre is on the
# sample, the pixels across its edge (half background) too; scored as its definition says, on the pixels that see
# the sample alone: copper 0.032 / 0.044 (session 41's fit 0.036 / 0.057), tiles 0.022 / 0.029; the final
# code of session 42 (scenes suite, clean clone): copper 0.030 / 0.040 / 0.029, tiles 0.021 / 0.033 / 0.021 (the
# tiles' held-out lights 0.029 and 0.033 in two runs: threads and k-means vary). The bounds: the larger
# measurement plus about 15 %, and never above the (0.05 / 0.07 / 0.10); docs/accuracy.md.
MITSUBA_TILES_BSDF = {"type": "blendbsdf", "weight": 0.5,
                      "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.30, 0.30, 0.30]}},
                      "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha_u": 0.10, "alpha_v": 0.30,
                                 "eta": 1.5, "k": 0.0}}
# - "rgl-quadrants": resources/scenes/rgl-quadrants.yaml's four measured RGL BRDFs (mc.scene_regions: one mesh
#   per quadrant, Mitsuba's `measured` BSDF; the camera in the files' incident slot, where the virtual rig puts
#   the light: test_measured_quadrants_match_the_virtual_rigs_model_of_the_same_files). Measured 2026-12-05:
#   relit 0.072 / held-out lights 0.120 / paper view 0.130 (theta 50.9 deg) / OTHER_VIEW 0.484 (theta 30 deg,
#   reported, not asserted: the vinyl's highlight predicted broader and about half as high, as on the virtual
#   rig's 0.463, docs/decisions.md "What the measured quadrants can reach"); render 54 s, fit and self-check
#   137 s on 2 cores. The bounds 0.08 / 0.10 / 0.20: relit met (bound 0.08, the issue's: the
#   measurement plus 15 % would pass it), held-out lights NOT met (bound 0.138, the measurement plus 15 %),
#   paper view met (bound 0.15, the measurement plus 15 %). Session 42: 0.070 / 0.103 / 0.127 / 0.484 on the
#   pixels that see the sample alone (0.072 / 0.132 with the pixels across its edge); held-out lights NOT met
#   (0.10), bound 0.118, the measurement plus 15 %. Session 44 (the balanced preset's grid up to 48 rings:
#   the satin's narrow peak takes 48 x 192): 0.052 / 0.087 / 0.115 / 0.480, every bound of the issue met; the
#   bounds are the measurement plus 15 % and never above the issue's: 0.06 / 0.10 / 0.133. Copper keeps 32 x 128
#   (no figure moved); tiles take 40 x 160: 0.021 / 0.029 / 0.021 / 0.019 (session 43: 0.022 / 0.034 / 0.023 /
#   0.023). Session 49 (refine: one turned lobe is one material, its table folded; docs/decisions.md): copper
#   0.026 / 0.030 / 0.025 / 0.030 (0.032 / 0.042 / 0.032 / 0.048 before, drawn in wedges that the old bounds
#   0.037 / 0.051 / 0.036 passed); its bounds are now the measurement plus 15 %: 0.030 / 0.035 / 0.029.
# Every case also renders OTHER_VIEW (config.yaml's theta30, an elevation 23 deg above the fitting camera's
# 53.1 deg; the paper's view is at 50.9 deg), reported (printed, and recorded as a test property), not asserted.
OTHER_VIEW = (30.0, 20.0)
NATIVE = {"copper": (COPPER, "turned", (0.030, 0.035, 0.029)),
          "tiles": (MITSUBA_TILES_BSDF, "tiles", (0.025, 0.038, 0.025)),
          "rgl-quadrants": (mitsuba_capture.scene_regions(RGL_QUADRANTS)["regions"], 0.0, (0.06, 0.10, 0.133))}


@pytest.fixture(scope="module", params=sorted(NATIVE))
def fitted_native(request, repo, tmp_path_factory):
    """Mitsuba renders the scene under paper-480 and two held-out views (30 lights each: the paper's and
    OTHER_VIEW); the default workflow fits it at native resolution and self-checks it; `facetsynth predict`
    renders the held-out views from the fit. Render and fit times are printed."""
    bsdf, frame, bounds = NATIVE[request.param]
    root = tmp_path_factory.mktemp(f"mitsuba480-{request.param}")
    start = time.perf_counter()
    mitsuba_capture.render_capture(PAPER_480, bsdf, root / "capture", SIZE, frame=frame, spp=8, seed=3)
    rendered = time.perf_counter()
    for name, view in (("heldout", HELDOUT_VIEW), ("heldout-other", OTHER_VIEW)):
        mitsuba_capture.render_capture(PAPER_480, bsdf, root / name, SIZE, frame=frame, spp=8, seed=3,
                                       view=view, led_every=4, position_every=4)
    workdir = _workdir(repo, root / "wf", root / "capture")
    fitting = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "results/mitsuba/svbrdf",
                           "results/mitsuba/selfcheck/metrics.json"], cwd=workdir, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    fit_done = time.perf_counter()
    for name in ("heldout", "heldout-other"):
        assert cli.main(["predict", str(workdir / "results/mitsuba/svbrdf"), str(root / name / "manifest.json"),
                         str(root / name.replace("heldout", "predicted"))]) == 0
    print(f"{request.param}: fitting capture rendered in {rendered - start:.0f} s, fitted and self-checked in "
          f"{fit_done - fitting:.0f} s")
    return {"root": root, "workdir": workdir, "name": request.param, "bounds": bounds}


def _heldout_rel_l2(root: Path, name: str) -> float:
    """Relative L2 of `facetsynth predict`'s frames against Mitsuba's held-out frames ``root/name`` over the
    sample pixels (whole footprint on the sample, off the markers), all frames pooled. Writes the brightest
    frame as validate draws the virtual rig's, ``root/{name}.png`` (truth | prediction | 4 x difference): the
    copper's wedges passed every figure until they were looked at (session 48)."""
    held = manifest.load(root / name)
    mask = mitsuba_capture.sample_pixels(manifest.camera(held), SIZE, held["provenance"]["markers"])
    truth = np.stack([read_rgb(f["exposures"][0]["file"]) for f in held["frames"]]).astype(float)
    predicted = np.stack([read_rgb(root / name.replace("heldout", "predicted") / f"frames/{q:04d}.exr")
                          for q in range(len(held["frames"]))]).astype(float)
    q = int(np.argmax(truth[:, mask].sum(axis=(1, 2))))
    _to_png(root / f"{name}.png", side_by_side(truth[q], predicted[q], None, float(truth[q][mask].max())))
    truth, predicted = truth[:, mask], predicted[:, mask]
    return float(np.sqrt(((predicted - truth) ** 2).sum() / (truth ** 2).sum()))


@pytest.mark.scenes
def test_the_native_fit_reproduces_its_own_mitsuba_frames(fitted_native, record_property):
    """Issue 29: the fitting view relit, lights held out of the fit, and views never seen (the paper's, at an
    elevation near the fitting camera's: asserted; OTHER_VIEW: reported), all against Mitsuba's frames; the
    refinement lowers the error on the samples the fit used."""
    relit_bound, lights_bound, view_bound = fitted_native["bounds"]
    selfcheck = json.loads((fitted_native["workdir"] / "results/mitsuba/selfcheck/metrics.json").read_text())
    refine = json.loads((fitted_native["workdir"] / "results/mitsuba/refine/metrics.json").read_text())
    root = fitted_native["root"]
    rel_l2, other = _heldout_rel_l2(root, "heldout"), _heldout_rel_l2(root, "heldout-other")
    record_property("heldout_view_rel_l2", rel_l2)
    record_property("other_elevation_view_rel_l2", other)
    print(f"{fitted_native['name']}: relit {selfcheck['relit']['rel_l2']:.4f}, held-out lights "
          f"{selfcheck['heldout']['rel_l2']:.4f}, held-out view {rel_l2:.4f} (theta {HELDOUT_VIEW[0]}), other "
          f"elevation {other:.4f} (theta {OTHER_VIEW[0]}); refine on the samples "
          f"{refine['fitting_samples_rel_l2_before']:.4f} -> {refine['fitting_samples_rel_l2_after']:.4f}; pictures "
          f"{root / 'heldout.png'}, {root / 'heldout-other.png'}")
    assert np.isfinite(other)
    assert selfcheck["relit"]["frames"] == 54 and selfcheck["heldout"]["frames"] == 48
    assert selfcheck["relit"]["rel_l2"] <= relit_bound
    assert selfcheck["heldout"]["rel_l2"] <= lights_bound
    assert refine["fitting_samples_rel_l2_after"] < 0.5 * refine["fitting_samples_rel_l2_before"]
    assert rel_l2 <= view_bound
