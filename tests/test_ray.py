"""The Ray backend of the evaluator: same records as the local backend, lost workers retried, a clear error
without Ray. The tests marked ``ray`` start one local Ray instance of 2 CPUs and run on their own
(``.ci/run``: ``pytest -m ray -p no:xdist``), never two instances at a time under xdist."""

from __future__ import annotations

import json
import sys
import textwrap
from collections import Counter
from pathlib import Path

import pandas as pd
import pytest

from racebench.cli import main
from racebench.evaluation import EVAL_SEED_BASE, Evaluator, load_records
from racebench.evaluation.ray_backend import INSTALL_HINT, RayOptions
from racebench.evaluation.records import read_folder


def test_ray_backend_without_ray_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError, as when not installed
    argv = ["evaluate", "--agent", "hover", "--envs", "RaceObs-S-Level1-v0", "--episodes", "1"]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--out", str(tmp_path / "o"), "--backend", "ray"])
    message = str(exit_info.value.code)
    assert INSTALL_HINT in message and "\n" not in message
    assert not (tmp_path / "o").exists(), "nothing may run before the missing extra is reported"


def test_bad_ray_options_are_named(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    with pytest.raises(ValueError, match="backend must be one of"):
        Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=1, out_dir=tmp_path, backend="dask")
    with pytest.raises(ValueError, match="episodes per Ray task must be >= 1"):
        Evaluator("hover", ["RaceObs-S-Level1-v0"], 1, tmp_path, backend="ray", ray_options=RayOptions(task_episodes=0))
    with pytest.raises(SystemExit, match="Ray task CPUs must be > 0"):
        main(["evaluate", "--agent", "hover", "--out", str(tmp_path), "--backend", "ray", "--task-cpus", "0"])
    with pytest.raises(SystemExit, match="max_retries must be >= 0"):
        main(["evaluate", "--agent", "hover", "--out", str(tmp_path), "--backend", "ray", "--max-retries", "-1"])
    with pytest.raises(SystemExit, match="--address needs --backend ray"):
        main(["evaluate", "--agent", "hover", "--out", str(tmp_path), "--address", "auto"])


@pytest.mark.ray
def test_ray_evaluation_writes_the_records_of_the_local_backend(ray_cluster, tmp_path: Path) -> None:
    envs = ["RaceObs-S-v0", "RaceObs-J-v0"]
    Evaluator("planner", envs, episodes=2, out_dir=tmp_path / "local").run(progress=False)
    ray_eval = Evaluator("planner", envs, episodes=2, out_dir=tmp_path / "ray", backend="ray")
    summary = ray_eval.run(progress=False)
    local, remote = (read_folder(tmp_path / side).lines for side in ("local", "ray"))
    assert len(local) == 4 and sorted(remote) == sorted(local)  # same episode slots
    assert not list((tmp_path / "ray").glob("records-*.jsonl"))  # the workers' and the driver's shards merged
    outcome = ["success", "lap_time", "crashed", "crash_reason", "gates_passed", "return", "steps", "error"]
    for name, data in local.items():
        mine, theirs = json.loads(data), json.loads(remote[name])
        assert [mine[k] for k in outcome] == [theirs[k] for k in outcome], name  # bit-identical floats
        assert mine == theirs, name  # same machine and checkout: the whole sealed record is the same
    assert summary["n"].tolist() == [2, 2]
    for name in ("episodes.csv", "summary.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "local" / name), pd.read_csv(tmp_path / "ray" / name))
    # Resume is the local one: a Ray evaluation of the same folder finds nothing to do.
    assert Evaluator("planner", envs, episodes=2, out_dir=tmp_path / "ray", backend="ray").pending() == []


DIES_ONCE = textwrap.dedent(
    """
    import os
    import signal
    from pathlib import Path

    import numpy as np

    MARKER = Path({marker!r})
    LOG = Path({log!r})
    KILL_SEED = {kill_seed}


    class DiesOnce:
        \"\"\"Kills its own (Ray worker) process in episode KILL_SEED the first time; logs every episode begun.\"\"\"

        obs_mode = "state"

        def reset(self, env=None, seed=None):
            self.seed = seed
            with LOG.open("a") as f:
                f.write(f"{{seed}}\\n")

        def act(self, obs):
            if self.seed == KILL_SEED and not MARKER.exists():
                MARKER.touch()
                os.kill(os.getpid(), signal.SIGKILL)
            return np.zeros(4)
    """
)


@pytest.mark.ray
def test_a_killed_ray_worker_is_retried_without_losing_or_duplicating_a_record(ray_cluster, tmp_path: Path) -> None:
    marker, log = tmp_path / "killed-once", tmp_path / "episodes.log"
    kill_seed = EVAL_SEED_BASE + 1  # the second episode of the first task: the first is already recorded
    agent = tmp_path / "dies_once.py"
    agent.write_text(DIES_ONCE.format(marker=str(marker), log=str(log), kill_seed=kill_seed))
    out = tmp_path / "out"
    evaluator = Evaluator(
        f"{agent}:DiesOnce", ["RaceObs-S-Level1-v0"], episodes=4, out_dir=out, trust_code=True, backend="ray",
        ray_options=RayOptions(task_episodes=2, max_retries=2),
    )  # fmt: skip
    evaluator.run(progress=False)
    assert marker.exists(), "the worker was never killed: the test tested nothing"
    begun = Counter(int(line) for line in log.read_text().split())
    seeds = [EVAL_SEED_BASE + i for i in range(4)]
    # The retried task re-flew only the killed episode: the one recorded before the kill was kept.
    assert begun == Counter({seeds[0]: 1, seeds[1]: 2, seeds[2]: 1, seeds[3]: 1})
    assert sorted(p.name for p in out.iterdir()) == ["episodes.csv", "records.jsonl", "summary.csv"]  # merged
    assert sorted(json.loads(line)["seed"] for line in (out / "records.jsonl").read_text().splitlines()) == seeds
    frame = load_records(out)
    assert frame["seed"].tolist() == seeds and not frame["crash_reason"].isin(["agent_error", "env_error"]).any()
