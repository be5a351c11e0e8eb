"""``trackdeform program ...`` subcommands."""

from __future__ import annotations

import argparse
import json

import pytest
import yaml

from orchestrator.cli_program import register


def _run(argv: list[str]) -> int:
    p = argparse.ArgumentParser()
    register(p.add_subparsers(dest="command"))
    args = p.parse_args(argv)
    return args.func(args)


def test_time_json_parses(capsys):
    assert _run(["program", "time", "rope_swing", "--speed", "fast", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["speed"] == "fast" and rep["segment_duration"] == 1.25
    assert rep["arms_end_together"] and not rep["limited_segments"]
    assert all(abs(s["actual"] - 1.25) < 1e-3 for s in rep["segments"])
    assert abs(rep["total"] - 1.25 * len(rep["segments"])) < 1e-3
    assert 0 < rep["peak_velocity_ratio"] < 1


def test_time_text_and_fast_duration(capsys):
    assert _run(["program", "time", "cloth_fold", "--speed", "fast", "--fast-duration", "1.0"]) == 0
    out = capsys.readouterr().out
    assert "total 5.0000 s" in out and "together: yes" in out


def test_validate_library_and_bad_file(tmp_path, capsys):
    assert _run(["program", "validate", "branched_lift"]) == 0
    assert "OK" in capsys.readouterr().out
    bad = yaml.safe_load(open(__import__("trajectories.program", fromlist=["x"]).library_path("rope_swing")))
    bad["waypoints"][2]["right"][3] = 0.5
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(bad))
    assert _run(["program", "validate", str(f)]) == 1
    assert "bad.yaml: waypoints[2].right[3] = 0.5 rad is above the Panda limit -0.0698" in capsys.readouterr().err


def test_preview_writes_png(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "p.png"
    assert _run(["program", "preview", "rope_swing", "--speed", "medium", "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
