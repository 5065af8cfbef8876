"""FilterWheel (Thorlabs FW102C / FW212C): golden byte transcripts and runs against the emulator.

Golden transcripts replay hand-written vendor-protocol bytes through ``ScriptedPort`` and assert the
exact bytes the driver writes and reads. The same operations then run over a real pseudo-terminal
against ``FilterWheelEmulator``, and the emulator's side of the pty must match the golden bytes.
"""

from __future__ import annotations

import pytest

from .support import scripted, transcript
from spherejax_hw.emulators import EmulatedPort, FilterWheelEmulator
from spherejax_hw.errors import DeviceError, DeviceTimeout, PortError, ProtocolError
from spherejax_hw.filterwheel import MODELS, FilterWheel

STRAY = b"\x00\x00Command error CMD_NOT_DEFINED\r> "
IDN = b"THORLABS FW102C/FW212C Filter Wheel version 1.07"
CONNECT = [
    (b"\r", STRAY + b"\r> "),
    (b"*idn?\r", b"*idn?\r" + IDN + b"\r> "),
    (b"pcount?\r", b"pcount?\r12\r> "),
    (b"sensors=0\r", b"sensors=0\r> "),
]

# Golden transcripts: operation -> (driver call, its result, [(bytes written, bytes answered)]).
OPERATIONS = {
    "pcount": (lambda w: w.position_count(), 12, [(b"pcount?\r", b"pcount?\r12\r> ")]),
    "pos": (lambda w: w.position(), 1, [(b"pos?\r", b"pos?\r1\r> ")]),
    "move_to": (lambda w: w.move_to(7), 7, [(b"pos=7\r", b"pos=7\r> "), (b"pos?\r", b"pos?\r7\r> ")]),
    "sensors": (lambda w: w.sensors(), False, [(b"sensors?\r", b"sensors?\r0\r> ")]),
    "set_sensors": (lambda w: w.set_sensors(True), None, [(b"sensors=1\r", b"sensors=1\r> ")]),
    "speed": (lambda w: w.speed(), 1, [(b"speed?\r", b"speed?\r1\r> ")]),
    "set_speed": (lambda w: w.set_speed(False), None, [(b"speed=0\r", b"speed=0\r> ")]),
    "set_position_count": (lambda w: w.set_position_count(12), None, [(b"pcount=12\r", b"pcount=12\r> ")]),
}


@pytest.fixture
def emulated(no_leaks):
    """A default FW212C on a pty and a connected driver (short timeouts for the fault tests)."""
    with EmulatedPort(FilterWheelEmulator()) as port:
        with FilterWheel(port.path, timeout_s=0.5, move_timeout_s=1.0) as wheel:
            yield port, wheel


# -- golden transcripts -----------------------------------------------------------------------------


def test_connect_transcript(monkeypatch):
    port = scripted(monkeypatch, CONNECT, 'scripted://wheel')
    with FilterWheel("scripted://wheel", model="FW212C") as wheel:
        assert wheel.identity == IDN.decode()
        assert wheel.is_connected
    port.assert_done()
    assert port.transcript == transcript(CONNECT)
    assert port.settings["baudrate"] == 115200 and not port.is_open


@pytest.mark.parametrize("name", sorted(OPERATIONS))
def test_operation_transcript(monkeypatch, name):
    call, result, script = OPERATIONS[name]
    port = scripted(monkeypatch, CONNECT + script, 'scripted://wheel')
    with FilterWheel("scripted://wheel") as wheel:
        assert call(wheel) == result
    port.assert_done()
    assert port.transcript[2 * len(CONNECT) :] == transcript(script)


@pytest.mark.parametrize("name", sorted(OPERATIONS))
def test_emulator_speaks_the_golden_transcript(no_leaks, name):
    """The emulator on a pty receives exactly the golden writes and sends exactly the golden replies."""
    call, result, script = OPERATIONS[name]
    with EmulatedPort(FilterWheelEmulator()) as port:
        with FilterWheel(port.path) as wheel:
            assert call(wheel) == result
        written = b"".join(data for kind, data in port.transcript if kind == "in")
        answered = b"".join(data for kind, data in port.transcript if kind == "out")
    assert written == b"".join(w for w, _ in CONNECT + script)
    assert answered == b"".join(a for _, a in CONNECT + script)


def test_connect_tolerates_prompt_without_space_and_lf_errors(monkeypatch):
    script = [
        (b"\r", b"\x00Command error CMD_NOT_DEFINED\n>"),
        (b"*idn?\r", b"*idn?\r" + IDN + b"\r>"),
        (b"pcount?\r", b"pcount?\r6\r>"),
        (b"sensors=0\r", b"sensors=0\r>"),
    ]
    port = scripted(monkeypatch, script, 'scripted://wheel')
    with FilterWheel("scripted://wheel", model="FW102C") as wheel:
        assert wheel.identity == IDN.decode()
    port.assert_done()


def test_move_read_back_mismatch_transcript(monkeypatch):
    script = [(b"pos=3\r", b"pos=3\r> "), (b"pos?\r", b"pos?\r4\r> ")]
    port = scripted(monkeypatch, CONNECT + script, 'scripted://wheel')
    with FilterWheel("scripted://wheel") as wheel, pytest.raises(DeviceError) as info:
        wheel.move_to(3)
    port.assert_done()
    assert info.value.command == "pos=3" and info.value.reply == b"pos?\r4\r> "
    assert "reads slot 4" in str(info.value)


def test_out_of_range_slot_sends_nothing(monkeypatch):
    port = scripted(monkeypatch, CONNECT, 'scripted://wheel')
    with FilterWheel("scripted://wheel") as wheel:
        for slot in (0, 13, -1):
            with pytest.raises(ValueError, match="outside 1..12"):
                wheel.move_to(slot)
        for slot in (True, 2.0, "3"):
            with pytest.raises(TypeError):
                wheel.move_to(slot)
    port.assert_done()
    assert port.transcript == transcript(CONNECT)  # not one byte after connect


def test_wrong_identity_is_protocol_error_and_closes(monkeypatch):
    reply = b"*idn?\rTHORLABS SC10 VERSION 1.07\r> "
    port = scripted(monkeypatch, [CONNECT[0], (b"*idn?\r", reply)], 'scripted://wheel')
    wheel = FilterWheel("scripted://wheel")
    with pytest.raises(ProtocolError, match="not a Thorlabs FW102C/FW212C") as info:
        wheel.connect()
    assert info.value.command == "*idn?" and info.value.reply == reply
    assert not wheel.is_connected and not port.is_open


def test_model_mismatch_is_protocol_error(monkeypatch):
    script = CONNECT[:2] + [(b"pcount?\r", b"pcount?\r6\r> ")]
    scripted(monkeypatch, script, 'scripted://wheel')
    with pytest.raises(ProtocolError, match="6 positions but an FW212C has 12"):
        FilterWheel("scripted://wheel", model="FW212C").connect()


def test_unparsable_values_are_protocol_errors(monkeypatch):
    script = [(b"pos?\r", b"pos?\rthree\r> "), (b"pcount?\r", b"pcount?\r8\r> "), (b"speed?\r", b"speed?\r2\r> ")]
    scripted(monkeypatch, CONNECT + script, 'scripted://wheel')
    with FilterWheel("scripted://wheel") as wheel:
        with pytest.raises(ProtocolError, match="expected an integer"):
            wheel.position()
        with pytest.raises(ProtocolError, match=r"expected one of \[6, 12\]"):
            wheel.position_count()
        with pytest.raises(ProtocolError):
            wheel.speed()


def test_constructor_validation():
    assert MODELS == {"FW102C": 6, "FW212C": 12}
    with pytest.raises(ValueError):
        FilterWheel("x", model="FW103C")
    with pytest.raises(ValueError):
        FilterWheel("x", move_timeout_s=0)
    with pytest.raises(PortError, match="not connected"):
        FilterWheel("x").move_to(1)
    with pytest.raises(ValueError):
        FilterWheel("x").set_position_count(8)


# -- against the emulator on a pty ------------------------------------------------------------------


def test_every_operation_over_a_pty(emulated):
    port, wheel = emulated
    emulator = port.emulator
    assert "FW102C/FW212C" in wheel.identity
    assert emulator.sensors == 0  # connect switched the sensors off for imaging
    assert wheel.position_count() == 12 and wheel.position() == 1
    for slot in (2, 12, 7, 7, 1):
        assert wheel.move_to(slot) == slot
        assert emulator.position == slot == wheel.position()
    assert not wheel.sensors()
    wheel.set_sensors(True)
    assert wheel.sensors() and emulator.sensors == 1
    wheel.set_speed(False)
    assert wheel.speed() == 0 == emulator.speed
    wheel.set_speed(True)
    assert wheel.speed() == 1
    wheel.set_position_count(6)
    assert wheel.position_count() == 6 == emulator.count
    with pytest.raises(ValueError, match="outside 1..6"):
        wheel.move_to(7)


@pytest.mark.parametrize("ending", [b"\r", b"\n"])
def test_device_error_names_port_command_reply(no_leaks, ending):
    emulator = FilterWheelEmulator(error_line_ending=ending)
    with EmulatedPort(emulator) as port, FilterWheel(port.path) as wheel:
        with pytest.raises(DeviceError) as info:
            wheel.command("pos=13")  # the driver's own range check would stop move_to(13)
        error = info.value
        assert error.port == port.path and error.command == "pos=13"
        assert error.reply == b"pos=13\rCommand error CMD_ARG_INVALID" + ending + b"> "
        assert str(error).startswith(f"{port.path}: 'pos=13': device error Command error CMD_ARG_INVALID (reply ")
        with pytest.raises(DeviceError, match="CMD_NOT_DEFINED"):
            wheel.command("POS=2")  # upper case is rejected
        assert wheel.move_to(3) == 3  # the session goes on after a device error


@pytest.mark.parametrize("stray", [b"", STRAY, b"\x00" * 5 + b"Command error CMD_NOT_DEFINED\n>"])
@pytest.mark.parametrize("prompt", [b"> ", b">"])
def test_connect_variants(no_leaks, stray, prompt):
    emulator = FilterWheelEmulator(model="FW102C", stray_on_open=stray, prompt=prompt, error_line_ending=b"\n")
    with EmulatedPort(emulator) as port, FilterWheel(port.path, model="FW102C") as wheel:
        assert wheel.move_to(6) == 6 and port.emulator.position == 6


def test_reconnect_on_the_same_port(no_leaks):
    with EmulatedPort(FilterWheelEmulator()) as port:
        with FilterWheel(port.path) as wheel:
            wheel.move_to(5)
        with FilterWheel(port.path) as wheel:
            assert wheel.position() == 5


def test_wrong_identity_over_a_pty(no_leaks):
    emulator = FilterWheelEmulator(identity="THORLABS SC10 VERSION 1.07")
    with EmulatedPort(emulator) as port:
        wheel = FilterWheel(port.path)
        with pytest.raises(ProtocolError, match="not a Thorlabs FW102C/FW212C") as info:
            wheel.connect()
        assert info.value.port == port.path and b"SC10" in info.value.reply
        assert not wheel.is_connected


def test_model_mismatch_over_a_pty(no_leaks):
    with EmulatedPort(FilterWheelEmulator(model="FW102C")) as port:
        with pytest.raises(ProtocolError, match="6 positions"):
            FilterWheel(port.path, model="FW212C").connect()


def test_move_timeout(no_leaks):
    # 1 -> 7 on an FW212C is the longest move (6 slots, ~3.9 s); scaled x100 it cannot end in 0.3 s.
    emulator = FilterWheelEmulator(move_time_scale=100.0)
    with EmulatedPort(emulator) as port, FilterWheel(port.path, move_timeout_s=0.3) as wheel:
        with pytest.raises(DeviceTimeout, match="echo but no prompt within 0.3 s") as info:
            wheel.move_to(7)
        assert info.value.command == "pos=7" and info.value.reply == b"pos=7\r"
    # Leaving the with blocks stopped the server mid-move: no_leaks checks the thread is gone.


def test_scaled_move_time_is_waited_for(no_leaks):
    emulator = FilterWheelEmulator(move_time_scale=0.05)
    with EmulatedPort(emulator) as port, FilterWheel(port.path, move_timeout_s=2.0) as wheel:
        assert wheel.move_to(7) == 7
    assert emulator.moves == [(1, 7, pytest.approx(0.4 + 0.55 * 6))]


def test_front_panel_move_is_detected(emulated):
    port, wheel = emulated
    port.emulator.press_button_during_next_move()
    with pytest.raises(DeviceError, match="reads slot 4 after the move, not 3") as info:
        wheel.move_to(3)
    assert info.value.port == port.path and info.value.command == "pos=3"
    assert info.value.reply == b"pos?\r4\r> "
    port.emulator.press_button(forward=False)
    assert wheel.position() == 3


def test_stop_answering_is_timeout(emulated):
    port, wheel = emulated
    port.stop_answering()
    with pytest.raises(DeviceTimeout, match="no answer"):
        wheel.position()
    with pytest.raises(DeviceTimeout):
        wheel.move_to(2)
    port.resume_answering()
    assert wheel.move_to(2) == 2


def test_garbage_is_protocol_error(emulated):
    port, wheel = emulated
    port.answer_garbage()
    with pytest.raises(ProtocolError, match="without the echo") as info:
        wheel.position()
    assert info.value.reply and b">" not in info.value.reply
    port.resume_answering()
    assert wheel.position() == 1


def test_vanish_is_port_error(emulated):
    port, wheel = emulated
    path = port.path
    port.vanish()
    with pytest.raises(PortError, match="port failed") as info:
        wheel.move_to(2)
    assert info.value.port == path and info.value.command == "pos=2"
    assert not wheel.is_connected and not port.holds_pty
    with pytest.raises(PortError, match="cannot open"):
        FilterWheel(path).connect()
