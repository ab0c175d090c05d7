"""The paper's tables, regenerated from summary CSVs alone, as Markdown or LaTeX (booktabs).

* Table II: lap time (LT, mean over successful laps) and success rate (SR) per track, one row per agent;
* Table III: SR per track for the ablation agents (same layout as Table II's SR half);
* Table IV: SR per track against obstacle density (2–5) and against gate shift (±0.3–±1.0 m).

SR cells show the percentage and, by default, the 95 % Wilson interval. A cell is bold only when its 95 %
interval (Wilson for SR, Student's t for the mean lap time) lies entirely beyond every other non-privileged
agent's in that comparison: the best point estimate alone is not a result. Privileged agents (e.g. the
planner) are marked and never bolded: they are a reference, not a competitor.

:func:`over_seeds` pools a sweep's training seeds (rows ``<config>-seed<k>``) into one row per config: the mean of
the seeds' success rates with their range, since another training seed usually moves a rate more than the episodes'
sampling does; a config is then bold only where its worst seed beats every other row's interval.
"""

from __future__ import annotations

import math
import re

import pandas as pd
from scipy.stats import t as student_t

from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER

TRACK_NAMES: dict[str, str] = {"S": "S-shaped", "Circle": "3D Circle", "J": "J-shaped"}
TABLES: tuple[str, ...] = ("II", "III", "IV")
SEED_MODES: tuple[str, ...] = ("separate", "mean")  # a sweep's training seeds: a row each, or one row per config
SEED_LABEL = re.compile(r"^(?P<config>.+)-seed(?P<seed>\d+)$")  # a sweep's runs: <config>-seed<k>


def _agent_label(agent: str, privileged: bool) -> str:
    return f"{agent} (privileged)" if privileged else agent


def _sr_text(row: pd.Series | None, ci: bool) -> str:
    if row is None:
        return "–"
    text = f"{100 * row['success_rate']:.0f}"
    if ci:
        text += f" [{100 * row['sr_ci_low']:.0f}–{100 * row['sr_ci_high']:.0f}]"
    return text


def _lt_text(row: pd.Series | None) -> str:
    if row is None or not math.isfinite(row["lap_time_mean"]):
        return "–"
    return f"{row['lap_time_mean']:.2f}"


def _lookup(summary: pd.DataFrame, agent: str, track: str, variant: str) -> pd.Series | None:
    hit = summary[(summary["agent"] == agent) & (summary["track"] == track) & (summary["variant"] == variant)]
    return None if hit.empty else hit.iloc[0]


def _agents(summary: pd.DataFrame) -> list[tuple[str, bool]]:
    order = summary.drop_duplicates("agent")[["agent", "privileged"]]
    # Learned agents first (as in the paper), privileged references last.
    return sorted(((str(a), bool(p)) for a, p in order.itertuples(index=False)), key=lambda x: (x[1], x[0]))


def _interval(row: pd.Series | None, lap_time: bool) -> tuple[float, float] | None:
    """A cell's 95 % interval: Wilson for a success rate, Student's t for a mean lap time (None if unknown)."""
    if row is None:
        return None
    if not lap_time:
        return float(row["sr_ci_low"]), float(row["sr_ci_high"])
    laps, mean, std = int(row["successes"]), float(row["lap_time_mean"]), float(row["lap_time_std"])
    if laps < 2 or not (math.isfinite(mean) and math.isfinite(std)):
        return None
    half = float(student_t.ppf(0.975, laps - 1)) * std / math.sqrt(laps)
    return mean - half, mean + half


def best_separated(intervals: dict[str, tuple[float, float] | None], lower_is_better: bool) -> set[str]:
    """Agents whose interval is entirely better than every other agent's (needs a rival; unknown never bold).

    Bold means "distinguishable from the rest at 95 %", not "highest point estimate": 10/10 [72–100] against
    9/10 [60–98] is not bold.
    """
    known = {a: i for a, i in intervals.items() if i is not None}
    if len(known) < 2 or len(known) < len(intervals):
        return set()  # an agent without an interval (no laps) cannot be ranked against
    if lower_is_better:
        return {a for a, (_, high) in known.items() if all(high < low for b, (low, _) in known.items() if b != a)}
    return {a for a, (low, _) in known.items() if all(low > high for b, (_, high) in known.items() if b != a)}


def table_ii(summary: pd.DataFrame, ci: bool = True, lap_time: bool = True) -> tuple[pd.DataFrame, set]:
    """Table II (or, with ``lap_time=False``, Table III): cells as text plus the set of bold cells."""
    agents = _agents(summary)
    privileged = dict(agents)
    columns: dict[str, dict[str, str]] = {}
    bold: set[tuple[str, str]] = set()
    groups = ([("LT [s]", True)] if lap_time else []) + [("SR [%]", False)]
    for title, is_lt in groups:
        for track in TRACK_ORDER:
            col = f"{title} {TRACK_NAMES[track]}"
            rows = {a: _lookup(summary, a, track, "default") for a, _ in agents}
            columns[col] = {a: (_lt_text(r) if is_lt else _sr_text(r, ci)) for a, r in rows.items()}
            # Lap times compare agents that finished laps; a success rate compares every agent flown.
            flown = {a: r for a, r in rows.items() if r is not None and not privileged[a]}
            if is_lt:
                flown = {a: r for a, r in flown.items() if int(r["successes"]) > 0}
            intervals = {a: _interval(r, is_lt) for a, r in flown.items()}
            bold |= {(a, col) for a in best_separated(intervals, lower_is_better=is_lt)}
    labels = {a: _agent_label(a, p) for a, p in agents}
    frame = pd.DataFrame(columns, index=[a for a, _ in agents]).rename(index=labels)
    return frame, {(labels[a], col) for a, col in bold}


def table_iv(summary: pd.DataFrame, ci: bool = True) -> tuple[pd.DataFrame, set]:
    """Table IV: SR per track vs density and vs gate shift, one column per agent × track."""
    agents = _agents(summary)
    privileged = dict(agents)
    variants = [(f"Density {d}", f"Density{d}") for d in DENSITIES] + [
        (f"Gate ±{s} m", f"GateShift{s}") for s in GATE_SHIFTS
    ]
    columns: dict[str, dict[str, str]] = {}
    bold: set[tuple[str, str]] = set()
    for agent, priv in agents:
        for track in TRACK_ORDER:
            col = f"{_agent_label(agent, priv)} {TRACK_NAMES[track]}"
            columns[col] = {label: _sr_text(_lookup(summary, agent, track, v), ci) for label, v in variants}
    # Bold: for each row and track, the best non-privileged agent.
    for label, variant in variants:
        for track in TRACK_ORDER:
            intervals = {}
            for agent, _ in agents:
                row = _lookup(summary, agent, track, variant)
                if row is not None and not privileged[agent]:
                    intervals[agent] = _interval(row, lap_time=False)
            for agent in best_separated(intervals, lower_is_better=False):
                bold.add((label, f"{_agent_label(agent, privileged[agent])} {TRACK_NAMES[track]}"))
    return pd.DataFrame(columns, index=[label for label, _ in variants]), bold


def over_seeds(summary: pd.DataFrame) -> pd.DataFrame:
    """Rows of one config's training seeds (labels ``<config>-seed<k>``, as a sweep writes them) pooled per env id.

    A config with two or more seeds becomes the row ``<config> (<k> seeds)``: ``success_rate`` the mean of the
    seeds' rates, ``sr_ci_low`` / ``sr_ci_high`` their lowest and highest, ``n`` and ``successes`` the totals,
    ``lap_time_mean`` the mean of the seeds' mean laps (over the seeds with a lap) without a spread (so no lap-time
    cell of a column it is in is bold), ``seeds`` the count (1 on every other row, each kept as it is). A config
    whose seeds were not all flown on the same ids is an error: its mean would average different seeds on different
    ids.
    """
    matches = [SEED_LABEL.match(str(agent)) for agent in summary["agent"]]
    configs = pd.Series([m["config"] if m else None for m in matches], index=summary.index)
    seeds = pd.Series([int(m["seed"]) if m else -1 for m in matches], index=summary.index)
    pooled, kept = [], []
    for config, group in summary[configs.notna()].groupby(configs[configs.notna()], sort=False):
        all_seeds = sorted(set(seeds[group.index]))
        if len(all_seeds) < 2:
            kept.append(group)
            continue
        for env_id, cell in group.groupby("env_id", sort=False):
            flown = sorted(seeds[cell.index])
            if flown != all_seeds:
                raise ValueError(f"{config}: {env_id} has results of seeds {flown}, its other ids of {all_seeds}; "
                                 "pool seeds flown on the same ids")  # fmt: skip
            laps = cell.loc[cell["successes"] > 0, "lap_time_mean"]
            pooled.append({
                **cell.iloc[0].to_dict(),
                "agent": f"{config} ({len(all_seeds)} seeds)",
                "privileged": bool(cell["privileged"].any()),
                "n": int(cell["n"].sum()),
                "successes": int(cell["successes"].sum()),
                "success_rate": float(cell["success_rate"].mean()),
                "sr_ci_low": float(cell["success_rate"].min()),
                "sr_ci_high": float(cell["success_rate"].max()),
                "lap_time_mean": float(laps.mean()) if len(laps) else float("nan"),
                "lap_time_median": float("nan"),
                "lap_time_std": float("nan"),
                "seeds": len(all_seeds),
            })  # fmt: skip
    frames = [summary[configs.isna()], *kept, pd.DataFrame(pooled)]
    return pd.concat([f for f in frames if not f.empty], ignore_index=True).fillna({"seeds": 1})


def _latex_escape(text: str) -> str:
    for char, repl in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#")):
        text = text.replace(char, repl)
    return text.replace("±", r"$\pm$").replace("–", "--").replace("·", r"$\cdot$")


def render(frame: pd.DataFrame, bold: set, fmt: str, caption: str) -> str:
    """A table as Markdown (``fmt="md"``) or LaTeX booktabs (``fmt="latex"``), bold cells emphasised."""
    if fmt not in ("md", "latex"):
        raise ValueError(f"format must be 'md' or 'latex', got {fmt!r}")
    cells = frame.copy().astype(object)
    for row, col in bold:
        if row in cells.index and col in cells.columns:
            value = str(cells.loc[row, col])
            cells.loc[row, col] = f"**{value}**" if fmt == "md" else rf"\textbf{{{_latex_escape(value)}}}"
    if fmt == "md":
        return f"**{caption}**\n\n" + cells.to_markdown(disable_numparse=True) + "\n"
    escaped = cells.map(lambda v: v if str(v).startswith(r"\textbf") else _latex_escape(str(v)))
    escaped.index = [_latex_escape(str(i)) for i in escaped.index]
    escaped.columns = [_latex_escape(str(c)) for c in escaped.columns]
    body = escaped.style.to_latex(hrules=True, column_format="l" + "c" * len(escaped.columns))
    return f"\\begin{{table}}[t]\n\\centering\n\\caption{{{_latex_escape(caption)}}}\n{body}\\end{{table}}\n"


def make_table(summary: pd.DataFrame, which: str, fmt: str = "md", ci: bool = True, seeds: str = "separate") -> str:
    """Table ``II``, ``III`` or ``IV`` of the paper from a summary DataFrame.

    ``seeds="mean"`` pools each config's training seeds into one row first (:func:`over_seeds`).
    """
    if seeds not in SEED_MODES:
        raise ValueError(f"seeds must be one of {SEED_MODES}, got {seeds!r}")
    pooled = False
    if seeds == "mean":
        summary = over_seeds(summary)
        pooled = bool((summary["seeds"] > 1).any())
    which = which.upper()
    if which == "II":
        frame, bold = table_ii(summary, ci=ci, lap_time=True)
        caption = "Table II: lap time (mean over successful laps) and success rate per track."
    elif which == "III":
        frame, bold = table_ii(summary, ci=ci, lap_time=False)
        caption = "Table III: success rate of the ablations per track."
    elif which == "IV":
        frame, bold = table_iv(summary, ci=ci)
        caption = "Table IV: success rate vs obstacle density (per 2 gates) and vs gate shift."
    else:
        raise ValueError(f"unknown table {which!r}; choose from {TABLES}")
    if frame.empty or frame.isin(["–"]).all().all():
        raise ValueError(f"no results for Table {which} in the given summaries")
    if ci:
        caption += " SR in % with 95% Wilson interval in brackets."
    if pooled:
        caption += (" Rows '(k seeds)': the mean over k training seeds, SR range over the seeds in brackets, lap time"
                    " the mean of the seeds' mean laps.")  # fmt: skip
    caption += " Bold: a non-privileged agent whose 95% interval lies entirely beyond every other's."
    return render(frame, bold, fmt, caption)


def lap_text(seconds: float) -> str:
    """A mean lap time as printed: seconds to 0.01 s, or "–" without a successful lap (NaN)."""
    return "–" if seconds != seconds else f"{seconds:.2f}"  # NaN != NaN


def compare_header(pairs: pd.DataFrame) -> pd.DataFrame:
    """``racebench compare``'s per-env-id table of each side on the paired episodes (see its printed legend)."""
    table = {"env_id": pairs["env_id"], "pairs": pairs["pairs"]}
    for side in "ab":
        table[f"{side} SR [%]"] = [
            f"{k}/{n} {100 * k / n:.0f} [{100 * low:.0f}–{100 * high:.0f}]" if n else "–"
            for k, n, low, high in zip(
                pairs[f"successes_{side}"],
                pairs["pairs"],
                pairs[f"sr_ci_low_{side}"],
                pairs[f"sr_ci_high_{side}"],
                strict=True,
            )  # fmt: skip
        ]
        table[f"{side} lap [s]"] = [lap_text(float(v)) for v in pairs[f"lap_time_mean_{side}"]]
    return pd.DataFrame(table)
