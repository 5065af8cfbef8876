"""Exceptions raised by hw/: one root, `InstrumentError`, with every kind under it.

    InstrumentError                  anything hw/ raises (catch this to catch them all)
        HardwareError                a serial device failed (port, command, reply; below)
            DeviceTimeout, ProtocolError, DeviceError, PortError
        camera.CameraError           a camera failed or cannot do what was asked
        lamp.LampError               a lamp record out of order
        lamp.LampStateError          a malformed lamp state file (also a ValueError)
        profile.ProfileError         an instrument profile that cannot be used (also a ValueError)
        filterbank.WheelCountMismatch  a wheel with another number of positions (also a ValueError)
        AcquisitionError             an acquisition that cannot start (also acquire.AcquisitionError)
            AcquisitionStopped       one that a fault stopped (also acquire.AcquisitionStopped)

Each is one line naming what failed and, where there is one, the file, key or value and what
was expected. Those that were ValueError or RuntimeError before this root existed still are, so
callers that caught them as such still do.

A serial device's error names the port (the pyserial URL or device path as given), the command that was being
carried out (``None`` when the failure is not tied to one, e.g. opening the port) and, when the
device said something, the raw reply. ``str(error)`` is always one line, e.g.::

    /dev/pts/3: 'pos=7': device error Command error CMD_ARG_INVALID (reply b'pos=7\\rCommand error CMD_ARG_INVALID\\n> ')

The classes split failures by what a caller can do about them (see docs/instrument.md for the
protocols): a ``DeviceTimeout`` may be retried, a ``ProtocolError`` means the wrong device or a
garbled line, a ``DeviceError`` is the instrument refusing a command or failing to reach a slot, and a
``PortError`` means the serial port itself is gone.
"""

from __future__ import annotations

__all__ = [
    "InstrumentError", "HardwareError", "DeviceTimeout", "ProtocolError", "DeviceError", "PortError",
    "AcquisitionError", "AcquisitionStopped",
]


class InstrumentError(Exception):
    """Base class of every error hw/ raises (the module docstring lists them)."""


class HardwareError(InstrumentError):
    """Base class of every hw/ driver error.

    Args:
        port: the pyserial URL or device path the driver was given.
        command: the command being carried out (without its ``\\r``), or ``None``.
        problem: what went wrong, one line.
        reply: the raw bytes (or decoded text) the device answered with, or ``None``.
    """

    def __init__(self, port: str, command: str | None, problem: str, reply: bytes | str | None = None):
        self.port = port
        self.command = command
        # Newlines in a problem would break the one-line contract that log parsers rely on.
        self.problem = " ".join(str(problem).split())
        self.reply = reply
        super().__init__(self._message())

    def _message(self) -> str:
        where = f"{self.port}: " if self.command is None else f"{self.port}: {self.command!r}: "
        tail = "" if self.reply is None else f" (reply {self.reply!r})"
        return f"{where}{self.problem}{tail}"

    def __reduce__(self):
        # Exception pickles as cls(*self.args); our args hold only the message, so rebuild from the
        # fields instead (errors cross process boundaries when acquisition runs under dask/multiprocessing).
        return (type(self), (self.port, self.command, self.problem, self.reply))


class DeviceTimeout(HardwareError):
    """No (complete) answer arrived within the timeout: a silent device, or a move that ran too long."""


class ProtocolError(HardwareError):
    """The answer did not follow the protocol: garbage, no echo of the command, an unparsable value,
    or a device that identifies as something else."""


class DeviceError(HardwareError):
    """The device answered ``Command error ...`` (``CMD_NOT_DEFINED`` / ``CMD_ARG_INVALID``), or it did
    not end up in the requested state (a wheel not at the commanded slot, a shutter that did not move)."""


class PortError(HardwareError):
    """The serial port could not be opened, is not open, or vanished mid-session
    (``serial.SerialException`` / ``OSError`` from pyserial)."""


# Here rather than in acquire.py: every module of the acquisition (acquisition_devices,
# acquisition_journal, acquisition_protocol, acquisition_session) raises them, and acquire.py,
# which re-exports them, imports those modules.
class AcquisitionError(InstrumentError):
    """The acquisition cannot start: one line saying why; nothing moved, nothing was written."""


class AcquisitionStopped(AcquisitionError):
    """A fault stopped a running acquisition: one line saying why and what was kept."""
