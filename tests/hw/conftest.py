"""Shared by the hw tests: the no-leak check for emulated ports."""

from __future__ import annotations

import pytest

from .support import pty_resources


@pytest.fixture
def no_leaks():
    """Fail if a test leaves pty fds or server threads behind (faults included)."""
    fds, threads = pty_resources()
    yield
    assert pty_resources() == (fds, threads)
