"""Digests of the scenes (gates, obstacles, start pose) every registered id draws at fixed seeds.

``tests/data/scene_digests.json`` holds these digests as computed on the code before parameter validation was
added (issue 50, item 5), floats rounded to 1 µm (:func:`to_micrometres`); ``test_env_params.py`` recomputes them,
so any change to scene generation for valid input fails there. Regenerate (only for an intended, ENV_VERSION-bumping
change or new ids) with ``python tests/scene_digest.py tests/data/scene_digests.json`` from the repository root.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

from gymnasium.utils import seeding

from racebench.envs.env import RaceEnv
from racebench.envs.random_tracks import RandomTrackEnv, race_env
from racebench.envs.registration import ENV_KWARGS, ENV_VERSION

#: Training-range seeds 0-99 and a sample of the evaluation seeds (1_000_000 + episode index).
SEED_GROUPS: dict[str, list[int]] = {
    "seeds_0_99": list(range(100)),
    "eval_sample": [1_000_000 + i for i in range(0, 100, 5)],
}


def generator_key(kwargs: dict) -> tuple:
    """The settings that decide an id's scenes (ids that share them draw the same scenes)."""
    return (kwargs["track"], kwargs.get("density", 3), kwargs.get("gate_shift", 0.0), kwargs.get("gate_shift_z"))


def scene_digest(env: RaceEnv, seeds: list[int]) -> str:
    """SHA-256 over the JSON of the scene ``env.reset(seed=s)`` draws for each seed (``start_mode="track"``).

    Draws through the env's own generator with the generator ``reset`` seeds (Gymnasium's ``np_random``), so no
    PyBullet scene is built per seed; a track-source env (``RaceObs-Random-v0``, ``RaceObs-Unseen-v0``) draws the
    episode's track first, as its ``reset`` does (``RandomTrackEnv.draw_scene``), and the scene's JSON holds the gates.
    """
    digest = hashlib.sha256()
    for seed in seeds:
        if isinstance(env, RandomTrackEnv):
            scene = env.draw_scene(seed)
        else:
            rng, _ = seeding.np_random(seed)
            scene = env.generator.sample_scene(rng)
        digest.update(json.dumps(to_micrometres(scene.to_dict()), sort_keys=True).encode())
    return digest.hexdigest()


def to_micrometres(value):
    """``value`` with every float rounded to 6 decimals (1 µm, 1 µrad), ``-0.0`` as ``0.0``.

    The scenes agree across CPUs only to the last bit or so: numpy dispatches ``np.power`` (the band placement's
    lateral profile) to SIMD code that differs between CPUs with and without AVX-512. Rounding to 1 µm keeps the
    digests the same on every CPU (a value would have to lie within 1e-16 of a rounding boundary to differ).
    """
    if isinstance(value, float):
        return round(value, 6) + 0.0
    if isinstance(value, dict):
        return {k: to_micrometres(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_micrometres(v) for v in value]
    return value


def all_digests(env_ids: list[str] | None = None) -> dict[str, dict[str, str]]:
    """``{env_id: {seed group: digest}}`` for the given (default: every) registered id."""
    out: dict[str, dict[str, str]] = {}
    cache: dict[tuple, dict[str, str]] = {}
    for env_id in env_ids or list(ENV_KWARGS):
        kwargs = ENV_KWARGS[env_id]
        key = generator_key(kwargs)
        if key not in cache:
            env = race_env(**{**kwargs, "obs_mode": "state"})
            try:
                cache[key] = {group: scene_digest(env, seeds) for group, seeds in SEED_GROUPS.items()}
            finally:
                env.close()
        out[env_id] = cache[key]
    return out


def main(path: str) -> None:
    """Write the digests of every registered id to ``path`` (JSON)."""
    import racebench

    data = {
        "env_version": ENV_VERSION,
        "seed_groups": SEED_GROUPS,
        "source": f"racebench at {Path(racebench.__file__).parent}",
        "digests": all_digests(),
    }
    Path(path).write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main(sys.argv[1])
