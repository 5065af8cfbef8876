"""Outputs that are not inputs: the check every writing command makes before any work.

spherejax never overwrites a file it was given to read. Comparing the paths as typed is not
enough: `a.tif`, `./a.tif`, `dir/../a.tif`, a symbolic link to it and a hard link to it all name
one file. So each path is compared twice: resolved (`os.path.realpath`: links and `..` undone),
and, where the file exists, by its identity on disk, (st_dev, st_ino), which also catches a hard
link. Two outputs that are one file are refused the same way: the second would replace the first.

What every writing command checks, before any work (each raises a one-line `SpherejaxFileError`,
"PATH: problem (expected ...)", naming the output's path):

- `refuse_overlaps`: no output file is an input, the calibration or another output;
- `refuse_nesting`: an output folder of outputs named after the inputs (`correct`'s OUT) is no
  input, lies inside none and holds none, at any depth;
- `refuse_holding`: no output folder (one a command fills, creates or removes whole) is an input
  or holds one, directly or at any depth as the command needs: an evaluation written into the
  session's own folder or its frames folder, an acquisition's work folder holding its profile;
- `refuse_in_the_way`: what already lies at an output's name is replaced only when spherejax wrote
  it (a calibration file, the tables of an earlier evaluation, recognised by `not_a_calibration`
  and `earlier_run`); a folder, a link, a FIFO or a file of the user's there is refused, naming it;
- `check_output_folder`: the three for a folder of named outputs (`--out DIR` of evaluate, study,
  demo's evaluation).
"""

from __future__ import annotations

import os
import pathlib
import stat
from collections.abc import Callable, Mapping

from .errors import SpherejaxFileError

#: The largest record of an earlier run (`earlier_run`) read to recognise it: a run's JSON is a
#: few kilobytes.
MAX_RECORD_BYTES = 16 << 20


def path_identity(path: pathlib.Path) -> tuple[str, tuple[int, int] | None]:
    """(resolved path, (st_dev, st_ino) or None where nothing is there yet)."""
    resolved = os.path.realpath(path)
    try:
        status = os.stat(resolved)
    except OSError:
        return resolved, None
    return resolved, (status.st_dev, status.st_ino)


def refuse_overlaps(outputs: Mapping[str, os.PathLike | str], inputs: Mapping[str, os.PathLike | str]) -> None:
    """Raise unless every output is a file other than every input and every other output.

    Args:
      outputs: what each output is (e.g. "--cgats FILE") -> the path it will be written to.
      inputs: what each input is (e.g. "the input cube", "the calibration") -> its path.

    Raises:
      SpherejaxFileError: naming the output's path, what else it is, and what was expected.
    """
    seen: list[tuple[str, str, tuple[str, tuple[int, int] | None]]] = [
        (label, str(path), path_identity(pathlib.Path(path))) for label, path in inputs.items()
    ]
    for label, path in outputs.items():
        resolved, node = path_identity(pathlib.Path(path))
        for other_label, other_path, (other_resolved, other_node) in seen:
            if resolved == other_resolved or (node is not None and node == other_node):
                raise SpherejaxFileError(
                    path, f"{label} is also {other_label} ({other_path})",
                    f"{label} a file of its own, not an input, the calibration or another output",
                )
        seen.append((label, str(path), (resolved, node)))


def _holders(resolved: str) -> list[tuple[str, tuple[int, int] | None]]:
    """The folders above a resolved path, nearest first, each with its identity."""
    found = []
    parent = os.path.dirname(resolved)
    while True:
        found.append(path_identity(pathlib.Path(parent)))
        above = os.path.dirname(parent)
        if above == parent:
            return found
        parent = above


def refuse_holding(
    folders: Mapping[str, os.PathLike | str], inputs: Mapping[str, os.PathLike | str], *, directly: bool = False,
) -> None:
    """Raise unless no output folder is an input or holds one.

    A folder is compared as files are (`refuse_overlaps`: resolved path and (st_dev, st_ino)), and
    so is each folder above an input, which also sees through a bind mount.

    Args:
      folders: what each output folder is (e.g. "--out DIR") -> its path, present or not.
      inputs: what each input is -> its path (a file or a folder).
      directly: True: only a folder an input lies in directly counts as holding it (outputs are
        written into the folder by name, each checked on its own: the session's folder and its
        frames folder are refused, the folder above the session is not); False: at any depth
        (a folder the command removes or must find empty).

    Raises:
      SpherejaxFileError: naming the folder, the input it is or holds, and what was expected.
    """
    identities = {label: (str(path), path_identity(pathlib.Path(path))) for label, path in inputs.items()}
    for label, folder in folders.items():
        resolved, node = path_identity(pathlib.Path(folder))

        def same(other: tuple[str, tuple[int, int] | None]) -> bool:
            return other[0] == resolved or (node is not None and other[1] == node)

        for other_label, (other_path, other) in identities.items():
            if same(other):
                raise SpherejaxFileError(
                    folder, f"{label} is also {other_label} ({other_path})",
                    f"{label} a folder of its own, apart from the inputs",
                )
            holders = _holders(other[0])
            if any(same(holder) for holder in (holders[:1] if directly else holders)):
                raise SpherejaxFileError(
                    folder, f"{label} holds {other_label} ({other_path})",
                    f"{label} a folder of its own, apart from the inputs",
                )


def refuse_nesting(
    folder: os.PathLike | str, inputs: Mapping[str, os.PathLike | str], *, label: str, expected: str,
) -> None:
    """Raise unless an output folder (present or not) is none of `inputs`, lies inside none of
    them and holds none of them, at any depth: `correct`'s OUT and its inputs, so that no output
    lands among the inputs (where a later batch would take it for one) or in a session's folder.

    Compared as `refuse_holding` compares: the resolved paths (links and `..` undone) of the
    folder, of every folder above it, of each input and of every folder above each input, and
    their (st_dev, st_ino) where they exist, which also sees through a bind mount. Each input is a
    file or a folder; only a folder can hold the output folder.

    Args:
      folder: the output folder.
      inputs: a name for each input in messages (the path as given) -> its path.
      label: what the folder is, in messages ("OUT").
      expected: what was expected, in messages.

    Raises:
      SpherejaxFileError: one line naming the folder, how it meets which input, and `expected`.
    """
    resolved, node = path_identity(pathlib.Path(folder))
    # The folder and every folder above it: an input among them is the folder or holds it.
    around = [(resolved, node), *_holders(resolved)]
    around_paths = {path for path, _ in around}
    around_nodes = {found for _, found in around if found is not None}
    holders_of: dict[str, list] = {}  # an input's parent folder -> its holders (inputs share folders)
    for name, path in inputs.items():
        other_resolved, other_node = path_identity(pathlib.Path(path))
        if other_resolved == resolved or (node is not None and other_node == node):
            how = "is"
        elif other_resolved in around_paths or (other_node is not None and other_node in around_nodes):
            how = "lies inside"
        else:
            parent = os.path.dirname(other_resolved)
            if parent not in holders_of:
                holders_of[parent] = [path_identity(pathlib.Path(parent)), *_holders(parent)]
            if not any(path_ == resolved or (node is not None and found == node) for path_, found in holders_of[parent]):
                continue
            how = "holds"
        raise SpherejaxFileError(folder, f"{label} {how} the input {name}", expected)


def _lstat(path: pathlib.Path) -> os.stat_result | None:
    try:
        return os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None


def refuse_in_the_way(
    outputs: Mapping[str, os.PathLike | str], *, replaceable: Callable[[pathlib.Path], str | None], expected: str,
) -> None:
    """Raise if something spherejax did not write lies where an output goes.

    Nothing there passes. A regular file passes when `replaceable(path)` returns None (spherejax
    wrote it: a calibration, the tables of an earlier run), else it is refused with the reason
    returned. A folder, a symbolic link (spherejax makes none: the new file would replace the
    link) and a FIFO, socket or device are refused by what they are.

    Raises:
      SpherejaxFileError: naming the path, what is there, and `expected`.
    """
    from .plain_files import file_kind

    for label, path in outputs.items():
        path = pathlib.Path(path)
        found = _lstat(path)
        if found is None:
            continue
        if stat.S_ISLNK(found.st_mode):
            problem = f"{label} is in the way: a symbolic link (to {os.readlink(path)}), not a file spherejax wrote"
        elif stat.S_ISDIR(found.st_mode):
            # errno's words (EISDIR), as the write itself would have failed after all the work.
            problem = f"{label} is in the way: Is a directory"
        elif not stat.S_ISREG(found.st_mode):
            problem = f"{label} is in the way: {file_kind(found.st_mode)}"
        else:
            reason = replaceable(path)
            if reason is None:
                continue
            problem = f"{label} is in the way: {reason}"
        raise SpherejaxFileError(path, problem, expected)


def not_a_calibration(path: os.PathLike | str) -> str | None:
    """None if `path` is a calibration file spherejax wrote (it opens and verifies), else why not:
    the `replaceable` test of `refuse_in_the_way` for a calibration's output."""
    from .calibration_files import open_calibration

    try:
        open_calibration(path).close()
    except SpherejaxFileError as error:
        return f"a file that is not a spherejax calibration ({error.problem})"
    return None


def earlier_run(record: os.PathLike | str, keys: frozenset[str] | set[str]) -> bool:
    """True if `record` is a regular file of at most `MAX_RECORD_BYTES` holding a JSON object with
    every one of `keys`: the record an earlier run of a command left beside its other outputs
    (evaluate's metrics.json, study's study.json), by which those outputs are known to be its own."""
    from .. import jsontext
    from .plain_files import read_small

    if os.path.islink(record):
        return False  # a link is nothing spherejax wrote
    try:
        data = read_small(record, MAX_RECORD_BYTES)
    except OSError:
        return False
    try:
        document = jsontext.loads(data)
    except ValueError:
        return False
    return isinstance(document, dict) and set(keys) <= set(document)


def check_output_folder(
    folder: os.PathLike | str, names, *, label: str, inputs: Mapping[str, os.PathLike | str],
    holding: Mapping[str, os.PathLike | str], replaceable: Callable[[pathlib.Path], str | None],
) -> None:
    """Before any work: the folder a command writes `names` into, and each of those files.

    The folder is a folder or nothing yet; it is not one of `holding` (the session's folder and
    files) nor holds one directly (`refuse_holding`); no file it will hold is an input, the
    calibration or another output (`refuse_overlaps`); and what lies at their names already is
    replaced only when spherejax wrote it (`refuse_in_the_way`, with `replaceable`).

    Raises:
      SpherejaxFileError: one line naming the folder or file.
    """
    from .plain_files import file_kind

    folder = pathlib.Path(folder)
    found = _lstat(folder)
    if found is not None and not os.path.isdir(folder):
        what = "a file" if stat.S_ISREG(found.st_mode) else file_kind(found.st_mode)
        if stat.S_ISLNK(found.st_mode):
            what = f"a symbolic link (to {os.readlink(folder)}) to no folder"
        raise SpherejaxFileError(folder, f"{label} is in the way: {what}", f"{label} a folder, or a new name")
    refuse_holding({label: folder}, holding, directly=True)
    outputs = {f"{label}/{name}": folder / name for name in names}
    refuse_overlaps(outputs, inputs)
    refuse_in_the_way(
        outputs, replaceable=replaceable,
        expected=f"a new name in {label}, or a file an earlier run of spherejax wrote there, to replace",
    )


__all__ = [
    "refuse_overlaps", "refuse_holding", "refuse_nesting", "refuse_in_the_way", "not_a_calibration", "earlier_run",
    "check_output_folder", "path_identity",
]
