"""Shared test fixtures."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _restore_racebench_logger() -> Iterator[None]:
    """Undo what ``racebench.cli.main`` does to the ``racebench`` logger (its own handlers, no propagation),
    so a CLI test run earlier in the same worker cannot hide later tests' warnings from ``caplog``."""
    logger = logging.getLogger("racebench")
    saved = (logger.handlers[:], logger.level, logger.propagate)
    yield
    logger.handlers[:], logger.level, logger.propagate = saved[0], saved[1], saved[2]
