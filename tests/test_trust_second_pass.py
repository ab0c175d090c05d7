"""Issue 70, trust second pass: nothing an outsider can write (a folder, a pull request, an entry) runs code or
reaches outside the repository. Each code-running test plants a payload that creates a marker file, shows that it
is refused by default, and that it does run once explicitly trusted (so the payload is live)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from payloads import evil_sb3_zip

from racebench import cli
from racebench.agents.trust import WRITTEN_FILE, _sha256_bytes, trust_store, written_sha256

# ------------------------------------------------ A: a folder's written.json cannot vouch for itself


def _planted_run(run: Path, marker: Path, name: str = "state-ppo_999424_steps.zip") -> Path:
    """A run folder with a payload checkpoint that its own written.json lists, as a pull request could commit."""
    (run / "checkpoints").mkdir(parents=True)
    evil = evil_sb3_zip(run / "checkpoints" / name, marker)
    (run / WRITTEN_FILE).write_text(json.dumps({f"checkpoints/{name}": _sha256_bytes(evil.read_bytes())}))
    return evil


def test_a_train_resume_refuses_a_payload_that_its_folders_written_json_lists(tmp_path: Path) -> None:
    marker, run = tmp_path / "ran", tmp_path / "run"
    evil = _planted_run(run, marker)
    assert written_sha256(run) == frozenset()  # listed, but this machine never wrote it
    argv = ["train", "--config", "state-ppo", "--num-processes", "1", "--steps", "64",
            "--eval-episodes", "0", "--resume", str(evil), "--out", str(run)]  # fmt: skip
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    message = str(exc.value.code)
    assert "--trust-code" in message and "racebench trust" in message and "\n" not in message
    assert not marker.exists()
    # The maintainer's explicit step: `racebench trust RUN_DIR` adopts the folder's list; the payload then runs.
    assert cli.main(["trust", str(run)]) == 0
    assert (trust_store() / _sha256_bytes(evil.read_bytes())).is_file()
    with pytest.raises((SystemExit, Exception)):
        cli.main(argv)
    assert marker.exists()


def test_a_trust_adopts_only_listed_files_with_their_listed_bytes(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "a.zip").write_bytes(b"a")
    (run / "b.zip").write_bytes(b"b")
    (run / WRITTEN_FILE).write_text(json.dumps({"a.zip": _sha256_bytes(b"a"), "b.zip": _sha256_bytes(b"other")}))
    assert cli.main(["trust", str(run)]) == 0
    assert written_sha256(run) == {_sha256_bytes(b"a")}
    with pytest.raises(SystemExit, match=r"^racebench trust: .*no written\.json"):
        cli.main(["trust", str(tmp_path / "nowhere")])


def test_a_sweep_refuses_a_listed_payload_checkpoint(tmp_path: Path) -> None:
    from test_ray_sweep import write_sweep

    from racebench.training.sweep import load_sweep, run_sweep

    path = write_sweep(tmp_path, tracks=["S"])
    run, marker = tmp_path / "out" / "tiny-S-seed0", tmp_path / "ran"
    _planted_run(run, marker, "tiny_128_steps.zip")
    rows = run_sweep(load_sweep(path))
    assert rows[0]["status"].startswith("failed: checkpoint") and "racebench trust" in rows[0]["status"]
    assert not marker.exists()
    # A swapped final policy that written.json lists, its summary marked for re-evaluation: refused too.
    (run / "checkpoints" / "tiny_128_steps.zip").unlink()
    evil = evil_sb3_zip(run / "tiny-S.zip", marker)
    (run / WRITTEN_FILE).write_text(json.dumps({"tiny-S.zip": _sha256_bytes(evil.read_bytes())}))
    (run / "summary.json").write_text(json.dumps({"timesteps": 256, "checkpoint": str(evil)}))
    rows = run_sweep(load_sweep(path))
    assert rows[0]["status"].startswith("failed: agent") and "--trust-code" in rows[0]["status"]
    assert not marker.exists()
    assert cli.main(["trust", str(run)]) == 0  # explicitly trusted, it is loaded (and runs)
    run_sweep(load_sweep(path))
    assert marker.exists()


def test_a_paper_tables_validation_curve_refuses_a_listed_payload(tmp_path: Path) -> None:
    marker, run = tmp_path / "ran", tmp_path / "state-ppo-S-seed0"
    _planted_run(run, marker)
    pd.DataFrame({"timesteps": [999_424], "mean_return": [3.0]}).to_csv(run / "progress.csv", index=False)
    argv = ["paper-tables", "--root", str(tmp_path), "--out", str(tmp_path / "results"), "--no-readme",
            "--validation-curve", str(run)]  # fmt: skip
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert "--trust-code" in str(exc.value.code) and "\n" not in str(exc.value.code)
    assert not marker.exists()
    with pytest.raises((SystemExit, Exception)):
        cli.main([*argv, "--trust-code"])
    assert marker.exists()


# ------------------------------------------------ B: a module:Class spec is resolved without importing anything

ROOT = Path(__file__).resolve().parents[1]


def _evil_package(folder: Path, name: str, marker: Path) -> None:
    """A package whose ``__init__.py`` creates ``marker`` when imported, with a module ``mod`` holding ``X``."""
    package = folder / name
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    (package / "mod.py").write_text(
        "class X:\n    obs_mode = 'state'\n\n    def __init__(self, **kw):\n        pass\n\n"
        "    def reset(self):\n        pass\n\n    def act(self, obs):\n        return None\n"
    )


@pytest.fixture
def evil_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    import sys

    name = f"evilpkg_{abs(hash(tmp_path)) % 10**8}"
    marker = tmp_path / "ran"
    _evil_package(tmp_path / "code", name, marker)
    monkeypatch.syspath_prepend(str(tmp_path / "code"))
    yield name, marker
    for module in [m for m in sys.modules if m == name or m.startswith(f"{name}.")]:
        del sys.modules[module]


def test_b_a_dotted_spec_runs_nothing_before_the_trust_check(evil_package) -> None:
    from racebench.agents import UntrustedCodeError, load_agent, policy_identity

    name, marker = evil_package
    spec = f"{name}.mod:X"
    assert policy_identity(spec).kind == "python"
    assert not marker.exists()
    with pytest.raises(UntrustedCodeError, match="--trust-code"):
        load_agent(spec)
    assert not marker.exists()
    for argv in (["evaluate", "--agent", spec, "--envs", "RaceObs-S-v0", "--episodes", "1"],
                 ["fly", "--agent", spec], ["fly", "--agent", spec, "--agent-kwargs", '{"k": 1}']):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert "--trust-code" in str(exc.value.code) and "\n" not in str(exc.value.code)
        assert not marker.exists(), argv
    load_agent(spec, trust_code=True)  # trusted, the package is imported: the payload is live
    assert marker.exists()


def test_b_a_leaderboard_entry_refuses_a_dotted_module_spec(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    import yaml
    from leaderboard_fixtures import make_repo, meta

    from racebench.leaderboard.entries import EntryError, load_entry, policy_sha256

    board = make_repo(tmp_path)
    root, marker = board.parents[1], tmp_path / "ran"
    _evil_package(root / "baselines", "evilsub", marker)  # as a pull request would add it
    spec = "evilsub.mod:X"
    (root / "evilsub.mod").write_text("")  # so that the file part of the spec exists in the repository
    monkeypatch.syspath_prepend(str(root / "baselines"))
    monkeypatch.chdir(root)
    folder = board / "evil"
    folder.mkdir()
    entry = {**meta("evil"), "policies": {"all": {"policy": spec, "records": ["results/none"]}}}
    (folder / "entry.yaml").write_text(yaml.safe_dump(entry))
    try:
        with pytest.raises(EntryError, match="file.py:Class"):
            load_entry(folder)
        with pytest.raises(EntryError, match="file.py:Class"):
            policy_sha256(spec, root, "evil")  # leaderboard add's check
        for command in (["verify"], ["build", "--out", str(tmp_path / "site")]):
            with pytest.raises(SystemExit) as exc:
                cli.main(["leaderboard", *command, "--leaderboard", str(board)])
            assert exc.value.code not in (0, None)
        assert not marker.exists()
    finally:
        sys.modules.pop("evilsub", None)


def test_b_baseline_configs_and_tracks_are_data_not_packages() -> None:
    import configparser

    from racebench.sim.track import track_path
    from racebench.training.config import BASELINES, baseline_path
    from racebench.training.run import load_config

    assert not (ROOT / "baselines" / "__init__.py").exists() and not (ROOT / "tracks" / "__init__.py").exists()
    setup = configparser.ConfigParser()
    setup.read(ROOT / "setup.cfg")
    packages = setup["options"]["packages"].split()
    assert "racebench.configs" not in packages and "racebench.tracks" not in packages
    assert "package_dir" not in setup["options"]
    for name in BASELINES:  # loading a config by name still works, from the checkout's files
        assert baseline_path(name) == ROOT / "baselines" / f"{name}.yaml"
        assert load_config(name).name == name
    assert track_path("S") == ROOT / "tracks" / "S.yaml"


# ------------------------------------------------ K: leaderboard build writes only regular files inside --out


def _build(board: Path, out: Path) -> SystemExit | None:
    try:
        cli.main(["leaderboard", "build", "--out", str(out), "--leaderboard", str(board)])
    except SystemExit as exc:
        return exc
    return None


@pytest.mark.parametrize("name", ["index.html", "style.css"])
def test_k_build_never_writes_through_a_symlinked_file(tmp_path: Path, name: str) -> None:
    from leaderboard_fixtures import make_repo

    board = make_repo(tmp_path / "repo")
    site = board / "site"
    assert _build(board, site) is None and (site / name).is_file()  # a plain build works
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (site / name).unlink()
    (site / name).symlink_to(victim)
    exc = _build(board, site)
    assert exc is not None and exc.code not in (0, None) and "symbolic link" in str(exc.code)
    assert "\n" not in str(exc.code) and victim.read_text() == "keep me"


def test_k_build_never_removes_through_a_symlinked_folder(tmp_path: Path) -> None:
    from leaderboard_fixtures import make_repo

    board = make_repo(tmp_path / "repo")
    victim = tmp_path / "victim"
    (victim / "entries").mkdir(parents=True)
    (victim / "entries" / "precious.txt").write_text("keep me")
    (victim / "index.html").write_text("keep me")
    (board / "site").symlink_to(victim, target_is_directory=True)
    exc = _build(board, board / "site")
    assert exc is not None and "symbolic link" in str(exc.code)
    assert (victim / "entries" / "precious.txt").read_text() == "keep me"
    assert (victim / "index.html").read_text() == "keep me"
    # A link deeper down (the entries folder) and a link among the site's parents inside the repository: refused.
    (board / "site").unlink()
    (board / "site").mkdir()
    (board / "site" / "entries").symlink_to(victim / "entries", target_is_directory=True)
    assert "symbolic link" in str(_build(board, board / "site").code)
    assert (victim / "entries" / "precious.txt").exists()
    (board / "deep").symlink_to(victim, target_is_directory=True)
    assert "symbolic link" in str(_build(board, board / "deep" / "site").code)
    assert not (victim / "site").exists()


# ------------------------------------------------ C: a symlinked ONNX file flies the weights its hash covers


def _external_onnx(folder: Path, hover: float) -> Path:
    """The fixture hover policy with its weights saved as external data ``w.bin`` beside it."""
    import onnx
    from leaderboard_fixtures import write_hover_onnx
    from onnx import numpy_helper

    path = write_hover_onnx(folder / "model.onnx")
    model = onnx.load(str(path))
    for i, tensor in enumerate(model.graph.initializer):  # raw data, which onnx saves as external data
        array = numpy_helper.to_array(tensor).copy()
        if tensor.name == "b":
            array[0] = hover
        model.graph.initializer[i].CopyFrom(numpy_helper.from_array(array, tensor.name))
    onnx.save(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True, location="w.bin",
              size_threshold=0)  # fmt: skip
    return path


def test_c_two_links_with_one_hash_fly_the_same_weights(tmp_path: Path) -> None:
    import numpy as np

    from racebench.agents import OnnxAgent

    target = _external_onnx(tmp_path / "a", 0.5)
    links = []
    for name, hover in (("b", 0.1), ("c", 0.9)):  # beside each link, other weights of the same layout
        other = _external_onnx(tmp_path / f"{name}-weights", hover)
        (tmp_path / name).mkdir()
        (tmp_path / name / "w.bin").write_bytes((other.parent / "w.bin").read_bytes())
        (tmp_path / name / "model.onnx").symlink_to(target)
        links.append(tmp_path / name / "model.onnx")
    agents = [OnnxAgent(path) for path in (target, *links)]
    assert len({agent.sha256 for agent in agents}) == 1
    actions = [agent.act(np.zeros(17, dtype=np.float32)) for agent in agents]
    assert all(np.array_equal(actions[0], a) for a in actions) and actions[0][0] == pytest.approx(0.5)


# ------------------------------------------------ D, E: what the verified badge stands beside is signed


@pytest.fixture()
def signed_repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict:
    from test_leaderboard_signing import repo, sign

    made = repo.__wrapped__(tmp_path, monkeypatch)
    sign(made, monkeypatch)
    return made


def _edit_entry(repo: dict, edit) -> None:
    import yaml

    from racebench.leaderboard.entries import dump_entry

    path = repo["board"] / "method" / "entry.yaml"
    meta = yaml.safe_load(path.read_text())
    edit(meta)
    path.write_text(dump_entry(meta))


@pytest.mark.parametrize(
    "field, value",
    [("description", "Now the best method ever, trained with no teacher."), ("teacher", "planner"),
     ("obs_mode", "vision"), ("authors", ["Someone Else"]), ("training_seeds", [0, 1, 2])],
)  # fmt: skip
def test_d_edited_metadata_of_a_verified_entry_is_refused(signed_repo, field: str, value) -> None:
    from test_leaderboard_signing import row

    assert row(signed_repo).tier == "verified"
    _edit_entry(signed_repo, lambda meta: meta.update({field: value}))
    verdict = row(signed_repo)
    assert verdict.tier == "self-reported" and "changed after signing" in verdict.refusal


def test_d_an_edited_budget_of_a_verified_entry_is_refused(signed_repo) -> None:
    from test_leaderboard_signing import row

    _edit_entry(signed_repo, lambda meta: meta["policies"]["S"].update({"steps": 1000, "wall_clock_s": 1.0}))
    assert "changed after signing" in row(signed_repo).refusal


def test_e_a_public_policy_line_pointed_elsewhere_is_refused(signed_repo) -> None:
    from leaderboard_fixtures import write_hover_onnx, write_records
    from test_leaderboard_signing import S, row

    root = signed_repo["root"]
    write_hover_onnx(root / "policies" / "other.onnx")  # another method's policy and records, all successes
    write_records(root / "results" / "other", str(root / "policies" / "other.onnx"), S, 10, 10)

    def point(meta):
        meta["policies"]["S"].update({"policy": "policies/other.onnx", "records": ["results/other"]})

    _edit_entry(signed_repo, point)
    verdict = row(signed_repo)
    assert verdict.tier == "self-reported" and "changed after signing" in verdict.refusal


def test_de_committed_verified_entries_stay_verified() -> None:
    from racebench.leaderboard.entries import load_config, load_entries
    from racebench.leaderboard.signing import FORMAT1_VIEWS
    from racebench.leaderboard.site import entry_row

    board = ROOT / "results" / "leaderboard"
    config = load_config(board)
    verified = {e.name for e in load_entries(board) if entry_row(e, config).tier == "verified"}
    assert verified == set(FORMAT1_VIEWS)


# ------------------------------------------------ G: the tables refuse incomplete cells


def _hover_eval(folder: Path, episodes: int = 6) -> Path:
    from racebench.evaluation import Evaluator

    Evaluator("hover", ["RaceObs-S-Level1-v0"], episodes=episodes, out_dir=folder).run(progress=False)
    return folder


def test_g_a_table_refuses_a_cell_with_a_deleted_record(tmp_path: Path) -> None:
    from racebench.evaluation.records import RECORDS_FILE
    from racebench.evaluation.results import read_summaries

    out = _hover_eval(tmp_path / "eval")
    assert read_summaries([out])["n"].tolist() == [6]  # complete: fine
    lines = (out / RECORDS_FILE).read_text().splitlines(keepends=True)
    (out / RECORDS_FILE).write_text("".join(lines[:2] + lines[3:]))  # one episode's line deleted
    with pytest.raises(SystemExit) as exc:
        cli.main(["table", str(out)])
    message = str(exc.value.code)
    assert "1 public seeds of the protocol are missing" in message and "\n" not in message
    assert f"({json.loads(lines[2])['seed']})" in message  # names the missing seed


def test_g_a_table_refuses_a_corrupted_record(tmp_path: Path) -> None:
    from racebench.evaluation.records import RECORDS_FILE

    out = _hover_eval(tmp_path / "eval")
    lines = (out / RECORDS_FILE).read_text().splitlines(keepends=True)
    record = json.loads(lines[1])
    record["success"] = True  # edited without re-digesting
    (out / RECORDS_FILE).write_text("".join([lines[0], json.dumps(record) + "\n", *lines[2:]]))
    with pytest.raises(SystemExit, match="invalid record"):
        cli.main(["table", str(out)])


def test_g_paper_tables_refuse_a_cell_with_dropped_failures(tmp_path: Path) -> None:
    from racebench.evaluation.records import RECORDS_FILE
    from racebench.reporting.paper import Source, load_episodes

    out = _hover_eval(tmp_path / "eval")
    assert len(load_episodes([Source("hover", out)])) == 6
    lines = (out / RECORDS_FILE).read_text().splitlines(keepends=True)
    (out / RECORDS_FILE).write_text("".join(lines[:1] + lines[2:]))
    with pytest.raises(ValueError, match="missing"):
        load_episodes([Source("hover", out)])


# ------------------------------------------------ H: an absurd episode count is a one-line error


@pytest.mark.parametrize("episodes", ["100000000", "0", "-5"])
def test_h_an_absurd_episode_count_is_a_one_line_error(episodes: str, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["evaluate", "--agent", "hover", "--envs", "RaceObs-S-v0", "--episodes", episodes,
                  "--out", str(tmp_path / "out")])  # fmt: skip
    message = str(exc.value.code)
    assert "episodes per env id must be an integer from 1 to 100,000" in message and "\n" not in message


def test_h_the_seed_lists_are_bounded() -> None:
    from racebench.evaluation.seeds import private_seeds, public_seeds

    with pytest.raises(ValueError, match="from 1 to 100,000"):
        public_seeds(10**8)
    with pytest.raises(ValueError, match="from 1 to 100,000"):
        private_seeds("a-test-salt-that-is-long-enough-0123456789", 10**8)


# ------------------------------------------------ I: a negative episode seed is a one-line error


@pytest.mark.parametrize("command", [["fly"], ["render", "--out", "x.mp4"], ["scene"]])
def test_i_a_negative_seed_is_a_one_line_error(command: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main([*command, "--seed", "-1"])
    message = str(exc.value.code)
    assert message.startswith(f"racebench {command[0]}: --seed must be") and "\n" not in message


# ------------------------------------------------ J: the site's embedded JSON cannot end its script element


def test_j_a_description_cannot_break_out_of_the_data_block(tmp_path: Path) -> None:
    import re

    import yaml
    from leaderboard_fixtures import add, make_repo, write_hover_onnx, write_records

    from racebench.leaderboard.entries import dump_entry
    from racebench.leaderboard.site import build_site

    board = make_repo(tmp_path / "repo")
    root = board.parents[1]
    policy = write_hover_onnx(root / "policies" / "p.onnx")
    write_records(root / "results" / "p", str(policy), "RaceObs-S-v0", 2, 10)
    add(board, {"S": str(policy)}, "sneaky", [root / "results" / "p"])
    description = "Fast & safe <!--<script>alert(1)</script> a > b"
    meta = yaml.safe_load((board / "sneaky" / "entry.yaml").read_text())
    (board / "sneaky" / "entry.yaml").write_text(dump_entry({**meta, "description": description}))
    html = build_site(board, tmp_path / "site").read_text()
    (block,) = re.findall(r'<script type="application/json" id="leaderboard-data">(.*?)</script>', html, re.S)
    assert not set("<>&") & set(block)  # nothing in it the HTML parser reads as markup
    assert json.loads(block)["entries"]["sneaky"]["description"] == description  # the same data
    assert html.rstrip().endswith("</html>") and html.count("</script>") == 1


# ------------------------------------------------ F: no entry chooses how many of its episodes are ranked


@pytest.mark.parametrize("committed", [50, 80, 100])
def test_f_a_self_reported_entry_is_ranked_on_the_protocols_first_seeds(tmp_path: Path, committed: int) -> None:
    from leaderboard_fixtures import add, make_repo, write_hover_onnx, write_records

    from racebench.leaderboard.entries import MAIN_IDS, load_config, load_entry
    from racebench.leaderboard.ranking import RANKED_EPISODES, entry_row

    assert RANKED_EPISODES == 50
    board = make_repo(tmp_path / "repo")
    root = board.parents[1]
    policy = write_hover_onnx(root / "policies" / "p.onnx")
    for env_id in MAIN_IDS:  # the first 35 seeds succeed, every later one fails
        write_records(root / "results" / "p", str(policy), env_id, 35, committed)
    add(board, str(policy), "method", [root / "results" / "p"])
    row = entry_row(load_entry(board / "method"), load_config(board))
    assert row.ranked and row.key()[0] == pytest.approx(35 / 50)  # however many were committed
    assert all(cell.n == 50 for cell in row.cells.values())


def test_f_an_entry_that_commits_fewer_than_the_protocols_count_is_not_ranked(tmp_path: Path) -> None:
    from leaderboard_fixtures import add, make_repo, write_hover_onnx, write_records

    from racebench.leaderboard.entries import MAIN_IDS
    from racebench.leaderboard.site import build_site

    board = make_repo(tmp_path / "repo")
    root = board.parents[1]
    policy = write_hover_onnx(root / "policies" / "p.onnx")
    for env_id in MAIN_IDS:  # flew 100, committed only the flattering first 35 (all successes)
        write_records(root / "results" / "p", str(policy), env_id, 35, 35)
    add(board, str(policy), "method", [root / "results" / "p"])
    html = build_site(board, tmp_path / "site").read_text()
    assert 'id="ranking-self-reported"' not in html and 'id="unranked-self-reported"' in html
    assert "fewer than the protocol&#x27;s 50 public episodes" in html or "fewer than the protocol's 50" in html
