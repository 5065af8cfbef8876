"""`spherejax measure`: the table, OUT.csv and OUT.json against `measure` called in Python, the
noise model's sources, and every bad argument (exit status 2, one line, nothing written).

The calibration is built by hand (identity Stage II, a Wiener matrix that interpolates the 16
bands to 31 wavelengths), so the module needs no simulated session.
"""

import csv
import json
import os
import pathlib
import types

import numpy as np
import pytest

from spherejax import cli, io, measurement_files
from spherejax.measurement import measure
from spherejax.pipeline import Calibration
from spherejax.uncertainty import NoiseModel

from .helpers import colour_lab

H, W = 20, 24
BANDS = list(range(400, 701, 20))
WAVELENGTHS = np.arange(400, 701, 10)
REGIONS = {"grey": (6, 12, 2, 10), "red": (6, 12, 12, 20)}  # one shape: one compilation
F32 = np.float32  # a calibration file's noise model reads back in float32
NOISE = NoiseModel(gain=F32(2), read_noise=F32(3), dark_frames=16, white_frames=16, white_reflectance_u=F32(0.002))
SATURATED = [(7, 13), (8, 14)]  # two pixels of "red", left out


def _calibration() -> Calibration:
    rng = np.random.default_rng(0)
    dark = (200 + rng.normal(0, 2, (H, W, len(BANDS)))).astype(np.float32)
    rows, cols = np.mgrid[0:H, 0:W]
    shading = 1.0 - 0.2 * ((rows - H / 2) ** 2 + (cols - W / 2) ** 2) / (H * H)
    white = (dark + 30000 * shading[..., None] * np.linspace(0.7, 1.0, len(BANDS))).astype(np.float32)
    patch = np.zeros((H, W), bool)
    patch[0:4, 0:4] = True
    coeffs = np.tile(np.array([0.0, 1.0, 0.0, 0.0], np.float32), (len(BANDS), 1))
    wiener = np.stack([np.interp(WAVELENGTHS, BANDS, np.eye(len(BANDS))[b]) for b in range(len(BANDS))], axis=1)
    return Calibration(dark=dark, white=white, patch=patch, coeffs=coeffs, wiener=wiener.astype(np.float32))


def _raw(calibration: Calibration, shape=(H, W)) -> np.ndarray:
    rng = np.random.default_rng(1)
    dark, white = np.asarray(calibration.dark), np.asarray(calibration.white)
    reflectance = np.full((H, W, len(BANDS)), 0.8)
    r0, r1, c0, c1 = REGIONS["grey"]
    reflectance[r0:r1, c0:c1] = 0.4
    r0, r1, c0, c1 = REGIONS["red"]
    reflectance[r0:r1, c0:c1] = np.linspace(0.05, 0.7, len(BANDS))
    reflectance[0:4, 0:4] = 1.0
    raw = dark + reflectance * (white - dark)
    raw = raw + rng.normal(0, 1, raw.shape) * np.sqrt(raw / 2.0)
    raw = np.clip(np.round(raw), 0, 65535).astype(np.uint16)
    for r, c in SATURATED:
        raw[r, c] = 65535
    return raw[: shape[0], : shape[1]]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("measure")
    calibration = _calibration()
    common = dict(instrument_id="test-sphere", band_centres_nm=BANDS)
    io.save_calibration(root / "cal.h5", calibration, noise_model=NOISE, **common)
    io.save_calibration(root / "bare.h5", calibration, **common)
    raw = _raw(calibration)
    names = [f"{b}nm" for b in BANDS]
    io.write_frame(root / "sample.tif", raw, channel_names=names)
    io.write_frame(root / "small.tif", raw[:10], channel_names=names)
    return {"root": root, "calibration": calibration, "raw": raw, "measured": {}}


def run(argv, capsys):
    status = cli.main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def region_args(regions=REGIONS):
    return [arg for name, rect in regions.items() for arg in ("--region", f"{name}=" + ",".join(map(str, rect)))]


def expected(files, noise, name, illuminant=None):
    """`measure` in Python on the same data (remembered: the module's time goes to compiling)."""
    key = (id(noise), name, illuminant)
    if key not in files["measured"]:
        r0, r1, c0, c1 = REGIONS[name]
        mask = np.zeros((H, W), bool)
        mask[r0:r1, c0:c1] = True
        files["measured"][key] = noise, measure(files["raw"], files["calibration"], mask, noise, illuminant=illuminant)
    return files["measured"][key][1]


def read_outputs(base: pathlib.Path):
    with open(base.with_name(base.name + ".csv"), newline="", encoding="utf-8") as handle:
        rows = {row["name"]: row for row in csv.DictReader(handle)}
    document = json.loads(base.with_name(base.name + ".json").read_text(encoding="utf-8"))
    return rows, document


def numbers(row, keys):
    return np.array([float(row[k]) for k in keys])


def close(actual, wanted):
    """The files state a float32 measurement's numbers (`Measurement.precision`) as the shortest
    decimals of their float32 values: the same float32 as `measure`'s, to within one unit in the
    last place (the command's run and this one may round the last float64 bit differently)."""
    np.testing.assert_array_max_ulp(np.float32(np.asarray(actual, np.float64)), np.float32(np.asarray(wanted, np.float64)), maxulp=1)


LAB, U_LAB, EXPANDED = ["L", "a", "b"], ["u_L", "u_a", "u_b"], ["U_L", "U_a", "U_b"]
R_COLUMNS = [f"R{nm}" for nm in WAVELENGTHS]
U_R_COLUMNS = [f"u_R{nm}" for nm in WAVELENGTHS]


class TestOutputs:
    def test_two_regions_against_a_region(self, files, tmp_path, capsys, monkeypatch):
        root = files["root"]
        monkeypatch.chdir(tmp_path)
        status, out, err = run(["measure", "-c", str(root / "cal.h5"), str(root / "sample.tif"),
                                *region_args(), "--reference", "grey"], capsys)
        assert status == 0, err
        assert err == ""
        base = tmp_path / "sample.measure"  # the default: INPUT's stem + .measure, here
        rows, document = read_outputs(base)
        assert list(rows) == ["grey", "red"]
        assert document["format"] == "spherejax-measurement" and document["format_version"] == 1
        assert document["coverage_factor"] == 2 and document["illuminant"] == "D65"
        assert document["reference"]["region"] == "grey"
        assert document["noise_model"]["source"] == "calibration"
        reference = expected(files, NOISE, "grey")
        for entry in document["regions"]:
            name = entry["name"]
            m = expected(files, NOISE, name)
            row = rows[name]
            delta_e, u = m.delta_e(reference)
            assert entry["rect"] == list(REGIONS[name])
            assert int(row["pixels"]) == m.pixels == entry["pixels"]
            assert int(row["excluded_pixels"]) == m.excluded == entry["excluded_pixels"]
            assert row["illuminant"] == "D65"
            close(numbers(row, LAB), m.lab)
            close(numbers(row, U_LAB), m.lab_u)
            close(numbers(row, EXPANDED), 2 * m.lab_u)
            close(numbers(row, R_COLUMNS), m.reflectance)
            close(numbers(row, U_R_COLUMNS), m.reflectance_u)
            close(numbers(row, ["delta_e00", "u_delta_e00", "U_delta_e00"]), [delta_e, u, 2 * u])
            close(entry["lab"], m.lab)
            close(entry["lab_covariance"], m.lab_covariance)
            close(entry["reflectance_covariance"], m.reflectance_covariance)
            close([entry["delta_e00"], entry["u_delta_e00"]], [delta_e, u])
            assert set(entry["lab_u_by_source"]) == set(m.lab_budget)
        assert rows["red"]["excluded_pixels"] == str(len(SATURATED))
        assert float(rows["grey"]["delta_e00"]) == 0.0
        # the table: one line per region with L*, a*, b*, ΔE00 ± U, then the reflectance block
        lines = out.splitlines()
        assert all(len(line) <= 100 for line in lines), out
        assert "k = 2" in lines[0] and "region 'grey'" in lines[1]
        red = expected(files, NOISE, "red")
        row = next(line for line in lines if line.startswith("red") and "±" in line and "(" not in line)
        for value, u in zip(red.lab, red.lab_u):
            assert f"{value:.2f} ± {2 * u:.2f}" in row
        delta_e, u = red.delta_e(reference)
        assert f"{delta_e:.2f} ± {2 * u:.2f}" in row
        reflectance_row = next(line for line in lines if line.startswith("red") and "(" in line)
        assert f"{red.reflectance[15]:.4f} ± {2 * red.reflectance_u[15]:.4f}" in reflectance_row  # 550 nm
        assert "excluded" in out
        assert "sample.measure.csv" in lines[-1] and "sample.measure.json" in lines[-1]

    def test_exact_reference_illuminant_and_output_base(self, files, tmp_path, capsys):
        root = files["root"]
        base = tmp_path / "out" / "result"
        base.parent.mkdir()
        status, out, err = run(["-q", "measure", "-c", str(root / "cal.h5"), str(root / "sample.tif"),
                                *region_args(), "--reference", "50,-2.5,10", "--illuminant", "A", "-o", str(base)],
                               capsys)
        assert status == 0 and out == "" and err == ""
        assert sorted(p.name for p in base.parent.iterdir()) == ["result.csv", "result.json"]
        rows, document = read_outputs(base)
        assert document["reference"] == {"lab": [50.0, -2.5, 10.0]} and document["illuminant"] == "A"
        for name, row in rows.items():
            m = expected(files, NOISE, name, illuminant="A")
            delta_e, u = m.delta_e([50.0, -2.5, 10.0])
            assert row["illuminant"] == "A"
            close(numbers(row, LAB), m.lab)
            close(numbers(row, ["delta_e00", "u_delta_e00", "U_delta_e00"]), [delta_e, u, 2 * u])

    def test_no_reference_no_delta_e(self, files, tmp_path, capsys):
        root = files["root"]
        status, out, _ = run(["measure", "-c", str(root / "cal.h5"), str(root / "sample.tif"),
                              *region_args(), "-o", str(tmp_path / "r")], capsys)
        assert status == 0 and "ΔE00" not in out
        rows, document = read_outputs(tmp_path / "r")
        assert document["reference"] is None
        assert all(row[k] == "" for row in rows.values() for k in ("delta_e00", "u_delta_e00", "U_delta_e00"))
        assert all(entry["delta_e00"] is None and entry["u_delta_e00"] is None for entry in document["regions"])

    def test_options_override_the_calibrations_noise_model(self, files, tmp_path, capsys):
        root = files["root"]
        status, _, err = run(["measure", "-c", str(root / "cal.h5"), str(root / "sample.tif"), *region_args(),
                              "--gain", "0.5", "--frames", "4", "-o", str(tmp_path / "r")], capsys)
        assert status == 0 and err == ""
        rows, document = read_outputs(tmp_path / "r")
        noise = NoiseModel(gain=F32(0.5), read_noise=F32(3), dark_frames=16, white_frames=16, sample_frames=4,
                           white_reflectance_u=F32(0.002))
        assert document["noise_model"]["source"] == "calibration, options"
        assert document["noise_model"]["dark_frames"] == 16 and document["noise_model"]["sample_frames"] == 4
        for name, row in rows.items():
            m = expected(files, noise, name)
            close(numbers(row, U_LAB), m.lab_u)
            close(numbers(row, U_R_COLUMNS), m.reflectance_u)
            assert not np.allclose(numbers(row, U_LAB), expected(files, NOISE, name).lab_u)

    def test_options_supply_a_noise_model(self, files, tmp_path, capsys):
        root = files["root"]
        status, _, err = run(["measure", "-c", str(root / "bare.h5"), str(root / "sample.tif"), *region_args(),
                              "--gain", "2", "--read-noise", "3", "-o", str(tmp_path / "r")], capsys)
        assert status == 0
        assert len(err.splitlines()) == 1 and err.startswith("spherejax: note: ") and "single frames" in err
        rows, document = read_outputs(tmp_path / "r")
        assert document["noise_model"]["source"] == "options"
        noise = NoiseModel(gain=F32(2), read_noise=F32(3))
        for name, row in rows.items():
            close(numbers(row, U_LAB), expected(files, noise, name).lab_u)

    def test_no_noise_model_gives_values_without_uncertainties(self, files, tmp_path, capsys):
        root = files["root"]
        status, out, err = run(["measure", "-c", str(root / "bare.h5"), str(root / "sample.tif"), *region_args(),
                                "--reference", "grey", "-o", str(tmp_path / "r")], capsys)
        assert status == 0
        assert len(err.splitlines()) == 1 and err.startswith("spherejax: note: no noise model") and "--gain" in err
        assert "n/a" in out and "Traceback" not in err
        rows, document = read_outputs(tmp_path / "r")
        for name, row in rows.items():
            m = expected(files, None, name)
            close(numbers(row, LAB), m.lab)
            close(numbers(row, R_COLUMNS), m.reflectance)
            close(float(row["delta_e00"]), m.delta_e(expected(files, None, "grey"))[0])
            assert all(row[k] == "" for k in [*U_LAB, *EXPANDED, *U_R_COLUMNS, "u_delta_e00", "U_delta_e00"])
        entry = document["regions"][1]
        assert entry["lab_u"] is None and entry["lab_covariance"] is None and entry["u_delta_e00"] is None
        assert document["noise_model"] is None


class TestRefused:
    @pytest.fixture
    def setup(self, files, tmp_path, monkeypatch):
        monkeypatch.chdir(tmp_path)
        return files["root"], tmp_path

    def refuse(self, argv, capsys, folder, *fragments):
        before = sorted(folder.rglob("*"))
        status, out, err = run(argv, capsys)
        assert status == cli.EXIT_BAD_INPUT
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        assert lines[0].startswith("spherejax: error: ") and "Traceback" not in err
        for fragment in fragments:
            assert fragment in lines[0], (fragment, lines[0])
        assert sorted(folder.rglob("*")) == before
        assert out == ""

    def base_args(self, root, cal="cal.h5", sample="sample.tif"):
        return ["measure", "-c", str(root / cal), str(root / sample)]

    @pytest.mark.parametrize("region, fragment", [
        ("a=0,21,0,5", "outside the 20 x 24 image"),
        ("a=0,5,-1,5", "outside"),
        ("a=3,3,0,5", "is empty"),
        ("a=0,5,6,2", "is empty"),
        ("a=0,5,0", "NAME=r0,r1,c0,c1"),
        ("0,5,0,5", "NAME=r0,r1,c0,c1"),
        ("=0,5,0,5", "NAME=r0,r1,c0,c1"),
        ("a=0,5,0,x", "not integers"),
        ("a=0,5.5,0,5", "not integers"),
        ("a\tb=0,5,0,5", "control character"),
    ])
    def test_bad_region(self, setup, capsys, region, fragment):
        root, folder = setup
        self.refuse([*self.base_args(root), "--region", region], capsys, folder, "--region", repr(region), fragment)

    def test_duplicate_region_name(self, setup, capsys):
        root, folder = setup
        argv = [*self.base_args(root), "--region", "a=0,5,0,5", "--region", "a=6,8,0,5"]
        self.refuse(argv, capsys, folder, "--region 'a=6,8,0,5'", "given twice")

    @pytest.mark.parametrize("reference, fragment", [
        ("white", "'white'"), ("50,0", "'50,0'"), ("50,0,x", "three finite numbers"), ("50,0,nan", "L,a,b"),
    ])
    def test_bad_reference(self, setup, capsys, reference, fragment):
        root, folder = setup
        argv = [*self.base_args(root), *region_args(), "--reference", reference]
        self.refuse(argv, capsys, folder, "--reference", fragment, "'grey'")

    @pytest.mark.parametrize("options, fragment", [
        (["--gain", "0"], "--gain '0'"),
        (["--gain", "x"], "--gain 'x'"),
        (["--read-noise", "-1"], "--read-noise '-1'"),
        (["--frames", "1.5"], "--frames '1.5'"),
        (["--frames", "0"], "--frames '0'"),
    ])
    def test_bad_noise_options(self, setup, capsys, options, fragment):
        root, folder = setup
        self.refuse([*self.base_args(root), *region_args(), *options], capsys, folder, fragment)

    def test_gain_without_read_noise_and_no_model(self, setup, capsys):
        root, folder = setup
        argv = [*self.base_args(root, cal="bare.h5"), *region_args(), "--gain", "2"]
        self.refuse(argv, capsys, folder, "--read-noise", "no noise model")

    def test_missing_input(self, setup, capsys):
        root, folder = setup
        self.refuse([*self.base_args(root, sample="nothing.tif"), *region_args()], capsys, folder, "nothing.tif", "no such file")

    def test_input_of_the_wrong_shape(self, setup, capsys):
        root, folder = setup
        self.refuse([*self.base_args(root, sample="small.tif"), *region_args()], capsys, folder, "small.tif")

    def test_missing_calibration(self, setup, capsys):
        root, folder = setup
        self.refuse([*self.base_args(root, cal="none.h5"), *region_args()], capsys, folder, "none.h5")

    def test_output_folder_missing(self, setup, capsys):
        root, folder = setup
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "missing" / "r")]
        self.refuse(argv, capsys, folder, "missing", "does not exist")

    def test_output_base_is_a_folder(self, setup, capsys):
        root, folder = setup
        (folder / "results").mkdir()
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "results")]
        self.refuse(argv, capsys, folder, "results", "is a folder")

    def test_region_with_every_pixel_flagged(self, setup, capsys):
        root, folder = setup
        r, c = SATURATED[0]
        argv = [*self.base_args(root), "--region", f"s={r},{r + 1},{c},{c + 1}"]
        self.refuse(argv, capsys, folder, "--region", "flagged")

    @pytest.mark.parametrize("target", ["input", "input via ..", "input via a link", "calibration", "hard link to the input"])
    def test_cgats_file_that_is_an_input_is_refused_and_the_input_kept(self, setup, capsys, target):
        """`measure ... --cgats mp/a.tif` overwrote the input cube with CGATS text (exit 0): the
        path was compared with OUT.csv and OUT.json only. Each spelling of an input is refused."""
        root, folder = setup
        sample = folder / "a.tif"
        sample.write_bytes((root / "sample.tif").read_bytes())
        cal = folder / "cal.h5"
        cal.write_bytes((root / "cal.h5").read_bytes())
        (folder / "sub").mkdir()
        paths = {
            "input": sample, "input via ..": folder / "sub" / ".." / "a.tif", "calibration": cal,
            "input via a link": folder / "link.tif", "hard link to the input": folder / "hard.tif",
        }
        (folder / "link.tif").symlink_to(sample)
        os.link(sample, folder / "hard.tif")
        before = {p: p.read_bytes() for p in (sample, cal)}
        argv = ["measure", "-c", str(cal), str(sample), *region_args(), "-o", str(folder / "r"), "--cgats", str(paths[target])]
        self.refuse(argv, capsys, folder, str(paths[target]), "--cgats FILE is also the")
        assert {p: p.read_bytes() for p in (sample, cal)} == before

    def test_output_base_whose_csv_is_the_input_is_refused(self, setup, capsys):
        """-o r with an input named r.csv: OUT.csv would have replaced the input."""
        root, folder = setup
        sample = folder / "r.csv"
        sample.write_bytes((root / "sample.tif").read_bytes())
        argv = ["measure", "-c", str(root / "cal.h5"), str(sample), *region_args(), "-o", str(folder / "r")]
        self.refuse(argv, capsys, folder, "r.csv", "OUT.csv is also the input cube")

    def test_cgats_file_is_a_folder(self, setup, capsys):
        root, folder = setup
        (folder / "qc").mkdir()
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "r"), "--cgats", str(folder / "qc")]
        self.refuse(argv, capsys, folder, "qc", "is a folder", "--cgats FILE")

    def test_cgats_file_in_a_missing_folder(self, setup, capsys):
        root, folder = setup
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "r"), "--cgats", str(folder / "no" / "m.txt")]
        self.refuse(argv, capsys, folder, "m.txt", "does not exist")

    def test_cgats_file_is_the_csv(self, setup, capsys):
        root, folder = setup
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "r"), "--cgats", str(folder / "r.csv")]
        self.refuse(argv, capsys, folder, "r.csv", "also the measurement's CSV or JSON")

    def test_failed_cgats_write_leaves_nothing(self, setup, capsys):
        """The CGATS file cannot be written (a folder appears in its place after the checks):
        neither OUT.csv nor OUT.json is left."""
        root, folder = setup
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "r"), "--cgats", str(folder / "m.txt")]
        real = measurement_files.cgats_text

        def cgats_text_then_block(*args, **kwargs):
            (folder / "m.txt").mkdir()
            return real(*args, **kwargs)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(measurement_files, "cgats_text", cgats_text_then_block)
            status, out, err = run(argv, capsys)
        assert status == cli.EXIT_BAD_INPUT and "m.txt" in err and len(err.strip().splitlines()) == 1
        assert sorted(p.name for p in folder.iterdir()) == ["m.txt"] and (folder / "m.txt").is_dir()

    def test_failed_write_leaves_nothing(self, setup, capsys):
        """OUT.json cannot be written (a folder is in the way): OUT.csv is not left either."""
        root, folder = setup
        (folder / "r.json").mkdir()
        argv = [*self.base_args(root), *region_args(), "-o", str(folder / "r")]
        self.refuse(argv, capsys, folder, "r.json")


def test_output_paths_append_the_suffixes():
    assert measurement_files.output_paths("a/b.v2") == (pathlib.Path("a/b.v2.csv"), pathlib.Path("a/b.v2.json"))
    assert measurement_files.default_base("/data/x/sample.tif") == pathlib.Path("sample.measure")
    assert measurement_files.csv_header()[:16] == [
        "name", "pixels", "excluded_pixels", "illuminant", "L", "a", "b", "u_L", "u_a", "u_b",
        "U_L", "U_a", "U_b", "delta_e00", "u_delta_e00", "U_delta_e00",
    ]
    assert len(measurement_files.csv_header()) == 16 + 2 * 31


@pytest.fixture(scope="module")
def written(files, tmp_path_factory):
    """(the CGATS file, the CSV rows and JSON document) of one `measure --cgats` run."""
    folder = tmp_path_factory.mktemp("cgats")
    regions = {**REGIONS, "paper white": (14, 18, 4, 12)}  # a name with a space: one token in CGATS
    argv = ["-q", "measure", "-c", str(files["root"] / "cal.h5"), str(files["root"] / "sample.tif"),
            *region_args(regions), "-o", str(folder / "r"), "--cgats", str(folder / "qc.txt")]
    assert cli.main(argv) == 0
    return folder / "qc.txt", read_outputs(folder / "r")


class TestCGATS:
    """--cgats FILE read back by colour-science's X-Rite reader (the spectra exactly) and checked
    against `measure` in Python and colour-science's own Lab of those spectra."""

    def test_colour_reads_the_spectra_exactly(self, written):
        import colour

        path, (rows, document) = written
        spectra = colour.io.read_sds_from_xrite_file(str(path))
        assert list(spectra) == ["grey", "red", "paper_white"]  # colour's reader splits on whitespace
        for entry in document["regions"][:2]:
            sd = spectra[entry["name"]]
            np.testing.assert_array_equal(sd.wavelengths, WAVELENGTHS)
            np.testing.assert_array_equal(sd.values, entry["reflectance"])  # exactly, not closely

    def test_fields_keywords_and_lab(self, written, files):
        import colour

        path, (rows, document) = written
        lines = path.read_text(encoding="utf-8").splitlines()
        assert lines[0] == "CGATS.17" and lines[-1] == "END_DATA"
        keywords = dict(line.split("\t", 1) for line in lines[1 : lines.index("BEGIN_DATA_FORMAT")])
        assert keywords["ILLUMINATION_NAME"] == '"D65"' and keywords["OBSERVER_ANGLE"] == '"2"'
        assert keywords["SPECTRAL_BANDS"] == '"31"' and keywords["NUMBER_OF_FIELDS"] == str(5 + 31)
        declared = {line.split("\t")[1].strip('"') for line in lines if line.startswith("KEYWORD\t")}
        assert {"ILLUMINATION_NAME", "OBSERVER_ANGLE", "SPECTRAL_BANDS"} <= declared
        assert "ORIGINATOR" not in declared  # a CGATS.17 keyword needs no declaration
        fields = lines[lines.index("BEGIN_DATA_FORMAT") + 1].split("\t")
        assert fields == ["SAMPLE_ID", "SAMPLE_NAME", "LAB_L", "LAB_A", "LAB_B", *(f"nm{nm}" for nm in WAVELENGTHS)]
        data = [line.split("\t") for line in lines[lines.index("BEGIN_DATA") + 1 : -1]]
        assert [row[:2] for row in data] == [["1", "grey"], ["2", "red"], ["3", "paper_white"]]
        for row, entry in zip(data, document["regions"]):
            lab = np.array([float(v) for v in row[2:5]])
            np.testing.assert_array_equal(lab, entry["lab"])
            oracle = colour_lab([np.array([float(v) for v in row[5:]])], "D65")[0]  # from the file's spectra
            assert colour.delta_E(lab, oracle, method="CIE 2000") < 0.05
        grey = expected(files, NOISE, "grey")
        assert grey.precision == np.float32  # the file holds the float32 values, in their shortest form
        np.testing.assert_array_equal(np.array([np.float32(v) for v in data[0][5:]]), grey.reflectance.astype(np.float32))



def test_cgats_names_the_observer_by_its_angle_whatever_its_alias():
    """A calibration may name its observer "1964": the CGATS file still says 10 degrees."""
    measurement = types.SimpleNamespace(observer="1964", illuminant="D65", lab=np.zeros(3), reflectance=np.zeros(31),
                                        precision=np.dtype(np.float32))
    row = measurement_files.RegionResult("a", (0, 1, 0, 1), measurement)
    text = measurement_files.cgats_text([row], input_path="x.tif", instrument_id=None, created="2026-01-01T00:00:00+00:00")
    assert 'OBSERVER_ANGLE\t"10"' in text.splitlines()


def test_names_readers_would_merge_or_run_stay_apart_and_inert(files, tmp_path):
    """Written as given, regions "red wool" and "red cotton" come back from colour-science's X-Rite
    reader as one spectrum named '"red' (a measurement lost), and a region named "+SUM(A1)" or
    "@SUM(A1)" goes into OUT.csv as a formula a spreadsheet would run (a number-like name is quoted
    in CGATS, so colour-science keeps its quotes: still one spectrum each). So: one token each in
    CGATS, unique; a leading quote in the CSV (OWASP); the exact names in the JSON."""
    import colour

    names = {"red wool": (6, 12, 2, 10), "red cotton": (6, 12, 12, 20), "red_wool": (14, 18, 4, 12),
             "+SUM(A1)": (2, 6, 2, 10), "@SUM(A1)": (2, 6, 12, 20), "+3": (14, 18, 12, 20)}
    argv = ["-q", "measure", "-c", str(files["root"] / "cal.h5"), str(files["root"] / "sample.tif"),
            *region_args(names), "-o", str(tmp_path / "r"), "--cgats", str(tmp_path / "qc.txt")]
    assert cli.main(argv) == 0
    spectra = colour.io.read_sds_from_xrite_file(str(tmp_path / "qc.txt"))
    assert list(spectra) == ["red_wool", "red_cotton", "red_wool_2", "+SUM(A1)", "@SUM(A1)", '"+3"']
    with open(tmp_path / "r.csv", newline="", encoding="utf-8") as handle:
        cells = [row["name"] for row in csv.DictReader(handle)]
    assert cells == ["red wool", "red cotton", "red_wool", "'+SUM(A1)", "'@SUM(A1)", "'+3"]
    document = json.loads((tmp_path / "r.json").read_text(encoding="utf-8"))
    assert [entry["name"] for entry in document["regions"]] == list(names)
    reflectance = {entry["name"]: entry["reflectance"] for entry in document["regions"]}
    np.testing.assert_array_equal(spectra["red_cotton"].values, reflectance["red cotton"])


def test_cgats_sample_names():
    names = measurement_files.cgats_sample_names(["a b", "a_b", "a\tb", ' "q" ', "x#y", "", "a_b_2"])
    assert names == ["a_b", "a_b_2", "a_b_3", "_q_", "x_y", "region", "a_b_2_2"]
    assert len(set(names)) == len(names)
