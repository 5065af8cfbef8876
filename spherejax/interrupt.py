"""Stopping a long run cleanly on SIGINT (Ctrl-C), SIGTERM (what batch schedulers send) or SIGHUP
(the terminal closed).

Python's default is KeyboardInterrupt wherever the main thread happens to be (SIGINT) or death
with no word at all (SIGTERM, SIGHUP): either can leave an input's temporary files, OUT's lock or
an open shutter behind. Instead, while `stop_requests()` is active, a signal only records that a
stop was asked for; the work calls `check()` at its safe points (between inputs, between the
strips of one input's writes, between band images, in every slice of a long wait: `sleep`) and
`check()` raises `Interrupted` there. The code above the safe point then cleans up in its
`finally` blocks as it would for any error, and the command line reports one line and exits 128 +
the signal's number (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP), as a shell does for a
process killed by that signal.

A signal that arrives after the last safe point of a run changes nothing on disk: the run
completes (there is nothing left to stop). The command still exits 128 + the signal, with its
one line, so that the shell or scheduler that sent it knows it was taken (`at_once()`, which the
command line runs every command in, raises a stop still recorded at its end).

Blocking waits that could last indefinitely (an operator prompt) run inside `immediately()`: a
signal there raises `Interrupted` at once rather than after the wait. Waits of a known length
(a filter's settling, a lamp's warm-up interval) call `sleep`, which waits in slices of at most
`SLICE_S` with a safe point after each, so a stop is acted on within a slice, never after the wait.

Commands without safe points of their own (calibrate, evaluate, study, simulate, demo, measure)
run inside `at_once()`. There too the handler only records the signal: raising from it would land
wherever the main thread is, and some places cannot take an exception. A garbage-collector
callback (JAX's `_xla_gc_callback`), a `__del__` or a weakref callback drops it ("Exception
ignored ...": the run went on and exited 0); a Python method that a C library calls back (h5py's
file-object driver writing the calibration) leaves the library's state torn when it raises
("Fatal Python error: Segmentation fault" when HDF5 later closed the file). Instead the handler
arms a profile function (`sys.setprofile`, main thread only, only while a stop is pending) that
raises `Interrupted` at the next call of a function of spherejax's maths or workflows (calibrate,
the fits, the estimators, evaluate, simulate: code nothing but Python calls) from a stack of
spherejax's own frames over the entry point's, with no other library's frame in between
(`_safe_to_raise`). Code that C libraries call back, and the file-owning code with its own safe
points (io, archive, cli), only records. There the stop unwinds through the same clean-up as any
error, at most a call or two after the library the main thread is in returns; it is never
silently dropped:

- `check()`, at the next safe point, raises any recorded stop;
- a raise that Python drops all the same is recognised by `sys.unraisablehook`, which says
  nothing and arms the profile function again;
- the end of the `at_once()` block raises a stop recorded but never raised out of it, so the
  command exits 128 + the signal, never 0.

Only one stop is raised per block: a second signal while the first unwinds (an impatient Ctrl-C)
is recorded, not raised again into the clean-up. Clean-up that must finish whatever arrives
(closing a shutter) runs inside `shielded()`, where nothing is raised and `check()` is quiet; a
stop asked for meanwhile is raised at the next safe point after it.

The state is per process and only the main thread may install handlers (a Python rule): outside
`stop_requests()` and `at_once()` -- a dask worker, a library caller -- `check()` never raises and
`sleep` is a plain wait.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

#: The signals that ask a run to stop.
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: The longest `sleep` waits between two safe points, s: how late a stop may be acted on in a wait.
SLICE_S = 0.05

_pending: int | None = None  # the signal received and not yet acted on
_active = False  # inside stop_requests() or at_once(): the handlers are ours
_at_once = False  # at_once()'s mode: raise where safe (`_safe_to_raise`), not only at safe points
_immediate = False  # inside immediately(): raise from the handler itself
_resumable = True  # the command has a --resume to suggest (not at_once's commands)
_raised = False  # an Interrupted raised by the handler or the profile function is unwinding
_shield_depth = 0  # inside shielded(): clean-up that must run to its end
_profile_before = None  # the profile function before ours was armed (restored when it disarms)


class Interrupted(BaseException):
    """A stop was asked for (SIGINT, SIGTERM or SIGHUP) and the run stopped at a safe point.

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
    """Record the signal (the first one wins); raise it only inside immediately() (a prompt
    waiting in input(), which takes it as it takes KeyboardInterrupt); inside at_once() arm the
    profile function that raises it where that is safe."""
    global _pending, _raised
    if _pending is None:
        _pending = signum
    if _raised or _shield_depth:
        return
    if _immediate:
        _raised = True
        raise Interrupted(_pending, resumable=_resumable)
    if _at_once:
        _arm()


#: Python 3.12+: the profile function is a `sys.monitoring` PY_START callback, which costs nothing
#: at the calls of code it has disabled (every other library's, after its first call): an import
#: of matplotlib under `sys.setprofile` took seconds longer. Python 3.11: `sys.setprofile`.
_MONITORING = getattr(sys, "monitoring", None)
_tool: int | None = None  # the sys.monitoring tool id while armed


def _arm() -> None:
    global _profile_before, _tool
    if _MONITORING is not None:
        if _tool is not None:
            return
        for tool in (5, 4, 3, 2):  # OPTIMIZER_ID first; coverage and debuggers take 0 and 1
            try:
                _MONITORING.use_tool_id(tool, "spherejax.interrupt")
            except ValueError:
                continue
            _MONITORING.register_callback(tool, _MONITORING.events.PY_START, _on_start)
            _MONITORING.set_events(tool, _MONITORING.events.PY_START)
            _tool = tool
            return
    if sys.getprofile() is not _raise_where_safe:  # 3.11, or every tool id taken
        _profile_before = sys.getprofile()
        sys.setprofile(_raise_where_safe)


def _disarm() -> None:
    global _profile_before, _tool
    if _tool is not None:
        _MONITORING.set_events(_tool, 0)
        _MONITORING.register_callback(_tool, _MONITORING.events.PY_START, None)
        _MONITORING.free_tool_id(_tool)
        _tool = None
    if sys.getprofile() is _raise_where_safe:
        sys.setprofile(_profile_before)
    _profile_before = None


def _on_start(code, offset):
    """sys.monitoring's PY_START callback while armed: `_raise_where_safe` for the starting frame;
    the code of other libraries (and spherejax's record-only code) disabled after its first call."""
    if not _may_raise_in(code):
        return _MONITORING.DISABLE
    frame = sys._getframe(1)
    while frame is not None and frame.f_code is not code:
        frame = frame.f_back
    if frame is not None:
        _raise_where_safe(frame, "call", None)
    return None


def _raise_where_safe(frame, event, arg) -> None:
    """The profile function armed by a stop inside at_once(): at the call of a function where
    `_safe_to_raise`, disarm and raise the stop; elsewhere (other libraries' code, a shielded
    clean-up, a stop_requests() block within) let the call go on."""
    global _raised
    if event != "call":
        return
    if _pending is None or _raised or not _active:
        _disarm()
        return
    if not _at_once or _shield_depth or not _safe_to_raise(frame):
        return
    _disarm()
    _raised = True
    raise Interrupted(_pending, resumable=_resumable)


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep

#: spherejax's modules and subpackages where a stop is never raised, only recorded: those whose
#: functions C code calls back (h5py's file-object driver calls io's file methods from HDF5,
#: XLA the kernel's), that own files, locks and terminals (each has its safe points, `check`),
#: and this one. A stop is raised at the call of a function of the others -- the maths and
#: workflows (calibrate, stage2, the estimators, evaluate, simulate, the pipeline), which nothing
#: but Python calls.
_RECORD_ONLY = tuple(_PACKAGE + name for name in (
    "io" + os.sep, "archive" + os.sep, "cli" + os.sep, "_engine" + os.sep, "atomic_files.py", "console.py",
    "cluster.py", "measurement_files.py", "jsontext.py", "interrupt.py", "__init__.py", "__main__.py",
))

#: Code names that the interpreter calls back, never spherejax's own calls.
_CALLBACK_NAMES = frozenset({"__del__"})

_STANDARD_LIBRARY = os.path.dirname(os.path.abspath(contextlib.__file__)) + os.sep
_SITE_PACKAGES = ("site-packages", "dist-packages")

#: Libraries whose Python frames may sit between spherejax's: JAX tracing spherejax's functions
#: and the solvers built on it call them from Python and pass an exception on as any error of
#: the traced code (KeyboardInterrupt's path); they call nothing of spherejax back from C.
_PASS_ON = tuple(f"{os.sep}{name}{os.sep}" for name in ("jax", "equinox", "optimistix", "lineax", "jaxtyping"))


def _may_raise_in(code) -> bool:
    """Whether a stop may ever be raised at the start of `code`: spherejax's maths or workflows,
    or the body of a module being imported (an import of minutes' worth under load, matplotlib
    and colour imported at their first use: stopped there, the import fails as any import may)."""
    name = code.co_filename
    if code.co_name == "<module>":
        return True
    return name.startswith(_PACKAGE) and not name.startswith(_RECORD_ONLY) and code.co_name not in _CALLBACK_NAMES


def _safe_to_raise(frame) -> bool:
    """Whether a stop may be raised at the call of `frame`'s function: a function of spherejax's
    maths or workflows (not `_RECORD_ONLY`, not a `__del__`), and below it a stack of spherejax's
    frames, then only the entry point's -- the standard library's (contextlib, functools) and
    JAX's (`_PASS_ON`) go anywhere -- so that no other library sits between (h5py calling back)."""

    def kind(code) -> str:
        name = code.co_filename
        if name.startswith(_PACKAGE):
            return "ours"
        if name.startswith("<frozen importlib") or code.co_name == "<module>":
            return "neutral"  # an import in progress: the statement that started it waits
        if name.startswith(_STANDARD_LIBRARY) and not any(part in name for part in _SITE_PACKAGES):
            return "neutral" if not name.endswith(f"{os.sep}weakref.py") else "foreign"
        if any(part in name for part in _PASS_ON) and code.co_name not in _CALLBACK_NAMES:
            return "neutral"
        return "foreign"

    if not _may_raise_in(frame.f_code):
        return False
    below_ours = True  # still in the top run of spherejax's frames
    caller = frame.f_back
    while caller is not None:
        what = kind(caller.f_code)
        if what == "foreign":
            below_ours = False
        elif what == "ours" and not below_ours:
            return False  # spherejax called back by another library's code
        caller = caller.f_back
    return True


def _unraisable(unraisable) -> None:
    """sys.unraisablehook while our handlers are in place: a stop raised where Python drops
    exceptions (module docstring) is not reported as "Exception ignored" but armed again;
    anything else goes to the hook that was there before."""
    global _raised
    if isinstance(unraisable.exc_value, Interrupted) and _active:
        _raised = False
        if _at_once:
            _arm()
        return
    _previous_unraisablehook(unraisable)


_previous_unraisablehook = sys.__unraisablehook__


def requested() -> int | None:
    """The signal asking to stop, if one arrived; None otherwise."""
    return _pending


def check() -> None:
    """A safe point: raise `Interrupted` if a stop was asked for (not inside `shielded()`)."""
    global _raised
    if _pending is not None and not _shield_depth:
        _raised = True
        raise Interrupted(_pending, resumable=_resumable)


def sleep(seconds: float) -> None:
    """Wait `seconds` (<= 0, NaN: not at all) in slices of at most SLICE_S, a safe point
    (`check`) before the wait and after every slice: a stop asked for during a wait of minutes is
    acted on within SLICE_S. Outside stop_requests() / at_once() it is a plain wait."""
    check()
    if not seconds > 0:
        return
    deadline = time.monotonic() + seconds if math.isfinite(seconds) else math.inf
    while (left := deadline - time.monotonic()) > 0:
        time.sleep(min(left, SLICE_S))
        check()


@contextlib.contextmanager
def stop_requests() -> Iterator[None]:
    """Turn SIGINT, SIGTERM and SIGHUP into stop requests (module docstring) for the `with` block,
    then restore what was there before. Outside the main thread it does nothing; inside
    `at_once()` it changes the mode for its block and keeps what was recorded."""
    global _at_once, _resumable
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = _at_once, _resumable
    _at_once, _resumable = False, True
    try:
        with _handling():
            yield
    finally:
        _at_once, _resumable = before


@contextlib.contextmanager
def immediately() -> Iterator[None]:
    """Inside the block, a stop request raises `Interrupted` at once (module docstring)."""
    global _immediate
    check()
    before, _immediate = _immediate, _active
    try:
        yield
    finally:
        _immediate = before


@contextlib.contextmanager
def at_once() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise `Interrupted` (not resumable) inside the block at the
    next call where that is safe, never lost (module docstring); `stop_requests()` inside it
    takes over for its own block. A stop recorded but never raised out of the block is raised at
    its end. Outside the main thread it does nothing."""
    global _at_once, _resumable
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = _at_once, _resumable
    _at_once, _resumable = True, False
    try:
        with _handling():
            try:
                yield
            except Interrupted:
                raise
            except BaseException:
                if _pending is None:
                    raise
                # A stop recorded before this error (a raise swallowed and turned into another
                # error, or an error met before the stop's call came): the stop wins.
                raise Interrupted(_pending, resumable=False) from None
            if _pending is not None:
                raise Interrupted(_pending, resumable=False)
    finally:
        _at_once, _resumable = before


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """Clean-up that must run to its end (closing a shutter after a stop): inside the block no
    signal raises and `check()` is quiet; a stop asked for meanwhile stays recorded for the next
    safe point after it."""
    global _shield_depth
    _shield_depth += 1
    try:
        yield
    finally:
        _shield_depth -= 1


@contextlib.contextmanager
def _handling() -> Iterator[None]:
    """Our handler for every signal of SIGNALS and our unraisable hook inside the outermost
    block, with a fresh record; the handlers, hook and record before it after."""
    global _pending, _active, _raised, _previous_unraisablehook
    if _active:  # nested: the outer block's handlers and record stay
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}
    previous_hook = sys.unraisablehook
    _pending, _raised, _active = None, False, True
    try:
        _previous_unraisablehook = previous_hook
        sys.unraisablehook = _unraisable
        for signum in SIGNALS:
            signal.signal(signum, _handler)
        yield
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)
        _disarm()
        sys.unraisablehook = previous_hook
        _pending, _raised, _active = None, False, False


__all__ = ["SIGNALS", "SLICE_S", "Interrupted", "at_once", "check", "immediately", "requested", "shielded",
           "sleep", "stop_requests"]
