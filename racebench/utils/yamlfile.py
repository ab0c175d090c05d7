"""Reading racebench's YAML files (configs, sweeps, tracks, leaderboard metadata) with ``yaml.safe_load``.

``safe_load`` builds plain data only: a ``!!python/...`` tag is refused with a ``ConstructorError``, never run.
PyYAML's messages span several lines (a snippet of the file with a caret); :func:`yaml_problem` makes them one
line, so each command reports a bad file as a one-line error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


def yaml_problem(exc: yaml.YAMLError) -> str:
    """What is wrong in a YAML document, on one line, with its line and column when PyYAML knows them."""
    problem = getattr(exc, "problem", None) or str(exc)
    context = getattr(exc, "context", None)
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    text = f"{context}: {problem}" if context else problem
    text = " ".join(f"{text}{where}".split())
    if "python/" in text:  # why an otherwise well-formed file is refused
        text += " (racebench reads plain YAML only: no !!python tags)"
    return text


def read_yaml(path: str | Path) -> Any:
    """``yaml.safe_load`` of the file ``path``; a YAML error becomes a ``ValueError`` naming the file on one line.

    An unreadable file raises ``OSError`` as ``Path.read_text`` does.
    """
    path = Path(path)
    text = path.read_text()
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None
