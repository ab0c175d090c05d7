"""``racebench leaderboard verify``: a faithful entry passes its replay, a doctored count or lap time fails."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from leaderboard_fixtures import ENV, SALT, add, evaluate, forge_successes, make_repo

from racebench import cli
from racebench.leaderboard.entries import Cell, load_entry
from racebench.leaderboard.seeds import SALT_ENV
from racebench.leaderboard.verify import LAP_ABS_TOL_S, check_cell, lap_tolerance, verify_entry
from racebench.records import env_facts, name_of, seal
from racebench.statistics import detectable_doctoring


def cell(k: int, n: int, laps: tuple[float, ...] = ()) -> Cell:
    """A public cell of ``k`` successes in ``n`` episodes with these laps."""
    return Cell(ENV, "public", n, k, laps)


def test_the_count_check_is_fisher_at_one_in_a_thousand() -> None:
    assert check_cell("e", cell(70, 100), [], cell(28, 40)).ok  # another CPU's replay of a 70 % claim
    low, high = detectable_doctoring((28, 40), (28, 40))
    assert not check_cell("e", cell(high, 40), [], cell(28, 40)).count_ok
    assert check_cell("e", cell(high - 1, 40), [], cell(28, 40)).count_ok
    # The size a doctored claim must have to be caught, at the leaderboard's 50 episodes per cell and a true 50 %:
    low, high = detectable_doctoring((25, 50), (25, 50))
    assert (25 - low, high - 25) == (17, 17)


def test_the_lap_check_allows_noise_and_catches_a_shift() -> None:
    laps = (6.0, 6.2, 6.4, 6.1)
    assert lap_tolerance(laps, laps) == pytest.approx(LAP_ABS_TOL_S + 4 * (2 * 0.1708**2 / 4) ** 0.5, abs=1e-3)
    assert check_cell("e", cell(4, 4, laps), laps, cell(4, 4, tuple(t + 0.3 for t in laps))).ok
    assert not check_cell("e", cell(4, 4, laps), laps, cell(4, 4, tuple(t + 1.0 for t in laps))).lap_ok
    assert check_cell("e", cell(1, 4, laps[:1]), laps[:1], cell(1, 4, (9.9,))).lap_ok  # one lap: not checked


@pytest.fixture()
def repo(tmp_path: Path) -> Path:
    """A leaderboard of hover (8 flown episodes) and the planner (3), on the obstacle-free level 1."""
    board = make_repo(tmp_path)
    evaluate("hover", tmp_path / "results" / "hover", 8)
    evaluate("planner", tmp_path / "results" / "planner", 3)
    add(board, "hover", "hover", [tmp_path / "results" / "hover"])
    add(board, "planner", "planner", [tmp_path / "results" / "planner"])
    return board


def test_verify_passes_a_rerun_and_fails_a_doctored_count(repo: Path, tmp_path: Path) -> None:
    checks = verify_entry(load_entry(repo / "hover"), tmp_path / "replay")
    assert [(c.committed, c.replayed, c.ok) for c in checks] == [((0, 8), (0, 8), True)]
    # 8 hover failures doctored into 8 record-valid successes: 8/8 claimed, 0/8 replayed, p = 1.6e-4 < 0.001.
    assert forge_successes(repo.parents[1] / "results" / "hover") == 8
    checks = verify_entry(load_entry(repo / "hover"), tmp_path / "replay")
    assert [(c.committed, c.replayed, c.count_ok) for c in checks] == [((8, 8), (0, 8), False)]
    assert checks[0].p_value < 0.001


def test_verify_checks_lap_times_and_the_cli_exits_nonzero(repo: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(repo.parents[1])
    argv = ["leaderboard", "verify", "--entry", "planner", "--out", str(tmp_path / "replay")]
    assert cli.main(argv) == 0
    # Doctor the planner's laps 2 s faster: each record stays consistent (its lap lies in its last step).
    dt = env_facts(ENV)["control_dt"]
    for path in (repo.parents[1] / "results" / "planner" / "records").glob("*.json"):
        record = json.loads(path.read_text())
        steps = record["steps"] - int(round(2.0 / dt))
        path.write_text(json.dumps(seal({**record, "steps": steps, "lap_time": steps * dt})))
    with pytest.raises(SystemExit, match=r"^racebench leaderboard verify: 1 of 1 cells failed$"):
        cli.main(argv)
    check = verify_entry(load_entry(repo / "planner"), tmp_path / "replay", episodes=3)[0]
    assert check.count_ok and not check.lap_ok
    assert check.lap_replayed - check.lap_committed == pytest.approx(2.0, abs=0.02)


def test_private_cells_need_the_salt_they_were_made_with(tmp_path: Path, monkeypatch) -> None:
    board = make_repo(tmp_path)
    evaluate("hover", tmp_path / "results" / "hover-private", 2, "private")
    add(board, "hover", "hover", [tmp_path / "results" / "hover-private"])
    entry = load_entry(board / "hover")
    monkeypatch.delenv(SALT_ENV, raising=False)
    with pytest.raises(ValueError, match=SALT_ENV):
        verify_entry(entry, tmp_path / "replay")
    with pytest.raises(ValueError, match="made with the salt"):
        verify_entry(entry, tmp_path / "replay", salt="another-salt-of-enough-length")
    monkeypatch.setenv(SALT_ENV, SALT)
    checks = verify_entry(entry, tmp_path / "replay", episodes=1)
    assert [(c.seed_set, c.committed, c.replayed, c.ok) for c in checks] == [("private", (0, 2), (0, 1), True)]
    # A private record moved to another seed of the range (re-sealed, renamed): only the salt can tell.
    path = sorted((tmp_path / "results" / "hover-private" / "records").glob("*.json"))[0]
    moved = seal({**json.loads(path.read_text()), "seed": 10**12 + 12345})
    path.unlink()
    (path.parent / name_of(moved)).write_text(json.dumps(moved))
    entry = load_entry(board / "hover")  # in range, so valid without the salt
    with pytest.raises(ValueError, match="none picked"):
        verify_entry(entry, tmp_path / "replay")
