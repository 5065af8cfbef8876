"""Every long wait of an acquisition stops within a fraction of a second on a stop request, and
every wait a profile sets is bounded when the profile is read.

The waits: a tunable filter's settling after each tune and its warm-up (a VariSpec's fixed
`warmup_s`, a Kurios's ST? polls), a filter wheel's move (the prompt that ends it), the lamp's
warm-up interval between white-standard checks, a camera's frames averaged. Each test sends the
signal at a known point -- as the wait begins (the first `time.sleep` of it) or as the device
receives the command that starts it (from the emulator) -- never after a fixed delay, so the
result does not depend on the machine's speed: the wait is 30 s or more, and the stop must come
within `PROMPT_S`.

The limits: `hw.profile.LIMITS` and `hw.camera.PROFILE_OPTIONS`; `settle_s = 1e300` was an
OverflowError traceback once the devices had moved, with SESSION.partial left behind.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from spherejax import interrupt
from spherejax_hw import acquire
from spherejax_hw.camera import Camera
from spherejax_hw.emulators import EmulatedPort, FilterWheelEmulator, ShutterEmulator
from spherejax_hw.filterwheel import FilterWheel
from spherejax_hw.profile import ProfileError, load_profile
from spherejax_hw.shutter import Shutter
from spherejax_hw.tunablefilter import open_filter
from spherejax_hw.tunablefilter_emulators import KuriosEmulator, VariSpecEmulator

from tests.helpers import wait_until
from tests.hw.support import BANDS, SAMPLES, quiet_settings, write_profile

#: How soon after the signal a wait must have stopped, s (the waits are 30 s and more).
PROMPT_S = 1.0


def write_lctf_profile(folder, *, model="VariSpec-VIS", bands=None):
    """A profile with a [tunable_filter] (settle_s = 0.0, to be replaced) and two samples."""
    lines = ["[instrument]", 'id = "sphere-lctf"', "[tunable_filter]", f'model = "{model}"', 'port = "/dev/ttyUSB0"',
             "settle_s = 0.0", *([f"bands = {bands}"] if bands is not None else []),
             "[shutter]", 'port = "/dev/ttyUSB2"', 'model = "SC10"', "[camera]", 'backend = "sim"',
             "[acquisition]", "frames_averaged = 2", "dark_frames = 2", "warmup_checks = 2"]
    for sample in SAMPLES:
        lines += ["[[samples]]", f'id = "{sample}"', f'set = "{"training" if sample.startswith("train") else "test"}"',
                  'background = "bg"']
    path = folder / "sphere.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def signal_as_wait_begins(monkeypatch):
    """`arm()`: the next `time.sleep` call (the first slice of a wait, or the whole of it) sends
    SIGTERM to this process before sleeping; returns the list the moment of sending goes into."""
    real_sleep = time.sleep
    sent: list[float] = []

    def sleeping(seconds):
        if not sent:
            sent.append(time.monotonic())
            os.kill(os.getpid(), signal.SIGTERM)
        real_sleep(seconds)

    def arm() -> list[float]:
        monkeypatch.setattr(time, "sleep", sleeping)
        return sent

    return arm


def _stopped_within(sent: list[float], action) -> float:
    """Run `action` inside stop_requests(); it must raise Interrupted (SIGTERM); the seconds from
    the signal to the stop."""
    with interrupt.stop_requests(), pytest.raises(interrupt.Interrupted) as stopped:
        action()
    assert sent, "the wait ran to its end without a slice (a plain time.sleep bound before the test)"
    took = time.monotonic() - sent[0]
    assert stopped.value.signum == signal.SIGTERM and stopped.value.exit_status == 143
    return took


def test_a_stop_during_a_tunable_filters_settling_is_acted_on_at_once(no_leaks, signal_as_wait_begins):
    """settle_s = 30 after a tune: the stop comes within PROMPT_S, not after the 30 s."""
    with EmulatedPort(KuriosEmulator()) as port:
        with open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS[1:], settle_s=30.0) as lctf:
            sent = signal_as_wait_begins()
            took = _stopped_within(sent, lambda: lctf.select(500))
    assert took < PROMPT_S, took


def test_a_stop_during_a_varispec_warm_up_is_acted_on_at_once(no_leaks, signal_as_wait_begins):
    """A VariSpec's fixed warm-up (warmup_s = 30): the same."""
    with EmulatedPort(VariSpecEmulator()) as port:
        with open_filter(port.path, model="VariSpec-VIS", bands_nm=BANDS, warmup_s=30.0) as lctf:
            sent = signal_as_wait_begins()
            took = _stopped_within(sent, lambda: lctf.wait_until_ready(timeout_s=600.0))
    assert took < PROMPT_S, took


def test_a_stop_during_a_filter_wheel_move_is_acted_on_before_the_move_ends(no_leaks):
    """A move of minutes (the emulator's modelled move times 1000; the move timeout 20 s): the
    signal comes as the wheel receives pos=; the wait for the prompt that ends the move stops
    within PROMPT_S."""
    sent: list[float] = []

    class SignallingWheel(FilterWheelEmulator):
        def receive(self, data: bytes):
            if b"pos=" in data and not sent:
                sent.append(time.monotonic())
                os.kill(os.getpid(), signal.SIGTERM)
            return super().receive(data)

    with EmulatedPort(SignallingWheel(model="FW212C", position=12, move_time_scale=1000.0)) as port:  # a move of minutes
        with FilterWheel(port.path, model="FW212C", move_timeout_s=20.0) as wheel:
            took = _stopped_within(sent, lambda: wheel.move_to(6))
    assert took < PROMPT_S, took


def test_a_stop_during_the_lamps_warm_up_interval_is_acted_on_at_once(tmp_path, signal_as_wait_begins):
    """The acquisition's wait between two white-standard checks of the lamp's warm-up
    (`Settings.sleep`, by default 30 s): the same."""
    sent = signal_as_wait_begins()
    took = _stopped_within(sent, lambda: acquire.Settings().sleep(30.0))
    assert took < PROMPT_S, took


def test_a_camera_average_stops_between_its_frames():
    """`average(n)`: a stop asked for during the first frame ends it before the second."""

    class OneSecondFrames(Camera):
        snaps = 0
        sensor_shape, bit_depth, exposure_limits_s = (4, 4), 12, (0.001, 10.0)

        def __init__(self):
            super().__init__("slow")
            self.exposure_s = 1.0

        def _set_exposure(self, seconds):
            return seconds

        def _apply_roi_binning(self, roi, binning):
            pass

        def _snap(self):
            OneSecondFrames.snaps += 1
            if OneSecondFrames.snaps == 1:
                os.kill(os.getpid(), signal.SIGTERM)
            return np.zeros((4, 4), np.uint16)

        def _read_temperature(self):
            return None

    camera = OneSecondFrames()
    with interrupt.stop_requests(), pytest.raises(interrupt.Interrupted):
        camera.average(1000)
    assert OneSecondFrames.snaps == 1


def test_the_shutter_still_closes_when_a_stop_is_pending(no_leaks):
    """The clean-up after a stop (make_safe) runs shielded: the safe point in every serial poll
    does not cut the closing of the shutter short, and the stop stays recorded after it."""
    emulator = ShutterEmulator(closed=True)
    with EmulatedPort(emulator) as port, Shutter(port.path) as shutter:
        shutter.open_shutter()
        with interrupt.stop_requests():
            os.kill(os.getpid(), signal.SIGTERM)
            assert interrupt.requested() == signal.SIGTERM
            shutter.make_safe()
            assert emulator.closed
            with pytest.raises(interrupt.Interrupted):
                interrupt.check()


@pytest.mark.slow
def test_sigterm_during_the_settle_wait_stops_acquire_at_once(tmp_path):
    """The reproducer through the command line: settle_s = 60 in the profile (its limit); SIGTERM
    once the run is in its first settling (SESSION.partial/profile.json is written just before
    the warm-up's first tune, then the run waits 60 s): exit 143 well before, one line, no
    traceback, the shutter's clean-up done and the work folder kept for --resume."""
    profile = write_lctf_profile(tmp_path, model="Kurios-VIS", bands=[440, 460, 480])
    profile.write_text(profile.read_text().replace("settle_s = 0.0", "settle_s = 60.0"))
    out = tmp_path / "s"
    command = [sys.executable, "-m", "spherejax.cli", "acquire", "--profile", str(profile), "-o", str(out), "--emulate", "--yes"]
    with subprocess.Popen(command, env={**os.environ, "JAX_PLATFORMS": "cpu"}, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE) as process:
        wait_until(process, lambda: (tmp_path / "s.partial" / "profile.json").exists())
        time.sleep(1.0)  # well inside the 60 s wait that follows
        assert process.poll() is None, "the acquisition ended before the signal"
        sent = time.monotonic()
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=60)
    took, err = time.monotonic() - sent, err.decode()
    assert process.returncode == 143, err
    assert took < 30.0, took  # the process's whole exit, on a loaded machine; the wait is 60 s
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("spherejax: interrupted"), err
    assert sorted(os.listdir(tmp_path)) == ["s.partial", "sphere.toml"]


# ------------------------------------------------------------------------ bounded profile numbers

#: (profile line to add or replace, the key named, words of the limit): one per bounded number.
UNBOUNDED = [
    ("settle_s = 1e300", "tunable_filter.settle_s", "<= 60"),
    ("settle_s = inf", "tunable_filter.settle_s", "<= 60"),
    ("warmup_s = 1e300", "tunable_filter.warmup_s", "<= 3600"),
    ("warmup_timeout_s = 1e300", "tunable_filter.warmup_timeout_s", "<= 86400"),
]
ACQUISITION_UNBOUNDED = [
    ("warmup_interval_s = 1e300", "acquisition.warmup_interval_s", "<= 3600"),
    ("warmup_timeout_s = 1e300", "acquisition.warmup_timeout_s", "<= 86400"),
    ("frames_averaged = 9223372036854775807", "acquisition.frames_averaged", "<= 1000"),
    ("dark_frames = 100000", "acquisition.dark_frames", "<= 1000"),
    ("warmup_checks = 100000", "acquisition.warmup_checks", "<= 1000"),
]


def _one_line_naming(error: ProfileError, profile, key: str, limit: str) -> None:
    message = str(error)
    assert "\n" not in message and message.startswith(f"{profile}: {key}: "), message
    assert "(expected " in message and limit in message, message


@pytest.mark.parametrize("line, key, limit", UNBOUNDED, ids=[case[0] for case in UNBOUNDED])
def test_a_tunable_filters_wait_beyond_its_limit_is_refused_when_read(tmp_path, line, key, limit):
    name = line.split(" = ")[0]
    profile = write_lctf_profile(tmp_path, model="VariSpec-VIS")
    text = profile.read_text().replace("settle_s = 0.0", "" if name == "settle_s" else "settle_s = 0.0")
    profile.write_text(text.replace('port = "/dev/ttyUSB0"', f'port = "/dev/ttyUSB0"\n{line}', 1))
    with pytest.raises(ProfileError) as refused:
        load_profile(profile)
    _one_line_naming(refused.value, profile, key, limit)


@pytest.mark.parametrize("line, key, limit", ACQUISITION_UNBOUNDED, ids=[case[0] for case in ACQUISITION_UNBOUNDED])
def test_an_acquisition_number_beyond_its_limit_is_refused_when_read(tmp_path, line, key, limit):
    name = line.split(" = ")[0]
    profile = write_profile(tmp_path)
    lines = [x for x in profile.read_text().splitlines() if not x.startswith(f"{name} = ")]
    at = lines.index("[acquisition]") + 1
    profile.write_text("\n".join([*lines[:at], line, *lines[at:]]) + "\n")
    with pytest.raises(ProfileError) as refused:
        load_profile(profile)
    _one_line_naming(refused.value, profile, key, limit)


@pytest.mark.parametrize("option, value, key", [
    ("move_timeout_s", "1e300", "wheels.a.move_timeout_s"),
])
def test_a_wheel_move_timeout_beyond_its_limit_is_refused_when_read(tmp_path, option, value, key):
    profile = write_profile(tmp_path, move_timeout_s=value)
    with pytest.raises(ProfileError) as refused:
        load_profile(profile)
    _one_line_naming(refused.value, profile, key, "<= 600")


@pytest.mark.parametrize("backend, option, value, limit", [
    ("pvcam", "exposure_s", "1e300", "<= 3600"),
    ("genicam", "timeout_s", "1e300", "<= 3600"),
    ("genicam", "exposure_s", "1e300", "<= 3600"),
    ("sim", "image_shape", "[1000000, 1000000]", "<= 16384"),
])
def test_a_camera_option_beyond_its_limit_is_refused_when_read(tmp_path, backend, option, value, limit):
    profile = write_profile(tmp_path, extra="[layout]\nwhite_patch = [10, 20, 10, 20]\nholder = [40, 160, 30, 240]\n")
    profile.write_text(profile.read_text().replace('backend = "sim"', f'backend = "{backend}"\n{option} = {value}'))
    with pytest.raises(ProfileError) as refused:
        load_profile(profile)
    _one_line_naming(refused.value, profile, f"camera.{option}", limit)


def test_settle_s_1e300_is_refused_by_acquire_in_one_line_with_nothing_left(tmp_path, capsys):
    """The reproducer through the command line: exit 2, one line naming the file and the key, no
    traceback, no SESSION.partial (before: an OverflowError traceback once the devices moved)."""
    from spherejax import cli

    profile = write_lctf_profile(tmp_path, model="Kurios-VIS", bands=[440, 460])
    profile.write_text(profile.read_text().replace("settle_s = 0.0", "settle_s = 1e300"))
    status = cli.main(["acquire", "--profile", str(profile), "-o", str(tmp_path / "s"), "--emulate", "--yes"])
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.count("\n") == 1 and "tunable_filter.settle_s" in err and str(profile) in err, err
    assert "Traceback" not in err and "OverflowError" not in err
    assert sorted(os.listdir(tmp_path)) == ["sphere.toml"]


@pytest.mark.parametrize("make", [
    lambda: open_filter("loop://", model="Kurios-VIS", bands_nm=BANDS[1:], settle_s=float("inf")),
    lambda: open_filter("loop://", model="VariSpec-VIS", bands_nm=BANDS, warmup_s=float("nan")),
    lambda: open_filter("loop://", model="VariSpec-VIS", bands_nm=BANDS, timeout_s=float("inf")),
    lambda: FilterWheel("loop://", move_timeout_s=float("nan")),
    lambda: Shutter("loop://", settle_s=float("inf")),
], ids=["settle-inf", "warmup-nan", "timeout-inf", "move-timeout-nan", "shutter-settle-inf"])
def test_drivers_refuse_a_wait_without_end(make):
    """Through the API, without a profile: a NaN or infinite wait is a ValueError naming it."""
    with pytest.raises(ValueError, match="finite number of seconds"):
        make()


def test_interrupt_sleep_waits_in_slices_and_ignores_nan():
    """`interrupt.sleep` outside any stop handling is a plain wait; NaN and negative are none."""
    start = time.monotonic()
    interrupt.sleep(float("nan"))
    interrupt.sleep(-5.0)
    assert time.monotonic() - start < 0.05
    start = time.monotonic()
    interrupt.sleep(0.12)
    assert 0.12 <= time.monotonic() - start < 1.0


def test_quiet_settings_still_wait_through_interrupt_sleep():
    """The acquisition's default wait is the sliced one (not time.sleep)."""
    assert quiet_settings().sleep is interrupt.sleep
