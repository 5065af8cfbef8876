"""The `spherejax` command line (docs/design.md, "The command line").

Modules: parser (conventions, every command's options and help), number_types (one argparse
type per kind of number an option takes), run (`main`), streams (stdin, stdout and stderr closed,
full or abandoned), shared (what several commands share), session_commands (simulate, calibrate,
evaluate, study, demo), correct_command, measure_command, written_paths (what each command reads
and writes, from its arguments: what --log-file may not be).

    spherejax demo [-o DIR] [--seed N]         simulate, calibrate, correct, evaluate
    spherejax simulate -o DIR [--seed N]       a synthetic session like the paper's experiment
    spherejax calibrate SESSION -o CAL [--force] [--gain E_PER_COUNT --read-noise COUNTS]
                                               Stage II and Wiener from the training captures,
                                               and the noise model (spherejax.uncertainty)
    spherejax evaluate SESSION [-c CAL] [-o DIR]
                                               the paper's tables (text, CSV, JSON) and figures
    spherejax study SESSION [-c CAL] [--wiener] [-o DIR]
                                               Stage II fitted for ΔE00 consistency, compared with
                                               the closed form on the held-out test captures
    spherejax correct -c CAL INPUT... -o OUT [--resume] [--illuminant NAME] [--format exr|envi]
                                               batch-correct cubes, sessions and folders into OUT
                                               (spherejax.archive): spectral OpenEXR or ENVI
    spherejax acquire --profile FILE -o SESSION [--yes] [--emulate] [--resume]
                                               drive the instrument into a session; added by the
                                               instrument package, spherejax_hw (hw/command.py),
                                               through the "spherejax.commands" entry points
    spherejax measure -c CAL INPUT --region NAME=r0,r1,c0,c1 ... [--reference NAME|L,a,b]
              [-o OUT] [--cgats FILE] [--gain E --read-noise COUNTS --frames N]
                                               regions of one cube as a spectrophotometer measures
                                               them: Lab, reflectance, ± U (k = 2), ΔE00; a table,
                                               OUT.csv and OUT.json, and CGATS.17 text with --cgats
                                               (spherejax.measurement_files)
    spherejax --version                        the version line; a bare `spherejax` prints help

Conventions (`build_parser` says why argparse): -o/--out names every output path (`--output` and
`simulate OUT`, the older spellings, still work and are marked deprecated in --help); the global
options -q, -v and --log-file go before or after the command (`_global_options`); messages go
through `logging` and progress through tqdm on a terminal (spherejax.console), results to stdout.

Exit status 0 on success; on bad input a one-line message on stderr (no traceback), exit
status 2, and nothing written. Numbers are bounded at both ends by what they can mean
(`number_types`); JSON is read strictly (`spherejax.jsontext`: a key given twice is refused);
output folders are tried before any work (`shared.check_writable`); a working folder deleted
under the shell is named in one line. The standard streams are guarded (`streams`): a closed one
is opened on /dev/null; results that cannot be written (a full or closed stdout) give one line
and exit status 2 once the work is done and kept; a reader of stdout that went away (`| head`)
gives 141, as a Unix tool killed by SIGPIPE, with the work done and recorded; under a locale that
is not UTF-8, names and arguments are taken by their bytes as UTF-8 (`io.library_path`,
`shared.argument_text`) or refused in one line. `correct` goes on past bad inputs: each is logged with its
reason, and the run ends with a summary and exit status 1 if any failed. Everything is computed before the first byte is written, and
every file is written to a temporary name and renamed into place.

Each command writes and deletes only what it created (`spherejax.io.ownership`): before any work
every output is checked against every input, the calibration and the other outputs, by resolved
path and (st_dev, st_ino), so links and `..` cannot hide an overlap. `calibrate -o CAL` may put
CAL beside the session's files, never over one, and replaces only a spherejax calibration, and
that only with --force;
`evaluate` and `study` refuse an --out DIR that is the session's folder or its frames folder, and
replace only the files of an earlier run there, whose very bytes its metrics.json or study.json
records (`run_records`);
`simulate` and `demo` refuse a session folder that is a link or ends in ".."; `demo` reuses a
session only when it is the one asked for (`demo_session_differs`) and replaces only what an
earlier demo wrote (its mark in the calibration's signed header; `demo --force` for another
spherejax calibration); `measure` replaces only files that begin with its own outputs' signatures;
--log-file appends only to a log spherejax wrote (spherejax.console) and is none of the command's
own files (`written_paths`). Anything else in the way is refused in one line naming it.

`correct` and `acquire` stop cleanly on SIGINT (Ctrl-C), SIGTERM or SIGHUP (spherejax.interrupt):
at the next safe point, with what was finished kept and recorded, nothing half-written left and
OUT's lock released, one line ("spherejax: interrupted after N of M inputs; run again with
--resume") and exit status 130 (SIGINT), 143 (SIGTERM) or 129 (SIGHUP); the other commands stop
at the next call of spherejax's own code where raising is safe, with the same statuses.
"""

from __future__ import annotations

from .parser import COMMAND_ENTRY_POINTS, DEPRECATED_SPELLINGS, add_output_option, add_plugin_commands, build_parser
from .run import main
from .session_commands import demo_session_differs
from .shared import EXIT_BAD_INPUT, LOSSES, WIENER_METHODS, wiener_report_table
# Private helpers that callers reach as cli.X (tests; the study's and demo's saving).
from .shared import _save_calibration, _write_files  # noqa: F401

__all__ = [
    "COMMAND_ENTRY_POINTS", "DEPRECATED_SPELLINGS", "EXIT_BAD_INPUT", "LOSSES", "WIENER_METHODS",
    "add_output_option",
    "add_plugin_commands", "build_parser", "demo_session_differs", "main", "wiener_report_table",
]
