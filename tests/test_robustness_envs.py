"""The robustness suite's ids and perturbations, from first principles (issue 72, item 5).

Each perturbation is checked against what it claims: the delay shifts the response by exactly its ticks, 30 Hz holds
each action for its span, mass and thrust move hover thrust as F = m g says, drag doubles, the wind and the estimate
errors have their stated statistics, the stereo model's noise matches its specification on a flat wall, and the
camera mount turns the image and nothing else. Every robustness id starts from its main id's scenes.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import racebench
from racebench.envs.env import RaceEnv
from racebench.envs.lap_bound import env_lap_time_bound
from racebench.envs.perturbations import ROBUSTNESS, Perturbations
from racebench.envs.registration import ENV_KWARGS
from racebench.sim.camera import DepthCamera
from racebench.sim.disturbances import CommandDelay, DrydenWind, EstimateNoise, StereoDepth, euler_rotation
from racebench.sim.quadrotor import QuadrotorParams

TRACKS = ("S", "J", "Circle")
ROBUST_IDS = [f"RaceObs-{t}-{name}-v0" for t in TRACKS for name in ROBUSTNESS]


def test_every_perturbation_is_registered_on_every_track_on_top_of_the_main_id() -> None:
    assert len(ROBUSTNESS) == 10
    for env_id in ROBUST_IDS:
        assert env_id in racebench.ENV_IDS and env_id in gym.registry
        track = env_id.split("-")[1]
        main = ENV_KWARGS[f"RaceObs-{track}-v0"]
        assert {k: v for k, v in ENV_KWARGS[env_id].items() if k in main} == main  # nothing of the main id changed


@pytest.mark.parametrize("name", list(ROBUSTNESS))
def test_each_id_flies_its_main_ids_scenes_seed_for_seed(name: str) -> None:
    main, perturbed = gym.make("RaceObs-J-v0"), gym.make(f"RaceObs-J-{name}-v0")
    for seed in (1_000_000, 1_000_007, 5):
        main.reset(seed=seed)
        perturbed.reset(seed=seed)
        assert perturbed.unwrapped.scene.to_dict() == main.unwrapped.scene.to_dict()
    main.close()
    perturbed.close()


def test_without_perturbations_an_env_draws_what_it_drew_before() -> None:
    """Off at the defaults: the same observations, bit for bit, as the same env with each option given as 0."""
    plain = RaceEnv(track="S")
    zeros = RaceEnv(track="S", command_delay=0.0, wind_gust_std=0.0, camera_tilt=0.0, state_noise=0.0)
    a, _ = plain.reset(seed=3)
    b, _ = zeros.reset(seed=3)
    for _ in range(20):
        assert np.array_equal(a["depth"], b["depth"]) and np.array_equal(a["state"], b["state"])
        a = plain.step(np.array([0.0, 0.1, 0.0, 0.0]))[0]
        b = zeros.step(np.array([0.0, 0.1, 0.0, 0.0]))[0]
    plain.close()
    zeros.close()


def _tick_positions(env: RaceEnv, actions: list[np.ndarray]) -> np.ndarray:
    """Positions after each control step (one physics tick each when control_freq == physics_freq)."""
    env.reset(seed=0)
    out = []
    for action in actions:
        env.advance(action)
        out.append(env.drone.position.copy())
    return np.array(out)


def test_the_delay_shifts_the_response_by_exactly_its_ticks() -> None:
    """At 200 Hz control (one tick per step), a 60 ms delay is 12 ticks: the delayed drone flies the nominal
    trajectory 12 ticks late, hovering on the hover command until then (the authors' simulator does the same)."""
    kwargs = {"track": "S", "density": 0, "obs_mode": "state", "control_freq": 200}
    nominal, delayed = RaceEnv(**kwargs), RaceEnv(**kwargs, command_delay=0.06)
    assert delayed.perturbations.delay.ticks == 12
    hover = nominal.params.hover_action
    rng = np.random.default_rng(0)
    actions = [np.array([hover + 0.3, *rng.uniform(-0.3, 0.3, 3)]) for _ in range(60)]
    late = _tick_positions(delayed, actions + [actions[0]] * 12)
    first = _tick_positions(nominal, [np.array([hover, 0.0, 0.0, 0.0])] * 12 + actions)
    np.testing.assert_allclose(late, first, rtol=0, atol=1e-12)
    # and it is a delay: the first 12 ticks of the delayed drone do not depend on the actions at all
    still = _tick_positions(delayed, [np.array([1.0, 1.0, -1.0, 1.0])] * 12)
    np.testing.assert_allclose(still, first[:12], rtol=0, atol=1e-12)
    nominal.close()
    delayed.close()


def test_command_delay_line_is_first_in_first_out() -> None:
    line = CommandDelay(3)
    line.reset(1.0, (0.0, 0.0, 0.0))
    applied = [line.push(float(i), (float(i), 0.0, 0.0))[0] for i in range(2, 8)]
    assert applied == [1.0, 1.0, 1.0, 2.0, 3.0, 4.0]
    assert CommandDelay(0).push(5.0, (1.0, 2.0, 3.0)) == (5.0, (1.0, 2.0, 3.0))


def test_30hz_holds_each_action_for_its_span_with_physics_unchanged() -> None:
    """At 30 Hz on 200 Hz physics the steps hold 6, 7, 7 ticks (0.1 s per 3 steps, exactly); the trajectory equals a
    200 Hz-control flight that repeats each action for those ticks, bit for bit."""
    slow = RaceEnv(track="S", density=0, obs_mode="state", control_freq=30)
    fast = RaceEnv(track="S", density=0, obs_mode="state", control_freq=200)
    assert [slow._ticks_of_step(k) for k in range(6)] == [6, 7, 7, 6, 7, 7]
    slow.reset(seed=1)
    fast.reset(seed=1)
    rng = np.random.default_rng(1)
    for k in range(9):
        action = np.array([slow.params.hover_action + 0.2, *rng.uniform(-0.5, 0.5, 3)])
        info = slow.advance(action)[3]
        for _ in range(slow._ticks_of_step(k)):
            fast.advance(action)
        assert np.array_equal(slow.drone.position, fast.drone.position)
        assert np.array_equal(slow.drone.velocity, fast.drone.velocity)
    assert info["time"] == pytest.approx(0.3, abs=1e-12) and slow.ticks == 60
    assert slow.max_steps == 450 and gym.spec("RaceObs-S-Control30Hz-v0").max_episode_steps == 450
    slow.close()
    fast.close()


@pytest.mark.parametrize(("name", "weight_ratio"), [("Mass", 1.2), ("Thrust", 1.0)])
def test_mass_and_thrust_move_hover_thrust_as_f_equals_mg(name: str, weight_ratio: float) -> None:
    nominal = QuadrotorParams()
    params = QuadrotorParams.from_overrides(ENV_KWARGS[f"RaceObs-S-{name}-v0"]["quadrotor"])
    hover_thrust = (params.hover_action + 1.0) / 2.0 * params.max_thrust
    assert hover_thrust == pytest.approx(weight_ratio * nominal.mass * nominal.gravity, rel=1e-12)
    if name == "Mass":  # the same inertia scaling as the mass: every axis 1.2 ×
        assert np.allclose(np.array(params.inertia) / np.array(nominal.inertia), 1.2)
    else:  # -15 % maximum thrust: the same weight needs a larger share of it
        assert params.max_thrust == pytest.approx(0.85 * nominal.max_thrust)
        assert params.hover_action > nominal.hover_action
    # at its own hover action the drone stays where it starts; at the nominal one a heavier drone sinks
    env = gym.make(f"RaceObs-S-{name}-v0", obs_mode="state", density=0).unwrapped
    env.reset(seed=2)
    start = env.drone.position.copy()
    for _ in range(25):
        env.advance(np.array([params.hover_action, 0.0, 0.0, 0.0]))
    assert np.linalg.norm(env.drone.position - start) < 1e-6
    env.reset(seed=2)
    for _ in range(25):
        env.advance(np.array([nominal.hover_action, 0.0, 0.0, 0.0]))
    sink = start[2] - env.drone.position[2]
    # F = m a: the nominal weight's thrust on the heavier (or weaker) drone: a = g (1 - T_nom / (m g)) downwards,
    # reached after the 30 ms motor lag; 0.5 s of it gives at least a third of a t^2 / 2
    thrust = (nominal.hover_action + 1.0) * params.max_thrust / 2.0
    accel = nominal.gravity * (1.0 - thrust / (params.mass * params.gravity))
    assert sink > 0.3 * accel * 0.5**2 / 2.0 > 0
    env.close()


def test_drag_doubles() -> None:
    nominal = QuadrotorParams()
    params = QuadrotorParams.from_overrides(ENV_KWARGS["RaceObs-Circle-Drag-v0"]["quadrotor"])
    assert np.allclose(np.array(params.drag_coefficients), 2.0 * np.array(nominal.drag_coefficients))


def test_dryden_wind_has_its_stated_intensity_and_correlation_time() -> None:
    wind = DrydenWind(1.5)
    # Dryden low altitude at 1.5 m (4.92 ft): sigma_w / sigma_u = 0.181^0.4 ~ 0.505, L_u ~ 11.7 m, L_w = 1.5 m
    assert wind.std[2] / wind.std[0] == pytest.approx(0.505, abs=0.002)
    assert wind.time_constants[0] * wind.airspeed == pytest.approx(11.66, abs=0.05)
    assert wind.time_constants[2] == pytest.approx(0.25)
    rng = np.random.default_rng(0)
    dt, n = 0.005, 400_000
    w = wind.initial(rng)
    samples = np.empty((n, 3))
    for i in range(n):
        w = wind.step(w, dt, rng)
        samples[i] = w
    assert np.all(np.abs(samples) <= 3.0 * wind.std + 1e-12)
    # 2000 s = about 1000 time constants of the horizontal axes: the std within 8 %, the lag-tau correlation ~ 1/e
    np.testing.assert_allclose(samples.std(axis=0), wind.std, rtol=0.08)
    lag = int(round(wind.time_constants[0] / dt))
    x = samples[:, 0]
    corr = np.corrcoef(x[:-lag], x[lag:])[0, 1]
    assert corr == pytest.approx(math.exp(-1.0), abs=0.08)


def test_wind_acts_through_drag_on_the_air_relative_velocity() -> None:
    """A hovering drone in a wind drifts downwind; its first-tick force is the drag of the wind's speed."""
    env = RaceEnv(track="S", density=0, obs_mode="state", wind_gust_std=1.5)
    env.reset(seed=4)
    start, air = env.drone.position.copy(), env.perturbations.air.copy()
    for _ in range(50):
        env.advance(np.array([env.params.hover_action, 0.0, 0.0, 0.0]))
    drift = env.drone.position[:2] - start[:2]
    assert float(drift @ air[:2]) > 0  # downwind, for a wind that changes over seconds
    env.close()


def test_stereo_noise_matches_its_specification_on_a_flat_wall() -> None:
    model, camera, rng = StereoDepth(), DepthCamera(), np.random.default_rng(0)
    wall = np.full((64, 64), 2.0)
    frames = np.stack([model.measure(wall, camera.focal_px, rng) for _ in range(200)])
    lost = frames == model.max_range
    # dropouts: 3 % (a flat wall has no depth edge); 819,200 pixels, 5 sigma = 0.1 %
    assert lost.mean() == pytest.approx(0.03, abs=0.001)
    error = frames[~lost] - 2.0
    assert abs(error.mean()) < 1e-3 and error.std() == pytest.approx(0.02 * 2.0, rel=0.01)  # 2 % RMS at 2 m
    # the error grows with the square of range: 4 x at 4 m, 1/4 at 1 m
    for depth, sigma in ((4.0, 0.16), (1.0, 0.01)):
        reading = model.measure(np.full((64, 64), depth), camera.focal_px, rng)
        assert (reading[reading != model.max_range] - depth).std() == pytest.approx(sigma, rel=0.05)
    # out of range: nearer than 0.28 m and at the far limit nothing is reported
    assert np.all(model.measure(np.full((8, 8), 0.25), camera.focal_px, rng) == model.max_range)
    assert np.all(model.measure(np.full((8, 8), 10.0), camera.focal_px, rng) == model.max_range)


def test_stereo_occlusion_shadow_is_left_of_a_nearer_surface_with_its_width() -> None:
    """Near half (2 m) right of a far half (10 m): the last far column is lost with probability f B (1/2 - 1/10)."""
    model, camera, rng = StereoDepth(dropout=0.0, relative_rms=0.0), DepthCamera(), np.random.default_rng(1)
    image = np.full((64, 64), 2.0)
    image[:, :32] = 9.0
    width = camera.focal_px * model.baseline * (1 / 2.0 - 1 / 9.0)
    frames = np.stack([model.measure(image, camera.focal_px, rng) for _ in range(400)])
    lost = frames == model.max_range
    assert lost[:, :, 31].mean() == pytest.approx(width, abs=0.02)  # 25,600 draws: 5 sigma < 0.015
    assert not lost[:, :, :31].any() and not lost[:, :, 32:].any()


def test_stereo_depth_reaches_the_observation() -> None:
    env = gym.make("RaceObs-S-DepthNoise-v0").unwrapped
    obs, _ = env.reset(seed=1_000_000)
    clean = env.depth_image()
    holes = np.isclose(obs["depth"][0], env.camera.min_depth / env.camera.max_depth)
    near = clean < env.camera.max_depth
    assert 0.01 < holes[near].mean() < 0.2  # dropouts and shadows on surfaces; the background reads far as before
    env.close()


def test_camera_mount_turns_the_image_and_nothing_else() -> None:
    env = gym.make("RaceObs-S-CameraTilt-v0").unwrapped
    env.reset(seed=1_000_001)
    mount = env.perturbations.mount_rotation
    angles = np.array(
        [math.atan2(mount[2, 1], mount[2, 2]), -math.asin(mount[2, 0]), math.atan2(mount[1, 0], mount[0, 0])]
    )
    assert np.all(np.abs(angles) <= math.radians(5.0) + 1e-12) and np.abs(angles).max() > math.radians(0.5)
    assert np.allclose(euler_rotation(*angles), mount)
    depth = env.depth_image()
    direct = env.camera.depth(env.sim.client, env.drone.position, env.drone.rotation @ mount)
    assert np.array_equal(depth, direct)
    level = env.camera.depth(env.sim.client, env.drone.position, env.drone.rotation)
    assert not np.array_equal(depth, level)
    env.step(np.zeros(4))
    assert env.perturbations.mount_rotation is mount  # fixed for the episode
    env.close()


def test_state_noise_changes_what_is_observed_not_how_it_flies() -> None:
    """The estimate error enters the state observation only: rewards and the trajectory equal the nominal env's."""
    noisy = RaceEnv(track="J", obs_mode="state", state_noise=1.0)
    exact = RaceEnv(track="J", obs_mode="state")
    a, _ = noisy.reset(seed=9)
    b, _ = exact.reset(seed=9)
    assert not np.array_equal(a, b)
    for _ in range(30):
        action = np.array([0.1, 0.05, -0.05, 0.0])
        ra = noisy.step(action)[1]
        rb = exact.step(action)[1]
        assert ra == rb and np.array_equal(noisy.drone.position, exact.drone.position)
    noisy.close()
    exact.close()


def test_estimate_error_has_its_stated_statistics() -> None:
    model, rng = EstimateNoise(1.0), np.random.default_rng(3)
    error, samples = model.initial(rng), []
    for _ in range(100_000):
        error = model.step(error, 0.02, rng)
        samples.append(error)
    std = np.std(samples, axis=0)
    np.testing.assert_allclose(std[:3], 0.10, rtol=0.1)
    np.testing.assert_allclose(std[3:6], 0.10, rtol=0.1)
    np.testing.assert_allclose(std[6:], math.radians(1.0), rtol=0.1)


def test_estimated_attitude_is_a_unit_quaternion_and_body_rates_stay_exact() -> None:
    env = RaceEnv(track="S", obs_mode="state", state_noise=3.0)
    env.reset(seed=11)
    env.step(np.array([0.2, 0.4, -0.3, 0.5]))
    pos, quat, rot, vel, ang = env.perturbations.estimated(*env.drone)
    assert np.linalg.norm(quat) == pytest.approx(1.0) and quat[3] >= 0
    assert np.allclose(rot.T @ ang, env.drone.body_rates)
    from racebench.sim.bullet import p

    assert np.allclose(np.array(p.getMatrixFromQuaternion(quat.tolist())).reshape(3, 3), rot, atol=1e-9)
    env.close()


def test_options_out_of_range_are_named() -> None:
    for kwargs, named in (
        ({"command_delay": 0.0123}, "command_delay"),
        ({"command_delay": 0.9}, "command_delay"),
        ({"wind_gust_std": -1.0}, "wind_gust_std"),
        ({"camera_tilt": 45.0}, "camera_tilt"),
        ({"state_noise": float("nan")}, "state_noise"),
        ({"depth_model": "lidar"}, "depth_model"),
    ):
        with pytest.raises(ValueError, match=named):
            Perturbations(200, **kwargs)


def test_lap_time_bounds_follow_the_airframe_and_the_wind() -> None:
    for track in TRACKS:
        nominal = env_lap_time_bound(f"RaceObs-{track}-v0")
        assert env_lap_time_bound(f"RaceObs-{track}-Mass-v0") > nominal
        assert env_lap_time_bound(f"RaceObs-{track}-Thrust-v0") > nominal
        assert env_lap_time_bound(f"RaceObs-{track}-Wind-v0") < nominal  # a tailwind's drag can push
        for name in ("Latency", "Latency30ms", "Control30Hz", "DepthNoise", "CameraTilt", "StateNoise", "Drag"):
            assert env_lap_time_bound(f"RaceObs-{track}-{name}-v0") == nominal
