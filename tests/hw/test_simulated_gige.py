"""The simulated camera's frames served through Aravis's fake GigE Vision camera and read by the
GenICam backend (hw.simulated_gige): the pixels are the simulator's, everything else is the
real camera protocol over loopback.

Needs PyGObject and Aravis 0.8 (CI installs both; skipped with the reason elsewhere). The fake
camera takes the machine's GVCP port, so every test holds the loopback lock of
tests/hw/fake_gv_camera.py, as the GenICam tests do.
"""

from __future__ import annotations

import numpy as np
import pytest

from spherejax_hw.camera import CameraError
from spherejax_hw.simcamera import SimulatedCamera

from .fake_gv_camera import exclusive, require_aravis

SHAPE = [48, 96]


@pytest.fixture(autouse=True)
def loopback():
    require_aravis()
    with exclusive():
        yield


def simulated(scene="white"):
    camera = SimulatedCamera(seed=3, image_shape=SHAPE, light_path=lambda: 5, shutter_open=lambda: True)
    camera.set_scene(scene)
    return camera


def test_frames_are_the_simulators_through_the_camera_protocol():
    """Mono16 frames of the simulator's shape and bit depth; their level and their vignetting
    (column profile) are the simulator's own frames' at the same exposure, to noise."""
    from spherejax_hw.simulated_gige import SimulatorThroughGigE

    direct = simulated()
    direct.exposure_s = 0.02
    expected = direct.average(4)
    with SimulatorThroughGigE(simulated()) as camera:
        assert camera.sensor_shape == tuple(SHAPE) and camera.bit_depth == 14
        camera.exposure_s = 0.02
        assert camera.exposure_s == pytest.approx(0.02, abs=1e-6)  # the device's µs, read back
        frame = camera.snap()
        assert frame.dtype == np.uint16 and frame.shape == tuple(SHAPE)
        got = camera.average(4)
    assert got.mean() == pytest.approx(expected.mean(), rel=0.01)
    assert np.corrcoef(got.mean(axis=0), expected.mean(axis=0))[0, 1] > 0.98


def test_roi_binning_exposure_and_scene_reach_the_simulator():
    from spherejax_hw.simulated_gige import SimulatorThroughGigE

    with SimulatorThroughGigE(simulated()) as camera:
        camera.exposure_s = 0.004
        white = camera.snap().mean()
        camera.set_scene("empty")  # the bare black holder
        assert camera.snap().mean() < 0.5 * white
        camera.set_scene("white")
        camera.exposure_s = 0.008
        direct = simulated()
        direct.exposure_s = 0.004
        short = direct.snap().mean()
        direct.exposure_s = 0.008
        # Twice the exposure: as much more signal as the simulator itself gives.
        assert camera.snap().mean() / white == pytest.approx(direct.snap().mean() / short, rel=0.02)
        # The scenes' regions (in frame pixels) and the noise model are the simulator's.
        assert camera.scene_frames() == simulated().scene_frames()
        assert camera.noise_parameters == simulated().noise_parameters
        camera.set_roi_binning((8, 16, 16, 32), 2)
        assert camera.snap().shape == (8, 16) == camera.frame_shape


def test_the_fake_camera_is_released_on_close():
    """Closed, the fake camera gives up the GVCP port: another can start at once."""
    from spherejax_hw.simulated_gige import SimulatorThroughGigE

    first = SimulatorThroughGigE(simulated())
    first.close()
    with pytest.raises(CameraError, match="is closed"):
        first.snap()
    with SimulatorThroughGigE(simulated()) as second:
        second.exposure_s = 0.01
        assert second.snap().shape == tuple(SHAPE)


def test_a_simulator_that_fails_in_the_streaming_thread_fails_the_snap_in_one_line():
    from spherejax_hw.simulated_gige import SimulatorThroughGigE

    source = simulated()
    with SimulatorThroughGigE(source) as camera:
        camera.exposure_s = 0.01

        def broken():
            raise RuntimeError("renderer lost its device")

        source.snap = broken
        with pytest.raises(CameraError, match="the simulator could not fill the frame: renderer lost its device") as info:
            camera.snap()
        assert "\n" not in str(info.value)


@pytest.mark.slow
def test_an_emulated_acquisition_through_the_gige_camera_writes_a_session(tmp_path, capsys):
    """`spherejax acquire --emulate --through-gige`: emulated wheels and shutter, the simulated
    camera's frames through the fake GigE Vision camera and the GenICam backend. The session is
    the one the simulator gives directly: the same frames and bands, the white standard near 80 %
    of the simulated sensor's 14-bit full scale in every band, nothing saturated."""
    from spherejax import cli, io

    from .support import BANDS, SAMPLES, write_profile

    profile = write_profile(tmp_path, samples=SAMPLES[:1])
    out = tmp_path / "session"
    status = cli.main(["acquire", "--profile", str(profile), "-o", str(out), "--emulate", "--through-gige", "--yes"])
    assert status == 0, capsys.readouterr().err
    session = io.load_session(out)
    assert [f.id for f in session.frames] == ["dark", "white", SAMPLES[0]] and list(session.band_centres_nm) == BANDS
    white = session.white().astype(float)
    level = np.percentile(white.reshape(-1, 16), 99.5, axis=0) / (2**14 - 1)
    assert np.all(np.abs(level - 0.8) < 0.1), level
    assert white.max() < 2**14 - 1
    assert session.frame(SAMPLES[0]).regions  # the simulator's scene regions came through


@pytest.mark.parametrize("flags", [["--through-gige"], ["--emulate", "--real-camera", "--through-gige"]])
def test_through_gige_without_the_simulated_camera_is_refused(tmp_path, capsys, flags):
    from spherejax import cli

    from .support import write_profile

    profile = write_profile(tmp_path)
    status = cli.main(["acquire", "--profile", str(profile), "-o", str(tmp_path / "s"), "--yes", *flags])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    assert "--through-gige: expected it with --emulate and without --real-camera" in err
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.partial").exists()
