"""A capture on the rig (``source: rig``): the journal, resuming after faults, bad input, ``facetsynth rig``.

The rig here is the controller's firmware built for the host (or the emulator) on a pseudo-terminal, spoken
to through a :class:`FaultProxy` that drops, garbles and unplugs, and the virtual camera, which renders what
the controller reports (``POS?``, ``LED?``). The calibration is the virtual rig's own (nominal) one, so a
frame's recorded light is where the virtual camera put it. An interrupted capture must resume at the next
missing frame and end byte for byte equal to an uninterrupted one: every frame taken exactly once.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
# The conformance suite's backends and the fault proxy: fixtures imported to be used here.
from test_rig_conformance import host_firmware, spawn  # noqa: F401
from test_rig_faults import FaultProxy

from facetsynth.capture import manifest
from facetsynth.app.cli import main
from facetsynth.io.errors import InputError
from facetsynth.io.fileio import write_json
from facetsynth.rig import session
from facetsynth.rig.emulator import PtyServer, VirtualController
from facetsynth.rig.protocol import RigError
from facetsynth.truth.virtual_rig import VirtualRig

ROOT = Path(__file__).resolve().parents[2]
VIRTUAL_RIG = ROOT / "rig/descriptions/virtual-demo.yaml"
SCENE = ROOT / "resources/scenes/demo.yaml"
SCAN = {"positions": 3, "travel_steps": 4000, "use_every": 8}   # 3 carriage positions x 5 LEDs = 15 frames
N_FRAMES = 15


def rig_description(tmp_path: Path, port: str, **changes) -> session.RigDescription:
    """A rig description: the virtual camera of the demo rig, the nominal calibration, ``port``."""
    calibration = tmp_path / "calibration.json"
    if not calibration.exists():
        write_json(calibration, VirtualRig.load(VIRTUAL_RIG).nominal_calibration(sample_width=0.1, seed=3))
    desc = {"name": "test-rig", "controller": {"port": port, "timeout_s": 0.3},
            "camera": {"backend": "virtual", "scene": str(SCENE), "rig": str(VIRTUAL_RIG), "seed": 3, "retries": 1},
            "calibration": str(calibration), "sample": {"width": 0.1, "height": 0.1}, "scan": dict(SCAN),
            "exposure": {"times": [0.01, 0.1, 1.0], "saturation": 1.0},
            "noise": {"read_sigma": 0.001, "shot_gain": 0.0001}}
    for key, value in changes.items():
        desc[key] = value
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(desc))
    return session.RigDescription.load(path)


class CountingCamera:
    """The description's camera, counting each (carriage steps, LED) it saw, failing on request."""

    def __init__(self, rig, driver, taken: Counter, fail_at: set[int] | None = None):
        self.inner = session.open_camera(rig, driver)
        self.driver, self.taken, self.fail_at = driver, taken, fail_at if fail_at is not None else set()

    def describe(self) -> str:
        return self.inner.describe()

    def capture(self, times, folder, stem):
        frame = int(stem)
        if frame in self.fail_at:
            raise RuntimeError(f"camera error at frame {frame} (injected)")
        written = self.inner.capture(times, folder, stem)
        self.taken[(self.driver.position(), self.driver.lit_led())] += 1
        return written

    def truth(self, folder):
        return self.inner.truth(folder)

    def close(self) -> None:
        self.inner.close()


def counting(taken: Counter, fail_at: set[int] | None = None):
    return lambda rig, driver: CountingCamera(rig, driver, taken, fail_at)


def digest(folder: Path) -> dict[str, str]:
    """sha256 of every frame file, by name."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((folder / "frames").iterdir())}


@pytest.fixture
def emulator_port():
    controller = VirtualController(n_leds=40, max_steps=24000, steps_per_mm=80.0)
    with PtyServer(controller) as server:
        yield server.port


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    """The capture taken without a fault, through the emulator."""
    tmp = tmp_path_factory.mktemp("uninterrupted")
    controller = VirtualController(n_leds=40, max_steps=24000, steps_per_mm=80.0)
    with PtyServer(controller) as server:
        session.capture(rig_description(tmp, server.port), tmp / "capture")
    return tmp / "capture"


def test_a_rig_capture_records_the_calibrated_lights_and_what_the_camera_saw(uninterrupted: Path) -> None:
    captured = manifest.load(uninterrupted)
    vrig = VirtualRig.load(VIRTUAL_RIG)
    assert len(captured["frames"]) == N_FRAMES
    plan = session.ScanPlan(**SCAN).frames(40)
    assert [(f["carriage_steps"], f["led"]) for f in captured["frames"]] == plan
    assert plan[:2] == [(0, 0), (0, 8)] and plan[-1] == (4000, 32)
    for frame, (steps, led) in zip(captured["frames"], plan):
        np.testing.assert_allclose(frame["light"]["position"], vrig.led_position(led, steps), atol=1e-12)
        assert [e["time"] for e in frame["exposures"]] == [0.01, 0.1, 1.0]
    # the frames are what the virtual camera renders at the state the controller reported
    from facetsynth.io.fileio import read_rgb
    from facetsynth.truth.virtual_rig import VirtualCamera
    camera = VirtualCamera(SCENE, vrig, seed=3, noise=False)
    steps, led = plan[7]
    longest = read_rgb(uninterrupted / captured["frames"][7]["exposures"][2]["file"])
    expected = camera.render(led, steps)
    unclipped = (expected > 0.01) & (expected < 0.95)
    z = (longest - expected)[unclipped] / np.sqrt(0.001**2 + 0.0001 * expected[unclipped])   # the sensor's sigma
    assert unclipped.sum() > 10000
    assert abs(z.mean()) < 0.03 and 0.95 < z.std() < 1.1     # LED or position one off: |mean z| > 10
    assert captured["truth"]["scene"] == str(uninterrupted / "truth/scene.yaml")
    assert (uninterrupted / "journal.jsonl").is_file()        # the record of the capture stays with it


def test_faults_through_the_firmware_resume_to_the_uninterrupted_capture(
        tmp_path: Path, spawn, uninterrupted: Path) -> None:  # noqa: F811
    """The issue's end-to-end case, on the firmware's host build: a garbled and a lost reply (retried by the
    driver), a USB disconnect that outlasts the driver's reconnection and a power cycle of the controller
    (the capture stops), and a camera error that outlasts the retries (it stops again). Two resumes finish
    it: no frame lost, none taken twice, every file equal to the uninterrupted capture's."""
    backend = spawn("firmware")
    proxy = FaultProxy(backend.port, tmp_path / "ttyRIG")
    try:
        rig = rig_description(tmp_path, str(proxy.path))
        out = tmp_path / "capture"
        taken: Counter = Counter()
        proxy.inject("reply", "OK POS 2000", "garble")                    # a move's reply, retried
        proxy.inject("reply", "OK LED 16", "drop")                          # an LED's reply, retried
        proxy.inject("cmd", "LED 24", "disconnect", gap=4.0, reset=backend.power_cycle)  # frame 3: beyond 5 x 0.5 s
        with pytest.raises(RigError, match="ttyRIG"):
            session.capture(rig, out, camera_factory=counting(taken))
        assert not out.exists() and (tmp_path / ".capture.partial/journal.jsonl").is_file()
        assert sum(taken.values()) == 3
        while not proxy.path.resolve().exists() or "unplugged" in str(proxy.path.resolve()):
            time.sleep(0.1)                                                 # the adapter comes back
        with pytest.raises(RuntimeError, match="camera error at frame 9"):
            session.capture(rig, out, camera_factory=counting(taken, fail_at={9}))
        assert sum(taken.values()) == 9
        captured = session.capture(rig, out, camera_factory=counting(taken))
        assert sorted(taken.values()) == [1] * N_FRAMES                     # each frame once, none lost
        assert any(line.startswith("x ") for line in proxy.lines("reply")) and proxy.disconnects == 1
    finally:
        proxy.close()
    assert digest(out) == digest(uninterrupted)
    reference = json.loads((uninterrupted / "manifest.json").read_text())
    assert captured["frames"] == reference["frames"]
    assert json.loads((out / "manifest.json").read_text())["camera"] == reference["camera"]


def test_ctrl_c_keeps_the_saved_frames(tmp_path: Path, emulator_port: str) -> None:
    rig = rig_description(tmp_path, emulator_port)
    taken: Counter = Counter()

    class Interrupting(CountingCamera):
        def capture(self, times, folder, stem):
            if stem == "0005" and not interrupted.is_set():
                interrupted.set()
                raise KeyboardInterrupt
            return super().capture(times, folder, stem)

    interrupted = threading.Event()
    with pytest.raises(KeyboardInterrupt):
        session.capture(rig, tmp_path / "capture", camera_factory=lambda r, d: Interrupting(r, d, taken))
    assert sum(taken.values()) == 5
    session.capture(rig, tmp_path / "capture", camera_factory=lambda r, d: Interrupting(r, d, taken))
    assert sorted(taken.values()) == [1] * N_FRAMES


def test_a_torn_journal_line_or_a_lost_file_retakes_only_that_frame(tmp_path: Path, emulator_port: str) -> None:
    rig = rig_description(tmp_path, emulator_port)
    taken: Counter = Counter()
    with pytest.raises(RuntimeError):
        session.capture(rig, tmp_path / "capture", camera_factory=counting(taken, fail_at={6}))
    staging = tmp_path / ".capture.partial"
    journal = staging / "journal.jsonl"
    lines = journal.read_text().splitlines()
    assert len(lines) == 6
    journal.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])   # a power cut mid-append
    (staging / "frames/0002_e1.exr").unlink()                                           # a file lost
    assert sorted(session.Journal(staging).saved()) == [0, 1, 3, 4]
    session.capture(rig, tmp_path / "capture", camera_factory=counting(taken))
    assert sum(taken.values()) == 6 + (N_FRAMES - 4)            # frames 2 and 5 taken again, nothing else
    plan = session.ScanPlan(**SCAN).frames(40)
    assert taken[plan[2]] == 2 and taken[plan[5]] == 2 and taken[plan[0]] == 1


def test_another_scan_starts_afresh_a_new_port_resumes(tmp_path: Path, emulator_port: str) -> None:
    taken: Counter = Counter()
    rig = rig_description(tmp_path, emulator_port)
    with pytest.raises(RuntimeError):
        session.capture(rig, tmp_path / "capture", camera_factory=counting(taken, fail_at={4}))
    moved = rig_description(tmp_path, emulator_port, controller={"port": emulator_port, "timeout_s": 0.5})
    assert moved.frames_key() == rig.frames_key()
    other = rig_description(tmp_path, emulator_port, scan={**SCAN, "use_every": 20})
    taken.clear()
    session.capture(other, tmp_path / "capture", camera_factory=counting(taken))
    assert sum(taken.values()) == 3 * 2                         # the other scan's frames, all taken


def test_bad_input_is_named(tmp_path: Path, emulator_port: str) -> None:
    with pytest.raises(InputError, match=r"rig\.yaml: invalid rig description at 'scan'"):
        rig_description(tmp_path, emulator_port, scan={"positions": 3})
    rig = rig_description(tmp_path, emulator_port, scan={**SCAN, "travel_steps": 30000})
    with pytest.raises(InputError, match="travel_steps 30000 is beyond the controller's travel .24000 steps"):
        session.capture(rig, tmp_path / "capture")
    calibration = json.loads(Path(rig.calibration).read_text())
    calibration["leds"] = {k: v[:20] if isinstance(v, list) and k != "step" else v
                           for k, v in calibration["leds"].items()}
    calibration["leds"]["count"] = 20
    write_json(rig.calibration, calibration)
    rig = rig_description(tmp_path, emulator_port)
    with pytest.raises(InputError, match="calibrates 20 LEDs, the controller has 40"):
        session.capture(rig, tmp_path / "capture")
    rig = rig_description(tmp_path, str(tmp_path / "no-such-port"))
    with pytest.raises(RigError, match="no-such-port"):
        session.capture(rig, tmp_path / "capture")


def test_rig_check_and_capture_commands(tmp_path: Path, emulator_port: str, capsys) -> None:
    rig = rig_description(tmp_path, emulator_port)
    assert main(["rig", "check", str(rig.path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("controller: firmware ") and "40 LEDs" in out[0]
    assert out[1] == "carriage: homed, moved to 200 steps and back, positions verified"
    assert out[2] == "LEDs: each of the 40 lit in turn and confirmed, all off"
    assert out[3].startswith("camera: virtual camera 240x160")
    assert main(["rig", "capture", str(rig.path), str(tmp_path / "quick")]) == 0
    assert f"{N_FRAMES} frames of 3 exposure(s)" in capsys.readouterr().out
    assert main(["rig", "check", str(rig.path), "--port", str(tmp_path / "absent")]) == 1
    assert "facetsynth rig: error:" in capsys.readouterr().err
