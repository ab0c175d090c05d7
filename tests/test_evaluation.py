"""The evaluator: statistics, resumable sweeps, failing agents, loaders, tables."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

from racebench.agents import AgentLoadError, OnnxAgent, SB3Agent, export_onnx, load_agent
from racebench.evaluation import (
    EVAL_SEED_BASE,
    SUITES,
    Evaluator,
    eval_seeds,
    load_records,
    paired_comparison,
    read_summaries,
    resolve_envs,
    split_env_id,
    wilson_interval,
)
from racebench.evaluation.records import atomic_write, name_of, read_folder, read_trajectories, validate_record
from racebench.reporting.tables import make_table

# ------------------------------------------------------------------ statistics


@pytest.mark.parametrize(
    "k, n, low, high",
    [
        # Newcombe (1998), Statistics in Medicine 17:857, Table I, method 3 (Wilson score, no correction).
        (81, 263, 0.2553, 0.3662),
        (15, 148, 0.0624, 0.1605),
        (0, 20, 0.0000, 0.1611),
        (1, 29, 0.0061, 0.1718),
        # The paper's 10 trials: 10/10 and 0/10.
        (10, 10, 0.7225, 1.0000),
        (0, 10, 0.0000, 0.2775),
    ],
)
def test_wilson_interval_matches_textbook_values(k: int, n: int, low: float, high: float) -> None:
    got = wilson_interval(k, n)
    assert got == pytest.approx((low, high), abs=6e-5)


def test_seed_protocol_and_suites() -> None:
    assert eval_seeds(3) == [EVAL_SEED_BASE, EVAL_SEED_BASE + 1, EVAL_SEED_BASE + 2]
    assert resolve_envs(["main"]) == ["RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-v0"]
    assert len(resolve_envs(["paper"])) == 3 + 12 + 12
    assert len(SUITES["density"]) == 12 and len(SUITES["gates"]) == 12
    assert split_env_id("RaceObs-J-GateShift0.7-v0") == ("J", "GateShift0.7")
    assert split_env_id("RaceObs-Circle-v0") == ("Circle", "default")
    with pytest.raises(ValueError, match="unknown env id or suite 'RaceObs-X-v0'"):
        resolve_envs(["RaceObs-X-v0"])


# -------------------------------------------------------------- failing agents

BAD_AGENTS = textwrap.dedent(
    """
    import numpy as np

    class Raises:
        obs_mode = "state"
        def reset(self, env=None, seed=None):
            self.t = 0
        def act(self, obs):
            self.t += 1
            if self.t > 3:
                raise RuntimeError("policy exploded")
            return np.zeros(4)

    class ReturnsNaN:
        obs_mode = "state"
        def reset(self, env=None, seed=None):
            pass
        def act(self, obs):
            return np.array([0.0, np.nan, 0.0, 0.0])

    class WrongShape:
        obs_mode = "vision"
        def reset(self, env=None, seed=None):
            pass
        def act(self, obs):
            assert obs["depth"].shape == (1, 64, 64)
            return np.zeros(3)

    class NoAct:
        def reset(self, env=None, seed=None):
            pass
    """
)


@pytest.fixture()
def bad_agents(tmp_path: Path) -> Path:
    path = tmp_path / "bad_agents.py"
    path.write_text(BAD_AGENTS)
    return path


@pytest.mark.parametrize(
    "cls, reason",
    [("Raises", "act raised RuntimeError: policy exploded"), ("ReturnsNaN", "not finite"), ("WrongShape", "shape")],
)
def test_failing_agent_fails_its_episodes_and_the_sweep_goes_on(
    tmp_path: Path, bad_agents: Path, cls: str, reason: str
) -> None:
    out = tmp_path / "out"
    summary = Evaluator(f"{bad_agents}:{cls}", ["RaceObs-S-Level1-v0"], episodes=2, out_dir=out, trust_code=True).run(
        progress=False
    )
    assert summary["n"].tolist() == [2] and summary["successes"].tolist() == [0]
    episodes = pd.read_csv(out / "episodes.csv")
    assert (episodes["crash_reason"] == "agent_error").all()
    assert episodes["error"].str.contains(reason).all()


def test_bad_agent_specs_are_named(tmp_path: Path, bad_agents: Path) -> None:
    with pytest.raises(AgentLoadError, match="unknown agent spec 'pilot'"):
        load_agent("pilot")
    with pytest.raises(AgentLoadError, match="no method act"):
        load_agent(f"{bad_agents}:NoAct", trust_code=True)
    with pytest.raises(AgentLoadError, match="has no attribute 'Nope'"):
        load_agent(f"{bad_agents}:Nope", trust_code=True)
    with pytest.raises(AgentLoadError, match="does not exist"):
        load_agent(str(tmp_path / "missing.zip"))
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"PK\x03\x04 this is not really a checkpoint")
    with pytest.raises(AgentLoadError, match="corrupt.zip"):
        load_agent(str(corrupt), trust_code=True)
    broken_onnx = tmp_path / "broken.onnx"
    broken_onnx.write_bytes(b"\x00\x01garbage")
    with pytest.raises(AgentLoadError, match="broken.onnx"):
        load_agent(str(broken_onnx))


# --------------------------------------------------------------------- resume


def test_resume_skips_finished_episodes(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    first = Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=2, out_dir=out)
    first.run(progress=False)
    before = read_folder(out).lines
    second = Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=3, out_dir=out)
    assert second.pending() == [("RaceObs-S-Level1-v0", EVAL_SEED_BASE + 2)]
    second.run(progress=False)
    after = read_folder(out).lines
    assert {name: after[name] for name in before} == before  # finished episodes untouched
    assert len(pd.read_csv(out / "episodes.csv")) == 3 and len(after) == 3


def test_a_complete_rerun_prints_no_empty_progress_bar(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from racebench import cli

    argv = ["evaluate", "--agent", "hover", "--envs", "RaceObs-S-Level1-v0", "--episodes", "1", "--out",
            str(tmp_path / "eval")]  # fmt: skip
    assert cli.main(argv) == 0
    assert "1/1" in capsys.readouterr().err  # the first run's bar
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    assert "0ep" not in err and "ep/s" not in err and "it/s" not in err  # was "hover: 0ep [00:00, ?ep/s]" twice
    assert "1/1 episodes already done" in out and ", 0 to run" in out  # the one line that says so


def _shard_lines(out: Path) -> list[bytes]:
    return [line for shard in out.glob("records-*.jsonl") for line in shard.read_bytes().splitlines(keepends=True)]


def test_a_killed_sweep_loses_only_the_episodes_in_flight(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """SIGKILL of a two-worker evaluation (spawned processes, each appending to its own shard) mid-run, a torn
    last line as a kill mid-write leaves it; the resume keeps every whole line, re-runs the rest, counts right."""
    out = tmp_path / "killed"
    script = (
        "from racebench.evaluation import Evaluator\n"
        f"Evaluator('planner', ['RaceObs-S-Level1-v0'], episodes=40, out_dir={str(out)!r}, workers=2)"
        ".run(progress=False)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    deadline = time.time() + 180
    # Until both workers have written: two processes appending at once is what could interleave lines.
    while time.time() < deadline and (
        len([x for x in _shard_lines(out) if x.endswith(b"\n")]) < 3 or len(list(out.glob("records-*.jsonl"))) < 2
    ):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "records.jsonl").exists(), "the sweep should have been killed part-way"
    shards = sorted(out.glob("records-*.jsonl"))
    whole = [line for line in _shard_lines(out) if line.endswith(b"\n")]
    assert 3 <= len(whole) < 40 and len(shards) == 2  # one shard per worker process, never a shared file
    for line in whole:
        validate_record(json.loads(line))  # no two processes' lines interleaved
    # A kill in the middle of a write: the shard's last line cut off (each line is one write, so only the last).
    victim = shards[0]
    if victim.read_bytes().endswith(b"\n"):  # unless the kill itself cut a write off, cut one off as it would
        with victim.open("ab") as f:
            f.write(whole[0][: len(whole[0]) // 2])
    kept = [line for line in _shard_lines(out) if line.endswith(b"\n")]
    with caplog.at_level(logging.WARNING, logger="racebench"):
        resumed = Evaluator("planner", ["RaceObs-S-Level1-v0"], episodes=40, out_dir=out)
    assert "torn record line dropped" in caplog.text
    assert not list(out.glob("records-*.jsonl")) and not (out / "invalid.jsonl").exists()
    merged = (out / "records.jsonl").read_bytes().splitlines(keepends=True)
    assert set(kept) <= set(merged) and len(merged) == len(set(kept))  # every finished episode kept, once
    assert len(resumed.pending()) == 40 - len(merged)
    resumed.run(progress=False)
    frame = load_records(out)
    assert len(frame) == 40 and frame["seed"].is_unique and frame["success"].all()
    assert set(kept) <= set((out / "records.jsonl").read_bytes().splitlines(keepends=True))


def test_the_old_layout_is_read_and_migrated_on_resume(tmp_path: Path) -> None:
    """A folder of one JSON file per record (before records.jsonl) still counts, and a resume converts it."""
    out = tmp_path / "old"
    Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=2, out_dir=out, save_trajectories=True).run(progress=False)
    found = read_folder(out)
    flights = read_trajectories(out)
    for name, record in found.records.items():  # as the old RecordWriter wrote them
        atomic_write(out / "records" / name, json.dumps(record, indent=1))
    (out / "trajectories").mkdir()
    for row, positions, scene in flights:
        np.savez_compressed(out / "trajectories" / name_of(row).replace(".json", ".npz"), positions=positions,
                            scene=json.dumps(scene), row=json.dumps(row))  # fmt: skip
    (out / "records.jsonl").unlink()
    (out / "trajectories.npz").unlink()
    assert load_records(out)["digest"].tolist() == [
        r["digest"] for r in sorted(found.records.values(), key=lambda r: r["seed"])
    ]
    assert [r for r, _, _ in read_trajectories(out)] == [r for r, _, _ in flights]
    resumed = Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=3, out_dir=out, save_trajectories=True)
    assert len(resumed.pending()) == 1 and not (out / "records").exists() and not (out / "trajectories").exists()
    resumed.run(progress=False)
    assert len(read_folder(out).records) == 3 and len(read_trajectories(out)) == 3


# -------------------------------------------------------------------- loaders


@pytest.fixture(scope="module")
def tiny_ppo(tmp_path_factory: pytest.TempPathFactory):
    from stable_baselines3 import PPO

    env = gym.make("RaceObs-S-Level1-v0", obs_mode="state")
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0,
                policy_kwargs={"net_arch": [16]}, device="cpu")  # fmt: skip
    model.learn(128)
    path = tmp_path_factory.mktemp("ppo") / "tiny_ppo.zip"
    model.save(path)
    return model, path


def test_sb3_checkpoint_round_trip(tiny_ppo) -> None:
    model, path = tiny_ppo
    agent = load_agent(str(path), trust_code=True)
    assert isinstance(agent, SB3Agent) and agent.obs_mode == "state" and agent.name == "tiny_ppo"
    obs = np.random.default_rng(0).uniform(-1, 1, size=(5, 17)).astype(np.float32)
    agent.reset()
    for o in obs:
        np.testing.assert_array_equal(agent.act(o), model.predict(o, deterministic=True)[0])


def test_worker_processes_give_the_same_episodes(tiny_ppo, tmp_path: Path) -> None:
    """``workers=2`` (spawned processes, after torch ran in this one) records what one process records."""
    _, path = tiny_ppo
    envs = ["RaceObs-S-Level1-v0", "RaceObs-S-v0"]
    Evaluator(str(path), envs, episodes=2, out_dir=tmp_path / "one", trust_code=True).run(progress=False)
    pool_run = threading.Thread(  # a deadlocked pool fails the test instead of hanging the suite
        target=Evaluator(str(path), envs, episodes=2, out_dir=tmp_path / "two", workers=2, trust_code=True).run,
        kwargs={"progress": False},
        daemon=True,
    )
    pool_run.start()
    pool_run.join(timeout=180)
    assert not pool_run.is_alive(), "the worker pool hung"
    columns = ["env_id", "seed", "success", "crash_reason", "gates_passed", "return", "steps"]
    one = pd.read_csv(tmp_path / "one" / "episodes.csv")[columns]
    two = pd.read_csv(tmp_path / "two" / "episodes.csv")[columns]
    pd.testing.assert_frame_equal(one, two)


def test_onnx_export_round_trip(tiny_ppo, tmp_path: Path) -> None:
    model, _ = tiny_ppo
    path = export_onnx(model, tmp_path / "tiny.onnx")
    agent = load_agent(str(path))
    assert isinstance(agent, OnnxAgent) and agent.obs_mode == "state"
    agent.reset()
    for o in np.random.default_rng(1).uniform(-1, 1, size=(5, 17)).astype(np.float32):
        np.testing.assert_allclose(agent.act(o), model.predict(o, deterministic=True)[0], atol=1e-5)


def test_policy_only_export_keeps_the_policy_and_drops_the_optimizer(tiny_ppo, tmp_path: Path) -> None:
    import torch

    from racebench.agents import export_policy

    model, path = tiny_ppo
    optimizer = model.policy.optimizer
    out = export_policy(model, tmp_path / "policy.zip")
    assert model.policy.optimizer is optimizer and optimizer.state  # the model keeps its Adam moments
    with zipfile.ZipFile(out) as archive:
        assert torch.load(io.BytesIO(archive.read("policy.optimizer.pth")))["state"] == {}
        assert "_last_obs" not in json.loads(archive.read("data"))
    agent = load_agent(str(out), trust_code=True)
    for o in np.random.default_rng(2).uniform(-1, 1, size=(5, 17)).astype(np.float32):
        np.testing.assert_array_equal(agent.act(o), model.predict(o, deterministic=True)[0])
    with pytest.raises(ValueError, match="not 'x.onnx'"):
        export_policy(model, "x.onnx")


def test_export_policy_cli_on_the_gru_checkpoint(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import torch
    from sb3_contrib import RecurrentPPO

    from racebench import cli

    # A training checkpoint of the shipped GRU policy: the committed one is policy-only already, so give it Adam's
    # moments back (one step on zero gradients: the moments exist, the weights do not move) and save it whole.
    model = RecurrentPPO.load(Path(__file__).parents[1] / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip",
                              device="cpu")  # fmt: skip
    for parameter in model.policy.parameters():
        parameter.grad = torch.zeros_like(parameter)
    model.policy.optimizer.step()
    checkpoint = tmp_path / "full" / "vision-ppo-S.zip"
    checkpoint.parent.mkdir()
    model.save(checkpoint)
    out = tmp_path / "lean" / "vision-ppo-S.zip"
    assert cli.main(["export-policy", str(checkpoint), "--out", str(out), "--trust-code"]) == 0
    assert "policy sha256" in capsys.readouterr().out
    assert out.stat().st_size < checkpoint.stat().st_size / 2  # Adam's two moments per weight were most of it
    with zipfile.ZipFile(out) as archive:
        assert torch.load(io.BytesIO(archive.read("policy.optimizer.pth")))["state"] == {}
    full, lean = load_agent(str(checkpoint), trust_code=True), load_agent(str(out), trust_code=True)
    env = gym.make("RaceObs-S-v0")
    obs, _ = env.reset(seed=EVAL_SEED_BASE)
    full.reset()
    lean.reset()
    for _ in range(10):
        action = full.act(obs)
        np.testing.assert_array_equal(lean.act(obs), action)
        obs, *_ = env.step(action)
    with pytest.raises(SystemExit, match="is the checkpoint itself"):
        cli.main(["export-policy", str(out), "--out", str(out), "--trust-code"])
    with pytest.raises(SystemExit, match="pass --trust-code"):
        cli.main(["export-policy", str(out), "--out", str(tmp_path / "again.zip")])
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "vecnormalize.pkl").write_bytes(b"stale")
    with pytest.raises(SystemExit, match="would be read as this policy's observation statistics"):
        cli.main(["export-policy", str(checkpoint), "--out", str(tmp_path / "other" / "p.zip"), "--trust-code"])


def test_recurrent_sb3_checkpoint_carries_state(tmp_path: Path) -> None:
    from sb3_contrib import RecurrentPPO

    env = gym.make("RaceObs-S-Level1-v0", obs_mode="state")
    model = RecurrentPPO("MlpLstmPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0,
                         policy_kwargs={"lstm_hidden_size": 8, "net_arch": [8]}, device="cpu")  # fmt: skip
    model.learn(32)
    model.save(tmp_path / "lstm.zip")
    agent = load_agent(str(tmp_path / "lstm.zip"), trust_code=True)
    assert agent.recurrent
    obs = np.random.default_rng(2).uniform(-1, 1, size=(4, 17)).astype(np.float32)
    agent.reset()
    first = [agent.act(o) for o in obs]
    agent.reset()
    again = [agent.act(o) for o in obs]
    np.testing.assert_array_equal(np.array(first), np.array(again))  # reset clears the memory
    state, starts, expected = None, np.ones((1,), dtype=bool), []
    for o in obs:
        action, state = model.predict(o, state=state, episode_start=starts, deterministic=True)
        starts = np.zeros((1,), dtype=bool)
        expected.append(action)
    np.testing.assert_array_equal(np.array(first), np.array(expected))


# -------------------------------------------------------------------- planner


@pytest.mark.parametrize("env_id", ["RaceObs-S-v0", "RaceObs-J-v0", "RaceObs-Circle-v0"])
def test_privileged_planner_flies_the_default_tracks(tmp_path: Path, env_id: str) -> None:
    summary = Evaluator("planner", [env_id], episodes=5, out_dir=tmp_path).run(progress=False)
    assert summary["privileged"].all()
    assert summary["successes"].iloc[0] >= 4, summary.to_dict("records")


# --------------------------------------------------------------------- tables

DATA = Path(__file__).parent / "data"
FIXED_SUMMARY = DATA / "summary_fixed.csv"


def test_tables_bold_only_where_95_percent_intervals_separate() -> None:
    """10/10 against 9/10 is not a result (Wilson [72–100] meets [60–98]); 10/10 against 2/10 is. Lap times:
    bold only where Student's t intervals of the means separate."""
    from racebench.evaluation.statistics import wilson_interval

    def row(agent: str, k: int, lap: float, std: float, privileged: bool = False) -> dict:
        low, high = wilson_interval(k, 10)
        return {"agent": agent, "privileged": privileged, "env_id": "RaceObs-S-v0", "track": "S", "variant": "default",
                "n": 10, "successes": k, "success_rate": k / 10, "sr_ci_low": low, "sr_ci_high": high,
                "lap_time_median": lap, "lap_time_mean": lap, "lap_time_std": std}  # fmt: skip

    close = make_table(pd.DataFrame([row("a", 10, 3.0, 0.5), row("b", 9, 3.1, 0.5)]), "II")
    assert "**" not in close.split("\n", 1)[1]  # nothing bold below the caption
    apart = make_table(
        pd.DataFrame([row("a", 10, 3.0, 0.05), row("b", 2, 4.0, 0.05), row("p", 10, 1.0, 0.01, True)]), "II"
    )
    bold = [cell.strip() for line in apart.splitlines()[4:] for cell in line.split("|") if "**" in cell]
    assert bold == ["**3.00**", "**100 [72–100]**"]  # a's lap and SR; the privileged p's faster lap never
    # An agent without laps (0/10) has no lap time to compare: it does not cancel a's lap-time bold.
    with_zero = make_table(pd.DataFrame([row("a", 10, 3.0, 0.05), row("b", 2, 4.0, 0.05), row("z", 0, 0.0, 0.0)]), "II")
    assert "**3.00**" in with_zero


def test_table_ii_from_a_fixed_csv() -> None:
    expected = (DATA / "table_ii_expected.md").read_text()
    assert make_table(pd.read_csv(FIXED_SUMMARY), "II", "md", ci=False) == expected


def test_seeds_pooled_into_one_row_per_config_with_their_mean_and_range() -> None:
    """``--seeds mean``: a sweep's rows <config>-seed<k> become one row of the seeds' mean success rate, the range over
    the seeds in brackets, and bold only where the worst seed beats every other row's interval."""
    from racebench.evaluation.statistics import wilson_interval
    from racebench.reporting.tables import over_seeds

    def row(agent: str, k: int, lap: float, env: str = "RaceObs-S-v0") -> dict:
        low, high = wilson_interval(k, 10)
        track = env.split("-")[1]
        return {"agent": agent, "privileged": False, "env_id": env, "track": track, "variant": "default", "n": 10,
                "successes": k, "success_rate": k / 10, "sr_ci_low": low, "sr_ci_high": high,
                "lap_time_median": lap, "lap_time_mean": lap, "lap_time_std": 0.1}  # fmt: skip

    j = "RaceObs-J-v0"
    seeds = [row("c-seed0", 9, 3.0), row("c-seed1", 10, 3.2), row("c-seed2", 10, 3.4),
             row("c-seed0", 6, 4.0, j), row("c-seed1", 8, 4.0, j), row("c-seed2", 7, 5.0, j)]  # fmt: skip
    summary = pd.DataFrame([*seeds, row("b", 2, 5.0), row("lone-seed0", 5, 4.0)])
    pooled = over_seeds(summary).set_index(["agent", "env_id"])
    s_cell, j_cell = pooled.loc[("c (3 seeds)", "RaceObs-S-v0")], pooled.loc[("c (3 seeds)", "RaceObs-J-v0")]
    assert (s_cell["n"], s_cell["successes"], s_cell["seeds"]) == (30, 29, 3)
    assert s_cell["success_rate"] == pytest.approx(29 / 30)
    assert (s_cell["sr_ci_low"], s_cell["sr_ci_high"]) == (0.9, 1.0)
    assert s_cell["lap_time_mean"] == pytest.approx(3.2) and j_cell["success_rate"] == pytest.approx(0.7)
    assert pooled.loc[("lone-seed0", "RaceObs-S-v0"), "seeds"] == 1  # one seed: its row, its Wilson interval
    table = make_table(summary, "II", seeds="mean")
    assert "| c (3 seeds) " in table and "c-seed" not in table and "lone-seed0" in table
    assert "**97 [90–100]**" in table  # the worst seed (9/10) beats b (2/10, Wilson [6–51]) and lone (5/10, [24–76])
    assert "70 [60–80]" in table and "'(k seeds)': the mean over k training seeds" in table
    assert "c-seed1" in make_table(summary, "II")  # the default keeps a row per seed
    with pytest.raises(ValueError, match=r"c: RaceObs-J-v0 has results of seeds \[0, 1\], its other ids of \[0, 1"):
        over_seeds(summary.drop(index=5))


def test_table_latex_is_booktabs_with_bold_and_ci() -> None:
    text = make_table(pd.read_csv(FIXED_SUMMARY), "III", "latex", ci=True)
    assert "\\toprule" in text and "\\midrule" in text and "\\bottomrule" in text
    assert "\\textbf{90 [60--98]}" in text
    assert "planner (privileged)" in text


def test_training_curves_figure_from_progress_files(tmp_path: Path) -> None:
    from racebench.reporting.plots import plot_training_curves

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("name: my-run\n")
    pd.DataFrame(
        {
            "timesteps": [2048, 4096, 6144],
            "episodes": [10, 20, 30],
            "mean_return": [-5.0, -1.0, 3.0],
            "success_rate": [0.0, None, 0.5],
            "level": [1, 1, 2],
            "samples_per_s": [1000.0] * 3,
            "wall_s": [2.0, 4.0, 6.0],
        }
    ).to_csv(run / "progress.csv", index=False)
    out = plot_training_curves([run], tmp_path / "curves.png")
    assert out.is_file() and out.stat().st_size > 10_000
    bad = tmp_path / "bad.csv"
    bad.write_text("timesteps,mean_return\n1,2\n")
    with pytest.raises(ValueError, match="missing columns"):
        plot_training_curves([bad], tmp_path / "x.png")
    with pytest.raises(ValueError, match="no progress.csv"):
        plot_training_curves([tmp_path / "nowhere"], tmp_path / "x.png")


# ------------------------------------------------------------- lockstep evaluation


def test_act_batch_is_predict_on_the_stacked_batch(tiny_ppo, tmp_path: Path) -> None:
    from sb3_contrib import RecurrentPPO

    model, path = tiny_ppo
    agent = load_agent(str(path), trust_code=True)
    obs = list(np.random.default_rng(3).uniform(-1, 1, size=(6, 17)).astype(np.float32))
    agent.start(6)
    np.testing.assert_array_equal(agent.act_batch(obs), model.predict(np.stack(obs), deterministic=True)[0])

    env = gym.make("RaceObs-S-Level1-v0", obs_mode="state")
    lstm = RecurrentPPO("MlpLstmPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0,
                        policy_kwargs={"lstm_hidden_size": 8, "net_arch": [8]}, device="cpu")  # fmt: skip
    lstm.save(tmp_path / "lstm.zip")
    agent = load_agent(str(tmp_path / "lstm.zip"), trust_code=True)
    agent.start(6)
    state, starts = None, np.ones(6, dtype=bool)
    for _ in range(3):  # the hidden state is carried between calls as predict carries it
        expected, state = lstm.predict(np.stack(obs), state=state, episode_start=starts, deterministic=True)
        np.testing.assert_allclose(agent.act_batch(obs), expected, rtol=0, atol=1e-6)
        starts = np.zeros(6, dtype=bool)
    agent.reset_slot(2)
    starts[2] = True
    expected, _ = lstm.predict(np.stack(obs), state=state, episode_start=starts, deterministic=True)
    np.testing.assert_allclose(agent.act_batch(obs), expected, rtol=0, atol=1e-6)


def test_the_direct_mean_action_is_bit_identical_to_predict_on_the_papers_gru_policy(tmp_path: Path) -> None:
    """act_batch computes a Gaussian policy's mean itself (no distribution object): same bits as ``_predict``."""
    import dataclasses

    from stable_baselines3 import SAC

    from racebench.training.train import TrainConfig, make_envs, make_model

    config = dataclasses.replace(TrainConfig.from_yaml("vision-ppo"), n_envs=2, n_steps=32, batch_size=32,
                                 n_epochs=1, vec_env="dummy", num_processes=1)  # fmt: skip
    env = make_envs(config, "S", 0)
    make_model(config, env, seed=0, tensorboard=None).save(tmp_path / "gru.zip")
    env.close()
    direct, reference = (load_agent(str(tmp_path / "gru.zip"), trust_code=True) for _ in range(2))
    envs = [gym.make("RaceObs-S-v0") for _ in range(3)]
    obs = [e.reset(seed=EVAL_SEED_BASE + i)[0] for i, e in enumerate(envs)]
    direct.start(3), reference.start(3)
    assert direct.lean
    reference.lean = False  # sb3-contrib's own _predict
    for t in range(12):
        if t == 6:
            direct.reset_slot(1), reference.reset_slot(1)
        actions = direct.act_batch(obs)
        np.testing.assert_array_equal(actions, reference.act_batch(obs))
        obs = [e.step(a)[0] for e, a in zip(envs, actions, strict=True)]
    for e in envs:
        e.close()
    sac = SAC("MlpPolicy", gym.make("RaceObs-S-Level1-v0", obs_mode="state"), learning_starts=0, device="cpu")
    sac.save(tmp_path / "sac.zip")
    squashed = load_agent(str(tmp_path / "sac.zip"), trust_code=True)
    squashed.start(2)
    assert not squashed.lean  # not an actor-critic with a Gaussian head: through _predict


def test_lockstep_flies_the_same_episodes_as_one_at_a_time(tiny_ppo, tmp_path: Path) -> None:
    _, path = tiny_ppo
    envs = ["RaceObs-S-Level1-v0", "RaceObs-S-v0"]
    columns = ["env_id", "seed", "success", "crash_reason", "gates_passed", "steps"]
    frames = {}
    for batch in (1, 3):
        out = tmp_path / f"b{batch}"
        Evaluator(str(path), envs, episodes=4, out_dir=out, trust_code=True, batch=batch).run(progress=False)
        frames[batch] = pd.read_csv(out / "episodes.csv")
    pd.testing.assert_frame_equal(frames[1][columns], frames[3][columns])
    np.testing.assert_allclose(frames[1]["return"], frames[3]["return"], rtol=1e-5)


def test_the_lockstep_width_is_at_most_the_evaluations_size(tmp_path: Path) -> None:
    """A 2 x 3-episode evaluation flies 6 slots, not --batch's 64 (no idle rows), whatever is left to fly."""
    evaluator = Evaluator("planner", ["RaceObs-S-v0", "RaceObs-J-v0"], episodes=3, out_dir=tmp_path, batch=64)
    assert evaluator.width == 6
    assert Evaluator("planner", ["RaceObs-S-v0"], episodes=100, out_dir=tmp_path, batch=64).width == 64


BATCH_AGENTS = textwrap.dedent(
    """
    import numpy as np
    import torch

    SEEN_THREADS = []

    class NanInSlotZero:
        obs_mode = "state"
        def reset(self, env=None, seed=None):
            pass
        def act(self, obs):
            return np.zeros(4)
        def start(self, slots):
            self.slots = slots
        def reset_slot(self, slot):
            pass
        def act_batch(self, observations):
            SEEN_THREADS.append(torch.get_num_threads())
            actions = np.tile([0.0, 0.0, 0.0, 0.0], (self.slots, 1))
            actions[0, 1] = np.nan
            return actions

    class Raises(NanInSlotZero):
        def act_batch(self, observations):
            raise RuntimeError("batch exploded")
    """
)


def test_lockstep_agent_failures_end_only_their_episodes(tmp_path: Path) -> None:

    path = tmp_path / "batch_agents.py"
    path.write_text(BATCH_AGENTS)
    out = tmp_path / "nan"
    Evaluator(f"{path}:NanInSlotZero", ["RaceObs-S-Level1-v0"], episodes=3, out_dir=out, trust_code=True,
              batch=2).run(progress=False)  # fmt: skip
    episodes = pd.read_csv(out / "episodes.csv")
    errors = episodes["crash_reason"].fillna("").eq("agent_error")
    # Slot 0 fails at once, every time it gets an episode; slot 1 flies its episode to the end.
    assert errors.sum() == 2 and episodes.loc[~errors, "steps"].iloc[0] > 1
    assert episodes.loc[errors, "error"].str.contains("not finite").all()
    out = tmp_path / "raises"
    Evaluator(f"{path}:Raises", ["RaceObs-S-Level1-v0"], episodes=3, out_dir=out, trust_code=True,
              batch=2).run(progress=False)  # fmt: skip
    episodes = pd.read_csv(out / "episodes.csv")
    assert len(episodes) == 3 and episodes["error"].str.contains("batch exploded").all()


def test_the_in_process_evaluator_runs_torch_on_its_configured_threads(tmp_path: Path) -> None:
    import torch

    from racebench.evaluation import worker

    path = tmp_path / "thread_probe.py"
    path.write_text(BATCH_AGENTS)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        Evaluator(f"{path}:NanInSlotZero", ["RaceObs-S-Level1-v0"], episodes=2, out_dir=tmp_path / "o",
                  trust_code=True, batch=2).run(progress=False)  # fmt: skip
        agent = worker.WORKER["agent"]  # the in-process evaluator's agent
        seen = agent.act_batch.__globals__["SEEN_THREADS"]  # torch threads at each of its policy calls
        assert seen and set(seen) == {worker.torch_threads()}
        assert torch.get_num_threads() == 2  # restored afterwards
    finally:
        torch.set_num_threads(before)


def test_the_gru_checkpoint_exports_to_onnx_and_flies_the_same(tmp_path: Path) -> None:
    from racebench import cli

    checkpoint = Path(__file__).parents[1] / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"
    out = tmp_path / "vision-ppo.onnx"
    assert cli.main(["export-onnx", str(checkpoint), "--out", str(out)]) == 0
    torch_agent, onnx_agent = load_agent(str(checkpoint)), load_agent(str(out))
    assert onnx_agent.obs_mode == "vision" and onnx_agent.hidden_size == 256
    env = gym.make("RaceObs-S-v0")
    obs, _ = env.reset(seed=EVAL_SEED_BASE)
    torch_agent.reset()
    onnx_agent.reset()
    for _ in range(40):  # closed loop on the torch agent's actions: the hidden state is carried the same way
        action = torch_agent.act(obs)
        np.testing.assert_allclose(onnx_agent.act(obs), action, atol=1e-4)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    env.close()


def test_one_label_on_several_policies_gets_each_directorys_name(tmp_path: Path, caplog) -> None:
    """Per-track students all labelled "vision-dagger", each also flown on another's track, must not share a row."""
    env = "RaceObs-S-Level1-v0"
    for agent, out in (("hover", tmp_path / "a" / "eval"), ("random", tmp_path / "b")):
        Evaluator(agent, [env], episodes=1, out_dir=out, agent_name="same").run(progress=False)
    Evaluator("hover", [env], episodes=1, out_dir=tmp_path / "c", agent_name="other").run(progress=False)
    # The same policy in a second directory (another suite, say) keeps its first directory's label.
    again = Evaluator("hover", ["RaceObs-J-Level1-v0"], episodes=1, out_dir=tmp_path / "d", agent_name="same")
    again.run(progress=False)
    summary = read_summaries([tmp_path / "a" / "eval", tmp_path / "b", tmp_path / "c", tmp_path / "d"])
    assert sorted(summary["agent"]) == ["other", "same (a)", "same (a)", "same (b)"]
    assert "name several policies" in caplog.text


def test_a_row_is_labelled_with_its_run_not_a_generic_evaluation_folder(tmp_path: Path) -> None:
    """``eval``, ``eval-*`` and ``exported`` folders take their run's name; track and seed subfolders keep it too."""
    env = "RaceObs-S-Level1-v0"
    outs = {
        "hover": tmp_path / "distill-ppo-bc" / "eval-exported",
        "random": tmp_path / "distill-ppo-gate-centre" / "Circle" / "exported",
        "follow": tmp_path / "per-track" / "J" / "seed1" / "eval",
    }
    for agent, out in outs.items():
        Evaluator(agent, [env], episodes=1, out_dir=out, agent_name="same").run(progress=False)
    summary = read_summaries(list(outs.values()))
    expected = ["same (J/seed1)", "same (distill-ppo-bc)", "same (distill-ppo-gate-centre/Circle)"]
    assert sorted(summary["agent"]) == expected


def test_one_label_with_one_policy_per_track_is_one_table_row(tmp_path: Path, caplog) -> None:
    """A sweep's per-track runs of one config and seed (one label, each policy flown on its own track only) are one
    row of Table II, as the paper's method rows are; a third policy on a track already covered splits them again."""
    Evaluator("hover", ["RaceObs-S-v0"], episodes=1, out_dir=tmp_path / "cfg-S-seed0" / "eval",
              agent_name="cfg-seed0").run(progress=False)  # fmt: skip
    Evaluator("random", ["RaceObs-J-v0"], episodes=1, out_dir=tmp_path / "cfg-J-seed0" / "eval",
              agent_name="cfg-seed0").run(progress=False)  # fmt: skip
    with caplog.at_level("DEBUG", logger="racebench"):
        summary = read_summaries([tmp_path / "cfg-S-seed0" / "eval", tmp_path / "cfg-J-seed0" / "eval"])
    assert sorted(zip(summary["agent"], summary["track"], strict=True)) == [("cfg-seed0", "J"), ("cfg-seed0", "S")]
    assert "one row of 2 policies, one per track" in caplog.text
    table = make_table(summary, "III")
    assert table.count("cfg-seed0") == 1  # one row, cells on S and J
    Evaluator("follow", ["RaceObs-J-v0"], episodes=1, out_dir=tmp_path / "other" / "eval",
              agent_name="cfg-seed0").run(progress=False)  # fmt: skip
    summary = read_summaries([tmp_path / p / "eval" for p in ("cfg-S-seed0", "cfg-J-seed0", "other")])
    assert sorted(summary["agent"]) == ["cfg-seed0 (cfg-J-seed0)", "cfg-seed0 (cfg-S-seed0)", "cfg-seed0 (other)"]


def test_compare_pairs_two_evaluations_scene_by_scene_from_their_valid_records(tmp_path: Path, capsys) -> None:
    """``racebench compare``: pairs on shared (env id, seed), McNemar's exact p on the discordant laps, an edited
    record never counted, a folder of two policies refused by name."""
    from scipy.stats import binomtest

    from racebench import cli

    a, b = tmp_path / "a", tmp_path / "b"
    Evaluator("follow", ["RaceObs-S-v0"], episodes=6, out_dir=a).run(progress=False)
    Evaluator("hover", ["RaceObs-S-v0", "RaceObs-J-Level1-v0"], episodes=4, out_dir=b).run(progress=False)
    follow = load_records(a).set_index("seed")["success"].astype(bool)
    wins = int(follow.iloc[:4].sum())  # hover never finishes: every pair follow finished is discordant
    assert wins > 0  # seeds 1000000-1000001: follow finishes, so there are discordant pairs to count
    assert cli.main(["compare", str(a), str(b), "--out", str(tmp_path / "pairs.csv")]) == 0
    out = capsys.readouterr().out
    assert "McNemar's exact test" in out
    # The header gives each side on the episodes actually paired, per env id, not every episode of its folder.
    assert "6 episodes in the folder, 4 paired" in out and "8 episodes in the folder, 4 paired" in out
    assert "95 % Wilson interval" in out and "in seconds" in out
    s_row = next(line for line in out.splitlines() if line.strip().startswith("RaceObs-S-v0") and "/4" in line)
    assert f"{wins}/4 " in s_row and "0/4 0 [0–" in s_row and s_row.split()[-1] == "–"  # hover: no lap, a dash
    assert "RaceObs-J-Level1-v0" not in out  # flown by b only: in no pair, in no line of the header
    pairs = pd.read_csv(tmp_path / "pairs.csv").set_index("env_id")
    assert list(pairs.index) == ["RaceObs-S-v0", "all"]  # the J id was flown by one side only: not paired
    expected_p = binomtest(0, wins).pvalue if wins else 1.0
    counts = pairs.loc["all", ["pairs", "successes_a", "successes_b", "only_a", "only_b"]].tolist()
    assert counts == [4, wins, 0, wins, 0]
    assert pairs.loc["all", "p"] == pytest.approx(expected_p)
    # An edited record (its outcome flipped) fails its digest: left out, its scene no longer paired.
    lines = [json.loads(line) for line in (a / "records.jsonl").read_text().splitlines()]
    for record in lines:
        record["success"] ^= record["seed"] == EVAL_SEED_BASE
    (a / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert paired_comparison(a, b)[1].set_index("env_id").loc["all", "pairs"] == 3
    with (a / "records.jsonl").open("ab") as merged:  # two policies in one folder
        merged.write((b / "records.jsonl").read_bytes())
    with pytest.raises(SystemExit, match=r"racebench compare: .* holds 2 policies' episodes \(follow, hover\)"):
        cli.main(["compare", str(a), str(b)])
    Evaluator("hover", ["RaceObs-Circle-Level1-v0"], episodes=1, out_dir=tmp_path / "c").run(progress=False)
    with pytest.raises(SystemExit, match=r"share no \(env_id, seed\) episode to pair"):
        cli.main(["compare", str(b), str(tmp_path / "c")])
