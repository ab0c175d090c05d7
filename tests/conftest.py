"""Shared test fixtures."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


def _pristine_racebench_logger() -> None:
    logger = logging.getLogger("racebench")
    logger.handlers[:] = []
    logger.setLevel(logging.NOTSET)
    logger.propagate = True


@pytest.fixture(autouse=True)
def _reset_racebench_logger() -> Iterator[None]:
    """Give every test the library's own ``racebench`` logger (no handlers, propagating to the root).

    ``racebench.cli.main`` installs its handlers and stops propagation; a CLI call made earlier in the same
    worker, even from a module-scoped fixture set up before this one, would otherwise hide later tests'
    warnings from ``caplog``.
    """
    _pristine_racebench_logger()
    yield
    _pristine_racebench_logger()


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray instance of 2 CPUs for this module's tests, shut down after them."""
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        ray.shutdown()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()
