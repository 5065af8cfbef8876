"""Stacked filter wheels as one band selector (docs/instrument.md, "16 filters do not fit one wheel").

Sixteen filters need two wheels (an FW212C holds 12, an FW102C 6), each with one open slot. To
select a band, the wheel carrying its filter moves it into the light path and every other wheel
sits on its open slot. The band -> (wheel, slot) mapping comes from the instrument profile.
"""

from __future__ import annotations

from collections.abc import Mapping

from .errors import DeviceError, InstrumentError
from .filterwheel import FilterWheel
from .profile import Profile


class WheelCountMismatch(InstrumentError, ValueError):
    """A wheel reports another number of positions (pcount?) than the profile's model."""


class FilterBank:
    """The profile's wheels driven together.

    Args:
      profile: the instrument profile.
      wheels: a connected `FilterWheel` per wheel name of the profile.
    """

    def __init__(self, profile: Profile, wheels: Mapping[str, FilterWheel]):
        if set(wheels) != set(profile.wheels):
            raise ValueError(f"wheels: expected {sorted(profile.wheels)}, got {sorted(wheels)}")
        self.profile = profile
        self.wheels = dict(wheels)
        self.positions: dict[str, int] = {}  # as last read back with pos?

    def check(self) -> None:
        """Before anything moves: every wheel's pcount? must be its model's position count."""
        for name, wheel in self.wheels.items():
            config = self.profile.wheels[name]
            count = wheel.position_count()
            if count != config.positions:
                raise WheelCountMismatch(
                    f"wheel {name!r} on {wheel.port} reports {count} positions (pcount?), the "
                    f"profile's {config.model} has {config.positions} (expected a wheel matching "
                    f"[wheels.{name}] model)"
                )
        self.positions = {name: wheel.position() for name, wheel in self.wheels.items()}

    def select(self, band_nm: int) -> dict[str, int]:
        """Put `band_nm`'s filter in the light path; return every wheel's slot as read back.

        Wheels already where they must be do not move. Every wheel is read back (pos?) after the
        moves, since the front-panel buttons can move a wheel behind the software's back.
        """
        target = self.profile.positions_for(band_nm)
        # Where the wheels are now, not where they were left: a front-panel press since the last
        # select would otherwise leave a wheel unmoved (and the read-back below refuse the band).
        self.positions = {name: wheel.position() for name, wheel in self.wheels.items()}
        # Open slots first: the filter of the previous band leaves the path before the next enters.
        order = sorted(target, key=lambda name: target[name] != self.profile.wheels[name].open_slot)
        for name in order:
            if self.positions.get(name) != target[name]:
                self.positions[name] = self.wheels[name].move_to(target[name])
        self.positions = {name: wheel.position() for name, wheel in self.wheels.items()}
        if self.positions != target:
            wrong = {name: slot for name, slot in self.positions.items() if slot != target[name]}
            name = next(iter(wrong))
            raise DeviceError(
                self.wheels[name].port, "pos?",
                f"wheel {name!r} is at slot {wrong[name]} after selecting {band_nm} nm, expected {target[name]}",
            )
        return dict(self.positions)

    def image_metadata(self, band_nm: int, positions: dict[str, int]) -> dict:
        """What a band image records of the selector: the band's wheel and slot, and every wheel's
        slot as read back by `select`."""
        wheel, slot = self.profile.bands[band_nm]
        return {"wheel": wheel, "slot": slot, "positions": positions}

    def band_in_path(self) -> int | None:
        """The band the last read-back positions put in the path (None: none, or ambiguous)."""
        return self.profile.band_at(self.positions)


__all__ = ["FilterBank", "WheelCountMismatch"]
