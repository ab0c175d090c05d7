"""Random scenes for a track: gate perturbation, start pose and obstacles with guaranteed clearances.

Implements the paper's obstacle generator (Sec. III-C, "Obstacle Generator"): the area between two
gates is a cuboid that receives a fixed number of obstacles; obstacles keep a safety distance from
the gates and the start region, and a traversable path through every gate always exists. The path is
not assumed: :func:`find_corridor` searches it on a 3D occupancy grid (or proves a straight leg clear),
and :class:`ObstacleGenerator` redraws layouts until one passes.

Soundness of the corridor: a grid cell is free when its centre is at least ``R + h/2`` from every gate
bar, obstacle, the ground, the arena walls and the ceiling (``R`` the sphere radius, ``h`` the cell
size). Every point of the segment joining two face-adjacent free centres is within ``h/2`` of one of
them, so it is at least ``R`` from all geometry (distance is 1-Lipschitz). Straight segments are
checked the same way: samples ``s`` apart with clearance ``>= R + s/2``.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from racebench.sim.corridor import _APPROACH, CORRIDOR_MARGIN, MAX_GRID_CELLS, _plan_corridor
from racebench.sim.corridor import find_corridor as find_corridor  # re-exported: racebench.obstacles.find_corridor
from racebench.sim.scene import Obstacle, Scene, arena_bounds
from racebench.sim.track import Gate, Track
from racebench.utils.validation import check_int, check_real, interval

KINDS: tuple[str, ...] = ("cylinder", "box", "mixed")
#: Where obstacle candidates are drawn in each region: ``"band"`` (env version 3, the default) a strip along the leg
#: between the region's two gates, as wide as the track's ``obstacle_band`` says (tuned per track so that the share
#: of obstacles near the racing line matches the authors' scenes, :mod:`racebench.sim.placement`); ``"box"`` (env
#: version 2, campaign 1) the axis-aligned box of the two gate centres widened by the region's ``half_width``.
PLACEMENTS: tuple[str, ...] = ("band", "box")
#: Most obstacles per region: 4x the densest registered id (Density5) and the curriculum's 4 (the densest any config
#: or test uses is 6). At 20 the built-in tracks' regions (about 20 m^2 each outside the gate and start clearances)
#: are nearly full: box layouts are already often redrawn there.
MAX_DENSITY = 20
#: Most obstacles in one scene (``density`` x the track's obstacle regions): bounds a layout's cost before anything
#: is allocated (its candidate-pair matrices hold ``(4 x this)^2`` entries, ~20 MB each).
MAX_SCENE_OBSTACLES = 400
#: Most layouts drawn per scene before giving up (the default 200 suffices at every valid setting of the built-in
#: tracks); with MAX_SCENE_OBSTACLES it bounds a scene's time, as the former bounds its memory.
MAX_ATTEMPTS = 1000
#: Largest horizontal gate shift (m, per axis; the paper uses up to 1.0): the arena reaches 3 m past the outermost
#: gate centres, so a shifted gate's frame (0.64 m half-width) stays at least 0.36 m inside its walls.
MAX_GATE_SHIFT = 2.0
#: Largest vertical gate shift (m; the paper's is 0.3, the GateShift1.0 ids use 1.0): the arena's ceiling is 2 m
#: above the highest gate frame, so a raised frame keeps 1 m to fly over it, above the corridor check's 0.6 m.
MAX_GATE_SHIFT_Z = 1.0
_CANDIDATES_PER_OBSTACLE = 4  # candidate draws per obstacle, accepted in order (rejection sampling)
_TOUCH = 1e-6  # "does not touch": footprint distances must exceed this (m)
_CORNER_SIGNS = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])


# --------------------------------------------------------------------------- 2D footprints
@dataclass(frozen=True)
class Footprints:
    """A batch of horizontal footprints: rectangles grown by a disc (rounded rectangles).

    Attributes:
        centre: ``(n, 2)`` centres.
        half: ``(n, 2)`` half sizes along the footprint's own axes; 0 gives a segment or a point.
        yaw: ``(n,)`` headings of the first axis.
        rounding: ``(n,)`` disc radius added around the rectangle (a cylinder is a point grown by its radius).
    """

    centre: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    rounding: np.ndarray

    @cached_property
    def _frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cosines, sines and corners ``(n, 4, 2)``, computed once per batch."""
        cos, sin = np.cos(self.yaw), np.sin(self.yaw)
        local = _CORNER_SIGNS * self.half[:, None, :]
        corners = np.stack(
            [
                self.centre[:, None, 0] + cos[:, None] * local[..., 0] - sin[:, None] * local[..., 1],
                self.centre[:, None, 1] + sin[:, None] * local[..., 0] + cos[:, None] * local[..., 1],
            ],
            axis=-1,
        )
        return cos, sin, corners


def footprint_distance(a: Footprints, b: Footprints) -> np.ndarray:
    """Exact horizontal distances ``(len(a), len(b))`` between two batches of footprints (0 where they overlap)."""
    cos_a, sin_a, corners_a = a._frame
    cos_b, sin_b, corners_b = b._frame
    # disjoint convex polygons: the closest pair involves a vertex of one of them
    core = np.minimum(
        _corner_distance(corners_a[:, None], b, cos_b, sin_b, rect_axis=1),
        _corner_distance(corners_b[None, :], a, cos_a, sin_a, rect_axis=0),
    )
    # overlap without a vertex inside the other (a cross) is caught by the separating-axis test
    separated = _separated(a, cos_a, sin_a, corners_b[None, :], rect_axis=0)
    separated |= _separated(b, cos_b, sin_b, corners_a[:, None], rect_axis=1)
    core = np.where(separated, core, 0.0)
    return np.maximum(core - a.rounding[:, None] - b.rounding[None, :], 0.0)


def _corner_distance(
    corners: np.ndarray, rect: Footprints, cos: np.ndarray, sin: np.ndarray, rect_axis: int
) -> np.ndarray:
    """Smallest distance ``(A, B)`` from 4 corners ``(A or 1, B or 1, 4, 2)`` to the rectangles of ``rect``.

    ``rect`` is laid along result axis ``rect_axis`` (0: A, 1: B); its rounding is ignored here.
    """
    shape = (-1, 1, 1) if rect_axis == 0 else (1, -1, 1)
    centre = rect.centre.reshape(*shape, 2)
    c, s = cos.reshape(shape), sin.reshape(shape)
    dx, dy = corners[..., 0] - centre[..., 0], corners[..., 1] - centre[..., 1]
    ex = np.maximum(np.abs(c * dx + s * dy) - rect.half[:, 0].reshape(shape), 0.0)
    ey = np.maximum(np.abs(c * dy - s * dx) - rect.half[:, 1].reshape(shape), 0.0)
    return np.hypot(ex, ey).min(axis=-1)


def _separated(rect: Footprints, cos: np.ndarray, sin: np.ndarray, corners: np.ndarray, rect_axis: int) -> np.ndarray:
    """Whether one of ``rect``'s two axes separates it from the quadrilaterals with ``corners`` (result ``(A, B)``).

    ``rect`` is laid along result axis ``rect_axis`` (0: A, 1: B), ``corners`` along the other one.
    """
    shape = (-1, 1, 1) if rect_axis == 0 else (1, -1, 1)
    c, s = cos.reshape(shape), sin.reshape(shape)
    centre = rect.centre.reshape(*shape, 2)
    dx, dy = corners[..., 0] - centre[..., 0], corners[..., 1] - centre[..., 1]
    out = np.zeros(np.broadcast_shapes(dx.shape[:2]), dtype=bool)
    for along, half in ((c * dx + s * dy, rect.half[:, 0]), (c * dy - s * dx, rect.half[:, 1])):
        half = half.reshape(shape[:2])
        out |= (along.max(axis=-1) < -half) | (along.min(axis=-1) > half)
    return out


# --------------------------------------------------------------------------- generator
class ObstacleGenerator:
    """Draws random scenes for a track: perturbed gates, a start pose and obstacles with safe margins.

    Every scene satisfies, by construction and by explicit checks:

    * every obstacle footprint is at least ``clearance`` (horizontally) from every gate opening (the
      segment ``center +- lateral * inner / 2``), every gate centre and the whole start region box, and
      does not touch any gate frame or another obstacle;
    * the start region box is at least ``drone_radius + corridor_margin`` from every gate bar;
    * a sphere of radius ``drone_radius + corridor_margin`` can fly from the start region centre through
      every gate opening in order (:func:`find_corridor`, searched below the highest gate top plus room to
      pass over a frame, which only makes the guarantee stronger).

    Candidates are drawn per region (``density`` obstacles each) where ``placement`` says (:data:`PLACEMENTS`):
    ``"band"``, a strip along the region's leg shaped by the track's ``obstacle_band`` (and inside the arena), or
    ``"box"``, the env-version-2 box of the two gate centres.

    Layouts failing a check are redrawn; :attr:`rejections` counts why. Obstacle sizes are drawn from
    the discrete ``radius_choices`` / ``box_half_choices`` on purpose: the simulator keeps a pool of
    pre-built bodies per shape.
    """

    def __init__(
        self,
        track: Track,
        density: int = 3,
        kind: str = "cylinder",
        gate_shift: float = 0.0,
        clearance: float = 0.5,
        gate_shift_z: float | None = None,
        drone_radius: float = 0.12,
        corridor_margin: float = CORRIDOR_MARGIN,
        pole_height: float = 3.0,
        radius_choices: tuple[float, ...] = (0.05, 0.075, 0.1, 0.125, 0.15),
        box_half_choices: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25),
        grid_resolution: float = 0.1,
        max_attempts: int = 200,
        placement: str = "band",
    ) -> None:
        """Validate the settings; see the class docstring. Raises ``ValueError`` naming a bad parameter."""
        if not isinstance(track, Track):
            raise ValueError(f"track must be a racebench Track, got {type(track).__name__}")
        # Every bound is checked before anything is allocated: a layout's memory and time follow from them.
        check_int("density", density, 0, MAX_DENSITY)
        regions = len(track.obstacle_regions)
        if density * regions > MAX_SCENE_OBSTACLES:
            most = MAX_SCENE_OBSTACLES // regions
            raise ValueError(
                f"density must be at most {most} on track {track.name!r} ({regions} obstacle regions, at most "
                f"{MAX_SCENE_OBSTACLES} obstacles per scene), got {density!r}"
            )
        check_int("max_attempts", max_attempts, 1, MAX_ATTEMPTS)
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        if placement not in PLACEMENTS:
            raise ValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        check_real("gate_shift", gate_shift, 0.0, MAX_GATE_SHIFT, unit="m")
        if gate_shift_z is None and gate_shift > MAX_GATE_SHIFT_Z:
            raise ValueError(
                f"gate_shift_z must be in {interval(0.0, MAX_GATE_SHIFT_Z, unit='m')} (it defaults to gate_shift: "
                f"pass gate_shift_z), got {gate_shift!r}"
            )
        if gate_shift_z is not None:
            check_real("gate_shift_z", gate_shift_z, 0.0, MAX_GATE_SHIFT_Z, unit="m")
        for name, value, positive in (
            ("clearance", clearance, False),
            ("drone_radius", drone_radius, True),
            ("corridor_margin", corridor_margin, False),
            ("pole_height", pole_height, True),
            ("grid_resolution", grid_resolution, True),
        ):
            check_real(name, value, 0.0, math.inf, unit="m", low_open=positive)
        for name, choices in (("radius_choices", radius_choices), ("box_half_choices", box_half_choices)):
            values = np.asarray(choices, dtype=float) if isinstance(choices, (tuple, list)) else np.array([])
            if values.ndim != 1 or len(values) == 0 or not np.all(np.isfinite(values)) or np.any(values <= 0):
                raise ValueError(f"{name} must be a non-empty tuple of positive numbers, got {choices!r}")
        arena_low, arena_high = arena_bounds(track)
        cells = math.prod(max(math.floor(float(v) / grid_resolution), 0) for v in arena_high - arena_low)
        if cells > MAX_GRID_CELLS:
            raise ValueError(
                f"grid_resolution must keep the corridor grid of track {track.name!r} within {MAX_GRID_CELLS} cells, "
                f"got {grid_resolution!r} m ({cells} cells)"
            )
        opening = min(g.inner for g in track.gates) / 2.0
        if drone_radius + corridor_margin >= opening:  # no corridor could pass a gate: every layout would fail
            raise ValueError(
                f"drone_radius must be < {opening - corridor_margin:g} m (plus corridor_margin {corridor_margin:g} m, "
                f"within half the {2 * opening:g} m gate opening of track {track.name!r}), got {drone_radius!r}"
            )
        self.track = track
        self.density = int(density)
        self.kind = kind
        self.placement = placement
        self.gate_shift = float(gate_shift)
        self.gate_shift_z = self.gate_shift if gate_shift_z is None else float(gate_shift_z)
        self.clearance = float(clearance)
        self.drone_radius = float(drone_radius)
        self.corridor_margin = float(corridor_margin)
        self.pole_height = float(pole_height)
        self.radius_choices = tuple(float(v) for v in radius_choices)
        self.box_half_choices = tuple(float(v) for v in box_half_choices)
        self.grid_resolution = float(grid_resolution)
        self.max_attempts = int(max_attempts)
        self.arena_low, self.arena_high = arena_low, arena_high
        self.rejections: Counter[str] = Counter()  # why layouts were redrawn, summed over all calls
        self._start_clear_of_track_gates: bool | None = None
        # A start region no gate shift can clear of the frames would have every layout rejected at reset: refuse it
        # now. Bars move with their gate, by at most hypot(sqrt(2) gate_shift, gate_shift_z).
        reach = math.hypot(math.sqrt(2.0) * self.gate_shift, self.gate_shift_z)
        bars = Scene(track, track.gates, (), track.start.center, 0.0, self.arena_low, self.arena_high)
        room = float(bars.distance(track.start.center)) + reach - self.corridor_radius
        if float(np.linalg.norm(track.start.spread)) > room:
            raise ValueError(
                f"start_spread must keep the start region {self.corridor_radius:g} m from the gate frames of track "
                f"{track.name!r} (a half-diagonal of at most {room:.3g} m), got {track.start.spread.tolist()}"
            )

    @property
    def corridor_radius(self) -> float:
        """Radius of the sphere that must fit through the guaranteed corridor (drone + margin)."""
        return self.drone_radius + self.corridor_margin

    def sample_scene(self, np_random: np.random.Generator) -> Scene:
        """Draw one scene; all randomness comes from ``np_random``, so a seeded generator fixes the scene.

        Obstacles are listed region by region, ``density`` per entry of ``track.obstacle_regions``.
        Raises ``RuntimeError`` when ``max_attempts`` layouts in a row fail the checks.
        """
        track = self.track
        radius = self.corridor_radius
        rejected: Counter[str] = Counter()
        for _ in range(self.max_attempts):
            gates = self._perturb_gates(np_random)
            spread = track.start.spread
            start = np_random.uniform(track.start.center - spread, track.start.center + spread)
            if not self._start_clear_of_gates(gates):
                rejected["start_near_gate"] += 1
                continue
            obstacles = self._place_obstacles(np_random, gates)
            if obstacles is None:
                rejected["placement"] += 1
                continue
            scene = Scene(
                track=track,
                gates=gates,
                obstacles=obstacles,
                start_position=start,
                start_yaw=track.start.yaw,
                arena_low=self.arena_low.copy(),
                arena_high=self.arena_high.copy(),
            )
            # room to fly over the highest frame is enough: the poles are vertical, height does not help
            ceiling = max(g.center[2] + g.outer / 2.0 for g in gates) + 2.0 * (radius + self.grid_resolution)
            legs = _plan_corridor(scene, radius, self.grid_resolution, None, _APPROACH, ceiling, need_path=False)
            if legs is not None:
                self.rejections.update(rejected)
                return scene
            rejected["corridor"] += 1
        self.rejections.update(rejected)
        raise RuntimeError(
            f"ObstacleGenerator: no valid layout for track {track.name!r} in {self.max_attempts} attempts "
            f"(density={self.density}, kind={self.kind!r}, gate_shift={self.gate_shift}, clearance={self.clearance}, "
            f"corridor radius={radius}); rejected layouts: {dict(rejected)}. "
            "Lower the density, clearance or gate_shift, or raise max_attempts."
        )

    def _perturb_gates(self, rng: np.random.Generator) -> tuple[Gate, ...]:
        """Shift each gate by up to ``gate_shift`` on x/y and ``gate_shift_z`` on z, keeping its frame above the
        ground."""
        gates = self.track.gates
        delta, delta_z = self.gate_shift, self.gate_shift_z
        if delta == 0.0 and delta_z == 0.0:
            return gates
        shift_xy = rng.uniform(-delta, delta, size=(len(gates), 2))
        unit = rng.uniform(0.0, 1.0, size=len(gates))
        moved = []
        for gate, dxy, u in zip(gates, shift_xy, unit, strict=True):
            z = float(gate.center[2])
            # a track gate lower than outer/2 + 0.1 keeps its own height as the lowest option
            z_low = max(z - delta_z, min(z, gate.outer / 2.0 + 0.1))
            moved.append(
                gate.moved(
                    np.array([gate.center[0] + dxy[0], gate.center[1] + dxy[1], z_low + u * (z + delta_z - z_low)])
                )
            )
        return tuple(moved)

    def _start_clear_of_gates(self, gates: tuple[Gate, ...]) -> bool:
        """Whether the whole start box is ``corridor_radius`` from every bar (centre bound: half-diagonal)."""
        if gates is self.track.gates and self._start_clear_of_track_gates is not None:
            return self._start_clear_of_track_gates  # unperturbed gates: the answer never changes
        bars = Scene(self.track, gates, (), self.track.start.center, 0.0, self.arena_low, self.arena_high)
        half_diagonal = float(np.linalg.norm(self.track.start.spread))
        clear = float(bars.distance(self.track.start.center)) >= half_diagonal + self.corridor_radius
        if gates is self.track.gates:
            self._start_clear_of_track_gates = clear
        return clear

    def _place_obstacles(self, rng: np.random.Generator, gates: tuple[Gate, ...]) -> tuple[Obstacle, ...] | None:
        """``density`` obstacles per region meeting the clearance rules, or ``None`` if a region cannot be filled."""
        regions = self.track.obstacle_regions
        if self.density == 0 or not regions:
            return ()
        n = self.density * _CANDIDATES_PER_OBSTACLE
        # candidates of all regions are drawn up front and checked in one vectorised pass
        xy, is_box, half, radius, yaw = [], [], [], [], []
        band = self.track.obstacle_band
        for region in regions:
            a, b = gates[region.between[0]].center[:2], gates[region.between[1]].center[:2]
            if self.placement == "box":
                lo, hi = np.minimum(a, b) - region.half_width, np.maximum(a, b) + region.half_width
                xy.append(rng.uniform(lo, hi, size=(n, 2)))
            else:  # a strip along the leg: the racing line runs down its middle, as in the authors' scenes
                leg = b - a
                length = float(np.hypot(leg[0], leg[1]))
                along = leg / length
                across = np.array([-along[1], along[0]])
                margin = min(band.end_margin, length / 2.0)
                t = rng.uniform(margin, length - margin, size=n)
                s = rng.uniform(-1.0, 1.0, size=n)
                u = band.half_width * np.sign(s) * np.abs(s) ** band.profile
                xy.append(a + t[:, None] * along + u[:, None] * across)
            if self.kind == "mixed":
                is_box.append(rng.uniform(size=n) < 0.5)
            else:
                is_box.append(np.full(n, self.kind == "box"))
            radius.append(rng.choice(self.radius_choices, size=n))
            half.append(rng.choice(self.box_half_choices, size=(n, 2)))
            yaw.append(rng.uniform(-math.pi, math.pi, size=n))
        xy, is_box = np.concatenate(xy), np.concatenate(is_box)
        half = np.where(is_box[:, None], np.concatenate(half), 0.0)
        rounding = np.where(is_box, 0.0, np.concatenate(radius))
        yaw = np.where(is_box, np.concatenate(yaw), 0.0)

        targets, t_min = self._targets(gates)
        dist = footprint_distance(Footprints(xy, half, yaw, rounding), targets)
        valid = np.all(dist >= t_min, axis=1)
        # obstacles keep apart by their circumscribed circles (conservative, cheap)
        reach = np.where(is_box, np.hypot(half[:, 0], half[:, 1]), rounding)
        if self.placement == "band":  # a wide strip along a shifted leg can reach past the arena's walls
            low, high = self.arena_low[:2], self.arena_high[:2]
            valid &= np.all((xy - reach[:, None] > low) & (xy + reach[:, None] < high), axis=1)
        gap = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
        conflict = gap <= reach[:, None] + reach[None, :] + _TOUCH
        available = valid.copy()
        height = self.pole_height
        obstacles = []
        for r in range(len(regions)):
            count = 0
            for i in range(r * n, (r + 1) * n):
                if count == self.density:
                    break
                if not available[i]:
                    continue
                available &= ~conflict[i]  # later candidates must keep clear of this one
                count += 1
                position = np.array([xy[i, 0], xy[i, 1], height / 2.0])
                if is_box[i]:
                    size = (float(half[i, 0]), float(half[i, 1]), height / 2.0)
                    obstacles.append(Obstacle("box", position, size, float(yaw[i])))
                else:
                    obstacles.append(Obstacle("cylinder", position, (float(rounding[i]), height)))
            if count < self.density:
                return None
        return tuple(obstacles)

    def _targets(self, gates: tuple[Gate, ...]) -> tuple[Footprints, np.ndarray]:
        """Footprints obstacles must keep away from, with the minimum distance to each."""
        centre, half, yaw, minimum = [], [], [], []
        for g in gates:
            centre += [g.center[:2]] * 3
            half += [(0.0, g.inner / 2.0), (0.0, 0.0), (g.depth / 2.0, g.outer / 2.0)]  # opening, centre, frame
            yaw += [g.yaw] * 3
            minimum += [self.clearance, self.clearance, _TOUCH]
        start = self.track.start
        centre.append(start.center[:2])
        half.append(start.spread[:2])
        yaw.append(0.0)
        minimum.append(self.clearance)
        targets = Footprints(np.array(centre), np.array(half, dtype=float), np.array(yaw), np.zeros(len(yaw)))
        return targets, np.array(minimum)
