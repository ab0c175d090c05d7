"""The leaderboard's robustness (issue 72, item 3): a column on the main table and a table on each entry's page,
from the records an entry already lists, validated like every record; it never changes the rank key."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from leaderboard_fixtures import add, make_repo, rewrite_records, write_records

from racebench.envs.perturbations import ROBUSTNESS
from racebench.leaderboard import ranking
from racebench.leaderboard.entries import MAIN_IDS, EntryError, load_config, load_entries
from racebench.leaderboard.robustness import ROBUSTNESS_EPISODES
from racebench.leaderboard.site import build_site

N = 12  # episodes per cell: the ranked count in these tests (the package's is 50)


@pytest.fixture()
def twelve(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rank (and pair) on the first 12 public seeds."""
    monkeypatch.setattr(ranking, "RANKED_EPISODES", N)


def board_with(tmp_path: Path) -> Path:
    """Two methods (one policy for all tracks each): hover 10/12 on every main id, random 6/12."""
    board = make_repo(tmp_path)
    for spec, wins in (("hover", 10), ("random", 6)):
        for env_id in MAIN_IDS:
            write_records(tmp_path / "results" / spec, spec, env_id, wins, N)
        add(board, spec, spec, [tmp_path / "results" / spec])
    return board


def rows(board: Path) -> dict[str, ranking.Row]:
    config = load_config(board)
    return {e.name: ranking.entry_row(e, config) for e in load_entries(board)}


def test_robustness_never_changes_the_rank_key_or_the_order(tmp_path: Path, twelve: None) -> None:
    board = board_with(tmp_path)
    before = rows(board)
    order = [r.name for r in ranking.rank(list(before.values()))]
    assert order == ["hover", "random"] and all(not r.robustness.flown for r in before.values())
    # hover collapses under every perturbation on S and J (0/12), random gains (12/12 on S): the key stays
    for name in ROBUSTNESS:
        for track in ("S", "J"):
            write_records(tmp_path / "results" / "hover", "hover", f"RaceObs-{track}-{name}-v0", 0, N)
        write_records(tmp_path / "results" / "random", "random", f"RaceObs-S-{name}-v0", N, N)
    after = rows(board)
    assert [r.name for r in ranking.rank(list(after.values()))] == order
    for name, row in after.items():
        assert row.key() == before[name].key() and row.cells == before[name].cells and row.ranked
    assert after["hover"].robustness.score.value == 0.0 and after["hover"].robustness.score.tracks == ("S", "J")
    assert after["random"].robustness.score.per_track == {"S": pytest.approx(N / 6)}  # 12/12 against 6/12


def test_the_site_shows_the_column_and_the_entry_table(tmp_path: Path, twelve: None) -> None:
    board = board_with(tmp_path)
    wins = {"Latency": 0, "Control30Hz": 10, "Mass": 5}  # the rest as nominal: 10/12
    for name in ROBUSTNESS:
        write_records(tmp_path / "results" / "hover", "hover", f"RaceObs-S-{name}-v0", wins.get(name, 10), N)
    for name in ("Latency", "Mass", "Drag"):  # J: three of the ten, so J does not count
        write_records(tmp_path / "results" / "hover", "hover", f"RaceObs-J-{name}-v0", 1, N)
    index = build_site(board, tmp_path / "site")
    text = index.read_text()
    header = re.search(r'<table class="ranking" id="ranking-self-reported">\n<tr>(.*?)</tr>', text).group(1)
    assert "robustness <small>(perturbed / nominal SR, not ranked)</small>" in header
    expected = (0 + 10 + 5 + 10 * (len(ROBUSTNESS) - 3)) / len(ROBUSTNESS) / 10  # mean perturbed over nominal 10/12
    assert f"{100 * expected:.0f} %<br><small>S; J left out: 3/10 perturbations flown</small>" in text
    data = json.loads(re.search(r'id="leaderboard-data">(.*?)</script>', text, re.S).group(1))["entries"]
    assert data["hover"]["robustness"]["score"] == pytest.approx(expected) and data["random"]["robustness"] is None
    page = (tmp_path / "site" / "entries" / "hover.html").read_text()
    table = re.search(r'<table id="robustness-table">(.*?)</table>', page, re.S).group(1)
    latency = re.findall(r"<td[^>]*>.*?</td>", table.split("<tr><th>S-shaped")[1])[1]
    assert 'class="num drop"' in latency and "0/12, Δ -83" in latency  # 10 laps lost, none gained: p_holm < 0.05
    assert "No robustness records" in (tmp_path / "site" / "entries" / "random.html").read_text()


def test_robustness_records_are_validated_like_every_record(tmp_path: Path) -> None:
    board = board_with(tmp_path)
    folder = write_records(tmp_path / "results" / "hover", "hover", "RaceObs-S-Wind-v0", 10, N)
    rewrite_records(folder, lambda r: {**r, "success": True} if r["env_id"].endswith("Wind-v0") else r)  # no reseal
    with pytest.raises(EntryError, match="invalid record"):
        load_entries(board)
    rewrite_records(folder, lambda r: r if not r["env_id"].endswith("Wind-v0") else None)
    write_records(folder, "random", "RaceObs-S-Wind-v0", 10, N)  # another policy's records in hover's folder
    with pytest.raises(EntryError, match="record of another policy"):
        load_entries(board)
    rewrite_records(folder, lambda r: None if r["agent"] == "random" else r)
    write_records(folder, "hover", "RaceObs-S-Wind-v0", 10, N)
    rewrite_records(folder, lambda r: None if r["env_id"].endswith("Wind-v0") and r["seed"] == 1_000_000 else r)
    with pytest.raises(EntryError, match="not the first 11 seeds"):  # a scene left out: the pairs would be chosen
        load_entries(board)


def test_the_robustness_count_is_the_ranked_count() -> None:
    assert ROBUSTNESS_EPISODES == ranking.RANKED_EPISODES
