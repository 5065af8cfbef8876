"""One batch, one calibration: the calibration a batch read, and the proof that every input of the
batch was corrected with it.

`run_batch` reads the calibration file once, at its start, and keeps what says which file that was
(`CalibrationIdentity`: the checksum in its header, verified against its contents when it was
opened, and the file's inode, size and modification time). Every input's unit of work,
`correct_input`, wherever it runs (a thread of the batch's process, a dask worker on this machine
or another), is given that identity and proves against it, twice, that what it corrects with is
the batch's calibration:

- before it reads anything: the file at the calibration's path is still the one the batch read
  (`check_file`), and the calibration it opened carries the batch's checksum (`check_opened`);
- once every strip is corrected and before any output goes into place (`check_file` again): a
  calibration read by rows during the input (a large one stays on disk, `io.CalibrationFile.rows`)
  was the batch's for every row read.

A calibration file replaced (`spherejax calibrate --force`, or any rename over it: a new inode),
rewritten in place (a new modification time or size) or removed while the batch runs raises
`CalibrationChangedError` there. It is a stop, not an input's failure: the input under way leaves
nothing (as on SIGINT), no input is started after it, the inputs already finished are recorded,
and the batch ends with one line naming the calibration file (exit status 2 on the command line).
A manifest therefore never holds two calibrations' checksums from one run, and `--resume` with the
new calibration redoes every input the old one corrected (`manifest.is_done` compares checksums).

Why the inode, size and time, and not the checksum alone: hashing a large calibration again for
every input would cost more than correcting it, and a rename over the file is what a rewrite by
spherejax (or most tools) looks like. The device number is left out: a worker on another machine
sees a network file system under another device number, but the same inode, size and time.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

from .. import io
from .errors import BatchError


class CalibrationChangedError(BatchError):
    """The calibration file changed while a batch ran (module docstring): the batch stopped."""

    def __init__(self, path, problem: str, expected: str | None = None):
        super().__init__(
            path, problem,
            expected or "the calibration file left unchanged until the batch ends; the inputs finished before "
                        "are recorded: run again with --resume",
        )


@dataclasses.dataclass(frozen=True)
class CalibrationIdentity:
    """Which calibration file a batch read: its header's checksum and the file's (inode, size,
    modification time in ns) when it was read. Picklable: it travels to dask workers."""

    checksum: str
    stamp: tuple[int, int, int]

    def check_file(self, path) -> None:
        """Raise `CalibrationChangedError` unless `path` is still the file the batch read."""
        changed = self.change_of(path)
        if changed is not None:
            raise changed

    def change_of(self, path) -> CalibrationChangedError | None:
        """The `CalibrationChangedError` to raise if `path` is no longer the file the batch read,
        else None."""
        now = file_stamp(path)
        if now is None:
            return CalibrationChangedError(path, "changed during the batch: it is no longer there")
        if now != self.stamp:
            return CalibrationChangedError(
                path, "changed during the batch: another file is there now, or the same one rewritten (its inode, "
                      "size or modification time are not those the batch read)",
            )
        return None

    def check_opened(self, path, calibration: io.CalibrationFile) -> None:
        """Raise `CalibrationChangedError` unless `calibration` (opened from `path`) is the batch's."""
        checksum = calibration.header["checksum"]
        if checksum != self.checksum:
            raise CalibrationChangedError(
                path, f"changed during the batch: its checksum is {checksum}, the batch read {self.checksum}",
            )


def file_stamp(path) -> tuple[int, int, int] | None:
    """(inode, size, modification time in ns) of the file at `path` (links followed), or None when
    there is none."""
    try:
        info = os.stat(path)
    except OSError:
        return None
    return info.st_ino, info.st_size, info.st_mtime_ns


def read_once(path: pathlib.Path, illuminant: str | None, load) -> tuple[io.CalibrationFile, CalibrationIdentity]:
    """The batch's one read of its calibration: (the open calibration, its identity). `load` is
    `inputs.load_calibration`. The file's stamp is taken before it is opened and compared after:
    a file replaced while it was being read is refused at once, as a change."""
    before = file_stamp(path)
    calibration = load(path, illuminant)  # CalibrationFileError: missing, damaged, ...
    identity = CalibrationIdentity(calibration.header["checksum"], before)
    identity.check_file(path)
    return calibration, identity


def open_for_input(path, illuminant: str | None, identity: CalibrationIdentity | None, load):
    """The calibration an input is corrected with, and the identity it must keep until its outputs
    go into place. With the batch's `identity`: the file must still be the one the batch read and
    carry its checksum (`CalibrationChangedError` otherwise; a file that no longer opens at all
    changed too). Without (an input corrected on its own, `correct_input` called directly): the
    file as found now, held to that until the input's outputs go into place."""
    if identity is None:
        before = file_stamp(path)
        calibration = load(path, illuminant)
        return calibration, CalibrationIdentity(calibration.header["checksum"], before)
    identity.check_file(path)
    try:
        calibration = load(path, illuminant)
    except io.CalibrationFileError as error:  # it was whole when the batch read it
        raise CalibrationChangedError(path, f"changed during the batch: {error.problem}") from None
    identity.check_opened(path, calibration)
    return calibration, identity


__all__ = ["CalibrationChangedError", "CalibrationIdentity", "file_stamp", "open_for_input", "read_once"]
