"""The outputs of `spherejax measure`: its table, and its CSV and JSON files (formats below).

`spherejax measure -c CAL INPUT --region NAME=r0,r1,c0,c1 ...` measures rectangles of one image
as a spectrophotometer would (`spherejax.measurement.measure`): each region's mean reflectance,
its L*, a*, b*, and, with a noise model, their uncertainties. This module turns those
measurements into text and files; it computes nothing.

Uncertainties follow the GUM (JCGM 100:2008): u is a standard uncertainty (one standard
deviation, first order), U = k u the expanded uncertainty with coverage factor k = 2
(`COVERAGE_FACTOR`; about 95 % coverage for a Gaussian). The table shows U, the CSV both u and U,
the JSON u and covariances (U = 2 u). Without a noise model there are no uncertainties: the
table shows "n/a", the CSV leaves those cells empty, the JSON has null.

ΔE00 (CIEDE2000) is against a reference: another region of the same image (its covariance
included, the two taken as independent) or L*, a*, b* typed in (exact). Its first-order
uncertainty is 0 at ΔE00 = 0 and an understatement near it (`Measurement.delta_e`).

CSV (OUT.csv)
-------------
UTF-8, a header row, then one row per region in the order given:

    name, pixels, excluded_pixels, illuminant,
    L, a, b,                        the region's L*, a*, b* under `illuminant`
    u_L, u_a, u_b,                  their standard uncertainties
    U_L, U_a, U_b,                  expanded uncertainties, k = 2
    delta_e00, u_delta_e00, U_delta_e00,
                                    ΔE00 against the reference, u and U (empty without one)
    R400, R410, ..., R700           mean reflectance, 400..700 nm step 10 (31 columns)
    u_R400, ..., u_R700             its standard uncertainties (31 columns)

A name starting with =, +, -, @, a tab or a carriage return is written with a leading single
quote, so that a spreadsheet shows it as text rather than running it as a formula (OWASP, CSV
injection); the JSON keeps every name exactly. `pixels` is the number of pixels averaged; `excluded_pixels` those of the rectangle that
`correct` flags (saturated, not finite, no usable flat field) and that were left out. Numbers
are written as the shortest decimal that reads back as the same value at the precision the
measurement was computed in (`Measurement.precision`, `spherejax.number_text`): "37.723576" for
a float32 result, not the float64 digits "37.723575592041016" it shows; Python's repr digits for a
float64 one. A cell without a value (no noise model, no reference) is empty. The file is written
by Python's csv module: a name with a comma or a quote is quoted, inner quotes doubled.

JSON (OUT.json)
---------------
    {
      "format": "spherejax-measurement", "format_version": 1,
      "software_version": "0.1.0",
      "input": "path of the cube measured",
      "calibration": {"path": ..., "checksum": "sha256:...", "instrument_id": ...},
      "illuminant": "D65",
      "coverage_factor": 2,
      "noise_model": null, or {"source": "calibration" | "options" | "calibration, options",
                     "gain_e_per_count", "read_noise_counts", "dark_frames", "white_frames",
                     "sample_frames", "white_reflectance_u",
                     "coeffs_covariance": true/false, "estimator_covariance": true/false},
      "reference": null, {"region": NAME, "lab": [L, a, b]} or {"lab": [L, a, b]} (exact),
      "regions": [
        {"name": ..., "rect": [r0, r1, c0, c1],    rows r0..r1-1, columns c0..c1-1
         "illuminant", "observer", "pixels", "excluded_pixels",
         "reflectance": [31], "reflectance_u": [31] or null, "reflectance_spread": [31],
         "reflectance_covariance": [31 x 31] or null,
         "lab": [3], "lab_u": [3] or null, "lab_covariance": [3 x 3] or null,
         "lab_u_by_source": {source: [3]},       each source's part of lab_u
         "delta_e00": number or null, "u_delta_e00": number or null},
        ...
      ]
    }

The region fields are `Measurement.to_dict()`; "reflectance_spread" is the standard deviation of
the per-pixel reflectances over the region (non-uniformity and pixel noise, not an uncertainty
of the mean). All numbers are finite, in the shortest form of their precision like the CSV's;
what is not known is null.

CGATS (--cgats FILE)
-------------------
The regions as colour quality-control software exchanges spectral measurements: CGATS.17 text
(ISO 28178, `spherejax.io.cgats`) in the X-Rite layout, which colour-science's
`read_sds_from_xrite_file` and ArgyllCMS read:

    CGATS.17
    ORIGINATOR "spherejax 0.1.0", DESCRIPTOR, CREATED (ISO 8601), INSTRUMENTATION
    ILLUMINATION_NAME "D65"           the illuminant of LAB_L, LAB_A, LAB_B
    OBSERVER_ANGLE "2"                2 (CIE 1931) or 10 (CIE 1964) degrees
    MEASUREMENT_SOURCE "Illumination=D65 ObserverAngle=2 WhiteBase=Abs"
    SPECTRAL_BANDS "31", SPECTRAL_START_NM "400", SPECTRAL_END_NM "700", SPECTRAL_NORM "1"
    SAMPLE_ID SAMPLE_NAME LAB_L LAB_A LAB_B nm400 nm410 ... nm700

one line per region in the order given: SAMPLE_ID 1, 2, ...; SAMPLE_NAME the region's name as
one token (`cgats_sample_names`: readers split data lines on whitespace, so spaces become "_",
and a name made equal to an earlier one gets "_2");
reflectance factors (0..1, white standard 1), numbers in the shortest form like the CSV's (plain
decimals, no exponent). The
uncertainties are in the CSV and JSON only (CGATS.17 has no fields for them).

The files are written together by `write_files`: each to a temporary name beside it, then
renamed into place, so that on any failure no file is left half-written and no new file is
left at all.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
from collections.abc import Mapping, Sequence

import numpy as np

from .colorimetry import OBSERVERS
from .grid import N_WAVELENGTHS
from . import atomic_files
from .io.cgats import cgats_text as _cgats_table
from .io.documents import _readable_json
from .io.errors import SpherejaxFileError
from .measurement import Measurement
from .number_text import csv_text as _csv_table
from .number_text import json_ready, number_text

FORMAT = "spherejax-measurement"
FORMAT_VERSION = 1
#: k of the expanded uncertainty U = k u (GUM, Sec. 6).
COVERAGE_FACTOR = 2
#: 400..700 nm step 10, the wavelengths of a reflectance.
WAVELENGTHS_NM = tuple(range(400, 400 + 10 * N_WAVELENGTHS, 10))
#: The wavelengths the table shows.
TABLE_WAVELENGTHS_NM = (450, 550, 650)
#: What `default_base` appends to the input's stem.
SUFFIX = ".measure"


@dataclasses.dataclass(frozen=True)
class RegionResult:
    """One row of the outputs.

    Fields:
      name: the region's name; rect: (r0, r1, c0, c1), rows r0..r1-1, columns c0..c1-1.
      measurement: its `Measurement`.
      delta_e: ΔE00 against the reference, or None without one.
      delta_e_u: its standard uncertainty (NaN or None without a noise model).
    """

    name: str
    rect: tuple[int, int, int, int]
    measurement: Measurement
    delta_e: float | None = None
    delta_e_u: float | None = None


def _known(x) -> float | None:
    """A float, or None for a value that is not known (None, NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _nulled(x):
    """Plain JSON with NaN and infinities as null."""
    if isinstance(x, dict):
        return {k: _nulled(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nulled(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _listed(x):
    """JSON of numbers (NumPy values in the shortest form of their dtype,
    `number_text.json_ready`), NaN and infinities as null."""
    return _nulled(json_ready(x))


def _number(x, precision) -> float | None:
    """A JSON number in the shortest form at `precision`, or None for a value not known."""
    x = _known(x)
    return None if x is None else json_ready(x, precision)


# ---------------------------------------------------------------------------------------- table


def _value_u(value: float, u: float | None, digits: int) -> str:
    """"value ± U" (U = k u), or "value ± n/a" without an uncertainty."""
    text = f"{value:.{digits}f} ± "
    if u is None or not math.isfinite(u):
        return text + "n/a"
    return text + f"{COVERAGE_FACTOR * u:.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Columns right-aligned (the first left-aligned), two spaces between."""
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = []
    for row in [header, *rows]:
        cells = [row[0].ljust(widths[0])] + [cell.rjust(width) for cell, width in zip(row[1:], widths[1:])]
        lines.append("  ".join(cells).rstrip())
    return lines


def format_table(results: Sequence[RegionResult], *, reference: str | None = None) -> str:
    """The table `spherejax measure` prints: per region the pixels, L*, a*, b* (and ΔE00) ± U,
    then a second block of reflectance at 450, 550 and 650 nm ± U and its minimum and maximum.

    Args:
      results: the regions, in order.
      reference: how the reference reads in the title ('region "white"', 'L*a*b* = (50, 0, 0)'),
        or None without a reference (no ΔE00 column).
    """
    first = results[0].measurement
    uncertain = any(r.measurement.lab_covariance is not None for r in results)
    title = f"L*a*b* under {first.illuminant} ({first.observer})"
    title += f"; ± U: expanded uncertainty, k = {COVERAGE_FACTOR}" if uncertain else "; no uncertainties (no noise model)"
    lines = [title]
    if reference is not None:
        lines.append(f"ΔE00 against {reference}")
    lines.append("")

    excluded = any(r.measurement.excluded for r in results)
    header = ["region", "pixels", *(["excluded"] if excluded else []), "L*", "a*", "b*"]
    if reference is not None:
        header.append("ΔE00")
    rows = []
    for r in results:
        m = r.measurement
        lab_u = m.lab_u if m.lab_u is not None else [None] * 3
        row = [r.name, str(m.pixels), *([str(m.excluded)] if excluded else [])]
        row += [_value_u(v, u, 2) for v, u in zip(m.lab.tolist(), lab_u)]
        if reference is not None:
            row.append(_value_u(r.delta_e, r.delta_e_u, 2))
        rows.append(row)
    lines += _table(header, rows)
    lines.append("")

    header = ["region", *(f"R{nm}" for nm in TABLE_WAVELENGTHS_NM), "min (nm)", "max (nm)"]
    rows = []
    for r in results:
        m = r.measurement
        u = m.reflectance_u if m.reflectance_u is not None else [None] * N_WAVELENGTHS
        row = [r.name]
        for nm in TABLE_WAVELENGTHS_NM:
            i = WAVELENGTHS_NM.index(nm)
            row.append(_value_u(float(m.reflectance[i]), None if u[i] is None else float(u[i]), 4))
        low, high = int(np.argmin(m.reflectance)), int(np.argmax(m.reflectance))
        row.append(f"{m.reflectance[low]:.4f} ({WAVELENGTHS_NM[low]})")
        row.append(f"{m.reflectance[high]:.4f} ({WAVELENGTHS_NM[high]})")
        rows.append(row)
    lines += _table(header, rows)
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ CSV


def csv_header() -> list[str]:
    """The CSV's columns (module docstring)."""
    return [
        "name", "pixels", "excluded_pixels", "illuminant",
        "L", "a", "b", "u_L", "u_a", "u_b", "U_L", "U_a", "U_b",
        "delta_e00", "u_delta_e00", "U_delta_e00",
        *(f"R{nm}" for nm in WAVELENGTHS_NM), *(f"u_R{nm}" for nm in WAVELENGTHS_NM),
    ]


def _cell(x, precision) -> str:
    """A number in the shortest form at `precision` (`number_text`), "" for a value not known."""
    x = _known(x)
    return "" if x is None else number_text(x, precision)


#: First characters that make a spreadsheet read a cell as a formula (OWASP, "CSV Injection").
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def _inert_text(text: str) -> str:
    """A text cell a spreadsheet shows as text: one starting like a formula gets a leading single
    quote, as OWASP recommends (a region named "=HYPERLINK(...)" or "-2+3" stays a name). The
    JSON keeps the name exactly."""
    return "'" + text if text.startswith(_FORMULA_STARTS) else text


def csv_text(results: Sequence[RegionResult]) -> str:
    """The CSV file's text (module docstring)."""
    rows = []
    for r in results:
        m = r.measurement
        cell = lambda x: _cell(x, m.precision)  # noqa: E731
        lab_u = m.lab_u.tolist() if m.lab_u is not None else [None] * 3
        refl_u = m.reflectance_u.tolist() if m.reflectance_u is not None else [None] * N_WAVELENGTHS
        expanded = [None if u is None else COVERAGE_FACTOR * u for u in lab_u]
        de_u = _known(r.delta_e_u)
        rows.append([
            _inert_text(r.name), m.pixels, m.excluded, m.illuminant,
            *map(cell, m.lab.tolist()), *map(cell, lab_u), *map(cell, expanded),
            cell(r.delta_e), cell(de_u), cell(None if de_u is None else COVERAGE_FACTOR * de_u),
            *map(cell, m.reflectance.tolist()), *map(cell, refl_u),
        ])
    return _csv_table(csv_header(), rows)


# ----------------------------------------------------------------------------------------- JSON


def noise_model_summary(noise, source: str) -> dict | None:
    """The JSON's "noise_model": where it came from and its scalar settings, or None."""
    if noise is None:
        return None
    summary = {"source": source}
    for key, field in (("gain_e_per_count", "gain"), ("read_noise_counts", "read_noise"), ("dark_frames", "dark_frames"),
                       ("white_frames", "white_frames"), ("sample_frames", "sample_frames"),
                       ("white_reflectance_u", "white_reflectance_u")):
        summary[key] = json_ready(np.asarray(getattr(noise, field)))  # in the model's own dtype
    summary["coeffs_covariance"] = noise.coeffs_covariance is not None
    summary["estimator_covariance"] = noise.estimator_covariance is not None
    return summary


def json_document(
    results: Sequence[RegionResult], *, input_path, calibration: Mapping, illuminant: str,
    reference: Mapping | None, noise_model: Mapping | None,
) -> dict:
    """The JSON file's document (module docstring).

    Args:
      results: the regions. input_path: the cube measured.
      calibration: {"path", "checksum", "instrument_id"} of the calibration file.
      illuminant: Lab's illuminant. reference: the "reference" entry (or None).
      noise_model: `noise_model_summary` (or None).
    """
    from . import __version__

    regions = []
    for r in results:
        entry = {"name": r.name, "rect": [int(v) for v in r.rect], **r.measurement.to_dict()}
        entry["delta_e00"] = _number(r.delta_e, r.measurement.precision)
        entry["u_delta_e00"] = _number(r.delta_e_u, r.measurement.precision)
        regions.append(entry)
    if reference is not None and "region" in reference:
        # A region's Lab as its own entry states it (the caller may hand it over as float64 digits).
        against = {r.name: r.measurement for r in results}.get(reference["region"])
        if against is not None:
            reference = {**reference, "lab": against.to_dict()["lab"]}
    return _listed({
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "software_version": __version__,
        "input": str(input_path),
        "calibration": dict(calibration),
        "illuminant": illuminant,
        "coverage_factor": COVERAGE_FACTOR,
        "noise_model": None if noise_model is None else dict(noise_model),
        "reference": None if reference is None else dict(reference),
        "regions": regions,
    })


def json_text(document: Mapping) -> str:
    """The document as text: one field per line, a list of numbers on one line."""
    return _readable_json(_listed(document)) + "\n"


# ---------------------------------------------------------------------------------------- CGATS

#: CGATS's OBSERVER_ANGLE of each observer `measure` may use.
_OBSERVER_ANGLE = {"CIE 1931 2 Degree Standard Observer": "2", "CIE 1964 10 Degree Standard Observer": "10"}


def cgats_text(results: Sequence[RegionResult], *, input_path, instrument_id: str | None, created: str) -> str:
    """The CGATS.17 file's text (module docstring).

    Args:
      results: the regions, in order; all measured under one illuminant and observer.
      input_path: the cube measured (in DESCRIPTOR). instrument_id: the calibration's (or None).
      created: ISO 8601 date and time of the measurement.
    """
    from . import __version__

    first = results[0].measurement
    angle = _OBSERVER_ANGLE[OBSERVERS[first.observer]]  # the observer's canonical name ("1964" too)
    instrument = "integrating-sphere multispectral camera" + (f" {instrument_id}" if instrument_id else "")
    keywords = {
        "ORIGINATOR": f"spherejax {__version__}",
        "DESCRIPTOR": f"regions of {input_path}",
        "CREATED": created,
        "INSTRUMENTATION": instrument,
        "MEASUREMENT_SOURCE": f"Illumination={first.illuminant} ObserverAngle={angle} WhiteBase=Abs",
        "ILLUMINATION_NAME": first.illuminant,
        "OBSERVER_ANGLE": angle,
        "SPECTRAL_BANDS": N_WAVELENGTHS,
        "SPECTRAL_START_NM": WAVELENGTHS_NM[0],
        "SPECTRAL_END_NM": WAVELENGTHS_NM[-1],
        "SPECTRAL_NORM": 1,
    }
    fields = ["SAMPLE_ID", "SAMPLE_NAME", "LAB_L", "LAB_A", "LAB_B", *(f"nm{nm}" for nm in WAVELENGTHS_NM)]
    rows = []
    for number, (r, name) in enumerate(zip(results, cgats_sample_names([r.name for r in results])), start=1):
        m = r.measurement
        # NumPy scalars of the measurement's precision: the shortest decimal of each (io.cgats).
        values = np.concatenate([m.lab, m.reflectance]).astype(np.dtype(m.precision))
        rows.append([number, name, *values])
    return _cgats_table(keywords, fields, rows)


def cgats_sample_names(names: Sequence[str]) -> list[str]:
    """SAMPLE_NAME of each region: one token, unique in the file.

    CGATS.17 allows a quoted name with spaces, but the readers colour labs use split data lines
    on whitespace (colour-science's `read_sds_from_xrite_file` names each spectrum by the second
    token; X-Rite's readers likewise), so "red wool" and "red cotton" both came back as `"red`,
    one measurement lost. A name that is one token (no whitespace, no quote) is written as it
    is; in others each run of whitespace becomes "_" and a quote "'"; a name that would then
    repeat an earlier one gets "_2", "_3", ... The CSV and JSON keep the names exactly.
    """
    tokens, taken = [], set()
    for name in names:
        token = re.sub(r"[\s\"'#]+", "_", name.strip()) or "region"
        candidate, count = token, 1
        while candidate in taken:
            count += 1
            candidate = f"{token}_{count}"
        taken.add(candidate)
        tokens.append(candidate)
    return tokens


def check_cgats_path(path, other_outputs: Sequence[pathlib.Path] = ()) -> None:
    """SpherejaxFileError unless --cgats FILE names a file (not a folder) in an existing folder,
    other than `other_outputs` (OUT.csv, OUT.json)."""
    path = pathlib.Path(path)
    for other in other_outputs:
        if path.absolute() == pathlib.Path(other).absolute():
            raise SpherejaxFileError(path, "is also the measurement's CSV or JSON file", "--cgats FILE another file than OUT.csv and OUT.json")
    _require_file_in_a_folder(path, "--cgats FILE: a file to write the CGATS.17 text to",
                              "--cgats FILE in an existing folder")


# ---------------------------------------------------------------------------------------- files


def default_base(input_path) -> pathlib.Path:
    """OUT when -o is not given: the input's stem + ".measure", in the current folder."""
    return pathlib.Path(pathlib.Path(input_path).stem + SUFFIX)


def output_paths(base) -> tuple[pathlib.Path, pathlib.Path]:
    """(OUT.csv, OUT.json): the suffixes are appended to the base path, never substituted."""
    base = pathlib.Path(base)
    return base.with_name(base.name + ".csv"), base.with_name(base.name + ".json")


def _require_file_in_a_folder(path: pathlib.Path, as_a_file: str, in_a_folder: str) -> None:
    """SpherejaxFileError unless `path` can name a new file: not a folder, in an existing folder;
    the expected texts say how the option should be given."""
    if path.name in ("", ".", "..") or path.is_dir():
        raise SpherejaxFileError(path, "is a folder", as_a_file)
    if not path.parent.is_dir():
        problem = "is in a folder that does not exist" if not path.parent.exists() else "is in something that is not a folder"
        raise SpherejaxFileError(path, problem, in_a_folder)


def check_output_base(base) -> None:
    """SpherejaxFileError unless OUT is a base path (not a folder) in an existing folder."""
    _require_file_in_a_folder(
        pathlib.Path(base), "a base path: -o FOLDER/NAME writes FOLDER/NAME.csv and FOLDER/NAME.json",
        "OUT in an existing folder (-o OUT writes OUT.csv and OUT.json)",
    )


# What each output of `measure` starts with: the signature on the file itself by which a file at
# an output's name is known to be one an earlier `measure` wrote, and so may be replaced
# (docs/reliability.md, "Files"). Nothing else counts: not the name, not the folder, not a
# file's being a regular file. A CSV begins with its header row (`csv_header`, as
# number_text.csv_text writes it), the JSON with its "format" field (`json_text` writes it first,
# on the second line), the CGATS file with CGATS.17's first line and ORIGINATOR "spherejax ..."
# (`cgats_text`: ORIGINATOR is a keyword of the standard, written first, with no KEYWORD line).
_SIGNATURES = {
    "csv": (",".join(csv_header()) + "\n").encode(),
    "json": b'{\n  "format": "' + FORMAT.encode() + b'",\n',
    "cgats": b'CGATS.17\nORIGINATOR\t"spherejax ',
}
_SIGNATURE_WORDS = {
    "csv": "its first line is not the header of measure's CSV",
    "json": f'it does not begin with "format": "{FORMAT}"',
    "cgats": 'it does not begin with CGATS.17 and ORIGINATOR "spherejax ..."',
}


def not_a_measurement_file(path, kind: str) -> str | None:
    """None if `path` is a `kind` ("csv", "json" or "cgats") output an earlier `spherejax measure`
    wrote (it begins with that output's signature, `_SIGNATURES`), else why not: the `replaceable`
    test of `io.ownership.refuse_in_the_way` for measure's outputs."""
    import os

    signature = _SIGNATURES[kind]
    try:
        # O_NOFOLLOW, O_NONBLOCK: a link or FIFO put there since it was looked at is not followed
        # or waited on (refuse_in_the_way refused them by what they are).
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as error:
        return f"a file that cannot be read ({error.strerror})"
    try:
        start = os.read(fd, len(signature))
    except OSError as error:
        return f"a file that cannot be read ({error.strerror})"
    finally:
        os.close(fd)
    if start == signature:
        return None
    return f"a file spherejax measure did not write ({_SIGNATURE_WORDS[kind]})"


def refuse_foreign_files(csv_path, json_path, cgats_path=None) -> None:
    """Before any work: nothing lies at an output's name but what an earlier `measure` wrote
    (`not_a_measurement_file`); a folder, link, FIFO or a file of the user's there is refused.

    Raises:
      SpherejaxFileError: one line naming the file in the way.
    """
    from .io import ownership

    outputs = [("OUT.csv", csv_path, "csv"), ("OUT.json", json_path, "json")]
    if cgats_path is not None:
        outputs.append(("--cgats FILE", cgats_path, "cgats"))
    for label, path, kind in outputs:
        ownership.refuse_in_the_way(
            {label: path}, replaceable=lambda found, kind=kind: not_a_measurement_file(found, kind),
            expected=f"{label} a new file, or one an earlier spherejax measure wrote, to replace",
        )


def write_files(files: Mapping[pathlib.Path, bytes]) -> None:
    """Write every path -> bytes as one set (`spherejax.atomic_files.write_together`: all the
    temporary files first, then the renames); SpherejaxFileError naming the file on a failure."""
    try:
        atomic_files.write_together(files)
    except OSError as error:
        raise SpherejaxFileError(error.filename, f"could not be written: {error.strerror or error}") from None


__all__ = [
    "COVERAGE_FACTOR",
    "FORMAT",
    "FORMAT_VERSION",
    "RegionResult",
    "cgats_text",
    "check_cgats_path",
    "check_output_base",
    "cgats_sample_names",
    "csv_header",
    "csv_text",
    "default_base",
    "format_table",
    "json_document",
    "json_text",
    "noise_model_summary",
    "not_a_measurement_file",
    "output_paths",
    "refuse_foreign_files",
    "write_files",
]
