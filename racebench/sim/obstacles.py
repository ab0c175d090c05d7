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

import heapq
import math
from collections import Counter
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage

from racebench.sim.scene import Obstacle, Scene, arena_bounds
from racebench.sim.track import Gate, Track
from racebench.utils.validation import check_int, check_real, interval

KINDS: tuple[str, ...] = ("cylinder", "box", "mixed")
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
#: Most cells of the corridor grid over the arena (16.8 M: a 67 MB label array); the built-in tracks at the
#: default 0.1 m resolution need 0.6-0.9 M.
MAX_GRID_CELLS = 1 << 24
#: Default margin (m) added to the drone's collision radius for the guaranteed corridor.
CORRIDOR_MARGIN = 0.08

_SIX = ndimage.generate_binary_structure(3, 1)  # face-adjacent cells only: the soundness argument needs it
_APPROACH = 0.25  # gate passages run this far before and after the gate plane (m)
_SEGMENT_STEP = 0.05  # sample spacing when proving a straight segment clear (m)
_LEG_MARGIN = 1.0  # margin of the local grid around one leg before falling back to the whole arena (m)
_CANDIDATES_PER_OBSTACLE = 4  # candidate draws per obstacle, accepted in order (rejection sampling)
_TOUCH = 1e-6  # "does not touch": footprint distances must exceed this (m)
_SNAP_OFFSETS = np.stack(np.meshgrid(*[np.arange(-1, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
_CORNER_SIGNS = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])


# --------------------------------------------------------------------------- corridor search
def find_corridor(
    scene: Scene,
    radius: float,
    resolution: float = 0.1,
    *,
    start: np.ndarray | None = None,
    approach: float = _APPROACH,
    ceiling: float | None = None,
) -> np.ndarray | None:
    """A collision-free path for a sphere of ``radius`` from the start through every gate opening in order.

    The path starts at ``start`` (default: the centre of the track's start region), passes each gate
    ``i`` along the straight segment from ``c_i - approach * n_i`` to ``c_i + approach * n_i`` (through
    the opening, along the normal) and ends at the last gate's exit point; a closed loop is one lap.
    Between gates it is a straight leg when that is provably clear, otherwise a path on an occupancy grid
    of cell size ``resolution``. Every point of the returned ``(N, 3)`` polyline is at least ``radius``
    from all gate bars and obstacles, above the ground by ``radius`` and ``radius`` inside the arena walls
    and below ``ceiling`` (default: the arena top). Returns ``None`` when no such path exists on the grid.
    """
    legs = _plan_corridor(scene, radius, resolution, start, approach, ceiling, need_path=True)
    if legs is None:
        return None
    points = np.concatenate(legs)
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(points, axis=0)) > 1e-12, axis=1)  # drop repeated junction points
    return points[keep]


def _plan_corridor(
    scene: Scene,
    radius: float,
    resolution: float,
    start: np.ndarray | None,
    approach: float,
    ceiling: float | None,
    need_path: bool,
) -> list[np.ndarray] | None:
    """The corridor as a list of polylines (legs and gate passages), or ``None``.

    With ``need_path=False`` a grid leg is only checked for connectivity and returned as its two ends.
    """
    if not radius > 0 or not resolution > 0 or not approach >= 0:
        raise ValueError(f"radius and resolution must be > 0 and approach >= 0, got {radius}, {resolution}, {approach}")
    if not scene.gates:
        raise ValueError("the scene has no gates to pass")
    vol_lo = np.array(scene.arena_low, dtype=float)
    vol_hi = np.array(scene.arena_high, dtype=float)
    if ceiling is not None:
        vol_hi[2] = min(vol_hi[2], float(ceiling))
    space = _FreeSpace(scene, radius, resolution, vol_lo, vol_hi)
    origin = np.asarray(scene.track.start.center if start is None else start, dtype=float)
    fronts = [g.center - approach * g.normal for g in scene.gates]
    backs = [g.center + approach * g.normal for g in scene.gates]
    legs = list(zip([origin, *backs[:-1]], fronts, strict=True))
    # one batched query proves the start, every gate passage and every straight leg at once
    clear = space.segments_clear([(origin, origin), *zip(fronts, backs, strict=True), *legs])
    if not np.all(clear[: 1 + len(fronts)]):
        return None
    pieces: list[np.ndarray] = []
    for (a, b), straight, front, back in zip(legs, clear[1 + len(fronts) :], fronts, backs, strict=True):
        leg = np.stack([a, b]) if straight else space.grid_leg(a, b, need_path)
        if leg is None:
            return None
        pieces += [leg, np.stack([front, back])]
    return pieces


class _FreeSpace:
    """Clearance queries and grid searches for one scene, sphere radius and search volume."""

    def __init__(self, scene: Scene, radius: float, resolution: float, vol_lo: np.ndarray, vol_hi: np.ndarray):
        self.scene = scene
        self.radius = radius
        self.h = resolution
        self.vol_lo = vol_lo
        self.vol_hi = vol_hi
        self._full: _Grid | None = None

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance from points ``(M, 3)`` to the nearest geometry, ground, wall or ceiling."""
        walls = np.minimum((points - self.vol_lo).min(axis=-1), (self.vol_hi - points).min(axis=-1))
        return np.minimum(self.scene.distance(points), walls)

    def segments_clear(self, segments: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Whether every point of each segment ``(a, b)`` is at least ``radius`` from everything (a proof).

        Samples ``s`` apart with clearance ``>= radius + s/2`` suffice: any point of the segment is within
        ``s/2`` of a sample and clearance is 1-Lipschitz.
        """
        lengths = np.array([np.linalg.norm(b - a) for a, b in segments])
        counts = np.maximum(np.ceil(lengths / _SEGMENT_STEP).astype(int) + 1, 2)
        spacing = lengths / (counts - 1)
        owner = np.repeat(np.arange(len(segments)), counts)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        t = (np.arange(len(owner)) - first[owner]) / (counts[owner] - 1)
        a = np.array([a for a, _ in segments])
        b = np.array([b for _, b in segments])
        samples = a[owner] + t[:, None] * (b - a)[owner]
        ok = self.clearance(samples) >= self.radius + spacing[owner] / 2.0
        return np.logical_and.reduceat(ok, first)

    def grid_leg(self, a: np.ndarray, b: np.ndarray, need_path: bool) -> np.ndarray | None:
        """A clear polyline from ``a`` to ``b`` through a local grid, then through the full one, or ``None``."""
        ends = self.clearance(np.stack([a, b]))
        lo = np.maximum(np.minimum(a, b) - _LEG_MARGIN, self.vol_lo)
        hi = np.minimum(np.maximum(a, b) + _LEG_MARGIN, self.vol_hi)
        path = _Grid(self, lo, hi).connect(a, ends[0], b, ends[1], need_path)
        if path is None and (np.any(lo > self.vol_lo) or np.any(hi < self.vol_hi)):
            # a detour may leave the local box: the whole volume decides
            path = self.full.connect(a, ends[0], b, ends[1], need_path)
        return path

    @property
    def full(self) -> _Grid:
        """The grid over the whole search volume, built on first use."""
        if self._full is None:
            self._full = _Grid(self, self.vol_lo, self.vol_hi)
        return self._full


class _Grid:
    """Occupancy grid over a box: a cell is free iff its centre has clearance ``>= radius + h/2``."""

    def __init__(self, space: _FreeSpace, lo: np.ndarray, hi: np.ndarray):
        self.space = space
        h = space.h
        self.origin = lo
        self.shape = tuple(int(v) for v in np.maximum(np.floor((hi - lo) / h), 0).astype(int))
        self.n_cells = int(np.prod(self.shape))
        self._labels: np.ndarray | None = None
        self._free_bytes: bytes | None = None
        if min(self.shape) < 3:
            self.free = np.zeros(self.shape, dtype=bool)
            return
        need = space.radius + h / 2.0
        axes = [lo[d] + (np.arange(self.shape[d]) + 0.5) * h for d in range(3)]
        walls = [np.minimum(axes[d] - space.vol_lo[d], space.vol_hi[d] - axes[d]) >= need for d in range(3)]
        free = walls[0][:, None, None] & walls[1][None, :, None] & walls[2][None, None, :]
        # the outermost layer stays blocked so that grid neighbours of a free cell never leave the array
        free[[0, -1]] = False
        free[:, [0, -1]] = False
        free[:, :, [0, -1]] = False
        self._rasterise(free, axes, need)
        self.free = free

    def _rasterise(self, free: np.ndarray, axes: list[np.ndarray], need: float) -> None:
        """Block every cell whose centre is closer than ``need`` to a primitive (only its bounding box is visited)."""
        centre, half, yaw, rounding = self.space.scene.primitive_arrays
        if len(rounding) == 0:
            return
        cos, sin = np.cos(yaw), np.sin(yaw)
        reach = np.stack(
            [
                np.abs(cos) * half[:, 0] + np.abs(sin) * half[:, 1] + rounding,
                np.abs(sin) * half[:, 0] + np.abs(cos) * half[:, 1] + rounding,
                half[:, 2],
            ],
            axis=1,
        )
        h = self.space.h
        top = np.array(self.shape) - 1
        first = np.maximum(np.ceil((centre - reach - need - self.origin) / h - 0.5), 0).astype(int)
        last = np.minimum(np.floor((centre + reach + need - self.origin) / h - 0.5), top).astype(int)
        inside = np.flatnonzero(np.all(first <= last, axis=1))
        if len(inside) == 0:
            return
        flat_free = free.reshape(-1)
        for group in _window_groups(inside, last[inside] - first[inside] + 1):
            # one padded window per group; cells past a primitive's own range are still computed exactly
            # (indices clipped into the grid), so padding never blocks a cell wrongly
            window = (last[group] - first[group] + 1).max(axis=0)
            idx = [np.minimum(first[group, d, None] + np.arange(window[d]), self.shape[d] - 1) for d in range(3)]
            c, s_ = cos[group, None, None], sin[group, None, None]
            dx = axes[0][idx[0]][:, :, None] - centre[group, 0, None, None]
            dy = axes[1][idx[1]][:, None, :] - centre[group, 1, None, None]
            ex = np.maximum(np.abs(c * dx + s_ * dy) - half[group, 0, None, None], 0.0)
            ey = np.maximum(np.abs(c * dy - s_ * dx) - half[group, 1, None, None], 0.0)
            exy = np.maximum(np.hypot(ex, ey) - rounding[group, None, None], 0.0)
            ez = np.maximum(np.abs(axes[2][idx[2]] - centre[group, 2, None]) - half[group, 2, None], 0.0)
            blocked = (exy * exy)[..., None] + (ez * ez)[:, None, None, :] < need * need
            k, i, j, m = np.nonzero(blocked)
            flat_free[(idx[0][k, i] * self.shape[1] + idx[1][k, j]) * self.shape[2] + idx[2][k, m]] = False

    def snap(self, point: np.ndarray, clearance: float) -> int | None:
        """Flat index of a nearby free cell whose straight link to ``point`` is provably clear, or ``None``.

        On the link of length ``L`` from ``point`` (clearance ``d``) to a free centre (clearance at least
        ``R + h/2``) the clearance is at least ``(d + R + h/2 - L) / 2``, which is ``>= R`` iff
        ``d >= R + L - h/2``.
        """
        h = self.space.h
        base = np.floor((point - self.origin) / h - 0.5).astype(int)
        cells = base + _SNAP_OFFSETS
        cells = cells[np.all((cells >= 0) & (cells < np.array(self.shape)), axis=1)]
        if len(cells) == 0:
            return None
        cells = cells[self.free[cells[:, 0], cells[:, 1], cells[:, 2]]]
        lengths = np.linalg.norm(self.origin + (cells + 0.5) * h - point, axis=1)
        ok = clearance >= self.space.radius + lengths - h / 2.0
        if not np.any(ok):
            return None
        best = cells[ok][np.argmin(lengths[ok])]
        return int(np.ravel_multi_index(tuple(best), self.shape))

    def connect(self, a: np.ndarray, da: float, b: np.ndarray, db: float, need_path: bool) -> np.ndarray | None:
        """A clear polyline ``a -> b`` through free cells (just ``[a, b]`` if not ``need_path``), or ``None``."""
        if self.n_cells == 0:
            return None
        sa, sb = self.snap(a, da), self.snap(b, db)
        if sa is None or sb is None:
            return None
        if self._labels is None:
            self._labels, _ = ndimage.label(self.free, structure=_SIX)
        flat = self._labels.reshape(-1)
        if flat[sa] != flat[sb]:
            return None
        if not need_path:
            return np.stack([a, b])
        if self._free_bytes is None:
            self._free_bytes = self.free.tobytes()
        cells = _astar(self._free_bytes, self.shape, sa, sb)
        centres = self.origin + (np.array(np.unravel_index(cells, self.shape)).T + 0.5) * self.space.h
        return self._shortcut(np.concatenate([a[None], _drop_collinear(centres), b[None]]))

    def _shortcut(self, points: np.ndarray) -> np.ndarray:
        """Replace runs of vertices by the longest straight segments proven clear (original links stay valid)."""
        out = [points[0]]
        i, last = 0, len(points) - 1
        while i < last:
            nxt = i + 1  # points[i] -> points[i + 1] is an original, already-proven link
            # candidates i+2, i+3, i+5, i+9, ... and the end: one batched query per output vertex
            targets = sorted({min(i + 1 + 2**k, last) for k in range(max(1, (last - i).bit_length() + 1))} - {i + 1})
            if targets:
                clear = self.space.segments_clear([(points[i], points[j]) for j in targets])
                if np.any(clear):
                    nxt = targets[int(np.flatnonzero(clear)[-1])]
            out.append(points[nxt])
            i = nxt
        return np.stack(out)


def _window_groups(indices: np.ndarray, sizes: np.ndarray, budget: int = 1 << 18) -> list[np.ndarray]:
    """Split primitives into groups whose padded windows (max size per axis x count) stay under ``budget`` cells.

    Sorting by window volume first keeps similar windows together (gate bars apart from tall poles).
    """
    order = np.argsort(np.prod(sizes, axis=1), kind="stable")
    groups: list[list[int]] = []
    current: list[int] = []
    bound = (0, 0, 0)
    for i in order:
        grown = tuple(max(a, int(b)) for a, b in zip(bound, sizes[i], strict=True))
        if current and grown[0] * grown[1] * grown[2] * (len(current) + 1) > budget:
            groups.append(current)
            current, grown = [], tuple(int(b) for b in sizes[i])
        current.append(int(indices[i]))
        bound = grown
    groups.append(current)
    return [np.array(g) for g in groups]


def _astar(free: bytes, shape: tuple[int, ...], source: int, target: int) -> list[int]:
    """Flat indices of a 6-connected path of free cells from ``source`` to ``target`` (known to be connected).

    Weighted A* with the Manhattan heuristic: the path need not be shortest, only found quickly.
    """
    nz = shape[2]
    stride = shape[1] * nz
    ti, rest = divmod(target, stride)
    tj, tk = divmod(rest, nz)
    steps = (1, -1, nz, -nz, stride, -stride)
    cost = {source: 0}
    parent = {source: -1}
    heap = [(0, 0, source)]
    while heap:
        _, neg_g, u = heapq.heappop(heap)
        if u == target:
            break
        g = -neg_g
        if g > cost[u]:
            continue
        for step in steps:
            v = u + step
            if free[v] and g + 1 < cost.get(v, 1 << 60):
                cost[v] = g + 1
                parent[v] = u
                i, r = divmod(v, stride)
                j, k = divmod(r, nz)
                # weight 2 on the Manhattan heuristic: a valid path fast, not the shortest one
                heapq.heappush(heap, (g + 1 + 2 * (abs(i - ti) + abs(j - tj) + abs(k - tk)), -(g + 1), v))
    else:
        raise AssertionError("A* ran out of cells between two cells of the same component")
    path = [target]
    while path[-1] != source:
        path.append(parent[path[-1]])
    return path[::-1]


def _drop_collinear(points: np.ndarray) -> np.ndarray:
    """Keep the ends and the corners of a polyline of grid centres."""
    if len(points) < 3:
        return points
    turn = np.any(np.abs(np.diff(np.diff(points, axis=0), axis=0)) > 1e-9, axis=1)
    return points[np.concatenate([[True], turn, [True]])]


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
        for region in regions:
            a, b = gates[region.between[0]].center[:2], gates[region.between[1]].center[:2]
            lo, hi = np.minimum(a, b) - region.half_width, np.maximum(a, b) + region.half_width
            xy.append(rng.uniform(lo, hi, size=(n, 2)))
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
