"""Procedural race tracks in the paper's style: 4-6 square gates, sprints and closed loops, in the paper's arena.

The paper trains and evaluates on three fixed tracks (S, 3D Circle, J: ``tracks/*.yaml``) and names unseen layouts as
its open problem. :func:`generate_track` draws new tracks of the same kind, from a numpy ``Generator`` only (a seed
fixes the track, bit for bit), as :class:`~racebench.sim.track.Track` data of the same schema as ``tracks/*.yaml``
(:func:`write_track` writes one, :func:`~racebench.sim.track.load_track` reads it back identically).

**The rules** (``docs/unseen-tracks.md`` gives the reasons with the numbers):

* gates: 4-6 (:data:`GATE_COUNTS`), each the paper's square gate (:data:`GATE_SIZE`, the 1.0 m opening of
  ``tracks/S.yaml``); a sprint passes them once, a closed loop is one lap of them, as Circle;
* each gate faces the bisector of its incoming and outgoing legs (the paper's Circle and J gates do), so a leg meets a
  gate's normal at no more than half the turn there;
* gate spacing: :data:`LEG_LENGTH` (3-6 m between consecutive gate centres; the paper's legs are 3.6-4.5 m);
* turn between consecutive legs at most :data:`MAX_TURN_DEG` (120 degrees; the paper's sharpest is Circle's 90, and a
  4-gate loop's turns add up to 360 degrees); a sprint's turns are drawn within :data:`SPRINT_TURN_DEG`;
* heights: gate centres in :data:`GATE_HEIGHT` (1-2 m, the paper's), so at most 1 m of climb per leg (under 20 degrees
  on a 3 m leg, inside the camera's 45-degree half field of view);
* the arena: gates and start within :data:`ARENA_SPAN` (14 m along the start heading x 8 m across: the S track spans
  14 m, J and Circle 6 m across); the flight volume is then ``racebench.sim.scene.arena_bounds``, as for every track;
* no leg passes another: legs that share no gate keep :data:`LEG_SEPARATION` apart and every gate centre keeps
  :data:`GATE_CLEARANCE` from the legs that do not end at it (and from the start);
* the start: :data:`START_DISTANCE` before gate 0, facing it along its normal (+x), spread :data:`START_SPREAD`, as on
  the three paper tracks;
* obstacles: one region per gate-to-gate leg (a sprint's start leg has none, as on S and J) with the band
  :data:`OBSTACLE_BAND`, the mean of the three tracks' bands tuned to the authors' scenes, so
  :class:`~racebench.sim.obstacles.ObstacleGenerator` places them at the paper's densities (3 per region);
* no paper track: a draw whose gates lie within :data:`PAPER_TRACK_TOLERANCE` of S, J or Circle's (any translation,
  rotation about the vertical or mirror image; :func:`paper_track_match`) is redrawn;
* flyable: a sphere of the drone's radius plus the corridor margin (``CORRIDOR_MARGIN``) passes from the start through
  every gate in order on the obstacle-free track (:func:`~racebench.sim.corridor.find_corridor`), and an obstacle
  layout at the densest registered density passes the obstacle generator's own corridor check.

A draw that breaks a rule is redrawn from the same generator, at most :data:`MAX_DRAWS` times; past that
:func:`generate_track` raises ``RuntimeError`` naming the rules that failed (never seen: about one draw in
:data:`MAX_DRAWS` / 20 is needed at most over the tested seeds). Every episode on a generated track then draws its
obstacles with :class:`~racebench.sim.obstacles.ObstacleGenerator`, whose corridor check and redraws are the same as on
the paper's tracks.
"""

from __future__ import annotations

import functools
import json
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from racebench.sim.corridor import CORRIDOR_MARGIN, find_corridor
from racebench.sim.obstacles import ObstacleGenerator
from racebench.sim.scene import Scene, arena_bounds
from racebench.sim.track import BUILTIN_TRACKS, Track, load_track, parse_track
from racebench.utils.files import atomic_write

#: Track sources: names that stand for a generated track per episode where a track name is taken
#: (:class:`racebench.envs.random_tracks.RandomTrackEnv`): ``Random`` (training) and ``Unseen`` (held out).
TRACK_SOURCES: tuple[str, ...] = ("Random", "Unseen")
#: The paper's gate (``tracks/S.yaml``): 1.0 m square opening, 1.28 m frame, 0.1 m deep.
GATE_SIZE: dict[str, float] = {"inner": 1.0, "outer": 1.28, "depth": 0.10}
GATE_COUNTS: tuple[int, ...] = (4, 5, 6)
LEG_LENGTH: tuple[float, float] = (3.0, 6.0)  # m between consecutive gate centres (3D)
MAX_TURN_DEG = 120.0  # between consecutive legs; a gate's normal is within half of it from either leg
SPRINT_TURN_DEG = 90.0  # a sprint's turns are drawn uniformly within ± this
GATE_HEIGHT: tuple[float, float] = (1.0, 2.0)  # m, gate centres
MAX_CLIMB = 1.0  # m per leg (follows from GATE_HEIGHT)
ARENA_SPAN: tuple[float, float] = (14.0, 8.0)  # m: gates and start, along x (the start heading) and across (y)
LEG_SEPARATION = 1.5  # m, horizontal, between legs sharing no gate
GATE_CLEARANCE = 2.0  # m, horizontal, from a gate centre to a leg not ending at it, and from the start
START_DISTANCE = 2.0  # m before gate 0, along its normal (the paper's three tracks)
START_SPREAD = 0.3  # m, per axis (the paper's three tracks)
#: Where obstacles stand along each leg: the mean of the bands tuned per paper track (S 1.9/1.05, J 2.3/1.3,
#: Circle 2.2/1.5), so that the share of obstacles near the racing line is in the authors' range.
OBSTACLE_BAND: dict[str, float] = {"half_width": 2.1, "end_margin": 0.5, "profile": 1.3}
REGION_HALF_WIDTH = 1.2  # the "box" placement's widening, as on the paper's tracks
PAPER_TRACK_TOLERANCE = 0.5  # m: gate centres this close (RMS, best rigid motion) to a paper track's are that track
#: The densest registered id's obstacles per region: a generated track must take a layout at this density.
TRIAL_DENSITY = 5
DRONE_RADIUS = 0.12  # m, the airframe's collision sphere (QuadrotorParams.collision_radius)
MAX_DRAWS = 2000  # candidate tracks per generate_track call before it gives up
#: ``np.random.default_rng([seed, TRACK_STREAM])`` draws the track of a track seed: another stream than the
#: env's ``np_random`` of the same integer (``SeedSequence(seed)``), which draws the obstacles.
TRACK_STREAM = 0x7261636B  # "rack"


# --------------------------------------------------------------------------- drawing
def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _bisector(u_in: np.ndarray, u_out: np.ndarray) -> float:
    """Heading of the bisector of two horizontal unit vectors."""
    mid = u_in + u_out
    return math.atan2(mid[1], mid[0])


def _draw_sprint(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gate centres ``(n, 2)`` and yaws ``(n,)`` of a sprint: a walk of legs, gate 0 facing +x."""
    turns = np.radians(rng.uniform(-SPRINT_TURN_DEG, SPRINT_TURN_DEG, size=n))  # at each gate (the last: its exit)
    lengths = rng.uniform(*LEG_LENGTH, size=n - 1)
    heading = -turns[0] / 2.0  # the approach to gate 0, so that gate 0 faces +x
    xy, yaw = [np.zeros(2)], [heading + turns[0] / 2.0]
    for k in range(1, n):
        heading += turns[k - 1]
        xy.append(xy[-1] + lengths[k - 1] * _unit(heading))
        yaw.append(heading + turns[k] / 2.0)
    return np.array(xy), np.array(yaw)


def _draw_loop(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gate centres ``(n, 2)`` and yaws ``(n,)`` of a closed loop: n points around a jittered ellipse, either way round,
    gate 0 at the end of its short axis (so that it faces along the long one, as Circle's gate 0 faces +x)."""
    direction = 1.0 if rng.uniform() < 0.5 else -1.0
    step = 2.0 * math.pi / n
    angles = direction * (-math.pi / 2.0 + np.arange(n) * step + rng.uniform(-0.2, 0.2, size=n) * step)
    leg = rng.uniform(3.5, 5.0)  # the mean leg the ellipse's perimeter is sized for
    aspect = rng.uniform(0.45, 1.0)  # short axis over long axis
    long_axis = n * leg / (2.0 * math.pi * math.sqrt((1.0 + aspect**2) / 2.0))  # perimeter ~ 2 pi RMS radius
    radii = rng.uniform(0.9, 1.1, size=n)
    xy = np.stack([np.cos(angles) * long_axis, np.sin(angles) * long_axis * aspect], axis=1) * radii[:, None]
    yaw = []
    for k in range(n):
        u_in, u_out = xy[k] - xy[k - 1], xy[(k + 1) % n] - xy[k]
        yaw.append(_bisector(u_in / np.linalg.norm(u_in), u_out / np.linalg.norm(u_out)))
    return xy, np.array(yaw)


def _candidate(rng: np.random.Generator, name: str, n: int, closed: bool) -> dict[str, Any]:
    """One candidate track of ``n`` gates as the plain data of a track file (rounded to cm, 0.1 m heights and 0.1
    degrees)."""
    xy, yaw = _draw_loop(rng, n) if closed else _draw_sprint(rng, n)
    z = np.round(rng.uniform(*GATE_HEIGHT, size=n), 1)
    # gate 0 faces +x (the start heading, as on the paper's tracks), the start lies START_DISTANCE before it
    c, s = math.cos(-yaw[0]), math.sin(-yaw[0])
    xy = (xy - xy[0]) @ np.array([[c, s], [-s, c]])
    yaw = yaw - yaw[0]
    start = np.array([-START_DISTANCE, 0.0])
    points = np.vstack([xy, start])
    shift = np.array([1.0 - points[:, 0].min(), -(points[:, 1].min() + points[:, 1].max()) / 2.0])
    xy, start = xy + shift, start + shift
    yaw_deg = (np.degrees(yaw) + 180.0) % 360.0 - 180.0
    gates = [
        {"center": [_round(x, 2), _round(y, 2), _round(h, 1)], "yaw_deg": _round(a, 1)}
        for (x, y), h, a in zip(xy, z, yaw_deg, strict=True)
    ]
    legs = [[i, (i + 1) % n] for i in range(n if closed else n - 1)]
    return {
        "name": name,
        "description": f"generated {'closed loop' if closed else 'sprint'}, {n} gates",
        "closed_loop": closed,
        "gate_size": dict(GATE_SIZE),
        "gates": gates,
        "start": {
            "center": [_round(start[0], 2), _round(start[1], 2), gates[0]["center"][2]],
            "yaw_deg": 0.0,
            "spread": [START_SPREAD] * 3,
        },
        "obstacle_regions": [{"between": leg, "half_width": REGION_HALF_WIDTH} for leg in legs],
        "obstacle_band": dict(OBSTACLE_BAND),
    }


def _round(value: float, digits: int) -> float:
    """``value`` rounded, as a plain float without negative zero (so that the YAML text is stable)."""
    return float(round(float(value), digits)) + 0.0


# --------------------------------------------------------------------------- rules
def legs_of(track: Track) -> list[tuple[int, int]]:
    """The gate-to-gate legs ``(i, j)`` in flying order (a loop's last leg closes it)."""
    n = track.num_gates
    return [(i, (i + 1) % n) for i in range(n if track.closed_loop else n - 1)]


def _segment_distance(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """Distance between the 2D segments ``ab`` and ``cd`` (0 where they cross)."""

    def cross(o: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
        return float((p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0]))

    if cross(a, b, c) * cross(a, b, d) < 0 and cross(c, d, a) * cross(c, d, b) < 0:
        return 0.0
    return min(_point_segment(a, c, d), _point_segment(b, c, d), _point_segment(c, a, b), _point_segment(d, a, b))


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    t = float(np.clip(np.dot(p - a, d) / np.dot(d, d), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * d)))


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Unsigned angle between two horizontal vectors, degrees."""
    cos = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def rule_violations(track: Track) -> list[str]:
    """The geometric rules (module docstring) ``track`` breaks, as short names; ``[]`` when it keeps them all.

    Everything but flyability and the paper-track rule (:func:`generate_track` checks those after these).
    """
    out: list[str] = []
    gates = track.gates
    n = len(gates)
    centres = np.array([g.center for g in gates])
    xy = centres[:, :2]
    start = track.start.center
    if n not in GATE_COUNTS:
        out.append("gate_count")
    if any((g.inner, g.outer, g.depth) != (GATE_SIZE["inner"], GATE_SIZE["outer"], GATE_SIZE["depth"]) for g in gates):
        out.append("gate_size")
    if np.any(centres[:, 2] < GATE_HEIGHT[0] - 1e-9) or np.any(centres[:, 2] > GATE_HEIGHT[1] + 1e-9):
        out.append("height")
    legs = legs_of(track)
    for i, j in legs:
        length = float(np.linalg.norm(centres[j] - centres[i]))
        if not LEG_LENGTH[0] - 1e-9 <= length <= LEG_LENGTH[1] + 1e-9:
            out.append("leg_length")
        if abs(centres[j, 2] - centres[i, 2]) > MAX_CLIMB + 1e-9:
            out.append("climb")
    # every leg (the start leg of a sprint too) meets the normals of its gates within half the largest turn
    flown = [(start[:2], xy[0], None, 0)] if not track.closed_loop else []
    flown += [(xy[i], xy[j], i, j) for i, j in legs]
    for a, b, i, j in flown:
        leg = b - a
        for k in (i, j):
            if k is not None and _angle_deg(leg, gates[k].normal[:2]) > MAX_TURN_DEG / 2.0 + 1e-6:
                out.append("turn")
    for (a0, b0, i0, j0), (a1, b1, i1, j1) in ((p, q) for m, p in enumerate(flown) for q in flown[m + 1 :]):
        if {i0, j0} & {i1, j1}:
            continue  # adjacent legs share a gate
        if _segment_distance(a0, b0, a1, b1) < LEG_SEPARATION - 1e-9:
            out.append("legs_too_close")
    for k in range(n):
        for a, b, i, j in flown:
            if k not in (i, j) and _point_segment(xy[k], a, b) < GATE_CLEARANCE - 1e-9:
                out.append("gate_near_leg")
        if k > 0 and float(np.linalg.norm(xy[k] - start[:2])) < GATE_CLEARANCE - 1e-9:
            out.append("gate_near_start")
    points = np.vstack([xy, start[:2]])
    span = points.max(axis=0) - points.min(axis=0)
    if span[0] > ARENA_SPAN[0] + 1e-9 or span[1] > ARENA_SPAN[1] + 1e-9:
        out.append("arena")
    g0 = gates[0]
    behind = g0.center - START_DISTANCE * g0.normal
    if float(np.linalg.norm(start - behind)) > 0.02 or abs(track.start.yaw - g0.yaw) > 1e-9:
        out.append("start")
    return list(dict.fromkeys(out))


def paper_track_match(track: Track, tolerance: float = PAPER_TRACK_TOLERANCE) -> str | None:
    """The paper track (``"S"``, ``"J"``, ``"Circle"``) whose gates ``track``'s match, else ``None``.

    A match: the same number of gates, in order or reversed (from any gate when either track is a loop), whose
    centres lie within ``tolerance`` m RMS of the paper track's after the best rigid motion: a translation in x, y and
    z, a rotation about the vertical, and a mirror image (least squares, Kabsch in the plane). Every gate within
    ``tolerance`` m under some such motion implies an RMS within it, so this catches at least every track whose gates
    each lie that close.
    """
    mine = np.array([g.center for g in track.gates])
    for name, (theirs, loop) in _paper_gates().items():
        if len(theirs) != len(mine):
            continue
        shifts = range(len(mine)) if (track.closed_loop or loop) else (0,)
        for shift in shifts:
            for order in (1, -1):  # either way round
                candidate = np.roll(mine[::order], -shift, axis=0)
                if _aligned_rms(candidate, theirs) <= tolerance:
                    return name
    return None


@functools.cache
def _paper_gates() -> dict[str, tuple[np.ndarray, bool]]:
    """Each paper track's gate centres ``(n, 3)`` and whether it is a loop (read once)."""
    out = {}
    for name in BUILTIN_TRACKS:
        paper = load_track(name)
        centres = np.array([g.center for g in paper.gates])
        centres.flags.writeable = False
        out[name] = (centres, paper.closed_loop)
    return out


def _aligned_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance between point sets ``a`` and ``b`` ``(n, 3)`` after the best motion of ``a``: a rotation about z,
    a mirror image or not, and a translation."""
    z = (a[:, 2] - a[:, 2].mean()) - (b[:, 2] - b[:, 2].mean())
    p, q = a[:, :2] - a[:, :2].mean(axis=0), b[:, :2] - b[:, :2].mean(axis=0)
    best = math.inf
    for mirror in (1.0, -1.0):
        pm = p * np.array([1.0, mirror])
        u, _, vt = np.linalg.svd(pm.T @ q)
        rotation = u @ vt
        if np.linalg.det(rotation) < 0:  # a reflection: the mirror case covers it, keep a proper rotation here
            u[:, -1] *= -1.0
            rotation = u @ vt
        residual = pm @ rotation - q
        best = min(best, float(np.sqrt(np.mean(np.sum(residual**2, axis=1) + z**2))))
    return best


def _flyable(track: Track, rng: np.random.Generator) -> str | None:
    """Why ``track`` is not flyable (``"corridor"``, ``"layout"``), else ``None``: the gates-only corridor, then one
    obstacle layout at :data:`TRIAL_DENSITY` (the obstacle generator's own corridor check)."""
    low, high = arena_bounds(track)
    bare = Scene(track, track.gates, (), track.start.center, track.start.yaw, low, high)
    if find_corridor(bare, DRONE_RADIUS + CORRIDOR_MARGIN) is None:
        return "corridor"
    try:
        ObstacleGenerator(track, density=TRIAL_DENSITY, max_attempts=50).sample_scene(rng)
    except (RuntimeError, ValueError):
        return "layout"
    return None


# --------------------------------------------------------------------------- generation
def generate_track(rng: np.random.Generator, name: str = "generated") -> Track:
    """A new track drawn from ``rng`` that keeps every rule of the module docstring (``name`` names it).

    Candidates breaking a rule are redrawn from ``rng``; after :data:`MAX_DRAWS` a ``RuntimeError`` says which rules
    failed how often. All randomness comes from ``rng``: the same generator state gives the same track, bit for bit.
    """
    n = int(rng.integers(GATE_COUNTS[0], GATE_COUNTS[-1] + 1))  # the kind first: every kind equally often
    closed = bool(rng.uniform() < 0.5)
    rejected: Counter[str] = Counter()
    for _ in range(MAX_DRAWS):
        data = _candidate(rng, name, n, closed)
        try:
            track = parse_track(data, source=f"<generated {name}>")
        except ValueError:
            rejected["format"] += 1
            continue
        broken = rule_violations(track)
        if broken:
            rejected.update(broken[:1])
            continue
        if paper_track_match(track) is not None:
            rejected["paper_track"] += 1
            continue
        why = _flyable(track, rng)
        if why is not None:
            rejected[why] += 1
            continue
        return track
    raise RuntimeError(f"generate_track: no track keeps every rule in {MAX_DRAWS} draws for {name!r} (rejected: "
                       f"{dict(rejected)})")  # fmt: skip


def track_rng(seed: int) -> np.random.Generator:
    """The generator that draws the track of track seed ``seed`` (:data:`TRACK_STREAM`)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"a track seed must be an int >= 0, got {seed!r}")
    return np.random.default_rng([int(seed), TRACK_STREAM])


def track_from_seed(seed: int, name: str | None = None) -> Track:
    """The track of track seed ``seed`` (named ``track-<seed>`` unless ``name`` is given)."""
    return generate_track(track_rng(seed), name or f"track-{int(seed)}")


def shortest_lap(
    spread: tuple[float, float, float] = (START_SPREAD,) * 3, gate_shift: float = 0.0, gate_shift_z: float | None = None
) -> tuple[float, float]:
    """``(L, H)`` for every track the rules allow, as :func:`racebench.envs.lap_bound.lap_geometry` gives for one
    track: no lap of any generated track is shorter than ``L`` m, and none starts more than ``H`` m above the ground.

    A point of a gate's opening lies within ``inner / sqrt(2)`` of its centre, plus ``sqrt(2 gate_shift^2 +
    gate_shift_z^2)`` for a shifted gate; a point of the start box within the box's half-diagonal of its centre. So
    the start leg is at least ``START_DISTANCE`` minus both, and each of the at least ``GATE_COUNTS[0] - 1`` legs
    between gates at least ``LEG_LENGTH[0]`` minus twice the gate's reach; the start lies at gate 0's height, at most
    ``GATE_HEIGHT[1]``, plus the spread.
    """
    shift_z = gate_shift if gate_shift_z is None else gate_shift_z
    reach = GATE_SIZE["inner"] / math.sqrt(2.0) + math.sqrt(2.0 * gate_shift**2 + shift_z**2)
    start = max(0.0, START_DISTANCE - float(np.linalg.norm(spread)) - reach)
    legs = (GATE_COUNTS[0] - 1) * max(0.0, LEG_LENGTH[0] - 2.0 * reach)
    return start + legs, GATE_HEIGHT[1] + float(spread[2])


# --------------------------------------------------------------------------- files
def _yaw_deg(yaw: float) -> float:
    """The shortest degrees value whose radians are exactly ``yaw`` (so that a file reads back the same float)."""
    degrees = math.degrees(yaw)
    for digits in range(16):
        candidate = round(degrees, digits) + 0.0
        if math.radians(candidate) == yaw:
            return candidate
    return degrees


def track_to_data(track: Track) -> dict[str, Any]:
    """``track`` as the plain data of a track file (``tracks/*.yaml``'s schema): :func:`parse_track` of it rebuilds
    the same track (every field but ``source``)."""
    first = track.gates[0]
    return {
        "name": track.name,
        "description": track.description,
        "closed_loop": track.closed_loop,
        "gate_size": {"inner": first.inner, "outer": first.outer, "depth": first.depth},
        "gates": [{"center": [float(v) for v in g.center], "yaw_deg": _yaw_deg(g.yaw)} for g in track.gates],
        "start": {
            "center": [float(v) for v in track.start.center],
            "yaw_deg": _yaw_deg(track.start.yaw),
            "spread": [float(v) for v in track.start.spread],
        },
        "obstacle_regions": [
            {"between": [int(r.between[0]), int(r.between[1])], "half_width": float(r.half_width)}
            for r in track.obstacle_regions
        ],
        "obstacle_band": {
            "half_width": float(track.obstacle_band.half_width),
            "end_margin": float(track.obstacle_band.end_margin),
            "profile": float(track.obstacle_band.profile),
        },
    }


def track_yaml(track: Track, header: str = "") -> str:
    """The YAML text of ``track`` (one flow-style line per gate and region), optionally after a comment ``header``."""
    if len({(g.inner, g.outer, g.depth) for g in track.gates}) != 1:
        raise ValueError(f"track {track.name!r}: a track file has one gate_size, its gates differ")
    data = track_to_data(track)

    def flow(value: Any) -> str:
        return yaml.safe_dump(value, default_flow_style=True, width=10_000, sort_keys=False).strip()

    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    lines += [f"{key}: {json.dumps(data[key])}" for key in ("name", "description", "closed_loop")]
    lines.append(f"gate_size: {flow(data['gate_size'])}")
    lines += ["gates:", *(f"  - {flow(g)}" for g in data["gates"])]
    lines += [f"start: {flow(data['start'])}", "obstacle_regions:"]
    lines += [f"  - {flow(r)}" for r in data["obstacle_regions"]]
    lines.append(f"obstacle_band: {flow(data['obstacle_band'])}")
    return "\n".join(lines) + "\n"


def write_track(track: Track, path: str | Path, header: str = "") -> Path:
    """Write ``track`` as a track file that :func:`~racebench.sim.track.load_track` reads back identically (every
    field but ``source``); returns the path."""
    path = Path(path)
    atomic_write(path, track_yaml(track, header))
    return path
