"""The command line's parser: its conventions (global options either side of the command, -o/--out
for every output path, one-line usage errors) and every command's options, description and examples."""

from __future__ import annotations

import argparse
import sys

from . import number_types as numbers
from .correct_command import cmd_correct
from .measure_command import cmd_measure
from .view_command import cmd_view
from .session_commands import cmd_calibrate, cmd_demo, cmd_evaluate, cmd_simulate, cmd_study, cmd_twin
from .shared import EXIT_BAD_INPUT, LOSSES, WIENER_METHODS, _one_line

#: Entry-point group through which installed packages add commands, each entry point a function
#: `add_command(commands)` given the subparsers action (spherejax_hw adds `acquire` this way: the
#: instrument package depends on spherejax, never spherejax on it).
COMMAND_ENTRY_POINTS = "spherejax.commands"


def add_plugin_commands(commands) -> None:
    """Let every installed `spherejax.commands` entry point add its subcommand, in name order.

    The entry point's module is imported here (to add its options), so it should defer heavy
    imports to when its command runs.
    """
    from importlib.metadata import entry_points

    for entry_point in sorted(entry_points(group=COMMAND_ENTRY_POINTS), key=lambda e: e.name):
        entry_point.load()(commands)


#: Every option and positional that names a path spherejax writes is -o/--out; the spellings
#: these replaced still work, say so in --help, and at debug level when used (`_Output`): old
#: spelling -> its replacement.
DEPRECATED_SPELLINGS = {"--output": "-o/--out", "OUT": "-o/--out"}


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and examples as written (paragraphs, aligned examples); options wrapped."""

    def __init__(self, prog):
        super().__init__(prog, max_help_position=34, width=min(100, max(60, _terminal_width())))


def _terminal_width() -> int:
    import shutil

    return shutil.get_terminal_size((100, 24)).columns


class _OneLineErrors:
    """argparse's usage errors as one line, like every other bad input:
    "spherejax correct: error: the following arguments are required: -c/--calibration (see
    'spherejax correct --help')", exit status 2.

    A value that is not a number of its option's kind (`number_types`) is bad input rather than
    a usage error: it gets the line every bad input gets, "spherejax: error: --gain '0': expected
    electrons per count, a finite number > 0", and `number_types.BadNumber` (exit status 2),
    which `main` returns as it returns the status of every other bad input."""

    def error(self, message):
        # argparse calls this inside its `except ArgumentError`, raised from the type's
        # ArgumentTypeError: the NumberError is that ArgumentError's context.
        failure = sys.exc_info()[1]
        if isinstance(failure, argparse.ArgumentError) and isinstance(failure.__context__, numbers.NumberError):
            line = failure.__context__.line(failure.argument_name)
            self._print_message(f"spherejax: error: {_one_line(line)}\n", sys.stderr)
            raise numbers.BadNumber(EXIT_BAD_INPUT)
        text = " ".join(str(message).split())
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {text} (see '{self.prog} --help')\n")


def _global_options(parser: argparse.ArgumentParser, *, defaults: bool) -> None:
    """-q, -v and --log-file on `parser`. On the subcommands (defaults False) they are SUPPRESSed
    when absent, so that one given before the subcommand is not reset by the subcommand's parser:
    either position works."""
    default = (lambda value: value) if defaults else (lambda value: argparse.SUPPRESS)
    group = parser.add_argument_group("global options (before or after the command)")
    group.add_argument("-q", "--quiet", action="store_true", default=default(False),
                       help="only warnings and errors: no progress, tables or summaries")
    group.add_argument("-v", "--verbose", action="count", default=default(0),
                       help="debug messages too (each instrument command, library choices)")
    group.add_argument("--log-file", metavar="FILE", default=default(None),
                       help="also append every message, with its time, to FILE: a new file or a log "
                            "spherejax wrote (anything else there is refused)")


class _CommandParser(_OneLineErrors, argparse.ArgumentParser):
    """A subcommand's parser: the global options accepted after the command name too, help laid
    out by `_HelpFormatter`, usage errors in one line. The instrument package's `acquire` gets
    the same through the subparsers action."""

    def __init__(self, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(**kwargs)
        _global_options(self, defaults=False)


class _MainParser(_OneLineErrors, argparse.ArgumentParser):
    pass


class _Output(argparse.Action):
    """An output path option: stores the path; an old spelling (DEPRECATED_SPELLINGS) also
    leaves a note for `main` to say once the messages are set up."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        if values is None:
            return  # an optional positional left out: argparse stores its default through here
        spelling = option_string or self.metavar
        if spelling in DEPRECATED_SPELLINGS:
            namespace.deprecated_spellings = (*getattr(namespace, "deprecated_spellings", ()), spelling)


def add_output_option(parser, *, dest: str, metavar: str, help: str, required: bool = False,
                      old_spelling: bool = False, default=None) -> None:
    """-o/--out on `parser` (and the old --output when `old_spelling`), the one way every
    command names an output path (also used by the instrument package's `acquire`)."""
    flags = ["-o", "--out"] + (["--output"] if old_spelling else [])
    note = " (--output: the old spelling, deprecated)" if old_spelling else ""
    parser.add_argument(*flags, dest=dest, metavar=metavar, required=required, default=default,
                        action=_Output, help=help + note)


# The type of each numeric option, by what its number is (`number_types`: one kind each).
SEED = numbers.non_negative_integer("the simulation's seed", maximum=numbers.SEED_MAX)
MISREGISTRATION = numbers.number_in("the largest band displacement in pixels", minimum=0.0, maximum=numbers.BAND_MISREGISTRATION_MAX)
GAIN = numbers.number_in("electrons per count", minimum=numbers.GAIN_MIN, maximum=numbers.GAIN_MAX)
GAIN_RANGE = f"{numbers.shown(numbers.GAIN_MIN)}..{numbers.shown(numbers.GAIN_MAX)}"  # for --help
READ_NOISE = numbers.number_in("one frame's read noise in counts rms", minimum=0.0, maximum=numbers.READ_NOISE_MAX)
WHITE_REFLECTANCE_U = numbers.number_in("the white standard's relative standard uncertainty (0.003 for 0.3 %)",
                                        minimum=0.0, maximum=numbers.WHITE_REFLECTANCE_U_MAX)
SAMPLE_FRAMES = numbers.positive_integer("the sample frames averaged", maximum=numbers.FRAMES_MAX)
# The number's whole range is for spherejax.cluster.check_workers, which knows the machine's cores.
WORKERS = numbers.integer("the number of worker processes (1..the cores this process may use)")
# `study`'s, in the words of the checks they replace (`number_types.EXPECTED_FIRST`).
RESPONSE_WEIGHT = numbers.number_in(minimum=0.0, maximum=numbers.RESPONSE_WEIGHT_MAX,
                                    expected=f"a value 0..{numbers.shown(numbers.RESPONSE_WEIGHT_MAX)}", layout=numbers.EXPECTED_FIRST)
MAX_STEPS = numbers.positive_integer(maximum=numbers.MAX_STEPS_MAX,
                                     expected=f"a positive number of BFGS iterations, at most {numbers.MAX_STEPS_MAX}",
                                     layout=numbers.EXPECTED_FIRST)


def _version_line() -> str:
    """ "spherejax 0.1.0 (Python 3.13.0, jax 0.12.0, jaxlib 0.12.0, numpy 2.3.4, OpenImageIO
    3.1.6)": the versions that decide results, read from the installed metadata (no import)."""
    import platform
    from importlib import metadata

    from .. import __version__

    parts = [f"Python {platform.python_version()}"]
    for name in ("jax", "jaxlib", "numpy", "OpenImageIO"):
        try:
            parts.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            parts.append(f"{name} not installed")
    return f"spherejax {__version__} ({', '.join(parts)})"


def _command(commands, name: str, *, summary: str, description: str, examples: str):
    """A subcommand with its one-line summary (in `spherejax --help`), a paragraph of description
    and examples (in `spherejax NAME --help`)."""
    return commands.add_parser(name, help=summary, description=description.strip(),
                               epilog="examples:\n" + examples.strip("\n"))


def build_parser() -> argparse.ArgumentParser:
    """The command line. argparse, kept over click or typer: the instrument package adds `acquire`
    through the "spherejax.commands" entry points by calling `add_parser` on this parser's
    subparsers (a click group would break that contract for every installed plugin), the standard
    library is one dependency less for a tool labs install on instrument PCs, and what the
    conventions need -- global options in either position (`_global_options`), one-line usage
    errors, an option's old spelling noted (`_Output`) -- is a few lines on top of it."""
    parser = _MainParser(
        prog="spherejax",
        description=(
            "Lighting deviation correction for integrating-sphere multispectral imaging (Zou et al., Sensors 2019):\n"
            "Stage I (white board and white patch), Stage II (a per-band polynomial in the response and the\n"
            "white-patch ratio), Wiener estimation of 31-band reflectance, CIELAB and CIEDE2000."
        ),
        epilog=(
            "Run 'spherejax COMMAND --help' for a command's description, options and examples.\n"
            "Exit status: 0 done; 1 a batch or acquisition with failed inputs; 2 bad input (one line on\n"
            "stderr naming the file, the value and what was expected; nothing written), or standard output\n"
            "full or closed (after the work, which is kept); 130/143/129 stopped by SIGINT/SIGTERM/SIGHUP;\n"
            "141 the reader of standard output went away (after the work, which is kept and recorded)."
        ),
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=_version_line(),
                        help="print spherejax's version and those of the libraries that decide its results")
    _global_options(parser, defaults=True)
    parser.set_defaults(command=None, deprecated_spellings=())
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_CommandParser,
                                     title="commands")

    def calibration_options(p):
        p.add_argument("--reference-background", metavar="NAME", default=None,
                       help="background whose Stage I responses are the Stage II targets (default: median brightness)")
        p.add_argument("--illuminant", default="D65", choices=["D65", "A", "F2"], help="illuminant for Lab (default D65)")
        p.add_argument("--loss", default="l2", choices=list(LOSSES),
                       help="Stage II loss: l2 (closed form, Eq. 22; default) or a robust huber, cauchy, tukey")
        p.add_argument("--wiener-method", default="auto", choices=list(WIENER_METHODS),
                       help="reflectance estimator: auto (default: the affine method of lower cross-validated "
                            "error, plus a kernel regression of its residuals where that gains at least 5 %% "
                            "beyond chance), training (regression on the targets), model (system model + Wiener) "
                            "or kernel (auto's affine one plus the kernel regression, whatever its gain)")
        p.add_argument("--wiener-groups", metavar="FIELD", default=None,
                       help="manifest field naming each target capture's group (a key of its metadata, "
                            "or id, set, background): cross-validation holds out one group at a time")
        p.add_argument("--no-registration", action="store_true",
                       help="take the bands as in register: do not estimate each band's map from the session's "
                            "registration target (or target chart) and store none (default: register them)")

    demo = _command(commands, "demo", summary="simulate, calibrate, correct and evaluate the paper's experiment",
                    description="""
The main job on an embedded default, start to finish: simulate a session like the paper's
experiment (training and test captures of colour patches on differently coloured backgrounds,
targets, dark and white frames), calibrate Stage II and the reflectance estimator from it, correct
every capture and print Tables 1 and 3-6 with Figures 5 and 6. OUT gets session/, calibration.h5
and evaluation/. Run again with the same seed, the session is reused; a session of another seed,
simulator or spherejax version in OUT is refused (choose another OUT), never replaced.""",
                    examples="""
  spherejax demo                          # into ./spherejax-demo
  spherejax demo -o demo-seed1 --seed 1   # another simulated experiment
  spherejax demo -q -o demo               # tables and figures only in demo/evaluation""")
    add_output_option(demo, dest="out", metavar="DIR", default="spherejax-demo",
                      help="output folder: session/, calibration.h5, evaluation/ (default ./spherejax-demo)")
    demo.add_argument("--seed", type=SEED, default=0, help="simulation seed, 0..2**63 - 1 (default 0)")
    demo.add_argument("--force", action="store_true",
                      help="replace OUT/calibration.h5 even when no earlier demo wrote it (a spherejax calibration only)")
    calibration_options(demo)
    demo.set_defaults(run=cmd_demo)

    simulate = _command(commands, "simulate", summary="write a synthetic session like the paper's experiment",
                        description="""
Simulate the paper's experiment on a physical model of the sphere, lamp, filters and camera
(spherejax.simulate) and write it as a session folder: manifest.json and 16-bit TIFF frames, as
`acquire` writes from the instrument. The same seed gives the same frames.""",
                        examples="""
  spherejax simulate -o session-a
  spherejax simulate -o session-b --seed 7
  spherejax simulate -o session-c --band-misregistration 2   # bands up to 2 px out of register""")
    add_output_option(simulate, dest="out", metavar="DIR", help="session folder to create (new, or empty)")
    simulate.add_argument("out_positional", nargs="?", metavar="OUT", action=_Output,
                          help="the session folder as a positional argument: the old spelling of -o/--out, deprecated")
    simulate.add_argument("--seed", type=SEED, default=0, help="simulation seed, 0..2**63 - 1 (default 0)")
    simulate.add_argument("--instrument", metavar="FILE", default=None,
                          help="the instrument to simulate: a file `spherejax twin` wrote (or one written by hand "
                               "with some of its fields); default the paper's instrument")
    simulate.add_argument("--band-misregistration", metavar="PX", type=MISREGISTRATION, default=None,
                          help="move the bands out of register: each filter's and the lens's map (spherejax.band_geometry) "
                               "scaled so that the largest displacement from the 560 nm band over the frame is PX pixels, "
                               f"0..{numbers.shown(numbers.BAND_MISREGISTRATION_MAX)}; the manifest records the maps under "
                               "\"band_transforms\" (default: the instrument's maps as its filters and lens make them, at most 0.2-0.5 "
                               "px for the paper's; 0 puts the bands in register)")
    simulate.set_defaults(run=cmd_simulate)

    twin = _command(commands, "twin", summary="fit the simulator's instrument to a session (a digital twin)",
                    description="""
Fit the simulator's physical parameters to a session's frames (spherejax.twin): the camera's gain
and read noise from the dark and white frames, vignetting, filter gradients and veiling glare from
the white frame, the sphere wall's reflectance and the lamp's flicker from the white patch across
the captures. Writes FILE (JSON, a new file) for `spherejax simulate --instrument FILE`, with
what each statistic left; the other parameters keep the paper's instrument's values.""",
                    examples="""
  spherejax twin session -o instrument.json
  spherejax twin session -o instrument.json --instrument my-sphere.json   # a sphere of other size
  spherejax simulate -o like-my-lab --instrument instrument.json""")
    twin.add_argument("session", metavar="SESSION", help="session folder (manifest.json and frames/)")
    add_output_option(twin, dest="output", metavar="FILE", required=True,
                      help="instrument file to write (JSON; a new file, never over one)")
    twin.add_argument("--instrument", metavar="BASE", default=None,
                      help="the instrument the fit starts from (an instrument file): the fields the twin does not "
                           "fit, such as the sphere's size and ports, keep its values; default the paper's instrument")
    twin.set_defaults(run=cmd_twin)

    calibrate = _command(commands, "calibrate", summary="fit Stage II and the reflectance estimator from a session",
                         description="""
Register the bands (each band's map from the 560 nm band's geometry, from the session's
registration target or its target chart), fit Stage II (Eq. 22, or a robust loss) per band from
the session's training captures, choose and fit the reflectance estimator by cross-validation on
its targets, attach the noise model, and write
one calibration file (HDF5) that `correct`, `measure` and `evaluate -c` read. An existing CAL is
replaced only with --force, and only when it is a spherejax calibration.""",
                         examples="""
  spherejax calibrate session -o cal.h5
  spherejax calibrate session -o cal.h5 --force --loss huber
  spherejax calibrate session -o cal.h5 --gain 1.9 --read-noise 3.2
  spherejax calibrate session -o cal.h5 --no-registration   # bands taken as in register""")
    calibrate.add_argument("session", metavar="SESSION", help="session folder (manifest.json and frames/)")
    add_output_option(calibrate, dest="output", metavar="CAL", required=True, old_spelling=True,
                      help="calibration file to write (HDF5, conventionally .h5)")
    calibrate.add_argument("--force", action="store_true",
                           help="replace CAL if it exists (it must be a spherejax calibration)")
    calibration_options(calibrate)
    calibrate.add_argument("--gain", metavar="E_PER_COUNT", type=GAIN,
                           help=f"camera gain, electrons per count ({GAIN_RANGE}), for the stored noise model "
                                "(default: the session's metadata camera, if it records one)")
    calibrate.add_argument("--read-noise", metavar="COUNTS", type=READ_NOISE,
                           help="read noise of one frame, counts rms (0..65536; default: the session's, as --gain)")
    calibrate.add_argument("--white-reflectance-u", metavar="REL", type=WHITE_REFLECTANCE_U,
                           help="relative standard uncertainty of the white standard's certified "
                                "reflectance, 0..1, e.g. 0.003 (default: the session's, else 0)")
    calibrate.set_defaults(run=cmd_calibrate)

    evaluate = _command(commands, "evaluate", summary="the paper's tables and figures for a session",
                        description="""
Correct every capture of a session with a calibration (-c, or one fitted from the session first)
and write the paper's tables (tables.txt, table*.csv, metrics.json) and Figures 5 and 6 (PNG)
into OUT: colour differences (CIEDE2000) of each patch across backgrounds before and after each
stage, and against the Markov model.""",
                        examples="""
  spherejax evaluate session -c cal.h5 -o session-evaluation
  spherejax evaluate session                 # calibrates first; OUT defaults to SESSION-evaluation""")
    evaluate.add_argument("session", metavar="SESSION", help="session folder (manifest.json and frames/)")
    evaluate.add_argument("-c", "--calibration", metavar="CAL", help="calibration file (default: calibrate from SESSION)")
    add_output_option(evaluate, dest="out", metavar="DIR",
                      help="output folder (default SESSION-evaluation beside the session)")
    calibration_options(evaluate)
    evaluate.set_defaults(run=cmd_evaluate)

    study = _command(commands, "study",
                     summary="fit Stage II end to end for colour consistency and compare on held-out data",
                     description="""
A differentiable calibration study: starting from the closed form (or -c CAL), minimise the mean
CIEDE2000 inconsistency of the training patches across backgrounds with optimistix (BFGS), through
Stage I, Stage II, the estimator and CIELAB, then compare both calibrations on the held-out test
captures (Table 6 format). OUT gets study.txt, study.csv, study.json and study-calibration.h5.""",
                     examples="""
  spherejax study session -o session-study
  spherejax study session -c cal.h5 --wiener --max-steps 100""")
    study.add_argument("session", metavar="SESSION", help="session folder with training and test captures")
    study.add_argument("-c", "--calibration", metavar="CAL", help="starting calibration (default: the closed form from SESSION)")
    study.add_argument("--wiener", action="store_true", help="also optimise the Wiener matrix")
    study.add_argument("--response-weight", type=RESPONSE_WEIGHT, default=0.01,
                       help="weight of the paper's response residual (Eq. 21) beside ΔE00, 0..1e6 (default 0.01; "
                            "0 = colour only)")
    study.add_argument("--max-steps", type=MAX_STEPS, default=300, help="BFGS iterations, 1..100000 (default 300)")
    add_output_option(study, dest="out", metavar="DIR", help="output folder (default SESSION-study beside the session)")
    calibration_options(study)
    study.set_defaults(run=cmd_study)

    correct = _command(commands, "correct", summary="batch-correct cube files, sessions and folders into OUT",
                       description="""
Correct every cube found in the INPUTs with one calibration: Stage I, Stage II, the reflectance
estimator and CIELAB, per pixel. For each input N, OUT gets N.reflectance.exr (31 bands, the
spectral OpenEXR layout of Fichet et al. 2021) or ENVI files, N.lab, N.quality.png (flags; the
PNG's description states the key) and N.preview.png, and a manifest.jsonl recording each input's
hash and outputs.
Bad inputs are reported and skipped; --resume continues an interrupted batch; Ctrl-C stops
cleanly. --workers or --scheduler spreads the batch over dask.distributed.""",
                       examples="""
  spherejax correct -c cal.h5 captures/ -o corrected
  spherejax correct -c cal.h5 captures/ -o corrected --resume
  spherejax correct -c cal.h5 a.tif b.tif -o corrected --format envi --workers 2""")
    correct.add_argument("inputs", nargs="+", metavar="INPUT",
                         help="cube files (TIFF, EXR), band-file folders, sessions, or folders to search")
    correct.add_argument("-c", "--calibration", required=True, metavar="CAL", help="calibration file (HDF5, or an .npz of format version 1 to 3)")
    add_output_option(correct, dest="output", metavar="OUT", required=True, old_spelling=True,
                      help="output folder (new, or an earlier batch's with --resume)")
    correct.add_argument("--resume", action="store_true",
                         help="continue the batch in OUT: skip inputs whose outputs are verified, redo the rest")
    correct.add_argument("--illuminant", default=None, choices=["D65", "A", "F2"],
                         help="illuminant for Lab (default: the calibration's)")
    correct.add_argument("--format", dest="output_format", default="exr", choices=["exr", "envi"],
                         help="exr (default): OpenEXR, the reflectance in the spectral layout of Fichet et al. "
                              "(2021); envi: ENVI reflectance and Lab (.hdr + .img, band interleaved by pixel)")
    # The choices and default are io.EXR_COMPRESSIONS / io.DEFAULT_EXR_COMPRESSION, spelled out
    # so that the parser does not import OpenImageIO (tests/test_cli_conventions.py checks them).
    correct.add_argument("--exr-compression", default="none", choices=["piz", "zip", "none"],
                         help="lossless compression of the EXR outputs (default none: the fastest by far; piz: "
                              "reflectance about 27%% smaller for about four times the time of a file's whole "
                              "correction on 2 cores; zip: 6%% smaller, slower still)")
    correct.add_argument("--reflectance-type", default="float", choices=["float", "half"],
                         help="pixel type of the EXR reflectance (default float: 32-bit; half: OpenEXR's 16-bit "
                              "float, half the size at no cost in time, within 4.9e-4 of every reflectance "
                              "factor, ΔE00 0.04 at most; EXR only)")
    scale = correct.add_mutually_exclusive_group()
    scale.add_argument("--workers", type=WORKERS, metavar="N",
                       help="start a local dask.distributed cluster of N single-threaded worker processes, "
                            "one per core: N in 1..the cores this process may use (its CPU affinity), no more "
                            "(refused before any work); its scratch space is a temporary spherejax-dask-* folder, "
                            "removed when the run ends")
    scale.add_argument("--scheduler", metavar="ADDRESS", help="use a running dask.distributed scheduler")
    correct.set_defaults(run=cmd_correct)

    add_plugin_commands(commands)

    measure = _command(commands, "measure",
                       summary="measure regions of one cube: Lab and reflectance with uncertainties (k = 2), ΔE00",
                       description="""
Measure named rectangles of one cube as a spectrophotometer measures a spot: the mean corrected
reflectance (31 bands) and CIELAB of each region with expanded uncertainties (k = 2) from the
calibration's noise model, and CIEDE2000 against a reference region or L*,a*,b* values. Writes
OUT.csv and OUT.json, and with --cgats a CGATS.17 file colour quality-control software reads.""",
                       examples="""
  spherejax measure -c cal.h5 sample.tif --region std=10,60,10,60 --region batch=10,60,80,130 \\
      --reference std -o sample --cgats sample.cgats
  spherejax measure -c cal.h5 sample.tif --region patch=0,40,0,40 --reference 52.1,10.3,-4.2""")
    measure.add_argument("input", metavar="INPUT", help="cube file (16-bit TIFF, EXR) of the calibration's size and bands")
    measure.add_argument("-c", "--calibration", required=True, metavar="CAL", help="calibration file (HDF5, or an .npz of format version 1 to 3)")
    measure.add_argument("--region", action="append", required=True, metavar="NAME=r0,r1,c0,c1",
                         help="a region to measure: rows r0..r1-1, columns c0..c1-1 (repeatable, names unique)")
    measure.add_argument("--reference", metavar="NAME|L,a,b",
                         help="ΔE00 against the region NAME (its uncertainty included) or an exact L*,a*,b* "
                              "(L* 0..200, a* and b* -500..500)")
    measure.add_argument("--illuminant", default=None, choices=["D65", "A", "F2"],
                         help="illuminant for Lab (default: the calibration's)")
    add_output_option(measure, dest="output", metavar="OUT", old_spelling=True,
                      help="writes OUT.csv and OUT.json (default: INPUT's stem + .measure, in this folder)")
    measure.add_argument("--cgats", metavar="FILE",
                         help="also write the regions as CGATS.17 text (X-Rite layout: SAMPLE_ID, SAMPLE_NAME, "
                              "LAB_L/A/B, nm400..nm700), as colour quality-control software and ArgyllCMS read")
    measure.add_argument("--gain", metavar="E_PER_COUNT", type=GAIN,
                         help=f"camera gain, electrons per count ({GAIN_RANGE}): overrides the calibration's noise "
                              "model, or with --read-noise supplies one")
    measure.add_argument("--read-noise", metavar="COUNTS", type=READ_NOISE,
                         help="read noise of one frame, counts rms, 0..65536 (as --gain)")
    measure.add_argument("--frames", metavar="N", type=SAMPLE_FRAMES,
                         help="sample frames averaged in INPUT, 1..2**24 (default: the noise model's, else 1)")
    measure.set_defaults(run=cmd_measure)

    view = _command(commands, "view", summary="look at a corrected output in napari: spectra, Lab, quality and ΔE00 at a click",
                    description="""
Open an output of `spherejax correct` (N.reflectance.exr or .hdr, any file of its set, or an OUT
folder) in napari with the spherejax readout docked: the sRGB preview, the quality mask with its
bits named, the reflectance cube (lazily, a slider per wavelength), and at a click the pixel's
spectrum, L*a*b* and quality bits, ΔE00 to a reference, and regions measured as `spherejax
measure` does. With -c CAL and --raw INPUT (the calibration and raw cube it was corrected from,
checked against the output) values come with their uncertainties. --screenshot renders the
window off screen into a PNG, with no display (needs the viewer extra, and Xvfb where $DISPLAY is
unset).""",
                    examples="""
  spherejax view out/sample.reflectance.exr
  spherejax view out/sample.reflectance.exr -c cal.h5 --raw sample.tif
  spherejax view out/sample.reflectance.exr --screenshot sample.png --pixel 120,200""")
    view.add_argument("path", metavar="PATH", help="an output of spherejax correct (any file of one input's set, or N), or its OUT folder")
    view.add_argument("-c", "--calibration", metavar="CAL", help="the calibration the output was corrected with (for uncertainties)")
    view.add_argument("--raw", metavar="INPUT", help="the raw cube it was corrected from (with -c: uncertainties)")
    view.add_argument("--illuminant", default=None, choices=["D65", "A", "F2"],
                      help="illuminant for Lab (default: the output's)")
    view.add_argument("--screenshot", metavar="FILE.png", help="render the window off screen into FILE.png and exit")
    view.add_argument("--pixel", metavar="ROW,COL", help="with --screenshot: the pixel the readout shows")
    view.set_defaults(run=cmd_view)
    return parser
