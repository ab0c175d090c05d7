"""The Gymnasium environments on the simulator: :class:`~racebench.envs.env.RaceEnv`, its reward, the batched
vector env, the SB3 adapter, the registered ids and the lap-time bound."""
