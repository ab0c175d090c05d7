"""Training: the paper's PPO + GRU policy, curriculum and multi-scene updating (``racebench train``)."""
