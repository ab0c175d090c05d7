"""The private seed set: derived from a secret salt, reproducible from it, disjoint from the public seeds."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest

import racebench  # noqa: F401 - registers the ids
from racebench import cli
from racebench.evaluation import EVAL_SEED_BASE, Evaluator, MixedResultsError, eval_seeds, load_records
from racebench.evaluation.records import (
    MAX_PUBLIC_EPISODES,
    RECORDS_FILE,
    InvalidRecordError,
    name_of,
    read_folder,
    seal,
    validate_record,
)
from racebench.evaluation.seeds import (
    PRIVATE_SEED_BASE,
    PUBLIC_SEED_BASE,
    SALT_ENV,
    SeedSetError,
    private_seeds,
    salt_sha256,
    seeds_for,
)

ENV = "RaceObs-S-Level1-v0"  # no obstacles: hover runs fast
SALT = "f3c1a9e07b5d4c2e8a6f1b3d5e7c9a0b"
OTHER = "0b9a7c5e3d1f6b8a2e4c6d8f0a1b3c5e"


def test_private_seeds_are_reproducible_from_the_salt_and_disjoint_from_public_ones() -> None:
    seeds = private_seeds(SALT, 1000)
    assert seeds == private_seeds(SALT, 1000)  # the salt is all it takes to reproduce them
    assert seeds[:10] == private_seeds(SALT, 10)  # a prefix of a longer run: --episodes N means the first N
    assert len(set(seeds)) == 1000
    assert not set(seeds) & set(private_seeds(OTHER, 1000))  # another salt, other scenes
    public = set(eval_seeds(MAX_PUBLIC_EPISODES))
    assert not set(seeds) & public
    assert min(seeds) >= PRIVATE_SEED_BASE > max(public) and min(public) > 999_999  # above training seeds too
    # Spread over the range, not clustered at its start (an HMAC is uniform; a bug like `% 1000` is not).
    assert max(seeds) - min(seeds) > 0.9 * PRIVATE_SEED_BASE
    assert PUBLIC_SEED_BASE == EVAL_SEED_BASE and seeds_for("public", 3) == eval_seeds(3)
    assert salt_sha256(SALT) != salt_sha256(OTHER) and SALT not in salt_sha256(SALT)


def test_private_scenes_are_not_public_scenes() -> None:
    env = gym.make("RaceObs-S-v0", obs_mode="state")
    scenes = []
    for seed in [*eval_seeds(5), *private_seeds(SALT, 5)]:
        env.reset(seed=seed)
        scenes.append(json.dumps(env.unwrapped.scene.to_dict(), sort_keys=True))
    env.close()
    assert len(set(scenes)) == 10


def test_weak_or_missing_salt_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    with pytest.raises(SeedSetError, match="at least 16"):
        private_seeds("short", 3)
    with pytest.raises(SeedSetError, match="unknown seed set"):
        seeds_for("secret", 3)
    monkeypatch.delenv(SALT_ENV, raising=False)
    with pytest.raises(SystemExit, match=rf"^racebench evaluate: --seed-set private needs .* {SALT_ENV}$"):
        cli.main(["evaluate", "--agent", "hover", "--envs", ENV, "--episodes", "1", "--seed-set", "private",
                  "--out", str(tmp_path / "x")])  # fmt: skip
    assert not (tmp_path / "x").exists()


def test_private_evaluation_records_the_set_and_the_salt_hash_not_the_salt(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv(SALT_ENV, SALT)
    out = tmp_path / "private"
    assert cli.main(["evaluate", "--agent", "hover", "--envs", ENV, "--episodes", "2", "--seed-set", "private",
                     "--out", str(out)]) == 0  # fmt: skip
    records = read_folder(out).sorted_records()
    assert len(records) == 2
    assert sorted(r["seed"] for r in records) == sorted(private_seeds(SALT, 2))
    assert {r["seed_set"] for r in records} == {"private"}
    assert {r["seed_salt_sha256"] for r in records} == {salt_sha256(SALT)}
    assert all(SALT not in p.read_text() for p in [out / RECORDS_FILE, out / "episodes.csv"])
    assert len(load_records(out)) == 2
    # Resumed with the same salt; refused with another salt or the public set (one folder, one seed set).
    assert Evaluator("hover", [ENV], episodes=2, out_dir=out, seed_set="private").pending() == []
    with pytest.raises(MixedResultsError, match="of another salt"):
        Evaluator("hover", [ENV], episodes=2, out_dir=out, seed_set="private", salt=OTHER)
    with pytest.raises(MixedResultsError, match="private seed set"):
        Evaluator("hover", [ENV], episodes=2, out_dir=out)

    record = records[0]
    public_twin = seal({**record, "seed_set": "public"})
    del public_twin["seed_salt_sha256"]
    assert name_of(public_twin) != name_of(record)  # the file name includes the seed set
    for forged in (
        seal({**record, "seed": EVAL_SEED_BASE}),  # a public seed claimed as private
        seal({k: v for k, v in record.items() if k != "seed_salt_sha256"}),  # private without its salt hash
        seal({**record, "seed_salt_sha256": "not-a-hash"}),
        seal({**record, "seed_set": "public"}),  # public with a salt hash and a private seed
        seal({**public_twin, "seed_set": "hidden"}),
    ):
        with pytest.raises(InvalidRecordError):
            validate_record(forged)
    assert validate_record(record, name_of(record)) == record
