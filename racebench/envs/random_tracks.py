"""``RaceObs-Random-v0`` and ``RaceObs-Unseen-v0``: a generated track per episode (the paper's open problem).

:class:`RandomTrackEnv` is :class:`~racebench.envs.env.RaceEnv` whose ``reset`` also chooses the episode's track
(:mod:`racebench.sim.track_generator`), then swaps the track, the obstacle generator and the simulation's gates
before drawing the scene as ``RaceEnv`` does. Its ``track`` kwarg names a **track source** (:data:`TRACK_SOURCES`):

* ``"Random"`` (``RaceObs-Random-v0``, for training): the first draw of the env's ``np_random`` after seeding is a
  track seed in ``[0, TRAIN_TRACK_SEEDS)`` and the episode flies that seed's track, so every reset brings a new track
  and new obstacles, and the seed fixes both;
* ``"Unseen"`` (``RaceObs-Unseen-v0``, held out): the :data:`UNSEEN_TRACKS` committed tracks
  ``tracks/unseen/unseen-NNN.yaml``, the tracks of track seeds ``UNSEEN_TRACK_SEED_BASE + NNN``
  (``scripts/make_unseen_tracks.py`` writes them). Seed ``s`` flies track ``s mod 100``, so evaluation episode ``i``
  (seed ``1,000,000 + i``) flies track ``i mod 100`` and the first 100 episodes fly each track once. A private seed
  (``>= 10^12``, the verified tier's) flies a track of its own, generated from the seed, never published: the
  maintainers' private evaluation then covers tracks nobody has seen. An unseeded reset draws a committed track from
  ``np_random``.

The splits are disjoint by construction: training track seeds lie below ``10^9``, the held-out ones at ``2 x 10^9`` and
up, private ones at ``10^12`` and up; and the generator never makes a paper track (tested). Observation and action
spaces are those of every racebench id; the state's next two gates and the lap's end follow the episode's track
(closed loop or sprint), as on the paper's tracks.

The records of these ids are validated against the episode's own track (:func:`episode_facts`: its gate count and
lap-time lower bound, computed from the record's seed as ``reset`` does).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding

from racebench.envs.env import RaceEnv
from racebench.envs.lap_bound import lap_time_lower_bound
from racebench.envs.registration import ENV_KWARGS
from racebench.sim.obstacles import ObstacleGenerator
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.scene import Scene
from racebench.sim.track import Track, load_track
from racebench.sim.track_generator import GATE_COUNTS, TRACK_SOURCES, generate_track, track_from_seed, track_rng
from racebench.utils.data import data_folder

#: ``RaceObs-Random-v0`` draws its track seeds in ``[0, TRAIN_TRACK_SEEDS)``.
TRAIN_TRACK_SEEDS = 1_000_000_000
#: The held-out track ``i`` is the track of track seed ``UNSEEN_TRACK_SEED_BASE + i``.
UNSEEN_TRACK_SEED_BASE = 2_000_000_000
UNSEEN_TRACKS = 100
UNSEEN_FOLDER = "unseen"  # under tracks/
#: Private seeds start here (``racebench.evaluation.seeds.PRIVATE_SEED_BASE``; a test keeps them equal).
PRIVATE_SEED_BASE = 10**12


# --------------------------------------------------------------------------- the held-out set
def unseen_track_path(index: int) -> Path:
    """The committed file of held-out track ``index`` (``tracks/unseen/unseen-NNN.yaml``)."""
    return data_folder("tracks") / UNSEEN_FOLDER / f"unseen-{_index(index):03d}.yaml"


def _index(index: int) -> int:
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < UNSEEN_TRACKS:
        raise ValueError(f"a held-out track index must be an int in [0, {UNSEEN_TRACKS - 1}], got {index!r}")
    return int(index)


@functools.cache
def unseen_track(index: int) -> Track:
    """Held-out track ``index``, read from its committed file."""
    return load_track(unseen_track_path(index))


def make_unseen_track(index: int) -> Track:
    """Held-out track ``index`` generated afresh (what its committed file must hold)."""
    return track_from_seed(UNSEEN_TRACK_SEED_BASE + _index(index), name=f"unseen-{_index(index):03d}")


def private_track(seed: int) -> Track:
    """The track a private seed flies on ``RaceObs-Unseen-v0``: generated from the seed, never published."""
    return generate_track(track_rng(seed), name="private")


def episode_track(source: str, seed: int | None, np_random: np.random.Generator) -> Track:
    """The track of an episode of ``source`` reset with ``seed``; ``np_random`` is the env's generator just seeded with
    it (a ``Random`` episode, and an unseeded ``Unseen`` one, draw from it first)."""
    if source == "Random":
        return track_from_seed(int(np_random.integers(TRAIN_TRACK_SEEDS)))
    if source != "Unseen":
        raise ValueError(f"track source must be one of {TRACK_SOURCES}, got {source!r}")
    if seed is None:
        return unseen_track(int(np_random.integers(UNSEEN_TRACKS)))
    if seed >= PRIVATE_SEED_BASE:
        return private_track(seed)
    return unseen_track(seed % UNSEEN_TRACKS)


def seed_track(source: str, seed: int) -> Track:
    """The track ``reset(seed=seed)`` flies on ``source`` (for records and tools: no env needed)."""
    return episode_track(source, seed, seeding.np_random(seed)[0])


# --------------------------------------------------------------------------- the env
class RandomTrackEnv(RaceEnv):
    """:class:`~racebench.envs.env.RaceEnv` on a generated track per episode (module docstring).

    Args:
        track: the track source, ``"Random"`` or ``"Unseen"`` (:data:`TRACK_SOURCES`).
        **kwargs: every other :class:`~racebench.envs.env.RaceEnv` kwarg, with the same meaning and ranges
            (``start_spread`` replaces each track's start spread).
    """

    def __init__(self, track: str = "Random", **kwargs: Any) -> None:
        if track not in TRACK_SOURCES:
            raise ValueError(f"track must be a track source {TRACK_SOURCES} for this env, got {track!r}")
        # The world is built on the S track (same gates), then given the source's gate bodies and first track.
        super().__init__(track="S", **kwargs)
        self.source = track
        self._spread = self.track.start.spread if kwargs.get("start_spread") is not None else None
        self.sim.fit_gates([self.track.gates[0]] * GATE_COUNTS[-1])  # every body built now, whatever comes first
        first = track_from_seed(0) if track == "Random" else unseen_track(0)
        self._use_track(first)

    def _with_spread(self, track: Track) -> Track:
        if self._spread is None or np.array_equal(track.start.spread, self._spread):
            return track
        return dataclasses.replace(track, start=dataclasses.replace(track.start, spread=self._spread))

    def _generator_for(self, track: Track) -> ObstacleGenerator:
        """An obstacle generator for ``track`` with this env's current settings (also those of ``set_task``)."""
        current = self.generator
        return ObstacleGenerator(
            self._with_spread(track),
            density=current.density,
            kind=current.kind,
            gate_shift=current.gate_shift,
            gate_shift_z=self._gate_shift_z,
            drone_radius=current.drone_radius,
            placement=current.placement,
        )

    def _use_track(self, track: Track) -> None:
        """Fly ``track`` from now on: the track, its obstacle generator and the simulation's gate bodies."""
        self.generator = self._generator_for(track)
        self.track = self.generator.track
        self.sim.fit_gates(self.track.gates)

    def reset_state(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> dict:
        """:meth:`RaceEnv.reset_state` on the episode's track: ``options["scene"]``'s or the shared layout's, else
        the track the source gives for ``seed`` (:func:`episode_track`)."""
        self._require_open("reset")
        gym.Env.reset(self, seed=seed)
        scene = (options or {}).get("scene")
        if isinstance(scene, Scene):
            track = scene.track
        elif scene is None and self.layout is not None:
            track = self.layout.track
        elif scene is None:
            track = episode_track(self.source, seed, self.np_random)
        else:
            track = self.track  # RaceEnv.reset_state refuses the option
        if track is not self.track:
            self._use_track(track)
        return super().reset_state(seed=None, options=options)

    def sample_layout(self) -> Scene:
        """A new track and its scene, from this env's ``np_random`` (for :meth:`set_layout` on a group of envs)."""
        track = episode_track(self.source, None, self.np_random)
        return self._generator_for(track).sample_scene(self.np_random)

    def set_layout(self, layout: Scene | None) -> None:
        """Fly every following episode in ``layout``'s track, gates and obstacles (start pose still random)."""
        if layout is not None and len(layout.gates) != len(layout.track.gates):
            raise ValueError(f"layout has {len(layout.gates)} gates, its track has {len(layout.track.gates)}")
        self.layout = layout

    def draw_scene(self, seed: int) -> Scene:
        """The scene ``reset(seed=seed)`` draws at ``start_mode="track"`` without a layout, without building it in the
        simulation (for scene digests)."""
        rng = seeding.np_random(seed)[0]
        return self._generator_for(episode_track(self.source, seed, rng)).sample_scene(rng)


def race_env(**kwargs: Any) -> RaceEnv:
    """The env of these kwargs: :class:`RandomTrackEnv` for a track source, else :class:`RaceEnv` (vector envs)."""
    if kwargs.get("track") in TRACK_SOURCES:
        return RandomTrackEnv(**kwargs)
    return RaceEnv(**kwargs)


# --------------------------------------------------------------------------- record facts
def most_gates(track: str) -> int:
    """Gates per lap of a track name or file, or the most any track of a source has."""
    return GATE_COUNTS[-1] if track in TRACK_SOURCES else load_track(track).num_gates


def _id_kwargs(env_id: str) -> dict[str, Any]:
    defaults = {k: p.default for k, p in inspect.signature(RaceEnv.__init__).parameters.items()}
    return {**defaults, **ENV_KWARGS[env_id]}


@functools.lru_cache(maxsize=4096)
def episode_facts(env_id: str, seed: int) -> dict[str, Any]:
    """What a record of ``env_id`` at ``seed`` is checked against beyond the id's facts: for a track-source id the
    episode's own track's gates per lap and lap-time lower bound (:mod:`racebench.envs.lap_bound`); ``{}`` for
    every other id."""
    kwargs = _id_kwargs(env_id) if env_id in ENV_KWARGS else {}
    if kwargs.get("track") not in TRACK_SOURCES:
        return {}
    track = seed_track(kwargs["track"], seed)
    if kwargs["start_spread"] is not None:
        spread = np.asarray(kwargs["start_spread"], dtype=float)
        track = dataclasses.replace(track, start=dataclasses.replace(track.start, spread=spread))
    quad = kwargs["quadrotor"]
    params = quad if isinstance(quad, QuadrotorParams) else QuadrotorParams(**(quad or {}))
    bound = lap_time_lower_bound(track, params, kwargs["gate_shift"], kwargs["gate_shift_z"], kwargs["physics_freq"])
    return {"gates": track.num_gates, "lap_time_bound": bound}
