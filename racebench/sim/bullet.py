"""PyBullet, imported in one place with its C-level chatter silenced.

The ``pybullet`` extension prints its build banner ("pybullet build time: ...") from C when first imported (to
stderr in the 3.2.x wheels, to stdout in some builds), and ``connect`` prints ``argv[0]=`` to stdout. Neither is
racebench's output, and ``-q`` promises only results, so every racebench module imports PyBullet from here::

    from racebench.sim.bullet import bullet_client, p
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def quiet_c_output(stderr: bool = False) -> Iterator[None]:
    """Send what C code writes to file descriptor 1 (and 2 with ``stderr``) to the null device meanwhile.

    Python-level exceptions still propagate (they are printed after the descriptors are restored). A stream
    without a real descriptor (a notebook, pytest's capture) is left alone.
    """
    streams = [sys.stdout, sys.stderr] if stderr else [sys.stdout]
    saved: list[tuple[int, int]] = []
    try:
        for stream in streams:
            try:
                stream.flush()
                fd = stream.fileno()
            except (AttributeError, OSError, ValueError):  # no real file descriptor
                continue
            saved.append((fd, os.dup(fd)))
        with open(os.devnull, "w") as devnull:
            for fd, _ in saved:
                os.dup2(devnull.fileno(), fd)
        yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


# The banner is printed once, by the first import in the process: this one, since racebench imports PyBullet
# nowhere else. stderr too: that is where the 3.2.x wheels print it (an import error still raises, shown after).
with quiet_c_output(stderr=True):
    import pybullet as p
    from pybullet_utils import bullet_client

__all__ = ["bullet_client", "p", "quiet_c_output"]


def display_available() -> bool:
    """Whether a GUI window can open here: always on macOS and Windows, with ``DISPLAY`` set elsewhere."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY"))
