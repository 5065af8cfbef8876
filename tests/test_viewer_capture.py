"""What the viewer shows, without Qt or napari (spherejax.viewer.capture, spherejax.viewer.outputs,
`measurement.measure_reflectances`) and `spherejax view`'s refusals that come before any window:
a pixel's readout against `open_corrected` and `correct(..., noise=)`, Lab under other
illuminants against colour-science, a region of the file against `spherejax.measure`, and the
files refused or written. These run without the viewer extra."""

import numpy as np
import pytest

import spherejax as sj
from spherejax import io, measurement_files
from spherejax.cli import view_command
from spherejax.measurement import measure_reflectances
from spherejax.measurement_files import RegionResult
from spherejax.viewer import outputs
from spherejax.viewer.capture import CorrectedCapture, Reference, quality_names

from .helpers import assert_refused, colour_lab, corrected_oracle, listing, run_cli

PIXELS = [(0, 0), (5, 7), (20, 31), (-1, -1)]


@pytest.fixture(scope="module")
def capture(corrected_workspace):
    files = corrected_workspace
    return CorrectedCapture(files["output"], calibration=files["calibration"], raw=files["raw"])


@pytest.fixture(scope="module")
def corrected(corrected_workspace):
    """correct() of the raw cube with the calibration's noise model: the per-pixel oracle."""
    oracle = corrected_oracle(corrected_workspace)
    return oracle["result"], oracle["raw"], oracle["calibration"], oracle["noise"]


def _pixel(capture, rc):
    h, w = capture.shape
    return rc[0] % h, rc[1] % w


@pytest.mark.parametrize("rc", PIXELS)
def test_a_pixel_reads_as_open_corrected_has_it(capture, corrected_workspace, rc):
    row, col = _pixel(capture, rc)
    ds = sj.open_corrected(corrected_workspace["output"])
    r = capture.pixel(row, col, uncertainty=False)
    np.testing.assert_array_equal(r["reflectance"], ds["reflectance"].values[row, col])
    np.testing.assert_array_equal(r["lab"], ds["lab"].values[row, col])
    assert r["quality"] == int(ds["quality"].values[row, col])
    assert r["illuminant"] == ds.attrs["spherejax:illuminant"]
    np.testing.assert_array_equal(r["wavelength_nm"], np.arange(400, 701, 10))
    assert "u_lab" not in r


@pytest.mark.parametrize("rc", [(20, 31), (40, 50), (61, 83)])
def test_a_pixels_uncertainty_is_corrects(capture, corrected, rc):
    """u_lab of the readout (measure of one pixel) is the u that correct(..., noise=) propagates."""
    result, _, _, _ = corrected
    row, col = _pixel(capture, rc)
    r = capture.pixel(row, col)
    assert r["quality"] == 0
    np.testing.assert_allclose(r["u_lab"], np.asarray(result.lab_u)[row, col], rtol=2e-3, atol=1e-5)
    np.testing.assert_allclose(r["u_reflectance"], np.asarray(result.reflectance_u)[row, col], rtol=2e-3, atol=1e-7)
    assert np.all(r["u_lab"] > 0)


def test_a_flagged_pixel_reads_its_bits_and_no_uncertainty(capture, corrected):
    """The corner lies outside some band's frame once the bands are registered (NOT_COVERED)."""
    result, _, _, _ = corrected
    r = capture.pixel(0, 0)
    assert r["quality"] == int(np.asarray(result.quality)[0, 0]) != 0
    assert "NOT_COVERED" in r["quality_names"]
    assert np.all(np.isnan(r["lab"])) and "u_lab" not in r


@pytest.mark.parametrize("illuminant", ["A", "F2"])
def test_lab_under_another_illuminant_is_colour_sciences(capture, illuminant):
    r = capture.pixel(9, 11, illuminant=illuminant, uncertainty=False)
    np.testing.assert_allclose(r["lab"], colour_lab([r["reflectance"]], illuminant)[0], atol=2e-3)
    assert r["illuminant"] == illuminant


def test_delta_e_against_a_typed_reference_is_ciede2000(capture):
    reference = Reference.typed("50, 10, -5")
    r = capture.pixel(3, 4, reference=reference)
    expected = float(sj.delta_e_2000(np.asarray(r["lab"], np.float32), np.array([50, 10, -5], np.float32)))
    assert r["delta_e"] == pytest.approx(expected, abs=1e-4)
    assert r["reference"] == "L*a*b* = (50, 10, -5)"
    assert 0 < r["delta_e_u"] < 1
    same = capture.pixel(3, 4, reference=Reference.of_pixel(r))
    assert same["delta_e"] == pytest.approx(0.0, abs=1e-4)


@pytest.mark.parametrize("text", ["50,10", "a,b,c", "150,0,0", "50,nan,0"])
def test_a_typed_reference_that_is_not_lab_is_refused(text):
    with pytest.raises(ValueError, match="expected three numbers L,a,b"):
        Reference.typed(text)


def test_quality_bits_are_named():
    assert quality_names(0) == []
    assert quality_names(1 | 16) == ["SATURATED", "BELOW_DARK"]
    assert quality_names(32 | 128) == ["NOT_COVERED", "bit 7"]


def test_a_region_with_the_raw_frames_is_measures(capture, corrected):
    _, raw, calibration, noise = corrected
    mask = np.zeros(capture.shape, bool)
    mask[4:12, 6:20] = True
    got = capture.region(mask, illuminant="A")
    expected = sj.measure(raw, calibration, mask, noise, illuminant="A")
    np.testing.assert_array_equal(got.reflectance, expected.reflectance)
    np.testing.assert_array_equal(got.lab_covariance, expected.lab_covariance)
    assert (got.pixels, got.excluded, got.illuminant) == (expected.pixels, expected.excluded, "A")


def test_a_region_of_the_file_alone_is_its_mean_reflectance(corrected_workspace):
    """Without the raw frames: the mean of the file's reflectances over the region's good pixels,
    and Lab of that mean (colour-science), as `measure` defines them; no covariance."""
    capture = CorrectedCapture(corrected_workspace["output"])
    ds = sj.open_corrected(corrected_workspace["output"])
    mask = np.zeros(capture.shape, bool)
    mask[2:9, 3:30] = True
    got = capture.region(mask)
    good = mask & (ds["quality"].values == 0)
    mean = ds["reflectance"].values[good].astype(np.float64).mean(axis=0)
    np.testing.assert_allclose(got.reflectance, mean, rtol=1e-12)
    np.testing.assert_allclose(got.lab, colour_lab([mean], capture.file_illuminant)[0], atol=2e-3)
    assert got.pixels == good.sum() and got.excluded == mask.sum() - good.sum()
    assert got.lab_covariance is None and not capture.has_uncertainty


def test_measure_reflectances_is_measure_for_an_affine_estimator(rng=np.random.default_rng(4)):
    """For the Wiener (affine) estimator, `measure`'s mean reflectance is the mean of the
    per-pixel ones: the identity the file-only region stands on."""
    h, w, bands = 12, 14, 16
    dark = np.full((h, w, bands), 100, np.float32)
    white = np.full((h, w, bands), 20000, np.float32) * np.linspace(0.8, 1, w)[None, :, None]
    patch = np.zeros((h, w), bool)
    patch[:3, :3] = True
    coeffs = np.tile(np.array([0.01, 0.95, 0.03, 0.0], np.float32), (bands, 1))
    wiener = rng.uniform(0, 0.2, (31, bands)).astype(np.float32)
    calibration = sj.Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener)
    raw = (dark + rng.uniform(0.05, 0.9, (h, w, bands)) * (white - dark)).astype(np.uint16)
    raw[0:3, 0:3] = (dark + 0.95 * (white - dark))[0:3, 0:3].astype(np.uint16)
    raw[6, 6, 3] = 65535  # saturated: left out by both
    mask = np.zeros((h, w), bool)
    mask[4:10, 2:12] = True
    result = sj.correct(raw, calibration)
    got = measure_reflectances(np.asarray(result.reflectance), mask, np.asarray(result.quality))
    expected = sj.measure(raw, calibration, mask)
    np.testing.assert_allclose(got.reflectance, expected.reflectance, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got.lab, expected.lab, atol=2e-3)
    np.testing.assert_allclose(got.reflectance_spread, expected.reflectance_spread, rtol=1e-3, atol=1e-6)
    assert (got.pixels, got.excluded) == (expected.pixels, expected.excluded) == (59, 1)


def test_measure_reflectances_refuses_a_region_of_flagged_pixels():
    reflectance = np.full((4, 4, 31), np.nan, np.float32)
    with pytest.raises(ValueError, match="all 4 pixels of the region are flagged"):
        measure_reflectances(reflectance, np.eye(4, dtype=bool))


def test_another_calibration_is_refused_naming_both(corrected_workspace, cal):
    with pytest.raises(io.SpherejaxFileError, match="was corrected with a calibration of checksum") as refused:
        CorrectedCapture(corrected_workspace["output"], calibration=cal)
    assert str(cal) in str(refused.value) and "\n" not in str(refused.value)


def test_another_raw_cube_is_refused_naming_both(corrected_workspace):
    files = corrected_workspace
    other = sorted(files["raw"].parent.glob("test-*.tif"))[1]
    with pytest.raises(io.SpherejaxFileError, match="was corrected from an input with SHA-256"):
        CorrectedCapture(files["output"], calibration=files["calibration"], raw=other)


def _results(capture):
    mask = np.zeros(capture.shape, bool)
    mask[1:6, 1:9] = True
    return [RegionResult("region 1", (1, 6, 1, 9), capture.region(mask))]


def test_regions_are_written_as_measure_writes_them(capture, tmp_path):
    results = _results(capture)
    written = outputs.write_region_files(results, inputs={}, input_path="x.tif", instrument_id="sphere",
                                         csv_path=tmp_path / "r.csv", cgats_path=tmp_path / "r.txt")
    assert written == [tmp_path / "r.csv", tmp_path / "r.txt"]
    assert (tmp_path / "r.csv").read_text() == measurement_files.csv_text(results)
    cgats = (tmp_path / "r.txt").read_text()
    assert 'DESCRIPTOR\t"regions of x.tif"' in cgats and "LAB_L" in cgats and "nm700" in cgats
    assert 'INSTRUMENTATION\t"integrating-sphere multispectral camera sphere"' in cgats
    # A second export replaces what the first wrote.
    outputs.write_region_files(results, inputs={}, input_path="x.tif", instrument_id=None, csv_path=tmp_path / "r.csv")


def test_a_file_of_the_users_is_not_replaced_by_an_export(capture, tmp_path):
    mine = tmp_path / "mine.csv"
    mine.write_text("my notes\n")
    with pytest.raises(io.SpherejaxFileError, match="did not write"):
        outputs.write_region_files(_results(capture), inputs={}, input_path="x", instrument_id=None, csv_path=mine)
    assert mine.read_text() == "my notes\n" and listing(tmp_path) == ["mine.csv"]
    with pytest.raises(io.SpherejaxFileError, match="is also the reflectance"):
        outputs.write_region_files(_results(capture), inputs={"the reflectance": capture.reflectance_path},
                                   input_path="x", instrument_id=None, cgats_path=capture.reflectance_path)


class TestViewRefusals:
    """`spherejax view`'s bad arguments: one line, exit 2, nothing written, no window."""

    def test_bad_pixels(self, corrected_workspace, tmp_path, capsys):
        out = corrected_workspace["output"]
        for given, fragment in [("3", "expected ROW,COL"), ("a,b", "expected ROW,COL"), ("-1,2", "of 0 or more")]:
            status, _, err = run_cli(["view", str(out), "--screenshot", str(tmp_path / "s.png"), f"--pixel={given}"], capsys)
            assert_refused(status, err, f"--pixel {given!r}", fragment)
        assert listing(tmp_path) == []

    def test_options_that_go_together(self, corrected_workspace, tmp_path, capsys):
        out = str(corrected_workspace["output"])
        status, _, err = run_cli(["view", out, "--raw", str(corrected_workspace["raw"])], capsys)
        assert_refused(status, err, "--raw: needs -c CAL")
        status, _, err = run_cli(["view", out, "--pixel", "1,2"], capsys)
        assert_refused(status, err, "--pixel: goes with --screenshot")
        status, _, err = run_cli(["view", str(tmp_path / "nothing.exr")], capsys)
        assert_refused(status, err, "nothing.exr: no such file or folder")

    def test_screenshot_names(self, corrected_workspace, tmp_path, capsys):
        out = corrected_workspace["output"]
        status, _, err = run_cli(["view", str(out), "--screenshot", str(tmp_path / "s.jpg")], capsys)
        assert_refused(status, err, "expected a file name ending in .png")
        mine = tmp_path / "mine.png"
        mine.write_bytes(b"\x89PNG\r\n\x1a\n not mine")
        status, _, err = run_cli(["view", str(out), "--screenshot", str(mine)], capsys)
        assert_refused(status, err, "mine.png", "is in the way", "not a PNG spherejax view wrote")
        assert mine.read_bytes() == b"\x89PNG\r\n\x1a\n not mine"
        preview = out.with_name(out.name.replace(".reflectance.exr", ".preview.png"))
        before = preview.read_bytes()
        status, _, err = run_cli(["view", str(out), "--screenshot", str(preview)], capsys)
        assert_refused(status, err, "preview.png", "did not write")
        assert preview.read_bytes() == before

    def test_without_the_viewer_extra(self, corrected_workspace, tmp_path, capsys, monkeypatch):
        real = view_command.importlib.util.find_spec
        monkeypatch.setattr(view_command.importlib.util, "find_spec",
                            lambda name, *a: None if name == "napari" else real(name, *a))
        status, _, err = run_cli(["view", str(corrected_workspace["output"]), "--screenshot", str(tmp_path / "s.png")],
                                 capsys)
        assert_refused(status, err, "the viewer extra is not installed", "pip install 'spherejax[viewer]'")
        assert listing(tmp_path) == []

    def test_no_display_for_a_window(self, corrected_workspace, capsys, monkeypatch):
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        monkeypatch.setattr(view_command.importlib.util, "find_spec", lambda name, *a: object())
        status, _, err = run_cli(["view", str(corrected_workspace["output"])], capsys)
        assert_refused(status, err, "no display to open a window on", "--screenshot FILE.png")


def test_the_cursor_reads_each_chunk_of_rows_once(corrected_workspace, monkeypatch):
    """Pixel after pixel of the same rows: the file's chunk is read once, then kept."""
    from spherejax.io import corrected

    monkeypatch.setattr(corrected, "CHUNK_BYTES", 8 * 272 * 31 * 4)  # eight rows a chunk
    calls = []
    real = corrected._read_rows
    monkeypatch.setattr(corrected, "_read_rows", lambda path, r0, r1, order: calls.append((path, r0)) or real(path, r0, r1, order))
    expected = sj.open_corrected(corrected_workspace["output"])["reflectance"].values
    capture = CorrectedCapture(corrected_workspace["output"])
    calls.clear()
    for row, col in [(9, 3), (10, 40), (15, 100), (9, 200)]:
        r = capture.pixel(row, col, illuminant="A")  # no Lab file under A: reflectance only
        np.testing.assert_array_equal(r["reflectance"], expected[row, col])
    assert [r0 for path, r0 in calls if "reflectance" in path] == [8]


def test_a_preview_that_is_not_rgb_is_refused_naming_it(corrected_workspace, tmp_path):
    """A grey PNG in the preview's place (its size right, so `open_corrected` takes the set):
    refused in one line naming the file and what was expected."""
    import shutil

    stem = corrected_workspace["output"].name.removesuffix(".reflectance.exr")
    for file in corrected_workspace["output"].parent.glob(stem + ".*"):
        shutil.copy(file, tmp_path / file.name)
    h, w = CorrectedCapture(tmp_path / f"{stem}.reflectance.exr").shape
    (tmp_path / f"{stem}.preview.png").unlink()
    io.write_png(tmp_path / f"{stem}.preview.png", np.zeros((h, w, 1), np.uint8), channel_names=["Y"])
    capture = CorrectedCapture(tmp_path / f"{stem}.reflectance.exr")
    with pytest.raises(io.SpherejaxFileError, match="with 1 channels") as refused:
        capture.preview  # noqa: B018
    assert f"{stem}.preview.png" in str(refused.value) and "expected an RGB preview PNG" in str(refused.value)


def test_a_truncated_preview_is_refused_naming_it(corrected_workspace, tmp_path):
    import shutil

    stem = corrected_workspace["output"].name.removesuffix(".reflectance.exr")
    for file in corrected_workspace["output"].parent.glob(stem + ".*"):
        shutil.copy(file, tmp_path / file.name)
    preview = tmp_path / f"{stem}.preview.png"
    data = preview.read_bytes()
    preview.write_bytes(data[: len(data) // 2])
    with pytest.raises(io.SpherejaxFileError) as refused:
        CorrectedCapture(tmp_path / f"{stem}.reflectance.exr").preview  # noqa: B018
    message = str(refused.value)
    assert message.startswith(str(preview)) and "\n" not in message and "expected" in message
