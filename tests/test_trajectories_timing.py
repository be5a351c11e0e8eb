"""Ruckig timing: exact durations, synchronised arms, limit-bound segments, samples and motions."""

from __future__ import annotations

import numpy as np
import pytest

from tdcommon.robot import HOME_Q, joint_limits
from trajectories.program import Program, Waypoint, library_path, load_program
from trajectories.timing import MEDIUM, SLOW, fast, speed_profile, time_program

HOME = np.array(HOME_Q)
D = np.array([0.4, 0.2, -0.1, 0.3, 0.02, 0.1, 0.4])


def _prog(*pairs: tuple[np.ndarray, np.ndarray], **kw) -> Program:
    wps = [Waypoint(left=list(a), right=list(b), **(kw if i else {})) for i, (a, b) in enumerate(pairs)]
    return Program(name="t", waypoints=wps)


PROG = _prog((HOME, HOME), (HOME + D, HOME - 0.3 * D), (HOME - 0.5 * D, HOME + 0.2), (HOME, HOME))


@pytest.mark.parametrize("speed", [SLOW, MEDIUM, fast(1.0), fast(1.25), fast(1.5)])
def test_segment_durations_exact(speed):
    timed = time_program(PROG, speed)
    assert len(timed.segments) == 3
    for s in timed.segments:
        assert abs(s.actual - speed.segment_duration) < 1e-3
        assert not s.longer_than_requested
        left_end, right_end = s.arm_end_times()
        assert abs(left_end - s.actual) < 1e-3 and abs(right_end - s.actual) < 1e-3  # both arms end together
    assert abs(timed.duration - 3 * speed.segment_duration) < 3e-3
    np.testing.assert_allclose(timed.waypoint_times(), np.arange(4) * speed.segment_duration, atol=3e-3)


def test_samples_reach_waypoints_within_limits():
    timed = time_program(PROG, MEDIUM)
    times, q, dq = timed.sample(100.0)
    assert times.shape == (601,) and q.shape == (601, 14) and dq.shape == (601, 14)
    np.testing.assert_allclose(np.diff(times), 0.01)
    for k, wq in zip((0, 200, 400, 600), PROG.q(), strict=True):
        np.testing.assert_allclose(q[k], wq, atol=1e-6)
        np.testing.assert_allclose(dq[k], 0.0, atol=1e-6)
    vmax = np.tile(joint_limits()["velocity"], 2)
    assert np.all(np.abs(dq) <= vmax * 0.8 + 1e-9)
    # phase synchronised: every joint moves on the same normalised profile (straight line in joint space)
    seg = q[:201] - q[0]
    frac = seg[:, 0] / (PROG.q()[1, 0] - PROG.q()[0, 0])
    np.testing.assert_allclose(seg, frac[:, None] * (PROG.q()[1] - PROG.q()[0]), atol=1e-9)


def test_stretched_moves_are_gentle():
    """Slow segments use a small fraction of the acceleration limits (no full-limit jolts)."""
    timed = time_program(PROG, SLOW)
    _, _, _, ddq = timed.sample_full(1000.0)
    amax = np.tile(joint_limits()["acceleration"], 2)
    assert np.max(np.abs(ddq) / amax) < 0.05
    assert all(s.acc_scale < 0.1 for s in timed.segments)


def test_limit_exceeding_segment_is_reported_longer():
    far = HOME.copy()
    far[0] += 2.5  # 2.5 rad on joint 1 in 1 s exceeds 0.8 x 2.175 rad/s
    timed = time_program(_prog((HOME, HOME), (far, HOME)), fast(1.0))
    (seg,) = timed.limited_segments()
    assert seg.index == 0 and seg.requested == 1.0 and seg.actual > 1.4
    _, _, dq = timed.sample(200.0)
    assert np.abs(dq).max() <= 2.175 * 0.8 + 1e-9


def test_duration_override_speed_scale_and_dwell():
    prog = _prog((HOME, HOME), (HOME + D, HOME), (HOME, HOME), (HOME + D, HOME))
    prog.waypoints[1].duration = 3.0
    prog.waypoints[2].speed_scale = 0.5
    prog.waypoints[2].dwell = 0.7
    timed = time_program(prog, MEDIUM)
    kinds = [(s.kind, round(s.actual, 4)) for s in timed.segments]
    assert kinds == [("move", 3.0), ("move", 4.0), ("dwell", 0.7), ("move", 2.0)]
    assert abs(timed.duration - 9.7) < 1e-3


def test_approach_from_current_state_at_slow_speed():
    current = np.concatenate([HOME + 0.2, HOME])
    timed = time_program(PROG, fast(), current=current)
    first = timed.segments[0]
    assert first.kind == "approach" and abs(first.actual - 4.0) < 1e-3
    np.testing.assert_allclose(timed.q_start, current)
    assert all(abs(s.actual - 1.25) < 1e-3 for s in timed.segments[1:])
    # already there: no approach
    assert time_program(PROG, fast(), current=PROG.q()[0]).segments[0].kind == "move"


def test_gripper_events_on_arrival_when_state_changes():
    prog = Program(name="g", waypoints=[
        Waypoint(left=list(HOME), right=list(HOME), grippers={"left": "closed", "right": "closed"}),
        Waypoint(left=list(HOME + D), right=list(HOME)),
        Waypoint(left=list(HOME), right=list(HOME), grippers={"left": {"state": "open", "width": 0.05}}),
    ])
    timed = time_program(prog, MEDIUM, current=np.concatenate([HOME + 0.1, HOME]))
    ev = [(round(e.time, 3), e.arm, e.command.state, e.waypoint) for e in timed.gripper_events]
    assert ev == [(4.0, "left", "closed", 0), (4.0, "right", "closed", 0), (8.0, "left", "open", 2)]
    assert timed.gripper_events[-1].command.width == 0.05


def test_to_motions():
    timed = time_program(PROG, MEDIUM)
    left, right = timed.to_motions(100.0)
    assert left.q.shape == right.q.shape == (601, 7)
    assert left.targets.shape == (3, 7) and left.durations.shape == (3,) and left.limit_scale.shape == (3,)
    np.testing.assert_allclose(left.targets[-1], HOME, atol=1e-9)
    assert abs(left.duration - 6.0) < 1e-6 and abs(left.dt - 0.01) < 1e-12
    q, dq = right.sample(2.0)
    np.testing.assert_allclose(q, PROG.waypoints[1].right, atol=1e-6)
    assert np.all((left.limit_scale > 0) & (left.limit_scale <= 1))


def test_speed_profiles():
    assert speed_profile("slow").segment_duration == 4.0
    assert speed_profile("medium").segment_duration == 2.0
    assert speed_profile("fast").segment_duration == 1.25
    assert speed_profile("fast", 1.4).segment_duration == 1.4
    with pytest.raises(ValueError):
        fast(0.5)
    with pytest.raises(ValueError):
        speed_profile("ludicrous")


@pytest.mark.parametrize("name", ["rope_swing", "branched_lift", "cloth_fold"])
def test_library_times_exactly_at_every_speed(name):
    prog = load_program(library_path(name))
    for speed in (SLOW, MEDIUM, fast(1.0), fast(1.5)):
        timed = time_program(prog, speed)
        assert not timed.limited_segments()
        assert abs(timed.duration - (len(prog.waypoints) - 1) * speed.segment_duration) < 1e-3


limits_lo = joint_limits()["lower"] + 0.05
limits_hi = joint_limits()["upper"] - 0.05


def test_random_segments_property():
    """Any in-limit segment at any speed: ruckig succeeds, duration exact or reported longer, within limits."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from trajectories.timing import TimingLimits, time_segment

    lim = TimingLimits.panda()
    unit = st.lists(st.floats(0.0, 1.0), min_size=14, max_size=14)

    @settings(max_examples=150, deadline=None, derandomize=True)
    @given(unit, unit, st.sampled_from([4.0, 2.0, 1.0, 1.25, 1.5]), st.floats(0.001, 1.0))
    def check(a, b, duration, reach):
        lo, hi = np.tile(limits_lo, 2), np.tile(limits_hi, 2)
        q0 = lo + np.asarray(a) * (hi - lo)
        q1 = q0 + reach * (lo + np.asarray(b) * (hi - lo) - q0)
        traj, sa, sj = time_segment(q0, q1, duration, lim)
        assert traj.duration <= duration + 1e-6 or (sa == 1.0 and sj == 1.0)
        assert traj.duration > duration - 1e-3 or np.max(np.abs(q1 - q0)) < 1e-3
        q, dq, _ = traj.at_time(traj.duration)
        np.testing.assert_allclose(q, q1, atol=1e-9)
        peak = np.max([np.abs(traj.at_time(t)[1]) / lim.velocity for t in np.linspace(0, traj.duration, 21)])
        assert peak <= 1 + 1e-9

    check()


def test_to_motions_with_nothing_left_to_do():
    """Resumed at its last waypoint with the arms already there (a fault after the motion ended): no segments."""
    last = _prog((HOME, HOME))
    timed = time_program(last, MEDIUM, current=last.q()[0])
    assert not timed.segments
    left, right = timed.to_motions(100.0)
    assert left.targets.shape == (0, 7) and left.durations.shape == (0,) and left.duration == 0.0
    np.testing.assert_allclose(right.q[0], HOME)
