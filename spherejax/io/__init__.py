"""Files on disk: camera frames, sessions and calibration files (the formats are documented here).

This module, `archive` and `cli` are the only ones that touch the filesystem; the maths modules
never import them. Every failure raises a `SpherejaxFileError` (a ValueError) whose message is one
line, "PATH: problem (expected ...)", naming the file, the value found and what was expected. No
format uses pickle. Every writer is atomic: it writes under a temporary name in the destination's
folder and renames into place only when complete, so a failure leaves nothing new on disk
(`spherejax.atomic_files`, below the engine so that its cache uses it too: the steps, and the one
rule for temporary names that cleanup recognises).

The package's modules, one job each (their names are all available here):

    errors             SpherejaxFileError and its kinds, the one-line messages
    library_messages   what OpenImageIO and HDF5 say of a damaged file, in plain words
    hashing            `sha256_file`, the one way a file is hashed (in blocks, each a safe point)
    journal            append-only fsynced JSON-lines files: a batch's manifest, an acquisition's
                       journal
    documents          canonical and readable JSON; documents declared as pydantic models and
                       checked into one-line messages (`check_document`)
    plain_files        files spherejax keeps for itself, opened so that nothing planted there
                       makes it wait or read without end
    ownership          outputs that are not inputs: the check before any work
    exclusive_lock     one run at a time: an exclusive flock on a lock file known by its record
    atomic_writer      `AtomicWriter`, the one state machine of every image writer: rows into
                       temporary files, put in place by `commit`, removed by `abort`
    direct_io          large new files written past the page cache (O_DIRECT) where allowed
    frames             camera frames (TIFF) and `AtomicImageWriter` (through OpenImageIO)
    streamed_writer    `StreamedImageWriter`: the images spherejax encodes itself, strip by strip
    exr_uncompressed   uncompressed scanline OpenEXR, OpenImageIO's bytes written faster
    cubes              cubes read by rows (`CubeReader`), OpenEXR and PNG outputs
    spectral_layout    the reflectance EXR's spectral layout (Fichet et al. 2021): channel names
    cgats              CGATS.17 text (ISO 28178), as colour quality-control software exchanges it
    envi               ENVI images (header + raw BIP pixels), written by strips, read lazily
    quality_png        the quality mask N.quality.png: palette PNG of the quality bits, by strips
    corrected          outputs opened as xarray (`spherejax.open_corrected`), lazily by rows
    sessions           session folders: `load_session`, `write_session`, `write_simulated_session`
    calibration_files  calibration files: `save_calibration`, `open_calibration`, `load_calibration`
    calibration_checks what a calibration file holds: the format and its versions, the header, the
                       checks of header and arrays, the noise model, the usable white patch
    calibration_hdf5   the calibration file's HDF5 layout: writing, indexing before reading (every
                       declared byte stored), reads by rows and blocks, the checksum
    calibration_npz    the .npz calibration files of format versions 1 to 3 (read only)
    instruments        simulated-instrument files: `save_instrument` (spherejax twin),
                       `load_instrument` (spherejax simulate --instrument)

Camera frame
------------
One TIFF per capture holding all bands as channels: shape (H, W, C), 16-bit unsigned samples,
deflate-compressed, a single page, no alpha channel. TIFF keeps no channel names or free attributes,
so `write_frame` also stores them as JSON in the ImageDescription tag,
``{"channel_names": ["400nm", ...], "attributes": {"key": "value", ...}}`` (`read_frame_metadata`).

Cube (an input of `spherejax correct`, `read_cube`)
---------------------------------------------------
A camera frame as above; a multi-page 16-bit TIFF with one single-channel page per band; or an
OpenEXR with one half or float channel per band. Channel names that all give a wavelength,
"<nm>nm" ("400nm", "420 nm") or the spectral layout's "T.<nm>nm", must be the calibration's
bands, each named once, and put the channels in band order whatever their order in the file.
Otherwise a TIFF's channels (or pages) are the bands in their stored order, and an OpenEXR of
more than one channel is refused, its channel names listed: OpenEXR stores channels sorted by
name (c0, c1, c10, .., c2), so the order they were written in is lost. A name written twice is
such a case: OpenImageIO writes "channel1" in place of the second. A folder of single-channel
band frames is read with `read_band_files`.

Corrected outputs (`write_exr`, `write_png`)
---------------------------------------------
float32 OpenEXR, or half float (`open_exr`'s `pixel_type`), uncompressed by default or PIZ or ZIP
(all lossless; `EXR_COMPRESSIONS` says why none is the default) with named channels and string
attributes, and 8-bit PNG. A reflectance EXR follows the spectral layout of Fichet,
Pacanowski, Wilkie (JCGT 10(3), 2021; `spectral_layout`): channels "T.400nm".."T.700nm" and
spectralLayoutVersion "1.0"; older ones named "400nm".."700nm" still read. Neither
carries a time stamp, so writing the same pixels twice gives the same bytes (`spherejax.archive`
relies on it to resume a batch into byte-identical outputs). Uncompressed EXRs with spherejax's
own attributes are written by `exr_uncompressed` (OpenImageIO's bytes, without its cost), and
they and the ENVI outputs go past the page cache where the file system allows it (`direct_io`).

Session (format "spherejax-session", version 1)
-----------------------------------------------
A folder with ``manifest.json`` and the frame files (`write_session` writes ``frames/<id>.tif``):

    {
      "format": "spherejax-session", "format_version": 1,
      "software_version": "0.1.0",             the spherejax that wrote it
      "instrument_id": "sim-sphere-1",
      "created": "2026-11-22T10:00:00+00:00",  ISO 8601
      "band_centres_nm": [400, 420, ..., 700], B integers, strictly increasing
      "image_shape": [H, W],
      "saturation": 16383,                     raw level at or above which a pixel is saturated
      "white_patch": [r0, r1, c0, c1],         reference white patch, rows r0:r1, columns c0:c1
      "holder": [r0, r1, c0, c1],              sample holder (the Markov baseline's holder mean)
      "frames": [frame, ...],
      "metadata": {...},                       optional, free JSON (e.g. simulator parameters)
      "band_transforms": [[[a, b, c], [d, e, f]], ...]
                                               optional: B 2 x 3 affine maps, one per band, from
                                               the reference geometry's pixel coordinates (x =
                                               column, y = row, pixel centres at integers) to the
                                               band's; a simulated session records its truth
    }

A frame is an object with
      "id": unique in the session ([A-Za-z0-9._-]+ when written by `write_session`),
      "role": "dark" | "white" | "sample" | "target" | "registration" (exactly one dark and one
              white frame; at most one registration frame: a registration target, high-contrast
              edges across the field, that calibrate registers the bands on; no regions),
      "file": path relative to the folder, inside it (no absolute paths, "..", or links out),
      "exposure_s": B exposure times in seconds, one per band, > 0,
      "timestamp": ISO 8601,
      "set": "training" | "test", required for samples, optional otherwise,
      "background": name of the background the sample lies on, required for samples,
      "regions": [region, ...], samples and targets only (optional, default []),
      "metadata": {...} optional, free JSON;
and a region is
      "name": unique in the frame, "patch": which physical patch it shows (default: the name),
      "region": [r0, r1, c0, c1], a non-empty rectangle inside the image,
      "reflectance": 31 known reflectances at 400..700 nm step 10 (required for targets).
Rectangles are half-open, like slices: rows r0..r1-1 and columns c0..c1-1. Every frame file is a
camera frame of shape (H, W, B). Unknown fields are refused (a typo must not pass silently).

Calibration file (format "spherejax-calibration", version 7)
------------------------------------------------------------
An HDF5 file (h5py; told by its first 8 bytes, b"\\x89HDF\\r\\n\\x1a\\n", not its name,
conventionally .h5) whose root group holds one dataset per array of a `Calibration`
    dark (H, W, B), white (H, W, B), patch (H, W) bool, coeffs (B, 4), wiener (31, B),
    wiener_offset (31,), wiener_residual_centre (B,), wiener_residual_whitening (B, B),
    wiener_residual_inducing (m, B), wiener_residual_weights (31, m)
and, optionally (all five or none), wiener_residual_variance_components (r, 31),
    wiener_residual_variance_prior (r,), wiener_residual_variance_projection (m, q),
    wiener_residual_variance_weights (r, q), wiener_residual_variance_noise (31,)
and, optionally, band_transforms (B, 2, 3) (the bands' maps, `Calibration.band_transforms`),
each with its meaning as the string attribute "description", and nothing else; and the root's
attribute "header", a string of UTF-8 JSON:
    {"format": "spherejax-calibration", "format_version": 7, "software_version",
     "instrument_id", "band_centres_nm": [B integers], "illuminant", "observer",
     "saturation": number or null, "created": UTC ISO 8601,
     "arrays": {name: {"shape": [...], "dtype": "<f4", "description": "..."}},
     "metadata": {...}, "noise_model": {...} or null, "checksum": "sha256:<64 hex digits>",
     "band_registration": {...} (only with band_transforms)}
Datasets are stored in the file, unfiltered (no compression), every byte written: dark, white
and patch in chunks of whole rows (about 1 MiB each), so that rows read without the rest of the
frame; the others contiguous. Hard links only (no external links, groups, external or virtual
storage). Read it with ``json.loads(h5py.File(path)["/"].attrs["header"])`` and
``h5py.File(path)["dark"][r0:r1]``. The checksum is SHA-256 over
the header JSON without the "checksum" field, serialised with sorted keys, separators "," and ":"
and UTF-8 (no ASCII escaping), followed, for each array in the order dark, white, patch, coeffs,
wiener, wiener_offset, wiener_residual_centre, wiener_residual_whitening, wiener_residual_inducing,
wiener_residual_weights and, when present, wiener_residual_variance_components, _prior,
_projection, _weights and _noise, then band_transforms, by the line ``"<name> <dtype.str> <shape as a JSON list>\\n"`` in ASCII and
the array's raw bytes in C order (as h5py reads the dataset: a bool patch is one byte per
pixel, 0 or 1). It is computed from the parsed header, so the stored JSON's layout does not
matter, and it is the same in both containers. "metadata" is free JSON from the writer
(`save_calibration(..., metadata=)`), e.g. how the Stage II and Wiener fits were made.

The reflectance estimate is r = W v_tilde + r0 + A k(v_tilde), with W the "wiener" array, r0 the
"wiener_offset" array and the kernel residual A k (`spherejax.estimation.kernel_residual`, E8-E10):
k_j(v) = exp(-|S (v - mu) - z_j|^2 / 2), mu the "wiener_residual_centre", S the
"wiener_residual_whitening" (the lengthscale folded in), z_j the rows of
"wiener_residual_inducing" and A the "wiener_residual_weights". An affine estimator has m = 0
(no inducing point: k and A k are empty and zero) and zeros for mu and S.
The "wiener_residual_variance_*" arrays are the residual's own predictive variance (E15,
`spherejax.estimation.ResidualVariance`: P, s^2, X, C and the targets' scatter), which the
uncertainties add (`spherejax.uncertainty`, N8): var_j(v) = s_j^2 (1 - |g|^2) + sum_i C_ji g_i^2,
g = X^T k(v), and Cov(r) = sum_j var_j P_j P_j^T; m >= 1, 1 <= r <= 31, q <= m, prior and noise
finite and >= 0.

"noise_model" (optional; absent or null: none) is the camera's noise and the calibration's
uncertainties for per-pixel uncertainties (`spherejax.uncertainty.NoiseModel`, as its
`to_json()` writes it, numbers as float64 JSON, so that `CalibrationFile.noise_model` reads
every value back exactly):
    {"gain_e_per_count": number or [B numbers] > 0 (electrons per count),
     "read_noise_counts": number or [B numbers] >= 0 (one frame's read noise, counts rms),
     "dark_frames", "white_frames": frames averaged in the dark and white-standard frames (>= 1),
     "sample_frames": frames averaged in the sample frames it corrects (>= 1),
     "white_reflectance_u": number or [B numbers] >= 0, the relative standard uncertainty of
       the white standard's certified reflectance,
     "coeffs_covariance": [B][4][4] covariance of the Stage II coefficients c1..c4, or null,
     "estimator_covariance": {"gram": [B + 1][B + 1], "residual": [31][31]} (the reflectance
       estimator's sampling covariance, `spherejax.EstimatorCovariance`), or null}
All numbers finite. Only "gain_e_per_count" and "read_noise_counts" are required inside it.

"band_transforms" (optional; absent: the bands are taken as in register, as every calibration
before version 7) holds one 2 x 3 affine matrix per band, in band order, mapping pixel
coordinates of the reference band's geometry (x = column, y = row, pixel centres at integers) to
that band's, as the session manifest's "band_transforms" does: each linear part within 0.05 of
the identity and each band within 50 px of the reference band over the frame. Every correction
resamples each band's flat-fielded response through it before Stage I (`spherejax.band_resampling`).
"band_registration" records how the maps were estimated (`calibrate`): "band_transforms" (the
same maps as JSON), "frame" (the capture they came from), "reference_band" (index) and
"reference_band_nm", "residual_px" (per band, the rms of its tiles' shifts about the map),
"tiles" and "largest_displacement_px".

Older versions are still read (whole). Version 6 is version 7 without "band_transforms" and
"band_registration" (any found there are refused). Version 5 is version 6 without the variance's five
arrays (a residual without its variance; any found there are refused). Version 4 is version 5 without the four
"wiener_residual_*" arrays (an affine estimator), in the header's "arrays" and in the checksum.
Version 3 is version 4 in an .npz archive
(`numpy.savez`, no pickled objects; told by its first bytes, b"PK\\x03\\x04"), read with
`numpy.load(allow_pickle=False)`: one .npy member per array and "header", a uint8 array of the
same UTF-8 JSON (``bytes(numpy.load(path)["header"]).decode()``). Versions 4 to 7 are HDF5
only and versions 1 to 3 .npz only.
Version 2 is version 3 without "noise_model" (no noise model;
a null one is read as absent, any other is refused).
Version 1 (before the offset existed) is version 2 without the member "wiener_offset", in the
header's "arrays" and in the checksum; it is read with r0 = 0, which is what it meant.
"""

from __future__ import annotations

from .errors import CalibrationFileError, SessionError, SpherejaxFileError
from ..atomic_files import is_temp_sibling, temp_sibling
from .ownership import refuse_overlaps
from .plain_files import file_kind, open_regular, read_lines, read_small
from .frames import (
    AtomicImageWriter,
    frame_spec,
    read_frame,
    read_frame_metadata,
    write_frame,
)
from .cubes import (
    band_centres_from_names,
    CubeReader,
    DEFAULT_EXR_COMPRESSION,
    EXR_COMPRESSIONS,
    EXR_PIXEL_TYPES,
    open_band_files,
    open_cube,
    open_exr,
    open_png,
    read_band_files,
    read_cube,
    write_exr,
    write_png,
)
from .sessions import (
    check_new_session_folder,
    FrameInfo,
    load_session,
    MANIFEST_NAME,
    rectangle_mask,
    Region,
    ROLES,
    Session,
    SESSION_FORMAT,
    SESSION_FORMAT_VERSION,
    SETS,
    write_session,
    write_simulated_session,
)
from .calibration_files import (
    CALIBRATION_ARRAYS,
    CALIBRATION_FORMAT,
    CALIBRATION_FORMAT_VERSION,
    CalibrationFile,
    IN_MEMORY_BYTES,
    load_calibration,
    noise_model_of,
    open_calibration,
    save_calibration,
)
from .spectral_layout import reflectance_channel_names, wavelengths_of_channels
from .quality_png import open_quality_png, read_quality_png, write_quality_png
from .instruments import INSTRUMENT_FORMAT, InstrumentFileError, load_instrument, save_instrument

__all__ = [
    "INSTRUMENT_FORMAT",
    "InstrumentFileError",
    "load_instrument",
    "save_instrument",
    "temp_sibling",
    "is_temp_sibling",
    "refuse_overlaps",
    "file_kind",
    "open_regular",
    "read_lines",
    "read_small",
    "write_simulated_session",
    "SpherejaxFileError",
    "SessionError",
    "CalibrationFileError",
    "ROLES",
    "SETS",
    "Region",
    "FrameInfo",
    "Session",
    "frame_spec",
    "read_frame",
    "read_frame_metadata",
    "write_frame",
    "band_centres_from_names",
    "CubeReader",
    "open_cube",
    "open_band_files",
    "read_cube",
    "read_band_files",
    "AtomicImageWriter",
    "open_exr",
    "open_png",
    "write_exr",
    "write_png",
    "open_quality_png",
    "read_quality_png",
    "write_quality_png",
    "rectangle_mask",
    "load_session",
    "write_session",
    "save_calibration",
    "CalibrationFile",
    "open_calibration",
    "load_calibration",
    "noise_model_of",
    "DEFAULT_EXR_COMPRESSION",
    "EXR_COMPRESSIONS",
    "EXR_PIXEL_TYPES",
    "check_new_session_folder",
    "MANIFEST_NAME",
    "SESSION_FORMAT",
    "SESSION_FORMAT_VERSION",
    "CALIBRATION_ARRAYS",
    "CALIBRATION_FORMAT",
    "CALIBRATION_FORMAT_VERSION",
    "IN_MEMORY_BYTES",
    "reflectance_channel_names",
    "wavelengths_of_channels",
]
