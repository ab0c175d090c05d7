"""``racebench paper-tables``: the statistics it rests on against textbook values, the claims' verdicts on hand-made
episodes, and the committed ``results/`` regenerated from the committed records byte for byte."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from racebench.cli import main
from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.statistics import holm_adjust, trend_test
from racebench.reporting.campaigns import Run, RunSet, readme_campaign
from racebench.reporting.paper import (
    PAPER_VARIANTS,
    README_BEGIN,
    README_END,
    ClaimsSection,
    at_a_glance,
    cell,
    claims_page,
    judge_claims,
    relink,
    replace_readme_block,
    write_report,
)

ROOT = Path(__file__).parents[1]
TRACKS = ("S", "Circle", "J")


def test_holm_adjustment_matches_the_step_down_rule() -> None:
    # sorted 0.005, 0.01, 0.03, 0.04 -> x4, x3, x2, x1 = 0.02, 0.03, 0.06, 0.04 -> running max 0.02, 0.03, 0.06, 0.06
    assert holm_adjust([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjust([0.5, 0.9]) == pytest.approx([1.0, 1.0])  # capped at 1
    assert holm_adjust([]) == []


def test_trend_test_matches_agrestis_alcohol_and_malformation_example() -> None:
    """Agresti, Categorical Data Analysis (3rd ed.), infant malformation against the mother's alcohol consumption
    (scores 0, 0.5, 1.5, 4, 7): the linear trend statistic is M^2 = 6.57, z = 2.56, one-sided P = 0.005."""
    present, absent = [48, 38, 5, 1, 1], [17066, 14464, 788, 126, 37]
    trials = [p + a for p, a in zip(present, absent, strict=True)]
    z, p_down, p_up = trend_test([([0, 0.5, 1.5, 4.0, 7.0], present, trials)])
    assert z == pytest.approx(2.563, abs=2e-3) and z**2 == pytest.approx(6.57, abs=0.01)
    assert p_up == pytest.approx(0.0052, abs=2e-4) and p_down == pytest.approx(1 - p_up)


def test_trend_test_is_n_r_squared_and_strata_add_up() -> None:
    rng = np.random.default_rng(0)
    scores = np.repeat([2.0, 3.0, 4.0, 5.0], 50)
    outcome = rng.random(scores.size) < np.interp(scores, [2, 5], [0.9, 0.4])
    successes = [int(outcome[scores == s].sum()) for s in (2, 3, 4, 5)]
    z, p_down, _ = trend_test([([2, 3, 4, 5], successes, [50] * 4)])
    r = np.corrcoef(scores, outcome.astype(float))[0, 1]
    assert z**2 == pytest.approx(scores.size * r**2) and z < 0 and p_down < 0.01
    twice, _, _ = trend_test([([2, 3, 4, 5], successes, [50] * 4)] * 2)
    assert twice == pytest.approx(z * np.sqrt(2))  # two identical strata: statistic x2, variance x2
    assert trend_test([([1, 2], [3, 3], [3, 3])]) == (0.0, 1.0, 1.0)  # all alike: no evidence either way


def episodes_of(method: str, env_id: str, successes: int, n: int = 100, seed: int = 0, order=None) -> pd.DataFrame:
    """``n`` hand-made episodes of ``method`` on ``env_id`` (seeds 1_000_000 + i), the first ``successes`` successful
    (or those at ``order``'s first positions)."""
    track, _, variant = env_id.removeprefix("RaceObs-").removesuffix("-v0").partition("-")
    won = np.zeros(n, bool)
    won[(order if order is not None else np.arange(n))[:successes]] = True
    return pd.DataFrame({
        "method": method, "training_seed": seed, "env_id": env_id, "track": track, "variant": variant or "default",
        "seed": 1_000_000 + np.arange(n), "success": won, "lap_time": np.where(won, 4.0, np.nan),
    })  # fmt: skip


def hand_made_campaign() -> pd.DataFrame:
    """vision-ppo clearly beats state-ppo (holds), clearly loses to vision-com (opposite), equals vision-no-gru on
    shuffled scenes (not separable); one-step at 2 %; success falls with density, not with gate shift."""
    rng = np.random.default_rng(1)
    frames = []
    for track in TRACKS:
        main_id = f"RaceObs-{track}-v0"
        frames += [
            episodes_of("vision-ppo", main_id, 60),
            episodes_of("state-ppo", main_id, 20),
            episodes_of("vision-com", main_id, 95),
            episodes_of("vision-no-gru", main_id, 60, order=rng.permutation(100)),
            episodes_of("vision-no-avoid", main_id, 58, order=rng.permutation(100)),
            episodes_of("vision-one-step", main_id, 2),
        ]
        for level, d in enumerate(DENSITIES):
            frames.append(episodes_of("vision-ppo", f"RaceObs-{track}-Density{d}-v0", 45 - 10 * level, n=50))
        for s in GATE_SHIFTS:
            frames.append(episodes_of("vision-ppo", f"RaceObs-{track}-GateShift{s}-v0", 30, n=50))
    return pd.concat(frames, ignore_index=True)


def test_claims_get_the_verdict_the_rule_gives() -> None:
    verdicts = {claim.claim: claim for claim in judge_claims(hand_made_campaign())}
    assert verdicts["vision-ppo > state-ppo"].verdict == "holds"
    assert verdicts["vision-ppo > vision-com"].verdict == "opposite"
    assert verdicts["vision-ppo > vision-no-gru"].verdict == "does not hold at this budget"
    assert verdicts["vision-ppo > vision-no-avoid"].verdict == "does not hold at this budget"
    assert verdicts["vision-ppo > vision-one-step"].verdict == "holds"
    assert verdicts["vision-one-step fails"].verdict == "holds"
    assert verdicts["vision-ppo: success falls with density 2-5"].verdict == "holds"
    assert verdicts["vision-ppo: success falls with gate shift 0.3-1.0 m"].verdict == "does not hold at this budget"
    held = verdicts["vision-ppo > state-ppo"]
    assert held.p_holm >= held.p and "S 60 vs 20" in held.evidence


def test_a_difference_claim_needs_the_same_direction_on_every_track_and_seed_pair() -> None:
    """Pooled, vision-ppo beats state-ppo by far; but on J a second training seed of vision-ppo does worse than
    state-ppo: the claim does not hold, whatever the pooled p."""
    frames = [hand_made_campaign(), episodes_of("vision-ppo", "RaceObs-J-v0", 10, seed=1)]
    verdicts = {claim.claim: claim.verdict for claim in judge_claims(pd.concat(frames, ignore_index=True))}
    assert verdicts["vision-ppo > state-ppo"] == "does not hold at this budget"


def test_missing_runs_are_named_not_judged() -> None:
    frame = hand_made_campaign()
    claims = judge_claims(frame[frame["method"] != "vision-com"])
    verdicts = {claim.claim: claim.verdict for claim in claims}
    assert verdicts["vision-ppo > vision-com"] == "not tested (missing runs)"
    assert verdicts["vision-ppo > state-ppo"] == "holds"


def _flying(frame: pd.DataFrame, flying: int, at_rest: int) -> pd.DataFrame:
    """``frame`` with vision-one-step (seed 0) at ``at_rest`` and vision-one-step-flying (seed 0) at ``flying``
    successes per track, on the same scenes; and a seed 1 of vision-one-step that finishes every scene."""
    frame = frame[frame["method"] != "vision-one-step"]
    extra = [episodes_of(m, f"RaceObs-{t}-v0", k, seed=s) for t in TRACKS for m, k, s in (
        ("vision-one-step", at_rest, 0), ("vision-one-step-flying", flying, 0), ("vision-one-step", 100, 1))]
    return pd.concat([frame, *extra], ignore_index=True)


def test_the_flying_start_claim_pairs_seed_0_of_each_and_joins_the_holm_family() -> None:
    """Campaign 2's rule: vision-one-step-flying > vision-one-step, seed 0 of each (the at-rest seed 1 that finishes
    everything is not its pair), judged as a difference claim; Holm over all eight claims. Without the flag (campaign
    1's rule) there is no such claim and the family is seven."""
    frame = _flying(hand_made_campaign(), flying=90, at_rest=2)
    seven = {claim.claim: claim for claim in judge_claims(frame)}
    eight = {claim.claim: claim for claim in judge_claims(frame, flying_start=True)}
    name = "flying-start hypothesis: vision-one-step-flying > vision-one-step (seed 0 of each)"
    assert name not in seven and set(eight) == set(seven) | {name}
    flying = eight[name]
    assert flying.verdict == "holds" and flying.evidence.startswith("S 90 vs 2; Circle 90 vs 2; J 90 vs 2")
    tested = [c for c in eight.values() if c.p is not None]
    assert len(tested) == 8 and not any(c.p_holm_bound for c in tested)
    for claim, adjusted in zip(tested, holm_adjust([c.p for c in tested]), strict=True):
        assert claim.p_holm == pytest.approx(adjusted)
    smallest = min(tested, key=lambda c: c.p)  # Holm multiplies the smallest p by the family's size
    assert smallest.p_holm == pytest.approx(8 * smallest.p)
    fewer = [c for c in seven.values() if c.p is not None]
    assert min(c.p_holm for c in fewer) == pytest.approx(7 * min(c.p for c in fewer))
    # Flying worse than at rest on every track, by far: the hypothesis is rejected (opposite).
    rejected = {c.claim: c for c in judge_claims(_flying(hand_made_campaign(), 5, 60), flying_start=True)}[name]
    assert rejected.verdict == "opposite"


def _runs(committed_but: set[tuple[str, str]] = frozenset()) -> RunSet:
    """The hand-made campaign's runs (seed 0 of each method on each track) as planned, all committed but
    ``committed_but`` ((config, track) pairs)."""
    methods = ("vision-ppo", "state-ppo", "vision-com", "vision-no-gru", "vision-no-avoid", "vision-one-step")
    planned = frozenset(Run(m, t, 0) for m in methods for t in TRACKS)
    return RunSet(planned, frozenset(r for r in planned if (r.config, r.track) not in committed_but))


def test_a_claim_waits_for_all_its_runs_and_holm_is_bounded_until_the_family_is_complete() -> None:
    """vision-com's J run is missing: its claim is not tested yet (5 of 6 runs). The others are tested, and Holm over
    the seven is only bounded: p (Holm) <= 7 p. A claim is given a verdict where the bound decides it (7 p < 0.05:
    holds; p >= 0.05 or a split direction: does not hold) and is pending otherwise (0.05 / 7 <= p < 0.05)."""
    frame = hand_made_campaign()
    frame = frame[frame["method"] != "vision-no-avoid"]
    order = np.r_[np.arange(50), np.arange(60, 65), np.arange(50, 60), np.arange(65, 100)]
    frame = pd.concat([frame, *(episodes_of("vision-no-avoid", f"RaceObs-{t}-v0", 55, order=order) for t in TRACKS)])
    partial = {c.claim: c for c in judge_claims(frame, _runs({("vision-com", "J")}))}
    assert partial["vision-ppo > vision-com"].verdict == "not tested yet (5 of 6 runs)"
    assert partial["vision-ppo > vision-com"].p is None
    held = partial["vision-ppo > state-ppo"]
    assert held.verdict == "holds" and held.p_holm_bound and held.p_holm == pytest.approx(7 * held.p)
    split = partial["vision-ppo > vision-no-gru"]
    assert split.verdict == "does not hold at this budget" and split.p_holm_bound
    waiting = partial["vision-ppo > vision-no-avoid"]  # 30 against 15 discordant scenes: p = 0.036
    assert 0.05 / 7 <= waiting.p < 0.05 and waiting.verdict == "pending (Holm over 7 claims, 1 not tested yet)"
    page = claims_page([ClaimsSection("campaign x", "x", 3, "", "x.yaml", 4_000_000, (17, 18),
                                      list(partial.values()), "")])  # fmt: skip
    assert f"| ≤ {7 * waiting.p:.2g} | **pending" in page and "While some of them wait for their runs" in page
    # All runs in: one Holm family of seven, exact, and every claim has its verdict.
    complete = {c.claim: c for c in judge_claims(frame, _runs())}
    tested = [c for c in complete.values() if c.p is not None]
    assert len(tested) == 7 and not any(c.p_holm_bound for c in tested)
    assert [c.p_holm for c in tested] == pytest.approx(holm_adjust([c.p for c in tested]))
    assert not any(c.verdict.startswith(("pending", "not tested")) for c in complete.values())
    assert complete["vision-ppo > vision-com"].verdict == "opposite"
    # One-step fails needs every run of vision-one-step.
    fails = {c.claim: c for c in judge_claims(frame, _runs({("vision-one-step", "S")}))}["vision-one-step fails"]
    assert fails.verdict == "not tested yet (2 of 3 runs)"


def test_claims_md_sets_each_campaigns_verdicts_side_by_side_never_pooled() -> None:
    """Two campaigns, each judged on its own episodes and Holm family: vision-ppo loses to vision-com in one and beats
    it in the other, and the page gives each its own verdict; the flying-start row is only the second's."""
    first = judge_claims(hand_made_campaign())
    frame = hand_made_campaign()
    frame = frame[frame["method"] != "vision-com"]
    frame = pd.concat([frame, *(episodes_of("vision-com", f"RaceObs-{t}-v0", 10) for t in TRACKS)])
    second = judge_claims(_flying(frame, 90, 2), flying_start=True)
    page = claims_page([
        ClaimsSection("campaign 1", "campaign-4m", 2, "flying starts", "one.yaml", 4_000_000, (26, 26), first, "B1"),
        ClaimsSection("campaign 2", "campaign-2", 3, "at rest", "two.yaml", 4_000_000, (1, 33), second, "B2"),
    ])  # fmt: skip
    lines = page.splitlines()
    assert "| claim | campaign 1 (env version 2) | campaign 2 (env version 3) |" in lines
    com = next(line for line in lines if line.startswith("| vision-ppo > vision-com |")).split(" | ")
    assert com[1].startswith("**opposite** (p Holm") and com[2].startswith("**holds** (p Holm")
    flying = next(line for line in lines if line.startswith("| flying-start hypothesis")).split(" | ")
    assert flying[1] == "– (not in campaign 1's rule)" and flying[2].startswith("**holds**")
    assert "| campaign 2 (`campaign-2`) | 3 | at rest | 4 M | 1 of 33 | `two.yaml` |" in lines
    one, two = page.index("## Campaign 1: `campaign-4m`, env version 2"), page.index("## Campaign 2: `campaign-2`")
    assert one < page.index("B1") < two < page.index("B2")
    assert "Holm's correction over its 7 claims" in page[one:two] and "over its 8 claims" in page[two:]


def test_a_cell_of_several_training_seeds_shows_their_mean_and_range() -> None:
    frame = pd.concat([episodes_of("m", "RaceObs-S-v0", k, seed=i) for i, k in enumerate((70, 80, 90))])
    found = cell(frame, "m", "RaceObs-S-v0")
    assert (found.seeds, found.success_rate, found.low, found.high) == (3, pytest.approx(0.8), 0.7, 0.9)
    assert found.text(100) == "80 (3 seeds 70–90) · paper 100"
    one = cell(frame[frame["training_seed"] == 0], "m", "RaceObs-S-v0")
    assert one.text() == "70 [60–78]" and one.text(3.4, lap=True) == "4.00 · paper 3.4"  # Wilson 70/100


def test_the_readme_block_sets_each_trained_row_below_the_papers() -> None:
    """The paper's row comes first, then ours; a method that finished no lap on a track says so instead of a time."""
    rows = [episodes_of(m, f"RaceObs-{t}-v0", k) for m, k in (("vision-ppo", 70), ("vision-distill", 80),
            ("vision-distill-ppo", 60), ("planner-fast", 95)) for t in TRACKS]  # fmt: skip
    rows += [episodes_of("state-ppo", f"RaceObs-{t}-v0", k) for t, k in (("S", 45), ("Circle", 0), ("J", 39))]
    lines = at_a_glance(pd.concat(rows, ignore_index=True)).splitlines()
    names = [line.split(" | ")[0].removeprefix("| ") for line in lines[2:8]]
    assert names == [
        "paper: vision-based (ours), 10 trials", "`vision-ppo`: the paper's method, trained here",
        "paper: state-based (ours), 10 trials", "`state-ppo`: the paper's method without depth, trained here",
        "`vision-distill`: best racebench method", "`planner-fast` (privileged reference)",
    ]  # fmt: skip
    assert lines[4].split(" | ")[1:4] == ["30 %, 3.5 s", "20 %, 3.8 s", "30 %, 3.1 s"]  # the paper's Table II
    assert lines[5].split(" | ")[1:4] == ["45 [36–55] %, 4.00 s", "0 [0–4] %, no lap", "39 [30–49] %, 4.00 s"]
    # Several training seeds: the same "SR [low–high] %" format, the row naming what the brackets are.
    rows += [episodes_of("vision-ppo", f"RaceObs-{t}-v0", k, seed=1) for t, k in (("S", 90), ("Circle", 50), ("J", 60))]
    lines = at_a_glance(pd.concat(rows, ignore_index=True)).splitlines()
    assert lines[3].startswith("| `vision-ppo`: the paper's method, trained here (mean [range] of 2 training seeds) |")
    assert lines[3].split(" | ")[1:4] == ["80 [70–90] %, 4.00 s", "60 [50–70] %, 4.00 s", "65 [60–70] %, 4.00 s"]


def test_the_readme_block_is_replaced_between_its_markers_only() -> None:
    text = f"head\n{README_BEGIN}\nold\n{README_END}\ntail\n"
    assert replace_readme_block(text, "new\n") == f"head\n{README_BEGIN}\nnew\n{README_END}\ntail\n"
    with pytest.raises(ValueError, match="no <!-- results-at-a-glance:begin -->"):
        replace_readme_block("no block", "new\n")


def test_committed_results_regenerate_byte_for_byte(tmp_path: Path) -> None:
    """The committed tables (campaign 1's in results/, campaign 2's in results/campaign-2/), claims.md and README
    block are what `racebench paper-tables` makes of the committed records (no training, no flying)."""
    written = write_report(ROOT, tmp_path, readme=None, links_from="results")  # as if written into results/
    compared = [path for path in written if path.suffix in (".md", ".csv", ".tex")]
    names = {path.relative_to(tmp_path).as_posix() for path in compared}
    assert names >= {"table_ii.md", "table_iii.tex", "table_iv.csv", "claims.md", "campaign-2/table_ii.md"}
    for path in compared:
        name = path.relative_to(tmp_path).as_posix()
        committed = ROOT / "results" / name
        assert committed.is_file(), f"results/{name} is missing: run racebench paper-tables"
        assert committed.read_text() == path.read_text(), f"results/{name} is stale: run racebench paper-tables"
    readme = (ROOT / "README.md").read_text()
    shown = readme_campaign(ROOT).out  # campaign 1's block until campaign 2 has all its runs
    block = relink((tmp_path / shown / "at_a_glance.md").read_text(), ROOT / "results" / shown, ROOT)  # from the root
    assert replace_readme_block(readme, block) == readme, "README's results block is stale: run racebench paper-tables"


def test_the_at_a_glance_links_work_from_the_readme_and_from_results(tmp_path: Path) -> None:
    block = "[a](docs/evaluation.md#the-lap-time-lower-bound), [b](results/table_ii.csv), [c](results/), [d](https://x.org/y)"
    assert relink(block, ROOT, ROOT / "results") == (
        "[a](../docs/evaluation.md#the-lap-time-lower-bound), [b](table_ii.csv), [c](./), [d](https://x.org/y)"
    )
    assert relink(relink(block, ROOT, ROOT / "results"), ROOT / "results", ROOT) == block
    for folder in (ROOT / "results", ROOT / "results" / "campaign-2"):  # each campaign's copy, from its folder
        links = re.findall(r"\]\(([^)\s#]+)", (folder / "at_a_glance.md").read_text())
        assert links and all((folder / link).exists() for link in links if ":" not in link)


def test_paper_tables_command_writes_into_out(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """One campaign by its run folder, with its references named: its tables in its own folder under --out, and
    claims.md (both campaigns) in --out; campaign 1's tables are not written."""
    argv = ["paper-tables", "--root", str(ROOT), "--out", str(tmp_path), "--no-readme",
            "--campaign", "baselines/experiments/campaign-2", "--references", "results"]  # fmt: skip
    assert main(argv) == 0
    assert (tmp_path / "campaign-2" / "table_ii.md").is_file() and "wrote" in capsys.readouterr().out
    assert (tmp_path / "claims.md").is_file() and not (tmp_path / "table_ii.md").exists()
    assert "env version 3" in (tmp_path / "campaign-2" / "table_iii.md").read_text()
    with pytest.raises(SystemExit, match="racebench paper-tables: .* is not a folder"):
        main(["paper-tables", "--root", str(tmp_path / "nowhere"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--references replaces one campaign's references: name the campaign"):
        main(["paper-tables", "--root", str(ROOT), "--out", str(tmp_path), "--references", "results"])
    with pytest.raises(SystemExit, match="several env versions"):  # campaign 2's runs with env version 2's references
        main([*argv[:-1], "results/env-v2"])


def test_final_training_success_pools_the_last_window_by_episodes() -> None:
    """One rollout's rate is a few episodes: the final success pools the rows of the last 200k steps by episodes."""
    from racebench.reporting.paper import FINAL_WINDOW_STEPS, final_training_success

    step = FINAL_WINDOW_STEPS // 4
    progress = pd.DataFrame({
        "timesteps": [step * k for k in range(1, 9)],
        "episodes": [10, 20, 30, 40, 50, 80, 110, 111],  # the last four rows: 10, 30, 30, 1 episodes
        "success_rate": [0.0, 0.0, 0.0, 0.0, 1.0, 0.5, 0.5, 0.0],
    })  # fmt: skip
    assert final_training_success(progress) == pytest.approx((10 * 1.0 + 30 * 0.5 + 30 * 0.5 + 1 * 0.0) / 71)
    assert final_training_success(progress.iloc[:0]) is None


def test_a_stopped_runs_checkpoint_never_stands_in_for_a_multiple_it_has_not_reached(tmp_path: Path) -> None:
    """A run stopped at 2.82 M steps keeps its checkpoint; the 3 M validation point waits for the run to reach 3 M
    (the kept rows stay and nothing is flown: the stop checkpoint is a file that would fail to load)."""
    from racebench.reporting.validation import validation_curve

    run = tmp_path / "state-ppo-S-seed0"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "state-ppo_2822144_steps.zip").write_bytes(b"not a checkpoint")
    pd.DataFrame({"timesteps": [2_820_096], "mean_return": [4.2]}).to_csv(run / "progress.csv", index=False)
    kept = pd.DataFrame([{"timesteps": 1_998_848, "episodes": 100, "successes": 0, "success_rate": 0.0,
                          "mean_return": 11.9}])  # fmt: skip
    kept.to_csv(run / "validation_curve.csv", index=False)
    curve = validation_curve(run, every=1_000_000, episodes=100)
    assert curve["timesteps"].tolist() == [1_998_848]
    (run / "validation_curve.csv").unlink()
    assert validation_curve(run, every=1_000_000, episodes=100).empty  # nothing reached yet, nothing flown


class _StateHover:
    """A batch agent on the state vector that hovers, and checks it is given the state vector."""

    obs_mode, name, privileged = "state", "hover-state", False

    def start(self, slots: int) -> None:
        self.slots = slots

    def reset_slot(self, slot: int) -> None:
        pass

    def reset(self, env: object = None, seed: int | None = None) -> None:
        pass

    shapes: set = set()  # the observation shapes it was given

    def act_batch(self, observations: list) -> np.ndarray:
        self.shapes.update(np.shape(obs) if isinstance(obs, np.ndarray) else type(obs).__name__ for obs in observations)
        return np.tile(np.array([0.0, 0.0, 0.0, 0.0], np.float32), (len(observations), 1))


def _one_checkpoint_run(tmp_path: Path) -> Path:
    run = tmp_path / "state-ppo-S-seed0"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "state-ppo_999424_steps.zip").write_bytes(b"stands for a checkpoint")
    pd.DataFrame({"timesteps": [999_424], "mean_return": [3.0]}).to_csv(run / "progress.csv", index=False)
    return run


def test_validation_flies_a_state_policy_on_the_state_vector(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Campaign run 3 (``state-ppo`` on S) got depth dicts in validation: every episode errored and the curve read
    0 % while its evaluation read 45 %. A state agent now gets its own observation."""
    from racebench.reporting import validation

    monkeypatch.setattr(validation, "load_agent", lambda *_a, **_k: _StateHover())
    curve = validation.validation_curve(_one_checkpoint_run(tmp_path), every=1_000_000, episodes=2, trust_code=True)
    assert curve["timesteps"].tolist() == [999_424] and curve["episodes"].tolist() == [2]
    assert _StateHover.shapes == {(17,)}


def test_validation_episodes_that_error_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from racebench.reporting import validation

    class Broken(_StateHover):
        def act_batch(self, observations: list) -> np.ndarray:
            raise TypeError("wrong observation")

    monkeypatch.setattr(validation, "load_agent", lambda *_a, **_k: Broken())
    run = _one_checkpoint_run(tmp_path)
    with pytest.raises(ValueError, match="2 of 2 validation episodes ended in an error, first: .*wrong observation"):
        validation.validation_curve(run, every=1_000_000, episodes=2, trust_code=True)
    assert not (run / "validation_curve.csv").exists()


def test_validation_points_flown_before_an_error_are_kept(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The 1 M point is flown and written; the 2 M checkpoint's agent fails: the 1 M row stays on disk."""
    from racebench.reporting import validation

    class Broken(_StateHover):
        def act_batch(self, observations: list) -> np.ndarray:
            raise TypeError("wrong observation")

    run = _one_checkpoint_run(tmp_path)
    (run / "checkpoints" / "state-ppo_1998848_steps.zip").write_bytes(b"stands for a checkpoint")
    agents = iter([_StateHover(), Broken()])
    monkeypatch.setattr(validation, "load_agent", lambda *_a, **_k: next(agents))
    with pytest.raises(ValueError, match="ended in an error"):
        validation.validation_curve(run, every=1_000_000, episodes=2, trust_code=True)
    assert pd.read_csv(run / "validation_curve.csv")["timesteps"].tolist() == [999_424]


def test_a_table_never_mixes_env_versions() -> None:
    """Campaign 1's report reads env version 2's references (results/env-v2); the current ones are version 3."""
    from racebench.evaluation.results import check_one_env_version, read_summaries
    from racebench.reporting.paper import Source, load_episodes

    assert check_one_env_version({"a": [3, 3], "b": [3]}) == 3 and check_one_env_version({"a": []}) is None
    with pytest.raises(ValueError, match=r"env version 2: a; env version 3: b\): a table is of one env version"):
        check_one_env_version({"a": [2], "b": [3]})
    old, new = ROOT / "results" / "env-v2" / "hover", ROOT / "results" / "hover"
    assert set(load_episodes([Source("hover", old)])["method"]) == {"hover"}
    with pytest.raises(ValueError, match="several env versions"):
        load_episodes([Source("hover", old), Source("hover", new)])
    with pytest.raises(ValueError, match="several env versions"):
        read_summaries([old, new])


def _validation_run(campaign: Path, name: str, points: dict[int, float], promotions=()) -> None:
    run = campaign / name
    run.mkdir(parents=True)
    pd.DataFrame({"timesteps": list(points), "episodes": 100, "successes": [round(100 * v) for v in points.values()],
                  "success_rate": list(points.values()), "mean_return": list(points.values())}).to_csv(
        run / "validation_curve.csv", index=False)  # fmt: skip
    (run / "curriculum.json").write_text(json.dumps({"level": 3, "promotions": [
        {"level": level, "timestep": step, "wall_s": 0.0, "by": "bar"} for level, step in promotions]}))  # fmt: skip


def test_learning_curves_join_seeds_and_resumed_parts_on_the_validation_grid(tmp_path: Path) -> None:
    """Campaign 1's artefacts: a resumed seed's checkpoint at 3.16 M and two seeds' final points at 3.998 M and
    4.002 M are one grid step each (3 M, 4 M), so the mean over seeds has no dip and no double point; a campaign
    validating every 0.5 M gets its own grid; promotions are read; one legend for the figure, the track named in
    every panel; PNG and PDF."""
    from racebench.reporting.validation import learning_curves, read_curves, seed_statistics

    campaign = tmp_path / "baselines/experiments/campaign-x"
    _validation_run(campaign, "vision-ppo-Circle-seed0", {999_424: 0.0, 1_998_848: 0.04, 3_164_160: 0.01,
                                                          4_001_792: 0.5}, [(2, 1_500_032)])  # fmt: skip
    _validation_run(campaign, "vision-ppo-Circle-seed1", {999_424: 0.0, 1_998_848: 0.02, 2_998_272: 0.78,
                                                          3_997_696: 0.73}, [(2, 1_290_048)])  # fmt: skip
    _validation_run(campaign, "vision-ppo-S-seed0", {k * 500_000 + 2_000: 0.1 * k for k in range(1, 9)})
    curves, promotions = read_curves(tmp_path, Path("baselines/experiments/campaign-x"))
    stats = seed_statistics(curves, "success_rate")
    circle = stats[stats["track"] == "Circle"].set_index("step")
    assert list(circle.index) == [1_000_000, 2_000_000, 3_000_000, 4_000_000]
    assert circle.loc[3_000_000, "mean"] == pytest.approx((0.01 + 0.78) / 2) and circle.loc[3_000_000, "seeds"] == 2
    assert circle.loc[4_000_000, "seeds"] == 2
    s_steps = stats[stats["track"] == "S"]["step"].tolist()
    assert s_steps == [k * 500_000 for k in range(1, 9)]  # the denser grid of campaign 2
    assert sorted(promotions["timestep"]) == [1_290_048, 1_500_032]
    out = tmp_path / "out"
    learning_curves(tmp_path, out, Path("baselines/experiments/campaign-x"))
    assert (out / "figures" / "learning_curves.png").stat().st_size > 0
    assert (out / "figures" / "learning_curves.pdf").read_bytes()[:4] == b"%PDF"
    assert "step" in pd.read_csv(out / "learning_curves.csv").columns


def test_the_learning_curve_figure_has_one_legend_and_names_the_track_in_every_panel(tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    from racebench.reporting.validation import learning_curves_figure, read_curves

    campaign = tmp_path / "c"
    for seed in range(3):
        _validation_run(campaign, f"vision-ppo-J-seed{seed}", {1_000_000: 0.1 * seed, 2_000_000: 0.5},
                        [(2, 800_000 + seed), (3, 1_600_000)])  # fmt: skip
    curves, promotions = read_curves(tmp_path, Path("c"))
    fig = learning_curves_figure(curves, promotions)
    try:
        assert all(ax.get_legend() is None for ax in fig.axes) and len(fig.legends) == 1
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert "vision-ppo (mean of 3 seeds, band: range)" in labels
        assert {"curriculum promotion to level 2", "curriculum promotion to level 3"} <= set(labels)
        titles = [ax.get_title() for ax in fig.axes]
        assert all(any(name in title for name in ("S-shaped", "3D Circle", "J-shaped")) for title in titles)
    finally:
        plt.close(fig)


def test_table_iv_figures_show_the_learned_method_the_paper_and_the_reference(tmp_path: Path) -> None:
    """Per track: each training seed's rate with its Wilson interval, the mean over seeds, the paper's points and
    planner-fast's line; written as PNG and PDF."""
    import matplotlib.pyplot as plt

    from racebench.reporting.paper import table_iv_figure, write_table_iv_figures

    frames = [hand_made_campaign(), episodes_of("vision-ppo", "RaceObs-J-Density2-v0", 20, n=50, seed=1)]
    frames += [episodes_of("planner-fast", f"RaceObs-{t}-Density{d}-v0", 9, n=10, seed=-1)
               for t in TRACKS for d in DENSITIES]  # fmt: skip
    episodes = pd.concat(frames, ignore_index=True)
    fig = table_iv_figure(episodes, "table_iv_density")
    try:
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert any(label.startswith("paper") for label in labels)
        assert any("planner-fast" in label and "10 episodes" in label for label in labels)
        assert any("95 % Wilson" in label and "50 episodes" in label for label in labels)
        j = next(ax for ax in fig.axes if ax.get_title().startswith("J-shaped"))
        assert j.get_title() == "J-shaped (2 seeds)"
        paper = [line for line in j.get_lines() if line.get_marker() == "x"][0]
        assert list(paper.get_ydata()) == [PAPER_VARIANTS[f"Density{d}"]["J"] for d in DENSITIES]
        reference = [line for line in j.get_lines() if line.get_linestyle() == "--"][0]
        assert list(reference.get_ydata()) == [90.0] * len(DENSITIES)
    finally:
        plt.close(fig)
    written = write_table_iv_figures(episodes, tmp_path, 3)
    assert sorted(p.name for p in written) == ["table_iv_density.pdf", "table_iv_density.png",
                                               "table_iv_gate_shift.pdf", "table_iv_gate_shift.png"]  # fmt: skip
