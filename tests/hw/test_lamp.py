"""The manual xenon lamp: switch-on records, warm-up time, lamp hours, the state file."""

from __future__ import annotations

import datetime
import json
import os

import pytest

from spherejax_hw.lamp import FORMAT, MAX_WARMUPS, Lamp, LampError, LampStateError

T0 = datetime.datetime(2026, 1, 5, 9, 0, 0, tzinfo=datetime.timezone.utc)


def at(**delta) -> datetime.datetime:
    return T0 + datetime.timedelta(**delta)


def test_missing_file_is_a_new_lamp(tmp_path):
    lamp = Lamp(tmp_path / "lamp.json")
    assert not lamp.is_on and lamp.on_since is None and lamp.ignitions == 0
    assert lamp.hours(at()) == 0.0 and lamp.warmed_up_s(at()) == 0.0 and lamp.warmups == []
    assert list(tmp_path.iterdir()) == []  # reading writes nothing


def test_state_round_trip(tmp_path):
    path = tmp_path / "lamp.json"
    Lamp(path).switch_on(at())
    again = Lamp(path)  # another process, later
    assert again.is_on and again.on_since == T0 and again.ignitions == 1
    assert again.warmed_up_s(at(seconds=90)) == 90.0
    assert again.hours(at(minutes=30)) == pytest.approx(0.5)
    state = json.loads(path.read_text())
    assert state == {"format": FORMAT, "hours": 0.0, "on_since": "2026-01-05T09:00:00+00:00", "ignitions": 1, "warmups": []}


def test_hours_accumulate_over_runs(tmp_path):
    lamp = Lamp(tmp_path / "lamp.json")
    lamp.switch_on(at())
    assert lamp.switch_off(at(hours=2)) == pytest.approx(2.0)
    assert not lamp.is_on and lamp.warmed_up_s(at(hours=3)) == 0.0
    assert lamp.hours(at(days=1)) == pytest.approx(2.0)  # off: no hours
    lamp.switch_on(at(days=1))
    assert lamp.hours(at(days=1, minutes=45)) == pytest.approx(2.75)
    lamp.switch_off(at(days=1, hours=1.5))
    assert Lamp(lamp.state_file).hours(at(days=2)) == pytest.approx(3.5)
    assert lamp.ignitions == 2


def test_injectable_clock_and_timezones(tmp_path):
    now = [at()]
    lamp = Lamp(tmp_path / "lamp.json", clock=lambda: now[0])
    lamp.switch_on()
    now[0] = at(minutes=10)
    assert lamp.warmed_up_s() == 600.0
    # Any UTC offset is accepted and stored in UTC.
    tokyo = datetime.timezone(datetime.timedelta(hours=9))
    assert lamp.warmed_up_s(at(minutes=20).astimezone(tokyo)) == 1200.0
    with pytest.raises(ValueError, match="is not a timezone-aware datetime"):
        lamp.hours(datetime.datetime(2026, 1, 5, 10, 0))


def test_records_out_of_order(tmp_path):
    lamp = Lamp(tmp_path / "lamp.json")
    with pytest.raises(LampError, match="recorded as off; switch_on first"):
        lamp.switch_off(at())
    lamp.switch_on(at())
    with pytest.raises(LampError, match=r"recorded as on since 2026-01-05T09:00:00\+00:00; switch_off first"):
        lamp.switch_on(at(hours=1))
    # A wall clock stepped back before the switch-on adds no (negative) hours.
    assert lamp.warmed_up_s(at(seconds=-5)) == 0.0
    assert lamp.switch_off(at(seconds=-5)) == 0.0 and lamp.hours(at()) == 0.0


def test_record_warmup(tmp_path):
    lamp = Lamp(tmp_path / "lamp.json")
    with pytest.raises(LampError, match="lamp recorded as off"):
        lamp.record_warmup(0.3, 3.0, at())
    lamp.switch_on(at())
    entry = lamp.record_warmup(0.31, 3.0, at(minutes=21))
    assert entry == {"at": "2026-01-05T09:21:00+00:00", "drift_percent": 0.31, "minutes": 3.0, "warmed_up_s": 1260.0}
    assert Lamp(lamp.state_file).warmups == [entry]
    for drift, minutes in ((float("nan"), 3.0), (0.3, 0.0), (0.3, -1.0), (0.3, float("inf"))):
        with pytest.raises(ValueError):
            lamp.record_warmup(drift, minutes, at(minutes=22))
    for k in range(MAX_WARMUPS + 5):
        lamp.record_warmup(0.2, 3.0, at(minutes=30 + k))
    kept = lamp.warmups
    assert len(kept) == MAX_WARMUPS and kept[-1]["at"] == at(minutes=30 + MAX_WARMUPS + 4).isoformat()


def test_hand_written_file_with_hours_only(tmp_path):
    path = tmp_path / "lamp.json"
    path.write_text('{"hours": 812.25}')
    lamp = Lamp(path)
    assert lamp.hours(at()) == 812.25 and not lamp.is_on and lamp.ignitions == 0
    lamp.switch_on(at())
    assert lamp.hours(at(hours=1)) == pytest.approx(813.25)
    assert json.loads(path.read_text())["format"] == FORMAT


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", "is not valid JSON: Expecting value at line 1 column 1"),
        ("\xff\xfe{}", "is not UTF-8 text (byte 0)"),
        ("{hours: 1}", "is not valid JSON: Expecting property name enclosed in double quotes at line 1 column 2"),
        ("[1, 2]", "is a JSON list, expected an object"),
        ("{}", "hours is missing, expected the lamp's hours, a finite number >= 0"),
        ('{"hours": -1}', "hours is -1, expected the lamp's hours, a finite number >= 0"),
        ('{"hours": "12"}', 'hours is "12", expected the lamp\'s hours, a finite number >= 0'),
        ('{"hours": true}', "hours is true, expected the lamp's hours, a finite number"),
        ('{"hours": NaN}', "hours is NaN, expected the lamp's hours, a finite number"),
        ('{"hours": 1, "on_since": "yesterday"}', 'on_since is "yesterday", expected an ISO 8601 time with a UTC offset'),
        ('{"hours": 1, "on_since": "2026-01-05T09:00:00"}', 'on_since is "2026-01-05T09:00:00", expected an ISO 8601 time with a UTC offset'),
        ('{"format": "hw.lamp/9", "hours": 1}', 'format is "hw.lamp/9", expected "hw.lamp/1"'),
        ('{"hours": 1, "hour": 2}', "hour is not a known key, expected one of ['format', 'hours', 'ignitions', 'on_since', 'warmups']"),
        ('{"hours": 1, "ignitions": -2}', "ignitions is -2, expected an integer >= 0"),
        ('{"hours": 1, "warmups": {}}', "warmups is {}, expected a list of warm-up checks"),
        ('{"hours": 1, "warmups": [{"at": "x"}]}', 'warmups[0].at is "x", expected an ISO 8601 time with a UTC offset'),
        ('{"hours": 1, "warmups": [{"at": "2026-01-05T09:00:00+00:00"}]}',
         "warmups[0].drift_percent is missing, expected a finite number"),
        ('{"hours": 1, "warmups": ["x"]}', 'warmups[0] is "x", expected a warm-up check: an object with at, drift_percent'),
        ('{"hours": 1, "warmups": [{"at": "2026-01-05T09:00:00+00:00", "drift_percent": 0.2, "minutes": 1, "warmed_up_s": 1, "k": 1}]}',
         "warmups[0].k is not a known key, expected one of ['at', 'drift_percent', 'minutes', 'warmed_up_s']"),
        ('{"hours": 1, "ignitions": 1.0}', "ignitions is 1.0, expected an integer >= 0"),
        ('{"hours": 1, "warmups": [{"at": "2026-01-05T09:00:00+00:00", "drift_percent": 0.2, "minutes": 0, "warmed_up_s": 1}]}',
         "warmups[0].minutes is 0, expected a finite number of minutes > 0"),
    ],
)
def test_malformed_state_file(tmp_path, text, expected):
    path = tmp_path / "lamp.json"
    path.write_bytes(text.encode("latin-1"))
    lamp = Lamp(path)
    for action in (lambda: lamp.is_on, lambda: lamp.hours(at()), lambda: lamp.switch_on(at())):
        with pytest.raises(LampStateError) as error:
            action()
        message = str(error.value)
        assert isinstance(error.value, ValueError)
        assert "\n" not in message and message.startswith(f"{path}: lamp state ") and expected in message
    assert path.read_bytes() == text.encode("latin-1")  # never overwritten


@pytest.mark.parametrize(
    "data, expected",
    [
        (b"[" * 100_000 + b"]" * 100_000, "is not valid JSON: nested deeper than the JSON parser can follow"),
        (b'{"hours": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "is not valid JSON: nested deeper"),
        (b'{"hours": ' + b"9" * 5000 + b"}", "is not valid JSON: Exceeds the limit (4300 digits)"),
        (b'{"hours": 1, "x": "caf\xe9"}', "is not UTF-8 text (byte 22)"),
        ("\ufeff{}".encode("utf-16"), "is not UTF-8 text (byte 0)"),  # json.loads would guess UTF-16
    ],
    ids=["nested-100000-deep", "nested-inside-hours", "integer-5000-digits", "latin-1", "utf-16"],
)
def test_damaged_state_file_is_one_line_not_a_crash(tmp_path, data, expected):
    """A state file spherejax wrote, then damaged: the same one-line LampStateError as any
    malformed file, never RecursionError (the parser is spherejax.jsontext's, as for every file)."""
    path = tmp_path / "lamp.json"
    path.write_bytes(data)
    for action in (lambda: Lamp(path).is_on, lambda: Lamp(path).switch_on(at())):
        with pytest.raises(LampStateError) as error:
            action()
        message = str(error.value)
        assert message == f"{path}: lamp state {expected}{message.split(expected, 1)[1]}", message
        assert "\n" not in message and message.endswith('expected a JSON object with "hours"'), message
    assert path.read_bytes() == data  # never overwritten


def test_atomic_write_leaves_no_temporary_files(tmp_path, monkeypatch):
    path = tmp_path / "lamp.json"
    lamp = Lamp(path)
    lamp.switch_on(at())
    lamp.record_warmup(0.4, 3.0, at(minutes=15))
    lamp.switch_off(at(hours=4))
    assert [p.name for p in tmp_path.iterdir()] == ["lamp.json"]
    before = path.read_text()

    def failing_replace(source, destination):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        lamp.switch_on(at(days=1))
    assert [p.name for p in tmp_path.iterdir()] == ["lamp.json"]
    assert path.read_text() == before
    monkeypatch.undo()
    assert not Lamp(path).is_on and Lamp(path).hours(at(days=2)) == pytest.approx(4.0)
