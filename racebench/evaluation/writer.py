"""The writer of an evaluation's records: one sealed record (and trajectory) per finished episode."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import racebench
from racebench.agents.trust import PolicyIdentity
from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.protocol import SEED_PROTOCOL, SEED_SET, split_env_id
from racebench.evaluation.records import (
    RECORD_FORMAT,
    TRAJECTORIES_DIR,
    append_line,
    git_state,
    host_info,
    record_line,
    record_name,
    seal,
    shard_path,
)


@dataclass(frozen=True)
class RecordWriter:
    """Writes the record (and trajectory) of each finished episode of one evaluation; picklable, so worker
    processes write their own records as episodes end (a killed run loses only the episodes in flight).

    Each process appends whole lines to its own shard (:func:`racebench.evaluation.records.shard_path`), so no two
    processes
    write into one file; the evaluator merges the shards into ``records.jsonl``
    (:func:`~racebench.evaluation.records.compact_folder`).
    """

    out_dir: Path
    identity: PolicyIdentity
    agent_name: str
    renderer: str
    seed_set: str = SEED_SET
    salt_sha256: str | None = None  # of the private seed set's salt; None for public seeds

    def name(self, env_id: str, seed: int) -> str:
        """File name of the record of ``(env_id, seed)``."""
        return record_name(self.identity.sha256, env_id, ENV_VERSION, SEED_PROTOCOL, self.seed_set, seed, self.renderer)

    def write(self, env_id: str, seed: int, result: dict[str, Any], flown: dict | None) -> dict[str, Any]:
        """Seal one episode's record, append it to this process's shard (synced); return the record."""
        track, variant = split_env_id(env_id)
        commit, dirty = git_state()
        record = seal(
            {
                "record_format": RECORD_FORMAT,
                "agent": self.agent_name,
                "policy_kind": self.identity.kind,
                "policy_sha256": self.identity.sha256,
                "policy_source": self.identity.source,
                "privileged": self.identity.privileged,
                "env_id": env_id,
                "track": track,
                "variant": variant,
                "env_version": ENV_VERSION,
                "renderer": self.renderer,
                "seed": seed,
                "seed_protocol": SEED_PROTOCOL,
                "seed_set": self.seed_set,
                **result,
                "racebench_version": racebench.__version__,
                "git_commit": commit,
                "git_dirty": dirty,
                **host_info(),
                **({"seed_salt_sha256": self.salt_sha256} if self.salt_sha256 else {}),
            }
        )
        name = self.name(env_id, seed)
        if flown is not None:
            traj_dir = self.out_dir / TRAJECTORIES_DIR
            traj_dir.mkdir(parents=True, exist_ok=True)
            tmp = traj_dir / f".{name}.tmp.npz"
            scene = json.dumps(flown["scene"])
            np.savez_compressed(tmp, positions=flown["positions"], scene=scene, row=json.dumps(record))
            os.chmod(tmp, 0o644)
            os.replace(tmp, traj_dir / name.replace(".json", ".npz"))
        # The trajectory first: a record on disk promises its trajectory (a kill in between re-flies the episode).
        append_line(shard_path(self.out_dir), record_line(record))
        return record
