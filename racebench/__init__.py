"""racebench: a benchmark for vision-based quadrotor racing through gates among random obstacles.

``import racebench`` registers every Gymnasium id in :data:`ENV_IDS`, e.g. ``gym.make("RaceObs-S-v0")``.
"""

import os

# Before anything loads torch's OpenMP runtime, which reads this once: idle OpenMP threads sleep instead of
# spinning. With 2 torch threads on 2 cores and any other busy process, spinning threads wait at every barrier for
# a descheduled peer: one PPO update took 28.7 s instead of 1.2 s (docs/training.md, "Threads"). Idle, it costs nothing
# measurable. A value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from racebench import compat  # noqa: E402
from racebench.envs.registration import ENV_IDS, ENV_VERSION, register_envs  # noqa: E402

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "ENV_VERSION", "__version__"]

compat.install()
register_envs()
