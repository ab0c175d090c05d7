"""The verified tier holds without trusting whoever built the site: only a result signed by the pinned key counts.

Every key and salt here is a throwaway made by the test; the site is built with no secret in the environment.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from leaderboard_fixtures import SALT, add, make_key, make_repo, write_config, write_hover_onnx, write_records

from racebench import cli
from racebench.evaluation.records import read_folder
from racebench.evaluation.seeds import SALT_ENV, private_seeds, salt_sha256
from racebench.leaderboard import signing
from racebench.leaderboard.entries import DEFAULT_LEADERBOARD, dump_entry, load_config, load_entry
from racebench.leaderboard.signing import SignatureError, build_payload, records_sha256
from racebench.leaderboard.site import build_site, entry_row
from racebench.utils.files import sha256_file

ROOT = Path(__file__).parents[1]
S = "RaceObs-S-v0"


@pytest.fixture()
def repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict:
    """A repository with one S-only method: public records of ``public.onnx``, its export ``export.onnx``, private
    records (7/10) outside the repository, the maintainers' throwaway key pinned and its public key committed."""
    root, secrets = tmp_path / "repo", tmp_path / "secrets"
    secrets.mkdir()
    key, pem, fingerprint = make_key(secrets, "maintainers")
    board = make_repo(root, public_key_pem=pem)
    public = write_hover_onnx(root / "policies" / "public.onnx")
    export = write_hover_onnx(root / "policies" / "export.onnx")
    write_records(root / "results" / "pub", str(public), S, 2, 10)
    write_records(secrets / "private" / "method-S", str(export), S, 7, 10, seed_set="private")
    add(board, {"S": str(public)}, "method", [root / "results" / "pub"])
    meta = yaml.safe_load((board / "method" / "entry.yaml").read_text())
    meta["policies"]["S"]["onnx"] = "policies/export.onnx"
    (board / "method" / "entry.yaml").write_text(dump_entry(meta))
    monkeypatch.setattr(signing, "MAINTAINERS_KEY_SHA256", fingerprint)
    monkeypatch.delenv(SALT_ENV, raising=False)  # building the site needs no secret
    return {"root": root, "board": board, "key": key, "secrets": secrets, "export": export}


def sign(repo: dict, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``racebench leaderboard sign`` as the maintainers run it (salt in the environment, only for this call)."""
    with monkeypatch.context() as m:
        m.setenv(SALT_ENV, SALT)
        argv = ["leaderboard", "sign", "--entry", "method", "--key", str(repo["key"]), "--private-records",
                str(repo["secrets"] / "private"), "--episodes", "10", "--leaderboard", str(repo["board"])]  # fmt: skip
        assert cli.main(argv) == 0
    return repo["board"] / "method" / signing.VERIFIED_FILE


def row(repo: dict):
    """The site's view of the method entry."""
    return entry_row(load_entry(repo["board"] / "method"), load_config(repo["board"]))


def test_a_signed_result_makes_the_entry_verified_with_the_signed_numbers(repo, monkeypatch, capsys) -> None:
    path = sign(repo, monkeypatch)
    assert "method RaceObs-S-v0 [private]: 7/10" in capsys.readouterr().out
    document = json.loads(path.read_text())
    payload = document["payload"]
    (policy,) = payload["policies"]
    records = read_folder(repo["secrets"] / "private" / "method-S").sorted_records()
    assert policy["policy_sha256"] == sha256_file(repo["export"]) and policy["policy"] == "policies/export.onnx"
    assert policy["records_sha256"] == records_sha256(records)
    assert (policy["cells"][S]["successes"], policy["cells"][S]["n"], len(policy["cells"][S]["lap_times"])) == (
        7,
        10,
        7,
    )
    assert payload["seed_salt_sha256"] == salt_sha256(SALT) and payload["seed_protocol"] == 1
    text = path.read_text()
    assert SALT not in text and str(private_seeds(SALT, 1)[0]) not in text  # neither the salt nor a private seed
    verdict = row(repo)
    assert verdict.tier == "verified" and (verdict.cells[S].successes, verdict.cells[S].n) == (7, 10)
    index = build_site(repo["board"], repo["root"] / "site")
    html = index.read_text()
    assert 'id="unranked-verified"' in html and "7/10" in html  # S only: a verified but unranked (partial) entry
    assert SALT not in html


def test_forged_private_records_without_a_signature_stay_self_reported(repo, monkeypatch) -> None:
    """All successes, digests recomputed, the accepted salt's fingerprint copied: record-valid, and worthless."""
    root, board = repo["root"], repo["board"]
    forged_dir = root / "results" / "forged-private"
    write_records(forged_dir, str(repo["export"]), S, 10, 10, seed_set="private")  # sealed: digests recomputed
    meta = yaml.safe_load((board / "method" / "entry.yaml").read_text())
    meta["policies"]["S"]["records"].append("results/forged-private")
    (board / "method" / "entry.yaml").write_text(dump_entry(meta))
    entry = load_entry(board / "method")
    assert {r.get("seed_salt_sha256") for r in entry.records} >= {salt_sha256(SALT)}  # copied fingerprint
    assert row(repo).tier == "self-reported" and row(repo).refusal is None  # no signed result at all
    # A verified.json of the forged numbers: unsigned, then signed by the submitter's own key.
    payload = build_payload(entry, {"S": [r for r in entry.records if r["seed_set"] == "private"]}, SALT)
    path = board / "method" / signing.VERIFIED_FILE
    path.write_text(json.dumps({"payload": payload}))
    assert row(repo).tier == "self-reported" and "is not a signed result" in row(repo).refusal
    own_key, _, _ = make_key(repo["secrets"], "submitter")
    path.write_text(json.dumps(signing.sign_payload(payload, signing.load_private_key(own_key))))
    verdict = row(repo)
    assert verdict.tier == "self-reported" and "does not check against the maintainers' key" in verdict.refusal
    site = build_site(board, root / "site")
    page = (site.parent / "entries" / "method.html").read_text()
    assert "Signed result refused" in page and 'id="unranked-verified"' not in site.read_text()


def test_an_edited_count_is_refused(repo, monkeypatch) -> None:
    path = sign(repo, monkeypatch)
    document = json.loads(path.read_text())
    cell = document["payload"]["policies"][0]["cells"][S]
    cell["successes"], cell["lap_times"] = 10, cell["lap_times"] + [cell["lap_times"][0]] * 3
    path.write_text(json.dumps(document))
    verdict = row(repo)
    assert verdict.tier == "self-reported"
    assert verdict.refusal == (
        "method: the signature of verified.json does not check against the maintainers' key (the result was edited "
        "after signing, or signed by another key)"
    )


def test_a_policy_file_swapped_after_signing_is_refused(repo, monkeypatch) -> None:
    sign(repo, monkeypatch)
    repo["export"].write_bytes(repo["export"].read_bytes() + b"\0")  # another graph under the signed name
    verdict = row(repo)
    assert verdict.tier == "self-reported" and "policies/export.onnx" in verdict.refusal
    assert "is not the one signed" in verdict.refusal and "swapped after signing" in verdict.refusal


def test_a_key_swapped_into_leaderboard_yaml_is_refused(repo, monkeypatch) -> None:
    """A pull request that signs with its own key and commits that key in the YAML: the pinned fingerprint wins."""
    other_key, other_pem, _ = make_key(repo["secrets"], "intruder")
    write_config(repo["board"], [salt_sha256(SALT)], other_pem)
    entry = load_entry(repo["board"] / "method")
    private = read_folder(repo["secrets"] / "private" / "method-S").sorted_records()
    document = signing.sign_payload(build_payload(entry, {"S": private}, SALT), signing.load_private_key(other_key))
    (repo["board"] / "method" / signing.VERIFIED_FILE).write_text(json.dumps(document))
    verdict = row(repo)
    assert verdict.tier == "self-reported"
    assert "is not the maintainers' key pinned in racebench" in verdict.refusal
    with pytest.raises(SignatureError, match="not the maintainers' key pinned"):
        signing.check_verified(entry, load_config(repo["board"]))


def test_sign_errors_are_one_line(repo, monkeypatch) -> None:
    base = ["leaderboard", "sign", "--entry", "method", "--leaderboard", str(repo["board"]), "--episodes", "10"]
    outside = ["--private-records", str(repo["secrets"] / "private")]
    with pytest.raises(SystemExit, match=r"^racebench leaderboard sign: --seed-set private needs the secret salt"):
        cli.main([*base, "--key", str(repo["key"]), *outside])
    monkeypatch.setenv(SALT_ENV, SALT)
    inside = ["--private-records", str(repo["root"] / "private")]
    with pytest.raises(SystemExit, match=r"^racebench leaderboard sign: .* lies inside the repository[^\n]*$"):
        cli.main([*base, "--key", str(repo["key"]), *inside])
    with pytest.raises(SystemExit, match=r"^racebench leaderboard sign: --key '[^']*nokey.pem': unreadable"):
        cli.main([*base, "--key", str(repo["secrets"] / "nokey.pem"), *outside])
    assert not (repo["board"] / "method" / signing.VERIFIED_FILE).exists()


def test_the_committed_public_key_is_the_pinned_one_and_its_signatures_check() -> None:
    board = ROOT / DEFAULT_LEADERBOARD
    config = load_config(board)
    key = signing.load_public_key(config["maintainers_public_key"])
    assert signing.public_key_sha256(key) == signing.MAINTAINERS_KEY_SHA256
    signed = sorted(p.parent.name for p in board.glob(f"*/{signing.VERIFIED_FILE}"))
    assert {"vision-distill", "vision-distill-ppo"} <= set(signed)
    for name in signed:
        verdict = entry_row(load_entry(board / name), config)
        assert verdict.tier == "verified", verdict.refusal
        assert all(c.seed_set == "private" and c.n == 50 for c in verdict.cells.values())


def test_robustness_records_added_after_signing_keep_the_signature_and_other_records_do_not(
    repo, monkeypatch
) -> None:
    """The suite's records join a signed entry's folder later (the maintainers evaluate every method on it): they
    are left out of the signed view, so the entry stays verified; a new record of a main id is not."""
    sign(repo, monkeypatch)
    public = str(repo["root"] / "policies" / "public.onnx")
    for name in ("Latency", "Wind"):
        write_records(repo["root"] / "results" / "pub", public, f"RaceObs-S-{name}-v0", 1, 10)
    verdict = row(repo)
    assert verdict.tier == "verified" and verdict.refusal is None
    assert {r["env_id"] for r in verdict.entry.records} == {S, "RaceObs-S-Latency-v0", "RaceObs-S-Wind-v0"}
    write_records(repo["root"] / "results" / "pub", public, "RaceObs-S-Density5-v0", 1, 10)
    verdict = row(repo)
    assert verdict.tier == "self-reported" and "changed after signing" in verdict.refusal
