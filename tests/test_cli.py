"""The command line: help on every option, the README's command table against the parser, -q/-v, agent
kwargs, and `fly` with any agent spec."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from racebench import cli
from racebench.agents import AgentLoadError, load_agent, parse_agent_kwargs, policy_identity

ROOT = Path(__file__).parents[1]
LEVEL1 = "RaceObs-S-Level1-v0"


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's sub-commands by name ({} for a leaf)."""
    action = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    return dict(action.choices) if action is not None else {}


def commands(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every leaf command (``("evaluate",)``, or nested as ``("leaderboard", "add")``) and its parser."""
    subs = subcommands(parser)
    if not subs:
        return {path: parser}
    found: dict[tuple[str, ...], argparse.ArgumentParser] = {}
    for name, sub in subs.items():
        found.update(commands(sub, (*path, name)))
    return found


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings if s.startswith("--") and s != "--help"}


def test_every_option_has_help_text() -> None:
    parser = cli.build_parser()
    every = [(("racebench",), parser), *commands(parser).items()]
    missing = [
        f"{' '.join(path)} {action.option_strings or action.dest}"
        for path, sub in every
        for action in sub._actions
        if not isinstance(action, argparse._SubParsersAction) and not (action.help or "").strip()
    ]
    assert not missing, f"options without help: {missing}"


def readme_commands(parser: argparse.ArgumentParser) -> dict[tuple[str, ...], str]:
    """Command path -> the synopsis in the README's command table (``\\|`` unescaped); the path follows the
    parser's sub-commands through the synopsis' words (``racebench leaderboard add ...``)."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## Command line\n", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(racebench [^`]*)` \|", section, re.M)
    assert rows, "the README's command table is gone"
    found = {}
    for row in (row.replace("\\|", "|") for row in rows):
        words, path, sub = row.split()[1:], (), parser
        while words and words[0] in subcommands(sub):
            sub = subcommands(sub)[words[0]]
            path, words = (*path, words[0]), words[1:]
        assert path not in found, f"two README rows for racebench {' '.join(path)}"
        found[path] = row
    return found


def test_readme_command_table_matches_the_parser() -> None:
    parser = cli.build_parser()
    written_commands = readme_commands(parser)
    glob = written_commands.pop(())  # racebench [-q|-v] COMMAND ...
    assert "[-q|-v]" in glob and {"-q", "-v"} <= {s for a in parser._actions for s in a.option_strings}
    leaves = commands(parser)
    assert set(written_commands) == set(leaves), "commands in the README table and in the parser differ"
    for path, synopsis in written_commands.items():
        name, known = " ".join(path), options(leaves[path])
        written = set(re.findall(r"--[a-z][a-z0-9-]*", synopsis))
        drift = f"{name}: README only {sorted(written - set(known))}, parser only {sorted(set(known) - written)}"
        assert written == set(known), drift
        for option, value in re.findall(r"\[(--[a-z0-9-]+) ([^\]\s]+)(?: \.\.\.)?\]", synopsis):
            action, values = known[option], value.split("|")
            if action.choices is not None and len(values) > 1:
                assert set(values) == {str(c) for c in action.choices}, f"{name} {option}: choices"
            elif len(values) == 1 and (action.choices or not re.fullmatch(r"[A-Z][A-Z0-9_]*(\.[a-z]+)?", value)):
                # one value, not a placeholder such as DIR, N or FILE.yaml: the default (alternatives of an
                # option without choices, as --envs main|density|...|ID, are examples, not checked)
                assert value == str(action.default), f"{name} {option}: README {value}, parser {action.default}"


def test_quiet_keeps_results_and_drops_the_chatter(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["scene", "--seed", "1", "--out", str(tmp_path / "a.glb")]) == 0
    assert "wrote" in capsys.readouterr().out
    assert cli.main(["-q", "scene", "--seed", "1", "--out", str(tmp_path / "b.glb")]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    assert (tmp_path / "b.glb").is_file()
    assert cli.main(["-q", "envs"]) == 0  # a command's result is not chatter
    assert "RaceObs-S-v0" in capsys.readouterr().out
    assert cli.main(["-v", "scene", "--seed", "1", "--out", str(tmp_path / "c.glb")]) == 0
    assert "racebench 0." in capsys.readouterr().out  # -v: the debug line with version, path and arguments
    with pytest.raises(SystemExit):
        cli.main(["-q", "-v", "envs"])  # one or the other


GAIN_AGENT = """
import numpy as np


class Gain:
    obs_mode = "state"

    def __init__(self, gain, hover=-0.187):
        self.action = np.array([hover * gain, 0.0, 0.0, 0.0], dtype=np.float32)
        self.gain = gain

    def reset(self, env=None, seed=None):
        pass

    def act(self, obs):
        if self.gain != 1.0:
            raise RuntimeError(f"gain {self.gain}")
        return self.action
"""


@pytest.fixture()
def gain_spec(tmp_path: Path) -> str:
    path = tmp_path / "gain.py"
    path.write_text(GAIN_AGENT)
    return f"{path}:Gain"


def test_agent_kwargs_reach_the_constructor_and_the_identity(gain_spec: str) -> None:
    assert load_agent(gain_spec, trust_code=True, agent_kwargs={"gain": 0.5}).gain == 0.5
    ids = {policy_identity(gain_spec, kw).sha256 for kw in ({"gain": 1.0}, {"gain": 0.5}, None)}
    assert len(ids) == 3  # other constructor arguments: another policy, other records
    assert policy_identity(gain_spec, {"gain": 1.0, "hover": -0.187}) == policy_identity(
        gain_spec, {"hover": -0.187, "gain": 1.0}
    )  # key order does not matter
    with pytest.raises(AgentLoadError, match=r"Gain\(\*\*\{\}\) failed: .*gain.*--agent-kwargs"):
        load_agent(gain_spec, trust_code=True)
    with pytest.raises(AgentLoadError, match="unexpected keyword argument 'k'"):
        load_agent(gain_spec, trust_code=True, agent_kwargs={"gain": 1.0, "k": 1})
    with pytest.raises(AgentLoadError, match="module:Class"):
        load_agent("hover", agent_kwargs={"k": 1})
    assert parse_agent_kwargs('{"k": 1}') == {"k": 1}
    for bad in ("{k: 1}", "[1, 2]"):
        with pytest.raises(AgentLoadError, match="--agent-kwargs"):
            parse_agent_kwargs(bad)


def test_evaluate_passes_agent_kwargs_and_errors_are_one_line(gain_spec: str, tmp_path: Path) -> None:
    base = ["evaluate", "--agent", gain_spec, "--trust-code", "--envs", LEVEL1, "--episodes", "1"]
    assert cli.main([*base, "--agent-kwargs", '{"gain": 1.0}', "--out", str(tmp_path / "ok")]) == 0
    record = json.loads(next((tmp_path / "ok" / "records").glob("*.json")).read_text())
    assert record["error"] is None and record["policy_sha256"] == policy_identity(gain_spec, {"gain": 1.0}).sha256
    for kwargs, reason in (("{gain: 1}", "not valid JSON"), ('{"k": 1}', "unexpected keyword argument 'k'")):
        with pytest.raises(SystemExit) as exc:
            cli.main([*base, "--agent-kwargs", kwargs, "--out", str(tmp_path / "bad")])
        message = str(exc.value.code)
        assert message.startswith("racebench evaluate: ") and reason in message and "\n" not in message


def test_fly_takes_any_agent_spec(gain_spec: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from stable_baselines3 import PPO

    fly = ["fly", "--env", LEVEL1, "--agent", gain_spec]
    assert cli.main([*fly, "--trust-code", "--agent-kwargs", '{"gain": 1}']) == 0
    flown = json.loads(capsys.readouterr().out.splitlines()[0])
    assert flown["agent"] == gain_spec and flown["truncated"] and flown["error"] is None
    with pytest.raises(SystemExit, match="^racebench fly: .*--trust-code"):
        cli.main([*fly, "--agent-kwargs", '{"gain": 1}'])
    with pytest.raises(SystemExit, match="^racebench fly: the agent failed: .*gain 2"):
        cli.main([*fly, "--trust-code", "--agent-kwargs", '{"gain": 2}'])
    import gymnasium as gym

    model = PPO("MlpPolicy", gym.make(LEVEL1, obs_mode="state"), n_steps=32, batch_size=32, n_epochs=1, seed=0,
                policy_kwargs={"net_arch": [8]}, device="cpu")  # fmt: skip
    model.save(tmp_path / "tiny.zip")
    capsys.readouterr()
    assert cli.main(["fly", "--env", LEVEL1, "--agent", str(tmp_path / "tiny.zip"), "--trust-code"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["agent"].endswith("tiny.zip")
    assert cli.main(["fly", "--env", LEVEL1, "--agent", "planner", "--seed", "3"]) == 0
