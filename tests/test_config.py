"""Config loading: the shipped configs are valid and bad ones get precise, located errors."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from orchestrator.config import DEFAULT_CONFIG, ConfigError, load_config
from tests.conftest import REPO


@pytest.mark.parametrize("name", ["mock.yaml", "dual_panda_realsense.yaml", "dual_ur_oak.yaml"])
def test_shipped_configs_load(name: str) -> None:
    cfg = load_config(REPO / "configs" / name)
    assert cfg.plan.episode_seconds == 5.0
    assert cfg.station.simulated == (name == "mock.yaml")


def test_default_is_mock() -> None:
    cfg = load_config(DEFAULT_CONFIG)
    assert cfg.station.camera.type == "fake"
    assert {o.category for o in cfg.plan.objects} == {"dlo", "bdlo", "cloth"}
    assert not cfg.bus.multicast_scouting


def _bad(tmp_path: Path, text: str) -> str:
    p = tmp_path / "bad.yaml"
    p.write_text(textwrap.dedent(text))
    with pytest.raises(ConfigError) as e:
        load_config(p)
    return str(e.value)


BASE = """\
station:
  left:
    arm: {type: fake, base: {xyz: [0, 0.45, 0]}}
    gripper: {type: fake}
  right:
    arm: {type: fake, base: {xyz: [0, -0.45, 0]}}
    gripper: {type: fake}
  camera: {type: fake, width: 320, height: 240}
plan:
  objects:
    - name: rope
      category: dlo
      programs: [rope_swing]
      sim: {length: 0.7}
"""


def test_bad_value_names_file_line_field_value_and_expectation(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE.replace("width: 320", "width: -5"))
    assert "bad.yaml:8: station.camera.width" in msg
    assert "greater than or equal to 64" in msg and "(got -5)" in msg


def test_unknown_field_is_an_error(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE.replace("gripper: {type: fake}\n  right", "gripper: {type: fake, forse: 3}\n  right"))
    assert "station.left.gripper.forse" in msg and "Extra inputs are not permitted" in msg


def test_unknown_driver_type_lists_the_known_ones(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE.replace("camera: {type: fake", "camera: {type: kinect"))
    assert "station.camera" in msg and "'fake', 'realsense', 'oak', 'replay'" in msg and "kinect" in msg


def test_bad_speed_and_missing_field(tmp_path: Path) -> None:
    text = BASE + "  speeds: [slow, warp]\n"
    msg = _bad(tmp_path, text.replace("      programs: [rope_swing]\n", ""))
    assert "plan.speeds[1]" in msg and "'slow', 'medium' or 'fast'" in msg and "(got 'warp')" in msg
    assert "plan.objects[0].programs: Field required" in msg


def test_sim_kind_must_match_category(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE.replace("sim: {length: 0.7}", "sim: {category: cloth}"))
    assert "plan.objects[0]" in msg and "does not match category 'dlo'" in msg


def test_simulated_station_needs_sim_block(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE.replace("      sim: {length: 0.7}\n", ""))
    assert "needs plan.objects[*].sim" in msg and "['rope']" in msg


def test_bad_endpoint_and_not_yaml_and_missing_file(tmp_path: Path) -> None:
    msg = _bad(tmp_path, BASE + "bus: {listen: ['127.0.0.1:7447']}\n")
    assert "bus.listen" in msg and "not a zenoh endpoint" in msg
    assert "not valid YAML" in _bad(tmp_path, "station: [unclosed\n")
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "nope.yaml")
    assert "the file is empty" in _bad(tmp_path, "")
