"""Fast depth for many cameras at once: analytic ray casting of the scene's primitives, compiled with numba.

The scene is made of few, simple primitives: the ground plane ``z = 0``, the gate bars and box obstacles
(boxes yawed about z, :meth:`racebench.sim.scene.Scene.boxes`) and vertical cylinders
(:meth:`racebench.sim.scene.Scene.cylinders`). Instead of rasterising their triangles, every pixel's ray is
intersected with them exactly. Each primitive is first projected to a screen rectangle (its 8 bounding
corners, clipped at the near plane), so a ray is only tested against the primitives that can cover its
pixel; one compiled call renders a whole batch of cameras, each looking at its own scene.

The image reproduces PyBullet's ``getCameraImage`` with TinyRenderer, as used by
:class:`racebench.sim.camera.DepthCamera` (measured, and tested over thousands of poses in
``tests/test_raycast.py``):

* pixel ``(i, j)`` samples the ray ``(j − size/2)`` pixels right of and ``(i + 1 − size/2)`` pixels below
  the optical axis (TinyRenderer's integer pixel grid with its row flip);
* the value is depth along the optical axis, not the ray length;
* back faces are culled and surfaces closer than the near plane are clipped: a surface whose entry point is
  nearer than ``near`` is invisible (also when the camera is inside a primitive);
* nothing within ``far`` reads ``far``; the result is clipped to the sensor range like ``DepthCamera.depth``;
* a cylinder is not drawn as a circle: PyBullet's renderer draws the convex hull of the support points of a
  32-gon prism in 42 fixed directions (an icosphere: the 12 vertices and 30 edge midpoints of an
  icosahedron), each pushed out by the 1 mm collision margin along its direction. Top and bottom keep
  different corners (the icosphere's two rings are 36° apart), so the facets are slanted, up to 22.5° wide
  and up to 2 % of the radius inside the circle, which matters where a pole is seen at a grazing angle from
  close by. :func:`cylinder_hull` rebuilds that polyhedron (measured: PyBullet's depth across a pole's
  facets to 0.1 mm on most pixels, 0.3 % on all) and the ray caster intersects its planes. Beyond
  :data:`LOD_DISTANCE` a pole is cast as its circumscribed cylinder, which is cheaper and a few mm off.

Numba, not numpy or torch, because the work is irregular (a few primitives, each covering a small, varying
part of the image): vectorised with numpy, every ray against every primitive (no screen rectangles), one
frame took 23 ms here, 9x slower than TinyRenderer; torch on this CPU-only machine would run the same dense
array work. Compiled loops skip it: about 50 µs a frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
from numba import njit
from scipy.spatial import ConvexHull

from racebench.sim.camera import DepthCamera
from racebench.sim.scene import Scene

BOX_FIELDS = 8  # centre x, y, z, half x, y, z, cos(yaw), sin(yaw)
HULL_FIELDS = 10  # axis x, y, circumradius, z low, z high, cap-free z low, high, first plane, side planes, planes
PLANE_FIELDS = 4  # n_x, n_y, n_z, c of a face's half-space n·p + c <= 0 (world frame)
_HULL_MARGIN = 0.001  # PyBullet's default collision margin, added to each support point of the drawn hull
# Beyond this horizontal distance (m) from its surface a cylinder is cast as its circumscribed circle: its
# facets lie at most 3 mm inside (2 % of a 0.15 m radius), 0.15 % of the depth there, a twentieth of a pixel.
LOD_DISTANCE = 2.0
_CYLINDER_SEGMENTS = 32


def _icosphere_directions() -> np.ndarray:
    """The 42 unit directions of a once-subdivided icosahedron with poles on ±z (12 vertices + 30 edge midpoints).

    One lower-ring vertex points at azimuth −36° (measured orientation of the directions PyBullet samples).
    """
    ring_z, ring_r = 1.0 / math.sqrt(5.0), 2.0 / math.sqrt(5.0)
    vertices = [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0)]
    for k in range(5):
        lower, upper = math.radians(-36.0 - 72.0 * k), math.radians(-72.0 * k)
        vertices.append((ring_r * math.cos(lower), ring_r * math.sin(lower), -ring_z))
        vertices.append((ring_r * math.cos(upper), ring_r * math.sin(upper), ring_z))
    v = np.array(vertices)
    dist = np.linalg.norm(v[:, None] - v[None], axis=-1)
    edge = dist[dist > 1e-9].min()
    mids = [v[i] + v[j] for i in range(12) for j in range(i + 1, 12) if abs(dist[i, j] - edge) < 1e-9]
    mids = np.array(mids)
    return np.vstack([v, mids / np.linalg.norm(mids, axis=1, keepdims=True)])


_DIRECTIONS = _icosphere_directions()


@lru_cache(maxsize=256)
def cylinder_hull(radius: float, height: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The polyhedron PyBullet's renderer draws for a cylinder, in the cylinder's frame (yaw it to place it).

    The convex hull of the support points, in :data:`_DIRECTIONS`, of the 32-gon prism with corners
    ``(r sin θ_i, r cos θ_i, ±h/2)``, ``θ_i = 2π i / 32``, each pushed out by the margin along its direction.
    Returns ``(points (42, 3), planes (F, 4), n_side)``: the faces as half-spaces ``n·p + c <= 0``, the
    ``n_side`` near-vertical ones first, then the caps.
    """
    theta = 2.0 * np.pi * np.arange(_CYLINDER_SEGMENTS) / _CYLINDER_SEGMENTS
    ring = np.stack([radius * np.sin(theta), radius * np.cos(theta)], axis=1)
    corners = np.empty((2 * _CYLINDER_SEGMENTS, 3))
    corners[0::2, :2], corners[1::2, :2] = ring, ring
    corners[0::2, 2], corners[1::2, 2] = height / 2.0, -height / 2.0
    # First maximum on ties (a horizontal direction picks the top corner), as Bullet's support search.
    points = corners[np.argmax(_DIRECTIONS @ corners.T, axis=1)] + _HULL_MARGIN * _DIRECTIONS
    planes = ConvexHull(points).equations
    side = np.abs(planes[:, 2]) < 0.7
    return points, np.concatenate([planes[side], planes[~side]]), int(side.sum())


def pack_scene(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The primitives of ``scene`` as the ray caster's arrays ``(boxes, hulls, planes)``.

    ``boxes`` ``(B, 8)``: gate bars and box obstacles. ``hulls`` ``(C, 10)``: cylinders as the polyhedra of
    :func:`cylinder_hull`; hull k's faces are rows ``hulls[k, 7]`` to ``hulls[k, 7] + hulls[k, 9]`` of
    ``planes`` ``(F, 4)``, its ``hulls[k, 8]`` side faces first. Between ``hulls[k, 5]`` and ``hulls[k, 6]``
    in z, a point within ``hulls[k, 2]`` of the axis is inside every cap face (so those can be skipped).
    """
    boxes = np.array(
        [[*centre, *half, math.cos(yaw), math.sin(yaw)] for centre, half, yaw in scene.boxes()], dtype=np.float64
    ).reshape(-1, BOX_FIELDS)
    hulls, planes = [], []
    first = 0
    for obs in scene.obstacles:
        if obs.kind != "cylinder":
            continue
        points, local, n_side = cylinder_hull(float(obs.size[0]), float(obs.size[1]))
        c, s = math.cos(obs.yaw), math.sin(obs.yaw)  # the body, and so its drawn hull, is yawed
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        normal = local[:, :3] @ rot.T
        offset = local[:, 3] - normal @ obs.position
        radius = float(np.max(np.hypot(points[:, 0], points[:, 1])))
        # Cap faces (|n_z| >= 0.7) hold every point within `radius` of the axis whose z is inside these.
        caps = local[n_side:]
        top, bottom = caps[caps[:, 2] > 0], caps[caps[:, 2] < 0]
        slack = radius * np.hypot(caps[:, 0], caps[:, 1]) / np.abs(caps[:, 2])
        safe_hi = np.min(-top[:, 3] / top[:, 2] - slack[caps[:, 2] > 0])
        safe_lo = np.max(-bottom[:, 3] / bottom[:, 2] + slack[caps[:, 2] < 0])
        x, y, z = obs.position
        zmin, zmax = z + points[:, 2].min(), z + points[:, 2].max()
        hulls.append([x, y, radius, zmin, zmax, z + safe_lo, z + safe_hi, first, n_side, len(local)])
        planes.append(np.column_stack([normal, offset]))
        first += len(local)
    hull_arr = np.array(hulls, dtype=np.float64).reshape(-1, HULL_FIELDS)
    plane_arr = np.concatenate(planes) if planes else np.zeros((0, PLANE_FIELDS))
    return boxes, hull_arr, plane_arr


class BatchDepthRenderer:
    """Render the depth images of many cameras, each in its own scene, in one compiled call.

    The output equals :meth:`racebench.sim.camera.DepthCamera.depth` (PyBullet's TinyRenderer) for the same
    pose and scene, within the tolerance checked by ``tests/test_raycast.py``; it is metric depth along the
    optical axis, float32, clipped to ``[camera.min_depth, camera.max_depth]``.

    Args:
        camera: the camera model (size, field of view, range, mounting offset, near plane).
    """

    def __init__(self, camera: DepthCamera) -> None:
        self.camera = camera
        self._offset = np.asarray(camera.offset, dtype=np.float64)
        # Packed geometry of the scenes of the last call, rebuilt only when a scene object changes.
        self._scenes: list[Scene] = []
        self._packed: tuple[np.ndarray, ...] | None = None
        self._per_scene: dict[int, tuple[Scene, tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}

    def _geometry(self, scenes: Sequence[Scene]) -> tuple[np.ndarray, ...]:
        if self._packed is not None and len(scenes) == len(self._scenes):
            if all(a is b for a, b in zip(scenes, self._scenes, strict=True)):
                return self._packed
        per_scene: dict[int, tuple[Scene, tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        for scene in scenes:
            if id(scene) in per_scene:
                continue
            cached = self._per_scene.get(id(scene))
            # Keep the scene object referenced with its arrays so its id cannot be reused while cached.
            per_scene[id(scene)] = cached if cached is not None and cached[0] is scene else (scene, pack_scene(scene))
        self._per_scene = per_scene
        # Each distinct scene once (cameras sharing a scene share its rows), and per camera its row ranges.
        unique = list(per_scene)
        arrays = [per_scene[key][1] for key in unique]
        boxes = np.concatenate([a[0] for a in arrays] + [np.zeros((0, BOX_FIELDS))])
        hulls = np.concatenate([a[1] for a in arrays] + [np.zeros((0, HULL_FIELDS))])
        planes = np.concatenate([a[2] for a in arrays] + [np.zeros((0, PLANE_FIELDS))])
        # Plane indices were per scene: shift them to the concatenated plane array.
        plane_base = np.repeat(np.cumsum([0] + [len(a[2]) for a in arrays[:-1]]), [len(a[1]) for a in arrays])
        hulls[:, 7] += plane_base
        box_first = np.cumsum([0] + [len(a[0]) for a in arrays])
        hull_first = np.cumsum([0] + [len(a[1]) for a in arrays])
        slot = {key: u for u, key in enumerate(unique)}
        which = np.array([slot[id(s)] for s in scenes], dtype=np.int64)
        box_start = np.stack([box_first[which], box_first[which + 1]], axis=1).astype(np.int64)
        hull_start = np.stack([hull_first[which], hull_first[which + 1]], axis=1).astype(np.int64)
        self._scenes = list(scenes)
        self._packed = (boxes, box_start, hulls, hull_start, planes)
        return self._packed

    def render(
        self,
        scenes: Sequence[Scene],
        positions: np.ndarray,
        rotations: np.ndarray,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Depth images ``(N, size, size)`` float32 of N drones, drone k at ``positions[k]`` in ``scenes[k]``.

        Args:
            scenes: the scene each camera looks at (the same object may appear several times).
            positions: ``(N, 3)`` body positions, m.
            rotations: ``(N, 3, 3)`` body→world rotation matrices.
            out: optional ``(N, size, size)`` float32 array to write into.
        """
        positions = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
        rotations = np.ascontiguousarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        n = len(positions)
        if len(rotations) != n or len(scenes) != n:
            sizes = f"{len(scenes)} scenes, {n} positions, {len(rotations)} rotations"
            raise ValueError(f"need one scene, position and rotation per camera, got {sizes}")
        cam = self.camera
        if out is None:
            out = np.empty((n, cam.size, cam.size), dtype=np.float32)
        elif out.shape != (n, cam.size, cam.size) or out.dtype != np.float32:
            raise ValueError(f"out must be float32 of shape {(n, cam.size, cam.size)}, got {out.dtype} {out.shape}")
        boxes, box_start, hulls, hull_start, planes = self._geometry(scenes)
        _render_batch(
            positions,
            rotations,
            self._offset,
            boxes,
            box_start,
            hulls,
            hull_start,
            planes,
            cam.focal_px,
            cam.near,
            cam.far,
            cam.min_depth,
            cam.max_depth,
            LOD_DISTANCE,
            out,
        )
        return out

    def render_one(self, scene: Scene, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """Depth image ``(size, size)`` float32 of one drone (the drop-in for ``DepthCamera.depth``)."""
        return self.render([scene], position, rotation)[0]


class ObstacleSight:
    """Which obstacles of one scene the onboard camera shows: obstacle ``j`` is in view when it is the nearest
    surface on at least ``min_pixels`` pixels of the noise-free depth image, i.e. rendering the scene without it
    makes those pixels deeper by more than ``margin`` (the definition ``scripts/crash_visibility.py`` uses).
    Occlusion, the 90° field of view and the 10 m range all count; one batched render of the scene and of the
    scene without each obstacle asked about.

    Args:
        camera: the onboard camera model.
        scene: the scene the drone flies in.
        margin: depth change (m) that makes a pixel the obstacle's.
        min_pixels: pixels an obstacle must cover to be in view.
    """

    def __init__(self, camera: DepthCamera, scene: Scene, margin: float = 0.01, min_pixels: int = 1) -> None:
        self.renderer = BatchDepthRenderer(camera)
        self.scene = scene
        self.margin = margin
        self.min_pixels = min_pixels
        # Built once per scene so the renderer's per-scene packing is reused from call to call.
        obstacles = scene.obstacles
        self._without = [
            dataclasses.replace(scene, obstacles=obstacles[:j] + obstacles[j + 1 :]) for j in range(len(obstacles))
        ]

    def pixels(self, position: np.ndarray, rotation: np.ndarray, which: Sequence[int] | None = None) -> np.ndarray:
        """Pixels where each obstacle of ``which`` (default: all) is the nearest surface, camera at the body pose."""
        which = range(len(self._without)) if which is None else which
        scenes = [self.scene] + [self._without[j] for j in which]
        if len(scenes) == 1:
            return np.zeros(0, dtype=np.int64)
        n = len(scenes)
        images = self.renderer.render(scenes, np.broadcast_to(position, (n, 3)), np.broadcast_to(rotation, (n, 3, 3)))
        return ((images[1:] - images[0]) > self.margin).sum(axis=(1, 2))

    def in_view(self, position: np.ndarray, rotation: np.ndarray, which: Sequence[int] | None = None) -> np.ndarray:
        """Boolean per obstacle of ``which`` (default: all): in view from the body pose."""
        return self.pixels(position, rotation, which) >= self.min_pixels


@njit(cache=True, error_model="numpy")
def _screen_rect(
    corners: np.ndarray, e: np.ndarray, basis: np.ndarray, focal: float, near: float, far: float, size: int
) -> tuple[int, int, int, int]:
    """Pixel rows/cols ``(i0, i1, j0, j1)`` (inclusive) that a box with ``corners`` (8, 3) can cover.

    Corner ``m`` has bits (x, y, z) = (m >> 2, m >> 1, m) & 1, so edges join corners one bit apart. The part
    of the box nearer than the near plane is clipped off first (its corners in front plus the points where
    its edges cross the plane), which keeps the rectangle tight for boxes the camera is right next to.
    ``i0 > i1`` when nothing can be seen: the box is wholly nearer than the near plane or beyond ``far``.
    """
    half = size / 2.0
    zs = np.empty(8)
    xs = np.empty(8)
    ys = np.empty(8)
    for c in range(8):
        rx, ry, rz = corners[c, 0] - e[0], corners[c, 1] - e[1], corners[c, 2] - e[2]
        zs[c] = rx * basis[0, 0] + ry * basis[0, 1] + rz * basis[0, 2]  # along the optical axis
        xs[c] = rx * basis[1, 0] + ry * basis[1, 1] + rz * basis[1, 2]  # right
        ys[c] = rx * basis[2, 0] + ry * basis[2, 1] + rz * basis[2, 2]  # up
    if zs.min() > far or zs.max() < near:
        return 1, 0, 1, 0
    umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
    for c in range(8):
        if zs[c] >= near:
            u, v = xs[c] / zs[c] * focal, -ys[c] / zs[c] * focal  # px right of / below the axis
            umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
        for bit in (1, 2, 4):
            d = c | bit
            if d == c or (zs[c] >= near) == (zs[d] >= near):
                continue
            f = (near - zs[c]) / (zs[d] - zs[c])  # the edge c-d crosses the near plane here
            u = (xs[c] + f * (xs[d] - xs[c])) / near * focal
            v = -(ys[c] + f * (ys[d] - ys[c])) / near * focal
            umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
    # Column j samples u = j − half, row i samples v = i + 1 − half; one pixel of slack for rounding.
    j0 = max(int(math.floor(max(umin, -2.0 * size) + half)) - 1, 0)
    j1 = min(int(math.ceil(min(umax, 2.0 * size) + half)) + 1, size - 1)
    i0 = max(int(math.floor(max(vmin, -2.0 * size) + half - 1.0)) - 1, 0)
    i1 = min(int(math.ceil(min(vmax, 2.0 * size) + half - 1.0)) + 1, size - 1)
    return i0, i1, j0, j1


@njit(cache=True, error_model="numpy")  # IEEE division: no zero-division checks in the pixel loops
def _render_batch(
    positions: np.ndarray,
    rotations: np.ndarray,
    offset: np.ndarray,
    boxes: np.ndarray,
    box_start: np.ndarray,
    hulls: np.ndarray,
    hull_start: np.ndarray,
    planes: np.ndarray,
    focal: float,
    near: float,
    far: float,
    min_depth: float,
    max_depth: float,
    lod_distance: float,
    out: np.ndarray,
) -> None:
    n, size = out.shape[0], out.shape[1]
    half = size / 2.0
    buf = np.empty((size, size))
    us = np.empty(size)  # ray offsets per column (right) and per row (up), in units of the focal length
    vs = np.empty(size)
    for j in range(size):
        us[j] = (j - half) / focal
    for i in range(size):
        vs[i] = -(i + 1.0 - half) / focal
    basis = np.empty((3, 3))  # rows: forward, right, up (world frame)
    e = np.empty(3)
    corners = np.empty((8, 3))
    max_planes = 1
    for q in range(hulls.shape[0]):
        max_planes = max(max_planes, int(hulls[q, 9]))
    plane_w = np.empty(max_planes)  # per hull and camera: −(n·eye + c) of each face
    plane_a = np.empty(max_planes)  # ... and n·forward, n·right, n·up, so that n·ray = a + u b + v c
    plane_b = np.empty(max_planes)
    plane_c = np.empty(max_planes)
    row_a = np.empty(max_planes)  # a + v c of the current pixel row
    for k in range(n):
        rot = rotations[k]
        for a in range(3):
            basis[0, a] = rot[a, 0]  # forward = body x
            basis[1, a] = -rot[a, 1]  # right = −body y
            basis[2, a] = rot[a, 2]  # up = body z
            e[a] = positions[k, a] + rot[a, 0] * offset[0] + rot[a, 1] * offset[1] + rot[a, 2] * offset[2]
        fx, fy, fz = basis[0, 0], basis[0, 1], basis[0, 2]
        rx, ry, rz = basis[1, 0], basis[1, 1], basis[1, 2]
        ux, uy, uz = basis[2, 0], basis[2, 1], basis[2, 2]

        # Ground plane z = 0 (seen from above only), else nothing within range.
        for i in range(size):
            for j in range(size):
                dz = fz + us[j] * rz + vs[i] * uz
                t = far
                if e[2] > 0.0 and dz < 0.0:
                    t = -e[2] / dz
                    if t < near or t > far:
                        t = far
                buf[i, j] = t

        # Boxes yawed about z: slab test in the box frame, only over the box's screen rectangle.
        for b in range(box_start[k, 0], box_start[k, 1]):
            cx, cy, cz = boxes[b, 0], boxes[b, 1], boxes[b, 2]
            hx, hy, hz = boxes[b, 3], boxes[b, 4], boxes[b, 5]
            c, s = boxes[b, 6], boxes[b, 7]
            m = 0
            for sx in (-1.0, 1.0):
                for sy in (-1.0, 1.0):
                    for sz in (-1.0, 1.0):
                        corners[m, 0] = cx + c * sx * hx - s * sy * hy
                        corners[m, 1] = cy + s * sx * hx + c * sy * hy
                        corners[m, 2] = cz + sz * hz
                        m += 1
            i0, i1, j0, j1 = _screen_rect(corners, e, basis, focal, near, far, size)
            if i0 > i1:
                continue
            # Camera origin and basis in the box frame (rotate by −yaw about z).
            ox = c * (e[0] - cx) + s * (e[1] - cy)
            oy = -s * (e[0] - cx) + c * (e[1] - cy)
            oz = e[2] - cz
            lfx, lfy = c * fx + s * fy, -s * fx + c * fy
            lrx, lry = c * rx + s * ry, -s * rx + c * ry
            lux, luy = c * ux + s * uy, -s * ux + c * uy
            for i in range(i0, i1 + 1):
                v = vs[i]
                for j in range(j0, j1 + 1):
                    u = us[j]
                    t0 = -np.inf
                    t1 = np.inf
                    d = lfx + u * lrx + v * lux
                    if d != 0.0:
                        ta, tb = (-hx - ox) / d, (hx - ox) / d
                        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                    elif abs(ox) > hx:
                        continue
                    d = lfy + u * lry + v * luy
                    if d != 0.0:
                        ta, tb = (-hy - oy) / d, (hy - oy) / d
                        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                    elif abs(oy) > hy:
                        continue
                    d = fz + u * rz + v * uz
                    if d != 0.0:
                        ta, tb = (-hz - oz) / d, (hz - oz) / d
                        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                    elif abs(oz) > hz:
                        continue
                    # Front faces only, and only beyond the near plane (TinyRenderer culls and clips).
                    if t0 <= t1 and t0 >= near and t0 < buf[i, j]:
                        buf[i, j] = t0

        # Cylinders as PyBullet draws them: convex polyhedra (slab test over their face planes).
        for q in range(hull_start[k, 0], hull_start[k, 1]):
            cx, cy, rc, zlo, zhi = hulls[q, 0], hulls[q, 1], hulls[q, 2], hulls[q, 3], hulls[q, 4]
            safe_lo, safe_hi = hulls[q, 5], hulls[q, 6]
            p0, n_side, n_all = int(hulls[q, 7]), int(hulls[q, 8]), int(hulls[q, 9])
            m = 0
            for sx in (-1.0, 1.0):
                for sy in (-1.0, 1.0):
                    for zc in (zlo, zhi):
                        corners[m, 0] = cx + sx * rc
                        corners[m, 1] = cy + sy * rc
                        corners[m, 2] = zc
                        m += 1
            i0, i1, j0, j1 = _screen_rect(corners, e, basis, focal, near, far, size)
            if i0 > i1:
                continue
            ox, oy = e[0] - cx, e[1] - cy
            cc = ox * ox + oy * oy - rc * rc
            distant = ox * ox + oy * oy > (rc + lod_distance) ** 2
            for g in range(n_all if not distant else 0):
                nx, ny, nz = planes[p0 + g, 0], planes[p0 + g, 1], planes[p0 + g, 2]
                plane_w[g] = -(nx * e[0] + ny * e[1] + nz * e[2] + planes[p0 + g, 3])
                plane_a[g] = nx * fx + ny * fy + nz * fz
                plane_b[g] = nx * rx + ny * ry + nz * rz
                plane_c[g] = nx * ux + ny * uy + nz * uz
            for i in range(i0, i1 + 1):
                v = vs[i]
                for g in range(n_all if not distant else 0):
                    row_a[g] = plane_a[g] + v * plane_c[g]
                for j in range(j0, j1 + 1):
                    u = us[j]
                    dx = fx + u * rx + v * ux
                    dy = fy + u * ry + v * uy
                    # Cheap rejection: rays that miss the circumscribed vertical cylinder miss the hull.
                    aa = dx * dx + dy * dy
                    bb = ox * dx + oy * dy
                    if bb * bb - aa * cc < 0.0:
                        continue
                    dz = fz + u * rz + v * uz
                    if distant:  # the circumscribed cylinder itself, a few mm off the hull (see LOD_DISTANCE)
                        root = math.sqrt(bb * bb - aa * cc)
                        t0, t1 = (-bb - root) / aa, (-bb + root) / aa
                        if dz != 0.0:
                            ta, tb = (zlo - e[2]) / dz, (zhi - e[2]) / dz
                            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                        elif e[2] < zlo or e[2] > zhi:
                            continue
                        if t0 <= t1 and t0 >= near and t0 < buf[i, j]:
                            buf[i, j] = t0
                        continue
                    # Slab test over the side faces; the caps only where the entry point may meet them.
                    t0, t1 = _slab(row_a, plane_b, plane_w, 0, n_side, u, -np.inf, np.inf)
                    if t0 > t1:
                        continue
                    z0 = e[2] + t0 * dz
                    px, py = ox + t0 * dx, oy + t0 * dy
                    if not (safe_lo < z0 < safe_hi and px * px + py * py <= rc * rc):
                        t0, t1 = _slab(row_a, plane_b, plane_w, n_side, n_all, u, t0, t1)
                        if t0 > t1:
                            continue
                    if t0 >= near and t0 < buf[i, j]:
                        buf[i, j] = t0

        for i in range(size):
            for j in range(size):
                out[k, i, j] = min(max(buf[i, j], min_depth), max_depth)


@njit(cache=True, inline="always", error_model="numpy")
def _slab(
    row_a: np.ndarray,
    plane_b: np.ndarray,
    plane_w: np.ndarray,
    lo: int,
    hi: int,
    u: float,
    t0: float,
    t1: float,
) -> tuple[float, float]:
    """Narrow the ray interval ``[t0, t1]`` by a hull's half-spaces ``lo .. hi`` (``t0 > t1``: a miss).

    The ray's component along face g's normal is ``row_a[g] + u * plane_b[g]``; ``plane_w[g]`` is the
    face's offset seen from the camera.
    """
    for g in range(lo, hi):
        nd = row_a[g] + u * plane_b[g]
        w = plane_w[g]
        if nd < 0.0:
            t0 = max(t0, w / nd)
        elif nd > 0.0:
            t1 = min(t1, w / nd)
        elif w < 0.0:  # parallel to this face and outside it
            return np.inf, -np.inf
    return t0, t1
