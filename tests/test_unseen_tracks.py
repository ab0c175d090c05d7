"""Generated tracks (issue 73): the generator's rules, the splits, determinism, flyability and the held-out set."""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils import seeding
from scripts_loader import load_script

import racebench
from racebench.agents.loading import load_agent
from racebench.envs.lap_bound import env_lap_time_bound, lap_time_lower_bound
from racebench.envs.random_tracks import (
    PRIVATE_SEED_BASE,
    TRAIN_TRACK_SEEDS,
    UNSEEN_TRACK_SEED_BASE,
    UNSEEN_TRACKS,
    RandomTrackEnv,
    episode_facts,
    make_unseen_track,
    race_env,
    seed_track,
    unseen_track,
    unseen_track_path,
)
from racebench.evaluation import Evaluator
from racebench.evaluation import seeds as seed_sets
from racebench.evaluation.protocol import EVAL_SEED_BASE, VALIDATION_SEED_BASE
from racebench.evaluation.records import RECORDS_FILE, InvalidRecordError, seal, validate_record
from racebench.evaluation.rollout import run_episode
from racebench.sim.corridor import CORRIDOR_MARGIN, find_corridor
from racebench.sim.obstacles import ObstacleGenerator
from racebench.sim.placement import AUTHORS_FRACTIONS, TOLERANCE, centreline_fractions, obstacle_line_distances
from racebench.sim.track import Track, load_track
from racebench.sim.track_generator import (
    ARENA_SPAN,
    GATE_HEIGHT,
    LEG_LENGTH,
    MAX_TURN_DEG,
    TRACK_SOURCES,
    paper_track_match,
    rule_violations,
    track_from_seed,
    track_rng,
    track_yaml,
    write_track,
)

IDS = ("RaceObs-Random-v0", "RaceObs-Unseen-v0")
RULE_SEEDS = range(200)  # Random episodes' seeds: their tracks are drawn from the training track range


@pytest.fixture(scope="module")
def training_tracks() -> list[Track]:
    """The tracks of the first 200 seeds of RaceObs-Random-v0 (what a training run flies first)."""
    return [seed_track("Random", seed) for seed in RULE_SEEDS]


def held_out() -> list[Track]:
    return [unseen_track(i) for i in range(UNSEEN_TRACKS)]


def same_track(a: Track, b: Track) -> bool:
    """Every field but ``source`` equal, floats bit for bit."""
    gates = len(a.gates) == len(b.gates) and all(
        np.array_equal(x.center, y.center) and (x.yaw, x.inner, x.outer, x.depth) == (y.yaw, y.inner, y.outer, y.depth)
        for x, y in zip(a.gates, b.gates, strict=True)
    )
    start = (
        np.array_equal(a.start.center, b.start.center)
        and a.start.yaw == b.start.yaw
        and np.array_equal(a.start.spread, b.start.spread)
    )
    rest = (a.name, a.description, a.closed_loop, a.obstacle_regions, a.obstacle_band)
    return gates and start and rest == (b.name, b.description, b.closed_loop, b.obstacle_regions, b.obstacle_band)


# ------------------------------------------------------------------ the rules, measured independently
def legs(track: Track) -> list[tuple[np.ndarray, np.ndarray]]:
    centres = [g.center for g in track.gates]
    ends = [*centres, centres[0]] if track.closed_loop else centres
    return list(zip(ends[:-1], ends[1:], strict=True))


def heading(v: np.ndarray) -> float:
    return math.degrees(math.atan2(v[1], v[0]))


def turn(a: float, b: float) -> float:
    return abs((b - a + 180.0) % 360.0 - 180.0)


def check_bounds(track: Track) -> None:
    """The generator's bounds, from the track's gates alone (not through the generator's own check)."""
    s = load_track("S").gates[0]
    assert 4 <= track.num_gates <= 6
    assert all((g.inner, g.outer, g.depth) == (s.inner, s.outer, s.depth) for g in track.gates)  # the paper's gate
    z = np.array([g.center[2] for g in track.gates])
    assert np.all((z >= GATE_HEIGHT[0]) & (z <= GATE_HEIGHT[1]))
    pieces = legs(track)
    lengths = [float(np.linalg.norm(b - a)) for a, b in pieces]
    assert min(lengths) >= LEG_LENGTH[0] - 1e-9 and max(lengths) <= LEG_LENGTH[1] + 1e-9
    assert max(abs(b[2] - a[2]) for a, b in pieces) <= 1.0 + 1e-9
    headings = [heading(b - a) for a, b in pieces]
    between = headings + headings[:1] if track.closed_loop else headings
    assert max(turn(p, q) for p, q in zip(between[:-1], between[1:], strict=True)) <= MAX_TURN_DEG + 0.2  # rounding
    points = np.array([g.center[:2] for g in track.gates] + [track.start.center[:2]])
    span = points.max(axis=0) - points.min(axis=0)
    assert span[0] <= ARENA_SPAN[0] + 1e-9 and span[1] <= ARENA_SPAN[1] + 1e-9
    g0 = track.gates[0]
    assert track.start.yaw == g0.yaw == 0.0 and np.allclose(track.start.center, g0.center - [2.0, 0.0, 0.0], atol=0.02)
    assert len(track.obstacle_regions) == len(pieces)


def test_training_tracks_keep_every_bound_and_are_never_a_paper_track(training_tracks: list[Track]) -> None:
    kinds = Counter((t.closed_loop, t.num_gates) for t in training_tracks)
    assert set(kinds) == {(loop, n) for loop in (False, True) for n in (4, 5, 6)}  # sprints and loops of 4-6 gates
    assert min(kinds.values()) >= 15  # every kind drawn about equally often (1/6 of 200)
    for track in training_tracks:
        check_bounds(track)
        assert rule_violations(track) == [], track.name
        assert paper_track_match(track) is None, track.name


def test_the_rules_admit_the_paper_tracks_and_catch_what_breaks_them() -> None:
    for name in ("S", "J", "Circle"):
        assert rule_violations(load_track(name)) == [], name  # the paper's tracks are of the generator's style
    s = load_track("S")
    gates = list(s.gates)
    stretched = dataclasses.replace(s, gates=(*gates[:3], gates[3].moved(gates[3].center + [3.0, 0.0, 0.0])))
    assert "leg_length" in rule_violations(stretched) and "arena" in rule_violations(stretched)
    raised = dataclasses.replace(s, gates=(*gates[:3], gates[3].moved(gates[3].center + [0.0, 0.0, 1.5])))
    assert {"height", "climb"} <= set(rule_violations(raised))
    turned = dataclasses.replace(s, gates=(*gates[:2], dataclasses.replace(gates[2], yaw=math.radians(80.0)), gates[3]))
    assert "turn" in rule_violations(turned)
    folded = dataclasses.replace(s, gates=(*gates[:3], gates[3].moved(np.array([7.5, 1.0, 1.0]))))
    assert "gate_near_leg" in rule_violations(folded)


def test_a_paper_track_is_recognised_however_it_is_placed() -> None:
    for name in ("S", "J", "Circle"):
        paper = load_track(name)
        angle, mirror = 2.1, np.array([1.0, -1.0, 1.0])
        rotation = np.array(
            [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0, 0, 1]]
        )
        moved = [g.moved(rotation @ (g.center * mirror) + [4.0, -7.0, 0.4]) for g in paper.gates]
        assert paper_track_match(dataclasses.replace(paper, gates=tuple(moved[::-1]))) == name  # also flown backwards
        nudged = [g.moved(g.center + [0.3, -0.3, 0.2]) if i % 2 else g for i, g in enumerate(moved)]
        assert paper_track_match(dataclasses.replace(paper, gates=tuple(nudged))) == name  # every gate within 0.5 m
        one_off = [g.moved(g.center + [0.0, 2.0, 0.0]) if i == 1 else g for i, g in enumerate(paper.gates)]
        assert paper_track_match(dataclasses.replace(paper, gates=tuple(one_off))) is None
    loop = load_track("Circle")
    shifted = dataclasses.replace(loop, gates=loop.gates[2:] + loop.gates[:2])  # a loop from another gate
    assert paper_track_match(shifted) == "Circle"


# ------------------------------------------------------------------ splits
def test_the_seed_ranges_of_the_splits_are_disjoint() -> None:
    assert seed_sets.PRIVATE_SEED_BASE == PRIVATE_SEED_BASE
    assert VALIDATION_SEED_BASE < EVAL_SEED_BASE < TRAIN_TRACK_SEEDS  # the episode seeds, below the track seeds
    assert TRAIN_TRACK_SEEDS <= UNSEEN_TRACK_SEED_BASE  # training tracks, then held-out tracks ...
    assert UNSEEN_TRACK_SEED_BASE + UNSEEN_TRACKS <= PRIVATE_SEED_BASE  # ... then the private seeds' own tracks
    # Random draws its track seeds in the training range, whatever the episode seed (training, validation, evaluation)
    for seed in [0, 1, 799_999, VALIDATION_SEED_BASE, EVAL_SEED_BASE, EVAL_SEED_BASE + 99_999]:
        track_seed = int(seeding.np_random(seed)[0].integers(TRAIN_TRACK_SEEDS))
        assert seed_track("Random", seed).name == f"track-{track_seed}" and track_seed < TRAIN_TRACK_SEEDS


def test_evaluation_episode_i_flies_held_out_track_i_mod_100() -> None:
    for i in (0, 1, 57, 99, 100, 250):
        assert seed_track("Unseen", EVAL_SEED_BASE + i) is unseen_track(i % UNSEEN_TRACKS)
    private = seed_track("Unseen", PRIVATE_SEED_BASE + 12_345)
    assert private.name == "private" and not any(same_track(private, t) for t in held_out())
    assert same_track(private, seed_track("Unseen", PRIVATE_SEED_BASE + 12_345))  # reproducible with the seed


def test_the_held_out_tracks_are_data_the_script_rewrites_byte_for_byte() -> None:
    script = load_script("make_unseen_tracks")
    sizes = 0
    for i in range(UNSEEN_TRACKS):
        path = unseen_track_path(i)
        assert path.read_text() == script.unseen_text(i), path
        sizes += path.stat().st_size
    assert sizes < 100_000  # tens of KB in the repository
    assert not any(p.name.startswith("unseen-1") and len(p.stem) > 10 for p in unseen_track_path(0).parent.iterdir())
    assert sorted(p.name for p in unseen_track_path(0).parent.iterdir()) == [f"unseen-{i:03d}.yaml" for i in range(100)]


def test_the_held_out_tracks_keep_the_rules_and_are_the_generators() -> None:
    kinds = Counter()
    for i, track in enumerate(held_out()):
        check_bounds(track)
        assert rule_violations(track) == [] and paper_track_match(track) is None, track.name
        if i % 10 == 0:  # the generator makes the committed track again (all of them: the byte test above)
            assert same_track(track, make_unseen_track(i))
        kinds[(track.closed_loop, track.num_gates)] += 1
    assert len(kinds) == 6 and min(kinds.values()) >= 8


def test_a_written_track_reads_back_identically(tmp_path: Path) -> None:
    tracks = [track_from_seed(seed) for seed in (3, 4, 5)] + [load_track(n) for n in ("S", "J", "Circle")]
    for track in tracks:
        path = write_track(track, tmp_path / f"{track.name}.yaml", header="a test\nof two lines")
        again = load_track(path)
        assert same_track(track, again), track.name
        assert track_yaml(again, header="a test\nof two lines") == path.read_text()
    with pytest.raises(ValueError, match="track seed"):
        track_rng(-1)


# ------------------------------------------------------------------ the envs
@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_track_and_scene(env_id: str) -> None:
    a, b = gym.make(env_id, obs_mode="state"), gym.make(env_id, obs_mode="state")
    for seed in (5, EVAL_SEED_BASE + 3):
        a.reset(seed=seed)
        b.reset(seed=seed + 1)  # another history first
        b.reset(seed=seed)
        sa, sb = a.unwrapped.scene, b.unwrapped.scene
        assert sa.to_dict() == sb.to_dict() and same_track(sa.track, sb.track)
        assert a.unwrapped.draw_scene(seed).to_dict() == sa.to_dict()  # the scene digests' draw is reset's
        assert len(a.unwrapped.sim.gates) == sa.track.num_gates
    a.reset(seed=1)
    first = a.unwrapped.scene.to_dict()
    a.reset(seed=2)
    assert a.unwrapped.scene.to_dict() != first
    a.close()
    b.close()


def test_random_gives_a_new_track_each_reset_and_unseen_cycles_the_held_out_set() -> None:
    env = gym.make("RaceObs-Random-v0", obs_mode="state")
    env.reset(seed=0)
    names = {env.unwrapped.track.name}
    for _ in range(4):
        env.reset()
        names.add(env.unwrapped.track.name)
    assert len(names) == 5
    env.close()
    env = gym.make("RaceObs-Unseen-v0", obs_mode="state")
    for i in (0, 1, 100):
        env.reset(seed=EVAL_SEED_BASE + i)
        assert env.unwrapped.track is unseen_track(i % 100)
    env.close()


def test_spaces_are_the_paper_ids_and_bad_kwargs_are_one_line_errors() -> None:
    paper = gym.make("RaceObs-S-v0")
    for env_id in IDS:
        env = gym.make(env_id)
        assert env.observation_space == paper.observation_space and env.action_space == paper.action_space
        env.close()
    paper.close()
    with pytest.raises(ValueError, match="track source"):
        RandomTrackEnv(track="S")
    with pytest.raises(ValueError, match="density"):
        gym.make("RaceObs-Unseen-v0", density=-1)
    with pytest.raises(TypeError, match="no_such_kwarg"):  # as every id: an unknown kwarg is named
        gym.make("RaceObs-Random-v0", no_such_kwarg=1)
    with pytest.raises(ValueError, match="held-out track index"):
        unseen_track(UNSEEN_TRACKS)
    assert set(IDS) <= set(racebench.ENV_IDS) and TRACK_SOURCES == ("Random", "Unseen")


def test_layouts_tasks_and_vector_envs_follow_the_track() -> None:
    env = race_env(track="Random", obs_mode="state", start_spread=(0.5, 0.5, 0.5))
    assert isinstance(env, RandomTrackEnv)
    env.reset(seed=0)
    layout = env.sample_layout()
    env.set_layout(layout)
    for _ in range(2):
        env.reset()
        assert env.track is layout.track and env.scene.obstacles == layout.obstacles
        assert np.array_equal(env.track.start.spread, [0.5, 0.5, 0.5])
    env.set_layout(None)
    env.set_task(density=1)
    env.reset()
    assert len(env.scene.obstacles) == len(env.track.obstacle_regions)  # one per region on the new track
    env.close()
    vec = gym.make_vec("RaceObs-Unseen-v0", num_envs=2, obs_mode="state")
    vec.reset(seed=EVAL_SEED_BASE)
    _, _, _, _, infos = vec.step(np.zeros((2, 4), dtype=np.float32))
    names = vec.get_attr("track")
    assert [t.name for t in names] == ["unseen-000", "unseen-001"] and infos["gates_passed"].shape == (2,)
    vec.close()


# ------------------------------------------------------------------ flyable
def test_every_scene_keeps_the_corridor(training_tracks: list[Track]) -> None:
    """The obstacle generator's corridor guarantee on generated tracks, at the ids' density and the densest id's."""
    radius = 0.12 + CORRIDOR_MARGIN
    for k, track in enumerate([*training_tracks[:12], *held_out()[:12]]):
        for density in (3, 5):
            scene = ObstacleGenerator(track, density=density).sample_scene(seeding.np_random(60_000 + k)[0])
            assert len(scene.obstacles) == density * len(track.obstacle_regions)
            assert find_corridor(scene, radius) is not None, (track.name, density)


def test_obstacles_stand_near_the_line_as_in_the_authors_scenes() -> None:
    """The band's share of obstacles within 0.5 and 1.0 m of the racing line lies in the authors' range over their
    three tracks (within the placement tests' tolerance): the paper's density, measured as on the paper's tracks."""
    distances = []
    for i, track in enumerate(held_out()[:40]):
        generator = ObstacleGenerator(track, density=3)
        scenes = [generator.sample_scene(seeding.np_random(50_000 + 3 * i + k)[0]) for k in range(3)]
        distances.append(obstacle_line_distances(scenes, track))
    fractions = centreline_fractions(np.concatenate(distances))
    for radius in (0.5, 1.0):
        authors = [AUTHORS_FRACTIONS[t][radius] for t in AUTHORS_FRACTIONS]
        assert min(authors) - TOLERANCE <= fractions[radius] <= max(authors) + TOLERANCE, radius


def test_planner_fast_flies_the_held_out_tracks() -> None:
    """planner-fast (privileged) on the first 20 evaluation episodes (20 held-out tracks, 4-6 gates, sprints and
    loops). It succeeds on 96-100 % of the paper's main-id scenes; at 95 % a run of 20 has fewer than 18 successes
    with probability 7.5 %, and the episodes are deterministic, so the threshold is a property of the generator."""
    agent = load_agent("planner-fast")
    env = gym.make("RaceObs-Unseen-v0", obs_mode=agent.obs_mode)
    results = [run_episode(agent, env, EVAL_SEED_BASE + i) for i in range(20)]
    env.close()
    assert sum(r["success"] for r in results) >= 18


# ------------------------------------------------------------------ records
def test_records_are_checked_against_the_episode_track() -> None:
    assert env_lap_time_bound("RaceObs-Unseen-v0") == env_lap_time_bound("RaceObs-Random-v0") > 0.3
    for seed in (EVAL_SEED_BASE, EVAL_SEED_BASE + 1, 5, PRIVATE_SEED_BASE + 7):
        for env_id in IDS:
            track = seed_track(env_id.split("-")[1], seed)
            facts = episode_facts(env_id, seed)
            assert facts == {"gates": track.num_gates, "lap_time_bound": lap_time_lower_bound(track)}
            assert env_lap_time_bound(env_id) <= facts["lap_time_bound"]  # the id's bound holds on every track
    for track in held_out():
        assert env_lap_time_bound("RaceObs-Unseen-v0") <= lap_time_lower_bound(track)
    assert episode_facts("RaceObs-S-v0", EVAL_SEED_BASE) == {}


def test_a_record_of_a_generated_track_is_held_to_that_track(tmp_path: Path) -> None:
    """A forged success is refused by its own track's facts where the id's (any track's) would let it through."""
    out = tmp_path / "eval"
    Evaluator("planner-fast", ["RaceObs-Unseen-v0"], episodes=2, out_dir=out).run(progress=False)
    records = [json.loads(line) for line in (out / RECORDS_FILE).read_text().splitlines()]
    assert len(records) == 2 and all(validate_record(r) == r for r in records)
    record = next(r for r in records if r["success"] and seed_track("Unseen", r["seed"]).num_gates < 6)
    gates = seed_track("Unseen", record["seed"]).num_gates
    assert record["gates_passed"] == gates
    with pytest.raises(InvalidRecordError, match=rf"outside \[0, {gates}\]"):  # the id alone allows 6
        validate_record(seal({**record, "gates_passed": gates + 1}))
    own = round(episode_facts(record["env_id"], record["seed"])["lap_time_bound"] * 200)
    assert own - 1 >= round(env_lap_time_bound(record["env_id"]) * 200)  # below its track's bound, not the id's
    fast = {**record, "lap_time": (own - 1) / 200, "steps": -(-(own - 1) // 4)}
    with pytest.raises(InvalidRecordError, match="lower bound"):
        validate_record(seal(fast))
