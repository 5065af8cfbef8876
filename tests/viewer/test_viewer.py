"""The napari plugin off screen, with pytest-qt: the reader's layers (opened as napari opens
them, `plugin="spherejax"`), `spherejax.viewer.readout` against `open_corrected` and
`correct(..., noise=)`, regions against `spherejax.measure` and their export, and `spherejax view
--screenshot`'s PNG: the preview drawn in the canvas, the spectrum in the plot."""

import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

import spherejax as sj
from spherejax import measurement_files
from spherejax.io import corrected as corrected_module
from spherejax.io.quality_png import PALETTE

from ..helpers import corrected_oracle, listing, run_cli

PIXELS = [(20, 31), (40, 50), (61, 83), (0, 0)]


@pytest.fixture
def viewer(qtbot, corrected_workspace):
    """A viewer with the output, its calibration and raw cube, and the readout docked."""
    from spherejax.viewer import open_viewer

    files = corrected_workspace
    v = open_viewer(files["output"], calibration=files["calibration"], raw=files["raw"], show=False)
    yield v
    v.layers.clear()
    v.close()


@pytest.fixture(scope="module")
def expected(corrected_workspace):
    return {**corrected_oracle(corrected_workspace), "dataset": sj.open_corrected(corrected_workspace["output"])}


def test_the_reader_opens_an_output_as_napari_opens_it(qtbot, corrected_workspace, monkeypatch):
    """`viewer.open(path, plugin="spherejax")`: the three layers, the reflectance read lazily."""
    import napari

    calls = []
    real = corrected_module._read_rows
    monkeypatch.setattr(corrected_module, "_read_rows", lambda *a: calls.append(a) or real(*a))
    v = napari.Viewer(show=False)
    try:
        v.open(str(corrected_workspace["output"]), plugin="spherejax")
        stem = corrected_workspace["raw"].stem
        assert [layer.name for layer in v.layers] == [f"{stem} reflectance", f"{stem} preview", f"{stem} quality"]
        reflectance, preview, quality = v.layers
        assert not reflectance.visible and type(reflectance.data).__module__.startswith("dask")
        assert calls == []  # opened, and nothing of the cube read
        ds = sj.open_corrected(corrected_workspace["output"])
        assert reflectance.data.shape == (31, *ds["quality"].shape)
        assert preview.rgb and preview.data.dtype == np.uint8
        np.testing.assert_array_equal(quality.data, ds["quality"].values)
        assert quality._type_string == "labels"
        # The palette's colours, good pixels transparent, each value's bits named.
        np.testing.assert_allclose(quality.colormap.map(np.array([1]))[0][:3], PALETTE[1] / 255, atol=1e-6)
        np.testing.assert_allclose(quality.colormap.map(np.array([32]))[0][:3], PALETTE[32] / 255, atol=1e-6)
        assert quality.colormap.map(np.array([0]))[0][3] == 0
        flags = dict(zip(quality.features["index"], quality.features["flags"]))
        assert flags[0] == "good" and flags[17] == "SATURATED | BELOW_DARK" and flags[32] == "NOT_COVERED"
        # A band shown reads its rows then.
        np.testing.assert_array_equal(np.asarray(reflectance.data[7]), ds["reflectance"].values[..., 7])
        assert calls
    finally:
        v.layers.clear()
        v.close()


def test_the_reader_declines_what_is_not_an_output(tmp_path):
    from spherejax.viewer.layers import napari_get_reader

    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    assert napari_get_reader(str(tmp_path / "photo.png")) is None
    assert napari_get_reader(str(tmp_path)) is None


@pytest.mark.parametrize("rc", PIXELS)
def test_readout_is_what_open_corrected_holds(viewer, expected, rc):
    from spherejax.viewer import readout

    ds, result = expected["dataset"], expected["result"]
    r = readout(viewer, rc)
    np.testing.assert_array_equal(r["reflectance"], ds["reflectance"].values[rc])
    np.testing.assert_array_equal(r["lab"], ds["lab"].values[rc])
    assert r["quality"] == int(ds["quality"].values[rc])
    if r["quality"] == 0:
        np.testing.assert_allclose(r["u_lab"], np.asarray(result.lab_u)[rc], rtol=2e-3, atol=1e-5)
    else:
        assert "u_lab" not in r
    # The widget shows the same pixel: its plot holds the spectrum.
    from spherejax.viewer.widget import widget_of

    widget = widget_of(viewer)
    line = widget.axes.lines[0]
    np.testing.assert_array_equal(line.get_ydata(), r["reflectance"])
    assert widget.title.text() == f"pixel (row {rc[0]}, col {rc[1]})"


def test_readout_under_another_illuminant_and_a_click(viewer, expected, qtbot):
    from spherejax.viewer import readout
    from spherejax.viewer.widget import widget_of

    r = readout(viewer, (40, 50), illuminant="A")
    lab_a = np.asarray(sj.reflectance_to_lab(np.asarray(r["reflectance"], np.float32), "A"))
    np.testing.assert_allclose(r["lab"], lab_a, atol=1e-4)
    widget = widget_of(viewer)
    assert widget.illuminant.currentText() == "A"
    # A click in pan-zoom mode (press, release) reads the pixel under it out; a drag (press,
    # move, release: a pan) does not.
    widget.illuminant.setCurrentText("D65")
    for moves, shown in [(0, (40, 50)), (2, (40, 50)), (0, (12, 61))]:
        position = (7, shown[0] + 0.4, shown[1] - 0.3) if moves == 0 else (7, 3.0, 3.0)
        event = type("Event", (), {"type": "mouse_press", "position": position})()
        drag = widget._clicked(viewer, event)
        next(drag)
        for _ in range(moves):
            event.type = "mouse_move"
            next(drag)
        event.type = "mouse_release"
        with pytest.raises(StopIteration):
            next(drag)
        assert (widget.current["row"], widget.current["col"]) == shown
        np.testing.assert_array_equal(widget.current["lab"], expected["dataset"]["lab"].values[shown])


def test_a_rectangle_and_a_polygon_are_measured_as_measure_does(viewer, expected, tmp_path):
    from matplotlib.path import Path

    from spherejax.viewer.widget import widget_of

    widget = widget_of(viewer)
    widget.reference_text.setText("60,5,5")
    widget._typed_reference()
    regions = widget.regions_layer
    regions.add_rectangles(np.array([[10, 20], [30, 60]], float))
    rect = widget.regions[-1]
    mask = np.zeros(expected["dataset"]["quality"].shape, bool)
    mask[10:31, 20:61] = True
    want = sj.measure(expected["raw"], expected["calibration"], mask, expected["noise"])
    np.testing.assert_allclose(rect.measurement.reflectance, want.reflectance, rtol=1e-6)
    np.testing.assert_allclose(rect.measurement.lab_covariance, want.lab_covariance, rtol=1e-5)
    assert rect.measurement.pixels == want.pixels == mask.sum() and rect.rect == (10, 31, 20, 61)
    delta_e, u = want.delta_e([60, 5, 5])
    assert rect.delta_e == pytest.approx(delta_e, abs=1e-6) and rect.delta_e_u == pytest.approx(u, rel=1e-5)
    assert f"{want.pixels} pixels" in widget.region_text.text()

    vertices = np.array([[40, 40], [70, 45], [60, 90], [45, 80]], float)
    regions.add_polygons([vertices])
    polygon = widget.regions[-1]
    rows, cols = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
    inside = Path(vertices).contains_points(np.column_stack([rows.ravel(), cols.ravel()])).reshape(mask.shape)
    napari_mask = np.asarray(regions.to_masks(mask_shape=mask.shape)[-1], bool)
    assert abs(int(napari_mask.sum()) - int(inside.sum())) <= 0.05 * inside.sum()  # edge pixels aside
    want = sj.measure(expected["raw"], expected["calibration"], napari_mask, expected["noise"])
    np.testing.assert_allclose(polygon.measurement.lab, want.lab, atol=1e-9)
    assert [r.name for r in widget.regions] == ["region 1", "region 2"]

    written = widget.export(csv_path=tmp_path / "regions.csv", cgats_path=tmp_path / "regions.txt")
    assert listing(tmp_path) == ["regions.csv", "regions.txt"] and len(written) == 2
    assert (tmp_path / "regions.csv").read_text() == measurement_files.csv_text(widget.regions)
    cgats = (tmp_path / "regions.txt").read_text()
    assert cgats.startswith("CGATS.17") and cgats.count("\n2\t") == 1  # two samples


def _screenshot_checks(png: pathlib.Path):
    """The PNG: spherejax's mark; the canvas showing the preview's colours; the plot's line."""
    from PIL import Image

    from spherejax.viewer.outputs import SCREENSHOT_SOFTWARE

    with Image.open(png) as image:
        assert image.text["Software"] == SCREENSHOT_SOFTWARE
        pixels = np.asarray(image.convert("RGB"))
    assert pixels.shape[0] > 500 and pixels.shape[1] > 1000 and pixels.std() > 10
    colours = {tuple(c) for c in pixels.reshape(-1, 3)[:: 7]}
    assert (31, 119, 180) in colours  # matplotlib's tab:blue: the spectrum's line is drawn
    return pixels


def test_screenshot_from_the_command_line(corrected_workspace, expected, tmp_path, capsys, qtbot):
    """In this process, with -c and --raw: the readout at --pixel, the file written, spherejax's."""
    files = corrected_workspace
    png = tmp_path / "view.png"
    status, out, err = run_cli(["view", str(files["output"]), "-c", str(files["calibration"]), "--raw", str(files["raw"]),
                                "--screenshot", str(png), "--pixel", "40,50"], capsys)
    assert status == 0, err
    assert out.strip() == f"written: {png}"
    pixels = _screenshot_checks(png)
    # The canvas shows the preview: its most common colours are in the window.
    preview = corrected_module.read_preview(files["output"].with_name(files["raw"].stem + ".preview.png"),
                                        expected["dataset"]["quality"].shape)
    values, counts = np.unique(preview.reshape(-1, 3), axis=0, return_counts=True)
    common = {tuple(int(x) for x in v) for v in values[np.argsort(counts)[-3:]]}
    window = {tuple(int(x) for x in c) for c in pixels.reshape(-1, 3)}
    assert len(common & window) >= 2, (common, len(window))
    # Run again: the screenshot spherejax wrote is replaced.
    status, _, err = run_cli(["view", str(files["output"]), "--screenshot", str(png), "--pixel", "5,6"], capsys)
    assert status == 0, err
    assert listing(tmp_path) == ["view.png"]
    status, _, err = run_cli(["view", str(files["output"]), "--screenshot", str(tmp_path / "b.png"), "--pixel", "9999,3"],
                             capsys)
    assert status == 2 and "--pixel '9999,3'" in err and "outside" in err and len(err.strip().splitlines()) == 1
    assert listing(tmp_path) == ["view.png"]


@pytest.mark.slow
def test_screenshot_needs_no_display(corrected_workspace, tmp_path):
    """A fresh process with no $DISPLAY: the command starts its own X server, writes the PNG,
    exits 0, and leaves no server or lock file behind."""
    files = corrected_workspace
    png = tmp_path / "fresh.png"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "QT_QPA_PLATFORM", "QT_API")}
    before = set(pathlib.Path("/tmp").glob(".X*-lock"))
    done = subprocess.run([sys.executable, "-m", "spherejax", "view", str(files["output"]), "--screenshot", str(png),
                           "--pixel", "40,50"], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert png.is_file()
    # Its Xvfb, told to stop by the kernel as the command ended, removes its lock file itself.
    import time

    deadline = time.monotonic() + 20
    while not set(pathlib.Path("/tmp").glob(".X*-lock")) <= before and time.monotonic() < deadline:
        time.sleep(0.2)
    assert set(pathlib.Path("/tmp").glob(".X*-lock")) <= before


def test_an_envi_output_and_an_out_folder_open(qtbot, corrected_workspace, expected, tmp_path):
    """The reader takes the ENVI outputs and a whole OUT folder (each output set's layers)."""
    import napari

    from spherejax import cli
    from spherejax.viewer import readout

    raws = sorted(corrected_workspace["raw"].parent.glob("test-*.tif"))[:2]
    out = tmp_path / "out"
    assert cli.main(["-q", "correct", "-c", str(corrected_workspace["calibration"]), *map(str, raws), "-o", str(out),
                     "--format", "envi"]) == 0
    v = napari.Viewer(show=False)
    try:
        v.open(str(out / f"{raws[0].stem}.reflectance.hdr"), plugin="spherejax")
        assert [layer.name for layer in v.layers][0] == f"{raws[0].stem} reflectance"
        r = readout(v, (40, 50), uncertainty=False)
        np.testing.assert_array_equal(r["reflectance"], expected["dataset"]["reflectance"].values[40, 50])
        v.layers.clear()
        v.open(str(out), plugin="spherejax")
        assert sorted(layer.name for layer in v.layers if layer.name.endswith("quality")) == \
            [f"{raw.stem} quality" for raw in raws]
    finally:
        v.layers.clear()
        v.close()


def test_the_readout_docks_from_naparis_plugin_menu(qtbot, corrected_workspace, expected):
    """The manifest's widget, as napari's Plugins menu docks it, is the one `readout` drives."""
    import napari

    from spherejax.viewer import readout
    from spherejax.viewer.widget import ReadoutWidget, widget_of

    v = napari.Viewer(show=False)
    try:
        v.open(str(corrected_workspace["output"]), plugin="spherejax")
        _, widget = v.window.add_plugin_dock_widget("spherejax", "spherejax readout")
        assert isinstance(widget, ReadoutWidget) and widget_of(v) is widget
        r = readout(v, (61, 83))
        np.testing.assert_array_equal(widget.axes.lines[0].get_ydata(), r["reflectance"])
        np.testing.assert_array_equal(r["lab"], expected["dataset"]["lab"].values[61, 83])
    finally:
        v.layers.clear()
        v.close()


@pytest.mark.slow
@pytest.mark.parametrize("signum, status", [(2, 130), (15, 143)])
def test_a_window_stops_on_a_signal(corrected_workspace, signum, status):
    """`spherejax view PATH` in a window (here Qt's offscreen platform on this session's X
    server): SIGINT or SIGTERM while Qt's loop runs ends the command with 128 + the signal and
    one line, as every command does."""
    import signal
    import time

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    assert env.get("DISPLAY") and env.get("QT_QPA_PLATFORM") == "offscreen"  # tests/viewer/conftest.py
    process = subprocess.Popen([sys.executable, "-m", "spherejax", "-v", "view", str(corrected_workspace["output"])],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        seen = ""
        while "the window is open" not in seen:
            assert time.monotonic() < deadline and process.poll() is None, seen
            seen += process.stderr.readline()
        time.sleep(0.5)
        process.send_signal(signum)
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == status, err
    ours = [line for line in err.splitlines() if line.startswith("spherejax: ")]
    assert ours == ["spherejax: interrupted; nothing half-written was left"] and "Traceback" not in err, err


def test_a_path_that_holds_no_output_is_refused(tmp_path, capsys):
    """A folder with no output of correct in it, or a file that is not one: one line, exit 2,
    nothing written."""
    (tmp_path / "notes.txt").write_text("not an image\n")
    for path in (tmp_path, tmp_path / "notes.txt"):
        status, _, err = run_cli(["view", str(path), "--screenshot", str(tmp_path / "s.png")], capsys)
        assert status == 2 and len(err.strip().splitlines()) == 1, err
        assert f"{path}: holds no output of spherejax correct" in err and "Traceback" not in err
    assert listing(tmp_path) == ["notes.txt"]


def test_a_window_without_the_xcb_libraries_is_refused(corrected_workspace, capsys, monkeypatch):
    """Qt's X11 platform plugin that cannot load (a machine without a desktop's xcb libraries)
    is said in one line, before Qt would abort the process."""
    import ctypes

    from spherejax.cli import view_command

    monkeypatch.delenv("QT_QPA_PLATFORM", raising=False)
    monkeypatch.setenv("DISPLAY", os.environ.get("DISPLAY") or ":0")
    real = ctypes.CDLL

    def cdll(name, *args, **kwargs):
        if str(name).endswith("libqxcb.so"):
            raise OSError("libxcb-icccm.so.4: cannot open shared object file: No such file or directory")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(ctypes, "CDLL", cdll)
    opened = []
    monkeypatch.setattr(view_command, "_run_until_closed_or_stopped", lambda: opened.append(True))
    status, _, err = run_cli(["view", str(corrected_workspace["output"])], capsys)
    assert status == 2 and len(err.strip().splitlines()) == 1, err
    assert "Qt's X11 platform cannot load: libxcb-icccm.so.4 is missing" in err and "apt-get install" in err
    assert opened == []
