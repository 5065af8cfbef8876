"""CGATS.17 (ISO 28178) text: the exchange format of colour measurement data.

Colour quality-control software, spectrophotometer drivers and ArgyllCMS exchange measurements as
CGATS text: a file identifier line, keyword lines (``KEYWORD<TAB>"value"``), a data format block
naming the fields, then one line per sample. This module writes that text from keywords, field
names and rows; what the fields mean is the caller's (`spherejax.measurement_files.cgats_text`).

    CGATS.17
    ORIGINATOR	"spherejax 0.1.0"
    KEYWORD	"ILLUMINATION_NAME"
    ILLUMINATION_NAME	"D65"
    NUMBER_OF_FIELDS	37
    BEGIN_DATA_FORMAT
    SAMPLE_ID	SAMPLE_NAME	LAB_L	LAB_A	LAB_B	nm400	...	nm700
    END_DATA_FORMAT
    NUMBER_OF_SETS	2
    BEGIN_DATA
    1	paper	93.1	-0.41	2.7	0.861	...
    END_DATA

Rules kept so that every reader in use takes the file (ArgyllCMS's cgats parser, X-Rite's
readers and colour-science's `read_sds_from_xrite_file`, which splits data lines on whitespace):
tab-separated; keyword values quoted; a keyword that CGATS.17 does not define is declared by a
``KEYWORD "NAME"`` line before its first use; numbers as plain decimals (no exponent), the shortest
that read back as the same value at its own precision (`spherejax.number_text`: a float32 value
as the shortest decimal of that float32, "37.723576", a float64 one as Python's repr digits,
an integer as an integer); a text field is written bare when it is a single token that cannot be
read as a number, else quoted with inner quotes doubled.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence

import numpy as np

from ..number_text import number_text

#: Keywords CGATS.17 defines (ISO 28178, Annex A; the ones ArgyllCMS knows without declaration).
STANDARD_KEYWORDS = frozenset(
    """ORIGINATOR DESCRIPTOR CREATED MANUFACTURER MANUFACTURE PROD_DATE SERIAL MATERIAL
    INSTRUMENTATION MEASUREMENT_SOURCE PRINT_CONDITIONS SAMPLE_BACKING FILTER POLARIZATION
    WEIGHTING_FUNCTION COMP_METHOD NORMALIZATION_METHOD NUMBER_OF_FIELDS NUMBER_OF_SETS""".split()
)

#: A token some reader would take for a number (integers, decimals, exponents, nan, inf).
_NUMBER_LIKE = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", re.IGNORECASE)


def _quoted(text: str) -> str:
    return '"' + text.replace('"', '""') + '"'


def _one_line(text: str) -> str:
    """A keyword's value on one line: CGATS is read line by line, and a control character (a
    newline in a file name, say) would end the value early."""
    return "".join(c if c.isprintable() else " " for c in text)


def _field(value) -> str:
    """One data cell: an integer as is, a float in the shortest decimal of its precision (a NumPy
    float32 as float32), text bare or quoted."""
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"a CGATS field holds numbers or text, not {value!r}")
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if not math.isfinite(value):
            raise ValueError(f"a CGATS number must be finite, not {value!r}")
        return number_text(value)
    text = str(value)
    if not text.isprintable():
        raise ValueError(f"a CGATS text field must be printable, not {text!r}")
    bare = text and not any(c.isspace() or c in "\"'#" for c in text) and not _NUMBER_LIKE.fullmatch(text)
    return text if bare else _quoted(text)


def cgats_text(keywords: Mapping[str, str | int | float], fields: Sequence[str], rows: Sequence[Sequence]) -> str:
    """The CGATS.17 text of one table.

    Args:
      keywords: header keyword -> value, in order (values written quoted, as strings, control
        characters as spaces); keywords that CGATS.17 does not define are declared first with
        KEYWORD lines.
      fields: the data format: field names (letters, digits and "_", no spaces).
      rows: one sequence of len(fields) values per sample: int, float (finite; a NumPy float32
        is written as the shortest decimal of its float32) or str.

    Returns:
      The text, lines ending in "\\n", ending with END_DATA.

    Raises:
      ValueError: a malformed field or keyword name, a row of the wrong length, a number that is
        not finite, a text field with a control character.
    """
    for name in [*keywords, *fields]:
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
            raise ValueError(f"CGATS name {name!r}: expected letters, digits and '_', starting with a letter")
    lines = ["CGATS.17"]
    for name, value in keywords.items():
        if name not in STANDARD_KEYWORDS:
            lines.append(f"KEYWORD\t{_quoted(name)}")
        lines.append(f"{name}\t{_quoted(_one_line(str(value)))}")
    lines += [f"NUMBER_OF_FIELDS\t{len(fields)}", "BEGIN_DATA_FORMAT", "\t".join(fields), "END_DATA_FORMAT"]
    lines += [f"NUMBER_OF_SETS\t{len(rows)}", "BEGIN_DATA"]
    for index, row in enumerate(rows):
        if len(row) != len(fields):
            raise ValueError(f"CGATS row {index}: {len(row)} values for {len(fields)} fields")
        lines.append("\t".join(_field(value) for value in row))
    lines.append("END_DATA")
    return "\n".join(lines) + "\n"


__all__ = ["STANDARD_KEYWORDS", "cgats_text"]
