"""`cbh inspect`: what a session holds, and --repair of a killed writer's file."""
from __future__ import annotations

import json
from pathlib import Path

from .conftest import small_station, write_session

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"


def test_inspect_reports_span_frames_drops_topics_layers(tmp_path, capsys):
    from cbh.cli.main import main

    path = tmp_path / "s.mcap"
    _, made = write_session(path, small_station(), n=4)
    assert main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "2024-03-01T12:00:00Z .. 2024-03-01T12:00:40Z (40.0 s)" in text
    assert "pairs:       4   frames: cam1 4, cam2 4" in text
    assert "pairs_dropped 1" in text and "unpaired 2" in text
    assert "/pair/points" in text and "foxglove.PointCloud" in text
    assert main(["inspect", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["pairs"] == 4 and d["frames"] == {"cam1": 4, "cam2": 4}
    assert d["drops"]["missing_pair_indices"] == 0
    h0 = [r.layers[0].height_m for _, r in made]
    assert d["layers"][0]["pairs"] == 4 and d["layers"][0]["min_m"] == min(h0) and d["layers"][0]["max_m"] == max(h0)
    assert d["layers"][1]["pairs"] == 2  # pairs 1 and 3 have a second layer
    assert d["flags"] == {"few_points": 1}
    assert {t["topic"] for t in d["topics"]} >= {"/cam1/image/compressed", "/pair/layers", "/service/status"}


def test_inspect_sample(capsys):
    from cbh.cli.main import main

    assert main(["inspect", str(SAMPLE), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["pairs"] == 8 and d["duration_s"] == 70.0 and d["station"] == "unb-lea"


def test_repair_of_truncated_file(tmp_path, capsys):
    from cbh.cli.main import main

    data = SAMPLE.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: len(data) * 3 // 4])  # the writer died three quarters through
    assert main(["inspect", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "truncated" in err and "--repair" in err
    fixed = tmp_path / "fixed.mcap"
    assert main(["inspect", str(cut), "--repair", str(fixed), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["repair"]["pairs"] == d["pairs"]
    assert 4 <= d["pairs"] <= 6  # ~3/4 of 8 pairs survive, minus the one cut through
    assert d["repair"]["source_complete"] is False


def test_repair_never_replaces_an_existing_file(tmp_path, capsys):
    """``--repair OTHER.mcap`` rewrote another recording with the repaired copy: OTHER's data were
    gone. Now one error line, exit 2, OTHER byte-identical."""
    from cbh.cli.main import main

    data = SAMPLE.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: len(data) // 2])
    other = tmp_path / "other.mcap"
    _, _ = write_session(other, small_station(), n=2)
    before = other.read_bytes()
    assert main(["inspect", str(cut), "--repair", str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cbh: error:") and "exists" in err and "\n" not in err, err
    assert other.read_bytes() == before


def test_foreign_files(tmp_path, capsys):
    from cbh.cli.main import main

    for name, content in [("a.mcap", b"hello world, this is not mcap"), ("b.mcap", b"")]:
        p = tmp_path / name
        p.write_bytes(content)
        assert main(["inspect", str(p)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("cbh: error:") and "not an MCAP file" in err and "\n" not in err
        assert main(["inspect", str(p), "--repair", str(tmp_path / "o.mcap")]) == 2
        assert "not an MCAP file" in capsys.readouterr().err
