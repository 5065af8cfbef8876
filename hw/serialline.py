"""The echo / value line / prompt protocol shared by the Thorlabs FW102C/FW212C and SC10.

Protocol facts (docs/instrument.md, "Thorlabs FW102C / FW212C serial protocol" and "SC10"):

- 8N1, no flow control; 115200 baud for the wheel, 9600 for the SC10.
- A command is lower-case ASCII ending in ``\\r``. The unit echoes the command, then prints one value
  line (queries only), then the prompt ``>`` (usually ``"> "``; the trailing space is not guaranteed)::

      b"pos?\\r"   ->  b"pos?\\r3\\r> "
      b"pos=3\\r"  ->  b"pos=3\\r" ... (the move) ... b"> "
      b"pos=7\\r"  ->  b"pos=7\\rCommand error CMD_ARG_INVALID\\n> "

- Error lines (``Command error CMD_NOT_DEFINED`` / ``Command error CMD_ARG_INVALID``) may end in
  ``\\n`` instead of ``\\r``, so replies are split on either.
- On open the line can carry stray bytes (``\\x00`` and a ``CMD_NOT_DEFINED`` error): send a bare
  ``\\r`` and drain whatever comes back before the first real command.

How a reply is read: the input buffer is flushed, the command written, and bytes are read in short
polls (``POLL_S``) until a deadline, never with one fixed read. Each poll is a safe point
(`spherejax.interrupt.check`): a stop asked for while a wheel moves (up to its ``move_timeout_s``)
is acted on within a poll, the port left open for the clean-up to close the shutter. The reply is complete once the
echo of the command has arrived followed by the prompt; lines before the echo are stale (a late
prompt after a timed-out move, a trailing space) and are ignored, and ``\\x00`` bytes are dropped.
Any line between echo and prompt that contains ``Command error`` or ``CMD_`` is a device error
(``DeviceError``).

Replies that do not complete are classified: prompt-terminated text without the echo is a
``DeviceError`` if it holds an error line and a ``ProtocolError`` otherwise (a bare stale prompt is
skipped); at the deadline, nothing at all or an echo without its prompt (a move still running) is a
``DeviceTimeout`` and other bytes without the echo are a ``ProtocolError`` (garbage, a wrong baud
rate, another device). Value lines must be printable ASCII, else ``ProtocolError``.

Any ``serial.SerialException`` / ``OSError`` from the port closes it and becomes a ``PortError``;
timeouts and protocol errors leave the port open, so a caller can still make the instrument safe.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import os
import re
import stat
import threading
import time

import serial
from spherejax import interrupt

from .errors import DeviceError, DeviceTimeout, PortError, ProtocolError

try:  # tcflush on a vanished pty raises termios.error, which is not an OSError.
    import termios

    _PORT_FAILURES: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # pragma: no cover - Windows has no termios
    _PORT_FAILURES = (serial.SerialException, OSError)

__all__ = ["PromptedSerialDevice", "Scan", "ERROR_MARKERS", "POLL_S", "DRAIN_QUIET_S", "PORT_EXPECTED", "open_problem",
           "failure_problem"]

log = logging.getLogger(__name__)

#: Seconds one read waits for a first byte; bounds how late a deadline can be noticed.
POLL_S = 0.05
#: Seconds of silence after a prompt that end the drain on connect. Stray bytes and the answer to
#: the bare \r come back to back; 50 ms is ~48 characters at 9600 baud. Anything later is flushed
#: before the next command or skipped as a stale line ahead of its echo.
DRAIN_QUIET_S = 0.05
#: Substrings that mark a line as a device error (docs/instrument.md: look for "Command error" / "CMD_").
ERROR_MARKERS = ("Command error", "CMD_")

_LINE_BREAK = re.compile(r"[\r\n]")
#: What a port should be, for the messages of one that cannot be opened or fails.
PORT_EXPECTED = "a serial port: a terminal device such as /dev/ttyUSB0, or a pyserial URL such as socket://host:port"
#: The most characters of pyserial's own words kept in a message.
_DETAIL_LENGTH = 160
_LEADING_PROMPTS = re.compile(r"^[\s>]+")


def _text(raw: bytes) -> str:
    # NULs are line noise the units emit on open. Non-ASCII bytes become U+FFFD, which _printable
    # rejects; messages show the raw bytes, so nothing is lost by replacing them here.
    return raw.replace(b"\x00", b"").decode("ascii", errors="replace")


def _errno_of(exc: BaseException) -> int | None:
    """The errno behind a pyserial failure: its own, its cause's, or the one pyserial wrote into
    its text ("Could not configure port: (25, 'Inappropriate ioctl for device')")."""
    for candidate in (exc, exc.__cause__, exc.__context__):
        number = getattr(candidate, "errno", None)
        if isinstance(number, int):
            return number
        args = getattr(candidate, "args", ())
        if args and isinstance(args[0], int):  # termios.error(5, 'Input/output error')
            return args[0]
    found = re.search(r"\[Errno (\d+)\]|\((\d+), '", str(exc))
    return int(found.group(1) or found.group(2)) if found else None


def _pyserial_words(exc: BaseException, port: str) -> str:
    """pyserial's message as a short detail: one line, no "[Errno N]", the port not repeated."""
    args = getattr(exc, "args", ())
    # (errno, words): termios.error(5, 'Input/output error'), SerialException(2, "could not open
    # port ..."): the words, not the tuple.
    words = args[1] if len(args) == 2 and isinstance(args[0], int) and isinstance(args[1], str) else exc
    text = " ".join(str(words).split())
    text = re.sub(r"\[Errno \d+\]\s*", "", text)
    text = re.sub(r"^could not open port\s*(?:" + re.escape(port) + r")?\s*:?\s*", "", text)
    text = text.replace(f"'{port}'", "").replace(port, "").replace("  ", " ")
    text = re.sub(r"\s*:\s*(?=:|$)", "", text).strip(" :")
    return text if len(text) <= _DETAIL_LENGTH else text[: _DETAIL_LENGTH - 3] + "..."


def open_problem(port: str, exc: BaseException) -> str:
    """Why pyserial could not open `port`, in plain words, then what was expected (`PortError`'s
    problem: "cannot open port: there is no such device ... (expected a serial port: ...)")."""
    number = _errno_of(exc)
    if number in (errno.ENOENT, errno.ENXIO, errno.ENODEV):
        what = "there is no such device (not plugged in, switched off, or named otherwise)"
    elif number == errno.EISDIR:
        what = "it is a folder, not a serial device"
    elif number == errno.ENOTTY:
        try:
            mode = os.stat(port).st_mode
        except OSError:
            mode = 0
        kind = ("a regular file" if stat.S_ISREG(mode) else
                "a device that is not a terminal" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
                "a FIFO" if stat.S_ISFIFO(mode) else "something other than a terminal")
        what = f"it is {kind}, not a serial port (it takes no serial settings)"
    elif number in (errno.EACCES, errno.EPERM):
        what = ("permission denied: this user may not read and write it (on Linux, join the group "
                "that owns it, often dialout)")
    elif number in (errno.EBUSY, errno.EAGAIN) or "exclusively lock" in str(exc):
        what = "it is busy: another program has it open"
    elif isinstance(exc, ValueError):
        what = f"it is neither a device path nor a URL pyserial knows ({_pyserial_words(exc, port)})"
    else:
        detail = _pyserial_words(exc, port)
        what = f"it could not be opened (pyserial: {detail})" if detail else "it could not be opened"
    return f"cannot open port: {what} (expected {PORT_EXPECTED})"


def failure_problem(port: str, exc: BaseException) -> str:
    """What a port's failure mid-session means (`PortError`'s problem: "port failed: the device is
    gone ..."), pyserial's words as a detail."""
    number = _errno_of(exc)
    detail = _pyserial_words(exc, port)
    if number in (errno.EIO, errno.ENXIO, errno.ENODEV) or "returned no data" in str(exc):
        what = "the device is gone: unplugged or switched off (or another program took the port)"
    elif number == errno.EBADF:
        what = "the port was closed under it"
    else:
        what = "the port stopped working"
    return f"port failed: {what}" + (f" (pyserial: {detail})" if detail else "") + " (expected a device that stays connected)"


def _printable(line: str) -> bool:
    """Protocol lines are printable ASCII; anything else is line noise or a wrong baud rate."""
    return all(" " <= c <= "~" for c in line)


def _ends_in_prompt(text: str) -> bool:
    return text.rstrip().endswith(">")


def _is_error(line: str) -> bool:
    return any(marker in line for marker in ERROR_MARKERS)


@dataclasses.dataclass(frozen=True)
class Scan:
    """What the bytes read so far for one command amount to."""

    echo: bool  # the echo of the command has arrived
    complete: bool  # echo and the prompt after it have arrived
    values: list[str]  # non-empty lines between the echo and the prompt (or the end, if incomplete)
    unechoed: list[str]  # non-empty lines when no echo has arrived (garbage, or an unechoed error)
    ends_in_prompt: bool  # the text so far ends with ">"


def _scan(command: str, raw: bytes) -> Scan:
    """Parse the bytes read so far in answer to ``command``.

    Lines are split on \\r or \\n. The echo is the first line ending in the command once stale
    prompts and whitespace are stripped from its start (lines before it are stale and ignored). The
    prompt is the first ``>`` after the echo; a value glued to it (``3>``) still counts as a value.
    """
    text = _text(raw)
    lines = _LINE_BREAK.split(text)
    wanted = command.strip().casefold()
    for i, line in enumerate(lines):
        # endswith: line noise glued ahead of the echo (no line break in between) is tolerated.
        if not _LEADING_PROMPTS.sub("", line).strip().casefold().endswith(wanted):
            continue
        # The echo line must be terminated, or "pos=1" would match the start of "pos=12".
        if i == len(lines) - 1:
            break
        values = []
        for rest in lines[i + 1 :]:
            value, prompt, _ = rest.partition(">")
            if value.strip():
                values.append(value.strip())
            if prompt:
                return Scan(True, True, values, [], True)
        return Scan(True, False, values, [], False)
    unechoed = [ln for ln in (_LEADING_PROMPTS.sub("", x).strip() for x in lines) if ln]
    return Scan(False, False, [], unechoed, _ends_in_prompt(text))


class PromptedSerialDevice:
    """A serial instrument that echoes each command, prints a value line and a ``>`` prompt.

    Owns its port: ``connect`` opens it with ``serial.serial_for_url`` (any pyserial URL or device
    path) and ``disconnect`` closes it; use it as a context manager. Transactions hold a re-entrant
    lock, so a watchdog thread calling e.g. ``Shutter.make_safe`` cannot interleave bytes with the
    acquisition thread.

    Args:
        port: pyserial URL (``"loop://"``, ``"socket://host:port"``, ...) or device path (``"/dev/ttyUSB0"``).
        baudrate: line speed in baud (8N1, no flow control).
        timeout_s: seconds to wait for a complete reply to an ordinary command or query.
    """

    #: Bytes `connect` sends before draining the line: a bare CR, which the Thorlabs units answer
    #: with an echo (or an error) and their prompt.
    WAKE = b"\r"
    #: Whether the device ends every reply with the ``>`` prompt (the drain waits for one).
    PROMPTED = True

    def __init__(self, port: str, *, baudrate: int, timeout_s: float = 1.0):
        if not (math.isfinite(timeout_s) and timeout_s > 0):  # NaN or inf: a wait without end
            raise ValueError(f"timeout_s must be a finite number of seconds > 0, got {timeout_s}")
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = float(timeout_s)
        self._serial = None
        self._lock = threading.RLock()
        #: Raw bytes of the last reply read (for error messages and logs).
        self.last_reply: bytes = b""

    # -- lifetime -------------------------------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        """True while the port is open."""
        return self._serial is not None

    def connect(self) -> None:
        """Open the port, send a bare ``\\r``, drain stray bytes, then run the device's checks.

        Does nothing when already connected. On any failure the port is closed again before the
        exception propagates.

        Raises:
            PortError: the port cannot be opened (or fails during the checks).
            DeviceTimeout, ProtocolError, DeviceError: from the subclass's identity checks.
        """
        with self._lock:
            if self._serial is not None:
                return
            try:
                self._serial = serial.serial_for_url(
                    self.port,
                    baudrate=self.baudrate,
                    bytesize=serial.EIGHTBITS,
                    parity=serial.PARITY_NONE,
                    stopbits=serial.STOPBITS_ONE,
                    xonxoff=False,
                    rtscts=False,
                    dsrdtr=False,
                    timeout=POLL_S,
                    write_timeout=self.timeout_s,
                )
            except (*_PORT_FAILURES, ValueError) as exc:
                # ValueError: pyserial's answer to an unknown URL scheme or an unsupported setting.
                raise PortError(self.port, None, open_problem(self.port, exc)) from exc
            try:
                self._drain()
                self._on_connect()
            except BaseException:
                self._close_quietly()
                raise

    def disconnect(self) -> None:
        """Close the port (idempotent; errors while closing a vanished port are ignored)."""
        with self._lock:
            self._close_quietly()

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.disconnect()

    def __repr__(self) -> str:
        state = "connected" if self.is_connected else "disconnected"
        return f"{type(self).__name__}({self.port!r}, {state})"

    def _on_connect(self) -> None:
        """Hook: identity checks and settings after the port is open and drained."""

    def _close_quietly(self) -> None:
        ser, self._serial = self._serial, None
        if ser is None:
            return
        try:
            ser.close()
        except _PORT_FAILURES as exc:
            log.debug("%s: ignoring error while closing: %s", self.port, exc)

    # -- transactions ---------------------------------------------------------------------------

    def query(self, command: str, *, timeout_s: float | None = None) -> str:
        """Send a query (e.g. ``"pos?"``) and return its value line, e.g. ``"3"``.

        Args:
            command: the query without its ``\\r``.
            timeout_s: seconds to wait for the prompt; defaults to ``self.timeout_s``.

        Raises:
            DeviceTimeout, ProtocolError (no value line), DeviceError (``Command error``), PortError.
        """
        lines = self._transact(command, timeout_s, expect_value=True)
        if not lines:
            raise ProtocolError(self.port, command, "no value line in the reply", self.last_reply)
        # One value line is the protocol; several are joined rather than dropped so nothing is lost.
        return " ".join(lines)

    def command(self, command: str, *, timeout_s: float | None = None) -> None:
        """Send a set command (e.g. ``"pos=3"``) and wait for its prompt.

        Args:
            command: the command without its ``\\r``.
            timeout_s: seconds to wait for the prompt (a wheel move needs far more than the default).

        Raises:
            DeviceTimeout, ProtocolError (a value line where none belongs), DeviceError, PortError.
        """
        lines = self._transact(command, timeout_s, expect_value=False)
        if lines:
            raise ProtocolError(
                self.port, command, f"unexpected value line {lines[0]!r} after a set command", self.last_reply
            )

    def _scan_reply(self, command: str, raw: bytes, expect_value: bool) -> Scan:
        """Hook: what the bytes read so far in answer to ``command`` amount to (`_scan`: echo,
        value lines, prompt). A device with another framing overrides it; ``expect_value`` says
        whether a value line belongs to the reply (a query) or not (a set command)."""
        return _scan(command, raw)

    def _transact(self, command: str, timeout_s: float | None, *, expect_value: bool) -> list[str]:
        """Write ``command\\r`` and read up to its prompt; return the value lines after the echo."""
        if not command or any(c in command for c in "\r\n"):
            raise ValueError(f"command must be one non-empty line, got {command!r}")
        data = (command + "\r").encode("ascii")  # UnicodeEncodeError (a ValueError) for non-ASCII
        timeout = self.timeout_s if timeout_s is None else float(timeout_s)
        with self._lock:
            ser = self._require_open(command)
            # Stale bytes (a late prompt, a trailing space) would otherwise precede the echo.
            self._flush_input(ser, command)
            self._port_call(command, ser.write, data)
            log.debug("%s <- %r", self.port, data)
            raw = bytearray()
            deadline = time.monotonic() + timeout
            scan = self._scan_reply(command, b"", expect_value)
            while True:
                interrupt.check()  # a safe point every poll: a move can take its whole timeout
                chunk = self._read_chunk(ser, command)
                if chunk:
                    raw += chunk
                    scan = self._scan_reply(command, bytes(raw), expect_value)
                    if scan.complete or (not scan.echo and scan.ends_in_prompt and scan.unechoed):
                        break
                if time.monotonic() >= deadline:
                    # No early give-up on a missing echo: a unit (or emulator) may hold back the whole
                    # reply to pos=n, echo included, until the move ends.
                    self.last_reply = bytes(raw)
                    log.debug("%s -> %r (deadline)", self.port, self.last_reply)
                    raise self._failure(command, scan, timeout)
            self.last_reply = bytes(raw)
            log.debug("%s -> %r", self.port, self.last_reply)
            if not scan.complete:
                raise self._failure(command, scan, timeout)
            for line in scan.values:
                if _is_error(line):
                    raise DeviceError(self.port, command, f"device error {line}", self.last_reply)
            if not all(_printable(line) for line in scan.values):
                raise ProtocolError(self.port, command, "non-protocol bytes in the reply", self.last_reply)
            return scan.values

    def _failure(self, command: str, scan: Scan, timeout: float) -> Exception:
        """The exception for a reply that ended (prompt or deadline) without echo + prompt."""
        raw = self.last_reply
        lines = scan.values if scan.echo else scan.unechoed
        for line in lines:
            if _is_error(line):
                # The device did answer; an echo lost to line noise does not make it less of a refusal.
                return DeviceError(self.port, command, f"device error {line}", raw)
        if scan.echo and not all(_printable(line) for line in lines):
            return ProtocolError(self.port, command, "non-protocol bytes after the echo, no prompt", raw)
        if scan.echo:
            return DeviceTimeout(self.port, command, f"echo but no prompt within {timeout:g} s", raw)
        if not lines:
            return DeviceTimeout(self.port, command, f"no answer within {timeout:g} s", raw or None)
        return ProtocolError(self.port, command, "reply without the echo of the command", raw)

    def _flush_input(self, ser, command: str | None) -> None:
        try:
            reset = ser.reset_input_buffer
        except AttributeError:  # a minimal URL handler: the reply parser skips stale lines anyway
            return
        try:
            self._port_call(command, reset)
        except NotImplementedError:
            pass

    def _read_chunk(self, ser, command: str | None) -> bytes:
        """Wait up to ``POLL_S`` for a byte, then take whatever else is already buffered."""
        chunk = self._port_call(command, ser.read, 1)
        if chunk:
            try:
                waiting = self._port_call(command, lambda: ser.in_waiting)
            except (AttributeError, NotImplementedError):  # a handler without in_waiting: byte by byte
                waiting = 0
            if waiting:
                chunk += self._port_call(command, ser.read, waiting)
        return chunk

    def _drain(self) -> None:
        """Send ``WAKE`` (a bare ``\\r``) and read until a prompt (any byte, for a device without
        one) followed by ``DRAIN_QUIET_S`` of silence.

        Never raises for silence or garbage: the identity query that follows judges the device.
        """
        ser = self._require_open(None)
        self._flush_input(ser, None)
        self._port_call(None, ser.write, self.WAKE)
        raw = bytearray()
        start = last = time.monotonic()
        while True:
            chunk = self._read_chunk(ser, None)
            now = time.monotonic()
            if chunk:
                raw += chunk
                last = now
            elif (_ends_in_prompt(_text(bytes(raw))) or not self.PROMPTED) and now - last >= DRAIN_QUIET_S:
                break
            if now - start >= self.timeout_s:
                break
        log.debug("%s: drained %r on connect", self.port, bytes(raw))

    def _require_open(self, command: str | None):
        if self._serial is None:
            raise PortError(self.port, command, "port is not open (connect first, or it vanished)")
        return self._serial

    def _port_call(self, command: str | None, fn, *args):
        """Call a pyserial method, turning port failures into PortError (and closing the port)."""
        try:
            return fn(*args)
        except serial.SerialTimeoutException as exc:
            # Writes only block when the other end stops reading (pty full, flow control): a dead device.
            raise DeviceTimeout(self.port, command, f"write timed out: {exc}") from exc
        except _PORT_FAILURES as exc:
            self._close_quietly()
            raise PortError(self.port, command, failure_problem(self.port, exc)) from exc
