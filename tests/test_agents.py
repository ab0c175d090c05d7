"""The SB3 loader (VecNormalize statistics beside a checkpoint, uint8-depth policies on the standard envs) and what
a policy hash covers (ONNX external data, a Python agent's modules, the committed hashes)."""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import racebench  # noqa: F401  (registers the ids)
from racebench.agents import (
    TRUSTED_CHECKPOINTS,
    AgentLoadError,
    SB3Agent,
    UntrustedCodeError,
    export_onnx,
    load_agent,
    policy_identity,
    python_agent_modules,
    vecnormalize_path,
)
from racebench.evaluation.records import sha256_file

ROOT = Path(__file__).parents[1]
LEVEL1 = "RaceObs-S-Level1-v0"


@pytest.fixture(scope="module")
def normalised_ppo(tmp_path_factory: pytest.TempPathFactory):
    """A tiny PPO trained under VecNormalize(norm_obs=True): its zip with vecnormalize.pkl, and a bare copy."""
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(LEVEL1, obs_mode="state")]), norm_obs=True, norm_reward=False)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0,
                policy_kwargs={"net_arch": [16]}, device="cpu")  # fmt: skip
    model.learn(128)
    assert np.any(np.abs(venv.obs_rms.mean) > 0.05), "the statistics must move observations for the test to bite"
    folder = tmp_path_factory.mktemp("normalised")
    model.save(folder / "model.zip")
    venv.save(str(folder / "vecnormalize.pkl"))  # SB3's VecNormalize.save: a pickle at the given path
    bare = tmp_path_factory.mktemp("bare") / "model.zip"
    shutil.copy(folder / "model.zip", bare)
    venv.training = False
    return model, venv, folder / "model.zip", bare


def observations(n: int = 6) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, size=(n, 17)).astype(np.float32)


def test_saved_observation_statistics_are_applied(normalised_ppo) -> None:
    model, venv, with_stats, bare = normalised_ppo
    agent, plain = load_agent(str(with_stats), trust_code=True), load_agent(str(bare), trust_code=True)
    assert agent.normalizer is not None and plain.normalizer is None
    obs = observations()
    agent.reset()
    plain.reset()
    got = np.array([agent.act(o) for o in obs])
    raw = np.array([plain.act(o) for o in obs])
    expected = np.array([model.predict(venv.normalize_obs(o), deterministic=True)[0] for o in obs])
    np.testing.assert_array_equal(got, expected)  # SB3's own normalised predict
    assert not np.allclose(got, raw), "with and without the statistics the actions must differ"
    agent.start(len(obs))  # the lockstep path normalises too
    np.testing.assert_allclose(agent.act_batch(list(obs)), expected, atol=1e-6)


def test_the_statistics_are_part_of_the_policy_identity(normalised_ppo) -> None:
    _, _, with_stats, bare = normalised_ppo
    assert vecnormalize_path(with_stats) == with_stats.parent / "vecnormalize.pkl"
    assert vecnormalize_path(bare) is None
    identity = policy_identity(str(with_stats))
    assert identity.sha256 == load_agent(str(with_stats), trust_code=True).sha256
    assert identity.sha256 != sha256_file(with_stats)  # same zip bytes, other statistics: another policy
    assert policy_identity(str(bare)).sha256 == sha256_file(bare)  # no statistics: the zip's hash, as before


def test_periodic_checkpoint_statistics_are_found_by_sb3s_name(tmp_path: Path) -> None:
    (tmp_path / "ppo_2048_steps.zip").write_bytes(b"")
    (tmp_path / "vecnormalize.pkl").write_bytes(b"")  # a final model's, not this checkpoint's: never used silently
    with pytest.raises(AgentLoadError, match="none is named as its own.*--no-vecnormalize"):
        vecnormalize_path(tmp_path / "ppo_2048_steps.zip")
    (tmp_path / "ppo_vecnormalize_2048_steps.pkl").write_bytes(b"")
    assert vecnormalize_path(tmp_path / "ppo_2048_steps.zip") == tmp_path / "ppo_vecnormalize_2048_steps.pkl"


class _Marker:
    """Unpickling it creates a file: proof that a pickle ran."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def test_statistics_beside_a_trusted_checkpoint_still_need_trust_code(tmp_path: Path) -> None:
    shipped = ROOT / "baselines/checkpoints" / TRUSTED_CHECKPOINTS[min(TRUSTED_CHECKPOINTS)]
    copy = tmp_path / shipped.name
    shutil.copy(shipped, copy)
    assert isinstance(load_agent(str(copy)), SB3Agent)  # the zip alone is trusted by its bytes
    marker = tmp_path / "ran"
    (tmp_path / "vecnormalize.pkl").write_bytes(pickle.dumps(_Marker(marker)))
    with pytest.raises(UntrustedCodeError, match="VecNormalize"):
        load_agent(str(copy))
    assert not marker.exists(), "the statistics must be refused before they are unpickled"


def test_reward_only_statistics_leave_the_actions_alone(normalised_ppo, tmp_path: Path) -> None:
    model, venv, with_stats, _ = normalised_ppo
    shutil.copy(with_stats, tmp_path / "model.zip")
    venv.norm_obs = False  # what racebench train saves: rewards normalised, observations not
    try:
        venv.save(str(tmp_path / "vecnormalize.pkl"))
    finally:
        venv.norm_obs = True
    agent = load_agent(str(tmp_path / "model.zip"), trust_code=True)
    assert agent.normalizer is None
    obs = observations(3)
    agent.reset()
    np.testing.assert_array_equal([agent.act(o) for o in obs], [model.predict(o, deterministic=True)[0] for o in obs])


def test_a_uint8_depth_policy_flies_the_standard_envs(tmp_path: Path) -> None:
    """A policy trained with depth_format="uint8" gets, from the float envs, exactly the uint8 envs' input."""
    small = gym.make(LEVEL1, depth_format="uint8")
    model = PPO("MultiInputPolicy", small, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(32)
    model.save(tmp_path / "cnn.zip")
    agent = load_agent(str(tmp_path / "cnn.zip"), trust_code=True)
    assert agent.obs_mode == "vision" and agent.uint8_depth
    standard = gym.make(LEVEL1)
    obs_float, _ = standard.reset(seed=4)
    obs_uint8, _ = small.reset(seed=4)
    agent.reset()
    expected = model.predict(obs_uint8, deterministic=True)[0]
    np.testing.assert_array_equal(agent.act(obs_float), expected)
    agent.start(2)
    np.testing.assert_allclose(agent.act_batch([obs_float, obs_float]), [expected, expected], atol=1e-6)
    standard.close()
    small.close()


def test_a_stock_multiinput_policy_on_float_depth_is_warned_about_once(tmp_path: Path, caplog) -> None:
    """Stock SB3 MultiInputPolicy on the default float32 depth flattens the image into an MLP: loading it says so
    once per process, naming depth_format="uint8"; a uint8-depth policy (a NatureCNN) is not warned about."""
    from racebench.agents import loading

    flat = PPO("MultiInputPolicy", gym.make(LEVEL1), n_steps=32, batch_size=32, seed=0, device="cpu")
    assert loading.flattens_depth(flat.policy)
    flat.save(tmp_path / "flat.zip")
    cnn = PPO(
        "MultiInputPolicy", gym.make(LEVEL1, depth_format="uint8"), n_steps=32, batch_size=32, seed=0, device="cpu"
    )
    assert not loading.flattens_depth(cnn.policy)
    loading._warned_flat_depth = False
    with caplog.at_level("WARNING", logger="racebench"):
        load_agent(str(tmp_path / "flat.zip"), trust_code=True)
        load_agent(str(tmp_path / "flat.zip"), trust_code=True)
    warnings = [r.getMessage() for r in caplog.records if "flattens the 64x64 depth" in r.getMessage()]
    assert len(warnings) == 1 and 'depth_format="uint8"' in warnings[0]


def test_onnx_external_data_is_part_of_the_policy_identity(tmp_path: Path) -> None:
    """Weights saved as external data beside the graph: changing them changes the hash; a missing file is named."""
    import onnx

    model = PPO("MlpPolicy", gym.make(LEVEL1, obs_mode="state"), n_steps=32, seed=0, device="cpu")
    inline = export_onnx(model, tmp_path / "inline.onnx")
    assert policy_identity(str(inline)).sha256 == sha256_file(inline)  # no external data: the file's hash, as before
    external = tmp_path / "external" / "policy.onnx"
    external.parent.mkdir()
    onnx.save_model(onnx.load(str(inline)), str(external), save_as_external_data=True, location="weights.bin",
                    size_threshold=0)  # fmt: skip
    weights = external.parent / "weights.bin"
    agent = load_agent(str(external))
    obs = observations(4)
    agent.start(len(obs))
    np.testing.assert_allclose(agent.act_batch(list(obs)), model.predict(obs, deterministic=True)[0], atol=1e-5)
    before = policy_identity(str(external)).sha256
    assert agent.sha256 == before != sha256_file(external)
    graph_bytes = external.read_bytes()
    data = bytearray(weights.read_bytes())
    data[0] ^= 1  # other weights, the same graph file
    weights.write_bytes(bytes(data))
    assert external.read_bytes() == graph_bytes and policy_identity(str(external)).sha256 != before
    weights.unlink()
    for load in (policy_identity, load_agent):
        with pytest.raises(AgentLoadError, match=r"external data 'weights.bin' does not exist") as caught:
            load(str(external))
        assert "\n" not in str(caught.value)


AGENT_WITH_HELPER = """
import numpy as np

from helper import THRUST


class Agent:
    obs_mode = "state"

    def reset(self, env=None, seed=None):
        pass

    def act(self, obs):
        return np.array([THRUST, 0, 0, 0], dtype=np.float32)
"""


def test_a_python_agents_hash_covers_the_modules_it_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "agent.py").write_text(AGENT_WITH_HELPER)
    (tmp_path / "helper.py").write_text("from numbers_helper import HALF\nTHRUST = HALF\n")
    (tmp_path / "numbers_helper.py").write_text("HALF = 0.5\n")
    spec = f"{tmp_path / 'agent.py'}:Agent"
    first = policy_identity(spec).sha256
    assert set(python_agent_modules(tmp_path / "agent.py")) == {"helper", "numbers_helper"}  # numpy is installed
    assert first != sha256_file(tmp_path / "agent.py")
    (tmp_path / "helper.py").write_text("from numbers_helper import HALF\nTHRUST = HALF * 1.0\n")
    second = policy_identity(spec).sha256
    assert second != first  # a changed helper: another policy, other records
    (tmp_path / "numbers_helper.py").write_text("HALF = 0.25\n")
    assert policy_identity(spec).sha256 not in (first, second)  # and a helper's helper
    monkeypatch.delitem(sys.modules, "helper", raising=False)
    monkeypatch.delitem(sys.modules, "numbers_helper", raising=False)
    assert load_agent(spec, trust_code=True).act(None)[0] == 0.25


def test_a_python_agent_loading_unhashed_code_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "hidden_helper", raising=False)
    (tmp_path / "hidden_helper.py").write_text("THRUST = 0.5\n")
    agent = AGENT_WITH_HELPER.replace(
        "from helper import THRUST", 'THRUST = __import__("importlib").import_module(\n    "hidden" + "_helper").THRUST'
    )
    (tmp_path / "sneaky.py").write_text(agent)
    with pytest.raises(AgentLoadError, match="loaded module 'hidden_helper' .* without importing it by name") as caught:
        load_agent(f"{tmp_path / 'sneaky.py'}:Agent", trust_code=True)
    assert "\n" not in str(caught.value)


def committed_sha256(source: str) -> str:
    """The policy_sha256 of the first committed record (results/, baselines/) of ``source``."""
    for folder in ("results", "baselines"):
        for records in sorted((ROOT / folder).glob("**/records.jsonl")):
            for line in records.read_text().splitlines():
                meta = json.loads(line)
                if meta["policy_source"] == source:
                    return meta["policy_sha256"]
    raise AssertionError(f"no committed record of {source!r}")


def test_builtin_and_committed_hashes_are_unchanged() -> None:
    """Committed records key on these hashes: a built-in's, a shipped checkpoint's; a shipped Python agent importing
    installed code only keeps its file's hash."""
    for builtin in ("planner-fast", "hover"):
        assert policy_identity(builtin).sha256 == committed_sha256(builtin)
    # A campaign checkpoint's records name the path it was evaluated at (the run's folder): key on its own eval.
    checkpoint = ROOT / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"
    evaluated = {json.loads(line)["policy_sha256"] for line in (checkpoint.parent / "eval/records.jsonl").open()}
    assert evaluated == {policy_identity(str(checkpoint)).sha256}
    ensemble = ROOT / "scripts/ensemble_agent.py"
    assert python_agent_modules(ensemble) == {}  # racebench, numpy and the standard library only
    assert policy_identity(f"{ensemble}:EnsembleAgent").sha256 == sha256_file(ensemble)


def test_a_checkpoint_whose_schedules_cannot_be_unpickled_loads_without_a_warning(tmp_path: Path) -> None:
    """cloudpickle's pickles of the training schedules do not load across its versions (a zip written under
    cloudpickle 3 and read under 2 warns "Can't get attribute '_function_setstate'"); flying never uses them."""
    import warnings
    import zipfile

    model = PPO("MlpPolicy", gym.make(LEVEL1, obs_mode="state"), n_steps=32, batch_size=32, seed=0, device="cpu",
                learning_rate=lambda progress: 3e-4 * progress)  # fmt: skip
    model.save(tmp_path / "written.zip")
    with zipfile.ZipFile(tmp_path / "written.zip") as source:
        members = {name: source.read(name) for name in source.namelist()}
    data = json.loads(members["data"])
    for key in ("learning_rate", "lr_schedule", "clip_range"):  # as another cloudpickle version would see them
        data[key][":serialized:"] = "gARjYnVpbHRpbnMKbm9fc3VjaF9uYW1lCnEALg=="  # builtins.no_such_name
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(tmp_path / "unreadable.zip", "w") as target:
        for name, content in members.items():
            target.writestr(name, content)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.warns(UserWarning, match="Could not deserialize object lr_schedule"):
            PPO.load(tmp_path / "unreadable.zip", device="cpu")  # what SB3 alone does with it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        agent = load_agent(str(tmp_path / "unreadable.zip"), trust_code=True)
    assert not [w for w in caught if "deserialize" in str(w.message)], [str(w.message) for w in caught]
    obs = observations(3)
    agent.start(len(obs))
    np.testing.assert_allclose(agent.act_batch(list(obs)), model.predict(obs, deterministic=True)[0], atol=1e-6)
