"""Episode videos: MP4 and GIF through imageio, the drone visible in the chase view, depth in colour, a caption
that ends with the outcome."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from racebench import cli
from racebench.reporting.video import CAPTION_HEIGHT, CHASE_SIZE, render_episode_video

ENV = "RaceObs-S-Level1-v0"


def test_mp4_frames_show_the_drone_coloured_depth_and_a_caption(tmp_path: Path) -> None:
    path, result = render_episode_video("random", ENV, 3, tmp_path / "random.mp4", fps=10)
    reader = imageio.get_reader(path)
    frames = [np.asarray(frame, dtype=int) for frame in reader]
    reader.close()
    steps, every, hold = result["steps"], 5, 10  # 50 Hz control at 10 fps; the outcome held for a second
    expected = 1 + sum(1 for k in range(1, steps) if k % every == 0) + hold
    assert len(frames) == expected
    width, height = CHASE_SIZE
    assert frames[0].shape == (height + CAPTION_HEIGHT, width + height + 96, 3)
    chase = frames[0][:height, :width]
    red = (chase[..., 0] > 150) & (chase[..., 1] < 60) & (chase[..., 2] < 60)
    assert red.sum() > 400, "the drone (a red body) must be large in the chase view"
    depth = frames[0][:height, width : width + height]
    spread = np.abs(depth[..., 0] - depth[..., 1]).mean() + np.abs(depth[..., 1] - depth[..., 2]).mean()
    assert spread > 40, "the depth image must be shown in colour"
    caption_first, caption_last = frames[0][height:], frames[-1][height:]
    assert (caption_first.sum(axis=2) < 250).sum() > 300  # text
    assert np.abs(caption_first - caption_last).sum() > 0  # time, gates and the outcome changed


def test_gif_and_bad_suffix(tmp_path: Path) -> None:
    path, _ = render_episode_video("random", ENV, 3, tmp_path / "random.gif", fps=5)
    frames = imageio.mimread(path)
    width, height = CHASE_SIZE
    assert len(frames) > 5 and frames[0].shape[:2] == ((height + CAPTION_HEIGHT) // 2, (width + height + 96) // 2)
    with pytest.raises(ValueError, match=r"\.gif, \.mp4"):
        render_episode_video("random", ENV, 3, tmp_path / "random.avi")
    with pytest.raises(SystemExit, match="^racebench render: .*videos are written as"):
        cli.main(["-q", "render", "--agent", "random", "--env", ENV, "--out", str(tmp_path / "x.webm")])
