"""The paper's claims, judged by the decision rule committed in a campaign's sweep file before its first run.

Difference claims (paired exact McNemar, pooled over tracks), "one-step fails" and the trend claims (stratified
Cochran-Armitage), Holm-adjusted together: :func:`judge_claims`, written out by :func:`claims_markdown`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER, env_id_of
from racebench.evaluation.statistics import holm_adjust, paired_outcomes, trend_test, wilson_interval
from racebench.reporting.cells import cell

ALPHA = 0.05

@dataclass(frozen=True)
class Claim:
    """One of the paper's claims as tested: both sides' numbers, the test, its p-value and the verdict."""

    claim: str
    evidence: str
    test: str
    p: float | None  # raw p-value (None: not a test, e.g. "one-step fails")
    verdict: str = ""
    p_holm: float | None = None


def _seed_episodes(episodes: pd.DataFrame, method: str, env_id: str, training_seed: int) -> pd.DataFrame:
    rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id)]
    return rows[rows["training_seed"] == training_seed]


def difference_claim(episodes: pd.DataFrame, better: str, worse: str) -> Claim:
    """``better`` > ``worse`` on every track's main id: directions per track and seed pair, pooled McNemar p."""
    directions, evidence, only_better, only_worse = [], [], 0, 0
    for track in TRACK_ORDER:
        env_id = env_id_of(track)
        ours, theirs = cell(episodes, better, env_id), cell(episodes, worse, env_id)
        if ours is None or theirs is None:
            return Claim(f"{better} > {worse}", f"{track}: missing runs", "exact McNemar, pooled", None)
        evidence.append(f"{track} {100 * ours.success_rate:.0f} vs {100 * theirs.success_rate:.0f}")
        seeds_a = sorted(set(episodes.loc[episodes["method"] == better, "training_seed"]))
        seeds_b = sorted(set(episodes.loc[episodes["method"] == worse, "training_seed"]))
        for a in seeds_a:
            for b in seeds_b:
                left, right = _seed_episodes(episodes, better, env_id, a), _seed_episodes(episodes, worse, env_id, b)
                if len(left) and len(right):
                    pairs = left.merge(right, on=["env_id", "seed"], suffixes=("_a", "_b"))
                    directions.append(np.sign(pairs["success_a"].mean() - pairs["success_b"].mean()))
        seed0_a, seed0_b = min(seeds_a), min(seeds_b)  # the pooled test pairs one run per side: the first seed
        _, a_only, b_only, _ = paired_outcomes(
            _seed_episodes(episodes, better, env_id, seed0_a), _seed_episodes(episodes, worse, env_id, seed0_b)
        )
        only_better, only_worse = only_better + a_only, only_worse + b_only
    from scipy.stats import binomtest

    p = binomtest(only_worse, only_better + only_worse).pvalue if only_better + only_worse else 1.0
    signs = set(directions)
    direction = 1 if signs == {1.0} else -1 if signs == {-1.0} else 0
    evidence.append(f"discordant scenes {only_better} vs {only_worse}")
    return Claim(f"{better} > {worse}", "; ".join(evidence), "exact McNemar, pooled over tracks", p,
                 verdict=str(direction))  # fmt: skip


def one_step_fails(episodes: pd.DataFrame, method: str = "vision-one-step") -> Claim:
    """``method`` fails on every main id: success rate < 10 % and its Wilson upper bound < 20 % on each track."""
    evidence, holds = [], True
    for track in TRACK_ORDER:
        rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id_of(track))]
        if rows.empty:
            return Claim(f"{method} fails", f"{track}: missing run", "success < 10 %, Wilson upper < 20 %", None,
                         verdict="not tested (missing runs)")  # fmt: skip
        k, n = int(rows["success"].sum()), len(rows)
        high = wilson_interval(k, n)[1]
        evidence.append(f"{track} {k}/{n} (upper {100 * high:.0f} %)")
        holds = holds and k / n < 0.10 and high < 0.20
    return Claim(f"{method} fails", "; ".join(evidence), "success < 10 % and Wilson upper < 20 % on every track",
                 None, verdict="holds" if holds else "does not hold")  # fmt: skip


def trend_claim(episodes: pd.DataFrame, kind: str, method: str = "vision-ppo") -> Claim:
    """``method``'s success falls with obstacle density (``kind="density"``) or gate shift (``"gates"``)."""
    if kind == "density":
        levels = [(float(d), f"Density{d}") for d in DENSITIES]
    else:
        levels = [(float(s), f"GateShift{s}") for s in GATE_SHIFTS]
    what = "density 2-5" if kind == "density" else "gate shift 0.3-1.0 m"
    strata, evidence = [], []
    for track in TRACK_ORDER:
        scores, successes, trials, rates = [], [], [], []
        for score, variant in levels:
            rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id_of(track, variant))]
            rows = rows[rows["training_seed"] == rows["training_seed"].min()] if len(rows) else rows
            if rows.empty:
                return Claim(f"{method}: success falls with {what}", f"{track} {variant}: missing",
                             "stratified Cochran-Armitage", None)  # fmt: skip
            scores.append(score)
            successes.append(int(rows["success"].sum()))
            trials.append(len(rows))
            rates.append(f"{100 * successes[-1] / trials[-1]:.0f}")
        strata.append((scores, successes, trials))
        evidence.append(f"{track} {'/'.join(rates)}")
    z, p_down, p_up = trend_test(strata)
    claim = Claim(f"{method}: success falls with {what}", "; ".join(evidence) + f"; z = {z:.2f}",
                  "Cochran-Armitage trend, stratified by track, one-sided", min(p_down, p_up),
                  verdict="1" if p_down <= p_up else "-1")  # fmt: skip
    return claim


def judge_claims(episodes: pd.DataFrame) -> list[Claim]:
    """The paper's claims with their verdicts under the rule committed in ``baselines/sweeps/campaign-4m.yaml``:
    Holm over every tested claim at level 0.05; a difference needs the same direction on every track and seed pair;
    a trend the one-sided stratified Cochran-Armitage test."""
    tested = [
        difference_claim(episodes, "vision-ppo", "state-ppo"),
        difference_claim(episodes, "vision-ppo", "vision-com"),
        difference_claim(episodes, "vision-ppo", "vision-no-gru"),
        difference_claim(episodes, "vision-ppo", "vision-no-avoid"),
        difference_claim(episodes, "vision-ppo", "vision-one-step"),
        trend_claim(episodes, "density"),
        trend_claim(episodes, "gates"),
    ]
    known = [claim for claim in tested if claim.p is not None]
    adjusted = dict(zip([id(c) for c in known], holm_adjust([c.p for c in known]), strict=True))
    judged = []
    for claim in tested:
        if claim.p is None:
            judged.append(Claim(claim.claim, claim.evidence, claim.test, None, "not tested (missing runs)"))
            continue
        p_holm = adjusted[id(claim)]
        direction = int(claim.verdict)
        if p_holm < ALPHA and direction == 1:
            verdict = "holds"
        elif p_holm < ALPHA and direction == -1:
            verdict = "opposite"
        else:
            verdict = "does not hold at this budget"
        judged.append(Claim(claim.claim, claim.evidence, claim.test, claim.p, verdict, p_holm))
    return judged + [one_step_fails(episodes)]


def claims_markdown(claims: list[Claim], budget_note: str) -> str:
    """``claims.md``: one line per claim with both numbers, the test, raw and Holm p, and the verdict."""
    lines = [
        "# The paper's claims, tested at 4 M steps per run",
        "",
        "Generated by `racebench paper-tables`; the decision rule was committed in `baselines/sweeps/campaign-4m.yaml`"
        " before the first run. Success on each track's main id (100 evaluation scenes per run) or on the density and"
        " gate-shift ids (50 each); Holm's correction over every tested claim, level 0.05.",
        "",
        "| claim | evidence (success %) | test | p | p (Holm) | verdict |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for c in claims:
        p = "–" if c.p is None else f"{c.p:.2g}"
        holm = "–" if c.p_holm is None else f"{c.p_holm:.2g}"
        lines.append(f"| {c.claim} | {c.evidence} | {c.test} | {p} | {holm} | **{c.verdict}** |")
    return "\n".join(lines + ["", budget_note, ""])


#: The window of a run's final training success: one rollout's rate is a handful of episodes (a run's last row
#: can read 0 % between rows of 100 %), so the rate is pooled over the episodes of its last 200k steps.
