"""The quality mask N.quality.png (`spherejax.io.quality_png`): a palette PNG whose indices are the
quality bits, read back by independent readers (Pillow: the indices; OpenImageIO: the palette's
colours; the chunks parsed here by hand), written by strips into the same bytes as at once,
atomically; the grey quality PNGs of earlier versions still read; and `spherejax correct` writes
it, `open_corrected` reads it and `--resume` verifies it."""

import hashlib
import struct
import zlib

import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

import spherejax
from spherejax import io
from spherejax.io import quality_png

from .batch_support import NAMES, frame, manifest_records, outputs_of, run

FLAGS = (spherejax.QUALITY_SATURATED, spherejax.QUALITY_NONFINITE, spherejax.QUALITY_WHITE_NOT_ABOVE_DARK,
         spherejax.QUALITY_PATCH_UNUSABLE, spherejax.QUALITY_BELOW_DARK)


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of each chunk of a PNG, every CRC checked."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    found, at = [], 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at:at + 4])
        kind, body = data[at + 4:at + 8], data[at + 8:at + 8 + length]
        (crc,) = struct.unpack(">I", data[at + 8 + length:at + 12 + length])
        assert crc == zlib.crc32(kind + body), kind
        found.append((kind, body))
        at += 12 + length
    assert at == len(data)
    return found


def every_combination() -> np.ndarray:
    """(4, 8) uint8: the 32 combinations of the five flags, 0..31."""
    return np.arange(32, dtype=np.uint8).reshape(4, 8)


def test_all_32_combinations_round_trip_through_pillow(tmp_path):
    bits = every_combination()
    digest = io.write_quality_png(tmp_path / "q.png", bits)
    assert digest == hashlib.sha256((tmp_path / "q.png").read_bytes()).hexdigest()
    with Image.open(tmp_path / "q.png") as image:
        assert image.format == "PNG" and image.mode == "P" and image.size == (8, 4)
        np.testing.assert_array_equal(np.asarray(image), bits)
        assert image.info["Description"] == quality_png.KEY_TEXT
        palette = np.asarray(image.getpalette(), np.uint8).reshape(-1, 3)
    np.testing.assert_array_equal(palette, quality_png.PALETTE)
    np.testing.assert_array_equal(io.read_quality_png(tmp_path / "q.png"), bits)
    # Any value of a byte too (bits not used yet), through spherejax's reader and Pillow.
    every_byte = np.arange(256, dtype=np.uint8).reshape(16, 16)
    io.write_quality_png(tmp_path / "all.png", every_byte[..., None])
    np.testing.assert_array_equal(io.read_quality_png(tmp_path / "all.png"), every_byte)


def test_the_chunks_are_a_plain_palette_png(tmp_path):
    """Parsed by hand: IHDR (8-bit, colour type 3, not interlaced), PLTE of 256 entries, the key
    in tEXt "Description", IDAT of filter 0 rows, IEND; no time stamp."""
    bits = every_combination()
    io.write_quality_png(tmp_path / "q.png", bits)
    found = chunks((tmp_path / "q.png").read_bytes())
    kinds = [kind for kind, _ in found]
    assert kinds[:2] == [b"IHDR", b"PLTE"] and kinds[-1] == b"IEND" and b"tIME" not in kinds
    assert struct.unpack(">IIBBBBB", found[0][1]) == (8, 4, 8, 3, 0, 0, 0)
    assert len(found[1][1]) == 256 * 3
    texts = dict(body.split(b"\0", 1) for kind, body in found if kind == b"tEXt")
    assert texts[b"Description"].decode("latin-1") == quality_png.KEY_TEXT
    for bit, (_, colour, meaning) in quality_png.BIT_COLOURS.items():
        if meaning != "not used":
            assert f"{bit} {colour} = " in quality_png.KEY_TEXT
    raw = zlib.decompress(b"".join(body for kind, body in found if kind == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(4, 9)
    assert (rows[:, 0] == 0).all()
    np.testing.assert_array_equal(rows[:, 1:], bits)


def test_the_palette_shows_each_flag_and_good_is_black(tmp_path):
    palette = quality_png.PALETTE
    assert palette.shape == (256, 3) and tuple(palette[0]) == (0, 0, 0)
    colours = [tuple(palette[bit]) for bit in FLAGS]
    assert len(set(colours)) == len(FLAGS)
    assert all(max(colour) == 255 for colour in colours)  # bright on black
    # Within 0..31 every flagged value is visible (not black) and, with several flags, has the
    # colour of its highest one.
    for value in range(1, 32):
        assert tuple(palette[value]) == tuple(palette[1 << (value.bit_length() - 1)]) != (0, 0, 0)
    # OpenImageIO expands the palette: the colours a viewer shows.
    bits = every_combination()
    io.write_quality_png(tmp_path / "q.png", bits)
    image = oiio.ImageInput.open(str(tmp_path / "q.png"))
    shown = image.read_image(oiio.UINT8)
    image.close()
    np.testing.assert_array_equal(shown, palette[bits])


def test_strips_give_the_bytes_of_one_write(tmp_path, rng=np.random.default_rng(11)):
    bits = rng.choice(np.array([0, 0, 0, 1, 2, 4, 5, 16, 31], np.uint8), size=(37, 53))
    whole = io.write_quality_png(tmp_path / "whole.png", bits)
    for heights in ([1] * 37, [5, 7, 11, 14], [36, 1]):
        with io.open_quality_png(tmp_path / "strips.png", (37, 53, 1)) as writer:
            row0 = 0
            for height in heights:
                writer.write_rows(row0, bits[row0:row0 + height, :, None])
                row0 += height
            assert writer.commit() == whole
        assert (tmp_path / "strips.png").read_bytes() == (tmp_path / "whole.png").read_bytes()
    # Large enough for several IDAT chunks.
    big = rng.integers(0, 32, (600, 800), dtype=np.uint8)
    io.write_quality_png(tmp_path / "big.png", big)
    assert sum(kind == b"IDAT" for kind, _ in chunks((tmp_path / "big.png").read_bytes())) > 1
    with Image.open(tmp_path / "big.png") as image:
        np.testing.assert_array_equal(np.asarray(image), big)


def test_written_atomically_or_not_at_all(tmp_path):
    target = tmp_path / "q.png"
    target.write_bytes(b"the earlier file")
    with io.open_quality_png(target, (4, 8)) as writer:
        writer.write_rows(0, every_combination()[:2])
        with pytest.raises(ValueError, match="expected the next row 2"):
            writer.write_rows(3, every_combination()[3:])
        with pytest.raises(ValueError, match="uint8"):
            writer.write_rows(2, every_combination()[2:].astype(np.uint16))
        with pytest.raises(io.SpherejaxFileError, match="has 2 of its 4 rows"):
            writer.commit()
    assert target.read_bytes() == b"the earlier file" and sorted(p.name for p in tmp_path.iterdir()) == ["q.png"]
    with io.open_quality_png(target, (4, 8)) as writer:
        writer.write_rows(0, every_combination())  # never committed: an error on the way
    assert target.read_bytes() == b"the earlier file" and sorted(p.name for p in tmp_path.iterdir()) == ["q.png"]
    with pytest.raises(io.SpherejaxFileError, match="cannot hold"):
        io.open_quality_png(tmp_path / "x.png", (4, 8, 3))


def test_an_earlier_versions_grey_quality_png_still_reads(tmp_path):
    bits = every_combination()
    io.write_png(tmp_path / "old.png", bits[..., None], channel_names=["quality"])  # as earlier versions wrote it
    with Image.open(tmp_path / "old.png") as image:
        assert image.mode == "L"
    np.testing.assert_array_equal(io.read_quality_png(tmp_path / "old.png"), bits)


def test_other_files_are_refused_in_one_line(tmp_path):
    io.write_png(tmp_path / "rgb.png", np.zeros((4, 8, 3), np.uint8), channel_names=["R", "G", "B"])
    with pytest.raises(io.SpherejaxFileError, match="mode RGB"):
        io.read_quality_png(tmp_path / "rgb.png")
    (tmp_path / "text.png").write_text("not a PNG")
    with pytest.raises(io.SpherejaxFileError, match="is not a PNG file"):
        io.read_quality_png(tmp_path / "text.png")
    with pytest.raises(io.SpherejaxFileError, match="cannot be read: No such file or directory"):
        io.read_quality_png(tmp_path / "missing.png")


def flagged_cube() -> np.ndarray:
    """A float32 cube with saturated, non-finite and below-dark pixels, and one with two flags."""
    raw = frame(np.random.default_rng(4)).astype(np.float32)
    raw[10, 11, 3] = np.nan
    raw[20:24, 30:40, 5] = -1000.0  # far below the dark level
    raw[30, 7, 2] = np.inf
    raw[30, 7, 9] = 20000.0  # and saturated
    return raw


def test_correct_writes_the_bits_and_resume_verifies_them(cal, tmp_path, capsys):
    raw = flagged_cube()
    io.write_exr(tmp_path / "a.exr", raw, channel_names=NAMES)
    out = tmp_path / "out"
    argv = ["correct", "-c", str(cal), str(tmp_path / "a.exr"), "-o", str(out)]
    assert run(argv, capsys)[0] == 0
    calibration, _ = io.load_calibration(cal)
    expected = np.asarray(spherejax.correct(raw, calibration).quality)
    assert {int(v) for v in np.unique(expected)} == {0, 1, 2, 3, 16}
    with Image.open(out / "a.quality.png") as image:
        assert image.mode == "P" and image.info["Description"] == quality_png.KEY_TEXT
        np.testing.assert_array_equal(np.asarray(image), expected)
    np.testing.assert_array_equal(spherejax.open_corrected(out / "a")["quality"].values, expected)
    (record,) = manifest_records(out)
    assert record["outputs"]["a.quality.png"] == hashlib.sha256((out / "a.quality.png").read_bytes()).hexdigest()

    reference = outputs_of(out)
    status, stdout, _ = run([*argv, "--resume"], capsys)
    assert status == 0 and stdout.strip() == "0 corrected, 1 skipped (already done), 0 failed"
    assert outputs_of(out) == reference
    # The same bits as an earlier version's grey PNG: not the file the manifest records, so not
    # provably spherejax's (docs/reliability.md, section 3): refused in one line and left as it is.
    io.write_png(out / "a.quality.png", expected[..., None], channel_names=["quality"])
    np.testing.assert_array_equal(spherejax.open_corrected(out / "a")["quality"].values, expected)
    grey = (out / "a.quality.png").read_bytes()
    status, stdout, stderr = run([*argv, "--resume"], capsys)
    assert status == 2 and "a.quality.png" in stderr and len(stderr.strip().splitlines()) == 1
    assert (out / "a.quality.png").read_bytes() == grey
    # Moved away by its owner, the output is redone with the bits the manifest records.
    (out / "a.quality.png").unlink()
    status, stdout, _ = run([*argv, "--resume"], capsys)
    assert status == 0 and stdout.strip() == "1 corrected, 0 skipped (already done), 0 failed"
    assert outputs_of(out) == reference

