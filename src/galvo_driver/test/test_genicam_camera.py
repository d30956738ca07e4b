"""GenICamCamera against the simulated GigE Vision camera (real GVCP/GVSP on loopback)."""

import math
import time

import numpy as np
import pytest

from galvo_driver.fake_camera import FakeCamera
from galvo_driver.genicam_camera import CameraError, GenICamCamera, pixel_format_info

SERIAL = "GSTEST0"
USER_ID = "galvo-cam"
W, H = 160, 120  # small sensor: the test is about the interface, not the bandwidth


@pytest.fixture(scope="module")
def fake():
    with FakeCamera(SERIAL, width=W, height=H, user_id=USER_ID) as f:
        yield f


@pytest.fixture(scope="module")
def opened(fake):
    cam = GenICamCamera(serial=SERIAL)
    cam.open()
    yield cam
    cam.close()


@pytest.fixture
def cam(opened, fake):
    """The opened camera, in software-trigger mode, full sensor, Mono8; reset after the test."""
    if not fake.running:
        fake.replug()
    if opened.error is not None or not opened.is_open:
        assert opened.reopen()
    opened.stop()
    for name, value in (("OffsetX", 0), ("OffsetY", 0), ("Width", W), ("Height", H),
                        ("PixelFormat", "Mono8"), ("TriggerMode", "On"),
                        ("TriggerSource", "Software"), ("ExposureTime", 10000.0), ("Gain", 0.0)):
        opened.set(name, value)
    yield opened
    opened.stop()


def triggered(cam, n):
    frames = []
    for _ in range(n):
        cam.software_trigger()
        frame = cam.grab(2.0)
        assert frame is not None
        frames.append(frame)
    return frames


def test_open_by_serial_and_by_user_id(opened):
    assert opened.get("DeviceSerialNumber") == SERIAL
    assert opened.get("DeviceUserID") == USER_ID
    by_user = GenICamCamera(user_id=USER_ID)
    by_user.open()
    try:
        assert by_user.get("DeviceSerialNumber") == SERIAL
    finally:
        by_user.close()


def test_wrong_serial_or_user_id_refused(fake):
    with pytest.raises(CameraError, match="NOSUCHCAM"):
        GenICamCamera(serial="NOSUCHCAM").open()
    with pytest.raises(CameraError, match="nobody-here"):
        GenICamCamera(user_id="nobody-here").open()
    with pytest.raises(CameraError, match="user id"):  # both given: both must match
        GenICamCamera(serial=SERIAL, user_id="other-name").open()


def test_features_read_back_and_ranges(cam):
    cam.set("ExposureTime", 2500.0)
    cam.set("Gain", 3.0)
    cam.set("AcquisitionFrameRate", 250.0)
    cam.set("TriggerActivation", "FallingEdge")
    assert cam.get("ExposureTime") == 2500.0
    assert cam.get("Gain") == 3.0
    assert math.isclose(cam.get("AcquisitionFrameRate"), 250.0)
    assert cam.get("TriggerActivation") == "FallingEdge"
    assert cam.get("TriggerMode") == "On" and cam.get("TriggerSource") == "Software"
    assert cam.feature_range("ExposureTime") == (10.0, 1_000_000.0)
    assert cam.feature_range("Width") == (16, W)
    assert set(cam.feature_range("PixelFormat")) == {"Mono8", "Mono12", "Mono16"}
    assert set(cam.feature_range("TriggerSource")) == {"Line0", "Software"}
    cam.set("TriggerActivation", "RisingEdge")


@pytest.mark.parametrize("name, value, words", [
    ("ExposureTime", float("nan"), "finite"),
    ("ExposureTime", float("inf"), "finite"),
    ("ExposureTime", 5.0, "outside"),
    ("Gain", 11.0, "outside"),
    ("Width", W + 1, "outside"),
    ("Width", 100.5, "integer"),
    ("Width", "wide", "number"),
    ("AcquisitionFrameRate", -1.0, "outside"),
    ("PixelFormat", "Mono14", "not one of"),
    ("TriggerSource", "Line7", "not one of"),
    ("TriggerMode", True, "not one of"),
    ("NoSuchFeature", 1, "unknown feature"),
    ("TriggerSoftware", 1, "command"),
    ("DeviceSerialNumber", "X", "not writable"),
])
def test_bad_values_refused_and_camera_unchanged(cam, name, value, words):
    watched = ("ExposureTime", "Gain", "Width", "Height", "AcquisitionFrameRate",
               "PixelFormat", "TriggerMode", "TriggerSource", "DeviceSerialNumber")
    before = {n: cam.get(n) for n in watched}
    with pytest.raises(CameraError, match=words) as err:
        cam.set(name, value)
    assert repr(name) in str(err.value)
    assert {n: cam.get(n) for n in watched} == before


def test_triggered_frames_ids_timestamps_and_image(cam):
    cam.start()
    frames = triggered(cam, 20)
    ids = [f.frame_id for f in frames]
    stamps = [f.timestamp_ns for f in frames]
    pairs = zip(ids[:-1], ids[1:], strict=True)
    assert all(b == a + 1 or (a == 65535 and b == 1) for a, b in pairs)  # 16-bit GVSP ids
    assert all(b > a for a, b in zip(stamps[:-1], stamps[1:], strict=True))
    assert abs(stamps[-1] - time.time_ns()) < 60e9  # the fake camera's clock is wall time
    for f in frames:
        assert f.image.shape == (H, W) and f.image.dtype == np.uint8 and f.bit_depth == 8
        # the simulated sensor's diagonal ramp, one grey level further per frame
        y, x = np.mgrid[0:H, 0:W]
        np.testing.assert_array_equal(f.image, (x + y + f.frame_id) % 255)
    assert cam.grab(0.05) is None  # no trigger, no frame


def test_gain_brightens_the_image(cam):
    cam.start()
    dim = triggered(cam, 1)[0]
    cam.stop()
    cam.set("Gain", 1.0)
    cam.start()
    bright = triggered(cam, 1)[0]

    def level(f):
        return (np.add.outer(np.arange(H), np.arange(W)) + f.frame_id) % 255

    np.testing.assert_array_equal(dim.image, level(dim))
    np.testing.assert_array_equal(bright.image, np.minimum(2 * level(bright), 255))


def test_roi_changes_the_image_shape(cam):
    cam.set("Width", 64)
    cam.set("Height", 32)
    cam.set("OffsetX", W - 64)
    cam.set("OffsetY", 10)
    assert cam.feature_range("Width") == (16, 64)  # the offset now limits the width
    cam.start()
    assert triggered(cam, 1)[0].image.shape == (32, 64)
    with pytest.raises(CameraError, match="stop acquiring"):
        cam.set("Width", 48)
    assert cam.get("Width") == 64
    cam.stop()


@pytest.mark.parametrize("fmt", ["Mono12", "Mono16"])
def test_deeper_pixel_formats_are_uint16(cam, fmt):
    dtype, depth = pixel_format_info(fmt)
    cam.set("PixelFormat", fmt)
    cam.start()
    frame = triggered(cam, 1)[0]
    assert frame.image.dtype == np.uint16 == dtype and frame.bit_depth == depth
    assert frame.image.shape == (H, W)
    assert int(frame.image.max()) < 2 ** depth
    y, x = np.mgrid[0:H, 0:W]
    np.testing.assert_array_equal(frame.image, ((x + y + frame.frame_id) % 255) << (depth - 8))


def test_statistics_count_completed_buffers(cam):
    before = cam.statistics()
    cam.start(n_buffers=4)
    triggered(cam, 7)
    after = cam.statistics()
    assert after["completed"] - before["completed"] == 7
    assert after["failed"] == before["failed"] and after["underrun"] == before["underrun"]
    cam.stop()
    assert cam.statistics() == after  # counts survive a stop


def test_unplug_sets_error_then_reopen_restores(cam, fake):
    cam.set("Width", 96)
    cam.set("ExposureTime", 4000.0)
    cam.start()
    assert triggered(cam, 2)[-1].image.shape == (H, 96)
    fake.unplug()
    with pytest.raises(CameraError):
        cam.software_trigger()
    assert cam.error is not None and SERIAL in cam.error
    assert cam.reopen() is False  # still unplugged
    assert "reopen failed" in cam.error
    fake.replug()
    assert cam.reopen() is True
    assert cam.error is None and cam.acquiring
    assert cam.get("Width") == 96 and cam.get("ExposureTime") == 4000.0  # restored
    assert cam.get("TriggerSource") == "Software"
    frames = triggered(cam, 3)
    assert [f.image.shape for f in frames] == [(H, 96)] * 3
    assert frames[1].frame_id == frames[0].frame_id + 1


def test_use_before_open_and_bad_arguments(fake):
    cam = GenICamCamera(serial=SERIAL)
    with pytest.raises(CameraError, match="not open"):
        cam.get("Width")
    with pytest.raises(CameraError, match="not acquiring"):
        cam.grab(0.1)
    with pytest.raises(CameraError, match="PixelFormat 'RGB8'"):
        pixel_format_info("RGB8")
