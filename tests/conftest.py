"""Shared test fixtures."""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator

import pytest

# The machine-local trust store (racebench.agents.trust.trust_store) of a throwaway folder: the tests never read or
# write the user's own, and what they record is gone with the session (subprocesses and Ray workers inherit it).
os.environ["RACEBENCH_STATE_DIR"] = tempfile.mkdtemp(prefix="racebench-test-state-")
atexit.register(shutil.rmtree, os.environ["RACEBENCH_STATE_DIR"], True)


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


@pytest.fixture(autouse=True, scope="session")
def _records_of_committed_code() -> Iterator[None]:
    """Records written by the tests say ``git_dirty: false``, as from a clean checkout.

    ``racebench leaderboard add`` refuses records made from uncommitted code; the tests' fixture repositories
    stand for committed ones, and must not fail because the checkout running them has local edits. A test of the
    refusal writes its dirty record explicitly. (In-process only: a worker process sees the real state.)
    """
    import racebench.evaluation.writer
    from racebench.evaluation.records import git_state

    commit, _ = git_state()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(racebench.evaluation.writer, "git_state", lambda: (commit, False))
        yield


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray instance of 2 CPUs for this module's tests, shut down after them."""
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        ray.shutdown()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()
