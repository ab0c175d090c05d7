"""Every result keyed to what produced it: policy hash, env version, validation on read, untrusted code refused."""

from __future__ import annotations

import base64
import json
import logging
import pickle
import re
import shlex
import stat
import textwrap
import zipfile
from pathlib import Path

import pandas as pd
import pytest

from racebench import ENV_VERSION, cli
from racebench.agents import (
    BUILTIN_PRIVILEGED,
    AgentLoadError,
    UntrustedCodeError,
    builtin_identity,
    load_agent,
    policy_identity,
)
from racebench.evaluation import (
    EVAL_SEED_BASE,
    Evaluator,
    MixedResultsError,
    load_records,
    read_summaries,
    summarize,
)
from racebench.evaluation.records import (
    RECORD_FIELDS,
    RECORDS_FILE,
    InvalidRecordError,
    name_of,
    read_folder,
    record_digest,
    record_line,
    seal,
    validate_record,
)
from racebench.evaluation.statistics import counts_consistent, detectable_doctoring

ENV = "RaceObs-S-Level1-v0"  # no obstacles: hover and the planner run quickly and deterministically
ROOT = Path(__file__).parents[1]

AGENT_FILE = textwrap.dedent(
    """
    import numpy as np

    class Hover:
        obs_mode = "state"
        def reset(self, env=None, seed=None):
            pass
        def act(self, obs):
            return np.array([{thrust}, 0.0, 0.0, 0.0])
    """
)


def write_agent(path: Path, thrust: float) -> str:
    path.write_text(AGENT_FILE.format(thrust=thrust))
    return f"{path}:Hover"


# ------------------------------------------------------------------ keying


def test_a_changed_policy_file_is_not_resumed_from_the_old_results(tmp_path: Path) -> None:
    spec = write_agent(tmp_path / "agent.py", -0.2)
    out = tmp_path / "out"
    Evaluator(spec, [ENV], episodes=1, out_dir=out, trust_code=True).run(progress=False)
    write_agent(tmp_path / "agent.py", -0.1)  # "retrained and saved over the old file"
    with pytest.raises(MixedResultsError, match="another policy"):
        Evaluator(spec, [ENV], episodes=1, out_dir=out, trust_code=True)
    fresh = Evaluator(spec, [ENV], episodes=1, trust_code=True)  # the default folder differs per policy
    assert fresh.pending() == [(ENV, EVAL_SEED_BASE)]


def test_two_policies_never_share_an_output_directory(tmp_path: Path) -> None:
    out = tmp_path / "planner"
    Evaluator("planner", [ENV], episodes=1, out_dir=out).run(progress=False)
    with pytest.raises(MixedResultsError, match="'hover'"):
        Evaluator("hover", [ENV], episodes=1, out_dir=out)
    with pytest.raises(MixedResultsError, match="'hover'"):  # --name labels, it never selects records
        Evaluator("hover", [ENV], episodes=1, out_dir=out, agent_name="planner")
    with pytest.raises(MixedResultsError, match="--name planner"):
        Evaluator("planner", [ENV], episodes=1, out_dir=out, agent_name="other-label")
    assert set(load_records(out)["agent"]) == {"planner"}


def test_a_folder_that_came_to_hold_two_policies_is_not_summarised(tmp_path: Path) -> None:
    """Two evaluations writing into one folder at once (each checked it at start, when it was empty): the tables
    are not rebuilt as one policy's, and the error names both hashes."""
    first, second = write_agent(tmp_path / "a.py", -0.2), write_agent(tmp_path / "b.py", -0.1)
    out = tmp_path / "out"
    late = Evaluator(second, [ENV], episodes=1, out_dir=out, trust_code=True, agent_name="hover-x")
    Evaluator(first, [ENV], episodes=1, out_dir=out, trust_code=True, agent_name="hover-x").run(progress=False)
    tables_before = [(out / name).read_text() for name in ("episodes.csv", "summary.csv")]
    with pytest.raises(MixedResultsError, match="come from 2 policies"):
        late.run(progress=False)  # its record lands beside the first policy's
    assert len(read_folder(out).records) == 2  # both finished records kept, neither counted
    assert [(out / name).read_text() for name in ("episodes.csv", "summary.csv")] == tables_before
    with pytest.raises(MixedResultsError, match="come from 2 policies"):
        summarize(load_records(out))


def test_force_discards_what_the_directory_held(tmp_path: Path) -> None:
    out = tmp_path / "out"
    Evaluator("planner", [ENV], episodes=1, out_dir=out).run(progress=False)
    Evaluator("hover", [ENV], episodes=1, out_dir=out, force=True).run(progress=False)
    frame = load_records(out)
    assert frame["agent"].tolist() == ["hover"] and not frame["privileged"].any()
    assert pd.read_csv(out / "episodes.csv")["agent"].tolist() == ["hover"]


def test_identities(tmp_path: Path) -> None:
    assert policy_identity("planner") == builtin_identity("planner")
    assert policy_identity("planner").privileged and not policy_identity("hover").privileged
    assert policy_identity("planner").sha256 != policy_identity("follow").sha256
    import onnx
    from onnx import TensorProto, helper

    a, b = tmp_path / "x.onnx", tmp_path / "x.zip"
    value = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [value],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])  # fmt: skip
    onnx.save(helper.make_model(graph), a)
    b.write_bytes(b"one")
    assert policy_identity(str(a)).kind == "onnx" and policy_identity(str(b)).kind == "sb3"
    (tmp_path / "bad.onnx").write_bytes(b"one")  # the identity reads the graph for external data: corrupt is named
    with pytest.raises(AgentLoadError, match="bad.onnx"):
        policy_identity(str(tmp_path / "bad.onnx"))
    spec = write_agent(tmp_path / "agent.py", 0.0)
    assert policy_identity(spec).sha256 == policy_identity(spec).sha256
    write_agent(tmp_path / "agent.py", 0.5)
    assert policy_identity(spec).sha256 != policy_identity(f"{tmp_path / 'x.onnx'}").sha256


def test_the_summary_is_what_was_asked(tmp_path: Path) -> None:
    out = tmp_path / "out"
    Evaluator("hover", [ENV, "RaceObs-J-Level1-v0"], episodes=3, out_dir=out).run(progress=False)
    summary = Evaluator("hover", [ENV], episodes=2, out_dir=out).run(progress=False)
    assert summary[["env_id", "n"]].values.tolist() == [[ENV, 2]]
    assert len(pd.read_csv(out / "episodes.csv")) == 6  # the folder's CSVs still hold all its records


def test_records_and_csvs_are_world_readable(tmp_path: Path) -> None:
    Evaluator("hover", [ENV], episodes=1, out_dir=tmp_path).run(progress=False)
    for path in [tmp_path / RECORDS_FILE, tmp_path / "episodes.csv", tmp_path / "summary.csv"]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o644, path


def test_builtins_replay_bit_identically_on_one_machine(tmp_path: Path) -> None:
    for out in ("a", "b"):
        Evaluator("planner", [ENV, "RaceObs-S-v0"], episodes=1, out_dir=tmp_path / out).run(progress=False)
    a, b = ((tmp_path / out / RECORDS_FILE).read_bytes() for out in ("a", "b"))
    assert a == b and a.count(b"\n") == 2


# ---------------------------------------------------------------- validation


@pytest.fixture(scope="module")
def hover_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("hover")
    Evaluator("hover", [ENV], episodes=4, out_dir=out).run(progress=False)
    return out


@pytest.fixture(scope="module")
def planner_record(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("planner")
    Evaluator("planner", [ENV], episodes=1, out_dir=out).run(progress=False)
    return json.loads((out / RECORDS_FILE).read_text())


def test_a_fresh_record_is_valid(planner_record: dict) -> None:
    assert list(planner_record) == list(RECORD_FIELDS)
    assert planner_record["success"] and planner_record["env_version"] == ENV_VERSION
    assert validate_record(planner_record, name_of(planner_record)) == planner_record


# Each edit is re-sealed (a forger recomputes the digest): the consistency checks must catch it alone.
FORGERIES = {
    "success without every gate": {"gates_passed": 3},
    "lap time outside the last step": {"lap_time": 1.23},
    "success with a crash": {"crashed": True, "crash_reason": "obstacle:0"},
    "failure with a lap time": {"success": False},
    "failure that stopped early": {"success": False, "lap_time": None},
    "crash after the last gate": {"success": False, "lap_time": None, "crashed": True, "crash_reason": "ground"},
    "crash without a reason": {"success": False, "lap_time": None, "crashed": True},
    "error without a reason": {"success": False, "lap_time": None, "error": "boom"},
    "unknown crash reason": {"success": False, "lap_time": None, "crashed": True, "crash_reason": "wind"},
    "training seed": {"seed": 12},
    "other protocol": {"seed_protocol": 2},
    "unknown env": {"env_id": "RaceObs-X-v0"},
    "track mismatch": {"track": "J"},
    "too many steps": {"steps": 100_000},
    "privileged hover": {"policy_source": "hover", "privileged": True},
    "unprivileged planner": {"privileged": False},
    "string success": {"success": "True"},
    "int as bool": {"crashed": 0},
    "bad hash": {"policy_sha256": "abc"},
    "unknown field": {"note": "trust me"},
    "old format": {"record_format": 1},
}


@pytest.mark.parametrize("edit", list(FORGERIES), ids=list(FORGERIES))
def test_inconsistent_records_are_rejected(planner_record: dict, edit: str) -> None:
    forged = {**planner_record, **FORGERIES[edit]}
    forged["digest"] = record_digest(forged)
    with pytest.raises(InvalidRecordError):
        validate_record(forged)


def test_an_edit_without_a_new_digest_and_a_moved_record_are_rejected(planner_record: dict) -> None:
    with pytest.raises(InvalidRecordError, match="digest"):
        validate_record({**planner_record, "return": 99.0})
    moved = seal({**planner_record, "seed": planner_record["seed"] + 1})
    with pytest.raises(InvalidRecordError, match="renamed"):
        validate_record(moved, name_of(planner_record))
    missing = {k: v for k, v in planner_record.items() if k != "steps"}
    with pytest.raises(InvalidRecordError, match="missing fields"):
        validate_record(missing)


def _forge_hover_success(record: dict) -> dict:
    """The issue's forgery: a hover record edited to claim a 1.23 s lap, digest recomputed."""
    return seal({**record, "success": True, "lap_time": 1.23, "crashed": False, "crash_reason": None})


def test_corrupt_and_forged_records_are_named_set_aside_and_rerun(
    hover_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "damaged"
    out.mkdir()
    original = (hover_dir / RECORDS_FILE).read_bytes().splitlines(keepends=True)
    forged = record_line(_forge_hover_success(json.loads(original[3])))
    (out / RECORDS_FILE).write_bytes(original[0][:40] + b"\n" + b"\x00\xffnot json\n" + b"{}\n" + forged)
    (out / "records-1-feedbeef.jsonl").write_bytes(original[1][:-30])  # a worker killed mid-write: torn last line

    with caplog.at_level(logging.WARNING, logger="racebench"):
        assert load_records(out).empty  # read-only use: left out, never counted
        named = " ".join(r.getMessage() for r in caplog.records)
    for line in (1, 2, 3, 4):  # each one-line error names the folder's file, the line and the reason
        assert f"{out / RECORDS_FILE}:{line}: " in named
    assert f"{out / RECORDS_FILE}:4: success with 0 of 4 gates" in named
    assert "records-1-feedbeef.jsonl:1: torn last line" in named
    with pytest.raises(ValueError, match=r"invalid record .*records\.jsonl:1: "):  # a table never drops one
        read_summaries([out])

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="racebench"):
        evaluator = Evaluator("hover", [ENV], episodes=4, out_dir=out)
    assert len(evaluator.pending()) == 4
    assert "torn record line dropped" in caplog.text
    aside = [json.loads(line) for line in (out / "invalid.jsonl").read_text().splitlines()]
    assert [a["source"] for a in aside] == [f"{out / RECORDS_FILE}:{n}" for n in (1, 2, 3, 4)]  # the torn one: dropped
    assert "success with 0 of 4 gates" in aside[3]["reason"] and aside[3]["text"] == forged.decode().strip()
    assert not list(out.glob("records-*.jsonl"))  # merged: one records file again
    summary = evaluator.run(progress=False)
    assert summary[["n", "successes"]].values.tolist() == [[4, 0]]
    assert (out / RECORDS_FILE).read_bytes() == b"".join(original)  # re-run: the same hover episodes, byte for byte


def test_tables_never_read_a_summary_back(hover_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "copy"
    out.mkdir()
    (out / RECORDS_FILE).write_bytes((hover_dir / RECORDS_FILE).read_bytes())
    pd.DataFrame([{"agent": "hover", "env_id": ENV, "success_rate": 0.99, "sr_ci_low": 0.0, "sr_ci_high": 0.1}]).to_csv(
        out / "summary.csv", index=False
    )
    for given in (out, out / "summary.csv"):
        summary = read_summaries([given])
        assert summary["success_rate"].tolist() == [0.0] and summary["n"].tolist() == [4]
    with pytest.raises(FileNotFoundError, match="no evaluation records"):
        read_summaries([tmp_path / "nowhere"])


# ------------------------------------------------------------ untrusted code


@pytest.fixture(scope="module")
def tiny_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import gymnasium as gym
    from stable_baselines3 import PPO

    env = gym.make(ENV, obs_mode="state")
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0, policy_kwargs={"net_arch": [8]})
    path = tmp_path_factory.mktemp("zip") / "tiny.zip"
    model.save(path)
    return path


class _Payload:
    """Unpickling this creates ``marker``: a stand-in for a checkpoint that runs a shell command."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _poisoned(zip_path: Path, out: Path, marker: Path) -> Path:
    """A copy of an SB3 checkpoint whose ``data`` holds a pickled payload, as SB3 serialises objects."""
    with zipfile.ZipFile(zip_path) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            content = src.read(item.filename)
            if item.filename == "data":
                data = json.loads(content)
                blob = base64.b64encode(pickle.dumps(_Payload(str(marker)))).decode()
                data["payload"] = {":type:": "<class 'object'>", ":serialized:": blob}
                content = json.dumps(data).encode()
            dst.writestr(item, content)
    return out


def test_a_pickled_payload_is_refused_without_trust_code_and_never_runs(tiny_zip: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    evil = _poisoned(tiny_zip, tmp_path / "evil.zip", marker)
    with pytest.raises(UntrustedCodeError, match="--trust-code"):
        load_agent(str(evil))
    with pytest.raises(SystemExit, match="unpickled"):
        cli.main(["evaluate", "--agent", str(evil), "--envs", ENV, "--episodes", "1", "--out", str(tmp_path / "o")])
    assert not marker.exists()
    # The refusal is what protects: with the flag the same file does run its payload.
    load_agent(str(evil), trust_code=True)
    assert marker.exists()


def test_python_agents_need_trust_code_and_are_never_privileged(tmp_path: Path) -> None:
    marker = tmp_path / "imported"
    module = tmp_path / "side_effect.py"
    module.write_text(f"open({str(marker)!r}, 'w').close()\nclass A:\n    pass\n")
    with pytest.raises(UntrustedCodeError, match="imported and run"):
        load_agent(f"{module}:A")
    assert not marker.exists()
    sneaky = tmp_path / "sneaky.py"
    sneaky.write_text(
        "class Sneaky:\n    obs_mode = 'state'\n    privileged = True\n"
        "    def reset(self, env=None, seed=None):\n        pass\n"
        "    def act(self, obs):\n        return [0, 0, 0, 0]\n"
    )
    with pytest.raises(AgentLoadError, match="only built-in agents"):
        load_agent(f"{sneaky}:Sneaky", trust_code=True)
    assert not any(BUILTIN_PRIVILEGED[name] for name in ("random", "hover"))


def test_the_allowlist_trusts_exactly_the_committed_bytes(tmp_path: Path) -> None:
    from racebench.agents import TRUSTED_CHECKPOINTS
    from racebench.evaluation.records import sha256_file

    committed = {sha256_file(p): p.relative_to(ROOT / "baselines/checkpoints").as_posix()
                 for p in (ROOT / "baselines/checkpoints").glob("*/*.zip")}  # fmt: skip
    assert committed == TRUSTED_CHECKPOINTS
    first = ROOT / "baselines/checkpoints" / sorted(TRUSTED_CHECKPOINTS.values())[0]
    assert load_agent(str(first)).sha256 in TRUSTED_CHECKPOINTS
    altered = tmp_path / first.name
    altered.write_bytes(first.read_bytes() + b"\0")  # still a readable zip, no longer the trusted bytes
    with pytest.raises(UntrustedCodeError):
        load_agent(str(altered))


# ------------------------------------------------------------------- README


def test_the_readme_first_command_evaluates_what_it_asks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    first_block = re.search(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), re.S).group(1)
    command = next(line for line in first_block.splitlines() if "racebench evaluate" in line)
    argv = shlex.split(command[command.index("racebench evaluate") :])[1:]
    monkeypatch.chdir(tmp_path)  # a fresh checkout: nothing evaluated yet
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "0/30 episodes already done" in printed
    table = [line.split() for line in printed.splitlines() if line.strip().startswith("RaceObs-")]
    assert [row[0] for row in table] == ["RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-v0"]
    assert [row[1] for row in table] == ["10", "10", "10"]
    (written,) = (tmp_path / "runs" / "eval").glob(f"planner-*/{RECORDS_FILE}")
    assert len(read_folder(written.parent).records) == 30


def test_cli_errors_are_one_line_and_nonzero(tmp_path: Path) -> None:
    out = tmp_path / "o"
    cli.main(["evaluate", "--agent", "hover", "--envs", ENV, "--episodes", "1", "--out", str(out)])
    with pytest.raises(SystemExit, match=r"^racebench evaluate: .* holds results of another policy"):
        cli.main(["evaluate", "--agent", "planner", "--envs", ENV, "--episodes", "1", "--out", str(out)])
    spec = write_agent(tmp_path / "a.py", 0.0)
    with pytest.raises(SystemExit, match="--trust-code"):
        cli.main(["evaluate", "--agent", spec, "--envs", ENV, "--out", str(tmp_path / "p")])
    with pytest.raises(SystemExit, match="^racebench table: no evaluation records"):
        cli.main(["table", str(tmp_path / "missing")])
    with pytest.raises(SystemExit, match="not a mesh format"):
        cli.main(["scene", "--out", str(tmp_path / "scene.png")])
    broken = tmp_path / "broken.py"
    broken.write_text("class B:\n    obs_mode = 'state'\n    def reset(self, env=None, seed=None):\n        pass\n"
                      "    def act(self, obs):\n        raise RuntimeError('no policy here')\n")  # fmt: skip
    with pytest.raises(SystemExit, match="every episode failed.*no policy here"):
        cli.main(["evaluate", "--agent", f"{broken}:B", "--trust-code", "--envs", ENV, "--episodes", "2",
                  "--out", str(tmp_path / "b")])  # fmt: skip
    modeless = tmp_path / "modeless.py"
    modeless.write_text("class M:\n    def reset(self, env=None, seed=None):\n        pass\n"
                        "    def act(self, obs):\n        return [0, 0, 0, 0]\n")  # fmt: skip
    with pytest.raises(AgentLoadError, match="must declare obs_mode"):
        load_agent(f"{modeless}:M", trust_code=True)


# --------------------------------------------------------------- statistics


def test_consistency_test_accepts_another_cpus_replay_and_catches_doctoring() -> None:
    assert counts_consistent((14, 20), (13, 20)).consistent  # issue #9: another CPU gave 13/20
    assert counts_consistent((70, 100), (28, 40)).consistent
    assert not counts_consistent((20, 20), (5, 20)).consistent
    low, high = detectable_doctoring((70, 100), (28, 40))
    assert not counts_consistent((high, 100), (28, 40)).consistent
    assert counts_consistent((high - 1, 100), (28, 40)).consistent
    assert not counts_consistent((low, 100), (28, 40)).consistent
    with pytest.raises(ValueError):
        counts_consistent((3, 2), (1, 2))


def test_records_of_os_level_copies_stay_valid(hover_dir: Path, tmp_path: Path) -> None:
    """A record copied byte for byte into another folder of the same policy is still that policy's record."""
    (tmp_path / RECORDS_FILE).write_bytes((hover_dir / RECORDS_FILE).read_bytes())
    assert len(load_records(tmp_path)) == 4
