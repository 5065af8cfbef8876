"""The viewer's Qt tests: skipped, with the reason, where the viewer's test extra (napari, PyQt5,
pytest-qt: `pip install -e ".[viewer-test]"`) or an X server for OpenGL (a display, or Xvfb) is
missing; the README's test command and .ci/run install them, so there they run. Qt runs off
screen (QT_QPA_PLATFORM=offscreen) with `spherejax.viewer.offscreen`'s own Xvfb where $DISPLAY is
unset, as `spherejax view --screenshot` does; this runs at collection, before pytest-qt makes the
QApplication."""

import importlib.util
import pathlib

import pytest

HERE = pathlib.Path(__file__).parent
#: What the tests here import, and the extra that brings it.
NEEDED = {"napari": "napari", "PyQt5": "PyQt5", "pytestqt": "pytest-qt"}


def _why_not() -> str | None:
    missing = [name for module, name in NEEDED.items() if importlib.util.find_spec(module) is None]
    if missing:
        return (f"the viewer's tests need {', '.join(missing)}: pip install -e '.[viewer-test]' "
                "(the viewer extra and pytest-qt)")
    from spherejax.viewer.offscreen import NoDisplay, use_offscreen

    try:
        use_offscreen()  # before any QApplication: the platform and the binding are chosen when Qt loads
    except NoDisplay as error:
        return str(error)
    return None


def pytest_collection_modifyitems(config, items):
    here = [item for item in items if HERE in item.path.parents]
    if not here:
        return
    reason = _why_not()
    if reason is not None:
        # A mark, not a skip in a fixture: without pytest-qt, `qtbot` itself is missing, and a
        # test asking for it would be an error before any fixture could skip it.
        for item in here:
            item.add_marker(pytest.mark.skip(reason=reason))
