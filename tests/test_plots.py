"""Figures: formats and resolution, 0 % bars against cells without results, the legend off the bars, the 3D
track figure cropped to what it draws, and a default output folder that is not the committed one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from racebench import cli
from racebench.evaluation import read_summaries
from racebench.evaluation.protocol import TRACK_ORDER
from racebench.reporting import plots

ROOT = Path(__file__).parents[1]
# The env-version-2 history of the built-ins (results/env-v2): stable records, while results/<agent> are re-flown.
HISTORY = ROOT / "results" / "env-v2"
RESULTS = [str(HISTORY / name) for name in ("hover", "planner")]


@pytest.fixture(scope="module")
def summary():
    return read_summaries(RESULTS)


def test_formats_and_dpi(summary, tmp_path: Path) -> None:
    svg = plots.plot_success_by_track(summary, tmp_path / "a.svg")
    assert b"<svg" in svg.read_bytes()[:500]
    assert plots.plot_success_by_track(summary, tmp_path / "a.pdf").read_bytes().startswith(b"%PDF")
    small = Image.open(plots.plot_success_by_track(summary, tmp_path / "small.png", dpi=100)).size
    large = Image.open(plots.plot_success_by_track(summary, tmp_path / "large.png", dpi=200)).size
    assert large[0] / small[0] == pytest.approx(2.0, rel=0.03) and large[1] / small[1] == pytest.approx(2.0, rel=0.03)
    with pytest.raises(ValueError, match="png, pdf, svg"):
        plots.plot_success_by_track(summary, tmp_path / "a.jpg")


def test_zero_bars_differ_from_cells_without_results_and_the_legend_covers_no_bar(summary) -> None:
    partial = summary[~((summary["agent"] == "hover") & (summary["env_id"] == "RaceObs-J-v0"))]
    assert (summary[(summary["agent"] == "hover") & (summary["variant"] == "default")]["success_rate"] == 0).all()
    fig = plots.success_by_track_figure(partial)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.texts]
    assert labels.count("0 %") == 2 and labels.count(plots.NOT_EVALUATED) == 1  # hover: S, Circle 0 %; J absent
    legend = ax.get_legend()
    assert "not evaluated" in legend.get_title().get_text()
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert legend.get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1  # beside the axes
    plots.plt.close(fig)


@pytest.fixture(scope="module")
def flown(tmp_path_factory) -> Path:
    """One saved trajectory each of planner and planner-fast on S's first public seed (about a second each), and a
    follow episode without one: the track figure's input, independent of the committed built-in folders."""
    from racebench.evaluation import Evaluator

    out = tmp_path_factory.mktemp("flown")
    for agent in ("planner", "planner-fast"):
        Evaluator(agent, ["RaceObs-S-v0"], episodes=1, out_dir=out / agent, save_trajectories=True).run(progress=False)
    Evaluator("follow", ["RaceObs-S-v0"], episodes=1, out_dir=out / "follow").run(progress=False)  # no trajectory
    return out


def test_track_figure_is_cropped_to_its_drawing(flown: Path, tmp_path: Path) -> None:
    path = plots.plot_track_3d(flown / "planner", "RaceObs-S-v0", tmp_path / "t.png", dpi=80)
    pixels = np.asarray(Image.open(path).convert("L"))
    blank_rows = np.all(pixels > 250, axis=1)
    height = len(blank_rows)
    top = np.argmax(~blank_rows)
    bottom = np.argmax(~blank_rows[::-1])
    assert top < 0.08 * height and bottom < 0.08 * height, (top, bottom, height)


def test_plot_writes_outside_the_committed_figures_by_default(tmp_path: Path, monkeypatch) -> None:
    parser = cli.build_parser()
    for name in ("plot", "curves"):
        sub = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)).choices[name]
        default = next(a.default for a in sub._actions if "--out" in a.option_strings)
        assert not str(default).startswith("results"), f"{name} would overwrite committed figures"
    committed = {p: p.stat().st_mtime_ns for p in (ROOT / "results" / "figures").iterdir()}
    monkeypatch.chdir(tmp_path)
    assert cli.main(["-q", "plot", *RESULTS, "--format", "svg", "--dpi", "100"]) == 0
    assert (tmp_path / "runs" / "figures" / "success_by_track.svg").is_file()
    assert committed == {p: p.stat().st_mtime_ns for p in (ROOT / "results" / "figures").iterdir()}
    with pytest.raises(SystemExit, match="--dpi"):
        cli.main(["-q", "plot", *RESULTS, "--dpi", "0"])


def test_curves_read_sb3s_own_progress_csv(tmp_path: Path) -> None:
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import configure

    run = tmp_path / "sb3-run"
    model = PPO("MlpPolicy", gym.make("RaceObs-S-Level1-v0", obs_mode="state"), n_steps=128, batch_size=64,
                n_epochs=1, seed=0, policy_kwargs={"net_arch": [8]}, device="cpu")  # fmt: skip
    model.set_logger(configure(str(run), ["csv"]))
    model.learn(384)
    progress = plots.read_progress(run / "progress.csv")
    assert progress["timesteps"].tolist() == [128, 256, 384]
    assert progress["mean_return"].notna().any() and progress["level"].isna().all()
    assert "rollout/success_rate" in (run / "progress.csv").read_text()  # the env's is_success reaches SB3
    out = plots.plot_training_curves([run], tmp_path / "curves.pdf")
    assert out.read_bytes().startswith(b"%PDF")
    assert progress["wall_s"].is_monotonic_increasing  # SB3's time/time_elapsed: --success reads it too
    assert plots.plot_success_curves([run], tmp_path / "success.png", dpi=60).is_file()
    assert cli.main(["-q", "curves", str(run), "--out", str(tmp_path / "c.png"), "--dpi", "60"]) == 0
    with pytest.raises(SystemExit, match="^racebench curves: .*png, pdf, svg"):
        cli.main(["-q", "curves", str(run), "--out", str(tmp_path / "c.jpg")])


def test_curriculum_ids_are_plotted_when_present(tmp_path: Path) -> None:
    from racebench.evaluation import Evaluator

    # Two agents flown on S's curriculum levels (the committed evaluations are on the paper's ids only).
    evals = [str(tmp_path / agent) for agent in ("hover", "planner-fast")]
    for folder in evals:
        agent = Path(folder).name
        Evaluator(agent, ["RaceObs-S-Level1-v0", "RaceObs-S-Level2-v0"], episodes=1, out_dir=folder).run(progress=False)
    assert cli.main(["-q", "plot", *evals, "--out", str(tmp_path), "--dpi", "60"]) == 0
    assert (tmp_path / "success_by_level.png").is_file()
    summary = read_summaries(evals)
    fig_path = plots.plot_success_vs(summary, "levels", tmp_path / "levels.svg")
    text = fig_path.read_text()
    assert "curriculum level" in text and "not evaluated" in text  # Circle and J have no level results here
    with pytest.raises(ValueError, match="no results on the levels variants"):
        plots.plot_success_vs(read_summaries(RESULTS), "levels", tmp_path / "none.png")


def test_success_curves_take_ppo_and_dagger_runs_alike(tmp_path: Path) -> None:
    dagger = tmp_path / "distill"
    dagger.mkdir()
    (dagger / "summary.json").write_text('{"method": "dagger", "config": {"name": "my-distill"}}')
    pd.DataFrame(
        {"iteration": [0, 1, 2], "beta": [1.0, 0.5, 0.25], "episodes": [9, 9, 9], "success_rate": [1.0, 0.4, 0.6],
         "mean_length": [90.0] * 3, "samples": [25_000, 50_000, 75_000], "loss": [0.1] * 3, "wall_s": [60, 120, 180]}
    ).to_csv(dagger / "progress.csv", index=False)  # fmt: skip
    progress = plots.read_progress(dagger / "progress.csv")
    assert progress["timesteps"].tolist() == [25_000, 50_000, 75_000]  # DAgger's samples are its env steps
    assert progress["level"].isna().all() and progress["mean_return"].isna().all()
    ppo = tmp_path / "ppo"
    ppo.mkdir()
    pd.DataFrame(
        {"timesteps": [2048, 4096, 6144, 8192], "episodes": [1, 2, 3, 4], "mean_return": [0.0] * 4,
         "success_rate": [None, 0.0, 0.9, 0.2], "level": [1, 1, 2, 2], "samples_per_s": [1e3] * 4,
         "wall_s": [2.0, 4.0, 6.0, 8.0]}
    ).to_csv(ppo / "progress.csv", index=False)  # fmt: skip
    assert [label for label, _ in plots._load_runs([dagger, ppo])] == ["my-distill", "ppo"]
    out = plots.plot_success_curves([dagger, ppo], tmp_path / "success.svg")
    svg = out.read_text()
    assert "my-distill" in svg and "L2" in svg  # the PPO run's promotion is marked
    assert cli.main(["-q", "curves", "--success", str(dagger), str(ppo), "--out", str(tmp_path / "s.png"),
                     "--window-steps", "25000", "--dpi", "60"]) == 0  # fmt: skip
    pd.read_csv(ppo / "progress.csv").drop(columns="wall_s").to_csv(ppo / "progress.csv", index=False)
    with pytest.raises(SystemExit, match="^racebench curves: ppo: progress.csv has no wall_s"):
        cli.main(["-q", "curves", "--success", str(ppo), "--out", str(tmp_path / "s.png")])
    pd.read_csv(dagger / "progress.csv").assign(success_rate=np.nan).to_csv(dagger / "progress.csv", index=False)
    with pytest.raises(SystemExit, match="^racebench curves: my-distill: progress.csv has no success rate"):
        cli.main(["-q", "curves", "--success", str(dagger), "--out", str(tmp_path / "s.png")])
    with pytest.raises(SystemExit, match="--window-steps must be >= 1"):
        cli.main(["-q", "curves", "--success", str(dagger), "--window-steps", "0"])


def test_seeds_of_one_config_are_drawn_as_a_mean_with_a_band(tmp_path: Path) -> None:
    # Two seeds whose success climbs linearly, one 20 points above the other and lasting longer: on the common
    # grid the mean is midway, the band spans exactly the two, and the grid stops at the shorter run's end.
    low = pd.DataFrame({"timesteps": [0.0, 100.0], "wall_s": [0.0, 10.0], "success": [0.0, 50.0]})
    high = pd.DataFrame({"timesteps": [0.0, 200.0], "wall_s": [0.0, 40.0], "success": [20.0, 120.0]})
    band = plots.seed_band([low, high], "timesteps", points=11)
    assert band["timesteps"].iloc[-1] == 100.0  # never extrapolated past a seed's last point
    np.testing.assert_allclose(band["min"], np.linspace(0, 50, 11))
    np.testing.assert_allclose(band["max"], np.linspace(20, 70, 11))
    np.testing.assert_allclose(band["mean"], np.linspace(10, 60, 11))
    assert plots.seed_band([low, high], "wall_s")["wall_s"].max() == 10.0
    for seed in (0, 1):
        run = tmp_path / f"distill-seed{seed}"
        run.mkdir()
        (run / "summary.json").write_text(json.dumps({"method": "dagger", "config": {"name": "my-distill",
                                                                                       "track": "J", "seed": seed}}))
        pd.DataFrame(
            {"iteration": [0, 1, 2], "success_rate": [1.0, 0.2 + 0.2 * seed, 0.6], "env_steps": [25e3, 50e3, 75e3],
             "samples": [25e3, 50e3, 75e3], "wall_s": [60 + seed, 120, 180]}
        ).to_csv(run / "progress.csv", index=False)  # fmt: skip
    svg = plots.plot_success_curves(sorted(tmp_path.glob("distill-seed*")), tmp_path / "seeds.svg").read_text()
    assert "my-distill (mean of 2 training seeds 0, 1; band: min–max)" in svg
    assert "Training success on J-shaped" in svg  # the track is named
    (tmp_path / "distill-seed1" / "summary.json").write_text(json.dumps({"config": {"name": "my-distill", "seed": 0}}))
    svg = plots.plot_success_curves(sorted(tmp_path.glob("distill-seed*")), tmp_path / "seeds.svg").read_text()
    assert "my-distill (mean of 2 runs, training seeds 0, 0; band: min–max)" in svg  # runs, not seeds, counted


def test_a_fine_tuning_is_drawn_after_the_student_it_started_from(tmp_path: Path) -> None:
    # student (DAgger, 75k steps, 180 s) -> fine-tuning (PPO, 8192 steps, 8 s) -> a second fine-tuning of that one;
    # an unrelated run keeps its own origin, and so does a fine-tuning whose student is not drawn.
    def run(name: str, summary: dict, rows: dict) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        (folder / "summary.json").write_text(json.dumps(summary))
        pd.DataFrame(rows).to_csv(folder / "progress.csv", index=False)
        return folder

    dagger_rows = {"iteration": [0, 1, 2], "success_rate": [1.0, 0.4, 0.6], "samples": [25_000, 50_000, 75_000],
                   "wall_s": [60, 120, 180]}  # fmt: skip
    ppo_rows = {"timesteps": [2048, 8192], "mean_return": [0.0, 1.0], "success_rate": [0.5, 0.7], "level": [3, 3],
                "wall_s": [2.0, 8.0]}  # fmt: skip
    student = run("student", {"method": "dagger", "checkpoint": "runs/student/s.zip"}, dagger_rows)
    tuned = run("tuned", {"config": "my-tuning", "checkpoint": "runs/tuned/t.zip", "init_from": "runs/student/s.zip"},
                ppo_rows)  # fmt: skip
    twice = run("twice", {"checkpoint": "runs/twice/t.zip", "init_from": "runs/tuned/t.zip"}, ppo_rows)
    other = run("other", {"checkpoint": "runs/other/o.zip", "init_from": "runs/elsewhere/x.zip"}, ppo_rows)
    runs = [twice, student, other, tuned]
    loaded = plots._load_runs(runs)
    assert [label for label, _ in loaded] == ["twice", "student", "other", "my-tuning"]  # a PPO summary: its config
    progresses = [progress for _, progress in loaded]
    assert plots.offsets_after_students(runs, progresses) == [
        (75_000 + 8192, 180 + 8.0),
        (0.0, 0.0),
        (0.0, 0.0),
        (75_000.0, 180.0),
    ]
    assert plots.offsets_after_students([tuned], progresses[3:]) == [(0.0, 0.0)]  # its student not given
    assert plots.plot_success_curves(runs, tmp_path / "chain.png", dpi=60).is_file()


def test_track_legend_sits_off_the_box_and_names_only_what_is_drawn(flown: Path, tmp_path: Path, monkeypatch) -> None:
    """The legend lies below the 3D drawing (it covered the box), and a line style that no flight shows (every
    flight successful) gets no entry (the grey "successful flight" was drawn nowhere)."""
    from matplotlib.transforms import Bbox

    kept = {}
    save = plots._save

    def capture(fig, path, dpi=plots.DEFAULT_DPI, bbox=None):
        renderer = fig.canvas.get_renderer()
        ax = fig.axes[0]
        box = Bbox.union([a.get_tightbbox(renderer) for a in (ax.xaxis, ax.yaxis, ax.zaxis)])
        kept["legend"], kept["box"] = fig.legends[0].get_window_extent(renderer), box
        kept["labels"] = [t.get_text() for t in fig.legends[0].get_texts()]
        return save(fig, path, dpi, bbox)

    from racebench.reporting import track_plot

    monkeypatch.setattr(track_plot, "_save", capture)
    plots.plot_track_3d([flown / "planner", flown / "planner-fast"], "RaceObs-S-v0", tmp_path / "t.png", dpi=60)
    assert kept["legend"].y1 <= kept["box"].y0 + 1  # below the drawing, not over it
    assert not any("flight" in label for label in kept["labels"])  # both successful: no line-style entries
    assert "planner (1/1 successful)" in kept["labels"]
    plots.plot_track_3d(flown / "planner", "RaceObs-S-v0", tmp_path / "one.png", dpi=60)
    assert "successful flight" in kept["labels"] and not any("failed" in label for label in kept["labels"])


def test_track_figure_draws_every_result_directory_by_agent(flown: Path, tmp_path: Path, capsys) -> None:
    both = [str(flown / name) for name in ("planner", "planner-fast")]
    hover = str(flown / "follow")  # no saved trajectories: named, not silently dropped
    args = ["-q", "plot", *both, hover, "--track-env", "RaceObs-S-v0", "--format", "svg", "--dpi", "60"]
    assert cli.main([*args, "--out", str(tmp_path)]) == 0
    svg = (tmp_path / "track_RaceObs-S-v0.svg").read_text()
    for agent in ("planner", "planner-fast"):  # a legend entry each, in its own colour
        assert f"{agent} (1/1 successful)" in svg
    assert f"no saved trajectories in {hover}" in capsys.readouterr().err


def test_agents_without_density_or_gate_shift_results_are_named(summary, tmp_path: Path, monkeypatch, capsys) -> None:
    partial = summary[
        ~((summary["agent"] == "hover") & summary["variant"].str.startswith("Density"))
        & ~((summary["agent"] == "planner") & summary["variant"].str.startswith("GateShift"))
    ]
    monkeypatch.setattr(cli, "_summaries", lambda results, command: partial)
    assert cli.main(["-q", "plot", "unused", "--out", str(tmp_path), "--format", "svg", "--dpi", "60"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert "success_vs_density.svg: no obstacle density results of hover; left out" in err
    assert "success_vs_gate_shift.svg: no gate shift results of planner; left out" in err


def test_learned_entries_join_the_figures_and_never_mix_env_versions(flown: Path, tmp_path: Path, monkeypatch) -> None:
    """``racebench plot --leaderboard``: the verified learned entries' own-track public cells beside the references
    (the fixture entry is self-reported, so it is shown only when that tier is asked for); records of another env
    version than the results' are refused, not drawn."""
    from leaderboard_fixtures import add, make_repo, write_hover_onnx, write_records

    from racebench.leaderboard import ranking
    from racebench.leaderboard.entries import MAIN_IDS

    board = make_repo(tmp_path / "repo")
    policy = write_hover_onnx(tmp_path / "repo" / "p" / "mine.onnx")
    for env_id in MAIN_IDS:
        write_records(tmp_path / "repo" / "results" / "mine", str(policy), env_id, 7, 10)
    add(board, str(policy), "mine", [tmp_path / "repo" / "results" / "mine"])
    assert ranking.entry_summary(board)[0].empty  # verified only, by default
    entries, versions = ranking.entry_summary(board, tiers=("self-reported",))
    assert set(entries["agent"]) == {"mine (self-reported, public seeds)"}
    assert sorted(entries["track"]) == sorted(TRACK_ORDER) and set(entries["success_rate"]) == {0.7}
    assert set(versions) == {"leaderboard entry mine"}
    monkeypatch.setattr(ranking, "entry_summary", lambda leaderboard: (entries, dict(versions)))
    args = ["-q", "plot", str(flown / "planner"), "--leaderboard", str(board), "--format", "svg", "--dpi", "60"]
    assert cli.main([*args, "--out", str(tmp_path / "figs")]) == 0  # fixture records: this env version
    assert "mine (self-reported, public seeds)" in (tmp_path / "figs" / "success_by_track.svg").read_text()
    older = {"leaderboard entry mine": [2] * len(versions["leaderboard entry mine"])}
    monkeypatch.setattr(ranking, "entry_summary", lambda leaderboard: (entries, older))
    with pytest.raises(SystemExit, match="--leaderboard: records of several env versions"):
        cli.main([*args, "--out", str(tmp_path / "figs2")])


def test_success_vs_cost_names_the_track_and_methods_and_keeps_its_legend_off_the_data(tmp_path: Path) -> None:
    run = tmp_path / "vision-ppo-J-seed0"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"config": "vision-ppo", "track": "J", "seed": 0}))
    (run / "config.yaml").write_text("name: vision-ppo-gate-centre\n")
    progress = {"timesteps": [1e5, 2e5, 3e5], "mean_return": [1.0, 2.0, 3.0], "success_rate": [0.1, 0.5, 0.6],
                "level": [1, 2, 2], "wall_s": [10.0, 20.0, 30.0]}  # fmt: skip
    pd.DataFrame(progress).to_csv(run / "progress.csv", index=False)
    outs = [tmp_path / "cost.svg", tmp_path / "cost.pdf"]
    assert cli.main(["-q", "curves", "--success", str(run), "--label", f"{run}=vision-ppo", "--out",
                     *map(str, outs), "--dpi", "60"]) == 0  # fmt: skip
    svg = outs[0].read_text()
    assert "Training success on J-shaped" in svg and "vision-ppo (training seed 0)" in svg
    assert "vision-ppo-gate-centre" not in svg  # the leaderboard's name given replaces the run's config name
    assert "curriculum promotion to level k" in svg  # the "L2" markers explained
    assert outs[1].read_bytes()[:4] == b"%PDF"
