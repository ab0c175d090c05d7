"""``racebench sweep``: a two-run grid of tiny configs finishes, is skipped when re-run and resumes a killed run
from its own folder, locally and on a local Ray instance of 2 CPUs (tests marked ``ray``, run on their own)."""

from __future__ import annotations

import json
import os
import signal
import textwrap
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

from racebench.cli import main
from racebench.evaluation import load_records, read_summaries
from racebench.evaluation.ray_backend import RayOptions
from racebench.reporting.tables import make_table
from racebench.training.sweep import latest_checkpoint, load_sweep, run_sweep, track_envs

# State observations, 2 envs in this process, 128-step updates: a run of 256 steps takes seconds.
TINY = textwrap.dedent(
    """
    name: tiny
    obs_mode: state
    recurrent: false
    vec_env: dummy
    n_envs: 2
    num_processes: 1
    update_threads: 1
    n_steps: 64
    batch_size: 64
    n_epochs: 1
    window: 4
    net_arch: [16]
    gru_hidden: 16
    """
)


def write_sweep(tmp_path: Path, **changes) -> Path:
    """A two-run sweep (tiny config × tracks S, J × seed 0) under ``tmp_path``."""
    (tmp_path / "tiny.yaml").write_text(TINY)
    sweep = {
        "name": "two", "out": str(tmp_path / "out"), "configs": ["tiny.yaml"], "tracks": ["S", "J"], "seeds": [0],
        "steps": 256, "eval_episodes": 1, "checkpoint_every": 128, **changes,
    }  # fmt: skip
    path = tmp_path / "two.yaml"
    path.write_text(json.dumps(sweep))  # JSON is YAML
    return path


def check_finished(out: Path, runs: list[str]) -> dict[str, float]:
    """Every run folder holds its checkpoint, an evaluated summary and one valid record; return mtimes."""
    stamps = {}
    for run in runs:
        summary = json.loads((out / run / "summary.json").read_text())
        assert summary["timesteps"] == 256 and summary["eval"]["n"] == 1, run
        assert Path(summary["checkpoint"]).is_file()
        records = load_records(out / run / "eval")
        assert len(records) == 1 and records["agent"].iloc[0] == "tiny-seed0"
        stamps[run] = (out / run / "summary.json").stat().st_mtime_ns
    table = pd.read_csv(out / "sweep.csv")
    assert table["run"].tolist() == runs
    # `racebench table <out>/*/eval`: one row per config and seed, each track's cells from that track's run
    summary = read_summaries([out / run / "eval" for run in runs])
    assert summary["agent"].tolist() == ["tiny-seed0"] * len(runs) and summary["track"].nunique() == len(runs)
    return stamps


RUNS = ["tiny-S-seed0", "tiny-J-seed0"]


def test_bad_sweep_files_are_named(tmp_path: Path) -> None:
    for changes, message in [
        ({"tracks": ["X"]}, "track 'X' is not one of"),
        ({"seeds": [1_000_000]}, "seeds must be integers in"),
        ({"overrides": {"n_env": 3}}, "override 'n_env' of 'tiny.yaml' is not a config key"),
        ({"stepz": 3}, "unknown key 'stepz'"),
        ({"configs": ["tiny.yaml", "tiny.yaml"]}, "two runs would share the folder 'tiny-S-seed0'"),
        ({"overrides": {"batch_size": 100}}, "multiple of batch_size"),
        ({"eval_suite": "hard"}, r"eval_suite must be one of \['density', 'gates', 'main', 'paper', 'robustness', "
                                 r"'robustness-Circle', 'robustness-J', 'robustness-S'\], not 'hard'"),
        ({"configs": [{"config": "tiny.yaml", "tracks": ["Q"]}]}, "track 'Q' is not one of"),
        ({"configs": [{"config": "tiny.yaml", "seeds": []}]}, "seeds of 'tiny.yaml' must be a non-empty list"),
        ({"eval_episodes_other": 0}, "eval_episodes_other must be an integer >= 1"),
        ({"validation_every": 100}, "validation_every must be a multiple of checkpoint_every"),
        ({"evaluate_policy_only": "yes"}, "evaluate_policy_only must be true or false"),
    ]:
        with pytest.raises(SystemExit, match=message) as exit_info:
            main(["sweep", str(write_sweep(tmp_path, **changes))])
        assert "\n" not in str(exit_info.value.code)
    assert not (tmp_path / "out").exists()


def test_a_student_of_several_tracks_is_swept_over_one_of_them(tmp_path: Path) -> None:
    """A DAgger config with train_tracks trains one student for all its tracks: swept over two tracks (or one it does
    not fly) it would train that student twice (or fail), so the sweep file is refused by name."""
    (tmp_path / "multi.yaml").write_text("method: dagger\nname: multi\nn_envs: 4\ntrain_tracks: [S, J]\n")
    sweep = {"name": "m", "out": str(tmp_path / "out"), "configs": ["multi.yaml"], "seeds": [0], "steps": 256}
    path = tmp_path / "m.yaml"
    for tracks in (["S", "J"], ["Circle"]):
        path.write_text(json.dumps({**sweep, "tracks": tracks}))
        with pytest.raises(ValueError, match=r"trains one student for the tracks \['S', 'J'\] \(train_tracks\)"):
            load_sweep(path)
    path.write_text(json.dumps({**sweep, "tracks": ["J"]}))
    assert [(run.track, run.out.name) for run in load_sweep(path).runs] == [("J", "multi-J-seed0")]


def test_a_local_sweep_finishes_is_skipped_when_rerun_and_resumes_a_killed_run(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    path = write_sweep(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(path)]) == 0
    stamps = check_finished(out, RUNS)
    assert main(["sweep", str(path)]) == 0
    assert "tiny-S-seed0: skipped" in capsys.readouterr().out
    assert check_finished(out, RUNS) == stamps  # nothing re-run, nothing rewritten
    assert set(pd.read_csv(out / "sweep.csv")["status"]) == {"skipped"}

    # Killed in training after its first checkpoint: no summary, final model, later checkpoints or evaluation
    # (train writes summary.json last, the evaluation starts after it). It resumes from that checkpoint.
    import shutil

    run = out / "tiny-J-seed0"
    for name in ("summary.json", "tiny-J.zip"):
        (run / name).unlink()
    for late in (run / "checkpoints").glob("tiny*_256_steps.*"):
        late.unlink()
    shutil.rmtree(run / "eval")
    assert latest_checkpoint(run, "tiny")[1] == 128
    # Killed while evaluating: summary.json without its eval. Only the evaluation is run again.
    trained = out / "tiny-S-seed0"
    summary = json.loads((trained / "summary.json").read_text())
    del summary["eval"]
    (trained / "summary.json").write_text(json.dumps(summary))
    shutil.rmtree(trained / "eval")
    model_stamp = (trained / "tiny-S.zip").stat().st_mtime_ns
    rows = run_sweep(load_sweep(path))
    assert [row["status"] for row in rows] == ["done", "done"]
    assert (trained / "tiny-S.zip").stat().st_mtime_ns == model_stamp, "a trained run must not train again"
    assert json.loads((run / "summary.json").read_text())["resumed_at"] == 128
    check_finished(out, RUNS)


def test_a_sweep_unpickles_only_the_checkpoints_its_runs_wrote(tmp_path: Path) -> None:
    """A checkpoint dropped into a run folder (not in its written.json) is refused, for training and evaluation."""
    from payloads import evil_sb3_zip

    path = write_sweep(tmp_path, tracks=["S"])
    run, marker = tmp_path / "out" / "tiny-S-seed0", tmp_path / "ran"
    (run / "checkpoints").mkdir(parents=True)
    evil_sb3_zip(run / "checkpoints" / "tiny_128_steps.zip", marker)
    rows = run_sweep(load_sweep(path))
    assert rows[0]["status"].startswith("failed: checkpoint") and "--trust-code" in rows[0]["status"]
    # Killed while evaluating, and its summary now names a planted checkpoint: the evaluation refuses it too.
    (run / "checkpoints" / "tiny_128_steps.zip").unlink()
    evil = evil_sb3_zip(run / "tiny-S.zip", marker)
    (run / "summary.json").write_text(json.dumps({"timesteps": 256, "checkpoint": str(evil)}))
    rows = run_sweep(load_sweep(path))
    assert rows[0]["status"].startswith("failed: agent") and "--trust-code" in rows[0]["status"]
    assert not marker.exists()
    with pytest.raises(SystemExit, match="1 of 1 runs failed"):
        main(["sweep", str(path)])
    assert not marker.exists()


def test_eval_suite_flies_each_run_on_its_tracks_ids_and_extends_a_finished_run(tmp_path: Path) -> None:
    """``eval_suite: density``: every run's policy on its own track's ids of that suite, main id first; a run
    evaluated on the main id alone is evaluated on the rest without training again; Table IV from the runs."""
    path = write_sweep(tmp_path)
    out = tmp_path / "out"
    assert main(["sweep", str(path)]) == 0
    model = out / "tiny-S-seed0" / "tiny-S.zip"
    stamp = model.stat().st_mtime_ns
    path = write_sweep(tmp_path, eval_suite="density")
    assert [row["status"] for row in run_sweep(load_sweep(path))] == ["done", "done"]
    assert model.stat().st_mtime_ns == stamp, "a trained run must not train again"
    for run, track in zip(RUNS, ["S", "J"], strict=True):
        wanted = track_envs("density", track)
        assert wanted[0] == f"RaceObs-{track}-v0" and len(wanted) == 5
        assert sorted(load_records(out / run / "eval")["env_id"]) == sorted(wanted)
        evaluation = json.loads((out / run / "summary.json").read_text())["eval"]
        assert evaluation["envs"] == list(wanted) and evaluation["n"] == 1
    assert [row["status"] for row in run_sweep(load_sweep(path))] == ["skipped", "skipped"]
    table = make_table(read_summaries([out / run / "eval" for run in RUNS]), "IV")
    assert "tiny-seed0 S-shaped" in table and "tiny-seed0 J-shaped" in table and "tiny-seed0 3D Circle" in table


def test_entries_with_their_own_tracks_and_seeds_run_in_the_files_order_one_at_a_time(tmp_path: Path) -> None:
    """A config listed twice with other tracks or seeds (a campaign's extra seeds) plans its runs in the file's
    order; --max-runs 1 trains the next unfinished one only; the main id gets eval_episodes, the rest
    eval_episodes_other."""
    configs = [{"config": "tiny.yaml", "tracks": ["J"]}, {"config": "tiny.yaml", "tracks": ["S"], "seeds": [1, 2]}]
    path = write_sweep(tmp_path, configs=configs, eval_suite="density", eval_episodes=2, eval_episodes_other=1,
                       evaluate_policy_only=True, validation_every=128, validation_episodes=2)  # fmt: skip
    sweep = load_sweep(path)
    assert [run.label for run in sweep.runs] == ["tiny-J-seed0", "tiny-S-seed1", "tiny-S-seed2"]
    out = tmp_path / "out"
    assert main(["sweep", str(path), "--max-runs", "1"]) == 0
    assert [p.name for p in out.iterdir() if p.is_dir()] == ["tiny-J-seed0"]
    assert pd.read_csv(out / "sweep.csv")["status"].tolist() == ["done", "not started", "not started"]
    counts = load_records(out / "tiny-J-seed0" / "eval").groupby("env_id").size()
    assert counts["RaceObs-J-v0"] == 2 and len(counts) == 5 and set(counts.drop("RaceObs-J-v0")) == {1}
    summary = json.loads((out / "tiny-J-seed0" / "summary.json").read_text())
    assert summary["eval"]["n"] == 2 and summary["policy"].endswith("tiny-J-seed0/policy/tiny-J.zip")
    records = load_records(out / "tiny-J-seed0" / "eval")
    assert set(records["policy_source"]) == {summary["policy"]}  # the policy-only file that gets committed
    curve = pd.read_csv(out / "tiny-J-seed0" / "validation_curve.csv")
    assert curve["timesteps"].tolist() == [128, 256] and set(curve["episodes"]) == {2}
    # Incremental: a kept row is not flown again, a missing multiple is (a run spanning sessions keeps its points).
    from racebench.reporting.validation import validation_curve

    curve.loc[0, "successes"] = 99  # a marker: flown again, it would be 0, 1 or 2
    curve.iloc[:1].to_csv(out / "tiny-J-seed0" / "validation_curve.csv", index=False)
    again = validation_curve(out / "tiny-J-seed0", every=128, episodes=2)
    assert again["timesteps"].tolist() == [128, 256] and again["successes"].iloc[0] == 99
    # A finished run's final model stands in where no periodic checkpoint is near a multiple (a resumed run's).
    for late in (out / "tiny-J-seed0" / "checkpoints").glob("tiny*_256_steps.*"):
        late.unlink()
    curve.iloc[:1].to_csv(out / "tiny-J-seed0" / "validation_curve.csv", index=False)
    last = validation_curve(out / "tiny-J-seed0", every=128, episodes=2)
    assert last["timesteps"].tolist() == [128, summary["timesteps"]] and last["episodes"].iloc[1] == 2
    rows = run_sweep(load_sweep(path), max_runs=1)
    assert [row["status"] for row in rows] == ["skipped", "done", "not started"]
    with pytest.raises(SystemExit, match="--max-runs is an integer >= 1, for the local backend"):
        main(["sweep", str(path), "--max-runs", "0"])


def test_a_sweep_runs_a_dagger_config_and_resumes_it_from_its_folder(tmp_path: Path) -> None:
    """A ``method: dagger`` config in a sweep: trained, evaluated, skipped when finished, resumed when killed."""
    (tmp_path / "distill.yaml").write_text(
        "method: dagger\nname: distill\nsteps_per_iteration: 128\nn_envs: 4\nepochs: 1\nbatch_size: 64\n"
    )
    sweep = {"name": "d", "out": str(tmp_path / "out"), "configs": ["distill.yaml"], "tracks": ["S"], "seeds": [1],
             "steps": 256, "eval_episodes": 1}  # fmt: skip
    path = tmp_path / "d.yaml"
    path.write_text(json.dumps(sweep))
    loaded = load_sweep(path)
    assert loaded.runs[0].cpus == 2.0  # update_threads: the CPUs a DAgger run uses
    assert [row["status"] for row in run_sweep(loaded)] == ["done"]
    run = tmp_path / "out" / "distill-S-seed1"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["timesteps"] == 256 and summary["eval"]["n"] == 1 and summary["config"]["seed"] == 1
    assert [row["status"] for row in run_sweep(load_sweep(path))] == ["skipped"]
    # Killed after its first iteration: the run's state says iteration 0; the sweep runs only iteration 1.
    import shutil

    from racebench.training.dagger import DaggerConfig, distill

    shutil.rmtree(tmp_path / "out")
    first = DaggerConfig(name="distill", track="S", seed=1, iterations=1, steps_per_iteration=128, n_envs=4,
                         epochs=1, batch_size=64)  # fmt: skip
    distill(first, run, eval_episodes=0)
    (run / "summary.json").unlink()  # as if killed before the run ended
    assert [row["status"] for row in run_sweep(load_sweep(path))] == ["done"]
    progress = pd.read_csv(run / "progress.csv")
    assert progress["iteration"].tolist() == [0, 1]
    assert json.loads((run / "summary.json").read_text())["eval"]["n"] == 1


def write_chained_sweep(tmp_path: Path) -> Path:
    """A teacher-student chain: a tiny DAgger student (its own 128-step budget), then vision-distill-ppo
    started from it (``after``), on S with training seed 1; no final evaluations."""
    (tmp_path / "student.yaml").write_text(
        "method: dagger\nname: student\nsteps_per_iteration: 64\nn_envs: 4\nepochs: 1\nbatch_size: 64\n"
    )
    tuned = {"n_envs": 4, "n_steps": 16, "batch_size": 64, "n_epochs": 1, "vec_env": "dummy", "num_processes": 1,
             "critic_warmup": 0}  # fmt: skip
    configs = [{"config": "student.yaml", "steps": 128},
               {"config": "vision-distill-ppo", "after": "student", "overrides": tuned}]  # fmt: skip
    sweep = {"name": "chain", "out": str(tmp_path / "out"), "tracks": ["S"], "seeds": [1], "steps": 64,
             "eval_episodes": 0, "configs": configs}  # fmt: skip
    path = tmp_path / "chain.yaml"
    path.write_text(json.dumps(sweep))
    return path


def check_chained(out: Path) -> None:
    """The student trained its own budget; the fine-tuning run started from the student's final policy."""
    student = json.loads((out / "student-S-seed1" / "summary.json").read_text())
    tuned = json.loads((out / "vision-distill-ppo-S-seed1" / "summary.json").read_text())
    assert student["timesteps"] == 128 and tuned["timesteps"] == 64
    assert tuned["init_from"] == str(out / "student-S-seed1" / "student-S.zip") == student["checkpoint"]


def test_a_chained_sweep_starts_a_run_from_the_final_policy_of_the_run_it_is_after(tmp_path: Path) -> None:
    path = write_chained_sweep(tmp_path)
    sweep = load_sweep(path)
    assert [run.steps for run in sweep.runs] == [128, 64]
    assert [run.after for run in sweep.runs] == [None, "student-S-seed1"]
    assert [row["status"] for row in run_sweep(sweep)] == ["done", "done"]
    check_chained(tmp_path / "out")


def test_a_chained_run_whose_predecessor_failed_is_reported_and_not_started(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import racebench.training.sweep as sweep_module

    started = []

    def job(run):  # the student fails; the follower must not be started at all
        started.append(run.label)
        raise RuntimeError("teacher exploded")

    monkeypatch.setattr(sweep_module, "run_job", job)
    rows = run_sweep(load_sweep(write_chained_sweep(tmp_path)))
    assert started == ["student-S-seed1"]
    assert [row["status"] for row in rows] == [
        "failed: teacher exploded", "failed: it starts from student-S-seed1, which failed",
    ]  # fmt: skip


def test_bad_chains_are_named(tmp_path: Path) -> None:
    path = write_chained_sweep(tmp_path)
    data = json.loads(path.read_text())
    for configs, message in [
        (list(reversed(data["configs"])), "'vision-distill-ppo' is after 'student', not a config listed before it"),
        ([data["configs"][0], {"config": "student.yaml", "after": "student", "overrides": {"name": "again"}}],
         "'again' cannot start from another run's policy"),
        ([{"config": "student.yaml", "steps": 0}], "steps of 'student.yaml' must be an integer >= 1"),
        ([{"config": "student.yaml", "step": 5}], "each configs entry is a name/file or a mapping with keys among"),
        ([{"config": "student.yaml", "steps": True}], "steps of 'student.yaml' must be an integer >= 1"),
        ([data["configs"][0], {**data["configs"][1], "overrides": {"init_from": "x.zip"}}],
         "'vision-distill-ppo' has both after and an init_from override"),
    ]:  # fmt: skip
        path.write_text(json.dumps({**data, "configs": configs}))
        with pytest.raises(SystemExit, match=message):
            main(["sweep", str(path)])
    assert not (tmp_path / "out").exists()


def write_failing_chain(tmp_path: Path) -> Path:
    """Three tiny state configs a -> b -> c (each after the previous); a fails when it starts (no init_from file)."""
    (tmp_path / "tiny.yaml").write_text(TINY)
    configs = [
        {"config": "tiny.yaml", "overrides": {"name": "a", "init_from": str(tmp_path / "missing.zip")}},
        {"config": "tiny.yaml", "overrides": {"name": "b"}, "after": "a"},
        {"config": "tiny.yaml", "overrides": {"name": "c"}, "after": "b"},
    ]
    sweep = {"name": "abc", "out": str(tmp_path / "out"), "configs": configs, "tracks": ["S"], "seeds": [0],
             "steps": 128, "eval_episodes": 0}  # fmt: skip
    path = tmp_path / "abc.yaml"
    path.write_text(json.dumps(sweep))
    return path


FAILED_CHAIN = ["failed: it starts from a-S-seed0, which failed", "failed: it starts from b-S-seed0, which failed"]


def test_a_failed_run_fails_its_whole_chain_without_starting_it(tmp_path: Path) -> None:
    rows = run_sweep(load_sweep(write_failing_chain(tmp_path)))
    assert "is not a file" in rows[0]["status"] and [r["status"] for r in rows[1:]] == FAILED_CHAIN
    assert not (tmp_path / "out" / "b-S-seed0").exists() and not (tmp_path / "out" / "c-S-seed0").exists()


@pytest.mark.ray
def test_a_chained_ray_sweep_submits_a_run_after_the_run_it_starts_from(ray_cluster, tmp_path: Path) -> None:
    rows = run_sweep(load_sweep(write_chained_sweep(tmp_path)), backend="ray", ray_options=RayOptions())
    assert [row["status"] for row in rows] == ["done", "done"]
    check_chained(tmp_path / "out")


@pytest.mark.ray
def test_a_ray_sweep_finishes_and_is_skipped_when_rerun(ray_cluster, tmp_path: Path) -> None:
    path = write_sweep(tmp_path)
    out = tmp_path / "out"
    rows = run_sweep(load_sweep(path), backend="ray", ray_options=RayOptions())
    assert [row["status"] for row in rows] == ["done", "done"]
    stamps = check_finished(out, RUNS)
    rows = run_sweep(load_sweep(path), backend="ray", ray_options=RayOptions())
    assert [row["status"] for row in rows] == ["skipped", "skipped"]
    assert check_finished(out, RUNS) == stamps


def descendants_running(task: str) -> list[int]:
    """PIDs of this process's descendants whose title is ``ray::<task>``: the Ray workers of the instance this
    test started, running that task (Ray renames a worker process after the task it runs)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = [], list(children.get(os.getpid(), []))
    while todo:
        pid = todo.pop()
        todo += children.get(pid, [])
        try:
            if (Path("/proc") / str(pid) / "cmdline").read_bytes().startswith(f"ray::{task}".encode()):
                found.append(pid)
        except OSError:
            continue
    return found


@pytest.mark.ray
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the Ray worker to kill through /proc")
def test_a_ray_sweep_run_whose_worker_is_killed_resumes_from_its_checkpoint(ray_cluster, tmp_path: Path) -> None:
    path = write_sweep(tmp_path, tracks=["S"], steps=2048, eval_episodes=1, checkpoint_every=128)
    run = tmp_path / "out" / "tiny-S-seed0"
    rows: list = []
    sweeping = threading.Thread(
        target=lambda: rows.extend(run_sweep(load_sweep(path), backend="ray", ray_options=RayOptions(max_retries=2)))
    )
    sweeping.start()
    killed = None
    deadline = time.time() + 120
    while killed is None and time.time() < deadline and sweeping.is_alive():
        if latest_checkpoint(run, "tiny")[1] >= 128:  # mid-run: a checkpoint written, the run not finished
            workers = descendants_running("run_job")
            if workers:
                killed = workers[0]
                os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    sweeping.join(timeout=300)
    assert killed is not None, "the run finished before its worker could be killed: the test tested nothing"
    assert [row["status"] for row in rows] == ["done"]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["timesteps"] == 2048 and summary["resumed_at"] >= 128  # resumed from a checkpoint, not afresh
    assert summary["eval"]["n"] == 1 and len(load_records(run / "eval")) == 1
    progress = pd.read_csv(run / "progress.csv")
    assert progress["timesteps"].is_unique and progress["timesteps"].iloc[-1] == 2048  # no update logged twice


def test_the_shipped_paper_sweep_loads() -> None:
    path = Path(__file__).parents[1] / "baselines" / "sweeps" / "paper-tables.yaml"
    sweep = load_sweep(path)
    configs = {"vision-ppo", "state-ppo", "vision-com", "vision-no-gru", "vision-no-avoid", "vision-one-step"}
    assert len(sweep.runs) == 18 and {run.config.name for run in sweep.runs} == configs
    assert {run.track for run in sweep.runs} == {"S", "Circle", "J"}
    assert all(run.steps == 100_000_000 and run.cpus == run.config.num_processes for run in sweep.runs)
    # Tables II-IV from the runs alone: each on its track's 9 ids of the paper suite
    assert all(run.eval_envs == track_envs("paper", run.track) and len(run.eval_envs) == 9 for run in sweep.runs)


def test_the_shipped_campaign_plans_the_24_runs_of_the_paper_tables_in_order() -> None:
    """Issue 48's campaign: seed 0 of the six paper configs on the three tracks, vision-ppo on J and Circle first,
    then seeds 1-2 of vision-no-gru on S and of vision-ppo on J and Circle; 4M steps; 9 ids, 100 + 8 x 50 episodes."""
    sweep = load_sweep(Path(__file__).parents[1] / "baselines" / "sweeps" / "campaign-4m.yaml")
    labels = [run.label for run in sweep.runs]
    configs = ["state-ppo", "vision-com", "vision-no-avoid", "vision-one-step", "vision-no-gru"]
    expected = [
        "vision-ppo-J-seed0", "vision-ppo-Circle-seed0",
        *[f"{config}-{track}-seed0" for config in configs for track in ("S", "J", "Circle")],
        "vision-ppo-S-seed0", "vision-no-gru-S-seed1", "vision-no-gru-S-seed2",
        "vision-ppo-J-seed1", "vision-ppo-J-seed2", "vision-ppo-Circle-seed1", "vision-ppo-Circle-seed2",
    ]  # fmt: skip
    assert labels == expected and len(labels) == 24
    assert {run.steps for run in sweep.runs} == {4_000_000} and {run.device for run in sweep.runs} == {"cpu"}
    assert all(run.eval_envs == track_envs("paper", run.track) and len(run.eval_envs) == 9 for run in sweep.runs)
    assert {(run.eval_episodes, run.eval_episodes_other) for run in sweep.runs} == {(100, 50)}
    assert {(run.validation_every, run.validation_episodes, run.evaluate_policy_only) for run in sweep.runs} == {
        (1_000_000, 100, True)
    }
    assert all(run.config.name == run.label.split(f"-{run.track}-")[0] for run in sweep.runs)


def test_campaign_2_plans_its_33_runs_and_the_long_run_on_the_papers_distribution() -> None:
    """Issue 69's campaign: the six paper configs and the flying-start one-step on the three tracks (seed 0), seeds 1-2
    of vision-ppo and vision-one-step; 4 M steps, validation every 0.5 M; then vision-ppo on S to 24 M steps."""
    root = Path(__file__).parents[1] / "baselines" / "sweeps"
    sweep = load_sweep(root / "campaign-2.yaml")
    tracks = ("S", "J", "Circle")
    configs = ["vision-ppo", "vision-one-step", "vision-one-step-flying", "state-ppo", "vision-com", "vision-no-avoid",
               "vision-no-gru"]  # fmt: skip
    expected = [f"{config}-{track}-seed0" for config in configs for track in tracks]
    expected += [f"{config}-{track}-seed{seed}" for config in ("vision-ppo", "vision-one-step") for track in tracks
                 for seed in (1, 2)]  # fmt: skip
    assert [run.label for run in sweep.runs] == expected and len(expected) == 33
    assert {run.steps for run in sweep.runs} == {4_000_000} and sweep.out.name == "campaign-2"
    assert all(run.eval_envs == track_envs("paper", run.track) for run in sweep.runs)
    assert {(run.eval_episodes, run.eval_episodes_other) for run in sweep.runs} == {(100, 50)}
    assert {(run.validation_every, run.checkpoint_every, run.evaluate_policy_only) for run in sweep.runs} == {
        (500_000, 500_000, True)
    }
    for run in sweep.runs:  # the paper's distribution, [com]'s own regime and the named flying start
        start = {"vision-com": "track", "vision-one-step-flying": "gates"}.get(run.config.name, "points")
        shift_z = None if run.config.name == "vision-com" else 0.3
        assert (run.config.start_mode, run.config.gate_shift, run.config.gate_shift_z) == (start, 1.0, shift_z)
        assert run.config.obstacle_placement == "band"
    (long,) = load_sweep(root / "campaign-2-long.yaml").runs
    assert (long.label, long.steps, long.validation_every) == ("vision-ppo-long-S-seed0", 24_000_000, 2_000_000)
    assert long.config.start_mode == "points" and long.config.gru_hidden == 256


def test_the_shipped_teacher_student_sweep_chains_each_student_to_its_fine_tuning() -> None:
    path = Path(__file__).parents[1] / "baselines" / "sweeps" / "teacher-student.yaml"
    sweep = load_sweep(path)
    students = [run for run in sweep.runs if run.config.name == "vision-distill"]
    tuned = [run for run in sweep.runs if run.config.name == "vision-distill-ppo"]
    assert len(students) == len(tuned) == 9 and sweep.runs[:9] == students  # students first: local order
    assert {run.steps for run in students} == {500_000} and {run.steps for run in tuned} == {2_000_000}
    assert all(f"RaceObs-{run.track}-Density5-v0" in run.eval_envs for run in sweep.runs)  # the hard ids too
    for run in tuned:
        assert run.after == f"vision-distill-{run.track}-seed{run.seed}"
        start = run.config.init_from.format(track=run.track, seed=run.seed)
        assert start == str(sweep.out / run.after / f"vision-distill-{run.track}.zip")


@pytest.mark.ray
def test_a_failed_run_fails_its_whole_chain_on_ray(ray_cluster, tmp_path: Path) -> None:
    rows = run_sweep(load_sweep(write_failing_chain(tmp_path)), backend="ray", ray_options=RayOptions())
    assert "is not a file" in rows[0]["status"] and [r["status"] for r in rows[1:]] == FAILED_CHAIN


def test_sigterm_checkpoints_the_run_in_progress_ends_the_sweep_and_the_same_command_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``kill -TERM`` during training: a checkpoint at the end of the rollout being collected, no summary, no further
    run; the SIGTERM handler is the old one again afterwards; re-running the command resumes from that checkpoint."""
    from racebench.training import callbacks

    path = write_sweep(tmp_path, steps=384, checkpoint_every=10**6)  # no periodic checkpoint: only the stop's
    out = tmp_path / "out"
    rollout_end, sent = callbacks.ProgressCSVCallback._on_rollout_end, []

    def end_then_sigterm(self) -> None:
        rollout_end(self)
        if not sent:  # after the first rollout: the stop comes at the end of the second, at 256 steps
            sent.append(True)
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(callbacks.ProgressCSVCallback, "_on_rollout_end", end_then_sigterm)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit, match=r"stopped on request during tiny-S-seed0 \(checkpointed\); the same command"):
        main(["sweep", str(path)])
    assert signal.getsignal(signal.SIGTERM) is before and not callbacks.STOP_REQUESTED.is_set()
    statuses = pd.read_csv(out / "sweep.csv")["status"].tolist()
    assert statuses[0].startswith("interrupted: ") and "stopped on request at 256 steps" in statuses[0]
    assert statuses[1] == "not started" and not (out / "tiny-J-seed0").exists()
    run = out / "tiny-S-seed0"
    assert latest_checkpoint(run, "tiny")[1] == 256 and not (run / "summary.json").exists()
    assert "checkpoints/tiny_256_steps.zip" in json.loads((run / "written.json").read_text())  # trusted on resume

    monkeypatch.setattr(callbacks.ProgressCSVCallback, "_on_rollout_end", rollout_end)
    assert main(["sweep", str(path)]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["resumed_at"] == 256 and summary["timesteps"] == 384
    assert json.loads((out / "tiny-J-seed0" / "summary.json").read_text())["timesteps"] == 384


def test_sigterm_outside_training_or_a_second_time_does_what_it_did_before() -> None:
    """Under ``checkpoint_on_sigterm`` the signal only asks a training run to stop; otherwise (an evaluation, or a
    second signal while the first is pending) the previous handler gets it, as without the context."""
    from racebench.training import callbacks

    received: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: received.append(signum))
    try:
        with callbacks.checkpoint_on_sigterm():
            os.kill(os.getpid(), signal.SIGTERM)  # no training under way
            assert received == [signal.SIGTERM] and not callbacks.STOP_REQUESTED.is_set()
        with callbacks.checkpoint_on_sigterm():
            callbacks._TRAINING.set()
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                assert callbacks.STOP_REQUESTED.is_set() and len(received) == 1  # asked to stop, not passed on
                os.kill(os.getpid(), signal.SIGTERM)
                assert len(received) == 2  # the second one is not swallowed
            finally:
                callbacks._TRAINING.clear()
        assert not callbacks.STOP_REQUESTED.is_set()
    finally:
        signal.signal(signal.SIGTERM, previous)
