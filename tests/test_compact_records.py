"""The one-off converter of issue 47 (``scripts/compact_records.py``): legacy per-record files to records.jsonl."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scripts_loader import load_script

from racebench.evaluation import Evaluator, load_records
from racebench.evaluation.records import (
    RECORDS_FILE,
    TRAJECTORIES_FILE,
    atomic_write,
    name_of,
    read_folder,
    read_record,
    read_trajectories,
    record_digest,
)

ROOT = Path(__file__).parents[1]
ENV = "RaceObs-S-Level1-v0"


def to_legacy(folder: Path) -> None:
    """Rewrite an evaluation folder as the old RecordWriter left it: ``records/<name>.json`` (indented),
    ``trajectories/<name>.npz``."""
    found, flights = read_folder(folder), read_trajectories(folder)
    for name, record in found.records.items():
        atomic_write(folder / "records" / name, json.dumps(record, indent=1))
    for row, positions, scene in flights:
        (folder / "trajectories").mkdir(exist_ok=True)
        np.savez_compressed(folder / "trajectories" / name_of(row).replace(".json", ".npz"), positions=positions,
                            scene=json.dumps(scene), row=json.dumps(row))  # fmt: skip
    (folder / RECORDS_FILE).unlink()
    (folder / TRAJECTORIES_FILE).unlink(missing_ok=True)


@pytest.fixture(scope="module")
def legacy_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small tree of two legacy evaluation folders (one with trajectories), as committed before the migration."""
    root = tmp_path_factory.mktemp("tree")
    Evaluator("hover", [ENV], episodes=3, out_dir=root / "results" / "hover", save_trajectories=True).run(
        progress=False
    )
    Evaluator("planner", [ENV, "RaceObs-J-Level1-v0"], episodes=2, out_dir=root / "exp" / "a" / "eval").run(
        progress=False
    )
    for folder in (root / "results" / "hover", root / "exp" / "a" / "eval"):
        to_legacy(folder)
    return root


def test_every_record_and_trajectory_round_trips(legacy_tree: Path, tmp_path: Path, capsys) -> None:
    import shutil

    tree = tmp_path / "tree"
    shutil.copytree(legacy_tree, tree)
    folders = [tree / "results" / "hover", tree / "exp" / "a" / "eval"]
    before = {f: {p.name: read_record(p) for p in (f / "records").glob("*.json")} for f in folders}
    tables = {f: load_records(f) for f in folders}  # the legacy layout is read as it is
    flights = read_trajectories(folders[0])
    assert [len(b) for b in before.values()] == [3, 4] and len(flights) == 3
    script = load_script("compact_records")
    assert script.main([str(tree / "results"), str(tree / "exp")]) == 0
    assert "2 folders converted: 7 records, 3 trajectories" in capsys.readouterr().out
    for folder in folders:
        assert sorted(p.name for p in folder.iterdir() if p.name.startswith(("records", "trajectories"))) == [
            RECORDS_FILE, *([TRAJECTORIES_FILE] if folder == folders[0] else [])
        ]  # fmt: skip
        lines = (folder / RECORDS_FILE).read_text().splitlines()
        after = {name_of(json.loads(line)): json.loads(line) for line in lines}
        assert after == before[folder]  # every record, every field, as it was
        assert all(r["digest"] == record_digest(r) == before[folder][n]["digest"] for n, r in after.items())
        assert list(after) == sorted(after)  # one record per line, in record-name order
        assert load_records(folder).equals(tables[folder])  # every table computed from them stays identical
    moved = read_trajectories(folders[0])
    for (row, positions, scene), (row2, positions2, scene2) in zip(flights, moved, strict=True):
        assert row == row2 and scene == scene2 and positions.dtype == positions2.dtype
        assert np.array_equal(positions, positions2)
    converted = (folders[0] / RECORDS_FILE).read_bytes(), (folders[0] / TRAJECTORIES_FILE).read_bytes()
    assert script.main([str(tree)]) == 0  # nothing left to convert: untouched
    assert "0 folders converted" in capsys.readouterr().out
    assert ((folders[0] / RECORDS_FILE).read_bytes(), (folders[0] / TRAJECTORIES_FILE).read_bytes()) == converted


def test_an_invalid_legacy_record_stops_the_conversion(legacy_tree: Path, tmp_path: Path) -> None:
    import shutil

    tree = tmp_path / "tree"
    shutil.copytree(legacy_tree / "results", tree)
    path = sorted((tree / "hover" / "records").glob("*.json"))[0]
    record = json.loads(path.read_text())
    path.write_text(json.dumps({**record, "success": True}))  # edited, digest not recomputed
    with pytest.raises(SystemExit, match=rf"^compact_records: {path}: digest does not match"):
        load_script("compact_records").main([str(tree)])
    assert path.is_file() and not (tree / "hover" / RECORDS_FILE).exists()  # nothing converted, nothing lost
