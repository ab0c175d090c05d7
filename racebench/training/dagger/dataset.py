"""The DAgger aggregate: every labelled step, each episode's steps kept contiguous and cut into chunks."""

from __future__ import annotations

import numpy as np
import torch

from racebench.training.dagger.config import PATH_AUX_SIZE


class Dataset:
    """The DAgger aggregate: observations (depth as uint8), the teacher's actions, each step's loss weight and its
    auxiliary target (``aux``, with ``aux_mask`` 0 where there is none; :func:`line_ahead`), a ring buffer.

    Samples are stored one episode segment at a time (:meth:`add_segment`), so consecutive indices are
    consecutive steps of one episode except where ``starts`` marks a new segment. Index 0 and the oldest
    surviving sample after an overwrite also start one (their predecessor is gone or at the far end).
    """

    def __init__(self, capacity: int, depth_size: int) -> None:
        self.state = np.zeros((capacity, 17), dtype=np.float32)
        self.depth = np.zeros((capacity, 1, depth_size, depth_size), dtype=np.uint8)
        self.action = np.zeros((capacity, 4), dtype=np.float32)
        self.weight = np.ones(capacity, dtype=np.float32)
        self.aux = np.zeros((capacity, PATH_AUX_SIZE), dtype=np.float32)
        self.aux_mask = np.zeros(capacity, dtype=np.float32)
        self.starts = np.zeros(capacity, dtype=bool)
        self.size = self.next = 0

    def add_segment(
        self, state: np.ndarray, depth: np.ndarray, action: np.ndarray, weight: np.ndarray | None = None,
        aux: np.ndarray | None = None, aux_mask: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """Store consecutive steps of one episode (depth quantised to uint8; loss weights default 1; auxiliary
        targets default none: mask 0); the first starts a sequence."""
        capacity = len(self.state)
        quantised = np.round(depth * 255.0).astype(np.uint8)
        weight = np.ones(len(state), dtype=np.float32) if weight is None else weight
        aux = np.zeros((len(state), PATH_AUX_SIZE), dtype=np.float32) if aux is None else aux
        aux_mask = np.zeros(len(state), dtype=np.float32) if aux_mask is None else aux_mask
        for k in range(len(state)):
            i = self.next
            self.state[i], self.depth[i], self.action[i] = state[k], quantised[k], action[k]
            self.weight[i], self.aux[i], self.aux_mask[i] = weight[k], aux[k], aux_mask[k]
            self.starts[i] = k == 0 or i == 0
            self.next = (i + 1) % capacity
            self.size = min(self.size + 1, capacity)
        if self.size == capacity and len(state):
            self.starts[self.next] = True  # the oldest surviving step lost its predecessor

    def chunks(self, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stored steps cut into sequences of at most ``length`` that never cross a segment start.

        Returns ``(first, count, position)``: each chunk's first index, its number of steps, and its ordinal
        within its segment (0: the chunk starts a segment, so a recurrent state of zero). Chunks are in index
        order and cover every stored step exactly once.
        """
        bounds = np.flatnonzero(self.starts[: self.size])  # index 0 is always one (add_segment)
        ends = np.append(bounds[1:], self.size)
        per_run = -(-(ends - bounds) // length)
        run = np.repeat(np.arange(len(bounds)), per_run)
        position = np.arange(len(run)) - np.repeat(np.cumsum(per_run) - per_run, per_run)
        first = bounds[run] + position * length
        count = np.minimum(length, ends[run] - first)
        return first, count, position

    def batch(self, index: np.ndarray) -> dict[str, torch.Tensor]:
        """A minibatch as the student's observation dict (depth back to [0, 1] floats) plus its labels
        (``action``) and their loss weights (``weight``)."""
        return {
            **self.observations(index),
            "action": torch.from_numpy(self.action[index]),
            "weight": torch.from_numpy(self.weight[index]),
        }

    def observations(self, index: np.ndarray) -> dict[str, torch.Tensor]:
        """The student's observation dict of ``index`` alone (no labels)."""
        return {
            "state": torch.from_numpy(self.state[index]),
            "depth": torch.from_numpy(self.depth[index].astype(np.float32) / 255.0),
        }
