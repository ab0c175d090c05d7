"""The corridor search: a path that keeps a sphere clear of every gate bar, obstacle, the ground and the arena.

:func:`find_corridor` searches it on a 3D occupancy grid (or proves a straight leg clear). Soundness: a grid cell
is free when its centre is at least ``R + h/2`` from every gate bar, obstacle, the ground, the arena walls and the
ceiling (``R`` the sphere radius, ``h`` the cell size). Every point of the segment joining two face-adjacent free
centres is within ``h/2`` of one of them, so it is at least ``R`` from all geometry (distance is 1-Lipschitz).
Straight segments are checked the same way: samples ``s`` apart with clearance ``>= R + s/2``.
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy import ndimage

from racebench.sim.scene import Scene

#: Most cells of the corridor grid over the arena (16.8 M: a 67 MB label array); the built-in tracks at the
#: default 0.1 m resolution need 0.6-0.9 M.
MAX_GRID_CELLS = 1 << 24
#: Default margin (m) added to the drone's collision radius for the guaranteed corridor.
CORRIDOR_MARGIN = 0.08

_SIX = ndimage.generate_binary_structure(3, 1)  # face-adjacent cells only: the soundness argument needs it
_APPROACH = 0.25  # gate passages run this far before and after the gate plane (m)
_SEGMENT_STEP = 0.05  # sample spacing when proving a straight segment clear (m)
_LEG_MARGIN = 1.0  # margin of the local grid around one leg before falling back to the whole arena (m)


_SNAP_OFFSETS = np.stack(np.meshgrid(*[np.arange(-1, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)


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
