"""Directional lights and orthographic cameras (issue 35): homogeneous points through the pixel model, the
manifest's checks, the plane of the lights at infinity, and separate's shading-normal decisions."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from facetsynth import manifest as manifest_io
from facetsynth.camera import Camera
from facetsynth.errors import InputError
from facetsynth.lightplane import LightTriangulation, light_plane
from facetsynth.render import light_geometry, radiance, towards
from facetsynth.stages.separate import FLAT_TILT_P95_DEG, relief_normals


def top_down(width=40, height=30, metres=0.04) -> Camera:
    s = width / metres
    K = np.array([[s, 0, (width - 1) / 2], [0, s, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(width, height, K, np.diag([1.0, -1.0, -1.0]), np.array([0, 0, 1.0]), projection="orthographic")


def test_directional_light_geometry_is_the_same_at_every_point():
    """(d, 0): i = d/|d| everywhere and |P - x|^2 = 1 (the light's intensity is irradiance); (P, 1) as before."""
    points = np.array([[0.0, 0, 0], [0.03, -0.02, 0], [-0.05, 0.04, 0]])
    d = np.array([1.0, 2.0, 2.0])
    wi, r2 = light_geometry(points, np.append(d, 0.0))
    np.testing.assert_allclose(wi, np.broadcast_to(d / 3.0, (3, 3)))
    np.testing.assert_array_equal(r2, 1.0)
    P = np.array([0.1, 0.2, 0.5])
    wi_p, r2_p = light_geometry(points, np.append(P, 1.0))
    wi_3, r2_3 = light_geometry(points, P)                       # a position (3,) is a point light
    np.testing.assert_array_equal(wi_p, wi_3)
    np.testing.assert_array_equal(r2_p, r2_3)
    np.testing.assert_allclose(r2_p, np.sum((P - points) ** 2, axis=1))


def test_radiance_under_a_directional_light_and_an_orthographic_camera():
    """I = rho (n . i) E, the same at every point of a uniform Lambertian plane; o is the camera's direction."""
    cam = top_down()
    points = np.array([[0.0, 0, 0], [0.01, 0.01, 0]])
    np.testing.assert_allclose(towards(points, cam.view_point), [[0, 0, 1], [0, 0, 1]], atol=1e-15)
    light = np.array([0.0, 0.6, 0.8, 0.0])
    value = radiance(points, lambda wi, wo: np.full(wi.shape[:-1] + (3,), 0.5 / np.pi), light, np.ones(3),
                     cam.view_point)
    np.testing.assert_allclose(value, 0.5 / np.pi * 0.8)


def test_orthographic_camera_maps_the_plane_affinely():
    """col = s x + cx, row = -s y + cy (image up = world +y); the plane homography is the same affine map."""
    cam = top_down(40, 30, 0.04)
    xy = np.array([[0.0, 0.0, 0.0], [0.01, 0.005, 0.0], [-0.02, -0.01, 0.0]])
    cols_rows = cam.project(xy)
    np.testing.assert_allclose(cols_rows, [[19.5, 14.5], [29.5, 9.5], [-0.5, 24.5]])
    H = cam.plane_homography()
    mapped = np.c_[xy[:, :2], np.ones(3)] @ H.T
    np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], cols_rows)
    np.testing.assert_allclose(cam.view_point, [0, 0, 1, 0])
    with pytest.raises(ValueError, match="no centre"):
        cam.centre


def _dome_manifest() -> dict:
    cam = top_down()
    return {"version": 1, "units": "m", "sample": {"width": 0.04, "height": 0.03},
            "camera": {"projection": "orthographic", "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
                       "R": cam.R.tolist(), "t": cam.t.tolist()},
            "saturation": None,
            "frames": [{"light": {"direction": [np.cos(a), np.sin(a), 1.0], "intensity": [1, 1, 1]},
                        "exposures": [{"file": f"f{q}.exr", "time": 1.0}]}
                       for q, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))]}


def test_manifest_accepts_directional_lights_and_orthographic_cameras():
    m = _dome_manifest()
    manifest_io.validate(m, "dome.json")
    lights = manifest_io.lights(m["frames"])
    assert lights.shape == (6, 4) and np.all(lights[:, 3] == 0)
    np.testing.assert_allclose(np.linalg.norm(lights[:, :3], axis=1), 1.0)
    assert manifest_io.camera(m).orthographic


@pytest.mark.parametrize("change, where", [
    (lambda m: m["frames"][2]["light"].update(direction=[1.0, 0.0, 0.0]), "frames/2/light/direction/2"),
    (lambda m: m["frames"][1]["light"].update(position=[0, 0, 1.0]), "frames/1/light"),       # both: not oneOf
    (lambda m: m["camera"].update(R=np.eye(3).tolist()), "camera/R"),                        # looks up
])
def test_manifest_refuses_bad_directional_captures_naming_the_key(change, where):
    m = copy.deepcopy(_dome_manifest())
    change(m)
    with pytest.raises(InputError, match="dome.json") as info:
        manifest_io.validate(m, "dome.json")
    assert where in str(info.value)


def test_lights_at_infinity_are_one_triangulation_for_every_point():
    """Directional lights sit at d / d_z on the plane z = 1 seen from the origin: a direction's interpolation
    weights do not depend on the point, and a mix of light kinds is refused."""
    rng = np.random.default_rng(0)
    az, el = rng.uniform(0, 2 * np.pi, 30), rng.uniform(0.3, 1.3, 30)
    d = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    lights = np.c_[d, np.zeros(30)]
    positions, at_infinity = light_plane(lights)
    assert at_infinity
    np.testing.assert_allclose(positions, d / d[:, 2:])
    tri = LightTriangulation.from_lights(lights)
    values = rng.uniform(size=(1, 30))
    query = np.array([[0.1, 0.2, 0.97]]) / np.linalg.norm([0.1, 0.2, 0.97])
    here, _ = tri.interpolate(values, np.ones((1, 30), bool), np.zeros((1, 3)), query)
    there, _ = tri.interpolate(values, np.ones((1, 30), bool), np.array([[0.05, -0.04, 0.0]]), query)
    np.testing.assert_array_equal(here, there)
    with pytest.raises(ValueError, match="mixes point lights and directional"):
        light_plane(np.r_[lights[:3], [[0, 0, 1.0, 1.0]]])


def _tilted(tilt_deg: np.ndarray, azimuth: float = 0.3) -> np.ndarray:
    t = np.radians(tilt_deg)
    return np.c_[np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), np.cos(t)]


def test_relief_normals_remove_a_common_tilt_and_keep_a_relief():
    """A relief whose estimate carries a 2 deg bias everywhere (a lobe's shoulder): the bias goes, the relief stays."""
    rng = np.random.default_rng(1)
    slopes = rng.normal(0, np.tan(np.radians(12)), size=(4000, 2))
    slopes -= np.median(slopes, axis=0)
    bias = np.tan(np.radians(2.0)) * np.array([0.6, 0.8])
    n = np.c_[-(slopes + bias), np.ones(4000)]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out, what = relief_normals(n, np.ones(4000, bool))
    truth = np.c_[-slopes, np.ones(4000)]
    truth /= np.linalg.norm(truth, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(out * truth, axis=1), -1, 1)))
    assert what.startswith("relief") and "common tilt 2.00 deg removed" in what
    assert angle.max() < 1e-4                                  # arccos near 1: ~1e-6 deg of rounding


def test_relief_normals_of_a_flat_sample_are_exactly_flat():
    """Estimation noise and a common bias below FLAT_TILT_P95_DEG: +z everywhere, bit for bit; points that are
    not trusted (too little diffuse) are +z whatever they were."""
    rng = np.random.default_rng(2)
    n = _tilted(np.abs(rng.normal(0, 0.7, 3000)) + 1.5, azimuth=1.0)
    trusted = np.ones(3000, bool)
    trusted[:100] = False
    n[:100] = _tilted(np.full(100, 40.0))                       # a metal's noise
    out, what = relief_normals(n, trusted)
    assert what.startswith("flat") and f"< {FLAT_TILT_P95_DEG:g}" in what
    np.testing.assert_array_equal(out, np.tile([0.0, 0.0, 1.0], (3000, 1)))
