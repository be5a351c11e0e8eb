"""``trackdeform program ...``: validate, time and preview waypoint programs.

``register(subparsers)`` adds the ``program`` command with the subcommands ``list``,
``validate FILE``, ``time FILE --speed ...``, ``preview FILE --speed ... --out plot.png`` and
``teach --config CONFIG --out FILE`` (record waypoints by hand-guiding the arms; see orchestrator.teach).
FILE is a program file (YAML/JSON) or the name of a library program (e.g. ``rope_swing``).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

SPEEDS = ("slow", "medium", "fast")


def _load(ref: str) -> Any:  # noqa: ANN401 - trajectories.program.Program, imported lazily
    from trajectories.program import load_program, resolve_program

    return load_program(resolve_program(ref))


def _timed(args: argparse.Namespace, speed: str) -> Any:  # noqa: ANN401 - TimedProgram
    from trajectories.timing import TimingLimits, speed_profile, time_program

    return time_program(_load(args.file), speed_profile(speed, args.fast_duration),
                        limits=TimingLimits.panda(args.safety_scale))


def timing_report(timed: Any) -> dict[str, Any]:  # noqa: ANN401 - TimedProgram
    """JSON-ready summary of a timed program: segments (requested/actual s, when each arm stops), totals."""
    segs = []
    for s in timed.segments:
        left_end, right_end = s.arm_end_times()
        segs.append({
            "index": s.index, "kind": s.kind, "to_waypoint": s.to_waypoint, "start": round(s.start, 6),
            "requested": round(s.requested, 6), "actual": round(s.actual, 9),
            "longer_than_requested": s.longer_than_requested,
            "left_end": round(left_end, 3), "right_end": round(right_end, 3),
            "acc_scale": s.acc_scale, "jerk_scale": s.jerk_scale,
        })
    return {
        "program": timed.program.name,
        "category": timed.program.category,
        "speed": timed.speed.name,
        "segment_duration": timed.speed.segment_duration,
        "safety_scale": timed.limits.safety_scale,
        "waypoints": len(timed.program.waypoints),
        "total": round(timed.duration, 6),
        "peak_velocity_ratio": round(timed.peak_velocity_ratio(), 4),
        "arms_end_together": all(abs(s["left_end"] - s["right_end"]) <= 1e-3 for s in segs if s["kind"] != "dwell"),
        "limited_segments": [s["index"] for s in segs if s["longer_than_requested"]],
        "segments": segs,
        "gripper_events": [
            {"time": round(e.time, 6), "arm": e.arm, "waypoint": e.waypoint, **e.command.model_dump(exclude_none=True)}
            for e in timed.gripper_events
        ],
    }


def cmd_list(args: argparse.Namespace) -> int:
    """Print the library programs with their category and size."""
    from trajectories.program import library_path, list_library, load_program

    for name in list_library():
        p = load_program(library_path(name))
        print(f"{name:20s} {p.category:6s} {len(p.waypoints)} waypoints  {p.description}")
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    """Load FILE, time it at every speed and run the safety checks; 0 when all pass."""
    from trajectories.program import ProgramError, ProgramUnreadable
    from trajectories.safety import check_program

    try:
        program = _load(args.file)
    except ProgramError as e:
        print(f"error: {e}" if isinstance(e, ProgramUnreadable) else e, file=sys.stderr)
        return 2 if isinstance(e, ProgramUnreadable) else 1
    print(f"{program.name} ({program.category}): {len(program.waypoints)} waypoints, within the joint limits")
    bad = 0
    for speed in SPEEDS:
        timed = _timed(args, speed)
        report = check_program(timed)
        longer = timed.limited_segments()
        status = "OK" if report.ok else f"{len(report.violations)} violation(s)"
        print(f"  {speed:6s} {timed.duration:7.3f} s  {status}")
        for s in longer:
            print(f"    {s.label()}: {s.actual:.3f} s instead of {s.requested:.3f} s (joint limits)")
        for v in report.violations:
            print(f"    {v}")
        bad += len(report.violations)
    return 0 if bad == 0 else 1


def cmd_time(args: argparse.Namespace) -> int:
    """Print per-segment requested/actual durations, the total and the peak velocity ratio."""
    from trajectories.program import ProgramError, ProgramUnreadable

    try:
        timed = _timed(args, args.speed)
    except (ProgramError, ValueError) as e:
        print(f"error: {e}" if isinstance(e, ProgramUnreadable) else e, file=sys.stderr)
        return 2 if isinstance(e, ProgramUnreadable) else 1
    rep = timing_report(timed)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"{rep['program']} at {rep['speed']} ({rep['segment_duration']:g} s per waypoint, "
          f"safety scale {rep['safety_scale']:g})")
    print(f"  {'seg':>3} {'kind':8} {'to wp':>5} {'requested':>10} {'actual':>10} {'left end':>9} {'right end':>9}")
    for s in rep["segments"]:
        flag = "  LONGER (limits)" if s["longer_than_requested"] else ""
        print(f"  {s['index']:>3} {s['kind']:8} {s['to_waypoint']:>5} {s['requested']:>10.4f} {s['actual']:>10.4f} "
              f"{s['left_end']:>9.3f} {s['right_end']:>9.3f}{flag}")
    print(f"  total {rep['total']:.4f} s, peak joint velocity {100 * rep['peak_velocity_ratio']:.1f} % of the limit, "
          f"arms end every segment together: {'yes' if rep['arms_end_together'] else 'NO'}")
    for e in rep["gripper_events"]:
        print(f"  t={e['time']:.3f} s: {e['arm']} gripper {e['state']} (waypoint {e['waypoint']})")
    return 0


def cmd_preview(args: argparse.Namespace) -> int:
    """Plot joint positions and velocities of both arms over time, waypoints marked, to ``--out``."""
    from trajectories.program import ProgramError

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("program preview needs matplotlib: pip install 'trackdeform3d[plot]' (or pip install matplotlib)",
              file=sys.stderr)
        return 2
    try:
        timed = _timed(args, args.speed)
    except (ProgramError, ValueError) as e:
        print(e, file=sys.stderr)
        return 1
    times, q, dq = timed.sample(100.0)
    wp_t = timed.waypoint_times()
    fig, axes = plt.subplots(2, 2, figsize=(13, 7), sharex=True)
    for col, arm in enumerate(("left", "right")):
        sl = slice(7 * col, 7 * col + 7)
        for row, (data, unit) in enumerate(((q, "rad"), (dq, "rad/s"))):
            ax = axes[row, col]
            ax.plot(times, data[:, sl], lw=1.2)
            for t in wp_t:
                ax.axvline(t, color="0.6", ls="--", lw=0.8)
            if row == 0:
                ax.plot(wp_t, timed.program.q()[:, sl], "k.", ms=5)
                ax.set_title(f"{arm} arm")
            ax.set_ylabel(f"{'q' if row == 0 else 'dq'} ({unit})")
            ax.grid(alpha=0.3)
        axes[1, col].set_xlabel("time (s)")
    axes[0, 1].legend([f"j{i + 1}" for i in range(7)], loc="upper right", fontsize=7, ncol=2)
    fig.suptitle(f"{timed.program.name} at {timed.speed.name} ({timed.speed.segment_duration:g} s per waypoint): "
                 f"{timed.duration:.2f} s, peak {100 * timed.peak_velocity_ratio():.0f} % of velocity limit")
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    plt.close(fig)
    print(f"wrote {args.out} ({len(times)} samples, {int(np.size(wp_t))} waypoints)")
    return 0


def cmd_teach(args: argparse.Namespace) -> int:
    """Teach a program on the config's station from stdin commands (see ``orchestrator.teach``)."""
    from orchestrator.config import ConfigError, load_config
    from orchestrator.teach import teach_station

    try:
        config = load_config(args.config)
    except ConfigError as e:
        print(e, file=sys.stderr)
        return 2
    return teach_station(config, sys.stdin, sys.stdout, out_path=args.out, name=args.name,
                         category=args.category, grip_dwell=args.grip_dwell)


def _speed_args(p: argparse.ArgumentParser, speed_required: bool) -> None:
    p.add_argument("file", help="program file (YAML/JSON) or library name, e.g. rope_swing")
    if speed_required:
        p.add_argument("--speed", choices=SPEEDS, required=True, help="slow 4 s, medium 2 s, fast 1-1.5 s per waypoint")
    p.add_argument("--fast-duration", type=float, default=1.25, help="seconds per waypoint at fast (1.0-1.5)")
    p.add_argument("--safety-scale", type=float, default=0.8, help="fraction of the Panda limits used (default 0.8)")


def register(subparsers: Any) -> None:  # noqa: ANN401 - argparse's private _SubParsersAction
    """Add ``program {list,validate,time,preview,teach}`` to the main CLI's ``subparsers``."""
    prog = subparsers.add_parser("program", help="validate, time and preview waypoint programs")
    sub = prog.add_subparsers(dest="program_command", metavar="SUBCOMMAND")
    prog.set_defaults(func=lambda args: (prog.print_help(), 2)[1])

    ls = sub.add_parser("list", help="list the shipped library programs")
    ls.set_defaults(func=cmd_list)

    v = sub.add_parser("validate", help="check limits, collisions and workspace at every speed")
    _speed_args(v, speed_required=False)
    v.set_defaults(func=cmd_validate)

    t = sub.add_parser("time", help="per-segment durations of a program at a speed")
    _speed_args(t, speed_required=True)
    t.add_argument("--json", action="store_true", help="machine-readable output")
    t.set_defaults(func=cmd_time)

    pv = sub.add_parser("preview", help="plot joint positions and velocities over time (needs matplotlib)")
    _speed_args(pv, speed_required=True)
    pv.add_argument("--out", required=True, help="image file, e.g. plot.png")
    pv.set_defaults(func=cmd_preview)

    te = sub.add_parser(
        "teach", help="record a program by hand-guiding the arms (Enter = waypoint, g l/g r, u, q)",
        description="Connect the station's arms and grippers (never commanded) and read commands from stdin: "
                    "Enter records a waypoint (both arms' joints and grippers), 'g l' / 'g r' toggles a gripper "
                    "(recorded at the next waypoint), 'u' undoes the last waypoint, 'q' or end of input checks "
                    "(limits, timing and collisions at slow) and saves (with a warning when problems are found), "
                    "Ctrl-C quits without saving. Franka Pandas: activate FCI and guide each arm with the two "
                    "guiding buttons at the flange (see orchestrator/teach.py).",
    )
    te.add_argument("--config", required=True, help="station config (YAML), e.g. configs/dual_panda_realsense.yaml")
    te.add_argument("--out", required=True, help="program file to write (.yaml or .json)")
    te.add_argument("--name", help="program name (default: the file name without extension)")
    te.add_argument("--category", choices=("dlo", "bdlo", "cloth", "any"), default="any",
                    help="object category the program is written for (default any)")
    te.add_argument("--grip-dwell", type=float, default=1.0,
                    help="seconds to hold still at a waypoint where a gripper changes (default 1.0)")
    te.set_defaults(func=cmd_teach)
