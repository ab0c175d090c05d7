"""racebench: a benchmark for vision-based quadrotor racing through gates among random obstacles.

``import racebench`` registers every Gymnasium id in :data:`ENV_IDS`, e.g. ``gym.make("RaceObs-S-v0")``.
"""

from racebench.registration import ENV_IDS, ENV_VERSION, register_envs

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "ENV_VERSION", "__version__"]

register_envs()
