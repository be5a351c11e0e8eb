"""The ``trackdeform`` command line: demo, run, validate, program, worker, watch, track, inspect, report, eval,
retrack."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from orchestrator.config import DEFAULT_CONFIG, Config, ConfigError, load_config

log = logging.getLogger("trackdeform")
DEMO_OBJECTS = ("rope", "branched_rope", "cloth")
FRESH_HELP = (
    "start the plan over instead of resuming: the output folder's journal is moved aside "
    "(session.journal.<time>.jsonl), its episodes are kept and numbering continues"
)


def _install_signal_handlers(stop: threading.Event, finishing: threading.Event | None = None) -> None:
    """First SIGINT/SIGTERM: finish the current frame, close episodes, stop. Second: abort the recording,
    unless the session is already writing its last files and the summary (``finishing``): those finish."""

    def handler(signum: int, _frame: Any) -> None:
        if stop.is_set():
            if finishing is not None and finishing.is_set():
                print(f"\n{signal.Signals(signum).name}: already stopping; writing the last episode files and "
                      "summary.json", file=sys.stderr)
                return
            raise KeyboardInterrupt
        print(f"\n{signal.Signals(signum).name}: stopping after the current frame (again to abort)", file=sys.stderr)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def _session_dir(config: Config, out: str | None, fresh: bool = False) -> Path:
    """``--out``, else the newest unfinished session folder of this plan (resume), else a new timestamped one."""
    if out:
        return Path(out)
    if not fresh:
        from orchestrator.journal import find_resumable

        found = find_resumable(Path(config.output.directory), config)
        if found is not None:
            print(f"resuming the unfinished session in {found} (--fresh starts a new folder)", file=sys.stderr)
            return found
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path(config.output.directory) / f"{stamp}_{config.station.name}"


def run_session(
    config: Config,
    out_dir: Path,
    *,
    max_seconds: float | None,
    loop: bool,
    with_worker: bool,
    quiet: bool = False,
    fresh: bool = False,
) -> int:
    """Open the folder's journal (resume) and the bus; run a session (it supervises the tracking worker if asked);
    print the summary."""
    from drivers.clock import RealClock, SimClock
    from orchestrator.bus import Bus
    from orchestrator.journal import Journal, JournalError
    from orchestrator.progress import Progress
    from orchestrator.session import Session

    try:  # before anything starts: another plan's journal is refused with the way out
        journal = Journal.open(out_dir, config, fresh=fresh)
    except JournalError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stop, finishing = threading.Event(), threading.Event()
    _install_signal_handlers(stop, finishing)
    progress = Progress(enabled=not quiet)
    if journal.moved_aside is not None:
        progress.message(f"--fresh: moved the previous journal aside to {journal.moved_aside.name}; "
                         "its episodes stay and numbering continues")
    clock = SimClock() if config.clock == "sim" else RealClock()
    bus = None
    try:
        if config.bus.enabled:
            try:
                bus = Bus(config.bus, config.station.name)
            except RuntimeError as e:
                print(f"error: {e}\nhint: another session may be using the port; pass --port", file=sys.stderr)
                return 2
        progress.message(f"recording to {out_dir}")
        session = Session(config, out_dir, clock, bus=bus, progress=progress, stop_event=stop, journal=journal,
                          with_worker=with_worker and bus is not None and config.tracking.enabled,
                          finishing=finishing)
        try:
            summary = session.run(max_seconds=max_seconds, loop=loop)
        except KeyboardInterrupt:
            print(f"error: {out_dir}: aborted by a second signal; summary.json says what was written "
                  f"(unfinished files: `trackdeform recover {out_dir}`)", file=sys.stderr)
            return 2
    finally:
        journal.close()  # the session closes it too; this covers a failure before it ran
        if bus is not None:
            bus.close()
    print(summary.text())
    recorded_or_resumed = summary.episodes or summary.runs_already_done  # nothing left to do is a success
    return 0 if recorded_or_resumed and not summary.runs_failed and not summary.errors else 1


# ---------------------------------------------------------------------- commands
def cmd_demo(args: argparse.Namespace) -> int:
    """A mock collection session in real time (or simulated time with --sim-time)."""
    overrides: dict[str, Any] = {}
    if args.sim_time:
        overrides["clock"] = "sim"
    if args.port:
        overrides["bus.listen"] = [f"tcp/127.0.0.1:{args.port}"]
    config = load_config(args.config, overrides)
    objects = [o for o in config.plan.objects if o.name == args.object]
    if not objects:
        names = [o.name for o in config.plan.objects]
        print(f"error: {args.config}: no object named {args.object!r} in plan.objects (have {names})", file=sys.stderr)
        return 2
    data = config.model_dump()
    data["plan"]["objects"] = [o.model_dump() for o in objects]
    if args.no_tracking:
        data["tracking"]["enabled"] = False
    config = Config.model_validate(data)
    out = Path(args.out) if args.out else Path("runs") / f"demo-{time.strftime('%Y%m%d-%H%M%S')}"
    return run_session(config, out, max_seconds=args.seconds, loop=True, with_worker=not args.no_tracking,
                       fresh=args.fresh)


def cmd_run(args: argparse.Namespace) -> int:
    """Run a config's plan (the nightly job)."""
    overrides: dict[str, Any] = {}
    if args.connect:
        overrides["bus.connect"] = args.connect
    config = load_config(args.config, overrides)
    out = _session_dir(config, args.out, fresh=args.fresh)
    return run_session(config, out, max_seconds=args.seconds, loop=False, with_worker=not args.no_tracking,
                       fresh=args.fresh)


def cmd_validate(args: argparse.Namespace) -> int:
    """Check a config and everything it references (programs, at every planned speed)."""
    from orchestrator.programs import check_config_programs

    config = load_config(args.config)
    print(f"{args.config}: configuration is valid")
    st = config.station
    print(f"  station {st.name}: arms {st.left.arm.type}/{st.right.arm.type}, grippers "
          f"{st.left.gripper.type}/{st.right.gripper.type}, camera {st.camera.type} "
          f"{st.camera.width}x{st.camera.height}@{st.camera.fps:g}")
    problems = check_config_programs(config, out=sys.stdout)
    if problems:
        print(f"{args.config}: {problems} problem(s) found", file=sys.stderr)
        return 1
    print(f"{args.config}: OK")
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    """Print what episode files (or the episodes of folders) hold: metadata, message counts per channel, rates,
    gaps, drops and keypoint coverage (orchestrator.episode_stats), and a summary over several files.

    A file that cannot be read gets one ``error: FILE: ...`` line on stderr and the next file is
    shown; the exit code is 2 when any file failed.
    """
    from orchestrator.episode_stats import episode_stats, expand_inputs, folder_summary, format_summary

    failed = 0
    stats: list[dict[str, Any]] = []
    metas: list[dict[str, Any]] = []
    files = expand_inputs(args.files)
    for path in files:
        try:
            info = _inspect_one(path)
            if info is not None:
                info["stats"] = episode_stats(path)
        except Exception as e:  # any broken file: one line naming it, then the next file
            print(f"error: {path}: {_unreadable(e)}", file=sys.stderr)
            failed += 1
            continue
        if info is None:
            print(f"{path}: no summary (unfinished file? run `trackdeform recover {path.parent}`)")
            continue
        stats.append(info["stats"])
        metas.append(info.pop("_metadata"))
        print(json.dumps(info, indent=2) if args.json else _pretty(info), flush=True)
    if len(stats) > 1:
        total = folder_summary(stats, metas)
        print(json.dumps({"summary": total}, indent=2) if args.json else format_summary(total))
    if failed:
        print(f"error: {failed} of {len(files)} file(s) could not be read", file=sys.stderr)
        return 2
    return 0


def _unreadable(e: BaseException) -> str:
    """The one-line reason an episode file could not be read."""
    if isinstance(e, FileNotFoundError):
        return "no such file"
    if isinstance(e, IsADirectoryError):
        return "is a folder (pass the .mcap files in it)"
    if isinstance(e, OSError):
        return f"cannot read: {e.strerror or e}"
    if isinstance(e, ValueError) and str(e).startswith("the file is empty"):
        return str(e)
    return f"not a readable MCAP episode file ({type(e).__name__}: {e})"


def _inspect_one(path: Path) -> dict[str, Any] | None:
    """What :func:`cmd_inspect` shows of one file; None for a file without a summary (unfinished)."""
    from mcap.reader import make_reader

    from tdrecord.episodes import merge_metadata

    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            raise ValueError("the file is empty (0 bytes)")
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            return None
        meta = merge_metadata(reader.iter_metadata()) or {}
    st = summary.statistics
    return {
        "file": str(path),
        "duration_s": (st.message_end_time - st.message_start_time) / 1e9,
        "channels": {summary.channels[c].topic: n for c, n in sorted(st.channel_message_counts.items())},
        "metadata": {k: v for k, v in meta.items() if k not in ("calibration", "segments")},
        "_metadata": meta,
    }


def _pretty(info: dict[str, Any]) -> str:
    lines = [f"{info['file']}  ({info['duration_s']:.2f} s)"]
    lines += [f"  {topic:32s} {n:6d} messages" for topic, n in info["channels"].items()]
    lines += [f"  {k} = {json.dumps(v)}" for k, v in info["metadata"].items()]
    if "stats" in info:
        from orchestrator.episode_stats import format_stats

        lines += format_stats(info["stats"])
    return "\n".join(lines)


def cmd_recover(args: argparse.Namespace) -> int:
    """Recover or quarantine unfinished ``.mcap.active`` files in a folder no live session holds.

    2 for a missing folder or one a live session holds (nothing is touched), 1 when a file could
    not be recovered (the line says why: e.g. too little free space), else 0.
    """
    from orchestrator.journal import FolderLock, JournalError
    from orchestrator.recovery import recover_active

    directory = Path(args.directory)
    if not directory.is_dir():
        print(f"error: {directory}: no such folder", file=sys.stderr)
        return 2
    try:
        with FolderLock(directory):
            results = recover_active(directory)
    except JournalError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for path, outcome in results:
        print(f"{path}: {outcome}")
    if not results:
        print(f"{args.directory}: nothing to recover")
    return 1 if any(outcome.startswith("not recovered") for _, outcome in results) else 0


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every subcommand."""
    p = argparse.ArgumentParser(
        prog="trackdeform",
        description="Unattended dual-arm RGB-D collection of deformable-object datasets with TrackDeform3D tracking.",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser("demo", help="run a mock collection session (simulated arms, camera and object)")
    d.add_argument("--object", choices=DEMO_OBJECTS, default="rope", help="object to simulate (default rope)")
    d.add_argument("--seconds", type=float, default=20.0, help="seconds to record (whole 5 s episodes; default 20)")
    d.add_argument("--out", help="output folder (default runs/demo-<time>)")
    d.add_argument("--config", default=str(DEFAULT_CONFIG), help="mock config (default configs/mock.yaml)")
    d.add_argument("--sim-time", action="store_true", help="simulated time: as fast as the CPU allows")
    d.add_argument("--port", type=int, help="zenoh TCP port on 127.0.0.1 (default from the config)")
    d.add_argument("--no-tracking", action="store_true", help="do not start the tracking worker")
    d.add_argument("--fresh", action="store_true", help=FRESH_HELP)
    d.set_defaults(func=cmd_demo)

    r = sub.add_parser("run", help="run the plan of a station config")
    r.add_argument("config", help="station + plan YAML")
    r.add_argument("--out", help="output folder (default <output.directory>/<time>_<station>)")
    r.add_argument("--seconds", type=float, help="stop after this much recording")
    r.add_argument("--no-tracking", action="store_true", help="do not start the tracking worker")
    r.add_argument("--connect", action="append", help="zenoh endpoint to connect to, e.g. a zenohd router (repeatable)")
    r.add_argument("--fresh", action="store_true", help=FRESH_HELP + "; without --out: a new folder")
    r.set_defaults(func=cmd_run)

    v = sub.add_parser("validate", help="check a config and the programs it references")
    v.add_argument("config")
    v.set_defaults(func=cmd_validate)

    i = sub.add_parser("inspect", help="show what episode files hold: channels, metadata, rates, gaps, drops, "
                       "keypoint coverage")
    i.add_argument("files", nargs="+", metavar="FILE|FOLDER")
    i.add_argument("--json", action="store_true")
    from orchestrator.episode_stats import pipe_safe

    i.set_defaults(func=pipe_safe(cmd_inspect))

    rc = sub.add_parser("recover", help="recover unfinished episode files after a crash")
    rc.add_argument("directory")
    rc.set_defaults(func=cmd_recover)

    for module in ("orchestrator.cli_program", "orchestrator.cli_tracking", "orchestrator.cli_devices",
                   "orchestrator.cli_live", "orchestrator.report", "orchestrator.cli_eval", "orchestrator.export",
                   "orchestrator.cli_router", "orchestrator.retrack"):
        try:
            mod = __import__(module, fromlist=["register"])
        except ModuleNotFoundError as e:
            if e.name != module:
                raise
            continue
        mod.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``trackdeform`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `trackdeform inspect ... | head`: the reader left; not an error of ours
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the interpreter's final flush does not fail again
        return 0


if __name__ == "__main__":
    sys.exit(main())
