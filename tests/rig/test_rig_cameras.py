"""Camera backends of the real rig (issue 16 item 3): gphoto2 against libgphoto2's own virtual camera and at
the python-gphoto2 API boundary, RAW decoding of a synthetic DNG, and the watch-folder backend."""

import json
import os
import struct
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from facetsynth.io.fileio import read_exr
from facetsynth.rig.cameras import (CameraBackend, CameraError, Gphoto2Camera, WatchFolderCamera, WatchSettings,
                                    decode_raw, nearest_choice, open_camera, parse_shutter_speed)

gp = pytest.importorskip("gphoto2")


# --- shutter speeds ------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, seconds", [("1/100", 0.01), ("1/100s", 0.01), ("0.0100s", 0.01), ("1", 1.0),
                                           ('30"', 30.0), ('2.5"', 2.5), ('1"3', 1.3), ("30s", 30.0),
                                           ("1/4000", 0.00025), ("0,5", 0.5), ("bulb", None), ("auto", None),
                                           ("x 1/200", None), ("0", None)])
def test_shutter_speed_choices_parse_to_seconds(text, seconds):
    assert parse_shutter_speed(text) == (pytest.approx(seconds) if seconds else None)


def test_nearest_choice_is_nearest_in_stops():
    choices = ["bulb", "1.0000s", "0.1000s", "0.0500s", "0.0200s", "0.0100s"]
    assert nearest_choice(choices, 1 / 30) == ("0.0500s", 0.05)     # 0.58 stops from 0.05, 0.74 from 0.02
    assert nearest_choice(choices, 0.3) == ("0.1000s", 0.1)         # 1.58 stops below, 1.74 above
    assert nearest_choice(choices, 5.0) == ("1.0000s", 1.0)
    with pytest.raises(ValueError, match="no shutter speed"):
        nearest_choice(["bulb", "auto"], 0.1)


# --- libgphoto2's virtual camera (vusb + ptp2), in a subprocess ------------------------------------------

VCAM_SCRIPT = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    from facetsynth.rig.cameras import Gphoto2Camera
    cam = Gphoto2Camera(event_timeout_ms=20)
    config = cam._camera.get_config()
    read_back = []
    for t in [0.01, 1 / 30, 0.3, 2.0]:
        actual = cam.set_exposure(t)
        read_back.append([actual, cam._camera.get_config().get_child_by_name("shutterspeed").get_value()])
    exposures = cam.capture([0.01, 1 / 30, 0.3, 2.0], Path(sys.argv[1]), "0007")
    print(json.dumps({"describe": cam.describe(), "choices": cam.shutter_choices(), "read_back": read_back,
                      "exposures": exposures}))
    cam.close()
""")


def virtual_camera_env(images: Path) -> dict:
    """Environment that makes libgphoto2 see its virtual USB camera serving ``images`` (set before the
    process imports gphoto2: libgphoto2 reads IOLIBS when it loads its port drivers)."""
    vusb = Path(gp.__file__).parent / "libgphoto2" / "vusb"
    if not (vusb / "vusb.so").is_file():
        pytest.skip("this python-gphoto2 wheel has no virtual USB driver (libgphoto2/vusb/vusb.so)")
    return {**os.environ, "IOLIBS": str(vusb), "VCAMERADIR": str(images)}


def test_gphoto2_backend_brackets_libgphoto2s_virtual_camera(tmp_path):
    """The real python-gphoto2 / libgphoto2 PTP stack, against libgphoto2's virtual camera (vcamera.c):
    shutter speeds set to the nearest choice and read back, one file per exposure under its final name,
    nothing else left in the folder. The virtual camera answers every capture with a copy of the first
    ``*.jpg`` it finds in VCAMERADIR (an empty or PNG-only folder: capture fails, "[-1] Unspecified
    error"), so its pixels do not depend on the exposure: here the files are byte for byte the source."""
    images, out = tmp_path / "vcamera", tmp_path / "frames"
    images.mkdir(), out.mkdir()
    ramp = np.tile(np.arange(0, 256, 4, dtype=np.uint8)[None, :, None], (16, 1, 3))
    assert cv2.imwrite(str(images / "source.jpg"), ramp)
    run = subprocess.run([sys.executable, "-c", VCAM_SCRIPT, str(out)], env=virtual_camera_env(images),
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["describe"].startswith("gphoto2: ") and "usb:" in result["describe"]
    assert result["choices"][:3] == ["1.0000s", "0.1000s", "0.0500s"]
    assert result["read_back"] == [[0.01, "0.0100s"], [0.05, "0.0500s"], [0.1, "0.1000s"], [1.0, "1.0000s"]]
    assert result["exposures"] == [{"file": f"0007_e{k}.jpg", "time": t} for k, t in enumerate([0.01, 0.05, 0.1, 1.0])]
    assert sorted(os.listdir(out)) == [f"0007_e{k}.jpg" for k in range(4)]      # no temporaries left
    source = (images / "source.jpg").read_bytes()
    assert all((out / f"0007_e{k}.jpg").read_bytes() == source for k in range(4))


def test_gphoto2_backend_reports_a_capture_failure_of_the_virtual_camera(tmp_path):
    """No JPEG for the virtual camera to serve: the capture fails; one line naming the camera, no file."""
    images, out = tmp_path / "vcamera", tmp_path / "frames"
    images.mkdir(), out.mkdir()
    assert cv2.imwrite(str(images / "only.png"), np.zeros((4, 4, 3), np.uint8))
    script = ("import sys\nfrom pathlib import Path\nfrom facetsynth.rig.cameras import Gphoto2Camera, CameraError\n"
              "cam = Gphoto2Camera(event_timeout_ms=20)\n"
              "try:\n    cam.capture([0.01], Path(sys.argv[1]), '0000')\n"
              "except CameraError as exc:\n    print('ERROR', exc)\n")
    run = subprocess.run([sys.executable, "-c", script, str(out)], env=virtual_camera_env(images),
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    line = run.stdout.strip().splitlines()[-1]
    assert line.startswith("ERROR gphoto2: ") and "capture failed" in line and "\n" not in line
    assert os.listdir(out) == []


# --- RAW decoding of a synthetic DNG ---------------------------------------------------------------------

def write_dng(path, cfa, white=4095, black=0, neutral=(1.0, 1.0, 1.0)):
    """A minimal uncompressed DNG 1.4 (RGGB Bayer mosaic, 16-bit little-endian, one strip) LibRaw opens."""
    cfa = np.ascontiguousarray(cfa, "<u2")
    h, w = cfa.shape

    def rational(xs):
        return [v for x in xs for v in (int(round(x * 10000)), 10000)]

    model = b"facetsynth synthetic\0"
    tags = [(254, 4, [0]), (256, 4, [w]), (257, 4, [h]), (258, 3, [16]), (259, 3, [1]), (262, 3, [32803]),
            (271, 2, b"facetsynth\0"), (272, 2, model), (273, 4, [0]), (277, 3, [1]), (278, 4, [h]),
            (279, 4, [cfa.nbytes]), (284, 3, [1]), (33421, 3, [2, 2]), (33422, 1, [0, 1, 1, 2]),
            (50706, 1, [1, 4, 0, 0]), (50708, 2, model), (50714, 4, [black]), (50717, 4, [white]),
            (50721, 10, rational([1, 0, 0, 0, 1, 0, 0, 0, 1])), (50728, 5, rational(neutral)), (50778, 3, [21])]
    formats = {1: "B", 3: "H", 4: "I", 5: "I", 10: "i"}
    data_at = 8 + 2 + 12 * len(tags) + 4
    entries, blobs = [], b""
    for code, typ, values in tags:
        payload = values if typ == 2 else struct.pack("<" + formats[typ] * len(values), *values)
        count = len(values) // 2 if typ in (5, 10) else len(values)
        if len(payload) <= 4:
            entries.append((code, typ, count, payload.ljust(4, b"\0")))
        else:
            entries.append((code, typ, count, struct.pack("<I", data_at + len(blobs))))
            blobs += payload + b"\0" * (len(payload) % 2)
    pixels_at = data_at + len(blobs)
    ifd = struct.pack("<H", len(tags)) + b"".join(
        struct.pack("<HHI", code, typ, count) + (struct.pack("<I", pixels_at) if code == 273 else value)
        for code, typ, count, value in entries) + struct.pack("<I", 0)
    Path(path).write_bytes(b"II*\0" + struct.pack("<I", 8) + ifd + blobs + cfa.tobytes())


def test_decode_raw_is_linear_in_the_sensor_values_scaled_by_the_white_level(tmp_path):
    """Uniform patches of a synthetic DNG: (raw - black) / (white - black), no gamma, no auto-brightening, and
    the white level is the file's even when the image's maximum is near it (LibRaw's adjust_maximum off)."""
    cfa = np.full((32, 64), 256, np.uint16)
    for k, level in enumerate([400, 1000, 2000, 4000]):
        cfa[:, 16 * k:16 * (k + 1)] = level
    write_dng(tmp_path / "a.dng", cfa, white=4095, black=256)
    rgb = decode_raw(tmp_path / "a.dng")
    assert rgb.shape == (32, 64, 3) and rgb.dtype == np.float32
    centres = np.array([rgb[12:20, 16 * k + 5:16 * k + 11].mean(axis=(0, 1)) for k in range(4)])
    expected = (np.array([400, 1000, 2000, 4000]) - 256) / (4095 - 256)
    np.testing.assert_allclose(centres, np.repeat(expected[:, None], 3, axis=1), rtol=2e-3, atol=2e-5)


def test_decode_raw_applies_only_the_cameras_white_balance_multipliers_and_clips_at_1(tmp_path):
    """AsShotNeutral (0.5, 1, 0.8): red x2, blue x1.25 (multipliers normalised to green); a channel pushed past
    the white level by its multiplier clips at exactly 1; no colour matrix mixes the channels."""
    cfa = np.full((32, 32), 1000, np.uint16)
    cfa[:, 16:] = 3500
    write_dng(tmp_path / "wb.dng", cfa, white=4095, neutral=(0.5, 1.0, 0.8))
    rgb = decode_raw(tmp_path / "wb.dng")
    low, high = rgb[12:20, 4:12].mean(axis=(0, 1)), rgb[12:20, 20:28].mean(axis=(0, 1))
    np.testing.assert_allclose(low, 1000 / 4095 * np.array([2.0, 1.0, 1.25]), rtol=3e-3)
    np.testing.assert_allclose(high, [1.0, 3500 / 4095, 1.0], rtol=3e-3)     # 2 x 3500 and 1.25 x 3500 clip


def test_decode_raw_refuses_a_file_that_is_not_raw(tmp_path):
    (tmp_path / "IMG_0001.CR2").write_bytes(b"not a raw file" * 10)
    with pytest.raises(CameraError, match=r"IMG_0001.CR2: not a RAW file LibRaw can decode"):
        decode_raw(tmp_path / "IMG_0001.CR2")


# --- the python-gphoto2 API boundary, with a fake camera (the RAW path) ------------------------------------

class FakeWidget:
    def __init__(self, choices, value):
        self.choices, self.value = choices, value

    def count_choices(self):
        return len(self.choices)

    def get_choice(self, i):
        return self.choices[i]

    def get_value(self):
        return self.value

    def set_value(self, value):
        assert value in self.choices
        self.value = value


class FakeCamera:
    """What Gphoto2Camera calls on a gphoto2.Camera: a RAW+JPEG camera whose RAW arrives as an event, and
    whose sensor value is min(white, 40000 t) (a DNG made per shot at the shutter speed set)."""

    def __init__(self, tmp_path, raw_bytes=None):
        self.widget = FakeWidget(["bulb", "30", "1", "1/4", "1/15", "1/60", "1/250"], "1/60")
        self.files, self.deleted, self.events, self.set_values, self.shots = {}, [], [], [], 0
        self.tmp_path, self.raw_bytes = tmp_path, raw_bytes

    def get_abilities(self):
        return SimpleNamespace(model="Fake EOS 80D")

    def get_port_info(self):
        return SimpleNamespace(get_path=lambda: "usb:009,001")

    def get_config(self):
        return SimpleNamespace(get_child_by_name=self._child)

    def _child(self, name):
        if name != "shutterspeed":
            raise gp.GPhoto2Error(gp.GP_ERROR_BAD_PARAMETERS)
        return self.widget

    def set_config(self, cfg):
        self.set_values.append(self.widget.value)

    def capture(self, kind):
        assert kind == gp.GP_CAPTURE_IMAGE
        self.shots += 1
        seconds = parse_shutter_speed(self.widget.value)
        dng = self.tmp_path / f"shot{self.shots}.dng"
        write_dng(dng, np.full((32, 32), min(4095, int(round(40000 * seconds))), np.uint16))
        jpg, raw = ("/DCIM", f"IMG_{self.shots:04d}.JPG"), ("/DCIM", f"IMG_{self.shots:04d}.DNG")
        self.files[jpg], self.files[raw] = b"\xff\xd8jpeg", self.raw_bytes or dng.read_bytes()
        self.events = [(gp.GP_EVENT_FILE_ADDED, SimpleNamespace(folder=raw[0], name=raw[1])),
                       (gp.GP_EVENT_CAPTURE_COMPLETE, None)]
        return SimpleNamespace(folder=jpg[0], name=jpg[1])

    def wait_for_event(self, timeout_ms):
        return self.events.pop(0) if self.events else (gp.GP_EVENT_TIMEOUT, None)

    def file_get(self, folder, name, kind):
        data = self.files[(folder, name)]
        return SimpleNamespace(get_data_and_size=lambda: data)

    def file_delete(self, folder, name):
        self.deleted.append(name)

    def exit(self):
        pass


def test_gphoto2_backend_keeps_the_raw_of_raw_plus_jpeg_as_linear_exr(tmp_path):
    fake = FakeCamera(tmp_path)
    camera = Gphoto2Camera(camera=fake)
    assert isinstance(camera, CameraBackend) and camera.describe() == "gphoto2: Fake EOS 80D (usb:009,001)"
    out = tmp_path / "frames"
    out.mkdir()
    exposures = camera.capture([1 / 250, 1 / 60, 0.05], out, "0012")
    assert exposures == [{"file": "0012_e0.exr", "time": 1 / 250}, {"file": "0012_e1.exr", "time": 1 / 60},
                         {"file": "0012_e2.exr", "time": 1 / 15}]
    assert fake.set_values == ["1/250", "1/60", "1/15"]      # the nearest choices, each set once
    assert sorted(os.listdir(out)) == ["0012_e0.exr", "0012_e1.exr", "0012_e2.exr"]
    assert fake.deleted == [f"IMG_{n:04d}.{ext}" for n in (1, 2, 3) for ext in ("JPG", "DNG")]
    for e in exposures:
        channels, header = read_exr(out / e["file"])
        assert header["exposure_time"] == pytest.approx(e["time"])
        expected = min(4095, round(40000 * e["time"])) / 4095          # value = t I up to the white level
        np.testing.assert_allclose(channels["RGB"][8:24, 8:24], expected, rtol=2e-3)


def test_gphoto2_backend_leaves_no_file_when_the_raw_is_corrupt(tmp_path):
    camera = Gphoto2Camera(camera=FakeCamera(tmp_path, raw_bytes=b"garbage" * 100))
    out = tmp_path / "frames"
    out.mkdir()
    with pytest.raises(CameraError, match=r"^gphoto2: Fake EOS 80D \(usb:009,001\): IMG_0001.DNG: .*not a RAW file"):
        camera.capture([0.01], out, "0000")
    assert os.listdir(out) == []


def test_gphoto2_backend_without_a_shutter_speed_setting_says_so(tmp_path):
    camera = Gphoto2Camera(camera=FakeCamera(tmp_path), config="exposuretime")
    with pytest.raises(CameraError, match=r"no 'exposuretime' config \(is the camera in manual mode"):
        camera.capture([0.01], tmp_path, "0000")


# --- watch folder ---------------------------------------------------------------------------------------

def write_slowly(path: Path, data: bytes, chunks: int = 3, pause: float = 0.08):
    with open(path, "wb") as f:
        for k in range(chunks):
            f.write(data[k * len(data) // chunks:(k + 1) * len(data) // chunks])
            f.flush()
            time.sleep(pause)


def encoded(ext, image):
    ok, buf = cv2.imencode(ext, image)
    assert ok
    return buf.tobytes()


def write_oiio(path: Path, pixels: np.ndarray, **attributes):
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2],
                          oiio.FLOAT if pixels.dtype == np.float32 else oiio.UINT8)
    for key, value in attributes.items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()


def test_watch_folder_takes_each_new_file_once_complete(tmp_path):
    """A thread plays the camera's software: files appear late, are written in slow chunks, an EXR through
    a hidden temporary; a file there before the backend opened and hidden files are ignored."""
    watch, out = tmp_path / "incoming", tmp_path / "frames"
    watch.mkdir(), out.mkdir()
    (watch / "old.jpg").write_bytes(encoded(".jpg", np.zeros((4, 4, 3), np.uint8)))
    jpeg = encoded(".jpg", np.full((6, 8, 3), 120, np.uint8))
    png8 = encoded(".png", np.full((6, 8, 3), 60, np.uint8))
    png16 = encoded(".png", np.full((6, 8, 3), 30000, np.uint16))
    linear = np.full((6, 8, 3), 0.25, np.float32)
    camera = WatchFolderCamera(watch, "*", WatchSettings(timeout_s=5, poll_s=0.02, settle_s=0.25))

    def software():
        time.sleep(0.3)
        write_slowly(watch / "DSC_0001.JPG", jpeg)
        (watch / ".DSC_0002.tmp").write_bytes(b"partial")
        time.sleep(0.1)
        write_slowly(watch / "DSC_0002.png", png8)
        write_oiio(watch / ".DSC_0003.tmp.exr", linear)
        os.replace(watch / ".DSC_0003.tmp.exr", watch / "DSC_0003.exr")
        time.sleep(0.05)
        write_slowly(watch / "DSC_0004.png", png16)

    thread = threading.Thread(target=software)
    thread.start()
    try:
        exposures = camera.capture([0.01, 0.04, 0.16, 0.64], out, "0002")
    finally:
        thread.join()
    assert exposures == [{"file": "0002_e0.jpg", "time": 0.01}, {"file": "0002_e1.png", "time": 0.04},
                         {"file": "0002_e2.exr", "time": 0.16}, {"file": "0002_e3.exr", "time": 0.64}]
    assert (out / "0002_e0.jpg").read_bytes() == jpeg and (out / "0002_e1.png").read_bytes() == png8
    np.testing.assert_array_equal(read_exr(out / "0002_e2.exr")[0]["RGB"], linear)
    np.testing.assert_allclose(read_exr(out / "0002_e3.exr")[0]["RGB"], 30000 / 65535, rtol=1e-6)
    assert sorted(os.listdir(out)) == ["0002_e0.jpg", "0002_e1.png", "0002_e2.exr", "0002_e3.exr"]
    assert (watch / "DSC_0001.JPG").exists()         # the watched files stay (remove=False)


def test_watch_folder_records_the_exif_exposure_time_and_refuses_a_wrong_one(tmp_path):
    watch, out = tmp_path / "incoming", tmp_path / "frames"
    watch.mkdir(), out.mkdir()
    camera = WatchFolderCamera(watch, "*.jpg", WatchSettings(timeout_s=2, poll_s=0.02, settle_s=0.05), remove=True)
    write_oiio(watch / "a.jpg", np.full((4, 4, 3), 90, np.uint8), ExposureTime=0.0125)
    assert camera.capture([0.01], out, "0000") == [{"file": "0000_e0.jpg", "time": pytest.approx(0.0125)}]
    assert not (watch / "a.jpg").exists()
    write_oiio(watch / "b.jpg", np.full((4, 4, 3), 90, np.uint8), ExposureTime=0.05)
    with pytest.raises(CameraError, match=r"b.jpg: exposure time 0.05 s \(EXIF\), the bracket asks for 0.01 s"):
        camera.capture([0.01], out, "0001")
    assert not (out / "0001_e0.jpg").exists()


def test_watch_folder_timeout_names_the_expected_pattern(tmp_path):
    camera = WatchFolderCamera(tmp_path, "*.CR2", WatchSettings(timeout_s=0.3, poll_s=0.02))
    (tmp_path / "frames").mkdir()
    t0 = time.monotonic()
    with pytest.raises(CameraError, match=r"no new complete file matching '\*.CR2' within 0.3 s \(exposure 1 of 2, "
                                          r"0.01 s\)"):
        camera.capture([0.01, 0.1], tmp_path / "frames", "0000")
    assert time.monotonic() - t0 < 2
    with pytest.raises(CameraError, match=r"is also the capture's folder"):
        camera.capture([0.01], tmp_path, "0000")


# --- open_camera ------------------------------------------------------------------------------------------

def test_open_camera_builds_backends_from_the_description(tmp_path):
    camera = open_camera({"backend": "watch", "folder": str(tmp_path), "pattern": "*.NEF", "timeout_s": 5,
                          "retries": 2})
    assert isinstance(camera, WatchFolderCamera) and camera.settings.timeout_s == 5
    assert camera.describe() == f"watch folder: {tmp_path} (*.NEF)"
    with pytest.raises(CameraError, match=r"camera backend 'watch' needs 'folder'"):
        open_camera({"backend": "watch"})
    with pytest.raises(CameraError, match=r"unknown camera backend 'virtual' \(known: gphoto2, watch\)"):
        open_camera({"backend": "virtual"})
    marker = object()
    assert open_camera({"backend": "virtual"}, registry={"virtual": lambda desc: marker}) is marker
