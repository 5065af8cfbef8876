"""spherejax.figures: Figures 5 and 6 can be read. Every series has its own (colour, line style,
marker) and a legend entry naming it in full; the one legend lies outside every panel; every text
lies inside the canvas once drawn at the command line's resolution (110 dpi, a plain savefig);
the plotted values are the evaluation's."""

import itertools

import matplotlib
import matplotlib.colors
import matplotlib.text
import numpy as np
import pytest

from spherejax import evaluate, figures, spectra
from spherejax.evaluate import STAGES, Evaluation, StageData
from spherejax.grid import WAVELENGTHS_NM

BANDS = list(range(400, 701, 20))
#: Background names as long as the simulator's, one longer than `figures.LABEL_LIMIT`.
BACKGROUNDS = [
    "pattern-TCS4 (CIE 2017)+TCS92 (CIE 2017)",
    "pattern-TCS64 (CIE 2017)+TCS60 (CIE 2017)+TCS92 (CIE 2017)",
    "pattern-TCS13 (CIE 2017)+TCS98 (CIE 2017)+VS8+TCS4 (CIE 2017)",
    "pattern-VS6+TCS21 (CIE 2017)",
    "pattern-TCS52 (CIE 2017)+TCS12 (CIE 2017)+TCS73 (CIE 2017)+VS6+TCS9 (CIE 2017)+TCS30 (CIE 2017)",
    "CES / TCS43 (CIE 2017)",
    "a background with no measurement",
]
PATCHES = ["BabelColor / cyan", "BabelColor / dark skin", "BabelColor / foliage", "BabelColor / red",
           "BabelColor / yellow green", "BabelColor / never measured"]


def an_evaluation() -> Evaluation:
    """Stage data whose "dark skin" and "foliage" coincide exactly (a curve hidden under
    another), the last background has no measurement and the last patch none either."""
    rng = np.random.default_rng(7)
    patches, backgrounds = len(PATCHES), len(BACKGROUNDS)
    truth = np.stack([np.clip(s, 0.02, 0.98) for s in spectra.all_reflectances()[::30][:patches]])
    responses = rng.uniform(0.05, 0.4, (patches, 1, 16)) + rng.normal(0, 0.005, (patches, backgrounds, 16))
    reflectance = np.clip(truth[:, None] + rng.normal(0, 0.01, (patches, backgrounds, 31)), 0.0, 1.0)
    responses[2], reflectance[2] = responses[1], reflectance[1]
    for array in (responses, reflectance):
        array[:, -1] = np.nan
        array[-1] = np.nan
    sets = {"test": StageData(PATCHES, BACKGROUNDS, {s: responses + 0.01 * k for k, s in enumerate(STAGES)},
                              {s: reflectance for s in STAGES}, truth)}
    metrics = {"test": {stage: evaluate.consistency_metrics(sets["test"], stage) for stage in STAGES}}
    return Evaluation(BANDS, [0.5] * 16, sets, metrics)


EVALUATION = an_evaluation()
SHOWN_PATCHES = ["cyan", "dark skin", "foliage", "red", "yellow green"]  # the measured ones, short
#: The measured backgrounds: each after its " / " (no two alike then), the absurd one shortened.
SHOWN_BACKGROUNDS = [figures.legend_label(name.split(" / ")[-1]) for name in BACKGROUNDS[:-1]]


@pytest.fixture(params=["figure_5", "figure_6"])
def drawn(request):
    """(name, figure) drawn as the command line saves it: dpi 110."""
    figure = getattr(figures, request.param)(EVALUATION, "test")
    figure.set_dpi(110)
    figure.canvas.draw()
    yield request.param, figure
    matplotlib.pyplot.close(figure)


def expected_labels(name: str) -> list[str]:
    if name == "figure_5":
        return SHOWN_PATCHES
    return ["known reflectance", *SHOWN_BACKGROUNDS]


def style(line) -> tuple[str, str, str]:
    return matplotlib.colors.to_hex(line.get_color()), line.get_linestyle(), str(line.get_marker())


def test_one_legend_naming_every_series_in_full(drawn):
    name, figure = drawn
    assert all(axis.get_legend() is None for axis in figure.axes)
    (legend,) = figure.legends
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels == expected_labels(name)
    # As many entries as series drawn in each panel, in the same order.
    for axis in figure.axes:
        assert [line.get_label() for line in axis.get_lines()] == labels
    # Full names where they fit (the simulator's longest, 62 characters); only the absurd one shortened.
    if name == "figure_6":
        assert BACKGROUNDS[2] in labels
        (shortened,) = [label for label in labels if label.endswith("…")]
        assert len(shortened) <= figures.LABEL_LIMIT and BACKGROUNDS[4].startswith(shortened[:-1].rstrip())


def test_every_series_has_its_own_colour_line_style_and_marker(drawn):
    name, figure = drawn
    (legend,) = figure.legends
    handles = legend.legend_handles
    assert len(handles) == len(expected_labels(name))
    styles = [style(handle) for handle in handles]
    assert len(set(styles)) == len(styles), styles
    # The legend shows each series as it is drawn; coinciding series ("dark skin" and "foliage":
    # the same values) differ in each of colour, line style and marker, and their markers are hollow.
    for axis in figure.axes:
        assert [style(line) for line in axis.get_lines()] == styles
        lines = {line.get_label(): line for line in axis.get_lines()}
        if name == "figure_5":
            a, b = style(lines["dark skin"]), style(lines["foliage"])
            assert all(x != y for x, y in zip(a, b))
            assert all(line.get_markerfacecolor() == "none" for line in lines.values())


def drawn_texts(figure) -> list[matplotlib.text.Text]:
    """Every visible, non-empty text of `figure` but the labels of ticks outside the view limits,
    which the locator makes and matplotlib does not draw."""
    hidden = set()
    for axis in figure.axes:
        for ticks, index, (low, high) in ((axis.xaxis, 0, sorted(axis.get_xlim())), (axis.yaxis, 1, sorted(axis.get_ylim()))):
            hidden |= {id(label) for label in ticks.get_ticklabels(which="both")
                       if not low - 1e-9 * (high - low) <= label.get_position()[index] <= high + 1e-9 * (high - low)}
    return [t for t in figure.findobj(matplotlib.text.Text) if t.get_visible() and t.get_text().strip() and id(t) not in hidden]


def test_every_text_lies_inside_the_canvas(drawn):
    _, figure = drawn
    canvas = figure.bbox
    texts = drawn_texts(figure)
    assert len(texts) > 20  # titles, axis labels, tick labels, legend entries and title
    # And all that is drawn, as matplotlib sees it (bbox_inches="tight" would crop to this).
    tight = figure.get_tightbbox()
    assert tight.x0 >= -0.01 and tight.y0 >= -0.01 and tight.x1 <= figure.bbox_inches.x1 + 0.01 and tight.y1 <= figure.bbox_inches.y1 + 0.01
    outside = []
    for text in texts:
        box = text.get_window_extent()
        if box.x0 < canvas.x0 - 0.5 or box.y0 < canvas.y0 - 0.5 or box.x1 > canvas.x1 + 0.5 or box.y1 > canvas.y1 + 0.5:
            outside.append((text.get_text(), box.bounds))
    assert outside == []


def test_the_legend_covers_no_panel(drawn):
    """The legend's box (frame included) meets no axes' box: it never hides data, wherever
    the data lie."""
    _, figure = drawn
    (legend,) = figure.legends
    box = legend.get_window_extent()
    for axis in figure.axes:
        panel = axis.get_window_extent()
        assert box.x1 <= panel.x0 or box.x0 >= panel.x1 or box.y1 <= panel.y0 or box.y0 >= panel.y1, (box, panel)


def test_the_checks_can_fail():
    """A legend inside a panel, cut labels and two series alike are all found."""
    figure, axis = matplotlib.pyplot.subplots(figsize=(3, 2))
    axis.plot([0, 1], [0, 1], color="tab:blue", marker="o", label="x" * 60)
    axis.plot([0, 1], [1, 0], color="tab:blue", marker="o", label="y")
    legend = axis.legend(loc="upper right")
    figure.canvas.draw()
    box, panel, canvas = legend.get_window_extent(), axis.get_window_extent(), figure.bbox
    assert not (box.x1 <= panel.x0 or box.x0 >= panel.x1 or box.y1 <= panel.y0 or box.y0 >= panel.y1)
    assert legend.get_texts()[0].get_window_extent().x0 < canvas.x0
    assert len({style(h) for h in legend.legend_handles}) == 1
    matplotlib.pyplot.close(figure)


def test_figure_5_plots_the_responses_beside_each_tick():
    figure = figures.figure_5(EVALUATION, "test", band_nm=440)
    data, band = EVALUATION.sets["test"], BANDS.index(440)
    ticks = np.arange(1, len(BACKGROUNDS) + 1)
    for axis, stage in zip(figure.axes, ("original", "stage1", "stage2")):
        offsets = []
        for line in axis.get_lines():
            i = [p.split(" / ")[-1] for p in PATCHES].index(line.get_label())
            np.testing.assert_array_equal(line.get_ydata(), data.responses[stage][i, :, band])
            offset = np.asarray(line.get_xdata()) - ticks
            assert np.ptp(offset) < 1e-12 and abs(offset[0]) < 0.26  # beside its background's tick
            offsets.append(offset[0])
        assert len(set(offsets)) == len(offsets)  # each patch to its own side
        np.testing.assert_array_equal(axis.get_xticks(), ticks)
    matplotlib.pyplot.close(figure)


def test_figure_6_draws_the_truth_thick_red_under_the_measurements():
    figure = figures.figure_6(EVALUATION, "test")
    data = EVALUATION.sets["test"]
    i = PATCHES.index("BabelColor / dark skin")  # the default: the first patch that mentions skin
    assert figure.get_suptitle().startswith("dark skin on the test backgrounds")
    for axis, stage in zip(figure.axes, ("original", "stage1", "stage2")):
        truth, *measured = axis.get_lines()
        assert truth.get_label() == "known reflectance" and matplotlib.colors.same_color(truth.get_color(), "red")
        assert truth.get_linewidth() >= 3 and truth.get_linewidth() > 2 * max(line.get_linewidth() for line in measured)
        assert all(truth.get_zorder() < line.get_zorder() for line in measured)
        assert not any(matplotlib.colors.same_color(line.get_color(), "red") or line.get_color() == "tab:red" for line in measured)
        np.testing.assert_array_equal(truth.get_ydata(), data.truth[i])
        np.testing.assert_array_equal(truth.get_xdata(), WAVELENGTHS_NM)
        for j, line in enumerate(measured):
            np.testing.assert_array_equal(line.get_ydata(), data.reflectance[stage][i, j])
    matplotlib.pyplot.close(figure)


def test_series_styles_are_distinct_for_180_series():
    styles = figures.series_styles(180)
    combos = [(s["color"], s["linestyle"], s["marker"]) for s in styles]
    assert len(set(combos)) == 180
    assert all(a != b for x, y in itertools.pairwise(combos) for a, b in zip(x, y))  # neighbours differ in each
    assert "tab:red" not in figures.COLOURS and figures.TRUTH_COLOUR == "red"


@pytest.mark.parametrize("name, limit, expected", [
    ("dark skin", 80, "dark skin"),
    ("pattern-TCS4 (CIE 2017)+TCS92 (CIE 2017)", 40, "pattern-TCS4 (CIE 2017)+TCS92 (CIE 2017)"),
    ("pattern-TCS4 (CIE 2017)+TCS92 (CIE 2017)", 30, "pattern-TCS4 (CIE 2017)+TCS92…"),
    ("pattern-TCS4 (CIE 2017)+TCS92 (CIE 2017)", 24, "pattern-TCS4 (CIE…"),  # at a word
    ("one two three", 8, "one two…"),  # a cut just before a space keeps the whole word
    ("abcdefghijklmnop", 8, "abcdefg…"),  # one word too long: cut, with the ellipsis
])
def test_legend_label(name, limit, expected):
    assert figures.legend_label(name, limit) == expected
    assert len(expected) <= limit
