"""Malicious pickles for the trust tests: unpickling any of them creates a marker file."""

from __future__ import annotations

import base64
import json
import pickle
import zipfile
from pathlib import Path

import torch


class Payload:
    """Unpickling it opens ``marker`` for writing: proof that a pickle ran."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def evil_pickle(marker: Path) -> bytes:
    """A plain pickle (e.g. a ``vecnormalize.pkl``) whose loading creates ``marker``."""
    return pickle.dumps(Payload(marker))


def evil_sb3_zip(path: Path, marker: Path) -> Path:
    """An SB3-shaped zip whose pickled ``data`` entry and ``policy.pth`` both create ``marker`` when unpickled."""
    serialized = base64.b64encode(evil_pickle(marker)).decode()
    data = {"policy_class": {":type:": "<class 'type'>", ":serialized:": serialized}, "num_timesteps": 64}
    pth = path.with_suffix(".pth.tmp")
    torch.save({"weight": Payload(marker)}, pth)  # a torch file that only a full unpickle would run
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", json.dumps(data))
        archive.write(pth, "policy.pth")
        archive.writestr("_stable_baselines3_version", "2.9.2")
    pth.unlink()
    return path
