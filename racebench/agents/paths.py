"""Path geometry for the planners: resampling, cusps, the fast expert's smoothing of a corridor (pulled taut and
relaxed away from obstacles) and where a path crosses the gates.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from racebench.sim.corridor import _SEGMENT_STEP, _FreeSpace
from racebench.sim.scene import _clearance_batch


def split_at_cusps(polyline: np.ndarray, max_turn: float = 2.0) -> list[np.ndarray]:
    """Split a polyline where it doubles back (turn > ``max_turn`` rad): each piece is flown to its end."""
    pieces, start = [], 0
    for i in range(1, len(polyline) - 1):
        a, b = polyline[i] - polyline[i - 1], polyline[i + 1] - polyline[i]
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        if math.acos(max(-1.0, min(1.0, cos))) > max_turn:
            pieces.append(polyline[start : i + 1])
            start = i
    pieces.append(polyline[start:])
    return [p for p in pieces if len(p) >= 2]


def resample(polyline: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` m along a polyline, and their arc length."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, arc[-1], spacing)
    s = np.append(s, arc[-1])
    points = np.stack([np.interp(s, arc, polyline[:, k]) for k in range(3)], axis=1)
    return points, s


def _free_space(scene, radius: float = 0.0) -> _FreeSpace:
    """The corridor search's clearance queries for ``scene`` (the whole arena as its volume)."""
    lo, hi = np.asarray(scene.arena_low, dtype=float), np.asarray(scene.arena_high, dtype=float)
    return _FreeSpace(scene, radius, _SEGMENT_STEP, lo, hi)


def scene_clearance(scene, points: np.ndarray) -> np.ndarray:
    """Distance from points ``(M, 3)`` to the nearest gate bar, obstacle, the ground or an arena wall.

    Compiled (:meth:`~racebench.sim.scene.Scene.clearance`): smoothing a path asks it thousands of times per plan.
    """
    return scene.clearance(points, scene.arena_low, scene.arena_high)


def pull_taut(scene, polyline: np.ndarray, radius: float) -> np.ndarray:
    """String-pulling: from each kept vertex jump to the farthest later vertex joined by a ``radius``-clear
    straight segment. The ends stay; the result is no longer and every new segment is proven clear."""
    space = _free_space(scene, radius)
    kept, i = [polyline[0]], 0
    while i < len(polyline) - 1:
        later = np.arange(i + 1, len(polyline))
        clear = space.segments_clear([(polyline[i], polyline[j]) for j in later])
        clear[0] = True  # the corridor's own segment is clear by construction
        i = int(later[np.flatnonzero(clear)[-1]])
        kept.append(polyline[i])
    return np.array(kept)


def relax(
    scene,
    polyline: np.ndarray,
    min_clearance: float,
    wanted_clearance: float,
    gate_clearance: float = 0.4,
    gate_floor: float = 0.32,
    spacings: tuple[float, ...] = (0.4, 0.2),
    iterations: int = 350,
    bending: float = 0.06,
    tension: float = 0.05,
    push: float = 0.1,
) -> np.ndarray:
    """Smooth a clear polyline into a racing line: an elastic band whose points descend the bending energy
    (``Σ|Δ²p|²``, which moves corners outward and spreads turns over a longer arc) plus a little length
    (tension) and, closer than ``wanted_clearance`` to the scene (``gate_clearance`` within 0.8 m of a gate
    centre: the opening must still allow oblique crossings, which round a turn), a push away from it. A point's move is
    not taken if it would bring it closer than ``min_clearance`` to the scene. Moves are small, so the
    path keeps threading the same gate openings; the two first and last points stay fixed. Coarse
    spacing first (turns spread fast), then fine.

    Each stage's iterations run compiled (:func:`_relax_stage`); ``tests/test_planner_fast.py`` holds the
    same algorithm in numpy and checks that both give the same path bit for bit."""
    gate_centres = np.array([g.center for g in scene.gates], dtype=np.float64)
    tables = scene.clearance_tables()
    low, high = np.asarray(scene.arena_low, dtype=np.float64), np.asarray(scene.arena_high, dtype=np.float64)
    points = polyline
    for spacing in spacings:
        points, _ = resample(points, spacing)
        if len(points) < 5:
            continue
        points = _relax_stage(
            np.ascontiguousarray(points, dtype=np.float64), gate_centres, *tables, low, high,
            float(min_clearance), float(wanted_clearance), float(gate_clearance), float(gate_floor),
            int(iterations), float(bending), float(tension), float(push),
        )  # fmt: skip
    return points


@njit(cache=True)
def _midpoints(points: np.ndarray) -> np.ndarray:
    """``0.5 * (points[:-1] + points[1:])``."""
    out = np.empty((len(points) - 1, 3))
    for i in range(len(points) - 1):
        for d in range(3):
            out[i, d] = 0.5 * (points[i, d] + points[i + 1, d])
    return out


@njit(cache=True)
def _relax_stage(
    points: np.ndarray,
    gate_centres: np.ndarray,
    centre: np.ndarray,
    half: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    rounding: np.ndarray,
    reach: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    min_clearance: float,
    wanted_clearance: float,
    gate_clearance: float,
    gate_floor: float,
    iterations: int,
    bending: float,
    tension: float,
    push: float,
) -> np.ndarray:
    """One spacing stage of :func:`relax`: ``iterations`` moves of the band (no resampling inside a stage:
    the Laplacian terms keep the spacing even on their own, and resampling would place points on segments
    that were only proven clear at their samples). Every float operation is the numpy version's, in its order."""
    n = len(points)
    eps = 0.02
    points = points.copy()
    probes = np.empty((7 * n, 3))
    for _ in range(iterations):
        step = np.zeros((n, 3))
        for i in range(2, n - 2):
            for d in range(3):
                fourth = (
                    points[i - 2, d] - 4.0 * points[i - 1, d] + 6.0 * points[i, d] - 4.0 * points[i + 1, d]
                    + points[i + 2, d]
                )  # fmt: skip
                step[i, d] -= bending * fourth
        for i in range(1, n - 1):
            for d in range(3):
                step[i, d] += tension * (0.5 * (points[i - 1, d] + points[i + 1, d]) - points[i, d])
        # Clearance and its gradient (central differences, one batched query of 7 probes per point).
        for r in range(7):
            for i in range(n):
                for d in range(3):
                    probes[r * n + i, d] = points[i, d]
                if r >= 1:
                    axis = (r - 1) % 3
                    probes[r * n + i, axis] = points[i, axis] + (eps if r <= 3 else -eps)
        values = _clearance_batch(probes, centre, half, cos, sin, rounding, reach, low, high)
        clearance = values[:n]
        at_gate = np.zeros(n, dtype=np.bool_)
        for i in range(n):
            g = np.empty(3)
            for d in range(3):
                g[d] = values[(1 + d) * n + i] - values[(4 + d) * n + i]
            norm = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
            for k in range(len(gate_centres)):
                dx = points[i, 0] - gate_centres[k, 0]
                dy = points[i, 1] - gate_centres[k, 1]
                dz = points[i, 2] - gate_centres[k, 2]
                if math.sqrt(dx * dx + dy * dy + dz * dz) < 0.8:
                    at_gate[i] = True
            # Near a gate the wanted clearance is what the opening allows a little off its centre.
            wanted = gate_clearance if at_gate[i] else wanted_clearance
            if clearance[i] < wanted:
                scale = push * (wanted - clearance[i])
                for d in range(3):
                    step[i, d] += scale * (g[d] / max(norm, 1e-9))
        for i in (0, 1, n - 2, n - 1):
            step[i, 0] = step[i, 1] = step[i, 2] = 0.0
        # Cap each move well below the thinnest gate bar plus twice the clearance, so no point can hop
        # across a bar in one step: the path stays threaded through every opening it threaded before.
        target = np.empty((n, 3))
        for i in range(n):
            length = math.sqrt(step[i, 0] * step[i, 0] + step[i, 1] * step[i, 1] + step[i, 2] * step[i, 2])
            factor = min(1.0, 0.05 / max(length, 1e-12))
            for d in range(3):
                target[i, d] = points[i, d] + step[i, d] * factor
        # A move counts only if the point and the midpoints of its two segments stay clear: the samples
        # alone could let a segment cut a corner between them. Inside a gate zone the floor is higher: the
        # path crosses the opening away from its bars.
        both = _clearance_batch(
            np.concatenate((target, _midpoints(target))), centre, half, cos, sin, rounding, reach, low, high
        )
        ok = np.empty(n, dtype=np.bool_)
        moved = np.empty((n, 3))
        for i in range(n):
            floor = max(min_clearance, gate_floor) if at_gate[i] else min_clearance
            after = both[i]
            ok[i] = (after >= floor) or (after >= min(clearance[i], floor))  # below the floor: no worse
            for d in range(3):
                moved[i, d] = target[i, d] if ok[i] else points[i, d]
        middle = both[n:]
        if not ok.all():  # the midpoints above were of the all-moved path
            middle = _clearance_batch(_midpoints(moved), centre, half, cos, sin, rounding, reach, low, high)
        while True:  # undo moves until every segment's midpoint of the result is clear
            undone = False
            bad = np.zeros(n - 1, dtype=np.bool_)
            for j in range(n - 1):  # segments no move touched stay as they were
                bad[j] = middle[j] < min_clearance - 1e-9 and (ok[j] or ok[j + 1])
            for j in range(n - 1):
                if bad[j]:
                    ok[j] = ok[j + 1] = False  # each pass undoes at least one move: the loop ends
                    undone = True
            if not undone:
                break
            for i in range(n):
                for d in range(3):
                    moved[i, d] = target[i, d] if ok[i] else points[i, d]
            middle = _clearance_batch(_midpoints(moved), centre, half, cos, sin, rounding, reach, low, high)
        points = moved
    return points


def _arc_length_spline(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples ``spacing`` m apart on a cubic spline through ``points``: positions, arc length, unit
    tangents and curvature vectors (``d²r/ds²``)."""
    from scipy.interpolate import CubicSpline

    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    spline = CubicSpline(chord, points, axis=0, bc_type="natural")
    u = np.linspace(0.0, chord[-1], int(math.ceil(chord[-1] / (spacing / 4))) + 1)
    fine = spline(u)
    s_fine = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(fine, axis=0), axis=1))])
    s = np.arange(0.0, s_fine[-1], spacing)
    u_s = np.interp(s, s_fine, u)
    d1, d2 = spline(u_s, 1), spline(u_s, 2)
    speed = np.linalg.norm(d1, axis=1, keepdims=True)
    tangent = d1 / speed
    curvature = (d2 - np.sum(d2 * tangent, axis=1, keepdims=True) * tangent) / speed**2
    return spline(u_s), s, tangent, curvature


def gate_crossings(path: np.ndarray, gates) -> list[int]:
    """Index ``k`` of the segment ``path[k] → path[k+1]`` that passes each gate's opening (the env's own
    passage test), in order; shorter than ``gates`` when the polyline misses one."""
    crossings, k = [], 0
    for gate in gates:
        while k < len(path) - 1 and not gate.passed_by(path[k], path[k + 1]):
            k += 1
        if k == len(path) - 1:
            break
        crossings.append(k)
        k += 1
    return crossings
