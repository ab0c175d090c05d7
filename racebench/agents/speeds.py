"""Speed profiles along a planned path: curvature-limited, minimum-time under a thrust budget, jerk-limited."""

from __future__ import annotations

import math

import numpy as np


def speed_profile(
    points: np.ndarray,
    arc: np.ndarray,
    v_max: float,
    lateral_accel: float,
    decel: float,
    v_min: float = 0.6,
    end_speed: float = 0.3,
) -> np.ndarray:
    """Speed along a resampled path: limited by curvature (``v² κ ≤ a_lat``), by braking ahead of turns and
    to ``end_speed`` at the end."""
    ds = float(arc[1] - arc[0]) if len(arc) > 1 else 1.0
    span = max(1, int(round(0.3 / ds)))  # estimate curvature over ±0.3 m: grid corners are sharp
    direction = np.diff(points, axis=0, append=points[-1:] + (points[-1:] - points[-2:-1]))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
    ahead = direction[np.minimum(np.arange(len(points)) + span, len(points) - 1)]
    behind = direction[np.maximum(np.arange(len(points)) - span, 0)]
    turn = np.arccos(np.clip(np.sum(ahead * behind, axis=1), -1.0, 1.0))
    curvature = turn / (2 * span * ds)
    v = np.clip(np.sqrt(lateral_accel / np.maximum(curvature, 1e-9)), v_min, v_max)
    v[-1] = min(v[-1], end_speed)
    for i in range(len(v) - 2, -1, -1):  # brake in time for what comes
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * decel * (arc[i + 1] - arc[i])))
    return v


def minimum_time_speeds(
    arc: np.ndarray,
    curvature: np.ndarray,
    max_accel: float,
    max_speed: float | np.ndarray,
    start_speed: float,
    drag: float = 0.0,
) -> np.ndarray:
    """Fastest speed profile along a path whose total acceleration (tangential and centripetal) stays within
    ``max_accel``: the classic forward/backward pass over the friction circle. ``drag`` (1/m) eats into
    the forward budget as ``drag · v²``."""
    kappa = np.linalg.norm(curvature, axis=1)
    v = np.minimum(np.sqrt(max_accel / np.maximum(kappa, 1e-9)), max_speed)
    v[0] = min(v[0], start_speed)
    v = np.minimum(v, max_speed)  # max_speed may be a per-sample cap
    ds = np.diff(arc)
    for i in range(len(v) - 1):
        lateral = v[i] ** 2 * kappa[i]
        along = math.sqrt(max(max_accel**2 - lateral**2, 0.0)) - drag * v[i] ** 2
        v[i + 1] = min(v[i + 1], math.sqrt(max(v[i] ** 2 + 2.0 * max(along, 0.0) * ds[i], 0.0)))
    for i in range(len(v) - 2, -1, -1):
        lateral = v[i + 1] ** 2 * kappa[i + 1]
        along = math.sqrt(max(max_accel**2 - lateral**2, 0.0))
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * along * ds[i]))
    return v


def thrust_limited_speeds(
    arc: np.ndarray,
    tangent: np.ndarray,
    curvature: np.ndarray,
    max_thrust_accel: float,
    max_speed: float | np.ndarray,
    start_speed: float,
    drag: float = 0.0,
    gravity: float = 9.81,
) -> np.ndarray:
    """Fastest speed profile along a path whose mass-normalised thrust stays within ``max_thrust_accel``.

    A multirotor's limit is its thrust vector, not an acceleration circle: the thrust must supply the path's
    acceleration ``a_t t + v² κ``, hold up against gravity and cancel drag (``drag · v²`` along ``t``), so
    ``|a_t t + v² κ + drag v² t + g ẑ| ≤ max_thrust_accel``. A level turn can pull ``sqrt(F² − g²)``
    sideways, a climb less, a dive more. The part normal to the path fixes the highest speed at each
    sample; what the thrust has left along the path bounds acceleration (forward pass) and braking
    (backward pass)."""
    up = np.array([0.0, 0.0, gravity])
    g_along = tangent @ up
    g_normal = up[None, :] - g_along[:, None] * tangent
    # The speed cap: the highest u = v² that can be held (a_t = 0), |(drag u + g_t) t + u κ + g⊥|² ≤ F², i.e.
    # the larger root of (|κ|² + drag²) u² + 2 (κ·g⊥ + drag g_t) u + g² − F² (κ ⊥ t). Below it the thrust has
    # something left along the path both ways, so the passes never have to clip.
    quad = np.sum(curvature**2, axis=1) + drag**2
    half = np.sum(curvature * g_normal, axis=1) + drag * g_along
    const = gravity**2 - max_thrust_accel**2
    disc = np.maximum(half**2 - quad * const, 0.0)
    u_cap = np.where(quad > 1e-12, (-half + np.sqrt(disc)) / np.maximum(quad, 1e-12), np.inf)
    v = np.minimum(np.sqrt(np.maximum(u_cap, 0.0)), max_speed)
    v[0] = min(v[0], start_speed)

    def spare(i: int, u: float) -> float:
        """Thrust left along the path at sample ``i`` and squared speed ``u``."""
        normal = u * curvature[i] + g_normal[i]
        return math.sqrt(max(max_thrust_accel**2 - float(normal @ normal), 0.0))

    ds = np.diff(arc)
    for i in range(len(v) - 1):
        u = v[i] ** 2
        along = spare(i, u) - drag * u - g_along[i]
        v[i + 1] = min(v[i + 1], math.sqrt(max(u + 2.0 * max(along, 0.0) * ds[i], 0.0)))
    for i in range(len(v) - 2, -1, -1):
        u = v[i + 1] ** 2
        braking = spare(i + 1, u) + drag * u + g_along[i + 1]
        v[i] = min(v[i], math.sqrt(u + 2.0 * max(braking, 0.0) * ds[i]))
    return v


def limit_jerk(speeds: np.ndarray, arc: np.ndarray, window: float) -> np.ndarray:
    """A speed profile never above ``speeds`` whose acceleration changes over ``window`` seconds rather
    than instantly: a moving minimum, then a moving average, both over ``window`` of travel time.

    Going from full acceleration to full braking means tilting the thrust through ~90°, which the body
    rate limits spread over a fraction of a second; a bang-bang profile would ask for it at once."""
    ds = float(arc[1] - arc[0])
    n = len(speeds)
    # The take-off from rest is left alone (floor of 1 m/s): its zero would otherwise spread down the path.
    floor = np.maximum(speeds, 1.0)
    half = np.maximum(1, np.round(0.5 * window * floor / ds).astype(int))
    lo, hi = np.maximum(np.arange(n) - half, 0), np.minimum(np.arange(n) + half + 1, n)
    eroded = np.array([floor[a:b].min() for a, b in zip(lo, hi, strict=True)])
    csum = np.concatenate([[0.0], np.cumsum(eroded)])
    # erosion then averaging over the same window: the average of values below the profile stays below it
    return np.minimum((csum[hi] - csum[lo]) / (hi - lo), speeds)


def limit_braking_onset(speeds: np.ndarray, arc: np.ndarray, jerk: float) -> np.ndarray:
    """The highest speed profile below ``speeds`` whose acceleration falls no faster than ``jerk`` (m/s³) at
    top speed (``jerk · v / v_max`` below it: a conservative constant in ``u = v²``).

    A multirotor brakes by tilting its thrust backwards: from full acceleration to full braking the thrust
    direction turns by up to ~90°, which takes a body-rate-limited fraction of a second, so a profile that
    switches at once overshoots every speed peak. With ``u = v²`` the along-path acceleration is ``u′/2`` and
    ``da/dt = v u″ / 2``, so the bound is ``u″ ≥ −2 jerk / v``; taken at the path's top speed it is a constant
    ``−c``, and the highest ``u`` below the profile with ``u″ ≥ −c`` is the lower convex hull of
    ``u + c s²/2``, minus ``c s²/2``. It lowers speed peaks (the switch from speeding up to braking) and
    rounds any other fall in acceleration (e.g. levelling off onto a plateau); rises are left alone: the
    switch from braking to speeding up at a turn's apex is already gradual, since there the turn takes the
    whole thrust budget."""
    c = 2.0 * jerk / max(float(speeds.max()), 1.0)
    lifted = speeds**2 + 0.5 * c * arc**2
    hull: list[int] = []  # indices of the lower convex hull, left to right (monotone chain)
    for k in range(len(arc)):
        while len(hull) >= 2:
            i, j = hull[-2], hull[-1]
            cross = (arc[j] - arc[i]) * (lifted[k] - lifted[i]) - (lifted[j] - lifted[i]) * (arc[k] - arc[i])
            if cross > 0.0:
                break
            hull.pop()
        hull.append(k)
    envelope = np.interp(arc, arc[hull], lifted[hull]) - 0.5 * c * arc**2
    return np.minimum(np.sqrt(np.maximum(envelope, 0.0)), speeds)
