"""Liquid-crystal tunable filters (hw.tunablefilter): golden byte transcripts of each driver
operation through a scripted port, and runs against the emulators (hw.tunablefilter_emulators) on
pseudo-terminals, faults included.

The transcripts pin the protocol facts the drivers rely on (docs/instrument.md, "Liquid-crystal
tunable filters"): the Kurios's ``KEY=value`` commands and ``KEY?`` queries answered before a
``>`` prompt, with no echo; the VariSpec's echoed lines, ``W 550.000`` and ``V?``, ESC before
``R 1``; and both readings the drivers accept where the manuals leave a detail open.
"""

from __future__ import annotations

import pytest

from .support import scripted, transcript
from spherejax_hw.emulators import EmulatedPort
from spherejax_hw.errors import DeviceError, DeviceTimeout, PortError, ProtocolError
from spherejax_hw.tunablefilter import KuriosFilter, VariSpecFilter, open_filter
from spherejax_hw.tunablefilter_emulators import KuriosEmulator, VariSpecEmulator

BANDS = list(range(420, 701, 20))

KURIOS_CONNECT = [
    (b"\r", b"CMD_NOT_DEFINED\r>"),
    (b"*IDN?\r", b"THORLABS KURIOS-VB1 SN-M00251234 HW1.0 FW3.1 CN-M00250987\r>"),
    (b"SP?\r", b"WLmax=730.000\rWLmin=420.000\r>"),
    (b"OH?\r", b"OH=271\r>"),
    (b"OM=1\r", b">"),
    (b"BW=2\r", b">"),
]
VARISPEC_CONNECT = [
    (b"\x1b", b""),
    (b"\x1b", b""),
    (b"R 1\r", b"R 1\r"),
    (b"V?\r", b"V?\rV   1.32  400.00  720.00 50527\r"),
]


class FakeClock:
    """A clock the driver's sleep advances, shared with the emulator's warm-up."""

    def __init__(self):
        self.now = 0.0
        self.slept = []

    def __call__(self):
        return self.now

    def sleep(self, seconds):
        self.slept.append(seconds)
        self.now += seconds


def test_kurios_connect_and_select_golden_transcript(monkeypatch):
    """Identity, range (SP?), bandwidth modes (OH?), manual output mode, bandwidth, then one band:
    WL= tunes, the settle time is waited, WL? reads back."""
    select = [(b"WL=560.000\r", b">"), (b"WL?\r", b"WL=560.000\r>")]
    port = scripted(monkeypatch, KURIOS_CONNECT + select, "scripted://kurios")
    clock = FakeClock()
    with KuriosFilter("scripted://kurios", bands_nm=BANDS, settle_s=0.25, sleep=clock.sleep) as lctf:
        assert lctf.identity.startswith("THORLABS KURIOS-VB1") and lctf.range_nm == (420.0, 730.0)
        lctf.check()
        assert lctf.select(560) == 560.0 and lctf.band_in_path() == 560
        assert clock.slept == [0.25]
        assert lctf.image_metadata(560, 560.0) == {"tunable_filter": "Kurios-VIS", "wavelength_nm": 560.0,
                                                   "bandwidth": "wide"}
    port.assert_done()
    assert port.transcript == transcript(KURIOS_CONNECT + select)


def test_kurios_readings_the_manual_leaves_open_are_accepted(monkeypatch):
    """An echo of the command before the reply, a reply without its KEY= prefix, and an error
    line in place of the prompt-terminated reply: the same results."""
    script = KURIOS_CONNECT + [
        (b"WL=600.000\r", b"WL=600.000\r>"),  # echoed
        (b"WL?\r", b"WL?\r600.000\r>"),  # echoed, no prefix
        (b"WL=900.000\r", b"CMD_ARG_INVALID\r>"),
    ]
    scripted(monkeypatch, script, "scripted://kurios")
    with KuriosFilter("scripted://kurios", bands_nm=BANDS, settle_s=0, sleep=lambda s: None) as lctf:
        assert lctf.select(600) == 600.0
        with pytest.raises(DeviceError, match="device error CMD_ARG_INVALID") as info:
            lctf.select(900)
        assert "\n" not in str(info.value) and lctf.band_in_path() is None


def test_varispec_connect_and_select_golden_transcript(monkeypatch):
    """ESC and the reset on connect, V? for the range, then W 550.000 echoed and W? read back."""
    select = [(b"W 550.000\r", b"W 550.000\r"), (b"W?\r", b"W?\rW 550.000\r")]
    port = scripted(monkeypatch, VARISPEC_CONNECT + select, "scripted://varispec")
    with VariSpecFilter("scripted://varispec", bands_nm=BANDS, settle_s=0, sleep=lambda s: None) as lctf:
        assert lctf.range_nm == (400.0, 720.0) and "50527" in lctf.identity
        assert lctf.select(550) == 550.0
    port.assert_done()
    assert port.transcript == transcript(VARISPEC_CONNECT + select)


@pytest.fixture
def kurios_port(no_leaks):
    clock = FakeClock()
    with EmulatedPort(KuriosEmulator(warmup_s=3.0, clock=clock)) as port:
        yield port, clock


def test_kurios_against_its_emulator(kurios_port):
    port, clock = kurios_port
    with open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS, bandwidth="narrow", settle_s=0.05,
                     sleep=clock.sleep) as lctf:
        assert port.emulator.bandwidth == 8 and port.emulator.output_mode == 1
        # Warming up for 3 s of the shared clock: polled every 0.5 s until ST? says ready.
        assert lctf.wait_until_ready(timeout_s=10.0)["status"] == "ready"
        assert clock.now >= 3.0 and port.emulator.commands.count("ST?") == 7
        for band in (420, 560, 700):
            assert lctf.select(band) == band and port.emulator.wavelength_nm == band
        assert lctf.band_in_path() == 700


def test_kurios_warm_up_that_never_ends_is_one_line(no_leaks):
    clock = FakeClock()
    with EmulatedPort(KuriosEmulator(warmup_s=1e9, clock=clock)) as port:
        with open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS, sleep=clock.sleep) as lctf:
            with pytest.raises(DeviceTimeout, match=r"'ST\?': still warming up after 2 s") as info:
                lctf.wait_until_ready(timeout_s=2.0)
    assert "\n" not in str(info.value) and port.path in str(info.value)


def test_a_band_outside_the_range_the_filter_reports_is_refused_before_anything_moves(no_leaks):
    """A head that reports 450-730 nm (not what the profile's model promises): check() names the
    bands outside it; nothing was tuned."""
    with EmulatedPort(KuriosEmulator(range_nm=(450.0, 730.0))) as port:
        with open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS, sleep=lambda s: None) as lctf:
            with pytest.raises(DeviceError, match=r"450-730 nm; bands \[420, 440\] nm lie outside it"):
                lctf.check()
        assert not any(command.startswith("WL=") for command in port.emulator.commands)


def test_a_bandwidth_the_head_lacks_is_refused_at_connect(no_leaks):
    with EmulatedPort(KuriosEmulator(features=0x0102)) as port:  # VIS, wide only
        with pytest.raises(DeviceError, match=r"no narrow bandwidth mode \(OH=258\)"):
            open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS, bandwidth="narrow").connect()


def test_another_device_on_the_port_is_refused(no_leaks):
    from spherejax_hw.emulators import ShutterEmulator

    with EmulatedPort(ShutterEmulator()) as port:
        with pytest.raises((ProtocolError, DeviceError)) as info:
            open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS).connect()
    assert "\n" not in str(info.value)


def test_varispec_against_its_emulator_and_a_refused_wavelength(no_leaks):
    with EmulatedPort(VariSpecEmulator()) as port:
        with open_filter(port.path, model="VariSpec-VIS", bands_nm=[400, *BANDS], settle_s=0,
                         sleep=lambda s: None) as lctf:
            assert lctf.wait_until_ready(timeout_s=1.0) == {"warmup_s": 0.0, "status": "waited"}
            assert lctf.select(400) == 400.0
            with pytest.raises(DeviceError, match=r"refused the wavelength \(reply 'W\*'\)") as info:
                lctf.select(760)
            assert "\n" not in str(info.value)
            # The fault was reset (ESC, R 1): the next band tunes.
            assert not port.emulator.fault and lctf.select(500) == 500.0


@pytest.mark.parametrize("fault", ["stop_answering", "vanish"])
def test_a_filter_that_stops_answering_or_vanishes_is_one_line(no_leaks, fault):
    with EmulatedPort(KuriosEmulator()) as port:
        lctf = open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS, timeout_s=0.3, sleep=lambda s: None)
        with lctf:
            getattr(port, fault)()
            with pytest.raises(DeviceTimeout if fault == "stop_answering" else PortError) as info:
                lctf.select(500)
    assert "\n" not in str(info.value) and port.path in str(info.value)


def test_an_unknown_model_is_refused():
    with pytest.raises(ValueError, match=r"model 'Kurios-UV': expected one of \['Kurios-NIR', 'Kurios-VIS', 'VariSpec-VIS'\]"):
        open_filter("/dev/null", model="Kurios-UV", bands_nm=BANDS)


def test_a_stop_request_during_a_long_warm_up_stops_it_within_one_poll(no_leaks):
    """SIGTERM while the acquisition waits for a Kurios's warm-up (it can take minutes): the wait
    the acquisition gives the driver is a safe point (`spherejax.interrupt`), so the run stops
    within one 0.5 s poll instead of after the warm-up timeout."""
    import os
    import signal
    import threading
    import time

    from spherejax import interrupt

    with EmulatedPort(KuriosEmulator(warmup_s=1e9)) as port:
        with open_filter(port.path, model="Kurios-VIS", bands_nm=BANDS) as lctf:  # the default wait
            timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM))
            start = time.monotonic()
            with interrupt.stop_requests(), pytest.raises(interrupt.Interrupted) as info:
                timer.start()
                lctf.wait_until_ready(timeout_s=600.0)
            timer.join()
    assert info.value.signum == signal.SIGTERM and time.monotonic() - start < 2.0
