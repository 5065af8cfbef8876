"""Fixtures shared with the rest of the suite, made available to the robustness tests (and
`workspace`, a small simulated session and its calibration, from tests/conftest.py)."""

from tests.test_archive import cal  # noqa: F401  (a calibration file for 40 x 48 x 16 cubes)
