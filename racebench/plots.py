"""Figures from result files alone: success rates with confidence intervals, SR vs density and vs gate
shift, the 3D track plot with flown trajectories (the paper's Fig. 4), and an episode GIF.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from PIL import Image  # noqa: E402

from racebench.evaluation import TRACK_ORDER  # noqa: E402
from racebench.registration import DENSITIES, GATE_SHIFTS  # noqa: E402
from racebench.tables import TRACK_NAMES  # noqa: E402


def _label(agent: str, privileged: bool) -> str:
    return f"{agent} (privileged)" if privileged else agent


def _agents(summary: pd.DataFrame) -> list[tuple[str, bool]]:
    pairs = summary.drop_duplicates("agent")[["agent", "privileged"]].itertuples(index=False)
    return sorted(((str(a), bool(p)) for a, p in pairs), key=lambda x: (x[1], x[0]))


def plot_success_by_track(summary: pd.DataFrame, path: str | Path) -> Path:
    """Grouped bars: SR per track and agent with 95 % Wilson intervals (privileged agents hatched)."""
    main = summary[summary["variant"] == "default"]
    if main.empty:
        raise ValueError("no results on the main ids (RaceObs-{S,J,Circle}-v0) to plot")
    agents = _agents(main)
    width = 0.8 / len(agents)
    fig, ax = plt.subplots(figsize=(1.8 + 1.6 * len(TRACK_ORDER), 3.4))
    x = np.arange(len(TRACK_ORDER))
    for i, (agent, privileged) in enumerate(agents):
        rows = [main[(main["agent"] == agent) & (main["track"] == t)] for t in TRACK_ORDER]
        sr = np.array([100 * r["success_rate"].iloc[0] if len(r) else np.nan for r in rows])
        low = np.array([100 * r["sr_ci_low"].iloc[0] if len(r) else np.nan for r in rows])
        high = np.array([100 * r["sr_ci_high"].iloc[0] if len(r) else np.nan for r in rows])
        ax.bar(
            x + (i - (len(agents) - 1) / 2) * width,
            sr,
            width,
            yerr=[sr - low, high - sr],
            capsize=3,
            label=_label(agent, privileged),
            hatch="//" if privileged else None,
            edgecolor="black",
            linewidth=0.5,
        )
    ax.set_xticks(x, [TRACK_NAMES[t] for t in TRACK_ORDER])
    ax.set_ylabel("success rate [%]")
    ax.set_ylim(0, 105)
    n = int(main["n"].min())
    ax.set_title(f"Success rate, 95% Wilson CI (n ≥ {n} per cell)", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def plot_success_vs(summary: pd.DataFrame, factor: str, path: str | Path) -> Path:
    """SR vs obstacle density (``factor="density"``) or gate shift (``"gates"``), one panel per track."""
    if factor == "density":
        xs, xlabel = list(DENSITIES), "obstacles per 2 gates"
        variants = [f"Density{d}" for d in DENSITIES]
    elif factor == "gates":
        xs, xlabel = [float(s) for s in GATE_SHIFTS], "gate shift ±[m]"
        variants = [f"GateShift{s}" for s in GATE_SHIFTS]
    else:
        raise ValueError(f"factor must be 'density' or 'gates', got {factor!r}")
    data = summary[summary["variant"].isin(variants)]
    if data.empty:
        raise ValueError(f"no results on the {factor} variants to plot")
    fig, axes = plt.subplots(1, len(TRACK_ORDER), figsize=(10, 3.2), sharey=True)
    for ax, track in zip(axes, TRACK_ORDER, strict=True):
        for agent, privileged in _agents(data):
            mine = data[(data["agent"] == agent) & (data["track"] == track)]
            rows = [mine[mine["variant"] == v] for v in variants]
            sr = np.array([100 * r["success_rate"].iloc[0] if len(r) else np.nan for r in rows])
            low = np.array([100 * r["sr_ci_low"].iloc[0] if len(r) else np.nan for r in rows])
            high = np.array([100 * r["sr_ci_high"].iloc[0] if len(r) else np.nan for r in rows])
            style = "--" if privileged else "-"
            (line,) = ax.plot(xs, sr, style, marker="o", label=_label(agent, privileged))
            ax.fill_between(xs, low, high, color=line.get_color(), alpha=0.15)
        ax.set_title(TRACK_NAMES[track], fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_xticks(xs)
        ax.set_ylim(0, 105)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate [%] (95% CI)")
    axes[-1].legend(fontsize=8, loc="lower left")
    return _save(fig, path)


def _draw_scene(ax, scene: dict) -> None:
    for gate in scene["gates"]:
        c = np.array(gate["center"])
        n = np.array([np.cos(gate["yaw"]), np.sin(gate["yaw"]), 0.0])
        lat = np.array([-n[1], n[0], 0.0])
        up = np.array([0.0, 0.0, 1.0])
        for half, width in ((gate["inner"] / 2, 1.0), (gate["outer"] / 2, 2.0)):
            corners = [c + half * (sx * lat + sy * up) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))]
            ax.plot(*np.array(corners).T, color="tab:orange", linewidth=width)
    theta = np.linspace(0, 2 * np.pi, 16)
    for obs in scene["obstacles"]:
        x, y, z = obs["position"]
        if obs["kind"] == "cylinder":
            r, h = obs["size"]
            ring_x, ring_y = x + r * np.cos(theta), y + r * np.sin(theta)
        else:
            hx, hy, hz = obs["size"]
            h = 2 * hz
            cy, sy = np.cos(obs["yaw"]), np.sin(obs["yaw"])
            local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy], [-hx, -hy]])
            ring_x, ring_y = x + local[:, 0] * cy - local[:, 1] * sy, y + local[:, 0] * sy + local[:, 1] * cy
        zs = np.array([z - h / 2, z + h / 2])
        X, Z = np.meshgrid(ring_x, zs)
        Y, _ = np.meshgrid(ring_y, zs)
        ax.plot_surface(X, Y, Z, color="tab:blue", alpha=0.35, linewidth=0)
    start = scene["start"]["position"]
    ax.scatter(*start, color="tab:green", s=30, label="start")


def plot_track_3d(
    out_dir: str | Path, env_id: str, path: str | Path, agent: str | None = None, seed: int | None = None
) -> Path:
    """The paper's Fig. 4: gates, obstacles and flown trajectories of one env id (needs saved trajectories).

    One scene (the episode ``seed``, default the first saved one) with every saved trajectory flown in it
    (each agent's, or only ``agent``'s); successful flights solid, failures dotted with an x at the crash.
    """
    files = sorted((Path(out_dir) / "trajectories").glob("*.npz"))
    runs = []
    for f in files:
        with np.load(f) as data:
            row = json.loads(str(data["row"]))
            if row["env_id"] == env_id and (agent is None or row["agent"] == agent):
                runs.append((row, data["positions"], json.loads(str(data["scene"]))))
    if not runs:
        raise ValueError(f"no trajectories of {env_id!r} in {str(out_dir)!r} (evaluate with --save-trajectories)")
    seed = min(r["seed"] for r, _, _ in runs) if seed is None else seed
    runs = [run for run in runs if run[0]["seed"] == seed]  # one scene: trajectories of other seeds flew others
    if not runs:
        raise ValueError(f"no trajectory of {env_id!r} with seed {seed} in {str(out_dir)!r}")
    fig = plt.figure(figsize=(7, 5.5))
    ax = fig.add_subplot(projection="3d")
    _draw_scene(ax, runs[0][2])
    for row, positions, _ in runs:
        ok = bool(row["success"])
        ax.plot(*positions.T, "-" if ok else ":", color="tab:green" if ok else "tab:red", linewidth=1.2, alpha=0.8)
        if not ok:
            ax.scatter(*positions[-1], marker="x", color="tab:red", s=25)
    all_points = np.concatenate([p for _, p, _ in runs] + [np.array([g["center"] for g in runs[0][2]["gates"]])])
    low, high = all_points.min(axis=0) - 1.0, all_points.max(axis=0) + 1.0
    low[2], high[2] = 0.0, max(high[2], 3.0)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(0, high[2])
    ax.set_box_aspect(high - low)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    k = sum(bool(r["success"]) for r, _, _ in runs)
    who = agent or ", ".join(sorted({r["agent"] for r, _, _ in runs}))
    ax.set_title(f"{env_id}, seed {seed}: {who} ({k}/{len(runs)} successful)", fontsize=9)
    return _save(fig, path)


def render_episode_gif(
    agent_spec: str,
    env_id: str,
    seed: int,
    path: str | Path,
    fps: int = 25,
    trust_code: bool = False,
    agent_kwargs: dict[str, Any] | None = None,
) -> Path:
    """Fly one episode and write a GIF: chase-camera view beside the onboard inverse-depth image."""
    import gymnasium as gym

    from racebench.agents import load_agent
    from racebench.evaluation import SingleTorchThread, run_episode

    agent = load_agent(agent_spec, trust_code=trust_code, agent_kwargs=agent_kwargs)
    env = gym.make(env_id, render_mode="rgb_array", obs_mode="vision")
    frames: list[Image.Image] = []
    every = max(1, round(env.unwrapped.control_freq / fps))

    class Recorder(gym.Wrapper):
        def step(self, action):
            out = super().step(action)
            if self.unwrapped.steps % every == 0 or out[2] or out[3]:
                frames.append(_compose(self.render(), out[0]["depth"][0]))
            return out

    wrapped = Recorder(env)
    if agent.obs_mode == "state":
        # The recorder, inside, still sees the depth image; the state agent gets the state alone.
        state_space = env.unwrapped.observation_space["state"]
        wrapped = gym.wrappers.TransformObservation(wrapped, lambda o: o["state"], state_space)
    with SingleTorchThread():
        result = run_episode(agent, wrapped, seed)
    env.close()
    if not frames:
        raise RuntimeError(f"episode produced no frames ({result})")
    path = Path(path)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path


def _compose(rgb: np.ndarray, depth: np.ndarray) -> Image.Image:

    h = rgb.shape[0]
    depth_img = Image.fromarray((np.clip(depth, 0, 1) * 255).astype(np.uint8)).resize((h, h), Image.NEAREST)
    canvas = Image.new("RGB", (rgb.shape[1] + h, h))
    canvas.paste(Image.fromarray(rgb), (0, 0))
    canvas.paste(depth_img.convert("RGB"), (rgb.shape[1], 0))
    return canvas


def plot_training_curves(runs: list[str | Path], path: str | Path, smooth: int = 20) -> Path:
    """The paper's Fig. 5 from training runs: mean episode return (rolling mean over ``smooth`` updates),
    success rate from the track start, and curriculum level, against environment steps.

    ``runs``: run directories (holding ``progress.csv``) or ``progress.csv`` files; each is labelled by its
    ``config.yaml`` name when present, else by its directory name.
    """
    import yaml

    fig, axes = plt.subplots(3, 1, figsize=(6.4, 6.4), sharex=True, height_ratios=[2, 1.4, 1])
    for run in runs:
        run = Path(run)
        csv_path = run / "progress.csv" if run.is_dir() else run
        if not csv_path.is_file():
            raise ValueError(f"{run}: no progress.csv (is it a `racebench train` run directory?)")
        progress = pd.read_csv(csv_path)
        missing = {"timesteps", "mean_return", "success_rate", "level"} - set(progress.columns)
        if missing:
            raise ValueError(f"{csv_path}: missing columns {sorted(missing)}")
        config = csv_path.parent / "config.yaml"
        label = yaml.safe_load(config.read_text()).get("name") if config.is_file() else csv_path.parent.name
        steps = progress["timesteps"] / 1e6
        window = dict(window=smooth, min_periods=1)
        (line,) = axes[0].plot(steps, progress["mean_return"].rolling(**window).mean(), label=label)
        axes[1].plot(steps, 100 * progress["success_rate"].rolling(**window).mean(), color=line.get_color())
        axes[2].step(steps, progress["level"], where="post", color=line.get_color())
    axes[0].set_ylabel("mean episode return")
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_ylabel("success from start [%]")
    axes[1].set_ylim(-2, 102)
    axes[2].set_ylabel("level")
    axes[2].set_yticks([1, 2, 3])
    axes[2].set_xlabel("environment steps [millions]")
    for ax in axes:
        ax.grid(alpha=0.3)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return path
