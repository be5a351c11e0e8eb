"""Live keypoints: the gate before the recorder, the worker following the session's runs, the supervisor,
health and control over zenoh (real sessions on loopback, explicit ports, multicast off)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from drivers.clock import RealClock
from orchestrator.bus import Bus
from orchestrator.cli import main
from orchestrator.config import DEFAULT_CONFIG, Config, load_config
from orchestrator.journal import JOURNAL_NAME, read_journal
from orchestrator.live import KeypointGate
from orchestrator.session import Session
from tdcommon.wire import check_keypoints, decode_frame, decode_json, encode_frame, encode_json, encode_keypoints
from tdrecord import read_episode_metadata
from tdrecord.channels import keypoints_record
from tests.conftest import NO_LIVE_INIT, make_frame


def mock_config(port: int, *, tracking: bool = True, small: bool = False, **extra: object) -> Config:
    """The mock config with only the rope, on ``tcp/127.0.0.1:<port>``; the worker initialises on the run itself
    (the live initialisation before recording is tested in test_liveinit.py)."""
    overrides: dict[str, Any] = {"bus.listen": [f"tcp/127.0.0.1:{port}"], "tracking.enabled": tracking,
                                 **NO_LIVE_INIT, **extra}
    if small:
        overrides.update({"station.camera.width": 160, "station.camera.height": 120, "plan.episode_seconds": 1.0})
    cfg = load_config(DEFAULT_CONFIG, overrides)
    data = cfg.model_dump()
    data["plan"]["objects"] = [o for o in data["plan"]["objects"] if o["name"] == "rope"]
    return Config.model_validate(data)


def wait_for(cond: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.1)


class Background:
    """A real-time session on a thread: ``with Background(session) as bg: ...``; ``bg.summary`` afterwards."""

    def __init__(self, session: Session, **run: Any) -> None:
        self.session, self.run, self.summary = session, run, None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.error: BaseException | None = None

    def _run(self) -> None:
        try:
            self.summary = self.session.run(**self.run)
        except BaseException as e:  # surfaced by __exit__
            self.error = e

    def __enter__(self) -> Background:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.session.stop_event.set()
        self.thread.join(120)
        assert not self.thread.is_alive(), "the session did not stop"
        if self.error is not None and exc[0] is None:
            raise self.error


def kp_message(n: int = 4, frame: int = 0, session: str = "S", run: str = "R", **kw: Any) -> bytes:
    args: dict[str, Any] = dict(
        frame_number=frame, stamp=frame / 30, keypoints=np.zeros((n, 3)),
        edges=np.array([[i, i + 1] for i in range(n - 1)]), grasp_indices={"left": 0, "right": n - 1},
        object_name="rope", category="dlo", status="tracking", abs_mm=1.0, cd_mm=2.0, session_id=session, run_id=run,
    )
    args.update(kw)
    return encode_keypoints(**args)


# ---------------------------------------------------------------------- the gate (no bus)
def test_gate_records_only_checked_keypoints_of_this_session_run_and_frame() -> None:
    gate = KeypointGate("S", fps=30.0, gap_seconds=1.0)
    gate.begin_run("R")
    for fn in range(10):
        gate.frame(fn, fn / 30)
    assert gate.accept(kp_message(frame=3)) is not None
    assert gate.accept(kp_message(frame=3)) is None  # the same frame again (a second worker)
    assert gate.accept(kp_message(frame=4, session="OLD")) is None  # a worker of an earlier session
    assert gate.accept(kp_message(frame=5, run="R2")) is None  # a run this session did not announce
    assert gate.accept(kp_message(frame=99)) is None  # a frame it did not record
    bad = json.loads(kp_message(frame=6))
    bad["keypoints"] = [[0.0, 1.0]] * 4  # 2-component points
    assert gate.accept(json.dumps(bad).encode()) is None
    bad = json.loads(kp_message(frame=6))
    bad["edges"] = [[0, 17]]  # out of range
    assert gate.accept(json.dumps(bad).encode()) is None
    assert gate.accept(b"\xff not json") is None
    assert gate.rejected.counts == {"duplicate": 1, "other_session": 1, "unknown_run": 1, "unknown_frame": 1,
                                    "keypoints": 1, "edges": 1, "not_json": 1}
    assert gate.accepted == 1
    gate.begin_run("R2")  # the previous run's late keypoints still count
    assert gate.accept(kp_message(frame=7)) is not None


def test_rejections_are_logged_once_per_kind(caplog: pytest.LogCaptureFixture) -> None:
    firsts: list[str] = []
    gate = KeypointGate("S", fps=30.0, gap_seconds=1.0)
    gate.rejected.on_first = lambda kind, detail: firsts.append(kind)
    gate.begin_run("R")
    with caplog.at_level("WARNING"):
        for _ in range(500):
            gate.accept(b"{")
    assert gate.rejected.counts == {"not_json": 500}
    assert len([r for r in caplog.records if "not_json" in r.getMessage()]) == 1 and firsts == ["not_json"]


def test_episode_report_counts_tracking_gaps() -> None:
    gate = KeypointGate("S", fps=10.0, gap_seconds=1.0)
    gate.begin_run("R")
    for fn in range(50):
        gate.frame(fn, fn / 10)
    for fn in [*range(0, 10, 2), *range(30, 50, 3)]:  # every other frame (busy worker: no gap), then 2 s missing
        assert gate.accept(kp_message(frame=fn)) is not None
    r = gate.episode_report()
    assert r["frames"] == 50 and r["with_keypoints"] == 12
    assert r["gaps"] == 1 and r["gap_frames"] == 21 and r["longest_gap_s"] == pytest.approx(2.1)
    assert gate.episode_report()["frames"] == 0  # the next episode starts empty


# ---------------------------------------------------------------------- the worker
def _worker_keys(session_bus: Bus) -> tuple[str, str, dict[str, Any], list[dict]]:
    """The run and frame keys, run R1's announcement of session S, and the keypoint messages published."""
    announce = {"schema": "trackdeform.Run/1", "session_id": "S", "run_id": "R1", "object": "rope",
                "category": "dlo", "run_index": 0, "n_keypoints": 20}
    published: list[dict] = []
    session_bus.subscribe(session_bus.key("keypoints"), callback=lambda s: published.append(
        decode_json(s.payload.to_bytes())))
    return session_bus.key("session", "run"), session_bus.key("cam", "cam0", "frame"), announce, published


def test_forged_frame_with_another_run_does_not_reset_tracking(port: int) -> None:
    """The tracker switches runs only on the session's announcement, never on a frame header."""
    from orchestrator.worker import Worker

    cfg = mock_config(port)
    with Bus(cfg.bus, cfg.station.name) as session_bus:
        worker = Worker(cfg, session_id="S")
        try:
            run_key, frame_key, announce, published = _worker_keys(session_bus)

            def send(n: int, run: dict[str, Any]) -> None:
                session_bus.put(frame_key, encode_frame(make_frame(n, 160, 120), np.eye(4), "cam0", run))
                wait_for(lambda: worker.step(), 10, f"frame {n} at the worker")

            session_bus.put(run_key, encode_json(announce))
            wait_for(lambda: worker._announced is not None, 10, "the announcement")
            send(0, {"run_index": 0, "object": "rope", "run_id": "R1"})
            first = worker.pipeline
            assert first is not None and worker.stats.runs == 1
            send(1, {"run_index": 7, "object": "cloth", "category": "cloth"})  # forged: another run index
            send(2, {"run_index": 7, "object": "cloth", "run_id": "FORGED"})  # forged: another run id
            assert worker.pipeline is first and worker.stats.runs == 1 and worker.stats.other_run == 1
            session_bus.put(run_key, encode_json({**announce, "run_id": "OTHER", "session_id": "X"}))  # not ours
            send(3, {"run_id": "R1"})
            assert worker.pipeline is first
            session_bus.put(run_key, encode_json({**announce, "run_id": "R2", "run_index": 1}))
            wait_for(lambda: worker._announced["run_id"] == "R2", 10, "the second announcement")
            send(4, {"run_id": "R2"})
            assert worker.pipeline is not first and worker.stats.runs == 2
            wait_for(lambda: len(published) == 4, 10, "four keypoint messages")
            assert [(m["frame_number"], m["run_id"], m["session_id"]) for m in published] == [
                (0, "R1", "S"), (1, "R1", "S"), (3, "R1", "S"), (4, "R2", "S")]
            assert all(check_keypoints(m) is None for m in published)
        finally:
            worker.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux only")
def test_a_frame_ahead_of_its_run_announcement_is_tracked_once_it_comes(port: int) -> None:
    """In simulated time the session waits for the answer to a run's first frame: a frame that overtook its
    run's announcement waits at the worker (retried) and is tracked once the announcement arrives."""
    from orchestrator.worker import Worker

    cfg = mock_config(port)
    with Bus(cfg.bus, cfg.station.name) as session_bus:
        worker = Worker(cfg, session_id="S")
        try:
            run_key, frame_key, announce, published = _worker_keys(session_bus)
            session_bus.put(run_key, encode_json(announce))
            wait_for(lambda: worker._announced is not None, 10, "the announcement")
            session_bus.put(frame_key, encode_frame(make_frame(0, 160, 120), np.eye(4), "cam0", {"run_id": "R2"}))
            wait_for(lambda: worker.step(), 10, "frame 0 at the worker")
            assert worker._pending is not None and not published  # R2 is not announced yet: kept
            session_bus.put(run_key, encode_json({**announce, "run_id": "R2", "run_index": 1}))
            wait_for(lambda: worker._announced["run_id"] == "R2", 10, "the R2 announcement")
            assert worker.step() is False  # no new frame: the pending one is retried
            wait_for(lambda: len(published) == 1, 10, "its keypoint message")
            assert published[0]["frame_number"] == 0 and published[0]["run_id"] == "R2"
            assert worker._pending is None
        finally:
            worker.close()


def test_worker_dies_with_its_parent(tmp_path: Path, port: int) -> None:
    cfg = mock_config(port)
    cfg_path = tmp_path / "c.json"
    cfg_path.write_text(json.dumps(cfg.model_dump(mode="json")))
    parent_code = (
        "import os, subprocess, sys, time\n"
        f"p = subprocess.Popen([sys.executable, '-m', 'orchestrator.worker', {str(cfg_path)!r}, '--connect', "
        f"'tcp/127.0.0.1:{port}', '--parent-pid', str(os.getpid())])\n"
        "print(p.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    with Bus(cfg.bus, cfg.station.name) as bus:
        alive: set[str] = set()
        bus.watch_liveliness(bus.key("worker", "alive", "**"), lambda s: (
            alive.add(str(s.key_expr)) if str(s.kind).endswith("PUT") else alive.discard(str(s.key_expr))))
        parent = subprocess.Popen([sys.executable, "-c", parent_code], stdout=subprocess.PIPE, text=True,
                                  env={**os.environ, "PYTHONPATH": os.getcwd()})
        worker_pid = int(parent.stdout.readline())
        try:
            wait_for(lambda: any(k.endswith(f"-{worker_pid}") for k in alive), 120, "the worker's liveliness token")
            parent.kill()  # kill -9: no cleanup code of the parent runs
            parent.wait()

            def gone() -> bool:
                try:
                    state = Path(f"/proc/{worker_pid}/stat").read_text().split()[2]
                except FileNotFoundError:
                    return True
                return state in ("Z", "X")

            wait_for(gone, 20, "the orphaned worker to die")
            wait_for(lambda: not alive, 10, "its token to disappear")
        finally:
            if not gone():
                os.kill(worker_pid, signal.SIGKILL)


@pytest.mark.slow
def test_killed_worker_is_restarted_and_reported(tmp_path: Path, port: int) -> None:
    """kill -9 of the worker mid-session: the supervisor sees it, restarts it, keypoints come again."""
    cfg = mock_config(port, **{"tracking.worker_restart_backoff": 0.5})
    with Bus(cfg.bus, cfg.station.name) as bus:
        session = Session(cfg, tmp_path, RealClock(), bus=bus, with_worker=True)
        with Background(session, max_seconds=300.0, loop=True) as bg:
            # 15 accepted before and after the kill: the check at the end counts the frames with keypoints in the
            # recorded episodes, which may be fewer than the gate accepted (20 of > 20 once, on a loaded machine)
            wait_for(lambda: session.gate is not None and session.gate.accepted > 15, 180, "keypoints from the worker")
            sup = session.supervisor
            assert sup is not None
            first_pid = sup.proc.proc.pid
            os.kill(first_pid, signal.SIGKILL)
            accepted = session.gate.accepted
            wait_for(lambda: sup.restarts == 1 and sup.status()["alive"], 180, "the restarted worker")
            assert sup.proc.proc.pid != first_pid
            wait_for(lambda: session.gate.accepted > accepted + 15, 120, "keypoints from the restarted worker")
            health = session.monitor.health()
            assert health["worker"]["restarts"] == 1 and health["worker"]["alive"]
            assert any(i["kind"] == "worker_restart" for i in health["incidents"])
        summary = bg.summary
    assert summary is not None and summary.worker_restarts == 1
    assert any("worker_restart" in i and "SIGKILL" in i for i in summary.incidents), summary.incidents
    events = [json.loads(ln) for ln in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert any(e["event"] == "incident" and e["kind"] == "worker_restart" and f"pid {first_pid}" in e["message"]
               for e in events)
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["worker_restarts"] == 1 and saved["incidents"]
    metas = [read_episode_metadata(p) for p in sorted(tmp_path.glob("episode_*.mcap"))]
    assert metas and all("tracking" in m for m in metas)
    assert sum(m["tracking"]["with_keypoints"] for m in metas) > 20


# ---------------------------------------------------------------------- malformed messages on the bus
def test_malformed_keypoint_messages_are_not_recorded(tmp_path: Path, port: int) -> None:
    """A real-time session (no worker); a forger publishes bad messages for real frames and one good one."""
    cfg = mock_config(port, small=True)
    with Bus(cfg.bus, cfg.station.name) as bus:
        forger = Bus(cfg.bus, cfg.station.name, listen=False, connect=[f"tcp/127.0.0.1:{port}"])
        runs: list[dict] = []
        frames: list[int] = []
        forger.subscribe(forger.key("session", "run"), callback=lambda s: runs.append(decode_json(
            s.payload.to_bytes())))
        forger.subscribe(forger.key("cam", "cam0", "frame"), callback=lambda s: frames.append(
            decode_frame(s.payload.to_bytes()).frame.frame_number))
        session = Session(cfg, tmp_path, RealClock(), bus=bus)
        try:
            with Background(session, max_seconds=3.0):
                wait_for(lambda: len(frames) > 5 and any(r["run_id"] for r in runs), 60, "frames and a run")
                run = next(r for r in runs if r["run_id"])
                fn = frames[-1]
                key = forger.key("keypoints")
                good = json.loads(kp_message(n=20, frame=fn, session=run["session_id"], run=run["run_id"]))
                for bad in (
                    {**good, "keypoints": [[0.0, 0.0]] * 20},  # 2-component points
                    {**good, "edges": [[0, 25], [3, 4]]},  # out of range
                    {**good, "keypoints": [[float("nan")] * 3] * 20},
                    {**good, "session_id": "another"},
                    {**good, "run_id": "another"},
                    {**good, "frame_number": fn + 10_000},
                ):
                    forger.put(key, json.dumps(bad).encode())
                forger.put(key, b"\x00garbage")
                forger.put(key, json.dumps(good).encode())
                forger.put(key, json.dumps(good).encode())  # again: a duplicate
                wait_for(lambda: session.gate.accepted == 1 and session.gate.rejected.total() == 8, 30,
                         "the messages at the gate")
        finally:
            forger.close()
    recorded = []
    for ep in sorted(tmp_path.glob("episode_*.mcap")):
        with open(ep, "rb") as f:
            recorded += [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/keypoints"])]
    assert recorded == [keypoints_record(good)]  # as recorded: points {x, y, z}, edges {i, j}
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["keypoints_recorded"] == 1
    assert s["keypoints_rejected"] == {"keypoints": 1, "edges": 1, "not_finite": 1, "other_session": 1,
                                       "unknown_run": 1, "unknown_frame": 1, "not_json": 1, "duplicate": 1}
    kinds = [e["message"].split(":")[0] for e in map(json.loads, (tmp_path / "events.jsonl").read_text().splitlines())
             if e["event"] == "incident" and e["kind"] == "keypoints_rejected"]
    assert sorted(kinds) == sorted(s["keypoints_rejected"])


# ---------------------------------------------------------------------- health and control
@pytest.mark.slow
def test_status_and_ctl_pause_resume_skip_stop(tmp_path: Path, port: int, capsys: pytest.CaptureFixture) -> None:
    cfg = mock_config(port, tracking=False, small=True)
    ep = ["--connect", f"tcp/127.0.0.1:{port}", "--station", "mock", "--timeout", "30"]

    def cli(*args: str) -> tuple[int, str]:
        rc = main(list(args) + ep)
        return rc, capsys.readouterr().out

    with Bus(cfg.bus, cfg.station.name) as bus:
        session = Session(cfg, tmp_path, RealClock(), bus=bus)
        with Background(session, loop=True) as bg:
            wait_for(lambda: session.summary.frames_captured > 45, 60, "recording")
            time.sleep(1.5)  # a rate over more than one health period
            rc, out = cli("status", "--json")
            h = json.loads(out)
            assert rc == 0 and h["state"] == "running" and h["run"]["object"] == "rope"
            assert h["camera"]["rate_hz"] and 10 < h["camera"]["rate_hz"] < 45, h["camera"]
            # joint states are polled at 250 Hz: a test process sharing the cores with others measured 40
            assert h["joint_states"]["rate_hz"] > 20 and h["disk"]["free_gb"] > 0, h["joint_states"]
            assert h["episode"]["frames"] > 0 and h["progress"]["runs_planned"] == 1
            rc, out = cli("status")
            assert rc == 0 and "state     running" in out and "camera " in out

            rc, out = cli("ctl", "pause")
            assert rc == 0 and "pausing" in out
            wait_for(lambda: session.monitor.state == "paused", 30, "the pause at the episode's end")
            frames = session.summary.frames_captured
            time.sleep(1.5)
            assert session.summary.frames_captured == frames  # nothing recorded while paused
            assert json.loads(cli("status", "--json")[1])["state"] == "paused"
            rc, out = cli("ctl", "resume")
            assert rc == 0
            wait_for(lambda: session.summary.frames_captured > frames + 30, 30, "recording after resume")
            rc, out = cli("ctl", "skip")
            assert rc == 0 and "skipping" in out
            wait_for(lambda: bool(session.summary.runs_skipped), 30, "the skip")
            rc, out = cli("ctl", "stop")
            assert rc == 0
            bg.thread.join(60)
    summary = bg.summary
    assert summary is not None and summary.stopped_early
    skipped = [r for r in read_journal(tmp_path / JOURNAL_NAME).records
               if r["type"] == "run" and r["outcome"] == "skipped"]
    assert len(skipped) == 1 and "ctl skip" in skipped[0]["reason"]
    metas = [read_episode_metadata(p) for p in sorted(tmp_path.glob("episode_*.mcap"))]
    assert metas[0]["complete"] is True  # the pause finished the episode
    events = [json.loads(ln) for ln in (tmp_path / "events.jsonl").read_text().splitlines()]
    states = [e["state"] for e in events if e["event"] == "state"]
    assert "paused" in states and states[states.index("paused") + 1] == "running" and states[-1] in ("done",
                                                                                                       "failed")
    assert [e["command"] for e in events if e["event"] == "ctl"] == ["pause", "resume", "skip", "stop"]
    assert main(["ctl", "stop", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1"]) == 2  # nobody there
