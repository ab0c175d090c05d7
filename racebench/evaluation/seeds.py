"""Evaluation seed sets: the public seeds anyone can replay, and a private set derived from a secret salt.

Public seeds (``EVAL_SEED_BASE + i``) can be fitted: any submitted code can rebuild the env with
``gym.make(id).reset(seed=s)`` and recognise the scene. The *private* set is what the maintainers verify on:
seed ``i`` is ``PRIVATE_SEED_BASE + HMAC-SHA256(salt, "racebench-private-seed:<protocol>:<i>") mod
PRIVATE_SEED_SPAN``. Without the salt the seeds are unpredictable (the range holds 10^12 scenes), with it they
are reproducible; they lie above every public and training seed by construction. A record of a private episode
carries :func:`salt_sha256` (never the salt), so which secret produced a result can be checked without
revealing it.
"""

from __future__ import annotations

import hashlib
import hmac
import os

#: Environment variable holding the maintainers' secret salt for ``--seed-set private``.
SALT_ENV = "RACEBENCH_PRIVATE_SALT"
#: A salt shorter than this could be found by brute force from its published hash.
MIN_SALT_CHARS = 16
PUBLIC_SEED_BASE = 1_000_000  # racebench.evaluation.protocol.EVAL_SEED_BASE; training seeds lie below it
MAX_PUBLIC_EPISODES = 100_000  # racebench.evaluation.records.MAX_PUBLIC_EPISODES
# Private seeds lie in [BASE, BASE + SPAN): far above the public ones, and below 2**63 so pandas keeps them int64.
PRIVATE_SEED_BASE = 10**12
PRIVATE_SEED_SPAN = 10**12
SEED_SETS: tuple[str, ...] = ("public", "private")


class SeedSetError(ValueError):
    """A seed set was asked for that cannot be produced (unknown name, missing or weak salt)."""


def salt_from_env() -> str:
    """The private salt from :data:`SALT_ENV`; :class:`SeedSetError` (one line) when unset or too short."""
    salt = os.environ.get(SALT_ENV, "")
    if not salt:
        raise SeedSetError(f"--seed-set private needs the secret salt in the environment variable {SALT_ENV}")
    check_salt(salt)
    return salt


def check_salt(salt: str) -> None:
    """Refuse a salt short enough to be guessed from its published hash."""
    if len(salt) < MIN_SALT_CHARS:
        raise SeedSetError(
            f"{SALT_ENV} is {len(salt)} characters; use at least {MIN_SALT_CHARS} random ones "
            "(e.g. `openssl rand -hex 32`), or its published hash reveals it"
        )


def salt_sha256(salt: str) -> str:
    """The published fingerprint of a salt: sha256 of a domain tag and the salt (not the salt itself)."""
    return hashlib.sha256(b"racebench-private-salt\0" + salt.encode()).hexdigest()


def check_episodes(episodes: int) -> None:
    """Episodes per env id are 1 to :data:`MAX_PUBLIC_EPISODES` (the public seed set's size, which bounds the plan's
    memory too); anything else is a one-line :class:`ValueError`."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or not 1 <= episodes <= MAX_PUBLIC_EPISODES:
        raise ValueError(f"episodes per env id must be an integer from 1 to {MAX_PUBLIC_EPISODES:,} (the public seed "
                         f"set's size), got {episodes!r}")  # fmt: skip


def private_seeds(salt: str, episodes: int, protocol: int = 1) -> list[int]:
    """The first ``episodes`` private seeds of ``salt`` under seed protocol ``protocol`` (distinct, in order)."""
    check_episodes(episodes)
    check_salt(salt)
    seeds: list[int] = []
    seen: set[int] = set()
    index = 0
    while len(seeds) < episodes:
        mac = hmac.new(salt.encode(), f"racebench-private-seed:{protocol}:{index}".encode(), hashlib.sha256)
        seed = PRIVATE_SEED_BASE + int.from_bytes(mac.digest()[:8], "big") % PRIVATE_SEED_SPAN
        index += 1
        if seed not in seen:  # a repeat (chance ~n^2/10^12) would make two episodes one record slot
            seen.add(seed)
            seeds.append(seed)
    return seeds


def public_seeds(episodes: int) -> list[int]:
    """The public evaluation seeds: ``PUBLIC_SEED_BASE + i``."""
    check_episodes(episodes)
    return [PUBLIC_SEED_BASE + i for i in range(episodes)]


def seed_in_set(seed: int, seed_set: str) -> bool:
    """Whether ``seed`` can belong to ``seed_set`` (the range only: private membership needs the salt)."""
    if seed_set == "public":
        return PUBLIC_SEED_BASE <= seed < PUBLIC_SEED_BASE + MAX_PUBLIC_EPISODES
    if seed_set == "private":
        return PRIVATE_SEED_BASE <= seed < PRIVATE_SEED_BASE + PRIVATE_SEED_SPAN
    return False


def seeds_for(seed_set: str, episodes: int, salt: str | None = None, protocol: int = 1) -> list[int]:
    """The seeds of ``seed_set`` (``public`` or ``private``; private reads the salt from the env when not given)."""
    if seed_set == "public":
        return public_seeds(episodes)
    if seed_set == "private":
        return private_seeds(salt if salt is not None else salt_from_env(), episodes, protocol)
    raise SeedSetError(f"unknown seed set {seed_set!r}; choose from {SEED_SETS}")
