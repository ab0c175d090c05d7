"""PyBullet world of one environment: ground, drone body, gate frames and a pool of obstacle bodies.

One ``BulletClient`` (``p.DIRECT``; ``p.GUI`` for ``render_mode="human"``, same physics) per environment.
The world is built once; a new episode's scene is loaded by moving bodies with
``resetBasePositionAndOrientation``. Obstacle bodies are pooled by shape
(the obstacle generator quantises sizes), unused ones are parked far below the arena.

The per-physics-step path (:meth:`Simulation.step_raw`) calls the ``pybullet``
functions directly with the client id and plain tuples: ``BulletClient.__getattr__`` builds a
``functools.partial`` on every call, and numpy arrays of 3 or 4 numbers cost more to make and convert than
the arithmetic on them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from racebench.sim.bullet import bullet_client, display_available, p, quiet_c_output
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.scene import Scene
from racebench.sim.track import Gate, Track

_PARK_Z = -100.0  # unused obstacle bodies wait here, out of sight and out of reach
_GATE_RGBA = [0.95, 0.45, 0.05, 1.0]
_OBSTACLE_RGBA = [0.35, 0.35, 0.8, 1.0]


Vec3 = tuple[float, float, float]
# (position, quaternion x y z w, linear velocity, angular velocity), world frame, as PyBullet returns them.
RawState = tuple[Vec3, tuple[float, float, float, float], Vec3, Vec3]


class DroneState(NamedTuple):
    """Kinematic state of the drone, world frame unless said otherwise."""

    position: np.ndarray  # m
    quaternion: np.ndarray  # x, y, z, w (body → world)
    rotation: np.ndarray  # 3×3 body → world
    velocity: np.ndarray  # m/s
    angular_velocity: np.ndarray  # rad/s, world frame

    @property
    def body_rates(self) -> np.ndarray:
        """Angular velocity in the body frame, rad/s."""
        return self.rotation.T @ self.angular_velocity

    @classmethod
    def from_raw(cls, raw: RawState) -> DroneState:
        """Arrays from PyBullet's tuples (the rotation from PyBullet's own quaternion-to-matrix conversion)."""
        pos, quat, vel, ang = raw
        rot = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return cls(np.array(pos), np.array(quat), rot, np.array(vel), np.array(ang))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """PyBullet (x, y, z, w) quaternion of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


_NO_COPY = (
    "{what} cannot be copied or pickled: it owns a PyBullet connection that a copy would share (and disconnect "
    "when garbage-collected). Make a new env with gym.make(env.spec) instead; for the same scene, "
    "new_env.reset(options={{'scene': env.unwrapped.scene}})"
)


class _Uncopyable:
    """Refuses ``copy.copy``, ``copy.deepcopy`` and pickling with a TypeError, as
    :class:`~racebench.envs.env.RaceEnv` does.

    A copy of an object holding a PyBullet client id would share the connection, and the copy's clean-up (or
    ``BulletClient.__del__``) would disconnect the original's physics server.
    """

    def __getstate__(self) -> None:
        """Refuse pickling (a client id means nothing in another process, and a copy would share it)."""
        raise TypeError(_NO_COPY.format(what=f"a racebench {type(self).__name__}"))

    def __reduce_ex__(self, protocol: int) -> None:
        """Refuse pickling and copying at the one entry both go through."""
        raise TypeError(_NO_COPY.format(what=f"a racebench {type(self).__name__}"))

    def __copy__(self) -> None:
        """Refuse shallow copies."""
        raise TypeError(_NO_COPY.format(what=f"a racebench {type(self).__name__}"))

    def __deepcopy__(self, memo: dict) -> None:
        """Refuse deep copies."""
        raise TypeError(_NO_COPY.format(what=f"a racebench {type(self).__name__}"))


class RaceBulletClient(_Uncopyable, bullet_client.BulletClient):
    """PyBullet's ``BulletClient`` that refuses to be copied or pickled (see :class:`_Uncopyable`)."""


def _gui_client() -> RaceBulletClient:
    """A client with PyBullet's GUI window, or a RuntimeError that says why there is none."""
    if not display_available():
        raise RuntimeError(
            "render_mode='human' opens PyBullet's GUI window and needs a display: DISPLAY is not set "
            "(on a headless machine run under xvfb-run, or use render_mode='rgb_array')"
        )
    why = "PyBullet allows one GUI window per process: close the other human-mode env first"
    try:
        client = RaceBulletClient(connection_mode=p.GUI)
    except p.error as exc:
        raise RuntimeError(f"render_mode='human': PyBullet could not open its GUI ({exc}); {why}") from exc
    if client._client < 0:  # a second GUI connection is refused with a printed message, not an exception
        client._client = -1
        raise RuntimeError(f"render_mode='human': PyBullet could not open its GUI; {why}")
    client.configureDebugVisualizer(p.COV_ENABLE_GUI, 0)  # the scene alone, without PyBullet's side panels
    return client


class Simulation(_Uncopyable):
    """The physics world of one :class:`~racebench.envs.env.RaceEnv`.

    Args:
        track: the track whose gates are built (their poses change per episode).
        params: airframe of the drone (mass, inertia, collision radius).
        physics_freq: physics rate in Hz.
        gui: open PyBullet's GUI window (needs a display; one per process) instead of the headless client.
    """

    def __init__(self, track: Track, params: QuadrotorParams, physics_freq: int, gui: bool = False) -> None:
        if gui:
            self.client = _gui_client()
        else:
            with quiet_c_output():  # connect prints argv[0]= to stdout
                self.client = RaceBulletClient(connection_mode=p.DIRECT)
        c = self.client
        c.setGravity(0.0, 0.0, -params.gravity)
        c.setTimeStep(1.0 / physics_freq)
        # Contacts end the episode, so a few solver iterations suffice; deterministic pair order keeps
        # episodes bit-identical whatever happened before in this client.
        c.setPhysicsEngineParameter(numSolverIterations=10, deterministicOverlappingPairs=1)

        self.ground = c.createMultiBody(
            baseMass=0.0,
            baseCollisionShapeIndex=c.createCollisionShape(p.GEOM_PLANE),
            baseVisualShapeIndex=c.createVisualShape(
                p.GEOM_BOX,
                halfExtents=[100.0, 100.0, 0.005],
                rgbaColor=[0.75, 0.75, 0.75, 1.0],
                visualFramePosition=[0.0, 0.0, -0.005],
            ),
        )
        r = params.collision_radius
        self.drone = c.createMultiBody(
            baseMass=params.mass,
            baseCollisionShapeIndex=c.createCollisionShape(p.GEOM_SPHERE, radius=r),
            # A flat visual body inside the sphere: behind the depth camera, so it never occludes it.
            baseVisualShapeIndex=c.createVisualShape(
                p.GEOM_BOX, halfExtents=[0.08, 0.08, 0.02], rgbaColor=[0.8, 0.1, 0.1, 1.0]
            ),
            basePosition=[0.0, 0.0, 1.0],
        )
        c.changeDynamics(
            self.drone, -1, localInertiaDiagonal=list(params.inertia), linearDamping=0.0, angularDamping=0.0
        )
        # No collision response for the drone: Bullet resolves hits at a small positive distance and lets the
        # drone bounce on; every touch is decided from the scene's exact geometry instead (racebench.sim.collision).
        c.setCollisionFilterGroupMask(self.drone, -1, 0, 0)
        self.gates = [self._build_gate(g) for g in track.gates]
        first = track.gates[0]  # a track's gates share one size (its file's gate_size)
        self._gate_bodies = {(first.inner, first.outer, first.depth): list(self.gates)}  # by size: fit_gates
        self._pool: dict[tuple, list[int]] = {}
        self._active: list[int] = []
        self._cid = c._client  # the raw client id, for direct pybullet calls on the hot path
        self._raw: RawState = self._read_state()

    def _build_gate(self, gate) -> int:
        c = self.client
        bars = gate.bars()
        kwargs = dict(
            halfExtents=[h.tolist() for _, h in bars],
            shapeTypes=[p.GEOM_BOX] * len(bars),
        )
        positions = [b.tolist() for b, _ in bars]
        collision = c.createCollisionShapeArray(collisionFramePositions=positions, **kwargs)
        visual = c.createVisualShapeArray(visualFramePositions=positions, rgbaColors=[_GATE_RGBA] * len(bars), **kwargs)
        return c.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=collision, baseVisualShapeIndex=visual, useMaximalCoordinates=True
        )

    def _obstacle_body(self, key: tuple, index: int) -> int:
        pool = self._pool.setdefault(key, [])
        while len(pool) <= index:
            c = self.client
            kind, size = key
            if kind == "cylinder":
                shape = dict(shapeType=p.GEOM_CYLINDER, radius=size[0])
                col = c.createCollisionShape(height=size[1], **shape)
                vis = c.createVisualShape(length=size[1], rgbaColor=_OBSTACLE_RGBA, **shape)
            else:
                shape = dict(shapeType=p.GEOM_BOX, halfExtents=list(size))
                col = c.createCollisionShape(**shape)
                vis = c.createVisualShape(rgbaColor=_OBSTACLE_RGBA, **shape)
            body = c.createMultiBody(
                baseMass=0.0,
                baseCollisionShapeIndex=col,
                baseVisualShapeIndex=vis,
                basePosition=[0.0, 0.0, _PARK_Z],
                useMaximalCoordinates=True,
            )
            pool.append(body)
        return pool[index]

    def fit_gates(self, gates: Sequence[Gate]) -> None:
        """Use one gate body per gate of ``gates`` from now on, for a track of another gate count (its gates all of
        one size): bodies are built once per size and count, and those not in use are parked out of reach."""
        sizes = {(g.inner, g.outer, g.depth) for g in gates}
        if len(sizes) != 1:
            raise ValueError(f"fit_gates needs gates of one size, got {sorted(sizes)}")
        size = sizes.pop()
        pool = self._gate_bodies.setdefault(size, [])
        while len(pool) < len(gates):
            pool.append(self._build_gate(gates[len(pool)]))
        used = pool[: len(gates)]
        for body in set(self.gates) - set(used):
            self.client.resetBasePositionAndOrientation(body, [0.0, 0.0, _PARK_Z], (0.0, 0.0, 0.0, 1.0))
        self.gates = used

    def load_scene(self, scene: Scene) -> None:
        """Move gates and obstacles to the poses of ``scene`` (creating pooled bodies only when new)."""
        c = self.client
        if len(scene.gates) != len(self.gates):
            raise ValueError(f"scene has {len(scene.gates)} gates, this track has {len(self.gates)}")
        for body, gate in zip(self.gates, scene.gates, strict=True):
            c.resetBasePositionAndOrientation(body, gate.center.tolist(), yaw_quaternion(gate.yaw))
        used: dict[tuple, int] = {}
        active = []
        for obs in scene.obstacles:
            key = (obs.kind, tuple(round(float(s), 6) for s in obs.size))
            body = self._obstacle_body(key, used.get(key, 0))
            used[key] = used.get(key, 0) + 1
            c.resetBasePositionAndOrientation(body, obs.position.tolist(), yaw_quaternion(obs.yaw))
            active.append(body)
        for body in set(self._active) - set(active):
            c.resetBasePositionAndOrientation(body, [0.0, 0.0, _PARK_Z], (0.0, 0.0, 0.0, 1.0))
        self._active = active

    def reset_drone(self, position: np.ndarray, yaw: float, velocity: np.ndarray | None = None) -> None:
        """Put the drone level at ``position`` with heading ``yaw``, at rest or moving at ``velocity`` (m/s)."""
        c = self.client
        c.resetBasePositionAndOrientation(self.drone, position.tolist(), yaw_quaternion(yaw))
        linear = [0.0, 0.0, 0.0] if velocity is None else [float(v) for v in velocity]
        c.resetBaseVelocity(self.drone, linear, [0.0, 0.0, 0.0])
        self._raw = self._read_state()

    def _read_state(self) -> RawState:
        pos, quat = p.getBasePositionAndOrientation(self.drone, self._cid)
        vel, ang = p.getBaseVelocity(self.drone, self._cid)
        return pos, quat, vel, ang

    @property
    def raw_state(self) -> RawState:
        """The drone's state as PyBullet's tuples ``(position, quaternion, velocity, angular velocity)``."""
        return self._raw

    def drone_state(self) -> DroneState:
        """The drone's current kinematic state (read from PyBullet, so it also sees bodies moved directly)."""
        self._raw = self._read_state()
        return DroneState.from_raw(self._raw)

    def step_raw(self, force_world: Vec3, torque_world: Vec3, position: Vec3) -> RawState:
        """Apply a world-frame force at ``position`` (the centre of mass) and a world-frame torque, step once.

        Returns the new state (also kept as :attr:`raw_state`).
        """
        cid, drone = self._cid, self.drone
        # World-frame application on purpose: PyBullet's LINK_FRAME torque on a base is unreliable.
        p.applyExternalForce(drone, -1, force_world, position, p.WORLD_FRAME, cid)
        p.applyExternalTorque(drone, -1, torque_world, p.WORLD_FRAME, cid)
        p.stepSimulation(cid)
        pos, quat = p.getBasePositionAndOrientation(drone, cid)
        vel, ang = p.getBaseVelocity(drone, cid)
        self._raw = (pos, quat, vel, ang)
        return self._raw

    def step(self, force_world: np.ndarray, torque_world: np.ndarray, position: np.ndarray) -> None:
        """Apply a world-frame force at the centre of mass and a world-frame torque, then step once."""
        self.step_raw(tuple(force_world.tolist()), tuple(torque_world.tolist()), tuple(position.tolist()))

    def chase_image(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """A 320×240 RGB image from a camera 2.5 m behind and 1.2 m above a drone at ``position``, ``rotation``."""
        pos, rot = position, rotation
        heading = rot[:, 0].copy()
        heading[2] = 0.0
        norm = np.linalg.norm(heading)
        heading = heading / norm if norm > 1e-6 else np.array([1.0, 0.0, 0.0])
        eye = pos - 2.5 * heading + np.array([0.0, 0.0, 1.2])
        c = self.client
        view = c.computeViewMatrix(eye.tolist(), pos.tolist(), [0.0, 0.0, 1.0])
        proj = c.computeProjectionMatrixFOV(70.0, 320 / 240, 0.05, 60.0)
        _, _, rgba, _, _ = c.getCameraImage(
            320,
            240,
            viewMatrix=view,
            projectionMatrix=proj,
            renderer=p.ER_TINY_RENDERER,
            flags=p.ER_NO_SEGMENTATION_MASK,
            shadow=0,
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(240, 320, 4)[:, :, :3].copy()

    def close(self) -> None:
        """Disconnect the PyBullet client."""
        try:
            self.client.disconnect()
        except p.error:
            pass
        self.client._client = -1  # so BulletClient.__del__ does not disconnect again at interpreter exit
