"""Figures like the paper's Figures 5 and 6, as matplotlib Figure objects (the command line
saves them; nothing here touches the filesystem).

- Figure 5: responses of the test patches across the test backgrounds at one band (440 nm in the
  paper), one panel per stage: original, Stage I, Stage II. Flat curves mean consistency.
- Figure 6: reflectance curves of one test patch (a brown one in the paper) on every test
  background, one panel per stage, with the patch's known reflectance as a thick red curve.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # figures are written to files; no display is assumed

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .evaluate import STAGE_LABELS, Evaluation  # noqa: E402
from .grid import WAVELENGTHS_NM  # noqa: E402

_PANELS = ("original", "stage1", "stage2")


def _short(name: str) -> str:
    return name.split(" / ")[-1]


def figure_5(evaluation: Evaluation, set_name: str = "test", band_nm: int = 440):
    """Responses of each patch across backgrounds at `band_nm`, three panels."""
    data = evaluation.sets[set_name]
    band = evaluation.band_centres_nm.index(band_nm)
    figure, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True, constrained_layout=True)
    x = np.arange(1, len(data.backgrounds) + 1)
    for axis, stage, letter in zip(axes, _PANELS, "abc"):
        for i, patch in enumerate(data.patches):
            axis.plot(x, data.responses[stage][i, :, band], marker="o", label=_short(patch))
        axis.set_title(f"({letter}) {STAGE_LABELS[stage]}")
        axis.set_xlabel("background")
        axis.set_xticks(x)
        axis.grid(alpha=0.3)
    axes[0].set_ylabel(f"camera response at {band_nm} nm")
    axes[-1].legend(fontsize="small", loc="best")
    figure.suptitle(f"Responses of {set_name} patches across backgrounds at {band_nm} nm (cf. Zou et al. Fig. 5)")
    return figure


def figure_6(evaluation: Evaluation, set_name: str = "test", patch: str | None = None):
    """Reflectance of one patch on every background, three panels, truth in thick red.

    `patch` defaults to the first patch whose name mentions "skin" (the ColorChecker's brown
    "dark skin", like the paper's brown patch), else the first patch.
    """
    data = evaluation.sets[set_name]
    if patch is None:
        patch = next((p for p in data.patches if "skin" in p), data.patches[0])
    i = data.patches.index(patch)
    figure, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True, constrained_layout=True)
    for axis, stage, letter in zip(axes, _PANELS, "abc"):
        for j, background in enumerate(data.backgrounds):
            axis.plot(WAVELENGTHS_NM, data.reflectance[stage][i, j], lw=1, label=_short(background)[:28])
        if np.all(np.isfinite(data.truth[i])):
            axis.plot(WAVELENGTHS_NM, data.truth[i], color="red", lw=3, label="known reflectance")
        axis.set_title(f"({letter}) {STAGE_LABELS[stage]}")
        axis.set_xlabel("wavelength (nm)")
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("reflectance")
    axes[-1].legend(fontsize="x-small", loc="best")
    figure.suptitle(f"{_short(patch)} on the {set_name} backgrounds (cf. Zou et al. Fig. 6)")
    return figure


__all__ = ["figure_5", "figure_6"]
