"""``trackdeform router``: a zenoh router (eclipse-zenoh's own router mode) for stations on several hosts.

No ``zenohd`` binary is needed: the Python package opens a session in router mode, which routes
between the clients and peers connected to it. TLS and access control come from the config's
``bus`` section, so the router is where a lab enforces who may publish or subscribe.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import Any

from orchestrator.config import DEFAULT_CONFIG, BusConfig


def router_config(bus: BusConfig, listen: list[str], connect: list[str]) -> Any:
    """A router-mode ``zenoh.Config``: the bus section's TLS/ACL with these endpoints, multicast scouting off."""
    import zenoh

    from orchestrator.zenoh_security import check_endpoints, zenoh_security_json5

    check_endpoints(bus.tls, listen, connect)
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps("router"))
    c.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    for key, value in zenoh_security_json5(bus.tls, bus.access_control).items():
        c.insert_json5(key, json.dumps(value))
    return c


def cmd_router(args: argparse.Namespace) -> int:
    """Run a zenoh router until SIGTERM/SIGINT."""
    import zenoh

    from orchestrator.config import load_config

    bus = load_config(args.config).bus if args.config else BusConfig()
    listen = args.listen or ["tcp/127.0.0.1:7447"]
    try:
        conf = router_config(bus, listen, args.connect or [])
    except ValueError as e:
        print(f"error: {args.config or 'router'}: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        session = zenoh.open(conf)
    except Exception as e:  # zenoh's ZError names the endpoint that failed
        print(f"error: cannot open the zenoh router on {listen}: {e}", file=sys.stderr)
        return 2
    try:
        print(f"zenoh router {session.zid()} listening on {listen}", file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.seconds if args.seconds else None
        while not stop.wait(0.2):
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        session.close()
    print("zenoh router stopped", file=sys.stderr)
    return 0


def register(sub: Any) -> None:
    """Add ``router`` to the ``trackdeform`` subcommands."""
    r = sub.add_parser("router", help="run a zenoh router (daemon, worker and subscribers on several hosts)")
    r.add_argument("--listen", action="append",
                   help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447, loopback only)")
    r.add_argument("--connect", action="append", help="another router to connect to (repeatable)")
    r.add_argument("--config", help=f"station config whose bus section gives TLS and access control (e.g. "
                                    f"{DEFAULT_CONFIG.name}); without it: plain TCP, no ACL")
    r.add_argument("--seconds", type=float, help="stop after this long (tests)")
    r.set_defaults(func=cmd_router)
