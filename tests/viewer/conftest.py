"""The viewer's Qt tests: skipped, with the reason, where the viewer extra (napari, PyQt5) or an
X server for OpenGL (a display, or Xvfb) is missing; the README's test command and .ci/run
install both, so there they run. Qt runs off screen (QT_QPA_PLATFORM=offscreen) with
`spherejax.viewer.offscreen`'s own Xvfb where $DISPLAY is unset, as `spherejax view
--screenshot` does; this runs before pytest-qt makes the QApplication."""

import importlib.util

import pytest


def pytest_collection_modifyitems(config, items):
    # Before any QApplication exists: the platform and the binding are chosen when Qt loads.
    if importlib.util.find_spec("napari") is None:
        return
    from spherejax.viewer.offscreen import NoDisplay, use_offscreen

    try:
        use_offscreen()
    except NoDisplay as error:
        config._spherejax_no_display = str(error)


@pytest.fixture(autouse=True)
def _viewer_extra(request):
    if importlib.util.find_spec("napari") is None or importlib.util.find_spec("PyQt5") is None:
        pytest.skip("the viewer's tests need the viewer extra (napari, PyQt5): pip install -e '.[viewer]'")
    reason = getattr(request.config, "_spherejax_no_display", None)
    if reason is not None:
        pytest.skip(reason)
