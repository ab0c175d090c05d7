"""The paper's Table IV as figures: a campaign's ``vision-ppo`` against obstacle density and gate shift, per track.

Written by ``racebench paper-tables`` (:func:`write_table_iv_figures`) beside the tables, from the same validated
episodes (:func:`racebench.reporting.paper.load_episodes`, one env version).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER
from racebench.evaluation.statistics import wilson_interval
from racebench.reporting.paper_numbers import PAPER_VARIANTS
from racebench.reporting.tables import TRACK_NAMES

CAMPAIGN = Path("baselines/experiments/campaign-4m")  # the default campaign, as racebench.reporting.paper's


#: The two Table IV figures: file stem, the variants' prefix, their x values and the x axis label.
TABLE_IV_FIGURES: dict[str, tuple[list[str], list[float], str]] = {
    "table_iv_density": ([f"Density{d}" for d in DENSITIES], [float(d) for d in DENSITIES], "obstacles per 2 gates"),
    "table_iv_gate_shift": (
        [f"GateShift{s}" for s in GATE_SHIFTS], [float(s) for s in GATE_SHIFTS], "gate shift ±[m]"
    ),
}
FIGURE_FORMATS = ("png", "pdf")


def table_iv_figure(
    episodes: pd.DataFrame, factor: str, method: str = "vision-ppo", reference: str = "planner-fast",
    title: str | None = None,
):  # fmt: skip
    """Table IV as a figure (``factor``: a :data:`TABLE_IV_FIGURES` key), one panel per track: ``method``'s success
    rate per training seed with its 95 % Wilson interval, the mean over seeds with a band for their range, the
    paper's numbers as markers and ``reference`` (the privileged planner, same env version) as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    names, xs, xlabel = TABLE_IV_FIGURES[factor]
    step = min(np.diff(xs)) if len(xs) > 1 else 1.0
    fig, axes = plt.subplots(1, len(TRACK_ORDER), figsize=(11, 3.6), sharey=True, squeeze=False)
    seeds_seen, n_seen, ref_n = set(), set(), set()
    for ax, track in zip(axes[0], TRACK_ORDER, strict=True):
        rows = episodes[(episodes["method"] == method) & (episodes["track"] == track) & episodes["variant"].isin(names)]
        seeds = sorted(rows["training_seed"].unique())  # those flown on these ids (not only on the main id)
        seeds_seen.add(len(seeds))
        rates = pd.DataFrame(index=names, columns=seeds, dtype=float)
        for j, seed in enumerate(seeds):
            offset = (j - (len(seeds) - 1) / 2) * 0.08 * step
            for x, variant in zip(xs, names, strict=True):
                mine = rows[(rows["training_seed"] == seed) & (rows["variant"] == variant)]
                if mine.empty:
                    continue
                k, n = int(mine["success"].sum()), len(mine)
                n_seen.add(n)
                low, high = wilson_interval(k, n)
                rates.loc[variant, seed] = k / n
                ax.errorbar(x + offset, 100 * k / n, yerr=[[100 * (k / n - low)], [100 * (high - k / n)]],
                            fmt="o", markersize=3, color="tab:blue", alpha=0.55, capsize=2, linewidth=0.8)  # fmt: skip
        if len(seeds):
            mean, low, high = rates.mean(axis=1), rates.min(axis=1), rates.max(axis=1)
            ax.plot(xs, 100 * mean, color="tab:blue", linewidth=1.8)
            if len(seeds) > 1:
                ax.fill_between(xs, 100 * low, 100 * high, color="tab:blue", alpha=0.15, linewidth=0)
        else:
            ax.text(0.5, 0.5, f"no {method} run", transform=ax.transAxes, ha="center", color="0.4", style="italic")
        ref = episodes[(episodes["method"] == reference) & (episodes["track"] == track)]
        ref_rates = [ref.loc[ref["variant"] == v, "success"] for v in names]
        ref_n.update(len(r) for r in ref_rates if len(r))
        ax.plot(xs, [100 * r.mean() if len(r) else np.nan for r in ref_rates], "--", color="0.35", linewidth=1.2,
                marker=".", zorder=1)  # fmt: skip
        ax.plot(xs, [PAPER_VARIANTS[v][track] for v in names], "x", color="tab:red", markersize=8,
                markeredgewidth=1.8, zorder=4)  # fmt: skip
        ax.set_title(f"{TRACK_NAMES[track]} ({len(seeds)} seed{'s' if len(seeds) != 1 else ''})", fontsize=10)
        ax.set_xticks(xs)
        ax.set_xlabel(xlabel)
        ax.set_ylim(-4, 105)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success rate [%]")
    per_cell = "/".join(str(n) for n in sorted(n_seen)) or "–"
    ref_cell = "/".join(str(n) for n in sorted(ref_n)) or "–"
    handles = [
        Line2D([], [], color="tab:blue", marker="o", markersize=3, alpha=0.55, linestyle="",
               label=f"{method}: one training seed, 95 % Wilson interval ({per_cell} episodes)"),
        Line2D([], [], color="tab:blue", linewidth=1.8, label=f"{method}: mean over training seeds"),
        Patch(color="tab:blue", alpha=0.15, label=f"{method}: range over training seeds"),
        Line2D([], [], color="tab:red", marker="x", linestyle="", markeredgewidth=1.8,
               label="paper (Sun et al., Table IV; 10 trials)"),
        Line2D([], [], color="0.35", linestyle="--", marker=".",
               label=f"{reference} (privileged reference; {ref_cell} episodes)"),
    ]  # fmt: skip
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    return fig


def write_table_iv_figures(
    episodes: pd.DataFrame, out: Path, env_version: int | None, campaign: Path = CAMPAIGN
) -> list[Path]:
    """Both Table IV figures of ``vision-ppo`` under ``out/figures`` as PNG and PDF (none without its episodes)."""
    import matplotlib.pyplot as plt

    if not (episodes["method"] == "vision-ppo").any():
        return []
    written = []
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for stem in TABLE_IV_FIGURES:
        what = "obstacle density" if stem.endswith("density") else "gate shift"
        title = (f"vision-ppo's success rate against {what} ({Path(campaign).name}, "
                 f"env version {env_version}; references on the same env version)")  # fmt: skip
        fig = table_iv_figure(episodes, stem, title=title)
        for fmt in FIGURE_FORMATS:
            path = out / "figures" / f"{stem}.{fmt}"
            metadata = {"Software": None} if fmt == "png" else {"Creator": None, "Producer": None, "CreationDate": None}
            fig.savefig(path, dpi=200, bbox_inches="tight", pad_inches=0.05, metadata=metadata)
            written.append(path)
        plt.close(fig)
    return written
