"""Time a dual-arm program with ruckig: one synchronised 14-DoF trajectory of rest-to-rest segments.

The free ruckig has no intermediate waypoints, so every move from one waypoint to the next is its
own offline calculation with one ``ruckig.Ruckig(14)``: both arms start and stop together.

Gentle stretching (docs/architecture.md, decisions): asking ruckig for ``minimum_duration`` alone gives the exact
duration but a jolty move (full acceleration for a few ms, then a slow cruise). Instead each
segment's acceleration limits are scaled by ``s`` and its jerk limits set so that ramping that
acceleration takes ``ramp_fraction`` of the requested duration; ``s`` is the smallest fraction
whose time-optimal, phase-synchronised move still takes no longer than requested, found by
bisection to ~1e-9 s. With ``ramp_fraction`` = 0.25 that is the minimum-peak-jerk S-curve: a
smooth bell of velocity, every joint on the same normalised profile (a straight line in joint
space). Only when the full (safety-scaled) limits cannot meet the duration is the jerk raised
towards its limit, and if even that is too slow the segment is longer than asked and reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import ruckig

from tdcommon.types import JointMotion
from trajectories.program import ARMS, GripperCommand, Program

N = 14  # both arms, left joints then right joints
DURATION_TOL = 1e-6  # s: a segment within this of its request meets it
SAME_Q_TOL = 1e-4  # rad: closer than this, two configurations are the same (no approach / dwell only)


@dataclass(frozen=True)
class SpeedProfile:
    """How long every move of a program takes: ``segment_duration`` s per waypoint."""

    name: str
    segment_duration: float


SLOW = SpeedProfile("slow", 4.0)
MEDIUM = SpeedProfile("medium", 2.0)
FAST_RANGE = (1.0, 1.5)


def fast(duration: float = 1.25) -> SpeedProfile:
    """The fast profile, ``duration`` s per waypoint, 1.0–1.5 s."""
    if not FAST_RANGE[0] <= duration <= FAST_RANGE[1]:
        raise ValueError(f"fast duration {duration} s is outside {FAST_RANGE[0]}–{FAST_RANGE[1]} s")
    return SpeedProfile("fast", float(duration))


def speed_profile(name: str, fast_duration: float = 1.25) -> SpeedProfile:
    """The profile called ``name`` (slow | medium | fast)."""
    if name == "slow":
        return SLOW
    if name == "medium":
        return MEDIUM
    if name == "fast":
        return fast(fast_duration)
    raise ValueError(f"unknown speed {name!r}: expected slow, medium or fast")


@dataclass(frozen=True)
class TimingLimits:
    """Dynamic limits for timing, each (14,): the Panda's published limits times ``safety_scale``."""

    velocity: np.ndarray  # rad/s
    acceleration: np.ndarray  # rad/s^2
    jerk: np.ndarray  # rad/s^3
    lower: np.ndarray  # rad
    upper: np.ndarray  # rad
    safety_scale: float
    ramp_fraction: float = 0.25

    @classmethod
    def panda(cls, safety_scale: float = 0.8, ramp_fraction: float = 0.25) -> TimingLimits:
        """Both Pandas' datasheet limits scaled by ``safety_scale`` in (0, 1]."""
        from tdcommon.robot import joint_limits

        if not 0.0 < safety_scale <= 1.0:
            raise ValueError(f"safety_scale {safety_scale} must be in (0, 1]")
        if not 0.0 < ramp_fraction <= 0.25:
            raise ValueError(f"ramp_fraction {ramp_fraction} must be in (0, 0.25]")
        lim = joint_limits()
        two = {k: np.tile(v, 2) for k, v in lim.items()}
        return cls(
            velocity=two["velocity"] * safety_scale,
            acceleration=two["acceleration"] * safety_scale,
            jerk=two["jerk"] * safety_scale,
            lower=two["lower"],
            upper=two["upper"],
            safety_scale=safety_scale,
            ramp_fraction=ramp_fraction,
        )


@dataclass(frozen=True)
class TimedSegment:
    """One rest-to-rest piece of the timed program.

    kind: ``approach`` (current state to waypoint 0), ``move`` (waypoint i-1 to i) or ``dwell``
    (hold at a waypoint). start/requested/actual: s. acc_scale / jerk_scale: fraction of the
    safety-scaled limits the segment was timed with (0 for a dwell). q_start, q_end: (14,) rad.
    """

    index: int
    kind: Literal["approach", "move", "dwell"]
    to_waypoint: int
    start: float
    requested: float
    actual: float
    acc_scale: float
    jerk_scale: float
    q_start: np.ndarray
    q_end: np.ndarray
    trajectory: ruckig.Trajectory | None = field(default=None, repr=False, compare=False)

    @property
    def end(self) -> float:
        """Segment end time from program start, s."""
        return self.start + self.actual

    @property
    def longer_than_requested(self) -> bool:
        """True when the limits made this segment take longer than requested."""
        return self.actual > self.requested + DURATION_TOL

    def label(self) -> str:
        """Human-readable name, e.g. ``segment 2 (move to waypoint 2)``."""
        what = {"approach": "approach to", "move": "move to", "dwell": "dwell at"}[self.kind]
        return f"segment {self.index} ({what} waypoint {self.to_waypoint})"

    def arm_end_times(self) -> tuple[float, float]:
        """(left, right) s from segment start at which each arm's last joint comes to rest (ruckig profiles)."""
        if self.trajectory is None:
            return 0.0, 0.0
        ends = np.zeros(N)
        for d, prof in enumerate(self.trajectory.profiles[-1]):  # rest to rest: a single section
            t, j = np.asarray(prof.t), np.asarray(prof.j)
            a, v = np.asarray(prof.a)[:-1], np.asarray(prof.v)[:-1]
            moving = np.flatnonzero((np.abs(j) > 0) | (np.abs(a) > 0) | (np.abs(v) > 0))
            ends[d] = np.cumsum(t)[moving[-1]] if len(moving) else 0.0
        return float(ends[:7].max()), float(ends[7:].max())

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, dq, ddq, each (len(t), 14), at times ``t`` (s, from segment start, clamped)."""
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.actual)
        if self.trajectory is None:
            z = np.zeros((len(t), N))
            return np.broadcast_to(self.q_end, (len(t), N)).copy(), z, z.copy()
        out = np.array([np.concatenate(self.trajectory.at_time(float(x))) for x in t]).reshape(len(t), 3 * N)
        return out[:, :N], out[:, N : 2 * N], out[:, 2 * N :]


@dataclass(frozen=True)
class GripperEvent:
    """Command ``arm``'s gripper at ``time`` s from program start (on arrival at ``waypoint``)."""

    time: float
    arm: str
    waypoint: int
    command: GripperCommand


@dataclass(frozen=True)
class TimedProgram:
    """A program timed at one speed: its segments back to back and the gripper events."""

    program: Program
    speed: SpeedProfile
    segments: tuple[TimedSegment, ...]
    gripper_events: tuple[GripperEvent, ...]
    limits: TimingLimits

    @property
    def duration(self) -> float:
        """Total duration, s."""
        return self.segments[-1].end if self.segments else 0.0

    @property
    def q_start(self) -> np.ndarray:
        """(14,) rad: where the trajectory starts."""
        return self.segments[0].q_start if self.segments else self.program.waypoints[0].q()

    def waypoint_times(self) -> np.ndarray:
        """(W,) s: arrival time at each waypoint."""
        out = np.zeros(len(self.program.waypoints))
        for s in self.segments:
            if s.kind != "dwell":
                out[s.to_waypoint] = s.end
        return out

    def limited_segments(self) -> list[TimedSegment]:
        """Segments the limits made longer than requested."""
        return [s for s in self.segments if s.longer_than_requested]

    def segment_at(self, t: np.ndarray) -> np.ndarray:
        """(len(t),) int: index of the segment running at each time ``t`` s."""
        ends = np.array([s.end for s in self.segments])
        return np.minimum(np.searchsorted(ends, np.asarray(t), side="left"), len(self.segments) - 1)

    def sample(self, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """times (K,) s at uniform 1/rate_hz from 0, q (K, 14) rad and dq (K, 14) rad/s; ends at rest."""
        q, dq, _ = self._sample(rate_hz)
        return q[0], q[1], dq

    def sample_full(self, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """times (K,), q, dq, ddq (K, 14): like ``sample`` plus accelerations (rad/s^2)."""
        (times, q), dq, ddq = self._sample(rate_hz)
        return times, q, dq, ddq

    def _sample(self, rate_hz: float) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
        if rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        k = int(round(self.duration * rate_hz)) + 1
        times = np.arange(k) / rate_hz
        if not self.segments:  # a single waypoint, already there
            q = self.q_start[None].copy()
            return (times, q), np.zeros_like(q), np.zeros_like(q)
        q, dq, ddq = np.empty((k, N)), np.empty((k, N)), np.empty((k, N))
        seg = self.segment_at(times)
        for i, s in enumerate(self.segments):
            m = seg == i
            if m.any():
                q[m], dq[m], ddq[m] = s.state(times[m] - s.start)
        if k > 1 and abs(times[-1] - self.duration) < 0.5 / rate_hz:  # end exactly on the last target
            q[-1], dq[-1], ddq[-1] = self.segments[-1].q_end, 0.0, 0.0
        return (times, q), dq, ddq

    def to_motions(self, rate_hz: float = 100.0) -> tuple[JointMotion, JointMotion]:
        """(left, right) JointMotion: samples at ``rate_hz``, segment targets, durations and limit scales.

        ``limit_scale`` is the segment's acceleration scale times the safety scale, i.e. the fraction
        of the Panda's published acceleration limit the segment was timed with (0 for a dwell). A program
        with nothing left to do (resumed at its last waypoint, already there) gives motions without segments.
        """
        times, q, dq = self.sample(rate_hz)
        targets = np.array([s.q_end for s in self.segments], dtype=np.float64).reshape(len(self.segments), N)
        durations = np.array([s.actual for s in self.segments])
        scale = np.array([s.acc_scale * self.limits.safety_scale for s in self.segments])
        return tuple(  # type: ignore[return-value]
            JointMotion(times.copy(), q[:, sl].copy(), dq[:, sl].copy(), targets[:, sl].copy(), durations.copy(),
                        scale.copy())
            for sl in (slice(0, 7), slice(7, 14))
        )

    def peak_velocity_ratio(self, rate_hz: float = 100.0) -> float:
        """Largest |dq| over the published Panda velocity limit, any joint, any sample."""
        _, _, dq = self.sample(rate_hz)
        vmax = self.limits.velocity / self.limits.safety_scale
        return float(np.max(np.abs(dq) / vmax)) if len(dq) else 0.0


def _calculate(q0: np.ndarray, q1: np.ndarray, vel: np.ndarray, acc: np.ndarray, jerk: np.ndarray,
               lo: np.ndarray, hi: np.ndarray) -> ruckig.Trajectory:
    """Time-optimal phase-synchronised rest-to-rest ruckig trajectory q0 -> q1 (14,) within the limits."""
    inp = ruckig.InputParameter(N)
    inp.current_position = q0.tolist()
    inp.current_velocity = [0.0] * N
    inp.current_acceleration = [0.0] * N
    inp.target_position = q1.tolist()
    inp.target_velocity = [0.0] * N
    inp.target_acceleration = [0.0] * N
    inp.max_velocity = vel.tolist()
    inp.max_acceleration = acc.tolist()
    inp.max_jerk = jerk.tolist()
    inp.min_position = lo.tolist()
    inp.max_position = hi.tolist()
    inp.synchronization = ruckig.Synchronization.Phase
    otg = ruckig.Ruckig(N)
    # ruckig 0.19 can fail on exact boundary cases between profile shapes ("error in step 1"):
    # nudging the limits by a relative 1e-7..1e-5 (far below anything measurable) gets past them
    for eps in (0.0, -1e-7, 1e-7, -1e-5, 1e-5):
        inp.max_acceleration = (acc * (1 + eps)).tolist()
        inp.max_jerk = (jerk * (1 + eps)).tolist()
        traj = ruckig.Trajectory(N)
        try:
            res = otg.calculate(inp, traj)
        except ruckig.RuckigError as e:
            err = str(e).strip().splitlines()[0]
            continue
        if res in (ruckig.Result.Working, ruckig.Result.Finished):
            return traj
        err = res.name
    raise ValueError(f"ruckig could not time the segment: {err}")


def time_segment(q0: np.ndarray, q1: np.ndarray, duration: float,
                 limits: TimingLimits) -> tuple[ruckig.Trajectory, float, float]:
    """Gentlest rest-to-rest move q0 -> q1 (14,) rad taking ``duration`` s (longer if the limits force it).

    Returns (trajectory, acc_scale, jerk_scale) with the scales relative to ``limits``.
    """
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    v, a, j = limits.velocity, limits.acceleration, limits.jerk
    lo, hi = np.minimum(limits.lower, np.minimum(q0, q1)), np.maximum(limits.upper, np.maximum(q0, q1))
    ramp = limits.ramp_fraction * duration

    def gentle(s: float) -> tuple[ruckig.Trajectory, float]:
        js = np.minimum(1.0, s * a / (j * ramp))  # jerk so that ramping s*a takes `ramp` s
        return _calculate(q0, q1, v, s * a, js * j, lo, hi), float(np.max(js))

    def steep(js: float) -> ruckig.Trajectory:
        return _calculate(q0, q1, v, a, np.maximum(js, np.minimum(1.0, a / (j * ramp))) * j, lo, hi)

    traj, js1 = gentle(1.0)
    if traj.duration <= duration + DURATION_TOL:
        s_lo, s_hi, best = 0.0, 1.0, traj  # duration(s) decreases with s: find the smallest s that fits
        # bracket on a log scale first (cheap), then bisect
        s = 1.0
        while s > 1e-9:
            s *= 0.1
            t = gentle(s)[0]
            if t.duration > duration:
                s_lo = s
                break
            s_hi, best = s, t
        for _ in range(80):
            mid = math.sqrt(s_lo * s_hi) if s_lo > 0 else s_hi / 2
            t = gentle(mid)[0]
            if t.duration <= duration:
                s_hi, best = mid, t
            else:
                s_lo = mid
            if best.duration > duration - 1e-9:
                break
        return best, s_hi, gentle(s_hi)[1]
    full = steep(1.0)
    if full.duration > duration + DURATION_TOL:
        return full, 1.0, 1.0  # the limits make it longer than requested
    j_lo, j_hi, best = js1, 1.0, full
    for _ in range(80):
        mid = math.sqrt(j_lo * j_hi)
        t = steep(mid)
        if t.duration <= duration:
            j_hi, best = mid, t
        else:
            j_lo = mid
        if best.duration > duration - 1e-9:
            break
    return best, 1.0, j_hi


def _segment(index: int, kind: Literal["approach", "move", "dwell"], to_wp: int, start: float,
             q0: np.ndarray, q1: np.ndarray, requested: float, limits: TimingLimits) -> TimedSegment:
    if kind == "dwell" or np.max(np.abs(q1 - q0)) < SAME_Q_TOL:
        return TimedSegment(index, "dwell" if kind == "dwell" else kind, to_wp, start, requested, requested,
                            0.0, 0.0, q1.copy(), q1.copy(), None)
    traj, sa, sj = time_segment(q0, q1, requested, limits)
    return TimedSegment(index, kind, to_wp, start, requested, float(traj.duration), sa, sj, q0.copy(), q1.copy(),
                        traj)


def time_program(program: Program, speed: SpeedProfile, current: np.ndarray | None = None,
                 limits: TimingLimits | None = None) -> TimedProgram:
    """Time ``program`` at ``speed``; from ``current`` (14,) rad (left then right) add a slow approach.

    Waypoint i > 0 is reached ``duration`` s after waypoint i-1 when given, else
    ``speed.segment_duration / speed_scale``. The approach (only when ``current`` differs from
    waypoint 0) always uses the slow profile. Gripper commands fire on arrival at a waypoint whose
    state differs from the previous one (all commands on arrival at waypoint 0).
    """
    limits = limits or TimingLimits.panda()
    wq = program.q()
    segs: list[TimedSegment] = []
    events: list[GripperEvent] = []
    t = 0.0
    prev_state: dict[str, GripperCommand] | None = None
    if current is not None:
        current = np.asarray(current, dtype=np.float64).reshape(N)
        if np.max(np.abs(current - wq[0])) >= SAME_Q_TOL:
            segs.append(_segment(0, "approach", 0, t, current, wq[0], SLOW.segment_duration, limits))
            t = segs[-1].end
    for i, (w, state) in enumerate(zip(program.waypoints, program.gripper_states(), strict=True)):
        if i > 0:
            req = w.duration if w.duration is not None else speed.segment_duration / w.speed_scale
            segs.append(_segment(len(segs), "move", i, t, wq[i - 1], wq[i], req, limits))
            t = segs[-1].end
        for arm in ARMS:
            if prev_state is None or not state[arm].same_as(prev_state[arm]):
                events.append(GripperEvent(t, arm, i, state[arm]))
        prev_state = state
        if w.dwell > 0:
            segs.append(_segment(len(segs), "dwell", i, t, wq[i], wq[i], w.dwell, limits))
            t = segs[-1].end
    return TimedProgram(program, speed, tuple(segs), tuple(events), limits)
