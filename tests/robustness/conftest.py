"""Fixtures shared with the rest of the suite, made available to the robustness tests."""

from tests.test_archive import cal  # noqa: F401  (a calibration file for 40 x 48 x 16 cubes)
from tests.test_cli import workspace  # noqa: F401  (a small simulated session and its calibration)
