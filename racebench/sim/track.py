"""Race tracks: gates, start region and obstacle regions, loaded from YAML files.

A track is data, not code: ``tracks/*.yaml`` ship the paper's S, J and 3D-Circle tracks and users can
pass the path of their own file anywhere a track name is accepted. Every field is validated on load and
a bad file raises :class:`TrackFormatError` naming the file and the field.

Frame convention: x forward, y left, z up, metres. A gate's ``yaw`` is the heading of its normal,
the direction in which it must be flown through (0 = +x, +pi/2 = +y).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from racebench.utils.data import data_file
from racebench.utils.yamlfile import yaml_problem

BUILTIN_TRACKS: tuple[str, ...] = ("S", "J", "Circle")


class TrackFormatError(ValueError):
    """A track file is malformed; the message names the file and the offending field."""


@dataclass(frozen=True)
class Gate:
    """A square racing gate: a frame of four bars around a square opening.

    Attributes:
        center: centre of the opening (world frame, m).
        yaw: heading of the gate normal (rad); the gate is passed flying along the normal.
        inner: side of the square opening (m).
        outer: outer side of the frame (m); bars are ``(outer - inner) / 2`` wide.
        depth: thickness of the frame along the normal (m).
    """

    center: np.ndarray
    yaw: float
    inner: float = 1.0
    outer: float = 1.28
    depth: float = 0.10

    @property
    def normal(self) -> np.ndarray:
        """Unit vector along which the gate is traversed."""
        return np.array([math.cos(self.yaw), math.sin(self.yaw), 0.0])

    @property
    def lateral(self) -> np.ndarray:
        """Unit vector in the gate plane, horizontal (the opening's width axis)."""
        return np.array([-math.sin(self.yaw), math.cos(self.yaw), 0.0])

    @property
    def bar_width(self) -> float:
        """Width of each frame bar (m)."""
        return (self.outer - self.inner) / 2.0

    def bars(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four frame bars as ``(centre, half_extents)`` boxes in the gate's own frame.

        The gate frame has x along the normal, y along :attr:`lateral`, z up; rotate by :attr:`yaw`
        and translate by :attr:`center` to get world coordinates.
        """
        w, half_out, half_in = self.bar_width, self.outer / 2.0, self.inner / 2.0
        mid = half_in + w / 2.0
        d = self.depth / 2.0
        return [
            (np.array([0.0, 0.0, mid]), np.array([d, half_out, w / 2.0])),  # top
            (np.array([0.0, 0.0, -mid]), np.array([d, half_out, w / 2.0])),  # bottom
            (np.array([0.0, mid, 0.0]), np.array([d, w / 2.0, half_in])),  # left
            (np.array([0.0, -mid, 0.0]), np.array([d, w / 2.0, half_in])),  # right
        ]

    def passed_by(self, p0: Sequence[float], p1: Sequence[float]) -> bool:
        """Whether the segment ``p0 → p1`` crosses the gate plane inside the opening, along the normal.

        The crossing must go from the back half-space (``(p − c)·n < 0``) to the front (``≥ 0``); the
        intersection point with the plane must lie inside the square opening.
        """
        # Plain floats: this runs at every physics step, where numpy's per-call overhead dominates.
        cx, cy, cz, nx, ny = self._plane
        ax, ay, az = float(p0[0]) - cx, float(p0[1]) - cy, float(p0[2]) - cz
        bx, by, bz = float(p1[0]) - cx, float(p1[1]) - cy, float(p1[2]) - cz
        s0 = ax * nx + ay * ny
        s1 = bx * nx + by * ny
        if not (s0 < 0.0 <= s1):
            return False
        f = s0 / (s0 - s1)
        hx, hy, hz = ax + (bx - ax) * f, ay + (by - ay) * f, az + (bz - az) * f
        half = self.inner / 2.0
        return abs(-hx * ny + hy * nx) <= half and abs(hz) <= half  # (lateral = (−n_y, n_x, 0))

    @cached_property
    def _plane(self) -> tuple[float, float, float, float, float]:
        """Centre and horizontal normal as floats, computed once per gate."""
        return (*(float(v) for v in self.center), math.cos(self.yaw), math.sin(self.yaw))

    def moved(self, center: np.ndarray) -> Gate:
        """A copy of this gate with its centre moved to ``center``."""
        return replace(self, center=np.asarray(center, dtype=float))


@dataclass(frozen=True)
class StartRegion:
    """Where episodes start: a box of half-sizes ``spread`` around ``center``, heading ``yaw``."""

    center: np.ndarray
    yaw: float
    spread: np.ndarray


@dataclass(frozen=True)
class ObstacleRegion:
    """Obstacles are drawn in the cuboid spanned by gates ``between`` widened by ``half_width``."""

    between: tuple[int, int]
    half_width: float


@dataclass(frozen=True)
class ObstacleBand:
    """Where ``placement="band"`` draws obstacles: a strip along each region's leg (gate centre to gate centre).

    Attributes:
        half_width: lateral half-width of the strip (m), perpendicular to the leg, horizontal.
        end_margin: length kept free at each end of the leg (m), along it.
        profile: exponent of the lateral offset ``half_width · sign(s) · |s|^profile``, ``s`` uniform in [-1, 1]: 1 is
            uniform across the strip, larger values crowd obstacles towards the racing line.
    """

    half_width: float = 1.9
    end_margin: float = 0.5
    profile: float = 1.0


@dataclass(frozen=True)
class Track:
    """A race track as loaded from a YAML file (see the module docstring and docs/environment.md)."""

    name: str
    gates: tuple[Gate, ...]
    start: StartRegion
    closed_loop: bool
    obstacle_regions: tuple[ObstacleRegion, ...] = field(default_factory=tuple)
    obstacle_band: ObstacleBand = field(default_factory=ObstacleBand)
    description: str = ""
    source: str = ""

    @property
    def num_gates(self) -> int:
        """Number of gates; one lap (closed loop) or one run (sprint) passes each once, in order."""
        return len(self.gates)


def track_path(name_or_path: str | Path) -> Path:
    """Resolve a built-in track name (``"S"``, ``"J"``, ``"Circle"``) or a file path to a path."""
    if str(name_or_path) in BUILTIN_TRACKS:
        return data_file("tracks", str(name_or_path))
    path = Path(name_or_path)
    if not path.is_file():
        raise FileNotFoundError(
            f"track {str(name_or_path)!r} is neither a built-in track {BUILTIN_TRACKS} nor an existing file"
        )
    return path


def load_track(name_or_path: str | Path) -> Track:
    """Load and validate a track from a built-in name or a YAML file path."""
    path = track_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise TrackFormatError(f"{path}: not valid YAML: {yaml_problem(exc)}") from exc
    return parse_track(data, source=str(path))


def _fail(source: str, where: str, what: str) -> TrackFormatError:
    return TrackFormatError(f"{source}: field '{where}': {what}")


def _number(value: Any, source: str, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _fail(source, where, f"expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise _fail(source, where, f"must be > 0, got {value!r}")
    return float(value)


def _vector(value: Any, source: str, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise _fail(source, where, f"expected a list of 3 numbers [x, y, z], got {value!r}")
    return np.array([_number(v, source, f"{where}[{i}]") for i, v in enumerate(value)])


def _require(mapping: Any, key: str, source: str, where: str) -> Any:
    if not isinstance(mapping, dict):
        raise _fail(source, where, f"expected a mapping, got {mapping!r}")
    if key not in mapping:
        raise _fail(source, f"{where}.{key}" if where else key, "missing")
    return mapping[key]


def _check_keys(mapping: dict, allowed: set[str], source: str, where: str) -> None:
    unknown = sorted(set(mapping) - allowed)
    if unknown:
        prefix = f"{where}." if where else ""
        raise _fail(source, prefix + unknown[0], f"unknown field (allowed: {sorted(allowed)})")


def parse_track(data: Any, source: str = "<track>") -> Track:
    """Validate a track given as plain data (the parsed YAML) and build a :class:`Track`."""
    if not isinstance(data, dict):
        raise TrackFormatError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    _check_keys(
        data,
        {"name", "description", "closed_loop", "gate_size", "gates", "start", "obstacle_regions", "obstacle_band"},
        source,
        "",
    )
    name = _require(data, "name", source, "")
    if not isinstance(name, str) or not name:
        raise _fail(source, "name", f"expected a non-empty string, got {name!r}")
    closed_loop = _require(data, "closed_loop", source, "")
    if not isinstance(closed_loop, bool):
        raise _fail(source, "closed_loop", f"expected true or false, got {closed_loop!r}")

    size = data.get("gate_size", {})
    if not isinstance(size, dict):
        raise _fail(source, "gate_size", f"expected a mapping, got {size!r}")
    _check_keys(size, {"inner", "outer", "depth"}, source, "gate_size")
    inner = _number(size.get("inner", 1.0), source, "gate_size.inner", positive=True)
    outer = _number(size.get("outer", 1.28), source, "gate_size.outer", positive=True)
    depth = _number(size.get("depth", 0.10), source, "gate_size.depth", positive=True)
    if outer <= inner:
        raise _fail(source, "gate_size.outer", f"must exceed inner ({inner}), got {outer}")

    raw_gates = _require(data, "gates", source, "")
    if not isinstance(raw_gates, list) or len(raw_gates) < 2:
        raise _fail(source, "gates", f"expected a list of at least 2 gates, got {raw_gates!r}")
    gates = []
    for i, g in enumerate(raw_gates):
        where = f"gates[{i}]"
        if not isinstance(g, dict):
            raise _fail(source, where, f"expected a mapping, got {g!r}")
        _check_keys(g, {"center", "yaw_deg"}, source, where)
        center = _vector(_require(g, "center", source, where), source, f"{where}.center")
        yaw = math.radians(_number(_require(g, "yaw_deg", source, where), source, f"{where}.yaw_deg"))
        if center[2] - outer / 2.0 < 0.0:
            raise _fail(
                source,
                f"{where}.center",
                f"gate frame reaches below the ground (z={center[2]} < outer/2={outer / 2})",
            )
        for j, other in enumerate(gates):
            # Closer than a frame's side, two frames overlap or leave no room to fly between them.
            gap = float(np.linalg.norm(center - other.center))
            if gap < outer:
                raise _fail(
                    source,
                    f"{where}.center",
                    f"gate {i} is {gap:.3g} m from gate {j}: gate centres must be at least outer={outer} m apart",
                )
        gates.append(Gate(center=center, yaw=yaw, inner=inner, outer=outer, depth=depth))

    raw_start = _require(data, "start", source, "")
    if not isinstance(raw_start, dict):
        raise _fail(source, "start", f"expected a mapping, got {raw_start!r}")
    _check_keys(raw_start, {"center", "yaw_deg", "spread"}, source, "start")
    start_center = _vector(_require(raw_start, "center", source, "start"), source, "start.center")
    if start_center[2] <= 0.0:
        raise _fail(source, "start.center", f"start must be above the ground, got z={start_center[2]}")
    start_yaw = math.radians(_number(_require(raw_start, "yaw_deg", source, "start"), source, "start.yaw_deg"))
    spread = _vector(raw_start.get("spread", [0.0, 0.0, 0.0]), source, "start.spread")
    if np.any(spread < 0):
        raise _fail(source, "start.spread", f"half-sizes must be >= 0, got {spread.tolist()}")
    if start_center[2] - spread[2] <= 0.0:
        raise _fail(source, "start.spread", "start region reaches the ground")

    regions = []
    raw_regions = data.get("obstacle_regions", [])
    if not isinstance(raw_regions, list):
        raise _fail(source, "obstacle_regions", f"expected a list, got {raw_regions!r}")
    for i, r in enumerate(raw_regions):
        where = f"obstacle_regions[{i}]"
        if not isinstance(r, dict):
            raise _fail(source, where, f"expected a mapping, got {r!r}")
        _check_keys(r, {"between", "half_width"}, source, where)
        between = _require(r, "between", source, where)
        if (
            not isinstance(between, list)
            or len(between) != 2
            or not all(isinstance(b, int) and not isinstance(b, bool) for b in between)
            or not all(0 <= b < len(gates) for b in between)
            or between[0] == between[1]
        ):
            expected = f"expected two different gate indices in [0, {len(gates) - 1}], got {between!r}"
            raise _fail(source, f"{where}.between", expected)
        half_width = _number(r.get("half_width", 1.2), source, f"{where}.half_width", positive=True)
        regions.append(ObstacleRegion(between=(between[0], between[1]), half_width=half_width))

    raw_band = data.get("obstacle_band", {})
    if not isinstance(raw_band, dict):
        raise _fail(source, "obstacle_band", f"expected a mapping, got {raw_band!r}")
    _check_keys(raw_band, {"half_width", "end_margin", "profile"}, source, "obstacle_band")
    default_band = ObstacleBand()
    band = ObstacleBand(
        half_width=_number(
            raw_band.get("half_width", default_band.half_width), source, "obstacle_band.half_width", positive=True
        ),
        end_margin=_number(raw_band.get("end_margin", default_band.end_margin), source, "obstacle_band.end_margin"),
        profile=_number(raw_band.get("profile", default_band.profile), source, "obstacle_band.profile", True),
    )
    if band.end_margin < 0:
        raise _fail(source, "obstacle_band.end_margin", f"must be >= 0, got {band.end_margin!r}")

    description = data.get("description", "")
    if not isinstance(description, str):
        raise _fail(source, "description", f"expected a string, got {description!r}")
    return Track(
        name=name,
        gates=tuple(gates),
        start=StartRegion(center=start_center, yaw=start_yaw, spread=spread),
        closed_loop=closed_loop,
        obstacle_regions=tuple(regions),
        obstacle_band=band,
        description=description,
        source=source,
    )
