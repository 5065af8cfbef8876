"""Input discovery: the inputs named by the paths of a batch, each physical input once (the
package docstring, "Inputs"). Discovery looks with os.stat only: nothing is opened here."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import pathlib
import re
import stat
from collections.abc import Callable, Iterable, Sequence

from .. import io
from ..io.ownership import refuse_nesting
from .errors import BatchError, NoInputError

#: The names of cube files (`io.read_cube`), in any case.
CUBE_SUFFIXES = (".tif", ".tiff", ".exr")
#: A band file's name without its suffix: "<prefix>400nm" (package docstring, "Inputs").
_BAND_FILE = re.compile(r"(?P<prefix>.*?)[_-]?(?P<nm>\d{3,4})nm", re.IGNORECASE)


#: What discovery looks for in a folder (`_Discovery`), for the message of one that holds none.
_SEARCHED = (
    "searched {them} and every folder below (hidden names and OUT left out) for cube files (*.tif, "
    "*.tiff, *.exr), band files (*<nm>nm.tif, *<nm>nm.tiff) and sessions (folders holding "
    "manifest.json) with sample or target frames"
)
_NAMES_SHOWN = 5


def no_input_error(inputs: Sequence) -> NoInputError:
    """The error of a batch whose `inputs` (as given) hold nothing to correct."""
    names = [str(path) for path in inputs]
    shown = ", ".join(names[:_NAMES_SHOWN])
    if len(names) > _NAMES_SHOWN:
        shown += f" and {len(names) - _NAMES_SHOWN} more"
    return NoInputError(
        shown, "no cube found: " + _SEARCHED.format(them="it" if len(names) == 1 else "them"),
        "at least one cube, set of band files or session with frames to correct",
    )


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """One input of a batch: strings only, so it pickles to any worker.

    Fields:
      name: output name relative to OUT, POSIX ("batch/a"); outputs are "<name>.<kind>".
      source: the input as recorded in outputs and the manifest, relative to the common folder.
      files: absolute paths read: one cube file, or one band file per band in band order.
      kind: "cube" or "bands".
      band_centres_nm: for "bands", the centre of each file.
      instrument_id: a session's instrument, checked against the calibration's; None otherwise.
      problem: set when discovery already knows the input is bad; it then fails with this reason.
      owned: the files of OUT (paths relative to OUT, POSIX) at this input's output names proved
        spherejax's, each by its own bytes (`lock.claim_outputs`: a SHA-256 OUT's manifest or a
        stopped run's lock file records at that name): the only ones it may replace or remove
        (set by `run_batch`; empty for a fresh OUT).
    """

    name: str
    source: str
    files: tuple[str, ...]
    kind: str = "cube"
    band_centres_nm: tuple[int, ...] = ()
    instrument_id: str | None = None
    problem: str | None = None
    owned: tuple[str, ...] = ()


def _common_folder(paths: Sequence[pathlib.Path]) -> pathlib.Path:
    return pathlib.Path(os.path.commonpath([str(p.parent) for p in paths]))


def _is_hidden(path: pathlib.Path) -> bool:
    return path.name.startswith(".")


# A file that is neither a regular file nor a folder (io.plain_files.SPECIAL_FILES) is refused by
# what it is and never opened: opening a FIFO for reading blocks until a writer comes, a character
# device such as /dev/zero reads forever.
_EXPECTED_INPUT = "a cube file or a folder"

#: (st_dev, st_ino): one file or folder, however many names it has.
Identity = tuple[int, int]


def identity(st: os.stat_result) -> Identity:
    """The `Identity` of what `st` describes."""
    return (st.st_dev, st.st_ino)


def _special_file_problem(path, mode: int) -> str:
    """"PATH: is a FIFO (expected a cube file or a folder)" for a FIFO, socket or device."""
    return str(io.SpherejaxFileError(path, f"is {io.file_kind(mode)}", _EXPECTED_INPUT))


def _not_found(path: pathlib.Path, error: OSError) -> str:
    """Why a path given leads to no input, in words: the `os.stat` that failed."""
    if isinstance(error, FileNotFoundError):
        return "is a symbolic link to nothing" if os.path.islink(path) else "no such file or folder"
    if error.errno == errno.ELOOP:
        return "is a loop of symbolic links"
    return f"cannot be read: {error.strerror}"


@dataclasses.dataclass
class _Found:
    """An input found by discovery, with the identities of its files (None: not all readable)."""

    spec: InputSpec
    files: tuple[Identity, ...] | None = None


class _Discovery:
    """The inputs named by the paths given, each physical input once (module docstring, Inputs).

    Folders are searched depth first; a folder already searched ((st_dev, st_ino) seen, through
    whatever names) is not searched again, and a folder that holds the folder searched (one of
    its ancestors, reached by a symbolic link such as ``self -> ..``, or a bind mount) is not entered:
    following it would search outside the folder asked for, and loop. Each such folder gets one
    warning line and is skipped rather than failing the batch: it holds no input of its own (its
    inputs are found where they really are, or lie outside what was asked for), and an archive
    with a stray link should still be corrected.
    """

    def __init__(self, root: pathlib.Path, out_root: pathlib.Path, warn: Callable[[str], None]):
        self.root, self.warn = root, warn
        try:
            self.out = identity(os.stat(out_root))
        except OSError:
            self.out = None  # OUT does not exist yet: nothing of it to skip
        self.found: list[_Found] = []
        self.searched: dict[Identity, pathlib.Path] = {}
        self.sessions: list[pathlib.Path] = []  # every session folder found (`refuse_out_among_inputs`)

    def _rel(self, path: pathlib.Path) -> str:
        return path.relative_to(self.root).as_posix()

    def _cube(self, path: pathlib.Path, identity: Identity) -> None:
        rel = path.relative_to(self.root)
        spec = InputSpec(name=rel.with_suffix("").as_posix(), source=rel.as_posix(), files=(str(path),))
        self.found.append(_Found(spec, (identity,)))

    def _failing(self, path: pathlib.Path, problem: str) -> None:
        rel = self._rel(path)
        self.found.append(_Found(InputSpec(name=rel, source=rel, files=(str(path),), problem=problem)))

    def given(self, path: pathlib.Path) -> None:
        """One path of the command line: a file, a folder to search, or a bad input.

        Raises:
          BatchError: the path leads to nothing (a mistyped name, a link to nothing, a loop of
            links) or cannot be looked at: the batch is refused before OUT is created, so that
            the corrected command runs as a new batch, not as a `--resume`.
        """
        try:
            st = os.stat(path)  # follows links: what the name leads to
        except OSError as error:
            raise BatchError(path, _not_found(path, error), "an input to correct; nothing was created") from None
        if stat.S_ISDIR(st.st_mode):
            ancestors = set()
            for parent in pathlib.Path(os.path.realpath(path)).parents:
                with contextlib.suppress(OSError):
                    ancestors.add(identity(os.stat(parent)))
            self._folder(path, st, path, ancestors)
        elif stat.S_ISREG(st.st_mode):
            self._cube(path, identity(st))
        else:
            self._failing(path, _special_file_problem(path, st.st_mode))

    def _folder(self, folder: pathlib.Path, st: os.stat_result, top: pathlib.Path, ancestors: set) -> None:
        key = identity(st)
        if key in ancestors:
            self.warn(f"{folder}: leads to {os.path.realpath(folder)}, which holds {top}, the folder searched; "
                      f"not followed (expected folders inside {top})")
            return
        if key in self.searched:
            self.warn(f"{folder}: is {self.searched[key]} again, searched already; not searched twice")
            return
        self.searched[key] = folder
        if (folder / io.MANIFEST_NAME).is_file():
            self.sessions.append(folder)
            self._session(folder)
            return
        try:
            names = sorted(os.listdir(folder))
        except OSError as error:
            self._failing(folder, str(io.SpherejaxFileError(folder, f"cannot be listed: {error.strerror}", "a readable folder")))
            return
        files, folders = [], []
        for name in names:
            path = folder / name
            if _is_hidden(path):
                continue
            try:
                entry = os.stat(path)
            except OSError:
                continue  # a link to nothing, or a loop of links: no input (as other non-cubes)
            if stat.S_ISDIR(entry.st_mode):
                folders.append((path, entry))
            elif stat.S_ISREG(entry.st_mode):
                files.append((path, entry))
            elif path.suffix.lower() in CUBE_SUFFIXES:
                # Named like a cube but a FIFO, socket or device: refused by what it is. Special
                # files with other names are ignored, as every file not named like a cube is.
                self._failing(path, _special_file_problem(path, entry.st_mode))
        identities = {path: identity(entry) for path, entry in files}
        groups, cubes = _band_groups(path for path, _ in files)
        for prefix, members in sorted(groups.items()):
            spec = _band_input(folder, prefix, members, self.root)
            self.found.append(_Found(spec, tuple(identities[pathlib.Path(f)] for f in spec.files)))
        for path in cubes:
            self._cube(path, identities[path])
        for path, entry in folders:
            if identity(entry) != self.out:  # OUT is never searched: its outputs are no inputs
                self._folder(path, entry, top, ancestors)

    def _session(self, folder: pathlib.Path) -> None:
        for spec in _session_inputs(folder, self.root):
            try:
                files = tuple(identity(os.stat(file)) for file in spec.files)
            except OSError:
                files = None  # the input fails when it is read, with that reason
            self.found.append(_Found(spec, files if spec.problem is None else None))

    def inputs(self) -> list[InputSpec]:
        """Every input found, each physical input once: a file found under several names is
        corrected under its first name that is not a symbolic link (else its first name), and
        every other name gets one warning line."""
        chosen: dict[tuple, _Found] = {}
        for found in self.found:
            if found.files is None:
                continue
            first = chosen.setdefault(found.files, found)
            if os.path.islink(first.spec.files[0]) and not os.path.islink(found.spec.files[0]):
                chosen[found.files] = found
        inputs = []
        for found in self.found:
            winner = chosen.get(found.files) if found.files is not None else None
            if winner is None or winner is found:
                inputs.append(found.spec)
            else:
                self.warn(f"{found.spec.source}: is {winner.spec.source} again (the same file, given twice); "
                          f"skipped: corrected once, as {winner.spec.source}")
        return inputs


def _session_inputs(folder: pathlib.Path, root: pathlib.Path) -> list[InputSpec]:
    rel = folder.relative_to(root).as_posix()
    try:
        session = io.load_session(folder)
    except io.SpherejaxFileError as error:
        return [InputSpec(name=rel, source=rel, files=(str(folder),), problem=str(error))]
    inputs = []
    for frame in session.frames:
        if frame.role not in ("sample", "target"):
            continue
        file = pathlib.PurePosixPath(rel) / frame.file
        inputs.append(
            InputSpec(
                name=str(file.with_suffix("")),
                source=str(file),
                files=(str(session.frame_path(frame)),),
                instrument_id=session.instrument_id,
            )
        )
    return inputs


def _band_groups(files: Iterable[pathlib.Path]) -> tuple[dict[str, list], list[pathlib.Path]]:
    """Split a folder's files into band-file groups {prefix: [(nm, path)]} and other cubes."""
    groups: dict[str, list] = {}
    cubes = []
    for path in files:
        match = _BAND_FILE.fullmatch(path.stem)
        if match and path.suffix.lower() in (".tif", ".tiff"):
            groups.setdefault(match.group("prefix"), []).append((int(match.group("nm")), path))
        elif path.suffix.lower() in CUBE_SUFFIXES:
            cubes.append(path)
    return groups, cubes


def _band_input(folder: pathlib.Path, prefix: str, members: list, root: pathlib.Path) -> InputSpec:
    members = sorted(members)
    folder_rel = folder.relative_to(root)
    name = (folder_rel / prefix).as_posix() if prefix else folder_rel.as_posix()
    source = (folder_rel / f"{prefix}*nm").as_posix() if prefix else (folder_rel / "*nm").as_posix()
    centres = [nm for nm, _ in members]
    problem = None
    if len(set(centres)) != len(centres):
        problem = f"{folder / prefix}*nm: two files for one band centre in {centres}"
    return InputSpec(
        name=name,
        source=source,
        files=tuple(str(path) for _, path in members),
        kind="bands",
        band_centres_nm=tuple(centres),
        problem=problem,
    )


def discover_inputs(paths: Sequence, out_root, warn: Callable[[str], None] | None = None) -> list[InputSpec]:
    """Every input named by `paths` (files, sessions, folders searched recursively), in order,
    each physical input once (module docstring, Inputs).

    Every path given must lead to something: one that does not (a mistyped name, a link to
    nothing) refuses the batch, as does an OUT among the inputs (`refuse_out_among_inputs`), both
    before `run_batch` creates anything. A FIFO, socket or device given becomes an input that
    fails with that reason; OUT is never searched (so a link to it inside an input folder does
    not make its outputs inputs). `warn` gets one line per folder not followed and per input
    named again (skipped).

    Raises:
      BatchError: a path given leads to nothing, or OUT is, lies inside or holds an input.
    """
    if not paths:
        raise ValueError("no INPUT given: name cube files, session folders or folders to search")
    given = [pathlib.Path(os.path.abspath(p)) for p in paths]
    discovery = _Discovery(_common_folder(given), pathlib.Path(out_root), warn or (lambda line: None))
    for path in given:
        discovery.given(path)
    inputs = _refuse_repeated_names(discovery.inputs())
    refuse_out_among_inputs(out_root, {str(path): path for path in paths}, discovery.sessions, inputs)
    return inputs


def refuse_out_among_inputs(out_root, given: dict, sessions: Sequence[pathlib.Path], inputs: Sequence[InputSpec]) -> None:
    """Refuse OUT where its outputs would land among the inputs: OUT is, lies inside or holds
    (at any depth) a path given, a session's folder (its frames folder among them) or an input's
    file. `correct caps -o caps` would write beside the inputs, outputs a later batch of `caps`
    takes for inputs; `-o` the folder holding a session would fill its frames folder.

    Called before anything is created (`run_batch` makes OUT after discovery). Links, `..`
    and bind mounts hide nothing (`io.ownership.refuse_nesting`).

    Args:
      given: each path as given (its name in messages) -> the path.
      sessions: the session folders found, given or searched (through links too).
      inputs: the inputs found; their files are compared too.

    Raises:
      BatchError: "OUT: OUT is|lies inside|holds the input PATH (expected ...)", one line.
    """
    compared = dict(given)
    compared.update((f"session {folder}", folder) for folder in sessions)
    compared.update((file, file) for spec in inputs for file in spec.files)
    try:
        refuse_nesting(out_root, compared, label="OUT", expected=(
            "an OUT apart from the inputs, neither one of them, nor inside one, nor holding one; nothing was created"))
    except io.SpherejaxFileError as error:
        raise BatchError(error.path, error.problem, error.expected) from None


def _refuse_repeated_names(inputs: list[InputSpec]) -> list[InputSpec]:
    """The second input with an output name already taken fails (a.tif and a.exr both give a)."""
    owner: dict[str, str] = {}
    checked = []
    for spec in inputs:
        first = owner.setdefault(spec.name, spec.source)
        if first != spec.source and spec.problem is None:
            problem = f"{spec.source}: its outputs {spec.name}.* are already those of {first}"
            spec = dataclasses.replace(spec, problem=problem)
        checked.append(spec)
    return checked


__all__ = [
    "CUBE_SUFFIXES", "Identity", "InputSpec", "discover_inputs", "identity", "no_input_error", "refuse_out_among_inputs",
]
