"""Batch correction of archives: input discovery, per-file correction, manifest, lock, resume.

`spherejax correct -c CAL INPUT... -o OUT` is `run_batch`; the unit of work is `correct_input`,
which corrects ONE input into OUT given paths only (no shared state, picklable arguments and
result), so a process pool or a dask cluster can call it as it is.

Inputs (`discover_inputs`)
--------------------------
- A file: a cube (`io.read_cube`): a 16-bit TIFF with one channel or one page per band, or an
  OpenEXR with one float channel per band.
- A session folder (holding ``manifest.json``): each of its "sample" and "target" frames is one
  input. The session's instrument must be the calibration's.
- Any other folder, searched recursively (sorted; hidden names and OUT itself are left out):
  sessions as above; ``.tif``/``.tiff``/``.exr`` files as cubes, except band files. A band file
  is a TIFF whose name ends in the band centre, ``<prefix>400nm.tif`` (``a_400nm.tif``,
  ``a-400nm.tif``, ``400nm.tif``); the band files of one folder with the same prefix form one
  input, which must hold exactly one file per calibration band. Other files are ignored.
- A FIFO, socket or device (given, or named like a cube inside a folder) is refused by what it
  is ("PATH: is a FIFO (expected a cube file or a folder)"), a failed input; it is never opened
  (reading a FIFO waits for a writer, /dev/zero never ends). Discovery looks with os.stat only.
- Inputs in which discovery finds nothing to correct refuse the batch (`NoInputError`, exit status
  2: one line naming them and what was searched for) before OUT or its lock is created.

Each physical input is corrected once, however many ways it is named. Folders are known by
(st_dev, st_ino), so a folder reached again (a link to a folder searched already, the same folder
given twice) is not searched again, and a folder that holds the folder being searched (a link
such as ``self -> ..``, which would otherwise be followed about 40 levels deep and correct
everything under the parent at every level) is not followed. Files are known the same way: a
file named again (given twice, or through a link and directly) is corrected under its first name
that is not a symbolic link and skipped under the others. Each folder not followed and each name
skipped gets one line, "spherejax: warning: ...", naming it and what it repeats. These are no
failures: every input found is corrected once, so they leave the exit status alone (0 if nothing
failed) and nothing about them goes into the manifest. Links to folders elsewhere (neither
searched already nor above the folder searched) are followed as before.

Output names
------------
Names mirror the inputs relative to the deepest folder that holds all of them (the common folder
of the inputs' parent folders, so an input's own name is kept): ``batch/a.tif`` -> ``OUT/batch/a``,
a session ``s`` -> ``OUT/s/frames/<id>``, band files ``x/a_400nm.tif``... -> ``OUT/x/a`` (no
prefix: ``OUT/x``). For each input name N:

    N.reflectance.exr  float32 in the spectral layout of Fichet et al. (2021) (`io.spectral_layout`):
                       channels "T.400nm".."T.700nm" (31), spectralLayoutVersion "1.0";
                       attributes spherejax:calibration_checksum, spherejax:software_version,
                       spherejax:source (the input relative to that common folder),
                       spherejax:input_sha256, spherejax:illuminant
    N.lab.exr          float32, channels "L*", "a*", "b*" under the illuminant, same attributes
                       (not "L", "a", "b": OpenImageIO takes a channel "a" for alpha)
    N.quality.png      uint8, one channel: the quality bits (pipeline.QUALITY_*), 0 = good, as the
                       indices of a palette PNG whose palette shows them (`io.quality_png`): 0
                       black, each flag in its own colour; a tEXt "Description" states the key
    N.preview.png      8-bit sRGB (D65, IEC 61966-2-1 encoding) for browsing, whatever the
                       illuminant; pixels with no reflectance (quality != 0) are magenta

With `--format envi` (`output_format="envi"`) the reflectance and Lab are ENVI images instead
(`spherejax.io.envi`): N.reflectance.hdr + N.reflectance.img (float32, band interleaved by pixel,
wavelength in nm, the same attributes as header fields) and N.lab.hdr + N.lab.img; quality and
preview as above.

Bad pixels are NaN in both EXR files and the ENVI files' "data ignore value" (-9999) in ENVI
ones. Outputs carry no time stamps: a rerun writes the same bytes.

Out of core
-----------
An input is never read whole: its white-patch ratio is computed from the patch's rows first, then
it is read, corrected and written in strips of rows (`spherejax.stripwise`), and a calibration
whose dark frame and white standard are large stays on disk, read by rows
(`io.CalibrationFile`). Peak memory is then bounded by the strip size, whatever the image size,
and the outputs are byte-identical to correcting the whole image at once (tested). The unit of
distribution stays the file: one file's outputs are written by one process, in row order.
An input whose output folder would resolve outside OUT (a link inside OUT), or whose name is
already taken by another input of the batch, fails.

Safety
------
Before any work, every output is checked against every input and the calibration (resolved
paths, and (st_dev, st_ino) where the file exists, so links and `..` hide nothing), and every
output name already taken by a file is checked against what spherejax owns: the outputs OUT's
manifest records, and those a killed run claimed in its lock file (`OutputLock`). A file
spherejax did not write refuses the batch in one line naming it; it is never replaced, and
clean-up (a failed input's outputs, the other format's files) removes only owned files
(`_claim_outputs`).

Every output is written under a temporary name beside it (created with O_EXCL) and renamed into
place when complete. An input that fails has none of its outputs left in OUT. An input's hash and
its pixels are one file: the name must still lead to the file hashed (st_dev, st_ino) once the
pixels are read, else the input fails (a file swapped in mid-correction). OUT/manifest.jsonl
gets one JSON line per finished input (`FileResult.to_json`), appended with a single write and
fsync: the last line of an input wins. Without --resume an OUT holding a manifest is refused.
With it, an input is skipped when its last line is "done" with the same input and calibration
checksums, the same software version and settings (`output_settings`: illuminant, format, EXR
compression) and every output is present with the recorded SHA-256; anything else is redone.
Hashing and reading the manifest are safe points (below): a signal never waits for them.

OUT/.spherejax.lock holds an exclusive `fcntl.flock` for the whole run, and one JSON object: the
holder's pid and host (for the message that refuses a second run) and the outputs the run claims
before writing them (`OutputLock`). The kernel drops the flock when a process dies,
so a crashed or killed run never leaves OUT locked: its lock file is simply taken over. This is
sturdier than "is that pid alive", which a reused pid fools. Temporary files left by a killed run
are removed when the next run takes the lock.

Stopping
--------
Inside `interrupt.stop_requests()` (the command line), SIGINT and SIGTERM stop the batch at the
next safe point: before an input, between the strips of its writes, or before its outputs are
renamed into place. The input under way then leaves nothing (its temporary files and the folders
it created are removed; it gets no manifest line), every input finished before it is in the
manifest, the lock is released, and `run_batch` raises `interrupt.Interrupted`; `--resume`
continues with the rest. With dask, submitting stops and the inputs already on workers finish and
are recorded first (`cluster.DaskExecutor.map`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import functools
import hashlib
import json
import os
import pathlib
import re
import socket
import stat
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Annotated

import numpy as np

from . import interrupt, io
from .io import envi, spectral_layout
from .io.documents import Checksum, Document, Expect, NonEmptyStr, Sha256, check_document, choice, located
from .grid import WAVELENGTHS_NM

MANIFEST_NAME = "manifest.jsonl"
LOCK_NAME = ".spherejax.lock"
#: The outputs of one input in each output format (`--format`): "<name>.<kind>" in OUT.
OUTPUT_KINDS_BY_FORMAT = {
    "exr": ("reflectance.exr", "lab.exr", "quality.png", "preview.png"),
    "envi": ("reflectance.img", "reflectance.hdr", "lab.img", "lab.hdr", "quality.png", "preview.png"),
}
OUTPUT_FORMATS = tuple(OUTPUT_KINDS_BY_FORMAT)
#: The outputs of the default format, EXR.
OUTPUT_KINDS = OUTPUT_KINDS_BY_FORMAT["exr"]
#: Every kind of output any format writes (what removing an input's outputs looks for).
_ALL_OUTPUT_KINDS = tuple(dict.fromkeys(kind for kinds in OUTPUT_KINDS_BY_FORMAT.values() for kind in kinds))
CUBE_SUFFIXES = (".tif", ".tiff", ".exr")

#: Preview colour of pixels without reflectance (sRGB 8-bit): magenta, never a real colour of a
#: flat-fielded reflectance preview, so bad pixels stand out.
PREVIEW_BAD_PIXEL = (255, 0, 255)

_BAND_FILE = re.compile(r"(?P<prefix>.*?)[_-]?(?P<nm>\d{3,4})nm", re.IGNORECASE)


class BatchError(io.SpherejaxFileError):
    """The batch cannot start: OUT locked, already holding a batch, or not writable."""


class NoInputError(BatchError):
    """The inputs given hold no cube, band files or session to correct (`run_batch`, before OUT
    is created): "IN1, IN2: no cube found: searched ... (expected at least one ...)"."""


#: What discovery looks for in a folder (`_Discovery`), for the message of one that holds none.
_SEARCHED = (
    "searched {them} and every folder below (hidden names and OUT left out) for cube files (*.tif, "
    "*.tiff, *.exr), band files (*<nm>nm.tif, *<nm>nm.tiff) and sessions (folders holding "
    "manifest.json) with sample or target frames"
)
_NAMES_SHOWN = 5


def _no_input_error(inputs: Sequence) -> NoInputError:
    """The error of a batch whose `inputs` (as given) hold nothing to correct."""
    names = [str(path) for path in inputs]
    shown = ", ".join(names[:_NAMES_SHOWN])
    if len(names) > _NAMES_SHOWN:
        shown += f" and {len(names) - _NAMES_SHOWN} more"
    return NoInputError(
        shown, "no cube found: " + _SEARCHED.format(them="it" if len(names) == 1 else "them"),
        "at least one cube, set of band files or session with frames to correct",
    )


# ----------------------------------------------------------------------------------------- inputs


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
      owned: the files of OUT (paths relative to OUT, POSIX) at this input's output names that
        OUT's manifest records as written by spherejax: the only ones its clean-up may remove
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

_Identity = tuple[int, int]  # (st_dev, st_ino): one file or folder, however many names it has


def _identity(st: os.stat_result) -> _Identity:
    return (st.st_dev, st.st_ino)


def _special_file_problem(path, mode: int) -> str:
    """"PATH: is a FIFO (expected a cube file or a folder)" for a FIFO, socket or device."""
    return str(io.SpherejaxFileError(path, f"is {io.file_kind(mode)}", _EXPECTED_INPUT))


def _stat_problem(path: pathlib.Path, error: OSError) -> str:
    if isinstance(error, FileNotFoundError):
        what = "is a symbolic link to nothing" if os.path.islink(path) else "no such file or folder"
        return str(io.SpherejaxFileError(path, what, "an input to correct"))
    if error.errno == errno.ELOOP:
        return str(io.SpherejaxFileError(path, "is a loop of symbolic links", "an input to correct"))
    return str(io.SpherejaxFileError(path, f"cannot be read: {error.strerror}", "an input to correct"))


@dataclasses.dataclass
class _Found:
    """An input found by discovery, with the identities of its files (None: not all readable)."""

    spec: InputSpec
    files: tuple[_Identity, ...] | None = None


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
            self.out = _identity(os.stat(out_root))
        except OSError:
            self.out = None  # OUT does not exist yet: nothing of it to skip
        self.found: list[_Found] = []
        self.searched: dict[_Identity, pathlib.Path] = {}

    def _rel(self, path: pathlib.Path) -> str:
        return path.relative_to(self.root).as_posix()

    def _cube(self, path: pathlib.Path, identity: _Identity) -> None:
        rel = path.relative_to(self.root)
        spec = InputSpec(name=rel.with_suffix("").as_posix(), source=rel.as_posix(), files=(str(path),))
        self.found.append(_Found(spec, (identity,)))

    def _failing(self, path: pathlib.Path, problem: str) -> None:
        rel = self._rel(path)
        self.found.append(_Found(InputSpec(name=rel, source=rel, files=(str(path),), problem=problem)))

    def given(self, path: pathlib.Path) -> None:
        """One path of the command line: a file, a folder to search, or a bad input."""
        try:
            st = os.stat(path)  # follows links: what the name leads to
        except OSError as error:
            self._failing(path, _stat_problem(path, error))
            return
        if stat.S_ISDIR(st.st_mode):
            ancestors = set()
            for parent in pathlib.Path(os.path.realpath(path)).parents:
                with contextlib.suppress(OSError):
                    ancestors.add(_identity(os.stat(parent)))
            self._folder(path, st, path, ancestors)
        elif stat.S_ISREG(st.st_mode):
            self._cube(path, _identity(st))
        else:
            self._failing(path, _special_file_problem(path, st.st_mode))

    def _folder(self, folder: pathlib.Path, st: os.stat_result, top: pathlib.Path, ancestors: set) -> None:
        key = _identity(st)
        if key in ancestors:
            self.warn(f"{folder}: leads to {os.path.realpath(folder)}, which holds {top}, the folder searched; "
                      f"not followed (expected folders inside {top})")
            return
        if key in self.searched:
            self.warn(f"{folder}: is {self.searched[key]} again, searched already; not searched twice")
            return
        self.searched[key] = folder
        if (folder / io.MANIFEST_NAME).is_file():
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
        identities = {path: _identity(entry) for path, entry in files}
        groups, cubes = _band_groups(path for path, _ in files)
        for prefix, members in sorted(groups.items()):
            spec = _band_input(folder, prefix, members, self.root)
            self.found.append(_Found(spec, tuple(identities[pathlib.Path(f)] for f in spec.files)))
        for path in cubes:
            self._cube(path, identities[path])
        for path, entry in folders:
            if _identity(entry) != self.out:  # OUT is never searched: its outputs are no inputs
                self._folder(path, entry, top, ancestors)

    def _session(self, folder: pathlib.Path) -> None:
        for spec in _session_inputs(folder, self.root):
            try:
                files = tuple(_identity(os.stat(file)) for file in spec.files)
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

    A path that does not exist, or is a FIFO, socket or device, becomes an input that fails with
    that reason; OUT is never searched (so a rerun does not take its own outputs for inputs).
    `warn` gets one line per folder not followed and per input named again (skipped).
    """
    if not paths:
        raise ValueError("no INPUT given: name cube files, session folders or folders to search")
    given = [pathlib.Path(os.path.abspath(p)) for p in paths]
    discovery = _Discovery(_common_folder(given), pathlib.Path(out_root), warn or (lambda line: None))
    for path in given:
        discovery.given(path)
    return _refuse_repeated_names(discovery.inputs())


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


# ------------------------------------------------------------------------------- one input


@dataclasses.dataclass(frozen=True)
class FileResult:
    """What became of one input: a manifest line (`to_json`) plus timing for progress.

    status is "done" or "failed" (with a one-line `reason`); outputs maps each output's path
    relative to OUT to its SHA-256 (hex); settings are the options that shape the outputs
    (`output_settings`), which `--resume` compares.
    """

    name: str
    source: str
    status: str
    input_sha256: str | None = None
    outputs: dict = dataclasses.field(default_factory=dict)
    calibration_checksum: str | None = None
    software_version: str | None = None
    reason: str | None = None
    settings: dict | None = None
    megapixels: float = 0.0
    seconds: float = 0.0

    def to_json(self) -> dict:
        record = {
            "name": self.name,
            "input": self.source,
            "input_sha256": self.input_sha256,
            "outputs": self.outputs,
            "calibration_checksum": self.calibration_checksum,
            "software_version": self.software_version,
            "status": self.status,
        }
        if self.settings is not None:
            record["settings"] = self.settings
        if self.reason is not None:
            record["reason"] = self.reason
        return record


@functools.lru_cache(maxsize=4)
def _calibration(path: str, stamp: tuple, illuminant: str | None) -> io.CalibrationFile:
    """The open calibration file, verified once per process (per file version and illuminant)."""
    return io.open_calibration(path, illuminant=illuminant)


def load_calibration(path, illuminant: str | None = None) -> io.CalibrationFile:
    """The open `io.CalibrationFile` of a calibration, cached per process; --illuminant applied."""
    path = pathlib.Path(path).resolve()
    try:
        stat = path.stat()
        stamp = (stat.st_mtime_ns, stat.st_size)
    except OSError:
        stamp = None  # open_calibration names the problem
    return _calibration(str(path), stamp, illuminant)


def input_checksum(spec: InputSpec, max_bytes: tuple[int, str] | None = None) -> str:
    """SHA-256 (hex) over the bytes of the input's files, in order. A file larger than
    `max_bytes` is refused before any read (a sparse file claiming a terabyte would be read for
    hours). `max_bytes`: (the limit, the cube it is for, in words), `max_input_bytes`."""
    return _hash_input(spec, max_bytes)[0]


# What says a name still leads to the file hashed is its identity, `_identity` (st_dev, st_ino):
# os.replace (how a file is swapped for another, or a copy lands) gives the name another inode.
# Bytes appended in place (a copy still arriving) leave the pixels read those hashed (the image is
# what its header points at); the hash recorded then differs from the file's, so --resume
# corrects it again.


def _hash_input(spec: InputSpec, max_bytes: tuple[int, str] | None = None) -> tuple[str, tuple[_Identity, ...]]:
    """(SHA-256 hex over the input's files, each file's `_identity` as hashed): the state lets
    `_check_unchanged` prove afterwards that the pixels read came from the bytes hashed."""
    digest = hashlib.sha256()
    states = []
    for file in spec.files:
        if not _utf8_name(file):
            # OpenImageIO takes paths as UTF-8 text only; refused here, before any read, in words
            # rather than with its "incompatible function arguments".
            raise io.SpherejaxFileError(
                file, "has a name that is not UTF-8 text, which OpenImageIO cannot open",
                "a cube file whose name is UTF-8: rename it",
            )
        # The first read of an input. O_NONBLOCK: should a FIFO have taken the file's place since
        # discovery, the open returns at once instead of waiting for a writer; then it is refused
        # by what it is, before any read.
        try:
            fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as error:
            gone = isinstance(error, FileNotFoundError)
            problem = "no such file (removed or renamed since the batch found it)" if gone else f"cannot be read: {error.strerror}"
            raise io.SpherejaxFileError(file, problem, "a readable cube file") from None
        with open(fd, "rb") as handle:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise io.SpherejaxFileError(file, f"is {io.file_kind(st.st_mode)}", "a cube file")
            if max_bytes is not None and st.st_size > max_bytes[0]:
                raise io.SpherejaxFileError(
                    file, f"is {st.st_size} bytes, more than {max_bytes[1]} can take ({max_bytes[0]} at most)",
                    "a cube file",
                )
            _hash_stream(handle, digest)
            states.append(_identity(st))
    return digest.hexdigest(), tuple(states)


def _hash_stream(handle, digest) -> None:
    """Feed a file to `digest` in 1 MiB blocks, each a safe point (`interrupt.check`): hashing
    gigabytes never keeps a signal waiting (hashlib.file_digest cannot be interrupted)."""
    while block := handle.read(1 << 20):
        interrupt.check()
        digest.update(block)


def _check_unchanged(spec: InputSpec, states: tuple[_Identity, ...]) -> None:
    """Raise unless each of the input's files is still the file `_hash_input` hashed.

    The hash is taken through one open and the pixels are read through OpenImageIO's own: an
    input replaced (os.replace) or rewritten in between gave outputs of the new pixels recorded
    under the old file's hash, which --resume then trusted. Checked once the pixels are read and
    before the outputs go into place, so such an input fails and leaves nothing.
    """
    for file, state in zip(spec.files, states, strict=True):
        try:
            now = _identity(os.stat(file))
        except OSError as error:
            now = error.strerror
        if now != state:
            raise io.SpherejaxFileError(
                file, "was replaced while it was corrected: its outputs would not match its hash",
                "an input left alone until it is corrected; run again with --resume",
            )


def _utf8_name(path) -> bool:
    """True if `path` is UTF-8 text (a name with other bytes reaches Python as lone surrogates)."""
    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def max_input_bytes(calibration: io.CalibrationFile) -> tuple[int, str]:
    """The most bytes one input file may hold: the calibration's cube in 64-bit samples, twice
    over (any layout, compression that grew the data, metadata), and 64 MiB to spare
    (`io.frames.image_byte_limit`, the limit every cube reader applies)."""
    from .io.frames import image_byte_limit

    height, width = calibration.image_shape
    cube = f"a {height} x {width} x {calibration.bands} cube"
    return image_byte_limit((height, width, calibration.bands)), cube


def _open_input(spec: InputSpec, calibration: io.CalibrationFile) -> io.CubeReader:
    """The input opened for reading by strips, after checking it against the calibration."""
    header = calibration.header
    bands = header["band_centres_nm"]
    shape = (*calibration.image_shape, calibration.bands)
    if spec.instrument_id is not None and spec.instrument_id != header["instrument_id"]:
        raise io.SpherejaxFileError(
            spec.files[0],
            f"was taken on instrument {spec.instrument_id!r}, the calibration was built for "
            f"{header['instrument_id']!r}",
            "a calibration of the session's instrument",
        )
    if spec.kind == "bands":
        if list(spec.band_centres_nm) != list(bands):
            raise io.SpherejaxFileError(
                spec.source,
                f"has band files for {list(spec.band_centres_nm)} nm",
                f"one file per calibration band, {bands} nm",
            )
        return io.open_band_files(spec.files, expected_shape=shape)
    return io.open_cube(spec.files[0], expected_shape=shape, band_centres_nm=bands)


def srgb_preview(reflectance: np.ndarray) -> np.ndarray:
    """8-bit sRGB of a reflectance cube (H, W, 31) under D65 -> (H, W, 3) uint8.

    XYZ by ASTM E308 (Y = 1 for the perfect diffuser), the IEC 61966-2-1 matrix and encoding
    (colour-science), clipped to [0, 1] and rounded. Non-finite pixels become PREVIEW_BAD_PIXEL.
    """
    import colour

    from .colorimetry import tristimulus_weights

    refl = reflectance.astype(np.float64)
    xyz = refl @ (tristimulus_weights("D65") / 100.0)
    matrix = colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB
    linear = np.clip(xyz @ np.asarray(matrix).T, 0.0, 1.0)
    good = np.all(np.isfinite(linear), axis=-1)
    encoded = np.asarray(colour.models.eotf_inverse_sRGB(np.where(good[..., None], linear, 0.0)))
    rgb = np.round(encoded * 255.0).astype(np.uint8)
    rgb[~good] = PREVIEW_BAD_PIXEL
    return rgb


def _output_folder(out_root: pathlib.Path, name: str) -> tuple[pathlib.Path, list[pathlib.Path]]:
    """The folder of `name`'s outputs, created inside OUT, and the folders that were created.

    Each existing component is resolved before anything is created below it, so a link inside
    OUT can never make mkdir or a write land outside OUT.
    """
    parts = pathlib.PurePosixPath(name).parts
    if not parts or pathlib.PurePosixPath(name).is_absolute() or ".." in parts:
        raise io.SpherejaxFileError(out_root / name, "would be written outside OUT", f"a path inside {out_root}")
    root = out_root.resolve()
    folder, created = root, []
    for part in parts[:-1]:
        folder = folder / part
        if folder.exists() or folder.is_symlink():
            if not folder.resolve().is_relative_to(root):
                raise io.SpherejaxFileError(
                    out_root / name,
                    f"would be written outside OUT: {folder} resolves to {folder.resolve()}",
                    f"outputs inside {root}",
                )
            if not folder.is_dir():
                raise io.SpherejaxFileError(folder, "is not a folder: outputs cannot go there", "a folder")
        else:
            try:
                folder.mkdir()
            except OSError as error:
                raise io.SpherejaxFileError(folder, f"cannot be created: {error.strerror}") from None
            created.append(folder)
    return folder, created


def _remove_outputs(out_root: pathlib.Path, spec: InputSpec, keep: Sequence[str] = ()) -> None:
    """Remove the outputs of `spec` an earlier run left, but those of the kinds in `keep`: all of
    them for a failed input (the manifest says it failed), those of the other format for one just
    corrected (the manifest lists what it wrote). Only files OUT's manifest records as
    spherejax's (`InputSpec.owned`) are removed: a file of the same name that spherejax never
    wrote is the user's. Nothing is touched outside OUT."""
    root = out_root.resolve()
    path = root / spec.name
    if ".." in pathlib.PurePosixPath(spec.name).parts or not path.parent.resolve().is_relative_to(root):
        return
    for kind in _ALL_OUTPUT_KINDS:
        if kind in keep or f"{spec.name}.{kind}" not in spec.owned:
            continue
        output = path.parent / f"{path.name}.{kind}"
        if output.is_file() or output.is_symlink():
            output.unlink(missing_ok=True)


def _correct_into(
    cube: io.CubeReader, calibration: io.CalibrationFile, folder: pathlib.Path, stem: str,
    attributes: dict, rows_per_strip: int | None, exr_compression: str, output_format: str = "exr",
    before_commit: Callable[[], None] | None = None,
) -> dict[pathlib.Path, str]:
    """Correct `cube` strip by strip (`stripwise.correct_strips`) into its outputs in
    `output_format` (`OUTPUT_KINDS_BY_FORMAT`), each written under a temporary name and renamed
    into place once complete; on a failure the temporary files go and the outputs already
    renamed are removed. `before_commit` runs once every strip is written and before anything
    is renamed: raising there leaves nothing. Returns {path: SHA-256 (hex)} of every file written."""
    from .stripwise import correct_strips

    kinds = OUTPUT_KINDS_BY_FORMAT[output_format]
    paths = {kind: folder / f"{stem}.{kind}" for kind in kinds}
    for path in paths.values():
        if path.is_symlink() or path.is_dir():
            raise io.SpherejaxFileError(path, "is a link or a folder", "a file spherejax may replace")
    height, width, _ = cube.shape
    spectral_names = spectral_layout.reflectance_channel_names(WAVELENGTHS_NM.tolist())
    lab_names = ["L*", "a*", "b*"]
    if output_format == "exr":
        spectral_attributes = {spectral_layout.LAYOUT_VERSION_ATTRIBUTE: spectral_layout.LAYOUT_VERSION, **attributes}
        openers = {
            "reflectance": lambda: io.open_exr(
                paths["reflectance.exr"], (height, width, len(spectral_names)), channel_names=spectral_names,
                attributes=spectral_attributes, compression=exr_compression,
            ),
            "lab": lambda: io.open_exr(
                paths["lab.exr"], (height, width, 3), channel_names=lab_names, attributes=attributes,
                compression=exr_compression,
            ),
        }
    else:
        source = attributes.get("spherejax:source", stem)
        openers = {
            "reflectance": lambda: envi.EnviWriter(
                paths["reflectance.hdr"], (height, width, len(spectral_names)),
                description=f"spherejax reflectance factor (0..1) of {source}", band_names=spectral_names,
                wavelengths_nm=WAVELENGTHS_NM.tolist(), attributes=attributes,
            ),
            "lab": lambda: envi.EnviWriter(
                paths["lab.hdr"], (height, width, 3),
                description=f"spherejax CIELAB of {source} under {attributes.get('spherejax:illuminant')}",
                band_names=lab_names, attributes=attributes,
            ),
        }
    openers["quality"] = lambda: io.open_quality_png(paths["quality.png"], (height, width, 1))
    openers["preview"] = lambda: io.open_png(paths["preview.png"], (height, width, 3), channel_names=["R", "G", "B"])
    committed: dict[pathlib.Path, str] = {}
    with contextlib.ExitStack() as stack:
        writers = {}
        for row0, arrays in correct_strips(cube, calibration, rows_per_strip=rows_per_strip):
            interrupt.check()  # a safe point: leaving here removes the temporary files (ExitStack)
            if not writers:
                # Opened once the first strip is corrected: an input that fails before (in its
                # header, or its patch rows) leaves no file to abandon (libpng complains on
                # stderr about a PNG closed without rows).
                for output, open_writer in openers.items():
                    writers[output] = stack.enter_context(open_writer())
            writers["reflectance"].write_rows(row0, arrays["reflectance"])
            writers["lab"].write_rows(row0, arrays["lab"])
            writers["quality"].write_rows(row0, arrays["quality"][..., None])
            writers["preview"].write_rows(row0, srgb_preview(arrays["reflectance"]))
        # The last safe point: from here the outputs go into place together.
        interrupt.check()
        if before_commit is not None:
            before_commit()
        try:
            for output, writer in writers.items():
                digests = writer.commit()
                # An image writer gives its file's digest; an ENVI writer, its two files'.
                committed.update(digests if isinstance(digests, dict) else {writer.path: digests})
        except BaseException:
            for path in committed:
                path.unlink(missing_ok=True)
            raise
    return committed


def _remove_empty_folders(created: list[pathlib.Path]) -> None:
    """Remove the output folders an input created, deepest first, while they are empty."""
    for folder in reversed(created):
        try:
            folder.rmdir()  # only if still empty: never another input's outputs
        except OSError:
            break


def output_settings(calibration: io.CalibrationFile, output_format: str, exr_compression: str) -> dict:
    """The options that shape an input's outputs beyond the input and the calibration: the Lab
    illuminant in effect (the calibration's or --illuminant), the format and, for EXR, its
    compression. Each manifest record carries them and `--resume` redoes an input whose record
    holds other ones (`is_done`)."""
    return {
        "illuminant": calibration.patch_calibration.illuminant,
        "format": output_format,
        "exr_compression": exr_compression if output_format == "exr" else None,
    }


def correct_input(
    source: InputSpec, out_root, calibration_path, *, illuminant: str | None = None,
    rows_per_strip: int | None = None, exr_compression: str = io.DEFAULT_EXR_COMPRESSION,
    output_format: str = "exr",
) -> FileResult:
    """Correct one input into OUT and return its `FileResult`; never raises for a bad input.

    Checks the input against the calibration (instrument, bands, size), then reads, corrects and
    writes it strip by strip (`stripwise`), so memory stays bounded whatever the image's size,
    into its four outputs (module docstring). On failure nothing of this input is left in OUT
    (outputs, temporary files and folders it created are removed) and the result says why.

    Args:
      source: from `discover_inputs`.
      out_root: OUT, an existing folder.
      calibration_path: the calibration file (verified once per process).
      illuminant: Lab illuminant ("D65", "A", "F2"); None = the calibration's.
      rows_per_strip: strip height; None = `stripwise.strip_height` (the whole image when small).
      exr_compression: of the EXR outputs, one of `io.EXR_COMPRESSIONS` (all lossless).
      output_format: "exr" (the default) or "envi" (`OUTPUT_KINDS_BY_FORMAT`).
    """
    from . import __version__

    out_root = pathlib.Path(out_root)
    start = time.perf_counter()
    checksum = calibration_checksum = None
    created: list[pathlib.Path] = []
    try:
        calibration = load_calibration(calibration_path, illuminant)
        calibration_checksum = calibration.header["checksum"]
        if source.problem is not None:
            raise ValueError(source.problem)
        checksum, states = _hash_input(source, max_input_bytes(calibration))
        with _open_input(source, calibration) as cube:
            attributes = {
                "spherejax:calibration_checksum": calibration_checksum,
                "spherejax:software_version": __version__,
                "spherejax:source": source.source,
                "spherejax:input_sha256": checksum,
                "spherejax:illuminant": calibration.patch_calibration.illuminant,
            }
            folder, created = _output_folder(out_root, source.name)
            stem = pathlib.PurePosixPath(source.name).name
            written = _correct_into(
                cube, calibration, folder, stem, attributes, rows_per_strip, exr_compression, output_format,
                before_commit=lambda: _check_unchanged(source, states),
            )
        # An earlier run in the other format left files the manifest will no longer list.
        _remove_outputs(out_root, source, keep=OUTPUT_KINDS_BY_FORMAT[output_format])
        outputs = {
            path.resolve().relative_to(out_root.resolve()).as_posix(): digest
            for path, digest in written.items()
        }
        height, width = calibration.image_shape
        return FileResult(
            name=source.name, source=source.source, status="done", input_sha256=checksum,
            outputs=outputs, calibration_checksum=calibration_checksum,
            software_version=__version__, settings=output_settings(calibration, output_format, exr_compression),
            megapixels=height * width / 1e6,
            seconds=time.perf_counter() - start,
        )
    except interrupt.Interrupted:
        # Stopped at a safe point: the writers removed their temporary files and nothing was
        # renamed into place; the folders this input created go too. Outputs an earlier run left
        # stay as they are (the manifest says what they are): this run changed nothing of them.
        _remove_empty_folders(created)
        raise
    except Exception as error:  # noqa: BLE001 -- the batch boundary: one bad input never stops it
        if source.problem is None:  # (a repeated name's outputs are the other input's)
            _remove_outputs(out_root, source)
        _remove_empty_folders(created)
        reason = " ".join(str(error).split()) or type(error).__name__
        if isinstance(error, OSError) and error.strerror:  # "[Errno 13] Permission denied: 'PATH'"
            reason = f"{error.filename or source.source}: {error.strerror}"
        if not isinstance(error, (io.SpherejaxFileError, OSError, ValueError)):
            reason = f"{type(error).__name__}: {reason}"
        return FileResult(
            name=source.name, source=source.source, status="failed", input_sha256=checksum,
            calibration_checksum=calibration_checksum, software_version=__version__,
            reason=reason, seconds=time.perf_counter() - start,
        )


def failed_result(source: InputSpec, reason: str) -> FileResult:
    """A FileResult for an input whose correction never reported back (e.g. a lost worker)."""
    from . import __version__

    return FileResult(name=source.name, source=source.source, status="failed",
                      software_version=__version__, reason=" ".join(reason.split()))


# --------------------------------------------------------------------------- manifest and lock


def _manifest_records(out_root) -> Iterable[dict]:
    """Every line of OUT's manifest that is a JSON object with a name, in order. Lines that are
    not whole JSON objects (a run killed during its last write) are left out."""
    path = pathlib.Path(out_root) / MANIFEST_NAME
    if not path.is_file():
        return
    # Streamed: a manifest truncated up to gigabytes (sparse, no newline) was read whole.
    for line in io.read_lines(path, safe_point=interrupt.check):
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):  # RecursionError: arrays nested thousands deep
            continue
        if isinstance(record, dict) and isinstance(record.get("name"), str):
            yield record


def _manifest_state(out_root) -> tuple[dict[str, dict], set[str]]:
    """One pass over OUT's manifest: (the last record of each input name, every output path any
    record lists). Lines that are not whole JSON objects are ignored."""
    last: dict[str, dict] = {}
    owned: set[str] = set()
    for record in _manifest_records(out_root):
        last[record["name"]] = record
        outputs = record.get("outputs")
        if isinstance(outputs, dict):
            owned.update(name for name in outputs if isinstance(name, str))
    return last, owned


def read_manifest(out_root) -> dict[str, dict]:
    """The last manifest record of each input name (lines that are not whole JSON objects are
    ignored)."""
    return _manifest_state(out_root)[0]


def recorded_outputs(out_root) -> set[str]:
    """Every output path (relative to OUT) any record of OUT's manifest lists: the files in OUT
    that spherejax wrote, and so the only ones it may replace or remove (module docstring,
    Safety)."""
    return _manifest_state(out_root)[1]


_Status = choice("done", "failed")


class _Record(Document):
    """One line of OUT/manifest.jsonl, as `FileResult.to_json` writes it."""

    name: NonEmptyStr
    input: NonEmptyStr
    status: _Status
    input_sha256: Sha256 | None
    outputs: Annotated[dict[str, Sha256], Expect("an object: output path -> SHA-256")]
    calibration_checksum: Checksum | None
    software_version: NonEmptyStr | None
    settings: Annotated[dict | None, Expect("an object: the settings that shape the outputs")] = None
    reason: NonEmptyStr | None = None


def _is_record(record: dict, path: pathlib.Path) -> bool:
    """Whether a manifest line is a record as `FileResult.to_json` writes it."""
    try:
        check_document(_Record, record, error=located(BatchError, path))
    except BatchError:
        return False
    return True


def _link_or(error: OSError) -> str:
    """The reason an os.open with O_NOFOLLOW failed, in words: ELOOP means a symbolic link."""
    return "it is a symbolic link" if error.errno == errno.ELOOP else str(error.strerror)


class Manifest:
    """OUT/manifest.jsonl opened for appending: one os.write + fsync per record."""

    def __init__(self, out_root: pathlib.Path):
        self.path = out_root / MANIFEST_NAME
        # O_NOFOLLOW: a symbolic link planted as OUT's manifest must not make us append to the
        # file it points at, outside OUT (tests/robustness/test_security.py).
        try:
            # open_regular: a FIFO in the manifest's place made `--resume` wait forever for a reader.
            self.fd = io.open_regular(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
        except OSError as error:
            raise BatchError(self.path, f"cannot be opened: {_link_or(error)}", "a regular file inside OUT") from None
        # A run killed mid-write may have left a line without its newline: end it, so the next
        # record starts on a line of its own (the broken line is then skipped on reading).
        size = os.fstat(self.fd).st_size
        if size:
            with open(self.path, "rb") as handle:
                handle.seek(size - 1)
                if handle.read(1) != b"\n":
                    os.write(self.fd, b"\n")

    def append(self, record: dict) -> None:
        line = json.dumps(record, sort_keys=True, ensure_ascii=False, allow_nan=False) + "\n"
        # A file name that is not UTF-8 reaches Python as lone surrogates (os.fsdecode), which
        # UTF-8 cannot encode; backslashreplace writes each as the JSON escape "\udcXX", which
        # reads back as the same name.
        os.write(self.fd, line.encode("utf-8", errors="backslashreplace"))  # one write on O_APPEND: never interleaved
        os.fsync(self.fd)

    def close(self) -> None:
        os.close(self.fd)


class OutputLock:
    """An exclusive lock on OUT for one run (module docstring): flock on OUT/.spherejax.lock.

    The lock file is one JSON object: the holder's "pid" and "host", then "claims", every output
    path (relative to OUT) the run set out to write, written and fsynced before any of them is
    (`claim`). A run that ends removes the file; one killed (or failed) leaves it,
    and the run that takes it over reads its claims (`claimed`): outputs put in place and never
    recorded in the manifest (a kill between the two) are known as spherejax's, not taken for a
    user's files in the way. They live here, not in a file of their own, because the lock file is
    the one file a killed run is known to leave in OUT.
    """

    def __init__(self, out_root: pathlib.Path):
        self.path = out_root / LOCK_NAME
        self.fd: int | None = None
        self.taken_over: str | None = None  # the previous holder, when its lock file was left
        self.claimed: set[str] = set()  # output paths claimed by runs that left the lock file
        self.holds_claims = False  # the file holds claims (this run's or carried over)

    def acquire(self) -> None:
        while True:
            try:
                # O_NOFOLLOW: the lock is written (the holder's pid); a symbolic link planted in
                # its place must not redirect that write to a file outside OUT.
                # open_regular: a FIFO in the lock's place made `correct` wait forever on its read.
                fd = io.open_regular(self.path, os.O_RDWR | os.O_CREAT)
            except OSError as error:
                raise BatchError(self.path, f"cannot be created: {_link_or(error)}", "a regular file in a writable OUT") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _describe_holder(os.read(fd, 4096))
                os.close(fd)
                raise BatchError(
                    self.path, f"is held by {holder}: another spherejax correct is writing to this OUT",
                    "one run per OUT; wait for it or use another OUT",
                ) from None
            # The previous holder may have removed the file between our open and flock: then we
            # hold a lock on a file nobody else will see. Start again on the file now there.
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            left = os.read(fd, 4096)
            if left:
                self.taken_over = _describe_holder(left)
                self.claimed = _read_claims(fd)
            self.fd = fd
            self._claims: list[str] = []
            self._write()
            self.claim(sorted(self.claimed))  # carried over until a run ends
            return

    def _write(self) -> None:
        """The lock file's one JSON object, written over what was there (it only grows)."""
        record = {"pid": os.getpid(), "host": socket.gethostname(), "claims": self._claims}
        data = (json.dumps(record, ensure_ascii=False) + "\n").encode("utf-8", errors="backslashreplace")
        if os.fstat(self.fd).st_size > len(data):  # only when taking over a longer file
            os.ftruncate(self.fd, len(data))
        os.pwrite(self.fd, data, 0)

    def claim(self, outputs: Iterable[str]) -> None:
        """Record, before writing them, the output paths (relative to OUT) this run may write."""
        new = [name for name in outputs if name not in self._claims]
        if new and self.fd is not None:
            self._claims.extend(new)
            self._write()
            os.fsync(self.fd)
            self.holds_claims = True

    def release(self, keep_claims: bool = False) -> None:
        """Give up the lock; the file goes unless `keep_claims` (a run that did not end) and it
        holds claims."""
        if self.fd is not None:
            # Unlink while still holding the lock, so nobody locks a file that is about to go.
            if not (keep_claims and self.holds_claims):
                self.path.unlink(missing_ok=True)
            os.close(self.fd)
            self.fd = None


#: The most of a left lock file read for its claims: 10,000 inputs' claims take about 3 MB.
_MAX_LOCK_BYTES = 64 << 20


def _read_claims(fd: int) -> set[str]:
    """The output paths a lock file left by an earlier run claims (`OutputLock`); none from a file
    that is not such an object (torn by a kill mid-write, or not spherejax's)."""
    size = os.fstat(fd).st_size
    if size > _MAX_LOCK_BYTES:
        return set()
    try:
        record = json.loads(os.pread(fd, size, 0))
    except (ValueError, RecursionError):
        return set()
    claims = record.get("claims") if isinstance(record, dict) else None
    return {name for name in claims if isinstance(name, str)} if isinstance(claims, list) else set()


def _describe_holder(content: bytes) -> str:
    """The holder a lock file names, in one line (it goes into messages); never raises: the file
    may hold anything."""
    # The holder's pid and host open the object; the claims after them may run past what was read.
    match = re.match(rb'\{"pid": (\d+), "host": ("(?:[^"\\]|\\.)*")', content)
    try:
        holder = {"pid": int(match[1]), "host": json.loads(match[2])} if match else json.loads(content)
        return " ".join(f"pid {holder['pid']} on {holder['host']}".split())
    except (ValueError, TypeError, KeyError, RecursionError):
        return "another process"


def _remove_temporaries(out_root: pathlib.Path) -> int:
    """Remove the temporary files a killed run left in OUT (only ours: io's naming)."""
    removed = 0
    for dirpath, _, filenames in os.walk(out_root):
        for filename in filenames:
            if io.is_temp_sibling(filename):
                os.unlink(os.path.join(dirpath, filename))
                removed += 1
    return removed


def _sha256_file(path: pathlib.Path) -> str | None:
    try:
        with open(io.open_regular(path, os.O_RDONLY), "rb") as handle:  # a FIFO there: None, at once
            digest = hashlib.sha256()
            _hash_stream(handle, digest)
            return digest.hexdigest()
    except OSError:
        return None


def is_done(record: dict | None, spec: InputSpec, out_root: pathlib.Path, calibration_checksum: str,
            output_format: str = "exr", settings: dict | None = None) -> bool:
    """True if `record` says `spec` is done with this calibration, this version of spherejax and
    these `settings` (`output_settings`; None: not compared), its input is unchanged and every
    output of `output_format` is recorded and there with its checksum (a batch resumed in another
    format, illuminant or compression redoes its inputs)."""
    from . import __version__

    if not record or spec.problem is not None or not _is_record(record, out_root / MANIFEST_NAME):
        return False  # a line another writer or a damaged file left is redone, not trusted
    if record["status"] != "done":
        return False
    if record.get("calibration_checksum") != calibration_checksum:
        return False
    # Each output names the version that wrote it (spherejax:software_version): another version
    # writes other bytes, and may compute other numbers.
    if record.get("software_version") != __version__:
        return False
    if settings is not None and record.get("settings") != settings:
        return False
    expected = {f"{spec.name}.{kind}" for kind in OUTPUT_KINDS_BY_FORMAT[output_format]}
    outputs = record.get("outputs")
    if not isinstance(outputs, dict) or set(outputs) != expected:
        return False
    try:
        if record.get("input_sha256") != input_checksum(spec):
            return False
    except OSError:
        return False
    return all(_sha256_file(out_root / name) == digest for name, digest in outputs.items())


# ----------------------------------------------------------------------------------- the batch


@dataclasses.dataclass
class BatchSummary:
    """Counts of a run and every failed input's `FileResult`."""

    corrected: int = 0
    skipped: int = 0
    failed: list[FileResult] = dataclasses.field(default_factory=list)
    taken_over: str | None = None

    def line(self) -> str:
        return f"{self.corrected} corrected, {self.skipped} skipped (already done), {len(self.failed)} failed"


def run_batch(
    inputs: Sequence,
    out_root,
    calibration_path,
    *,
    resume: bool = False,
    illuminant: str | None = None,
    exr_compression: str = io.DEFAULT_EXR_COMPRESSION,
    output_format: str = "exr",
    on_start: Callable[[list[InputSpec]], None] | None = None,
    on_result: Callable[[InputSpec, FileResult | None], None] | None = None,
    on_warning: Callable[[str], None] | None = None,
    executor=None,
) -> BatchSummary:
    """Correct every input into OUT, in process (`spherejax correct`).

    Args:
      inputs: files and folders (module docstring).
      out_root: OUT; created if missing.
      calibration_path: the calibration file.
      resume: continue a batch already in OUT, skipping verified inputs.
      illuminant: Lab illuminant; None = the calibration's.
      exr_compression: of the EXR outputs (`io.EXR_COMPRESSIONS`, all lossless).
      output_format: "exr" (default: OpenEXR, the reflectance in the spectral layout) or "envi"
        (ENVI reflectance and Lab); `OUTPUT_KINDS_BY_FORMAT` lists the files of each.
      on_start: called with the inputs found, before the first is corrected.
      on_result: called per input with its FileResult, or None when it was skipped.
      on_warning: called with one line per folder not followed and per input named twice
        (`discover_inputs`).
      executor: None corrects in this process; otherwise an object whose
        map(specs, out_root, calibration_path, **options) calls `correct_input` with those
        keyword options and yields (spec, FileResult) in any order, e.g.
        `spherejax.cluster.DaskExecutor`. Paths reach it absolute: a worker may run elsewhere.
        When a stop is asked for (`spherejax.interrupt`) it stops submitting, yields the inputs
        already under way as they finish and raises `interrupt.Interrupted`.

    Raises (before anything is written):
      CalibrationFileError: a calibration that cannot be read.
      BatchError: OUT is not a folder, holds a manifest and resume is False, or is locked.
      NoInputError (a BatchError): the inputs hold no cube, band files or session (OUT is not
        created). Inputs that are all done already are not that: --resume skips them.
    Raises (inside `interrupt.stop_requests()`, on SIGINT or SIGTERM):
      interrupt.Interrupted: at the next safe point, with `done` (inputs finished, skipped or
        failed) and `total`; the input under way has left nothing in OUT, the lock is released,
        the manifest records every input finished.
    """
    # Absolute: workers started in other folders read and write these paths themselves.
    out_root = pathlib.Path(os.path.abspath(out_root))
    calibration_path = pathlib.Path(os.path.abspath(calibration_path))
    if exr_compression not in io.EXR_COMPRESSIONS:
        raise ValueError(f"exr_compression: expected one of {list(io.EXR_COMPRESSIONS)}, got {exr_compression!r}")
    if output_format not in OUTPUT_FORMATS:
        raise ValueError(f"output_format: expected one of {list(OUTPUT_FORMATS)}, got {output_format!r}")
    calibration = load_calibration(calibration_path, illuminant)
    header = calibration.header
    settings = output_settings(calibration, output_format, exr_compression)
    if out_root.exists() and not out_root.is_dir():
        raise BatchError(out_root, "is not a folder", "an output folder (OUT)")
    if not resume and (out_root / MANIFEST_NAME).exists():
        raise BatchError(
            out_root, f"already holds a batch ({MANIFEST_NAME})",
            "--resume to continue it, or a new OUT",
        )
    specs = discover_inputs(inputs, out_root, warn=on_warning)
    if not specs:  # refused before OUT (or its lock) is created: a typo in INPUT leaves nothing
        raise _no_input_error(inputs)
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise BatchError(out_root, f"cannot be created: {error.strerror}", "a writable OUT") from None

    lock = OutputLock(out_root)
    lock.acquire()
    summary = BatchSummary(taken_over=lock.taken_over)
    ended = False
    try:
        _remove_temporaries(out_root)
        last, recorded = _manifest_state(out_root)  # one read of the manifest, streamed
        done = last if resume else {}
        specs = _claim_outputs(specs, out_root, calibration_path, output_format, recorded | lock.claimed)
        manifest = Manifest(out_root)
        try:
            if on_start is not None:
                on_start(specs)
            try:
                pending = []
                for spec in specs:
                    interrupt.check()  # verifying what is done reads every output: a while
                    if resume and is_done(done.get(spec.name), spec, out_root, header["checksum"], output_format, settings):
                        summary.skipped += 1
                        if on_result is not None:
                            on_result(spec, None)
                        continue
                    pending.append(spec)
                lock.claim(f"{spec.name}.{kind}" for spec in pending if spec.problem is None
                           for kind in OUTPUT_KINDS_BY_FORMAT[output_format])
                options = {"illuminant": illuminant, "exr_compression": exr_compression, "output_format": output_format}
                if executor is None:
                    results = _in_process(pending, out_root, calibration_path, options)
                else:
                    results = executor.map(pending, out_root, calibration_path, **options)
                # The manifest is written here, by the one process that holds the lock, whoever
                # corrected the input; an input is recorded only once its outputs are complete.
                for spec, result in results:
                    manifest.append(result.to_json())
                    if result.status == "done":
                        summary.corrected += 1
                    else:
                        summary.failed.append(result)
                    if on_result is not None:
                        on_result(spec, result)
            except interrupt.Interrupted as stopped:
                stopped.done = summary.corrected + summary.skipped + len(summary.failed)
                stopped.total = len(specs)
                raise
            ended = True
        finally:
            manifest.close()
    except interrupt.Interrupted:
        ended = True  # a clean stop: every input is recorded or has left nothing
        raise
    finally:
        # A run that ended removes its lock file, claims and all; after any other error the
        # claims stay for the next run (as after a kill): outputs may be in place unrecorded.
        lock.release(keep_claims=not ended)
    return summary


def _claim_outputs(specs: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path,
                   output_format: str, owned: set[str]) -> list[InputSpec]:
    """Check, before any work, that no output can touch a file spherejax does not own, and give
    each input the files of OUT it may remove (`InputSpec.owned`).

    Refused (BatchError, one line naming the file):
    - an output that is an input of the batch or the calibration, however named (resolved path,
      or (st_dev, st_ino) where it exists: `OUT` being the inputs' folder made a.tif's Lab output
      replace the input a.lab.exr);
    - an output name where a file already is that neither OUT's manifest nor the claims of a
      killed run record (`owned`, `OutputLock.claimed`): a file spherejax did not write is the user's, never replaced
      and never removed. One exception, for a manifest whose last record was torn by a kill
      (which leaves the outputs in place unrecorded): in an OUT that holds a manifest, the
      outputs of an input whose reflectance output names that very input as its source
      (spherejax:source, `_written_for`) are taken as spherejax's.
    Files of the other format at an input's names are left alone unless the manifest records them.
    """
    has_manifest = os.path.lexists(out_root / MANIFEST_NAME)
    owned = set(owned)
    protected: dict = {}
    for spec in specs:
        for file in spec.files:
            protected[os.path.realpath(file)] = spec.source
            with contextlib.suppress(OSError):
                protected[_identity(os.stat(file))] = spec.source
    protected[os.path.realpath(calibration_path)] = f"the calibration ({calibration_path})"
    with contextlib.suppress(OSError):
        protected[_identity(os.stat(calibration_path))] = f"the calibration ({calibration_path})"
    in_the_way = []
    claimed = []
    for spec in specs:
        if spec.problem is None:
            for kind in OUTPUT_KINDS_BY_FORMAT[output_format]:
                relative = f"{spec.name}.{kind}"
                path = out_root / relative
                other = protected.get(os.path.realpath(path))
                if other is None:
                    with contextlib.suppress(OSError):
                        other = protected.get(_identity(os.stat(path)))
                if other is not None:
                    raise BatchError(
                        path, f"is the output {relative} of {spec.source}, and also the input {other}",
                        "an OUT whose outputs are no inputs: choose another OUT",
                    )
                if os.path.lexists(path) and relative not in owned:
                    if not (has_manifest and _written_for(out_root, spec)):
                        in_the_way.append(path)
                    else:
                        owned.add(relative)
        mine = tuple(f"{spec.name}.{kind}" for kind in _ALL_OUTPUT_KINDS if f"{spec.name}.{kind}" in owned)
        claimed.append(dataclasses.replace(spec, owned=mine) if mine else spec)
    if in_the_way:
        more = f" (and {len(in_the_way) - 1} more)" if len(in_the_way) > 1 else ""
        raise BatchError(
            in_the_way[0],
            f"is in the way of an output{more}: OUT's manifest does not record it as written by spherejax, "
            "so it is not replaced",
            "no file at an output's name but spherejax's own: move it, or choose another OUT",
        )
    return claimed


def _written_for(out_root: pathlib.Path, spec: InputSpec) -> bool:
    """Whether `spec`'s reflectance output in OUT (EXR or ENVI) says spherejax wrote it from this
    input: its spherejax:source attribute (header field "spherejax source") is `spec.source`."""
    import OpenImageIO as oiio

    base = out_root / spec.name
    exr = base.parent / f"{base.name}.reflectance.exr"
    with contextlib.suppress(OSError):
        os.close(io.open_regular(exr, os.O_RDONLY))  # a FIFO or a link there: not ours, at once
        image = oiio.ImageInput.open(str(exr))
        if image is not None:
            try:
                return image.spec().get_string_attribute("spherejax:source") == spec.source
            finally:
                image.close()
    header = base.parent / f"{base.name}.reflectance.hdr"
    with contextlib.suppress(OSError):
        fd = io.open_regular(header, os.O_RDONLY)
        with open(fd, "rb") as handle:
            text = handle.read(1 << 16).decode("utf-8", errors="replace")
        wanted = f"spherejax source = {envi._header_value(spec.source)}"
        return any(line.strip() == wanted for line in text.splitlines())
    return False


def _in_process(pending: list[InputSpec], out_root: pathlib.Path, calibration_path: pathlib.Path, options: dict):
    """(spec, FileResult) of each input corrected in this process, stopping at the safe point
    before each input when a stop is asked for (`correct_input` has its own, inside)."""
    for spec in pending:
        interrupt.check()
        yield spec, correct_input(spec, out_root, calibration_path, **options)


__all__ = [
    "MANIFEST_NAME",
    "LOCK_NAME",
    "OUTPUT_FORMATS",
    "OUTPUT_KINDS",
    "OUTPUT_KINDS_BY_FORMAT",
    "PREVIEW_BAD_PIXEL",
    "BatchError",
    "NoInputError",
    "InputSpec",
    "FileResult",
    "BatchSummary",
    "discover_inputs",
    "correct_input",
    "failed_result",
    "load_calibration",
    "input_checksum",
    "srgb_preview",
    "read_manifest",
    "recorded_outputs",
    "output_settings",
    "is_done",
    "run_batch",
]
