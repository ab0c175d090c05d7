"""The paper's claims, judged by the decision rule committed in a campaign's sweep file before its first run.

Difference claims (paired exact McNemar, pooled over tracks), "one-step fails", the trend claims (stratified
Cochran-Armitage) and, where the campaign's rule has it (campaign 2), the flying-start hypothesis, Holm-adjusted
together within the campaign: :func:`judge_claims`. One campaign's table: :func:`claims_markdown`; every campaign's
verdicts side by side, never pooled: :func:`claims_page` (``results/claims.md``).

A claim is tested once every run it needs is committed (its verdict says how many are, until then). While some
claims of a campaign wait for their runs, Holm's adjustment over the whole family is not known yet; a tested claim's
adjusted p is then bounded by Bonferroni's ``m p`` (Holm never exceeds it) from above and by its raw p from below,
so a verdict is given where both bounds agree and the claim is "pending" otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER, env_id_of
from racebench.evaluation.statistics import holm_adjust, paired_outcomes, trend_test, wilson_interval
from racebench.reporting.campaigns import RunSet
from racebench.reporting.cells import cell

ALPHA = 0.05
#: The difference claims of both campaigns' rules: (better, worse) on every track's main id.
DIFFERENCES: tuple[tuple[str, str], ...] = (
    ("vision-ppo", "state-ppo"), ("vision-ppo", "vision-com"), ("vision-ppo", "vision-no-gru"),
    ("vision-ppo", "vision-no-avoid"), ("vision-ppo", "vision-one-step"),
)  # fmt: skip
#: Campaign 2's flying-start hypothesis: (flying start, at rest), seed 0 of each, tested as a difference claim.
FLYING_START: tuple[str, str] = ("vision-one-step-flying", "vision-one-step")
FLYING_START_CLAIM = f"flying-start hypothesis: {FLYING_START[0]} > {FLYING_START[1]} (seed 0 of each)"
#: The tests, as claims.md names them.
MCNEMAR = "exact McNemar, pooled over tracks"
TREND_TEST = "Cochran-Armitage trend, stratified by track, one-sided"
FAILS_TEST = "success < 10 % and Wilson upper < 20 % on every track"


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims as tested: both sides' numbers, the test, its p-value and the verdict."""

    claim: str
    evidence: str
    test: str
    p: float | None  # raw p-value (None: not a test, e.g. "one-step fails")
    verdict: str = ""
    p_holm: float | None = None
    p_holm_bound: bool = False  # p_holm is an upper bound (m p): some claims of the family are not tested yet


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
            return Claim(f"{better} > {worse}", f"{track}: missing runs", MCNEMAR, None)
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
    return Claim(f"{better} > {worse}", "; ".join(evidence), MCNEMAR, p,
                 verdict=str(direction))  # fmt: skip


def one_step_fails(episodes: pd.DataFrame, method: str = "vision-one-step") -> Claim:
    """``method`` fails on every main id: success rate < 10 % and its Wilson upper bound < 20 % on each track."""
    evidence, holds = [], True
    for track in TRACK_ORDER:
        rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id_of(track))]
        if rows.empty:
            return Claim(f"{method} fails", f"{track}: missing run", FAILS_TEST, None,
                         verdict="not tested (missing runs)")  # fmt: skip
        k, n = int(rows["success"].sum()), len(rows)
        high = wilson_interval(k, n)[1]
        evidence.append(f"{track} {k}/{n} (upper {100 * high:.0f} %)")
        holds = holds and k / n < 0.10 and high < 0.20
    return Claim(f"{method} fails", "; ".join(evidence), FAILS_TEST, None,
                 verdict="holds" if holds else "does not hold")  # fmt: skip


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
                             TREND_TEST, None)  # fmt: skip
            scores.append(score)
            successes.append(int(rows["success"].sum()))
            trials.append(len(rows))
            rates.append(f"{100 * successes[-1] / trials[-1]:.0f}")
        strata.append((scores, successes, trials))
        evidence.append(f"{track} {'/'.join(rates)}")
    z, p_down, p_up = trend_test(strata)
    claim = Claim(f"{method}: success falls with {what}", "; ".join(evidence) + f"; z = {z:.2f}",
                  TREND_TEST, min(p_down, p_up),
                  verdict="1" if p_down <= p_up else "-1")  # fmt: skip
    return claim


def flying_start_claim(episodes: pd.DataFrame) -> Claim:
    """The flying-start hypothesis: :data:`FLYING_START`'s flying config beats its at-rest one, training seed 0 of
    each, paired on the same evaluation scenes and judged exactly as a difference claim."""
    mine = episodes["method"].isin(FLYING_START)
    claim = difference_claim(episodes[~mine | (episodes["training_seed"] == 0)], *FLYING_START)
    return replace(claim, claim=FLYING_START_CLAIM)


def _untested(claim: Claim, committed: int, planned: int) -> Claim:
    """``claim`` (its name and test) waiting for its runs: ``committed`` of the ``planned`` it needs are in."""
    if planned == 0:
        return Claim(claim.claim, "no run planned", claim.test, None, "not tested (no run planned)")
    return Claim(claim.claim, f"{committed} of {planned} runs committed", claim.test, None,
                 f"not tested yet ({committed} of {planned} runs)")  # fmt: skip


def judge_claims(episodes: pd.DataFrame, runs: RunSet | None = None, flying_start: bool = False) -> list[Claim]:
    """The paper's claims with their verdicts under a campaign's committed rule (campaign 1:
    ``baselines/sweeps/campaign-4m.yaml``; campaign 2, ``flying_start``: ``campaign-2.yaml``, which adds
    :func:`flying_start_claim`): Holm over every difference, trend and flying-start claim of the campaign at level
    0.05; a difference needs the same direction on every track and seed pair; a trend the one-sided stratified
    Cochran-Armitage test.

    ``runs``: the campaign's planned and committed runs; a claim is judged only once all the runs it needs are
    committed (else "not tested yet (k of n runs)"). Without it, a claim is judged whenever its cells exist.
    While some claims of the family are not tested, a tested one's Holm p is only bounded (module docstring)."""
    first_ppo = min((r.seed for r in runs.planned if r.config == "vision-ppo"), default=0) if runs else 0
    family = [difference_claim(episodes, better, worse) for better, worse in DIFFERENCES]
    family += [trend_claim(episodes, "density"), trend_claim(episodes, "gates")]
    needs: list[tuple[tuple[str, ...], int | None]] = [(pair, None) for pair in DIFFERENCES]  # configs, seed
    needs += [(("vision-ppo",), first_ppo)] * 2  # a trend is tested on the first training seed
    if flying_start:
        family.append(flying_start_claim(episodes))
        needs.append((FLYING_START, 0))
    tested = []
    for claim, (configs, seed) in zip(family, needs, strict=True):
        if runs is not None:
            committed, planned = runs.count(configs, seed)
            if planned == 0 or committed < planned:
                claim = _untested(claim, committed, planned)
        tested.append(claim)
    known = [claim for claim in tested if claim.p is not None]
    bound = len(known) < len(tested)  # the family is not complete: Holm's p is known only up to m p
    if bound:
        adjusted = {id(c): min(1.0, len(tested) * c.p) for c in known}
    else:
        adjusted = dict(zip([id(c) for c in known], holm_adjust([c.p for c in known]), strict=True))
    judged = []
    for claim in tested:
        if claim.p is None:
            verdict = claim.verdict or "not tested (missing runs)"
            judged.append(Claim(claim.claim, claim.evidence, claim.test, None, verdict))
            continue
        p_holm = adjusted[id(claim)]
        direction = int(claim.verdict)
        if p_holm < ALPHA and direction == 1:
            verdict = "holds"
        elif p_holm < ALPHA and direction == -1:
            verdict = "opposite"
        elif not bound or direction == 0 or claim.p >= ALPHA:  # Holm's p is at least the raw p
            verdict = "does not hold at this budget"
        else:
            waiting = len(tested) - len(known)
            verdict = f"pending (Holm over {len(tested)} claims, {waiting} not tested yet)"
        judged.append(Claim(claim.claim, claim.evidence, claim.test, claim.p, verdict, p_holm, bound))
    fails = one_step_fails(episodes)
    if runs is not None:
        committed, planned = runs.count(["vision-one-step"])
        if planned == 0 or committed < planned:
            fails = _untested(fails, committed, planned)
    return judged + [fails]


def _p_text(claim: Claim) -> tuple[str, str]:
    """The raw and Holm p of a claim as printed ("≤" before a bound)."""
    p = "–" if claim.p is None else f"{claim.p:.2g}"
    holm = "–" if claim.p_holm is None else f"{'≤ ' if claim.p_holm_bound else ''}{claim.p_holm:.2g}"
    return p, holm


def claims_markdown(claims: list[Claim], budget_note: str, heading: str = "# The paper's claims, tested at 4 M steps "
                    "per run", rule: str = "baselines/sweeps/campaign-4m.yaml") -> str:  # fmt: skip
    """One campaign's claims: one line per claim with both numbers, the test, raw and Holm p, and the verdict; then
    ``budget_note``."""
    family = sum(c.test != FAILS_TEST for c in claims)
    flying = any(c.claim == FLYING_START_CLAIM for c in claims)
    kinds = "the differences, the trends and the flying-start hypothesis" if flying else "the differences and trends"
    waiting = any(c.p is None and c.test != FAILS_TEST for c in claims)
    bound = (" While some of them wait for their runs, a tested claim's p (Holm) is its upper bound m p (Holm's own"
             " cannot exceed it, nor fall below the raw p): a verdict is given where both bounds agree, else it is"
             " pending." if waiting else "")  # fmt: skip
    lines = [
        heading,
        "",
        f"The decision rule was committed in `{rule}` before the first run. Success on each track's main id (100"
        " evaluation scenes per run) or on the density and"
        f" gate-shift ids (50 each); Holm's correction over its {family} claims ({kinds}), level 0.05.{bound}",
        "",
        "| claim | evidence (success %) | test | p | p (Holm) | verdict |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for c in claims:
        p, holm = _p_text(c)
        lines.append(f"| {c.claim} | {c.evidence} | {c.test} | {p} | {holm} | **{c.verdict}** |")
    return "\n".join(lines + ["", budget_note, ""])


@dataclass(frozen=True)
class ClaimsSection:
    """One campaign's part of ``claims.md``: who it is, its judged claims and its budget note."""

    title: str  # "campaign 1"
    name: str  # "campaign-4m"
    env_version: int | None
    distribution: str
    rule: str  # the sweep file holding its decision rule
    steps: int  # environment steps per run
    runs: tuple[int, int] | None  # (committed, planned) runs; None: not known
    claims: list[Claim]
    budget_note: str


def _short(claim: Claim) -> str:
    """A claim's verdict in one cell: the verdict, with its Holm p where it is a test."""
    if claim.verdict.startswith("not tested"):
        return claim.verdict
    if claim.p_holm is None:  # a judgement without a test ("one-step fails")
        return f"**{claim.verdict}**"
    return f"**{claim.verdict}** (p Holm {_p_text(claim)[1]})"


def claims_page(sections: list[ClaimsSection]) -> str:
    """``claims.md``: every campaign's verdicts side by side (one column each, never pooled: each is judged by its
    own rule and Holm family), then each campaign's own table (:func:`claims_markdown`)."""
    order: list[str] = []
    for section in sections:
        order += [c.claim for c in section.claims if c.claim not in order]
    label = {s.name: f"{s.title} (env version {s.env_version if s.env_version is not None else '–'})" for s in sections}
    lines = [
        "# The paper's claims, tested in each training campaign",
        "",
        "Generated by `racebench paper-tables` from the committed runs (no training, no flying). Each campaign is"
        " judged by its own decision rule, committed in its sweep file before its first run, on its own env version and"
        " evaluation scenes, with Holm's correction over its own claims at level 0.05: the campaigns are never pooled."
        " A claim is tested once every run it needs is committed; until then its cell says how many are.",
        "",
        "| campaign | env version | training distribution | steps per run | runs committed | decision rule |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for s in sections:
        runs = "–" if s.runs is None else f"{s.runs[0]} of {s.runs[1]}"
        version = "–" if s.env_version is None else str(s.env_version)
        lines.append(f"| {s.title} (`{s.name}`) | {version} | {s.distribution or '–'} | {s.steps / 1e6:g} M | {runs} "
                     f"| `{s.rule}` |")  # fmt: skip
    lines += ["", "| claim | " + " | ".join(label[s.name] for s in sections) + " |",
              "| --- |" + " --- |" * len(sections)]  # fmt: skip
    for name in order:
        cells = []
        for s in sections:
            found = next((c for c in s.claims if c.claim == name), None)
            cells.append(f"– (not in {s.title}'s rule)" if found is None else _short(found))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if any(c.claim == FLYING_START_CLAIM for s in sections for c in s.claims):
        lines += ["", f"The flying-start hypothesis: campaign 1's `{FLYING_START[1]}` succeeded because its flying "
                  "mid-leg starts gave gate-pass reward for free. Tested on the same env version and evaluation "
                  "scenes as the at-rest runs: **holds** supports it; **does not hold** or **opposite** rejects it at "
                  "this budget."]  # fmt: skip
    for s in sections:
        version = "–" if s.env_version is None else s.env_version
        heading = f"## {s.title[:1].upper()}{s.title[1:]}: `{s.name}`, env version {version}, {s.steps / 1e6:g} M steps"
        lines += ["", claims_markdown(s.claims, s.budget_note, heading, s.rule).rstrip("\n")]
    return "\n".join(lines) + "\n"
