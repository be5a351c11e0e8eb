"""Program format: loading, located errors, saving, library lookup."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from tdcommon.robot import HOME_Q
from trajectories.program import (
    FORMAT,
    Program,
    ProgramError,
    Waypoint,
    library_path,
    list_library,
    load_program,
    resolve_program,
    save_program,
)

HOME = list(HOME_Q)


def _raw(n: int = 3) -> dict:
    wps = [{"left": list(HOME), "right": list(HOME), "grippers": {"left": "closed", "right": "open"}}]
    for i in range(1, n):
        q = list(HOME)
        q[0] = 0.1 * i
        wps.append({"left": q, "right": list(HOME)})
    return {"format": FORMAT, "name": "t", "category": "dlo", "arms": ["left", "right"], "waypoints": wps}


def _write(tmp_path: Path, data: dict, name: str = "fig8.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if p.suffix != ".json" else json.dumps(data))
    return p


def test_load_valid_and_gripper_shorthand(tmp_path):
    prog = load_program(_write(tmp_path, _raw()))
    assert prog.q().shape == (3, 14)
    states = prog.gripper_states()
    assert states[2]["left"].state == "closed" and states[2]["right"].state == "open"


def test_joint_beyond_limit_names_file_waypoint_joint(tmp_path):
    data = _raw(5)
    data["waypoints"][3]["left"][5] = 4.1
    with pytest.raises(ProgramError) as e:
        load_program(_write(tmp_path, data))
    assert str(e.value) == "fig8.yaml: waypoints[3].left[5] = 4.1 rad is above the Panda limit 3.7525"


def test_structural_errors_are_located(tmp_path):
    data = _raw()
    data["waypoints"][1]["right"] = HOME[:6]
    data["waypoints"][2]["bogus"] = 1
    data["waypoints"][0]["grippers"]["left"] = "half"
    with pytest.raises(ProgramError) as e:
        load_program(_write(tmp_path, data, "bad.json"))
    msg = str(e.value)
    assert "bad.json: waypoints[1].right" in msg
    assert "bad.json: waypoints[2].bogus" in msg
    assert "bad.json: waypoints[0].grippers.left" in msg


def test_wrong_format_version(tmp_path):
    data = _raw()
    data["format"] = "trackdeform-program/9"
    with pytest.raises(ProgramError, match="format"):
        load_program(_write(tmp_path, data))


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_save_load_roundtrip(tmp_path, suffix):
    prog = Program(name="rt", category="cloth", waypoints=[
        Waypoint(left=HOME, right=HOME, grippers={"left": {"state": "closed", "width": 0.01, "force": 20}}),
        Waypoint(left=HOME, right=HOME, duration=3.0, speed_scale=0.5, dwell=0.2),
    ])
    path = tmp_path / f"p{suffix}"
    save_program(prog, path)
    back = load_program(path)
    assert back == prog


def test_library_lookup():
    names = list_library()
    assert {"rope_swing", "branched_lift", "cloth_fold"} <= set(names)
    assert resolve_program("rope_swing") == library_path("rope_swing")
    with pytest.raises(ProgramError, match="available"):
        library_path("nope")


def test_library_programs_start_holding_the_object():
    from tdcommon.robot import PandaKinematics
    from trajectories.safety import MOCK_BASES

    kin = {a: PandaKinematics(MOCK_BASES[a]) for a in ("left", "right")}
    for name, cat in (("rope_swing", "dlo"), ("branched_lift", "bdlo"), ("cloth_fold", "cloth")):
        prog = load_program(library_path(name))
        assert prog.category == cat and 4 <= len(prog.waypoints) <= 6
        w = prog.waypoints[0]
        for arm, y in (("left", 0.25), ("right", -0.25)):
            T = kin[arm].tcp_pose(np.asarray(getattr(w, arm)))
            np.testing.assert_allclose(T[:3, 3], [0.45, y, 0.40], atol=1e-3)
            assert T[2, 2] < -0.999  # gripper pointing down
        assert all(g.state == "closed" for g in prog.gripper_states()[0].values())
