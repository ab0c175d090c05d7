"""Statistics of success rates: Wilson intervals, a test that two success counts agree, paired tests and the
bootstrap intervals of the leaderboard (a mean over tracks, the probability of improvement).

A learned policy's closed loop amplifies last-bit float differences between CPUs, so the same checkpoint
on the same seeds can give a different episode on another machine. What the benchmark promises about a
learned policy is therefore a *success rate*, checked statistically (:func:`counts_consistent`), not a
bit-identical replay.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.stats import binomtest, bootstrap, fisher_exact, norm

if TYPE_CHECKING:
    import pandas as pd

#: False-fail rate of :func:`counts_consistent` (two-sided): a reproduction of a committed count is
#: rejected by chance at most this often.
CONSISTENCY_ALPHA = 0.001
#: Resamples and seed of every bootstrap interval here (the leaderboard's aggregate and improvement columns).
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (``nan, nan`` when ``n == 0``)."""
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(successes, n).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


@dataclass(frozen=True)
class Consistency:
    """Outcome of :func:`counts_consistent`: the p-value of Fisher's exact test and the verdict."""

    p_value: float
    alpha: float

    @property
    def consistent(self) -> bool:
        """True when the counts are consistent at the false-fail rate ``alpha``."""
        return self.p_value >= self.alpha


def counts_consistent(
    committed: tuple[int, int], replayed: tuple[int, int], alpha: float = CONSISTENCY_ALPHA
) -> Consistency:
    """Are ``replayed = (k1, n1)`` successes consistent with a ``committed = (k0, n0)`` claim of the same policy?

    Two-sided Fisher exact test of equal success probability, rejected when ``p < alpha``. The test treats
    the two samples as independent. A replay of the *same* seeds is positively correlated with the
    committed sample, which only narrows the spread of ``k1/n1 - k0/n0``, so the false-fail rate stays
    at most ``alpha`` (the test is conservative there).
    """
    (k0, n0), (k1, n1) = committed, replayed
    for k, n in (committed, replayed):
        if not (0 <= k <= n and n > 0):
            raise ValueError(f"a success count must satisfy 0 <= k <= n, n > 0; got k={k}, n={n}")
    p = fisher_exact([[k0, n0 - k0], [k1, n1 - k1]], alternative="two-sided").pvalue
    return Consistency(float(p), alpha)


def detectable_doctoring(committed: tuple[int, int], replayed: tuple[int, int], alpha: float = CONSISTENCY_ALPHA):
    """The committed counts that :func:`counts_consistent` would reject against ``replayed``.

    Returns ``(low, high)``: every committed count ``k <= low`` or ``k >= high`` (out of the same ``n0``)
    is rejected, i.e. a claim doctored that far from what the replay shows is caught. ``low`` is ``-1``
    or ``high`` is ``n0 + 1`` when no count on that side is rejected.
    """
    _, n0 = committed
    rejected = [k for k in range(n0 + 1) if not counts_consistent((k, n0), replayed, alpha).consistent]
    below = [k for k in rejected if k < committed[0]]
    above = [k for k in rejected if k > committed[0]]
    return (max(below) if below else -1), (min(above) if above else n0 + 1)


def paired_outcomes(a: pd.DataFrame, b: pd.DataFrame) -> tuple[int, int, int, float]:
    """Two evaluations paired on the same scenes (``env_id``, ``seed``): the number of pairs, the laps finished only
    by ``a``, only by ``b``, and the two-sided exact binomial p-value on those discordant pairs (McNemar's exact
    test; 1 without any)."""
    pairs = a.merge(b, on=["env_id", "seed"], suffixes=("_a", "_b"))
    only_a = int((pairs["success_a"] & ~pairs["success_b"]).sum())
    only_b = int((pairs["success_b"] & ~pairs["success_a"]).sum())
    return len(pairs), only_a, only_b, binomtest(only_b, only_a + only_b).pvalue if only_a + only_b else 1.0


def holm_adjust(pvalues: list[float]) -> list[float]:
    """Holm's step-down adjustment of ``pvalues`` (family-wise error rate), in the order given.

    The i-th smallest p becomes ``max_{j<=i} min(1, (m - j + 1) p_(j))`` (Holm 1979): compare each with the level.
    """
    m = len(pvalues)
    order = sorted(range(m), key=lambda i: pvalues[i])
    adjusted = [0.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvalues[i]))
        adjusted[i] = running
    return adjusted


def trend_test(strata: list[tuple[list[float], list[int], list[int]]]) -> tuple[float, float, float]:
    """Cochran–Armitage test for a trend in proportions over ordered levels, stratified by summing the strata's
    score statistics and variances (each stratum keeps its own success rate under the null hypothesis).

    ``strata``: per stratum (e.g. per track) the levels' scores, successes and trials. Returns ``(z, p_decreasing,
    p_increasing)``: the standardised statistic (negative when success falls as the score grows) and its one-sided
    normal p-values. Unstratified, ``z**2`` equals ``N r**2``, r the Pearson correlation of score and outcome over
    the N episodes (Agresti, *Categorical Data Analysis*, 3rd ed., Sec. 5.3.5).
    """
    statistic = variance = 0.0
    for scores, successes, trials in strata:
        if not len(scores) == len(successes) == len(trials):
            raise ValueError("trend_test: each stratum needs as many scores as success and trial counts")
        total = sum(trials)
        if total == 0:
            continue
        rate = sum(successes) / total
        mean_score = sum(x * n for x, n in zip(scores, trials, strict=True)) / total
        statistic += sum((s - n * rate) * x for x, s, n in zip(scores, successes, trials, strict=True))
        variance += rate * (1 - rate) * sum(n * (x - mean_score) ** 2 for x, n in zip(scores, trials, strict=True))
    if variance == 0:  # every episode of every stratum ended alike: no evidence of any trend
        return 0.0, 1.0, 1.0
    z = statistic / variance**0.5
    return z, float(norm.cdf(z)), float(norm.sf(z))


def mean_of_means_interval(samples: list[np.ndarray]) -> tuple[float, float, float]:
    """The mean of the samples' means (e.g. of per-track success rates) and its 95 % percentile interval from a
    bootstrap stratified over the samples (scipy resamples each one separately): ``(point, low, high)``."""
    point = float(np.mean([s.mean() for s in samples]))
    if all(np.all(s == s[0]) for s in samples):  # no spread at all: every resample gives the point itself
        return point, point, point
    result = bootstrap(
        samples,
        lambda *s, axis=-1: np.mean([x.mean(axis=axis) for x in s], axis=0),
        n_resamples=BOOTSTRAP_RESAMPLES,
        confidence_level=0.95,
        method="percentile",
        rng=np.random.default_rng(BOOTSTRAP_SEED),
    )
    return point, float(result.confidence_interval.low), float(result.confidence_interval.high)


def probability_of_improvement(
    x: Sequence[dict[str, Any]], y: Sequence[dict[str, Any]], ids: Sequence[str]
) -> dict[str, float]:
    """P(an episode of X succeeds where one of Y does not) + half the ties, averaged over ``ids`` (rliable's
    probability of improvement, a Mann–Whitney U / (n·m) per track, here over evaluation episodes), with a 95 %
    percentile interval from scipy's bootstrap resampling each entry's episodes within each track (tests check
    the closed form against ``scipy.stats.mannwhitneyu``)."""
    samples = []
    for env_id in ids:
        samples.append(np.array([float(r["success"]) for r in x if r["env_id"] == env_id]))
        samples.append(np.array([float(r["success"]) for r in y if r["env_id"] == env_id]))

    def statistic(*arrays: np.ndarray, axis: int = -1) -> np.ndarray:
        per_track = []
        for a, b in zip(arrays[::2], arrays[1::2], strict=True):
            # P(X > Y) + P(X = Y) / 2 for 0/1 outcomes, vectorised over bootstrap resamples.
            pa, pb = a.mean(axis=axis), b.mean(axis=axis)
            per_track.append(pa * (1 - pb) + 0.5 * (pa * pb + (1 - pa) * (1 - pb)))
        return np.mean(per_track, axis=0)

    point = float(statistic(*samples))
    if all(np.all(a == a[0]) for a in samples):
        return {"p": point, "low": point, "high": point}
    result = bootstrap(samples, statistic, n_resamples=BOOTSTRAP_RESAMPLES, confidence_level=0.95,
                       method="percentile", rng=np.random.default_rng(BOOTSTRAP_SEED))  # fmt: skip
    return {"p": point, "low": float(result.confidence_interval.low), "high": float(result.confidence_interval.high)}
