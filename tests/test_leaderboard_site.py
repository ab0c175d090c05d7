"""The static site: built from small fixture entries (records written, not flown), checked as HTML and in chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from leaderboard_fixtures import GC_AGENT, SALT, add, evaluate, make_key, make_repo, write_hover_onnx, write_records

from racebench import cli
from racebench.evaluation.statistics import wilson_interval
from racebench.leaderboard import ranking
from racebench.leaderboard.entries import MAIN_IDS

ROOT = Path(__file__).parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class Page(HTMLParser):
    """Links, table rows (cell texts and bold flags) and the embedded JSON of one page."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []
        self.tables: dict[str, list[list[tuple[str, bool]]]] = {}
        self.table: str | None = None
        self.cell: list[str] | None = None
        self.bold = False
        self.script = False
        self.data = ""

    def handle_starttag(self, tag: str, attrs: list) -> None:
        """Collect links; open tables, rows and cells."""
        attrs = dict(attrs)
        for key in ("href", "src"):
            if key in attrs:
                self.refs.append(attrs[key])
        if tag == "table":
            self.table = attrs.get("id", f"table{len(self.tables)}")
            self.tables[self.table] = []
        elif tag == "tr" and self.table:
            self.tables[self.table].append([])
        elif tag == "td" and self.table:
            self.cell, self.bold = [], "best" in attrs.get("class", "")
        elif tag == "script":
            self.script = attrs.get("type") == "application/json"

    def handle_endtag(self, tag: str) -> None:
        """Close cells (text and bold flag), tables and scripts."""
        if tag == "td" and self.cell is not None:
            self.tables[self.table][-1].append((" ".join("".join(self.cell).split()), self.bold))
            self.cell = None
        elif tag == "table":
            self.table = None
        elif tag == "script":
            self.script = False

    def handle_data(self, data: str) -> None:
        """Cell text and the embedded JSON."""
        if self.cell is not None:
            self.cell.append(data + " ")
        if self.script:
            self.data += data


def parse(path: Path) -> Page:
    """Parse one HTML file of the site."""
    page = Page()
    page.feed(path.read_text())
    return page


#: The protocol's ranked count of the committed leaderboard (the fixtures below rank their 10-episode cells).
RANKED_EPISODES = ranking.RANKED_EPISODES


@pytest.fixture(scope="module", autouse=True)
def _ten_ranked_episodes():
    """The fixture entries write 10 episodes per cell (fast): ranked on the first 10 seeds in these tests."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ranking, "RANKED_EPISODES", 10)
        yield


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Entries with chosen counts: strong (9/10 a track), weak (2/10), a one-track entry, a signed ONNX, refs."""
    from racebench.leaderboard.entries import load_entries
    from racebench.leaderboard.signing import sign_entry
    from racebench.leaderboard.site import build_site

    root = tmp_path_factory.mktemp("repo")
    keys = tmp_path_factory.mktemp("keys")  # outside the repository, as the maintainers' secrets are
    key, pem, fingerprint = make_key(keys)
    board = make_repo(root, public_key_pem=pem)
    res = root / "results"
    onnx_a, onnx_b = write_hover_onnx(root / "p" / "a.onnx"), write_hover_onnx(root / "p" / "b.onnx")
    onnx_b.write_bytes(onnx_b.read_bytes() + b"")  # same graph, other file: the ids below are by path
    (root / "p" / "sneaky.py").write_text(GC_AGENT)
    (root / "p" / "weak.py").write_text(GC_AGENT.replace("Sneaky", "Weak"))
    strong_spec, weak_spec = f"{root / 'p' / 'sneaky.py'}:Sneaky", f"{root / 'p' / 'weak.py'}:Weak"
    for env_id in MAIN_IDS:
        write_records(res / "strong", strong_spec, env_id, 9, 10, lap=6.0)
        write_records(res / "weak", weak_spec, env_id, 2, 10, lap=5.0)
        write_records(res / "verified", str(onnx_a), env_id, 2, 10)
        write_records(keys / "private" / "verified-onnx-all", str(onnx_a), env_id, 5, 10, seed_set="private")
        write_records(res / "planner", "planner", env_id, 10, 10, lap=7.0)
    for variant, (strong_k, weak_k) in {"Density5": (8, 1), "GateShift1.0": (6, 3)}.items():
        write_records(res / "strong", strong_spec, f"RaceObs-S-{variant}-v0", strong_k, 10)
        write_records(res / "weak", weak_spec, f"RaceObs-S-{variant}-v0", weak_k, 10)
    write_records(res / "one-track", str(onnx_b), MAIN_IDS[0], 10, 10)
    add(board, strong_spec, "strong", [res / "strong"])
    add(board, weak_spec, "weak", [res / "weak"])
    add(board, str(onnx_a), "verified-onnx", [res / "verified"])
    add(board, {"S": str(onnx_b)}, "one-track", [res / "one-track"])
    add(board, "planner", "planner", [res / "planner"])
    (entry,) = load_entries(board, ["verified-onnx"])
    sign_entry(entry, SALT, key, keys / "private", episodes=10)  # the records are there: nothing is flown
    out = root / "site"
    build_site(board, out, pinned_key_sha256=fingerprint)
    return out


def test_the_site_is_self_contained(site: Path) -> None:
    pages = [site / "index.html", *sorted((site / "entries").glob("*.html"))]
    assert {p.stem for p in pages[1:]} == {"strong", "weak", "verified-onnx", "one-track", "planner"}
    for page in pages:
        for ref in parse(page).refs:
            assert not re.match(r"^[a-z]+:", ref) and not ref.startswith("//"), f"{page.name}: external {ref}"
            assert (page.parent / ref).resolve().is_file(), f"{page.name}: {ref} does not exist"
        assert "<script" not in page.read_text().replace('<script type="application/json"', "")


def test_ranking_per_tier_with_n_intervals_and_separated_bold(site: Path) -> None:
    page = parse(site / "index.html")
    ranked = page.tables["ranking-self-reported"][1:]
    assert [row[1][0].split()[0] for row in ranked] == ["strong", "weak"]
    assert ranked[0][2][0].startswith("90.0 % lap ")  # the rank key is a column of its own
    low, high = wilson_interval(9, 10)
    assert ranked[0][3][0].startswith(f"90 % [{100 * low:.0f}–{100 * high:.0f}] 9/10")
    # Circle and J: 9/10 [60–98] against 2/10 [6–51] is separated, so bold; on S the unranked one-track
    # entry's 10/10 [72–100] overlaps it, so not bold. The weak row never.
    assert [bold for _, bold in ranked[0][3:6]] == [False, True, True]
    assert not any(bold for _, bold in ranked[1])
    assert ranked[0][6][0] == "one policy for all" and ranked[0][8][0] == "no"  # cross-track, teacher
    assert ranked[0][7][0] == "–"  # robustness: no records of the suite
    assert ranked[0][9][0] == "steps unknown, wall clock unknown a test machine"  # no summary.json, none declared
    unranked = page.tables["unranked-self-reported"][1:]
    assert [(row[0][0], row[1][0].split()[0]) for row in unranked] == [("–", "one-track")]
    assert unranked[0][2][0] == "– (1/3 tracks)"
    assert unranked[0][3][0].startswith("100 % [72–100] 10/10") and not unranked[0][3][1]  # overlaps strong's
    verified = page.tables["ranking-verified"][1:]
    assert [row[1][0].split()[0] for row in verified] == ["verified-onnx"]
    assert verified[0][3][0].startswith("50 % [24–76] 5/10")  # the signed private numbers, not the public 2/10
    assert "private seeds" in verified[0][10][0]
    reference = page.tables["table-reference"][1:]
    assert [(row[0][0], row[1][0].split()[0]) for row in reference] == [("–", "planner")]
    assert not any(bold for row in reference for _, bold in row)


def test_aggregate_statistics_bootstrap_and_the_single_seed_caveat(site: Path) -> None:
    page = parse(site / "index.html")
    data = json.loads(page.data)["entries"]
    agg = data["strong"]["aggregate"]
    assert agg["mean_sr"] == pytest.approx(0.9) and agg["episodes"] == 30
    assert 0.7 < agg["low"] < 0.9 < agg["high"] <= 1.0  # a real interval around the point
    assert data["one-track"]["aggregate"] is None  # one track: no aggregate over tracks to bootstrap
    rows = {row[0][0]: row for row in page.tables["aggregate"][1:]}
    assert set(rows) == {"strong", "weak", "verified-onnx", "planner"}
    assert "one training run per policy" in rows["strong"][4][0]
    assert "single training run (one training seed)" in (site / "index.html").read_text()


def test_probability_of_improvement_within_a_tier(site: Path) -> None:
    rows = parse(site / "index.html").tables["improvement"][1:]
    assert [(row[0][0], row[1][0]) for row in rows] == [("strong", "weak")]  # the verified tier has one entry
    # 9/10 against 2/10 on every track: P = 0.9 * 0.8 + (0.9 * 0.2 + 0.1 * 0.8) / 2 = 0.85.
    point, interval = rows[0][2][0].split(" ", 1)
    low, high = (float(x) for x in interval.strip("[]").split("–"))
    assert float(point) == pytest.approx(0.85) and 0.5 < low < 0.85 < high <= 1.0


def test_probability_of_improvement_is_mann_whitney_u_over_n_m() -> None:
    from scipy.stats import mannwhitneyu

    from racebench.evaluation.statistics import probability_of_improvement

    rng = np.random.default_rng(5)
    ids = ["A", "B"]
    x = [{"env_id": i, "success": bool(s)} for i in ids for s in rng.random(40) < (0.7 if i == "A" else 0.4)]
    y = [{"env_id": i, "success": bool(s)} for i in ids for s in rng.random(30) < 0.5]
    expected = np.mean([
        mannwhitneyu([r["success"] for r in x if r["env_id"] == i], [r["success"] for r in y if r["env_id"] == i])
        .statistic / (40 * 30) for i in ids
    ])  # fmt: skip
    result = probability_of_improvement(x, y, ids)
    assert result["p"] == pytest.approx(expected) and result["low"] < result["p"] < result["high"]
    assert probability_of_improvement(x, x, ids)["p"] == pytest.approx(0.5)
    wins = [{"env_id": i, "success": True} for i in ids]
    losses = [{"env_id": i, "success": False} for i in ids]
    assert probability_of_improvement(wins, losses, ids) == {"p": 1.0, "low": 1.0, "high": 1.0}


def test_paper_tables_bold_only_where_intervals_separate(site: Path) -> None:
    from types import SimpleNamespace

    from racebench.leaderboard.entries import Cell
    from racebench.leaderboard.ranking import Row, table_ii_html

    # On the fixture site no SR interval is separated from every rival's (strong's [60–98] meets verified's).
    table = parse(site / "index.html").tables["table-ii"]
    assert len(table) == 1 + 5 and not any(bold for row in table[1:] for _, bold in row)
    assert ("90 [60–98]", False) in [row[3] for row in table[1:]]  # strong's SR on S
    rows = [
        Row(SimpleNamespace(name=name), tier, {"RaceObs-S-v0": Cell("RaceObs-S-v0", "public", 10, k, (5.0,) * k)})
        for name, tier, k in (("good", "self-reported", 10), ("bad", "self-reported", 0), ("ref", "reference", 10),
                              ("mid", "self-reported", 6))
    ]  # fmt: skip
    separated = parse_html(table_ii_html(rows[:3]))
    sr_on_s = sorted(cells[3] for cells in separated[1:])  # good, bad and the privileged ref
    assert sr_on_s == [("0 [0–28]", False), ("100 [72–100]", False), ("100 [72–100]", True)]  # ref never bold
    overlapping = parse_html(table_ii_html([rows[0], rows[3]]))
    assert not any(b for cells in overlapping[1:] for _, b in cells)  # 10/10 [72–100] meets 6/10 [31–83]


def test_table_iv_is_one_table_per_track_and_table_iii_says_why_it_is_empty(site: Path) -> None:
    page = parse(site / "index.html")
    text = (site / "index.html").read_text()
    s_table = page.tables["table-iv-s"]
    assert len(s_table) == 1 + 2  # strong and weak: the only methods flown on S's variants
    strong = s_table[1]
    assert len(strong) == 8 and strong[3] == ("80 [49–94]", True) and strong[7] == ("60 [31–83]", False)
    assert [cell[0] for cell in strong[:3]] == ["–", "–", "–"]  # densities 2-4 not flown
    assert "table-iv-circle" not in page.tables and "No method was flown on the 3D Circle track" in text
    assert "No ablation entries yet" in text and "table-iii" not in page.tables


def test_table_iii_rows_are_vision_ppo_and_its_ablations_in_the_papers_order() -> None:
    from types import SimpleNamespace

    from racebench.leaderboard.entries import Cell
    from racebench.leaderboard.ranking import Row, table_iii_html

    def row(name: str, k: int, tier: str = "self-reported") -> Row:
        cell = Cell("RaceObs-S-v0", "public", 10, k, (5.0,) * k)
        return Row(SimpleNamespace(name=name), tier, {"RaceObs-S-v0": cell})

    others = [row("vision-distill", 10), row("planner", 10, "reference")]
    assert table_iii_html([row("vision-ppo", 9), *others]) is None  # the method alone is no ablation table
    rows = [row("vision-one-step", 0), *others, row("vision-ppo", 10), row("vision-no-gru", 2)]
    html = table_iii_html(rows)
    assert re.findall(r"<tr><th>([^<]+)</th>", html) == ["vision-ppo", "vision-no-gru", "vision-one-step"]
    table = parse_html(html)  # the td cells: SR on S, 3D Circle, J
    assert table[1][0] == ("100 [72–100]", True) and table[3][0] == ("0 [0–28]", False)  # 10/10 apart from 0/10
    assert table[2][0] == ("20 [6–51]", False) and table[1][1] == ("–", False)  # no Circle policy: no cell
    assert [line[-1][0] for line in table[1:]] == ["public"] * 3  # the seeds of each row's cells are named
    verified = [row("vision-ppo", 6, "verified"), row("vision-no-gru", 9)]
    assert "private (signed)" in table_iii_html(verified)


def test_self_reported_methods_above_a_verified_one_are_noted(site: Path) -> None:
    """strong (self-reported, 9/10 public) ranks above verified-onnx (5/10 signed private): the site says in one
    line why the two do not compare like for like, and Table III names each row's seeds."""
    from types import SimpleNamespace

    from racebench.leaderboard.entries import Cell
    from racebench.leaderboard.ranking import Row, above_verified, above_verified_note

    text = (site / "index.html").read_text()
    assert "strong scores above a verified method" in text  # weak (2/10) lies below it: not named
    assert "Rows differ in their seeds" in text

    def row(name: str, k: int, tier: str) -> Row:
        return Row(SimpleNamespace(name=name), tier, {i: Cell(i, "public", 10, k, (5.0,) * k) for i in MAIN_IDS})

    rows = [row("a", 9, "self-reported"), row("b", 2, "self-reported"), row("v", 5, "verified")]
    assert above_verified(rows) == ["a"]
    assert above_verified_note([row("a", 9, "self-reported")]) == ""  # no verified method: nothing to compare


def test_entry_pages_show_trajectory_plots_and_on_demand_videos(tmp_path: Path, monkeypatch) -> None:
    """Trajectories saved with the records become a plot per main id; videos only with videos=True."""
    import racebench.reporting.video
    from racebench.leaderboard.site import build_site

    board = make_repo(tmp_path)
    flown = evaluate("follow", tmp_path / "results" / "follow", 1, envs=(MAIN_IDS[0],), save_trajectories=True)
    add(board, "follow", "follow", [flown])
    written_site = build_site(board, tmp_path / "site")
    page = (written_site.parent / "entries" / "follow.html").read_text()
    assert 'src="follow/S.png"' in page and (written_site.parent / "entries" / "follow" / "S.png").stat().st_size > 0
    assert "No saved trajectories for RaceObs-Circle-v0, RaceObs-J-v0" in page and "<video" not in page

    def fake_video(spec, env_id, seed, path, **kw):  # flying the episode is tested in test_video.py
        Path(path).write_bytes(b"mp4")
        return Path(path), {}

    monkeypatch.setattr(racebench.reporting.video, "render_episode_video", fake_video)
    with_videos = build_site(board, tmp_path / "site", videos=True)
    page = (with_videos.parent / "entries" / "follow.html").read_text()
    assert page.count("<video") == 1 and (with_videos.parent / "entries" / "follow" / "S.mp4").is_file()
    for ref in parse(with_videos.parent / "entries" / "follow.html").refs:
        assert (with_videos.parent / "entries" / ref).resolve().is_file(), ref


def test_the_ranking_weighs_each_track_the_same(tmp_path: Path) -> None:
    """100/100 on its own track and 0/10 elsewhere (pooled 83 %, mean 33 %) ranks below 5/10 everywhere (50 %)."""
    board = make_repo(tmp_path)
    res = tmp_path / "results"
    for name in ("own", "even"):
        (tmp_path / f"{name}.py").write_text(GC_AGENT.replace("Sneaky", name.capitalize()))
    own, even = (f"{tmp_path / n}.py:{n.capitalize()}" for n in ("own", "even"))
    write_records(res / "own", own, MAIN_IDS[0], 100, 100, lap=3.0)  # laps 3.0-12.9 s: inside the time limit
    for env_id in MAIN_IDS:
        if env_id != MAIN_IDS[0]:
            write_records(res / "own", own, env_id, 0, 10)
        write_records(res / "even", even, env_id, 5, 10)
    add(board, own, "own", [res / "own"])
    add(board, even, "even", [res / "even"])
    out = tmp_path / "site"
    assert cli.main(["leaderboard", "build", "--leaderboard", str(board), "--out", str(out)]) == 0
    ranked = parse(out / "index.html").tables["ranking-self-reported"][1:]
    assert [row[1][0].split()[0] for row in ranked] == ["even", "own"]
    assert ranked[1][2][0].startswith("33.3 %") and ranked[0][2][0].startswith("50.0 %")  # the key: mean of tracks


def parse_html(text: str) -> list:
    """The rows of the single table in an HTML fragment."""
    page = Page()
    page.feed(text)
    return next(iter(page.tables.values()))


def test_entry_pages_show_metadata_and_every_cell(site: Path) -> None:
    page = parse(site / "entries" / "strong.html")
    text = (site / "entries" / "strong.html").read_text()
    assert "A. Tester" in text and "self-reported" in text and "training_seeds" in text
    assert "strong: a test policy" in text  # the one-line description
    cells = page.tables["cells"][1:]
    assert [row[1][0] for row in cells][:3] == list(MAIN_IDS) and all(row[4][0] == "10" for row in cells)
    signed = parse(site / "entries" / "verified-onnx.html").tables["signed"][1:]
    assert [(row[1][0], row[2][0].split(" ", 4)[-1]) for row in signed] == [(i, "5/10") for i in MAIN_IDS]


def console_messages(url: str) -> list[str]:
    """Console output of chromium loading ``url`` headless (our pages run no script, so any is an error)."""
    proc = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0",
         "--dump-dom", url],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0 and "</html>" in proc.stdout, proc.stderr[-2000:]
    return [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_the_site_loads_in_headless_chromium_without_console_messages(site: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.html"
    broken.write_text("<!DOCTYPE html><html><body><script>undefinedFunction();</script></body></html>")
    assert any("undefinedFunction" in m for m in console_messages(broken.as_uri()))  # the detector detects
    for page in [site / "index.html", *sorted((site / "entries").glob("*.html"))]:
        assert console_messages(page.as_uri()) == [], page.name


def test_the_committed_site_is_current(tmp_path: Path) -> None:
    """``results/leaderboard/site`` is what ``racebench leaderboard build`` makes of the committed entries."""
    ranking.RANKED_EPISODES = RANKED_EPISODES  # the package's own count (restored by the module's fixture)
    committed = ROOT / "results" / "leaderboard" / "site"
    assert (committed / "index.html").is_file() and (ROOT / "results" / "leaderboard" / "site.png").is_file()
    from racebench.leaderboard.site import build_site

    fresh = build_site(ROOT / "results" / "leaderboard", tmp_path / "site")
    for path in [fresh, *sorted((fresh.parent / "entries").glob("*.html")), fresh.parent / "style.css"]:
        relative = path.relative_to(fresh.parent)
        assert (committed / relative).read_text() == path.read_text(), f"{relative} is stale: rebuild the site"
