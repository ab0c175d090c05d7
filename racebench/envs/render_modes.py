"""RaceEnv's render modes: the ones this machine offers, and an error that names them and says why one is missing.

``"rgb_array"`` (a chase-camera image) works everywhere; ``"human"`` (PyBullet's GUI window) only where a display
is. Gymnasium's checkers make one env per mode in ``metadata["render_modes"]``, so an env lists only the modes this
machine offers, and the error for a mode it refuses lists the same ones.
"""

from __future__ import annotations

import math
import time

import numpy as np

from racebench.sim.bullet import display_available

#: Every render mode of RaceEnv, wherever it runs.
RENDER_MODES: tuple[str, ...] = ("rgb_array", "human")
#: Why a mode is not offered (shown when it is asked for); "human" only where there is no display.
NO_DISPLAY = (
    "'human' (PyBullet's GUI window) needs a display and DISPLAY is not set here: run under xvfb-run, or use "
    "'rgb_array'"
)
NO_DEPTH_ARRAY = (
    "'depth_array' is not a render mode: the depth image is the observation's 'depth' (obs_mode='vision'), and "
    "`racebench render` draws it coloured beside the chase view"
)


def offered_render_modes() -> list[str]:
    """The render modes this machine offers: ``"human"`` only with a display."""
    return [m for m in RENDER_MODES if m != "human" or display_available()]


def check_render_mode(render_mode: str | None) -> None:
    """Refuse a render mode RaceEnv does not have, naming the modes this machine offers and why one is missing.

    ``"human"`` without a display is left to the simulator, whose error says how to get one.
    """
    if render_mode is None or render_mode in RENDER_MODES:
        return
    offered = offered_render_modes()
    why = [NO_DEPTH_ARRAY] if render_mode == "depth_array" else []
    why += [] if "human" in offered else [NO_DISPLAY]
    raise ValueError(
        f"render_mode must be None or one of {offered} (this machine's), got {render_mode!r}"
        + "".join(f"; {reason}" for reason in why)
    )


class ChaseRendering:
    """``RaceEnv.render``: a chase-camera image, or PyBullet's GUI camera following the drone at real time.

    A mixin of :class:`~racebench.envs.env.RaceEnv`; it uses the env's ``render_mode``, ``scene``, ``drone``,
    ``sim`` and ``metadata["render_fps"]``.
    """

    _frame_due = 0.0  # human mode: wall-clock time (time.monotonic) at which the next frame is due

    def render(self) -> np.ndarray | None:
        """A 320×240 RGB chase-camera image (``render_mode="rgb_array"``); in ``"human"`` mode the GUI's camera
        follows the drone and the call waits until the frame is due at real time (``None`` is returned)."""
        if self.render_mode == "human" and self.scene is not None:
            self._render_human()
            return None
        if self.render_mode != "rgb_array" or self.scene is None:
            return None
        return self.sim.chase_image(self.drone.position, self.drone.rotation)

    def _render_human(self) -> None:
        """Point the GUI's camera at the drone from behind, then wait until this frame is due at real time."""
        pos, _, rot, _, _ = self.drone
        yaw = math.degrees(math.atan2(rot[1, 0], rot[0, 0]))
        # PyBullet's debug camera looks along +y at yaw 0: yaw - 90 puts it behind a drone heading along yaw.
        self.sim.client.resetDebugVisualizerCamera(2.5, yaw - 90.0, -20.0, pos.tolist())
        now = time.monotonic()
        if self._frame_due > now:
            time.sleep(self._frame_due - now)
        self._frame_due = max(now, self._frame_due) + 1.0 / self.metadata["render_fps"]
