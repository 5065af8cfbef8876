"""What each command reads and writes, from its arguments alone: what --log-file FILE may not be.

The log file is one more file a command writes, so it follows the rule every output follows
(`spherejax.io.ownership`): it is none of the command's inputs and outputs, by resolved path and
by (st_dev, st_ino), and it lies in no folder the command creates, fills or removes whole. Each
command's own checks run only once the command runs, after the log is open (it must be, to
record them); so the paths are derived here from the parsed arguments, before the log is opened
(`spherejax.console.configured`), without reading any file. Unchecked, `--log-file
OUT/.spherejax.lock` had `correct` write its lock over a log and delete it, and `--log-file
mdir/lg.csv measure ... -o mdir/lg` had the log replaced by the measurement.

A command added by another package (the instrument package's `acquire`) declares its paths with
`set_defaults(written_paths=FUNCTION)`, FUNCTION(args) -> `CommandPaths`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Mapping


@dataclasses.dataclass(frozen=True)
class CommandPaths:
    """A command's files, each labelled as its messages name it.

    Fields:
      inputs: what it reads (files or folders).
      outputs: the files it writes, replaces or removes by name.
      folders: the folders it creates, fills and removes whole (a session it simulates or
        acquires, an acquisition's work folder): no file of anyone else's may lie inside.
      named: (label, folder, suffixes): every file directly in `folder` whose name ends with one
        of `suffixes` is an output (`correct`'s OUT, whose outputs are named after inputs not yet
        found).
    """

    inputs: Mapping[str, pathlib.Path] = dataclasses.field(default_factory=dict)
    outputs: Mapping[str, pathlib.Path] = dataclasses.field(default_factory=dict)
    folders: Mapping[str, pathlib.Path] = dataclasses.field(default_factory=dict)
    named: tuple[tuple[str, pathlib.Path, tuple[str, ...]], ...] = ()


def _path(value) -> pathlib.Path:
    return pathlib.Path(value)


def _evaluation_outputs(label: str, folder: pathlib.Path) -> dict[str, pathlib.Path]:
    """Every file an evaluation may write into `folder` (`shared._evaluation_names`, with the
    test tables whatever the session holds: the session is not read here)."""
    names = ["tables.txt", *(f"table{n}.csv" for n in (1, 3, 4, 5, 6)), "metrics.json", "figure5.png", "figure6.png"]
    return {f"{label}/{name}": folder / name for name in names}


def _simulate(args) -> CommandPaths:
    out = args.out if args.out is not None else args.out_positional
    return CommandPaths(folders={} if out is None else {"the session folder (-o OUT)": _path(out)})


def _calibrate(args) -> CommandPaths:
    return CommandPaths(inputs={"SESSION": _path(args.session)}, outputs={"-o CAL": _path(args.output)})


def _session_inputs(args) -> dict[str, pathlib.Path]:
    inputs = {"SESSION": _path(args.session)}
    if args.calibration:
        inputs["the calibration (-c)"] = _path(args.calibration)
    return inputs


def _evaluate(args) -> CommandPaths:
    session = _path(args.session)
    out = _path(args.out) if args.out else session.with_name(session.name + "-evaluation")
    return CommandPaths(inputs=_session_inputs(args), outputs=_evaluation_outputs("--out DIR", out))


def _study(args) -> CommandPaths:
    from .shared import _STUDY_FILES

    session = _path(args.session)
    out = _path(args.out) if args.out else session.with_name(session.name + "-study")
    return CommandPaths(inputs=_session_inputs(args), outputs={f"--out DIR/{name}": out / name for name in _STUDY_FILES})


def _demo(args) -> CommandPaths:
    out = _path(args.out)
    return CommandPaths(
        outputs={"OUT/calibration.h5": out / "calibration.h5", **_evaluation_outputs("OUT/evaluation", out / "evaluation")},
        folders={"OUT/session": out / "session"},
    )


def _correct(args) -> CommandPaths:
    from ..archive.lock import LOCK_NAME
    from ..archive.manifest import MANIFEST_NAME
    from ..archive.outputs import ALL_OUTPUT_KINDS

    out = _path(args.output)
    inputs = {f"the input {value}": _path(value) for value in args.inputs}
    inputs["the calibration (-c)"] = _path(args.calibration)
    return CommandPaths(
        inputs=inputs,
        outputs={"OUT's lock": out / LOCK_NAME, "OUT's manifest": out / MANIFEST_NAME},
        named=(("an output in OUT", out, tuple(f".{kind}" for kind in ALL_OUTPUT_KINDS)),),
    )


def _measure(args) -> CommandPaths:
    from .. import measurement_files

    base = _path(args.output) if args.output else measurement_files.default_base(args.input)
    csv_path, json_path = measurement_files.output_paths(base)
    outputs = {"OUT.csv": csv_path, "OUT.json": json_path}
    if args.cgats is not None:
        outputs["--cgats FILE"] = _path(args.cgats)
    return CommandPaths(inputs={"INPUT": _path(args.input), "the calibration (-c)": _path(args.calibration)},
                        outputs=outputs)


def _view(args) -> CommandPaths:
    inputs = {"PATH": _path(args.path)}
    for label, value in (("the calibration (-c)", args.calibration), ("the raw cube (--raw)", args.raw)):
        if value is not None:
            inputs[label] = _path(value)
    outputs = {} if args.screenshot is None else {"--screenshot FILE": _path(args.screenshot)}
    return CommandPaths(inputs=inputs, outputs=outputs)


_BY_COMMAND = {
    "simulate": _simulate, "calibrate": _calibrate, "evaluate": _evaluate, "study": _study, "demo": _demo,
    "correct": _correct, "measure": _measure, "view": _view,
}


def of(args) -> CommandPaths:
    """The paths of the command `args` asks for (an empty `CommandPaths` for one that declares
    none)."""
    declared = getattr(args, "written_paths", None) or _BY_COMMAND.get(args.command)
    return CommandPaths() if declared is None else declared(args)


__all__ = ["CommandPaths", "of"]
