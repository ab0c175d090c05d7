"""Leaderboard entries: methods of per-track policies, metadata validated, unique names, tiers computed not declared."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from leaderboard_fixtures import (
    ENV,
    GC_AGENT,
    SALT,
    add,
    evaluate,
    folder_records,
    make_repo,
    meta,
    rewrite_records,
    write_hover_onnx,
    write_records,
)

from racebench import cli
from racebench.agents import BUILTIN_PRIVILEGED, TRUSTED_CHECKPOINTS
from racebench.evaluation import EVAL_SEED_BASE
from racebench.evaluation.records import seal
from racebench.evaluation.seeds import salt_sha256
from racebench.leaderboard.entries import (
    DEFAULT_LEADERBOARD,
    MAIN_IDS,
    EntryError,
    load_config,
    load_entries,
    load_entry,
    policy_sha256,
    summarize_cells,
)
from racebench.leaderboard.site import entry_row

ROOT = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fixture repository: an ONNX policy (public and private records), the gc agent, the planner, hover."""
    root = tmp_path_factory.mktemp("repo")
    board = make_repo(root)
    onnx_file = write_hover_onnx(root / "policies" / "hover.onnx")
    (root / "policies" / "sneaky.py").write_text(GC_AGENT)
    sneaky = f"{root / 'policies' / 'sneaky.py'}:Sneaky"
    results = root / "results"
    evaluate(str(onnx_file), results / "onnx-public", 2)
    evaluate(str(onnx_file), results / "onnx-private", 2, "private")
    evaluate(sneaky, results / "sneaky-private", 2, "private", trust_code=True)
    evaluate("planner", results / "planner", 1)
    evaluate("hover", results / "hover", 1)
    add(board, str(onnx_file), "onnx-verified", [results / "onnx-public", results / "onnx-private"])
    add(board, str(onnx_file), "onnx-public-only", [results / "onnx-public"])
    add(board, sneaky, "sneaky", [results / "sneaky-private"])
    add(board, "planner", "planner", [results / "planner"])
    add(board, "hover", "hover", [results / "hover"])
    return board


def tiers(board: Path) -> dict[str, str]:
    """Entry name -> computed tier (no signed result in this fixture)."""
    config = load_config(board)
    return {e.name: entry_row(e, config).tier for e in load_entries(board)}


def test_tiers_are_computed_from_the_policy_kind_and_the_seed_set(board: Path) -> None:
    assert tiers(board) == {
        "onnx-verified": "self-reported",  # ONNX on the maintainers' private seeds, but nobody signed it
        "onnx-public-only": "self-reported",  # the same graph on public seeds only: fittable
        "sneaky": "self-reported",  # Python code, even on private seeds; it flew the privileged follower
        "planner": "reference",
        "hover": "self-reported",  # a built-in, but code: never verified
    }
    entries = {e.name: e for e in load_entries(board)}
    sneaky = entries["sneaky"]
    assert not any(r["privileged"] for r in sneaky.records)
    # It did cheat successfully (2 of 2 laps), so the tier is what protects the ranking; its private records are
    # not ranked at all (a self-reported entry ranks on public seeds, of which it has none).
    assert summarize_cells(sneaky.records)[ENV].successes == 2 and sneaky.own_cells() == {}
    config = load_config(board)
    assert salt_sha256(SALT) in config["private_salt_sha256"]  # the records' salt is the accepted one...
    unsigned = entry_row(entries["onnx-verified"], config)
    assert {c.seed_set for c in unsigned.cells.values()} <= {"public"}  # ...yet it ranks on public records only


def test_a_policy_is_judged_on_its_own_track() -> None:
    """A per-track method: each policy's own main id is its cell; its other main ids are cross-track only."""
    entries = {e.name: e for e in load_entries(ROOT / DEFAULT_LEADERBOARD, ["vision-distill", "planner"])}
    distill = entries["vision-distill"]
    assert distill.complete and distill.tracks == ("S", "Circle", "J")
    own = distill.own_cells()
    for track in ("S", "Circle", "J"):
        policy = distill.policies[track]
        assert all(r["policy_sha256"] == policy.sha256 for r in distill.public_records(track))
        assert own[f"RaceObs-{track}-v0"].n == 100  # its own track: 100 episodes, the others 50
    assert {k.split("→")[0] for k in distill.cross_cells()} == {"S", "Circle", "J"} and len(distill.cross_cells()) == 6
    assert entries["planner"].cross_cells() == {} and entries["planner"].complete


def test_add_validates_the_policy_and_refuses_duplicates(board: Path, tmp_path: Path) -> None:
    root = board.parents[1]
    onnx_file = root / "policies" / "hover.onnx"
    with pytest.raises(EntryError, match="already exists"):
        add(board, str(onnx_file), "ONNX-Verified", [root / "results" / "onnx-public"])  # case-insensitive
    with pytest.raises(EntryError, match="description must be one line"):
        from racebench.leaderboard.submit import add_entry

        add_entry(
            board, str(onnx_file), {**meta("x"), "description": "two\nlines"}, [str(root / "results" / "onnx-public")]
        )
    outside = write_hover_onnx(tmp_path / "elsewhere.onnx")
    with pytest.raises(EntryError, match="inside the repository"):
        add(board, str(outside), "outside", [root / "results" / "onnx-public"])
    with pytest.raises(EntryError, match="record of another policy"):
        add(board, str(onnx_file), "stolen", [root / "results" / "planner"])  # someone else's results
    with pytest.raises(EntryError, match="obs_mode"):
        from racebench.leaderboard.submit import add_entry

        add_entry(board, str(onnx_file), {**meta("bad"), "obs_mode": "lidar"}, [str(root / "results" / "onnx-public")])
    assert not (board / "stolen").exists() and not (board / "bad" / "entry.yaml").exists()


def test_a_committed_entry_whose_policy_changed_is_refused(board: Path) -> None:
    folder = board / "onnx-public-only"
    text = (folder / "entry.yaml").read_text()
    data = yaml.safe_load(text)
    line = data["policies"]["all"]
    try:
        swapped = {**data, "policies": {"all": {**line, "policy": "builtin:planner"}}}
        (folder / "entry.yaml").write_text(yaml.safe_dump(swapped))
        with pytest.raises(EntryError, match="record of another policy"):
            load_entry(folder)
        (folder / "entry.yaml").write_text(yaml.safe_dump({**data, "name": "renamed"}))
        with pytest.raises(EntryError, match="differs from its folder"):
            load_entry(folder)
        outside = {**data, "policies": {"all": {**line, "records": ["../outside"]}}}
        (folder / "entry.yaml").write_text(yaml.safe_dump(outside))
        with pytest.raises(EntryError, match="inside the repository"):
            load_entry(folder)
        (folder / "entry.yaml").write_text(yaml.safe_dump({**data, "policies": {"S": line, "all": line}}))
        with pytest.raises(EntryError, match="excludes per-track policies"):
            load_entry(folder)
    finally:
        (folder / "entry.yaml").write_text(text)


def test_cli_add_evaluates_and_errors_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    board = make_repo(tmp_path)
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("my-hover")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--evaluate", "1"]
    assert cli.main(argv) == 0
    entry = load_entry(board / "my-hover")
    assert entry.meta["policies"]["all"]["records"] == ["results/leaderboard/my-hover/eval-public-all"]
    assert sorted(entry.own_cells()) == sorted(MAIN_IDS) and all(c.n == 1 for c in entry.own_cells().values())
    assert "  all: {policy: 'builtin:hover'" in (board / "my-hover" / "entry.yaml").read_text()  # one line a policy
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: an entry named 'my-hover' already exists"):
        cli.main(argv)
    meta_file.write_text("name: [unclosed")
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: --meta .* unreadable"):
        cli.main(argv)
    with pytest.raises(SystemExit, match=r"^racebench leaderboard verify: no entry named \['nobody'\]"):
        cli.main(["leaderboard", "verify", "--entry", "nobody"])


def test_the_committed_entries_are_methods_with_descriptions() -> None:
    board = ROOT / DEFAULT_LEADERBOARD
    entries = {e.name: e for e in load_entries(board)}
    assert set(entries) == {
        "planner", "planner-fast", "follow", "hover", "vision-distill", "vision-distill-ppo", "vision-ppo", "state-ppo",
        "vision-com", "vision-no-avoid", "vision-one-step", "vision-no-gru",
    }  # fmt: skip
    for name in ("planner", "planner-fast", "follow", "hover"):
        assert entries[name].meta["policies"] == {"all": {"policy": f"builtin:{name}", "records": [f"results/{name}"]}}
    privileged = {name for name, flag in BUILTIN_PRIVILEGED.items() if flag}
    assert {n for n, e in entries.items() if e.privileged} == privileged
    checkpoints = {p.policy for e in entries.values() for p in e.policies.values() if p.kind == "sb3"}
    assert checkpoints <= {f"baselines/checkpoints/{p}" for p in TRUSTED_CHECKPOINTS.values()}
    assert {e.name for e in entries.values() if e.complete and not e.privileged} == {
        "hover", "vision-distill", "vision-distill-ppo", "vision-ppo", "state-ppo", "vision-com", "vision-no-avoid",
        "vision-one-step", "vision-no-gru",
    }  # fmt: skip
    # campaign runs 1-17: a policy per track
    campaign = ("vision-ppo", "state-ppo", "vision-com", "vision-no-avoid", "vision-one-step", "vision-no-gru")
    for name in campaign:
        assert entries[name].tracks == ("S", "Circle", "J"), name
    for entry in entries.values():
        assert entry.meta["description"].strip() and "\n" not in entry.meta["description"].strip()
        steps, wall = entry.budget()
        assert steps is not None and wall is not None, entry.name  # every budget is known
        for policy in entry.policies.values():
            assert policy.sha256 == policy_sha256(policy.policy, ROOT)
            assert policy.records and all(r["policy_sha256"] == policy.sha256 for r in policy.records)
    assert entries["state-ppo"].policies["S"].budget_source == "summary.json"
    assert entries["vision-distill"].privileged_teacher and not entries["vision-ppo"].privileged_teacher


def test_cherry_picked_episodes_are_refused(tmp_path: Path) -> None:
    board = make_repo(tmp_path)
    folder = write_records(tmp_path / "results" / "hover", "hover", ENV, 0, 3)
    rewrite_records(folder, lambda r: None if r["seed"] == EVAL_SEED_BASE else r)  # "flew 3, committed the 2 I liked"
    with pytest.raises(EntryError, match=r"not the first 2 seeds .*missing e\.g\. \[1000000\].*none picked"):
        add(board, "hover", "hover", [folder])


def test_records_of_uncommitted_code_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    board = make_repo(tmp_path)
    folder = write_records(tmp_path / "results" / "hover", "hover", ENV, 0, 3)
    records = folder_records(folder)
    record = records[1]
    assert not record["git_dirty"]
    rewrite_records(folder, lambda r: seal({**r, "git_dirty": True}) if r == record else r)  # a checkout with edits
    with pytest.raises(EntryError, match=rf"^hover: 1 of 3 records were made from uncommitted code .*{ENV} seed "
                       rf"{record['seed']}\)"):  # fmt: skip
        add(board, "hover", "hover", [folder])
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("hover")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--records", str(folder)]
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: hover: 1 of 3 records [^\n]*clean checkout$"):
        cli.main(argv)
    assert not (board / "hover").exists()
    rewrite_records(folder, lambda r: record if r["seed"] == record["seed"] else r)  # re-evaluated from a clean commit
    assert cli.main(argv) == 0 and load_entry(board / "hover").records


def test_cli_add_shows_progress_and_the_result_numbers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    board = make_repo(tmp_path)
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("hover-2")))
    monkeypatch.chdir(tmp_path)
    assert cli.main(["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--evaluate", "1"]) == 0
    out, err = capsys.readouterr()
    assert "hover-2-all: 100%" in err and "3/3" in err  # the progress bar, as `racebench evaluate` shows it
    for env_id in MAIN_IDS:  # hover passes no gate: 0 of 1, no lap
        numbers = "0/1 successes (0%, 95 % CI 0%–79%), mean lap – (no successful lap)"
        assert f"hover-2 all {env_id} [public]: {numbers}" in out
    assert "budget" not in err  # a built-in was not trained: nothing to warn about
    assert load_entry(board / "hover-2").policies["all"].budget_source == "none (not trained)"


def test_add_warns_of_a_missing_budget_and_meta_sets_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    board = make_repo(tmp_path)
    onnx_file = write_hover_onnx(tmp_path / "policies" / "hover.onnx")
    folder = evaluate(str(onnx_file), tmp_path / "results" / "onnx-public", 1)
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("no-budget")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", str(onnx_file), "--meta", str(meta_file), "--records", str(folder)]
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "no-budget: the all policy's training budget is unknown" in err
    assert "set it in --meta: policies: {all: {steps: N, wall_clock_s: SECONDS}}" in err
    assert load_entry(board / "no-budget").policies["all"].budget_source == "unknown"
    meta_file.write_text(yaml.safe_dump({**meta("budget"), "policies": {"all": {"steps": 1000, "wall_clock_s": 9.5}}}))
    assert cli.main(argv) == 0
    assert "budget" not in capsys.readouterr().err
    policy = load_entry(board / "budget").policies["all"]
    assert (policy.steps, policy.wall_clock_s, policy.budget_source) == (1000, 9.5, "entry.yaml")
    meta_file.write_text(yaml.safe_dump({**meta("bad-budget"), "policies": {"all": {"records": ["x"]}}}))
    with pytest.raises(SystemExit, match=r"policies\.all may hold only \['steps', 'wall_clock_s'\]"):
        cli.main(argv)
    meta_file.write_text(yaml.safe_dump({**meta("bad-track"), "policies": {"S": {"steps": 1}}}))
    with pytest.raises(SystemExit, match=r"policies\.S: no --policy for that track"):
        cli.main(argv)


def test_add_refuses_records_git_ignores(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import subprocess

    board = make_repo(tmp_path)
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / ".gitignore").write_text("runs/\n")
    folder = write_records(tmp_path / "runs" / "eval" / "hover", "hover", ENV, 0, 3)
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("ignored")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--records", str(folder)]
    with pytest.raises(SystemExit) as raised:
        cli.main(argv)
    message = str(raised.value)
    assert "\n" not in message and message.startswith("racebench leaderboard add: ignored: records folder")
    assert "'runs/eval/hover' is ignored by git (.gitignore:1:runs/)" in message
    assert "a pull request cannot carry its records" in message
    assert not (board / "ignored").exists()
    tracked = write_records(tmp_path / "results" / "hover", "hover", ENV, 0, 3)  # the same records, carriable
    assert cli.main([*argv[:-1], str(tracked)]) == 0


def test_an_onnx_policy_is_named_once(board: Path) -> None:
    from racebench.leaderboard.entries import Entry, Policy

    entries = {e.name: e for e in load_entries(board)}
    assert entries["onnx-public-only"].policies["all"].onnx == entries["onnx-public-only"].policies["all"].policy
    assert entries["onnx-public-only"].kind == "onnx"  # was "onnx + onnx": the policy is its own export
    assert entries["planner"].kind == "builtin"
    zips = {t: Policy(t, f"{t}.zip", "0" * 64, [], onnx=f"{t}.onnx") for t in ("S", "Circle", "J")}
    assert Entry({}, board, board, zips).kind == "sb3 + onnx"
    assert Entry({}, board, board, {**zips, "J": Policy("J", "J.onnx", "0" * 64, [], onnx="J.onnx")}).kind == "onnx/sb3"
