"""Out-of-core correction: strip readers and writers, calibration files read by rows, and strip
results bit for bit equal to whole-image correction."""

from __future__ import annotations

import pathlib

import h5py
import numpy as np
import OpenImageIO as oiio
import pytest

import spherejax
from spherejax import archive, io, pipeline, stripwise
from spherejax.grid import BAND_CENTRES_NM

H, W, B = 45, 38, 16
BANDS = [int(b) for b in BAND_CENTRES_NM]
NAMES = [f"{b}nm" for b in BANDS]
PATCH = (20, 27, 9, 17)  # mid-image, so the patch's rows fall inside some strip, not the first


def make_calibration(rng, dtype=np.float32):
    dark = rng.uniform(90, 110, (H, W, B)).astype(dtype)
    white = rng.uniform(9000, 11000, (H, W, B)).astype(dtype)
    white[3, 5, 7] = dark[3, 5, 7]  # one pixel without a flat field
    patch = np.zeros((H, W), dtype=bool)
    r0, r1, c0, c1 = PATCH
    patch[r0:r1, c0:c1] = True
    coeffs = np.tile(np.asarray([0.01, 0.97, 0.02, -0.01], dtype), (B, 1))
    wiener = (rng.uniform(0, 1, (31, B)) / B).astype(dtype)
    # A non-zero Wiener offset r0: strips (read from the file, the last one padded) must carry
    # it like the whole image does.
    wiener_offset = rng.uniform(-0.05, 0.05, 31).astype(dtype)
    return spherejax.Calibration(
        dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener, saturation=16383.0,
        wiener_offset=wiener_offset,
    )


def make_raw(rng):
    raw = rng.integers(2000, 9000, (H, W, B)).astype(np.uint16)
    raw[0, 0, 0] = 16383  # saturated
    raw[PATCH[0] + 1, PATCH[2] + 2, 4] = 16383  # saturated inside the patch: left out of p
    return raw


@pytest.fixture
def rng():
    return np.random.default_rng(7)


@pytest.fixture
def calibration(rng):
    return make_calibration(rng)


@pytest.fixture
def calibration_path(tmp_path, calibration):
    path = tmp_path / "cal.h5"
    io.save_calibration(path, calibration, instrument_id="sphere-1", band_centres_nm=BANDS)
    return path


def strips_of(cube, calibration_file, rows_per_strip):
    parts = list(stripwise.correct_strips(cube, calibration_file, rows_per_strip=rows_per_strip))
    assert [row0 for row0, _ in parts] == list(range(0, H, rows_per_strip or H))
    return {key: np.concatenate([arrays[key] for _, arrays in parts]) for key in ("reflectance", "lab", "quality")}


def assert_same_as_whole(result: dict, whole: spherejax.CorrectionResult):
    for key in ("reflectance", "lab", "quality"):
        expected = np.asarray(getattr(whole, key))
        assert result[key].dtype == expected.dtype and result[key].shape == expected.shape, key
        # Bit for bit, NaNs in the same places.
        assert result[key].tobytes() == expected.tobytes(), key


# ------------------------------------------------------------------------------ strips = whole image


@pytest.mark.parametrize("rows_per_strip", [1, 4, 16, H, None])
def test_strips_equal_whole_image_correction(tmp_path, rng, calibration, calibration_path, rows_per_strip):
    raw = make_raw(rng)
    io.write_frame(tmp_path / "a.tif", raw, channel_names=NAMES)
    whole = spherejax.correct(raw, calibration)
    assert np.isnan(np.asarray(whole.reflectance)[0, 0]).all()  # the saturated pixel is flagged
    with io.open_calibration(calibration_path) as opened, io.open_cube(tmp_path / "a.tif", expected_shape=(H, W, B)) as cube:
        assert_same_as_whole(strips_of(cube, opened, rows_per_strip), whole)


def test_strips_equal_whole_image_with_calibration_on_disk(tmp_path, rng, calibration, calibration_path, monkeypatch):
    """A calibration larger than IN_MEMORY_BYTES keeps dark and white on disk, read by rows."""
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 1024)
    raw = make_raw(rng)
    io.write_frame(tmp_path / "a.tif", raw)
    with io.open_calibration(calibration_path) as opened:
        assert isinstance(opened._arrays["dark"], io.calibration_files._StoredArray)
        assert isinstance(opened._arrays["white"], io.calibration_files._StoredArray)
        with io.open_cube(tmp_path / "a.tif", expected_shape=(H, W, B)) as cube:
            assert_same_as_whole(strips_of(cube, opened, 7), spherejax.correct(raw, calibration))


def test_float_exr_input_with_nan_in_strips(tmp_path, rng, calibration, calibration_path):
    raw = make_raw(rng).astype(np.float32)
    raw[10, 11, 3] = np.nan
    io.write_exr(tmp_path / "a.exr", raw, channel_names=NAMES)  # stored sorted by name
    whole = spherejax.correct(raw, calibration)
    assert np.asarray(whole.quality)[10, 11] & spherejax.QUALITY_NONFINITE
    with io.open_calibration(calibration_path) as opened, io.open_cube(tmp_path / "a.exr", expected_shape=(H, W, B), band_centres_nm=BANDS) as cube:
        assert_same_as_whole(strips_of(cube, opened, 6), whole)


def test_unusable_patch_flags_every_strip(tmp_path, rng, calibration, calibration_path):
    raw = make_raw(rng)
    r0, r1, c0, c1 = PATCH
    raw[r0:r1, c0:c1, 2] = 16383  # every patch pixel saturated in one band: p is NaN there
    io.write_frame(tmp_path / "a.tif", raw)
    with io.open_calibration(calibration_path) as opened, io.open_cube(tmp_path / "a.tif", expected_shape=(H, W, B)) as cube:
        result = strips_of(cube, opened, 5)
    assert np.all(result["quality"] & spherejax.QUALITY_PATCH_UNUSABLE)
    assert np.isnan(result["reflectance"]).all()


def test_correct_with_p_on_calibration_rows(rng, calibration):
    raw = make_raw(rng)
    p = pipeline.patch_ratio(raw, calibration)
    whole = spherejax.correct(raw, calibration)
    assert np.asarray(p).tobytes() == np.asarray(whole.p).tobytes()
    part = spherejax.correct(raw[10:30], calibration.rows(10, 30), p=p)
    assert np.asarray(part.reflectance).tobytes() == np.asarray(whole.reflectance)[10:30].tobytes()


def test_calibration_rows_refuses_without_p(rng, calibration):
    rows = calibration.rows(0, 5)
    assert rows.patch is None and rows.image_shape == (5, W)
    with pytest.raises(ValueError, match="p: expected the whole image's white-patch ratio"):
        spherejax.correct(make_raw(rng)[:5], rows)
    with pytest.raises(ValueError, match=r"p: expected shape \(16,\)"):
        spherejax.correct(make_raw(rng)[:5], rows, p=np.ones((2, B)))
    with pytest.raises(ValueError, match="rows: expected 0 <= row0 < row1"):
        calibration.rows(5, 5)
    with pytest.raises(ValueError, match="has no patch"):
        pipeline.patch_ratio(make_raw(rng)[:5], rows)


def test_strip_height_bounds_memory():
    rows = stripwise.strip_height(8192, 8192, 16)
    assert rows % stripwise.ROW_QUANTUM == 0
    assert rows * 8192 * stripwise.BYTES_PER_PIXEL <= stripwise.STRIP_BYTES
    assert stripwise.strip_height(40, 48, 16) == 40  # a small image is one strip
    assert stripwise.strip_height(10, 10**9, 16) == 1
    assert stripwise.strip_height(1024, 1024, 16) == 128  # 8 strips, none padded (not 7 of 160)


def test_cube_of_the_wrong_shape_is_refused(tmp_path, rng, calibration_path):
    io.write_frame(tmp_path / "a.tif", rng.integers(0, 100, (H, W + 1, B)).astype(np.uint16))
    with io.open_calibration(calibration_path) as opened, io.open_cube(tmp_path / "a.tif", expected_shape=(H, W + 1, B)) as cube:
        with pytest.raises(ValueError, match=r"cube: expected shape \(45, 38, 16\)"):
            next(stripwise.correct_strips(cube, opened))


# --------------------------------------------------------------------------------------- readers


def write_layouts(folder: pathlib.Path, raw: np.ndarray) -> dict:
    """The same cube in every layout `open_cube` / `open_band_files` accept -> name: opener."""
    io.write_frame(folder / "channels.tif", raw, channel_names=NAMES)
    io.write_exr(folder / "scanline.exr", raw.astype(np.float32), channel_names=NAMES)
    spec = oiio.ImageSpec(W, H, B, oiio.FLOAT)
    spec.channelnames = tuple(NAMES)
    spec.tile_width, spec.tile_height = 16, 16
    tiled = oiio.ImageOutput.create(str(folder / "tiled.exr"))
    assert tiled.open(str(folder / "tiled.exr"), spec)
    assert tiled.write_image(raw.astype(np.float32))
    tiled.close()
    pages = oiio.ImageOutput.create(str(folder / "pages.tif"))
    page_specs = [oiio.ImageSpec(W, H, 1, oiio.UINT16) for _ in range(B)]
    assert pages.open(str(folder / "pages.tif"), page_specs)
    for band in range(B):
        if band:
            assert pages.open(str(folder / "pages.tif"), page_specs[band], "AppendSubimage")
        assert pages.write_image(np.ascontiguousarray(raw[..., band : band + 1]))
    pages.close()
    band_files = []
    for band, nm in enumerate(BANDS):
        band_files.append(folder / f"x_{nm}nm.tif")
        io.write_frame(band_files[-1], np.ascontiguousarray(raw[..., band : band + 1]))
    shape = dict(expected_shape=(H, W, B))
    return {
        "channels.tif": lambda: io.open_cube(folder / "channels.tif", band_centres_nm=BANDS, **shape),
        "scanline.exr": lambda: io.open_cube(folder / "scanline.exr", band_centres_nm=BANDS, **shape),
        "tiled.exr": lambda: io.open_cube(folder / "tiled.exr", band_centres_nm=BANDS, **shape),
        "pages.tif": lambda: io.open_cube(folder / "pages.tif", **shape),
        "band files": lambda: io.open_band_files(band_files, **shape),
    }


def test_every_layout_reads_the_same_rows(tmp_path, rng):
    raw = make_raw(rng)
    for name, opener in write_layouts(tmp_path, raw).items():
        with opener() as cube:
            assert cube.shape == (H, W, B), name
            for row0, row1 in [(0, H), (0, 1), (5, 21), (15, 17), (31, H), (H - 1, H)]:
                rows = cube.read_rows(row0, row1)
                np.testing.assert_array_equal(rows, raw[row0:row1].astype(rows.dtype), err_msg=f"{name} {row0}:{row1}")
            with pytest.raises(ValueError, match="rows: expected 0 <= row0 < row1"):
                cube.read_rows(3, H + 1)


def test_damaged_rows_are_found_when_read(tmp_path, rng):
    """A strip reader meets the damage only when it gets to it: the error names the file."""
    raw = rng.integers(0, 65535, (400, W, B)).astype(np.uint16)  # incompressible: many TIFF strips
    path = tmp_path / "cut.tif"
    io.write_frame(path, raw)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.8)])
    with io.open_cube(path, expected_shape=(400, W, B)) as cube:
        np.testing.assert_array_equal(cube.read_rows(0, 8), raw[:8])
        with pytest.raises(io.SpherejaxFileError, match=rf"{path}: is truncated or corrupted: rows 392 to 399 of its 400 cannot be (read|decoded)"):
            cube.read_rows(392, 400)


# --------------------------------------------------------------------------------------- writers


@pytest.mark.parametrize("rows", [1, 7, 16, H])
def test_writer_bytes_do_not_depend_on_strips(tmp_path, rng, rows):
    image = rng.uniform(0, 1, (H, W, 31)).astype(np.float32)
    preview = rng.integers(0, 255, (H, W, 3)).astype(np.uint8)
    exr_digest = io.write_exr(tmp_path / "whole.exr", image, channel_names=[f"c{i}" for i in range(31)])
    png_digest = io.write_png(tmp_path / "whole.png", preview, channel_names=["R", "G", "B"])
    with io.open_exr(tmp_path / "strips.exr", image.shape, channel_names=[f"c{i}" for i in range(31)]) as exr, \
            io.open_png(tmp_path / "strips.png", preview.shape, channel_names=["R", "G", "B"]) as png:
        for row0 in range(0, H, rows):
            exr.write_rows(row0, image[row0 : row0 + rows])
            png.write_rows(row0, preview[row0 : row0 + rows])
        assert (exr.commit(), png.commit()) == (exr_digest, png_digest)
    assert (tmp_path / "strips.exr").read_bytes() == (tmp_path / "whole.exr").read_bytes()
    assert (tmp_path / "strips.png").read_bytes() == (tmp_path / "whole.png").read_bytes()


def test_writer_left_unfinished_leaves_nothing(tmp_path, rng):
    image = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    (tmp_path / "old.exr").write_bytes(b"earlier output")
    with pytest.raises(RuntimeError):
        with io.open_exr(tmp_path / "old.exr", image.shape, channel_names=["L*", "a*", "b*"]) as writer:
            writer.write_rows(0, image[:10])
            raise RuntimeError("the input turned out to be damaged")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.exr"]
    assert (tmp_path / "old.exr").read_bytes() == b"earlier output"

    with io.open_exr(tmp_path / "new.exr", image.shape, channel_names=["L*", "a*", "b*"]) as writer:
        writer.write_rows(0, image[:10])
        with pytest.raises(ValueError, match="rows: expected the next row 10, got 20"):
            writer.write_rows(20, image[20:30])
        with pytest.raises(io.SpherejaxFileError, match=rf"new.exr: has 10 of its {H} rows"):
            writer.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.exr"]


# ----------------------------------------------------------------------- calibration files by rows


def test_calibration_file_rows_match_the_loaded_calibration(calibration_path, calibration, monkeypatch):
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)  # everything on disk
    with io.open_calibration(calibration_path) as opened:
        assert opened.image_shape == (H, W) and opened.bands == B and opened.patch_box == PATCH
        rows = opened.rows(11, 29)
        np.testing.assert_array_equal(np.asarray(rows.dark), np.asarray(calibration.dark)[11:29])
        np.testing.assert_array_equal(np.asarray(rows.white), np.asarray(calibration.white)[11:29])
        whole = opened.calibration()
        for name in (n for n in io.CALIBRATION_ARRAYS if n not in io.calibration_checks.RESIDUAL_ARRAYS):
            assert np.asarray(getattr(whole, name)).tobytes() == np.asarray(getattr(calibration, name)).tobytes()
        assert whole.wiener_residual is None and rows.wiener_residual is None  # an affine estimator
        r0, r1, c0, c1 = PATCH
        box = opened.patch_calibration
        np.testing.assert_array_equal(np.asarray(box.white), np.asarray(calibration.white)[r0:r1, c0:c1])
        assert bool(np.all(np.asarray(box.patch)))


def test_calibration_file_on_disk_detects_tampering(calibration_path, monkeypatch):
    """The checksum of arrays left on disk is verified block by block, as for a loaded one."""
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    monkeypatch.setattr(io.calibration_hdf5, "_READ_BLOCK", 4096)  # many blocks
    with h5py.File(calibration_path, "r") as stored:
        at = stored["dark"].id.get_chunk_info(0).byte_offset  # the dark frame's first chunk
    data = bytearray(calibration_path.read_bytes())
    data[at + 5000] ^= 0x01
    calibration_path.write_bytes(bytes(data))
    with pytest.raises(io.CalibrationFileError, match="does not match its checksum: tampered or corrupted"):
        io.open_calibration(calibration_path)


def test_calibration_file_reads_the_file_it_opened(tmp_path, calibration_path, calibration, rng, monkeypatch):
    """Replacing the calibration file during a batch cannot mix two calibrations: reads go to the
    file that was opened and verified."""
    monkeypatch.setattr(io.calibration_files, "IN_MEMORY_BYTES", 0)
    with io.open_calibration(calibration_path) as opened:
        io.save_calibration(calibration_path, make_calibration(rng), instrument_id="sphere-1", band_centres_nm=BANDS)
        np.testing.assert_array_equal(np.asarray(opened.rows(0, H).dark), np.asarray(calibration.dark))


# ------------------------------------------------------------------------------------ the archive


@pytest.mark.parametrize("output_format", archive.OUTPUT_FORMATS)
def test_archive_output_bytes_do_not_depend_on_strips(tmp_path, rng, calibration_path, output_format):
    raw = make_raw(rng)
    io.write_frame(tmp_path / "a.tif", raw, channel_names=NAMES)
    [spec] = archive.discover_inputs([tmp_path / "a.tif"], tmp_path / "out1")
    outputs = {}
    for rows in (None, 1, 6):
        out = tmp_path / f"out-{rows}"
        out.mkdir()
        result = archive.correct_input(spec, out, calibration_path, rows_per_strip=rows, output_format=output_format)
        assert result.status == "done", result.reason
        outputs[rows] = {p.name: p.read_bytes() for p in sorted(out.iterdir())}
    assert outputs[1] == outputs[None] and outputs[6] == outputs[None]
    assert sorted(outputs[None]) == sorted(f"a.{kind}" for kind in archive.OUTPUT_KINDS_BY_FORMAT[output_format])


def test_archive_input_damaged_mid_image_leaves_nothing(tmp_path, rng, calibration_path):
    """Damage found after the first strips were written: no output, no temporary file."""
    big = (400, W)
    calibration = make_calibration(rng)
    fields = {name: np.asarray(getattr(calibration, name)) for name in ("coeffs", "wiener")}
    dark = np.resize(np.asarray(calibration.dark), (*big, B))
    white = np.resize(np.asarray(calibration.white), (*big, B))
    patch = np.zeros(big, dtype=bool)
    patch[2:6, 2:6] = True
    tall = spherejax.Calibration(dark=dark, white=white, patch=patch, saturation=16383.0, **fields)
    path = tmp_path / "tall.h5"
    io.save_calibration(path, tall, instrument_id="sphere-1", band_centres_nm=BANDS)
    raw = rng.integers(0, 16000, (*big, B)).astype(np.uint16)
    io.write_frame(tmp_path / "cut.tif", raw)
    data = (tmp_path / "cut.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(data[: int(len(data) * 0.8)])
    [spec] = archive.discover_inputs([tmp_path / "cut.tif"], tmp_path / "out")
    out = tmp_path / "out"
    out.mkdir()
    result = archive.correct_input(spec, out, path, rows_per_strip=16)
    assert result.status == "failed" and "cut.tif: is truncated or corrupted: rows" in result.reason
    assert list(out.iterdir()) == []


# ------------------------------------------------------------------------------ one plan per input


def test_strips_of_every_input_reuse_the_plan_of_the_first(tmp_path, rng, calibration_path, monkeypatch):
    """Three inputs of seven strips each, the calibration held in memory: the first input makes
    every plan its strips need (with the fused kernel, one: the whole frame's, whose `Plan.rows`
    slices dark and white for each strip and runs the kernel on the NumPy rows where they lie),
    the others make none; the numbers are the whole-image call's."""
    from spherejax._engine import fused
    from spherejax._engine.plan import Plan

    made, direct = [], []
    plan_init, correct_directly = Plan.__init__, Plan._correct_directly

    def counting_init(self, calibration, shape, *args, **kwargs):
        made.append(tuple(shape))
        plan_init(self, calibration, shape, *args, **kwargs)

    def counting_direct(self, raw, p=None, rows=None):
        direct.append(rows)
        return correct_directly(self, raw, p, rows)

    monkeypatch.setattr(Plan, "__init__", counting_init)
    monkeypatch.setattr(Plan, "_correct_directly", counting_direct)
    per_input = []
    with io.open_calibration(calibration_path) as opened:
        whole = opened.calibration()
        for k in range(3):
            raw = make_raw(np.random.default_rng(k))
            io.write_frame(tmp_path / f"{k}.tif", raw)
            with io.open_cube(tmp_path / f"{k}.tif", expected_shape=(H, W, B)) as cube:
                assert_same_as_whole(strips_of(cube, opened, 7), spherejax.correct(raw, whole))
            per_input.append(len(made))
    assert per_input[1] == per_input[2] == per_input[0], made
    strips = -(-H // 7)
    if fused.enabled():
        # The whole frame's plan and the patch box's, nothing a strip: every strip went direct.
        assert sorted(made) == sorted([(H, W, B), (PATCH[1] - PATCH[0], PATCH[3] - PATCH[2], B)]), made
        assert direct == [(r, min(r + 7, H)) for r in range(0, H, 7)] * 3
    else:
        assert len(made) == 2 + strips and direct == []


def test_one_strip_of_an_in_memory_calibration_is_the_whole_frame_call(tmp_path, rng, calibration_path, monkeypatch):
    """An image corrected in one strip with a calibration held in memory goes through
    `correct(frame, calibration)` itself (the plan of the whole frame, p from the patch's box),
    with the file's one Calibration object; the numbers are the strips'."""
    calls = []
    real = stripwise.correct

    def spy(raw, calibration, **kwargs):
        calls.append((raw.shape, calibration, sorted(kwargs)))
        return real(raw, calibration, **kwargs)

    monkeypatch.setattr(stripwise, "correct", spy)
    raw = make_raw(rng)
    io.write_frame(tmp_path / "a.tif", raw)
    with io.open_calibration(calibration_path) as opened, io.open_cube(tmp_path / "a.tif", expected_shape=(H, W, B)) as cube:
        assert opened.in_memory and opened.calibration() is opened.calibration()
        one = strips_of(cube, opened, None)
        assert calls == [((H, W, B), opened.calibration(), [])]
        calls.clear()
        assert_same_as_whole(strips_of(cube, opened, 4), spherejax.correct(raw, opened.calibration()))
        assert calls == []  # several strips: the whole plan's rows (the test above)
    assert_same_as_whole(one, spherejax.correct(raw, opened.calibration()))


@pytest.mark.parametrize("switch", ["auto", "0"])
def test_plan_rows_equal_correct_with_the_calibration_rows(rng, calibration, monkeypatch, switch):
    """`Plan.rows` (the fused kernel on NumPy rows, or with SPHEREJAX_FUSED=0 the rows' own plan)
    gives `correct(rows, calibration.rows(...), p=p)` bit for bit; rows outside the image or of
    another width are refused naming the shape."""
    monkeypatch.setenv("SPHEREJAX_FUSED", switch)
    raw = make_raw(rng)
    p = pipeline.patch_ratio(raw, calibration)
    prepared = spherejax.plan(calibration, raw.shape, dtype=raw.dtype)
    for row0, row1 in ((0, 7), (21, 45), (44, 45)):
        got = prepared.rows(np.ascontiguousarray(raw[row0:row1]), row0, p)
        want = spherejax.correct(raw[row0:row1], calibration.rows(row0, row1), p=p)
        for key in ("reflectance", "lab", "quality"):
            assert np.asarray(getattr(got, key)).tobytes() == np.asarray(getattr(want, key)).tobytes(), (row0, key)
    with pytest.raises(ValueError, match=r"expected rows \(n, 38, 16\) of the image from row 40"):
        prepared.rows(raw[:10], 40, p)  # rows 40:50 of a 45-row image
    with pytest.raises(ValueError, match=r"got shape \(3, 37, 16\)"):
        prepared.rows(raw[:3, :37], 0, p)


def test_a_derivative_with_respect_to_p_of_numpy_rows(rng, calibration):
    """NumPy rows given a traced p (jax.grad with respect to it) take the jitted step, not the fused
    kernel's direct call (which reads concrete arrays): the derivative is the jax.numpy path's."""
    import jax

    raw = make_raw(rng)
    p = pipeline.patch_ratio(raw, calibration)
    rows, strip = calibration.rows(7, 21), np.ascontiguousarray(raw[7:21])

    def loss(frames):
        return lambda ratio: jax.numpy.nansum(spherejax.correct(frames, rows, p=ratio).lab[..., 0])

    got = np.asarray(jax.grad(loss(strip))(p))
    # The same rows as a jax.Array, which never take the direct call: the jitted step's derivative.
    want = np.asarray(jax.grad(loss(jax.numpy.asarray(strip)))(p))
    assert np.isfinite(got).all() and np.abs(got).max() > 0
    np.testing.assert_array_equal(got, want)
    # And against central differences in float64 terms of the same function (float32 sums: 5 %).
    step = 1e-2
    numeric = [(loss(strip)(p.at[b].add(step)) - loss(strip)(p.at[b].add(-step))) / (2 * step) for b in range(B)]
    np.testing.assert_allclose(got, np.asarray(numeric), rtol=5e-2)


def test_a_calibration_keeps_its_rows_and_regions(rng, calibration):
    """`Calibration.rows` and `Calibration.box` give the same object for the same pixels (so the
    strips and regions of every input reuse one plan), the right pixels, no patch, and refuse
    pixels outside the image naming them; a pickled calibration carries none of them."""
    import pickle

    rows, box = calibration.rows(3, 9), calibration.box(20, 27, 9, 17)
    assert calibration.rows(3, 9) is rows and calibration.box(20, 27, 9, 17) is box
    assert rows.patch is None and box.patch is None
    assert np.asarray(rows.dark).tobytes() == np.asarray(calibration.dark)[3:9].tobytes()
    assert np.asarray(box.white).tobytes() == np.asarray(calibration.white)[20:27, 9:17].tobytes()
    assert spherejax.plan(box, (7, 8, B)) is spherejax.plan(calibration.box(20, 27, 9, 17), (7, 8, B))
    with pytest.raises(ValueError, match=r"box: expected 0 <= row0 < row1 <= 45 and 0 <= col0 < col1 <= 38, got 20:27, 9:39"):
        calibration.box(20, 27, 9, 39)
    assert "_parts" not in pickle.loads(pickle.dumps(calibration)).__dict__


def test_refusals_of_rows_padding_and_a_plan_without_its_calibration(rng, calibration_path, monkeypatch):
    """`CalibrationFile.rows` refuses a padding shorter than the rows asked for, naming both; a plan
    whose calibration is gone refuses `Plan.rows` where it needs the calibration's rows (off the
    fused kernel), saying why, rather than failing on None."""
    import gc

    with io.open_calibration(calibration_path) as opened:
        with pytest.raises(ValueError, match=r"^padded_to: expected at least the 6 rows asked for, got 4$"):
            opened.rows(3, 9, padded_to=4)
        assert opened.rows(3, 9, padded_to=8) is opened.rows(3, 9, padded_to=8)
        assert np.asarray(opened.rows(3, 9, padded_to=8).dark)[6:].tobytes() == bytes(2 * W * B * 4)
    monkeypatch.setenv("SPHEREJAX_FUSED", "0")
    raw = make_raw(rng)
    prepared = spherejax.plan(make_calibration(np.random.default_rng(1)), raw.shape, dtype=raw.dtype)
    gc.collect()
    assert prepared.calibration is None
    with pytest.raises(ValueError, match=r"^rows: this plan's calibration is gone"):
        prepared.rows(np.ascontiguousarray(raw[:5]), 0, np.ones(B, np.float32))
