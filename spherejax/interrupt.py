"""Stopping a long run cleanly on SIGINT (Ctrl-C) or SIGTERM (what batch schedulers send).

Python's default is KeyboardInterrupt wherever the main thread happens to be (SIGINT) or death
with no word at all (SIGTERM): either can leave an input's temporary files, OUT's lock or an open
shutter behind. Instead, while `stop_requests()` is active, a signal only records that a stop was
asked for; the work calls `check()` at its safe points (between inputs, between the strips of one
input's writes, between band images) and `check()` raises `Interrupted` there. The code above the
safe point then cleans up in its `finally` blocks as it would for any error, and the command
line reports one line and exits 128 + the signal's number (130 for SIGINT, 143 for SIGTERM), as a
shell does for a process killed by that signal.

A signal that arrives after the last safe point of a run changes nothing: the run completes (there
is nothing left to stop) and exits as it would have.

Blocking waits that could last indefinitely (an operator prompt) run inside `immediately()`: a
signal there raises `Interrupted` at once rather than after the wait.

Commands without safe points of their own (calibrate, evaluate, study, simulate, demo, measure)
run inside `at_once()`: SIGINT and SIGTERM raise `Interrupted` wherever the program is, as Python
does for SIGINT alone (KeyboardInterrupt). Python's default for SIGTERM is death without a word,
which skips every `finally`: temporary files stayed behind. Raised, the stop unwinds through the
same clean-up as any error, and the command line prints one line and exits 130 or 143.

The state is per process and only the main thread may install handlers (a Python rule): outside
`stop_requests()` -- a dask worker, a library caller -- `check()` never raises.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

#: The signals that ask a run to stop.
SIGNALS = (signal.SIGINT, signal.SIGTERM)

_pending: int | None = None  # the signal received and not yet acted on
_active = False  # inside stop_requests()
_raise_now = False  # inside immediately()


class Interrupted(BaseException):
    """A stop was asked for (SIGINT or SIGTERM) and the run stopped at a safe point.

    A BaseException, like KeyboardInterrupt, so the `except Exception` that turns a bad input into
    a failed one never records an interruption as the input's failure. `done` and `total` say how
    far the run got, in `unit`s, once the code that knows has filled them in.
    """

    def __init__(self, signum: int, resumable: bool = True):
        super().__init__(signum)
        self.signum = signum
        self.done: int | None = None
        self.total: int | None = None
        self.unit = "inputs"
        self.resumable = resumable  # whether the command has a --resume to suggest

    @property
    def exit_status(self) -> int:
        return 128 + self.signum

    def message(self) -> str:
        """The one line the command line prints."""
        if not self.resumable:
            return "spherejax: interrupted; nothing half-written was left"
        if self.done is None or self.total is None:
            return "spherejax: interrupted; run again with --resume"
        return f"spherejax: interrupted after {self.done} of {self.total} {self.unit}; run again with --resume"


def _handler(signum, frame) -> None:
    global _pending
    _pending = signum
    if _raise_now:
        raise Interrupted(signum)


def requested() -> int | None:
    """The signal asking to stop, if one arrived; None otherwise."""
    return _pending


def check() -> None:
    """A safe point: raise `Interrupted` if a stop was asked for."""
    if _pending is not None:
        raise Interrupted(_pending)


@contextlib.contextmanager
def stop_requests() -> Iterator[None]:
    """Turn SIGINT and SIGTERM into stop requests (module docstring) for the `with` block, then
    restore the handlers that were there before. Outside the main thread it does nothing."""
    global _pending, _active
    if threading.current_thread() is not threading.main_thread() or _active:
        yield
        return
    _pending, _active = None, True
    try:
        with _handling(_handler):
            yield
    finally:
        _pending, _active = None, False


@contextlib.contextmanager
def immediately() -> Iterator[None]:
    """Inside the block, a stop request raises `Interrupted` at once (module docstring)."""
    global _raise_now
    check()
    before, _raise_now = _raise_now, _active
    try:
        yield
    finally:
        _raise_now = before


def _raise_at_once(signum, frame) -> None:
    raise Interrupted(signum, resumable=False)


@contextlib.contextmanager
def at_once() -> Iterator[None]:
    """SIGINT and SIGTERM raise `Interrupted` (not resumable) at once inside the block (module
    docstring); `stop_requests()` inside it takes over for its own block. Outside the main thread
    it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    with _handling(_raise_at_once):
        yield


@contextlib.contextmanager
def _handling(handler) -> Iterator[None]:
    """`handler` for every signal of SIGNALS inside the block; the handlers before it after."""
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}
    try:
        for signum in SIGNALS:
            signal.signal(signum, handler)
        yield
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)


__all__ = ["SIGNALS", "Interrupted", "at_once", "check", "immediately", "requested", "stop_requests"]
