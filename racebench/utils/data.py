"""The built-in data folders (``tracks/``, ``baselines/``): YAML read as files, never importable as packages.

They used to be mapped to ``racebench.tracks`` and ``racebench.configs``, which made any folder a pull request adds
under them (``baselines/evilsub/__init__.py``) importable as ``racebench.configs.evilsub``. Now they are plain data:
in a checkout (an editable install, ``PYTHONPATH``) the folders beside the ``racebench`` package, in an installed
wheel the copies under ``<prefix>/share/racebench/`` (``setup.cfg``'s ``data_files``).
"""

from __future__ import annotations

import sys
from pathlib import Path

#: The data folders, by the name they have in the repository and under ``<prefix>/share/racebench``.
DATA_FOLDERS = ("tracks", "baselines")


def data_folder(name: str) -> Path:
    """The folder of built-in data ``name`` (``tracks`` or ``baselines``): the checkout's, else the installed one."""
    if name not in DATA_FOLDERS:
        raise ValueError(f"unknown data folder {name!r} (known: {DATA_FOLDERS})")
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / "setup.cfg").is_file() and (checkout / name).is_dir():
        return checkout / name
    return Path(sys.prefix) / "share" / "racebench" / name


def data_file(name: str, stem: str) -> Path:
    """The built-in YAML file ``<stem>.yaml`` of data folder ``name``."""
    return data_folder(name) / f"{stem}.yaml"
