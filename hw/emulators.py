"""Emulated Thorlabs FW102C/FW212C filter wheels and SC10 shutters, served on pseudo-terminals.

Three layers (docs/instrument.md, "Testing without hardware"):

``FilterWheelEmulator`` / ``ShutterEmulator``
    Pure protocol state machines, no I/O: ``receive(bytes)`` returns ``[(delay_s, bytes), ...]``,
    each chunk to be written ``delay_s`` seconds after the previous one. They follow the vendor
    protocol: a command is complete at ``\\r`` (``\\n`` is ignored), the unit echoes it with ``\\r``,
    then a value line ending in ``\\r`` (queries only), then the prompt ``"> "``. Commands are lower
    case; anything not in the table (``POS=2`` included) answers ``Command error CMD_NOT_DEFINED``,
    bad arguments ``Command error CMD_ARG_INVALID``, each error line ending in ``error_line_ending``
    (``\\r`` or ``\\n``: both occur on real units). A wheel move holds the prompt back for the move
    time times ``move_time_scale`` (tests use 0).

``EmulatedPort``
    Serves one emulator on an ``os.openpty`` pseudo-terminal, so drivers go through the real
    ``serial.Serial`` path: give ``port.path`` (e.g. ``/dev/pts/5``) to the driver. A daemon thread
    reads the master side and writes the replies; the slave side is put in raw mode. Faults:
    ``stop_answering`` (reads time out), ``answer_garbage`` (non-protocol bytes), ``vanish`` (the pty
    is closed, so the driver's next read or write fails), ``resume_answering``.

``ScriptedPort``
    A stand-in for ``serial.Serial`` that replays scripted (bytes written, bytes answered) pairs and
    records the exact bytes written and read, for golden-transcript tests (as pymeasure's
    ``expected_protocol``). Install it with ``monkeypatch.setattr(serial, "serial_for_url", ...)``.

Interpretations of docs/instrument.md made here: ``stray_on_open`` goes out ahead of the first reply
(a pty cannot tell the emulator when the driver opens it, and pyserial flushes the input queue on
open, so bytes sent earlier would never be seen); an empty command (a bare ``\\r``) answers with its
echo and the prompt; the SC10 emulator does not run the timed cycles of modes 2..5 and reports the
shutter closed in them.
"""

from __future__ import annotations

import abc
import collections
import os
import random
import re
import select
import threading
import time
import tty

import serial

__all__ = [
    "FilterWheelEmulator",
    "ShutterEmulator",
    "EmulatedPort",
    "ScriptedPort",
    "CMD_NOT_DEFINED",
    "CMD_ARG_INVALID",
]

CMD_NOT_DEFINED = "CMD_NOT_DEFINED"
CMD_ARG_INVALID = "CMD_ARG_INVALID"

_WHEEL_MODELS = {"FW102C": 6, "FW212C": 12}
_UINT = re.compile(r"[0-9]+")


class _CommandError(Exception):
    def __init__(self, code: str):
        super().__init__(code)
        self.code = code


def _uint_arg(arg: str, allowed) -> int:
    """Parse a decimal argument that must lie in ``allowed`` (a range or tuple), else CMD_ARG_INVALID."""
    if not _UINT.fullmatch(arg):
        raise _CommandError(CMD_ARG_INVALID)
    value = int(arg)
    if value not in allowed:
        raise _CommandError(CMD_ARG_INVALID)
    return value


class _PromptedEmulator(abc.ABC):
    """Line assembly, echo, value line, prompt and error replies shared by both Thorlabs units."""

    def __init__(self, *, error_line_ending: bytes, prompt: bytes, stray_on_open: bytes):
        if error_line_ending not in (b"\r", b"\n"):
            raise ValueError(f"error_line_ending must be b'\\r' or b'\\n', got {error_line_ending!r}")
        self.error_line_ending = error_line_ending
        self.prompt = prompt
        self.stray_on_open = stray_on_open
        self._line = bytearray()
        self._first_reply = True
        #: Commands received, in order (decoded; for tests).
        self.commands: list[str] = []

    def receive(self, data: bytes) -> list[tuple[float, bytes]]:
        """Feed bytes from the host; return ``[(delay_s, bytes), ...]`` to send back, in order.

        ``delay_s`` is measured from the previous chunk (from now for the first one).
        """
        out: list[tuple[float, bytes]] = []
        for byte in data:
            if byte == 0x0D:
                line = bytes(self._line)
                self._line.clear()
                out.extend(self._reply(line))
            elif byte != 0x0A:  # the units end commands on CR only; a LF from a CRLF host is dropped
                self._line.append(byte)
        if out and self._first_reply:
            self._first_reply = False
            out[0] = (out[0][0], self.stray_on_open + out[0][1])
        # Merge chunks that go out back to back, so a reply without delay is one write.
        merged: list[tuple[float, bytes]] = []
        for delay, chunk in out:
            if merged and delay == 0:
                merged[-1] = (merged[-1][0], merged[-1][1] + chunk)
            else:
                merged.append((delay, chunk))
        return merged

    def _reply(self, line: bytes) -> list[tuple[float, bytes]]:
        echo = line + b"\r"
        text = line.decode("ascii", errors="replace")
        self.commands.append(text)
        if not text:
            return [(0.0, echo + self.prompt)]
        try:
            value, delay = self._execute(text)
        except _CommandError as exc:
            error = f"Command error {exc.code}".encode("ascii")
            return [(0.0, echo + error + self.error_line_ending + self.prompt)]
        body = echo if value is None else echo + value.encode("ascii") + b"\r"
        if delay > 0:
            return [(0.0, body), (delay, self.prompt)]
        return [(0.0, body + self.prompt)]

    @abc.abstractmethod
    def _execute(self, text: str) -> tuple[str | None, float]:
        """Run one command: return (value line or None, seconds before the prompt); raise
        ``_CommandError`` for an unknown command or a bad argument."""


class FilterWheelEmulator(_PromptedEmulator):
    """A Thorlabs FW102C / FW212C as a protocol state machine.

    Args:
        model: ``"FW102C"`` (6 positions) or ``"FW212C"`` (12); sets the initial ``pcount``.
        position: initial slot, 1..count.
        move_time_scale: factor on the modelled move times (0: instant, 1: real time).
        firmware: version in the ``*idn?`` reply.
        error_line_ending: ``b"\\r"`` or ``b"\\n"`` after ``Command error ...``.
        stray_on_open: bytes sent ahead of the first reply (power-up / line-glitch noise).
        prompt: the prompt; ``b">"`` models units that omit the trailing space.
        identity: overrides the whole ``*idn?`` reply (to emulate a wrong device).

    ``position`` takes the target slot as soon as ``pos=n`` arrives; only the prompt waits for the
    move. Attributes read by tests and the simulated camera: ``position``, ``count``, ``speed`` (0 slow,
    1 high), ``sensors``, ``trigger``, ``baud`` (1 = 115200, 0 = 9600), ``saved`` (settings stored by
    ``save``), ``moves`` (list of ``(from, to, seconds)`` before scaling).
    """

    #: Seconds to start and settle a move, and seconds per slot at high and slow speed.
    MOVE_START_S = 0.4
    FAST_S_PER_SLOT = 0.55
    SLOW_S_PER_SLOT = 1.1

    def __init__(
        self,
        *,
        model: str = "FW212C",
        position: int = 1,
        move_time_scale: float = 0.0,
        firmware: str = "1.07",
        error_line_ending: bytes = b"\r",
        stray_on_open: bytes = b"\x00\x00Command error CMD_NOT_DEFINED\r> ",
        prompt: bytes = b"> ",
        identity: str | None = None,
    ):
        super().__init__(error_line_ending=error_line_ending, prompt=prompt, stray_on_open=stray_on_open)
        if model not in _WHEEL_MODELS:
            raise ValueError(f"model must be one of {sorted(_WHEEL_MODELS)}, got {model!r}")
        self.model = model
        self.count = _WHEEL_MODELS[model]
        if not 1 <= position <= self.count:
            raise ValueError(f"position must be in 1..{self.count}, got {position}")
        if move_time_scale < 0:
            raise ValueError(f"move_time_scale must be >= 0, got {move_time_scale}")
        self.position = position
        self.move_time_scale = float(move_time_scale)
        self.identity = identity or f"THORLABS FW102C/FW212C Filter Wheel version {firmware}"
        self.speed = 1
        self.sensors = 1
        self.trigger = 0
        self.baud = 1
        self.saved: dict[str, int] = {}
        self.moves: list[tuple[int, int, float]] = []
        self._pending_presses = 0

    def move_time_s(self, start: int, target: int) -> float:
        """Unscaled seconds for a move from slot ``start`` to ``target``.

        The wheel turns the short way round: ``MOVE_START_S`` plus a time per slot, which gives
        0.95 s to a neighbour and about 2.5 s for a typical 4-slot move at high speed, and 7 s for the
        longest move (6 slots of an FW212C) in slow mode (docs/instrument.md's figures).
        """
        steps = abs(target - start)
        steps = min(steps, self.count - steps)
        if steps == 0:
            return 0.0
        return self.MOVE_START_S + (self.FAST_S_PER_SLOT if self.speed else self.SLOW_S_PER_SLOT) * steps

    def press_button(self, forward: bool = True) -> None:
        """A front-panel button press: one slot forward or back, behind the software's back."""
        self.position = (self.position - 1 + (1 if forward else -1)) % self.count + 1

    def press_button_during_next_move(self, presses: int = 1) -> None:
        """Someone presses the forward button ``presses`` times while the next ``pos=`` move runs:
        that move ends ``presses`` slots past its target (the driver's ``pos?`` check must notice)."""
        self._pending_presses += presses

    def _execute(self, text: str) -> tuple[str | None, float]:
        queries = {
            "*idn?": lambda: self.identity,
            "pos?": lambda: str(self.position),
            "pcount?": lambda: str(self.count),
            "speed?": lambda: str(self.speed),
            "sensors?": lambda: str(self.sensors),
            "trig?": lambda: str(self.trigger),
            "baud?": lambda: str(self.baud),
        }
        if text in queries:
            return queries[text](), 0.0
        if text == "save":
            self.saved = {"pcount": self.count, "speed": self.speed, "sensors": self.sensors,
                          "trig": self.trigger, "baud": self.baud}
            return None, 0.0
        name, sep, arg = text.partition("=")
        if not sep:
            raise _CommandError(CMD_NOT_DEFINED)
        if name == "pos":
            return None, self._move(_uint_arg(arg, range(1, self.count + 1)))
        if name == "pcount":
            self.count = _uint_arg(arg, tuple(_WHEEL_MODELS.values()))
            if self.position > self.count:
                self.position = 1
        elif name == "speed":
            self.speed = _uint_arg(arg, (0, 1))
        elif name == "sensors":
            self.sensors = _uint_arg(arg, (0, 1))
        elif name == "trig":
            self.trigger = _uint_arg(arg, (0, 1))
        elif name == "baud":
            self.baud = _uint_arg(arg, (0, 1))
        else:
            raise _CommandError(CMD_NOT_DEFINED)
        return None, 0.0

    def _move(self, target: int) -> float:
        start = self.position
        seconds = self.move_time_s(start, target)
        self.moves.append((start, target, seconds))
        self.position = target
        for _ in range(self._pending_presses):
            self.press_button()
        self._pending_presses = 0
        return seconds * self.move_time_scale


class ShutterEmulator(_PromptedEmulator):
    """A Thorlabs SC10 shutter controller as a protocol state machine.

    The shutter is open only while enabled, in manual mode (1) and with the interlock intact.

    Args:
        closed: initial shutter state (sets ``enabled = not closed``).
        mode: 1 manual, 2 auto, 3 single, 4 repeat, 5 external gate.
        firmware: version in the ``id?`` reply.
        open_ms, shut_ms: the timed-mode open and shut durations in milliseconds.
        error_line_ending, stray_on_open, prompt, identity: as for ``FilterWheelEmulator``.

    Attributes: ``closed`` (settable), ``enabled``, ``mode``, ``open_ms``, ``shut_ms``,
    ``interlock`` (True when tripped), ``baud`` (0 = 9600, 1 = 115200), ``saved``, ``toggles``
    (number of ``ens`` received).
    """

    def __init__(
        self,
        *,
        closed: bool = True,
        mode: int = 1,
        firmware: str = "1.07",
        open_ms: int = 100,
        shut_ms: int = 100,
        error_line_ending: bytes = b"\r",
        stray_on_open: bytes = b"",
        prompt: bytes = b"> ",
        identity: str | None = None,
    ):
        super().__init__(error_line_ending=error_line_ending, prompt=prompt, stray_on_open=stray_on_open)
        if mode not in range(1, 6):
            raise ValueError(f"mode must be 1..5, got {mode}")
        self.enabled = not closed
        self.mode = mode
        self.open_ms = open_ms
        self.shut_ms = shut_ms
        self.interlock = False
        self.baud = 0
        self.identity = identity or f"THORLABS SC10 VERSION {firmware}"
        self.saved: dict[str, int] = {}
        self.toggles = 0

    @property
    def closed(self) -> bool:
        """True when the blades are shut (what ``closed?`` reports)."""
        return not (self.enabled and self.mode == 1 and not self.interlock)

    @closed.setter
    def closed(self, value: bool) -> None:
        self.enabled = not value

    def trip_interlock(self) -> None:
        """Open the interlock circuit: the shutter closes and stays closed, enable drops."""
        self.interlock = True
        self.enabled = False

    def reset_interlock(self) -> None:
        """Restore the interlock circuit (the shutter stays closed until enabled again)."""
        self.interlock = False

    def _execute(self, text: str) -> tuple[str | None, float]:
        queries = {
            "id?": lambda: self.identity,
            "ens?": lambda: str(int(self.enabled)),
            "closed?": lambda: str(int(self.closed)),
            "mode?": lambda: str(self.mode),
            "open?": lambda: str(self.open_ms),
            "shut?": lambda: str(self.shut_ms),
            "interlock?": lambda: str(int(self.interlock)),
            "baud?": lambda: str(self.baud),
        }
        if text in queries:
            return queries[text](), 0.0
        if text == "ens":
            self.toggles += 1
            self.enabled = not self.enabled
            return None, 0.0
        if text == "save":
            self.saved = {"mode": self.mode, "open": self.open_ms, "shut": self.shut_ms, "baud": self.baud}
            return None, 0.0
        name, sep, arg = text.partition("=")
        if not sep:
            raise _CommandError(CMD_NOT_DEFINED)
        if name == "mode":
            self.mode = _uint_arg(arg, range(1, 6))
        elif name == "open":
            self.open_ms = _uint_arg(arg, range(0, 1_000_000))
        elif name == "shut":
            self.shut_ms = _uint_arg(arg, range(0, 1_000_000))
        elif name == "baud":
            self.baud = _uint_arg(arg, (0, 1))
        else:
            raise _CommandError(CMD_NOT_DEFINED)
        return None, 0.0


# Bytes no Thorlabs reply contains: no CR/LF, no prompt, no ASCII letters (so no "CMD_"), no NUL.
_GARBAGE = bytes(range(0x80, 0x100)) + b"#$%&*@~^|"


class EmulatedPort:
    """Serve one emulator on a pseudo-terminal.

    Use as a context manager (or ``start()`` / ``stop()``)::

        with EmulatedPort(FilterWheelEmulator()) as port, FilterWheel(port.path) as wheel:
            wheel.move_to(3)
            assert port.emulator.position == 3

    The server thread is a daemon; ``stop()`` joins it and closes both pty fds, so nothing leaks.
    A port serves once: after ``stop()`` or ``vanish()`` create a new one.

    Attributes:
        emulator: the state machine (read its state; hold ``lock`` to change it mid-session).
        path: slave device path for the driver, set by ``start()``.
        lock: held while the emulator processes input.
        transcript: the last bytes exchanged, ``("in", bytes)`` from the host and ``("out", bytes)``
            to it (recorded as each chunk is queued to the pty), at most ``transcript_limit`` entries.
    """

    def __init__(self, emulator, *, transcript_limit: int = 10_000, seed: int = 0):
        self.emulator = emulator
        self.path: str | None = None
        self.lock = threading.Lock()
        self.transcript: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=transcript_limit)
        self._mode = "answer"
        self._rng = random.Random(seed)
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._used = False

    # -- lifetime -------------------------------------------------------------------------------

    def start(self) -> "EmulatedPort":
        """Open the pty and start serving; returns self."""
        if self._used:
            raise RuntimeError("an EmulatedPort serves once; create a new one")
        self._used = True
        master, slave = os.openpty()
        try:
            # Raw mode: no echo, no CR/LF translation, no line buffering on the slave side, so the
            # driver sees exactly the bytes the emulator writes (pyserial sets the same on open).
            tty.setraw(slave)
            os.set_blocking(master, False)
            self.path = os.ttyname(slave)
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        # The slave fd stays open here for the port's lifetime: with no slave open, reads on the
        # master fail with EIO, and the path would vanish whenever the driver disconnects.
        self._master, self._slave = master, slave
        self._thread = threading.Thread(target=self._serve, name=f"EmulatedPort {self.path}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, join the thread and close the pty (idempotent)."""
        self._halt.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        self._close_fds()

    @property
    def is_running(self) -> bool:
        """True while the server thread runs."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def holds_pty(self) -> bool:
        """True while this port keeps its pty open. Once it closes both ends the kernel removes
        `path`, but another process may be given the same /dev/pts number the next moment, so
        whether `path` exists says nothing of this port."""
        return self._master is not None or self._slave is not None

    def __enter__(self) -> "EmulatedPort":
        if not self._used:
            self.start()
        elif not self.is_running:
            raise RuntimeError("this EmulatedPort was stopped; create a new one")
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"EmulatedPort({type(self.emulator).__name__}, path={self.path!r}, mode={self._mode!r})"

    # -- faults ---------------------------------------------------------------------------------

    def stop_answering(self) -> None:
        """Fault: swallow everything from now on (the driver's reads time out)."""
        self._mode = "silent"

    def answer_garbage(self) -> None:
        """Fault: answer every input with random non-protocol bytes (no echo, no prompt)."""
        self._mode = "garbage"

    def resume_answering(self) -> None:
        """End ``stop_answering`` / ``answer_garbage``; the emulator keeps its state."""
        self._mode = "answer"

    def vanish(self) -> None:
        """Fault: the port disappears (USB unplugged): the pty is closed and its path removed.

        The driver's next read or write raises ``serial.SerialException``; opening the path fails.
        """
        self._mode = "vanished"
        self.stop()

    # -- server thread --------------------------------------------------------------------------

    def _close_fds(self) -> None:
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            setattr(self, name, None)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    def _serve(self) -> None:
        master = self._master
        try:
            while not self._halt.is_set():
                # A short select timeout bounds how long stop() waits; data wakes it at once.
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    continue
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    continue
                if not data:
                    return
                self._handle(master, data)
        except (OSError, ValueError):
            # The fd went away under us (stop() after a join timeout): nothing left to serve.
            return

    def _handle(self, master: int, data: bytes) -> None:
        self.transcript.append(("in", data))
        mode = self._mode
        if mode == "silent":
            return
        if mode == "garbage":
            self._write(master, bytes(self._rng.choice(_GARBAGE) for _ in range(len(data) + 8)))
            return
        with self.lock:
            replies = self.emulator.receive(data)
        for delay, chunk in replies:
            # A move holds the prompt back; stop() must not wait for it.
            if delay > 0 and self._halt.wait(delay):
                return
            if self._mode != "answer":  # a fault injected mid-move drops the rest of the reply
                return
            self._write(master, chunk)

    def _write(self, master: int, chunk: bytes) -> None:
        # Recorded before writing, so a reader that has seen the bytes also finds them in the transcript.
        self.transcript.append(("out", chunk))
        while chunk and not self._halt.is_set():
            try:
                written = os.write(master, chunk)
            except BlockingIOError:
                # The slave's input queue is full (the driver is not reading): wait, but stay stoppable.
                select.select([], [master], [], 0.05)
                continue
            chunk = chunk[written:]


class ScriptedPort:
    """A fake ``serial.Serial`` replaying a script, recording the exact bytes written and read.

    Each script entry is ``(expected_write, reply)``: when the bytes written so far complete
    ``expected_write`` the reply becomes readable. Writing anything else raises ``AssertionError``.
    ``transcript`` lists ``("write", bytes)`` and ``("read", bytes)`` with consecutive reads merged, i.e.
    exactly what the driver sent and received. ``assert_done()`` checks every entry was used and
    every reply byte read.

    Install it with pytest's monkeypatch, so drivers get it from ``serial.serial_for_url``::

        port = ScriptedPort([(b"pos?\\r", b"pos?\\r3\\r> ")])
        monkeypatch.setattr(serial, "serial_for_url", port.serial_for_url)

    Args:
        script: ``(bytes the driver must write, bytes answered)`` pairs, in order.
        url: the port name the fake reports.
    """

    def __init__(self, script, *, url: str = "scripted://"):
        self.script = [(bytes(w), bytes(r)) for w, r in script]
        self.port = url
        self.is_open = False
        self.timeout: float | None = None
        #: Keyword arguments the driver passed to ``serial_for_url`` (baudrate, timeouts, ...).
        self.settings: dict = {}
        self.transcript: list[tuple[str, bytes]] = []
        self.opened = 0
        self._unmatched = bytearray()
        self._pending = bytearray()
        self._vanished = False

    def serial_for_url(self, url, *args, **kwargs) -> "ScriptedPort":
        """Replacement for ``serial.serial_for_url``: records the settings and returns self, open."""
        if self._vanished:
            raise serial.SerialException(f"could not open port {url}: vanished")
        self.port = url
        self.settings = dict(kwargs)
        self.timeout = kwargs.get("timeout")
        self.is_open = True
        self.opened += 1
        return self

    def vanish(self) -> None:
        """Fault: every later call fails as pyserial does for an unplugged adapter."""
        self._vanished = True

    def reappear(self, script=()) -> None:
        """End ``vanish()`` (the adapter is plugged back in): the port opens again and replays
        ``script``, appended to whatever is left of the old one."""
        self._vanished = False
        self._unmatched.clear()
        self._pending.clear()
        self.script.extend((bytes(w), bytes(r)) for w, r in script)

    def _check(self) -> None:
        if self._vanished:
            raise serial.SerialException("device reports readiness to read but returned no data")
        if not self.is_open:
            raise serial.PortNotOpenError()

    def _log(self, kind: str, data: bytes) -> None:
        if self.transcript and self.transcript[-1][0] == kind == "read":
            self.transcript[-1] = (kind, self.transcript[-1][1] + data)
        else:
            self.transcript.append((kind, data))

    def write(self, data: bytes) -> int:
        self._check()
        self._log("write", bytes(data))
        self._unmatched += data
        while self.script and self._unmatched.startswith(self.script[0][0]):
            expected, reply = self.script.pop(0)
            del self._unmatched[: len(expected)]
            self._pending += reply
        if self._unmatched and not (self.script and self.script[0][0].startswith(bytes(self._unmatched))):
            expected = self.script[0][0] if self.script else None
            raise AssertionError(f"driver wrote {bytes(self._unmatched)!r}, script expects {expected!r}")
        return len(data)

    def read(self, size: int = 1) -> bytes:
        self._check()
        if not self._pending:
            # Behave like a port with a read timeout, waiting a little (not all of it: no device
            # will answer later, and the drain's quiet period would otherwise cost whole timeouts).
            time.sleep(min(self.timeout or 0.0, 0.01))
            return b""
        data = bytes(self._pending[:size])
        del self._pending[:size]
        self._log("read", data)
        return data

    @property
    def in_waiting(self) -> int:
        self._check()
        return len(self._pending)

    def reset_input_buffer(self) -> None:
        self._check()
        if self._pending:
            raise AssertionError(f"driver discarded unread reply bytes {bytes(self._pending)!r}")

    def close(self) -> None:
        self.is_open = False

    def assert_done(self) -> None:
        """Every scripted write happened and every reply byte was read."""
        if self.script:
            raise AssertionError(f"script entries never written: {self.script!r}")
        if self._pending:
            raise AssertionError(f"reply bytes never read: {bytes(self._pending)!r}")
