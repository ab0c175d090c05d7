"""The simulator: PyBullet, the quadrotor's dynamics, tracks, scenes and obstacles, collisions, cameras, ray casting.

It knows no episodes, rewards or agents (:mod:`racebench.envs` builds those on it).
"""
