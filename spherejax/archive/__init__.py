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
searched already nor above the folder searched) are followed like any folder.

Output names
------------
Names mirror the inputs relative to the deepest folder that holds all of them (the common folder
of the inputs' parent folders, so an input's own name is kept): ``batch/a.tif`` -> ``OUT/batch/a``,
a session ``s`` -> ``OUT/s/frames/<id>``, band files ``x/a_400nm.tif``... -> ``OUT/x/a`` (no
prefix: ``OUT/x``). For each input name N:

    N.reflectance.exr  float32 (or half float, --reflectance-type half) in the spectral layout of
                       Fichet et al. (2021) (`io.spectral_layout`):
                       channels "T.400nm".."T.700nm" (31), spectralLayoutVersion "1.0";
                       attributes spherejax:calibration_checksum, spherejax:software_version,
                       spherejax:source (the input relative to that common folder),
                       spherejax:input_sha256, spherejax:illuminant, spherejax:output_set
                       (the same in every output of the input, the PNGs' tEXt included:
                       `open_corrected` refuses files side by side from two corrections)
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

The EXRs are uncompressed unless `exr_compression` says "piz" or "zip" (lossless; `io.cubes`'s
EXR_COMPRESSIONS gives the measurements behind the default). `reflectance_type="half"` stores the
reflectance as OpenEXR half floats, each the float32 value rounded to nearest: within 4.9e-4 of
every reflectance factor between 0 and 1.03 (the half spacing there, 2^-11), at most 0.041 ΔE00
(99th percentile 0.012) on two synthetic 1-megapixel cubes (benchmarks/README.md); Lab stays
float32 (half floats would round L* near 100 to 1/16).

Throughput
----------
In process, two inputs are under way at once, each corrected whole by `correct_input` in a thread
of its own (`batch._in_process`): one input's outputs are encoded, hashed and fsynced while the
next is hashed, decoded and corrected, so both cores of a 2-core machine work. The steps that take
the time release Python's GIL (OpenImageIO's reads and writes, hashlib, zlib, the correction,
fsync). OpenImageIO's and OpenEXR's own thread pools are left at their default, one thread per
core: with one OpenEXR thread the two inputs' PIZ writes queue on it (measured). Results, the
manifest's lines, stops and failures are as for one input at a time. `stage_times` says where an
input's time goes when asked (`benchmarks/bench_archive.py`).

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
Before anything is created, every path given must lead to something, and OUT must lie apart
from the inputs: not a path given, a session's folder or an input's file, not inside one and
holding none (`discovery.refuse_out_among_inputs`: resolved paths and the (st_dev, st_ino) of
every folder above, so links and `..` hide nothing); else the batch is refused in one line.
Before any work, every output is checked against every input and the calibration (resolved
paths, and (st_dev, st_ino) where the file exists), and every file already at an output's name
must be proved spherejax's on its own, by its bytes: a SHA-256 that a record of OUT's manifest
lists at that very name, or that a run stopped by a kill wrote into its lock file just before
renaming the file into place (`lock.record_made`). Nothing else proves anything: not a claim of
the name, not a matching EXR beside it. A file not so proved refuses the batch in one line naming
it; it is never replaced, and clean-up (a failed input's outputs, the other format's files)
removes only proved files (`lock.claim_outputs`).

Every output is written under a temporary name beside it (created with O_EXCL) and renamed into
place when complete. An input that fails has none of its outputs left in OUT. An input's hash and
its pixels are one file: the name must still lead to the file hashed (st_dev, st_ino) once the
pixels are read, else the input fails (a file swapped in mid-correction). OUT/manifest.jsonl
gets one JSON line per finished input (`FileResult.to_json`), appended with a single write and
fsync (`spherejax.io.journal`, the format of an acquisition's journal too): the last line of an input wins. Without --resume an OUT holding a manifest is refused.
With it, an input is skipped when its last line is "done" with the same input and calibration
checksums, the same software version and settings (`output_settings`: illuminant, format, EXR
compression and reflectance type) and every output is present with the recorded SHA-256; anything else is redone.
Hashing and reading the manifest are safe points (below): a signal never waits for them.

OUT/.spherejax.lock holds an exclusive `fcntl.flock` for the whole run, and JSON lines: the
holder's pid and host (for the message that refuses a second run), the outputs the run claims
before writing them, and the SHA-256 of each output finished, written before it is renamed into
place (`lock.OutputLock`). The kernel drops the flock when a process dies,
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

One batch, one calibration (`batch_calibration`): the calibration is read once, when the batch
starts, and every input, in whichever thread or worker, proves before it reads anything and again
before its outputs go into place that the calibration file is still the one the batch read (its
checksum, inode, size and modification time). A calibration replaced (`calibrate --force`),
rewritten or removed mid-batch stops the batch as a signal does (the input under way leaves
nothing, the finished ones are recorded), with `CalibrationChangedError`: one line naming the
file, exit status 2. A manifest never holds two calibrations from one run.

On the way out, whatever ended the batch (its end, a stop, a failure, a full disk), the output
folders the batch created and left empty are removed (only those it created: an input that
fails while another uses its folder cannot remove it), and an OSError is reported in one line
naming its file (the manifest, the lock file, the working folder) and what the system said.

Modules
-------
    discovery  InputSpec and `discover_inputs`: what the paths given name, each input once
    inputs     the calibration (cached per process), an input opened and hashed, the proof that
               the pixels read are the bytes hashed
    outputs    output names per format, one writer interface for every format (`OutputWriter`:
               `commit` gives {path: SHA-256}), the sRGB preview, output folders and clean-up
    manifest   OUT/manifest.jsonl: `FileResult`, the one record type, and what --resume reads
    lock       OUT/.spherejax.lock (`OutputLock`) and the ownership check of every output
    batch      `run_batch`, `correct_input`, and the two inputs under way at once
    batch_calibration  one batch, one calibration: what the batch read, and the checks every
               input makes against it (`CalibrationIdentity`, `CalibrationChangedError`)
    stage_times  seconds per stage of each input, collected only when asked (the benchmark)
    errors     `BatchError`, `NoInputError`

The names below are this package's public interface (`spherejax.archive.X`); the modules' other
names are for the package and its tests.
"""

from __future__ import annotations

from .batch import BatchSummary, correct_input, run_batch
from .batch_calibration import CalibrationChangedError, CalibrationIdentity
from .discovery import InputSpec, discover_inputs
from .errors import BatchError, NoInputError
from .inputs import input_checksum, load_calibration
from .lock import LOCK_NAME, OutputLock
from .manifest import MANIFEST_NAME, FileResult, failed_result, is_done, read_manifest, recorded_outputs
from .outputs import (
    OUTPUT_FORMATS, OUTPUT_KINDS, OUTPUT_KINDS_BY_FORMAT, PREVIEW_BAD_PIXEL, output_settings, srgb_preview,
)

__all__ = [
    "MANIFEST_NAME",
    "LOCK_NAME",
    "OUTPUT_FORMATS",
    "OUTPUT_KINDS",
    "OUTPUT_KINDS_BY_FORMAT",
    "PREVIEW_BAD_PIXEL",
    "BatchError",
    "CalibrationChangedError",
    "CalibrationIdentity",
    "NoInputError",
    "InputSpec",
    "FileResult",
    "BatchSummary",
    "OutputLock",
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
