"""`spherejax acquire`: the command this package adds to spherejax's command line.

pyproject.toml names `add_command` in the "spherejax.commands" entry points, which
`spherejax.cli` reads when it builds its parser; so spherejax_hw depends on spherejax and never
the other way. Only argparse is imported here: the devices load when the command runs.
"""

from __future__ import annotations

import sys

from spherejax import interrupt
from spherejax.cli import EXIT_BAD_INPUT


def add_command(commands) -> None:
    """Add `acquire` to the command line's subparsers (`commands`, an argparse subparsers action)."""
    acquire = commands.add_parser("acquire", help="drive the instrument through the acquisition protocol into a session")
    acquire.add_argument("--profile", required=True, metavar="FILE", help="instrument profile (TOML)")
    acquire.add_argument("-o", "--output", required=True, metavar="SESSION", help="session folder to write")
    acquire.add_argument("--yes", action="store_true", help="answer every operator prompt as done (scripts, tests)")
    acquire.add_argument("--emulate", action="store_true",
                         help="emulated wheels and shutter on pseudo-terminals and the simulated camera: no hardware")
    acquire.add_argument("--resume", action="store_true",
                         help="complete an interrupted acquisition without retaking what it captured")
    acquire.set_defaults(run=run_acquire)


def run_acquire(args) -> int:
    """`spherejax acquire`: the acquisition protocol with progress on stderr; the exit status."""
    # Imported when the command runs, so that the other commands never load serial drivers.
    from . import acquire

    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(unit="image", file=sys.stderr, dynamic_ncols=True, desc="band images")

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()
        elif not args.quiet and (done == total or done % 16 == 0):
            print(f"spherejax: {done}/{total} band images", file=sys.stderr, flush=True)

    def log(line: str) -> None:
        if args.quiet:
            return
        if bar is not None:
            bar.write(f"spherejax: {line}", file=sys.stderr)
        else:
            print(f"spherejax: {line}", file=sys.stderr, flush=True)

    settings = acquire.Settings(log=log, progress=progress)
    try:
        with interrupt.stop_requests():  # SIGINT / SIGTERM: stop between band images (`main` reports)
            session = acquire.acquire(
                args.profile, args.output, emulate=args.emulate, resume=args.resume,
                operator=acquire.Operator(yes=args.yes), settings=settings,
            )
    except acquire.AcquisitionStopped as error:
        print(f"spherejax: {error}", file=sys.stderr)
        return 1
    except acquire.AcquisitionError as error:
        print(f"spherejax: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if bar is not None:
            bar.close()
    print(f"session written to {session}")
    return 0
