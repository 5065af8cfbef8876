"""Numbers in the files spherejax writes: the shortest decimal that reads back as the same value at
the precision it was computed in (a float32 as float32, a float64 as float64, an integer as an
integer), in CSV, CGATS.17 and JSON; and every CSV written by Python's csv module, so that a
label with a comma or a quote reads back whole with pandas and with csv.reader.

Shortness is checked here from its definition, not with the module's own formatting: a text is
the shortest when it parses back to the value and no decimal with fewer significant digits (the
nearest ones of each length) does.
"""

from __future__ import annotations

import csv
import decimal
import io as text_io
import json
import re

import numpy as np
import pandas as pd
import pytest

from spherejax import evaluate, measurement_files
from spherejax.evaluate import Evaluation
from spherejax.measurement import Measurement
from spherejax.number_text import csv_text, json_ready, number_text

BANDS = list(range(400, 701, 20))
WAVELENGTHS = list(range(400, 701, 10))
#: A label that broke the hand-joined CSV: a comma (an extra field) and a quote (never escaped).
AWKWARD = 'Stage "II", closed form (Eq. 22)'


def significant_digits(text: str) -> int:
    """Significant digits of a decimal ("-0.0012300" -> 3, "1.5e-07" -> 2); 1 for zero."""
    assert re.fullmatch(r"-?\d+(\.\d+)?(e[-+]?\d+)?", text), f"{text!r} is not a decimal"
    digits = text.split("e")[0].lstrip("-").replace(".", "").lstrip("0").rstrip("0")
    return max(len(digits), 1)


def nearest_decimals(value: float, digits: int) -> list[float]:
    """The decimals of `digits` significant digits around `value`: the nearest and its two
    neighbours (at a power of two the values reading back lie unevenly about it)."""
    nearest = decimal.Decimal(f"{value:.{digits - 1}e}")  # exact decimal arithmetic from here
    step = decimal.Decimal(1).scaleb(nearest.adjusted() - (digits - 1))
    return [float(nearest + k * step) for k in (-1, 0, 1)]


def assert_shortest(text: str, value, dtype) -> None:
    """`text` reads back as `value` in `dtype`, and no shorter decimal does."""
    target = dtype(value)
    assert dtype(float(text)) == target, (text, value)
    n = significant_digits(text)
    for fewer in range(1, n):
        for candidate in nearest_decimals(float(target), fewer):
            assert dtype(candidate) != target, f"{candidate!r} ({fewer} digits) also reads back as {target!r}; {text!r} has {n}"


def float32_sample(count=400, seed=0) -> np.ndarray:
    """float32 values of every sign and many magnitudes, with zero, integers and powers of two."""
    rng = np.random.default_rng(seed)
    values = rng.uniform(-1, 1, count) * 10.0 ** rng.integers(-7, 7, count)
    special = [0.0, 1.0, -2.0, 0.5, 50.0, 1e-7, 65504.0, 2.0**-20, 37.723575592041016, 0.1, 1 / 3]
    return np.concatenate([special, values]).astype(np.float32)


# ------------------------------------------------------------------------------ number_text


def test_a_float32_is_written_as_its_shortest_decimal():
    assert number_text(np.float32(37.723575592041016)) == "37.723576"
    assert number_text(np.float32(0.1)) == "0.1"
    assert number_text(np.float32(50)) == "50.0"  # a float column stays a float column
    # A float32 result already held as a float64 (a Python float) says its precision.
    assert number_text(float(np.float32(0.1)), np.float32) == "0.1"
    assert number_text(np.float64(np.float32(0.1)), np.float32) == "0.1"
    for value in float32_sample():
        text = number_text(value)
        assert "e" not in text.lower()  # plain decimals: CGATS and spreadsheets take them everywhere
        assert_shortest(text, value, np.float32)


def test_a_float64_keeps_every_digit_it_needs():
    assert number_text(0.1 + 0.2) == "0.30000000000000004"
    assert number_text(37.723575592041016) == "37.723575592041016"  # not cut to the float32 digits
    assert number_text(np.float64(1e-5)) == "0.00001"
    rng = np.random.default_rng(1)
    for value in rng.uniform(-1, 1, 200) * 10.0 ** rng.integers(-6, 8, 200):
        text = number_text(float(value))
        assert significant_digits(text) == significant_digits(repr(float(value)))  # Python's repr digits
        assert_shortest(text, value, np.float64)


def test_integers_stay_integers_and_what_is_not_a_number_is_refused():
    assert number_text(16) == "16" and number_text(np.int64(-3)) == "-3" and number_text(np.uint16(65535)) == "65535"
    assert number_text(np.array(np.float32(0.25))) == "0.25"
    assert number_text(float("nan")) == "nan" and number_text(np.float32("-inf")) == "-inf"
    with pytest.raises(TypeError):
        number_text(True)
    with pytest.raises(TypeError):
        number_text("1.5")


# ------------------------------------------------------------------------------- json_ready


def test_json_of_float32_values_is_the_shortest_and_reads_back_exactly():
    import jax.numpy as jnp

    values = float32_sample()
    document = {
        "array": values.reshape(-1, 1)[:20], "scalar": np.float32(37.723575592041016), "jax": jnp.asarray(values[:5]),
        "float64": np.array([0.1 + 0.2, 1 / 3]), "python": 1 / 3, "ints": np.arange(3, dtype=np.int16),
        "flag": np.bool_(True), "nested": ({"x": np.float32(0.1)}, [np.int64(7)]), "text": "a", "none": None,
    }
    text = json.dumps(json_ready(document))
    assert '"scalar": 37.723576' in text and '"x": 0.1' in text
    back = json.loads(text)
    assert back["float64"] == [0.1 + 0.2, 1 / 3] and back["python"] == 1 / 3  # float64 untouched
    assert back["ints"] == [0, 1, 2] and back["flag"] is True and back["nested"] == [{"x": 0.1}, [7]]
    assert back["text"] == "a" and back["none"] is None
    assert [row[0] for row in back["array"]] == [float(number_text(v)) for v in values[:20]]
    np.testing.assert_array_equal(np.float32(back["jax"]), values[:5])
    # Every float32 of the sample: json.dumps writes its shortest decimal, which reads back the same.
    written = json.dumps(json_ready(values)).strip("[]").split(", ")
    for token, value in zip(written, values, strict=True):
        assert np.float32(float(token)) == value
        assert significant_digits(number_text(float(token))) == significant_digits(number_text(value))


def test_json_ready_with_a_precision_rounds_float32_results_held_as_float64():
    held = np.float32([0.1, 37.723575592041016]).astype(np.float64)  # what .tolist() hands over
    assert json.dumps(held.tolist()) == "[0.10000000149011612, 37.723575592041016]"
    assert json.dumps(json_ready(held, np.float32)) == "[0.1, 37.723576]"
    assert json.dumps(json_ready(held)) == "[0.10000000149011612, 37.723575592041016]"  # float64: as it is


# --------------------------------------------------------------------------------- csv_text


def read_both(text: str, fields: int) -> tuple[list[list[str]], pd.DataFrame]:
    """The CSV read by csv.reader (every row of `fields` fields) and by pandas."""
    rows = list(csv.reader(text_io.StringIO(text)))
    assert all(len(row) == fields for row in rows), [len(row) for row in rows]
    frame = pd.read_csv(text_io.StringIO(text), keep_default_na=False)
    assert frame.shape == (len(rows) - 1, fields)
    return rows, frame


def test_csv_text_quotes_what_needs_quoting():
    values = float32_sample(20)
    text = csv_text(["label", "float32", "float64", "count", "empty"],
                    [[AWKWARD, values[0], 1 / 3, 3, None], ["line\nbreak", values[1], 0.5, -1, ""],
                     *[[f"row {k}", v, float(v), k, None] for k, v in enumerate(values[2:])]])
    rows, frame = read_both(text, 5)
    assert rows[1][0] == AWKWARD and frame["label"][0] == AWKWARD and frame["label"][1] == "line\nbreak"
    assert rows[1][2] == repr(1 / 3) and rows[1][3] == "3" and rows[1][4] == ""
    for row, value in zip(rows[1:], values):
        assert_shortest(row[1], value, np.float32)
        assert_shortest(row[2], float(row[2]), np.float64)
    assert frame["float32"].astype(np.float32).tolist() == values.tolist()
    assert text.endswith("\n") and "\r" not in text.replace("line\nbreak", "")


# ------------------------------------------------------------------------------- evaluate


def hand_evaluation(kappa) -> Evaluation:
    rng = np.random.default_rng(2)

    def stage_metrics():
        per_band = rng.uniform(0, 0.01, len(BANDS))
        out = {"response_std_per_band": [float(x) for x in per_band], "response_std": float(per_band.mean()),
               "spectral_rms": float(rng.uniform(0, 0.02))}
        out.update({f"delta_e00_{i}": float(rng.uniform(0, 3)) for i in evaluate.ILLUMINANTS})
        return out

    metrics = {name: {stage: stage_metrics() for stage in evaluate.STAGES} for name in ("training", "test")}
    return Evaluation(BANDS, kappa, {"training": None, "test": None}, metrics)


def test_every_evaluation_table_reads_back_with_pandas_and_csv(monkeypatch):
    monkeypatch.setitem(evaluate.STAGE_LABELS, "stage2", AWKWARD)
    evaluation = hand_evaluation([0.5] * len(BANDS))
    tables = evaluate.tables(evaluation)
    texts = evaluate.tables_csv(evaluation)
    assert sorted(texts) == ["table1", "table3", "table4", "table5", "table6"]
    for name, text in texts.items():
        _, header, table_rows = tables[name]
        rows, frame = read_both(text, len(header))
        assert rows == [header, *table_rows], name
        labels = [row[0] for row in rows[1:]]
        assert frame.iloc[:, 0].tolist() == labels
        if name != "table6":
            assert AWKWARD in labels, name
        # The tables' own four decimals, as printed.
        assert all(re.fullmatch(r"-?\d+\.\d{4}", cell) for row in rows[1:] for cell in row[1:]), name


def test_metrics_json_states_kappa_at_its_precision_and_the_metrics_in_full():
    kappa = np.float32(np.random.default_rng(3).uniform(0.1, 0.9, len(BANDS)))
    evaluation = hand_evaluation(json_ready(kappa))
    text = evaluate.to_json(evaluation)
    document = json.loads(text)
    assert document["metrics"] == evaluation.metrics  # float64 metrics: every digit
    np.testing.assert_array_equal(np.float32(document["markov_kappa"]), kappa)
    written = re.search(r'"markov_kappa": \[([^\]]*)\]', text).group(1).split(",")
    for token, value in zip(written, kappa, strict=True):
        assert_shortest(token.strip(), value, np.float32)
    # A float32 κ handed over as an array is written the same way.
    assert json.loads(evaluate.to_json(hand_evaluation(kappa)))["markov_kappa"] == document["markov_kappa"]


# ---------------------------------------------------------------------------- measurement


def a_measurement(precision, seed=4) -> Measurement:
    rng = np.random.default_rng(seed)
    reflectance = rng.uniform(0.05, 0.9, 31).astype(precision).astype(np.float64)
    lab = np.array([37.723575592041016, -1.25, 12.5]).astype(precision).astype(np.float64)
    a = rng.normal(size=(31, 31)) * 1e-3
    covariance = a @ a.T
    jacobian = rng.normal(size=(3, 31))
    return Measurement(
        reflectance=reflectance, lab=lab, illuminant="D65", observer="CIE 1931 2 Degree Standard Observer",
        pixels=48, excluded=2, reflectance_spread=np.abs(rng.normal(size=31)) * 1e-2,
        reflectance_covariance=covariance, lab_covariance=jacobian @ covariance @ jacobian.T,
        reflectance_budget={"sample frame": covariance}, lab_budget={"sample frame": jacobian @ covariance @ jacobian.T},
        precision=np.dtype(precision),
    )


def results(precision) -> list[measurement_files.RegionResult]:
    return [
        measurement_files.RegionResult(AWKWARD, (0, 4, 0, 4), a_measurement(precision), 1.2345678901234567, 0.012345678901234),
        measurement_files.RegionResult("=1+2", (4, 8, 0, 4), a_measurement(precision, seed=5)),
    ]


def test_measurement_csv_reads_back_whole_with_shortest_float32_numbers():
    rows_in = results(np.float32)
    text = measurement_files.csv_text(rows_in)
    header = measurement_files.csv_header()
    rows, frame = read_both(text, len(header))
    assert rows[0] == header
    assert [row[0] for row in rows[1:]] == [AWKWARD, "'=1+2"] == frame["name"].tolist()
    first = dict(zip(header, rows[1]))
    m = rows_in[0].measurement
    assert first["L"] == "37.723576"
    expected = {"L": m.lab[0], "a": m.lab[1], "b": m.lab[2], "u_L": m.lab_u[0], "U_L": 2 * m.lab_u[0],
                "delta_e00": 1.2345678901234567, "u_delta_e00": 0.012345678901234,
                **{f"R{nm}": m.reflectance[i] for i, nm in enumerate(WAVELENGTHS)},
                **{f"u_R{nm}": m.reflectance_u[i] for i, nm in enumerate(WAVELENGTHS)}}
    for key, value in expected.items():
        assert_shortest(first[key], value, np.float32)
    assert first["pixels"] == "48" and first["excluded_pixels"] == "2"
    second = dict(zip(header, rows[2]))
    assert second["delta_e00"] == second["u_delta_e00"] == second["U_delta_e00"] == ""  # no reference
    np.testing.assert_array_equal(frame[[f"R{nm}" for nm in WAVELENGTHS]].to_numpy(np.float32)[0], np.float32(m.reflectance))


def test_a_float64_measurement_keeps_its_float64_digits():
    rows_in = results(np.float64)
    m = rows_in[0].measurement
    rows = list(csv.DictReader(text_io.StringIO(measurement_files.csv_text(rows_in))))
    assert rows[0]["L"] == "37.723575592041016"
    np.testing.assert_array_equal([float(rows[0][f"R{nm}"]) for nm in WAVELENGTHS], m.reflectance)
    document = json.loads(measurement_files.json_text(measurement_files.json_document(
        rows_in, input_path="x.tif", calibration={}, illuminant="D65", reference=None, noise_model=None)))
    assert document["regions"][0]["lab"] == m.lab.tolist()
    assert document["regions"][0]["lab_covariance"] == m.lab_covariance.tolist()
    assert document["regions"][0]["delta_e00"] == 1.2345678901234567


def test_measurement_json_states_float32_numbers_shortest():
    rows_in = results(np.float32)
    m = rows_in[0].measurement
    reference = {"region": "=1+2", "lab": rows_in[1].measurement.lab.tolist()}  # as the command hands it over
    text = measurement_files.json_text(measurement_files.json_document(
        rows_in, input_path="x.tif", calibration={"path": "c.h5"}, illuminant="D65", reference=reference, noise_model=None))
    document = json.loads(text)
    entry = document["regions"][0]
    assert entry["name"] == AWKWARD and entry["lab"][0] == 37.723576
    assert '"lab": [37.723576, -1.25, 12.5]' in text
    np.testing.assert_array_equal(np.float32(entry["reflectance"]), np.float32(m.reflectance))
    np.testing.assert_array_equal(np.float32(entry["lab_covariance"]), np.float32(m.lab_covariance))
    np.testing.assert_array_equal(np.float32(document["reference"]["lab"]), np.float32(rows_in[1].measurement.lab))
    # Every float in the text is the shortest decimal of its float32.
    numbers = re.findall(r"(?<![\w.])-?\d+(?:\.\d+e[-+]?\d+|\.\d+|e[-+]?\d+)", text)
    assert len(numbers) > 31 * 31
    for token in numbers:
        assert_shortest(token, np.float32(float(token)), np.float32)


def test_cgats_numbers_are_plain_shortest_decimals_colour_reads(tmp_path):
    import colour

    rows_in = results(np.float32)
    text = measurement_files.cgats_text(rows_in, input_path="x.tif", instrument_id=None, created="2026-01-01T00:00:00+00:00")
    lines = text.splitlines()
    fields = lines[lines.index("BEGIN_DATA_FORMAT") + 1].split("\t")
    data = [line.split("\t") for line in lines[lines.index("BEGIN_DATA") + 1 : lines.index("END_DATA")]]
    assert all(len(row) == len(fields) for row in data) and len(data) == 2
    for row, result in zip(data, rows_in):
        m = result.measurement
        values = [*m.lab, *m.reflectance]
        for token, value in zip(row[2:], values, strict=True):
            assert "e" not in token.lower()
            assert_shortest(token, value, np.float32)
    assert data[0][2] == "37.723576"

    (tmp_path / "qc.txt").write_text(text, encoding="utf-8")
    spectra = colour.io.read_sds_from_xrite_file(str(tmp_path / "qc.txt"))
    assert len(spectra) == 2
    for sd, result in zip(spectra.values(), rows_in):
        np.testing.assert_array_equal(sd.wavelengths, WAVELENGTHS)
        np.testing.assert_array_equal(np.float32(sd.values), np.float32(result.measurement.reflectance))
