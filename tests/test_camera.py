"""Depth camera: the z-buffer is linearised to metric depth along the optical axis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from racebench.sim.camera import DepthCamera
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.scene import Obstacle, Scene, arena_bounds
from racebench.sim.simulation import Simulation
from racebench.sim.track import load_track

TRACK = load_track("S")


def world_with(obstacles: tuple[Obstacle, ...], gates=None) -> Simulation:
    sim = Simulation(TRACK, QuadrotorParams(), 200)
    low, high = arena_bounds(TRACK)
    far_gates = tuple(g.moved(g.center + np.array([0.0, 50.0, 0.0])) for g in TRACK.gates)
    scene = Scene(TRACK, gates or far_gates, obstacles, np.array([0.0, 0.0, 1.0]), 0.0, low, high)
    sim.load_scene(scene)
    return sim


def yaw_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("distance", [0.5, 1.4, 4.0, 9.0])
@pytest.mark.parametrize("yaw", [0.0, math.pi / 2])
def test_fronto_parallel_wall_reads_constant_depth(distance: float, yaw: float) -> None:
    # A wall facing the camera has the same depth along the optical axis at every pixel.
    rot = yaw_rotation(yaw)
    camera = DepthCamera()
    eye_height = 1.5
    wall_centre = np.array([distance + 0.5, 0.0, eye_height]) @ rot.T * np.array([1, 1, 0]) + [0, 0, eye_height]
    wall = Obstacle("box", wall_centre, (0.5, 30.0, 15.0), yaw=yaw)
    sim = world_with((wall,))
    body = np.array([-0.1, 0.0, 0.0]) @ rot.T + [0.0, 0.0, eye_height]  # camera sits 0.1 m ahead of the body
    depth = camera.depth(sim.client, body, rot)
    upper = depth[:30]  # the ground is never above the horizon
    np.testing.assert_allclose(upper, distance, rtol=2e-3)
    sim.close()


def test_ground_depth_matches_pinhole_geometry() -> None:
    camera = DepthCamera()
    sim = world_with(())
    height = 1.0
    depth = camera.depth(sim.client, np.array([-0.1, 0.0, height]), np.eye(3))
    f = camera.focal_px
    rows = np.arange(40, 64)
    # TinyRenderer samples row i at (i + 1 − size/2) pixels below the optical axis.
    expected = np.minimum(height * f / (rows + 1 - camera.size / 2), camera.max_depth)
    np.testing.assert_allclose(depth[rows, 32], expected, rtol=5e-3)
    assert np.all(depth[:31] == camera.max_depth)  # sky: nothing within range
    sim.close()


def test_range_limits_and_normalisation() -> None:
    camera = DepthCamera()
    too_close = world_with((Obstacle("box", np.array([0.15, 0.0, 1.5]), (0.05, 30.0, 15.0)),))
    depth = camera.depth(too_close.client, np.array([-0.1, 0.0, 1.5]), np.eye(3))
    assert np.all(depth == camera.min_depth)
    inv = camera.normalise(depth)
    assert inv.shape == (1, 64, 64) and inv.dtype == np.float32 and np.all(inv == 1.0)
    far = camera.normalise(np.full((64, 64), camera.max_depth, dtype=np.float32))
    np.testing.assert_allclose(far, camera.min_depth / camera.max_depth)
    too_close.close()


def test_noise_is_gaussian_with_the_configured_sigma() -> None:
    camera = DepthCamera(noise_std=0.05)
    depth = np.full((64, 64), 1.0, dtype=np.float32)  # normalised 0.2, far from the clip bounds
    samples = np.stack([camera.normalise(depth, np.random.default_rng(i)) for i in range(20)])
    assert samples.mean() == pytest.approx(0.2, abs=2e-3)
    assert samples.std() == pytest.approx(0.05, rel=0.03)


def test_gate_opening_is_seen_through() -> None:
    camera = DepthCamera()
    gate = TRACK.gates[0].moved(np.array([2.0, 0.0, 1.0]))
    far_gates = (gate,) + tuple(g.moved(g.center + np.array([0.0, 50.0, 0.0])) for g in TRACK.gates[1:])
    sim = world_with((), gates=far_gates)
    depth = camera.depth(sim.client, np.array([-0.1, 0.0, 1.0]), np.eye(3))
    # Centre pixels look through the opening (nothing behind), the frame is at 2 − depth/2 m.
    assert np.all(depth[26:31, 28:36] == camera.max_depth)
    bar_column = depth[30:34, :].min(axis=0)
    assert bar_column.min() == pytest.approx(2.0 - gate.depth / 2, rel=5e-3)
    sim.close()
