"""Episode videos through imageio, GIF or MP4: a chase view large enough to see the drone, the onboard depth
image in colour with a scale bar in metres, and a caption (agent, env id, seed, time, gates passed, outcome).

One implementation for every user of episode videos (``racebench render``,
:func:`racebench.reporting.plots.render_episode_gif`
and anything that shows episodes, such as a results site): :func:`render_episode_video` flies an episode and
writes the file, :class:`EpisodeFrames` turns env states into frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from racebench.agents.loading import load_agent
from racebench.evaluation.rollout import run_episode
from racebench.evaluation.worker import SingleTorchThread
from racebench.sim.bullet import p

VIDEO_FORMATS: tuple[str, ...] = (".gif", ".mp4")
CHASE_SIZE = (640, 480)  # width, height of the chase view (px)
SCALE_WIDTH = 96  # the depth scale bar and its labels (px)
CAPTION_HEIGHT = 48  # px; every panel size is a multiple of 16, as H.264's macro blocks want
DEPTH_TICKS_M: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
DEPTH_COLORMAP = "turbo_r"  # near = red, far = blue: the dark inverse-depth image made readable


class EpisodeFrames:
    """Frames of one episode: chase view | coloured depth | scale bar, above a caption line.

    Args:
        label: who flies (the caption's first field).
        env_id: the id flown, for the caption.
        seed: the episode seed, for the caption.
    """

    def __init__(self, label: str, env_id: str, seed: int) -> None:
        from matplotlib import colormaps

        self.label, self.env_id, self.seed = label, env_id, seed
        self.cmap = colormaps[DEPTH_COLORMAP]
        self.font = ImageFont.load_default(size=18)
        self.small = ImageFont.load_default(size=14)
        self._scale: Image.Image | None = None

    def frame(self, env: Any, depth: np.ndarray, outcome: str | None = None) -> np.ndarray:
        """The frame of ``env``'s current state (``env``: an unwrapped ``RaceEnv``; ``depth``: its float depth
        observation ``(1, H, W)``); ``outcome`` ends the caption once the episode is over (else "flying")."""
        height = CHASE_SIZE[1]
        canvas = Image.new("RGB", (CHASE_SIZE[0] + height + SCALE_WIDTH, height + CAPTION_HEIGHT), "white")
        canvas.paste(Image.fromarray(chase_view(env)), (0, 0))
        canvas.paste(self._depth(env, depth, height), (CHASE_SIZE[0], 0))
        canvas.paste(self._scale_bar(env, height), (CHASE_SIZE[0] + height, 0))
        gates = f"gates {env.next_gate - env.start_gate}/{len(env.scene.gates) - env.start_gate}"
        text = f"{self.label}  |  {self.env_id}  |  seed {self.seed}  |  t = {env.time:5.2f} s  |  {gates}  |  "
        text += outcome or "flying"
        draw = ImageDraw.Draw(canvas)
        draw.text((12, height + (CAPTION_HEIGHT - 18) // 2), text, fill="black", font=self.font)
        return np.asarray(canvas)

    def _depth(self, env: Any, depth: np.ndarray, size: int) -> Image.Image:
        camera = env.camera
        inverse = np.clip(np.asarray(depth, dtype=np.float64).reshape(depth.shape[-2:]), 1e-6, 1.0)
        metres = np.clip(camera.min_depth / inverse, camera.min_depth, camera.max_depth)
        rgb = (self.cmap(self._scaled(metres, camera))[..., :3] * 255).astype(np.uint8)
        image = Image.fromarray(rgb).resize((size, size), Image.NEAREST)
        ImageDraw.Draw(image).text((8, 6), "onboard depth", fill="white", font=self.small)
        return image

    @staticmethod
    def _scaled(metres: np.ndarray, camera: Any) -> np.ndarray:
        """Depth on a log scale in [0, 1]: equal steps for 0.2-2 m and 2-10 m (near matters most)."""
        return np.log(metres / camera.min_depth) / math.log(camera.max_depth / camera.min_depth)

    def _scale_bar(self, env: Any, height: int) -> Image.Image:
        if self._scale is None:
            camera = env.camera
            bar = Image.new("RGB", (SCALE_WIDTH, height), "white")
            top, bottom, left, width = 24, height - 24, 10, 22
            levels = np.linspace(0.0, 1.0, bottom - top)[:, None]  # near at the top
            strip = (self.cmap(np.repeat(levels, width, axis=1))[..., :3] * 255).astype(np.uint8)
            bar.paste(Image.fromarray(strip), (left, top))
            draw = ImageDraw.Draw(bar)
            for tick in DEPTH_TICKS_M:
                if camera.min_depth <= tick <= camera.max_depth:
                    y = top + self._scaled(np.array(tick), camera) * (bottom - top - 1)
                    draw.line([(left + width, y), (left + width + 5, y)], fill="black")
                    draw.text((left + width + 8, y - 8), f"{tick:g} m", fill="black", font=self.small)
            self._scale = bar
        return self._scale


def chase_view(env: Any, size: tuple[int, int] = CHASE_SIZE) -> np.ndarray:
    """RGB chase view of an unwrapped ``RaceEnv``: 1.6 m behind the drone and 0.6 m above it, looking 1 m past
    it (60° FOV), so the drone (16 cm across) spans about 50 px at 640×480."""
    position, _, rotation, _, _ = env.drone
    heading = rotation[:, 0].copy()
    heading[2] = 0.0
    norm = float(np.linalg.norm(heading))
    heading = heading / norm if norm > 1e-6 else np.array([1.0, 0.0, 0.0])
    eye = position - 1.6 * heading + np.array([0.0, 0.0, 0.6])
    target = position + 1.0 * heading
    client = env.sim.client
    view = client.computeViewMatrix(eye.tolist(), target.tolist(), [0.0, 0.0, 1.0])
    projection = client.computeProjectionMatrixFOV(60.0, size[0] / size[1], 0.05, 60.0)
    _, _, rgba, _, _ = client.getCameraImage(
        size[0], size[1], viewMatrix=view, projectionMatrix=projection, renderer=p.ER_TINY_RENDERER,
        flags=p.ER_NO_SEGMENTATION_MASK, shadow=0,
    )  # fmt: skip
    return np.asarray(rgba, dtype=np.uint8).reshape(size[1], size[0], 4)[:, :, :3].copy()


def outcome_text(result: dict[str, Any]) -> str:
    """The caption's last field for a finished episode (a :func:`racebench.evaluation.rollout.run_episode` result)."""
    if result.get("error"):
        return "FAILED: agent error"
    if result.get("success"):
        return f"SUCCESS, lap {result['lap_time']:.2f} s"
    if result.get("crashed"):
        return f"CRASH ({result['crash_reason']})"
    return "TIME LIMIT"


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write RGB frames as an MP4 (H.264, streamed) or a GIF (half size, looping), by ``path``'s suffix."""
    import imageio.v2 as imageio
    import imageio.v3 as iio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_FORMATS:
        formats = ", ".join(VIDEO_FORMATS)
        raise ValueError(f"{str(path)!r}: videos are written as {formats}, not {suffix or 'no suffix'!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".mp4":
        with imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=16) as writer:
            for frame in frames:
                writer.append_data(frame)
        return path
    # GIF keeps every frame in memory and has 256 colours: half size keeps a 15 s episode near 100 MB in
    # memory and a few MB on disk.
    small = [np.asarray(Image.fromarray(f).resize((f.shape[1] // 2, f.shape[0] // 2), Image.BILINEAR)) for f in frames]
    if not small:
        raise ValueError("no frames to write")
    iio.imwrite(path, np.stack(small), extension=".gif", duration=round(1000 / fps), loop=0)
    return path


def render_episode_video(
    agent_spec: str,
    env_id: str,
    seed: int,
    path: str | Path,
    fps: float = 25.0,
    trust_code: bool = False,
    agent_kwargs: dict[str, Any] | None = None,
    label: str | None = None,
    vecnormalize: str | Path | bool | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Fly one episode of ``env_id`` with ``agent_spec`` (any spec ``racebench evaluate`` accepts) and write its
    video to ``path`` (``.mp4`` or ``.gif``); return the path and the episode's result. ``vecnormalize``: an SB3
    checkpoint's statistics (:func:`racebench.agents.trust.resolve_vecnormalize`).

    Frames are taken every ``control_freq / fps`` steps, at the start and on the last step; the last frame
    is held for a second with the outcome in the caption.
    """
    if Path(path).suffix.lower() not in VIDEO_FORMATS:
        raise ValueError(f"{str(path)!r}: videos are written as {', '.join(VIDEO_FORMATS)}")
    agent = load_agent(agent_spec, trust_code=trust_code, agent_kwargs=agent_kwargs, vecnormalize=vecnormalize)
    env = gym.make(env_id, obs_mode="vision")
    raw = env.unwrapped
    every = max(1, round(raw.control_freq / fps))
    frames_of = EpisodeFrames(label or getattr(agent, "name", agent_spec), env_id, seed)
    frames: list[np.ndarray] = []
    last: dict[str, Any] = {}

    class Recorder(gym.Wrapper):
        def reset(self, **kwargs: Any) -> Any:
            obs, info = super().reset(**kwargs)
            frames.append(frames_of.frame(raw, obs["depth"]))
            return obs, info

        def step(self, action: Any) -> Any:
            out = super().step(action)
            last["depth"] = out[0]["depth"]
            if raw.steps % every == 0 and not (out[2] or out[3]):
                frames.append(frames_of.frame(raw, out[0]["depth"]))
            return out

    wrapped: gym.Env = Recorder(env)
    if agent.obs_mode == "state":  # the recorder, inside, still sees the depth image; the agent gets the state
        wrapped = gym.wrappers.TransformObservation(wrapped, lambda o: o["state"], raw.observation_space["state"])
    try:
        with SingleTorchThread():
            result = run_episode(agent, wrapped, seed)
        final = frames_of.frame(raw, last.get("depth", np.zeros((1, 64, 64))), outcome_text(result))
        frames.extend([final] * max(1, round(fps)))  # hold the outcome for a second
        written = write_video(frames, path, fps)
    finally:
        env.close()
    return written, result
