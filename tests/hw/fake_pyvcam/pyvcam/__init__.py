"""Fake PyVCAM for tests (README.md beside this package): the subset hw/pvcam.py uses."""
