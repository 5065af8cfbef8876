"""`spherejax acquire`: the command this package adds to spherejax's command line.

pyproject.toml names `add_command` in the "spherejax.commands" entry points, which
`spherejax.cli` reads when it builds its parser; so spherejax_hw depends on spherejax and never
the other way. Only argparse is imported here: the devices load when the command runs.
"""

from __future__ import annotations

import logging

from spherejax import console, interrupt
from spherejax.cli import EXIT_BAD_INPUT, add_output_option


def add_command(commands) -> None:
    """Add `acquire` to the command line's subparsers (`commands`, an argparse subparsers action)."""
    acquire = commands.add_parser(
        "acquire", help="drive the instrument through the acquisition protocol into a session",
        description=(
            "Drive the instrument described by an instrument profile (camera, filter wheels or a tunable\n"
            "filter, shutter, lamp) through the acquisition protocol: dark and white frames, the training,\n"
            "test and target captures and the registration target the profile lists ([[samples]]; role =\n"
            "\"registration\" marks the registration target, optional), each band at its exposure, into a\n"
            "session folder that calibrate, evaluate and correct read. Operator steps (place the white\n"
            "board, the next sample) are prompted; --yes answers them. Ctrl-C stops between band images and\n"
            "keeps what was captured; --resume completes the session without retaking it."
        ),
        epilog=(
            "examples:\n"
            "  spherejax acquire --profile lab.toml -o session-2026-11-26\n"
            "  spherejax acquire --profile lab.toml -o session-2026-11-26 --resume\n"
            "  spherejax acquire --profile lab.toml -o demo-session --emulate --yes   # no hardware"
        ),
    )
    acquire.add_argument("--profile", required=True, metavar="FILE", help="instrument profile (TOML)")
    add_output_option(acquire, dest="output", metavar="SESSION", required=True, old_spelling=True,
                      help="session folder to write (new, or an interrupted one with --resume)")
    acquire.add_argument("--yes", action="store_true", help="answer every operator prompt as done (scripts, tests)")
    acquire.add_argument("--emulate", action="store_true",
                         help="emulated wheels or tunable filter and shutter on pseudo-terminals and the simulated "
                              "camera: no hardware")
    acquire.add_argument("--real-camera", action="store_true",
                         help="with --emulate: the profile's [camera] instead of the simulated one (emulated wheels and shutter)")
    acquire.add_argument("--through-gige", action="store_true",
                         help="with --emulate: the simulated camera's frames served through Aravis's fake GigE Vision "
                              "camera on 127.0.0.1 and read by the GenICam backend (needs Aravis and PyGObject)")
    acquire.add_argument("--resume", action="store_true",
                         help="complete an interrupted acquisition without retaking what it captured")
    acquire.set_defaults(run=run_acquire, written_paths=written_paths)


def written_paths(args):
    """What `acquire` reads and writes, for the check of --log-file FILE before it is opened
    (`spherejax.cli.written_paths`): the profile; SESSION and SESSION.partial, folders it writes
    whole; SESSION.lock."""
    import pathlib

    from spherejax.cli.written_paths import CommandPaths

    out = pathlib.Path(args.output)
    return CommandPaths(
        inputs={"--profile FILE": pathlib.Path(args.profile)},
        outputs={"SESSION.lock": out.with_name(out.name + ".lock")},
        folders={"-o SESSION": out, "SESSION.partial": out.with_name(out.name + ".partial")},
    )


def run_acquire(args) -> int:
    """`spherejax acquire`: the acquisition protocol with progress on stderr; the exit status."""
    # Imported when the command runs, so that the other commands never load serial drivers.
    from . import acquire

    if args.through_gige and (not args.emulate or args.real_camera):
        console.say("spherejax: error: --through-gige: expected it with --emulate and without --real-camera "
                    "(it routes the simulated camera's frames)", logging.ERROR)
        return EXIT_BAD_INPUT
    bar = None
    if not args.quiet and console.on_terminal():
        bar = console.bar(unit="image", desc="band images")

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()
        elif done == total or done % 16 == 0:
            console.say(f"spherejax: {done}/{total} band images")

    def log(line: str) -> None:
        console.say(f"spherejax: {line}")  # through tqdm.write while the bar is drawn (spherejax.console)

    settings = acquire.Settings(log=log, progress=progress)
    try:
        with interrupt.stop_requests():  # SIGINT / SIGTERM / SIGHUP: stop between band images (`main` reports)
            session = acquire.acquire(
                args.profile, args.output, emulate=args.emulate, real_camera=args.real_camera,
                through_gige=args.through_gige, resume=args.resume,
                operator=acquire.Operator(yes=args.yes), settings=settings,
            )
    except acquire.AcquisitionStopped as error:
        console.say(f"spherejax: {error}", logging.ERROR)
        return 1
    except acquire.AcquisitionError as error:
        console.say(f"spherejax: error: {error}", logging.ERROR)
        return EXIT_BAD_INPUT
    finally:
        if bar is not None:
            bar.close()
    print(f"session written to {session}")
    return 0
