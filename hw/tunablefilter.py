"""Liquid-crystal tunable filters as band selectors: the Thorlabs Kurios and the VariSpec.

The paper selects bands with "narrow-band filters or a liquid crystal tunable filter (LCTF)". An
LCTF replaces the stacked wheels (`hw.filterbank`): a band is a wavelength the filter is tuned to,
not a (wheel, slot). Both drivers here offer what the acquisition asks of a band selector
(`FilterBank` has the same methods): `check()` before anything moves, `wait_until_ready()` before
the first frame (the filter's warm-up), `select(band_nm)` (tune, let the liquid crystal settle,
read the wavelength back), `band_in_path()`, and `image_metadata(band, selection)`.

Protocol facts relied on (docs/instrument.md, "Liquid-crystal tunable filters", with sources);
where a detail is *unverified* the code accepts either reading:

Thorlabs Kurios (Kurios user guide, rev. G 2019, chapter 5 "Command Line"; Thorlabs' Kurios
command library for ST?'s values)
    115200 baud, 8N1, no flow control. ``keyword=argument`` commands and ``keyword?`` queries end
    in CR; the prompt ``>`` follows every accepted command; an empty or unknown command answers
    ``CMD_NOT_DEFINED``. ``*IDN?`` -> ``THORLABS KURIOS-VB1 SN-... HWx.x FWx.x CN-...``; ``SP?`` ->
    ``WLmax=730.000`` and ``WLmin=420.000`` (VIS head; NIR 650-1100); ``OH?`` -> ``OH=n``, its low
    byte the bandwidth modes the head has (1 black, 2 wide, 4 medium, 8 narrow); ``BW=n`` selects
    one; ``OM=1`` manual output mode (the filter holds the wavelength it is told); ``WL=nnn.nnn``
    tunes and ``WL?`` -> ``WL=nnn.nnn``; ``ST?`` -> 0 initialising, 1 warming up, 2 ready.
    *Unverified*, and so accepted either way: whether a command is echoed before its reply (a line
    equal to the command is dropped), whether replies carry the ``KEY=`` prefix (the number after
    the last ``=`` or the whole line is read), and the words of an out-of-range argument (any line
    with ``CMD_`` is a device error).

VariSpec (CRi / PerkinElmer; the VariSpec manual, "Controlling VariSpec Filters"; Micro-Manager's
VarispecLCTF adapter for the framing)
    9600 baud, 8N1. Single-letter commands with an argument and CR: ``W 550.000`` tunes (an
    out-of-range argument is an error and lights the status LED red), ``W?`` the wavelength,
    ``V?`` -> firmware revision, shortest and longest wavelength and serial number, ``R 1`` resets
    pending faults, ESC clears the filter's input buffer (sent before the first command and
    before ``R 1``). The filter echoes each command line with CR; a query's reply follows as a
    line of its own, its letter first (``W 550.000``); ``W*`` (no number) after an out-of-range
    tune. There is no prompt. *Unverified*: how a refused tune reads (both a missing number and
    ``*`` are taken as a refusal) and any warm-up query, which the line protocol does not give:
    the profile's ``warmup_s`` is waited instead.

After every tune the driver waits ``settle_s`` (liquid crystals settle in tens of milliseconds;
the profile's default 0.1 s) and reads the wavelength back; a read-back more than
``TOLERANCE_NM`` from the band is a `DeviceError`.

Every wait (the settling, a VariSpec's ``warmup_s``, a Kurios's ST? polls) goes through the
`sleep` the driver is given, by default `spherejax.interrupt.sleep`: slices of at most
`interrupt.SLICE_S` with a safe point after each, so a stop (SIGINT, SIGTERM, SIGHUP) during a
warm-up of minutes is acted on within a fraction of a second, not after it. Wait lengths must be
finite and >= 0 (`ValueError` otherwise); an instrument profile bounds them further (`hw.profile`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
from collections.abc import Callable, Sequence

from spherejax import interrupt

from .errors import DeviceError, DeviceTimeout, ProtocolError
from .serialline import PromptedSerialDevice, Scan, _text

__all__ = ["MODELS", "TOLERANCE_NM", "FilterModel", "KuriosFilter", "TunableFilter", "VariSpecFilter", "open_filter"]

log = logging.getLogger(__name__)

#: How far the read-back wavelength may lie from the band asked for, nm (both families report
#: three decimals; their tuning resolution is finer than 0.1 nm).
TOLERANCE_NM = 0.5

_LINE_BREAK = re.compile(r"[\r\n]")
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d*)?")


@dataclasses.dataclass(frozen=True)
class FilterModel:
    """A tunable filter model: its protocol family, nominal tuning range (nm) and line speed."""

    family: str
    range_nm: tuple[float, float]
    baudrate: int


#: The models a profile's [tunable_filter] model may name, with their nominal ranges: a profile
#: asking for a band outside them is refused when it is read; the range the filter itself
#: reports is checked again when it is connected.
MODELS = {
    "Kurios-VIS": FilterModel("kurios", (420.0, 730.0), 115200),
    "Kurios-NIR": FilterModel("kurios", (650.0, 1100.0), 115200),
    "VariSpec-VIS": FilterModel("varispec", (400.0, 720.0), 9600),
}

#: Kurios bandwidth modes (BW=n, and the low byte of OH?).
KURIOS_BANDWIDTHS = {"black": 1, "wide": 2, "medium": 4, "narrow": 8}


def _lines(raw: bytes) -> list[str]:
    return [line.strip() for line in _LINE_BREAK.split(_text(raw))]


def _last_number(text: str, port: str, command: str, raw: bytes) -> float:
    """The number after the last '=' of a reply line (or the line's last number)."""
    numbers = _NUMBER.findall(text.rpartition("=")[2]) or _NUMBER.findall(text)
    if not numbers:
        raise ProtocolError(port, command, f"expected a number, got {text!r}", raw)
    return float(numbers[-1])


def _wait_seconds(name: str, value) -> float:
    """A wait length as float seconds: finite and >= 0, else ValueError naming it."""
    seconds = float(value)
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"{name} {value!r}: expected a finite number of seconds >= 0")
    return seconds


class TunableFilter(PromptedSerialDevice):
    """What both families share: the tuning, settling and read-back of a band, and the checks.

    Args:
      port: pyserial URL or device path.
      model: a key of `MODELS`.
      bands_nm: the bands the acquisition will ask for (checked against the filter's range).
      settle_s: seconds to wait after each tune before the read-back (and the first frame).
      timeout_s: seconds to wait for a reply.
      sleep: the waiting function (module docstring; tests pass a fake clock's).
    """

    def __init__(self, port: str, *, model: str, bands_nm: Sequence[int], settle_s: float = 0.1,
                 timeout_s: float = 1.0, sleep: Callable[[float], None] = interrupt.sleep):
        if model not in MODELS:
            raise ValueError(f"tunable filter model {model!r}: expected one of {sorted(MODELS)}")
        super().__init__(port, baudrate=MODELS[model].baudrate, timeout_s=timeout_s)
        self.model = model
        self.bands_nm = [int(band) for band in bands_nm]
        self.settle_s = _wait_seconds("settle_s", settle_s)
        self.sleep = sleep
        #: The identity reply and the tuning range the filter reports, set by `connect`.
        self.identity = ""
        self.range_nm: tuple[float, float] = MODELS[model].range_nm
        #: The wavelength last read back, nm (None before the first select).
        self.wavelength_nm: float | None = None

    # --- what a family provides -----------------------------------------------------------------

    def _tune(self, nm: float) -> None:
        raise NotImplementedError

    def read_wavelength(self) -> float:
        """The wavelength the filter reports it is tuned to, nm."""
        raise NotImplementedError

    def wait_until_ready(self, timeout_s: float) -> dict:
        """Wait for the filter's warm-up; return what to record of it."""
        raise NotImplementedError

    # --- shared ----------------------------------------------------------------------------------

    def check(self) -> None:
        """Before anything moves: every band inside the tuning range the filter reports."""
        low, high = self.range_nm
        outside = [band for band in self.bands_nm if not low <= band <= high]
        if outside:
            raise DeviceError(
                self.port, None,
                f"the {self.model} reports a tuning range of {low:g}-{high:g} nm; bands {outside} nm lie outside it",
            )

    def select(self, band_nm: int) -> float:
        """Tune to `band_nm`, wait `settle_s`, read the wavelength back and return it (nm).

        Raises:
          DeviceError: the filter refused the wavelength, or reads back more than TOLERANCE_NM
            from it; DeviceTimeout, ProtocolError, PortError as `PromptedSerialDevice`.
        """
        with self._lock:
            self.wavelength_nm = None
            self._tune(float(band_nm))
            self.sleep(self.settle_s)
            wavelength = self.read_wavelength()
            if abs(wavelength - band_nm) > TOLERANCE_NM:
                raise DeviceError(
                    self.port, None,
                    f"tuned to {band_nm} nm but reads back {wavelength:g} nm (expected within {TOLERANCE_NM:g} nm)",
                )
            self.wavelength_nm = wavelength
            return wavelength

    def band_in_path(self) -> int | None:
        """The band the last read-back wavelength is (None before a select, or off every band)."""
        if self.wavelength_nm is None:
            return None
        for band in self.bands_nm:
            if abs(self.wavelength_nm - band) <= TOLERANCE_NM:
                return band
        return None

    def image_metadata(self, band_nm: int, wavelength_nm: float) -> dict:
        """What a band image records of the selector: the model and the wavelength read back."""
        return {"tunable_filter": self.model, "wavelength_nm": wavelength_nm}


class KuriosFilter(TunableFilter):
    """A Thorlabs Kurios controller and head (module docstring), in manual output mode.

    Args (beyond `TunableFilter`'s):
      bandwidth: "wide", "medium" or "narrow" (BW=), refused at `connect` if the head lacks it.
    """

    def __init__(self, port: str, *, model: str = "Kurios-VIS", bandwidth: str = "wide", **options):
        super().__init__(port, model=model, **options)
        if bandwidth not in KURIOS_BANDWIDTHS or bandwidth == "black":
            raise ValueError(f"bandwidth {bandwidth!r}: expected one of wide, medium, narrow")
        self.bandwidth = bandwidth

    def _scan_reply(self, command: str, raw: bytes, expect_value: bool) -> Scan:
        """The Kurios's framing: reply lines, then the ``>`` prompt; a line equal to the command
        (an echo, unverified) is dropped."""
        lines = _lines(raw)
        values, wanted = [], command.strip().casefold()
        for line in lines:
            value, prompt, _ = line.partition(">")
            value = value.strip()
            if value and value.casefold() != wanted:
                values.append(value)
            if prompt:
                return Scan(True, True, values, [], True)
        return Scan(False, False, [], values, False)

    def _on_connect(self) -> None:
        identity = self.query("*IDN?")
        if "KURIOS" not in identity.upper():
            raise ProtocolError(self.port, "*IDN?", f"not a Thorlabs Kurios: {identity!r}", self.last_reply)
        self.identity = identity
        reply = self.query("SP?")
        limits = dict(re.findall(r"WL(max|min)\s*=\s*([-+]?\d+(?:\.\d*)?)", reply, flags=re.IGNORECASE))
        if set(limits) != {"max", "min"}:
            raise ProtocolError(self.port, "SP?", f"expected WLmax= and WLmin=, got {reply!r}", self.last_reply)
        self.range_nm = (float(limits["min"]), float(limits["max"]))
        features = int(_last_number(self.query("OH?"), self.port, "OH?", self.last_reply))
        mode = KURIOS_BANDWIDTHS[self.bandwidth]
        if not features & mode:
            raise DeviceError(self.port, "OH?", f"the head has no {self.bandwidth} bandwidth mode (OH={features})")
        self.command("OM=1")  # manual: the filter holds the wavelength it is told
        self.command(f"BW={mode}")

    def _tune(self, nm: float) -> None:
        self.command(f"WL={nm:.3f}")

    def read_wavelength(self) -> float:
        return _last_number(self.query("WL?"), self.port, "WL?", self.last_reply)

    def status(self) -> int:
        """ST?: 0 initialising, 1 warming up, 2 ready."""
        return int(_last_number(self.query("ST?"), self.port, "ST?", self.last_reply))

    def wait_until_ready(self, timeout_s: float) -> dict:
        """Poll ST? (every 0.5 s) until the filter reports ready (2).

        Raises:
          DeviceTimeout: still initialising or warming up after `timeout_s`.
        """
        start = time.monotonic()
        waited = 0.0
        while (state := self.status()) != 2:
            if waited >= timeout_s:
                words = {0: "initialising", 1: "warming up"}.get(state, f"in state {state}")
                raise DeviceTimeout(self.port, "ST?", f"still {words} after {timeout_s:g} s (ST? {state}, 2 is ready)")
            self.sleep(0.5)
            waited += 0.5
        return {"warmup_s": round(time.monotonic() - start, 3), "status": "ready"}

    def image_metadata(self, band_nm: int, wavelength_nm: float) -> dict:
        return {**super().image_metadata(band_nm, wavelength_nm), "bandwidth": self.bandwidth}


class VariSpecFilter(TunableFilter):
    """A VariSpec filter (module docstring).

    Args (beyond `TunableFilter`'s):
      warmup_s: seconds to wait before the first frame (the line protocol gives no warm-up
        query); 0 when the filter has been on long enough.
    """

    WAKE = b"\x1b"  # ESC clears the filter's input buffer (the manual); a CR would be a command
    PROMPTED = False

    def __init__(self, port: str, *, model: str = "VariSpec-VIS", warmup_s: float = 0.0, **options):
        super().__init__(port, model=model, **options)
        self.warmup_s = _wait_seconds("warmup_s", warmup_s)

    def _scan_reply(self, command: str, raw: bytes, expect_value: bool) -> Scan:
        """The VariSpec's framing: the echo of the command, then (a query) one reply line, each
        ending in CR; no prompt. Lines before the echo are stale and dropped."""
        text = _text(raw)
        lines = _LINE_BREAK.split(text)
        wanted = command.strip().casefold()
        for i, line in enumerate(lines[:-1]):  # a line is complete once a line break follows it
            if line.strip().casefold() != wanted:
                continue
            rest = [x.strip() for x in lines[i + 1:-1] if x.strip()]
            if not expect_value or rest:
                return Scan(True, True, rest[:1] if expect_value else rest, [], True)
            return Scan(True, False, [], [], False)
        unechoed = [x.strip() for x in lines if x.strip()]
        return Scan(False, False, [], unechoed, False)

    def _on_connect(self) -> None:
        self.reset()
        reply = self.query("V?")
        numbers = [float(x) for x in _NUMBER.findall(reply)]
        if len(numbers) < 4:
            raise ProtocolError(
                self.port, "V?", f"expected revision, shortest and longest wavelength and serial number, got {reply!r}",
                self.last_reply,
            )
        _revision, shortest, longest, serial_number = numbers[-4:]
        if not 0 < shortest < longest:
            raise ProtocolError(self.port, "V?", f"not a tuning range: {shortest:g}-{longest:g} nm", self.last_reply)
        self.identity = f"VariSpec serial {serial_number:.0f}, firmware {_revision:g}"
        self.range_nm = (shortest, longest)

    def reset(self) -> None:
        """ESC, then ``R 1``: clear the input buffer and any pending fault (the status LED)."""
        with self._lock:
            ser = self._require_open("R 1")
            self._port_call("R 1", ser.write, b"\x1b")
            self.command("R 1")

    def _tune(self, nm: float) -> None:
        self.command(f"W {nm:.3f}")

    def read_wavelength(self) -> float:
        reply = self.query("W?")
        if "*" in reply or not _NUMBER.search(reply):
            self.reset()
            raise DeviceError(self.port, "W?", f"the filter refused the wavelength (reply {reply!r})")
        return _last_number(reply, self.port, "W?", self.last_reply)

    def wait_until_ready(self, timeout_s: float) -> dict:
        self.sleep(self.warmup_s)
        return {"warmup_s": self.warmup_s, "status": "waited"}


def open_filter(port: str, *, model: str, bands_nm: Sequence[int], **options) -> TunableFilter:
    """The driver of `model`'s family (not yet connected; use it as a context manager)."""
    family = MODELS[model].family if model in MODELS else None
    if family == "kurios":
        return KuriosFilter(port, model=model, bands_nm=bands_nm, **options)
    if family == "varispec":
        return VariSpecFilter(port, model=model, bands_nm=bands_nm, **options)
    raise ValueError(f"tunable filter model {model!r}: expected one of {sorted(MODELS)}")

