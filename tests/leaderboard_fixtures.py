"""Small leaderboards for the leaderboard tests: a repository in a temporary folder, fast agents, a test salt."""

from __future__ import annotations

import json
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path

import onnx
from onnx import TensorProto, helper

from racebench.evaluation import Evaluator
from racebench.evaluation.records import RECORDS_FILE, compact_folder, record_line, seal
from racebench.evaluation.seeds import salt_sha256
from racebench.leaderboard.submit import add_entry
from racebench.sim.quadrotor import QuadrotorParams

ENV = "RaceObs-S-Level1-v0"  # no obstacles: hover and the planner run quickly and deterministically
SALT = "leaderboard-test-salt-7d2f9c41b8e6"

#: An agent that declares itself unprivileged, then finds the RaceEnv through the garbage collector and flies the
#: privileged gate follower (issue 13): the evaluator cannot stop it reading memory, so the tier rule must.
GC_AGENT = textwrap.dedent(
    """
    import gc

    from racebench.agents.control import GateFollower


    class Sneaky:
        obs_mode = "state"
        privileged = False

        def __init__(self):
            self.follower = GateFollower()

        def reset(self, env=None, seed=None):
            from racebench.envs.env import RaceEnv

            # The live env of this episode: reset with this episode's seed, not closed (old envs linger in memory).
            self.env = next(
                o for o in gc.get_objects()
                if isinstance(o, RaceEnv) and not getattr(o, "_closed", False) and o.np_random_seed == seed
            )

        def act(self, obs):
            return self.follower.act_privileged(self.env)
    """
)


def meta(name: str, obs_mode: str = "state") -> dict:
    """Descriptive entry fields, as a submitter fills them."""
    return {
        "name": name,
        "description": f"{name}: a test policy that sees the state; 1000 steps on a test machine.",
        "authors": ["A. Tester"],
        "obs_mode": obs_mode,
        "teacher": "none",
        "config": "tests/leaderboard_fixtures.py",
        "command": "none",
        "hardware": "a test machine",
        "training_seeds": [0],
    }


def write_hover_onnx(path: Path) -> Path:
    """A state policy as a plain ONNX graph (``action = state @ 0 + hover``): no code in the file, no torch."""
    path.parent.mkdir(parents=True, exist_ok=True)
    hover = [QuadrotorParams().hover_action, 0.0, 0.0, 0.0]
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["state", "w"], ["z"]), helper.make_node("Add", ["z", "b"], ["action"])],
        "hover",
        [helper.make_tensor_value_info("state", TensorProto.FLOAT, ["batch", 17])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 4])],
        [
            helper.make_tensor("w", TensorProto.FLOAT, [17, 4], [0.0] * 68),
            helper.make_tensor("b", TensorProto.FLOAT, [4], hover),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def make_repo(tmp: Path, private_accepted: bool = True, public_key_pem: str | None = None) -> Path:
    """A repository root with ``results/leaderboard`` whose config accepts :data:`SALT` (or nothing) and, given,
    a maintainers' public key."""
    board = tmp / "results" / "leaderboard"
    board.mkdir(parents=True)
    salts = [salt_sha256(SALT)] if private_accepted else []
    write_config(board, salts, public_key_pem)
    return board


def write_config(board: Path, salts: list[str], public_key_pem: str | None) -> None:
    """``leaderboard.yaml`` of a fixture leaderboard."""
    text = f"private_salt_sha256: {json.dumps(salts)}\n"
    if public_key_pem is not None:
        text += "maintainers_public_key: |\n" + "".join(f"  {line}\n" for line in public_key_pem.splitlines())
    (board / "leaderboard.yaml").write_text(text)


def make_key(folder: Path, name: str = "key") -> tuple[Path, str, str]:
    """A throwaway Ed25519 key: the private key's PEM file, the public key's PEM text and its fingerprint."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from racebench.leaderboard.signing import public_key_sha256

    key = Ed25519PrivateKey.generate()
    path = folder / f"{name}.pem"
    path.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    public = key.public_key()
    pem = public.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo).decode()
    return path, pem, public_key_sha256(public)


def evaluate(
    spec: str, out: Path, episodes: int, seed_set: str = "public", envs: tuple[str, ...] = (ENV,), **kw
) -> Path:
    """Evaluate ``spec`` into ``out`` (the fixture repository's result folder)."""
    salt = SALT if seed_set == "private" else None
    Evaluator(spec, list(envs), episodes=episodes, out_dir=out, seed_set=seed_set, salt=salt, **kw).run(progress=False)
    return out


def add(board: Path, policy: str | dict, name: str, records: list[Path], **kw) -> object:
    """``racebench leaderboard add`` for the fixture repository (one policy for all tracks, or per track)."""
    return add_entry(board, policy, meta(name, kw.pop("obs_mode", "state")), [str(r) for r in records], **kw)


def forge_successes(folder: Path) -> int:
    """Doctor every failed record of ``folder`` into a success that still passes validation; return how many.

    A hover episode runs to the time limit, so claiming every gate passed with the lap at its last step is
    consistent record by record: only the statistical replay can catch it.
    """
    from racebench.evaluation.records import env_facts

    count = 0

    def forge(record: dict) -> dict:
        nonlocal count
        if record["success"]:
            return record
        facts = env_facts(record["env_id"])
        count += 1
        return seal({**record, "success": True, "gates_passed": facts["gates"], "crashed": False, "crash_reason": None,
                     "error": None, "lap_time": record["steps"] * facts["control_dt"]})  # fmt: skip

    rewrite_records(folder, forge)
    return count


def folder_records(folder: Path) -> list[dict]:
    """The records of ``folder/records.jsonl``, line by line (unvalidated: a test may have tampered with them)."""
    return [json.loads(line) for line in (folder / RECORDS_FILE).read_text().splitlines()]


def rewrite_records(folder: Path, edit: Callable[[dict], dict | None]) -> None:
    """Rewrite ``folder/records.jsonl`` line by line through ``edit`` (``None`` drops the line): tampering."""
    kept = [edit(record) for record in folder_records(folder)]
    (folder / RECORDS_FILE).write_bytes(b"".join(record_line(r) for r in kept if r is not None))


def write_records(
    out: Path,
    spec: str,
    env_id: str,
    successes: int,
    n: int,
    lap: float = 6.0,
    seed_set: str = "public",
    outcomes: Sequence[bool] | None = None,
) -> Path:
    """Write ``n`` record-valid episodes of ``spec`` on ``env_id`` without flying: the first ``successes`` succeed,
    or, given ``outcomes``, episode i succeeds where ``outcomes[i]`` is true (``successes`` and ``n`` ignored).

    For site tests, which need chosen counts on the main ids and must stay fast. Successes take ``lap`` + 0.1 s × i
    (spread, so lap statistics are not degenerate); failures crash into an obstacle after one second.
    """
    from racebench.agents import policy_identity
    from racebench.envs.random_tracks import episode_facts
    from racebench.evaluation import RecordWriter
    from racebench.evaluation.records import env_facts
    from racebench.evaluation.seeds import seeds_for

    identity = policy_identity(spec)
    salt = SALT if seed_set == "private" else None
    writer = RecordWriter(out, identity, identity.source, "pybullet", seed_set, salt_sha256(SALT) if salt else None)
    facts = env_facts(env_id)
    dt = facts["control_dt"]
    if outcomes is not None:
        n = len(outcomes)
    for i, seed in enumerate(seeds_for(seed_set, n, salt)):
        gates = {**facts, **episode_facts(env_id, seed)}["gates"]  # a generated track's own count (Unseen, Random)
        if outcomes[i] if outcomes is not None else i < successes:
            steps = int(round((lap + 0.1 * i) / dt))
            result = {"success": True, "lap_time": steps * dt, "crashed": False, "crash_reason": None,
                      "gates_passed": gates, "return": 10.0, "steps": steps, "error": None}  # fmt: skip
        else:
            result = {"success": False, "lap_time": None, "crashed": True, "crash_reason": "obstacle:0",
                      "gates_passed": 1, "return": -5.0, "steps": int(round(1.0 / dt)), "error": None}  # fmt: skip
        writer.write(env_id, seed, result, None)
    compact_folder(out)  # one records.jsonl, as an evaluation leaves it
    return out
