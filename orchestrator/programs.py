"""From a plan item to the arms' motions: load, time (ruckig), check, and turn into JointMotions."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np

from orchestrator.config import Config
from tdcommon.types import JointMotion
from trajectories.program import Program, ProgramError, load_program, resolve_program
from trajectories.timing import TimedProgram, speed_profile, time_program

EXECUTION_RATE = 1000.0  # Hz: the samples every driver receives (UR resamples to its servo rate)


class ProgramRejected(RuntimeError):
    """A program failed its checks (limits, collisions, workspace) before the arms moved."""


@dataclass(frozen=True)
class GripperAction:
    """Command ``arm``'s gripper at ``time`` s after motion start."""

    time: float
    arm: str
    closed: bool
    width: float | None
    force: float | None


@dataclass(frozen=True)
class PlannedMotion:
    """Everything the session needs to execute one program run."""

    timed: TimedProgram
    left: JointMotion
    right: JointMotion
    gripper_events: tuple[GripperAction, ...]
    waypoint_offset: int = 0  # the timed program starts at this waypoint of the original program

    @property
    def duration(self) -> float:
        """Total motion time, s."""
        return self.timed.duration

    @property
    def segment_report(self) -> list[dict[str, Any]]:
        """Per segment: kind, target waypoint, requested and actual duration (s)."""
        return [
            {"index": s.index, "kind": s.kind, "to_waypoint": s.to_waypoint,
             "requested": round(s.requested, 6), "actual": round(s.actual, 6)}
            for s in self.timed.segments
        ]


def _safety_problems(timed: TimedProgram, bases: dict[str, np.ndarray]) -> list[str]:
    """Limits along the whole trajectory, self / arm-arm collisions and the TCP workspace."""
    from trajectories.safety import check_program

    report = check_program(timed, bases)
    return [str(v) for v in report.violations]


def program_from(program: Program, k: int) -> Program:
    """The program from waypoint ``k`` on, the gripper states in force at ``k`` made explicit there."""
    if k <= 0:
        return program
    if k >= len(program.waypoints):
        raise ValueError(f"{program.name} has {len(program.waypoints)} waypoints; cannot start at {k}")
    first = program.waypoints[k].model_copy(update={"grippers": program.gripper_states()[k]})
    return program.model_copy(update={"waypoints": [first, *program.waypoints[k + 1 :]]})


def plan_motion(item: Any, station: Any, fast_duration: float, start_waypoint: int = 0) -> PlannedMotion:
    """Load ``item.program``, time it from the arms' current state at ``item.speed``, check it.

    ``start_waypoint`` > 0 resumes after a fault: a slow approach from where the arms are to that
    waypoint, then the rest at the item's speed. Raises ProgramRejected (before anything moves).
    """
    try:
        program = program_from(load_program(resolve_program(item.program)), start_waypoint)
    except ProgramError as e:
        raise ProgramRejected(str(e)) from None
    q = station.current_q()
    current = np.concatenate([q["left"], q["right"]])
    timed = time_program(program, speed_profile(item.speed, fast_duration), current=current)
    problems = _safety_problems(timed, station.bases)
    if problems:
        raise ProgramRejected(f"{program.name} at {item.speed} refused before motion:\n  " + "\n  ".join(problems))
    left, right = timed.to_motions(EXECUTION_RATE)
    events = tuple(
        GripperAction(e.time, e.arm, e.command.state == "closed", e.command.width, e.command.force)
        for e in timed.gripper_events
    )
    return PlannedMotion(timed, left, right, events, start_waypoint)


def check_config_programs(config: Config, out: TextIO) -> int:
    """Load, time and check every program of the plan at every planned speed; print a line each."""
    bases = {"left": config.station.left.arm.base.matrix(), "right": config.station.right.arm.base.matrix()}
    problems = 0
    for obj in config.plan.objects:
        for ref in obj.programs:
            try:
                program: Program = load_program(resolve_program(ref))
            except ProgramError as e:
                print(f"  program {ref} ({obj.name}): {e}", file=out)
                problems += 1
                continue
            if program.category not in ("any", obj.category):
                print(f"  program {ref}: written for {program.category}, used with {obj.name} ({obj.category})",
                      file=out)
                problems += 1
            for speed in config.plan.speeds:
                timed = time_program(program, speed_profile(speed, config.plan.fast_duration))
                bad = _safety_problems(timed, bases)
                status = "OK" if not bad else f"{len(bad)} problem(s)"
                print(f"  program {ref} ({obj.name}) at {speed}: {timed.duration:.2f} s, "
                      f"{len(timed.segments)} segments, {status}", file=out)
                for b in bad:
                    print(f"    {b}", file=out)
                problems += len(bad)
    return problems
