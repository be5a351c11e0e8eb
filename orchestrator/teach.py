"""Teach a dual-arm program by hand: guide both arms, press Enter to record each waypoint.

``trackdeform program teach --config CONFIG --out FILE`` connects the station's two arms and two
grippers (never the camera), then reads commands, one per line:

- Enter (empty line): record a waypoint: both arms' current joints and both grippers' states;
- ``g l`` / ``g r`` (or ``g left`` / ``g right``): toggle that gripper now (it is commanded at once
  and its new state is recorded at the next waypoint, followed by a ``--grip-dwell`` pause);
- ``u``: undo the last waypoint (the grippers stay as they are);
- ``h`` / ``?``: help;
- ``q`` (or end of input): check the program (joint limits; timing at slow with ruckig; collisions,
  table and workspace along the timed path) and save it. Problems are reported and the file is
  saved anyway, with a warning, so a long teaching session is never lost;
- Ctrl-C: quit without saving.

The arms are never commanded while teaching: the command only reads their joint states. The
grippers move only when toggled, except that a Franka Hand homes its fingers on connect when its
config has ``home_on_connect: true`` (the default): start teaching with the hands empty, or set it
to false.

Hand guiding on the Franka Panda (``type: franka``, driver ``drivers.franka`` over franky): the
FCI must be activated in Desk and the joints unlocked so that franky can connect. Guide an arm by
pressing the two opposing guiding buttons at the pilot grip near the flange: the arm switches to
guiding mode (libfranka ``RobotMode.kGuiding``) and follows the hand in gravity compensation, and
holds where it is released. Depending on the Panda's system version, Desk may allow guiding
only in the monitored-stop state (external activation device pressed, white lights); libfranka
keeps streaming the robot state then (robot mode ``kUserStopped`` / ``kGuiding``). Which Cartesian
axes and the elbow are free is libfranka's ``setGuidingMode`` (franky ``Robot.set_guiding_mode``);
this command leaves it as it is. The driver reads joints through franky's
``Robot.current_joint_state`` (libfranka's state read), which needs no motion to be running and
so works while an arm is guided, according to libfranka; this has not been tried on hardware
from this repository. UR arms are taught in the pendant's freedrive mode the same way (ur-rtde's
receive interface streams joints independently of the control script; also not tried here).

In mock mode (``type: fake``) the arms hold still, which makes teaching useful only to tests;
:func:`teach` takes a ``guide`` hook that moves the fake arms between commands.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from drivers.base import Arm, DeviceError, Gripper
from trajectories.program import ARMS, GripperCommand, Program, ProgramError, Waypoint, limit_violations, save_program

CLOSED_WIDTH = 0.04  # m: a gripper reading narrower than this (or holding something) counts as closed
GRIPPER_NAMES = {"l": "left", "left": "left", "r": "right", "right": "right"}
HELP = (
    "commands: Enter = record a waypoint | g l / g r = toggle a gripper | u = undo the last waypoint | "
    "q = check and save | h = help | Ctrl-C = quit without saving"
)
GuideHook = Callable[[int, dict[str, Arm]], None]

# exit codes of teach()
SAVED, SAVED_WITH_PROBLEMS, NOTHING_SAVED, INTERRUPTED = 0, 1, 2, 130


@dataclass
class TeachState:
    """The waypoints recorded so far and what each gripper was commanded to."""

    waypoints: list[Waypoint] = field(default_factory=list)
    grippers: dict[str, bool] = field(default_factory=dict)  # arm -> closed
    initial_grippers: dict[str, bool] = field(default_factory=dict)
    toggled_since_waypoint: set[str] = field(default_factory=set)


def gripper_closed(gripper: Gripper) -> bool:
    """Whether a gripper is closed now: it holds something or its opening is below CLOSED_WIDTH."""
    s = gripper.read_state()
    return bool(s.grasped) or s.width < CLOSED_WIDTH


def _fmt_xyz(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:+.3f}" for v in p) + ")"


def _problems(program: Program, bases: dict[str, np.ndarray]) -> tuple[list[str], list[str], float | None]:
    """(problems, notes, slow duration s) for the taught program: limits, then slow timing and safety."""
    from trajectories.safety import check_program
    from trajectories.timing import SLOW, TimingLimits, time_program

    problems = list(limit_violations(program))
    notes: list[str] = []
    try:
        timed = time_program(program, SLOW, limits=TimingLimits.panda())
    except (ValueError, RuntimeError) as e:
        problems.append(f"timing at slow failed: {e}")
        return problems, notes, None
    for s in timed.limited_segments():
        notes.append(f"{s.label()} takes {s.actual:.2f} s instead of {s.requested:.2f} s at slow (joint limits)")
    problems += [str(v) for v in check_program(timed, bases).violations]
    return problems, notes, timed.duration


def teach(
    arms: dict[str, Arm],
    grippers: dict[str, Gripper],
    kin: dict[str, Any],
    bases: dict[str, np.ndarray],
    inp: TextIO,
    out: TextIO,
    *,
    out_path: str | Path,
    name: str,
    category: Literal["dlo", "bdlo", "cloth", "any"] = "any",
    description: str = "",
    grip_dwell: float = 1.0,
    guide: GuideHook | None = None,
) -> int:
    """Run the teaching loop on connected devices, reading commands from ``inp``; returns an exit code.

    ``kin`` maps each arm to its kinematics (``tcp_pose(q)`` in the world frame), ``bases`` to its
    (4, 4) world <- base for the safety check. ``guide(step, arms)`` is called before each command
    is read (tests move fake arms with it). Exit codes: 0 saved, 1 saved with problems, 2 nothing
    saved (no waypoint), 130 interrupted (nothing saved).
    """
    state = TeachState()
    for arm in ARMS:
        state.grippers[arm] = state.initial_grippers[arm] = gripper_closed(grippers[arm])
    interactive = bool(getattr(inp, "isatty", lambda: False)())
    print(HELP, file=out)
    print("grippers now: " + ", ".join(f"{a} {'closed' if state.grippers[a] else 'open'}" for a in ARMS), file=out)
    step = 0
    try:
        while True:
            if guide is not None:
                guide(step, arms)
            step += 1
            if interactive:
                print("> ", end="", file=out, flush=True)
            line = inp.readline()
            if line == "":  # end of input: same as q
                print("end of input: saving", file=out)
                break
            cmd = line.strip().lower().split()
            if not cmd:
                _record(state, arms, kin, out, grip_dwell)
            elif cmd[0] == "q":
                break
            elif cmd[0] == "u":
                if state.waypoints:
                    state.waypoints.pop()
                    print(f"removed waypoint {len(state.waypoints)}; {len(state.waypoints)} left", file=out)
                else:
                    print("nothing to undo", file=out)
            elif cmd[0] == "g" and len(cmd) == 2 and cmd[1] in GRIPPER_NAMES:
                _toggle(state, grippers, GRIPPER_NAMES[cmd[1]], out)
            elif cmd[0] in ("h", "?", "help"):
                print(HELP, file=out)
            else:
                print(f"unknown command {line.strip()!r}; {HELP}", file=out)
    except KeyboardInterrupt:
        print(f"\ninterrupted: quit without saving ({len(state.waypoints)} waypoint(s) discarded)", file=out)
        return INTERRUPTED
    return _save(state, bases, out, Path(out_path), name, category, description)


def _record(state: TeachState, arms: dict[str, Arm], kin: dict[str, Any], out: TextIO, grip_dwell: float) -> None:
    """Append a waypoint at the arms' current joints with the grippers' commanded states."""
    q = {a: np.asarray(arms[a].read_state().q, dtype=np.float64) for a in ARMS}
    previous = state.waypoints[-1] if state.waypoints else None
    before = (
        {a: previous.grippers[a].state == "closed" for a in ARMS} if previous is not None else state.initial_grippers
    )
    changed = [a for a in ARMS if state.grippers[a] != before[a]]
    wp = Waypoint(
        left=[float(v) for v in q["left"]],
        right=[float(v) for v in q["right"]],
        grippers={a: GripperCommand(state="closed" if state.grippers[a] else "open") for a in ARMS},
        dwell=grip_dwell if changed else 0.0,
    )
    state.waypoints.append(wp)
    state.toggled_since_waypoint.clear()
    i = len(state.waypoints) - 1
    parts = []
    for a in ARMS:
        tcp = kin[a].tcp_pose(q[a])[:3, 3]
        g = "closed" if state.grippers[a] else "open"
        parts.append(f"{a} TCP {_fmt_xyz(tcp)} m gripper {g}{' (changes here)' if a in changed else ''}")
    print(f"waypoint {i}: " + " | ".join(parts), file=out)
    if previous is not None:
        moved = float(np.max(np.abs(wp.q() - previous.q())))
        if moved < 1e-3 and not changed:
            print(f"  note: waypoint {i} is where waypoint {i - 1} was (the arms did not move)", file=out)
    for msg in limit_violations(Program(name="taught", waypoints=[wp])):
        print(f"  warning: {msg.replace('waypoints[0]', f'waypoint {i}')}", file=out)


def _toggle(state: TeachState, grippers: dict[str, Gripper], arm: str, out: TextIO) -> None:
    """Command ``arm``'s gripper to the opposite state; it is recorded at the next waypoint."""
    closed = not state.grippers[arm]
    try:
        grippers[arm].command(closed)
    except DeviceError as e:
        print(f"error: {arm} gripper: {e} (state unchanged)", file=out)
        return
    state.grippers[arm] = closed
    state.toggled_since_waypoint.add(arm)
    print(f"{arm} gripper {'closing' if closed else 'opening'} (recorded at the next waypoint)", file=out)


def _save(
    state: TeachState, bases: dict[str, np.ndarray], out: TextIO, path: Path, name: str,
    category: Literal["dlo", "bdlo", "cloth", "any"], description: str,
) -> int:
    """Check the taught program, report, and save it (even with problems); returns the exit code."""
    if not state.waypoints:
        print("no waypoint recorded: nothing saved", file=out)
        return NOTHING_SAVED
    if state.toggled_since_waypoint:
        arms = " and ".join(sorted(state.toggled_since_waypoint))
        print(f"warning: the {arms} gripper toggle after the last waypoint is not recorded "
              "(press Enter before q to record it)", file=out)
    program = Program(name=name, description=description, category=category, waypoints=state.waypoints)
    problems, notes, duration = _problems(program, bases)
    for n in notes:
        print(f"note: {n}", file=out)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        save_program(program, path)
    except (OSError, ProgramError) as e:
        print(f"error: could not save {path}: {e}", file=out)
        return NOTHING_SAVED
    timing = f", {duration:.1f} s at slow" if duration is not None and math.isfinite(duration) else ""
    if problems:
        print(f"warning: {len(problems)} problem(s) found:", file=out)
        for p in problems:
            print(f"  {p}", file=out)
        print(f"warning: saved {path} anyway ({len(program.waypoints)} waypoints{timing}); fix it before use "
              f"(`trackdeform program validate {path}`)", file=out)
        return SAVED_WITH_PROBLEMS
    print(f"saved {path}: {len(program.waypoints)} waypoints{timing}, within the joint limits, "
          "no collision at slow", file=out)
    return SAVED


def teach_station(
    config: Any,  # noqa: ANN401 - orchestrator.config.Config
    inp: TextIO,
    out: TextIO,
    *,
    out_path: str | Path,
    name: str | None = None,
    category: Literal["dlo", "bdlo", "cloth", "any"] = "any",
    grip_dwell: float = 1.0,
    guide: GuideHook | None = None,
) -> int:
    """Connect the config's arms and grippers (a simulated station in mock mode), teach, disconnect."""
    from drivers.clock import RealClock, SimClock
    from orchestrator.station import Station

    objects = config.plan.objects
    obj = next((o for o in objects if o.category == category), objects[0])
    # a simulated station needs no wall time while teaching (and its physics stays cheap on a sim clock)
    clock = SimClock() if config.station.simulated else RealClock()
    station = Station(config, obj, clock)
    devices: list[tuple[str, Any]] = [
        *((f"{n} arm", station.arms[n]) for n in ARMS), *((f"{n} gripper", station.grippers[n]) for n in ARMS),
    ]
    connected: list[Any] = []
    try:
        for label, dev in devices:
            try:
                dev.connect()
            except DeviceError as e:
                print(f"error: {label}: could not connect: {e}", file=out)
                return NOTHING_SAVED
            connected.append(dev)
        where = f"simulated station with {obj.name}" if station.sim is not None else config.station.name
        print(f"teaching on {where}: both arms and grippers connected; the arms will not be commanded", file=out)
        return teach(
            station.arms, station.grippers, station.kin, station.bases, inp, out,
            out_path=out_path, name=name or Path(out_path).stem, category=category,
            description=f"taught on {config.station.name} on {time.strftime('%Y-%m-%d %H:%M')}",
            grip_dwell=grip_dwell, guide=guide,
        )
    finally:
        for dev in reversed(connected):
            try:
                dev.close()
            except Exception as e:  # noqa: BLE001 - closing must not hide the result
                print(f"warning: closing {dev!r} failed: {e}", file=out)
