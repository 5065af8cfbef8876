"""`main`: parse, set up the messages, run the command, turn what stops it into one line and an
exit status."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import warnings

from .. import console, interrupt
from .._engine.allocator import keep_freed_memory
from . import streams
from .number_types import BadNumber
from .parser import DEPRECATED_SPELLINGS, _version_line, build_parser
from .shared import EXIT_BAD_INPUT, _one_line
from . import written_paths


#: The start of JAX's warning about a torn persistent compilation cache entry (`_run`).
TORN_CACHE_ENTRY_WARNING = "Error reading persistent compilation cache entry"


def _error_line(error: BaseException) -> str:
    return "spherejax: error: " + _one_line(" ".join(str(error).split()))


def main(argv=None) -> int:
    """Run the command line on `argv` (default sys.argv[1:]); the exit status.

    stdin, stdout and stderr are guarded for the whole run (`streams`): a closed one is opened on
    /dev/null, a failed write never stops the work, and the exit status says, once the work is
    done and recorded, that the results could not be written (141 for a reader that went away,
    as Unix tools exit; 2 with one line for a full or closed stdout). argparse's own exits
    (--help, --version) go through the same check: `--version > /dev/full` is not a success.
    """
    with streams.guarded() as guard:
        try:
            status = _main(argv)
        except SystemExit as exiting:
            if exiting.code not in (None, 0):
                raise
            status = guard.exit_status(0)
            if status == 0:
                raise
            raise SystemExit(status) from None
        return guard.exit_status(status)


def _main(argv) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except BadNumber as refused:  # said on stderr in one line by the parser (`number_types`)
        return refused.code
    if args.command is None:
        parser.print_help()  # a bare `spherejax`: what it can do, not an error
        return 0
    with contextlib.ExitStack() as messages:
        try:
            # The log is checked against the command's own files like any output (`written_paths`).
            messages.enter_context(console.configured(quiet=args.quiet, verbose=args.verbose, log_file=args.log_file,
                                                      apart_from=written_paths.of(args) if args.log_file else None))
        except (ValueError, OSError) as error:  # --log-file refused: there is no log to say it through
            print(_error_line(error), file=sys.stderr)
            return EXIT_BAD_INPUT
        given = sys.argv[1:] if argv is None else list(argv)
        console.log.debug("%s; command line: spherejax %s", _version_line(), " ".join(given))
        # At debug level only (-v, the log file): the default output, the one-line error contract
        # above all, reads the same whichever spelling a lab's scripts use; --help says it.
        for spelling in dict.fromkeys(args.deprecated_spellings):
            console.log.debug("%s is the old spelling of %s; it still works, and may go in a later release",
                              spelling, DEPRECATED_SPELLINGS[spelling])
        return _run(args)


def _missing_working_folder() -> str | None:
    """None if the working folder exists; else the one-line refusal naming it. A folder deleted
    while a shell stood in it makes os.getcwd() fail, and every relative path with it, as
    "[Errno 2] No such file or directory" naming no file."""
    try:
        os.getcwd()
    except FileNotFoundError:
        where = os.environ.get("PWD")  # the shell's record of it: the folder itself is gone
        named = f" {_one_line(where)}" if where and not os.path.isdir(where) else ""
        return (f"spherejax: error: the working folder{named} no longer exists (deleted since the shell "
                "entered it) (expected a working folder that exists: cd to one)")
    return None


def _run(args) -> int:
    missing = _missing_working_folder()
    if missing is not None:
        console.say(missing, logging.ERROR)
        return EXIT_BAD_INPUT
    # Before any JAX work: reuse freed blocks instead of page-faulting fresh ones on every image
    # (spherejax._engine.allocator says why; about 2x on a 1-megapixel correction).
    keep_freed_memory()
    try:
        # A mistyped switch (SPHEREJAX_FUSED=off) is refused up front, not per input of a batch.
        from .._engine import fused

        fused.switch()
        # SIGTERM, like SIGINT, unwinds through the clean-up wherever a command is (`correct` and
        # `acquire` turn both into stop requests at their safe points instead).
        with interrupt.at_once(), warnings.catch_warnings():
            # JAX warns on stderr when an entry of its persistent compilation cache is torn (a
            # process killed while writing it, on JAX releases that do not write entries
            # atomically: seen with jax 0.10.2 in a clean-clone CI run), then recompiles, which
            # is all there is to do; the warning would break the one-line messages of every run.
            warnings.filterwarnings("ignore", message=TORN_CACHE_ENTRY_WARNING, category=UserWarning)
            return args.run(args)
    except interrupt.Interrupted as stopped:
        # A stop request honoured at a safe point (`correct`, `acquire`): what was finished is
        # kept and recorded, what was under way removed; the exit status a shell gives a process
        # killed by that signal, 130 for SIGINT, 143 for SIGTERM.
        console.say(stopped.message(), logging.ERROR)
        return stopped.exit_status
    except KeyboardInterrupt:
        console.say("spherejax: interrupted", logging.ERROR)
        return 130
    except (ValueError, OSError) as error:
        console.say(_error_line(error), logging.ERROR)
        return EXIT_BAD_INPUT
