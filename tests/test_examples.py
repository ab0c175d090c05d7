"""The documentation's snippets run as written: the README's quickstart, the stock stable-baselines3 snippet of
docs/training.md (fewer steps) and the CleanRL-style example; the README's shape and every relative link of the
documentation."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from scripts_loader import load_script

ROOT = Path(__file__).parents[1]


def page_block(page: str, heading: str) -> str:
    """The first ```python block of the section under ``## heading`` of the Markdown page ``page``."""
    text = (ROOT / page).read_text()
    section = text.split(f"\n## {heading}\n", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_stock_sb3_snippet_builds_a_cnn(tmp_path, monkeypatch) -> None:
    code = page_block("docs/training.md", "Train with stock stable-baselines3")
    # Only the step budget changes: one rollout instead of the page's few thousand steps.
    code, count = re.subn(r"^steps = [\d_]+", "steps = 512", code, flags=re.M)
    assert count == 1, "the snippet must set its budget in one `steps = N` line"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs__"}
    exec(compile(code, "docs/training.md", "exec"), namespace)
    model = namespace["model"]
    convs = [m for m in model.policy.features_extractor.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) >= 3, "stock SB3 must give the depth image a CNN (NatureCNN)"
    assert model.num_timesteps >= 512
    saved = list(tmp_path.glob("*.zip"))
    assert saved, "the snippet saves the model"


def load_cleanrl():
    return load_script("cleanrl_ppo")


def test_cleanrl_ppo_trains_on_a_level1_id(tmp_path) -> None:
    cleanrl = load_cleanrl()
    out = tmp_path / "agent.pt"
    args = ["--env-id", "RaceObs-S-Level1-v0", "--total-timesteps", "384", "--num-envs", "3", "--num-steps", "64"]
    stats = cleanrl.main([*args, "--update-epochs", "2", "--save", str(out)])
    assert stats["global_step"] == 384
    for key in ("policy_loss", "value_loss", "approx_kl"):
        assert np.isfinite(stats[key]), key
    assert stats["clipfrac"] >= 0.0
    # The saved network is the trained one: it differs from a fresh one built with the same seed.
    trained = torch.load(out)
    torch.manual_seed(0)
    import gymnasium as gym

    envs = gym.make_vec("RaceObs-S-Level1-v0", num_envs=1, depth_format="uint8", renderer="raycast")
    fresh = cleanrl.Agent(envs).state_dict()
    envs.close()
    assert set(trained) == set(fresh)
    assert any(not torch.equal(trained[k], fresh[k]) for k in fresh)


def test_cleanrl_ppo_rejects_a_budget_below_one_rollout() -> None:
    with pytest.raises(ValueError, match="total_timesteps"):
        load_cleanrl().main(["--total-timesteps", "10", "--num-envs", "2", "--num-steps", "64"])


def test_readme_first_python_snippet_runs_as_written(tmp_path, monkeypatch, capsys) -> None:
    text = (ROOT / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)  # the first one: gym.make, step, export
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
    assert (tmp_path / "scene.glb").stat().st_size > 1000
    assert "prog" in capsys.readouterr().out  # the reward terms it prints


SETUP = [  # README.md's first 8 lines, exactly: .ci/run and tests/test_records.py rely on them
    "# racebench",
    "",
    "```bash",
    "# 1. set up and evaluate the built-in privileged planner on the paper's three tracks (Table II suite)",
    "pip install torch==2.13.0 && pip install -e . && racebench evaluate --agent planner --envs main",
    "# 2. set up and run the tests",
    "pip install torch==2.13.0 && pip install -e '.[test,ray]' && python -m pytest -q -n 2 -m \"not ray\" && "
    "python -m pytest -q -m ray -p no:xdist",
    "```",
]


def test_the_readme_is_a_front_page() -> None:
    """README.md: at most 250 lines, opening with the two set-up commands as .ci/run and the tests use them, and
    the results-at-a-glance block (whose body may be generated) within its first 80 lines."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; details belong in docs/"
    assert lines[:8] == SETUP, "README.md must open with the title and the two set-up commands, unchanged"
    begin, end = "<!-- results-at-a-glance:begin -->", "<!-- results-at-a-glance:end -->"
    assert lines.count(begin) == 1 and lines.count(end) == 1, "one results-at-a-glance block, markers on own lines"
    assert lines.index(begin) < lines.index(end) < 80, "the results-at-a-glance block must end within line 80"
    assert lines[lines.index(begin) - 2] == "## Results at a glance", "the block sits under its heading"


def tracked_markdown() -> list[str]:
    """Every Markdown file git tracks (without git, e.g. an unpacked archive: every one outside ignored folders)."""
    try:
        listed = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--", "*.md"], capture_output=True,
                                check=True).stdout.decode().split("\0")  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "runs", "build", "dist", ".pytest_cache", ".ruff_cache"}
        listed = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*.md") if not skip & set(p.relative_to(ROOT).parts)]
    return sorted(page for page in listed if page and (ROOT / page).is_file())


DOC_PAGES = tracked_markdown()


def test_the_link_check_covers_every_tracked_markdown_file() -> None:
    pages = set(DOC_PAGES)
    assert {"README.md", "results/at_a_glance.md", "baselines/experiments/distill-select/README.md"} <= pages
    assert len(pages) > 40 and not any(page.startswith("runs/") for page in pages)


@pytest.mark.parametrize("page", DOC_PAGES)
def test_every_relative_link_resolves(page: str) -> None:
    """Every relative link and image of the page names a file or folder of the repository, and every #anchor into a
    Markdown page names one of its headings (GitHub's slugs)."""

    def slug(heading: str) -> str:
        return re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", "")).replace(" ", "-")

    text = re.sub(r"```.*?```", "", (ROOT / page).read_text(), flags=re.S)  # links in code blocks are not links
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # https:, mailto:
        path, _, anchor = target.partition("#")
        file = (ROOT / page).parent / path if path else ROOT / page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md":
            headings = re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", file.read_text(), flags=re.S), re.M)
            if anchor not in {slug(h) for h in headings}:
                broken.append(target)
    assert not broken, f"{page}: links to nothing: {broken}"


def test_the_ab_report_reads_run_folders_and_applies_the_stated_rule(tmp_path) -> None:
    """scripts/ab_report.py: rows from a sweep's run folders; the decision only with 3 finished runs per arm."""

    report = load_script("ab_report")

    def run(name: str, to_l3: int, successes: int, finished: bool = True) -> None:
        folder = tmp_path / name
        folder.mkdir()
        promotions = [{"level": 2, "timestep": to_l3 // 2, "wall_s": 60.0, "by": "bar"},
                      {"level": 3, "timestep": to_l3, "wall_s": 120.0, "by": "bar"}]  # fmt: skip
        (folder / "curriculum.json").write_text(json.dumps({"level": 3, "promotions": promotions, "solved": None}))
        (folder / "progress.csv").write_text("timesteps,success_rate,level,samples_per_s\n4000000,0.7,3,900\n")
        if finished:
            evaluation = {"n": 50, "successes": successes, "success_rate": successes / 50, "lap_time_mean": 4.0}
            (folder / "summary.json").write_text(json.dumps({"timesteps": 4000000, "eval": evaluation}))

    for seed, (a, b) in enumerate([(35, 34), (36, 33), (34, 36)]):
        run(f"vision-ppo-S-seed{seed}", 2_000_000, a)
        run(f"vision-ppo-fast-S-seed{seed}", 1_900_000, b, finished=seed < 2)
    table = pd.DataFrame([report.run_row(p) for p in sorted(tmp_path.iterdir())])
    assert "no decision yet" in report.decide(table, "vision-ppo", "vision-ppo-fast")  # 2 of 3 finished
    run_row = table.set_index("run").loc["vision-ppo-S-seed0"]
    assert run_row["steps_to_L3"] == 2_000_000 and run_row["eval_ci"].startswith("[")
    run("extra", 0, 0)  # not an arm's run: ignored
    (tmp_path / "vision-ppo-fast-S-seed2" / "summary.json").write_text(
        json.dumps(
            {"timesteps": 4000000, "eval": {"n": 50, "successes": 36, "success_rate": 0.72, "lap_time_mean": 4.0}}
        )
    )
    table = pd.DataFrame([report.run_row(p) for p in sorted(tmp_path.iterdir())])
    # Means 70 % vs 68.7 %, spreads 4 and 6 points: within; 1.9M steps to level 3 vs 2.0M: not higher.
    assert report.decide(table, "vision-ppo", "vision-ppo-fast").endswith("vision-ppo-fast becomes the default")
    for seed in range(3):  # the variant now needs more steps to level 3: it stays a variant
        state = tmp_path / f"vision-ppo-fast-S-seed{seed}" / "curriculum.json"
        state.write_text(state.read_text().replace("1900000", "2100000"))
    table = pd.DataFrame([report.run_row(p) for p in sorted(tmp_path.iterdir())])
    assert report.decide(table, "vision-ppo", "vision-ppo-fast").endswith("stays a named variant")


def test_gate_crossings_finds_where_a_policy_crosses_each_gate(tmp_path, monkeypatch, capsys) -> None:
    """scripts/gate_crossings.py on the expert's own saved flights: it crosses where it planned to."""
    from racebench import cli

    out = tmp_path / "eval"
    assert cli.main(["-q", "evaluate", "--agent", "planner-fast", "--envs", "RaceObs-S-v0", "--episodes", "2",
                     "--out", str(out), "--save-trajectories"]) == 0  # fmt: skip
    script = load_script("gate_crossings")
    monkeypatch.setattr(sys, "argv", ["gate_crossings.py", str(out), "--env", "RaceObs-S-v0"])
    capsys.readouterr()
    script.main()
    lines = capsys.readouterr().out.strip().splitlines()[2:]
    assert [line.split(", ")[:3] for line in lines] == [[str(g), "2", "0"] for g in range(4)]  # 4 gates, no hit
    for line in lines:  # flown within a few cm of the planned line at every gate
        cells = [float(c.split(" ")[0]) for c in line.split(", ")[3:]]
        assert abs(cells[0] - cells[2]) < 0.08 and abs(cells[1] - cells[3]) < 0.08, line
    monkeypatch.setattr(sys, "argv", ["gate_crossings.py", str(tmp_path)])
    with pytest.raises(SystemExit, match="no trajectories"):
        script.main()


def test_paired_outcomes_counts_the_discordant_pairs_and_tests_them_exactly(tmp_path, monkeypatch, capsys) -> None:
    module = load_script("paired_outcomes")
    # Seeds 0-9 on one id: A finishes 0-5, B finishes 2-9; so 2 only by A (0, 1), 4 only by B (6-9).
    for name, wins in (("a", range(0, 6)), ("b", range(2, 10))):
        (tmp_path / name).mkdir()
        rows = [{"env_id": "RaceObs-S-v0", "seed": s, "success": s in wins, "lap_time": 4.0 if s in wins else None,
                 "crash_reason": None if s in wins else "obstacle:3"} for s in range(10)]  # fmt: skip
        pd.DataFrame(rows).to_csv(tmp_path / name / "episodes.csv", index=False)
    monkeypatch.setattr("sys.argv", ["paired_outcomes", str(tmp_path / "a"), str(tmp_path / "b")])
    module.main()
    out = capsys.readouterr().out
    assert "6/10 (60 % [31-83])" in out and "8/10 (80 % [49-94])" in out  # Wilson intervals
    assert "failures {'obstacle': 4}" in out
    assert "2 finished only by the first, 4 only by the second; exact McNemar p = 0.69" in out  # binomtest(4, 6)
    monkeypatch.setattr("sys.argv", ["paired_outcomes", str(tmp_path / "a"), str(tmp_path / "missing")])
    with pytest.raises(SystemExit, match="missing/episodes.csv does not exist"):
        module.main()


def test_failure_overlap_finds_failures_piled_on_the_same_scenes(tmp_path, monkeypatch, capsys) -> None:
    module = load_script("failure_overlap")
    # Three agents, 20 scenes: all fail scenes 0-3 (so each finishes 16 of 20), the rest they all finish.
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
        rows = [{"env_id": "RaceObs-S-v0", "seed": s, "success": s >= 4, "crash_reason": None if s >= 4 else "gate:2"}
                for s in range(20)]  # fmt: skip
        pd.DataFrame(rows).to_csv(tmp_path / name / "episodes.csv", index=False)
    monkeypatch.setattr("sys.argv", ["failure_overlap", *(str(tmp_path / n) for n in "abc"), "--permutations", "500"])
    module.main()
    out = capsys.readouterr().out
    assert "3 agents on 20 shared scenes (success 80 %, 80 %, 80 %)" in out
    assert "scenes, observed:           16      0      0      4" in out
    assert "failed by all 3: 4 scenes, seeds 0, 1, 2, 3; ended by {'gate': 12}" in out
    assert "permutation p = 0.0020 (500 shuffles)" in out  # no shuffle piles them up as much: (0 + 1) / 501
    # Independent failures (each agent fails other scenes): no evidence of overlap.
    result = module.overlap(np.eye(20, 3, dtype=bool) == 0, 500, np.random.default_rng(0))
    assert result["observed"].tolist() == [17, 3, 0, 0] and result["p"] == 1.0
    monkeypatch.setattr("sys.argv", ["failure_overlap", str(tmp_path / "a")])
    with pytest.raises(SystemExit, match="at least two evaluation folders"):
        module.main()


def test_seeds_report_takes_the_mean_and_spread_of_validated_records(tmp_path, monkeypatch, capsys) -> None:
    module = load_script("seeds_report")
    # Three committed 100-episode evaluations on S stand in for three seeds: 76, 69 and 62 laps finished.
    folders = [ROOT / "baselines/experiments" / name / "eval"
               for name in ("distill-wide-berth", "distill-stateless-teacher", "distill-teacher-v3")]  # fmt: skip
    table = module.seed_table(folders)
    assert table["successes"].tolist() == [76, 69, 62] and (table["n"] == 100).all()
    summary = module.across_seeds(table).iloc[0]
    assert (summary["seeds"], round(summary["sr_mean"], 3), round(summary["sr_spread"], 3)) == (3, 0.69, 0.14)
    assert summary["lap_time_mean"] == pytest.approx(table["lap_time_mean"].mean())
    monkeypatch.setattr("sys.argv", ["seeds_report", *map(str, folders)])
    module.main()
    out = capsys.readouterr().out
    assert "76/100 = 76 % [67–83]" in out and "| RaceObs-S-v0 | 3 | 69.0 % | 62–76 % (14 points) |" in out
    monkeypatch.setattr("sys.argv", ["seeds_report", str(tmp_path)])
    with pytest.raises(SystemExit, match="^seeds_report: no evaluation records at"):
        module.main()


def test_crash_visibility_counts_the_hit_obstacles_pixels_and_replays_crashes(tmp_path, monkeypatch, capsys) -> None:
    import gymnasium as gym

    from racebench.evaluation import Evaluator
    from racebench.sim.raycast import BatchDepthRenderer

    module = load_script("crash_visibility")
    env = gym.make("RaceObs-S-v0")
    env.reset(seed=1_000_000)
    race = env.unwrapped
    scene, renderer = race.scene, BatchDepthRenderer(race.camera)
    target = scene.obstacles[0].position
    towards = np.arctan2(*(target[:2] - (target[:2] + [3.0, 0.0]))[::-1])  # yaw from 3 m in +x, facing it
    poses = []
    for yaw in (towards, towards + np.pi):  # facing the obstacle, then facing away from it
        c, s = np.cos(yaw), np.sin(yaw)
        poses.append(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    at = np.array([target[0] + 3.0, target[1], target[2]])
    pixels = module.obstacle_pixels(renderer, scene, 0, np.stack([at, at]), np.stack(poses))
    assert pixels[0] > 10 and pixels[1] == 0  # an obstacle 3 m ahead covers pixels; behind the camera, none
    env.close()

    # `follow` flies the gate axes blind to obstacles: two of these four S scenes end on one (results/follow).
    Evaluator("follow", ["RaceObs-S-v0"], episodes=4, out_dir=tmp_path / "eval").run(progress=False)
    monkeypatch.setattr("sys.argv", ["crash_visibility", str(tmp_path / "eval"), "--agent", "follow"])
    module.main()
    out = capsys.readouterr().out
    assert re.search(r"RaceObs-S-v0\): 2 obstacle crashes replayed of 2; the obstacle was in view in the last second "
                     r"before 2", out)  # fmt: skip


def test_crash_geometry_finds_an_obstacle_blind_agent_unmoved_by_what_it_hits(tmp_path, monkeypatch, capsys) -> None:
    """`follow` ignores obstacles: flown again with the hit obstacle taken out of the scene, its flight is the same
    to the step of the hit, and passes where the obstacle stood within the drone's collision radius."""
    from racebench.evaluation import Evaluator

    monkeypatch.syspath_prepend(str(ROOT / "scripts"))  # crash_geometry imports crash_visibility's replay
    module = load_script("crash_geometry")
    Evaluator("follow", ["RaceObs-S-v0"], episodes=4, out_dir=tmp_path / "eval").run(progress=False)
    argv = ["crash_geometry", str(tmp_path / "eval"), "--agent", "follow", "--successes", "1", "--without-obstacle"]
    monkeypatch.setattr("sys.argv", argv)
    module.main()
    out = capsys.readouterr().out
    assert "RaceObs-S-v0): 2 obstacle crashes replayed of 2" in out
    rows = [dict(kv.rsplit(" ", 1) for kv in line.split(", ")) for line in out.splitlines() if line.startswith("seed ")]
    assert len(rows) == 2
    for row in rows:
        assert float(row["apart_at_hit"]) == 0.0 and float(row["blind_pass"]) <= 0.12
        assert float(row["line_clearance"]) > 0.3  # the teacher's line keeps its berth from what follow hits
    assert "finished laps (1), every step" in out


def test_ensemble_agent_averages_its_members_actions_and_pins_them(tmp_path, monkeypatch, capsys) -> None:
    """scripts/ensemble_agent.py: one member acts as that member alone; two act as their mean, per episode
    and in lockstep; a member whose bytes differ from its pinned sha256 is refused."""
    import gymnasium as gym

    from racebench.agents import AgentLoadError, SB3Agent

    module = load_script("ensemble_agent")
    paths = [str(ROOT / "baselines" / "checkpoints" / f"vision-distill-{t}" / f"vision-distill-{t}.zip") for t in "SJ"]
    digests = [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths]
    env = gym.make("RaceObs-S-v0")
    observations = [env.reset(seed=seed)[0] for seed in (1, 2)]
    env.close()

    singles = [SB3Agent(p, trust_code=True) for p in paths]
    for single in singles:
        single.start(2)
    expected = np.mean([single.act_batch(observations) for single in singles], axis=0)
    pair = module.EnsembleAgent(paths, digests)
    assert pair.obs_mode == "vision" and pair.privileged is False
    pair.start(2)
    np.testing.assert_allclose(pair.act_batch(observations), expected, rtol=0, atol=1e-6)

    alone = module.EnsembleAgent(paths[:1], digests[:1])
    alone.reset()
    singles[0].reset()
    np.testing.assert_array_equal(alone.act(observations[0]), np.asarray(singles[0].act(observations[0])).reshape(-1))

    with pytest.raises(AgentLoadError, match="expected"):
        module.EnsembleAgent(paths, digests[::-1])
    with pytest.raises(AgentLoadError, match="2 checkpoints but 1"):
        module.EnsembleAgent(paths, digests[:1])
    with pytest.raises(AgentLoadError, match="does not exist"):
        module.EnsembleAgent([str(tmp_path / "none.zip")], ["0" * 64])

    monkeypatch.setattr("sys.argv", ["ensemble_agent", *paths])
    module.main()
    assert json.loads(capsys.readouterr().out) == {"checkpoints": paths, "sha256": digests}


def test_data_scaling_solves_the_logistic_fit_for_the_steps_to_a_target(tmp_path, monkeypatch) -> None:
    module = load_script("data_scaling")
    from scipy.special import expit, logit

    # 10 scenes: 3 finished at 1,000 steps, 8 at 4,000 (two doublings). Two points: the fit goes through both
    # rates, so b = (logit 0.8 - logit 0.3) / 2 per doubling, and 50 % lies at logit 0.3 + b x = 0.
    for steps, wins in ((1000, 3), (4000, 8)):
        (tmp_path / str(steps)).mkdir()
        rows = [{"env_id": "RaceObs-S-v0", "seed": s, "success": s < wins} for s in range(10)]
        pd.DataFrame(rows).to_csv(tmp_path / str(steps) / "episodes.csv", index=False)
    points = [f"{s}:{tmp_path / str(s)}" for s in (1000, 4000)]
    row = module.project(module.load_points(points), 0.5, 200, 0, predict=(1000, 4000)).iloc[0]
    slope = (logit(0.8) - logit(0.3)) / 2
    assert row["sr_1000"] == 0.3 and row["sr_4000"] == 0.8
    assert row["steps_to_target"] == pytest.approx(1000 * 2 ** (-logit(0.3) / slope), rel=1e-4)  # ~1,692
    assert row["gain_per_doubling"] == pytest.approx(0.8 - expit(logit(0.8) - slope), abs=1e-4)
    assert row["ci_low"] <= row["steps_to_target"] <= row["ci_high"]
    assert (row["fit_1000"], row["fit_4000"]) == pytest.approx((0.3, 0.8), abs=1e-4)  # through both points
    assert row["fit_4000_low"] <= 0.8 <= row["fit_4000_high"]
    assert module.steps_to_target(0.0, -0.1, 0.9) == float("inf")  # a falling fit never gets there
    monkeypatch.setattr("sys.argv", ["data_scaling", "many:" + str(tmp_path / "1000"), points[1]])
    with pytest.raises(SystemExit, match="'many:.*' is not STEPS:FOLDER"):
        module.main()
    monkeypatch.setattr("sys.argv", ["data_scaling", "--predict", "2e6", *points])
    with pytest.raises(SystemExit, match="--predict takes step counts"):
        module.main()
    monkeypatch.setattr("sys.argv", ["data_scaling", points[0]])
    with pytest.raises(SystemExit, match="two or more step counts"):
        module.main()
