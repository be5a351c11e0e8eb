"""Live session commands: ``status`` (the health message), ``ctl`` (pause / resume / stop / skip), ``schema``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from orchestrator.config import DEFAULT_CONFIG

CTL_COMMANDS = ("pause", "resume", "stop", "skip")


def _client(args: argparse.Namespace) -> Any:
    """A client Bus to the session named by ``--config`` / ``--station`` / ``--connect``; raises RuntimeError."""
    from orchestrator.bus import local_endpoints, open_client
    from orchestrator.config import load_config

    config = load_config(args.config)
    endpoints = args.connect or config.bus.connect or local_endpoints(config.bus.listen)
    bus = open_client(config.bus, args.station or config.station.name, endpoints, args.timeout)
    bus.endpoints = endpoints
    return bus


def read_health(bus: Any, timeout: float) -> dict[str, Any] | None:
    """The session's health: a get on ``health`` (answered at once), else the next published one."""
    from tdcommon.wire import decode_json

    sub = bus.subscribe(bus.key("health"), ring=1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for payload in bus.get(bus.key("health"), timeout=min(2.0, max(0.1, deadline - time.monotonic()))):
            return decode_json(payload)
        s = sub.try_recv()
        if s is not None:
            return decode_json(s.payload.to_bytes())
        time.sleep(0.1)
    return None


def _fmt(v: Any, unit: str = "", nd: int = 1) -> str:
    return "-" if v is None else f"{v:.{nd}f}{unit}" if isinstance(v, float) else f"{v}{unit}"


def format_health(h: dict[str, Any]) -> str:
    """The health message as a few human lines."""
    run, ep, prog = h.get("run") or {}, h.get("episode") or {}, h.get("progress") or {}
    cam, js, w, kp, disk = (h.get(k) or {} for k in ("camera", "joint_states", "worker", "keypoints", "disk"))
    lines = [f"state     {h.get('state')}  (session {h.get('session_id')}, up {_fmt(h.get('uptime_s'), ' s')}, "
             f"{h.get('out_dir')})"]
    if run:
        where = ""
        if ep:
            where = (f", episode {ep.get('episode')}, frame {ep.get('frame')}/{ep.get('frames')} "
                     f"({100 * ep.get('fraction', 0):.0f} %)")
        lines.append(f"run       [{_fmt(run.get('run_index'))}] {run.get('label') or run.get('object')} "
                     f"(run {run.get('run_id')}){where}")
    lines.append(f"progress  {prog.get('runs_done', 0)} of {prog.get('runs_planned', '?')} runs done "
                 f"(pass {prog.get('plan_pass', 0) + 1}), recorded {_fmt(prog.get('recorded_s'), ' s')}"
                 + (f" of {prog['max_s']:.0f} s" if prog.get("max_s") else "")
                 + f", {prog.get('episodes_written', 0)} episodes finished, ETA {_fmt(h.get('eta_s'), ' s', 0)}")
    lines.append(f"camera    {_fmt(cam.get('rate_hz'), ' Hz')}, {cam.get('frames', 0)} frames, "
                 f"{cam.get('dropped', 0)} dropped; joint states {_fmt(js.get('rate_hz'), ' Hz')}")
    if w:
        lines.append(f"worker    {w.get('state')} (pid {w.get('pid')}), lag {_fmt(w.get('lag_s'), ' s', 2)}, "
                     f"{w.get('restarts', 0)} restarts" + (f"; {w['given_up']}" if w.get("given_up") else ""))
    else:
        lines.append("worker    none started by the session")
    if kp:
        rejected = ", ".join(f"{k} {n}" for k, n in sorted((kp.get("rejected") or {}).items())) or "none"
        lines.append(f"keypoints {kp.get('recorded', 0)} recorded, rejected: {rejected}")
    lines.append(f"disk      {_fmt(disk.get('free_gb'), ' GiB', 2)} free (stops below {disk.get('min_free_gb')}), "
                 f"time to full {_fmt(disk.get('time_to_full_s'), ' s', 0)}")
    for inc in h.get("incidents") or []:
        lines.append(f"incident  {inc.get('time')} {inc.get('kind')}: {inc.get('message')}")
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    """Print the running session's health (``<prefix>/<station>/health``)."""
    try:
        bus = _client(args)
    except RuntimeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        h = read_health(bus, args.timeout)
        if h is None:
            print(f"error: no health message on {bus.key('health')} via {bus.endpoints} within {args.timeout:g} s "
                  "(is a session running there?)", file=sys.stderr)
            return 1
        print(json.dumps(h, indent=2) if args.json else format_health(h))
        return 0
    finally:
        bus.close()


def cmd_ctl(args: argparse.Namespace) -> int:
    """Send a control command to the running session (a get on ``<prefix>/<station>/ctl/<command>``)."""
    from tdcommon.wire import decode_json

    try:
        bus = _client(args)
    except RuntimeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        key = bus.key("ctl", args.command)
        deadline = time.monotonic() + args.timeout
        replies: list[bytes] = []
        while not replies and time.monotonic() < deadline:  # the route to the queryable may take a moment
            replies = bus.get(key, timeout=min(2.0, max(0.1, deadline - time.monotonic())))
            if not replies:
                time.sleep(0.2)
        if not replies:
            print(f"error: no session answered on {key} via {bus.endpoints} within {args.timeout:g} s",
                  file=sys.stderr)
            return 2
        reply = decode_json(replies[0])
        print(json.dumps(reply) if args.json else f"{args.command}: {reply.get('message')} "
              f"(state {reply.get('state')})")
        return 0 if reply.get("ok") else 1
    finally:
        bus.close()


def cmd_schema(args: argparse.Namespace) -> int:
    """Print (or write) the JSON Schema of the live keypoint message."""
    from tdcommon.wire import KEYPOINTS_JSON_SCHEMA

    text = json.dumps(KEYPOINTS_JSON_SCHEMA, indent=2) + "\n"
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write(text)
    else:
        sys.stdout.write(text)
    return 0


def _bus_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="the session's config (prefix, station, endpoints)")
    p.add_argument("--station", help="station name (default: the config's)")
    p.add_argument("--connect", action="append", help="zenoh endpoint (default: the config's listen endpoints)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the session (default 10)")


def register(sub: Any) -> None:
    """Add the live-session subcommands to the main parser."""
    st = sub.add_parser("status", help="show a running session's health (state, run, rates, worker, disk)")
    _bus_args(st)
    st.set_defaults(func=cmd_status)

    c = sub.add_parser("ctl", help="control a running session: pause, resume, stop, skip")
    c.add_argument("command", choices=CTL_COMMANDS,
                   help="pause: after the current episode, arms held at rest; resume; stop; skip: end the current run")
    _bus_args(c)
    c.set_defaults(func=cmd_ctl)

    sc = sub.add_parser("schema", help="print the JSON Schema of the live keypoint message")
    sc.add_argument("--out", help="write it to this file instead")
    sc.set_defaults(func=cmd_schema)
