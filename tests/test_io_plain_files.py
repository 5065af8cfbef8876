"""io.plain_files: the files spherejax keeps for itself open without waiting and read without
holding more than a line in memory."""

from __future__ import annotations

import errno
import os

import pytest

from spherejax import io


def test_a_regular_file_opens_for_each_use(tmp_path):
    path = tmp_path / "manifest.jsonl"
    for flags in (os.O_WRONLY | os.O_APPEND | os.O_CREAT, os.O_RDWR, os.O_RDONLY):
        os.close(io.open_regular(path, flags))
    assert path.is_file()


@pytest.mark.parametrize("flags", [os.O_RDONLY, os.O_WRONLY | os.O_APPEND | os.O_CREAT, os.O_RDWR | os.O_CREAT],
                         ids=["read", "append", "read-write"])
def test_a_fifo_is_refused_at_once_for_every_use(tmp_path, flags):
    """Opening a FIFO waits for the other end (for writing: a reader; a read of one opened
    read-write: a writer): `correct` waited forever on a FIFO lock, `--resume` on a FIFO
    manifest. A blocking open would hang this test, not fail it: pytest would be stopped by
    CI's time limit, so each call is also made in a thread with a deadline."""
    import threading

    os.mkfifo(tmp_path / "lock")
    outcome = []

    def attempt():
        try:
            io.open_regular(tmp_path / "lock", flags)
            outcome.append("opened")
        except OSError as error:
            outcome.append(error)

    thread = threading.Thread(target=attempt, daemon=True)
    thread.start()
    thread.join(timeout=10)
    assert outcome, "open_regular blocked on a FIFO"
    error = outcome[0]
    assert isinstance(error, OSError) and error.strerror == "it is a FIFO", error
    assert error.errno in (errno.ENXIO, errno.EINVAL)


def test_a_symbolic_link_or_a_folder_is_refused(tmp_path):
    (tmp_path / "target").write_text("x")
    (tmp_path / "link").symlink_to(tmp_path / "target")
    with pytest.raises(OSError) as raised:
        io.open_regular(tmp_path / "link", os.O_RDONLY)
    assert raised.value.errno == errno.ELOOP
    (tmp_path / "folder").mkdir()
    with pytest.raises(OSError, match="it is a folder"):
        io.open_regular(tmp_path / "folder", os.O_RDONLY)


def test_lines_are_read_in_chunks_and_an_overlong_line_is_skipped_whole(tmp_path):
    path = tmp_path / "manifest.jsonl"
    path.write_bytes(b"first\n" + b"x" * 100 + b"\nsecond\n" + b"y" * 45 + b"\nlast")
    lines = list(io.read_lines(path, max_line_bytes=40, chunk_bytes=7))
    assert lines == [b"first", b"second", b"last"]
    assert list(io.read_lines(path, max_line_bytes=1000, chunk_bytes=3)) == path.read_bytes().split(b"\n")


def test_a_sparse_gigabyte_without_a_newline_is_read_in_bounded_memory(tmp_path):
    """`truncate -s 3G OUT/manifest.jsonl` made `--resume` hold 4.3 GB: the file was read whole.
    Here 1 GiB of zeros after a record: the record comes back, the zeros are skipped, and the
    reader never holds much more than a chunk and a line."""
    import tracemalloc

    path = tmp_path / "manifest.jsonl"
    path.write_bytes(b'{"name": "a"}\n')
    os.truncate(path, 1 << 30)
    tracemalloc.start()
    try:
        lines = list(io.read_lines(path))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert lines == [b'{"name": "a"}']
    assert peak < 8 * io.plain_files.MAX_LINE_BYTES, peak
