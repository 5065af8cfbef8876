"""What several commands share: writing a set of files, the figures and tables of an evaluation,
calibrating a session with its report, and the ownership checks of their outputs."""

from __future__ import annotations

import contextlib
import io as _bytes_io
import os
import pathlib

from .. import console

EXIT_BAD_INPUT = 2

#: Stage II losses (spherejax.polynomial.LOSSES, repeated so --help needs no JAX import).
LOSSES = ("l2", "huber", "cauchy", "tukey")

#: Reflectance estimators (spherejax.estimation.ESTIMATOR_NAMES, repeated for the same reason).
WIENER_METHODS = ("auto", "training", "model", "kernel")


def _write_files(out_dir: pathlib.Path, files: dict[str, bytes], record: str | None = None) -> None:
    """Write name -> bytes into out_dir as one set (`spherejax.atomic_files.write_together`: all
    the temporary files first, then the renames). When one cannot be written (a full disk), none
    of the files is changed and a folder this call created is removed. With `record` (one of
    `files`, a JSON object), it lists the SHA-256 of the others (`run_records`): what lets a later
    run replace them."""
    from .. import atomic_files  # here, not at the top: --help imports nothing of JAX
    from .run_records import with_file_record

    if record is not None:
        files = with_file_record(files, record)
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        atomic_files.write_together({out_dir / name: payload for name, payload in files.items()})
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
    from .. import evaluate, figures

    files = {"tables.txt": (evaluate.format_tables(evaluation) + "\n").encode()}
    files.update({f"{name}.csv": text.encode() for name, text in evaluate.tables_csv(evaluation).items()})
    files["metrics.json"] = evaluate.to_json(evaluation).encode()
    figure_set = "test" if "test" in evaluation.sets else "training"
    files["figure5.png"] = _figure_bytes(figures.figure_5(evaluation, figure_set))
    files["figure6.png"] = _figure_bytes(figures.figure_6(evaluation, figure_set))
    return files


def _one_line(text: str) -> str:
    """A name for a message line: a newline or other control character escaped (a file may be
    named with one), bytes that are not UTF-8 shown as \\xNN, so that the line stays one line
    and printable."""
    text = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    return "".join(c if c.isprintable() or c == " " else c.encode("unicode_escape").decode("ascii") for c in text)


def check_writable(path, label: str, *, folder: bool) -> None:
    """Before any work: files can be created where `path` goes, so that a read-only or immutable
    folder, or a read-only file system, is found in one line before minutes of work, not at the
    first write after them.

    `path` is an output folder (`folder` True: its files go inside it) or an output file (its
    files go into its folder); either may not exist yet, and is then created in the nearest
    folder above it that does. That folder is tried the only way that answers for every cause
    (mode bits, which root ignores; chattr +i, which stops root too; a read-only mount; ACLs): a
    temporary name (`atomic_files.temp_sibling`, so a kill in between leaves only what clean-up
    recognises) created with O_EXCL and removed at once.

    Raises:
      SpherejaxFileError: one line naming `path`, the folder and the system's reason.
    """
    from .. import atomic_files
    from ..io.errors import SpherejaxFileError

    path = pathlib.Path(path)
    where = path if folder else path.parent
    while not os.path.lexists(where) and where != where.parent:
        where = where.parent
    if not os.path.isdir(where):
        return  # a file or link in the way: the ownership checks name it
    probe = atomic_files.temp_sibling(where / "write-check")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    except OSError as error:
        same = where.resolve() == path.resolve()
        problem = (f"cannot be written ({error.strerror})" if same
                   else f"cannot be created: the folder {where} cannot be written ({error.strerror})")
        raise SpherejaxFileError(path, problem, f"{label} where spherejax can create files") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def argument_text(value: str, option: str) -> str:
    """A command-line value (a region's name, say) as the text typed: under a locale that is not
    UTF-8 (LC_ALL=C) Python decodes the arguments' bytes as ASCII with lone surrogates for the
    rest, so "rôt" arrives as 'r\\udcc3\\udcb4t', which is neither printable nor what was meant;
    its bytes are decoded as UTF-8 instead. Text without such bytes is returned as it is.

    Raises:
      ValueError: the bytes are not UTF-8 either, in one line naming `option` and the value.
    """
    raw = value.encode("utf-8", "surrogateescape")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{option} '{_one_line(value)}': is not UTF-8 text (expected text in UTF-8)") from None


def _calibrate(session, args, progress):
    from .. import calibrate

    calibrate.check_session(session, args.reference_background, args.wiener_groups)  # bad input before any work
    calibrate.check_frames(session, registration=not getattr(args, "no_registration", False))
    progress.start(f"calibrating from {session.path}")
    calibration, report = calibrate.calibrate_session(
        session, reference=args.reference_background, loss=args.loss, illuminant=args.illuminant,
        wiener_method=args.wiener_method, wiener_groups=args.wiener_groups,
        # `calibrate`'s numbers (parsed by cli.number_types); the other commands have none.
        gain=getattr(args, "gain", None), read_noise=getattr(args, "read_noise", None),
        white_reflectance_u=getattr(args, "white_reflectance_u", None),
        registration=not getattr(args, "no_registration", False),
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
        f"  {'method':<10} {'spectral rms':>12} {'mean ΔE00 D65':>14}  settings (cost_per_pixel: multiply-adds a pixel)",
    ]
    for entry in tried:
        chosen = "*" if entry["method"] == report.wiener_method else " "
        settings = ", ".join(_setting_text(k, v) for k, v in entry["settings"].items() if k != "tried")
        if entry["folds"] != tried[0]["folds"]:  # the kernel estimator's own folds (random, not k-means)
            settings += f", folds={entry['folds']}"
        lines.append(
            f"{chosen} {entry['method']:<10} {entry['spectral_rms']:>12.5f} {entry['delta_e_d65']:>14.3f}  {settings}"
        )
    return "\n".join(lines)


def _setting_text(name: str, value) -> str:
    """One setting of a method's report as the table shows it: numbers to 3 digits, a list of
    numbers (the kernel estimator's lengthscales or ridges) as its range."""
    if isinstance(value, (list, tuple)) and value and all(isinstance(x, (int, float)) for x in value):
        return f"{name}={min(value):.3g}..{max(value):.3g}"
    return f"{name}={value:.3g}" if isinstance(value, float) else f"{name}={value}"


def _save_calibration(path, calibration, report, session, marks=None) -> None:
    """Save with the session's path, the report and `marks` (more metadata, e.g. the demo's
    mark `session_commands.DEMO_MARK`) in the signed header."""
    from .. import io

    metadata = {"session": str(session.path), **(marks or {})}
    if report is not None:
        metadata["calibration_report"] = report.as_dict()
    io.save_calibration(
        path, calibration, instrument_id=session.instrument_id,
        band_centres_nm=[int(b) for b in session.band_centres_nm], metadata=metadata,
        noise_model=None if report is None else report.noise_model,
        band_registration=None if report is None else report.band_registration,
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
    from ..io import ownership
    from ..io.errors import SpherejaxFileError

    ownership.refuse_overlaps({label: path}, inputs)
    ownership.refuse_in_the_way(
        {label: path}, replaceable=ownership.not_a_calibration,
        expected=f"{label} a new file, or a spherejax calibration to replace",
    )
    if not force and os.path.lexists(path):
        raise SpherejaxFileError(path, "exists: a spherejax calibration",
                                 f"{label} a new file, or --force to replace this calibration")
    check_writable(path, label, folder=False)


def _evaluation_names(session) -> list[str]:
    """The files `_evaluation_files` writes for `session` (Tables 3, 5 and 6 need test captures)."""
    tables = ["table1", "table4"] + (["table3", "table5", "table6"] if session.frames_with(role="sample", set="test") else [])
    return ["tables.txt", *(f"{name}.csv" for name in sorted(tables)), "metrics.json", "figure5.png", "figure6.png"]


def _check_output_folder(out_dir, names, record, *, label: str, inputs, holding) -> None:
    """Before any work: `out_dir` and the files `names` it will hold (io.ownership.check_output_folder).
    Files already there are replaced when an earlier run of the command wrote them (its `record`
    beside them lists their very bytes, `run_records`) and, for a calibration, when it is one."""
    from ..io import ownership
    from .run_records import not_recorded, recorded_files

    out_dir = pathlib.Path(out_dir)
    record_name, keys = record
    earlier = ownership.earlier_run(out_dir / record_name, keys)
    recorded = recorded_files(out_dir / record_name) if earlier else {}

    def replaceable(path: pathlib.Path) -> str | None:
        if path.suffix == ".h5":
            return ownership.not_a_calibration(path)
        if path.name == record_name:  # the record itself: known by its own keys
            return None if earlier else f"a file spherejax did not write (not an earlier run's {record_name})"
        return not_recorded(path, recorded, record_name)

    ownership.check_output_folder(out_dir, names, label=label, inputs=inputs, holding=holding, replaceable=replaceable)
    check_writable(out_dir, label, folder=True)


def _evaluate(session, calibration, out_dir, progress, quiet):
    from .. import evaluate

    progress.start(f"correcting and evaluating every capture of {session.path}")
    evaluation = evaluate.evaluate_session(session, calibration)
    files = _evaluation_files(evaluation)
    _write_files(pathlib.Path(out_dir), files, record=_EVALUATION_RECORD[0])
    progress.done(f"tables and figures in {out_dir}")
    if not quiet:
        print(evaluate.format_tables(evaluation))
    return evaluation
