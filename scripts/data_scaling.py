"""How many DAgger steps would a student need to reach a success target? A logistic fit of success on log2(steps).

    python scripts/data_scaling.py --target 0.95 \\
        500000:baselines/experiments/distill-slow-beta/S/eval \\
        750000:baselines/experiments/distill-more-data/S/eval \\
        1000000:baselines/experiments/distill-more-data-1m/S/eval

Each argument is ``STEPS:FOLDER``: one student of a run (the same run resumed to more steps) and its evaluation
(``episodes.csv``, as ``racebench evaluate --out`` writes it). Per ``env_id`` the script fits, by maximum
likelihood, ``logit P(success) = a + b * log2(steps)`` over every episode, and solves it for the steps at which the
fitted success rate reaches ``--target``. The model rises to 1, so it is optimistic near a ceiling (a teacher that
fails some scenes caps its student below 1): read the projection as a lower bound on the steps needed.

The evaluations fly the same scenes at every step count (the seed protocol), so episodes are not independent. The
95 % interval resamples scenes, not episodes (a cluster bootstrap: each drawn seed brings its outcome at every step
count); a replicate whose slope is not positive never reaches the target and counts as infinitely many steps.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import minimize
from scipy.special import expit, logit


def load_points(points: list[str]) -> pd.DataFrame:
    """The episodes of every ``STEPS:FOLDER`` argument with a ``steps`` column; exits naming a bad argument."""
    frames = []
    for point in points:
        steps, _, folder = point.partition(":")
        if not steps.isdigit() or int(steps) <= 0 or not folder:
            raise SystemExit(f"data_scaling: {point!r} is not STEPS:FOLDER (e.g. 500000:runs/x/eval)")
        path = Path(folder) / "episodes.csv"
        if not path.is_file():
            raise SystemExit(f"data_scaling: {path} does not exist (pass an evaluation's --out folder)")
        try:
            frame = pd.read_csv(path, usecols=["env_id", "seed", "success"])
        except ValueError as exc:  # a missing column, or a file that is not CSV
            raise SystemExit(f"data_scaling: {path} is not an evaluation's episodes.csv ({exc})") from None
        frames.append(frame.assign(steps=int(steps)))
    data = pd.concat(frames, ignore_index=True)
    if data["steps"].nunique() < 2:
        raise SystemExit("data_scaling: a slope needs evaluations at two or more step counts")
    return data


def fit_logistic(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood ``(a, b)`` of ``P(y = 1) = expit(a + b x)``."""

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        z = theta[0] + theta[1] * x
        # -log-likelihood, written with logaddexp so that a separable sample does not overflow
        value = float(np.sum(np.logaddexp(0.0, z) - y * z))
        residual = expit(z) - y
        return value, np.array([residual.sum(), (residual * x).sum()])

    start = np.array([logit(np.clip(y.mean(), 0.01, 0.99)), 0.0])
    return tuple(minimize(loss, start, jac=True, method="BFGS").x)


def steps_to_target(a: float, b: float, target: float) -> float:
    """The steps at which ``expit(a + b log2(steps))`` equals ``target`` (infinite if the fit does not rise)."""
    if b <= 0:
        return float("inf")
    return float(2.0 ** ((logit(target) - a) / b))


def project(
    data: pd.DataFrame, target: float, replicates: int, seed: int, predict: tuple[int, ...] = ()
) -> pd.DataFrame:  # fmt: skip
    """One row per ``env_id``: the observed rates, the fitted gain per doubling, the projected steps with a
    scene-bootstrap 95 % interval, and for each step count in ``predict`` the fitted rate there (``fit_<steps>``,
    ``fit_<steps>_low``, ``fit_<steps>_high``): a prediction a longer run can check."""
    rng = np.random.default_rng(seed)
    rows = []
    for env_id, frame in data.groupby("env_id"):
        table = frame.pivot_table(index="seed", columns="steps", values="success", aggfunc="first").dropna()
        counts = np.array(table.columns, dtype=float)
        x = np.tile(np.log2(counts), len(table))
        outcomes = table.to_numpy(dtype=float)
        a, b = fit_logistic(x, outcomes.reshape(-1))
        fits = [
            fit_logistic(x, outcomes[rng.integers(0, len(table), len(table))].reshape(-1)) for _ in range(replicates)
        ]
        ends = int(0.025 * replicates), int(np.ceil(0.975 * replicates)) - 1  # percentiles by rank (inf - inf is nan)
        draws = np.sort([steps_to_target(ai, bi, target) for ai, bi in fits])
        row = {"env_id": env_id, "scenes": len(table), **{f"sr_{c}": float(table[c].mean()) for c in table.columns}}
        top = counts.max()
        # fitted points gained by the last doubling observed, at the largest step count's fitted rate
        row["gain_per_doubling"] = float(expit(a + b * np.log2(top)) - expit(a + b * np.log2(top / 2)))
        row["steps_to_target"] = steps_to_target(a, b, target)
        row["ci_low"], row["ci_high"] = float(draws[ends[0]]), float(draws[ends[1]])
        for steps in predict:
            rates = np.sort([expit(ai + bi * np.log2(steps)) for ai, bi in fits])
            row[f"fit_{steps}"] = float(expit(a + b * np.log2(steps)))
            row[f"fit_{steps}_low"], row[f"fit_{steps}_high"] = float(rates[ends[0]]), float(rates[ends[1]])
        rows.append(row)
    return pd.DataFrame(rows)


def format_number(value: float) -> str:
    """Rates with three decimals, step counts with thousands separators, beyond 1e9 steps in scientific notation."""
    if abs(value) < 10:
        return f"{value:.3f}"
    return f"{value:,.0f}" if abs(value) < 1e9 else f"{value:.1e}"


def main() -> None:
    """Print the projection table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("points", nargs="+", help="STEPS:FOLDER, one per evaluated student of the run")
    parser.add_argument("--target", type=float, default=0.95, help="success rate to reach (default 0.95)")
    parser.add_argument("--replicates", type=int, default=2000, help="bootstrap replicates (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="bootstrap random seed")
    parser.add_argument("--predict", default="", help="step counts, comma-separated, to print the fitted rate at")
    args = parser.parse_args()
    try:
        predict = tuple(int(steps) for steps in args.predict.split(",") if steps)
    except ValueError:
        raise SystemExit(
            f"data_scaling: --predict takes step counts separated by commas, got {args.predict!r}"
        ) from None
    if args.replicates < 40:
        raise SystemExit(f"data_scaling: --replicates must be at least 40 for a 95 % interval, got {args.replicates}")
    if not 0.0 < args.target < 1.0:
        raise SystemExit(f"data_scaling: --target must lie strictly between 0 and 1, got {args.target}")
    table = project(load_points(args.points), args.target, args.replicates, args.seed, predict)
    print(f"steps for a fitted success rate of {args.target:.2f} (95 % scene-bootstrap interval; inf: never)")
    print(table.to_string(index=False, float_format=format_number))


if __name__ == "__main__":
    main()
