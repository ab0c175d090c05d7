"""A DAgger run's resumable state: saved after each finished iteration in the run folder, and restored."""

from __future__ import annotations

import json
import pickle
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from racebench.training.dagger.config import DaggerConfig
from racebench.training.dagger.dataset import Dataset

RESUME_DIR = "resume"  # in a run folder: the state after the last finished iteration
# settings a resumption may change: they do not change the iterations already run
AFTER_TRAINING: tuple[str, ...] = ("iterations", "select_episodes", "final_student")
# Settings of the machine, not of the run: a run started beside another (one fit thread) may go on alone with two. The
# resumed part's fits then differ from an unstopped run's in their last bits (a sum's order follows the thread count).
RESOURCE_SETTINGS: tuple[str, ...] = ("update_threads",)
KEPT_DIR = "iterations"  # in a run folder: the students kept for selection (DaggerConfig.keep_iterations)


def saved_policy_state(path: Path) -> dict[str, torch.Tensor]:
    """The policy weights of an SB3 zip the run saved, read as tensors only (``torch.load(weights_only=True)``):
    the zip's pickled ``data`` is not read, so nothing in the file can run code."""
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        _, params, _ = load_from_zip_file(path, load_data=False, device="cpu")
    except (ValueError, pickle.UnpicklingError, RuntimeError) as exc:  # a bad zip, or a .pth with more than tensors
        why = " ".join(str(exc).split())[:200]  # torch's weights_only message spans many lines
        raise ValueError(f"dagger: {path} holds no readable policy weights ({why})") from None
    if not params or "policy" not in params:
        raise ValueError(f"dagger: {path} holds no policy weights")
    return params["policy"]


def load_optimizer_state(path: Path) -> dict[str, Any]:
    """The optimizer, random and auxiliary-head state :func:`save_resume_state` wrote, read with
    ``torch.load(weights_only=True)``: tensors, numbers and containers only; a file asking for more is refused."""
    try:
        return torch.load(path, weights_only=True)
    except pickle.UnpicklingError:
        raise ValueError(f"dagger: {path} holds more than tensors and numbers (weights_only refused it)") from None


def save_resume_state(
    out: Path, iteration: int, student: Any, optimizer: Any, dataset: Dataset, rng: np.random.Generator,
    seeds: list[int], rows: list[dict[str, Any]], config: DaggerConfig, failed: list[int] | None = None,
    path_head: torch.nn.Module | None = None,
) -> None:  # fmt: skip
    """Everything iteration ``iteration + 1`` needs, written beside the run and swapped in whole.

    The student (SB3 zip), the optimizer's state (and the auxiliary head's weights, ``path_head``), the aggregate
    dataset (with the auxiliary targets when there is a head), the numpy generator's state, the scene
    seed counter, the queue of failed scenes to replay (``failed``) and the progress rows. Episodes never span
    iterations (``collect`` starts every env afresh), so nothing of the envs needs saving. The folder is written
    under another name and renamed into place, so a kill leaves either the previous iteration's state or this one's.
    """

    partial, final, old = out / f"{RESUME_DIR}.partial", out / RESUME_DIR, out / f"{RESUME_DIR}.old"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    student.save(partial / "student.zip")
    extra = {"optimizer": optimizer.state_dict(), "torch_rng": torch.get_rng_state()}
    if path_head is not None:
        extra["path_head"] = path_head.state_dict()
    torch.save(extra, partial / "optimizer.pt")
    n = dataset.size
    aux = {"aux": dataset.aux[:n], "aux_mask": dataset.aux_mask[:n]} if path_head is not None else {}
    np.savez(partial / "dataset.npz", state=dataset.state[:n], depth=dataset.depth[:n], action=dataset.action[:n],
             weight=dataset.weight[:n], starts=dataset.starts[:n], next=np.array(dataset.next), **aux)  # fmt: skip
    state = {"iteration": iteration, "rng": rng.bit_generator.state, "seeds": seeds, "failed": failed or [],
             "rows": rows, "config": asdict(config)}  # fmt: skip
    (partial / "state.json").write_text(json.dumps(_json_safe(state), allow_nan=False))
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)
        final.rename(old)
    partial.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def resume_folder(out: Path) -> Path | None:
    """The folder holding the newest complete saved state of the run in ``out``, if any.

    Normally ``resume/``. A kill inside :func:`save_resume_state`'s swap can leave ``resume.partial/`` (complete
    once its ``state.json``, written last, exists) and ``resume.old/`` (the previous state) instead.
    """
    for name in (RESUME_DIR, f"{RESUME_DIR}.partial", f"{RESUME_DIR}.old"):
        if (out / name / "state.json").is_file():
            return out / name
    return None


def completed_iterations(out: Path) -> int:
    """How many iterations the saved state of the run in ``out`` has finished (0 without one)."""
    folder = resume_folder(out)
    return 0 if folder is None else int(json.loads((folder / "state.json").read_text())["iteration"]) + 1


def load_resume_state(out: Path, config: DaggerConfig) -> dict[str, Any] | None:
    """The state :func:`save_resume_state` left in ``out`` (``None`` if there is none), checked against ``config``.

    Every setting must match the saved run's except ``iterations``, which may grow (a finished run continues), those
    that only choose the final checkpoint (:data:`AFTER_TRAINING`) and ``update_threads`` (:data:`RESOURCE_SETTINGS`).
    The returned dict's ``folder`` is where the state was found (:func:`resume_folder`).
    """
    folder = resume_folder(out)
    if folder is None:
        return None
    try:
        state = json.loads((folder / "state.json").read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"dagger: {folder / 'state.json'} is not valid JSON ({exc})") from exc
    # A setting added after the state was saved: that run had the setting's default.
    saved, asked = {**asdict(DaggerConfig()), **state["config"]}, asdict(config)
    for key in asked:
        if key not in AFTER_TRAINING + RESOURCE_SETTINGS and saved[key] != asked[key]:
            raise ValueError(f"dagger: cannot resume {out}: it was run with {key}={saved[key]!r}, not {asked[key]!r}")
    if state["iteration"] + 1 > config.iterations:
        raise ValueError(
            f"dagger: {out} has finished {state['iteration'] + 1} iterations, more than the {config.iterations} asked"
        )
    return {**state, "folder": str(folder)}


def restore_state(
    saved: dict[str, Any], student: Any, optimizer: Any, dataset: Dataset, rng: np.random.Generator,
    path_head: torch.nn.Module | None = None,
) -> None:  # fmt: skip
    """Load a state :func:`load_resume_state` returned into the student (SB3 model), its optimizer, the auxiliary
    head, the aggregate, the numpy generator and torch's random state, as the run left them after its last finished
    iteration."""
    folder = Path(saved["folder"])
    student.policy.load_state_dict(saved_policy_state(folder / "student.zip"))
    extra = load_optimizer_state(folder / "optimizer.pt")
    optimizer.load_state_dict(extra["optimizer"])
    torch.set_rng_state(extra["torch_rng"])
    if path_head is not None:
        path_head.load_state_dict(extra["path_head"])  # the config matched (load_resume_state): it was saved
    with np.load(folder / "dataset.npz") as data:
        n = len(data["state"])
        dataset.state[:n], dataset.depth[:n], dataset.action[:n] = data["state"], data["depth"], data["action"]
        dataset.starts[:n] = data["starts"]
        if "weight" in data:  # a state saved before loss weights existed: all 1
            dataset.weight[:n] = data["weight"]
        if "aux" in data:
            dataset.aux[:n], dataset.aux_mask[:n] = data["aux"], data["aux_mask"]
        dataset.size, dataset.next = n, int(data["next"])
    rng.bit_generator.state = saved["rng"]


def _json_safe(value: Any) -> Any:
    """NaN (an iteration without a finished episode, a lap time without a success) as JSON ``null``."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
