"""Numbers as text, at the precision they were computed in, and tables as CSV.

spherejax computes in float32 by default. A float32 value printed as a float64 shows digits the
computation never had: np.float32(37.723576) is 37.723575592041016 as a float64, and
`.tolist()` or `float()` of a float32 array hands over exactly that float64. Every file
spherejax writes (CSV, CGATS.17, JSON) states a number instead by the shortest decimal that
reads back as the same value of its own precision:

- a float32 value: the shortest decimal that parses back to the same float32 ("37.723576");
- a float64 value: the shortest that parses back to the same float64 (Python's repr digits);
- an integer: as an integer.

The precision is the value's dtype: a NumPy float32 array or scalar (or a JAX one) is float32,
a Python float float64. Where a float32 result has already become a Python float (a float64
array holding float32 values, `float(x)` of a float32 scalar), the writer says so with
`precision=`; better, it keeps the value in its dtype until it is written.

`number_text` gives the text of one number for CSV and CGATS: positional, never an exponent
(CGATS.17 data and spreadsheets take plain decimals everywhere), at least one digit after the
point for a float ("50.0"), so that a float column reads as floats. `json_ready` turns values
(NumPy arrays and scalars included) into plain JSON values whose floats are Python floats with
those digits: `json.dumps` then writes the short form, since Python's repr of the float64
nearest "37.723576" is "37.723576". `csv_text` writes a table with Python's csv module (RFC 4180
quoting: a cell with a comma, a quote or a line break is quoted, inner quotes doubled), numbers
by `number_text`.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping, Sequence

import numpy as np


def _precision(value, precision) -> np.dtype:
    """The floating dtype a number is written at: `precision` if given, else its own."""
    if precision is not None:
        dtype = np.dtype(precision)
        if not np.issubdtype(dtype, np.floating):
            raise ValueError(f"precision: expected a floating dtype (float32, float64), got {dtype}")
        return dtype
    if isinstance(value, np.floating):
        return value.dtype
    return np.dtype(np.float64)


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def number_text(value, precision=None) -> str:
    """The shortest decimal that reads back as the same value at its precision (module docstring).

    Args:
      value: an int, a float, a NumPy integer or floating scalar, or a 0-d array.
      precision: the floating dtype the value was computed in (np.float32 for a float64 or Python
        float that holds a float32 result); None: the value's own (a Python float is float64).

    Returns:
      An integer as an integer ("16"); a float positional with at least one digit after the
      point ("37.723576", "50.0", "0.0001", "-0.0"), "nan", "inf" or "-inf" when not finite.

    Raises:
      TypeError: a bool, text or anything else that is not a number.
    """
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if _is_integer(value):
        return str(int(value))
    if not isinstance(value, (float, np.floating)):
        raise TypeError(f"number_text: expected a number, got {type(value).__name__} {value!r}")
    dtype = _precision(value, precision)
    scalar = dtype.type(value)
    if not np.isfinite(scalar):
        return "nan" if np.isnan(scalar) else ("inf" if scalar > 0 else "-inf")
    return np.format_float_positional(scalar, unique=True, trim="0")


def _short_float(value, dtype: np.dtype) -> float:
    """A Python float whose repr is the shortest decimal of `value` as a `dtype` number."""
    if dtype == np.float64:
        return float(value)
    scalar = dtype.type(value)
    if not np.isfinite(scalar):
        return float(scalar)
    # Its shortest round-trip decimal (not str(): NumPy's legacy print mode, which a library may
    # switch on, shows 6 digits).
    return float(np.format_float_scientific(scalar, unique=True))


def json_ready(value, precision=None):
    """`value` as plain JSON values, every float in its shortest form at its precision.

    Walks mappings (to dicts), lists and tuples (to lists), NumPy and JAX arrays (to nested
    lists) and NumPy scalars (to Python numbers); a float32 value becomes the Python float whose
    repr is its shortest float32 decimal, a float64 value stays itself, an integer an int, a NumPy
    bool a bool. Anything else (str, None, int, bool) is returned as it is. Non-finite floats are
    kept (nan, inf): whether JSON may hold them is the writer's choice (json.dumps allow_nan).

    Args:
      value: what to convert.
      precision: the floating dtype every float in `value` was computed in (np.float32 for
        float64 arrays or Python floats that hold float32 results), or None for each value's own
        dtype (Python floats are float64).
    """
    if isinstance(value, Mapping):
        return {key: json_ready(item, precision) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(item, precision) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if _is_integer(value):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _short_float(value, _precision(value, precision))
    if not isinstance(value, (str, np.ndarray)) and hasattr(value, "__array__") and hasattr(value, "dtype"):
        value = np.asarray(value)  # a JAX array
    if isinstance(value, np.ndarray):
        if value.dtype == np.bool_ or np.issubdtype(value.dtype, np.integer):
            return value.tolist()
        if np.issubdtype(value.dtype, np.floating):
            dtype = _precision(value.dtype.type(0), precision)
            if dtype == np.float64:
                return value.astype(np.float64).tolist()
            return _nested(value.astype(dtype))
        return json_ready(value.tolist(), precision)
    return value


def _nested(array: np.ndarray):
    if array.ndim == 0:
        return _short_float(array[()], array.dtype)
    return [_nested(row) for row in array]


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, float, np.number)) or (isinstance(value, np.ndarray) and value.ndim == 0):
        return number_text(value)
    return str(value)


def csv_text(header: Sequence, rows: Iterable[Sequence]) -> str:
    """CSV text of a table, written by Python's csv module.

    RFC 4180 quoting (a cell holding a comma, a quote or a line break is quoted, inner quotes
    doubled), lines ending in "\\n", UTF-8 as the caller encodes it. Cells: text as it is, None
    as empty, numbers by `number_text` at their own precision (a NumPy float32 is float32; a
    writer that holds float32 results as Python floats formats them with `number_text(x,
    np.float32)` first).

    Args:
      header: the column names.
      rows: one sequence of cells per row.
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([_cell(c) for c in header])
    for row in rows:
        writer.writerow([_cell(c) for c in row])
    return buffer.getvalue()


__all__ = ["csv_text", "json_ready", "number_text"]
