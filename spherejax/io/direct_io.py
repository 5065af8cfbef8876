"""Writing a large new file past the page cache (O_DIRECT), where the system allows it.

Why. Every output spherejax writes is fsynced before it is renamed into place (`atomic_files`), so
the page cache buys it nothing: the bytes must reach the disk before the commit anyway. What a
buffered write costs instead is the kernel's copy of every byte into the page cache, which on
the 2-core VM spherejax is measured on took 0.22-0.27 s of system time for the 130 MB of one
megapixel's reflectance (about 0.5 GB/s, against 0.08 s for the same bytes written with
O_DIRECT, whose final fsync then has nothing left to wait for: benchmarks/README.md, "Archive
throughput"). In a batch that copy competes for the same two cores as decoding and correcting
the next input.

How. `DirectFile` copies what it is given into a page-aligned staging buffer (O_DIRECT wants the
memory, the length and the file offset aligned to the device's logical block, 512 or 4096
bytes; `ALIGNMENT` covers both) and writes that buffer whenever it is full. The last partial
block goes through the page cache (O_DIRECT cleared with fcntl), and `finish` fsyncs: the file
holds exactly the bytes written, as a buffered file would.

Where O_DIRECT is not available (not Linux, or a file system that refuses it: tmpfs before
Linux 6.6, some FUSE and network file systems, which fcntl answers with EINVAL), or where a
direct write is refused (EINVAL: a device with larger blocks than `ALIGNMENT`), the file is
written through the page cache from there on, the same bytes in the same place. Writing never
depends on O_DIRECT working; only its speed does.
"""

from __future__ import annotations

import contextlib
import errno
import mmap
import os

#: Alignment of the staging buffer, of each direct write's length and of its file offset: the
#: logical block of nearly every disk (512 or 4096 bytes); a device that needs more refuses the
#: write with EINVAL, and the file goes on through the page cache.
ALIGNMENT = 4096

#: Staging buffer: 8 MiB, written in one call (a megapixel of reflectance is 16 such writes,
#: each long enough for the disk to stream; small enough to be nothing beside the strips).
STAGING_BYTES = 8 << 20

#: O_DIRECT where the platform has it (Linux), else 0: no direct I/O is attempted.
_O_DIRECT = getattr(os, "O_DIRECT", 0)


def _set_direct(descriptor: int, on: bool) -> bool:
    """Switch O_DIRECT on `descriptor` on or off; False where the system refuses to."""
    if not _O_DIRECT:
        return False
    import fcntl

    try:
        flags = fcntl.fcntl(descriptor, fcntl.F_GETFL)
        fcntl.fcntl(descriptor, fcntl.F_SETFL, (flags | _O_DIRECT) if on else (flags & ~_O_DIRECT))
    except OSError:
        return False
    return True


class DirectFile:
    """Sequential writes into a file opened for writing (descriptor `descriptor`, positioned at
    its start, owned by the caller, who closes it), past the page cache where it can be.

    `write` takes any bytes-like object (a NumPy array's memoryview, say) and copies it into the
    staging buffer; `finish` writes what is left and fsyncs. Errors from the system (a full disk:
    ENOSPC or EFBIG) are raised as OSError from `write` or `finish`.
    """

    def __init__(self, descriptor: int, *, staging_bytes: int = STAGING_BYTES):
        if staging_bytes <= 0 or staging_bytes % ALIGNMENT:
            raise ValueError(f"staging_bytes: expected a positive multiple of {ALIGNMENT}, got {staging_bytes}")
        self._descriptor = descriptor
        # An anonymous map is page-aligned, and pages are a multiple of ALIGNMENT on every
        # system that has O_DIRECT.
        self._staging = mmap.mmap(-1, staging_bytes)
        self._view = memoryview(self._staging)
        self._staged = 0
        self.direct = _set_direct(descriptor, True)

    def write(self, data) -> None:
        """Append `data` (bytes-like) to the file."""
        source = memoryview(data).cast("B")
        size = len(self._view)
        while len(source):
            taken = min(len(source), size - self._staged)
            self._view[self._staged:self._staged + taken] = source[:taken]
            self._staged += taken
            source = source[taken:]
            if self._staged == size:
                self._write_out(self._view[:size])
                self._staged = 0

    def finish(self) -> None:
        """Write what is staged and fsync: the file then holds every byte written, on disk."""
        whole = self._staged - self._staged % ALIGNMENT
        if whole:
            self._write_out(self._view[:whole])
        if self._staged > whole:
            # The last partial block through the page cache: O_DIRECT cannot write a length
            # that is not a whole block (padding and truncating would be the other way).
            if self.direct:
                self.direct = not _set_direct(self._descriptor, False)
            self._write_out(self._view[whole:self._staged])
        self._staged = 0
        os.fsync(self._descriptor)
        self.release()

    def release(self) -> None:
        """Free the staging buffer (done by `finish`; call it when abandoning the file)."""
        view, staging, self._view, self._staging = self._view, self._staging, None, None
        if staging is None:
            return
        # After a failed write the error's traceback may still hold a slice of the buffer: then
        # it is freed with the traceback instead of here (closing it would raise BufferError).
        with contextlib.suppress(BufferError):
            view.release()
            staging.close()

    def _write_out(self, block: memoryview) -> None:
        """Write all of `block` at the file's position, falling back to the page cache for good
        if a direct write is refused (EINVAL) or comes back short (the rest would be unaligned)."""
        while len(block):
            try:
                written = os.write(self._descriptor, block)
            except OSError as error:
                if error.errno != errno.EINVAL or not self.direct:
                    raise
                # Refused as a direct write (alignment the device does not take): the same
                # bytes, at the same offset, through the page cache.
                self.direct = False
                if not _set_direct(self._descriptor, False):
                    raise
                continue
            block = block[written:]
            if len(block) and self.direct:
                self.direct = not _set_direct(self._descriptor, False)


__all__ = ["ALIGNMENT", "DirectFile", "STAGING_BYTES"]
