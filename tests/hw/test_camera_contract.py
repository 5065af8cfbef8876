"""The camera contract (`hw.camera.Camera`'s module docstring) run against every backend in
`hw.camera.BACKENDS`: the simulated camera, PVCAM through a fake `pyvcam` that follows
PyVCAM's documented API (tests/hw/fake_pyvcam/README.md), since PyVCAM and the PVCAM SDK cannot
be installed here, and GenICam through Aravis against Aravis's own fake GigE Vision camera on
loopback (tests/hw/fake_gv_camera.py; skipped only where PyGObject or Aravis is absent).

Every backend must give frames of `frame_shape`, uint16 below 2**bit_depth, for any ROI and
binning the interface accepts; read back the exposure it uses (within its time resolution);
refuse what the interface refuses with a one-line ValueError; report a finite temperature or,
for a camera without a sensor thermometer, None; and, once closed, refuse everything with a
CameraError and release the device.
"""

import math
import pathlib
import sys

import numpy as np
import pytest

from spherejax_hw.camera import BACKENDS, CameraError, open_camera

from tests.hw import fake_gv_camera

FAKE_PYVCAM = pathlib.Path(__file__).parent / "fake_pyvcam"


@pytest.fixture(params=sorted(BACKENDS))
def backend(request, monkeypatch):
    """(backend name, options, the fake pvc module or None), with the fake PyVCAM importable
    and, for GenICam, Aravis's fake GigE Vision camera running for the test."""
    name = request.param
    if name == "genicam":
        fake_gv_camera.require_aravis()
        with fake_gv_camera.running() as fake:
            yield name, {"device_id": fake.device_id, "exposure_s": 0.005}, None
        return
    if name == "pvcam":
        monkeypatch.syspath_prepend(str(FAKE_PYVCAM))
        for module in [m for m in sys.modules if m == "pyvcam" or m.startswith("pyvcam.")]:
            monkeypatch.delitem(sys.modules, module)
        from pyvcam import pvc

        yield name, {"exposure_s": 0.05}, pvc
        return
    # The light path and shutter are the acquisition's to wire (`hw.acquire.connect`): here a
    # 500 nm filter in the path (band index 5) and an open shutter.
    yield name, {"seed": 3, "image_shape": [48, 96], "light_path": lambda: 5, "shutter_open": lambda: True}, None


def test_this_checks_every_backend():
    assert set(BACKENDS) == {"sim", "pvcam", "genicam"}  # a new backend gets a fixture entry above


def test_frames_follow_roi_and_binning(backend):
    name, options, _ = backend
    with open_camera(name, **options) as camera:
        height, width = camera.sensor_shape
        assert camera.frame_shape == (height, width) and camera.roi == (0, 0, height, width)
        for roi, binning in [(None, 1), ((2, 4, 16, 24), 1), ((2, 4, 16, 24), 2), ((0, 0, height, width), 4)]:
            camera.set_roi_binning(roi, binning)
            frame = camera.snap()
            assert frame.dtype == np.uint16 and frame.shape == camera.frame_shape
            expected = ((height, width) if roi is None else roi[2:])
            assert frame.shape == (expected[0] // binning, expected[1] // binning)
            assert int(frame.max()) <= camera.saturation_dn == 2 ** camera.bit_depth - 1
        mean = camera.average(3)
        assert mean.dtype == np.float64 and mean.shape == camera.frame_shape


def test_exposure_reads_back_what_the_device_uses(backend):
    name, options, _ = backend
    with open_camera(name, **options) as camera:
        low, high = camera.exposure_limits_s
        assert 0 < low < high
        for asked in (max(low, 0.0123), min(high, 0.25)):
            camera.exposure_s = asked
            assert abs(camera.exposure_s - asked) <= 0.0005 + 1e-12  # 1 ms resolution at worst
        for bad in (math.nan, -1.0, high * 2, "0.1", True):
            with pytest.raises(ValueError, match=f"camera {camera.name!r}") as info:
                camera.exposure_s = bad
            assert "\n" not in str(info.value)


def test_what_the_interface_refuses_every_backend_refuses(backend):
    name, options, _ = backend
    with open_camera(name, **options) as camera:
        height, width = camera.sensor_shape
        for roi, binning in [((0, 0, height + 1, width), 1), ((-1, 0, 4, 4), 1), ((0, 0, 6, 6), 4), (None, 0)]:
            with pytest.raises(ValueError) as info:
                camera.set_roi_binning(roi, binning)
            assert "\n" not in str(info.value)
        assert camera.frame_shape == (height, width)  # a refused setting changes nothing


def test_temperature_and_closing(backend):
    name, options, pvc = backend
    camera = open_camera(name, **options)
    temperature = camera.temperature_c()
    if name == "genicam":  # Aravis's fake camera has no DeviceTemperature feature
        assert temperature is None
    else:
        assert isinstance(temperature, float) and math.isfinite(temperature)
    camera.close()
    camera.close()  # closing twice is harmless
    assert camera.closed
    for action in (camera.snap, camera.temperature_c, lambda: setattr(camera, "exposure_s", 0.1)):
        with pytest.raises(CameraError, match="is closed"):
            action()
    if pvc is not None:  # PVCAM's camera closed and the library released
        assert pvc.open_cameras() == set() and not pvc.is_initialised()


def test_pvcam_names_a_camera_it_cannot_find(monkeypatch):
    monkeypatch.syspath_prepend(str(FAKE_PYVCAM))
    for module in [m for m in sys.modules if m == "pyvcam" or m.startswith("pyvcam.")]:
        monkeypatch.delitem(sys.modules, module)
    from pyvcam import pvc

    with pytest.raises(CameraError, match="PVCAM failed to open: Failed to create a detected camera") as info:
        open_camera("pvcam", camera_name="no-such-camera")
    assert "\n" not in str(info.value)
    assert not pvc.is_initialised()  # released on the way out
    monkeypatch.setattr(pvc, "CAMERAS", {})
    with pytest.raises(CameraError, match="PVCAM found no camera"):
        open_camera("pvcam")
    assert not pvc.is_initialised()
