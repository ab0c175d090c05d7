"""The policy network, under the module path that SB3 checkpoints pickled it by.

The network moved to :mod:`racebench.agents.recurrent` (below both training, which builds it, and loading, which
unpickles it). Every committed checkpoint names ``racebench.training.policies.RecurrentGRUPolicy`` and
``racebench.training.policies.RaceFeatures``, so they stay importable here (``tests/test_checkpoints.py``).
"""

from racebench.agents.recurrent import (
    ACTION_OUTPUTS,
    CNN_KINDS,
    LSTMShapedGRU,
    MixtureActionHead,
    RaceFeatures,
    RecurrentGRUPolicy,
    depth_cnn,
    mixture_action_loss,
)

__all__ = [
    "ACTION_OUTPUTS",
    "CNN_KINDS",
    "LSTMShapedGRU",
    "MixtureActionHead",
    "RaceFeatures",
    "RecurrentGRUPolicy",
    "depth_cnn",
    "mixture_action_loss",
]
