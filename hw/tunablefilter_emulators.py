"""Emulated liquid-crystal tunable filters (Thorlabs Kurios, VariSpec), served like the wheels.

Pure protocol state machines with the `receive(bytes) -> [(delay_s, bytes), ...]` interface of
`hw.emulators`, so that `hw.emulators.EmulatedPort` serves them on a pseudo-terminal and the
drivers (`hw.tunablefilter`) go through the real `serial.Serial` path. They follow the protocol
facts of `hw.tunablefilter`'s docstring (docs/instrument.md), choosing one reading where a detail
is unverified and the driver accepts both:

`KuriosEmulator`
    No echo; ``KEY=value`` replies; every accepted command and every error ends with the ``>``
    prompt; ``CMD_NOT_DEFINED`` for an empty or unknown command, ``CMD_ARG_INVALID`` for a bad
    argument (an out-of-range wavelength, a bandwidth mode the head lacks). ST? reports 1 (warming
    up) until `warmup_s` (times `time_scale`) after the emulator was made, then 2 (ready). Lower
    case keywords are taken as upper case (unverified; the Thorlabs wheels refuse them).

`VariSpecEmulator`
    Echoes every command line with CR, then a query's reply line (``W 550.000``); no prompt. An
    out-of-range ``W`` sets the fault and leaves the wavelength unchanged; ``W?`` then answers
    ``W*`` until ``R 1`` resets it. ESC empties the input line. ``V?`` answers
    ``V 1.32 400.00 720.00 50527`` for the VIS model.
"""

from __future__ import annotations

import re
import time

from .emulators import CMD_ARG_INVALID, CMD_NOT_DEFINED

__all__ = ["KuriosEmulator", "VariSpecEmulator"]

_NUMBER = re.compile(r"[-+]?\d+(?:\.\d*)?")


class _LineEmulator:
    """Line assembly shared by both: a command ends at CR, LF is dropped, ESC empties the line."""

    def __init__(self):
        self._line = bytearray()
        #: Commands received, in order (decoded; for tests).
        self.commands: list[str] = []

    def receive(self, data: bytes) -> list[tuple[float, bytes]]:
        out = bytearray()
        for byte in data:
            if byte == 0x0D:
                line = bytes(self._line).decode("ascii", errors="replace")
                self._line.clear()
                self.commands.append(line)
                out += self._reply(line)
            elif byte == 0x1B:
                self._line.clear()
            elif byte != 0x0A:
                self._line.append(byte)
        return [(0.0, bytes(out))] if out else []

    def _reply(self, line: str) -> bytes:
        raise NotImplementedError


class KuriosEmulator(_LineEmulator):
    """A Kurios controller with a VIS head (module docstring).

    Args:
      model: the *IDN? model word; range_nm: the head's SP? range; features: OH?'s word (271: a
      VIS head with black, wide, medium and narrow modes); warmup_s: seconds of ST? = 1;
      time_scale: factor on warmup_s (tests: 0); clock: the time source.
    """

    def __init__(self, *, model: str = "KURIOS-VB1", range_nm=(420.0, 730.0), features: int = 271,
                 warmup_s: float = 0.0, time_scale: float = 1.0, clock=time.monotonic):
        super().__init__()
        self.identity = f"THORLABS {model} SN-M00251234 HW1.0 FW3.1 CN-M00250987"
        self.range_nm = tuple(float(x) for x in range_nm)
        self.features = int(features)
        self.wavelength_nm = 550.0
        self.bandwidth = 2
        self.output_mode = 1
        self.clock = clock
        self._ready_at = clock() + float(warmup_s) * float(time_scale)

    #: Set commands: KEY -> (the attribute set, which values the unit takes).
    _SETTINGS = {
        "WL": ("wavelength_nm", lambda self, nm: self.range_nm[0] <= nm <= self.range_nm[1]),
        "BW": ("bandwidth", lambda self, mode: mode in (1, 2, 4, 8) and bool(self.features & int(mode))),
        "OM": ("output_mode", lambda self, mode: mode in (1, 2, 3, 4, 5)),
    }

    def _reply(self, line: str) -> bytes:
        try:
            value = self._execute(line.strip())
        except ValueError as error:
            return f"{error}\r>".encode("ascii")
        return (b"" if value is None else value.encode("ascii") + b"\r") + b">"

    def _execute(self, text: str) -> str | None:
        key, sign, argument = text.partition("=") if "=" in text else text.partition("?")
        key = key.strip().upper()
        if text in ("*IDN?", "*idn?"):
            return self.identity
        if sign == "?" and not argument:
            if key == "SP":
                low, high = self.range_nm
                return f"WLmax={high:.3f}\rWLmin={low:.3f}"
            if key == "OH":
                return f"OH={self.features}"
            if key in self._SETTINGS:
                value = getattr(self, self._SETTINGS[key][0])
                return f"{key}={value:.3f}" if key == "WL" else f"{key}={value}"
            if key == "ST":
                return f"ST={2 if self.clock() >= self._ready_at else 1}"
        if sign == "=" and key in self._SETTINGS:
            attribute, allowed = self._SETTINGS[key]
            if not _NUMBER.fullmatch(argument.strip()) or not allowed(self, float(argument)):
                raise ValueError(CMD_ARG_INVALID)
            value = float(argument)
            setattr(self, attribute, round(value, 3) if key == "WL" else int(value))
            return None
        raise ValueError(CMD_NOT_DEFINED)


class VariSpecEmulator(_LineEmulator):
    """A VariSpec VIS filter (module docstring)."""

    def __init__(self, *, range_nm=(400.0, 720.0), serial_number: int = 50527):
        super().__init__()
        self.range_nm = tuple(float(x) for x in range_nm)
        self.serial_number = int(serial_number)
        self.wavelength_nm = 550.0
        self.fault = False

    def _reply(self, line: str) -> bytes:
        echo = line.encode("ascii", errors="replace") + b"\r"
        text = line.strip()
        if not text:
            return echo
        letter, argument = text[0].upper(), text[1:].strip()
        value = None
        if argument == "?":
            if letter == "W":
                value = "W*" if self.fault else f"W {self.wavelength_nm:.3f}"
            elif letter == "V":
                low, high = self.range_nm
                value = f"V   1.32  {low:.2f}  {high:.2f} {self.serial_number}"
            elif letter == "R":
                value = f"R {1 if self.fault else 0}"
        elif letter == "W":
            low, high = self.range_nm
            if _NUMBER.fullmatch(argument) and low <= float(argument) <= high:
                self.wavelength_nm = round(float(argument), 3)
            else:
                self.fault = True  # the manual: an error, the status LED red
        elif letter == "R" and argument not in ("", "0"):
            self.fault = False
        return echo if value is None else echo + value.encode("ascii") + b"\r"
