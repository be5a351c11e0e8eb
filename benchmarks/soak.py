"""Soak test: a real-time mock collection session (``trackdeform run`` as a subprocess) with faults injected
at intervals, then an audit of the dataset it wrote.

    PYTHONPATH=$PWD python benchmarks/soak.py --minutes 5

Faults (times are fractions of the soak, so every length gets each one once):

- worker kill: ``kill -9`` of the tracking worker (the daemon's child); the session's supervisor must restart it;
- camera stall of 3 s and an arm reflex (recoverable): scheduled through the fake devices' config
  (``station.camera.stalls`` / ``station.left.arm.faults``, wall-clock times, mock only);
- disk nearly full: when root, the output folder is a tmpfs mounted here and a filler file leaves less
  than ``output.min_free_gb`` free for a while (the session pauses, ``on_low_disk: pause``); otherwise skipped;
- malformed bus messages: garbage, 2-component points and a forged run id on the session's keypoints key,
  from a zenoh client;
- daemon kill -9, then the same command again on the same folder (resume).

Printed: episodes written, frames lost outside injected faults (frame-number gaps inside episodes that do
not overlap a fault window), incidents from events.jsonl / summary.json, CPU and RSS of the daemon over
time, and whether every planned run is journaled ``done`` exactly once with no duplicated episode.
Loopback only, a free port, bounded (the plan is sized to ``--minutes``; a hard deadline stops it), and
cleans up (kills its process groups, unmounts, removes the folder unless ``--keep``).

One script (~560 lines) on purpose: the fault schedule, the processes it drives and the audit read the
same session folder and timeline.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from orchestrator.config import Config, load_config  # noqa: E402
from orchestrator.journal import read_journal, record_key, run_key  # noqa: E402
from orchestrator.plan import build_plan  # noqa: E402
from tdrecord.episodes import read_episode_metadata  # noqa: E402

PASS_SECONDS = 48.0  # one pass over configs/mock.yaml's plan at medium speed (8 episodes of 5 s + set-up), s
EPISODE_BYTES = 40e6  # a 5 s 640x480 mock episode is ~36 MB; sizes the tmpfs
STARTUP_SECONDS = 8.0  # launch to the first recorded frame (worker start), s
MIN_FREE_GB = 0.25  # the soak config's output.min_free_gb
DISK_FULL_SECONDS = 12.0  # how long the filler file stays
STALL_SECONDS = 3.0
SAMPLE_SECONDS = 5.0  # CPU / RSS sampling period, s
WORKER_START_SECONDS = 10.0  # a restarted worker's imports and tracker set-up load both cores this long, s
# When each fault fires, as a fraction of the soak's length.
SCHEDULE = (("worker_kill", 0.12), ("camera_stall", 0.25), ("arm_reflex", 0.38), ("malformed_bus", 0.50),
            ("disk_full", 0.62), ("daemon_kill", 0.78))
CLK_TCK = os.sysconf("SC_CLK_TCK")


@dataclass
class Fault:
    """One injected fault: its kind, when it was done and the window (CLOCK_MONOTONIC, s) it may lose frames in."""

    kind: str
    at_wall: float
    window: tuple[float, float] = (0.0, 0.0)
    note: str = ""
    done: bool = False
    skipped: str = ""


@dataclass
class Sample:
    t: float
    pid: int
    cpu_s: float
    rss_mb: float
    worker_cpu_s: float | None
    worker_rss_mb: float | None
    render_pid: int | None  # the mock camera's render process (drivers/fake/render_process.py)
    render_cpu_s: float | None
    render_rss_mb: float | None
    load1: float  # the machine's 1-minute load average (it is shared)


@dataclass
class Soak:
    minutes: float
    work: Path
    out: Path
    config_path: Path
    port: int
    log: Path
    faults: list[Fault] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    daemons: list[subprocess.Popen[bytes]] = field(default_factory=list)
    daemon_rcs: list[int | None] = field(default_factory=list)
    mounted: bool = False
    tmpfs_fraction: float = 0.5  # the largest share of available memory the dataset's tmpfs may take
    worker_pids: set[int] = field(default_factory=set)


# ---------------------------------------------------------------------- processes
def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def children(pid: int) -> list[int]:
    """Direct child pids of ``pid`` (every thread's children file)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def child_pid(daemon: int, name: bytes) -> int | None:
    """The daemon's child whose command line holds ``name`` (b"orchestrator.worker", b"render_process")."""
    for c in children(daemon):
        try:
            cmd = Path(f"/proc/{c}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if name in cmd:
            return c
    return None


def worker_pid(daemon: int) -> int | None:
    """The tracking worker among the daemon's children."""
    return child_pid(daemon, b"orchestrator.worker")


def proc_usage(pid: int) -> tuple[float, float] | None:
    """(user + system CPU s, RSS MB) of ``pid`` from /proc, None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()
    cpu = (int(fields[11]) + int(fields[12])) / CLK_TCK
    rss_kb = next((int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")), 0)
    return cpu, rss_kb / 1024.0


def alive(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


# ---------------------------------------------------------------------- set-up
def write_config(soak: Soak, t0: float, final: bool) -> Config:
    """A copy of configs/mock.yaml: plan sized to the soak, a free port, low-disk pause, scheduled device faults."""
    data = yaml.safe_load((REPO / "configs" / "mock.yaml").read_text())
    seconds = soak.minutes * 60.0
    data["plan"]["repeats"] = max(1, round(seconds / PASS_SECONDS))
    data["bus"]["listen"] = [f"tcp/127.0.0.1:{soak.port}"]
    data.setdefault("output", {}).update(min_free_gb=MIN_FREE_GB, on_low_disk="pause", low_disk_poll_seconds=1.0)
    data.setdefault("tracking", {})["final"] = final
    at = {kind: t0 + frac * seconds for kind, frac in SCHEDULE}
    data["station"]["camera"]["stalls"] = [{"at_wall": at["camera_stall"], "seconds": STALL_SECONDS}]
    data["station"]["left"]["arm"]["faults"] = [{"at_wall": at["arm_reflex"], "kind": "reflex"}]
    soak.faults = [Fault(kind, at[kind]) for kind, _ in SCHEDULE]
    soak.config_path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_config(soak.config_path)


def mount_tmpfs(soak: Soak, config: Config) -> str:
    """Mount a tmpfs sized to the plan on the output folder (root only); '' or the reason it was not."""
    if os.geteuid() != 0:
        return "not root: cannot mount a tmpfs (no simulated quota either: the session reads real free space)"
    episodes = len(build_plan(config.plan)) * 3 + 4
    size = int(episodes * EPISODE_BYTES + 1.5e9)
    avail = next(int(line.split()[1]) * 1024 for line in Path("/proc/meminfo").read_text().splitlines()
                 if line.startswith("MemAvailable:"))
    if size > avail * soak.tmpfs_fraction:
        return (f"a {size / 1e9:.1f} GB tmpfs would take over {soak.tmpfs_fraction:.0%} of the {avail / 1e9:.1f} GB "
                "of free memory (--tmpfs-fraction)")
    soak.out.mkdir(parents=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(soak.out)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        return f"mount -t tmpfs failed: {r.stderr.strip()}"
    soak.mounted = True
    print(f"output on a {size / 1e9:.1f} GB tmpfs at {soak.out}")
    return ""


def launch(soak: Soak) -> subprocess.Popen[bytes]:
    """Start (or resume: the same command on the same folder) the daemon in its own process group."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "orchestrator.cli", "run", str(soak.config_path), "--out", str(soak.out)]
    with soak.log.open("ab") as log:
        p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    soak.daemons.append(p)
    return p


# ---------------------------------------------------------------------- faults
def inject(soak: Soak, f: Fault, daemon: subprocess.Popen[bytes], config: Config) -> subprocess.Popen[bytes]:
    """Do fault ``f`` now; returns the daemon process (a new one after daemon_kill)."""
    now = time.monotonic()
    f.done = True
    if f.kind == "worker_kill":
        pid = worker_pid(daemon.pid)
        if pid is None:
            f.skipped = "no tracking worker running at that moment"
            return daemon
        os.kill(pid, signal.SIGKILL)
        restarted = wait_for(lambda: (w := worker_pid(daemon.pid)) is not None and w != pid, 60.0)
        f.window = (now, time.monotonic() + WORKER_START_SECONDS)
        f.note = f"killed worker pid {pid}; " + (f"new worker pid {worker_pid(daemon.pid)} after "
                                                 f"{time.monotonic() - now:.1f} s" if restarted else
                                                 "NOT restarted within 60 s")
    elif f.kind in ("camera_stall", "arm_reflex"):  # scheduled in the device config; the window is known
        length = STALL_SECONDS if f.kind == "camera_stall" else 15.0  # a reflex cuts the episode, run retried
        f.window = (now - 0.5, now + length + 1.0)
        f.note = "scheduled through the fake devices' config (" + (
            "camera.stalls" if f.kind == "camera_stall" else "left.arm.faults") + ")"
    elif f.kind == "malformed_bus":
        f.note = publish_malformed(soak, config)
        f.window = (now, now + 1.0)
    elif f.kind == "disk_full":
        if not soak.mounted:
            f.skipped = "no tmpfs (see above)"
            return daemon
        filler = soak.out / "soak_filler.bin"
        fill = 0
        block = b"\0" * (1 << 24)
        with filler.open("wb", buffering=0) as fh:  # unbuffered real bytes (a sparse file takes no tmpfs pages)
            # fill until less than half of min_free_gb is left; the session writes meanwhile, so the free
            # space is read again for every block and a disk that fills first just ends the filling
            while True:
                st = os.statvfs(soak.out)
                left = st.f_bavail * st.f_frsize - int(MIN_FREE_GB * 1e9 / 2)
                if left <= 0:
                    break
                try:
                    fill += fh.write(block[:min(left, len(block))]) or 0
                except OSError as e:
                    if e.errno != errno.ENOSPC:
                        raise
                    break
        time.sleep(DISK_FULL_SECONDS)
        filler.unlink()
        f.window = (now, time.monotonic() + 8.0)
        f.note = f"filled {fill / 1e9:.2f} GB (free below {MIN_FREE_GB} GB) for {DISK_FULL_SECONDS:.0f} s"
    elif f.kind == "daemon_kill":
        worker = worker_pid(daemon.pid)
        os.kill(daemon.pid, signal.SIGKILL)
        daemon.wait()
        soak.daemon_rcs.append(daemon.returncode)
        worker_gone = worker is None or wait_for(lambda: not alive(worker), 10.0)
        daemon = launch(soak)
        f.window = (now, time.monotonic() + STARTUP_SECONDS + 20.0)
        f.note = (f"killed daemon pid {soak.daemons[-2].pid}; its worker "
                  + ("exited with it" if worker_gone else f"pid {worker} STILL ALIVE 10 s later")
                  + f"; resumed as pid {daemon.pid}")
    return daemon


def publish_malformed(soak: Soak, config: Config) -> str:
    """Garbage, a 2-component-point message and a forged run id on the keypoints key, from a zenoh client."""
    from orchestrator.bus import open_client

    events = read_events(soak.out)
    session_id = next((e["session_id"] for e in reversed(events) if e.get("event") == "session"), "unknown")
    good = {"schema": "trackdeform.Keypoints/2", "session_id": session_id, "run_id": "forged-run",
            "frame_number": int(time.monotonic() * config.station.camera.fps), "stamp": time.monotonic(),
            "keypoints": [[0.4, 0.0, 0.1]] * 20, "edges": [[i, i + 1] for i in range(19)],
            "grasp_indices": {"left": -1, "right": -1}, "object": "rope", "category": "dlo", "status": "tracking",
            "abs_mm": None, "cd_mm": None, "anchors": []}
    two_d = dict(good, keypoints=[[0.4, 0.0]] * 20, edges=[[0, 99]])
    msgs = [b"\x00\xffnot json at all", json.dumps(two_d).encode(), json.dumps(good).encode()]
    bus = open_client(config.bus, config.station.name, list(config.bus.listen), timeout=5.0)
    try:
        time.sleep(1.0)  # let the routes settle
        key = bus.key("keypoints")
        for _ in range(3):
            for m in msgs:
                bus.put(key, m)
            time.sleep(0.1)
    finally:
        bus.close()
    return f"published {3 * len(msgs)} messages (garbage, 2-component points + bad edges, forged run id) on {key}"


def wait_for(cond: Any, timeout: float) -> bool:
    """Poll ``cond()`` every 0.2 s for ``timeout`` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.2)
    return False


def sample(soak: Soak, daemon: subprocess.Popen[bytes]) -> None:
    """One CPU / RSS sample of the daemon and its worker."""
    u = proc_usage(daemon.pid)
    if u is None or u[1] == 0.0:  # gone, or not yet exec'd
        return
    w = worker_pid(daemon.pid)
    wu = proc_usage(w) if w is not None else None
    if w is not None:
        soak.worker_pids.add(w)
    r = child_pid(daemon.pid, b"render_process")
    ru = proc_usage(r) if r is not None else None
    soak.samples.append(Sample(time.monotonic(), daemon.pid, u[0], u[1], wu[0] if wu else None,
                               wu[1] if wu else None, r if ru else None, ru[0] if ru else None,
                               ru[1] if ru else None, os.getloadavg()[0]))


# ---------------------------------------------------------------------- audit
def read_events(out: Path) -> list[dict[str, Any]]:
    """events.jsonl records (a torn last line skipped)."""
    path = out / "events.jsonl"
    recs = []
    if path.exists():
        for line in path.read_text(errors="replace").splitlines():
            try:
                recs.append(json.loads(line))
            except json.JSONDecodeError:
                pass
    return recs


def episode_table(out: Path) -> list[dict[str, Any]]:
    """Every finished episode (tdrecord's manifest entries plus unlisted files); an entry without the close-time
    fields (a recovered episode) gets ``n_frames`` / ``first_frame`` / ``last_frame`` from its frames."""
    from tdrecord import load_episode
    from tdrecord.api import episode_entries

    entries = episode_entries(out)
    for e in entries:
        if not all(k in e for k in ("n_frames", "first_frame", "last_frame")):
            frames = load_episode(out / e["file"], images=False).frame_numbers
            e.update(n_frames=len(frames), first_frame=int(frames[0]) if len(frames) else 0,
                     last_frame=int(frames[-1]) if len(frames) else -1)
    return entries


def frames_lost(out: Path, manifest: list[dict[str, Any]], faults: list[Fault], fps: float,
                ) -> tuple[int, Counter[str], list[str]]:
    """(frames missing inside episodes outside every fault window, per fault: frames missing in its window, details).

    Frame k of the mock camera is captured at CLOCK_MONOTONIC k / fps, so a gap maps onto the faults' windows.
    """
    from tdrecord import load_episode

    outside = 0
    inside: Counter[str] = Counter()
    details = []
    windows = [(f.window, f.kind) for f in faults if f.done and not f.skipped]
    wall = time.time() - time.monotonic()
    for e in manifest:
        expected = int(e["last_frame"]) - int(e["first_frame"]) + 1
        if int(e["n_frames"]) >= expected:
            continue
        frames = load_episode(out / e["file"], images=False).frame_numbers
        for a, b in zip(frames[:-1], frames[1:], strict=True):
            if b - a <= 1:
                continue
            t0, t1 = (a + 1) / fps, (b - 1) / fps
            kinds = [kind for (w0, w1), kind in windows if t0 <= w1 and t1 >= w0]
            if kinds:
                inside[kinds[0]] += int(b - a - 1)
            else:
                outside += int(b - a - 1)
                details.append(f"{e['file']}: frames {a + 1}..{b - 1} ({b - a - 1}) at "
                               f"{time.strftime('%H:%M:%S', time.localtime(t0 + wall))}")
    return outside, inside, details


def audit_runs(out: Path, manifest: list[dict[str, Any]], config: Config) -> tuple[bool, list[str]]:
    """Every planned run journaled ``done`` exactly once, its episodes present, no duplicated episode."""
    problems: list[str] = []
    planned = {run_key(i) for i in build_plan(config.plan)}
    records = read_journal(out / "session.journal.jsonl").records
    done = Counter(record_key(r) for r in records if r.get("type") == "run" and r.get("outcome") == "done")
    missing = planned - set(done)
    if missing:
        problems.append(f"{len(missing)} planned run(s) not done: {sorted(missing)[:5]}")
    twice = {k: n for k, n in done.items() if n > 1}
    if twice:
        problems.append(f"{len(twice)} run(s) journaled done more than once: {list(twice.items())[:5]}")
    extra = set(done) - planned
    if extra:
        problems.append(f"{len(extra)} done run(s) not in the plan: {sorted(extra)[:5]}")
    files = {e["file"] for e in manifest}
    for r in records:
        if r.get("type") == "run" and r.get("outcome") == "done":
            lost = [f for f in r.get("episodes", []) if f not in files or not (out / f).exists()]
            if lost:
                problems.append(f"run {record_key(r)} done with missing episode(s) {lost}")
    ids = Counter(tuple(e.get(k) for k in ("object", "program", "speed", "repeat", "plan_pass", "attempt",
                                           "chunk_index")) for e in manifest)
    dups = [k for k, n in ids.items() if n > 1]
    if dups:
        problems.append(f"{len(dups)} episode(s) of one run attempt written twice: {dups[:5]}")
    spans = sorted((int(e["first_frame"]), int(e["last_frame"]), e["file"]) for e in manifest)
    overlaps = [(a[2], b[2]) for a, b in zip(spans[:-1], spans[1:], strict=True) if b[0] <= a[1]]
    if overlaps:
        problems.append(f"{len(overlaps)} pair(s) of episodes share frames: {overlaps[:5]}")
    leftovers = sorted(p.name for p in out.glob("*.mcap.*"))
    if leftovers:
        problems.append(f"unfinished files left: {leftovers[:5]}")
    return not problems, problems


def report(soak: Soak, config: Config, wall: float) -> bool:
    """Print the figures; True when the dataset audit passed and no frame was lost outside faults."""
    out = soak.out
    manifest = episode_table(out)
    print(f"\n=== soak: {soak.minutes:g} min planned, {wall / 60:.1f} min wall, "
          f"{len(build_plan(config.plan))} runs planned, daemon rc {soak.daemon_rcs} ===")
    complete = sum(1 for e in manifest if e.get("complete") is True)
    frames = sum(int(e["n_frames"]) for e in manifest)
    print(f"episodes written : {len(manifest)} ({complete} complete, {len(manifest) - complete} cut short by a "
          f"fault or recovered), "
          f"{frames} frames, {sum(int(e['bytes']) for e in manifest) / 1e9:.2f} GB")
    print("faults injected  :")
    wall = time.time() - time.monotonic()
    for f in soak.faults:
        if f.done and not f.skipped:
            f.note += (f" [window {time.strftime('%H:%M:%S', time.localtime(f.window[0] + wall))}"
                       f"-{time.strftime('%H:%M:%S', time.localtime(f.window[1] + wall))}]")
        state = f"SKIPPED ({f.skipped})" if f.skipped else ("done" if f.done else "NOT REACHED")
        print(f"  {f.kind:<14} {state}{': ' + f.note if f.note and not f.skipped else ''}")
    lost_out, lost_in, details = (frames_lost(out, manifest, soak.faults, config.station.camera.fps) if manifest
                                  else (0, Counter(), []))
    print(f"frames lost      : {lost_out} outside injected faults, {sum(lost_in.values())} inside fault windows ("
          + (", ".join(f"{k} {n}" for k, n in lost_in.items()) or "none") + ")")
    for d in details[:10]:
        print(f"  {d}")
    events = read_events(out)
    kinds = Counter(e.get("kind", "?") for e in events if e.get("event") == "incident")
    print(f"incidents        : {sum(kinds.values())} in events.jsonl: "
          + (", ".join(f"{k} x{n}" for k, n in sorted(kinds.items())) or "none"))
    for e in [e for e in events if e.get("event") == "incident"][:20]:
        print(f"  {e['time'][11:19]} {e.get('kind')}: {str(e.get('message'))[:150]}")
    summary_path = out / "summary.json"
    if summary_path.exists():
        s = json.loads(summary_path.read_text())
        print(f"summary.json     : {len(s.get('incidents', []))} incident(s), {len(s.get('errors', []))} error(s)"
              + "".join(f"\n  error: {str(x)[:150]}" for x in s.get("errors", [])))
    else:
        print("summary.json     : MISSING")
    kp_frames = sum(int(e.get("n_frames", 0)) for e in manifest)
    with_kp = 0  # live keypoint coverage from the episode metadata
    for e in manifest:
        with_kp += int(read_episode_metadata(out / e["file"]).get("tracking", {}).get("with_keypoints", 0))
    print(f"live keypoints   : {with_kp} of {kp_frames} frames ({100 * with_kp / max(kp_frames, 1):.1f} %), "
          f"{len(soak.worker_pids)} worker process(es) seen")
    print("daemon CPU / RSS : (CPU % over the previous sample; worker, then the mock camera's render process)")
    print(f"  {'t s':>6} {'pid':>7} {'CPU %':>6} {'RSS MB':>7} {'[wCPU %':>8} {'wRSS MB]':>9} "
          f"{'[rCPU %':>8} {'rRSS MB]':>9} {'load':>5}")
    start = soak.samples[0].t if soak.samples else 0.0
    prev: Sample | None = None
    rows = [s for i, s in enumerate(soak.samples) if i % max(1, len(soak.samples) // 25) == 0 or
            i == len(soak.samples) - 1]
    for s in rows:
        same = prev is not None and prev.pid == s.pid
        cpu = 100 * (s.cpu_s - prev.cpu_s) / (s.t - prev.t) if same and prev is not None else float("nan")
        wcpu = (100 * (s.worker_cpu_s - prev.worker_cpu_s) / (s.t - prev.t)
                if same and prev is not None and s.worker_cpu_s is not None and prev.worker_cpu_s is not None
                and s.worker_cpu_s >= prev.worker_cpu_s else float("nan"))
        rcpu = (100 * (s.render_cpu_s - prev.render_cpu_s) / (s.t - prev.t)
                if same and prev is not None and s.render_pid is not None and prev.render_pid == s.render_pid
                and s.render_cpu_s is not None and prev.render_cpu_s is not None else float("nan"))
        print(f"  {s.t - start:6.0f} {s.pid:7d} {cpu:6.1f} {s.rss_mb:7.0f} {wcpu:8.1f} "
              f"{s.worker_rss_mb if s.worker_rss_mb is not None else float('nan'):9.0f} {rcpu:8.1f} "
              f"{s.render_rss_mb if s.render_rss_mb is not None else float('nan'):9.0f} {s.load1:5.1f}")
        prev = s
    for pid in dict.fromkeys(s.pid for s in soak.samples):  # memory growth per daemon process, after start-up
        mine = [s for s in soak.samples if s.pid == pid]
        mine = [s for s in mine if s.t - mine[0].t >= 20.0]
        if len(mine) >= 4:
            q = len(mine) // 4
            first = sum(s.rss_mb for s in mine[:q]) / q
            last = sum(s.rss_mb for s in mine[-q:]) / q
            print(f"  daemon pid {pid} RSS after its first 20 s: first quarter {first:.0f} MB -> last quarter "
                  f"{last:.0f} MB ({last - first:+.0f} MB over {mine[-1].t - mine[0].t:.0f} s)")
    ok, problems = audit_runs(out, manifest, config) if manifest else (False, ["no episodes"])
    print("every planned run exactly once: " + ("YES" if ok else "NO"))
    for p in problems:
        print(f"  {p}")
    return ok and lost_out == 0


# ---------------------------------------------------------------------- main
def run(soak: Soak, final: bool) -> bool:
    """Set up, run the session with its faults until the plan is done (or the deadline), audit, print."""
    t_wall0 = time.time()
    config = write_config(soak, t_wall0 + STARTUP_SECONDS, final)
    reason = mount_tmpfs(soak, config)
    if reason:
        print(f"disk-full fault will be skipped: {reason}")
        soak.out.mkdir(parents=True, exist_ok=True)
    print(f"soak: {len(build_plan(config.plan))} runs planned ({config.plan.repeats} repeats), port {soak.port}, "
          f"final keypoints {'on' if final else 'off'}, log {soak.log}")
    deadline = time.monotonic() + soak.minutes * 60.0 * 1.6 + 120.0
    daemon = launch(soak)
    next_sample = time.monotonic()
    pending = sorted(soak.faults, key=lambda f: f.at_wall)
    while True:
        now = time.monotonic()
        if daemon.poll() is not None:
            soak.daemon_rcs.append(daemon.returncode)
            break
        if now >= deadline:
            print("deadline reached: stopping the daemon (SIGTERM)")
            os.killpg(daemon.pid, signal.SIGTERM)
            try:
                daemon.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(daemon.pid, signal.SIGKILL)
                daemon.wait()
            soak.daemon_rcs.append(daemon.returncode)
            break
        if now >= next_sample:
            sample(soak, daemon)
            next_sample = now + SAMPLE_SECONDS
        if pending and time.time() >= pending[0].at_wall:
            f = pending.pop(0)
            print(f"{time.strftime('%H:%M:%S')} fault: {f.kind}")
            daemon = inject(soak, f, daemon, config)
        time.sleep(0.2)
    return report(soak, config, time.time() - t_wall0)


def cleanup(soak: Soak, keep: bool) -> None:
    """Kill what is left of every process group started, unmount, remove the folder."""
    for p in soak.daemons:
        for pid in [p.pid]:
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        p.wait()
    if soak.mounted:
        subprocess.run(["umount", str(soak.out)], check=False)
    if keep:
        print(f"kept {soak.work}" + (" (the dataset was on the unmounted tmpfs)" if soak.mounted else ""))
    else:
        shutil.rmtree(soak.work, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=5.0, help="soak length, minutes (the plan is sized to it)")
    ap.add_argument("--final", action="store_true",
                    help="keep tracking.final on (offline keypoints after each run; ~3x slower than real time "
                         "on 2 cores, so the session runs well past --minutes)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (config, log; dataset if on disk)")
    ap.add_argument("--tmpfs-fraction", type=float, default=0.5,
                    help="largest share of available memory the dataset's tmpfs may take (default 0.5)")
    args = ap.parse_args(argv)
    if args.minutes <= 0:
        ap.error("--minutes must be positive")
    work = Path(tempfile.mkdtemp(prefix="trackdeform-soak-"))
    soak = Soak(args.minutes, work, work / "data", work / "soak.yaml", free_port(), work / "daemon.log",
                tmpfs_fraction=args.tmpfs_fraction)
    ok = False
    try:
        ok = run(soak, args.final)
    finally:
        cleanup(soak, args.keep)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
