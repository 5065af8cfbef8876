"""Shutter (Thorlabs SC10): golden byte transcripts and runs against the emulator.

``ens`` toggles, so the transcripts pin down the one thing that matters most: ``ens`` is written only
when ``closed?`` says the state must change, and the new state is confirmed with ``closed?``.
"""

from __future__ import annotations

import logging

import pytest

from .support import scripted, transcript
from spherejax_hw.emulators import EmulatedPort, ShutterEmulator
from spherejax_hw.errors import DeviceError, DeviceTimeout, PortError, ProtocolError
from spherejax_hw.shutter import Shutter

CONNECT = [
    (b"\r", b"\r> "),
    (b"id?\r", b"id?\rTHORLABS SC10 VERSION 1.07\r> "),
    (b"mode=1\r", b"mode=1\r> "),
]
CLOSED = (b"closed?\r", b"closed?\r1\r> ")
OPEN = (b"closed?\r", b"closed?\r0\r> ")
ENS = (b"ens\r", b"ens\r> ")

# Golden transcripts: operation -> (driver call, its result, [(bytes written, bytes answered)]).
OPERATIONS = {
    "is_closed": (lambda s: s.is_closed(), True, [CLOSED]),
    "open_when_closed": (lambda s: s.open_shutter(), None, [CLOSED, ENS, OPEN]),
    "open_when_open": (lambda s: s.open_shutter(), None, [OPEN]),  # no ens: it would close
    "close_when_open": (lambda s: s.close_shutter(), None, [OPEN, ENS, CLOSED]),
    "close_when_closed": (lambda s: s.close_shutter(), None, [CLOSED]),
    "make_safe_when_open": (lambda s: s.make_safe(), None, [OPEN, ENS, CLOSED]),
    "make_safe_when_closed": (lambda s: s.make_safe(), None, [CLOSED]),
}


@pytest.fixture
def emulated(no_leaks):
    """A closed SC10 on a pty and a connected driver (short timeouts for the fault tests)."""
    with EmulatedPort(ShutterEmulator(closed=True)) as port:
        with Shutter(port.path, timeout_s=0.5, settle_s=0.1) as shutter:
            yield port, shutter


# -- golden transcripts -----------------------------------------------------------------------------


def test_connect_transcript(monkeypatch):
    port = scripted(monkeypatch, CONNECT, 'scripted://sc10')
    with Shutter("scripted://sc10") as shutter:
        assert shutter.identity == "THORLABS SC10 VERSION 1.07"
    port.assert_done()
    assert port.transcript == transcript(CONNECT)
    assert port.settings["baudrate"] == 9600 and not port.is_open


@pytest.mark.parametrize("name", sorted(OPERATIONS))
def test_operation_transcript(monkeypatch, name):
    call, result, script = OPERATIONS[name]
    port = scripted(monkeypatch, CONNECT + script, 'scripted://sc10')
    with Shutter("scripted://sc10") as shutter:
        assert call(shutter) == result
    port.assert_done()
    assert port.transcript[2 * len(CONNECT) :] == transcript(script)


@pytest.mark.parametrize("name", sorted(OPERATIONS))
def test_emulator_speaks_the_golden_transcript(no_leaks, name):
    call, result, script = OPERATIONS[name]
    closed = script[0] == CLOSED
    with EmulatedPort(ShutterEmulator(closed=closed)) as port:
        with Shutter(port.path) as shutter:
            assert call(shutter) == result
        written = b"".join(data for kind, data in port.transcript if kind == "in")
        answered = b"".join(data for kind, data in port.transcript if kind == "out")
    assert written == b"".join(w for w, _ in CONNECT + script)
    assert answered == b"".join(a for _, a in CONNECT + script)


def test_shutter_that_does_not_move_is_device_error(monkeypatch):
    # closed? still 1 after ens (interlock tripped): polled until settle_s, never a second ens.
    port = scripted(monkeypatch, CONNECT + [CLOSED, ENS] + [CLOSED] * 50, 'scripted://sc10')
    with Shutter("scripted://sc10", settle_s=0.05) as shutter:
        with pytest.raises(DeviceError, match="still closed") as info:
            shutter.open_shutter()
    assert info.value.command == "ens" and info.value.reply == CLOSED[1]
    writes = [data for kind, data in port.transcript if kind == "write"]
    assert writes.count(b"ens\r") == 1


def test_bad_closed_value_is_protocol_error(monkeypatch):
    scripted(monkeypatch, CONNECT + [(b"closed?\r", b"closed?\r2\r> ")], 'scripted://sc10')
    with Shutter("scripted://sc10") as shutter, pytest.raises(ProtocolError, match="expected 0 or 1"):
        shutter.is_closed()


def test_wrong_identity_is_protocol_error_and_closes(monkeypatch):
    reply = b"id?\rCommand error CMD_NOT_DEFINED\r> "
    port = scripted(monkeypatch, CONNECT[:1] + [(b"id?\r", reply)], 'scripted://sc10')
    shutter = Shutter("scripted://sc10")
    with pytest.raises(DeviceError, match="CMD_NOT_DEFINED"):
        shutter.connect()
    assert not shutter.is_connected and not port.is_open


def test_make_safe_never_raises(monkeypatch, caplog):
    port = scripted(monkeypatch, CONNECT, 'scripted://sc10')
    with Shutter("scripted://sc10") as shutter:
        port.vanish()
        with caplog.at_level(logging.WARNING, logger="spherejax_hw.shutter"):
            shutter.make_safe()  # the port failed: logged, not raised
            shutter.make_safe()  # reconnecting fails too: logged, not raised
    assert len(caplog.records) == 2 and "could not make the shutter safe" in caplog.text


def test_make_safe_reconnects_after_a_port_error(monkeypatch):
    port = scripted(monkeypatch, CONNECT, 'scripted://sc10')
    with Shutter("scripted://sc10") as shutter:
        port.vanish()
        with pytest.raises(PortError):
            shutter.is_closed()
        port.reappear(CONNECT + [OPEN, ENS, CLOSED])
        shutter.make_safe()
        assert shutter.is_connected
    port.assert_done()


# -- against the emulator on a pty ------------------------------------------------------------------


def test_every_operation_over_a_pty(emulated):
    port, shutter = emulated
    emulator = port.emulator
    assert shutter.identity == "THORLABS SC10 VERSION 1.07" and emulator.mode == 1
    assert shutter.is_closed()
    shutter.open_shutter()
    assert not emulator.closed and not shutter.is_closed()
    shutter.open_shutter()
    assert not emulator.closed and emulator.toggles == 1  # already open: no second ens
    shutter.close_shutter()
    shutter.close_shutter()
    assert emulator.closed and emulator.toggles == 2
    shutter.open_shutter()
    shutter.make_safe()
    assert emulator.closed and emulator.toggles == 4


def test_connect_selects_manual_mode(no_leaks):
    with EmulatedPort(ShutterEmulator(mode=5)) as port, Shutter(port.path) as shutter:
        assert port.emulator.mode == 1
        shutter.open_shutter()
        assert not port.emulator.closed


def test_interlock_keeps_it_closed(emulated):
    port, shutter = emulated
    port.emulator.trip_interlock()
    with pytest.raises(DeviceError, match="still closed") as info:
        shutter.open_shutter()
    assert info.value.port == port.path


@pytest.mark.parametrize("ending", [b"\r", b"\n"])
def test_device_error_over_a_pty(no_leaks, ending):
    with EmulatedPort(ShutterEmulator(error_line_ending=ending)) as port, Shutter(port.path) as shutter:
        with pytest.raises(DeviceError) as info:
            shutter.command("mode=9")
        assert info.value.reply == b"mode=9\rCommand error CMD_ARG_INVALID" + ending + b"> "
        assert info.value.command == "mode=9" and info.value.port == port.path


def test_wrong_identity_over_a_pty(no_leaks):
    emulator = ShutterEmulator(identity="THORLABS FW102C/FW212C Filter Wheel version 1.07")
    with EmulatedPort(emulator) as port:
        with pytest.raises(ProtocolError, match="not a Thorlabs SC10"):
            Shutter(port.path).connect()


def test_stop_answering_is_timeout_and_make_safe_survives(emulated):
    port, shutter = emulated
    shutter.open_shutter()
    port.stop_answering()
    with pytest.raises(DeviceTimeout):
        shutter.close_shutter()
    shutter.make_safe()  # times out inside, does not raise
    port.resume_answering()
    shutter.make_safe()
    assert port.emulator.closed


def test_garbage_is_protocol_error(emulated):
    port, shutter = emulated
    port.answer_garbage()
    with pytest.raises(ProtocolError):
        shutter.is_closed()


def test_vanish_is_port_error(emulated):
    port, shutter = emulated
    port.vanish()
    with pytest.raises(PortError) as info:
        shutter.open_shutter()
    assert info.value.command == "closed?"
    assert not shutter.is_connected
    shutter.make_safe()  # the path is gone: logged, not raised
