"""The lap-time lower bound from first principles, and records claiming an impossible lap kept out of every count."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from leaderboard_fixtures import add, make_repo, meta

from racebench import cli
from racebench.envs.lap_bound import env_lap_time_bound, lap_geometry, lap_time_lower_bound, min_time_from_rest
from racebench.evaluation.records import (
    RECORDS_FILE,
    InvalidRecordError,
    env_facts,
    name_of,
    read_folder,
    record_line,
    seal,
    validate_record,
)
from racebench.leaderboard.entries import EntryError
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.track import load_track

ROOT = Path(__file__).parents[1]
PARAMS = QuadrotorParams()
A, G = PARAMS.max_thrust / PARAMS.mass, PARAMS.gravity
PHYSICS_DT = 1.0 / 200


def fly_constant_tilts(distance: float, tilts: np.ndarray, ticks: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """A point mass from rest under full thrust tilted ``tilts`` (rad from vertical), PyBullet's semi-implicit Euler.

    Returns, per tilt, the time it first covers ``distance`` forwards (inf: never) and its height change by then.
    """
    ax, az = A * np.sin(tilts), A * np.cos(tilts) - G
    n = np.arange(1, ticks + 1)[:, None]
    # Velocity first, then position: after n ticks x = a dt² n (n + 1) / 2.
    x, z = ax * PHYSICS_DT**2 * n * (n + 1) / 2, az * PHYSICS_DT**2 * n * (n + 1) / 2
    reached = x >= distance
    first = np.where(reached.any(axis=0), reached.argmax(axis=0), -1)
    times = np.where(first >= 0, (first + 1) * PHYSICS_DT, np.inf)
    heights = z[np.maximum(first, 0), np.arange(len(tilts))]
    return times, heights


def test_level_and_falling_flights_have_their_closed_forms() -> None:
    # Holding its height, the best a point mass does is full thrust tilted to carry its weight: √(a² − g²) forwards.
    assert min_time_from_rest(10.0, 0.0, A, G) == pytest.approx(math.sqrt(2 * 10.0 / math.sqrt(A * A - G * G)))
    # Allowed to fall far enough, gravity carries the weight and every newton of thrust goes forwards.
    assert min_time_from_rest(2.0, 50.0, A, G) == pytest.approx(math.sqrt(2 * 2.0 / A))
    assert min_time_from_rest(0.0, 0.0, A, G) == 0.0
    # A climb costs time, a drop saves it, and farther is slower.
    level = min_time_from_rest(10.0, 0.0, A, G)
    assert min_time_from_rest(10.0, -1.0, A, G) > level > min_time_from_rest(10.0, 1.0, A, G)
    assert min_time_from_rest(11.0, 0.0, A, G) > level
    with pytest.raises(ValueError, match="thrust_accel > gravity"):
        min_time_from_rest(1.0, 0.0, 5.0, G)


@pytest.mark.parametrize("drop", [-0.5, 0.0, 0.8, 3.0])
def test_the_bound_is_the_least_time_of_the_inequality(drop: float) -> None:
    """The closed form against a bisection of L ≤ T²/2 · √(a² − max(0, g − 2 drop / T²)²) (module docstring)."""

    def reach(t: float) -> float:
        lift = max(0.0, G - 2.0 * drop / t**2)
        return t * t / 2.0 * math.sqrt(A * A - lift * lift) if lift < A else 0.0

    low, high = 1e-6, 10.0
    for _ in range(200):
        mid = (low + high) / 2
        low, high = (mid, high) if reach(mid) < 12.0 else (low, mid)
    assert min_time_from_rest(12.0, drop, A, G) == pytest.approx(high, rel=1e-9)


@pytest.mark.parametrize("start_z, drop", [(0.5, 0.0), (1.3, 0.8)])
def test_a_straight_two_gate_track_is_bounded_tightly(tmp_path: Path, start_z: float, drop: float) -> None:
    """Start at rest, two gates straight ahead: the bound is the point mass's minimum, to one physics tick."""
    track_file = tmp_path / "straight.yaml"
    track_file.write_text(yaml.safe_dump({
        "name": "straight", "closed_loop": False, "gate_size": {"inner": 1.0, "outer": 1.28, "depth": 0.1},
        "gates": [{"center": [4.0, 0.0, 1.0], "yaw_deg": 0}, {"center": [10.0, 0.0, 1.0], "yaw_deg": 0}],
        "start": {"center": [0.0, 0.0, start_z], "yaw_deg": 0, "spread": [0.0, 0.0, 0.0]},
    }))  # fmt: skip
    track = load_track(track_file)
    assert lap_geometry(track) == pytest.approx((10.0, drop))
    bound = lap_time_lower_bound(track, PARAMS)
    assert bound == pytest.approx(min_time_from_rest(10.0, drop, A, G) - PHYSICS_DT / 2)
    if drop == 0.0:
        assert bound + PHYSICS_DT / 2 == pytest.approx(math.sqrt(2 * 10.0 / math.sqrt(A * A - G * G)))
    # Every full-thrust tilt that ends the lap no lower than allowed takes at least the bound, and the best takes
    # less than one more tick (the optimum of the point mass is a constant tilt, so the grid comes that close).
    times, heights = fly_constant_tilts(10.0, np.linspace(0.0, math.pi / 2, 4001))
    feasible = times[heights >= -drop - 1e-12]
    assert feasible.min() >= bound
    assert feasible.min() - bound < PHYSICS_DT


def test_each_track_has_its_bound_and_a_shifted_gate_lowers_it() -> None:
    bounds = {track: env_lap_time_bound(f"RaceObs-{track}-v0") for track in ("S", "Circle", "J")}
    assert bounds == pytest.approx({"S": 1.1037, "Circle": 1.0399, "J": 1.0057}, abs=1e-4)
    assert env_lap_time_bound("RaceObs-S-Density5-v0") == bounds["S"]  # obstacles only ever make a lap longer
    shifted = [env_lap_time_bound(f"RaceObs-S-GateShift{s}-v0") for s in ("0.3", "0.5", "0.7", "1.0")]
    assert bounds["S"] > shifted[0] > shifted[1] > shifted[2] > shifted[3] > 0.5
    assert env_facts("RaceObs-S-v0")["lap_time_bound"] == bounds["S"]


def test_every_committed_success_is_slower_than_its_bound() -> None:
    """Over the committed summaries (episodes.csv); the fastest lap of each id is read back from its record.

    (A one-off check read all 25,540 committed records under the new rules: every one is valid.)
    """
    columns = ["policy_sha256", "env_id", "env_version", "seed_protocol", "seed_set", "seed", "renderer", "success",
               "lap_time"]  # fmt: skip
    fastest: dict[str, tuple[float, Path, dict]] = {}
    for csv in sorted([*ROOT.glob("results/**/episodes.csv"), *ROOT.glob("baselines/**/episodes.csv")]):
        episodes = pd.read_csv(csv, usecols=columns)
        laps = episodes[episodes["success"].astype(bool)]
        for env_id, index in laps.groupby("env_id")["lap_time"].idxmin().items():
            row = laps.loc[index].to_dict()
            if row["lap_time"] < fastest.get(env_id, (math.inf,))[0]:
                fastest[env_id] = (row["lap_time"], csv.parent, row)
    assert {"RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-v0"} <= set(fastest)
    for env_id, (lap, folder, row) in fastest.items():
        assert lap > 2.5 * env_lap_time_bound(env_id), env_id  # the bound is loose, not borderline
        ints = {k: int(row[k]) for k in ("seed", "env_version", "seed_protocol")}
        record = read_folder(folder).records.get(name_of({**row, **ints}))
        if record is not None:
            assert record["lap_time"] == lap


# ------------------------------------------------------------------- the forgery


@pytest.fixture()
def forged_hover(tmp_path: Path) -> Path:
    """Committed hover and planner records of RaceObs-S-v0 (first 3 seeds); hover's first turned into the issue's
    forgery: a success in 1.00 s with 4 gates and 50 steps, sealed with the project's own function."""
    for agent in ("hover", "planner"):
        out = tmp_path / "results" / agent
        out.mkdir(parents=True)
        found = read_folder(ROOT / "results" / agent)
        kept = [r for r in found.sorted_records() if r["env_id"] == "RaceObs-S-v0" and r["seed"] < 1_000_003]
        forged = [seal({**r, "success": True, "lap_time": 1.0, "gates_passed": 4, "steps": 50, "crashed": False,
                        "crash_reason": None}) if agent == "hover" and r["seed"] == 1_000_000 else r
                  for r in kept]  # fmt: skip
        (out / RECORDS_FILE).write_bytes(b"".join(record_line(r) for r in forged))
    return tmp_path / "results" / "hover"


def test_the_forged_hover_record_is_invalid(forged_hover: Path) -> None:
    (problem,) = read_folder(forged_hover).problems
    with pytest.raises(InvalidRecordError, match=r"records\.jsonl:\d: success lap_time 1\.0 s is below 1\.104 s, the"):
        raise problem.error()


def test_table_and_compare_never_count_the_forgery(forged_hover: Path, capsys: pytest.CaptureFixture) -> None:
    planner = forged_hover.parent / "planner"
    assert cli.main(["table", str(forged_hover), str(planner)]) == 0
    table = capsys.readouterr().out
    assert "| hover " in table and "0 [0–66]" in table  # 0 of its 2 valid episodes; the forgery is left out
    assert cli.main(["compare", str(forged_hover), str(planner)]) == 0
    compared = capsys.readouterr().out
    assert "hover (policy dbc725cbf2f6) 0/2 (0 %" in compared


def test_leaderboard_add_refuses_the_forgery(forged_hover: Path, tmp_path: Path, monkeypatch) -> None:
    board = make_repo(tmp_path)
    with pytest.raises(EntryError, match=r"invalid record .*below 1\.104 s"):
        add(board, "hover", "hover", [forged_hover])
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("hover")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--records", str(forged_hover)]
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: hover: invalid record [^\n]*below 1\.104 s"):
        cli.main(argv)
    assert not (board / "hover").exists()


def test_a_lap_between_physics_ticks_and_a_failure_with_every_gate_are_invalid(forged_hover: Path) -> None:
    record = validate_record(read_folder(forged_hover.parent / "planner").sorted_records()[0])
    assert record["success"]
    # Still inside its last control step, but not a multiple of the 5 ms physics step the env stamps laps on.
    with pytest.raises(InvalidRecordError, match=r"not a physics tick \(1/200 s\)"):
        validate_record(seal({**record, "lap_time": record["lap_time"] - 0.001}))
    crashed = {"success": False, "lap_time": None, "crashed": True, "crash_reason": "ground"}
    with pytest.raises(InvalidRecordError, match="failed episode with all 4 gates passed"):
        validate_record(seal({**record, **crashed}))
