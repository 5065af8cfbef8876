"""Property-based robustness tests (docs/reliability.md, "Properties"), with hypothesis.

Loaders: every file spherejax reads (batch manifest and lock file, session manifest, calibration
.npz, instrument profile TOML, camera frames and cubes), fed arbitrary bytes, byte-level damage
of a valid file (bit flips, overwritten, inserted or deleted bytes, truncation) and value-level
edits of a valid document, either loads or raises its documented error (the ValueError /
OSError that `spherejax.cli.main` turns into one line; hw.profile's ProfileError) with a
one-line message naming the file. Anything else (KeyError, OverflowError, RecursionError,
zipfile's RuntimeError, a UnicodeDecodeError from OpenImageIO's binding...) fails the test.

Kernels: ΔE00 is symmetric, non-negative and 0 on identical colours; the white standard
flat-fields to 1; Stage II with identity coefficients is Stage I; `correct` never raises on
arbitrary uint16 or float32 raw values, its quality bits are what the inputs say, its outputs
are NaN exactly where the quality is not 0 and finite elsewhere, and the fused CPU kernel agrees
with the jax.numpy path.

Every test is derandomized (the same examples on every run, no example database), so CI is
deterministic. Shapes are fixed so that JAX compiles each program once.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io as pyio
import json
import math
import os
import pathlib
import zipfile

import hypothesis.extra.numpy as hnp
import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import HealthCheck, currently_in_test_context, event, example, given, settings, strategies as st

import spherejax as sj
from spherejax_hw.profile import ProfileError, load_profile
from spherejax import archive, io
from spherejax._engine import fused
from spherejax.io import CalibrationFileError, SessionError, SpherejaxFileError
from spherejax.io.exclusive_lock import is_lock_file
from tests.helpers import (
    assert_exact_or_close, calibration_entries, division_rtol, write_calibration_entries, write_with_oiio,
)


def fuzz(examples: int):
    """Deterministic hypothesis settings: fixed seed, no database, no deadline (first calls
    compile)."""
    return settings(
        max_examples=examples,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


# ------------------------------------------------------------------------------------ helpers


def _event(name: str) -> None:
    """hypothesis.event, which the plain regression tests (no hypothesis) cannot call."""
    if currently_in_test_context():
        event(name)


def loads_or_refuses(what: str, load, names, errors):
    """Call `load()`: it may succeed (returns its result) or raise one of `errors` (returned)
    whose message is one line and contains one of `names` (the file, or the folder it lies in).
    Any other exception propagates and fails the test. `what` names the loader in the
    statistics (pytest --hypothesis-show-statistics)."""
    try:
        result = load()
    except errors as error:
        message = str(error)
        assert "\n" not in message and "\r" not in message, repr(message)
        assert any(str(name) in message for name in names), message
        _event(f"{what}: refused")
        return error
    _event(f"{what}: loaded")
    return result


def _edit(draw, data: bytearray, hotspots: tuple[int, ...]) -> None:
    """One edit of `data` in place, at a random offset or just after a hotspot (where the
    format's structures are: a header, a zip directory entry)."""
    if hotspots and draw(st.booleans()):
        pos = draw(st.sampled_from(hotspots)) + draw(st.integers(0, 47))
    else:
        pos = draw(st.integers(0, len(data) - 1))
    pos = min(pos, len(data) - 1)
    op = draw(st.sampled_from(("xor", "set", "insert", "delete", "truncate")))
    if op == "xor":
        data[pos] ^= 1 << draw(st.integers(0, 7))
    elif op == "set":
        data[pos] = draw(st.sampled_from((0x00, 0x01, 0x7F, 0x80, 0xE9, 0xFF)) | st.integers(0, 255))
    elif op == "insert":
        data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
    elif op == "delete":
        del data[pos : pos + draw(st.integers(1, 16))]
    else:
        del data[pos:]


@st.composite
def damaged(draw, original: bytes, hotspots: tuple[int, ...] = ()):
    """`original` with 1 to 4 byte-level edits."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 4))):
        if not data:
            break
        _edit(draw, data, hotspots)
    return bytes(data)


def offsets_of(data: bytes, *markers: bytes) -> tuple[int, ...]:
    """Offsets of every occurrence of the markers in `data` (hotspots for `damaged`)."""
    found = []
    for marker in markers:
        start = data.find(marker)
        while start >= 0:
            found.append(start)
            start = data.find(marker, start + 1)
    return tuple(sorted(found))


#: Numbers JSON and TOML hold that Python's float() cannot: beyond float range, and past
#: Python's 4300-digit limit for int() of a decimal string.
HUGE = 10**400
VAST = "9" * 5000  # as text: int() of it raises

#: Values that have broken parsers: beyond float range, non-finite, empty, NUL bytes, paths
#: out of a folder, wrong types where a number or a string is expected.
json_tricky = st.sampled_from(
    (HUGE, -HUGE, 2**64, -1, 0, math.nan, math.inf, -math.inf, 1e308, None, True, "", ".", "..",
     "a\x00b", "../x.tif", "/etc/passwd", "2026-11-22T10:00:00+00:00", "sha256:" + "0" * 64, [], {}, [[]], [0, 0, 0, 0])
)
json_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12)
)
def _nested(leaves, wrap, depth: int = 3):
    """Values nested up to `depth` levels: `wrap` applied to itself over `leaves`. Built by hand,
    not with st.recursive, whose check that `extend` uses its argument warned (an error under
    this suite's filterwarnings) in some runs for these lambdas."""
    strategy = leaves
    for _ in range(depth):
        strategy = leaves | wrap(strategy)
    return strategy


json_values = json_tricky | _nested(
    json_scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
)


def json_paths(doc, prefix=()):
    """Every position in a JSON document: () is the whole, ("frames", 0, "id") a field."""
    yield prefix
    if isinstance(doc, dict):
        for key, value in doc.items():
            yield from json_paths(value, (*prefix, key))
    elif isinstance(doc, list):
        for index, value in enumerate(doc):
            yield from json_paths(value, (*prefix, index))


@st.composite
def edited_json(draw, doc):
    """`doc` with one to three value-level edits: a value replaced by any JSON value, a field
    or item removed, or an unknown field added."""
    doc = json.loads(json.dumps(doc))
    for _ in range(draw(st.integers(1, 3))):
        paths = list(json_paths(doc))
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(("replace", "replace", "remove", "add")))
        if not path:
            if op == "replace":
                doc = copy.deepcopy(draw(json_values))
            continue
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        # Copies: the drawn values ([] or {} of json_tricky among them) are edited later.
        if op == "replace":
            parent[path[-1]] = copy.deepcopy(draw(json_values))
        elif op == "remove":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = copy.deepcopy(draw(json_values))
        else:
            parent.append(copy.deepcopy(draw(json_values)))
    return doc


@dataclasses.dataclass(frozen=True)
class Valid:
    """A valid file (or folder) the tests start from, and its content (bytes, or bytes by file
    name); kept out of repr, so that hypothesis's report of a failing example stays short."""

    path: pathlib.Path
    content: bytes | dict = dataclasses.field(repr=False)


# A scratch folder for the valid files and the examples (hypothesis runs many examples per test
# call, which a function-scoped tmp_path would share anyway).
@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> pathlib.Path:
    return tmp_path_factory.mktemp("properties")


# ------------------------------------------------------------------- archive: manifest and lock


@fuzz(200)
@given(content=st.binary(max_size=2000))
@example(content=b"[" * 100_000 + b"\n" + b"9" * 5000 + b'\n{"name": "x"}')  # RecursionError; int() limit
def test_batch_manifest_reader_never_raises_on_arbitrary_bytes(scratch, content):
    """`archive.read_manifest` skips every line that is not a whole JSON object with a name
    (a run killed mid-write leaves such lines), whatever the bytes."""
    out = scratch / "batch-bytes"
    out.mkdir(exist_ok=True)
    (out / archive.MANIFEST_NAME).write_bytes(content)
    records = archive.read_manifest(out)
    assert all(isinstance(r, dict) and r["name"] == name for name, r in records.items())


record_strategy = st.fixed_dictionaries(
    {"name": st.sampled_from(("a", "b", "batch/c", "é")), "status": st.sampled_from(("done", "failed"))},
    optional={"outputs": st.dictionaries(st.text(max_size=6), st.text(max_size=6), max_size=2), "n": st.integers()},
)
#: Garbage a killed run or a broken disk may leave: no "{" (so never a JSON object, in any of
#: the encodings json.loads detects) and no newline (one line each).
garbage_line = st.binary(max_size=60).filter(lambda b: b"{" not in b and b"\n" not in b) | st.sampled_from(
    (b"[" * 5000, b"9" * 5000)  # RecursionError; past int()'s 4300 digits
)


@fuzz(100)
@given(
    lines=st.lists(
        st.tuples(record_strategy, st.sampled_from(("whole", "whole", "cut", "garbage")), garbage_line, st.integers(1, 200)),
        max_size=8,
    ),
    last_newline=st.booleans(),
)
def test_batch_manifest_reader_keeps_every_whole_record(scratch, lines, last_newline):
    """Whole records survive any cut-off records and garbage between them; the last record of
    a name wins."""
    out = scratch / "batch-records"
    out.mkdir(exist_ok=True)
    chunks, expected = [], {}
    for record, kind, garbage, cut in lines:
        text = json.dumps(record, ensure_ascii=False).encode("utf-8")
        if kind == "whole":
            chunks.append(text)
            expected[record["name"]] = record
        elif kind == "cut":
            chunks.append(text[: min(cut, len(text) - 1)])  # a strict prefix is never whole JSON
        else:
            chunks.append(garbage)
    (out / archive.MANIFEST_NAME).write_bytes(b"\n".join(chunks) + (b"\n" if last_newline else b""))
    assert archive.read_manifest(out) == expected


@fuzz(100)
@given(content=st.binary(max_size=300))
@example(content=b"[" * 100_000)  # RecursionError, which also left the lock held
@example(content=b'{"pid": 1, "host": "a\\nb"}')  # a newline in the message
def test_lock_file_left_with_arbitrary_content_is_taken_over_or_refused(scratch, content):
    """A lock file that no process holds is taken over when it is spherejax's (empty, or
    beginning with a holder's {"pid": N, "host": ...}), the previous holder described in one
    line (the CLI prints it); anything else at its name is not spherejax's, so it is refused in
    one line and left as it was, never written over or removed."""
    out = scratch / "batch-lock"
    out.mkdir(exist_ok=True)
    (out / archive.LOCK_NAME).write_bytes(content)
    lock = archive.OutputLock(out)
    if content and not io.exclusive_lock.is_lock_file(content):
        with pytest.raises(archive.BatchError) as refused:
            lock.acquire()
        assert "\n" not in str(refused.value) and "not a spherejax lock" in str(refused.value)
        assert (out / archive.LOCK_NAME).read_bytes() == content
        (out / archive.LOCK_NAME).unlink()
        return
    lock.acquire()
    try:
        if content:
            assert isinstance(lock.taken_over, str) and "\n" not in lock.taken_over, repr(lock.taken_over)
        else:
            assert lock.taken_over is None
        holder = (out / archive.LOCK_NAME).read_text().splitlines()[0]
        assert json.loads(holder)["pid"] == os.getpid()
    finally:
        lock.release()
    assert not (out / archive.LOCK_NAME).exists()


# ---------------------------------------------------------------------------- session manifest

H, W = 6, 5
BANDS = [450, 550, 650]
CREATED = "2026-11-22T10:00:00+00:00"


def _frame(frame_id, role, **fields):
    return {"id": frame_id, "role": role, "exposure_s": [0.01, 0.02, 0.03], "timestamp": CREATED, **fields}


@pytest.fixture(scope="module")
def session_folder(scratch) -> Valid:
    """A valid session (dark, white, a sample with a region, a target with reflectances): its
    folder, and its manifest (the tests overwrite the manifest)."""
    rng = np.random.default_rng(1)
    counts = lambda: rng.integers(0, 16383, (H, W, len(BANDS)), dtype=np.uint16)  # noqa: E731
    frames = [
        (_frame("dark", "dark"), counts()),
        (_frame("white", "white"), counts()),
        (_frame("s1", "sample", set="training", background="bg", regions=[{"name": "g", "region": [2, 4, 1, 3]}]), counts()),
        (_frame("t1", "target", regions=[{"name": "t", "region": [0, 2, 0, 2], "reflectance": [0.5] * 31}]), counts()),
    ]
    path = scratch / "session"
    io.write_session(
        path, frames=frames, instrument_id="sim", band_centres_nm=BANDS, image_shape=(H, W),
        saturation=16383, white_patch=[0, 2, 3, 5], holder=[2, 6, 0, 5], metadata={"seed": 1},
        created=CREATED,
    )
    return Valid(path, (path / io.MANIFEST_NAME).read_bytes())


def load_session_checked(folder: pathlib.Path, manifest: bytes):
    """Write `manifest` into the session and load it: a Session or a SessionError naming a file
    of the session (the manifest, a frame file, or the folder)."""
    (folder / io.MANIFEST_NAME).write_bytes(manifest)
    result = loads_or_refuses("load_session", lambda: io.load_session(folder), [folder], errors=(SessionError,))
    if isinstance(result, io.Session):
        # What loads is a usable session: exactly one dark and white frame whose files read.
        assert len(result.frames_with("dark")) == len(result.frames_with("white")) == 1
        assert result.dark().shape == (*result.image_shape, result.bands)
    return result


@fuzz(200)
@given(content=st.binary(max_size=1500))
def test_session_manifest_of_arbitrary_bytes(session_folder, content):
    load_session_checked(session_folder.path, content)


@fuzz(500)
@given(data=st.data())
def test_session_manifest_with_damaged_bytes(session_folder, data):
    folder, original = session_folder.path, session_folder.content
    hotspots = offsets_of(original, b'"', b"[", b"{")
    load_session_checked(folder, data.draw(damaged(original, hotspots)))


@fuzz(600)
@given(data=st.data())
def test_session_manifest_with_edited_values(session_folder, data):
    folder, original = session_folder.path, session_folder.content
    doc = data.draw(edited_json(json.loads(original)))
    load_session_checked(folder, json.dumps(doc).encode("utf-8"))


@pytest.mark.parametrize(
    "old, new",
    [
        ('"saturation": 16383', f'"saturation": {HUGE}'),
        ('"exposure_s": [0.01', f'"exposure_s": [{HUGE}'),
        ('"saturation": 16383', f'"saturation": {VAST}'),
        ('"metadata": {', '"metadata": {"deep": ' + "[" * 100_000 + "]" * 100_000 + ","),
        ('"file": "frames/s1.tif"', '"file": "frames/s1\\u0000.tif"'),
    ],
    ids=["number-beyond-float", "exposure-beyond-float", "5000-digit-integer", "nested-100000-deep", "nul-in-file-name"],
)
def test_session_manifest_regressions(session_folder, old, new):
    """Cases the properties above found, each pinned: unchecked, they escape as OverflowError
    (math.isfinite of an integer beyond float range), ValueError naming no file (int() refuses
    4300+ digits), RecursionError (json), ValueError "embedded null byte" (resolving the frame
    path)."""
    manifest = session_folder.content.decode()
    assert old in manifest
    result = load_session_checked(session_folder.path, manifest.replace(old, new, 1).encode())
    assert isinstance(result, SessionError)
    assert str(session_folder.path / io.MANIFEST_NAME) in str(result)


# ---------------------------------------------------------------------------- calibration file

CAL_H, CAL_W, CAL_B = 4, 5, 3


def _calibration(rng) -> sj.Calibration:
    patch = np.zeros((CAL_H, CAL_W), bool)
    patch[0:2, 3:5] = True
    return sj.Calibration(
        dark=rng.uniform(50, 60, (CAL_H, CAL_W, CAL_B)).astype(np.float32),
        white=rng.uniform(9000, 12000, (CAL_H, CAL_W, CAL_B)).astype(np.float32),
        patch=patch,
        coeffs=rng.normal(size=(CAL_B, 4)).astype(np.float32),
        wiener=rng.normal(size=(31, CAL_B)).astype(np.float32),
        saturation=16383,
    )


@pytest.fixture(scope="module")
def valid_calibration(scratch) -> Valid:
    path = scratch / "valid-cal.h5"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(io.calibration_files, "_utc_now", lambda: CREATED)  # the same header on every run
        io.save_calibration(path, _calibration(np.random.default_rng(2)), instrument_id="sim", band_centres_nm=BANDS)
    return Valid(path, path.read_bytes())


@pytest.fixture(scope="module")
def valid_old_calibration(scratch, valid_calibration) -> Valid:
    """The valid calibration as the format version 3 writer wrote it: an .npz (np.savez)."""
    header, arrays = _valid_entries(valid_calibration)
    # Version 3 had no kernel residual (format version 5 added its four arrays).
    residual = io.calibration_checks.RESIDUAL_ARRAYS
    arrays = {name: array for name, array in arrays.items() if name not in residual}
    header = {**header, "format_version": 3, "arrays": {k: v for k, v in header["arrays"].items() if k not in residual}}
    header["checksum"] = io.calibration_files._checksum(header, arrays)
    path = scratch / "valid-cal-v3.npz"
    write_calibration_entries(path, {"header": np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays})
    return Valid(path, path.read_bytes())


def load_calibration_checked(path: pathlib.Path, content: bytes | None = None):
    """Load a calibration file: (Calibration, header) or a CalibrationFileError naming it."""
    if content is not None:
        path.write_bytes(content)
    result = loads_or_refuses("load_calibration", lambda: io.load_calibration(path), [path], errors=(CalibrationFileError,))
    if not isinstance(result, Exception):
        calibration, header = result
        assert calibration.dark.shape == calibration.white.shape
        assert header["checksum"].startswith("sha256:")
    return result


@fuzz(200)
@given(content=st.binary(max_size=600) | st.binary(max_size=600).map(lambda b: b"PK\x03\x04" + b)
       | st.binary(max_size=600).map(lambda b: io.calibration_files.HDF5_SIGNATURE + b))
def test_calibration_of_arbitrary_bytes(scratch, content):
    load_calibration_checked(scratch / "bytes.h5", content)


def _loads_as_saved(result, valid: Valid) -> None:
    """What loads from a damaged file must be the calibration that was saved."""
    if not isinstance(result, Exception):
        original, _ = io.load_calibration(valid.path)
        for name in io.CALIBRATION_ARRAYS:
            np.testing.assert_array_equal(stored_array(result[0], name), stored_array(original, name))


@fuzz(800)
@given(data=st.data())
def test_calibration_with_damaged_bytes(scratch, valid_calibration, data):
    """Damage aimed at the HDF5 structures (superblock, B-trees, local and global heaps, symbol
    table nodes) and the header's JSON as well as anywhere."""
    hotspots = offsets_of(valid_calibration.content, b"\x89HDF", b"TREE", b"HEAP", b"SNOD", b"GCOL", b'"format', b'"saturation')
    content = data.draw(damaged(valid_calibration.content, hotspots))
    _loads_as_saved(load_calibration_checked(scratch / "damaged.h5", content), valid_calibration)


@fuzz(300)
@given(data=st.data())
def test_old_npz_calibration_with_damaged_bytes(scratch, valid_old_calibration, data):
    """An old .npz: damage aimed at the zip structures (local headers, directory, end record)
    and the .npy headers as well as anywhere."""
    hotspots = offsets_of(valid_old_calibration.content, b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06", b"\x93NUMPY", b'"format', b'"saturation')
    content = data.draw(damaged(valid_old_calibration.content, hotspots))
    _loads_as_saved(load_calibration_checked(scratch / "damaged.npz", content), valid_old_calibration)


def _npy(array: np.ndarray) -> bytes:
    buffer = pyio.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def _valid_entries(valid: Valid) -> tuple[dict, dict]:
    """(header, arrays) of a valid calibration file."""
    arrays = calibration_entries(valid.path)
    return json.loads(arrays.pop("header").tobytes().decode("utf-8")), arrays


npy_arrays = hnp.arrays(
    st.sampled_from((np.float32, np.float64, np.dtype(">f4"), np.uint16, np.int64, np.bool_, np.complex64, np.dtype("<U2"))),
    hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4),
) | st.sampled_from((np.zeros((2, 3), "V3"), np.zeros((0, 0), np.float32), np.zeros((4, 5, 0), np.float32)))


@st.composite
def npy_member(draw):
    """(name, bytes) of one zip member: a real .npy, a .npy with a damaged header, or anything."""
    name = draw(st.sampled_from(("header", "dark", "white", "patch", "coeffs", "wiener", "extra")) | st.text(max_size=6))
    kind = draw(st.sampled_from(("npy", "npy", "damaged", "bytes")))
    if kind == "bytes":
        content = draw(st.binary(max_size=200))
    else:
        content = _npy(draw(npy_arrays))
        if kind == "damaged":
            content = draw(damaged(content, (0, 8, 10)))
    suffix = draw(st.sampled_from((".npy", ".npy", ".npy", "", ".txt")))
    return name + suffix, content


@fuzz(300)
@given(
    members=st.lists(
        st.tuples(npy_member(), st.sampled_from((zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED))),
        max_size=7, unique_by=lambda member: member[0][0],
    ),
)
def test_calibration_zip_of_arbitrary_members(scratch, members):
    """A well-formed zip whose members are anything: arrays of any dtype and shape (stored or
    deflated), .npy files with damaged headers, other files."""
    path = scratch / "members.npz"
    with zipfile.ZipFile(path, "w") as archive_file:
        for (name, content), compression in members:
            archive_file.writestr(zipfile.ZipInfo(name), content, compress_type=compression)
    load_calibration_checked(path)


#: Arrays HDF5 stores: as `npy_arrays`, byte strings in place of numpy's unicode ones.
stored_arrays = hnp.arrays(
    st.sampled_from((np.float32, np.float64, np.dtype(">f4"), np.uint16, np.int64, np.bool_, np.complex64, np.dtype("S2"))),
    hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4),
) | st.sampled_from((np.zeros((2, 3), "V3"), np.zeros((0, 0), np.float32), np.zeros((4, 5, 0), np.float32)))


def _save_forged(path: pathlib.Path, header, arrays: dict) -> None:
    """Write an HDF5 file as save_calibration would, with a correct checksum when the header
    allows one: what a third-party writer or a forger produces."""
    if isinstance(header, dict):
        with contextlib.suppress(ValueError, TypeError, KeyError, AttributeError):
            header = {**header, "checksum": io.calibration_files._checksum(header, arrays)}
    encoded = json.dumps(header, allow_nan=True).encode("utf-8")
    write_calibration_entries(path, {"header": np.frombuffer(encoded, dtype=np.uint8), **arrays}, "hdf5")


@st.composite
def forged_calibrations(draw, header, arrays):
    """(header, arrays) of a valid calibration with header values edited and arrays replaced by
    arrays of other shapes, dtypes or values; the header's array descriptions follow the
    arrays unless an edit changes them."""
    arrays = dict(arrays)
    for name in draw(st.lists(st.sampled_from(list(io.CALIBRATION_ARRAYS)), max_size=3, unique=True)):
        choice = draw(st.sampled_from(("other", "values", "drop")))
        if choice == "drop":
            del arrays[name]
        elif choice == "values":
            old = arrays[name]
            arrays[name] = draw(hnp.arrays(old.dtype, old.shape))
        else:
            arrays[name] = draw(stored_arrays)
    header = json.loads(json.dumps(header))
    header["arrays"] = {name: io.calibration_files._array_entry(name, array) for name, array in arrays.items()}
    if draw(st.booleans()):
        header["metadata"] = draw(st.dictionaries(st.text(max_size=4), json_values, max_size=3))
    if draw(st.booleans()):
        header = draw(edited_json(header))
    return header, arrays


@fuzz(400)
@given(data=st.data())
def test_calibration_forged_with_a_valid_checksum(scratch, valid_calibration, data):
    """A checksum that matches proves nothing about the contents: arrays of any shape, dtype or
    value and any header values must still load into a valid Calibration or be refused; what
    loads holds exactly the arrays written."""
    header, arrays = data.draw(forged_calibrations(*_valid_entries(valid_calibration)))
    path = scratch / "forged.h5"
    _save_forged(path, header, arrays)
    result = load_calibration_checked(path)
    if not isinstance(result, Exception):
        calibration, _ = result
        for name in io.CALIBRATION_ARRAYS:
            np.testing.assert_array_equal(stored_array(calibration, name), arrays[name])


def stored_array(calibration, name: str) -> np.ndarray:
    """Array `name` of a calibration file as the loaded `calibration` holds it (the kernel
    residual's four arrays in its `wiener_residual`, zeros with m = 0 for none)."""
    if name in io.calibration_checks.RESIDUAL_ARRAYS:
        return io.calibration_files._residual_arrays(calibration)[name]
    return np.asarray(getattr(calibration, name))


def _with_header_text(valid: Valid, old: str, new: str) -> bytes:
    """The valid calibration (HDF5) with its header's JSON text edited (checksum left as it was)."""
    header, arrays = _valid_entries(valid)
    text = json.dumps(header)
    assert old in text
    path = valid.path.with_name("edited-header.h5")
    write_calibration_entries(path, {"header": np.frombuffer(text.replace(old, new, 1).encode(), dtype=np.uint8), **arrays}, "hdf5")
    return path.read_bytes()


def _with_directory_edit(valid: Valid, offset: int, value: int) -> bytes:
    """The valid old (.npz) calibration with one byte of every zip central-directory entry set."""
    data = bytearray(valid.content)
    for entry in offsets_of(valid.content, b"PK\x01\x02"):
        data[entry + offset] = value
    return bytes(data)


def _zip_of(members: dict, compression=zipfile.ZIP_STORED) -> bytes:
    buffer = pyio.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as archive_file:
        for name, content in members.items():
            archive_file.writestr(name, content)
    return buffer.getvalue()


def _damaged_deflate(valid: Valid) -> bytes:
    """np.savez_compressed of the valid old (.npz) calibration, bytes inside the dark frame's
    deflate stream overwritten (its zip entry intact)."""
    header, arrays = _valid_entries(valid)
    buffer = pyio.BytesIO()
    np.savez_compressed(buffer, header=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
    data = bytearray(buffer.getvalue())
    start = data.find(b"dark.npy") + len(b"dark.npy") + 20
    data[start : start + 40] = bytes(range(40))
    return bytes(data)


def _huge_compressed_shape(valid: Valid) -> bytes:
    """A deflated member whose .npy header claims 10^16 floats (35 PiB)."""
    text = "{'descr': '<f4', 'fortran_order': False, 'shape': (100000000000, 100000), }"
    text += " " * (117 - len(text)) + "\n"
    npy = b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text.encode()
    return _zip_of({"dark.npy": npy}, zipfile.ZIP_DEFLATED)


CALIBRATION_REGRESSIONS = {
    # OverflowError: math.isfinite of an integer beyond float range.
    "number-beyond-float": lambda new, old: _with_header_text(new, '"saturation": 16383', f'"saturation": {HUGE}'),
    # ValueError naming no file: int() refuses 4300+ digits.
    "5000-digit-integer": lambda new, old: _with_header_text(new, '"saturation": 16383', f'"saturation": {VAST}'),
    # RecursionError in json.
    "nested-100000-deep": lambda new, old: _with_header_text(new, '"metadata": {', '"metadata": {"x": ' + "[" * 100_000 + "]" * 100_000 + ","),
    # ValueError naming no file: the checksum's strict JSON refuses NaN.
    "nan-in-metadata": lambda new, old: _with_header_text(new, '"metadata": {', '"metadata": {"x": NaN,'),
    # RuntimeError: "File ... is encrypted, password required for extraction".
    "encrypted-member": lambda new, old: _with_directory_edit(old, 8, 1),
    # NotImplementedError: "That compression method is not supported".
    "unknown-compression": lambda new, old: _with_directory_edit(old, 10, 99),
    # zlib.error: "Error -3 while decompressing data".
    "damaged-deflate-stream": lambda new, old: _damaged_deflate(old),
    # tokenize.TokenError out of numpy's .npy header parser.
    "npy-header-not-a-dict": lambda new, old: _zip_of({"header.npy": _npy(np.zeros((), np.float32)).replace(b"{'descr'", b"z'descr'")}),
    # TypeError: memoryview cannot cast an empty array.
    "empty-header-array": lambda new, old: _zip_of({"header.npy": _npy(np.zeros((0, 0), np.float32))}),
    # MemoryError: the claimed shape was allocated before reading.
    "huge-compressed-shape": lambda new, old: _huge_compressed_shape(old),
}


@pytest.mark.parametrize("damage", list(CALIBRATION_REGRESSIONS))
def test_calibration_regressions(scratch, valid_calibration, valid_old_calibration, damage):
    """Found by the properties above; each raised something other than CalibrationFileError."""
    path = scratch / f"regression-{damage}.npz"
    result = load_calibration_checked(path, CALIBRATION_REGRESSIONS[damage](valid_calibration, valid_old_calibration))
    assert isinstance(result, CalibrationFileError)


@pytest.mark.parametrize("dtype", ["V4", "S1", "c8"])
def test_calibration_of_non_numbers_is_refused(scratch, valid_calibration, dtype):
    """A checksummed file whose dark frame holds raw bytes, strings or complex numbers: JAX's
    TypeError (naming no file) unless the dtype is checked first."""
    header, arrays = _valid_entries(valid_calibration)
    arrays["dark"] = np.zeros(arrays["dark"].shape, dtype)
    header["arrays"] = {name: io.calibration_files._array_entry(name, array) for name, array in arrays.items()}
    path = scratch / f"dark-{dtype}.h5"
    _save_forged(path, header, arrays)
    result = load_calibration_checked(path)
    assert isinstance(result, CalibrationFileError) and "array 'dark' has dtype" in str(result)


def test_calibration_in_big_endian_byte_order_loads(scratch, valid_calibration):
    """">f4" arrays (a big-endian writer) load as the same values (JAX alone refuses them with a
    TypeError)."""
    header, arrays = _valid_entries(valid_calibration)
    swapped = {name: array.astype(array.dtype.newbyteorder(">")) for name, array in arrays.items()}
    header["arrays"] = {name: io.calibration_files._array_entry(name, array) for name, array in swapped.items()}
    path = scratch / "big-endian.h5"
    _save_forged(path, header, swapped)
    calibration, _ = load_calibration_checked(path)
    residual = io.calibration_checks.RESIDUAL_ARRAYS  # m = 0 here: an affine estimator
    assert calibration.wiener_residual is None and arrays["wiener_residual_inducing"].shape[0] == 0
    for name, array in arrays.items():
        if name not in residual:
            np.testing.assert_array_equal(np.asarray(getattr(calibration, name)), array)


# ------------------------------------------------------------------------- instrument profile

PROFILE = """\
[instrument]
id = "sphere-1"
[wheels.a]
port = "/dev/ttyUSB0"
model = "FW212C"
open_slot = 12
move_timeout_s = 3.0
[wheels.b]
port = "loop://"
model = "FW102C"
open_slot = 6
[shutter]
port = "/dev/ttyUSB2"
model = "SC10"
[camera]
backend = "sim"
seed = 3
[bands]
450 = ["a", 1]
550 = ["a", 2]
650 = ["b", 1]
[acquisition]
frames_averaged = 2
dark_frames = 2
target_level = 0.8
target_percentile = 99.5
warmup_drift_percent = 0.5
warmup_interval_s = 0.0
warmup_checks = 2
warmup_timeout_s = 60.0
[layout]
white_patch = [0, 2, 3, 5]
holder = [2, 6, 0, 5]
[lamp]
state_file = "lamp.json"
[[samples]]
id = "s1"
set = "training"
background = "bg"
"""


def load_profile_checked(path: pathlib.Path, content: bytes):
    path.write_bytes(content)
    return loads_or_refuses("load_profile", lambda: load_profile(path), [path], errors=(ProfileError,))


def test_the_profile_used_here_is_valid(scratch):
    """The base of the mutations below loads (so they start from a profile that works)."""
    profile = load_profile_checked(scratch / "valid.toml", PROFILE.encode())
    assert profile.band_centres_nm == [450, 550, 650]
    assert profile.acquisition.warmup_timeout_s == 60.0 and profile.samples[0].id == "s1"


@fuzz(200)
@given(content=st.binary(max_size=800) | st.text(max_size=400).map(str.encode))
def test_profile_of_arbitrary_bytes(scratch, content):
    load_profile_checked(scratch / "bytes.toml", content)


@fuzz(500)
@given(data=st.data())
def test_profile_with_damaged_bytes(scratch, data):
    original = PROFILE.encode()
    hotspots = offsets_of(original, b"=", b"[", b'"')
    load_profile_checked(scratch / "damaged.toml", data.draw(damaged(original, hotspots)))


def _toml_float(value: float) -> str:
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return repr(value)


toml_tricky = st.sampled_from(
    (str(HUGE), str(-HUGE), VAST, "1e400", "nan", "inf", "-1", "0", "0x7fffffffffffffff", '""', '"a\\u0000b"',
     '"../x"', '"/abs"', "true", "1979-05-27T07:32:00Z", "{}", "{ x = 1 }", "[]", "[[1], [2]]", "[" * 2000 + "]" * 2000)
)
toml_scalars = st.one_of(
    st.integers().map(str),
    st.floats().map(_toml_float),
    st.booleans().map(lambda b: "true" if b else "false"),
    st.text(max_size=10).map(lambda s: json.dumps(s)),
)
toml_values = toml_tricky | _nested(
    toml_scalars, lambda inner: st.lists(inner, max_size=4).map(lambda v: "[" + ", ".join(v) + "]"), depth=2
)


@fuzz(600)
@given(data=st.data())
def test_profile_with_edited_values(scratch, data):
    """A value replaced by any TOML value, a line dropped or repeated, a key added."""
    lines = PROFILE.splitlines()
    for _ in range(data.draw(st.integers(1, 3))):
        index = data.draw(st.integers(0, len(lines) - 1))
        op = data.draw(st.sampled_from(("replace", "replace", "drop", "repeat", "add")))
        if op == "replace" and " = " in lines[index]:
            lines[index] = lines[index].split(" = ")[0] + " = " + data.draw(toml_values)
        elif op == "drop":
            del lines[index]
        elif op == "repeat":
            lines.insert(index, lines[index])
        elif op == "add":
            key = data.draw(st.sampled_from(("id", "port", "open_slot", "seed", "x", "400", "holder")))
            lines.insert(index + 1, f"{key} = {data.draw(toml_values)}")
        if not lines:
            break
    load_profile_checked(scratch / "edited.toml", ("\n".join(lines) + "\n").encode())


@pytest.mark.parametrize(
    "old, new",
    [
        ("move_timeout_s = 3.0", f"move_timeout_s = {HUGE}"),
        ("move_timeout_s = 3.0", f"move_timeout_s = {VAST}"),
        ("holder = [2, 6, 0, 5]", "holder = " + "[" * 100_000 + "]" * 100_000),
        ('state_file = "lamp.json"', 'state_file = "lamp\\u0000.json"'),
    ],
    ids=["number-beyond-float", "5000-digit-integer", "nested-100000-deep", "nul-in-file-name"],
)
def test_profile_regressions(scratch, old, new):
    """Cases the properties above found, each pinned: unchecked, they escape as OverflowError
    (float() of the integer), ValueError naming no file (int() refuses 4300+ digits),
    RecursionError (tomllib), ValueError "embedded null byte" (resolving the path)."""
    assert old in PROFILE
    path = scratch / "regression.toml"
    assert isinstance(load_profile_checked(path, PROFILE.replace(old, new, 1).encode()), ProfileError)


# ---------------------------------------------------------------------------- images (OIIO)

IMAGE_SHAPE = (6, 5, 3)
IMAGE_SUFFIXES = (".tif", ".tiff", ".exr", ".png")


@pytest.fixture(scope="module")
def valid_images(scratch) -> Valid:
    """Valid files of every image kind spherejax reads or writes, by file name."""
    rng = np.random.default_rng(3)
    names = [f"{nm}nm" for nm in BANDS]
    counts = rng.integers(0, 65535, IMAGE_SHAPE, dtype=np.uint16)
    io.write_frame(scratch / "frame.tif", counts, channel_names=names, attributes={"k": "v"})
    io.write_exr(scratch / "cube.exr", rng.uniform(0, 1, IMAGE_SHAPE).astype(np.float32), channel_names=names)
    io.write_exr(scratch / "cube-none.exr", rng.uniform(0, 1, IMAGE_SHAPE).astype(np.float32), channel_names=names, compression="none")
    io.write_png(scratch / "preview.png", rng.integers(0, 255, IMAGE_SHAPE).astype(np.uint8), channel_names=["R", "G", "B"])
    write_with_oiio(scratch / "pages.tif", [counts[..., i : i + 1] for i in range(IMAGE_SHAPE[2])])
    files = ("frame.tif", "cube.exr", "cube-none.exr", "preview.png", "pages.tif")
    return Valid(scratch, {name: (scratch / name).read_bytes() for name in files})


def read_image_checked(path: pathlib.Path):
    """Every image reader on one file: each loads or raises SpherejaxFileError naming it."""

    def check(what, load):
        return loads_or_refuses(what, load, [path], errors=(SpherejaxFileError,))

    frame = check("read_frame", lambda: io.read_frame(path))
    if isinstance(frame, np.ndarray):
        assert frame.dtype == np.uint16 and frame.ndim == 3
        assert check("frame_spec", lambda: io.frame_spec(path)) == frame.shape
    metadata = check("read_frame_metadata", lambda: io.read_frame_metadata(path))
    if isinstance(metadata, dict):
        assert isinstance(metadata["channel_names"], list) and isinstance(metadata["attributes"], dict)
    cube = check("read_cube", lambda: io.read_cube(path, expected_shape=IMAGE_SHAPE, band_centres_nm=BANDS))
    if isinstance(cube, np.ndarray):
        assert cube.shape == IMAGE_SHAPE and cube.dtype in (np.uint16, np.float32)
    check("read_band_files", lambda: io.read_band_files([path] * IMAGE_SHAPE[2], expected_shape=IMAGE_SHAPE))


@fuzz(200)
@given(content=st.binary(max_size=1000), suffix=st.sampled_from(IMAGE_SUFFIXES))
def test_images_of_arbitrary_bytes(scratch, content, suffix):
    path = scratch / f"bytes{suffix}"
    path.write_bytes(content)
    read_image_checked(path)


@fuzz(800)
@given(data=st.data())
def test_images_with_damaged_bytes(scratch, valid_images, data):
    """Valid TIFF (one page and multi-page), OpenEXR (PIZ and uncompressed) and PNG files with
    damaged bytes; damage in the first 400 bytes (the headers) is favoured."""
    name = data.draw(st.sampled_from(sorted(valid_images.content)))
    content = data.draw(damaged(valid_images.content[name], tuple(range(0, 400, 16))))
    path = scratch / f"damaged-{name}"
    path.write_bytes(content)
    read_image_checked(path)


def _tiff_with_description(path: pathlib.Path, description: str) -> None:
    """A valid 16-bit frame whose ImageDescription is `description` (other software's TIFF)."""
    spec = oiio.ImageSpec(IMAGE_SHAPE[1], IMAGE_SHAPE[0], IMAGE_SHAPE[2], "uint16")
    spec.attribute("ImageDescription", description)
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), spec)
    assert output.write_image(np.zeros(IMAGE_SHAPE, np.uint16))
    output.close()


@pytest.mark.parametrize("description", ['{"channel_names": ["a", "b", "c"], "attributes": [1]}', "[" * 100_000])
def test_frame_description_that_is_not_write_frames_json(scratch, description):
    """read_frame_metadata falls back to OpenImageIO's names (unchecked: TypeError from dict([1])
    and RecursionError from json); the cube reader ignores it (RecursionError)."""
    path = scratch / "described.tif"
    _tiff_with_description(path, description)
    assert io.read_frame_metadata(path)["attributes"] == {}
    assert io.read_cube(path, expected_shape=IMAGE_SHAPE, band_centres_nm=BANDS).shape == IMAGE_SHAPE


@pytest.mark.parametrize(
    "old, new",
    [
        (b"\x00\x00compression\x00", b"\x00\xe9compression\x00"),  # OIIO's open error quotes the byte
        (b"screenWindowWidth\x00float", b"screenWindowWidth\x00flo\x92t"),  # its warning after a seek does
    ],
    ids=["channel-list", "attribute-type"],
)
def test_exr_whose_errors_are_not_utf8(scratch, valid_images, old, new):
    """OpenImageIO's binding raised UnicodeDecodeError (naming no file) on messages quoting
    bytes of the file; found by test_images_with_damaged_bytes."""
    content = valid_images.content["cube.exr"]
    assert old in content
    path = scratch / "non-utf8.exr"
    path.write_bytes(content.replace(old, new, 1))
    read_image_checked(path)


# --------------------------------------------------------------------------------- kernels

lab_elements = st.floats(-128, 128, allow_nan=False, allow_infinity=False)


@st.composite
def lab_batches(draw, dtype):
    """(16, 3) Lab values: L in [0, 100], a and b in [-128, 128], greys and opposite hues
    (the ΔE00 discontinuity) among them."""
    lab = draw(hnp.arrays(np.float64, (16, 3), elements=lab_elements))
    lab[:, 0] = np.abs(lab[:, 0]) % 100.0
    return lab.astype(dtype)


@fuzz(100)
@given(data=st.data(), dtype=st.sampled_from((np.float32, np.float64)))
def test_delta_e_symmetric_non_negative_and_zero_on_identical_colours(data, dtype):
    lab1 = data.draw(lab_batches(dtype))
    lab2 = data.draw(lab_batches(dtype) | st.just(lab1 * np.array([1, -1, -1], dtype)))  # opposite hues
    d12 = np.asarray(sj.delta_e_2000(lab1, lab2))
    d21 = np.asarray(sj.delta_e_2000(lab2, lab1))
    assert d12.dtype == dtype and d12.shape == (16,)
    assert np.all(np.isfinite(d12)) and np.all(d12 >= 0)
    tolerance = 1e-5 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(d12, d21, rtol=tolerance, atol=tolerance)
    np.testing.assert_array_equal(np.asarray(sj.delta_e_2000(lab1, lab1)), 0)


frames_shape = (3, 4, 5)


@fuzz(100)
@given(
    dark=hnp.arrays(np.float64, frames_shape, elements=st.floats(0, 1000)),
    # No white signal within 1e-3 of 0 but 0 itself: XLA on CPU flushes subnormal numbers to 0,
    # so a white signal of 1e-40 counts as white == dark there (NaN), which numpy would not say.
    signal=hnp.arrays(
        np.float64, frames_shape,
        elements=st.floats(1e-3, 60000) | st.floats(-100, -1e-3) | st.sampled_from((0.0, -0.0, np.nan, np.inf, -np.inf)),
    ),
    dtype=st.sampled_from((np.float32, np.float64)),
)
def test_flat_field_of_the_white_standard_is_one(dark, signal, dtype):
    """v = (white - dark) / (white - dark): exactly 1 where white > dark (finite), NaN where not
    (white <= dark, or not finite). Exactly on CPU; within a GPU's division (`division_rtol`)."""
    dark, white = dark.astype(dtype), (dark + signal).astype(dtype)
    v = np.asarray(sj.flat_field(white, dark, white))
    assert v.dtype == dtype
    usable = np.isfinite(white - dark) & (white - dark > 0)
    assert_exact_or_close(v[usable], 1, division_rtol(dtype))
    assert np.all(np.isnan(v[~usable]))


@fuzz(100)
@given(
    v=hnp.arrays(np.float64, (7, 16), elements=st.floats(-10, 10)),
    p=hnp.arrays(np.float64, (16,), elements=st.floats(0.01, 100)),
    dtype=st.sampled_from((np.float32, np.float64)),
)
def test_stage2_with_identity_coefficients_is_stage1(v, p, dtype):
    v, p = v.astype(dtype), p.astype(dtype)
    coeffs = sj.identity_coeffs(16, dtype=dtype)
    stage2 = np.asarray(sj.stage2(v, p, coeffs))
    stage1 = np.asarray(sj.stage1(v, p))
    assert stage2.dtype == stage1.dtype == dtype
    np.testing.assert_array_equal(stage2, stage1)


# `correct` on one fixed shape: its patch box and saturation are static, so both are drawn
# from fixed values (one compiled program per raw dtype and path).
CH, CW, CB = 4, 6, 16
PATCH = np.zeros((CH, CW), bool)
PATCH[0:2, 4:6] = True

uint16_specials = st.sampled_from((0, 1, 16382, 16383, 65534, 65535)) | st.integers(0, 65535)
# Finite values up to 1e5 in size: far beyond 16-bit counts, but not where float32 products
# overflow (values near 3e38 over a white signal of 1 count would give inf, unflagged).
float32_specials = st.sampled_from((np.nan, np.inf, -np.inf, 16383.0, 65535.0, -0.0)) | st.floats(-1e5, 1e5, width=32)


@st.composite
def correction_cases(draw):
    """(raw, calibration) for `correct`: bulk values from a numpy generator seeded by
    hypothesis (a sample of reflectance -5 % to 120 % of the white, coefficients and a Wiener
    matrix of either sign), and hypothesis-drawn damage on top: raw values of any kind at a few
    pixels and bands, white standards at or below the dark frame or not finite, and sometimes a
    white patch that gives no usable ratio."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    raw_dtype = draw(st.sampled_from((np.uint16, np.float32)))
    dark = rng.uniform(0, 200, (CH, CW, CB)).astype(np.float32)
    signal = rng.uniform(1000, 12000, (CH, CW, CB)).astype(np.float32)  # unsaturated: 16383 > 200 + 1.2 * 12000
    pixel = st.tuples(st.integers(0, CH - 1), st.integers(0, CW - 1), st.integers(0, CB - 1))
    for index, value in draw(st.lists(st.tuples(pixel, st.sampled_from((0.0, -5.0, np.nan, np.inf, -np.inf))), max_size=3)):
        signal[index] = value
    level = rng.uniform(-0.05, 1.2, (CH, CW, 1)) * rng.uniform(0.9, 1.1, (CH, CW, CB))
    raw = dark + np.where(np.isfinite(signal), signal, 10000.0) * level
    if raw_dtype == np.uint16:
        raw = np.clip(np.rint(raw), 0, 65535)
    raw = raw.astype(raw_dtype)
    if draw(st.integers(0, 9)) == 0:  # a patch that sees no light: no usable ratio
        raw[PATCH] = np.rint(dark[PATCH]).astype(raw_dtype)
    specials = uint16_specials if raw_dtype == np.uint16 else float32_specials
    for index, value in draw(st.lists(st.tuples(pixel, specials), max_size=6)):
        raw[index] = value
    calibration = sj.Calibration(
        dark=dark,
        white=dark + signal,
        patch=PATCH,
        coeffs=rng.uniform(-2, 2, (CB, 4)).astype(np.float32),
        wiener=rng.uniform(-0.25, 0.25, (31, CB)).astype(np.float32),
        saturation=draw(st.sampled_from((None, 16383.0))),
    )
    return raw, calibration


def expected_pixel_flags(raw, calibration) -> np.ndarray:
    """The QUALITY bits 1, 2 and 4, from the inputs in numpy (the documented definition)."""
    raw_f = raw.astype(np.float32)
    dark, white = np.asarray(calibration.dark), np.asarray(calibration.white)
    level = calibration.saturation if calibration.saturation is not None else (65535.0 if raw.dtype == np.uint16 else None)
    with np.errstate(invalid="ignore"):
        saturated = np.zeros(raw.shape[:2], bool) if level is None else np.any(np.isfinite(raw_f) & (raw_f >= level), axis=-1)
        signal = white - dark
        no_flat_field = np.any(~(np.isfinite(signal) & (signal > 0)), axis=-1)
    nonfinite = np.any(~np.isfinite(raw_f), axis=-1)
    return (saturated * sj.QUALITY_SATURATED | nonfinite * sj.QUALITY_NONFINITE | no_flat_field * sj.QUALITY_WHITE_NOT_ABOVE_DARK).astype(np.uint8)


def check_correction(result, raw, calibration) -> None:
    quality = np.asarray(result.quality)
    reflectance, lab = np.asarray(result.reflectance), np.asarray(result.lab)
    assert quality.shape == (CH, CW) and reflectance.shape == (CH, CW, 31) and lab.shape == (CH, CW, 3)
    bad = quality != 0
    for name, out in (("reflectance", reflectance), ("lab", lab)):
        # NaN in every channel exactly where the quality is not 0; finite everywhere else.
        np.testing.assert_array_equal(np.isnan(out), np.broadcast_to(bad[..., None], out.shape), err_msg=name)
        assert np.all(np.isfinite(out[~bad])), name
    np.testing.assert_array_equal(quality & 7, expected_pixel_flags(raw, calibration))
    patch_unusable = (quality & sj.QUALITY_PATCH_UNUSABLE) != 0
    assert patch_unusable.all() or not patch_unusable.any()  # the whole image or no pixel
    assert patch_unusable.any() == (not np.all(np.isfinite(np.asarray(result.p))))
    # What the examples covered (pytest --hypothesis-show-statistics).
    event(f"raw {raw.dtype}")
    event("patch unusable" if patch_unusable.any() else f"{bad.sum()} of {bad.size} pixels flagged")
    for bit in (sj.QUALITY_SATURATED, sj.QUALITY_NONFINITE, sj.QUALITY_WHITE_NOT_ABOVE_DARK):
        if (quality & bit).any():
            event(f"quality bit {bit} set")


@fuzz(150)
@given(case=correction_cases())
def test_correct_never_raises_and_flags_exactly_the_bad_pixels(case):
    """On arbitrary uint16 and float32 raw (NaN and ±inf included) and calibrations with
    unusable pixels, `correct` raises nothing; the quality bits say what the inputs say, and
    the outputs are NaN exactly where the quality is not 0 and finite elsewhere."""
    raw, calibration = case
    check_correction(sj.correct(raw, calibration), raw, calibration)


@pytest.mark.skipif(not fused.built(), reason="the fused kernel was not built")
@fuzz(100)
@given(case=correction_cases())
def test_fused_kernel_agrees_with_the_jax_numpy_path(case):
    """The kernel (the default on CPU) and SPHEREJAX_FUSED=0 give the same quality, the same
    NaN positions and values equal to float32 rounding."""
    raw, calibration = case
    kernel = sj.correct(raw, calibration)
    with _environment(fused.SWITCH, "0"):
        plain = sj.correct(raw, calibration)
    check_correction(plain, raw, calibration)
    np.testing.assert_array_equal(np.asarray(kernel.quality), np.asarray(plain.quality))
    np.testing.assert_array_equal(np.asarray(kernel.p), np.asarray(plain.p))
    for name in ("reflectance", "lab"):
        got, want = np.asarray(getattr(kernel, name)), np.asarray(getattr(plain, name))
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=name)
        # Relative to the size of the values, which arbitrary coefficients make large.
        scale = max(1.0, float(np.nanmax(np.abs(want), initial=0.0)))
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * scale, err_msg=name)


@contextlib.contextmanager
def _environment(name: str, value: str):
    """Set an environment variable for a block (monkeypatch is function-scoped: hypothesis
    runs many examples per call)."""
    old = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            del os.environ[name]
        else:
            os.environ[name] = old
