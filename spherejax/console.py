"""What the command line tells a person, and where: messages through `logging`, progress as tqdm
bars on a terminal and as plain lines everywhere else.

Every message of a command goes through the "spherejax" logger (and the instrument package's,
"spherejax_hw"): the progress lines ("[2/3] calibrating ...", "      done in 3.1 s"), warnings,
notes and the one error line. `configured()` gives them two destinations:

- the terminal (stderr), one handler, at INFO by default, WARNING with -q/--quiet, DEBUG with
  -v/--verbose. The command line's own lines (logger "spherejax.cli" and its children, and every
  line logged through `say`) are written as they are, so that the one-line error contract
  ("spherejax: error: PATH: problem (expected ...)") reads exactly as the contract says; a record of any
  other module gets "spherejax: warning: " (or "error", "debug: NAME") in front, so a line never
  appears without saying whose it is. While a tqdm bar is drawn, lines go through `tqdm.write` and
  never break it.
- --log-file FILE, at DEBUG, each line with its UTC time, level and logger. The file is appended to
  when it is a log spherejax wrote (its first line is one of spherejax's log lines: the signature
  on the file itself), created with that first line in it when nothing is there (so a log of
  spherejax's is never empty, and an empty file is nobody's proof), and refused in one line
  otherwise (a file of the user's, an empty file, a folder, a link, a FIFO): spherejax writes only
  files it owns. Like any output it is checked first against the command's own files
  (`configured`'s `apart_from`, `spherejax.cli.written_paths`): never an input or an output of
  the command (OUT's lock or manifest, measure's CSV), nor inside a folder the command writes
  whole.

Results (tables, "written: ...", the batch summary) are not messages: they go to stdout with
`print`, and -q leaves them out.

Progress (`Steps`, the numbered steps of calibrate, evaluate, study, simulate and demo): on a
terminal each step is a tqdm bar that shows its elapsed time while it runs, ticked twice a second
from a thread (the steps are single long library calls with no loop to hook into), and counts
where the step reports them (`Steps.count`); elsewhere, or with -q, one line when a step starts and
one when it ends.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import re
import sys
import threading
import time
from collections.abc import Iterator

#: The loggers the command line shows: spherejax's and the instrument package's.
LOGGER_NAMES = ("spherejax", "spherejax_hw")

#: The logger of the command line's own lines, written to the terminal as they are.
log = logging.getLogger("spherejax.cli")

#: One line of a spherejax log file: "2026-11-26T13:40:02.123Z INFO spherejax.cli: ...".
LOG_FILE_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_LOG_FILE_LINE = re.compile(rb"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z (DEBUG|INFO|WARNING|ERROR|CRITICAL) spherejax")


def say(line: str, level: int = logging.INFO) -> None:
    """Log one of the command line's own lines (written to the terminal as it is)."""
    log.log(level, line)


def warn(text: str) -> None:
    """ "spherejax: warning: TEXT" on the terminal and in the log file."""
    log.warning(f"spherejax: warning: {text}")


def on_terminal() -> bool:
    """Whether stderr is a terminal (progress bars) rather than a pipe or file (plain lines)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced by an object without it, or closed
        return False


class _TerminalHandler(logging.Handler):
    """Writes to whatever `sys.stderr` is when a record arrives (a test's capture replaces it), one
    line per record, through `tqdm.write` on a terminal so that a bar being drawn is kept whole."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = self.format(record)
            if on_terminal():
                from tqdm import tqdm

                tqdm.write(line, file=sys.stderr)
            else:
                sys.stderr.write(line + "\n")
            sys.stderr.flush()
        except Exception:  # noqa: BLE001  logging's own contract: a handler never raises
            self.handleError(record)


class _TerminalFormatter(logging.Formatter):
    """The command line's own lines as they are; another module's with whose and what in front."""

    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage()
        if record.name == log.name or record.name.startswith(log.name + "."):
            return message
        if record.levelno >= logging.ERROR:
            return f"spherejax: error: {message}"
        if record.levelno >= logging.WARNING:
            return f"spherejax: warning: {message}"
        if record.levelno >= logging.INFO:
            return f"spherejax: {message}"
        return f"spherejax: debug: {record.name}: {message}"


class _UTCFormatter(logging.Formatter):
    converter = time.gmtime

    def formatTime(self, record, datefmt=None):  # noqa: N802  (logging's name)
        return time.strftime("%Y-%m-%dT%H:%M:%S", self.converter(record.created)) + f".{int(record.msecs):03d}Z"


def not_a_log(path: pathlib.Path) -> str | None:
    """None if `path` is a log file spherejax wrote (its first line is one of its log lines), else
    why it may not be appended to: the `replaceable` test of `io.ownership.refuse_in_the_way`.
    An empty file is not one: spherejax creates a log with its first line in it (`_create_log`)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except OSError as error:
        return f"a file that cannot be read ({error.strerror})"
    try:
        first = os.read(fd, 256)
    finally:
        os.close(fd)
    if not first:
        return "an empty file, not a spherejax log (a spherejax log begins with one of its log lines)"
    if _LOG_FILE_LINE.match(first):
        return None
    return "a file that is not a spherejax log (its first line is not one of spherejax's log lines)"


def _create_log(target: pathlib.Path, formatter: logging.Formatter) -> None:
    """Create the log file `target` holding its first line, whole, or leave what another process
    put there since it was looked at (the check that follows judges it).

    The line is written to a temporary sibling first and linked into place (link(2) never
    replaces a file), so no log of spherejax's is ever seen empty or torn: its first line is
    its signature (`not_a_log`)."""
    from . import __version__, atomic_files

    record = logging.makeLogRecord({"name": log.name, "levelno": logging.DEBUG, "levelname": "DEBUG",
                                    "msg": f"log file created by spherejax {__version__}"})
    line = (formatter.format(record) + "\n").encode("utf-8")
    # Someone else's file at the name since the look: refused or appended to by the check after.
    atomic_files.create_whole(target, line, direct_without_links=True)


def _refuse_command_paths(target: pathlib.Path, paths) -> None:
    """Raise unless the log file `target` is apart from the command's own files (`paths`, a
    `spherejax.cli.written_paths.CommandPaths`): not one of its inputs or outputs (resolved path,
    or (st_dev, st_ino)), not in a folder it writes whole, not at a name it gives its outputs.

    Raises:
      SpherejaxFileError: one line naming the log file and the command's file it would be.
    """
    from .io import ownership
    from .io.errors import SpherejaxFileError

    label = "--log-file FILE"
    ownership.refuse_overlaps({label: target}, {**paths.inputs, **paths.outputs})

    identity = ownership.path_identity

    resolved = os.path.realpath(target)
    holders, folder = [], os.path.dirname(resolved)
    while True:
        holders.append(identity(folder))
        if os.path.dirname(folder) == folder:
            break
        folder = os.path.dirname(folder)

    def same(one, other) -> bool:
        return one[0] == other[0] or (one[1] is not None and one[1] == other[1])

    expected = f"{label} a file apart from the command's inputs, outputs and the folders it writes"
    for what, folder in paths.folders.items():
        if any(same(identity(folder), holder) for holder in holders):
            raise SpherejaxFileError(target, f"{label} lies in {what} ({folder}), a folder the command writes whole", expected)
    name = os.path.basename(resolved)
    for what, folder, suffixes in paths.named:
        suffix = next((suffix for suffix in suffixes if name.endswith(suffix)), None)
        if suffix is not None and same(identity(folder), holders[0]):
            raise SpherejaxFileError(target, f"{label} has the name of {what} ({folder}/*{suffix})", expected)


class _LogFileHandler(logging.StreamHandler):
    """A StreamHandler that owns its stream: closed with the handler (logging.FileHandler opens
    by name, which would follow a link put there after the check)."""

    def close(self) -> None:
        try:
            self.flush()
            self.stream.close()
        finally:
            super().close()


def _open_log_file(path: str, apart_from=None) -> logging.Handler:
    """A handler appending to the log file at `path`, checked first (module docstring) and, with
    `apart_from`, against the command's own files (`_refuse_command_paths`)."""
    from .io import ownership
    from .io.errors import SpherejaxFileError

    target = pathlib.Path(path)
    if not target.parent.is_dir():
        raise SpherejaxFileError(target, "cannot be created: its folder does not exist",
                                 "--log-file FILE in an existing folder")
    if apart_from is not None:
        _refuse_command_paths(target, apart_from)
    formatter = _UTCFormatter(LOG_FILE_FORMAT)
    if not os.path.lexists(target):
        try:
            _create_log(target, formatter)
        except OSError as error:  # a read-only folder, a full disk: said of the log, not its temporary
            raise SpherejaxFileError(target, f"cannot be created ({error.strerror or error})",
                                     "--log-file FILE in a folder spherejax may write") from None
    ownership.refuse_in_the_way({"--log-file FILE": target}, replaceable=not_a_log,
                                expected="--log-file FILE a new file, or a spherejax log to append to")
    try:
        # O_NOFOLLOW and O_NONBLOCK: a link or FIFO put there since the check is refused, never
        # followed or waited on.
        fd = os.open(target, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
    except OSError as error:
        raise SpherejaxFileError(target, f"cannot be opened for writing ({error.strerror})",
                                 "--log-file FILE a new file, or a spherejax log to append to") from None
    handler = _LogFileHandler(open(fd, "a", encoding="utf-8", errors="backslashreplace"))
    handler.setFormatter(formatter)
    handler.setLevel(logging.DEBUG)
    return handler


@contextlib.contextmanager
def configured(*, quiet: bool = False, verbose: int = 0, log_file: str | None = None,
               apart_from=None) -> Iterator[None]:
    """Route the loggers of `LOGGER_NAMES` to the terminal (and `log_file`) for one command.

    Args:
      quiet: only warnings and errors on the terminal.
      verbose: 1 or more: debug records too (each device command of hw/, for instance).
      log_file: a path to append every record to, at DEBUG, with times; None for none.
      apart_from: the command's own files (`spherejax.cli.written_paths.CommandPaths`), which
        `log_file` may not be nor lie among; None: not checked.

    Raises:
      SpherejaxFileError: `log_file` is something spherejax may not write (module docstring).
    """
    terminal = _TerminalHandler()
    terminal.setFormatter(_TerminalFormatter())
    terminal.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    handlers = [terminal]
    if log_file is not None:
        handlers.append(_open_log_file(log_file, apart_from))
    saved = []
    for name in LOGGER_NAMES:
        logger = logging.getLogger(name)
        saved.append((logger, logger.level, logger.propagate))
        logger.setLevel(logging.DEBUG)
        logger.propagate = False  # shown once, here, not again by a root handler an embedding program set
        for handler in handlers:
            logger.addHandler(handler)
    try:
        yield
    finally:
        for logger, level, propagate in saved:
            for handler in handlers:
                logger.removeHandler(handler)
            logger.setLevel(level)
            logger.propagate = propagate
        for handler in handlers[1:]:
            handler.close()


def _has_size(stream) -> bool:
    """Whether `stream` is a terminal that reports its columns and rows (a pty some tools open
    without setting a size reports 0 x 0: tqdm would draw a bar of no columns on no rows, that is
    nothing)."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, ValueError, OSError):  # a test's StringIO, a closed stream
        return False
    return size.columns > 0 and size.lines > 0


def bar(**options):
    """A tqdm bar on stderr for a terminal (`on_terminal`), sized to it, or drawn as on 80 x 24
    where the terminal reports no size. `options` as tqdm's (total, unit, desc, ...)."""
    from tqdm import tqdm

    sized = _has_size(sys.stderr)
    options.setdefault("dynamic_ncols", sized)
    if not sized:
        options.setdefault("ncols", 80)
        options.setdefault("nrows", 24)
    return tqdm(file=sys.stderr, **options)


class _Ticker:
    """A tqdm bar for one step, redrawn twice a second from a thread so its elapsed time moves
    while the step's one long call runs."""

    def __init__(self, description: str):
        self.bar = bar(total=None, desc=description, leave=False, bar_format="{desc} {elapsed}", mininterval=0.5)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._tick, name="spherejax-progress", daemon=True)
        self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(0.5):
            self.bar.refresh()

    def count(self, done: int, total: int | None) -> None:
        self.bar.total = total
        self.bar.bar_format = "{desc} {n_fmt}/{total_fmt} {elapsed}" if total else "{desc} {n_fmt} {elapsed}"
        self.bar.n = done
        self.bar.refresh()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.bar.close()


class Steps:
    """A command's numbered steps: "[2/4] calibrating from S ..." when one starts and
    "      done in 3.1 s (detail)" when it ends, through the log; on a terminal, a bar with the
    step's elapsed time (and counts, `count`) in between.

    `total` is the number of steps the command will announce; `finish` checks that it did. With
    `lines` False the start and end lines are debug lines (the log file, -v): a command whose
    default stderr is empty (`measure`) shows only the bar, and only on a terminal.
    """

    def __init__(self, total: int, quiet: bool = False, lines: bool = True):
        self.total, self.step, self.quiet = total, 0, quiet
        self.level = logging.INFO if lines else logging.DEBUG
        self._ticker: _Ticker | None = None
        self.t0 = time.perf_counter()

    def start(self, what: str) -> None:
        self._close_bar()
        self.step += 1
        self.t0 = time.perf_counter()
        say(f"[{self.step}/{self.total}] {what} ...", self.level)
        if not self.quiet and on_terminal():
            self._ticker = _Ticker(f"[{self.step}/{self.total}]")

    def count(self, done: int, total: int | None = None) -> None:
        """The running step has done `done` of `total` items (captures, folds)."""
        if self._ticker is not None:
            self._ticker.count(done, total)

    def done(self, detail: str = "") -> None:
        self._close_bar()
        extra = f" ({detail})" if detail else ""
        say(f"      done in {time.perf_counter() - self.t0:.1f} s{extra}", self.level)

    def finish(self) -> None:
        """Raise if the command announced a number of steps it did not run (a programming error)."""
        self._close_bar()
        if self.step != self.total:
            raise RuntimeError(f"announced {self.total} steps, ran {self.step}")

    def _close_bar(self) -> None:
        if self._ticker is not None:
            self._ticker.close()
            self._ticker = None

    def __enter__(self) -> Steps:
        return self

    def __exit__(self, *exc) -> None:
        self._close_bar()
        if exc[0] is None:
            self.finish()


__all__ = ["LOGGER_NAMES", "Steps", "bar", "configured", "log", "not_a_log", "on_terminal", "say", "warn"]
