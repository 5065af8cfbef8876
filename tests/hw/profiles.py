"""Instrument profiles for the tests (tests/hw/test_profile.py, test_noise_records.py): the
example profile as data, a writer of the TOML subset profiles use, and the check of a
refusal's one-line message."""

from __future__ import annotations

import json
import math
import pathlib
import re

from spherejax_hw.profile import ProfileError

BANDS = list(range(400, 701, 20))


def example() -> dict:
    """The example profile as data, to be changed by a test and written with `dump`."""
    return {
        "instrument": {"id": "sphere-1"},
        "wheels": {
            "a": {"port": "/dev/ttyUSB0", "model": "FW212C", "open_slot": 12},
            "b": {"port": "/dev/ttyUSB1", "model": "FW212C", "open_slot": 12},
        },
        "shutter": {"port": "/dev/ttyUSB2", "model": "SC10"},
        "camera": {"backend": "sim"},
        "bands": {str(nm): ["a" if i < 8 else "b", i % 8 + 1] for i, nm in enumerate(BANDS)},
    }


# -- a small TOML writer (the subset profiles use) -------------------------------------------------

_BARE = re.compile(r"[A-Za-z0-9_-]+")


def _key(name: str) -> str:
    return name if _BARE.fullmatch(name) else json.dumps(name)


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    raise TypeError(value)


def _is_table_array(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _table(lines: list[str], prefix: str, table: dict) -> None:
    for name, value in table.items():
        if not isinstance(value, dict) and not _is_table_array(value):
            lines.append(f"{_key(name)} = {_value(value)}")
    for name, value in table.items():
        dotted = f"{prefix}.{_key(name)}" if prefix else _key(name)
        if isinstance(value, dict):
            lines.append(f"[{dotted}]")
            _table(lines, dotted, value)
        elif _is_table_array(value):
            for item in value:
                lines.append(f"[[{dotted}]]")
                _table(lines, dotted, item)


def dump(data: dict) -> str:
    lines: list[str] = []
    _table(lines, "", data)
    return "\n".join(lines) + "\n"


def write(folder: pathlib.Path, data: dict | str, name: str = "profile.toml") -> pathlib.Path:
    path = folder / name
    path.write_text(data if isinstance(data, str) else dump(data), encoding="utf-8")
    return path


def check_message(error: ProfileError, path: pathlib.Path, key: str | None, expected: str) -> str:
    message = str(error)
    assert "\n" not in message and "\r" not in message, message
    assert message.startswith(f"{path}: "), message
    if key is not None:
        assert error.key == key, message
        assert f": {key}: " in message, message
    assert "(expected " in message, message
    assert expected in message, message
    return message
