"""The unseen-tracks line's verified cell (issue 73): only a result signed by the pinned key counts, on private seeds
whose tracks nobody has seen; the per-track signature is untouched by it.

Every key and salt here is a throwaway made by the test; records are written, not flown.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from leaderboard_fixtures import SALT, make_key, make_repo, meta, write_hover_onnx, write_records
from test_leaderboard_site import parse

from racebench import cli
from racebench.evaluation.records import read_folder
from racebench.evaluation.seeds import SALT_ENV, private_seeds, salt_sha256
from racebench.leaderboard import signing
from racebench.leaderboard.entries import MAIN_IDS, UNSEEN_ID, dump_entry, load_config, load_entry
from racebench.leaderboard.signing import SignatureError, records_sha256
from racebench.leaderboard.site import build_site
from racebench.leaderboard.submit import add_entry
from racebench.leaderboard.unseen import unseen_row
from racebench.leaderboard.unseen_signing import UNSEEN_VERIFIED_FILE, build_unseen_payload, check_unseen_verified
from racebench.utils.files import sha256_file


@pytest.fixture()
def repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict:
    """A method with per-track public records, an unseen line (30/100 public, its ONNX export beside it) and 7/10
    private records of that export on RaceObs-Unseen-v0 outside the repository; the throwaway key pinned."""
    root, secrets = tmp_path / "repo", tmp_path / "secrets"
    secrets.mkdir()
    key, pem, fingerprint = make_key(secrets, "maintainers")
    board = make_repo(root, public_key_pem=pem)
    policy = write_hover_onnx(root / "p" / "method.onnx")
    export = write_hover_onnx(root / "p" / "method-unseen.onnx")
    for env_id in MAIN_IDS:
        write_records(root / "results" / "main", str(policy), env_id, 5, 10)
    write_records(root / "results" / "unseen", str(policy), UNSEEN_ID, 30, 100)
    write_records(secrets / "private" / "method-unseen", str(export), UNSEEN_ID, 7, 10, seed_set="private")
    line = {"policy": "p/method.onnx", "onnx": "p/method-unseen.onnx", "records": ["results/unseen"]}
    add_entry(board, str(policy), {**meta("method"), "unseen": line}, [str(root / "results" / "main")])
    monkeypatch.setattr(signing, "MAINTAINERS_KEY_SHA256", fingerprint)
    monkeypatch.delenv(SALT_ENV, raising=False)  # building the site needs no secret
    return {"root": root, "board": board, "key": key, "secrets": secrets, "export": export}


def sign(repo: dict, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``racebench leaderboard sign --unseen`` as the maintainers run it (the salt only in this call's environment)."""
    with monkeypatch.context() as m:
        m.setenv(SALT_ENV, SALT)
        argv = ["leaderboard", "sign", "--entry", "method", "--unseen", "--key", str(repo["key"]), "--private-records",
                str(repo["secrets"] / "private"), "--episodes", "10", "--leaderboard", str(repo["board"])]  # fmt: skip
        assert cli.main(argv) == 0
    return repo["board"] / "method" / UNSEEN_VERIFIED_FILE


def row(repo: dict):
    """The site's unseen-tracks row of the method."""
    return unseen_row(load_entry(repo["board"] / "method"), load_config(repo["board"]))


def test_a_signed_unseen_line_is_ranked_on_its_private_cell(repo, monkeypatch, capsys) -> None:
    assert (row(repo).signed, row(repo).cell.successes, row(repo).cell.n) == (False, 30, 100)  # public before
    path = sign(repo, monkeypatch)
    assert f"method {UNSEEN_ID} [private]: 7/10" in capsys.readouterr().out
    payload = json.loads(path.read_text())["payload"]
    records = read_folder(repo["secrets"] / "private" / "method-unseen").sorted_records()
    assert payload["policy_sha256"] == sha256_file(repo["export"]) and payload["policy"] == "p/method-unseen.onnx"
    assert payload["records_sha256"] == records_sha256(records) and payload["seed_salt_sha256"] == salt_sha256(SALT)
    assert (payload["cell"]["successes"], payload["cell"]["n"]) == (7, 10)
    text = path.read_text()
    assert SALT not in text and str(private_seeds(SALT, 1)[0]) not in text  # neither the salt nor a private seed
    verdict = row(repo)
    assert verdict.signed and verdict.ranked and (verdict.cell.seed_set, verdict.cell.successes) == ("private", 7)
    index = build_site(repo["board"], repo["root"] / "site")
    table = parse(index).tables["ranking-unseen"]
    assert table[1][1][0] == "method" and table[1][2][0].startswith("70 %") and table[1][4][0] == "private (signed)"
    assert "(signed, <code>verified-unseen.json</code>)" in (index.parent / "entries" / "method.html").read_text()
    # Its per-track policies are not signed: the entry stays self-reported whatever its unseen line holds.
    assert 'id="ranking-verified"' not in index.read_text() and SALT not in index.read_text()


def test_an_edited_or_unsigned_result_falls_back_to_the_public_cell(repo, monkeypatch) -> None:
    path = sign(repo, monkeypatch)
    document = json.loads(path.read_text())
    document["payload"]["cell"]["successes"] = 10
    path.write_text(json.dumps(document))
    verdict = row(repo)
    assert not verdict.signed and (verdict.cell.seed_set, verdict.cell.n) == ("public", 100)
    assert "does not check against the maintainers' key" in verdict.refusal
    entry = load_entry(repo["board"] / "method")
    private = read_folder(repo["secrets"] / "private" / "method-unseen").sorted_records()
    forged = build_unseen_payload(entry, private, SALT)
    own, _, _ = make_key(repo["secrets"], "submitter")  # a submitter's own key signs nothing that counts
    path.write_text(json.dumps(signing.sign_payload(forged, signing.load_private_key(own))))
    assert not row(repo).signed and "does not check against the maintainers' key" in row(repo).refusal
    site = build_site(repo["board"], repo["root"] / "site")
    assert "signed result refused" in parse(site).tables["ranking-unseen"][1][7][0]


def test_a_swapped_file_or_a_changed_line_is_refused(repo, monkeypatch) -> None:
    sign(repo, monkeypatch)
    entry = load_entry(repo["board"] / "method")
    assert check_unseen_verified(entry, load_config(repo["board"])).successes == 7
    original = repo["export"].read_bytes()
    repo["export"].write_bytes(original + b"\0")
    with pytest.raises(SignatureError, match="is not the one signed .* swapped after signing"):
        check_unseen_verified(load_entry(repo["board"] / "method"), load_config(repo["board"]))
    repo["export"].write_bytes(original)
    entry_yaml = repo["board"] / "method" / "entry.yaml"
    data = yaml.safe_load(entry_yaml.read_text())
    data["unseen"]["steps"] = 123  # another budget claimed beside the signed cell
    entry_yaml.write_text(dump_entry(data))
    with pytest.raises(SignatureError, match="changed after signing: sign it again"):
        check_unseen_verified(load_entry(repo["board"] / "method"), load_config(repo["board"]))


def test_signing_refuses_public_records_and_a_line_without_onnx(repo, monkeypatch) -> None:
    entry = load_entry(repo["board"] / "method")
    public = read_folder(repo["root"] / "results" / "unseen").sorted_records()
    with pytest.raises(SignatureError, match="a record of its unseen policy .* is not on the private seeds"):
        build_unseen_payload(entry, public, SALT)
    with pytest.raises(SignatureError, match="no private records of its unseen policy"):
        build_unseen_payload(entry, [], SALT)
    entry_yaml = repo["board"] / "method" / "entry.yaml"
    data = yaml.safe_load(entry_yaml.read_text())
    del data["unseen"]["onnx"]
    entry_yaml.write_text(dump_entry(data))
    monkeypatch.setenv(SALT_ENV, SALT)
    argv = ["leaderboard", "sign", "--entry", "method", "--unseen", "--key", str(repo["key"]), "--private-records",
            str(repo["secrets"] / "private"), "--leaderboard", str(repo["board"])]  # fmt: skip
    with pytest.raises(SystemExit, match="its unseen line has no ONNX file: only ONNX policies are verified"):
        cli.main(argv)
