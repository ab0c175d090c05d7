"""Teacher–student distillation (DAgger): the dataset, the beta schedule, a tiny run end to end."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scripts_loader import load_script

from racebench.agents import BUILTIN_VERSIONS, SB3Agent
from racebench.training.dagger import DaggerConfig, Dataset, distill, load_resume_state

ROOT = Path(__file__).parents[1]


def segment(values: list[float], size: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A segment whose steps are numbered by ``values`` (state and action), depth 0.5."""
    k = np.array(values, np.float32)[:, None]
    return np.repeat(k, 17, 1), np.full((len(k), 1, size, size), 0.5, np.float32), np.repeat(k, 4, 1)


def test_dataset_is_a_ring_buffer_of_quantised_depth() -> None:
    data = Dataset(capacity=3, depth_size=2)
    for k in range(4):
        data.add_segment(*segment([k]))
    assert data.size == 3 and sorted(data.action[:, 0].tolist()) == [1.0, 2.0, 3.0]  # the oldest was overwritten
    batch = data.batch(np.arange(3))
    assert batch["depth"].dtype.is_floating_point and abs(float(batch["depth"][0, 0, 0, 0]) - 128 / 255) < 1e-6


def test_sequence_chunks_keep_episode_boundaries() -> None:
    """Chunks cover every stored step once, hold consecutive steps of one episode, and break at every start."""
    data = Dataset(capacity=100, depth_size=2)
    episodes = [list(range(100 * e, 100 * e + n)) for e, n in enumerate([5, 40, 3, 17])]  # step ids, by episode
    for steps in episodes:
        data.add_segment(*segment(steps))
    first, count, position = data.chunks(16)
    assert count.sum() == data.size == 65 and count.max() <= 16
    covered = np.concatenate([np.arange(a, a + n) for a, n in zip(first, count, strict=True)])
    assert np.array_equal(np.sort(covered), np.arange(65))  # each step once
    ids = data.action[:, 0]
    for a, n, p in zip(first, count, position, strict=True):
        chunk = ids[a : a + n]
        assert np.all(np.diff(chunk) == 1)  # consecutive steps ...
        assert len({int(i) // 100 for i in chunk}) == 1  # ... of one episode
        assert (p == 0) == (int(chunk[0]) % 100 == 0)  # position 0 exactly where an episode begins
    assert [int(n) for n in count] == [5, 16, 16, 8, 3, 16, 1]

    # The ring overwrites the oldest steps: the first survivor starts a chunk of its own (zero state), as does
    # index 0, where a segment that wrapped around the array's end continues.
    data.add_segment(*segment(list(range(400, 445))))  # 65 + 45 > 100: wraps, overwrites episode 0 and part of 1
    first, count, position = data.chunks(16)
    assert count.sum() == 100
    ids = data.action[:, 0]
    for a, n in zip(first, count, strict=True):
        chunk = ids[a : a + n]
        assert np.all(np.diff(chunk) == 1) and len({int(i) // 100 for i in chunk}) == 1
    assert position[np.searchsorted(first, data.next)] == 0  # the oldest surviving step (an episode-1 step)
    assert ids[data.next] == 105 and position[0] == 0


def test_chunk_start_states_are_the_states_of_stepping_each_episode_in_order() -> None:
    """The GRU state a training chunk starts from is the one the evaluator reaches stepping the episode."""
    import gymnasium as gym
    import torch

    from racebench.training.dagger import (
        chunk_start_states,
        make_student,
        sequence_loss,
        student_features,
        student_unroll,
    )  # fmt: skip

    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast")
    policy = make_student(env, seed=0).policy
    env.close()
    rng = np.random.default_rng(0)
    data = Dataset(capacity=200, depth_size=64)
    for n in (7, 30, 12):
        data.add_segment(rng.normal(size=(n, 17)).astype(np.float32), rng.random((n, 1, 64, 64), np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32))  # fmt: skip
    chunks = data.chunks(8)
    states = chunk_start_states(policy, data, chunks)
    first, _, position = chunks
    with torch.no_grad():
        features = student_features(policy, data.observations(np.arange(data.size)))
        stepped = torch.zeros(data.size, policy.lstm_actor.hidden_size)  # state before each step
        hidden = torch.zeros(1, 1, policy.lstm_actor.hidden_size)
        for i in range(data.size):
            if data.starts[i]:
                hidden = torch.zeros_like(hidden)
            stepped[i] = hidden[0, 0]
            _, output = student_unroll(policy, features[i].view(1, 1, -1), hidden)
            hidden = output[-1:]
    assert torch.allclose(states, stepped[first], atol=1e-5)
    assert torch.all(states[position == 0] == 0) and torch.any(states[position > 0] != 0)

    # The training loss of a minibatch of chunks (full and short ones, in any order) is the mean squared error
    # over their real steps of the actions stepped one at a time from each chunk's start state.
    _, count, _ = chunks
    pick = np.array([len(first) - 1, 0, 3, 5])
    assert len(set(count[pick].tolist())) > 1  # short chunks among them: padding must be masked
    loss = sequence_loss(policy, data, first[pick], count[pick], states[pick], 8)
    errors = []
    with torch.no_grad():
        for c in pick:
            hidden = states[c].view(1, 1, -1)
            for i in range(first[c], first[c] + count[c]):
                action, output = student_unroll(policy, features[i].view(1, 1, -1), hidden)
                hidden = output[-1:]
                errors.append(((action[0, 0] - torch.from_numpy(data.action[i])) ** 2).mean())
    assert torch.allclose(loss, torch.stack(errors).mean(), atol=1e-6)


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="beta_decay"):
        DaggerConfig(beta_decay=1.5).validate()
    with pytest.raises(ValueError, match="seed"):
        DaggerConfig(seed=1_000_000).validate()
    with pytest.raises(ValueError, match="teacher"):
        DaggerConfig(teacher="hover").validate()  # not a privileged planner: cannot label every state
    with pytest.raises(ValueError, match="teacher_gate_clearance must be in"):
        DaggerConfig(teacher_gate_clearance=0.6).validate()  # beyond the opening's centre
    with pytest.raises(ValueError, match="teacher planner-fast only"):
        DaggerConfig(teacher="planner", teacher_gate_clearance=0.5).validate()
    with pytest.raises(ValueError, match="teacher_integral_gain must be >= 0"):
        DaggerConfig(teacher_integral_gain=-1.0).validate()
    with pytest.raises(ValueError, match="teacher_replan_distance must be > 0"):
        DaggerConfig(teacher_replan_distance=0.0).validate()
    with pytest.raises(ValueError, match="teacher_obstacles must be one of"):
        DaggerConfig(teacher_obstacles="visible").validate()
    with pytest.raises(ValueError, match="apply to teacher planner-fast only"):
        DaggerConfig(teacher="planner", teacher_obstacles="seen").validate()
    with pytest.raises(ValueError, match="apply to teacher planner-fast only"):
        DaggerConfig(teacher="planner", teacher_integral_gain=0.0).validate()
    with pytest.raises(ValueError, match="gate_shift_z must be >= 0"):
        DaggerConfig(gate_shift_z=-0.1).validate()
    with pytest.raises(ValueError, match="teacher_wanted_clearance must be in"):
        DaggerConfig(teacher_wanted_clearance=0.2).validate()  # below the planner's own clearance floor
    with pytest.raises(ValueError, match="apply to teacher planner-fast only"):
        DaggerConfig(teacher="planner", teacher_wanted_clearance=0.6).validate()
    with pytest.raises(ValueError, match="crash_weight > 0 and crash_window >= 1"):
        DaggerConfig(crash_weight=0.0).validate()
    with pytest.raises(ValueError, match="crash_weight > 0 and crash_window >= 1"):
        DaggerConfig(crash_window=0).validate()
    with pytest.raises(ValueError, match="learning_rate_final must be > 0"):
        DaggerConfig(learning_rate_final=0.0).validate()
    with pytest.raises(ValueError, match="weight_decay must be >= 0"):
        DaggerConfig(weight_decay=-0.01).validate()
    with pytest.raises(ValueError, match="augment_shift must be a whole number of pixels"):
        DaggerConfig(augment_shift=9).validate()
    with pytest.raises(ValueError, match="path_aux_weight must be >= 0"):
        DaggerConfig(path_aux_weight=-0.5).validate()
    with pytest.raises(ValueError, match="path_aux_weight needs teacher planner-fast"):
        DaggerConfig(teacher="planner", path_aux_weight=1.0).validate()
    with pytest.raises(ValueError, match="mixture_sigma must be > 0"):
        DaggerConfig(mixture_sigma=0.0).validate()
    with pytest.raises(ValueError, match="freeze_features_after must be an iteration >= 0"):
        DaggerConfig(freeze_features_after=-1).validate()
    with pytest.raises(ValueError, match="freeze_features_after needs augment_shift 0"):
        DaggerConfig(freeze_features_after=2, augment_shift=1).validate()


def test_the_learning_rate_falls_linearly_from_the_first_iteration_to_the_last() -> None:
    """learning_rate_final: learning_rate at iteration 0, learning_rate_final at the last, a straight line between;
    unset (or a one-iteration run), the rate stays learning_rate."""
    from racebench.training.dagger import iteration_learning_rate

    config = DaggerConfig(iterations=5, learning_rate=3e-4, learning_rate_final=1e-4)
    rates = [iteration_learning_rate(config, k) for k in range(5)]
    assert rates[0] == 3e-4 and rates[-1] == 1e-4  # the ends exactly
    np.testing.assert_allclose(rates, [3e-4, 2.5e-4, 2e-4, 1.5e-4, 1e-4], rtol=1e-12)
    assert iteration_learning_rate(config, 9) == 1e-4  # a resumption that runs on past the plan stays at the end
    assert all(iteration_learning_rate(DaggerConfig(iterations=5), k) == 3e-4 for k in range(5))
    assert iteration_learning_rate(DaggerConfig(iterations=1, learning_rate_final=1e-5), 0) == 3e-4


def test_fit_samples_caps_each_fit_and_numbers_load_from_yaml(tmp_path: Path) -> None:
    """fit_samples cuts a fit's passes at that many samples (a recurrent student: that many // length chunks),
    counted in optimizer steps; without it every pass is whole. YAML may write it as 1e5 or null."""
    import gymnasium as gym

    from racebench.training.dagger import fit, make_student

    class CountingOptimizer:
        def __init__(self) -> None:
            self.steps = 0

        def zero_grad(self) -> None:
            pass

        def step(self) -> None:
            self.steps += 1

    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast")
    rng = np.random.default_rng(0)
    data = Dataset(capacity=200, depth_size=64)
    for n in (40, 40, 40):  # 15 chunks of 8 steps
        data.add_segment(rng.normal(size=(n, 17)).astype(np.float32), rng.random((n, 1, 64, 64), np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32))  # fmt: skip
    # (student, fit_samples, optimizer steps): a recurrent minibatch is 16 // 8 = 2 chunks of 8, so a whole pass
    # is 8 steps; a feed-forward one is 16 samples, so a whole pass over 120 is 7 steps (the remainder dropped).
    cases = [("vision-ppo", None, 3 * 8), ("vision-ppo", 80, 5), ("vision-ppo", 200, 8 + 5),
             ("vision-no-gru", None, 3 * 7), ("vision-no-gru", 100, 6), ("vision-no-gru", 250, 7 + 7)]  # fmt: skip
    for student, cap, steps in cases:
        policy = make_student(env, seed=0, student=student).policy
        config = DaggerConfig(epochs=3, batch_size=16, sequence_length=8, fit_samples=cap, student=student)
        optimizer = CountingOptimizer()
        assert np.isfinite(fit(policy, data, config, optimizer, np.random.default_rng(0)))
        assert optimizer.steps == steps, (student, cap)
    env.close()

    path = tmp_path / "capped.yaml"
    path.write_text("method: dagger\nname: capped\nfit_samples: 1e5\ngate_shift_z: '0.3'\n")
    loaded = DaggerConfig.from_yaml(path)
    assert loaded.fit_samples == 100_000 and isinstance(loaded.fit_samples, int) and loaded.gate_shift_z == 0.3
    path.write_text("method: dagger\nname: capped\nfit_samples: null\n")
    assert DaggerConfig.from_yaml(path).fit_samples is None
    path.write_text("method: dagger\nname: capped\nfit_samples: lots\n")
    with pytest.raises(ValueError, match="fit_samples must be a number, got 'lots'"):
        DaggerConfig.from_yaml(path)
    with pytest.raises(ValueError, match="fit_samples must be >= batch_size"):
        DaggerConfig(fit_samples=100, batch_size=256).validate()


def test_the_teacher_is_built_with_its_settings() -> None:
    from racebench.agents.planner import FastPlannerAgent, PlannerAgent
    from racebench.training.dagger import make_teacher

    centred = make_teacher(DaggerConfig(teacher_gate_clearance=0.5))
    assert isinstance(centred, FastPlannerAgent) and centred.gate_clearance == 0.5
    assert make_teacher(DaggerConfig()).gate_clearance == FastPlannerAgent().gate_clearance == 0.4
    assert isinstance(make_teacher(DaggerConfig(teacher="planner")), PlannerAgent)
    default = make_teacher(DaggerConfig())
    assert (default.integral_gain, default.replan_distance) == (FastPlannerAgent().integral_gain, None)
    stateless = make_teacher(DaggerConfig(teacher_integral_gain=0.0, teacher_replan_distance=0.5))
    assert (stateless.integral_gain, stateless.replan_distance) == (0.0, 0.5)
    assert default.wanted_clearance == FastPlannerAgent().wanted_clearance == 0.45
    assert make_teacher(DaggerConfig(teacher_wanted_clearance=0.6)).wanted_clearance == 0.6
    assert default.obstacle_knowledge == "all"
    assert make_teacher(DaggerConfig(teacher_obstacles="seen")).obstacle_knowledge == "seen"


def test_training_scenes_take_the_configs_gate_shifts() -> None:
    from racebench.training.dagger import make_training_envs

    paper = make_training_envs(DaggerConfig(n_envs=2, gate_shift=1.0, gate_shift_z=0.3))
    default = make_training_envs(DaggerConfig(n_envs=1))
    try:
        assert len(paper) == 2
        generator = paper[0].unwrapped.generator
        assert (generator.gate_shift, generator.gate_shift_z) == (1.0, 0.3)  # the paper's ±1 m x/y, ±0.3 m z
        assert (default[0].unwrapped.generator.gate_shift, default[0].unwrapped.generator.gate_shift_z) == (0.3, 0.3)
        assert paper[0].unwrapped.spec.id == "RaceObs-S-v0" and paper[0].unwrapped.obs_mode == "vision"
        shifts = []
        for seed in range(20):  # every gate moves within its box, and some use most of the x/y range
            paper[0].reset(seed=seed)
            scene, base = paper[0].unwrapped.scene, paper[0].unwrapped.track
            offsets = np.array([g.center for g in scene.gates]) - np.array([g.center for g in base.gates])
            shifts.append(offsets)
        shifts = np.abs(np.concatenate(shifts))
        assert shifts[:, :2].max() <= 1.0 + 1e-9 and shifts[:, 2].max() <= 0.3 + 1e-9
        assert shifts[:, :2].max() > 0.6
    finally:
        for env in paper + default:
            env.close()


def test_a_student_of_several_tracks_gets_an_equal_share_of_each(tmp_path: Path) -> None:
    """train_tracks: env i flies train_tracks[i % len]; bad lists are named; YAML reads the list."""
    from racebench.training.dagger import make_training_envs, training_env_ids

    config = DaggerConfig(n_envs=6, train_tracks=["S", "J", "Circle"])
    config.validate()
    assert training_env_ids(config) == ["RaceObs-S-v0", "RaceObs-J-v0", "RaceObs-Circle-v0"] * 2
    assert training_env_ids(DaggerConfig(n_envs=2, track="J")) == ["RaceObs-J-v0"] * 2  # one track: as before
    made = make_training_envs(dataclasses.replace(config, n_envs=3, gate_shift=0.5))
    try:
        assert [m.unwrapped.spec.id for m in made] == ["RaceObs-S-v0", "RaceObs-J-v0", "RaceObs-Circle-v0"]
        assert [m.unwrapped.track.name for m in made] == ["S", "J", "Circle"]
        assert all(m.unwrapped.generator.gate_shift == 0.5 for m in made)
    finally:
        for m in made:
            m.close()
    for bad in (["S", "Q"], ["S", "S"], "S"):
        with pytest.raises(ValueError, match="train_tracks must be a list of distinct tracks"):
            DaggerConfig(n_envs=4, train_tracks=bad).validate()  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_envs a multiple of its length"):
        DaggerConfig(n_envs=16, train_tracks=["S", "J", "Circle"]).validate()
    with pytest.raises(ValueError, match="n_envs a multiple of its length"):
        DaggerConfig(n_envs=4, train_tracks=["S", "J"], env_id="RaceObs-S-Density5-v0").validate()
    path = tmp_path / "multi.yaml"
    path.write_text("method: dagger\nname: multi\nn_envs: 18\ntrain_tracks: [S, J, Circle]\n")
    assert DaggerConfig.from_yaml(path).train_tracks == ["S", "J", "Circle"]
    with pytest.raises(ValueError, match="run's track 'Circle' is not one of train_tracks"):
        distill(DaggerConfig(track="Circle", n_envs=2, train_tracks=["S", "J"]), tmp_path / "run")


def test_a_tiny_distillation_of_one_student_for_two_tracks(tmp_path: Path) -> None:
    """Both tracks are flown and scored in progress.csv, and the final evaluation flies each track's main id."""
    config = DaggerConfig(track="J", iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64,
                          train_tracks=["S", "J"])  # fmt: skip
    summary = distill(config, tmp_path, eval_episodes=1)
    progress = pd.read_csv(tmp_path / "progress.csv")
    assert {"success_rate_S", "success_rate_J"} <= set(progress.columns)
    assert sorted(summary["eval_tracks"]) == ["RaceObs-J-v0", "RaceObs-S-v0"]
    assert summary["eval"] == summary["eval_tracks"]["RaceObs-J-v0"]  # the run's own track, as for one track
    assert Path(summary["checkpoint"]).name == "vision-dagger-J.zip"
    episodes = pd.read_csv(tmp_path / "eval" / "episodes.csv")
    assert sorted(episodes["env_id"]) == ["RaceObs-J-v0", "RaceObs-S-v0"]


def test_a_tiny_distillation_run(tmp_path: Path) -> None:
    config = DaggerConfig(iterations=2, steps_per_iteration=256, n_envs=4, epochs=1, batch_size=64)
    summary = distill(config, tmp_path, eval_episodes=1)
    progress = pd.read_csv(tmp_path / "progress.csv")
    assert progress["beta"].tolist() == [1.0, 0.5]  # the teacher flies first, then less and less
    assert progress["samples"].tolist() == [256, 512]  # every step labelled, aggregated
    assert progress["env_steps"].tolist() == [256, 512]  # the steps flown (samples stop at max_samples)
    assert np.isfinite(progress["loss"]).all()
    assert (progress["collect_s"] > 0).all() and (progress["fit_s"] > 0).all()  # where each iteration's time went
    assert (progress["collect_s"] + progress["fit_s"]).sum() <= progress["wall_s"].iloc[-1] + 0.2
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["teacher"] == "planner-fast" and saved["eval"]["n"] == 1  # the fast expert by default
    assert saved["teacher_version"] == BUILTIN_VERSIONS["planner-fast"]
    agent = SB3Agent(summary["checkpoint"], trust_code=True)
    assert agent.obs_mode == "vision" and not agent.privileged
    assert saved["student"] == "vision-ppo" and agent.recurrent  # the paper's GRU network by default

    # The evaluator flies the student exactly as training unrolled it: the same actions, step after step.
    import gymnasium as gym
    import torch

    from racebench.training.dagger import student_features, student_unroll

    env = gym.make("RaceObs-S-v0", obs_mode="vision")
    obs, _ = env.reset(seed=1_000_000)
    agent.start(1)
    hidden = torch.zeros(1, 1, agent.model.policy.lstm_actor.hidden_size)
    for _ in range(5):
        evaluated = agent.act_batch([obs])[0]
        with torch.no_grad():
            tensors = {k: torch.as_tensor(v[None]) for k, v in obs.items()}
            trained, output = student_unroll(agent.model.policy, student_features(agent.model.policy, tensors)[None],
                                             hidden)  # fmt: skip
        hidden = output[-1:]
        np.testing.assert_allclose(evaluated, trained[0, 0].numpy().clip(-1, 1), atol=1e-6)
        obs, *_ = env.step(evaluated)
    env.close()


def test_shift_depth_moves_each_image_by_its_own_whole_pixels_replicating_the_edge() -> None:
    import torch

    from racebench.training.dagger import shift_depth

    image = torch.arange(25.0).view(1, 1, 5, 5)
    depth = image.repeat(3, 1, 1, 1)
    out = shift_depth(depth, np.array([[0, 0], [2, 0], [-1, 1]]))
    torch.testing.assert_close(out[0], image[0])  # no shift: untouched
    torch.testing.assert_close(out[1, 0, :, 2:], image[0, 0, :, :3])  # content two pixels right ...
    torch.testing.assert_close(out[1, 0, :, :2], image[0, 0, :, :1].repeat(1, 2))  # ... the left column repeated
    torch.testing.assert_close(out[2, 0, 1:, :4], image[0, 0, :4, 1:])  # one left and one down
    torch.testing.assert_close(out[2, 0, 0, :4], image[0, 0, 0, 1:])  # the top row repeated
    assert shift_depth(depth, np.zeros((3, 2), dtype=int)) is depth


def test_weight_decay_and_depth_shifts_reach_the_fit(tmp_path: Path) -> None:
    """weight_decay makes the fit's optimiser AdamW with that decay; augment_shift shifts every fitted chunk's depth
    by a shift drawn from the run's generator, the same shift for all of a chunk's steps."""
    import torch

    from racebench.training.dagger import fitting as dagger  # where fit looks shift_depth up

    seen = []
    original = dagger.shift_depth

    def recording(depth, shifts):
        seen.append(shifts)
        return original(depth, shifts)

    config = DaggerConfig(iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64,
                          sequence_length=16, weight_decay=0.05, augment_shift=2)  # fmt: skip
    dagger_shift, dagger.shift_depth = dagger.shift_depth, recording
    try:
        summary = distill(config, tmp_path, eval_episodes=0)
    finally:
        dagger.shift_depth = dagger_shift
    assert np.isfinite(summary["last"]["loss"])
    saved = torch.load(tmp_path / "resume" / "optimizer.pt", weights_only=False)["optimizer"]
    assert saved["param_groups"][0]["weight_decay"] == 0.05  # AdamW's decoupled decay (Adam has none set)
    assert seen and all(s.shape[1] == 2 and np.abs(s).max() <= 2 for s in seen)
    chunks = len(seen[0]) // 16
    assert np.array_equal(seen[0], np.tile(seen[0][:chunks], (16, 1)))  # one shift per chunk, over its 16 steps
    assert len({tuple(row) for s in seen for row in s}) > 1  # drawn, not fixed


def test_frozen_features_train_the_gru_and_heads_on_the_same_features_and_leave_the_cnn(tmp_path: Path) -> None:
    """freeze_features_after: the loss on the fixed features is the loss through the CNN; a fit then changes the GRU
    and heads and leaves the feature layers as they were; the run switches at that iteration and resumes."""
    import gymnasium as gym
    import torch

    from racebench.training.dagger import dataset_features, fit, make_student, sequence_terms

    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast")
    model = make_student(env, seed=0)
    env.close()
    policy = model.policy
    rng = np.random.default_rng(0)
    data = Dataset(capacity=200, depth_size=64)
    for n in (40, 50, 30):
        data.add_segment(rng.normal(size=(n, 17)).astype(np.float32), rng.random((n, 1, 64, 64), np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32))  # fmt: skip
    first, count, _ = data.chunks(16)
    states = torch.zeros(len(first), policy.lstm_actor.hidden_size)
    features = dataset_features(policy, data)
    with torch.no_grad():
        through_cnn, _ = sequence_terms(policy, data, first, count, states, 16)
        fixed, _ = sequence_terms(policy, data, first, count, states, 16, features=features)
    assert torch.allclose(through_cnn, fixed, atol=1e-6)
    with pytest.raises(ValueError, match="fixed features cannot be shifted"):
        sequence_terms(policy, data, first, count, states, 16, shifts=np.zeros((len(first), 2), int), features=features)

    extractor = {k: v.clone() for k, v in policy.pi_features_extractor.state_dict().items()}
    gru = {k: v.clone() for k, v in policy.lstm_actor.state_dict().items()}
    config = DaggerConfig(epochs=1, batch_size=64, sequence_length=16)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    fit(policy, data, config, optimizer, rng, frozen_features=True)
    after = policy.pi_features_extractor.state_dict()
    assert all(torch.equal(extractor[k], after[k]) for k in extractor)  # the CNN and state MLP: untouched
    assert any(not torch.equal(gru[k], v) for k, v in policy.lstm_actor.state_dict().items())  # the GRU: fitted
    fit(policy, data, config, optimizer, rng)  # unfrozen: the feature layers train again
    assert any(not torch.equal(extractor[k], v) for k, v in policy.pi_features_extractor.state_dict().items())

    # A run: iteration 0 trains the feature layers, iteration 1 does not (stopped after iteration 0 and resumed).
    run = DaggerConfig(iterations=2, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64, sequence_length=16,
                       freeze_features_after=1, keep_iterations=0)  # fmt: skip
    start = make_student(gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast"), seed=0).policy.state_dict()
    distill(dataclasses.replace(run, iterations=1), tmp_path, eval_episodes=0)
    first = SB3Agent(tmp_path / "vision-dagger-S.zip", trust_code=True).model.policy.state_dict()
    distill(run, tmp_path, eval_episodes=0, resume=True)
    second = SB3Agent(tmp_path / "vision-dagger-S.zip", trust_code=True).model.policy.state_dict()
    cnn = [k for k in first if k.startswith("pi_features_extractor.")]
    gru = [k for k in first if k.startswith("lstm_actor.")]
    assert cnn and gru
    assert any(not torch.equal(start[k], first[k]) for k in cnn)  # iteration 0 trained them
    assert all(torch.equal(first[k], second[k]) for k in cnn)  # iteration 1 did not
    assert any(not torch.equal(first[k], second[k]) for k in gru)  # but fitted the GRU


def test_a_feed_forward_student(tmp_path: Path) -> None:
    """--student vision-no-gru: the feed-forward network, trained on shuffled single steps (here with the
    crash-weighted loss)."""
    config = DaggerConfig(iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=32,
                          student="vision-no-gru", crash_weight=2.0)  # fmt: skip
    summary = distill(config, tmp_path, eval_episodes=0)
    assert np.isfinite(summary["last"]["loss"]) and summary["student"] == "vision-no-gru"
    assert not SB3Agent(summary["checkpoint"], trust_code=True).recurrent


def test_an_interrupted_distillation_resumes_to_the_same_student(tmp_path: Path) -> None:
    """One iteration, stopped, then resumed to two: the student, dataset and rows of a run never interrupted."""
    import torch

    from racebench.training.dagger import RESUME_DIR

    # crash_weight: the loss weights are part of the saved dataset
    # learning_rate_final: each iteration's step size is set from the schedule, also in a resumed part
    # replay_failed: the queue of failed scenes is part of the saved state
    # path_aux_weight: the auxiliary head's weights and the stored targets are too (the head's gradient moves the
    # student, so a head restored wrong would change the resumed student)
    config = DaggerConfig(iterations=2, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64, crash_weight=2.0,
                          learning_rate_final=1e-4, replay_failed=0.5, path_aux_weight=1.0)  # fmt: skip
    whole = distill(config, tmp_path / "whole", eval_episodes=0)
    first = DaggerConfig(**{**config.__dict__, "iterations": 1})
    distill(first, tmp_path / "parts", eval_episodes=0)
    assert (tmp_path / "parts" / RESUME_DIR / "state.json").is_file()
    resumed = distill(config, tmp_path / "parts", eval_episodes=0, resume=True)
    a, b = (SB3Agent(s["checkpoint"], trust_code=True).model.policy.state_dict() for s in (whole, resumed))
    assert all(torch.equal(a[k], b[k]) for k in a)  # bit for bit: same labels, same minibatches, same Adam state
    columns = ["iteration", "beta", "episodes", "samples", "env_steps", "loss", "learning_rate", "aux_loss"]
    rows = [pd.read_csv(tmp_path / d / "progress.csv")[columns] for d in ("whole", "parts")]
    pd.testing.assert_frame_equal(*rows)
    assert rows[0]["learning_rate"].tolist() == [3e-4, 1e-4]
    assert not list((tmp_path / "parts").glob(f"{RESUME_DIR}.*"))  # no partial or old state left behind

    with pytest.raises(ValueError, match="epochs=1, not 2"):  # another setting: not the same run
        distill(DaggerConfig(**{**config.__dict__, "epochs": 2}), tmp_path / "parts", eval_episodes=0, resume=True)
    # the machine's threads are not the run's: a run started beside another may go on alone with more
    assert load_resume_state(tmp_path / "parts", DaggerConfig(**{**config.__dict__, "update_threads": 1})) is not None
    # A state saved before a setting existed was run with that setting's default: it resumes under the default,
    # and only under it.
    state_path = tmp_path / "parts" / RESUME_DIR / "state.json"
    state = json.loads(state_path.read_text())
    del state["config"]["teacher_integral_gain"]
    state_path.write_text(json.dumps(state))
    assert load_resume_state(tmp_path / "parts", config) is not None
    with pytest.raises(ValueError, match="teacher_integral_gain=4.0, not 0.0"):
        load_resume_state(tmp_path / "parts", DaggerConfig(**{**config.__dict__, "teacher_integral_gain": 0.0}))

    # The loss weights are part of the saved aggregate: weights in the saved state survive a resumption.
    saved = tmp_path / "parts" / RESUME_DIR / "dataset.npz"
    with np.load(saved) as data:
        arrays = dict(data)
    arrays["weight"][:10] = 2.0
    np.savez(saved, **arrays)
    distill(DaggerConfig(**{**config.__dict__, "iterations": 3}), tmp_path / "parts", eval_episodes=0, resume=True)
    with np.load(saved) as data:
        assert np.all(data["weight"][:10] == 2.0) and len(data["weight"]) == 3 * 128


def test_extending_a_finished_run_keeps_the_earlier_checkpoints_evaluation(tmp_path: Path) -> None:
    """A finished run (checkpoint, summary.json, eval/) resumed to more iterations: the old summary and evaluation
    move aside under their step count, the new checkpoint is evaluated into a fresh eval/ (before, the final
    evaluation refused the old policy's records and no summary was written)."""
    config = DaggerConfig(iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64)
    first = distill(config, tmp_path, eval_episodes=1)
    longer = distill(DaggerConfig(**{**config.__dict__, "iterations": 2}), tmp_path, eval_episodes=1, resume=True)
    assert json.loads((tmp_path / "summary-128-steps.json").read_text()) == first
    assert (tmp_path / "eval-128-steps" / "episodes.csv").is_file()
    assert json.loads((tmp_path / "summary.json").read_text()) == longer
    assert longer["env_steps"] == 256 and longer["eval"]["n"] == 1
    old, new = (pd.read_csv(tmp_path / d / "episodes.csv") for d in ("eval-128-steps", "eval"))
    assert old["policy_sha256"].iloc[0] != new["policy_sha256"].iloc[0]  # each keyed to its own checkpoint


def test_a_kill_inside_the_state_swap_resumes_from_the_state_it_left(tmp_path: Path) -> None:
    """Killed between moving resume/ aside and renaming resume.partial/ into place: either folder is found."""
    from racebench.training.dagger import RESUME_DIR, completed_iterations, load_resume_state

    config = DaggerConfig(iterations=1, steps_per_iteration=64, n_envs=4, epochs=1, batch_size=32)
    distill(config, tmp_path, eval_episodes=0)
    (tmp_path / RESUME_DIR).rename(tmp_path / f"{RESUME_DIR}.partial")  # the new state, not yet swapped in
    assert completed_iterations(tmp_path) == 1
    state = load_resume_state(tmp_path, DaggerConfig(**{**config.__dict__, "iterations": 2}))
    assert state is not None and state["folder"].endswith(f"{RESUME_DIR}.partial")
    (tmp_path / f"{RESUME_DIR}.partial" / "state.json").unlink()  # written last: without it the copy is partial
    assert completed_iterations(tmp_path) == 0


def test_labels_are_the_experts_actions_and_the_student_sees_the_public_observation() -> None:
    """Every stored step: the observation any agent gets from env.step (state and depth, nothing privileged),
    labelled with exactly the action the expert agent takes there when it flies the episode itself."""
    import gymnasium as gym

    from racebench.agents import load_agent
    from racebench.training.dagger import collect, make_student

    def make() -> gym.Env:
        return gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast", gate_shift=0.3)

    env = make()
    data = Dataset(capacity=500, depth_size=env.unwrapped.camera.size)
    policy = make_student(env, seed=0).policy
    collect([env.unwrapped], [load_agent("planner-fast")], policy, beta=1.0, steps=120,
            rng=np.random.default_rng(0), seeds=[5], dataset=data)  # fmt: skip
    assert data.size == 120 and data.starts[0] and not data.starts[1:120].any()  # one episode, in order

    twin, expert = make(), load_agent("planner-fast")
    obs, _ = twin.reset(seed=5)
    expert.reset(env=twin.unwrapped, seed=None)
    assert set(obs) == {"state", "depth"}  # the public vision observation: what the student is given
    for i in range(120):
        np.testing.assert_array_equal(data.state[i], obs["state"])
        np.testing.assert_array_equal(data.depth[i], np.round(obs["depth"] * 255.0).astype(np.uint8))
        action = np.clip(np.asarray(expert.act(obs), dtype=np.float32), -1.0, 1.0)
        np.testing.assert_array_equal(data.action[i], action)
        obs, _, terminated, truncated, _ = twin.step(action)
        assert not (terminated or truncated)
    env.close()
    twin.close()


def test_the_steps_before_a_crash_weigh_crash_weight_in_the_loss() -> None:
    """collect stores the last crash_window steps of each crashed episode with weight crash_weight, the rest with
    1; the sequence loss is then the weighted mean of the steps' squared errors (unweighted: the plain mean)."""
    import gymnasium as gym
    import torch

    from racebench.training.dagger import (
        collect,
        make_student,
        make_teacher,
        sequence_loss,
        student_features,
        student_unroll,
    )

    config = DaggerConfig(n_envs=2)
    made = [gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast") for _ in range(2)]
    policy = make_student(made[0], seed=0).policy  # untrained: with beta 0 it crashes within a few dozen steps
    data = Dataset(capacity=2000, depth_size=64)
    envs, teachers = [m.unwrapped for m in made], [make_teacher(config) for _ in made]
    stats = collect(envs, teachers, policy, beta=0.0, steps=400, rng=np.random.default_rng(0), seeds=[0],
                    dataset=data, crash_weight=3.0, crash_window=5)  # fmt: skip
    assert stats["episodes"] >= 2 and stats["success_rate"] == 0.0
    crashes_end = data.size
    # The teacher flying: finished laps end the episode too, and are not weighted.
    flown = collect(envs, teachers, policy, beta=1.0, steps=500, rng=np.random.default_rng(0), seeds=[100],
                    dataset=data, crash_weight=3.0, crash_window=5)  # fmt: skip
    for m in made:
        m.close()
    assert flown["episodes"] >= 1 and flown["success_rate"] == 1.0
    assert np.all(data.weight[crashes_end : data.size] == 1.0)
    bounds = np.append(np.flatnonzero(data.starts[:crashes_end]), crashes_end)
    weights = [data.weight[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    crashed = [w for w in weights if w[-1] == 3.0]
    assert len(crashed) == stats["episodes"]  # every finished episode crashed; the two cut at the end did not
    for w in crashed:
        assert np.all(w[-5:] == 3.0) and np.all(w[:-5] == 1.0)
    assert sum(np.all(w == 1.0) for w in weights) == len(weights) - len(crashed)

    first, count, _ = data.chunks(8)
    heavy = [k for k, (a, n) in enumerate(zip(first, count, strict=True)) if data.weight[a : a + n].max() > 1.0]
    pick = np.array(heavy[:3] + [k for k in range(len(first)) if k not in heavy][:3])  # weighted and unweighted
    states = torch.zeros(len(pick), policy.lstm_actor.hidden_size)
    with torch.no_grad():
        weighted = sequence_loss(policy, data, first[pick], count[pick], states, 8, weighted=True)
        plain = sequence_loss(policy, data, first[pick], count[pick], states, 8)
        errors, step_weights = [], []
        for a, n in zip(first[pick], count[pick], strict=True):
            steps = np.arange(a, a + n)
            actions, _ = student_unroll(policy, student_features(policy, data.observations(steps))[:, None],
                                        torch.zeros(1, 1, policy.lstm_actor.hidden_size))  # fmt: skip
            errors.append(((actions[:, 0] - torch.from_numpy(data.action[steps])) ** 2).mean(-1))
            step_weights.append(torch.from_numpy(data.weight[steps]))
    e, w = torch.cat(errors), torch.cat(step_weights)
    assert w.max() == 3.0 and w.min() == 1.0
    torch.testing.assert_close(weighted, (e * w).sum() / w.sum(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(plain, e.mean(), rtol=1e-5, atol=1e-7)


def test_failed_training_scenes_are_flown_again_with_probability_replay_failed() -> None:
    """replay_failed: a failed episode on a new scene queues its seed; a new episode takes the last queued seed with
    that probability (off the queue), else the next new seed; a replay is not queued again. Off (0), seeds run
    consecutively as before."""
    import gymnasium as gym

    from racebench.training.dagger import collect, make_student, make_teacher

    config = DaggerConfig(n_envs=2)
    made = [gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast") for _ in range(2)]
    envs, teachers = [m.unwrapped for m in made], [make_teacher(config) for _ in made]
    policy = make_student(made[0], seed=0).policy  # untrained, flying alone (beta 0): every episode fails
    flown: list[int] = []
    for env in envs:
        reset = env.reset_state
        env.reset_state = lambda seed, reset=reset: (flown.append(seed), reset(seed=seed))[1]
    seeds, failed = [0], []
    stats = collect(envs, teachers, policy, beta=0.0, steps=1200, rng=np.random.default_rng(0), seeds=seeds,
                    dataset=Dataset(2000, 64), replay_failed=0.7, failed=failed)  # fmt: skip
    assert stats["episodes"] >= 10 and stats["success_rate"] == 0.0
    new = [s for k, s in enumerate(flown) if s not in flown[:k]]
    assert new == list(range(seeds[0]))  # new scenes in order; the counter only counts those
    repeats = len(flown) - len(new)
    assert stats["replayed"] == repeats and 0.2 * stats["episodes"] < repeats
    # Each scene is flown twice at most (a failed replay is not queued again). The queue holds the failed new scenes
    # not replayed yet: every finished episode failed, and each of the 2 envs may leave one cut, unqueued, at the end.
    assert max(flown.count(s) for s in flown) == 2 and set(failed) <= set(new)
    assert len(new) - repeats - 2 <= len(failed) <= len(new) - repeats
    flown.clear()
    seeds, failed = [0], []
    off = collect(envs, teachers, policy, beta=0.0, steps=400, rng=np.random.default_rng(0), seeds=seeds,
                  dataset=Dataset(2000, 64), failed=failed)  # fmt: skip
    assert flown == list(range(seeds[0])) and failed == [] and "replayed" not in off
    for m in made:
        m.close()
    with pytest.raises(ValueError, match="replay_failed must be in"):
        DaggerConfig(replay_failed=1.0).validate()


def test_the_run_keeps_its_last_students_and_checkpoints_the_best_on_validation_scenes(tmp_path: Path) -> None:
    """keep_iterations + select_episodes: the last students and their weight average are flown on validation
    scenes; the checkpoint is the candidate that finished most (ties: the latest, the average last of all)."""
    import torch

    from racebench.training.dagger import KEPT_DIR, VALIDATION_SEED_BASE, choose_student

    config = DaggerConfig(iterations=3, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=32,
                          keep_iterations=2, select_episodes=3, final_student="best")  # fmt: skip
    summary = distill(config, tmp_path, eval_episodes=0)
    kept = sorted(p.name for p in (tmp_path / KEPT_DIR).iterdir())
    assert kept == ["vision-dagger-S-average.zip", "vision-dagger-S-it001.zip", "vision-dagger-S-it002.zip"]
    table = pd.read_csv(tmp_path / "selection.csv")
    assert table["candidate"].tolist() == ["it001", "it002", "average"] and (table["episodes"] == 3).all()
    assert table["chosen"].sum() == 1
    chosen = table[table["chosen"]].iloc[0]
    best = table[table["successes"] == table["successes"].max()]
    assert chosen["candidate"] == best["candidate"].iloc[-1]  # the most laps; among equals the latest
    assert summary["selection"]["candidate"] == chosen["candidate"]

    def weights(path: Path) -> dict[str, torch.Tensor]:
        return SB3Agent(str(path), trust_code=True).model.policy.state_dict()

    final = weights(Path(summary["checkpoint"]))
    picked = weights(tmp_path / KEPT_DIR / f"vision-dagger-S-{chosen['candidate']}.zip")
    assert all(torch.equal(final[k], picked[k]) for k in final)  # the checkpoint is the chosen candidate
    a, b, mean = (weights(tmp_path / KEPT_DIR / f"vision-dagger-S-{c}.zip") for c in ("it001", "it002", "average"))
    key = "action_net.weight"
    torch.testing.assert_close(mean[key], (a[key] + b[key]) / 2)
    assert not torch.equal(a[key], b[key])  # two different students were kept

    # scripts/average_students.py: the last 2 are the run's own average, the last 1 its last student.
    script = load_script("average_students")
    # Three kept students (it000 a copy of it002, so the last 2 differ from all 3): the last K of them, in order.
    import shutil

    shutil.copy(tmp_path / KEPT_DIR / "vision-dagger-S-it002.zip", tmp_path / KEPT_DIR / "vision-dagger-S-it000.zip")
    assert script.average_last(tmp_path, 2, tmp_path / "k2.zip") == [1, 2]
    assert script.average_last(tmp_path, 1, tmp_path / "k1.zip") == [2]
    assert script.average_last(tmp_path, 3, tmp_path / "k3.zip") == [0, 1, 2]
    k1, k2, k3 = (weights(tmp_path / f"k{k}.zip") for k in (1, 2, 3))
    assert all(torch.equal(k2[k], mean[k]) for k in mean) and all(torch.equal(k1[k], b[k]) for k in b)
    torch.testing.assert_close(k3[key], (a[key] + 2 * b[key]) / 3)
    for bad, message in ((4, "--last 4, but .* keeps 3 students"), (0, "--last 0")):
        with pytest.raises(SystemExit, match=message):
            script.average_last(tmp_path, bad, tmp_path / "bad.zip")
    (tmp_path / KEPT_DIR / "vision-dagger-S-it001.zip").rename(tmp_path / KEPT_DIR / "vision-dagger-S-it1001.zip")
    with pytest.raises(SystemExit, match=r"not consecutive iterations \[2, 1001\]"):
        script.average_last(tmp_path, 2, tmp_path / "gap.zip")
    (tmp_path / KEPT_DIR / "vision-dagger-S-it1001.zip").rename(tmp_path / KEPT_DIR / "vision-dagger-S-it001.zip")
    (tmp_path / KEPT_DIR / "vision-dagger-S-it000.zip").unlink()

    # The ranking itself, with made-up validation outcomes per candidate (flown in the order it001, it002, average).
    import racebench.training.dagger.selection as dagger  # where choose_student looks fly_student up

    student = SB3Agent(summary["checkpoint"], trust_code=True).model
    for counts, winner in (([2, 3, 3], "average"), ([3, 2, 1], "it001"), ([1, 3, 2], "it002"), ([0, 0, 0], "average")):
        made_up = iter(counts)

        def fly(envs: list, policy: object, seeds: list[int], made_up=made_up) -> list[dict]:
            n = next(made_up)
            assert seeds == [VALIDATION_SEED_BASE + i for i in range(3)]
            return [{"seed": s, "success": i < n, "steps": 100, "lap_time": 4.0 if i < n else float("nan")}
                    for i, s in enumerate(seeds)]  # fmt: skip

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(dagger, "fly_student", fly)
            row = choose_student(tmp_path, config, student, [], (0, 100))
        assert row["candidate"] == winner and row["successes"] == max(counts)
        held = student.policy.state_dict()
        assert all(
            torch.equal(held[k], weights(tmp_path / KEPT_DIR / f"vision-dagger-S-{winner}.zip")[k]) for k in held
        )
        assert pd.read_csv(tmp_path / "selection.csv")["successes"].tolist() == counts

    # final_student "average" / "last": that candidate whatever the flights say (here the average finishes fewest).
    for final, winner in (("average", "average"), ("last", "it002")):
        made_up = iter([3, 2, 1])

        def fly_made_up(envs: list, policy: object, seeds: list[int], made_up=made_up) -> list[dict]:
            n = next(made_up)
            return [{"seed": s, "success": i < n, "steps": 1, "lap_time": 4.0} for i, s in enumerate(seeds)]

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(dagger, "fly_student", fly_made_up)
            row = choose_student(tmp_path, DaggerConfig(**{**config.__dict__, "final_student": final}), student, [],
                                 (0, 100))  # fmt: skip
        assert row["candidate"] == winner and row["chosen_by"] == final
        held, expected = student.policy.state_dict(), weights(tmp_path / KEPT_DIR / f"vision-dagger-S-{winner}.zip")
        assert all(torch.equal(held[k], expected[k]) for k in held)
    with pytest.raises(ValueError, match="final_student 'average' needs keep_iterations >= 2"):
        DaggerConfig(keep_iterations=1, final_student="average").validate()
    with pytest.raises(ValueError, match="final_student 'best' needs select_episodes >= 1"):
        DaggerConfig(keep_iterations=3, final_student="best").validate()
    with pytest.raises(ValueError, match="final_student must be one of"):
        DaggerConfig(final_student="first").validate()

    # Validation scenes never overlap the scenes a run trained on, nor the evaluation scenes.
    with pytest.raises(ValueError, match="overlap the training seeds"):
        choose_student(tmp_path, config, student, [], (VALIDATION_SEED_BASE - 10, VALIDATION_SEED_BASE + 1))
    with pytest.raises(ValueError, match="past the validation seeds"):
        DaggerConfig(
            seed=700, iterations=20, steps_per_iteration=25_000, keep_iterations=6, select_episodes=200
        ).validate()
    DaggerConfig(seed=2, iterations=20, steps_per_iteration=25_000, keep_iterations=6, select_episodes=200).validate()
    with pytest.raises(ValueError, match="validation seeds stay below the evaluation seeds"):
        DaggerConfig(keep_iterations=1, select_episodes=200_001).validate()
    with pytest.raises(ValueError, match="select_episodes must be >= 0, and needs keep_iterations >= 1"):
        DaggerConfig(select_episodes=10).validate()
    # A missing kept student is named, not silently skipped.
    (tmp_path / KEPT_DIR / "vision-dagger-S-it001.zip").unlink()
    with pytest.raises(ValueError, match="it001.zip is missing"):
        choose_student(tmp_path, config, student, [], (0, 100))
    # A fresh run into the same folder starts without the old run's kept students.
    (tmp_path / KEPT_DIR / "vision-dagger-S-it007.zip").write_bytes(b"another run's")
    distill(
        DaggerConfig(**{**config.__dict__, "select_episodes": 0, "final_student": "last"}), tmp_path, eval_episodes=0
    )
    assert not (tmp_path / KEPT_DIR / "vision-dagger-S-it007.zip").exists()


def test_validation_flights_fly_the_student_as_the_evaluator_does(tmp_path: Path) -> None:
    """fly_student (batched, raw envs, ray-cast depth) against the evaluator's agent stepping a Gymnasium env:
    the same episode length and outcome on each scene, in the order the seeds were given."""
    import gymnasium as gym

    from racebench.training.dagger import fly_student

    summary = distill(DaggerConfig(iterations=1, steps_per_iteration=64, n_envs=4, epochs=1, batch_size=32),
                      tmp_path, eval_episodes=0)  # fmt: skip
    agent = SB3Agent(summary["checkpoint"], trust_code=True)
    made = [gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast") for _ in range(2)]
    seeds = [1_000_003, 1_000_001, 1_000_002]
    flown = fly_student([m.unwrapped for m in made], agent.model.policy, seeds)
    assert [f["seed"] for f in flown] == seeds
    for seed, result in zip(seeds, flown, strict=True):
        obs, _ = made[0].reset(seed=seed)
        agent.start(1)
        steps, done = 0, False
        while not done:
            obs, _, terminated, truncated, info = made[0].step(agent.act_batch([obs])[0])
            steps, done = steps + 1, terminated or truncated
        assert (result["steps"], result["success"]) == (steps, bool(info["is_success"]))
    for m in made:
        m.close()


def test_a_run_shorter_than_keep_iterations_ships_its_one_kept_student(tmp_path: Path) -> None:
    """final_student "average" with one kept student (a 1-iteration run of a keep-6 config): that student."""
    import torch

    from racebench.training.dagger import KEPT_DIR

    config = DaggerConfig(iterations=1, steps_per_iteration=64, n_envs=4, epochs=1, batch_size=32, keep_iterations=6,
                          final_student="average")  # fmt: skip
    summary = distill(config, tmp_path, eval_episodes=0)
    assert summary["selection"] == {"candidate": "it000", "chosen_by": "average"}
    final = SB3Agent(summary["checkpoint"], trust_code=True).model.policy.state_dict()
    kept = SB3Agent(str(tmp_path / KEPT_DIR / "vision-dagger-S-it000.zip"), trust_code=True).model.policy.state_dict()
    assert all(torch.equal(final[k], kept[k]) for k in final)


def test_line_ahead_is_the_teachers_line_ahead_in_the_body_frame() -> None:
    """The auxiliary target: the points 1-4 m further along the teacher's line than the point it tracks, as vectors
    from the drone in its body frame (a drone turned 90 degrees left sees a point ahead in the world on its right)."""
    import gymnasium as gym
    from scipy.spatial.transform import Rotation

    from racebench.training.dagger import LINE_AHEAD_M, line_ahead, make_teacher

    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast")
    env.reset(seed=3)
    teacher = make_teacher(DaggerConfig(teacher_integral_gain=0.0))
    teacher.reset(env=env.unwrapped, seed=None)
    teacher.act()
    drone = env.unwrapped.drone
    target = line_ahead(teacher, drone).reshape(len(LINE_AHEAD_M), 3)
    i = teacher._index
    for k, metres in enumerate(LINE_AHEAD_M):
        j = int(np.searchsorted(teacher.arc, teacher.arc[i] + metres))
        assert teacher.arc[j] - teacher.arc[i] == pytest.approx(metres, abs=0.06)  # the line's 5 cm spacing
        world = teacher.path[j] - drone.position
        np.testing.assert_allclose(target[k], drone.rotation.T @ world, atol=1e-5)
    # Along the first metre the line runs ahead of the drone, which starts facing it.
    assert target[0, 0] > 0.8 and np.linalg.norm(target[0]) == pytest.approx(1.0, abs=0.3)

    class Pose:  # the same position, yawed 90 degrees left: world +x is body -y
        position = np.zeros(3)
        rotation = Rotation.from_euler("z", 90, degrees=True).as_matrix()

    class Straight:  # a line along world +x
        path = np.stack([np.arange(0.0, 6.0, 0.05), np.zeros(120), np.zeros(120)], axis=1)
        arc = np.arange(0.0, 6.0, 0.05)
        _index = 0

    np.testing.assert_allclose(line_ahead(Straight, Pose).reshape(-1, 3), [[0, -m, 0] for m in LINE_AHEAD_M], atol=1e-9)
    Straight._index = 110  # 0.5 m before the end: every point past it is its last point
    np.testing.assert_allclose(line_ahead(Straight, Pose).reshape(-1, 3)[:, 1], -5.95)
    teacher.path = None  # a failed plan: no line, no target
    assert line_ahead(teacher, drone) is None
    env.close()


def test_clearance_ahead_is_the_free_distance_at_the_probes() -> None:
    """The "clearance" target: the distance from each body-frame probe ahead of the drone to the nearest surface,
    capped. A 0.3 m pole 2 m ahead of a drone yawed 90 degrees left (world +y is its forward): the centre probe 2 m
    ahead is inside it (0), those 1 and 3 m ahead are 0.7 m from it, and so on by hand; 10 m back, every probe is
    at the cap."""
    from scipy.spatial.transform import Rotation

    from racebench.sim.scene import Obstacle, Scene
    from racebench.sim.track import load_track
    from racebench.training.dagger import CLEARANCE_CAP_M, CLEARANCE_PROBES, aux_target, clearance_ahead

    track = load_track("S")
    pole = Obstacle("cylinder", np.array([0.0, 2.0, 2.0]), (0.3, 4.0))
    scene = Scene(track, (), (pole,), np.zeros(3), 0.0, np.full(3, -20.0), np.full(3, 20.0))

    class Pose:  # at 1 m height, yawed 90 degrees left: body +x is world +y, body +y (left) is world -x
        position = np.array([0.0, 0.0, 1.0])
        rotation = Rotation.from_euler("z", 90, degrees=True).as_matrix()

    target = clearance_ahead(scene, Pose).reshape(4, 3)  # rows 1-4 m ahead; columns 0.8 m left, centre, right
    assert CLEARANCE_PROBES.shape == (12, 3) and target.dtype == np.float32
    expected = np.array([[np.hypot(1.0, 0.8) - 0.3, 1.0 - 0.3, np.hypot(1.0, 0.8) - 0.3],
                         [0.8 - 0.3, 0.0, 0.8 - 0.3],  # the centre probe is inside the pole: 0
                         [np.hypot(1.0, 0.8) - 0.3, 1.0 - 0.3, np.hypot(1.0, 0.8) - 0.3],
                         [np.hypot(2.0, 0.8) - 0.3, 2.0 - 0.3, np.hypot(2.0, 0.8) - 0.3]])  # fmt: skip
    np.testing.assert_allclose(target, np.minimum(expected, CLEARANCE_CAP_M), atol=1e-5)
    Pose.position = np.array([0.0, -10.0, 1.0])  # 10 m back: every probe is farther than the cap
    np.testing.assert_array_equal(clearance_ahead(scene, Pose), np.full(12, CLEARANCE_CAP_M, dtype=np.float32))

    class Env:  # aux_target reads the env's scene and drone, not the teacher
        drone = Pose

    Env.scene = scene
    np.testing.assert_array_equal(aux_target("clearance", None, Env), clearance_ahead(scene, Pose))


def test_the_clearance_task_stores_its_targets(tmp_path: Path) -> None:
    """aux_task "clearance": every collected step is stored with a target (mask 1 throughout: it needs no teacher's
    line, so any teacher is accepted) within [0, the cap], and the progress has the auxiliary loss; an unknown task is
    refused by name. (The target's geometry: the test above.)"""
    from racebench.training.dagger import CLEARANCE_CAP_M

    with pytest.raises(ValueError, match="aux_task must be one of"):
        DaggerConfig(aux_task="obstacles").validate()
    DaggerConfig(teacher="planner", path_aux_weight=1.0, aux_task="clearance").validate()  # needs no teacher's line
    config = DaggerConfig(iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64,
                          sequence_length=16, path_aux_weight=1.0, aux_task="clearance")  # fmt: skip
    distill(config, tmp_path / "run", eval_episodes=0)
    assert np.isfinite(pd.read_csv(tmp_path / "run" / "progress.csv")["aux_loss"]).all()
    with np.load(tmp_path / "run" / "resume" / "dataset.npz") as data:
        aux, mask = data["aux"], data["aux_mask"]
    assert aux.shape == (128, 12) and mask.min() == 1.0
    assert aux.min() >= 0.0 and aux.max() <= CLEARANCE_CAP_M and aux.min() < CLEARANCE_CAP_M  # a gate is in reach


def test_the_path_head_shapes_the_student_and_stays_out_of_its_checkpoint(tmp_path: Path) -> None:
    """path_aux_weight: every stored step has its target; the fit minimises the action loss plus the weight times the
    head's loss (with weight 0 the student is bit for bit the one fitted without a head; with 1 it differs), the
    progress has the auxiliary loss, and the checkpoint is the student's network alone."""
    import gymnasium as gym
    import torch

    from racebench.training.dagger import fit, make_path_head, make_student, sequence_terms, student_features

    config = DaggerConfig(iterations=1, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64,
                          sequence_length=16, path_aux_weight=1.0)  # fmt: skip
    summary = distill(config, tmp_path / "run", eval_episodes=0)
    assert np.isfinite(pd.read_csv(tmp_path / "run" / "progress.csv")["aux_loss"]).all()
    with np.load(tmp_path / "run" / "resume" / "dataset.npz") as data:
        aux, mask = data["aux"], data["aux_mask"]
    assert aux.shape == (128, 12) and mask.min() == 1.0  # the teacher had a line throughout
    assert np.all(aux[:, 0::3] > 0.5)  # every point of the line ahead is in front of the drone
    plain = SB3Agent(distill(DaggerConfig(**{**config.__dict__, "path_aux_weight": 0.0}), tmp_path / "plain",
                             eval_episodes=0)["checkpoint"], trust_code=True)  # fmt: skip
    student = SB3Agent(summary["checkpoint"], trust_code=True)
    assert student.model.policy.state_dict().keys() == plain.model.policy.state_dict().keys()  # no head inside

    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast")
    rng = np.random.default_rng(0)
    data = Dataset(capacity=100, depth_size=64)
    for n in (40, 40):
        data.add_segment(rng.normal(size=(n, 17)).astype(np.float32), rng.random((n, 1, 64, 64), np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32), aux=rng.normal(size=(n, 12)).astype(np.float32),
                         aux_mask=(np.arange(n) % 4 != 0).astype(np.float32))  # fmt: skip

    def fitted(weight: float | None) -> dict:
        torch.manual_seed(0)
        policy = make_student(env, seed=0).policy
        head = None if weight is None else make_path_head(policy.lstm_actor.hidden_size)
        parameters = list(policy.parameters()) + ([] if head is None else list(head.parameters()))
        run = DaggerConfig(epochs=1, batch_size=32, sequence_length=8, path_aux_weight=weight or 0.0)
        losses: list[float] = []
        fit(policy, data, run, torch.optim.Adam(parameters, lr=1e-3), np.random.default_rng(0), head, losses)
        assert len(losses) == (0 if head is None else 3)  # one per minibatch of the pass: 10 chunks, 4 a batch
        return policy.state_dict()

    without, zero, one = fitted(None), fitted(0.0), fitted(1.0)
    assert all(torch.equal(without[k], zero[k]) for k in without)
    assert not all(torch.equal(without[k], one[k]) for k in without)

    # The auxiliary loss is the mean squared error over the steps that have a target.
    policy = make_student(env, seed=0).policy
    head = make_path_head(policy.lstm_actor.hidden_size)
    first, count, _ = data.chunks(8)
    with torch.no_grad():
        _, aux_loss = sequence_terms(policy, data, first[:3], count[:3], torch.zeros(3, 256), 8, path_head=head)
        errors = []
        for a, n in zip(first[:3], count[:3], strict=True):
            steps = np.arange(a, a + n)
            features = policy.lstm_actor(student_features(policy, data.observations(steps))[:, None],
                                         (torch.zeros(1, 1, 256), torch.zeros(1, 1, 256)))[0][:, 0]  # fmt: skip
            error = ((head(features) - torch.from_numpy(data.aux[steps])) ** 2).mean(-1)
            errors.append(error[torch.from_numpy(data.aux_mask[steps] > 0)])
    torch.testing.assert_close(aux_loss, torch.cat(errors).mean(), rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="needs a recurrent student"):
        fit(make_student(env, seed=0, student="vision-no-gru").policy, data, DaggerConfig(path_aux_weight=1.0),
            torch.optim.Adam(head.parameters()), np.random.default_rng(0), head)  # fmt: skip
    env.close()
    with pytest.raises(ValueError, match="path_aux_weight reads a GRU's output"):
        distill(DaggerConfig(**{**config.__dict__, "student": "vision-no-gru"}), tmp_path / "ff", eval_episodes=0)


def test_a_mixture_head_keeps_both_modes_of_bimodal_labels_where_the_mse_averages_them() -> None:
    """The same input labelled half the time +0.8 and half -0.8 on one axis (a teacher passing an obstacle left or
    right): the MSE head learns 0, the mixture head keeps a candidate at each label, scores them equally, and flies
    one of them, not their average."""
    import torch

    from racebench.agents.recurrent import MixtureActionHead, mixture_action_loss

    torch.manual_seed(0)
    latent = torch.ones(256, 8)
    target = torch.zeros(256, 4)
    target[:128, 0], target[128:, 0] = 0.8, -0.8
    mixture, linear = MixtureActionHead(8, 4, components=2), torch.nn.Linear(8, 4)
    optimizer = torch.optim.Adam([*mixture.parameters(), *linear.parameters()], lr=0.02)
    for _ in range(400):
        loss = mixture_action_loss(mixture, latent, target, sigma=0.2).mean()
        loss = loss + torch.nn.functional.mse_loss(linear(latent), target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        means, scores = mixture.components(latent[:1])
        assert abs(float(linear(latent[:1])[0, 0])) < 0.05  # the regression's average: no swerve at all
        np.testing.assert_allclose(sorted(means[0, :, 0].tolist()), [-0.8, 0.8], atol=0.05)
        np.testing.assert_allclose(torch.softmax(scores[0], -1).numpy(), [0.5, 0.5], atol=0.05)
        flown = mixture(latent[:1])[0]
        assert abs(abs(float(flown[0])) - 0.8) < 0.05 and float(flown[1:].abs().max()) < 0.05


def test_the_mixture_loss_is_the_mse_when_one_candidate_takes_all_and_the_head_flies_the_top_score() -> None:
    import torch

    from racebench.agents.recurrent import MixtureActionHead, mixture_action_loss

    head = MixtureActionHead(3, 4, components=3)
    latent = torch.randn(5, 3)
    target = torch.rand(5, 4) * 2 - 1
    with torch.no_grad():
        head.scores.weight.zero_()
        head.scores.bias.copy_(torch.tensor([0.0, 60.0, 0.0]))  # candidate 1 has all the weight
        means, _ = head.components(latent)
        for sigma in (0.1, 0.5):
            expected = ((means[:, 1] - target) ** 2).mean(-1)
            torch.testing.assert_close(mixture_action_loss(head, latent, target, sigma), expected, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(head(latent), means[:, 1])
        head.scores.bias.copy_(torch.tensor([0.0, 0.0, 60.0]))
        torch.testing.assert_close(head(latent), means[:, 2])
    with pytest.raises(ValueError, match="2 components"):
        MixtureActionHead(3, 4, components=1)


def test_a_mixture_student_is_distilled_and_flown_by_the_evaluator_as_trained(tmp_path: Path) -> None:
    """A student with ``action_components: 3`` (experiment distill-mixture's) goes through DAgger, its weight-averaged
    checkpoint reloads with the mixture head, the evaluator's actions are the training unroll's chosen candidates (also
    exported to ONNX); a bad count is refused."""
    import gymnasium as gym
    import torch

    from racebench.agents.recurrent import MixtureActionHead
    from racebench.training.dagger import student_features, student_unroll
    from racebench.training.train import TrainConfig

    student = tmp_path / "student.yaml"
    student.write_text((ROOT / "baselines" / "vision-ppo.yaml").read_text() + "\naction_components: 3\n")
    config = DaggerConfig(iterations=2, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64, sequence_length=16,
                          student=str(student), keep_iterations=2, final_student="average")  # fmt: skip
    summary = distill(config, tmp_path / "run", eval_episodes=0)
    assert np.isfinite(pd.read_csv(tmp_path / "run" / "progress.csv")["loss"]).all()
    agent = SB3Agent(summary["checkpoint"], trust_code=True)
    policy = agent.model.policy
    assert isinstance(policy.action_net, MixtureActionHead) and policy.action_net.n_components == 3

    env = gym.make("RaceObs-S-v0", obs_mode="vision")
    obs, _ = env.reset(seed=1_000_000)
    agent.start(1)
    hidden = torch.zeros(1, 1, policy.lstm_actor.hidden_size)
    for _ in range(3):
        evaluated = agent.act_batch([obs])[0]
        with torch.no_grad():
            tensors = {k: torch.as_tensor(v[None]) for k, v in obs.items()}
            trained, output = student_unroll(policy, student_features(policy, tensors)[None], hidden)
            means, scores = policy.action_net.components(policy.mlp_extractor.forward_actor(output[0]))
        hidden = output[-1:]
        np.testing.assert_allclose(evaluated, trained[0, 0].numpy().clip(-1, 1), atol=1e-6)
        np.testing.assert_allclose(trained[0, 0].numpy(), means[0, int(scores[0].argmax())].numpy(), atol=1e-6)
        obs, *_ = env.step(evaluated)
    env.close()
    # Exported to ONNX (the leaderboard's code-free format), it flies the same candidates.
    from racebench.agents import OnnxAgent, export_onnx

    onnx = OnnxAgent(export_onnx(agent.model, tmp_path / "mixture.onnx"))
    onnx.reset()
    agent.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        o = {"state": rng.uniform(-1, 1, 17).astype(np.float32), "depth": rng.random((1, 64, 64), np.float32)}
        np.testing.assert_allclose(onnx.act(o), agent.act(o), atol=1e-5)
    for bad, message in (("0", "must be >= 1"), ("2\nrecurrent: false", "needs the recurrent")):
        student.write_text((ROOT / "baselines" / "vision-ppo.yaml").read_text() + f"\naction_components: {bad}\n")
        with pytest.raises(ValueError, match=message):
            TrainConfig.from_yaml(student)
    # PPO from scratch would never train the scores: a mixture policy is only fine-tuned (init_from).
    from racebench.training.train import train

    student.write_text((ROOT / "baselines" / "vision-ppo.yaml").read_text() + "\naction_components: 3\n")
    with pytest.raises(ValueError, match="needs init_from"):
        train(TrainConfig.from_yaml(student), "S", steps=64, out=tmp_path / "ppo", eval_episodes=0)


def test_an_acceleration_student_is_taught_the_experts_commands_and_flown_through_the_controller(
    tmp_path: Path,
) -> None:
    """A student with ``action_output: acceleration`` (experiment distill-accel's): every stored label is the expert's
    acceleration command, which flown from the stored observation is the action the expert took; the distilled
    checkpoint reloads with that output, and the evaluator flies its commands through ``command_to_ctbr`` exactly as
    the training unroll computed them; ONNX export, PPO and a bad or feed-forward setting are refused by name."""
    import gymnasium as gym
    import torch

    from racebench.agents import export_onnx, load_agent
    from racebench.agents.control import command_to_ctbr
    from racebench.training.dagger import collect, make_student, student_features, student_unroll
    from racebench.training.train import TrainConfig, train

    student = tmp_path / "student.yaml"
    student.write_text((ROOT / "baselines" / "vision-ppo.yaml").read_text() + "\naction_output: acceleration\n")
    env = gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast", gate_shift=0.3)
    data = Dataset(capacity=200, depth_size=env.unwrapped.camera.size)
    policy = make_student(env, seed=0, student=str(student)).policy
    assert policy.action_output == "acceleration"
    collect([env.unwrapped], [load_agent("planner-fast")], policy, beta=1.0, steps=100,
            rng=np.random.default_rng(0), seeds=[5], dataset=data)  # fmt: skip
    twin, expert = (
        gym.make("RaceObs-S-v0", obs_mode="vision", renderer="raycast", gate_shift=0.3),
        load_agent("planner-fast"),
    )
    obs, _ = twin.reset(seed=5)
    expert.reset(env=twin.unwrapped, seed=None)
    for i in range(100):
        action = np.clip(np.asarray(expert.act(obs), dtype=np.float32), -1.0, 1.0)
        np.testing.assert_array_equal(data.state[i], obs["state"])
        np.testing.assert_allclose(command_to_ctbr(data.action[i], data.state[i]), action, atol=1e-5)
        assert np.abs(data.action[i] - action).max() > 1e-3  # a command, not the CTBR action
        obs, *_ = twin.step(action)
    twin.close()

    config = DaggerConfig(iterations=2, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64, sequence_length=16,
                          student=str(student), keep_iterations=2, final_student="average")  # fmt: skip
    summary = distill(config, tmp_path / "run", eval_episodes=0)
    agent = SB3Agent(summary["checkpoint"], trust_code=True)
    policy = agent.model.policy
    assert policy.action_output == "acceleration"
    obs, _ = env.reset(seed=1_000_000)
    agent.start(1)
    agent.reset()
    hidden = torch.zeros(1, 1, policy.lstm_actor.hidden_size)
    for _ in range(3):
        evaluated, single = agent.act_batch([obs])[0], agent.act(obs)
        with torch.no_grad():
            tensors = {k: torch.as_tensor(v[None]) for k, v in obs.items()}
            command, output = student_unroll(policy, student_features(policy, tensors)[None], hidden)
        hidden = output[-1:]
        flown = command_to_ctbr(command[0, 0].numpy().clip(-1, 1), obs["state"])
        np.testing.assert_allclose(evaluated, flown, atol=1e-6)
        np.testing.assert_allclose(single, flown, atol=1e-6)
        obs, *_ = env.step(evaluated)
    env.close()
    with pytest.raises(ValueError, match="needs teacher planner-fast"):
        DaggerConfig(student=str(student), teacher="planner").validate()
    with pytest.raises(ValueError, match="outputs acceleration commands"):
        export_onnx(agent.model, tmp_path / "accel.onnx")
    with pytest.raises(ValueError, match="is for DAgger students"):
        train(TrainConfig.from_yaml(student), "S", steps=64, out=tmp_path / "ppo", eval_episodes=0)
    for bad, message in (
        ("thrust", "action_output must be one of"),
        ("acceleration\nrecurrent: false", "needs the recurrent"),
    ):
        student.write_text((ROOT / "baselines" / "vision-ppo.yaml").read_text() + f"\naction_output: {bad}\n")
        with pytest.raises(ValueError, match=message):
            TrainConfig.from_yaml(student)


def test_a_dagger_resume_reads_tensors_and_arrays_only(tmp_path: Path) -> None:
    """The saved student and optimizer state are read with ``weights_only``: a pickle payload in them never runs."""
    import torch
    from payloads import Payload, evil_sb3_zip

    from racebench.training.dagger import load_optimizer_state, saved_policy_state

    marker = tmp_path / "ran"
    with pytest.raises(ValueError, match="holds no readable policy weights") as exc:
        saved_policy_state(evil_sb3_zip(tmp_path / "student.zip", marker))
    assert "\n" not in str(exc.value)
    torch.save({"optimizer": {}, "torch_rng": Payload(marker)}, tmp_path / "optimizer.pt")
    with pytest.raises(ValueError, match="optimizer.pt holds more than tensors"):
        load_optimizer_state(tmp_path / "optimizer.pt")
    assert not marker.exists()
    state = {"optimizer": torch.optim.Adam([torch.nn.Parameter(torch.ones(2))]).state_dict(),
             "torch_rng": torch.get_rng_state()}  # fmt: skip
    torch.save(state, tmp_path / "optimizer.pt")  # what save_resume_state writes loads as before
    assert torch.equal(load_optimizer_state(tmp_path / "optimizer.pt")["torch_rng"], state["torch_rng"])
