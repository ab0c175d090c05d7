"""Smoke test of the throughput benchmark: ``racebench bench --quick`` runs every measurement and writes them."""

from __future__ import annotations

import csv

from racebench.cli import main
from racebench.envs.perturbations import ROBUSTNESS


def test_bench_quick_writes_every_measurement(tmp_path, capsys) -> None:
    out = tmp_path / "bench.csv"
    assert main(["bench", "--quick", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "load average" in printed and "skipped (--quick)" in printed
    assert "MISSED" not in printed and "targets (2 cores)" not in printed  # no verdicts on tiny sizes
    rows = list(csv.DictReader(out.open()))
    values = {row["name"]: float(row["value"]) for row in rows}
    assert {row["section"] for row in rows} == {"depth", "steps", "cpu", "robustness", "parts", "memory", "run"}
    assert values["wall time"] > 0
    for name in (
        "pybullet getCameraImage (TinyRenderer)",
        "raycast, one camera per call",
        "single env, state",
        "single env, vision, raycast",
        "vector env, state, 4 envs, 1 process",
        "vector env, state, 4 envs, 2 processes",
        "vector env, vision, 4 envs, 1 process",
        "vector env, vision, 4 envs, 2 processes",
        "peak RSS, this process",
        "peak RSS, largest worker process",
        "collision check (swept sphere, 1 substep)",
        "RaceObs-S-v0, vision, raycast",
        *(f"RaceObs-S-{name}-v0, vision, raycast" for name in ROBUSTNESS),
        *(f"cost {name} / main, per step" for name in ROBUSTNESS),
        *(f"cost {name} / main, per second flown" for name in ROBUSTNESS),
    ):
        assert values[name] > 0, name
    # Even a tiny run shows the ray caster well ahead, on the same poses, with the same image.
    assert values["ratio raycast (per call) / pybullet"] > 2
    assert values["agreement: mean |d inverse depth|"] <= 0.01
    assert values["agreement: pixels within 2 %"] >= 98


def test_bench_quick_stays_a_smoke_test() -> None:
    """--quick stays quick by its sizes (a wall-clock bound would fail on a busy machine: benchmarks measure,
    tests check): no evaluation or training, and every measurement a few hundred steps at most."""
    from racebench.benchmark import BenchSettings

    quick, full = BenchSettings.quick(), BenchSettings()
    assert not quick.evaluation_and_training and quick.train_small
    assert quick.scenes * quick.poses_per_scene <= 50 and quick.single_steps <= 100
    assert quick.vector_envs * quick.vector_steps <= 100 and quick.eval_episodes <= 4
    assert quick.single_steps * 10 <= full.single_steps  # a tenth of a real run's work or less
