"""The leaderboard's unseen-tracks column and ranking (issue 73): fixture entries, records written, not flown."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from leaderboard_fixtures import SALT, add, make_key, make_repo, meta, write_hover_onnx, write_records
from test_leaderboard_site import parse

from racebench.leaderboard import ranking
from racebench.leaderboard.entries import MAIN_IDS, UNSEEN_ID, EntryError, dump_entry, load_entries
from racebench.leaderboard.submit import add_entry
from racebench.leaderboard.unseen import UNSEEN_RANKED_EPISODES, unseen_cell, unseen_rows


def unseen_line(root: Path, policy: str, folder: Path) -> dict:
    """An ``unseen:`` policy line (paths relative to the repository root)."""
    return {"policy": policy, "records": [folder.relative_to(root).as_posix()]}


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """Entries: two ranked on the held-out tracks (60 and 20 of 100), one short (10 episodes), one without an
    unseen line, a signed ONNX entry that adds an unseen line after signing, and the planner (a reference)."""
    from racebench.leaderboard.signing import sign_entry

    root = tmp_path_factory.mktemp("repo")
    keys = tmp_path_factory.mktemp("keys")
    key, pem, fingerprint = make_key(keys)
    board = make_repo(root, public_key_pem=pem)
    res = root / "results"
    specs = {}
    for name in ("strong", "weak", "short", "none"):
        onnx = write_hover_onnx(root / "p" / f"{name}.onnx")  # a file per entry (the same graph: records by path)
        specs[name] = onnx.relative_to(root).as_posix()
        for env_id in MAIN_IDS:
            write_records(res / name, str(onnx), env_id, 5, 10)
    for name, successes, n in (("strong", 60, 100), ("weak", 20, 100), ("short", 9, 10)):
        write_records(res / f"{name}-unseen", str(root / specs[name]), UNSEEN_ID, successes, n, lap=5.0)
        line = unseen_line(root, specs[name], res / f"{name}-unseen")
        add_entry(board, str(root / specs[name]), {**meta(name), "unseen": line}, [str(res / name)])
    add(board, str(root / specs["none"]), "none", [res / "none"])
    for env_id in MAIN_IDS:
        write_records(res / "planner", "planner", env_id, 10, 10)
    write_records(res / "planner", "planner", UNSEEN_ID, 100, 100, lap=4.0)
    planner = {"policy": "builtin:planner", "records": ["results/planner"]}
    add_entry(board, "planner", {**meta("planner"), "unseen": planner}, [str(res / "planner")])
    signed = write_hover_onnx(root / "p" / "signed.onnx")
    for env_id in MAIN_IDS:
        write_records(res / "signed", str(signed), env_id, 4, 10)
        write_records(keys / "private" / "signed-onnx-all", str(signed), env_id, 5, 10, seed_set="private")
    add(board, str(signed), "signed", [res / "signed"])
    (entry,) = load_entries(board, ["signed"])
    sign_entry(entry, SALT, key, keys / "private", episodes=10)
    write_records(res / "signed-unseen", str(signed), UNSEEN_ID, 30, 100)
    path = board / "signed" / "entry.yaml"
    data = yaml.safe_load(path.read_text())
    path.write_text(dump_entry({**data, "unseen": unseen_line(root, "p/signed.onnx", res / "signed-unseen")}))
    return board, fingerprint


def test_cells_count_the_first_100_public_episodes(board: tuple[Path, str]) -> None:
    entries = {e.name: e for e in load_entries(board[0])}
    assert (unseen_cell(entries["strong"]).successes, unseen_cell(entries["strong"]).n) == (60, 100)
    assert unseen_cell(entries["none"]) is None and entries["none"].unseen is None
    rows = unseen_rows(list(entries.values()))
    assert [r.entry.name for r in rows] == ["strong", "signed", "weak", "short", "planner", "none"]
    assert [r.ranked for r in rows] == [True, True, True, False, False, False]  # short: 10 < 100; planner: reference
    assert UNSEEN_RANKED_EPISODES == 100


def test_the_site_ranks_the_unseen_tracks_on_their_own(board: tuple[Path, str], tmp_path: Path) -> None:
    from racebench.leaderboard.site import build_site

    before = ranking.RANKED_EPISODES
    ranking.RANKED_EPISODES = 10  # the fixture's per-track cells have 10 episodes
    try:
        index = build_site(board[0], tmp_path / "site", pinned_key_sha256=board[1])
    finally:
        ranking.RANKED_EPISODES = before
    page = parse(index)
    table = page.tables["ranking-unseen"]
    names = [row[1][0] for row in table[1:]]
    assert names == ["strong", "signed", "weak", "short", "planner", "none"]
    assert [row[0][0] for row in table[1:]] == ["1", "2", "3", "–", "–", "–"]
    assert table[1][2][0].startswith("60 % [50–69]") and table[1][2][1]  # bold: above every other ranked interval
    assert not table[2][2][1] and table[6][2][0] == "—" and "no unseen-tracks policy" in table[6][7][0]
    assert "under 100 episodes" in table[4][7][0] and "reference" in table[5][7][0]
    assert [row[4][0] for row in table[1:6]] == ["public"] * 5  # no unseen line is signed here
    assert page.tables["ranking-verified"][1][1][0].startswith("signed")  # still verified: the line is not signed
    main = [row for table in page.tables.values() for row in table if row and row[1][0].startswith("none ")]
    assert main and any(cell[0] == "—" for cell in main[0])  # the main ranking's unseen column
    entry_page = parse(tmp_path / "site" / "entries" / "strong.html").tables["unseen"]
    assert [row[1][0].split(" 60/100")[0] for row in entry_page[1:]] == ["60 % [50–69]"] * 2  # ranked and all
    assert "No <code>unseen:</code> policy" in (tmp_path / "site" / "entries" / "none.html").read_text()
    data = page.data
    assert '"unseen": null' in data or '"unseen":null' in data.replace(" ", "")


def test_a_bad_unseen_line_is_named(board: tuple[Path, str], tmp_path: Path) -> None:
    root = board[0].parents[1]
    with pytest.raises(EntryError, match="unseen: missing fields"):
        add_entry(board[0], "builtin:hover", {**meta("x1"), "unseen": {"policy": "builtin:hover"}},
                  [str(root / "results" / "none")])  # fmt: skip
    other = {"policy": "builtin:hover", "records": ["results/strong-unseen"]}  # strong's records, another policy
    with pytest.raises(EntryError, match="another policy .* not of its unseen policy builtin:hover"):
        add_entry(board[0], str(root / "p/none.onnx"), {**meta("x2"), "unseen": other}, [str(root / "results/none")])
