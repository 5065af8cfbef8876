"""The `spherejax` command line (docs/design.md, "The command line").

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
status 2, and nothing written. `correct` goes on past bad inputs: each is logged with its
reason, and the run ends with a summary and exit status 1 if any failed. Everything is computed before the first byte is written, and
every file is written to a temporary name and renamed into place.

Each command writes and deletes only what it created (`spherejax.io.ownership`): before any work
every output is checked against every input, the calibration and the other outputs, by resolved
path and (st_dev, st_ino), so links and `..` cannot hide an overlap. `calibrate -o CAL` may put
CAL beside the session's files, never over one, and replaces only a spherejax calibration, and
that only with --force;
`evaluate` and `study` refuse an --out DIR that is the session's folder or its frames folder, and
replace only the files of an earlier run there (its metrics.json or study.json beside them);
`simulate` and `demo` refuse a session folder that is a link or ends in ".."; `demo` reuses a
session only when it is the one asked for (`demo_session_differs`) and replaces only what an
earlier demo wrote; --log-file appends only to a log spherejax wrote (spherejax.console). Anything else in the way is refused in one line naming it.

`correct` and `acquire` stop cleanly on SIGINT (Ctrl-C) or SIGTERM (spherejax.interrupt): at the
next safe point, with what was finished kept and recorded, nothing half-written left and OUT's
lock released, one line ("spherejax: interrupted after N of M inputs; run again with --resume")
and exit status 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io as _bytes_io
import json
import logging
import os
import pathlib
import sys

from . import console, interrupt
from .allocator import keep_freed_memory
from .console import Steps

EXIT_BAD_INPUT = 2

#: Stage II losses (spherejax.polynomial.LOSSES, repeated so --help needs no JAX import).
LOSSES = ("l2", "huber", "cauchy", "tukey")


def _write_files(out_dir: pathlib.Path, files: dict[str, bytes]) -> None:
    """Write name -> bytes into out_dir as one set (`spherejax.io.atomic.write_together`: all
    the temporary files first, then the renames). When one cannot be written (a full disk), none
    of the files is changed and a folder this call created is removed."""
    from .io import atomic  # here, not at the top: --help imports nothing of JAX

    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        atomic.write_together({out_dir / name: payload for name, payload in files.items()})
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                out_dir.rmdir()
        raise


def _figure_bytes(figure) -> bytes:
    import matplotlib.pyplot as plt

    buffer = _bytes_io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    return buffer.getvalue()


def _evaluation_files(evaluation) -> dict[str, bytes]:
    """Tables as text, CSV and JSON and Figures 5 and 6 as PNG, all in memory."""
    from . import evaluate, figures

    files = {"tables.txt": (evaluate.format_tables(evaluation) + "\n").encode()}
    files.update({f"{name}.csv": text.encode() for name, text in evaluate.tables_csv(evaluation).items()})
    files["metrics.json"] = evaluate.to_json(evaluation).encode()
    figure_set = "test" if "test" in evaluation.sets else "training"
    files["figure5.png"] = _figure_bytes(figures.figure_5(evaluation, figure_set))
    files["figure6.png"] = _figure_bytes(figures.figure_6(evaluation, figure_set))
    return files


# --------------------------------------------------------------------------------------------
# Commands


def cmd_simulate(args) -> int:
    from . import io

    if args.out is not None and args.out_positional is not None:
        raise ValueError(f"the session folder is given twice, as -o {args.out!r} and as OUT {args.out_positional!r} "
                         "(expected -o/--out DIR alone)")
    if args.out is None and args.out_positional is None:
        raise ValueError("no session folder given (expected -o/--out DIR, the session folder to create)")
    out = pathlib.Path(args.out if args.out is not None else args.out_positional)
    io.check_new_session_folder(out)  # before minutes of simulation, not after
    with Steps(1, args.quiet) as progress:
        progress.start(f"simulating a session into {out}")
        session = io.write_simulated_session(out, seed=args.seed)
        progress.done(f"{len(session.frames)} captures")
    return 0


def _calibrate(session, args, progress):
    from . import calibrate

    calibrate.check_session(session, args.reference_background, args.wiener_groups)  # bad input before any work
    progress.start(f"calibrating from {session.path}")
    calibration, report = calibrate.calibrate_session(
        session, reference=args.reference_background, loss=args.loss, illuminant=args.illuminant,
        wiener_method=args.wiener_method, wiener_groups=args.wiener_groups,
        # `calibrate` parses these (`_calibrate_noise_options`); the other commands have none.
        gain=getattr(args, "gain", None), read_noise=getattr(args, "read_noise", None),
        white_reflectance_u=getattr(args, "white_reflectance_u", None),
    )
    for band in report.unconverged_bands:
        console.warn(
            f"Stage II band {int(session.band_centres_nm[band])} nm: {report.stage2_status[band]} ({args.loss} fit)"
        )
    dropped = sum(report.stage2_dropped_samples)
    if dropped:
        console.warn(f"{dropped} non-finite Stage II training samples left out")
    progress.done(
        f"reference background {report.reference_background}, {report.training_samples} samples, "
        f"{report.targets} targets"
    )
    if not args.quiet:
        print(wiener_report_table(report))
    return calibration, report


def wiener_report_table(report) -> str:
    """The reflectance estimator's cross-validated errors per method tried, chosen one first."""
    tried = report.wiener_cross_validation
    lines = [
        f"reflectance estimator: {report.wiener_method} (cross-validated on {report.targets} targets, "
        f"{tried[0]['folds']})",
        f"  {'method':<10} {'spectral rms':>12} {'mean ΔE00 D65':>14}  settings",
    ]
    for entry in tried:
        chosen = "*" if entry["method"] == report.wiener_method else " "
        settings = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in entry["settings"].items())
        lines.append(
            f"{chosen} {entry['method']:<10} {entry['spectral_rms']:>12.5f} {entry['delta_e_d65']:>14.3f}  {settings}"
        )
    return "\n".join(lines)


def _save_calibration(path, calibration, report, session) -> None:
    from . import io

    metadata = {"session": str(session.path)}
    if report is not None:
        metadata["calibration_report"] = report.as_dict()
    io.save_calibration(
        path, calibration, instrument_id=session.instrument_id,
        band_centres_nm=[int(b) for b in session.band_centres_nm], metadata=metadata,
        noise_model=None if report is None else report.noise_model,
    )


#: The record of an earlier run that `evaluate` and `study` leave in their output folder, and the
#: keys it holds (evaluate.to_json, cmd_study's payload): the tables and figures beside one are
#: that run's, which a new run may replace (io.ownership.earlier_run).
_EVALUATION_RECORD = ("metrics.json", frozenset({"band_centres_nm", "markov_kappa", "metrics"}))
_STUDY_RECORD = ("study.json", frozenset({"objective_start", "objective_end", "closed_form", "study"}))
_STUDY_FILES = ("study.txt", "study.csv", "study.json", "study-calibration.h5")


def _session_files(session) -> dict[str, pathlib.Path]:
    """What each file of a loaded session is -> its path: the manifest and every frame."""
    files = {"the session's manifest": session.manifest_path}
    for frame in session.frames:
        files[f"the session's frame {frame.id!r}"] = session.frame_path(frame)
    return files


def _inputs(session, calibration=None) -> dict[str, pathlib.Path]:
    """Every input of a command on `session` (and -c CAL): what no output may be."""
    inputs = {"the session folder": session.path, **_session_files(session)}
    if calibration:
        inputs["the calibration (-c)"] = pathlib.Path(calibration)
    return inputs


def _check_calibration_output(path, label: str, inputs, *, force: bool = True) -> None:
    """Before any work: a calibration to be written at `path` is none of `inputs`, and replaces
    nothing but a spherejax calibration (io.ownership) -- and, with `force` False (`calibrate`
    without --force), nothing at all: a lab's calibration is replaced only when asked to."""
    from .io import ownership
    from .io.errors import SpherejaxFileError

    ownership.refuse_overlaps({label: path}, inputs)
    ownership.refuse_in_the_way(
        {label: path}, replaceable=ownership.not_a_calibration,
        expected=f"{label} a new file, or a spherejax calibration to replace",
    )
    if not force and os.path.lexists(path):
        raise SpherejaxFileError(path, "exists: a spherejax calibration",
                                 f"{label} a new file, or --force to replace this calibration")


def _evaluation_names(session) -> list[str]:
    """The files `_evaluation_files` writes for `session` (Tables 3, 5 and 6 need test captures)."""
    tables = ["table1", "table4"] + (["table3", "table5", "table6"] if session.frames_with(role="sample", set="test") else [])
    return ["tables.txt", *(f"{name}.csv" for name in sorted(tables)), "metrics.json", "figure5.png", "figure6.png"]


def _check_output_folder(out_dir, names, record, *, label: str, inputs, holding) -> None:
    """Before any work: `out_dir` and the files `names` it will hold (io.ownership.check_output_folder).
    Files already there are replaced when an earlier run of the command left them (its `record`
    beside them) and, for a calibration, when it is one."""
    from .io import ownership

    out_dir = pathlib.Path(out_dir)
    record_name, keys = record
    earlier = ownership.earlier_run(out_dir / record_name, keys)

    def replaceable(path: pathlib.Path) -> str | None:
        if path.suffix == ".h5":
            return ownership.not_a_calibration(path)
        return None if earlier else f"a file spherejax did not write (no earlier run's {record_name} beside it)"

    ownership.check_output_folder(out_dir, names, label=label, inputs=inputs, holding=holding, replaceable=replaceable)


def _calibrate_noise_options(args) -> None:
    """--gain, --read-noise and --white-reflectance-u as numbers on `args` (None when not given);
    ValueError (one line: exit status 2, nothing written) for a value that is not a finite number
    in range."""
    import math

    for option, name, expected, ok in (
        ("--gain", "gain", "electrons per count, a number > 0", lambda x: x > 0),
        ("--read-noise", "read_noise", "one frame's read noise in counts rms, a number >= 0", lambda x: x >= 0),
        ("--white-reflectance-u", "white_reflectance_u",
         "the white standard's relative standard uncertainty, a number >= 0 (0.003 for 0.3 %)", lambda x: x >= 0),
    ):
        value = getattr(args, name)
        if value is None:
            continue
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number) or not ok(number):
            raise ValueError(f"{option} {value!r}: expected {expected}")
        setattr(args, name, number)


def cmd_calibrate(args) -> int:
    from . import calibrate, io

    _calibrate_noise_options(args)  # before any work
    session = io.load_session(args.session)
    # CAL may go beside the session's files, never over one, nor over a file spherejax did not write.
    _check_calibration_output(args.output, "-o CAL", _inputs(session), force=args.force)
    with Steps(1, args.quiet) as progress:
        calibration, report = _calibrate(session, args, progress)
    _save_calibration(args.output, calibration, report, session)
    if not args.quiet:
        print(calibrate.noise_model_line(report))
    return 0


def _evaluate(session, calibration, out_dir, progress, quiet):
    from . import evaluate

    progress.start(f"correcting and evaluating every capture of {session.path}")
    evaluation = evaluate.evaluate_session(session, calibration)
    files = _evaluation_files(evaluation)
    _write_files(pathlib.Path(out_dir), files)
    progress.done(f"tables and figures in {out_dir}")
    if not quiet:
        print(evaluate.format_tables(evaluation))
    return evaluation


def cmd_evaluate(args) -> int:
    from . import io

    session = io.load_session(args.session)
    out = args.out or str(pathlib.Path(session.path).with_name(pathlib.Path(session.path).name + "-evaluation"))
    _check_output_folder(out, _evaluation_names(session), _EVALUATION_RECORD, label="--out DIR" if args.out else "SESSION-evaluation",
                         inputs=_inputs(session, args.calibration), holding=_session_files(session))
    steps = 1 if args.calibration else 2
    with Steps(steps, args.quiet) as progress:
        if args.calibration:
            calibration, _ = io.load_calibration(args.calibration, band_centres_nm=list(session.band_centres_nm))
        else:
            calibration, _ = _calibrate(session, args, progress)
        _evaluate(session, calibration, out, progress, args.quiet)
    return 0


def cmd_study(args) -> int:
    from . import evaluate, io, number_text, study

    session = io.load_session(args.session)
    if args.response_weight < 0:
        raise ValueError(f"--response-weight: expected a value >= 0, got {args.response_weight}")
    if args.max_steps < 1:
        raise ValueError(f"--max-steps: expected a positive number of BFGS iterations, got {args.max_steps}")
    out = pathlib.Path(args.out or str(pathlib.Path(session.path).with_name(pathlib.Path(session.path).name + "-study")))
    _check_output_folder(out, _STUDY_FILES, _STUDY_RECORD, label="--out DIR" if args.out else "SESSION-study",
                         inputs=_inputs(session, args.calibration), holding=_session_files(session))
    # Steps: calibrating (without -c), the BFGS fit, the held-out evaluation, writing the files.
    with Steps(3 if args.calibration else 4, args.quiet) as progress:
        if args.calibration:
            calibration, _ = io.load_calibration(args.calibration, band_centres_nm=list(session.band_centres_nm))
        else:
            calibration, _ = _calibrate(session, args, progress)
        progress.start("minimising the mean ΔE00 inconsistency with optimistix (BFGS)")
        result = study.study_session(session, calibration, fit_wiener=args.wiener, reference=args.reference_background,
                                     response_weight=args.response_weight, max_steps=args.max_steps)
        progress.done(f"objective {result.objective_start:.4f} -> {result.objective_end:.4f} in {result.steps} steps"
                      f"{'' if result.converged else ' (step limit reached)'}")
        progress.start("evaluating the closed form and the study on the held-out test captures")
        closed = evaluate.evaluate_session(session, calibration)
        studied = evaluate.evaluate_session(session, result.calibration)
        if "test" not in closed.sets:
            raise ValueError(f"{session.manifest_path}: no test captures (set 'test') to validate the study on")
        progress.done()
        progress.start(f"writing {', '.join(_STUDY_FILES)} into {out}")
        header, rows = study.comparison(closed, studied, "test")
        text = (
            "Stage II fitted for colour consistency, validated on the held-out test captures "
            "(Table 6 format)\n" + evaluate.format_table(header, rows) + "\n" + study.verdict(closed, studied, "test") + "\n"
        )
        csv = number_text.csv_text(header, rows)
        payload = {
            "reference_background": result.reference, "fit_wiener": result.fit_wiener,
            "response_weight": args.response_weight, "objective_start": result.objective_start,
            "objective_end": result.objective_end, "steps": result.steps, "converged": result.converged,
            "closed_form": closed.metrics, "study": studied.metrics,
        }
        _write_files(out, {"study.txt": text.encode(), "study.csv": csv.encode(),
                           "study.json": json.dumps(number_text.json_ready(payload), indent=2).encode()})
        _save_calibration(out / "study-calibration.h5", result.calibration, None, session)
        progress.done()
    if not args.quiet:
        print(text, end="")
    return 0


def _one_line(text: str) -> str:
    """A name for a message line: a newline or other control character escaped (a file may be
    named with one), bytes that are not UTF-8 shown as \\xNN, so that the line stays one line
    and printable."""
    text = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    return "".join(c if c.isprintable() or c == " " else c.encode("unicode_escape").decode("ascii") for c in text)


class _BatchProgress:
    """Progress of `correct`: a tqdm bar (files, MP/s) on a terminal, else one log line per input."""

    def __init__(self, quiet: bool):
        self.quiet, self.bar, self.total, self.index = quiet, None, 0, 0
        self.megapixels, self.seconds = 0.0, 0.0

    def start(self, specs) -> None:
        self.total = len(specs)
        if not self.quiet and console.on_terminal():
            self.bar = console.bar(total=self.total, unit="file")

    def result(self, spec, result) -> None:
        self.index += 1
        if result is not None:
            self.megapixels += result.megapixels
            self.seconds += result.seconds
        rate = self.megapixels / self.seconds if self.seconds else 0.0
        if self.bar is not None:
            self.bar.set_postfix_str(f"{rate:.1f} MP/s", refresh=False)
            self.bar.update(1)
            if result is not None and result.status == "failed":
                console.say(f"spherejax: failed {_one_line(spec.source)}: {_one_line(result.reason)}", logging.WARNING)
            return
        if self.quiet:
            return
        if result is None:
            what = "skipped (already done)"
        elif result.status == "done":
            what = f"done ({result.megapixels:.2f} MP, {result.seconds:.2f} s)"
        else:
            what = f"failed: {result.reason}"
        console.say(f"spherejax: [{self.index}/{self.total}] {_one_line(spec.source)}: {_one_line(what)}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def cmd_correct(args) -> int:
    from . import archive

    executor = contextlib.nullcontext()
    if args.workers is not None or args.scheduler is not None:
        from . import cluster

        executor = cluster.DaskExecutor(workers=args.workers, scheduler=args.scheduler)
    progress = _BatchProgress(args.quiet)

    try:
        # SIGINT / SIGTERM stop the batch at its next safe point (spherejax.interrupt); `main`
        # reports it. Outermost, so that the cluster's start and stop are covered too.
        with interrupt.stop_requests(), executor as running:
            summary = archive.run_batch(
                args.inputs, args.output, args.calibration, resume=args.resume,
                illuminant=args.illuminant, exr_compression=args.exr_compression, output_format=args.output_format,
                on_start=progress.start, on_result=progress.result, on_warning=console.warn, executor=running,
            )
    finally:
        progress.close()
    if summary.taken_over:
        console.say(f"spherejax: took over the lock left by {summary.taken_over} (that run ended without releasing it)",
                    logging.WARNING)
    for failure in summary.failed:
        console.say(f"spherejax: failed {_one_line(failure.source)}: {_one_line(failure.reason)}", logging.ERROR)
    print(summary.line())
    return 1 if summary.failed else 0


def _measure_regions(values, image_shape=None) -> list[tuple[str, tuple[int, int, int, int], str]]:
    """--region NAME=r0,r1,c0,c1 values -> [(name, rect, as given)]; ValueError naming the option
    and value. With `image_shape`, each rectangle must also lie inside the image."""
    regions, names = [], set()
    for given in values:
        expected = "NAME=r0,r1,c0,c1: a name, then four integers, rows r0..r1-1 and columns c0..c1-1"
        name, sep, numbers = given.partition("=")
        name = name.strip()
        parts = [part.strip() for part in numbers.split(",")]
        if not sep or not name or len(parts) != 4:
            raise ValueError(f"--region {given!r}: expected {expected}")
        if not name.isprintable():
            raise ValueError(f"--region {given!r}: the name holds a control character (expected a printable name)")
        try:
            rect = tuple(int(part) for part in parts)
        except ValueError:
            raise ValueError(f"--region {given!r}: the bounds are not integers (expected {expected})") from None
        r0, r1, c0, c1 = rect
        if not (r0 < r1 and c0 < c1):
            raise ValueError(f"--region {given!r}: is empty (expected r0 < r1 and c0 < c1)")
        if image_shape is not None:
            height, width = image_shape
            if not (0 <= r0 and r1 <= height and 0 <= c0 and c1 <= width):
                raise ValueError(
                    f"--region {given!r}: lies outside the {height} x {width} image (expected "
                    f"0 <= r0 < r1 <= {height} and 0 <= c0 < c1 <= {width})"
                )
        if name in names:
            raise ValueError(f"--region {given!r}: the name {name!r} is given twice (expected one name per region)")
        names.add(name)
        regions.append((name, rect, given))
    return regions


def _measure_reference(value: str | None, names):
    """--reference: None, ("region", NAME) or ("lab", [L, a, b]); ValueError naming the value."""
    import math

    if value is None:
        return None
    if value in names:
        return "region", value
    parts = value.split(",")
    if len(parts) == 3:
        try:
            lab = [float(part) for part in parts]
        except ValueError:
            lab = None
        if lab is not None and all(math.isfinite(x) for x in lab):
            return "lab", lab
    known = ", ".join(repr(name) for name in names)
    raise ValueError(
        f"--reference {value!r}: expected the name of a --region ({known}) or three finite numbers L,a,b"
    )


def _measure_number(option: str, value: str | None, expected: str, ok, kind=float):
    """The option's number, None if not given; ValueError naming option and value otherwise."""
    import math

    if value is None:
        return None
    try:
        number = kind(value)
    except ValueError:
        number = None
    if number is None or not math.isfinite(number) or not ok(number):
        raise ValueError(f"{option} {value!r}: expected {expected}")
    return number


def _measure_noise(args, from_file):
    """(noise model or None, where it came from, a note for stderr or None); ValueError on bad
    options.

    The calibration's model by default; --gain, --read-noise and --frames override its fields or,
    both of the first two given, make one when the calibration has none."""
    import numpy as np

    from .uncertainty import NoiseModel

    gain = _measure_number("--gain", args.gain, "electrons per count, a number > 0", lambda x: x > 0)
    read = _measure_number("--read-noise", args.read_noise, "counts rms of one frame, a number >= 0", lambda x: x >= 0)
    frames = _measure_number("--frames", args.frames, "the sample frames averaged, an integer >= 1",
                             lambda x: x >= 1, kind=int)
    options = gain is not None or read is not None or frames is not None
    single = lambda x: np.float32(x)  # noqa: E731  the dtype a calibration file's model reads back in
    if from_file is None:
        if not options:
            return None, None, (
                "spherejax: note: no noise model (the calibration has none): values without "
                "uncertainties; give --gain E_PER_COUNT and --read-noise COUNTS (and --frames N) for them"
            )
        missing = [name for name, value in (("--gain", gain), ("--read-noise", read)) if value is None]
        if missing:
            given = "--gain" if gain is not None else "--read-noise" if read is not None else "--frames"
            raise ValueError(
                f"{missing[0]}: missing; the calibration has no noise model, so {given} needs "
                f"{' and '.join(missing)} too (expected --gain E_PER_COUNT and --read-noise COUNTS)"
            )
        note = ("spherejax: note: noise model from --gain and --read-noise (the calibration has none): "
                "dark and white frames taken as single frames, Stage II and the estimator as exact")
        model = NoiseModel(gain=single(gain), read_noise=single(read), sample_frames=single(1 if frames is None else frames))
        return model, "options", note
    if not options:
        return from_file, "calibration", None
    model = NoiseModel(
        gain=from_file.gain if gain is None else single(gain),
        read_noise=from_file.read_noise if read is None else single(read),
        dark_frames=from_file.dark_frames, white_frames=from_file.white_frames,
        sample_frames=from_file.sample_frames if frames is None else single(frames),
        white_reflectance_u=from_file.white_reflectance_u, coeffs_covariance=from_file.coeffs_covariance,
        estimator_covariance=from_file.estimator_covariance,
    )
    return model, "calibration, options", None


def cmd_measure(args) -> int:
    import numpy as np

    from . import io, measurement_files
    from .measurement import measure
    from .uncertainty import NoiseModel

    # Everything the arguments alone decide is refused before any file is read.
    regions = _measure_regions(args.region)
    reference = _measure_reference(args.reference, [name for name, _, _ in regions])
    base = pathlib.Path(args.output) if args.output else measurement_files.default_base(args.input)
    measurement_files.check_output_base(base)
    if args.cgats is not None:
        measurement_files.check_cgats_path(args.cgats, measurement_files.output_paths(base))
    csv_path, json_path = measurement_files.output_paths(base)
    outputs = {"OUT.csv": csv_path, "OUT.json": json_path}
    if args.cgats is not None:
        outputs["--cgats FILE"] = args.cgats
    io.refuse_overlaps(outputs, {"the input cube": args.input, "the calibration (-c)": args.calibration})
    # A regular file there is an earlier measurement's, replaced; a FIFO, device, folder or link
    # is not spherejax's, and was replaced by the new file (a FIFO, exit 0).
    from .io import ownership

    ownership.refuse_in_the_way(outputs, replaceable=lambda path: None,
                                expected="new files, or regular files an earlier measurement wrote")

    calibration_file = io.open_calibration(args.calibration)
    try:
        header = calibration_file.header
        noise = getattr(calibration_file, "noise_model", None)
        if noise is None and header.get("noise_model") is not None:
            try:
                noise = NoiseModel.from_json(header["noise_model"])
            except ValueError as error:
                raise io.CalibrationFileError(args.calibration, f"has an invalid noise model: {error}") from None
        regions = _measure_regions(args.region, calibration_file.image_shape)
        noise, noise_source, note = _measure_noise(args, noise)
        shape = (*calibration_file.image_shape, calibration_file.bands)
        if noise is not None:
            noise.check_bands(shape[2])
        calibration = calibration_file.calibration()
    finally:
        calibration_file.close()
    raw = io.read_cube(args.input, expected_shape=shape, band_centres_nm=header["band_centres_nm"])

    results = {}
    # A bar on a terminal only: measure's stderr is otherwise empty unless something is wrong.
    with Steps(1, args.quiet, lines=False) as progress:
        progress.start(f"measuring {len(regions)} regions of {args.input}")
        for done, (name, rect, given) in enumerate(regions):
            progress.count(done, len(regions))
            r0, r1, c0, c1 = rect
            mask = np.zeros(shape[:2], bool)
            mask[r0:r1, c0:c1] = True
            try:
                results[name] = measure(raw, calibration, mask, noise, illuminant=args.illuminant)
            except ValueError as error:
                raise ValueError(f"--region {given!r}: {str(error).removeprefix('mask: ')}") from None
        progress.done()
    rows, label, reference_doc = [], None, None
    if reference is not None and reference[0] == "region":
        against = results[reference[1]]
        label = f"region {reference[1]!r} (its uncertainty included)"
        reference_doc = {"region": reference[1], "lab": against.lab.tolist()}
    elif reference is not None:
        against = reference[1]
        label = "L*a*b* = ({:g}, {:g}, {:g}) (exact)".format(*against)
        reference_doc = {"lab": against}
    for name, rect, _ in regions:
        m = results[name]
        delta_e = u = None
        if reference is not None:
            delta_e, u = m.delta_e(against)
        rows.append(measurement_files.RegionResult(name, rect, m, delta_e, u))

    illuminant = rows[0].measurement.illuminant
    document = measurement_files.json_document(
        rows, input_path=args.input, illuminant=illuminant, reference=reference_doc,
        calibration={"path": str(args.calibration), "checksum": header.get("checksum"),
                     "instrument_id": header.get("instrument_id")},
        noise_model=measurement_files.noise_model_summary(noise, noise_source),
    )
    files = {csv_path: measurement_files.csv_text(rows).encode(),
             json_path: measurement_files.json_text(document).encode()}
    if args.cgats is not None:
        created = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        files[pathlib.Path(args.cgats)] = measurement_files.cgats_text(
            rows, input_path=args.input, instrument_id=header.get("instrument_id"), created=created,
        ).encode()
    # A stop request (SIGINT, SIGTERM) while the two files are written waits until both are in place.
    with interrupt.stop_requests():
        measurement_files.write_files(files)
    if note is not None:
        console.say(note)
    if not args.quiet:
        print(measurement_files.format_table(rows, reference=label), end="")
        print("written: " + ", ".join(map(str, files)))
    return 0


def demo_session_differs(session, seed: int) -> str | None:
    """None if `session` is the session `spherejax demo --seed SEED` would simulate now: the same
    seed, instrument model and experiment design (the simulator's defaults) and the same software
    version; else what differs, in words, for the one-line refusal.

    The comparison is of the manifest's record (`metadata.simulator`, `software_version`) with
    the defaults as JSON would store them, so a session of another seed, another design or an
    older spherejax is never taken for this one."""
    import dataclasses

    from . import __version__, simulate

    recorded = session.metadata.get("simulator") if isinstance(session.metadata, dict) else None
    if not isinstance(recorded, dict):
        return "it is not a simulated session (its manifest has no simulator record)"
    if recorded.get("seed") != seed:
        return f"it was simulated with seed {recorded.get('seed')!r}, and this run asks for seed {seed}"
    as_stored = lambda value: json.loads(json.dumps(dataclasses.asdict(value)))  # noqa: E731  tuples -> lists
    for key, wanted in (("instrument", simulate.InstrumentModel()), ("design", simulate.ExperimentDesign())):
        if recorded.get(key) != as_stored(wanted):
            return f"its simulator {key} is not this version's default"
    if session.software_version != __version__:
        return f"spherejax {session.software_version} simulated it, and this is spherejax {__version__}"
    return None


def cmd_demo(args) -> int:
    from . import io

    out = pathlib.Path(args.out)
    session_dir = out / "session"
    # Before any work: a session already there is reused (read only) when it is the one this run
    # would simulate (`demo_session_differs`), and refused otherwise -- not replaced: the tables
    # and calibration beside it were computed from it, and a demo never deletes captures, which in
    # a real lab's folder cost an afternoon to take. Else OUT/session must be new or empty;
    # OUT/calibration.h5 and OUT/evaluation/ replace only what an earlier demo wrote.
    reuse = (session_dir / "manifest.json").exists()
    if os.path.lexists(out) and not out.is_dir():
        raise io.SpherejaxFileError(out, "--out DIR is in the way: it is not a folder", "--out DIR a folder, or a new name")
    session = io.load_session(session_dir) if reuse else None
    if session is None:
        io.check_new_session_folder(session_dir)
    else:
        differs = demo_session_differs(session, args.seed)
        if differs is not None:
            raise io.SpherejaxFileError(
                session_dir, f"holds a session that is not the one asked for: {differs}",
                "another -o/--out DIR for this run, or the same settings to reuse it",
            )
    inputs = {"the session folder (OUT/session)": session_dir, **({} if session is None else _session_files(session))}
    _check_calibration_output(out / "calibration.h5", "OUT/calibration.h5", inputs)
    names = _evaluation_names(session) if session is not None else [
        "tables.txt", *(f"table{n}.csv" for n in (1, 3, 4, 5, 6)), "metrics.json", "figure5.png", "figure6.png"]
    _check_output_folder(out / "evaluation", names, _EVALUATION_RECORD, label="OUT/evaluation",
                         inputs={**inputs, "OUT/calibration.h5": out / "calibration.h5"},
                         holding={} if session is None else _session_files(session))
    with Steps(3, args.quiet) as progress:
        progress.start(f"simulating the paper's experiment (seed {args.seed}) into {session_dir}")
        if session is not None:
            progress.done("reusing the session already there: the same seed, simulator and version")
        else:
            session = io.write_simulated_session(session_dir, seed=args.seed)
            progress.done(f"{len(session.frames)} captures")
        calibration, report = _calibrate(session, args, progress)
        _save_calibration(out / "calibration.h5", calibration, report, session)
        _evaluate(session, calibration, out / "evaluation", progress, args.quiet)
    return 0


# --------------------------------------------------------------------------------------------


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
    'spherejax correct --help')", exit status 2."""

    def error(self, message):
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


def _version_line() -> str:
    """ "spherejax 0.1.0 (Python 3.13.0, jax 0.12.0, jaxlib 0.12.0, numpy 2.3.4, OpenImageIO
    3.1.6)": the versions that decide results, read from the installed metadata (no import)."""
    import platform
    from importlib import metadata

    from . import __version__

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
            "stderr naming the file, the value and what was expected; nothing written); 130/143 stopped by\n"
            "SIGINT/SIGTERM."
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
        p.add_argument("--wiener-method", default="auto", choices=["auto", "training", "model"],
                       help="reflectance estimator: auto (default: the lower cross-validated error), "
                            "training (regression on the targets) or model (system model + Wiener)")
        p.add_argument("--wiener-groups", metavar="FIELD", default=None,
                       help="manifest field naming each target capture's group (a key of its metadata, "
                            "or id, set, background): cross-validation holds out one group at a time")

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
    demo.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    calibration_options(demo)
    demo.set_defaults(run=cmd_demo)

    simulate = _command(commands, "simulate", summary="write a synthetic session like the paper's experiment",
                        description="""
Simulate the paper's experiment on a physical model of the sphere, lamp, filters and camera
(spherejax.simulate) and write it as a session folder: manifest.json and 16-bit TIFF frames, as
`acquire` writes from the instrument. The same seed gives the same frames.""",
                        examples="""
  spherejax simulate -o session-a
  spherejax simulate -o session-b --seed 7""")
    add_output_option(simulate, dest="out", metavar="DIR", help="session folder to create (new, or empty)")
    simulate.add_argument("out_positional", nargs="?", metavar="OUT", action=_Output,
                          help="the session folder as a positional argument: the old spelling of -o/--out, deprecated")
    simulate.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    simulate.set_defaults(run=cmd_simulate)

    calibrate = _command(commands, "calibrate", summary="fit Stage II and the reflectance estimator from a session",
                         description="""
Fit Stage II (Eq. 22, or a robust loss) per band from the session's training captures, choose and
fit the reflectance estimator by cross-validation on its targets, attach the noise model, and write
one calibration file (HDF5) that `correct`, `measure` and `evaluate -c` read. An existing CAL is
replaced only with --force, and only when it is a spherejax calibration.""",
                         examples="""
  spherejax calibrate session -o cal.h5
  spherejax calibrate session -o cal.h5 --force --loss huber
  spherejax calibrate session -o cal.h5 --gain 1.9 --read-noise 3.2""")
    calibrate.add_argument("session", metavar="SESSION", help="session folder (manifest.json and frames/)")
    add_output_option(calibrate, dest="output", metavar="CAL", required=True, old_spelling=True,
                      help="calibration file to write (HDF5, conventionally .h5)")
    calibrate.add_argument("--force", action="store_true",
                           help="replace CAL if it exists (it must be a spherejax calibration)")
    calibration_options(calibrate)
    calibrate.add_argument("--gain", metavar="E_PER_COUNT",
                           help="camera gain, electrons per count, for the stored noise model "
                                "(default: the session's metadata camera, if it records one)")
    calibrate.add_argument("--read-noise", metavar="COUNTS",
                           help="read noise of one frame, counts rms (default: the session's, as --gain)")
    calibrate.add_argument("--white-reflectance-u", metavar="REL",
                           help="relative standard uncertainty of the white standard's certified "
                                "reflectance, e.g. 0.003 (default: the session's, else 0)")
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
    study.add_argument("--response-weight", type=float, default=0.01,
                       help="weight of the paper's response residual (Eq. 21) beside ΔE00 (default 0.01; 0 = colour only)")
    study.add_argument("--max-steps", type=int, default=300, help="BFGS iterations (default 300)")
    add_output_option(study, dest="out", metavar="DIR", help="output folder (default SESSION-study beside the session)")
    calibration_options(study)
    study.set_defaults(run=cmd_study)

    correct = _command(commands, "correct", summary="batch-correct cube files, sessions and folders into OUT",
                       description="""
Correct every cube found in the INPUTs with one calibration: Stage I, Stage II, the reflectance
estimator and CIELAB, per pixel. For each input N, OUT gets N.reflectance.exr (31 bands, the
spectral OpenEXR layout of Fichet et al. 2021) or ENVI files, N.lab, N.quality.png (flags; key
in the README) and N.preview.png, and a manifest.jsonl recording each input's hash and outputs.
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
    correct.add_argument("--exr-compression", default="piz", choices=["piz", "zip", "none"],
                         help="lossless compression of the EXR outputs (default piz: smaller and faster than zip "
                              "on noisy reflectance; none: fastest, largest)")
    scale = correct.add_mutually_exclusive_group()
    scale.add_argument("--workers", type=int, metavar="N",
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
                         help="ΔE00 against the region NAME (its uncertainty included) or an exact L*,a*,b*")
    measure.add_argument("--illuminant", default=None, choices=["D65", "A", "F2"],
                         help="illuminant for Lab (default: the calibration's)")
    add_output_option(measure, dest="output", metavar="OUT", old_spelling=True,
                      help="writes OUT.csv and OUT.json (default: INPUT's stem + .measure, in this folder)")
    measure.add_argument("--cgats", metavar="FILE",
                         help="also write the regions as CGATS.17 text (X-Rite layout: SAMPLE_ID, SAMPLE_NAME, "
                              "LAB_L/A/B, nm400..nm700), as colour quality-control software and ArgyllCMS read")
    measure.add_argument("--gain", metavar="E_PER_COUNT",
                         help="camera gain, electrons per count: overrides the calibration's noise model, "
                              "or with --read-noise supplies one")
    measure.add_argument("--read-noise", metavar="COUNTS", help="read noise of one frame, counts rms (as --gain)")
    measure.add_argument("--frames", metavar="N",
                         help="sample frames averaged in INPUT (default: the noise model's, else 1)")
    measure.set_defaults(run=cmd_measure)
    return parser


def _error_line(error: BaseException) -> str:
    return "spherejax: error: " + _one_line(" ".join(str(error).split()))


def main(argv=None) -> int:
    """Run the command line on `argv` (default sys.argv[1:]); the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()  # a bare `spherejax`: what it can do, not an error
        return 0
    with contextlib.ExitStack() as messages:
        try:
            messages.enter_context(console.configured(quiet=args.quiet, verbose=args.verbose, log_file=args.log_file))
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


def _run(args) -> int:
    # Before any JAX work: reuse freed blocks instead of page-faulting fresh ones on every image
    # (spherejax.allocator says why; about 2x on a 1-megapixel correction).
    keep_freed_memory()
    try:
        # A mistyped switch (SPHEREJAX_FUSED=off) is refused up front, not per input of a batch.
        from . import fused

        fused.switch()
        # SIGTERM, like SIGINT, unwinds through the clean-up wherever a command is (`correct` and
        # `acquire` turn both into stop requests at their safe points instead).
        with interrupt.at_once():
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


if __name__ == "__main__":
    sys.exit(main())
