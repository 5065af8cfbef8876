"""spherejax.io.direct_io: large outputs written past the page cache where the system allows it,
the same bytes through the page cache where it does not, and a full disk reported as for any
write."""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os

import numpy as np
import pytest

from spherejax import archive, io
from spherejax.io import direct_io, envi
from tests.batch_support import NAMES, frame
from tests.robustness.catalogue import run_child, snapshot


def _system_takes_o_direct(folder) -> bool:
    """Whether this folder's file system lets a descriptor switch to O_DIRECT (asked here,
    independently of the module)."""
    probe = folder / "probe"
    descriptor = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        flags = fcntl.fcntl(descriptor, fcntl.F_GETFL)
        fcntl.fcntl(descriptor, fcntl.F_SETFL, flags | os.O_DIRECT)
        return True
    except OSError:
        return False
    finally:
        os.close(descriptor)
        probe.unlink()


def _write(path, chunks, **kwargs) -> direct_io.DirectFile:
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        out = direct_io.DirectFile(descriptor, **kwargs)
        direct = out.direct
        for chunk in chunks:
            out.write(chunk)
        out.finish()
    finally:
        os.close(descriptor)
    out.direct_at_start = direct
    return out


# Sizes around the alignment and the staging buffer (two blocks here), in chunks that cross both.
SIZES = [0, 1, 4095, 4096, 4097, 8192, 8193, 3 * 8192 + 5, 100_003]


@pytest.mark.parametrize("size", SIZES)
def test_the_file_holds_exactly_the_bytes_written(tmp_path, size):
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    chunks = [data[i:i + 3001] for i in range(0, size, 3001)]
    out = _write(tmp_path / "f", chunks, staging_bytes=2 * direct_io.ALIGNMENT)
    assert (tmp_path / "f").read_bytes() == data
    # Direct I/O is used exactly where the file system takes it.
    assert out.direct_at_start == _system_takes_o_direct(tmp_path)


def test_a_numpy_array_is_written_as_its_bytes(tmp_path):
    values = np.random.default_rng(1).uniform(0, 1, (37, 11, 31)).astype("<f4")
    _write(tmp_path / "f", [memoryview(values[:20]).cast("B"), values[20:]], staging_bytes=direct_io.ALIGNMENT)
    np.testing.assert_array_equal(np.fromfile(tmp_path / "f", "<f4").reshape(values.shape), values)


def test_a_file_system_without_o_direct_gets_the_same_bytes_through_the_page_cache(tmp_path, monkeypatch):
    data = bytes(range(256)) * 97
    real_fcntl = fcntl.fcntl

    def refuses_o_direct(descriptor, command, *args):
        if command == fcntl.F_SETFL and args and args[0] & os.O_DIRECT:
            raise OSError(errno.EINVAL, "Invalid argument")  # as tmpfs before Linux 6.6
        return real_fcntl(descriptor, command, *args)

    monkeypatch.setattr(fcntl, "fcntl", refuses_o_direct)
    out = _write(tmp_path / "f", [data], staging_bytes=direct_io.ALIGNMENT)
    assert out.direct_at_start is False and out.direct is False
    assert (tmp_path / "f").read_bytes() == data


def test_a_refused_direct_write_is_written_again_through_the_page_cache(tmp_path, monkeypatch):
    """A device whose blocks are larger than ALIGNMENT answers a direct write with EINVAL: that
    block and every later one go through the page cache, nothing lost or doubled. The O_DIRECT
    flag is kept by a stand-in for fcntl (the real file stays buffered), so that the test does
    not depend on this file system taking O_DIRECT."""
    data = np.random.default_rng(2).integers(0, 256, 5 * direct_io.ALIGNMENT + 77, dtype=np.uint8).tobytes()
    real_fcntl, real_write = fcntl.fcntl, os.write
    direct_flag = {}
    refused = []

    def fcntl_keeping_o_direct(descriptor, command, *args):
        if command == fcntl.F_SETFL:
            direct_flag[descriptor] = bool(args[0] & os.O_DIRECT)
            return real_fcntl(descriptor, command, args[0] & ~os.O_DIRECT)
        flags = real_fcntl(descriptor, command, *args)
        return flags | os.O_DIRECT if command == fcntl.F_GETFL and direct_flag.get(descriptor) else flags

    def refuses_direct_writes(descriptor, block):
        if direct_flag.get(descriptor):
            refused.append(len(block))
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_write(descriptor, block)

    monkeypatch.setattr(fcntl, "fcntl", fcntl_keeping_o_direct)
    monkeypatch.setattr(os, "write", refuses_direct_writes)
    out = _write(tmp_path / "f", [data], staging_bytes=2 * direct_io.ALIGNMENT)
    assert out.direct_at_start is True
    assert refused == [2 * direct_io.ALIGNMENT] and out.direct is False
    assert (tmp_path / "f").read_bytes() == data


def test_a_short_direct_write_goes_on_through_the_page_cache(tmp_path, monkeypatch):
    """A write that comes back short (a file-size limit, a signal) would leave the next direct
    write unaligned: the rest goes through the page cache, nothing lost or doubled."""
    data = np.random.default_rng(3).integers(0, 256, 6 * direct_io.ALIGNMENT, dtype=np.uint8).tobytes()
    real_write = os.write
    calls = []

    def short_first(descriptor, block):
        calls.append(len(block))
        return real_write(descriptor, block[:direct_io.ALIGNMENT] if len(calls) == 1 else block)

    monkeypatch.setattr(os, "write", short_first)
    out = _write(tmp_path / "f", [data], staging_bytes=4 * direct_io.ALIGNMENT)
    assert (tmp_path / "f").read_bytes() == data
    assert calls[:2] == [4 * direct_io.ALIGNMENT, 3 * direct_io.ALIGNMENT]
    assert out.direct is False


def test_the_staging_buffer_must_be_whole_blocks():
    with pytest.raises(ValueError, match="multiple of 4096"):
        direct_io.DirectFile(0, staging_bytes=5000)


def test_envi_pixels_and_their_digest_are_those_given_through_either_path(tmp_path, monkeypatch):
    """The ENVI writer's pixels (NaN as the data ignore value) and the digest it reports, with
    and without direct I/O, across strips of different heights (its reused buffer)."""
    rng = np.random.default_rng(4)
    pixels = rng.uniform(0, 1, (53, 29, 31)).astype(np.float32)
    pixels[rng.random(pixels.shape[:2]) < 0.1] = np.nan
    expected = np.where(np.isnan(pixels), np.float32(envi.IGNORE_VALUE), pixels).astype("<f4")

    def write(name):
        with envi.EnviWriter(tmp_path / f"{name}.hdr", pixels.shape, description="t", band_names=["b"] * 31) as writer:
            for row0, row1 in [(0, 20), (20, 40), (40, 53)]:
                writer.write_rows(row0, pixels[row0:row1])
            return writer.commit()

    direct = write("direct")
    monkeypatch.setattr(direct_io, "_O_DIRECT", 0)
    cached = write("cached")
    for name, digests in (("direct", direct), ("cached", cached)):
        data = (tmp_path / f"{name}.img").read_bytes()
        assert data == expected.tobytes()
        assert digests[tmp_path / f"{name}.img"] == hashlib.sha256(data).hexdigest()
    assert sorted(os.listdir(tmp_path)) == ["cached.hdr", "cached.img", "direct.hdr", "direct.img"]


@pytest.mark.parametrize("limit", [64 * 1024, 100_000])
def test_a_full_disk_in_a_direct_write_of_correct_envi_leaves_nothing(tmp_path, cal, limit):
    """correct --format envi under a file-size limit that stops the reflectance's direct write
    part way (aligned: a short write; unaligned: refused, then short through the page cache):
    one line naming the input, exit status 1, the failure in the manifest, no output or
    temporary file."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    io.write_frame(inputs / "a.tif", frame(np.random.default_rng(5)), channel_names=NAMES)
    before = snapshot(tmp_path)
    status, err = run_child(["correct", "-c", str(cal), str(inputs), "-o", str(tmp_path / "out"), "--format", "envi"], limit)
    assert status == 1 and "Traceback" not in err, err
    lines = [line for line in err.splitlines() if "a.tif" in line]
    assert lines and all("could not be written" in line and "File too large" in line for line in lines), err
    after = snapshot(tmp_path)
    assert set(after) - set(before) <= {"out", f"out/{archive.MANIFEST_NAME}"}, sorted(set(after) - set(before))
    assert [record["status"] for record in archive.read_manifest(tmp_path / "out").values()] == ["failed"]


def test_an_envi_image_whose_last_write_fails_leaves_nothing_open_or_on_disk(tmp_path, monkeypatch):
    """The data file's descriptor is closed and both temporary files go when the final write or
    fsync fails (a full disk at the end): before, the file object was dropped unclosed."""
    pixels = np.random.default_rng(6).uniform(0, 1, (4, 3, 31)).astype(np.float32)

    def no_room(descriptor):
        raise OSError(errno.ENOSPC, "No space left on device")

    with envi.EnviWriter(tmp_path / "a.hdr", pixels.shape, description="t", band_names=["b"] * 31) as writer:
        writer.write_rows(0, pixels)
        monkeypatch.setattr(os, "fsync", no_room)
        with pytest.raises(io.SpherejaxFileError, match=r"a\.hdr.*could not be written: No space left on device"):
            writer.commit()
    assert os.listdir(tmp_path) == []
