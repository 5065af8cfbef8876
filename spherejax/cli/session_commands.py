"""The commands on a session: simulate, twin, calibrate, evaluate, study and demo."""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

from ..console import Steps
from .shared import (
    _STUDY_FILES, _STUDY_RECORD, _EVALUATION_RECORD, _calibrate, _check_calibration_output,
    _check_output_folder, _evaluate, _evaluation_names, _inputs, _save_calibration, _session_files, _write_files,
    check_writable,
)


def cmd_simulate(args) -> int:
    from .. import io

    if args.out is not None and args.out_positional is not None:
        raise ValueError(f"the session folder is given twice, as -o {args.out!r} and as OUT {args.out_positional!r} "
                         "(expected -o/--out DIR alone)")
    if args.out is None and args.out_positional is None:
        raise ValueError("no session folder given (expected -o/--out DIR, the session folder to create)")
    out = pathlib.Path(args.out if args.out is not None else args.out_positional)
    instrument = None if args.instrument is None else io.load_instrument(args.instrument)
    if args.band_misregistration is not None:
        from ..simulate import InstrumentModel

        instrument = dataclasses.replace(instrument or InstrumentModel(), band_misregistration_px=args.band_misregistration)
    io.check_new_session_folder(out)  # before minutes of simulation, not after
    check_writable(out, "-o DIR", folder=False)  # staged beside it, then renamed into place
    with Steps(1, args.quiet) as progress:
        progress.start(f"simulating a session into {out}")
        session = io.write_simulated_session(out, seed=args.seed, instrument=instrument)
        progress.done(f"{len(session.frames)} captures")
    return 0


def cmd_twin(args) -> int:
    from .. import io, twin

    session = io.load_session(args.session)
    base = None if args.instrument is None else io.load_instrument(args.instrument)
    twin.check_session(session, base)  # before the progress line: a refusal is one line
    output = pathlib.Path(args.output)
    # Before the fit, not after. Every input exists, so this also keeps the session's own files.
    if os.path.lexists(output):
        raise io.InstrumentFileError(output, "exists", "a new file name: spherejax does not replace a file")
    check_writable(output, "-o FILE", folder=False)
    with Steps(1, args.quiet) as progress:
        progress.start(f"fitting the simulator's instrument to {args.session}")
        fit = twin.fit_twin(session, base)
        progress.done(", ".join(f"{name} {_parameter_text(fit.fitted[name])}" for name in twin.FITTED_PARAMETERS))
    io.save_instrument(output, fit.instrument, fitted=twin.FITTED_PARAMETERS, report=fit.report, session=session.path)
    return 0


def _parameter_text(value: float) -> str:
    return f"{value:.4g}"


def cmd_calibrate(args) -> int:
    from .. import calibrate, io

    # --gain, --read-noise and --white-reflectance-u are numbers in range or None: the parser
    # refused anything else (cli.number_types) before any work.
    session = io.load_session(args.session)
    # CAL may go beside the session's files, never over one, nor over a file spherejax did not write.
    _check_calibration_output(args.output, "-o CAL", _inputs(session), force=args.force)
    with Steps(1, args.quiet) as progress:
        calibration, report = _calibrate(session, args, progress)
    _save_calibration(args.output, calibration, report, session)
    if not args.quiet:
        print(calibrate.registration_line(report))
        print(calibrate.noise_model_line(report))
    return 0


def cmd_evaluate(args) -> int:
    from .. import io

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
    from .. import evaluate, io, number_text, study

    # --response-weight >= 0 and --max-steps >= 1: the parser refused anything else (cli.number_types).
    session = io.load_session(args.session)
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
                           "study.json": json.dumps(number_text.json_ready(payload), indent=2).encode()},
                     record=_STUDY_RECORD[0])
        _save_calibration(out / "study-calibration.h5", result.calibration, None, session)
        progress.done()
    if not args.quiet:
        print(text, end="")
    return 0


def demo_session_differs(session, seed: int) -> str | None:
    """None if `session` is the session `spherejax demo --seed SEED` would simulate now: the same
    seed, instrument model and experiment design (the simulator's defaults) and the same software
    version; else what differs, in words, for the one-line refusal.

    The comparison is of the manifest's record (`metadata.simulator`, `software_version`) with
    the defaults as JSON would store them, so a session of another seed, another design or an
    older spherejax is never taken for this one."""
    import dataclasses

    from .. import __version__, simulate

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


#: The mark a demo leaves in its calibration's metadata, inside the header its checksum signs: the
#: proof, on the file itself, that OUT/calibration.h5 is a demo's, which a demo may replace. A
#: spherejax calibration without it (one `calibrate` made for an instrument, say) is a lab's
#: calibration: replaced only with --force.
DEMO_MARK = {"written_by": "spherejax demo"}


def not_a_demo_calibration(path) -> str | None:
    """None if `path` is a calibration a demo wrote (it opens, its checksum verifies and its
    metadata holds `DEMO_MARK`), else why not, in words for a refusal."""
    from .. import io

    try:
        calibration_file = io.open_calibration(path)
    except io.SpherejaxFileError as error:
        return f"a file that is not a spherejax calibration ({error.problem})"
    try:
        header = calibration_file.header
    finally:
        calibration_file.close()
    metadata = header.get("metadata")
    if isinstance(metadata, dict) and all(metadata.get(key) == value for key, value in DEMO_MARK.items()):
        return None
    return f"a spherejax calibration that no demo wrote (instrument {header.get('instrument_id')!r})"


def _check_demo_calibration(path: pathlib.Path, inputs, *, force: bool) -> None:
    """Before any work: OUT/calibration.h5 is none of `inputs` and replaces nothing but an earlier
    demo's calibration (`not_a_demo_calibration`) or, with --force, a spherejax calibration; a
    file that is no calibration is never replaced."""
    from .. import io

    label = "OUT/calibration.h5"
    _check_calibration_output(path, label, inputs)
    if force or not os.path.lexists(path):
        return
    reason = not_a_demo_calibration(path)
    if reason is not None:
        raise io.SpherejaxFileError(path, f"{label} is in the way: {reason}",
                                    f"{label} a new file or an earlier demo's, or --force to replace this calibration")


def cmd_demo(args) -> int:
    from .. import io

    out = pathlib.Path(args.out)
    session_dir = out / "session"
    # Before any work: a session already there is reused (read only) when it is the one this run
    # would simulate (`demo_session_differs`), and refused otherwise -- not replaced: the tables
    # and calibration beside it were computed from it, and a demo never deletes captures, which in
    # a real lab's folder cost an afternoon to take. Else OUT/session must be new or empty;
    # OUT/calibration.h5 and OUT/evaluation/ replace only what an earlier demo wrote (its mark in
    # the calibration's signed header; its metrics.json beside the tables).
    reuse = (session_dir / "manifest.json").exists()
    if os.path.lexists(out) and not out.is_dir():
        raise io.SpherejaxFileError(out, "--out DIR is in the way: it is not a folder", "--out DIR a folder, or a new name")
    session = io.load_session(session_dir) if reuse else None
    if session is None:
        io.check_new_session_folder(session_dir)
        check_writable(session_dir, "OUT/session", folder=False)  # staged beside it, then renamed
    else:
        differs = demo_session_differs(session, args.seed)
        if differs is not None:
            raise io.SpherejaxFileError(
                session_dir, f"holds a session that is not the one asked for: {differs}",
                "another -o/--out DIR for this run, or the same settings to reuse it",
            )
    inputs = {"the session folder (OUT/session)": session_dir, **({} if session is None else _session_files(session))}
    _check_demo_calibration(out / "calibration.h5", inputs, force=getattr(args, "force", False))
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
        _save_calibration(out / "calibration.h5", calibration, report, session, marks=DEMO_MARK)
        _evaluate(session, calibration, out / "evaluation", progress, args.quiet)
    return 0
