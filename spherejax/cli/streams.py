"""The command line's standard streams: what a command does when one is closed, full or gone.

A command's results go to stdout and its messages to stderr (spherejax.console); either may be
a pipe whose reader has gone (`spherejax correct ... | head -1`), a full device (`> /dev/full`),
or closed by the shell (`>&-`), and stdin may be closed (`<&-`) or not a terminal. `guarded`
gives every command the same behaviour for all of these:

- Closed descriptors 0, 1 and 2 are opened on /dev/null before anything else, so no file the
  command opens takes their number (a print, or a worker process writing to its inherited
  stdout, would write into that file), and `sys.stdin`, `sys.stdout` and `sys.stderr` are never
  None (`input()` and `isatty()` on a None stdin raised AttributeError). A closed stdin then reads
  as an empty file that is not a terminal, so a prompt says it needs a terminal or --yes.
- stdout and stderr are wrapped in `_GuardedStream`, which never raises: the first failed write
  (EPIPE, ENOSPC, EIO, EBADF) is kept and every later write to that stream dropped. The command
  goes on and finishes what it was doing, so a batch's outputs and manifest are written and true
  when the exit status is decided; nothing half-done is left because a report could not be shown.
- At the end (`Guard.exit_status`), stdout is flushed, and a failure decides the exit status:
  a reader that went away (EPIPE, on stdout or stderr) gives 141, 128 + SIGPIPE, what a shell
  reports for a Unix tool killed by that signal, with no message (the reader chose to stop
  reading); any other failure to write the results gives one line on stderr naming standard
  output and the error, and exit status 2 (the results, part of what was asked for, are lost).
  A command that already failed keeps its own status, the more telling one. For a closed stdout
  that is also the rule: nothing could be written, which is said once the command ends.
- Characters stdout's or stderr's encoding cannot hold (a non-UTF-8 locale, LC_ALL=C) never
  raise: a name read from disk (lone surrogates, os.fsdecode's escapes) is written as its own
  bytes, as `ls` writes it; any other character as a backslash escape ("±" as "\\xb1").
"""

from __future__ import annotations

import codecs
import contextlib
import errno
import io
import os
import sys
from collections.abc import Iterator

#: The exit status after a reader of stdout or stderr went away: 128 + SIGPIPE (13), what a shell
#: reports for a process killed by SIGPIPE, the signal Unix tools die of in that case.
EXIT_BROKEN_PIPE = 128 + 13

#: The codec error handler of the guarded streams (module docstring).
ERROR_HANDLER = "spherejax-names"


def _names_as_bytes(error: UnicodeError):
    """Encode errors: lone surrogates U+DC80..U+DCFF (bytes os.fsdecode could not decode) as those
    bytes, anything else as a backslash escape."""
    if not isinstance(error, UnicodeEncodeError):
        raise error
    text = error.object[error.start:error.end]
    if all("\udc80" <= c <= "\udcff" for c in text):
        return bytes(ord(c) - 0xDC00 for c in text), error.end
    return codecs.backslashreplace_errors(error)


codecs.register_error(ERROR_HANDLER, _names_as_bytes)


class _GuardedStream(io.TextIOBase):
    """A text stream that never raises on write or flush: the first OSError is kept (`failure`)
    and later writes are dropped (module docstring). Everything else is the wrapped stream's."""

    def __init__(self, stream, name: str):
        self._stream, self.name, self.failure = stream, name, None

    def write(self, text: str) -> int:
        if self.failure is None:
            try:
                self._stream.write(text)
            except OSError as error:
                self.failure = error
            except ValueError:  # the wrapped stream was closed under us (an embedding program)
                self.failure = OSError(errno.EBADF, os.strerror(errno.EBADF))
        return len(text)

    def flush(self) -> None:
        if self.failure is None:
            try:
                self._stream.flush()
            except OSError as error:
                self.failure = error
            except ValueError:
                self.failure = OSError(errno.EBADF, os.strerror(errno.EBADF))

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        try:
            return self.failure is None and self._stream.isatty()
        except (AttributeError, ValueError, OSError):
            return False

    def fileno(self) -> int:
        return self._stream.fileno()

    @property
    def encoding(self):
        return getattr(self._stream, "encoding", "utf-8")

    @property
    def errors(self):
        return getattr(self._stream, "errors", "strict")

    def __getattr__(self, name):  # buffer, reconfigure, line_buffering: the wrapped stream's
        return getattr(self._stream, name)


def _descriptor_open(fd: int) -> bool:
    try:
        os.fstat(fd)
    except OSError:
        return False
    return True


def _reopen_closed_descriptors() -> set[int]:
    """Open /dev/null on each of 0, 1, 2 that is closed; the ones that were."""
    closed = {fd for fd in (0, 1, 2) if not _descriptor_open(fd)}
    for fd in sorted(closed):
        opened = os.open(os.devnull, os.O_RDWR)
        if opened != fd:  # the lowest free number is taken: fd, unless a lower one was closed too
            os.dup2(opened, fd)
            os.close(opened)
    return closed


def _use_errors_handler(stream, errors: str | None) -> str | None:
    """Encoding errors of `stream` handled by `errors` (ERROR_HANDLER, or the one it had, put back
    when the command ends); the handler it had. A stream that cannot be reconfigured is left as it is."""
    before = getattr(stream, "errors", None)
    if errors is not None:
        with contextlib.suppress(AttributeError, ValueError, OSError, io.UnsupportedOperation):
            stream.reconfigure(errors=errors)
    return before


class Guard:
    """The guarded stdout and stderr of one command (`guarded`)."""

    def __init__(self, stdout: _GuardedStream, stderr: _GuardedStream):
        self.stdout, self.stderr = stdout, stderr

    def exit_status(self, status: int) -> int:
        """The command's exit status once stdout is flushed: `status` unless it is 0 and a stream
        failed (module docstring); says the failure on stderr where there is a line to say.
        Only stdout's failures count, and stderr's EPIPE: a full or closed stderr has nowhere to
        be reported and loses only messages the exit status already sums up."""
        self.stdout.flush()
        self.stderr.flush()
        if status != 0:
            return status
        if any(isinstance(s.failure, BrokenPipeError) for s in (self.stdout, self.stderr)):
            return EXIT_BROKEN_PIPE
        failure = self.stdout.failure
        if failure is None:
            return status
        reason = "it is closed" if failure.errno == errno.EBADF else failure.strerror or str(failure)
        self.stderr.write(f"spherejax: error: standard output: the results cannot be written: {reason} "
                          "(expected a standard output that can be written: a terminal, a file or a pipe)\n")
        self.stderr.flush()
        return 2


def _detach_broken(stream: _GuardedStream, real, fd: int) -> None:
    """After a failed write, point descriptor `fd` at /dev/null so that the interpreter's own
    flush of what `real` still buffers, at exit, succeeds instead of printing "Exception ignored"."""
    if stream.failure is None or real is None:
        return
    with contextlib.suppress(OSError, ValueError, io.UnsupportedOperation):
        if real.fileno() != fd:
            return
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)


@contextlib.contextmanager
def guarded() -> Iterator[Guard]:
    """stdin, stdout and stderr made safe for one command (module docstring); restored on exit.
    Yields the `Guard` whose `exit_status` the command's status goes through."""
    closed = _reopen_closed_descriptors()
    saved = sys.stdin, sys.stdout, sys.stderr
    if sys.stdin is None or 0 in closed:
        sys.stdin = open(0, encoding=sys.getfilesystemencoding(), errors="surrogateescape", closefd=False)
    real_out = sys.stdout if sys.stdout is not None and 1 not in closed else None
    real_err = sys.stderr if sys.stderr is not None and 2 not in closed else None
    # A closed stream fails its first write (EBADF), so that a command with nothing to write there
    # (-q) is not refused for it.
    stdout = _GuardedStream(real_out if real_out is not None else _Closed(), "<stdout>")
    stderr = _GuardedStream(real_err if real_err is not None else _Closed(), "<stderr>")
    handlers = [(real, _use_errors_handler(real, ERROR_HANDLER)) for real in (real_out, real_err) if real is not None]
    sys.stdout, sys.stderr = stdout, stderr
    try:
        yield Guard(stdout, stderr)
    finally:
        sys.stdin, sys.stdout, sys.stderr = saved
        _detach_broken(stdout, real_out, 1)
        _detach_broken(stderr, real_err, 2)
        for real, errors in handlers:  # an embedding program's streams as they were
            _use_errors_handler(real, errors)


class _Closed:
    """A stream the shell closed (`>&-`): every write fails as a write to a closed descriptor does."""

    def write(self, text: str) -> None:
        raise OSError(errno.EBADF, os.strerror(errno.EBADF))

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


__all__ = ["EXIT_BROKEN_PIPE", "Guard", "guarded"]
