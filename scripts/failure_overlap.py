"""Do several agents fail the same scenes? Per-scene failure counts across evaluations against independence.

    python scripts/failure_overlap.py EVAL_DIR EVAL_DIR [EVAL_DIR ...] [--permutations 2000] [--seed 0]

Each folder is an evaluation's output (``episodes.csv``); episodes are matched by ``(env_id, seed)``, i.e. the same
scene under the seed protocol, and only scenes every evaluation flew count. Per env id it prints how many scenes
k of the agents failed, for k = 0..agents, beside what independent failures would give: each agent's outcomes
shuffled across the scenes (its success rate kept), averaged over ``--permutations`` shuffles. The test statistic is
the variance of the per-scene failure count (failures piling up on some scenes raise it); its p-value is the share of
shuffles at least as extreme (one-sided, with the +1 correction). Then the "hard core": the scenes every agent
failed, with what ended them. Why: if the students of different seeds and recipes fail the same scenes, what limits
them is in those scenes (what the camera shows there, the layout), not the optimiser's noise, and more of the
same training will not fix it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd


def load(folder: Path) -> pd.DataFrame:
    """The evaluation's episodes; exits naming the folder if it holds none."""
    path = folder / "episodes.csv"
    if not path.is_file():
        raise SystemExit(f"failure_overlap: {path} does not exist (pass an evaluation's --out folder)")
    return pd.read_csv(path)


def overlap(outcomes: np.ndarray, permutations: int, rng: np.random.Generator) -> dict:
    """``outcomes`` (scenes, agents) booleans, True = finished. Returns the observed and independence-expected
    counts of scenes by number of failing agents, the per-scene failure-count variance and its permutation p."""
    failed = ~outcomes
    counts = failed.sum(axis=1)
    agents = outcomes.shape[1]
    observed = np.bincount(counts, minlength=agents + 1)
    expected = np.zeros(agents + 1)
    extreme = 0
    for _ in range(permutations):
        shuffled = np.column_stack([rng.permutation(failed[:, j]) for j in range(agents)]).sum(axis=1)
        expected += np.bincount(shuffled, minlength=agents + 1)
        extreme += shuffled.var() >= counts.var() - 1e-12
    return {"observed": observed, "expected": expected / permutations, "variance": float(counts.var()),
            "p": (extreme + 1) / (permutations + 1)}  # fmt: skip


def main() -> None:
    """Print per env id the failure-count table, the dispersion test and the scenes every agent failed."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="evaluation folders (at least two)")
    parser.add_argument("--permutations", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0, help="of the shuffles")
    args = parser.parse_args()
    if len(args.folders) < 2:
        raise SystemExit("failure_overlap: pass at least two evaluation folders")
    frames = [load(f).set_index(["env_id", "seed"]) for f in args.folders]
    success = pd.concat([f["success"].astype(bool) for f in frames], axis=1, join="inner", keys=range(len(frames)))
    if success.empty:
        raise SystemExit("failure_overlap: the evaluations share no (env_id, seed) episode")
    reasons = pd.concat([f["crash_reason"].fillna("timeout").str.split(":").str[0] for f in frames], axis=1,
                        keys=range(len(frames)))  # fmt: skip
    rng = np.random.default_rng(args.seed)
    agents = len(frames)
    for env_id, block in success.groupby(level="env_id"):
        result = overlap(block.to_numpy(), args.permutations, rng)
        rates = ", ".join(f"{100 * r:.0f} %" for r in block.mean())
        print(f"{env_id}: {agents} agents on {len(block)} shared scenes (success {rates})")
        print("  agents failing a scene:  " + "  ".join(f"{k:>5}" for k in range(agents + 1)))
        print("  scenes, observed:        " + "  ".join(f"{v:>5}" for v in result["observed"]))
        print("  scenes, if independent:  " + "  ".join(f"{v:>5.1f}" for v in result["expected"]))
        print(f"  variance of failures per scene {result['variance']:.2f}; permutation p = {result['p']:.4f} "
              f"({args.permutations} shuffles)")  # fmt: skip
        core = block.index[(~block).all(axis=1)]
        if len(core):
            ends = reasons.loc[core].stack().value_counts()
            scenes = f"{len(core)} scene" + ("s" if len(core) != 1 else "")
            print(f"  failed by all {agents}: {scenes}, seeds {', '.join(str(s) for _, s in core)}; "
                  f"ended by {({k: int(v) for k, v in ends.items()})}")  # fmt: skip


if __name__ == "__main__":
    main()
