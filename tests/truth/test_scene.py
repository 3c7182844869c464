"""Ground-truth scenes: every shipped scene loads; regions, frames and markers are where they should be."""

import numpy as np
import pytest

from facetsynth.io.errors import InputError
from facetsynth.truth.scene import Scene

SCENES = ["demo", "wallpaper", "satin", "brushed", "card"]


@pytest.mark.parametrize("name", SCENES)
def test_shipped_scenes_load_and_cover_the_sample(repo, name):
    scene = Scene.load(repo / f"resources/scenes/{name}.yaml")
    xy = np.stack(np.meshgrid(np.linspace(-0.049, 0.049, 50), np.linspace(-0.049, 0.049, 50)), -1)
    maps = scene.parameters(xy)
    on_material = ~scene.marker_mask(xy)
    assert np.all(maps.region[on_material] >= 0)
    assert np.all(maps.ks[~on_material] == 0) and np.all(maps.kd[~on_material] == 0)
    assert len(scene.marker_positions) == 4


def test_wallpaper_frames_rotate_continuously_and_brushed_is_constant(repo):
    wall = Scene.load(repo / "resources/scenes/wallpaper.yaml")
    xy = np.column_stack([np.linspace(-0.045, 0.045, 200), np.full(200, 0.03)])
    phi = np.unwrap(2 * wall.parameters(xy).phi_frame) / 2    # frame axes are defined modulo pi
    spread = np.degrees(phi.max() - phi.min())
    assert spread > 40                                          # turns through a wide range of azimuths
    brushed = Scene.load(repo / "resources/scenes/brushed.yaml").parameters(xy)
    assert np.allclose(brushed.phi_frame, np.radians(30))


def test_satin_has_two_thread_directions_at_different_brightness(repo):
    maps = Scene.load(repo / "resources/scenes/satin.yaml").parameters(np.array([[0.005, 0.005], [0.015, 0.005]]))
    assert set(np.degrees(maps.phi_frame).round()) == {0.0, 90.0}
    assert maps.ks[0].sum() != maps.ks[1].sum()


def test_invalid_scene_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nsize: [0.1, 0.1]\nregions:\n  - {name: a, where: {all: true}, kd: [0,0,0], "
                   "ks: [0,0,0], eta: 0.5, alpha: [0.1, 0.1], frame: {angle_deg: 0}}\n")
    with pytest.raises(InputError, match=r"bad\.yaml: invalid scene at 'regions/0/eta'"):
        Scene.load(bad)


def test_a_turned_sample_shows_each_point_turned_with_its_frame(repo):
    """rotation_deg turns the whole sample on the rig (a turntable): the point at R(psi) xy shows what xy
    showed unturned, with its frame azimuth + psi; markers and the sample's outline turn with it."""
    import yaml
    d = yaml.safe_load((repo / "resources/scenes/demo.yaml").read_text())
    flat = Scene.from_dict(d)
    turned = Scene.from_dict({**d, "rotation_deg": 60.0})
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.035, 0.035, (500, 2))
    psi = np.radians(60.0)
    rot = np.array([[np.cos(psi), -np.sin(psi)], [np.sin(psi), np.cos(psi)]])
    a, b = flat.parameters(xy), turned.parameters(xy @ rot.T)
    np.testing.assert_array_equal(a.region, b.region)
    np.testing.assert_allclose(b.kd, a.kd)
    on = a.region >= 0
    np.testing.assert_allclose(np.angle(np.exp(1j * (b.phi_frame[on] - a.phi_frame[on] - psi))), 0.0, atol=1e-9)
    np.testing.assert_allclose(turned.marker_positions, flat.marker_positions @ rot.T, atol=1e-12)
    corner = np.array([[0.049, 0.049]])
    assert flat.on_sample(corner).all() and not turned.on_sample(corner).all()   # the corner turned away
