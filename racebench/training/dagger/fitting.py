"""Fitting the student to the aggregate: chunk start states, the sequence loss, truncated BPTT minibatches."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from racebench.agents.recurrent import MixtureActionHead, mixture_action_loss
from racebench.training.dagger.config import DaggerConfig
from racebench.training.dagger.dataset import Dataset
from racebench.training.student import is_recurrent, student_features, student_mean, student_unroll


def dataset_features(policy: Any, dataset: Dataset, batch: int = 4096) -> torch.Tensor:
    """The student's features (:func:`student_features`) of every stored step, without gradient: ``(size, F)``."""
    with torch.no_grad():
        return torch.cat([
            student_features(policy, dataset.observations(np.arange(a, min(a + batch, dataset.size))))
            for a in range(0, dataset.size, batch)
        ])  # fmt: skip


def chunk_start_states(
    policy: Any, dataset: Dataset, chunks: tuple, batch: int = 4096, features: torch.Tensor | None = None
) -> torch.Tensor:  # fmt: skip
    """The GRU state each chunk starts from under the current student: ``(n_chunks, H)``.

    The student runs without gradient through every segment in order, chunk by chunk, all segments side by
    side (their ``position``-th chunks together); a chunk at position 0 starts from zero. ``features``: the
    stored steps' features if already computed (:func:`dataset_features`).
    """
    first, count, position = chunks
    length = int(count.max()) if len(count) else 1
    if features is None:
        features = dataset_features(policy, dataset, batch)
    with torch.no_grad():
        states = torch.zeros(len(first), policy.lstm_actor.hidden_size)
        segment = np.cumsum(position == 0) - 1  # each chunk's segment
        carried = torch.zeros(int(segment[-1]) + 1 if len(segment) else 0, policy.lstm_actor.hidden_size)
        for p in range(int(position.max()) + 1 if len(position) else 0):
            sel = np.flatnonzero(position == p)
            steps = np.minimum(first[sel, None] + np.arange(length), first[sel, None] + count[sel, None] - 1)
            start = carried[segment[sel]] if p > 0 else torch.zeros(len(sel), policy.lstm_actor.hidden_size)
            states[sel] = start
            output, _ = policy.lstm_actor(features[steps].transpose(0, 1), (start[None], torch.zeros_like(start[None])))
            carried[segment[sel]] = output[torch.from_numpy(count[sel] - 1), torch.arange(len(sel))]
    return states


def sequence_loss(
    policy: Any, dataset: Dataset, first: np.ndarray, count: np.ndarray, states: torch.Tensor, length: int,
    weighted: bool = False, shifts: np.ndarray | None = None,
) -> torch.Tensor:  # fmt: skip
    """Mean squared error over the real steps of the chunks ``(first, count)``, each unrolled from its start
    state in ``states`` ``(chunks, H)``; a chunk shorter than ``length`` is padded and its padding masked.
    With ``weighted``, each step's error counts by its stored loss weight (a weighted mean); ``shifts``
    ``(chunks, 2)``: each chunk's depth images shifted by that many pixels (:func:`shift_depth`)."""
    return sequence_terms(policy, dataset, first, count, states, length, weighted, shifts)[0]


def sequence_terms(
    policy: Any, dataset: Dataset, first: np.ndarray, count: np.ndarray, states: torch.Tensor, length: int,
    weighted: bool = False, shifts: np.ndarray | None = None, path_head: torch.nn.Module | None = None,
    mixture_sigma: float = 0.2, features: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
    """:func:`sequence_loss` and, with ``path_head``, the auxiliary loss: the mean squared error of the head's
    prediction from each step's GRU output against the stored target, over the real steps that have one
    (``aux_mask``; unweighted). Without a head the second term is ``None``. A student with a mixture head
    (:class:`~racebench.agents.recurrent.MixtureActionHead`) is fitted with its scaled mixture loss
    (:func:`~racebench.agents.recurrent.mixture_action_loss`, standard deviation ``mixture_sigma``) in place of
    the squared error, averaged the same way. ``features``: every stored step's features, fixed
    (:func:`dataset_features`; the feature layers then get no gradient), in place of the depth CNN's pass."""
    offsets = np.arange(length)
    steps = np.minimum(first[:, None] + offsets, first[:, None] + count[:, None] - 1)
    index = steps.T.reshape(-1)  # time-major: (length * chunks)
    if features is None:
        batch = dataset.batch(index)
        if shifts is not None:
            batch["depth"] = shift_depth(batch["depth"], np.tile(shifts, (length, 1)))
        target, weight = batch.pop("action"), batch.pop("weight")
        inputs = student_features(policy, batch)
    else:
        if shifts is not None:
            raise ValueError("dagger: fixed features cannot be shifted (augment_shift needs the CNN's pass)")
        target, weight = torch.from_numpy(dataset.action[index]), torch.from_numpy(dataset.weight[index])
        inputs = features[torch.from_numpy(index)]
    target, weight = target.view(length, len(first), -1), weight.view(length, len(first), 1)
    actions, output = student_unroll(policy, inputs.view(length, len(first), -1), states[None])
    real = torch.from_numpy(offsets[:, None] < count[None, :]).unsqueeze(-1)
    mask = real * weight if weighted else real
    if isinstance(policy.action_net, MixtureActionHead):
        latent = policy.mlp_extractor.forward_actor(output)
        per_step = mixture_action_loss(policy.action_net, latent, target, mixture_sigma).unsqueeze(-1)
        loss = (per_step * mask).sum() / mask.sum()
    else:
        loss = ((actions - target) ** 2 * mask).sum() / (mask.sum() * target.shape[-1])
    if path_head is None:
        return loss, None
    aux_target = torch.from_numpy(dataset.aux[index]).view(length, len(first), -1)
    aux_mask = real * torch.from_numpy(dataset.aux_mask[index]).view(length, len(first), 1)
    aux_error = ((path_head(output) - aux_target) ** 2 * aux_mask).sum()
    return loss, aux_error / (aux_mask.sum().clamp(min=1.0) * aux_target.shape[-1])


def shift_depth(depth: torch.Tensor, shifts: np.ndarray) -> torch.Tensor:
    """Each image of ``depth`` ``(N, 1, H, W)`` moved by ``shifts[i] = (dx, dy)`` whole pixels (content moves right
    and down for positive values), the edge pixels replicated into the gap."""
    k = int(np.abs(shifts).max(initial=0))
    if k == 0:
        return depth
    height, width = depth.shape[-2:]
    padded = torch.nn.functional.pad(depth, (k, k, k, k), mode="replicate")
    out = torch.empty_like(depth)
    for dx, dy in np.unique(shifts, axis=0):
        rows = torch.from_numpy(np.flatnonzero((shifts[:, 0] == dx) & (shifts[:, 1] == dy)))
        out[rows] = padded[rows, :, k - dy : k - dy + height, k - dx : k - dx + width]
    return out


def pass_orders(items: int, epochs: int, cap: int | None, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Each pass's random order over ``items`` indices: ``epochs`` passes, cut once ``cap`` indices have been
    given in all (``None``: never), so a cut pass is a uniform random subset."""
    budget = items * epochs if cap is None else cap
    for epoch in range(epochs):
        order = rng.permutation(items)[: max(0, budget - epoch * items)]
        if not len(order):
            return
        yield order


def iteration_learning_rate(config: DaggerConfig, iteration: int) -> float:
    """The fit's learning rate at ``iteration``: ``learning_rate``, or with ``learning_rate_final`` set the linear
    ramp from ``learning_rate`` (iteration 0) to ``learning_rate_final`` (iteration ``iterations - 1``)."""
    if config.learning_rate_final is None or config.iterations == 1:
        return config.learning_rate
    fraction = min(iteration, config.iterations - 1) / (config.iterations - 1)
    return (1.0 - fraction) * config.learning_rate + fraction * config.learning_rate_final


def fit(
    policy: Any, dataset: Dataset, config: DaggerConfig, optimizer: Any, rng: np.random.Generator,
    path_head: torch.nn.Module | None = None, aux_losses: list[float] | None = None, frozen_features: bool = False,
) -> float:  # fmt: skip
    """``config.epochs`` passes of minibatch MSE regression over the dataset, cut at ``config.fit_samples``
    samples (a recurrent student's: ``fit_samples // sequence_length`` chunks); returns the last pass's loss.

    With ``path_head`` (a recurrent student, ``config.path_aux_weight`` > 0) each minibatch minimises the action loss
    plus ``path_aux_weight`` times the auxiliary loss (:func:`sequence_terms`; the optimizer holds the head's
    parameters too); the returned loss is the action part alone, and the last pass's auxiliary losses are appended
    to ``aux_losses``.

    A recurrent student trains on chunks of ``config.sequence_length`` steps (``batch_size // sequence_length``
    chunks a minibatch), each unrolled from the state :func:`chunk_start_states` gave it; the loss averages
    the chunks' real steps (a short chunk's padding is masked). With ``config.crash_weight`` other than 1 the
    loss is the mean weighted by each step's stored weight (:func:`collect`). With ``frozen_features`` (a recurrent
    student) the feature layers are not trained: their outputs for the whole aggregate are computed once, without
    gradient, and the GRU and heads are fitted on them (``freeze_features_after``).
    """
    if frozen_features and not is_recurrent(policy):
        raise ValueError("dagger: freeze_features_after fits a GRU on fixed features: it needs a recurrent student")
    if path_head is not None and not is_recurrent(policy):
        raise ValueError("dagger: the auxiliary path head reads a GRU's output: it needs a recurrent student")
    policy.set_training_mode(True)
    losses: list[float] = []
    aux: list[float] = []
    weighted = config.crash_weight != 1.0  # unweighted runs keep the plain mean (bit for bit as before)
    if is_recurrent(policy):
        length = config.sequence_length
        chunks = dataset.chunks(length)
        policy.set_training_mode(False)
        features = dataset_features(policy, dataset) if frozen_features else None
        states = chunk_start_states(policy, dataset, chunks, features=features)
        policy.set_training_mode(True)
        first, count, _ = chunks
        per_batch = max(1, config.batch_size // length)
        cap = None if config.fit_samples is None else config.fit_samples // length
        for order in pass_orders(len(first), config.epochs, cap, rng):
            losses, aux = [], []
            for a in range(0, len(order), per_batch):
                pick = order[a : a + per_batch]
                shifts = (  # drawn only when on, so runs without it keep their random stream
                    rng.integers(-config.augment_shift, config.augment_shift + 1, size=(len(pick), 2))
                    if config.augment_shift
                    else None
                )
                error, aux_error = sequence_terms(
                    policy, dataset, first[pick], count[pick], states[pick], length, weighted, shifts, path_head,
                    config.mixture_sigma, features,
                )  # fmt: skip
                total = error if aux_error is None else error + config.path_aux_weight * aux_error
                optimizer.zero_grad()
                total.backward()
                optimizer.step()
                losses.append(error.item())
                if aux_error is not None:
                    aux.append(aux_error.item())
        if aux_losses is not None:
            aux_losses.extend(aux)
    else:
        if isinstance(policy.action_net, MixtureActionHead):
            raise ValueError("dagger: a mixture action head is fitted on sequences: it needs a recurrent student")
        for order in pass_orders(dataset.size, config.epochs, config.fit_samples, rng):
            if len(order) < config.batch_size:
                break  # too few left for one minibatch
            losses = []
            for start in range(0, len(order) - config.batch_size + 1, config.batch_size):
                batch = dataset.batch(order[start : start + config.batch_size])
                if config.augment_shift:
                    shifts = rng.integers(-config.augment_shift, config.augment_shift + 1, size=(config.batch_size, 2))
                    batch["depth"] = shift_depth(batch["depth"], shifts)
                target, weight = batch.pop("action"), batch.pop("weight")
                if weighted:
                    error = (student_mean(policy, batch) - target) ** 2 * weight[:, None]
                    loss = error.sum() / (weight.sum() * target.shape[-1])
                else:
                    loss = torch.nn.functional.mse_loss(student_mean(policy, batch), target)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                losses.append(loss.item())
    policy.set_training_mode(False)
    return float(np.mean(losses)) if losses else float("nan")
