"""render_mode="human": PyBullet's GUI window (under Xvfb where there is no display), the same episode as
the headless env, one GUI per process with a clear error."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest

import racebench  # noqa: F401  (registers the ids)

ROOT = Path(__file__).parents[1]
XVFB = shutil.which("xvfb-run")

SCRIPT = """
import json, time
import gymnasium as gym, numpy as np, pybullet as p
import racebench

human = gym.make("RaceObs-S-Level1-v0", render_mode="human")
plain = gym.make("RaceObs-S-Level1-v0")
method = human.unwrapped.sim.client.getConnectionInfo()["connectionMethod"]
hover = np.array([human.unwrapped.params.hover_action, 0.1, 0.0, 0.05], dtype=np.float32)
a, b = human.reset(seed=4)[0], plain.reset(seed=4)[0]
same = bool(np.array_equal(a["state"], b["state"]) and np.array_equal(a["depth"], b["depth"]))
started = time.monotonic()
for _ in range(25):
    a, b = human.step(hover)[0], plain.step(hover)[0]
    same = same and bool(np.array_equal(a["state"], b["state"]) and np.array_equal(a["depth"], b["depth"]))
elapsed = time.monotonic() - started
camera = human.unwrapped.sim.client.getDebugVisualizerCamera()
target = [round(v, 3) for v in camera[11]]
drone = [round(v, 3) for v in human.unwrapped.drone.position.tolist()]
rendered = human.render()
try:
    gym.make("RaceObs-J-v0", render_mode="human")
    second = "opened"
except RuntimeError as exc:
    second = str(exc)
human.close()
plain.close()
print(json.dumps({"gui": method == p.GUI, "same": same, "elapsed": elapsed, "target": target, "drone": drone,
                  "rendered": rendered, "second": second}))
"""


@pytest.mark.skipif(
    XVFB is None and not os.environ.get("DISPLAY"), reason="needs a display: xvfb-run (apt install xvfb) or DISPLAY"
)
def test_human_mode_opens_the_gui_and_flies_the_same_episode() -> None:
    command = [sys.executable, "-c", SCRIPT]
    if not os.environ.get("DISPLAY"):
        command = [XVFB, "-a", *command]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(command, capture_output=True, text=True, timeout=180, env=env)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    assert done.returncode == 0 and lines, done.stderr[-2000:]
    result = json.loads(lines[-1])
    assert result["gui"], "render_mode='human' must open PyBullet's GUI"
    assert result["same"], "the GUI must not change the physics or the observations"
    assert result["elapsed"] >= 25 / 50 * 0.9, "human mode paces the episode at real time (50 Hz)"
    # The GUI thread applies the camera asynchronously: within one step of the drone (PyBullet default: origin).
    assert result["target"] == pytest.approx(result["drone"], abs=0.1), "the GUI camera follows the drone"
    assert result["rendered"] is None
    assert "one GUI window per process" in result["second"]


def test_human_mode_without_a_display_is_a_clear_error(monkeypatch) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("the DISPLAY check is Linux's")
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match="needs a display.*xvfb-run"):
        gym.make("RaceObs-S-v0", render_mode="human")
    # Not offered where it cannot open: Gymnasium's check_env makes one env per offered mode.
    env = gym.make("RaceObs-S-v0", render_mode="rgb_array")
    assert env.unwrapped.metadata["render_modes"] == ["rgb_array"]
    env.close()
    monkeypatch.setenv("DISPLAY", ":99")
    env = gym.make("RaceObs-S-v0")
    assert env.unwrapped.metadata["render_modes"] == ["rgb_array", "human"]
    env.close()


def test_the_render_modes_agree_without_a_display(monkeypatch) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("the DISPLAY check is Linux's")
    monkeypatch.delenv("DISPLAY", raising=False)
    env = gym.make("RaceObs-S-v0")
    offered = env.unwrapped.metadata["render_modes"]
    env.close()
    for mode in ("depth_array", "rgbarray"):
        with pytest.raises(ValueError) as raised:
            gym.make("RaceObs-S-v0", render_mode=mode)
        message = str(raised.value)
        assert f"one of {offered} (this machine's), got {mode!r}" in message  # the list metadata gives
        assert "'human' (PyBullet's GUI window) needs a display and DISPLAY is not set here" in message
    with pytest.raises(ValueError, match=r"'depth_array' is not a render mode: the depth image is the observation"):
        gym.make("RaceObs-S-v0", render_mode="depth_array")
    monkeypatch.setenv("DISPLAY", ":99")  # with a display: both listed, nothing to explain
    with pytest.raises(ValueError) as raised:
        gym.make("RaceObs-S-v0", render_mode="rgbarray")
    expected = "render_mode must be None or one of ['rgb_array', 'human'] (this machine's), got 'rgbarray'"
    assert str(raised.value) == expected
