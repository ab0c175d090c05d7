"""RaceEnv's render modes: the ones this machine offers, and an error that names them and says why one is missing.

``"rgb_array"`` (a chase-camera image) works everywhere; ``"human"`` (PyBullet's GUI window) only where a display
is. Gymnasium's checkers make one env per mode in ``metadata["render_modes"]``, so an env lists only the modes this
machine offers, and the error for a mode it refuses lists the same ones.
"""

from __future__ import annotations

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
