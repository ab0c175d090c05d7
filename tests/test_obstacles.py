"""Tests of the obstacle generator, the corridor search and ``Scene.distance``.

Geometry is re-derived here with plain formulas (point-segment and point-rectangle distances, boxes
built from the gate parameters), independently of the implementation under test.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from racebench.sim.obstacles import Footprints, ObstacleGenerator, find_corridor, footprint_distance
from racebench.sim.scene import Obstacle, Scene, arena_bounds
from racebench.sim.track import Gate, Track, load_track

TRACK_DIR = Path(__file__).parents[1] / "tracks"
SEEDS_PER_TRACK = 1000
COMBOS = ((3, 0.0), (5, 0.0), (3, 1.0), (5, 1.0))  # (density, gate_shift), cycled over the seeds
TOL = 1e-9


def _track(name: str) -> Track:
    return load_track(TRACK_DIR / f"{name}.yaml")


def _scene(track: Track, obstacles: tuple[Obstacle, ...] = (), gates: tuple[Gate, ...] | None = None) -> Scene:
    low, high = arena_bounds(track)
    gates = track.gates if gates is None else gates
    return Scene(track, gates, obstacles, track.start.center.copy(), track.start.yaw, low, high)


# --------------------------------------------------------------------------- independent geometry
def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points ``p`` to segments ``ab`` (any dimension, broadcast)."""
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _rect_distance(p: np.ndarray, centre: np.ndarray, half: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Distance from 2D points to rectangles yawed by ``yaw`` (0 inside), broadcast."""
    d = p - centre
    c, s = np.cos(yaw), np.sin(yaw)
    u = np.abs(c * d[..., 0] + s * d[..., 1]) - half[..., 0]
    v = np.abs(-s * d[..., 0] + c * d[..., 1]) - half[..., 1]
    return np.hypot(np.maximum(u, 0.0), np.maximum(v, 0.0))


def _polygon(obs: Obstacle) -> np.ndarray:
    """Corners of a box obstacle's footprint, in order around the rectangle."""
    c, s = math.cos(obs.yaw), math.sin(obs.yaw)
    hx, hy = obs.size[0], obs.size[1]
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return obs.position[:2] + local @ np.array([[c, s], [-s, c]])


def _box_to_shape(obs: Obstacle, vertices: np.ndarray) -> float:
    """Horizontal distance from a box obstacle to a convex shape given by 1, 2 or 4 ordered vertices."""
    corners = _polygon(obs)
    t = np.linspace(0.0, 1.0, 200)[:, None, None]
    ends_b = np.roll(vertices, -1, axis=0)
    # overlap: a dense sample of either boundary inside the other shape (shapes with area only)
    samples_b = (vertices + t * (ends_b - vertices)).reshape(-1, 2) - obs.position[:2]
    c, s = math.cos(obs.yaw), math.sin(obs.yaw)
    local = np.stack([c * samples_b[:, 0] + s * samples_b[:, 1], -s * samples_b[:, 0] + c * samples_b[:, 1]], axis=1)
    if np.any(np.all(np.abs(local) <= np.array(obs.size[:2]), axis=1)):
        return 0.0
    ends_a = np.roll(corners, -1, axis=0)
    if len(vertices) == 4:
        samples_a = (corners + t * (ends_a - corners)).reshape(-1, 2)
        edge, rel = (ends_b - vertices)[:, None], samples_a[None] - vertices[:, None]
        cross = edge[..., 0] * rel[..., 1] - edge[..., 1] * rel[..., 0]
        if np.any(np.all(cross >= 0, axis=0) | np.all(cross <= 0, axis=0)):
            return 0.0
    # disjoint convex shapes: the closest pair involves a vertex of one of them
    to_b = _segment_distance(corners[:, None], vertices[None], ends_b[None]).min()
    to_a = _segment_distance(vertices[:, None], corners[None], ends_a[None]).min()
    return float(min(to_a, to_b))


def _gate_bars(gate: Gate) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The 4 bars as (centre, half sizes along (normal, lateral, z), normal, lateral), from the gate data."""
    n = np.array([math.cos(gate.yaw), math.sin(gate.yaw), 0.0])
    lat = np.array([-math.sin(gate.yaw), math.cos(gate.yaw), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    w = (gate.outer - gate.inner) / 2.0
    off = gate.inner / 2.0 + w / 2.0
    d = gate.depth / 2.0
    return [
        (gate.center + off * up, np.array([d, gate.outer / 2.0, w / 2.0]), n, lat),
        (gate.center - off * up, np.array([d, gate.outer / 2.0, w / 2.0]), n, lat),
        (gate.center + off * lat, np.array([d, w / 2.0, gate.inner / 2.0]), n, lat),
        (gate.center - off * lat, np.array([d, w / 2.0, gate.inner / 2.0]), n, lat),
    ]


def _brute_distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Distance to every gate bar and obstacle: per-primitive formulas, broadcast over points x primitives."""
    best = np.full(len(points), np.inf)
    bars = [bar for gate in scene.gates for bar in _gate_bars(gate)]
    if bars:
        centre, half, n, lat = (np.array(v) for v in zip(*bars, strict=True))
        along = np.abs(points @ n.T - np.sum(centre * n, axis=1)) - half[:, 0]
        across = np.abs(points @ lat.T - np.sum(centre * lat, axis=1)) - half[:, 1]
        up = np.abs(points[:, 2:] - centre[:, 2]) - half[:, 2]
        excess = [np.maximum(v, 0.0) for v in (along, across, up)]
        best = np.minimum(best, np.sqrt(sum(e * e for e in excess)).min(axis=1))
    poles = [o for o in scene.obstacles if o.kind == "cylinder"]
    if poles:
        d = points[:, None] - np.array([o.position for o in poles])[None]
        radial = np.maximum(np.hypot(d[..., 0], d[..., 1]) - np.array([o.size[0] for o in poles]), 0.0)
        vertical = np.maximum(np.abs(d[..., 2]) - np.array([o.size[1] for o in poles]) / 2.0, 0.0)
        best = np.minimum(best, np.hypot(radial, vertical).min(axis=1))
    for obs in scene.obstacles:
        if obs.kind == "box":
            d = points - obs.position
            c, s = math.cos(obs.yaw), math.sin(obs.yaw)
            local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
            best = np.minimum(best, np.linalg.norm(np.maximum(np.abs(local) - np.array(obs.size), 0.0), axis=1))
    return best


def _densify(path: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Points along a polyline, at most ``step`` apart, including every vertex."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, math.ceil(np.linalg.norm(b - a) / step))
        out.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    return np.concatenate(out)


def _crossings(path: np.ndarray, gate: Gate, margin: float) -> np.ndarray:
    """Polyline positions (segment index + fraction) where the path crosses the gate plane along the normal,
    at least ``margin`` inside the opening."""
    n = np.array([math.cos(gate.yaw), math.sin(gate.yaw), 0.0])
    lat = np.array([-math.sin(gate.yaw), math.cos(gate.yaw), 0.0])
    side = (path - gate.center) @ n
    k = np.flatnonzero((side[:-1] < 0.0) & (side[1:] >= 0.0))
    t = -side[k] / (side[k + 1] - side[k])
    x = path[k] + t[:, None] * (path[k + 1] - path[k])
    inside = (np.abs((x - gate.center) @ lat) <= gate.inner / 2.0 - margin + TOL) & (
        np.abs(x[:, 2] - gate.center[2]) <= gate.inner / 2.0 - margin + TOL
    )
    return (k + t)[inside]


def _ceiling(gen: ObstacleGenerator, scene: Scene) -> float:
    """Fly no higher than the pole tops, unless a gate is so high that passing over its frame needs more."""
    top = max(g.center[2] + g.outer / 2.0 for g in scene.gates)
    return max(gen.pole_height, top + 2.0 * gen.corridor_radius + 0.2)


def _check_corridor(scene: Scene, radius: float, path: np.ndarray | None, label: str, ceiling: float = np.inf) -> None:
    assert path is not None, f"{label}: no corridor found"
    assert path.ndim == 2 and path.shape[1] == 3
    np.testing.assert_allclose(path[0], scene.track.start.center, err_msg=label)
    last = scene.gates[-1]
    np.testing.assert_allclose(path[-1], last.center + 0.25 * last.normal, atol=1e-9, err_msg=label)
    points = _densify(path)
    assert np.all(scene.distance(points) >= radius - TOL), f"{label}: path within radius of geometry"
    assert np.all(_brute_distance(scene, points) >= radius - TOL), f"{label}: path hits geometry (brute force)"
    assert np.all(points[:, 2] >= radius - TOL), f"{label}: path too close to the ground"
    assert np.all(points[:, 2] <= ceiling - radius + TOL), f"{label}: path above the ceiling"
    assert np.all(points >= scene.arena_low + radius - TOL) and np.all(points <= scene.arena_high - radius + TOL)
    position = -1.0
    for i, gate in enumerate(scene.gates):
        later = _crossings(path, gate, radius)
        later = later[later > position]
        assert len(later), f"{label}: gate {i} not passed through its opening, along its normal, in order"
        position = later.min()


def _check_clearances(gen: ObstacleGenerator, scene: Scene, label: str) -> None:
    """Clearance rules for cylinder scenes, vectorised over obstacles x gates."""
    track = gen.track
    obstacles = scene.obstacles
    assert len(obstacles) == gen.density * len(track.obstacle_regions), label
    assert all(o.kind == "cylinder" for o in obstacles)
    centre = np.array([o.position[:2] for o in obstacles])
    radius = np.array([o.size[0] for o in obstacles])
    assert set(radius.tolist()) <= set(gen.radius_choices), label
    assert all(o.size[1] == gen.pole_height and o.position[2] == gen.pole_height / 2.0 for o in obstacles), label
    band = track.obstacle_band
    for r, region in enumerate(track.obstacle_regions):
        a, b = scene.gates[region.between[0]].center[:2], scene.gates[region.between[1]].center[:2]
        own = centre[r * gen.density : (r + 1) * gen.density]
        if gen.placement == "box":
            lo, hi = np.minimum(a, b) - region.half_width, np.maximum(a, b) + region.half_width
            assert np.all((own >= lo - TOL) & (own <= hi + TOL)), f"{label}: obstacle outside region {r}"
        else:  # the strip along the leg a -> b, end_margin short of either gate, inside the arena
            length = float(np.linalg.norm(b - a))
            along = (b - a) / length
            t = (own - a) @ along
            u = (own - a) @ np.array([-along[1], along[0]])
            margin = min(band.end_margin, length / 2.0)
            assert np.all((t >= margin - TOL) & (t <= length - margin + TOL)), f"{label}: obstacle off leg {r}"
            assert np.all(np.abs(u) <= band.half_width + TOL), f"{label}: obstacle outside band {r}"
            low, high = scene.arena_low[:2], scene.arena_high[:2]
            assert np.all((own - radius[r * gen.density : (r + 1) * gen.density, None] > low) & (own < high)), label
    g_centre = np.array([g.center[:2] for g in scene.gates])
    g_yaw = np.array([g.yaw for g in scene.gates])
    lateral = np.stack([-np.sin(g_yaw), np.cos(g_yaw)], axis=1)
    inner = np.array([g.inner for g in scene.gates])[:, None]
    ends_a, ends_b = g_centre - lateral * inner / 2.0, g_centre + lateral * inner / 2.0
    to_opening = _segment_distance(centre[:, None], ends_a[None], ends_b[None]) - radius[:, None]
    assert np.all(to_opening >= gen.clearance - TOL), f"{label}: obstacle near a gate opening ({to_opening.min():.3f})"
    to_centre = np.linalg.norm(centre[:, None] - g_centre[None], axis=-1) - radius[:, None]
    assert np.all(to_centre >= gen.clearance - TOL), f"{label}: obstacle near a gate centre"
    frame_half = np.array([[g.depth / 2.0, g.outer / 2.0] for g in scene.gates])
    to_frame = _rect_distance(centre[:, None], g_centre[None], frame_half[None], g_yaw[None]) - radius[:, None]
    assert np.all(to_frame > 0.0), f"{label}: obstacle intersects a gate frame"
    start = track.start
    to_start = _rect_distance(centre, start.center[:2], start.spread[:2], np.zeros(len(centre))) - radius
    assert np.all(to_start >= gen.clearance - TOL), f"{label}: obstacle near the start region ({to_start.min():.3f})"
    gaps = np.linalg.norm(centre[:, None] - centre[None], axis=-1) - radius[:, None] - radius[None]
    assert np.all(gaps[~np.eye(len(centre), dtype=bool)] > 0.0), f"{label}: obstacles overlap"
    assert np.all(np.abs(scene.start_position - start.center) <= start.spread + TOL), f"{label}: start outside box"


# --------------------------------------------------------------------------- generator, many seeds
@pytest.mark.parametrize("name", ["S", "J", "Circle"])
def test_generated_scenes_keep_clearances_and_a_corridor(name: str) -> None:
    """1000 seeds per track (density 3/5 x gate_shift 0/1 cycled): clearances and a real corridor."""
    track = _track(name)
    gens = [ObstacleGenerator(track, density=d, gate_shift=s) for d, s in COMBOS]
    for seed in range(SEEDS_PER_TRACK):
        gen = gens[seed % len(gens)]
        scene = gen.sample_scene(np.random.default_rng(seed))
        label = f"{name} seed {seed} density {gen.density} shift {gen.gate_shift}"
        _check_clearances(gen, scene, label)
        ceiling = _ceiling(gen, scene)
        path = find_corridor(scene, gen.corridor_radius, ceiling=ceiling)
        _check_corridor(scene, gen.corridor_radius, path, label, ceiling)


@pytest.mark.parametrize("name", ["S", "J", "Circle"])
def test_corridor_check_rejects_blocked_layouts(name: str) -> None:
    """Fat poles often wall a leg off: such layouts are redrawn, and every scene returned has a corridor."""
    track = _track(name)
    gen = ObstacleGenerator(track, density=6, gate_shift=0.5, clearance=0.25, radius_choices=(0.3, 0.5))
    for seed in range(15):
        scene = gen.sample_scene(np.random.default_rng(seed))
        _check_clearances(gen, scene, f"{name} fat seed {seed}")
        ceiling = _ceiling(gen, scene)
        path = find_corridor(scene, gen.corridor_radius, ceiling=ceiling)
        _check_corridor(scene, gen.corridor_radius, path, f"{name} fat seed {seed}", ceiling)
    assert gen.rejections["corridor"] > 0


@pytest.mark.parametrize("name", ["S", "J", "Circle"])
def test_env_version_2_box_placement_keeps_clearances_and_a_corridor(name: str) -> None:
    """placement="box" (env version 2's, kept for campaign 1): the same rules, obstacles in the gate-centre box."""
    track = _track(name)
    gens = [ObstacleGenerator(track, density=d, gate_shift=s, placement="box") for d, s in COMBOS]
    for seed in range(60):
        gen = gens[seed % len(gens)]
        scene = gen.sample_scene(np.random.default_rng(seed))
        label = f"{name} box seed {seed}"
        _check_clearances(gen, scene, label)
        ceiling = _ceiling(gen, scene)
        _check_corridor(scene, gen.corridor_radius, find_corridor(scene, gen.corridor_radius, ceiling=ceiling), label,
                        ceiling)  # fmt: skip


@pytest.mark.parametrize("kind", ["box", "mixed"])
@pytest.mark.parametrize("name", ["S", "J", "Circle"])
def test_box_obstacles_keep_clearances_and_a_corridor(name: str, kind: str) -> None:
    """Box footprints (yawed rectangles) obey the same rules, checked with polygon distances."""
    track = _track(name)
    gen = ObstacleGenerator(track, density=5, kind=kind, gate_shift=1.0)
    for seed in range(25):
        scene = gen.sample_scene(np.random.default_rng(seed))
        label = f"{name} {kind} seed {seed}"
        assert len(scene.obstacles) == 5 * len(track.obstacle_regions)
        kinds = {o.kind for o in scene.obstacles}
        assert kinds == {"box"} if kind == "box" else kinds <= {"box", "cylinder"}
        start = track.start
        start_box = start.center[:2] + np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * start.spread[:2]
        for obs in scene.obstacles:
            if obs.kind == "cylinder":
                continue
            assert set(obs.size[:2]) <= set(gen.box_half_choices) and obs.size[2] == gen.pole_height / 2.0
            for gate in scene.gates:
                lat = np.array([-math.sin(gate.yaw), math.cos(gate.yaw)])
                nrm = np.array([math.cos(gate.yaw), math.sin(gate.yaw)])
                opening = np.array([gate.center[:2] - lat * gate.inner / 2, gate.center[:2] + lat * gate.inner / 2])
                assert _box_to_shape(obs, opening) >= gen.clearance - TOL, f"{label}: box near a gate opening"
                assert _box_to_shape(obs, gate.center[None, :2]) >= gen.clearance - TOL, label
                frame = gate.center[:2] + np.array(
                    [
                        a * nrm * gate.depth / 2 + b * lat * gate.outer / 2
                        for a, b in ((1, 1), (-1, 1), (-1, -1), (1, -1))
                    ]
                )
                assert _box_to_shape(obs, frame) > 0.0, f"{label}: box intersects a gate frame"
            assert _box_to_shape(obs, start_box) >= gen.clearance - TOL, f"{label}: box near the start region"
        ceiling = _ceiling(gen, scene)
        path = find_corridor(scene, gen.corridor_radius, ceiling=ceiling)
        _check_corridor(scene, gen.corridor_radius, path, label, ceiling)


def test_same_seed_same_scene_and_different_seeds_differ() -> None:
    """A seed fixes gates, start and obstacles; other seeds give other scenes."""
    gen = ObstacleGenerator(_track("Circle"), density=4, kind="mixed", gate_shift=1.0)
    first = gen.sample_scene(np.random.default_rng(7)).to_dict()
    again = gen.sample_scene(np.random.default_rng(7)).to_dict()
    other = ObstacleGenerator(_track("Circle"), density=4, kind="mixed", gate_shift=1.0)
    assert first == again == other.sample_scene(np.random.default_rng(7)).to_dict()
    layouts = {str(gen.sample_scene(np.random.default_rng(seed)).to_dict()) for seed in range(20)}
    assert len(layouts) == 20
    for seed in (1, 2):
        d = gen.sample_scene(np.random.default_rng(seed)).to_dict()
        assert d["obstacles"] != first["obstacles"] and d["gates"] != first["gates"] and d["start"] != first["start"]


def test_vertical_gate_shift_has_its_own_range() -> None:
    """The paper's randomisation: ±1 m on x/y, ±0.3 m on z; without gate_shift_z, z uses gate_shift."""
    track = _track("S")
    gen = ObstacleGenerator(track, density=0, gate_shift=1.0, gate_shift_z=0.3)
    shifts = np.array(
        [
            g.center - o.center
            for seed in range(60)
            for g, o in zip(gen.sample_scene(np.random.default_rng(seed)).gates, track.gates, strict=True)
        ]
    )
    assert np.all(np.abs(shifts[:, :2]) <= 1.0) and np.abs(shifts[:, :2]).max() > 0.8
    assert np.all(np.abs(shifts[:, 2]) <= 0.3 + TOL) and np.abs(shifts[:, 2]).max() > 0.2
    same = ObstacleGenerator(track, density=2, gate_shift=0.5)
    explicit = ObstacleGenerator(track, density=2, gate_shift=0.5, gate_shift_z=0.5)
    for seed in range(5):
        a = same.sample_scene(np.random.default_rng(seed)).to_dict()
        b = explicit.sample_scene(np.random.default_rng(seed)).to_dict()
        assert a == b
    with pytest.raises(ValueError, match="gate_shift_z"):
        ObstacleGenerator(track, gate_shift_z=-0.1)


def test_gate_perturbation_stays_within_bounds_and_above_ground() -> None:
    track = _track("J")
    low_gates = tuple(g.moved(np.array([g.center[0], g.center[1], 0.7])) for g in track.gates)
    for base in (track, dataclasses.replace(track, gates=low_gates)):
        delta = 1.0
        gen = ObstacleGenerator(base, density=2, gate_shift=delta)
        for seed in range(150):
            scene = gen.sample_scene(np.random.default_rng(seed))
            for placed, orig in zip(scene.gates, base.gates, strict=True):
                shift = placed.center - orig.center
                assert np.all(np.abs(shift[:2]) <= delta)
                z_low = max(orig.center[2] - delta, min(orig.center[2], orig.outer / 2 + 0.1))
                assert z_low - TOL <= placed.center[2] <= orig.center[2] + delta
                assert placed.center[2] - placed.outer / 2 > 0.0, "gate frame touches the ground"
                assert placed.yaw == orig.yaw and placed.inner == orig.inner
        shifts = np.array(
            [
                g.center - o.center
                for seed in range(30)
                for g, o in zip(gen.sample_scene(np.random.default_rng(seed)).gates, base.gates, strict=True)
            ]
        )
        assert shifts[:, 0].min() < -0.5 and shifts[:, 0].max() > 0.5  # the full range is used
    gen = ObstacleGenerator(track, density=3, gate_shift=0.0)
    for seed in range(20):
        scene = gen.sample_scene(np.random.default_rng(seed))
        for placed, orig in zip(scene.gates, track.gates, strict=True):
            assert np.array_equal(placed.center, orig.center) and placed.yaw == orig.yaw


def test_density_zero_gives_no_obstacles() -> None:
    scene = ObstacleGenerator(_track("S"), density=0).sample_scene(np.random.default_rng(0))
    assert scene.obstacles == ()


def test_impossible_layout_raises_runtime_error() -> None:
    gen = ObstacleGenerator(_track("S"), density=3, clearance=5.0, max_attempts=3)
    with pytest.raises(RuntimeError, match="no valid layout.*3 attempts"):
        gen.sample_scene(np.random.default_rng(0))
    assert gen.rejections["placement"] == 3


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"density": -1}, "density"),
        ({"density": 2.5}, "density"),
        ({"density": True}, "density"),
        ({"kind": "sphere"}, "kind"),
        ({"gate_shift": -0.1}, "gate_shift"),
        ({"gate_shift": float("nan")}, "gate_shift"),
        ({"clearance": -1.0}, "clearance"),
        ({"drone_radius": 0.0}, "drone_radius"),
        ({"corridor_margin": -0.01}, "corridor_margin"),
        ({"pole_height": 0.0}, "pole_height"),
        ({"radius_choices": ()}, "radius_choices"),
        ({"radius_choices": (0.1, -0.1)}, "radius_choices"),
        ({"box_half_choices": (0.0,)}, "box_half_choices"),
        ({"grid_resolution": 0.0}, "grid_resolution"),
        ({"max_attempts": 0}, "max_attempts"),
        ({"max_attempts": 10**9}, "max_attempts"),
        ({"density": 10**6}, "density"),
        ({"gate_shift": 1e6}, "gate_shift"),
        ({"gate_shift": 0.5, "gate_shift_z": 1e6}, "gate_shift_z"),
        ({"gate_shift": 1.5}, "gate_shift_z"),
        ({"drone_radius": float("inf")}, "drone_radius"),
        ({"drone_radius": 0.5}, "drone_radius"),
        ({"grid_resolution": 1e-4}, "grid_resolution"),
        ({"grid_resolution": float("nan")}, "grid_resolution"),
    ],
)
def test_constructor_validation_names_the_parameter(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name} must"):
        ObstacleGenerator(_track("S"), **kwargs)


# --------------------------------------------------------------------------- corridor search on built scenes
def _wall(x: float, y_from: float, y_to: float, height: float) -> Obstacle:
    """A thin box wall across the track at ``x`` spanning ``y_from..y_to``."""
    return Obstacle("box", np.array([x, (y_from + y_to) / 2, height / 2]), (0.05, (y_to - y_from) / 2, height / 2))


def test_find_corridor_on_empty_and_blocked_scenes() -> None:
    track = _track("S")
    radius = 0.2
    empty = _scene(track)
    _check_corridor(empty, radius, find_corridor(empty, radius), "empty")
    top = float(empty.arena_high[2])
    low, high = empty.arena_low, empty.arena_high
    blocked = _scene(track, (_wall(9.0, low[1], high[1], top),))
    assert find_corridor(blocked, radius) is None
    # a wall lower than the arena can be flown over, but not below a ceiling lower than the wall
    low_wall = _scene(track, (_wall(9.0, low[1], high[1], 2.5),))
    _check_corridor(low_wall, radius, find_corridor(low_wall, radius), "low wall")
    assert find_corridor(low_wall, radius, ceiling=2.5) is None
    # a pole in a gate opening blocks the passage itself
    plugged = _scene(track, (Obstacle("cylinder", np.array([7.0, -1.0, 1.5]), (0.1, 3.0)),))
    assert find_corridor(plugged, radius) is None


@pytest.mark.parametrize("gap_y", [0.3, 3.3])
def test_find_corridor_detours_through_a_gap(gap_y: float) -> None:
    """A full-height wall between gates 1 and 2 with one gap: near the leg (local grid) or far (whole arena)."""
    track = _track("S")
    radius = 0.2
    empty = _scene(track)
    top, low, high = float(empty.arena_high[2]), empty.arena_low, empty.arena_high
    walls = (_wall(9.0, low[1], gap_y - 0.35, top), _wall(9.0, gap_y + 0.35, high[1], top))
    scene = _scene(track, walls)
    path = find_corridor(scene, radius)
    _check_corridor(scene, radius, path, f"gap at {gap_y}")
    points = _densify(path)
    at_wall = points[np.abs(points[:, 0] - 9.0) < 0.01]
    assert len(at_wall) and np.all(np.abs(at_wall[:, 1] - gap_y) <= 0.35 - radius + TOL)
    narrow = _scene(track, (_wall(9.0, low[1], gap_y - 0.15, top), _wall(9.0, gap_y + 0.15, high[1], top)))
    assert find_corridor(narrow, radius) is None  # a 0.3 m gap is narrower than the 0.4 m sphere


def test_find_corridor_rejects_a_blocked_start_and_bad_arguments() -> None:
    track = _track("J")
    scene = _scene(track, (Obstacle("cylinder", np.array([2.0, 3.0, 1.5]), (0.15, 3.0)),))
    assert find_corridor(scene, 0.2) is None
    assert find_corridor(scene, 0.2, start=np.array([2.0, 2.0, 1.0])) is not None
    with pytest.raises(ValueError, match="radius"):
        find_corridor(scene, 0.0)


# --------------------------------------------------------------------------- footprints
def _fp(centre: list, half: list, yaw: float = 0.0, rounding: float = 0.0) -> Footprints:
    return Footprints(np.array([centre], float), np.array([half], float), np.array([yaw]), np.array([rounding]))


def test_footprint_distance_hand_cases() -> None:
    square = _fp([0, 0], [0.5, 0.5])
    cases = [
        (_fp([2, 0], [0.5, 0.5]), 1.0),  # side to side
        (_fp([2, 0], [0.5, 0.5], math.pi / 4), 1.5 - math.sqrt(0.5)),  # a corner pointing at a side
        (_fp([0, 1.7], [0, 0], rounding=0.2), 1.0),  # a disc above the top side
        (_fp([1.5, 1.5], [0, 0], rounding=0.2), math.hypot(1, 1) - 0.2),  # a disc off a corner
        (_fp([0, 0.9], [1.0, 0.0]), 0.4),  # a segment above, longer than the square
        (_fp([0.3, 0.2], [0.1, 0.1]), 0.0),  # inside
        (_fp([0, 0], [2.0, 0.1]), 0.0),  # a cross: no corner of either lies inside the other
        (_fp([0, 0], [1.0, 0.0], math.pi / 3), 0.0),  # a segment straight through
    ]
    for other, expected in cases:
        assert footprint_distance(square, other)[0, 0] == pytest.approx(expected, abs=1e-12)
        assert footprint_distance(other, square)[0, 0] == pytest.approx(expected, abs=1e-12)


def test_footprint_distance_matches_polygon_distance() -> None:
    rng = np.random.default_rng(5)
    n = 300
    a = Footprints(rng.uniform(-1, 1, (n, 2)), rng.uniform(0.05, 0.6, (n, 2)), rng.uniform(-3, 3, n), np.zeros(n))
    b = Footprints(rng.uniform(-1, 1, (4, 2)), rng.uniform(0.05, 0.6, (4, 2)), rng.uniform(-3, 3, 4), np.zeros(4))
    got = footprint_distance(a, b)
    assert got.shape == (n, 4) and np.any(got == 0.0) and np.any(got > 0.0)
    for j in range(4):
        other = Obstacle("box", np.array([*b.centre[j], 0.0]), (*b.half[j], 1.0), float(b.yaw[j]))
        for i in range(n):
            box = Obstacle("box", np.array([*a.centre[i], 0.0]), (*a.half[i], 1.0), float(a.yaw[i]))
            assert got[i, j] == pytest.approx(_box_to_shape(box, _polygon(other)), abs=1e-9)


# --------------------------------------------------------------------------- Scene.distance
def test_scene_distance_hand_computed_values() -> None:
    track = _track("S")
    pole = Obstacle("cylinder", np.array([20.0, 10.0, 1.5]), (0.1, 3.0))
    box = Obstacle("box", np.array([30.0, 10.0, 0.5]), (0.5, 0.2, 0.5), yaw=math.pi / 4)
    gate = Gate(center=np.array([40.0, 0.0, 1.0]), yaw=0.0)
    turned = Gate(center=np.array([50.0, 0.0, 1.0]), yaw=math.pi / 2)
    scene = _scene(track, (pole, box), gates=(gate, turned))
    cases = [
        ([21.0, 10.0, 1.0], 0.9),  # 1 m from the pole axis
        ([20.0, 10.0, 4.0], 1.0),  # straight above the top
        ([20.5, 10.0, 3.3], math.hypot(0.4, 0.3)),  # diagonally off the top rim
        ([20.05, 10.0, 1.0], 0.0),  # inside the pole
        ([30.1, 10.1, 0.2], 0.0),  # inside the box
        ([30.0, 10.0, 1.75], 0.75),  # above the box
        ([30.0 - 0.6 / math.sqrt(2), 10.0 + 0.6 / math.sqrt(2), 0.5], 0.4),  # 0.6 m along the box's local y
        ([40.0, 0.0, 1.0], 0.5),  # gate centre: 0.5 m to every inner face
        ([41.0, -0.57, 1.0], 0.95),  # 1 m in front of the right bar, 0.05 m half depth
        ([40.0, 0.0, 1.64 + 0.3], 0.3),  # above the top bar
        ([50.2, 0.3, 1.0], math.hypot(0.3, 0.25)),  # off the corner of a side bar of the gate facing +y
    ]
    points = np.array([p for p, _ in cases])
    expected = np.array([d for _, d in cases])
    np.testing.assert_allclose(scene.distance(points), expected, atol=1e-12)
    np.testing.assert_allclose(_brute_distance(scene, points), expected, atol=1e-12)
    assert scene.distance(points[0]).shape == ()
    assert scene.distance(np.zeros((4, 5, 3))).shape == (4, 5)
    with pytest.raises(ValueError, match="shape"):
        scene.distance(np.zeros((4, 2)))


def test_scene_distance_matches_brute_force_and_empty_scene_is_infinite() -> None:
    gen = ObstacleGenerator(_track("Circle"), density=5, kind="mixed", gate_shift=1.0)
    scene = gen.sample_scene(np.random.default_rng(3))
    points = np.random.default_rng(4).uniform(scene.arena_low, scene.arena_high, size=(20000, 3))
    np.testing.assert_allclose(scene.distance(points), _brute_distance(scene, points), atol=1e-12)
    track = _track("S")
    low, high = arena_bounds(track)
    nothing = Scene(track, (), (), track.start.center, 0.0, low, high)
    assert np.all(np.isinf(nothing.distance(points[:3])))


def test_scene_clearance_is_the_distance_to_geometry_and_walls() -> None:
    """The compiled, culled query equals min(brute-force distance, distance to the volume's faces)."""
    gen = ObstacleGenerator(_track("J"), density=5, kind="mixed", gate_shift=1.0)
    scene = gen.sample_scene(np.random.default_rng(5))
    rng = np.random.default_rng(6)
    low, high = scene.arena_low, scene.arena_high
    spread = rng.uniform(low - 0.5, high + 0.5, size=(20000, 3))  # some outside the volume: negative
    centre, half, _, _ = scene.primitive_arrays
    pick = rng.integers(len(centre), size=20000)
    close = centre[pick] + rng.normal(0.0, 0.7, size=(20000, 3)) * (half[pick] + 0.1)
    for points in (spread, close):  # far from everything, and where culling must keep the nearest primitive
        walls = np.minimum((points - low).min(axis=1), (high - points).min(axis=1))
        expected = np.minimum(_brute_distance(scene, points), walls)
        np.testing.assert_allclose(scene.clearance(points, low, high), expected, rtol=0, atol=1e-12)
    assert (scene.clearance(spread, low, high) < 0).any() and (scene.clearance(close, low, high) == 0).any()
    track = _track("S")
    nothing = Scene(track, (), (), track.start.center, 0.0, *arena_bounds(track))
    inside = np.array([[0.0, 0.0, 1.0]])
    expected = np.minimum((inside - nothing.arena_low).min(), (nothing.arena_high - inside).min())
    assert nothing.clearance(inside, nothing.arena_low, nothing.arena_high)[0] == pytest.approx(expected)
    with pytest.raises(ValueError, match="shape"):
        scene.clearance(np.zeros(3), low, high)
    with pytest.raises(ValueError, match="low and high"):
        scene.clearance(spread[:2], low[:2], high)
    broken = np.array([[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 0.0, np.nan]])
    assert np.isnan(scene.clearance(broken, low, high)).all()  # never a finite clearance for a broken point
