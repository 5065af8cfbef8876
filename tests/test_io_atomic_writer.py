"""`spherejax.io.atomic_writer.AtomicWriter`: the state machine every image writer shares.

Checked on the smallest writer (`Rows`: each row's bytes appended to one stream) and on a
two-file one (`Pair`: a header written by name at the end, as ENVI's is), then on the four real
writers: an abort leaves nothing, the commit renames only complete, fsynced files (in order, the
folder fsynced after), a failure mid-write leaves no temporary and no partial target, and an
existing target is never replaced by a half file.
"""

import errno
import hashlib
import os
import pathlib
import uuid

import numpy as np
import OpenImageIO as oiio
import pytest

from spherejax import atomic_files, io
from spherejax.io import atomic_writer, cubes, envi, exr_uncompressed, frames, quality_png

OLD = b"the earlier file, complete"


class Rows(atomic_writer.AtomicWriter):
    """Rows of bytes appended to one stream, nothing around them."""

    def _open(self):
        self._open_stream(self.path)

    def _write_rows(self, row0, rows):
        for row in rows:
            self._write(row)

    def _complete(self):
        return self._close_stream()


class Pair(atomic_writer.AtomicWriter):
    """N.img streamed and N.txt written whole by `_complete` (a library writing it by name), the
    data renamed first."""

    def __init__(self, path, height):
        self.data = pathlib.Path(path).with_suffix(".img")
        super().__init__(path, height, targets=[self.data, path])

    def _open(self):
        self._create(self.path)
        self._open_stream(self.data)

    def _write_rows(self, row0, rows):
        for row in rows:
            self._write(row)

    def _complete(self):
        digest = self._close_stream()
        self._temp.write_text(f"rows = {self.height}\n")
        with open(self._temp, "rb") as handle:
            os.fsync(handle.fileno())
        return digest


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_commit_puts_every_row_in_place_and_returns_the_digest(tmp_path):
    rows = [b"first row\n", b"second\n", b"\x00\xff third\n"]
    with Rows(tmp_path / "out.bin", 3) as writer:
        writer.write_rows(0, rows[:2])
        writer.write_rows(2, rows[2:])
        digest = writer.commit()
    assert (tmp_path / "out.bin").read_bytes() == b"".join(rows)
    assert digest == hashlib.sha256(b"".join(rows)).hexdigest()
    assert listing(tmp_path) == ["out.bin"]


def test_abort_leaves_nothing_and_the_target_as_it_was(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(OLD)
    writer = Rows(target, 2)
    assert listing(tmp_path) == [writer._temp.name, "out.bin"]  # the temporary name beside it
    assert atomic_files.is_temp_sibling(writer._temp.name, "out.bin")
    writer.write_rows(0, [b"new"])
    writer.abort()
    assert listing(tmp_path) == ["out.bin"] and target.read_bytes() == OLD
    with pytest.raises(io.SpherejaxFileError, match=r"out\.bin: is no longer open for writing"):
        writer.write_rows(1, [b"more"])
    with pytest.raises(io.SpherejaxFileError, match="is no longer open for writing"):
        writer.commit()
    # Leaving the block without committing is an abort, of both files of a pair too.
    with Pair(tmp_path / "p.txt", 1) as pair:
        pair.write_rows(0, [b"x"])
        assert len(listing(tmp_path)) == 3
    assert listing(tmp_path) == ["out.bin"]


def test_commit_renames_only_complete_fsynced_files_then_fsyncs_the_folder(tmp_path, monkeypatch):
    """At each rename the temporary file holds every byte and was fsynced, and the target still
    holds the old file: a reader sees one or the other, never a mixture."""
    (tmp_path / "p.img").write_bytes(OLD)
    (tmp_path / "p.txt").write_bytes(OLD)
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(descriptor):
        events.append(("fsync", os.path.isdir(f"/proc/self/fd/{descriptor}")))
        real_fsync(descriptor)

    def replace(source, destination):
        source, destination = pathlib.Path(source), pathlib.Path(destination)
        events.append(("rename", destination.name))
        assert destination.read_bytes() == OLD
        assert source.read_bytes() == {"p.img": b"abcdef", "p.txt": b"rows = 2\n"}[destination.name]
        real_replace(source, destination)

    with Pair(tmp_path / "p.txt", 2) as writer:
        writer.write_rows(0, [b"abc"])
        writer.write_rows(1, [b"def"])
        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "replace", replace)
        assert writer.commit() == hashlib.sha256(b"abcdef").hexdigest()
    # data, then the file written by name, both fsynced; then the renames in the targets' order; then the folder
    assert events == [("fsync", False), ("fsync", False), ("rename", "p.img"), ("rename", "p.txt"), ("fsync", True)]
    assert listing(tmp_path) == ["p.img", "p.txt"]
    assert (tmp_path / "p.img").read_bytes() == b"abcdef" and (tmp_path / "p.txt").read_text() == "rows = 2\n"


def test_a_failed_write_mid_image_leaves_no_temporary_and_the_target_as_it_was(tmp_path, monkeypatch):
    """The disk fills while the rows are streamed (the 8 MiB staging buffer's first write out):
    one error naming the target, never the temporary name, and the writer closed."""
    target = tmp_path / "big.bin"
    target.write_bytes(OLD)
    real_write = os.write

    def no_room(descriptor, block):
        if len(block) >= 1 << 20:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(descriptor, block)

    monkeypatch.setattr(os, "write", no_room)
    row = np.full(1 << 20, 7, np.uint8)
    with Rows(target, 16) as writer:
        with pytest.raises(io.SpherejaxFileError) as raised:
            for row0 in range(16):
                writer.write_rows(row0, [row])
        assert str(raised.value) == f"{target}: could not be written: No space left on device"
        assert 0 < writer._next_row < 16  # it failed part way
        with pytest.raises(io.SpherejaxFileError, match="is no longer open for writing"):
            writer.write_rows(writer._next_row, [row])
    assert listing(tmp_path) == ["big.bin"] and target.read_bytes() == OLD


def test_a_failure_in_the_commit_or_missing_rows_never_replace_the_target(tmp_path, monkeypatch):
    target = tmp_path / "p.txt"
    target.write_bytes(OLD)
    with Pair(target, 3) as writer:
        writer.write_rows(0, [b"a", b"b"])
        with pytest.raises(io.SpherejaxFileError, match=r"p\.txt: has 2 of its 3 rows \(expected every row written\)"):
            writer.commit()
    assert listing(tmp_path) == ["p.txt"] and target.read_bytes() == OLD

    with Pair(target, 1) as writer:
        writer.write_rows(0, [b"a"])
        monkeypatch.setattr(os, "fsync", _no_room)
        with pytest.raises(io.SpherejaxFileError, match=r"p\.txt: could not be written: No space left on device"):
            writer.commit()
    assert listing(tmp_path) == ["p.txt"] and target.read_bytes() == OLD


def test_rows_out_of_order_are_refused_and_the_writer_stays_open(tmp_path):
    with Rows(tmp_path / "out.bin", 2) as writer:
        with pytest.raises(ValueError, match="rows: expected the next row 0, got 1"):
            writer.write_rows(1, [b"b"])
        writer.write_rows(0, [b"a"])
        writer.write_rows(1, [b"b"])
        writer.commit()
    assert (tmp_path / "out.bin").read_bytes() == b"ab"


def test_a_temporary_name_already_taken_is_not_the_writers_to_remove(tmp_path, monkeypatch):
    """The data's temporary name is taken (the header's was created first): the writer removes
    the file it made, never the one it found."""
    fixed = uuid.UUID(int=0xABC)
    monkeypatch.setattr(uuid, "uuid4", lambda: fixed)
    planted = atomic_files.temp_sibling(tmp_path / "p.img")
    planted.write_bytes(b"someone else's")
    with pytest.raises(io.SpherejaxFileError, match=r"p\.txt: could not be written: File exists"):
        Pair(tmp_path / "p.txt", 1)
    assert listing(tmp_path) == [planted.name] and planted.read_bytes() == b"someone else's"


# -- the real writers


def _no_room(descriptor):
    raise OSError(errno.ENOSPC, "No space left on device")


def _tiff(path):
    spec = oiio.ImageSpec(5, 4, 3, oiio.UINT16)
    return frames.AtomicImageWriter(path, spec, "tiff"), np.arange(60, dtype=np.uint16).reshape(4, 5, 3)


def _png(path):
    return quality_png.QualityPngWriter(path, (4, 5)), np.arange(20, dtype=np.uint8).reshape(4, 5)


def _exr(path):
    writer = cubes.open_exr(path, (4, 5, 3), channel_names=["L*", "a*", "b*"], compression="none")
    assert isinstance(writer, exr_uncompressed.UncompressedExrWriter)
    return writer, np.linspace(0, 1, 60, dtype=np.float32).reshape(4, 5, 3)


def _envi(path):
    writer = envi.EnviWriter(path, (4, 5, 3), description="t", band_names=["a", "b", "c"])
    return writer, np.linspace(0, 1, 60, dtype=np.float32).reshape(4, 5, 3)


WRITERS = {"a.tif": _tiff, "a.png": _png, "a.exr": _exr, "a.hdr": _envi}


@pytest.mark.parametrize("name", WRITERS)
def test_every_image_writer_is_one_and_keeps_an_existing_file_on_any_failure(tmp_path, monkeypatch, name):
    targets = [tmp_path / name] + ([tmp_path / "a.img"] if name == "a.hdr" else [])
    for target in targets:
        target.write_bytes(OLD)
    writer, pixels = WRITERS[name](tmp_path / name)
    assert isinstance(writer, atomic_writer.AtomicWriter)
    with writer:  # a strip short
        writer.write_rows(0, pixels[:3])
        with pytest.raises(io.SpherejaxFileError, match="has 3 of its 4 rows"):
            writer.commit()
    writer, pixels = WRITERS[name](tmp_path / name)
    with writer:  # every row, then the disk full at the last fsync
        writer.write_rows(0, pixels[:1])
        writer.write_rows(1, pixels[1:])
        with monkeypatch.context() as patch:
            patch.setattr(os, "fsync", _no_room)
            with pytest.raises(io.SpherejaxFileError, match=rf"{name}: could not be written: No space left on device"):
                writer.commit()
    writer, pixels = WRITERS[name](tmp_path / name)
    with writer:  # never committed
        writer.write_rows(0, pixels)
    assert listing(tmp_path) == sorted(t.name for t in targets)
    assert all(target.read_bytes() == OLD for target in targets)
    writer, pixels = WRITERS[name](tmp_path / name)
    with writer:
        writer.write_rows(0, pixels)
        digests = writer.commit()
    assert listing(tmp_path) == sorted(t.name for t in targets)
    digests = digests if isinstance(digests, dict) else {tmp_path / name: digests}
    assert digests == {target: hashlib.sha256(target.read_bytes()).hexdigest() for target in targets}
