"""Track files: the built-in tracks as published, and clear errors for malformed files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from racebench.sim.track import BUILTIN_TRACKS, TrackFormatError, load_track

TRACKS_DIR = Path(__file__).parents[1] / "tracks"


def test_builtin_tracks_match_the_published_gates() -> None:
    s = load_track("S")
    assert [g.center.tolist() for g in s.gates] == [[3, 0, 1], [7, -1, 1], [11, 1, 1], [15, 0, 1]]
    assert all(g.yaw == 0 for g in s.gates) and not s.closed_loop
    circle = load_track("Circle")
    assert circle.closed_loop
    np.testing.assert_allclose(circle.gates[1].normal, [0, -1, 0], atol=1e-12)  # facing -y
    np.testing.assert_allclose(circle.gates[2].normal, [-1, 0, 0], atol=1e-12)  # facing -x
    np.testing.assert_allclose(circle.gates[3].normal, [0, 1, 0], atol=1e-12)  # facing +y
    j = load_track("J")
    np.testing.assert_allclose(j.gates[3].center, [8, -3, 1])
    for name in BUILTIN_TRACKS:
        track = load_track(name)
        gate = track.gates[0]
        assert gate.inner == 1.0 and gate.outer == 1.28 and math.isclose(gate.bar_width, 0.14)


def test_gate_bars_tile_the_frame() -> None:
    gate = load_track("S").gates[0]
    bars = gate.bars()
    # Frame area = outer² − inner², covered exactly once by the four bars.
    area = sum(4 * h[1] * h[2] for _, h in bars)
    assert math.isclose(area, gate.outer**2 - gate.inner**2)


def _write(tmp_path: Path, data: object) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _base() -> dict:
    return yaml.safe_load((TRACKS_DIR / "S.yaml").read_text())


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d.pop("gates"), "gates"),
        (lambda d: d.update(gates=[d["gates"][0]]), "gates"),
        (lambda d: d["gates"][1].update(center=[7, -1]), "gates[1].center"),
        (lambda d: d["gates"][2].update(center=[11, 1, "high"]), "gates[2].center[2]"),
        (lambda d: d["gates"][0].update(center=[3, 0, 0.2]), "gates[0].center"),
        (lambda d: d["gates"][0].pop("yaw_deg"), "gates[0].yaw_deg"),
        (lambda d: d.update(closed_loop="yes"), "closed_loop"),
        (lambda d: d["start"].pop("center"), "start.center"),
        (lambda d: d["start"].update(center=[1, 0, -1]), "start.center"),
        (lambda d: d["gate_size"].update(outer=0.9), "gate_size.outer"),
        (lambda d: d["obstacle_regions"][0].update(between=[0, 9]), "obstacle_regions[0].between"),
        (lambda d: d.update(colour="red"), "colour"),
        (lambda d: d["gates"].append(dict(d["gates"][0])), "gates[4].center"),  # a duplicate gate
        (
            lambda d: d["gates"][1].update(center=[d["gates"][0]["center"][0] + 0.3, *d["gates"][0]["center"][1:]]),
            "gates[1].center",
        ),  # fmt: skip
    ],
)
def test_malformed_track_names_file_and_field(tmp_path: Path, mutate, field: str) -> None:
    data = _base()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(TrackFormatError) as err:
        load_track(path)
    assert str(path) in str(err.value)
    assert f"'{field}'" in str(err.value)


def test_not_yaml_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text("gates: [1, 2\n")
    with pytest.raises(TrackFormatError, match="not valid YAML"):
        load_track(path)
    with pytest.raises(FileNotFoundError, match="nowhere.yaml"):
        load_track(tmp_path / "nowhere.yaml")


def test_user_track_file_loads(tmp_path: Path) -> None:
    data = _base()
    data["name"] = "mine"
    data["gates"].append({"center": [19, 0, 1.5], "yaw_deg": 0})
    track = load_track(_write(tmp_path, data))
    assert track.name == "mine" and track.num_gates == 5
