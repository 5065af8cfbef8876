"""The emulated FW102C/FW212C and SC10 state machines, and the pty server with its faults.

State machines are checked byte for byte against the vendor protocol (docs/instrument.md); the server is
checked with a bare ``serial.Serial`` (no driver), so its bytes, faults and cleanup are seen directly.
"""

from __future__ import annotations

import os
import time

import pytest
import serial

from spherejax_hw.emulators import EmulatedPort, FilterWheelEmulator, ScriptedPort, ShutterEmulator

NOT_DEFINED = b"Command error CMD_NOT_DEFINED"
ARG_INVALID = b"Command error CMD_ARG_INVALID"


def wheel(**kwargs) -> FilterWheelEmulator:
    kwargs.setdefault("stray_on_open", b"")
    return FilterWheelEmulator(**kwargs)


def reply(emulator, data: bytes) -> bytes:
    """All bytes an instant emulator answers to ``data``."""
    chunks = emulator.receive(data)
    assert all(delay == 0 for delay, _ in chunks)
    return b"".join(chunk for _, chunk in chunks)


# -- filter wheel state machine ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "command, answer",
    [
        (b"*idn?", b"THORLABS FW102C/FW212C Filter Wheel version 1.07"),
        (b"pos?", b"1"),
        (b"pcount?", b"12"),
        (b"speed?", b"1"),
        (b"sensors?", b"1"),
        (b"trig?", b"0"),
        (b"baud?", b"1"),
    ],
)
def test_wheel_queries_echo_value_prompt(command, answer):
    assert reply(wheel(), command + b"\r") == command + b"\r" + answer + b"\r> "


@pytest.mark.parametrize(
    "command, attribute, value",
    [
        (b"pos=5", "position", 5),
        (b"pcount=6", "count", 6),
        (b"speed=0", "speed", 0),
        (b"sensors=0", "sensors", 0),
        (b"trig=1", "trigger", 1),
        (b"baud=0", "baud", 0),
    ],
)
def test_wheel_set_commands_echo_and_prompt(command, attribute, value):
    emulator = wheel()
    assert reply(emulator, command + b"\r") == command + b"\r> "
    assert getattr(emulator, attribute) == value


@pytest.mark.parametrize(
    "command, error",
    [
        (b"POS=2", NOT_DEFINED),  # upper case is rejected
        (b"*IDN?", NOT_DEFINED),
        (b"position?", NOT_DEFINED),
        (b"pos", NOT_DEFINED),
        (b"pos=0", ARG_INVALID),
        (b"pos=13", ARG_INVALID),
        (b"pos=x", ARG_INVALID),
        (b"pos=", ARG_INVALID),
        (b"pos=-1", ARG_INVALID),
        (b"pcount=8", ARG_INVALID),  # pcount accepts only 6 or 12
        (b"speed=2", ARG_INVALID),
        (b"sensors=on", ARG_INVALID),
        (b"trig=3", ARG_INVALID),
        (b"baud=2", ARG_INVALID),
    ],
)
@pytest.mark.parametrize("ending", [b"\r", b"\n"])
def test_wheel_errors(command, error, ending):
    emulator = wheel(error_line_ending=ending, position=4)
    assert reply(emulator, command + b"\r") == command + b"\r" + error + ending + b"> "
    assert emulator.position == 4


def test_fw102c_has_six_slots():
    emulator = wheel(model="FW102C")
    assert reply(emulator, b"pcount?\r") == b"pcount?\r6\r> "
    assert reply(emulator, b"pos=7\r") == b"pos=7\r" + ARG_INVALID + b"\r> "
    assert reply(emulator, b"pos=6\r") == b"pos=6\r> " and emulator.position == 6


def test_pcount_change_keeps_position_in_range():
    emulator = wheel(position=9)
    reply(emulator, b"pcount=6\r")
    assert emulator.position == 1 and emulator.count == 6


def test_save_stores_settings():
    emulator = wheel()
    assert reply(emulator, b"speed=0\rsave\r") == b"speed=0\r> save\r> "
    assert emulator.saved == {"pcount": 12, "speed": 0, "sensors": 1, "trig": 0, "baud": 1}


def test_line_assembly_across_chunks_lf_ignored_and_empty_line():
    emulator = wheel()
    assert emulator.receive(b"po") == [] and emulator.receive(b"s") == []
    assert reply(emulator, b"?\r\n") == b"pos?\r1\r> "
    assert reply(emulator, b"\r") == b"\r> "
    assert reply(emulator, b"pos?\rpcount?\r") == b"pos?\r1\r> pcount?\r12\r> "
    assert emulator.commands == ["pos?", "", "pos?", "pcount?"]


def test_stray_bytes_only_before_the_first_reply():
    emulator = FilterWheelEmulator()
    stray = b"\x00\x00Command error CMD_NOT_DEFINED\r> "
    assert emulator.stray_on_open == stray
    assert reply(emulator, b"\r") == stray + b"\r> "
    assert reply(emulator, b"\r") == b"\r> "


def test_prompt_without_trailing_space():
    assert reply(wheel(prompt=b">"), b"pos?\r") == b"pos?\r1\r>"


def test_move_holds_the_prompt_back():
    emulator = wheel(move_time_scale=1.0, position=1)
    assert emulator.receive(b"pos=2\r") == [(0.0, b"pos=2\r"), (pytest.approx(0.95), b"> ")]
    assert emulator.position == 2
    assert emulator.receive(b"pos=2\r") == [(0.0, b"pos=2\r> ")]  # already there: no wait


def test_move_times_follow_the_vendor_figures():
    emulator = wheel()
    assert emulator.move_time_s(1, 2) < 1.0  # under 1 s to the next slot
    assert emulator.move_time_s(1, 12) == emulator.move_time_s(1, 2)  # the short way round
    assert emulator.move_time_s(1, 5) == pytest.approx(2.6)  # about 2.5 s typical
    emulator.speed = 0
    assert emulator.move_time_s(1, 7) == pytest.approx(7.0)  # slow mode, longest move
    assert max(emulator.move_time_s(1, t) for t in range(1, 13)) == pytest.approx(7.0)


def test_front_panel_presses():
    emulator = wheel(position=12)
    emulator.press_button()
    assert emulator.position == 1
    emulator.press_button(forward=False)
    assert emulator.position == 12
    emulator.press_button_during_next_move(2)
    reply(emulator, b"pos=3\r")
    assert emulator.position == 5
    reply(emulator, b"pos=3\r")
    assert emulator.position == 3


def test_wheel_constructor_validation():
    with pytest.raises(ValueError):
        FilterWheelEmulator(model="FW103C")
    with pytest.raises(ValueError):
        FilterWheelEmulator(model="FW102C", position=7)
    with pytest.raises(ValueError):
        FilterWheelEmulator(error_line_ending=b"\r\n")
    with pytest.raises(ValueError):
        FilterWheelEmulator(move_time_scale=-1)


# -- SC10 state machine -----------------------------------------------------------------------------


def test_sc10_queries():
    emulator = ShutterEmulator()
    assert reply(emulator, b"id?\r") == b"id?\rTHORLABS SC10 VERSION 1.07\r> "
    for command, value in [(b"ens?", b"0"), (b"closed?", b"1"), (b"mode?", b"1"), (b"open?", b"100"),
                           (b"shut?", b"100"), (b"interlock?", b"0"), (b"baud?", b"0")]:
        assert reply(emulator, command + b"\r") == command + b"\r" + value + b"\r> "


def test_sc10_ens_toggles():
    emulator = ShutterEmulator(closed=True)
    assert reply(emulator, b"ens\r") == b"ens\r> "
    assert not emulator.closed and reply(emulator, b"closed?\r") == b"closed?\r0\r> "
    assert reply(emulator, b"ens?\r") == b"ens?\r1\r> "
    reply(emulator, b"ens\r")
    assert emulator.closed and emulator.toggles == 2


def test_sc10_settings_and_errors():
    emulator = ShutterEmulator(error_line_ending=b"\n")
    assert reply(emulator, b"mode=3\r") == b"mode=3\r> " and emulator.mode == 3
    assert reply(emulator, b"open=250\rshut=40\r") == b"open=250\r> shut=40\r> "
    assert (emulator.open_ms, emulator.shut_ms) == (250, 40)
    assert reply(emulator, b"baud=1\rsave\r") == b"baud=1\r> save\r> "
    assert emulator.saved == {"mode": 3, "open": 250, "shut": 40, "baud": 1}
    for bad in (b"mode=0", b"mode=6", b"open=-1", b"baud=2"):
        assert reply(emulator, bad + b"\r") == bad + b"\r" + ARG_INVALID + b"\n> "
    for bad in (b"ENS", b"close", b"closed"):
        assert reply(emulator, bad + b"\r") == bad + b"\r" + NOT_DEFINED + b"\n> "


def test_sc10_opens_only_in_manual_mode_with_interlock_intact():
    emulator = ShutterEmulator(closed=False, mode=2)
    assert emulator.closed  # timed modes are not run: reported closed
    emulator.mode = 1
    assert not emulator.closed
    emulator.trip_interlock()
    assert emulator.closed and reply(emulator, b"interlock?\r") == b"interlock?\r1\r> "
    reply(emulator, b"ens\r")
    assert emulator.closed
    emulator.reset_interlock()
    assert not emulator.closed  # enabled by the ens above
    emulator.closed = True
    assert not emulator.enabled
    with pytest.raises(ValueError):
        ShutterEmulator(mode=0)


# -- the pty server ---------------------------------------------------------------------------------


def open_serial(path):
    return serial.Serial(path, 115200, timeout=0.05)


def read_for(ser, seconds):
    out = bytearray()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += ser.read(256)
    return bytes(out)


def read_until_prompt(ser, seconds=2.0):
    out = bytearray()
    end = time.monotonic() + seconds
    while not out.rstrip().endswith(b">") and time.monotonic() < end:
        out += ser.read(256)
    return bytes(out)


def test_server_round_trip_and_transcript(no_leaks):
    with EmulatedPort(wheel()) as port:
        assert port.is_running and port.path.startswith("/dev/")
        with open_serial(port.path) as ser:
            ser.write(b"pos=3\r")
            assert read_until_prompt(ser) == b"pos=3\r> "
            ser.write(b"pos?\r")
            assert read_until_prompt(ser) == b"pos?\r3\r> "
        assert port.emulator.position == 3
        assert list(port.transcript) == [("in", b"pos=3\r"), ("out", b"pos=3\r> "),
                                         ("in", b"pos?\r"), ("out", b"pos?\r3\r> ")]
    assert not port.is_running and not port.holds_pty


def test_a_port_holds_its_pty_from_start_to_stop(no_leaks):
    """What the fault tests ask instead of whether the path exists (the kernel gives a freed
    /dev/pts number to the next pty opened anywhere, another test worker's included)."""
    port = EmulatedPort(wheel())
    assert not port.holds_pty
    with port:
        assert port.holds_pty and os.path.exists(port.path)
    assert not port.holds_pty


def test_server_stray_bytes_reach_the_first_reader(no_leaks):
    with EmulatedPort(FilterWheelEmulator()) as port, open_serial(port.path) as ser:
        ser.write(b"\r")
        assert read_for(ser, 0.2) == b"\x00\x00Command error CMD_NOT_DEFINED\r> \r> "


def test_server_start_once_and_stop_idempotent(no_leaks):
    port = EmulatedPort(ShutterEmulator()).start()
    with pytest.raises(RuntimeError):
        port.start()
    port.stop()
    port.stop()
    assert "ShutterEmulator" in repr(port)


def test_server_delays_the_prompt_and_stops_mid_move(no_leaks):
    emulator = wheel(move_time_scale=0.1)
    with EmulatedPort(emulator) as port, open_serial(port.path) as ser:
        ser.write(b"pos=7\r")
        start = time.monotonic()
        assert read_until_prompt(ser) == b"pos=7\r> "
        assert 0.35 <= time.monotonic() - start < 2.0  # 3.7 s x 0.1; a loaded machine may be late
    slow = wheel(move_time_scale=1000.0)
    with EmulatedPort(slow) as port, open_serial(port.path) as ser:
        ser.write(b"pos=7\r")
        assert read_for(ser, 0.2) == b"pos=7\r"
        start = time.monotonic()
    assert time.monotonic() - start < 2.0  # stop() did not wait for the hour-long move


def test_fault_stop_answering_and_resume(no_leaks):
    with EmulatedPort(wheel()) as port, open_serial(port.path) as ser:
        port.stop_answering()
        ser.write(b"pos=2\r")
        assert read_for(ser, 0.2) == b""
        assert port.emulator.position == 1  # a dead unit does not act on commands either
        port.resume_answering()
        ser.write(b"pos?\r")
        assert read_until_prompt(ser) == b"pos?\r1\r> "


def test_fault_garbage(no_leaks):
    with EmulatedPort(wheel()) as port, open_serial(port.path) as ser:
        port.answer_garbage()
        ser.write(b"pos?\r")
        junk = read_for(ser, 0.2)
        assert len(junk) == len(b"pos?\r") + 8
        assert not set(junk) & set(b"\r\n\x00>" + bytes(range(ord("A"), ord("z") + 1)))


def test_fault_vanish(no_leaks):
    with EmulatedPort(wheel()) as port:
        ser = open_serial(port.path)
        try:
            port.vanish()
            assert not port.is_running and not port.holds_pty
            with pytest.raises(serial.SerialException):
                ser.write(b"pos?\r")
            with pytest.raises(serial.SerialException):
                ser.read(1)
        finally:
            ser.close()
        with pytest.raises(serial.SerialException):
            open_serial(port.path)


def test_many_ports_leave_nothing_behind(no_leaks):
    ports = [EmulatedPort(wheel()).start() for _ in range(8)]
    assert len({p.path for p in ports}) == 8
    for p in ports:
        p.stop()


# -- the scripted port ------------------------------------------------------------------------------


def test_scripted_port_replays_and_checks():
    port = ScriptedPort([(b"pos?\r", b"pos?\r1\r> ")])
    ser = port.serial_for_url("scripted://x", baudrate=115200, timeout=0.0)
    assert ser is port and port.settings == {"baudrate": 115200, "timeout": 0.0}
    ser.write(b"pos")
    assert ser.in_waiting == 0
    ser.write(b"?\r")
    assert ser.read(100) == b"pos?\r1\r> " and ser.read(1) == b""
    port.assert_done()
    with pytest.raises(AssertionError, match="script expects None"):
        ser.write(b"pos=1\r")
    bad = ScriptedPort([(b"pos?\r", b"")])
    with pytest.raises(AssertionError, match=r"script expects b'pos\?\\r'"):
        bad.serial_for_url("x").write(b"POS?\r")
    with pytest.raises(AssertionError, match="never written"):
        bad.assert_done()
