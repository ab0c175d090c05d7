"""The cost of the Ray engine on one machine: planner evaluation throughput, Ray backend vs local backend.

Both backends get one CPU and are warm (agent built, numba code compiled, Ray already running, as on a
cluster), and fly the same episodes, alternately, ``--repeats`` times; the per-episode overhead is the
difference of the median wall times over the episodes. Used for the figures of docs/ray.md::

    PYTHONPATH=. python scripts/ray_overhead.py --episodes 20
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path


def measure(episodes: int, env_id: str, repeats: int) -> dict[str, list[float]]:
    """Wall seconds of ``repeats`` evaluations of ``episodes`` planner episodes per backend (first: warm-up)."""
    import ray

    from racebench.evaluation import Evaluator

    times: dict[str, list[float]] = {"local": [], "ray": []}
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for _ in range(repeats + 1):
                for backend in times:
                    evaluator = Evaluator(
                        "planner", [env_id], episodes=episodes, workers=1, out_dir=Path(tmp) / backend, force=True,
                        backend=backend,
                    )  # fmt: skip
                    evaluator.run(progress=False)
                    times[backend].append(evaluator.elapsed)
    finally:
        ray.shutdown()
    return {backend: values[1:] for backend, values in times.items()}  # the first round warms both up


def main() -> None:
    """Print each backend's episodes/s and the Ray engine's overhead per episode."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--env", default="RaceObs-S-v0")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    times = measure(args.episodes, args.env, args.repeats)
    for backend, values in times.items():
        rates = ", ".join(f"{args.episodes / t:.2f}" for t in values)
        print(f"{backend}: {statistics.median(values):.2f} s median for {args.episodes} episodes ({rates} episodes/s)")
    extra = (statistics.median(times["ray"]) - statistics.median(times["local"])) / args.episodes
    print(f"Ray overhead: {1000 * extra:.0f} ms per episode")


if __name__ == "__main__":
    main()
