"""The live initialisation before recording (orchestrator.liveinit): the check, the move, the config, and
mock sessions in simulated time whose recorded runs are tracked from their first frame or skipped."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.clock import SimClock
from orchestrator.bus import Bus
from orchestrator.config import DEFAULT_CONFIG, Config, ConfigError, LiveInitConfig, load_config
from orchestrator.journal import JOURNAL_NAME, read_journal
from orchestrator.live import KeypointGate
from orchestrator.liveinit import InitOutcome, check_result, expected_keypoints, plan_init_motions
from orchestrator.session import Session
from orchestrator.station import Station
from tdrecord import load_episode
from tests.test_live import kp_message
from trajectories.program import load_program, resolve_program, save_program

TCP = np.array([[0.45, 0.25, 0.40], [0.45, -0.25, 0.40]])
BOTH = np.array([True, True])


def _msg(frame: int, status: str = "tracking", n: int = 20, abs_mm: float = 1.0, end_gap: float = 0.0) -> dict:
    """A keypoint message: n keypoints on the line between the two TCPs, the ends ``end_gap`` m inside."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    a, b = TCP[0] + [0, -end_gap, 0], TCP[1] + [0, end_gap, 0]
    X = a + t * (b - a)
    rest = [float(np.linalg.norm(b - a)) / max(1, n - 1)] * max(0, n - 1)  # 26.3 mm for 20 keypoints, no gap
    return json.loads(kp_message(n=n, frame=frame, keypoints=X, status=status, abs_mm=abs_mm,
                                 extra={"rest_lengths": rest}))


def _check(msgs: list[dict], expected: int = 20, closed: np.ndarray = BOTH, **cfg: Any) -> tuple[str | None, dict]:
    return check_result(msgs, expected, TCP, closed, LiveInitConfig(**cfg))


# ---------------------------------------------------------------------- the check
def test_check_accepts_a_tracked_object_held_at_both_grippers() -> None:
    reason, m = _check([_msg(f) for f in range(5)])
    assert reason is None
    assert m["n_keypoints"] == 20 and m["abs_mm"] == 1.0 and m["gripper_distance_m"] == {"left": 0.0, "right": 0.0}
    assert m["mean_rest_length_m"] == pytest.approx(0.5 / 19, abs=1e-5)
    assert m["edge_error"] == pytest.approx(0.038, abs=1e-3)
    assert m["statuses"] == {"tracking": 5} and m["frames"] == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(("msgs", "cfg", "expected", "why"), [
    ([_msg(0, n=12)], {}, 20, "12 keypoints, expected 20"),
    ([_msg(0, abs_mm=5.0), _msg(1, abs_mm=5.5), _msg(2, abs_mm=1.0)], {}, 20,
     "edge-length error 5.0 mm = 0.19 of the mean edge length, must be below 0.15"),
    ([_msg(0, abs_mm=1.0)], {"max_edge_error": 0.01}, 20, "must be below 0.01"),
    ([_msg(0, end_gap=0.06)], {}, 20, "no keypoint at the closed gripper(s): nearest left 60 mm, right 60 mm"),
    ([_msg(0), _msg(1, status="lost")], {}, 20, "not tracking after the move (status lost)"),
    ([_msg(0, status="waiting", n=0)], {}, 20, "not tracking after the move (status waiting)"),
    ([_msg(0, status="degraded"), _msg(1, status="degraded"), _msg(2)], {}, 20, "degraded in 2 of the 3"),
    ([], {}, 20, "no result"),
])
def test_check_fails_with_the_reason(msgs: list[dict], cfg: dict, expected: int, why: str) -> None:
    reason, _ = _check(msgs, expected, **cfg)
    assert reason is not None and why in reason, reason


def test_check_only_asks_for_keypoints_at_closed_grippers() -> None:
    reason, m = _check([_msg(0, end_gap=0.06)], closed=np.array([False, False]))
    assert reason is None and m["gripper_distance_m"] == {}


def test_expected_keypoints_follow_the_worker() -> None:
    assert expected_keypoints("dlo", None) == 20 and expected_keypoints("bdlo", None) == 25
    assert expected_keypoints("dlo", 30) == 30
    assert expected_keypoints("cloth", None) == 36 and expected_keypoints("cloth", 50) == 49  # a 7 x 7 grid


# ---------------------------------------------------------------------- config
def test_config_defaults_and_validation(tmp_path: Path) -> None:
    cfg = load_config(DEFAULT_CONFIG)
    li = cfg.tracking.live_init
    assert li.enabled and li.attempts == 3 and li.on_failure == "skip"
    assert np.isclose(np.linalg.norm(li.displacement), 0.05)
    for bad, field in [({"displacement": [0, 0, 0.5]}, "displacement"), ({"displacement": [0, 0, 0.001]},
                       "displacement"), ({"attempts": 0}, "attempts"), ({"max_edge_error": 0}, "max_edge_error"),
                       ({"on_failure": "ignore"}, "on_failure"), ({"typo": 1}, "typo")]:
        with pytest.raises(ConfigError, match=rf"tracking\.live_init\.{field}"):
            load_config(DEFAULT_CONFIG, {f"tracking.live_init.{k}": v for k, v in bad.items()})
    off = load_config(DEFAULT_CONFIG, {"tracking.live_init.enabled": False})
    assert not off.tracking.live_init.enabled


# ---------------------------------------------------------------------- the gate hands init messages over
def test_gate_hands_watched_run_messages_to_the_watcher_without_recording_or_rejecting() -> None:
    gate = KeypointGate("S", 30.0, 1.0)
    got: list[dict] = []
    gate.watch("init-1", got.append)
    assert gate.accept(kp_message(frame=3, run="init-1")) is None
    assert [m["frame_number"] for m in got] == [3] and not gate.rejected.counts and gate.accepted == 0
    assert gate.accept(kp_message(frame=3, run="init-1", session="other")) is None  # another session: rejected
    assert len(got) == 1 and gate.rejected.counts == {"other_session": 1}
    gate.watch("init-1", None)  # its late answers are dropped quietly
    assert gate.accept(kp_message(frame=4, run="init-1")) is None and len(got) == 1 and gate.late_watched == 1
    assert gate.rejected.counts == {"other_session": 1}
    assert gate.accept(kp_message(frame=4, run="init-2")) is None and gate.rejected.counts["unknown_run"] == 1


# ---------------------------------------------------------------------- the move
def test_init_move_goes_out_by_the_displacement_and_back() -> None:
    cfg = load_config(DEFAULT_CONFIG, {"clock": "sim"})
    station = Station(cfg, cfg.plan.objects[0], SimClock())
    station.connect()
    try:
        q = station.current_q()
        start = np.concatenate([q["left"], q["right"]])
        li = LiveInitConfig(displacement=(0.02, 0.0, 0.04))
        approach, move = plan_init_motions(station, start, li)
        assert approach is None  # the arms are at the start pose already
        assert move.duration >= 2 * li.move_seconds + li.hold_seconds - 1e-6
        wq = move.program.q()
        np.testing.assert_allclose(wq[2], start)
        for k, arm in enumerate(("left", "right")):
            d = station.kin[arm].tcp_pose(wq[1][7 * k: 7 * k + 7])[:3, 3] - station.kin[arm].tcp_pose(start[7 * k:
                                                                                                    7 * k + 7])[:3, 3]
            np.testing.assert_allclose(d, li.displacement, atol=2e-4)
        away = start.copy()
        away[0] += 0.1
        approach, _ = plan_init_motions(station, away, li)
        assert approach is not None and approach.segments[0].kind == "approach"
    finally:
        station.close()


# ---------------------------------------------------------------------- sessions (the worker in its process)
def _session_config(port: int, program: Path | None = None, **extra: Any) -> Config:
    """The mock rope in simulated time at the mock camera's 640x480, final keypoints off (not under test);
    ``program``: run this program file instead of the library's."""
    overrides = {"clock": "sim", "bus.listen": [f"tcp/127.0.0.1:{port}"], "tracking.final": False, **extra}
    cfg = load_config(DEFAULT_CONFIG, overrides)
    data = cfg.model_dump()
    data["plan"]["objects"] = [o for o in data["plan"]["objects"] if o["name"] == "rope"]
    if program is not None:
        data["plan"]["objects"][0]["programs"] = [str(program)]
    return Config.model_validate(data)


# the failure tests check what follows a failed check, not the initialisation: shorter moves there
QUICK_MOVES = {"tracking.live_init.move_seconds": 1.0, "tracking.live_init.hold_seconds": 0.5}


def _short_program(path: Path) -> Path:
    """rope_swing's first move and back: a 2 s run (two 1 s episodes) from the library's start pose."""
    prog = load_program(resolve_program("rope_swing"))
    w0, w1 = prog.waypoints[0], prog.waypoints[1]
    short = prog.model_copy(update={"name": "rope_short", "waypoints": [
        w0, w1.model_copy(update={"duration": 0.75}), w0.model_copy(update={"grippers": {}, "duration": 0.75})]})
    save_program(short, path)
    return path


def _journal(out: Path) -> list[dict]:
    return read_journal(out / JOURNAL_NAME).records


@pytest.mark.slow
def test_recorded_runs_are_tracked_from_their_first_frame(tmp_path: Path, port: int) -> None:
    """Two runs of the rope: one initialisation before the first, the second keeps its track (warm start)."""
    program = _short_program(tmp_path / "rope_short.yaml")
    out = tmp_path / "session"
    cfg = _session_config(port, program, **{"plan.repeats": 2, "plan.episode_seconds": 1.0,
                                            "plan.settle_seconds": 0.0})
    with Bus(cfg.bus, cfg.station.name) as bus:
        summary = Session(cfg, out, SimClock(), bus=bus, with_worker=True).run()
    tmp_path = out
    assert not summary.errors and not summary.runs_failed, summary.text()
    inits = [r for r in _journal(tmp_path) if r["type"] == "live_init"]
    assert len(inits) == 1 and inits[0]["outcome"] == "ok", inits
    m = inits[0]["attempts"][-1]["metrics"]
    assert m["n_keypoints"] == 20 and m["edge_error"] < 0.15 and max(m["gripper_distance_m"].values()) <= 0.04
    assert m["timeline"]["initialised_during"] == "hold at P1", m["timeline"]
    assert "live init        : rope: ok after" in summary.text()
    eps = [load_episode(p, images=False) for p in sorted(tmp_path.glob("episode_*.mcap"))]
    firsts = [ep for ep in eps if ep.metadata["chunk_index"] == 0]
    assert len(firsts) == 2, [ep.metadata["run_index"] for ep in eps]
    for ep in firsts:  # the first recorded frame of each run is tracked
        assert np.isfinite(ep.keypoints_live[0]).all(), (ep.path.name, ep.metadata.get("tracking"))
    for ep in eps:
        li = ep.metadata["live_init"]
        assert li["outcome"] == "ok" and li["track_id"] == inits[0]["track_id"] and li["attempts"] == 1
    assert [ep.metadata["live_init"]["carried_over"] for ep in firsts] == [False, True]


@pytest.mark.slow
def test_failing_check_retries_then_skips_the_object_with_the_reason(tmp_path: Path, port: int) -> None:
    program = _short_program(tmp_path / "rope_short.yaml")
    cfg = _session_config(port, program, **{"tracking.live_init.max_edge_error": 1e-6,
                                            "tracking.live_init.attempts": 2, **QUICK_MOVES})
    tmp_path = tmp_path / "session"
    with Bus(cfg.bus, cfg.station.name) as bus:
        summary = Session(cfg, tmp_path, SimClock(), bus=bus, with_worker=True).run()
    assert not list(tmp_path.glob("episode_*.mcap")) and summary.frames_captured == 0
    records = _journal(tmp_path)
    (init,) = [r for r in records if r["type"] == "live_init"]
    assert init["outcome"] == "failed" and len(init["attempts"]) == 2
    assert all(a["outcome"] == "failed" and "edge-length error" in a["reason"] for a in init["attempts"])
    (run,) = [r for r in records if r["type"] == "run"]
    assert run["outcome"] == "skipped"
    assert run["reason"].startswith("live initialisation failed after 2 attempt(s): edge-length error")
    text = summary.text()
    assert "live init        : rope: FAILED after 2 attempts" in text and "skipped          : rope" in text
    assert any("live_init_failed" in i for i in summary.incidents)
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["live_init"][0]["outcome"] == "failed" and saved["live_init"][0]["attempts"] == 2


def test_a_later_run_initialises_again_after_a_worker_restart_or_a_lost_track(tmp_path: Path) -> None:
    session = Session(load_config(DEFAULT_CONFIG), tmp_path, SimClock())
    ok = InitOutcome("rope", True, "t1", worker_restarts=0)
    assert session._needs_init(None)  # the object's first run
    session._last_status = "tracking"
    assert not session._needs_init(ok)  # the track goes on into the next run
    session._last_status = "degraded"
    assert not session._needs_init(ok)
    for status in ("lost", "waiting", None):  # lost, never tracked, or no keypoints recorded in the last run
        session._last_status = status
        assert session._needs_init(ok)
    session._last_status = "tracking"
    assert session._needs_init(InitOutcome("rope", True, "t1", worker_restarts=1))  # the worker restarted since
    assert not session._needs_init(InitOutcome("rope", False, None))  # on_failure: record: not every run again
    off = Session(load_config(DEFAULT_CONFIG, {"tracking.live_init.reinitialise": False}), tmp_path, SimClock())
    off._last_status = "lost"
    assert not off._needs_init(ok)


@pytest.mark.slow
def test_on_failure_record_records_the_runs_with_the_failed_outcome(tmp_path: Path, port: int) -> None:
    program = _short_program(tmp_path / "rope_short.yaml")
    cfg = _session_config(port, program, **{"tracking.live_init.max_edge_error": 1e-6,
                                            "tracking.live_init.attempts": 1,
                                            "tracking.live_init.on_failure": "record", **QUICK_MOVES})
    out = tmp_path / "session"
    with Bus(cfg.bus, cfg.station.name) as bus:
        summary = Session(cfg, out, SimClock(), bus=bus, with_worker=True).run()
    assert summary.runs_done == 1 and not summary.runs_skipped, summary.text()
    (run,) = [r for r in _journal(out) if r["type"] == "run"]
    assert run["outcome"] == "done"
    eps = [load_episode(p, images=False) for p in sorted(out.glob("episode_*.mcap"))]
    assert eps and all(ep.metadata["live_init"]["outcome"] == "failed" for ep in eps)
    assert "edge-length error" in eps[0].metadata["live_init"]["reason"]
