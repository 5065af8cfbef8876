"""The shared echo / value line / prompt protocol (hw.serialline) and the error classes (hw.errors).

Byte-level behaviour is driven through ``ScriptedPort`` (installed as ``serial.serial_for_url``), so
each test states the exact bytes written and answered; ``loop://`` exercises a real pyserial URL.
"""

from __future__ import annotations

import pickle

import pytest
import serial

from spherejax_hw.emulators import ScriptedPort
from spherejax_hw.errors import DeviceError, DeviceTimeout, HardwareError, PortError, ProtocolError
from spherejax_hw.serialline import PromptedSerialDevice

DRAIN = (b"\r", b"\r> ")


def scripted(monkeypatch, script, url="scripted://dev"):
    port = ScriptedPort(script, url=url)
    monkeypatch.setattr(serial, "serial_for_url", port.serial_for_url)
    return port


def device(timeout_s=0.2, port="scripted://dev"):
    return PromptedSerialDevice(port, baudrate=115200, timeout_s=timeout_s)


# -- errors -----------------------------------------------------------------------------------------


def test_error_message_is_one_line_naming_port_command_reply():
    reply = b"pos=7\rCommand error CMD_ARG_INVALID\n> "
    error = DeviceError("/dev/pts/3", "pos=7", "device error Command error CMD_ARG_INVALID", reply)
    assert str(error) == (
        "/dev/pts/3: 'pos=7': device error Command error CMD_ARG_INVALID "
        "(reply b'pos=7\\rCommand error CMD_ARG_INVALID\\n> ')"
    )
    assert (error.port, error.command, error.reply) == ("/dev/pts/3", "pos=7", reply)
    assert isinstance(error, HardwareError) and "\n" not in str(error)


def test_error_without_command_or_reply_and_multiline_problem():
    error = PortError("COM4", None, "cannot open\nport")
    assert str(error) == "COM4: cannot open port"


@pytest.mark.parametrize("cls", [HardwareError, DeviceTimeout, ProtocolError, DeviceError, PortError])
def test_errors_pickle(cls):
    error = cls("/dev/x", "pos?", "problem", b"pos?\r")
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is cls and str(again) == str(error) and again.reply == b"pos?\r"


# -- transactions -----------------------------------------------------------------------------------


def test_query_and_command_transcript(monkeypatch):
    port = scripted(monkeypatch, [DRAIN, (b"pos?\r", b"pos?\r3\r> "), (b"pos=4\r", b"pos=4\r> ")])
    with device() as dev:
        assert dev.query("pos?") == "3"
        assert dev.command("pos=4", timeout_s=5) is None
    port.assert_done()
    assert port.transcript == [
        ("write", b"\r"),
        ("read", b"\r> "),
        ("write", b"pos?\r"),
        ("read", b"pos?\r3\r> "),
        ("write", b"pos=4\r"),
        ("read", b"pos=4\r> "),
    ]
    assert not port.is_open
    assert port.settings["baudrate"] == 115200 and port.settings["bytesize"] == 8
    assert port.settings["parity"] == "N" and port.settings["stopbits"] == 1
    assert not port.settings["xonxoff"] and not port.settings["rtscts"]


@pytest.mark.parametrize(
    "reply",
    [
        b"pos?\r3\r>",  # no trailing space after the prompt
        b"pos?\n3\n> ",  # LF line endings
        b"pos?\r\n3\r\n> ",
        b"\x00\x00pos?\r3\r> ",  # NUL line noise
        b"> pos?\r3\r> ",  # a stale prompt ahead of the echo
        b"Command error CMD_NOT_DEFINED\r> \rpos?\r3\r> ",  # a stale error ahead of the echo
        b"pos?\r3> ",  # value glued to the prompt
    ],
)
def test_query_tolerates(monkeypatch, reply):
    port = scripted(monkeypatch, [DRAIN, (b"pos?\r", reply)])
    with device() as dev:
        assert dev.query("pos?") == "3"
    port.assert_done()


@pytest.mark.parametrize("ending", [b"\r", b"\n"])
def test_error_line_is_device_error(monkeypatch, ending):
    reply = b"pos=7\rCommand error CMD_ARG_INVALID" + ending + b"> "
    scripted(monkeypatch, [DRAIN, (b"pos=7\r", reply)])
    with device() as dev, pytest.raises(DeviceError) as info:
        dev.command("pos=7")
    assert info.value.port == "scripted://dev" and info.value.command == "pos=7"
    assert info.value.reply == reply and "CMD_ARG_INVALID" in str(info.value)


def test_bare_cmd_marker_is_device_error(monkeypatch):
    scripted(monkeypatch, [DRAIN, (b"pos?\r", b"pos?\rCMD_NOT_DEFINED\r> ")])
    with device() as dev, pytest.raises(DeviceError):
        dev.query("pos?")


def test_error_without_echo_is_device_error(monkeypatch):
    scripted(monkeypatch, [DRAIN, (b"POS=2\r", b"Command error CMD_NOT_DEFINED\r> ")])
    with device() as dev, pytest.raises(DeviceError, match="CMD_NOT_DEFINED"):
        dev.command("POS=2")


def test_silence_is_timeout(monkeypatch):
    scripted(monkeypatch, [DRAIN, (b"pos?\r", b"")])
    with device(timeout_s=0.15) as dev:
        with pytest.raises(DeviceTimeout, match="no answer within 0.15 s") as info:
            dev.query("pos?")
        assert info.value.reply is None
        assert dev.is_connected  # a timeout leaves the port open, e.g. for Shutter.make_safe


def test_echo_without_prompt_is_timeout(monkeypatch):
    scripted(monkeypatch, [DRAIN, (b"pos=3\r", b"pos=3\r")])
    with device() as dev, pytest.raises(DeviceTimeout, match="echo but no prompt") as info:
        dev.command("pos=3", timeout_s=0.15)
    assert info.value.reply == b"pos=3\r"


@pytest.mark.parametrize("reply", [b"\xe2\xeb\x8a#%\xfc", b"\xe2\xeb\x8a#%\xfc\r> ", b"pos!\r3\r> "])
def test_garbage_is_protocol_error(monkeypatch, reply):
    scripted(monkeypatch, [DRAIN, (b"pos?\r", reply)])
    with device(timeout_s=0.15) as dev, pytest.raises(ProtocolError, match="without the echo") as info:
        dev.query("pos?")
    assert info.value.reply == reply


def test_query_without_value_and_command_with_value_are_protocol_errors(monkeypatch):
    scripted(monkeypatch, [DRAIN, (b"pos?\r", b"pos?\r> "), (b"pos=2\r", b"pos=2\r2\r> ")])
    with device() as dev:
        with pytest.raises(ProtocolError, match="no value line"):
            dev.query("pos?")
        with pytest.raises(ProtocolError, match="unexpected value line '2'"):
            dev.command("pos=2")


def test_connect_drains_stray_bytes(monkeypatch):
    stray = b"\x00\x00Command error CMD_NOT_DEFINED\r> "
    port = scripted(monkeypatch, [(b"\r", stray), (b"pos?\r", b"pos?\r1\r> ")])
    with device() as dev:
        assert dev.query("pos?") == "1"
    port.assert_done()
    assert port.transcript[:2] == [("write", b"\r"), ("read", stray)]


def test_connect_survives_a_silent_drain(monkeypatch):
    # Units that ignore an empty line: the drain gives up after timeout_s; the device still works.
    scripted(monkeypatch, [(b"\r", b""), (b"pos?\r", b"pos?\r1\r> ")])
    with device(timeout_s=0.1) as dev:
        assert dev.query("pos?") == "1"


def test_commands_must_be_one_line():
    dev = device()
    for bad in ["", "pos=1\rpos=2", "pos?\n"]:
        with pytest.raises(ValueError):
            dev.query(bad)


def test_not_connected_is_port_error():
    with pytest.raises(PortError, match="not open"):
        device().query("pos?")


def test_unopenable_ports_are_port_errors(tmp_path):
    missing = str(tmp_path / "ttyUSB9")
    with pytest.raises(PortError, match="cannot open port") as info:
        device(port=missing).connect()
    assert info.value.port == missing and info.value.command is None
    with pytest.raises(PortError):
        device(port="nosuchscheme://x").connect()


def test_vanished_port_is_port_error_and_closes(monkeypatch):
    port = scripted(monkeypatch, [DRAIN])
    with device() as dev:
        port.vanish()
        with pytest.raises(PortError, match="port failed"):
            dev.query("pos?")
        assert not dev.is_connected
        with pytest.raises(PortError, match="not open"):
            dev.query("pos?")


def test_connect_is_idempotent_and_disconnect_too(monkeypatch):
    port = scripted(monkeypatch, [DRAIN])
    dev = device()
    dev.connect()
    dev.connect()
    assert port.opened == 1
    dev.disconnect()
    dev.disconnect()
    assert not dev.is_connected and "disconnected" in repr(dev)


def test_loop_url_only_echoes():
    # pyserial's loop:// echoes the command but never prompts: a timeout after the echo, not a hang.
    with device(port="loop://", timeout_s=0.1) as dev:
        with pytest.raises(DeviceTimeout, match="echo but no prompt") as info:
            dev.query("pos?")
        assert info.value.reply == b"pos?\r"


def test_non_ascii_value_is_protocol_error(monkeypatch):
    idn = (b"*idn?\r", b"*idn?\rTHORLABS FW102C\xff\x01\r> ")
    scripted(monkeypatch, [DRAIN, idn, (b"pos?\r", b"pos?\r\xfe\xfd")])
    with device(timeout_s=0.15) as dev:
        with pytest.raises(ProtocolError, match="non-protocol bytes in the reply"):
            dev.query("*idn?")
        with pytest.raises(ProtocolError, match="non-protocol bytes after the echo"):
            dev.query("pos?")
