"""The camera interface (validation shared by every backend), the simulated camera's physics,
and the PVCAM backend's behaviour without PyVCAM."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import sys

import numpy as np
import pytest

from spherejax_hw.camera import BACKENDS, PROFILE_OPTIONS, Camera, CameraError, open_camera
from spherejax_hw.simcamera import FILTER_LEAK, SENSOR_TEMPERATURE_C, WARMUP_DEFICIT, SimulatedCamera
from spherejax import simulate

BLUE, GREEN = 0, 8  # band indices of 400 nm and 560 nm


class FakeCamera(Camera):
    """A backend that records what its hooks receive: the interface alone under test."""

    def __init__(self, frame_dtype=np.uint16):
        super().__init__("fake")
        self.calls = []
        self.frame_dtype = frame_dtype
        self.counter = 0
        self.exposure_s = 0.01

    sensor_shape = (60, 80)
    bit_depth = 12
    exposure_limits_s = (1e-3, 10.0)

    def _set_exposure(self, seconds):
        self.calls.append(("exposure", seconds))
        return round(seconds, 3)  # a device with ms resolution

    def _apply_roi_binning(self, roi, binning):
        self.calls.append(("roi", roi, binning))

    def _snap(self):
        self.counter += 1
        return np.full(self.frame_shape, self.counter, self.frame_dtype)

    def _read_temperature(self):
        return -10.0

    def _close(self):
        self.calls.append(("close",))


class Bench:
    """The light path and shutter the simulated camera asks about at every snap."""

    def __init__(self, band=GREEN, shutter=True):
        self.band = band
        self.shutter = shutter

    def camera(self, **options) -> SimulatedCamera:
        return SimulatedCamera(light_path=lambda: self.band, shutter_open=lambda: self.shutter, **options)


def one_line(error) -> str:
    message = str(error.value)
    assert "\n" not in message and message
    return message


# --- the interface ----------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [0, 0.0, -1.0, math.nan, math.inf, 11.0, 1e-4, "fast", "0.5", None, True, np.float64(np.nan)])
def test_exposure_validation(bad):
    camera = FakeCamera()
    camera.calls.clear()
    with pytest.raises(ValueError) as error:
        camera.exposure_s = bad
    message = one_line(error)
    assert "'fake'" in message and repr(bad) in message
    if isinstance(bad, (int, float)) and not isinstance(bad, bool):
        assert "[0.001, 10] s" in message  # the limits
    assert camera.calls == [] and camera.exposure_s == 0.01


def test_exposure_reads_back_what_the_device_uses():
    camera = FakeCamera()
    camera.exposure_s = 0.12345
    assert camera.calls[-1] == ("exposure", 0.12345)
    assert camera.exposure_s == 0.123
    camera.exposure_s = np.float32(2.0)  # numpy scalars are numbers too
    assert camera.exposure_s == 2.0


@pytest.mark.parametrize(
    "roi",
    [(0, 0, 61, 80), (0, 0, 60, 81), (-1, 0, 10, 10), (0, -1, 10, 10), (55, 0, 10, 10), (0, 75, 10, 10),
     (0, 0, 0, 10), (0, 0, 10, 0), (0, 0, 10.5, 10), (0, 0, 10), "full"],
)
def test_roi_outside_sensor(roi):
    camera = FakeCamera()
    with pytest.raises(ValueError) as error:
        camera.roi = roi
    message = one_line(error)
    assert "'fake'" in message and "ROI" in message
    assert camera.roi == (0, 0, 60, 80)


def test_roi_and_frame_shape():
    camera = FakeCamera()
    camera.roi = (10, 20, 30, 40)
    assert camera.roi == (10, 20, 30, 40) and camera.frame_shape == (30, 40)
    assert camera.calls[-1] == ("roi", (10, 20, 30, 40), 1)
    assert camera.snap().shape == (30, 40)
    camera.roi = None
    assert camera.roi == (0, 0, 60, 80) and camera.frame_shape == (60, 80)


@pytest.mark.parametrize("binning", [0, -2, 7, 1.5, "2", True])
def test_binning_validation(binning):
    camera = FakeCamera()
    with pytest.raises(ValueError) as error:
        camera.binning = binning
    assert "'fake'" in one_line(error) and "binning" in one_line(error)
    assert camera.binning == 1


def test_binning_must_divide_the_roi():
    camera = FakeCamera()
    camera.binning = 4
    assert camera.frame_shape == (15, 20)
    with pytest.raises(ValueError, match="binning 4 does not divide the ROI's height 10 and width 10"):
        camera.roi = (0, 0, 10, 10)
    camera.set_roi_binning((0, 0, 10, 10), 2)  # both at once
    assert camera.frame_shape == (5, 5) and camera.binning == 2


@pytest.mark.parametrize("n", [0, -1, 1.5, "4", True])
def test_average_validation(n):
    camera = FakeCamera()
    with pytest.raises(ValueError) as error:
        camera.average(n)
    assert "'fake'" in one_line(error) and repr(n) in one_line(error)


def test_average_is_float64_mean_of_snaps():
    camera = FakeCamera()
    mean = camera.average(4)
    assert mean.dtype == np.float64 and mean.shape == (60, 80)
    np.testing.assert_array_equal(mean, 2.5)  # snaps 1, 2, 3, 4


def test_backend_frame_is_checked():
    camera = FakeCamera(frame_dtype=np.float32)
    with pytest.raises(CameraError) as error:
        camera.snap()
    assert "'fake'" in one_line(error) and "uint16" in one_line(error)


def test_close_and_context_manager():
    with FakeCamera() as camera:
        assert camera.temperature_c() == -10.0 and camera.saturation_dn == 4095
    assert camera.closed and camera.calls[-1] == ("close",)
    camera.close()  # twice is harmless
    assert camera.calls.count(("close",)) == 1
    for action in (camera.snap, camera.temperature_c, lambda: camera.average(2)):
        with pytest.raises(CameraError) as error:
            action()
        assert one_line(error) == "camera 'fake': is closed"
    with pytest.raises(CameraError):
        camera.exposure_s = 1.0


@pytest.mark.parametrize("reading, expected", [(None, None), (-10, -10.0), (np.float32(21.5), 21.5)])
def test_temperature_is_a_float_or_none(monkeypatch, reading, expected):
    """A camera without a thermometer reports None (JSON null in the acquisition's metadata)."""
    camera = FakeCamera()
    monkeypatch.setattr(camera, "_read_temperature", lambda: reading)
    value = camera.temperature_c()
    assert value == expected and (value is None or type(value) is float)


@pytest.mark.parametrize("reading", [math.nan, math.inf, -math.inf])
def test_a_temperature_that_is_not_finite_is_refused(monkeypatch, reading):
    """NaN or infinity would not be valid JSON in the metadata: a CameraError naming it."""
    camera = FakeCamera()
    monkeypatch.setattr(camera, "_read_temperature", lambda: reading)
    with pytest.raises(CameraError) as error:
        camera.temperature_c()
    assert one_line(error) == f"camera 'fake': reported a sensor temperature of {reading!r} °C"


def test_open_camera_unknown_backend():
    with pytest.raises(ValueError) as error:
        open_camera("qcam")
    assert one_line(error) == "unknown camera backend 'qcam': choose one of 'genicam', 'pvcam', 'sim'"
    assert set(BACKENDS) == {"sim", "pvcam", "genicam"}


def test_open_camera_sim():
    bench = Bench()
    with open_camera("sim", light_path=lambda: bench.band, shutter_open=lambda: bench.shutter) as camera:
        assert isinstance(camera, SimulatedCamera) and camera.name == "sim"


def test_pvcam_without_pyvcam(monkeypatch):
    # A None entry in sys.modules makes `import pyvcam` raise ImportError, installed or not.
    monkeypatch.setitem(sys.modules, "pyvcam", None)
    from spherejax_hw.pvcam import PVCAMCamera

    for make in (PVCAMCamera, lambda: open_camera("pvcam")):
        with pytest.raises(CameraError) as error:
            make()
        assert one_line(error) == (
            "camera 'pvcam': PyVCAM is not installed: pip install PyVCAM "
            "(Teledyne Photometrics PVCAM SDK required)"
        )


#: Keywords of each backend's constructor that the acquisition passes, never a profile.
SET_BY_ACQUIRE = {"sim": {"light_path", "shutter_open", "instrument", "design", "lamp_on_s", "clock"}, "pvcam": set(), "genicam": set()}


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_profile_options_are_the_constructor_keywords(backend):
    """The option table profiles are checked against (hw.camera.PROFILE_OPTIONS) names exactly
    the backend's keyword parameters, less those the acquisition supplies: an option added to a
    constructor without the table, or a name in the table the constructor does not take, fails."""
    module, cls = BACKENDS[backend]
    parameters = inspect.signature(getattr(importlib.import_module(module, "spherejax_hw"), cls)).parameters
    keywords = {name for name, p in parameters.items() if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
    assert not any(p.kind is p.VAR_KEYWORD for p in parameters.values())
    assert set(PROFILE_OPTIONS[backend]) == keywords - SET_BY_ACQUIRE[backend]
    assert SET_BY_ACQUIRE[backend] <= keywords


def test_profile_options_open_the_simulated_camera():
    """Values the profile accepts are values the simulated camera takes (TOML gives lists)."""
    bench = Bench()
    with open_camera("sim", light_path=lambda: bench.band, shutter_open=lambda: bench.shutter,
                     seed=2**32 - 1, image_shape=[96, 136], name="bench") as camera:
        assert camera.sensor_shape == (96, 136) and camera.name == "bench"


# --- the simulated camera -----------------------------------------------------------------------


def test_sim_shapes_and_dtype():
    bench = Bench()
    camera = bench.camera()
    design = simulate.ExperimentDesign()
    instrument = simulate.InstrumentModel()
    assert camera.sensor_shape == design.image_shape(instrument) == (192, 272)
    assert camera.bit_depth == 14 and camera.saturation_dn == 2**14 - 1
    assert camera.white_patch == design.white_patch(instrument)
    assert camera.holder == (0, 192, 0, 240)
    assert camera.band_centres_nm == list(range(400, 701, 20))
    assert camera.temperature_c() == SENSOR_TEMPERATURE_C
    frame = camera.snap()
    assert frame.dtype == np.uint16 and frame.shape == camera.frame_shape == (192, 272)
    camera.binning = 2
    assert camera.snap().shape == (96, 136) == camera.frame_shape
    assert camera.white_patch == (4, 16, 122, 134)
    camera.set_roi_binning((0, 200, 64, 72), 1)
    assert camera.snap().shape == (64, 72)
    assert camera.white_patch == (8, 32, 44, 68)
    camera.roi = (0, 240, 64, 32)  # the white-patch strip only
    with pytest.raises(CameraError, match=r"the holder \(0, 192, 0, 240\) lies outside the ROI \(0, 240, 64, 32\)"):
        _ = camera.holder


def test_sim_exposure_validation_is_the_interface():
    camera = Bench().camera()
    with pytest.raises(ValueError, match=r"camera 'sim': exposure nan s is outside the camera's limits \[1e-05, 1200\] s"):
        camera.exposure_s = math.nan
    with pytest.raises(ValueError, match="ROI"):
        camera.roi = (0, 0, 193, 272)
    with pytest.raises(ValueError, match="binning 5 does not divide"):
        camera.binning = 5


def test_dark_frame_when_shutter_closed():
    bench = Bench(shutter=False)
    camera = bench.camera()
    inst = camera.instrument
    for exposure in (0.01, 300.0):
        camera.exposure_s = exposure
        expected = inst.bias_dn + inst.dark_current_e_per_s * exposure / inst.gain_e_per_dn
        means = []
        for band in (BLUE, GREEN, 15, None):
            bench.band = band
            dark = camera.average(4)
            means.append(dark.mean())
            # Read noise only: 6 e- / gain / sqrt(4) frames.
            assert dark.std() == pytest.approx(inst.read_noise_e / inst.gain_e_per_dn / 2.0, rel=0.05)
        np.testing.assert_allclose(means, expected, atol=0.05)
    assert expected > inst.bias_dn + 2.5  # 300 s of dark current shows


def test_white_level_is_linear_in_exposure():
    bench = Bench()
    camera = bench.camera()
    base = camera.calibrated_exposures_s[GREEN] / 4.0
    levels = []
    for exposure in (base, 2.0 * base, 3.0 * base):
        camera.exposure_s = exposure
        levels.append(camera.average(8).mean() - camera.instrument.bias_dn)
    # Lamp flicker (1.5 % per frame, 0.5 % after averaging 8) is the noise here.
    assert levels[1] / levels[0] == pytest.approx(2.0, rel=0.03)
    assert levels[2] / levels[0] == pytest.approx(3.0, rel=0.03)


def test_almost_no_light_without_a_band_filter():
    bench = Bench()
    camera = bench.camera()
    camera.exposure_s = camera.calibrated_exposures_s[GREEN]
    bias = camera.instrument.bias_dn
    lit = camera.average(4).mean() - bias
    bench.band = None
    leak = camera.average(4).mean() - bias
    assert abs(leak) < 0.01 * lit
    camera.exposure_s = 1000.0 * camera.calibrated_exposures_s[GREEN]
    leak_long = camera.average(4).mean() - bias
    # Two crossed filters still leak a little (FILTER_LEAK of the mean band), seen at long exposure.
    assert 0.1 * FILTER_LEAK * 1000.0 * lit < leak_long < 10.0 * FILTER_LEAK * 1000.0 * lit


def test_blue_needs_longer_exposures():
    bench = Bench()
    camera = bench.camera()
    camera.exposure_s = 0.02
    levels = {}
    for band in (BLUE, GREEN):
        bench.band = band
        levels[band] = camera.average(4).mean() - camera.instrument.bias_dn
    # The exposure that brings each band to the same level scales as 1 / level.
    assert levels[GREEN] / levels[BLUE] > 3.0
    exposures = camera.calibrated_exposures_s
    assert exposures[BLUE] > 3.0 * exposures[GREEN]
    assert np.argmax(exposures) == BLUE


def test_white_patch_bright_in_sample_scenes():
    bench = Bench()
    camera = bench.camera()
    scenes = camera.scenes()
    assert scenes[:2] == ["white", "empty"] and "targets" in scenes and "train-bg00-g0" in scenes
    camera.exposure_s = camera.calibrated_exposures_s[GREEN]
    full = camera.saturation_dn
    for scene in ("train-bg00-g0", "test-bg00-g0", "targets", "empty"):
        camera.set_scene(scene)
        frame = camera.average(2)
        r0, r1, c0, c1 = camera.white_patch
        h0, h1, k0, k1 = camera.holder
        patch = frame[r0:r1, c0:c1].mean()
        # A dark holder lowers the whole sphere's irradiance (Eq. 9), the patch's too.
        assert 0.25 * full < patch < full
        assert patch > 1.5 * frame[h0:h1, k0:k1].mean()
    with pytest.raises(ValueError) as error:
        camera.set_scene("teapot")
    assert "'teapot'" in one_line(error) and "scenes()" in one_line(error)


@pytest.mark.parametrize("scene", ["dark", "white"])
def test_averaging_reduces_noise(scene):
    instrument = dataclasses.replace(simulate.InstrumentModel(), lamp_fluctuation=0.0)
    bench = Bench(shutter=scene == "white")
    camera = bench.camera(instrument=instrument)
    camera.exposure_s = camera.calibrated_exposures_s[GREEN] / 2.0
    region = (slice(60, 130), slice(80, 160))

    def noise(n):
        # The difference of two independent averages removes the fixed pattern (vignetting).
        return np.std(camera.average(n)[region] - camera.average(n)[region]) / np.sqrt(2.0)

    assert noise(1) / noise(16) == pytest.approx(4.0, rel=0.1)


def test_saturation_clips_at_full_scale():
    camera = Bench().camera()
    camera.exposure_s = 10.0
    frame = camera.snap()
    assert frame.dtype == np.uint16 and frame.max() == 2**14 - 1
    assert np.mean(frame == 2**14 - 1) > 0.9


def test_binning_sums_charge_and_roi_crops():
    bench = Bench()
    camera = bench.camera()
    camera.exposure_s = camera.calibrated_exposures_s[GREEN] / 8.0
    bias = camera.instrument.bias_dn
    full = camera.average(8)
    camera.set_roi_binning((40, 60, 100, 120), 1)
    crop = camera.average(8)
    assert crop.mean() == pytest.approx(full[40:140, 60:180].mean(), rel=0.02)
    camera.binning = 2
    binned = camera.average(8)
    assert binned.shape == (50, 60)
    assert binned.mean() - bias == pytest.approx(4.0 * (crop.mean() - bias), rel=0.02)


def test_lamp_off_and_warming_up():
    instrument = dataclasses.replace(simulate.InstrumentModel(), lamp_fluctuation=0.0)
    lamp = {"on_s": None}
    camera = Bench().camera(instrument=instrument, lamp_on_s=lambda: lamp["on_s"])
    camera.exposure_s = camera.calibrated_exposures_s[GREEN] / 2.0
    bias = instrument.bias_dn
    assert camera.average(2).mean() == pytest.approx(bias, abs=0.1)  # lamp off: dark
    lamp["on_s"] = 0.0
    cold = camera.average(4).mean() - bias
    lamp["on_s"] = 3600.0
    warm = camera.average(4).mean() - bias
    assert 1.0 - cold / warm == pytest.approx(WARMUP_DEFICIT, abs=0.005)


def test_light_path_reporting_a_bad_band():
    bench = Bench(band=16)
    camera = bench.camera()
    with pytest.raises(CameraError) as error:
        camera.snap()
    assert one_line(error) == "camera 'sim': light path reports band 16, expected 0..15 or None"


def test_smaller_image_shape():
    camera = Bench().camera(image_shape=(96, 136))
    assert camera.sensor_shape == (96, 136) and camera.snap().shape == (96, 136)
    r0, r1, c0, c1 = camera.white_patch
    assert c0 >= camera.holder[3] and r1 <= 96
    with pytest.raises(ValueError, match="needs a width of at least"):
        Bench().camera(image_shape=(96, 125))


def test_frames_match_the_simulator():
    """Noise-free and with a steady lamp, each band frame at the simulator's exposure is the
    simulator's own frame, for the white standard, the dark and every sample capture; the
    layouts and regions are the simulator's too."""
    instrument = dataclasses.replace(simulate.InstrumentModel(), noise=False, lamp_fluctuation=0.0, lamp_drift_per_hour=0.0)
    design = simulate.ExperimentDesign(training_backgrounds=1, training_patches=3, test_backgrounds=1, test_patches=3, targets=4)
    experiment = simulate.simulate_experiment(seed=3, instrument=instrument, design=design)
    bench = Bench()
    camera = bench.camera(seed=3, instrument=instrument, design=design)
    np.testing.assert_allclose(camera.calibrated_exposures_s, experiment.exposure_s, rtol=1e-6)
    assert camera.white_patch == tuple(experiment.white_patch) and camera.holder == tuple(experiment.holder)
    fields = camera.scene_frames()
    assert [f["id"] for f in fields] == [f.id for f in experiment.frames if f.role in ("sample", "target")]
    for frame in experiment.frames:
        if frame.role in ("sample", "target"):
            mine = next(f for f in fields if f["id"] == frame.id)
            assert mine["role"] == frame.role and mine["regions"] == frame.regions
            assert mine.get("set") == frame.set and mine.get("background") == frame.background
        bench.shutter = frame.role != "dark"
        camera.set_scene("white" if frame.role in ("dark", "white") else frame.id)
        for band in (BLUE, 7, 15):
            bench.band = band
            camera.exposure_s = float(experiment.exposure_s[band])
            difference = camera.snap().astype(np.int32) - frame.pixels[..., band].astype(np.int32)
            assert np.abs(difference).max() <= 1, (frame.id, band)
