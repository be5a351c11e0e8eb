"""Camera -> live keypoints on zenoh: latency p50 / p99, a replayed 1280x720 camera, the worker in its own process.

The mock station records a few seconds of the rope program once (simulated time, 1280x720, no bus);
the benchmark then replays those frames at the camera rate as the session would: this process is the
zenoh router, announces the run, publishes each frame and the joint state nearest it, and a separate
client session (routed like any outside subscriber) receives the worker's keypoints. Latency is from
the frame's publication (the replayed camera costs nothing) to the keypoints of that frame arriving.
Frames the worker skips while busy (ring channel, newest wins) have no latency; their share is printed.
The replay runs forward and backward so the object moves continuously. Target p99 <= 50 ms.

Run: .venv/bin/python benchmarks/latency.py [--seconds 30] [--record 4] [--port 7481]   (prints figures)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drivers.clock import SimClock
from orchestrator.bus import Bus
from orchestrator.config import DEFAULT_CONFIG, Config, load_config
from orchestrator.session import Session
from tdcommon.types import RGBDFrame
from tdcommon.wire import decode_json, encode_frame, encode_json, run_announcement
from tdrecord import read_episodes


def config(port: int, width: int, height: int) -> Config:
    """The mock config, rope only, one camera size, on ``tcp/127.0.0.1:<port>``."""
    cfg = load_config(DEFAULT_CONFIG, {"clock": "sim", "station.camera.width": width,
                                       "station.camera.height": height, "bus.listen": [f"tcp/127.0.0.1:{port}"]})
    data = cfg.model_dump()
    data["plan"]["objects"] = [o for o in data["plan"]["objects"] if o["name"] == "rope"]
    return Config.model_validate(data)


def record(cfg: Config, out: Path, seconds: float) -> Path:
    """Record ``seconds`` of the rope program in simulated time (no bus, no tracking)."""
    data = cfg.model_dump()
    data["bus"]["enabled"] = False
    data["tracking"]["enabled"] = False
    data["plan"]["episode_seconds"] = seconds
    Session(Config.model_validate(data), out, SimClock()).run(max_seconds=seconds, loop=True)
    return out


def percentile(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="replay this long (default 30)")
    ap.add_argument("--record", type=float, default=4.0, help="seconds of frames to render once (default 4)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--port", type=int, default=7481)
    ap.add_argument("--warmup", type=float, default=5.0, help="seconds after the first keypoints not counted")
    args = ap.parse_args()
    cfg = config(args.port, args.width, args.height)
    tmp = Path(tempfile.mkdtemp(prefix="latency-"))
    t0 = time.monotonic()
    seq = read_episodes(record(cfg, tmp / "rec", args.record))
    frames: list[RGBDFrame] = list(seq.frames)
    print(f"rendered {len(frames)} frames {args.width}x{args.height} once in {time.monotonic() - t0:.1f} s")
    states = []
    for i in range(len(frames)):
        st = {a: {"q": getattr(seq, f"q_{a}")[i].tolist(), "dq": [0.0] * 7,
                  "gripper_width": float(getattr(seq, f"gripper_width_{a}")[i]),
                  "grasped": bool(getattr(seq, f"grasped_{a}")[i])} for a in ("left", "right")}
        states.append(encode_json({**st, "stamp": 0.0}))
    order = [*range(len(frames)), *range(len(frames) - 2, 0, -1)]  # forward and back: continuous motion

    session_id = "latency-bench"
    cfg_path = tmp / "worker_config.json"
    cfg_path.write_text(json.dumps(cfg.model_dump(mode="json")))
    with Bus(cfg.bus, cfg.station.name) as bus:  # the session's router
        sent: dict[int, float] = {}
        got: dict[int, tuple[float, float, str]] = {}
        client = Bus(cfg.bus, cfg.station.name, listen=False, connect=[f"tcp/127.0.0.1:{args.port}"])

        def on_kp(sample: object) -> None:
            t = time.perf_counter()
            m = decode_json(sample.payload.to_bytes())  # type: ignore[attr-defined]
            got[m["frame_number"]] = (t, float(m.get("processing_ms", np.nan)), m["status"])

        client.subscribe(client.key("keypoints"), callback=on_kp)
        run = {"object": "rope", "category": "dlo", "program": "rope_swing", "speed": "medium", "run_index": 0,
               "n_keypoints": None}
        announcement = encode_json(run_announcement(session_id=session_id, run_id="R", run=run, stamp=time.time()))
        bus.queryable(bus.key("session", "run"), lambda q: q.reply(q.key_expr, announcement))
        worker = subprocess.Popen([sys.executable, "-m", "orchestrator.worker", str(cfg_path), "--connect",
                                   f"tcp/127.0.0.1:{args.port}", "--session-id", session_id,
                                   "--parent-pid", str(os.getpid())], stderr=subprocess.PIPE, text=True)
        alive: list[str] = []
        bus.watch_liveliness(bus.key("worker", "alive", "**"), lambda s: alive.append(str(s.kind)))
        while not any(k.endswith("PUT") for k in alive):
            if worker.poll() is not None:
                print(worker.stderr.read())
                return 1
            time.sleep(0.1)
        print(f"worker ready after {time.monotonic() - t0:.1f} s")
        bus.put(bus.key("session", "run"), announcement)
        frame_key, state_key = bus.key("cam", "cam0", "frame"), bus.key("arms", "state")
        period = 1.0 / cfg.station.camera.fps
        n, t_next, t_end, first_kp = 0, time.perf_counter(), None, None
        while t_end is None or time.perf_counter() < t_end:
            src = frames[order[n % len(order)]]
            stamp = n * period
            f = RGBDFrame(src.color, src.depth, src.depth_scale, src.intrinsics, stamp, time.time(), n,
                          src.ground_truth)
            payload = encode_frame(f, seq.T_world_cam, "cam0", {**run, "run_id": "R"})
            bus.put(state_key, states[order[n % len(order)]])
            sent[n] = time.perf_counter()
            bus.put(frame_key, payload)
            n += 1
            if first_kp is None and got:
                first_kp = n
                t_end = time.perf_counter() + args.warmup + args.seconds
            t_next += period
            time.sleep(max(0.0, t_next - time.perf_counter()))
        time.sleep(1.0)
        worker.terminate()
        _, err = worker.communicate(timeout=30)
        client.close()
    skip = first_kp + int(args.warmup * cfg.station.camera.fps)
    fns = np.array(sorted(k for k in got if k >= skip and k in sent))
    lat = np.array([(got[k][0] - sent[k]) * 1e3 for k in fns])
    proc = np.array([got[k][1] for k in fns])
    counted = n - skip
    tracked = sum(got[k][2] in ("init", "tracking", "degraded") for k in fns)
    print(f"frames published {counted} (after {args.warmup:g} s warm-up), keypoint sets {len(fns)} "
          f"({100 * len(fns) / max(1, counted):.0f} % of frames; the worker takes the newest when free), "
          f"tracked {tracked}")
    print(f"camera -> keypoints latency ms: p50 {percentile(lat, 50):.1f}  p90 {percentile(lat, 90):.1f}  "
          f"p99 {percentile(lat, 99):.1f}  max {percentile(lat, 100):.1f}   (target p99 <= 50)")
    rest = lat - proc
    print(f"worker processing ms: p50 {percentile(proc, 50):.1f}  p99 {percentile(proc, 99):.1f};  "
          f"transport + decode + waiting for the busy worker ms: p50 {percentile(rest, 50):.1f}  "
          f"p99 {percentile(rest, 99):.1f}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; worker: {err.strip().splitlines()[-1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
