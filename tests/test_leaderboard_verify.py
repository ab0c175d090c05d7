"""``racebench leaderboard verify``: a faithful entry passes its replay, a doctored count or lap time fails."""

from __future__ import annotations

from pathlib import Path

import pytest
from leaderboard_fixtures import ENV, SALT, add, evaluate, folder_records, forge_successes, make_repo, rewrite_records

from racebench import cli
from racebench.evaluation.records import env_facts, seal
from racebench.evaluation.seeds import SALT_ENV
from racebench.evaluation.statistics import detectable_doctoring
from racebench.leaderboard.entries import Cell, load_entry
from racebench.leaderboard.verify import LAP_ABS_TOL_S, REPLAYED_FIELDS, check_cell, lap_tolerance, verify_entry


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
    steps_off = int(round(2.0 / dt))
    rewrite_records(
        repo.parents[1] / "results" / "planner",
        lambda r: seal({**r, "steps": r["steps"] - steps_off, "lap_time": (r["steps"] - steps_off) * dt}),
    )
    with pytest.raises(SystemExit, match=r"^racebench leaderboard verify: 1 of 1 cells failed$"):
        cli.main(argv)
    check = verify_entry(load_entry(repo / "planner"), tmp_path / "replay", episodes=3)[0]
    assert check.count_ok and not check.lap_ok
    assert check.lap_replayed - check.lap_committed == pytest.approx(2.0, abs=0.02)


@pytest.mark.parametrize(
    "edit",
    [
        pytest.param(lambda r, dt: {"steps": r["steps"] + 5, "lap_time": (r["steps"] + 5) * dt}, id="lap 0.1 s slower"),
        pytest.param(lambda r, dt: {"success": False, "lap_time": None, "crashed": True, "crash_reason": "gate:3",
                                    "gates_passed": 3, "steps": r["steps"] - 10}, id="crash at the last gate"),
    ],
)  # fmt: skip
def test_a_deterministic_builtin_is_verified_episode_by_episode(repo: Path, tmp_path: Path, edit, monkeypatch) -> None:
    """One planner episode edited to another plausible outcome: the count and mean-lap checks cannot see it."""
    folder = repo.parents[1] / "results" / "planner"
    record = folder_records(folder)[0]
    assert record["success"]
    edited = seal({**record, **edit(record, env_facts(ENV)["control_dt"])})
    rewrite_records(folder, lambda r: edited if r == record else r)
    check = verify_entry(load_entry(repo / "planner"), tmp_path / "replay")[0]
    assert check.count_ok and check.lap_ok  # 2 or 3 of 3 against 3 of 3; laps within 0.2 s
    assert check.episodes_compared == 3 and not check.episodes_ok and not check.ok
    (line,) = check.mismatches  # the other two episodes replay as recorded
    diff = [f"{k} {edited[k]!r} → {record[k]!r}" for k in REPLAYED_FIELDS if edited[k] != record[k]]
    assert line == f"seed {record['seed']}: {', '.join(diff)}"
    assert "FAIL (episodes)" in check.line() and line in check.line()
    monkeypatch.chdir(repo.parents[1])
    with pytest.raises(SystemExit, match=r"^racebench leaderboard verify: 1 of 1 cells failed$"):
        cli.main(["leaderboard", "verify", "--entry", "planner", "--out", str(tmp_path / "replay")])


def test_a_faithful_deterministic_entry_replays_every_episode(repo: Path, tmp_path: Path) -> None:
    checks = verify_entry(load_entry(repo / "hover"), tmp_path / "replay")
    assert [(c.episodes_compared, c.mismatches, c.ok) for c in checks] == [(8, (), True)]
    assert "episodes 8/8 replayed as recorded" in checks[0].line()


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
    first = folder_records(tmp_path / "results" / "hover-private")[0]
    moved = seal({**first, "seed": 10**12 + 12345})
    rewrite_records(tmp_path / "results" / "hover-private", lambda r: moved if r == first else r)
    entry = load_entry(board / "hover")  # in range, so valid without the salt
    with pytest.raises(ValueError, match="none picked"):
        verify_entry(entry, tmp_path / "replay")
