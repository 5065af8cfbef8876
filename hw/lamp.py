"""The xenon lamp, a manual device: switch-on time, warm-up and lamp hours kept in a state file.

The 150 W xenon lamp's power supply has no public serial protocol (docs/instrument.md), so the operator
switches it by hand and the software records it: `switch_on` when the arc strikes, `switch_off`
when it goes out. From those records `Lamp` answers how long the lamp has been warming up and how
many hours it has burned (xenon arcs age with hours and ignitions; both are logged with every
frame). `record_warmup` keeps the result of the protocol's warm-up drift check.

The state is a small JSON file beside the instrument profile:

    {"format": "hw.lamp/1", "hours": 812.25, "on_since": "2026-01-01T09:00:00+00:00",
     "ignitions": 341, "warmups": [{"at": "...", "drift_percent": 0.31, "minutes": 3.0,
     "warmed_up_s": 1260.0}]}

`hours` counts completed runs; a run in progress is added from `on_since`. The file is the one
source of truth: every call reads it, every change rewrites it atomically (temporary file, fsync,
`os.replace`), so a crash leaves either the old state or the new one. A missing file is a new
lamp (0 h, off). A hand-written file needs only "hours" (to carry over an old lamp's hours).

Times are timezone-aware datetimes (stored as ISO 8601 in UTC); `now` arguments and the
`clock` callable make them injectable for tests.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import pathlib
from typing import Annotated, Callable, Literal

from spherejax import jsontext
from spherejax import atomic_files
from spherejax.io.plain_files import read_small
from spherejax.io.documents import AwareTime, Document, Expect, check_document, integer, number

from .errors import InstrumentError

FORMAT = "hw.lamp/1"

#: Warm-up checks kept in the state file (the session manifests keep each session's own).
MAX_WARMUPS = 50



class LampStateError(InstrumentError, ValueError):
    """The lamp state file is malformed; the one-line message names the file, the value and what
    was expected."""


class LampError(InstrumentError, RuntimeError):
    """A lamp record out of order (switching on a lamp recorded as on, or off one recorded off)."""


class _Warmup(Document):
    """One passed warm-up check (`Lamp.record_warmup`)."""

    at: AwareTime
    drift_percent: Annotated[number(), Expect("a finite number")]
    minutes: Annotated[number(gt=0), Expect("a finite number of minutes > 0")]
    warmed_up_s: Annotated[number(ge=0), Expect("a finite number of seconds >= 0")]


class _State(Document):
    """The state file (module docstring); only "hours" is required."""

    format: Annotated[Literal[FORMAT], Expect(json.dumps(FORMAT))] = FORMAT
    hours: Annotated[number(ge=0), Expect("the lamp's hours, a finite number >= 0")]
    on_since: AwareTime | None = None
    ignitions: integer(0) = 0
    warmups: Annotated[list[Annotated[_Warmup, Expect("a warm-up check: an object with at, drift_percent, minutes, warmed_up_s")]], Expect("a list of warm-up checks")] = []


def _utc_now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


class Lamp:
    """The lamp's records in `state_file`.

    Args:
      state_file: path of the JSON state (its folder must exist).
      clock: () -> timezone-aware datetime, the time when a method's `now` is None.
    """

    def __init__(self, state_file: os.PathLike | str, *, clock: Callable[[], datetime.datetime] | None = None):
        self.state_file = pathlib.Path(state_file)
        self._clock = clock or _utc_now

    def __repr__(self) -> str:
        return f"Lamp({str(self.state_file)!r})"

    # --- time ----------------------------------------------------------------------------------

    def _now(self, now: datetime.datetime | None) -> datetime.datetime:
        value = self._clock() if now is None else now
        if not isinstance(value, datetime.datetime) or value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"lamp {self.state_file}: time {value!r} is not a timezone-aware datetime")
        return value.astimezone(datetime.timezone.utc)

    # --- state file ----------------------------------------------------------------------------

    def _error(self, location: str, problem: str, expected: str | None) -> LampStateError:
        return LampStateError(f"{self.state_file}: lamp state {location} {problem}, expected {expected}")

    def _read(self) -> dict:
        """The validated state: hours (float), on_since (datetime | None), ignitions (int),
        warmups (list of dicts)."""
        try:
            # Bounded (the record is a few kilobytes) and never waiting on a FIFO in its place.
            data = read_small(self.state_file, 1 << 20)
        except FileNotFoundError:
            return {"hours": 0.0, "on_since": None, "ignitions": 0, "warmups": []}
        except OSError as error:
            raise LampStateError(f"{self.state_file}: lamp state cannot be read: {error.strerror}; "
                                 "expected a JSON object with \"hours\"") from None
        try:
            # The parser every file spherejax reads goes through: a file written here and then
            # damaged (bad bytes, deep nesting, huge integers) is refused like any user file.
            raw = jsontext.loads(data)
        except jsontext.JSONTextError as error:
            raise LampStateError(f"{self.state_file}: lamp state {error.problem}; expected a JSON object with \"hours\"") from None
        if not isinstance(raw, dict):
            raise LampStateError(f"{self.state_file}: lamp state is a JSON {type(raw).__name__}, expected an object with \"hours\"")
        state = check_document(_State, raw, error=self._error, unknown="key")
        return {
            "hours": float(state.hours),
            "on_since": state.on_since,
            "ignitions": state.ignitions,
            "warmups": raw.get("warmups", []),  # as stored: they are written back unchanged
        }

    def _write(self, state: dict) -> None:
        """Replace the state file atomically: a reader (or a crash) sees the old file or the new."""
        record = {
            "format": FORMAT,
            "hours": state["hours"],
            "on_since": None if state["on_since"] is None else state["on_since"].isoformat(),
            "ignitions": state["ignitions"],
            "warmups": state["warmups"][-MAX_WARMUPS:],
        }
        text = json.dumps(record, indent=2) + "\n"
        atomic_files.write_atomic(self.state_file, text)

    # --- records -------------------------------------------------------------------------------

    @property
    def is_on(self) -> bool:
        """Whether the lamp is recorded as burning."""
        return self._read()["on_since"] is not None

    @property
    def on_since(self) -> datetime.datetime | None:
        """When the running lamp was switched on (UTC), None when off."""
        return self._read()["on_since"]

    @property
    def ignitions(self) -> int:
        """How many times the lamp has been switched on (xenon electrodes wear per ignition)."""
        return self._read()["ignitions"]

    @property
    def warmups(self) -> list[dict]:
        """Recorded warm-up checks, oldest first: {"at", "drift_percent", "minutes", "warmed_up_s"}."""
        return list(self._read()["warmups"])

    def switch_on(self, now: datetime.datetime | None = None) -> None:
        """Record that the operator switched the lamp on at `now`. Raises LampError if it is
        recorded as on already (switch it off first, at the time it actually went out)."""
        state = self._read()
        if state["on_since"] is not None:
            raise LampError(f"{self.state_file}: the lamp is recorded as on since {state['on_since'].isoformat()}; switch_off first")
        state["on_since"] = self._now(now)
        state["ignitions"] += 1
        self._write(state)

    def switch_off(self, now: datetime.datetime | None = None) -> float:
        """Record that the lamp went out at `now`; returns that run's hours, added to the total.
        Raises LampError if it is recorded as off."""
        state = self._read()
        if state["on_since"] is None:
            raise LampError(f"{self.state_file}: the lamp is recorded as off; switch_on first")
        run_h = self._run_s(state, self._now(now)) / 3600.0
        state["hours"] += run_h
        state["on_since"] = None
        self._write(state)
        return run_h

    @staticmethod
    def _run_s(state: dict, now: datetime.datetime) -> float:
        # A wall clock stepped backwards (NTP) must not make hours run backwards.
        return max((now - state["on_since"]).total_seconds(), 0.0) if state["on_since"] is not None else 0.0

    def warmed_up_s(self, now: datetime.datetime | None = None) -> float:
        """Seconds since switch-on at `now`; 0 when the lamp is off."""
        return self._run_s(self._read(), self._now(now))

    def hours(self, now: datetime.datetime | None = None) -> float:
        """Lamp hours at `now`: completed runs plus the run in progress."""
        state = self._read()
        return state["hours"] + self._run_s(state, self._now(now)) / 3600.0

    def record_warmup(self, drift_percent: float, minutes: float, now: datetime.datetime | None = None) -> dict:
        """Log a passed warm-up check: the white standard drifted `drift_percent` % over the last
        `minutes` minutes. Returns the entry stored (with the warm-up time at `now`). Raises
        LampError if the lamp is recorded as off, ValueError for a non-finite drift or minutes <= 0."""
        if isinstance(drift_percent, bool) or not math.isfinite(float(drift_percent)):
            raise ValueError(f"lamp {self.state_file}: warm-up drift {drift_percent!r} % is not a finite number")
        if isinstance(minutes, bool) or not math.isfinite(float(minutes)) or float(minutes) <= 0:
            raise ValueError(f"lamp {self.state_file}: warm-up window {minutes!r} min is not a finite number > 0")
        state = self._read()
        if state["on_since"] is None:
            raise LampError(f"{self.state_file}: a warm-up check with the lamp recorded as off; switch_on first")
        at = self._now(now)
        entry = {
            "at": at.isoformat(),
            "drift_percent": float(drift_percent),
            "minutes": float(minutes),
            "warmed_up_s": self._run_s(state, at),
        }
        state["warmups"] = [*state["warmups"], entry]
        self._write(state)
        return dict(entry)


__all__ = ["FORMAT", "Lamp", "LampError", "LampStateError", "MAX_WARMUPS"]
