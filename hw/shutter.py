"""Driver for the Thorlabs SC10 shutter controller.

Protocol facts implemented here (docs/instrument.md, "Thorlabs SC10 shutter controller"; the
echo / prompt framing lives in ``hw.serialline``):

- 9600 baud 8N1, the same echo / value line / ``> `` prompt and error strings as the filter wheel.
- ``id?`` answers e.g. ``THORLABS SC10 VERSION 1.07``.
- ``ens`` *toggles* the shutter enable, so it must only be sent when the state has to change: every
  open or close first reads ``closed?`` (1 closed, 0 open), sends ``ens`` only if needed, and then
  confirms with ``closed?``. Sending ``ens`` blindly after a lost reply would open a closed shutter.
- ``mode=1`` is manual mode (``ens`` opens and closes); 2..5 are timed and gated modes in which ``ens``
  starts a cycle instead, so ``connect`` sets mode 1.

Dark frames depend on this shutter being shut, so ``make_safe`` closes it on a best-effort basis and
never raises: it belongs in ``finally`` blocks.
"""

from __future__ import annotations

import logging
import math
import time

from spherejax import interrupt

from .errors import DeviceError, ProtocolError
from .serialline import PromptedSerialDevice

__all__ = ["Shutter"]

log = logging.getLogger(__name__)


class Shutter(PromptedSerialDevice):
    """A Thorlabs SC10 shutter controller in manual mode.

    Args:
        port: pyserial URL or device path.
        timeout_s: seconds to wait for a reply.
        baudrate: line speed in baud (the SC10 ships at 9600).
        settle_s: seconds ``closed?`` may take to report the new state after ``ens`` (the blades
            move in milliseconds; this only absorbs a slow sensor read-back).
    """

    def __init__(self, port: str, *, timeout_s: float = 1.0, baudrate: int = 9600, settle_s: float = 0.5):
        super().__init__(port, baudrate=baudrate, timeout_s=timeout_s)
        if not (math.isfinite(settle_s) and settle_s >= 0):
            raise ValueError(f"settle_s must be a finite number of seconds >= 0, got {settle_s}")
        self.settle_s = float(settle_s)
        #: The ``id?`` reply, set by ``connect``.
        self.identity: str = ""

    def _on_connect(self) -> None:
        """Check ``id?`` mentions SC10, then select manual mode (``mode=1``)."""
        identity = self.query("id?")
        if "SC10" not in identity.upper():
            raise ProtocolError(self.port, "id?", f"not a Thorlabs SC10: {identity!r}", self.last_reply)
        self.identity = identity
        self.command("mode=1")

    def is_closed(self) -> bool:
        """True when the shutter is closed (``closed?`` answers 1 closed, 0 open)."""
        value = self.query("closed?")
        if value not in ("0", "1"):
            raise ProtocolError(self.port, "closed?", f"expected 0 or 1, got {value!r}", self.last_reply)
        return value == "1"

    def open_shutter(self) -> None:
        """Open: read ``closed?``, send ``ens`` only if closed, confirm ``closed?`` is 0.

        Raises:
            DeviceError: still closed after ``ens`` (interlock tripped, controller not in mode 1).
            DeviceTimeout, ProtocolError, PortError: see ``PromptedSerialDevice``.
        """
        self._set_closed(False)

    def close_shutter(self) -> None:
        """Close: read ``closed?``, send ``ens`` only if open, confirm ``closed?`` is 1.

        Raises:
            DeviceError: still open after ``ens``.
            DeviceTimeout, ProtocolError, PortError: see ``PromptedSerialDevice``.
        """
        self._set_closed(True)

    def _set_closed(self, closed: bool) -> None:
        with self._lock:
            if self.is_closed() == closed:
                return
            self.command("ens")
            deadline = time.monotonic() + self.settle_s
            while self.is_closed() != closed:
                if time.monotonic() >= deadline:
                    state = "closed" if not closed else "open"
                    raise DeviceError(
                        self.port,
                        "ens",
                        f"shutter still {state} {self.settle_s:g} s after ens (interlock tripped?)",
                        self.last_reply,
                    )
                interrupt.sleep(0.02)

    def make_safe(self) -> None:
        """Close the shutter if at all possible; never raises (for ``finally`` blocks).

        Reconnects first when the port was closed (e.g. after it vanished and came back). Failures are
        logged as warnings, since the caller is usually already handling another exception. Runs
        shielded from stops (`spherejax.interrupt.shielded`): a second Ctrl-C, or the stop being
        cleaned up after, must not leave the shutter open halfway through closing it.
        """
        try:
            with interrupt.shielded(), self._lock:
                if not self.is_connected:
                    self.connect()
                self.close_shutter()
        except Exception as exc:  # noqa: BLE001 - best effort by contract
            # A driver error names the port already: "PORT: could not make the shutter safe: its words".
            reason = str(exc).removeprefix(f"{self.port}: ")
            log.warning("%s: could not make the shutter safe: %s", self.port, reason)
