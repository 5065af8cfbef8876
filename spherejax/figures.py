"""Figures like the paper's Figures 5 and 6, as matplotlib Figure objects (the command line
saves them; nothing here touches the filesystem).

- Figure 5: responses of the test patches across the test backgrounds at one band (440 nm in the
  paper), one panel per stage: original, Stage I, Stage II. Flat curves mean consistency.
- Figure 6: reflectance curves of one test patch (a brown one in the paper) on every test
  background, one panel per stage, with the patch's known reflectance as a thick red curve.

Made to be read where curves coincide (after correction they should): each series has its own
combination of colour, line style and marker (`series_styles`), markers are hollow so that one
drawn over another still shows, Figure 5 sets each patch's markers a little to the side of the
background's tick (its values are untouched; the x axis only names the background) and Figure 6
puts each background's markers on other wavelengths than its neighbours'. One legend for the
figure, below the panels, names every series in full (a label is shortened only past
`LABEL_LIMIT` characters, at a word, with an ellipsis); the constrained layout keeps it and every
other text inside the canvas, so a plain `savefig` shows everything.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # figures are written to files; no display is assumed

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .evaluate import STAGE_LABELS, Evaluation  # noqa: E402
from .grid import WAVELENGTHS_NM  # noqa: E402

_PANELS = ("original", "stage1", "stage2")

#: The series' colours: the tab10 palette without its red, which is the known reflectance's.
COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:gray",
           "tab:olive", "tab:cyan")
LINESTYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "h")
#: Colour of the known reflectance in Figure 6 (thick, as in the paper).
TRUTH_COLOUR = "red"
#: Labels longer than this many characters are shortened (`legend_label`).
LABEL_LIMIT = 80
_BASE_SIZE = (13.0, 4.0)  # inches, the three panels without the legend


def series_styles(count: int) -> list[dict]:
    """Line properties of `count` series: series i takes colour i mod 9, line style i mod 4 and
    marker i mod 10. 9, 4 and 10 have 180 as their least common multiple, so no two of the first
    180 series share all three (by the Chinese remainder theorem); neighbours differ in each."""
    return [
        {"color": COLOURS[i % len(COLOURS)], "linestyle": LINESTYLES[i % len(LINESTYLES)],
         "marker": MARKERS[i % len(MARKERS)]}
        for i in range(count)
    ]


def legend_label(name: str, limit: int = LABEL_LIMIT) -> str:
    """`name` in full, or shortened to at most `limit` characters at the end of a word, with an
    ellipsis ("…"); a single word longer than that is cut, with the ellipsis too."""
    name = " ".join(name.split())
    if len(name) <= limit:
        return name
    head = name[: limit - 1]
    if name[limit - 1] != " " and " " in head:
        head = head[: head.rindex(" ")]
    return head.rstrip() + "…"


def _labels(names: list[str]) -> list[str]:
    """The names after their last " / " (the data set each came from) where no two are then
    alike, else the whole names; each through `legend_label`."""
    short = [name.split(" / ")[-1] for name in names]
    return [legend_label(name) for name in (short if len(set(short)) == len(short) else names)]


def _panels():
    return plt.subplots(1, 3, figsize=_BASE_SIZE, sharey=True, layout="constrained")


def _figure_legend(figure, axis, title: str):
    """One legend for the figure, below the panels, of `axis`'s series: as many columns as fit
    the figure's width, and the figure made taller by the legend's height so the panels keep
    their size. The constrained layout then keeps it clear of the axes and inside the canvas."""
    handles, labels = axis.get_legend_handles_labels()
    if not labels:  # nothing measured: nothing to name
        return None
    for ncols in range(min(len(labels), 6), 0, -1):
        legend = figure.legend(handles, labels, loc="outside lower center", ncols=ncols, fontsize="small",
                               title=title, title_fontsize="small", handlelength=3.0, markerfirst=True)
        if ncols == 1 or legend.get_window_extent().width <= 0.97 * figure.bbox.width:
            break
        legend.remove()
    height = legend.get_window_extent().height / figure.dpi
    figure.set_size_inches(_BASE_SIZE[0], _BASE_SIZE[1] + height + 0.1)
    return legend


def _style_axis(axis, stage: str, letter: str, xlabel: str) -> None:
    axis.set_title(f"({letter}) {STAGE_LABELS[stage]}")
    axis.set_xlabel(xlabel)
    axis.grid(alpha=0.3)


def figure_5(evaluation: Evaluation, set_name: str = "test", band_nm: int = 440):
    """Responses of each patch across backgrounds at `band_nm`, three panels, one legend below.

    Each patch's markers sit slightly to one side of the background's tick (side by side, in
    patch order), so that patches of equal response stay distinguishable. Patches measured on
    no background are left out."""
    data = evaluation.sets[set_name]
    band = evaluation.band_centres_nm.index(band_nm)
    figure, axes = _panels()
    x = np.arange(1, len(data.backgrounds) + 1)
    shown = [i for i in range(len(data.patches))
             if any(np.any(np.isfinite(data.responses[stage][i, :, band])) for stage in _PANELS)]
    labels = _labels([data.patches[i] for i in shown])
    step = min(0.06, 0.5 / max(len(shown), 1))
    for axis, stage, letter in zip(axes, _PANELS, "abc"):
        for k, (i, style) in enumerate(zip(shown, series_styles(len(shown)))):
            offset = (k - (len(shown) - 1) / 2) * step
            axis.plot(x + offset, data.responses[stage][i, :, band], label=labels[k], lw=1.3, alpha=0.9,
                      markersize=6, markerfacecolor="none", markeredgewidth=1.3, **style)
        _style_axis(axis, stage, letter, "background")
        axis.set_xticks(x)
    axes[0].set_ylabel(f"camera response at {band_nm} nm")
    figure.suptitle(f"Responses of {set_name} patches across backgrounds at {band_nm} nm (cf. Zou et al. Fig. 5)")
    _figure_legend(figure, axes[0], "patch")
    return figure


def figure_6(evaluation: Evaluation, set_name: str = "test", patch: str | None = None):
    """Reflectance of one patch on every background, three panels, truth in thick red, one legend
    below.

    `patch` defaults to the first patch whose name mentions "skin" (the ColorChecker's brown
    "dark skin", like the paper's brown patch), else the first patch. Backgrounds the patch was
    not measured on are left out. The known reflectance is drawn under the measured curves, which
    would otherwise hide where they agree with it.
    """
    data = evaluation.sets[set_name]
    if patch is None:
        patch = next((p for p in data.patches if "skin" in p), data.patches[0])
    i = data.patches.index(patch)
    figure, axes = _panels()
    shown = [j for j in range(len(data.backgrounds))
             if any(np.any(np.isfinite(data.reflectance[stage][i, j])) for stage in _PANELS)]
    labels = _labels([data.backgrounds[j] for j in shown])
    truth = np.all(np.isfinite(data.truth[i]))
    for axis, stage, letter in zip(axes, _PANELS, "abc"):
        if truth:
            axis.plot(WAVELENGTHS_NM, data.truth[i], color=TRUTH_COLOUR, lw=3.5, alpha=0.6, zorder=1.5,
                      label="known reflectance")
        for k, (j, style) in enumerate(zip(shown, series_styles(len(shown)))):
            axis.plot(WAVELENGTHS_NM, data.reflectance[stage][i, j], label=labels[k], lw=1.2, alpha=0.9,
                      markevery=(k % 3, 3), markersize=5, markerfacecolor="none", markeredgewidth=1.1,
                      zorder=2, **style)
        _style_axis(axis, stage, letter, "wavelength (nm)")
    axes[0].set_ylabel("reflectance")
    figure.suptitle(f"{legend_label(patch.split(' / ')[-1])} on the {set_name} backgrounds (cf. Zou et al. Fig. 6)")
    _figure_legend(figure, axes[0], "background")
    return figure


__all__ = ["COLOURS", "LABEL_LIMIT", "LINESTYLES", "MARKERS", "TRUTH_COLOUR", "figure_5", "figure_6", "legend_label",
           "series_styles"]
