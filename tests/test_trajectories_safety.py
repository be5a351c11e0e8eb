"""Safety checks along the trajectory: collisions, limits, workspace, start state; library programs pass."""

from __future__ import annotations

import numpy as np
import pytest

from tdcommon.robot import HOME_Q, PandaKinematics, arm_inputs, arm_inputs_batch, panda_models
from trajectories.program import Program, Waypoint, library_path, load_program
from trajectories.safety import MOCK_BASES, Workspace, check_program
from trajectories.timing import MEDIUM, SLOW, fast, time_program

HOME = np.array(HOME_Q)


def _prog(*pairs: tuple[np.ndarray, np.ndarray]) -> Program:
    return Program(name="t", waypoints=[Waypoint(left=list(a), right=list(b)) for a, b in pairs])


def test_panda_models_equal_example_robot_data_load():
    """Built without the visual meshes, the kinematic and collision models are load("panda")'s."""
    from example_robot_data import load

    model, cmodel = panda_models()
    robot = load("panda")
    assert model == robot.model and cmodel == robot.collision_model
    assert len(cmodel.geometryObjects) > 0 and len(cmodel.collisionPairs) == len(robot.collision_model.collisionPairs)


def test_home_is_safe():
    report = check_program(time_program(_prog((HOME, HOME), (HOME, HOME)), MEDIUM))
    assert report.ok, report.summary()


def test_arms_driven_into_each_other_are_refused_with_time_and_segment():
    d = np.array([-1.2, 0.6, 0.0, 1.0, 0.0, 0.0, 0.0])
    inward_l, inward_r = HOME + d, HOME + d * np.array([-1, 1, 1, 1, 1, 1, 1])
    prog = _prog((HOME, HOME), (HOME + 0.05, HOME), (inward_l, inward_r), (HOME, HOME))
    report = check_program(time_program(prog, SLOW))
    assert not report.ok
    arm = [v for v in report.violations if v.kind == "arm_collision"]
    assert arm, report.summary()
    first = min(arm, key=lambda v: v.time)
    assert first.segment == 1 and 4.0 < first.time < 8.0  # on the way to waypoint 2
    assert first.message.startswith(f"t={first.time:.2f}")
    assert "segment 1 (move to waypoint 2)" in first.message
    assert "collides with" in first.message and "left panda_" in first.message and "right panda_" in first.message


def test_table_and_workspace_violations():
    down = HOME + np.array([0.0, 1.7, 0.0, 0.6, 0.0, 0.0, 0.0])  # reach forward and down into the table
    report = check_program(time_program(_prog((HOME, HOME), (down, HOME)), MEDIUM))
    kinds = {v.kind for v in report.violations}
    assert "table" in kinds and "workspace" in kinds, report.summary()
    assert any("left TCP z" in v.message for v in report.violations)
    assert sum("left panda_leftfinger reaches" in v.message for v in report.violations) == 1
    tight = Workspace(lower=(0.0, -0.9, 0.02), upper=(0.2, 0.9, 1.2))
    report = check_program(time_program(_prog((HOME, HOME), (HOME, HOME)), MEDIUM), workspace=tight)
    assert any(v.kind == "workspace" and "TCP x" in v.message for v in report.violations)


def test_start_state_must_match():
    timed = time_program(_prog((HOME, HOME), (HOME, HOME)), MEDIUM)
    current = np.concatenate([HOME, HOME + np.array([0, 0, 0, 0.1, 0, 0, 0])])
    report = check_program(timed, start=current)
    assert [v.kind for v in report.violations] == ["start"]
    assert "right arm is at joint 3" in report.violations[0].message
    assert check_program(time_program(timed.program, MEDIUM, current=current), start=current).ok


def test_joint_limit_along_trajectory():
    timed = time_program(_prog((HOME, HOME), (HOME, HOME)), MEDIUM)
    times, q, dq = timed.sample(50.0)
    q = q.copy()
    q[10:20, 5] = 3.9  # beyond 3.7525 between waypoints
    from trajectories.safety import check_trajectory

    v = check_trajectory(timed, times, q, dq, MOCK_BASES, Workspace())
    lim = [x for x in v if x.kind == "joint_limit"]
    assert len(lim) == 1 and abs(lim[0].time - 0.2) < 1e-9 and "left joint 5" in lim[0].message


@pytest.mark.parametrize("name", ["rope_swing", "branched_lift", "cloth_fold"])
def test_library_programs_pass_at_all_speeds(name):
    prog = load_program(library_path(name))
    for speed in (SLOW, MEDIUM, fast(1.0), fast(1.5)):
        report = check_program(time_program(prog, speed))
        assert report.ok, f"{name} at {speed}: {report.summary()}"


def test_arm_inputs_batch_matches_single():
    kl, kr = PandaKinematics(MOCK_BASES["left"]), PandaKinematics(MOCK_BASES["right"])
    rng = np.random.default_rng(0)
    ql, qr = HOME + rng.normal(0, 0.3, (6, 7)), HOME + rng.normal(0, 0.3, (6, 7))
    u = arm_inputs_batch(kl, kr, ql, qr)
    assert u.shape == (6, 12)
    np.testing.assert_allclose(u, np.stack([arm_inputs(kl, kr, a, b) for a, b in zip(ql, qr, strict=True)]))
    np.testing.assert_allclose(u[0, :3], kl.tcp_pose(ql[0])[:3, 3])  # left position first


def test_ik_reaches_pose():
    from trajectories.ik import solve_ik, tcp_target

    kin = PandaKinematics(MOCK_BASES["left"])
    T = tcp_target(np.array([0.5, 0.2, 0.3]), yaw=0.3)
    q = solve_ik(kin, T, HOME)
    np.testing.assert_allclose(kin.tcp_pose(q), T, atol=1e-3)
