"""The command line: help on every option, the command table of docs/commands.md against the parser, the README's
command list, -q/-v, agent kwargs, and `fly` with any agent spec."""

from __future__ import annotations

import argparse
import json
import re
import shutil
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


def documented_commands(parser: argparse.ArgumentParser) -> dict[tuple[str, ...], str]:
    """Command path -> the synopsis in the command table of docs/commands.md (``\\|`` unescaped); the path follows the
    parser's sub-commands through the synopsis' words (``racebench leaderboard add ...``)."""
    text = (ROOT / "docs" / "commands.md").read_text()
    rows = re.findall(r"^\| `(racebench [^`]*)` \|", text, re.M)
    assert rows, "the command table of docs/commands.md is gone"
    found = {}
    for row in (row.replace("\\|", "|") for row in rows):
        words, path, sub = row.split()[1:], (), parser
        while words and words[0] in subcommands(sub):
            sub = subcommands(sub)[words[0]]
            path, words = (*path, words[0]), words[1:]
        assert path not in found, f"two docs/commands.md rows for racebench {' '.join(path)}"
        found[path] = row
    return found


def test_the_command_table_matches_the_parser() -> None:
    parser = cli.build_parser()
    written_commands = documented_commands(parser)
    glob = written_commands.pop(())  # racebench [-q|-v] COMMAND ...
    assert "[-q|-v]" in glob and {"-q", "-v"} <= {s for a in parser._actions for s in a.option_strings}
    leaves = commands(parser)
    assert set(written_commands) == set(leaves), "commands in docs/commands.md and in the parser differ"
    for path, synopsis in written_commands.items():
        name, known = " ".join(path), options(leaves[path])
        written = set(re.findall(r"--[a-z][a-z0-9-]*", synopsis))
        drift = f"{name}: docs only {sorted(written - set(known))}, parser only {sorted(set(known) - written)}"
        assert written == set(known), drift
        for option, value in re.findall(r"\[(--[a-z0-9-]+) ([^\]\s]+)(?: \.\.\.)?\]", synopsis):
            action, values = known[option], value.split("|")
            if action.choices is not None and len(values) > 1:
                assert set(values) == {str(c) for c in action.choices}, f"{name} {option}: choices"
            elif len(values) == 1 and (action.choices or not re.fullmatch(r"[A-Z][A-Z0-9_]*(\.[a-z]+)?", value)):
                # one value, not a placeholder such as DIR, N or FILE.yaml: the default (alternatives of an
                # option without choices, as --envs main|density|...|ID, are examples, not checked)
                assert value == str(action.default), f"{name} {option}: docs {value}, parser {action.default}"


def test_the_readme_lists_every_command_once() -> None:
    """The README's short command list: one line per command, every leaf command of the parser and no other."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    listed = [tuple(item.split()) for item in re.findall(r"^- `racebench ([a-z -]+)`", section, re.M)]
    assert len(listed) == len(set(listed)), "a command listed twice in the README"
    assert set(listed) == set(commands(cli.build_parser())), "the README's command list and the parser differ"
    assert "(docs/commands.md)" in section, "the README's command list links the full reference"


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
    record = json.loads((tmp_path / "ok" / "records.jsonl").read_text())
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


READS_STATE_AGENT = """
import numpy as np


class ReadsVision:
    obs_mode = "vision"

    def reset(self, env=None, seed=None):
        pass

    def act(self, obs):
        return np.zeros(4, dtype=np.float32) * obs["depth"].mean()


class ReadsState:
    obs_mode = "state"

    def reset(self, env=None, seed=None):
        pass

    def act(self, obs):
        return np.zeros(4, dtype=np.float32) * np.asarray(obs, dtype=np.float32)[0]
"""


def test_fly_refuses_an_obs_mode_the_policy_does_not_read(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "readers.py"
    path.write_text(READS_STATE_AGENT)
    for cls, asked, own in (("ReadsVision", "state", "vision"), ("ReadsState", "vision", "state")):
        with pytest.raises(SystemExit) as exc:
            cli.main(["-q", "fly", "--env", LEVEL1, "--agent", f"{path}:{cls}", "--trust-code", "--obs-mode", asked])
        assert exc.value.code == f"racebench fly: this policy takes {own} observations (use --obs-mode {own})"

    def made(env_id: str, **kwargs):  # stands in for the env: how far fly() got, and with which mode
        raise RuntimeError(f"made with obs_mode={kwargs['obs_mode']}")

    from racebench.evaluation import episode

    monkeypatch.setattr(episode, "make_env", made)
    with pytest.raises(RuntimeError, match="obs_mode=vision"):  # built-ins ignore their observation: either goes
        cli.fly(LEVEL1, "hover", 0, obs_mode="vision")


def test_a_misspelled_option_is_reported_by_its_subcommand(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["evaluate", "--agent", "hover", "--epsiodes", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: racebench evaluate ")
    assert err.splitlines()[-1] == (
        "racebench evaluate: error: unrecognized arguments: --epsiodes 3 (did you mean --episodes?)"
    )
    with pytest.raises(SystemExit):  # named, though the required --agent is missing too
        cli.main(["evaluate", "--agnet", "hover"])
    assert capsys.readouterr().err.splitlines()[-1] == (
        "racebench evaluate: error: unrecognized arguments: --agnet (did you mean --agent?)"
    )
    with pytest.raises(SystemExit):
        cli.main(["fly", "--agnet", "hover", "--sede=3"])
    assert capsys.readouterr().err.splitlines()[-1] == (
        "racebench fly: error: unrecognized arguments: --agnet hover --sede=3 (did you mean --agent (for --agnet), "
        "--seed (for --sede)?)"
    )
    with pytest.raises(SystemExit):  # a missing required option alone: argparse's own message
        cli.main(["evaluate", "--episodes", "3"])
    assert capsys.readouterr().err.splitlines()[-1].endswith("error: the following arguments are required: --agent")
    with pytest.raises(SystemExit):
        cli.main(["leaderboard", "verify", "--bogus"])  # nested: the innermost command's usage
    assert capsys.readouterr().err.startswith("usage: racebench leaderboard verify ")
    with pytest.raises(SystemExit):
        cli.main(["--bogus", "envs"])  # before the command: the top level's
    assert capsys.readouterr().err.startswith("usage: racebench [-h]")


def test_agent_help_lists_every_builtin_agent() -> None:
    from racebench.agents import BUILTIN_AGENTS

    leaves = commands(cli.build_parser())
    helps = {path: options(leaves[path])["--agent"].help for path in (("fly",), ("evaluate",), ("render",))}
    helps["leaderboard add --policy"] = options(leaves[("leaderboard", "add")])["--policy"].help
    assert "planner-fast" in BUILTIN_AGENTS
    for where, text in helps.items():
        missing = [name for name in BUILTIN_AGENTS if not re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", text)]
        assert not missing, f"{where}: help omits {missing}"


def test_evaluate_prints_the_mean_lap_as_the_tables_do(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import shutil

    from racebench.evaluation import read_summaries

    out = tmp_path / "follow"
    shutil.copytree(ROOT / "results" / "follow", out)  # every episode already flown: evaluate only summarises
    flown = ["--envs", "RaceObs-S-v0", "--episodes", "50"]  # all of that id's records, as read_summaries reads
    assert cli.main(["-q", "evaluate", "--agent", "follow", *flown, "--out", str(out)]) == 0
    legend, header, row = capsys.readouterr().out.splitlines()[:3]
    assert legend == cli.SUMMARY_LEGEND
    assert header.split()[-1] == "lap_time_mean" and "median" not in header
    summary = read_summaries([out]).set_index("env_id")
    mean, median = summary.loc["RaceObs-S-v0", ["lap_time_mean", "lap_time_median"]]
    assert f"{mean:.3f}" != f"{median:.3f}"  # the test tells them apart
    assert row.split()[-1] == f"{mean:.3f}"


def test_evaluate_explains_its_columns_and_prints_no_lap_as_a_dash(tmp_path: Path, capsys) -> None:
    """The printed summary says what sr_ci_low/high are and the lap time's unit; a cell without a successful lap
    prints "–", not "NaN"."""
    assert cli.main(["-q", "evaluate", "--agent", "hover", "--envs", LEVEL1, "--episodes", "1",
                     "--out", str(tmp_path / "hover")]) == 0  # fmt: skip
    legend, header, row = capsys.readouterr().out.splitlines()[:3]
    assert "sr_ci_low/sr_ci_high: its 95 % Wilson interval" in legend and "in seconds" in legend
    assert row.split()[-1] == "–" and "nan" not in row.lower()


def test_no_pybullet_banner_even_on_commands_that_load_it(tmp_path: Path) -> None:
    import subprocess
    import sys

    import racebench

    def run(*args: str) -> subprocess.CompletedProcess:
        code = f"from racebench.cli import main; main({list(args)!r})"
        return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)

    envs = run("-q", "envs")
    assert envs.returncode == 0 and envs.stdout == "\n".join(racebench.ENV_IDS) + "\n" and envs.stderr == ""
    scene = run("-q", "scene", "--out", str(tmp_path / "s.obj"))  # imports PyBullet and connects
    assert scene.returncode == 0, scene.stderr
    assert "pybullet build time" not in scene.stdout + scene.stderr
    assert scene.stdout == "" and scene.stderr == ""
    # one import site, so that the banner cannot come back through a module importing PyBullet first
    importers = [
        str(path.relative_to(ROOT))
        for path in sorted((ROOT / "racebench").rglob("*.py"))
        if re.search(r"^\s*(import pybullet\b|from pybullet(_utils)? import)", path.read_text(), re.M)
    ]
    assert importers == ["racebench/sim/bullet.py"]


# ------------------------------------------------------- YAML files with Python tags


EVIL_YAML = "name: !!python/object/apply:os.system ['touch {marker}']\nmethod: ppo\n"


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--config", "{yaml}", "--out", "{tmp}/run", "--eval-episodes", "0"],
        ["sweep", "{yaml}", "--out", "{tmp}/sweep"],
        ["sweep", "{sweep}", "--out", "{tmp}/sweep"],  # a sweep naming a bad config file
        ["leaderboard", "add", "--policy", "planner", "--meta", "{yaml}", "--leaderboard", "{tmp}/board"],
        ["curves", "{tmp}/run"],  # a run folder's config.yaml
    ],
    ids=["train", "sweep", "sweep-config", "leaderboard-add", "curves"],
)
def test_yaml_with_python_tags_is_a_one_line_error(argv: list[str], tmp_path: Path) -> None:
    """``yaml.safe_load`` refuses ``!!python/...`` tags; each command says so in one line naming the file."""
    marker = tmp_path / "ran"
    evil = tmp_path / "evil.yaml"
    evil.write_text(EVIL_YAML.format(marker=marker))
    (tmp_path / "sweep.yaml").write_text("configs: [evil.yaml]\ntracks: [S]\nseeds: [0]\nsteps: 64\n")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "progress.csv").write_text("timesteps,episodes,success_rate,wall_s\n64,1,0.0,1.0\n")
    shutil.copy(evil, tmp_path / "run" / "config.yaml")
    values = {"yaml": str(evil), "sweep": str(tmp_path / "sweep.yaml"), "tmp": str(tmp_path)}
    with pytest.raises(SystemExit) as exc:
        cli.main([arg.format(**values) for arg in argv])
    message = str(exc.value.code)
    assert message.startswith(f"racebench {argv[0]}") and "\n" not in message, message
    assert "evil.yaml" in message or "config.yaml" in message
    assert "python/object/apply:os.system" in message and "line 1, column 7" in message
    assert not marker.exists()


@pytest.mark.parametrize("command", ["export-onnx", "export-policy"])
def test_export_commands_refuse_a_pickled_payload(command: str, tmp_path: Path) -> None:
    from payloads import evil_sb3_zip

    marker = tmp_path / "ran"
    evil = evil_sb3_zip(tmp_path / "evil.zip", marker)
    with pytest.raises(SystemExit) as exc:
        cli.main([command, str(evil), "--out", str(tmp_path / ("out.onnx" if command == "export-onnx" else "out.zip"))])
    message = str(exc.value.code)
    assert message.startswith(f"racebench {command}: agent") and "--trust-code" in message and "\n" not in message
    assert not marker.exists()


def test_the_help_names_every_command_and_each_command_has_a_description(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    head = out.split("positional arguments")[0]
    assert "``" not in out
    for command in ("fly", "evaluate", "train", "sweep", "compare", "leaderboard"):
        assert command in head, command  # the opening lines name it, not only the command list
    parser = cli.build_parser()
    for path, sub in commands(parser).items():
        assert (sub.description or "").strip(), f"racebench {' '.join(path)} --help has no description"
    with pytest.raises(SystemExit):
        cli.main(["compare", "--help"])
    assert "exact McNemar test" in capsys.readouterr().out.split("positional arguments")[0]
