"""`spherejax.io.cgats`: CGATS.17 text that every reader in use takes (the measurement's file is
read back with colour-science in tests/test_measure_cli.py)."""

import pytest

from spherejax.io.cgats import cgats_text


def test_cgats_text_refuses_what_no_reader_would_take():
    with pytest.raises(ValueError, match="finite"):
        cgats_text({}, ["A"], [[float("nan")]])
    with pytest.raises(ValueError, match="2 values for 1 fields"):
        cgats_text({}, ["A"], [[1, 2]])
    with pytest.raises(ValueError, match="letters, digits"):
        cgats_text({"MY KEY": 1}, ["A"], [])
    text = cgats_text({"ORIGINATOR": "x"}, ["SAMPLE_NAME"], [["12"], ["a'b"], ['say "hi"'], ["nan"], ["ok"]])
    data = text.split("BEGIN_DATA\n")[1].splitlines()[:-1]
    assert data == ['"12"', '"a\'b"', '"say ""hi"""', '"nan"', "ok"]  # nothing a reader would take for a number


def test_keywords_fields_and_counts():
    text = cgats_text({"ORIGINATOR": "me", "MY_KEY": 3}, ["SAMPLE_ID", "LAB_L"], [[1, 50.5], [2, 0.1]])
    assert text.splitlines() == [
        "CGATS.17", 'ORIGINATOR\t"me"', 'KEYWORD\t"MY_KEY"', 'MY_KEY\t"3"', "NUMBER_OF_FIELDS\t2",
        "BEGIN_DATA_FORMAT", "SAMPLE_ID\tLAB_L", "END_DATA_FORMAT", "NUMBER_OF_SETS\t2", "BEGIN_DATA",
        "1\t50.5", "2\t0.1", "END_DATA",
    ]


def test_a_keyword_value_stays_on_its_line_and_text_fields_are_printable():
    text = cgats_text({"DESCRIPTOR": 'regions of a\nb"c.tif'}, ["SAMPLE_NAME"], [["x"]])
    assert text.splitlines()[1] == 'DESCRIPTOR\t"regions of a b""c.tif"'
    with pytest.raises(ValueError, match="printable"):
        cgats_text({}, ["SAMPLE_NAME"], [["a\nb"]])
