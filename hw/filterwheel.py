"""Driver for the Thorlabs FW102C (6 positions, 1" filters) and FW212C (12 positions, 1/2" filters).

Protocol facts implemented here (docs/instrument.md, "Thorlabs FW102C / FW212C serial protocol";
the echo / prompt framing lives in ``hw.serialline``):

- 115200 baud 8N1 by default (``baud=0`` on the unit switches it to 9600: pass ``baudrate=9600``).
- ``*idn?`` answers e.g. ``THORLABS FW102C/FW212C Filter Wheel version 1.07``; both models share it,
  so the identity check only requires ``FW102C`` or ``FW212C`` and the model is told apart by ``pcount?``.
- ``pcount?`` is 6 or 12 (``pcount=`` accepts nothing else); slots are numbered 1..pcount.
- ``pos=n`` returns its prompt only when the move ends: under 1 s to a neighbouring slot, about 2.5 s
  typical, up to about 7 s in slow mode. ``move_timeout_s`` (20 s by default) is well above that.
  The front-panel buttons can move the wheel behind the software's back, so every move is confirmed
  with ``pos?``.
- ``sensors=0`` switches the position sensors off while idle; their LEDs leak stray light into the
  images, so ``connect`` sets it.
- ``speed=0|1`` is slow / high speed.

Example::

    with FilterWheel("/dev/ttyUSB0", model="FW212C") as wheel:
        wheel.move_to(5)
"""

from __future__ import annotations

import math
import operator

from .errors import DeviceError, PortError, ProtocolError
from .serialline import PromptedSerialDevice

__all__ = ["MODELS", "FilterWheel"]

#: Number of positions per model; ``pcount`` accepts only these values.
MODELS = {"FW102C": 6, "FW212C": 12}


class FilterWheel(PromptedSerialDevice):
    """A Thorlabs FW102C / FW212C motorized filter wheel.

    Args:
        port: pyserial URL or device path.
        model: ``"FW102C"`` or ``"FW212C"`` to require that position count on connect (``pcount?``
            must agree, else ``ProtocolError``); ``None`` accepts either.
        move_timeout_s: seconds to wait for the prompt after ``pos=n`` (the move's end).
        timeout_s: seconds to wait for any other reply.
        baudrate: line speed in baud.
    """

    def __init__(
        self,
        port: str,
        *,
        model: str | None = None,
        move_timeout_s: float = 20.0,
        timeout_s: float = 1.0,
        baudrate: int = 115200,
    ):
        if model is not None and model not in MODELS:
            raise ValueError(f"model must be one of {sorted(MODELS)} or None, got {model!r}")
        if not (math.isfinite(move_timeout_s) and move_timeout_s > 0):  # NaN, inf: a move without end
            raise ValueError(f"move_timeout_s must be a finite number of seconds > 0, got {move_timeout_s}")
        super().__init__(port, baudrate=baudrate, timeout_s=timeout_s)
        self.model = model
        self.move_timeout_s = float(move_timeout_s)
        #: The ``*idn?`` reply, set by ``connect``.
        self.identity: str = ""
        self._count: int | None = None

    def _on_connect(self) -> None:
        """Check ``*idn?``, read ``pcount?`` (against ``model`` if given), switch sensors off."""
        identity = self.query("*idn?")
        if not any(name in identity.upper() for name in MODELS):
            raise ProtocolError(
                self.port, "*idn?", f"not a Thorlabs FW102C/FW212C filter wheel: {identity!r}", self.last_reply
            )
        self.identity = identity
        count = self.position_count()
        if self.model is not None and count != MODELS[self.model]:
            raise ProtocolError(
                self.port,
                "pcount?",
                f"wheel reports {count} positions but an {self.model} has {MODELS[self.model]}",
                self.last_reply,
            )
        self.set_sensors(False)

    # -- queries --------------------------------------------------------------------------------

    def _int_query(self, command: str, allowed: tuple[int, ...] | None = None) -> int:
        value = self.query(command)
        try:
            number = int(value)
        except ValueError:
            problem = f"expected an integer, got {value!r}"
            raise ProtocolError(self.port, command, problem, self.last_reply) from None
        if allowed is not None and number not in allowed:
            raise ProtocolError(
                self.port, command, f"expected one of {list(allowed)}, got {number}", self.last_reply
            )
        return number

    def position_count(self) -> int:
        """Number of slots, 6 or 12 (``pcount?``); also the range ``move_to`` checks against."""
        self._count = self._int_query("pcount?", tuple(sorted(MODELS.values())))
        return self._count

    def set_position_count(self, count: int) -> None:
        """Tell the unit how many slots its wheel has (``pcount=``; 6 or 12, else ``ValueError``).

        Not saved across power cycles unless ``save`` is sent.
        """
        if count not in MODELS.values():
            raise ValueError(f"position count must be 6 or 12, got {count!r}")
        self.command(f"pcount={count}")
        self._count = count

    def position(self) -> int:
        """Slot the wheel is at, 1..count (``pos?``)."""
        return self._int_query("pos?")

    def sensors(self) -> bool:
        """True when the position sensors stay on while idle (``sensors?``)."""
        return bool(self._int_query("sensors?", (0, 1)))

    def set_sensors(self, on: bool) -> None:
        """``sensors=1`` keeps the sensors on while idle, ``sensors=0`` (for imaging) switches them off."""
        self.command(f"sensors={int(bool(on))}")

    def speed(self) -> int:
        """Move speed: 0 slow, 1 high (``speed?``)."""
        return self._int_query("speed?", (0, 1))

    def set_speed(self, fast: bool) -> None:
        """``speed=1`` (high) or ``speed=0`` (slow, up to about 7 s a move)."""
        self.command(f"speed={int(bool(fast))}")

    # -- moves ----------------------------------------------------------------------------------

    def move_to(self, slot: int) -> int:
        """Move to ``slot`` and confirm it with ``pos?``.

        The slot is checked against the position count read on connect before anything is sent.
        ``pos=n`` then waits up to ``move_timeout_s`` for the prompt that ends the move, in polls
        that are each a safe point (``hw.serialline``): a stop does not wait for the move's end.

        Args:
            slot: 1..count.

        Returns:
            The slot read back with ``pos?`` (equal to ``slot``).

        Raises:
            TypeError: ``slot`` is not an integer.
            ValueError: ``slot`` is outside 1..count.
            DeviceTimeout: the move did not end within ``move_timeout_s``.
            DeviceError: the unit refused the move, or ``pos?`` reads another slot afterwards (a
                front-panel press, a jammed wheel).
            PortError: not connected, or the port vanished.
        """
        if isinstance(slot, bool):
            raise TypeError(f"slot must be an integer, got {slot!r}")
        slot = operator.index(slot)
        if self._count is None:
            raise PortError(self.port, f"pos={slot}", "not connected (the position count is read on connect)")
        if not 1 <= slot <= self._count:
            raise ValueError(f"{self.port}: slot {slot} is outside 1..{self._count}")
        command = f"pos={slot}"
        self.command(command, timeout_s=self.move_timeout_s)
        reached = self.position()
        if reached != slot:
            raise DeviceError(
                self.port,
                command,
                f"wheel reads slot {reached} after the move, not {slot} (front-panel press or jam?)",
                self.last_reply,
            )
        return reached

    def disconnect(self) -> None:
        """Close the port; the cached position count is forgotten."""
        with self._lock:
            super().disconnect()
            self._count = None
