"""The robustness figure and the files of ``racebench table --table robustness`` (:func:`write_robustness`: the
table, its CSV and the figure from the same result folders, in one command).

The figure, for papers: success under each perturbation per method, the nominal success as reference. One panel per
track flown; along x the nominal case, then the suite's ten perturbations; per method a colour, a dot per case with
its 95 % Wilson interval, and its nominal success rate as a dotted line across the panel, so a drop reads as the
distance below it. A downward triangle marks a change that is significant after Holm's adjustment over the whole
table (:func:`racebench.reporting.robustness.adjusted`), an upward one a significant gain; a privileged method's
markers are hollow.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from racebench.evaluation.protocol import TRACK_ORDER  # noqa: E402
from racebench.evaluation.statistics import wilson_interval  # noqa: E402
from racebench.reporting.figure_files import DEFAULT_DPI, FIGURE_FORMATS, _save  # noqa: E402
from racebench.reporting.robustness import (  # noqa: E402
    NOMINAL,
    PERTURBATIONS,
    _row_order,
    adjusted,
    csv_frame,
    make_robustness_table,
    read_robustness,
    robustness_cells,
)
from racebench.reporting.tables import TRACK_NAMES  # noqa: E402
from racebench.utils.files import atomic_write  # noqa: E402

logger = logging.getLogger("racebench")

CASES: tuple[str, ...] = (NOMINAL, *PERTURBATIONS)


def _points(mine: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Success rates [%], their Wilson bounds and markers over :data:`CASES` for one method on one track."""
    first = mine.iloc[0]
    n = int(first["pairs"])
    rows = [(int(first["nominal_successes"]), n, "o")]
    by_name = mine.set_index("perturbation")
    for name in PERTURBATIONS:
        if name not in by_name.index:
            rows.append((-1, n, ""))
            continue
        cell = by_name.loc[name]
        marker = ("v" if cell["delta_sr"] < 0 else "^") if bool(cell["significant"]) else "o"
        rows.append((int(cell["successes"]), int(cell["pairs"]), marker))
    sr = np.array([100 * k / m if k >= 0 else np.nan for k, m, _ in rows])
    bounds = np.array([wilson_interval(k, m) if k >= 0 else (np.nan, np.nan) for k, m, _ in rows]) * 100
    return sr, bounds[:, 0], bounds[:, 1], [marker for _, _, marker in rows]


def robustness_figure(cells: pd.DataFrame) -> Any:
    """The figure of :func:`plot_robustness` from :func:`racebench.reporting.robustness.robustness_cells`."""
    if cells.empty:
        raise ValueError("no robustness results to plot (racebench evaluate --envs robustness)")
    if "p_holm" not in cells:
        cells = adjusted(cells)
    tracks = [t for t in TRACK_ORDER if (cells["track"] == t).any()]
    methods = list(dict.fromkeys(method for method, _ in _row_order(cells)))
    colours = plt.get_cmap("tab10" if len(methods) <= 10 else "tab20")
    privileged = dict(zip(cells["method"], cells["privileged"].astype(bool), strict=True))
    fig, axes = plt.subplots(len(tracks), 1, figsize=(10, 2.7 * len(tracks)), sharex=True, squeeze=False)
    width = 0.8 / len(methods)
    x = np.arange(len(CASES))
    for ax, track in zip(axes[:, 0], tracks, strict=True):
        for i, method in enumerate(methods):
            mine = cells[(cells["method"] == method) & (cells["track"] == track)]
            if mine.empty:
                continue
            colour = colours(i % colours.N)
            sr, low, high, markers = _points(mine)
            offset = x + (i - (len(methods) - 1) / 2) * width
            ax.axhline(sr[0], color=colour, linestyle=":", linewidth=0.9, alpha=0.8)
            ax.errorbar(offset, sr, yerr=[sr - low, high - sr], fmt="none", ecolor=colour, elinewidth=0.9, capsize=1.5)
            for xi, yi, marker in zip(offset, sr, markers, strict=True):
                if marker:
                    face = "white" if privileged[method] else colour
                    ax.plot(xi, yi, marker=marker, color=colour, markerfacecolor=face, markersize=5 if marker == "o"
                            else 7, markeredgecolor="black" if marker != "o" else colour, linestyle="none")  # fmt: skip
        n = int(cells.loc[cells["track"] == track, "pairs"].min())
        ax.set_title(f"{TRACK_NAMES[track]} (n ≥ {n} paired scenes per cell)", fontsize=10)
        ax.set_ylim(-4, 105)
        ax.set_ylabel("success rate [%]")
        ax.axvline(0.5, color="0.6", linewidth=0.8)  # the nominal case apart from the perturbations
        ax.grid(axis="y", alpha=0.3)
    axes[-1, 0].set_xticks(x, CASES, rotation=30, ha="right")
    handles = [Line2D([], [], color=colours(i % colours.N), marker="o", linestyle=":",
                      markerfacecolor="white" if privileged[m] else colours(i % colours.N),
                      label=f"{m} (privileged)" if privileged[m] else m) for i, m in enumerate(methods)]  # fmt: skip
    handles += [
        Line2D([], [], color="0.3", marker="v", markeredgecolor="black", linestyle="none", label="significant drop"),
        Line2D([], [], color="0.3", marker="^", markeredgecolor="black", linestyle="none", label="significant gain"),
    ]
    axes[0, 0].legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False,
                      title="dotted: nominal SR", title_fontsize=7)  # fmt: skip
    return fig


def plot_robustness(cells: pd.DataFrame, path: str | Path, dpi: int = DEFAULT_DPI) -> Path:
    """Write the robustness figure to ``path`` (PNG, PDF or SVG by its suffix): per track, each method's success
    rate with its 95 % Wilson interval on the nominal id and under each perturbation, the nominal rate dotted across,
    significant changes (McNemar, Holm over the table) as triangles."""
    return _save(robustness_figure(cells), path, dpi)


def write_robustness(
    results: Sequence[str | Path],
    fmt: str = "md",
    csv: str | Path | None = None,
    figures: Sequence[str | Path] | None = None,
    seeds: str = "separate",
) -> str:
    """The robustness table of the result folders ``results`` as text (``fmt``: ``md`` or ``latex``); with ``csv``
    also every number as CSV (:func:`racebench.reporting.robustness.csv_frame`), with ``figures`` the figure in each
    file given (its format by its suffix). Every output is of the same validated records."""
    if seeds != "separate":
        raise ValueError("--seeds mean pools a sweep's training seeds; a robustness row pairs one policy's episodes")
    for path in figures or []:
        if Path(path).suffix.lower().lstrip(".") not in FIGURE_FORMATS:  # before any work: a one-line error
            raise ValueError(f"--figure {str(path)!r}: figures are written as {', '.join(FIGURE_FORMATS)}")
    cells = robustness_cells(read_robustness(results))
    text = make_robustness_table(cells, fmt)
    if csv is not None:
        atomic_write(Path(csv), csv_frame(cells).to_csv(index=False, float_format="%.10g"))
        logger.info(f"wrote {csv}")
    for path in figures or []:
        logger.info(f"wrote {plot_robustness(cells, path)}")
    return text
