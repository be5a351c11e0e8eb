"""Program execution on the mock station in simulated time: synchronised start, arm and camera faults, refusal."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.clock import SimClock
from orchestrator.config import DEFAULT_CONFIG, Config, load_config
from orchestrator.session import Session, SessionSummary, Station
from tdrecord import read_episode_metadata
from trajectories.program import Program, Waypoint, library_path, load_program, save_program

# s after the station connects: mid-program (settle 0.5 s, program ~5.8 s at fast) and mid-episode (1 s episodes)
FAULT_AFTER = 2.35


def make_config(programs: list[str] | None = None) -> Config:
    """The mock config in simulated time, small and quick: the rope only, fast, 10 fps, 1 s episodes."""
    cfg = load_config(DEFAULT_CONFIG, {
        "clock": "sim", "station.camera.width": 160, "station.camera.height": 120,
        "tracking.enabled": False, "bus.enabled": False,
        "station.camera.fps": 10, "plan.speeds": ["fast"], "plan.episode_seconds": 1.0,
    })
    data = cfg.model_dump()
    data["plan"]["objects"] = [o for o in data["plan"]["objects"] if o["name"] == "rope"]
    if programs is not None:
        data["plan"]["objects"][0]["programs"] = programs
    return Config.model_validate(data)


def run(tmp_path: Path, on_station: Any = None, programs: list[str] | None = None,  # noqa: ANN401
        max_seconds: float = 60.0) -> SessionSummary:
    """Run the plan once in simulated time with ``on_station`` called on the connected station."""
    session = Session(make_config(programs), tmp_path / "out", SimClock(), on_station=on_station)
    return session.run(max_seconds=max_seconds)


def metadata(summary: SessionSummary) -> list[dict[str, Any]]:
    """Each finished episode's metadata, in order."""
    return [read_episode_metadata(p) for p in summary.episodes]


def no_active_files(summary: SessionSummary) -> bool:
    """No episode left half-written."""
    return not list(summary.out_dir.glob("*.active")) and not list(summary.out_dir.glob("*.active*"))


def test_both_arms_start_together(tmp_path: Path) -> None:
    starts: dict[str, list[float]] = {"left": [], "right": []}

    def watch_starts(station: Station) -> None:
        for name, arm in station.arms.items():
            start = arm.start_motion

            def timed_start(motion: Any, name: str = name, start: Any = start) -> None:  # noqa: ANN401
                start(motion)
                starts[name].append(station.clock.now())

            arm.start_motion = timed_start  # type: ignore[method-assign]

    summary = run(tmp_path, watch_starts)
    assert summary.runs_done == 1 and not summary.runs_failed and not summary.errors, summary.text()
    assert len(starts["left"]) == len(starts["right"]) == 1
    assert starts["left"] == pytest.approx(starts["right"], abs=1e-9)
    assert summary.start_skew_s == pytest.approx(0.0, abs=1e-9)
    assert "arm start skew   : 0.000 ms" in summary.text()
    meta = metadata(summary)
    assert all(m["complete"] and not m["fault"] for m in meta)
    assert [s["kind"] for s in meta[0]["segments"]] == ["move"] * 4  # started at the program's first waypoint


def test_start_skew_is_measured_and_reported(tmp_path: Path) -> None:
    """A left arm whose start call takes 4 ms (simulated) starts the right arm 4 ms late: the summary says so."""
    starts: dict[str, float] = {}

    def slow_left_start(station: Station) -> None:
        left, right = station.arms["left"], station.arms["right"]
        left_start, right_start = left.start_motion, right.start_motion

        def slow(motion: Any) -> None:  # noqa: ANN401
            left_start(motion)
            starts["left"] = station.clock.now()
            station.clock.sleep_until(station.clock.now() + 0.004)

        def timed(motion: Any) -> None:  # noqa: ANN401
            right_start(motion)
            starts["right"] = station.clock.now()

        left.start_motion = slow  # type: ignore[method-assign]
        right.start_motion = timed  # type: ignore[method-assign]

    summary = run(tmp_path, slow_left_start)
    assert summary.runs_done == 1, summary.text()
    assert starts["right"] - starts["left"] == pytest.approx(0.004, abs=1e-9)
    assert summary.start_skew_s == pytest.approx(0.004, abs=1e-9)
    assert "arm start skew   : 4.000 ms" in summary.text()


def test_recoverable_arm_fault_is_recovered_and_the_run_completes(tmp_path: Path) -> None:
    def reflex(station: Station) -> None:
        station.arms["left"].inject_fault(station.clock.now() + FAULT_AFTER, recoverable=True,  # type: ignore[attr-defined]
                                          message="cartesian reflex")

    summary = run(tmp_path, reflex)
    assert summary.faults_recovered == 1, summary.text()
    assert summary.runs_done == 1 and not summary.runs_failed, summary.text()
    meta = metadata(summary)
    faulted = [i for i, m in enumerate(meta) if m["fault"]]
    assert len(faulted) == 1
    i = faulted[0]
    assert meta[i]["complete"] is False
    assert all(m["complete"] for m in meta[:i])
    later = meta[i + 1:]
    assert later and all(m["complete"] and not m["fault"] for m in later)
    # the retry resumes the faulted segment from where the arm froze: a slow (4 s) approach to that
    # segment's waypoint, then the rest of the program at the run's speed
    k = later[0]["start_waypoint"]
    assert k >= 1
    retry = later[0]["segments"]
    assert retry[0]["kind"] == "approach" and retry[0]["requested"] == pytest.approx(4.0)
    assert [s["kind"] for s in retry[1:]] == ["move"] * (4 - k)
    assert all(s["requested"] == pytest.approx(1.25) for s in retry[1:])  # fast
    chunks = [m["chunk_index"] for m in meta]
    assert chunks == list(range(len(meta)))  # one run, numbered on across the retry
    assert no_active_files(summary)


def test_unrecoverable_arm_fault_fails_the_run_and_closes_every_episode(tmp_path: Path) -> None:
    def broken(station: Station) -> None:
        station.arms["right"].inject_fault(station.clock.now() + FAULT_AFTER, recoverable=False,  # type: ignore[attr-defined]
                                           message="joint 4 encoder error")

    summary = run(tmp_path, broken)
    assert summary.runs_done == 0 and summary.faults_recovered == 0
    assert len(summary.runs_failed) == 1, summary.text()
    msg = summary.runs_failed[0]
    assert "rope" in msg and "rope_swing" in msg and "device fault" in msg and "right arm: joint 4 encoder error" in msg
    assert f"problem          : {msg}" in summary.text()
    assert no_active_files(summary)
    meta = metadata(summary)  # every file finished and readable
    assert len(meta) == len(list(summary.out_dir.glob("episode_*.mcap"))) >= 2
    assert meta[-1]["fault"] is True and meta[-1]["complete"] is False
    assert all(m["complete"] and not m["fault"] for m in meta[:-1])


def test_camera_errors_are_retried_without_failing_the_run(tmp_path: Path) -> None:
    def flaky(station: Station) -> None:
        # three failed reads: the session retries, then reconnects the camera and goes on
        station.camera.inject_fault("error", count=3)  # type: ignore[attr-defined]

    summary = run(tmp_path, flaky)
    assert summary.runs_done == 1 and not summary.runs_failed and not summary.errors, summary.text()
    assert summary.faults_recovered == 0
    meta = metadata(summary)
    assert meta and all(m["complete"] and not m["fault"] for m in meta)


def test_colliding_program_is_refused_before_any_motion(tmp_path: Path) -> None:
    w0 = load_program(library_path("rope_swing")).waypoints[0]
    left, right = list(w0.left), list(w0.right)
    left[0], right[0] = -0.6, 0.6  # both shoulders swing inwards: the hands meet between the arms
    bad = Program(name="hands_meet", category="dlo", waypoints=[w0, Waypoint(left=left, right=right), w0])
    path = tmp_path / "hands_meet.yaml"
    save_program(bad, path)

    arms: dict[str, Any] = {}
    summary = run(tmp_path, lambda station: arms.update(station.arms), programs=[str(path)])
    assert summary.runs_done == 0 and len(summary.runs_failed) == 1, summary.text()
    msg = summary.runs_failed[0]
    assert "hands_meet at fast refused before motion" in msg
    assert "segment 0 (move to waypoint 1)" in msg and "left panda_hand collides with right panda_hand" in msg
    assert "t=0." in msg  # the time of the first contact is named
    assert summary.episodes == [] and summary.frames_captured == 0
    home = {n: np.asarray(getattr(make_config().station, n).arm.home) for n in ("left", "right")}
    for name, arm in arms.items():
        np.testing.assert_allclose(arm.read_state().q, home[name], atol=1e-9)  # never moved


def test_fault_at_an_episode_boundary_marks_the_episode(tmp_path: Path) -> None:
    def reflex(station: Station) -> None:
        station.arms["left"].inject_fault(station.clock.now() + 2.0, recoverable=True)  # type: ignore[attr-defined]

    summary = run(tmp_path, reflex, max_seconds=4.0)  # stops two episodes into the retry
    assert summary.runs_done == 1 and summary.faults_recovered == 1, summary.text()
    meta = metadata(summary)
    assert [m["fault"] for m in meta].count(True) == 1


def test_unrecoverable_fault_then_another_run_on_the_same_station(tmp_path: Path) -> None:
    cfg = make_config()
    data = cfg.model_dump()
    data["plan"]["repeats"] = 2
    cfg = Config.model_validate(data)

    def broken(station: Station) -> None:
        station.arms["right"].inject_fault(station.clock.now() + FAULT_AFTER, recoverable=False)  # type: ignore[attr-defined]

    summary = Session(cfg, tmp_path / "out", SimClock(), on_station=broken).run(max_seconds=60.0)
    assert summary.runs_done == 0 and len(summary.runs_failed) == 2, summary.text()
    assert no_active_files(summary)


def test_reflex_after_the_last_waypoint_ends_the_run_done(tmp_path: Path) -> None:
    """A reflex while the arms hold at the last waypoint (recording fills the last episode): nothing is left to
    retry, so the run ends done with the episode cut short (this crashed on an empty motion before)."""
    def late_reflex(station: Station) -> None:
        station.arms["left"].inject_fault(station.clock.now() + 5.8, recoverable=True,  # type: ignore[attr-defined]
                                          message="reflex while holding")

    summary = run(tmp_path, late_reflex)
    assert summary.faults_recovered == 1 and summary.runs_done == 1 and not summary.runs_failed, summary.text()
    meta = metadata(summary)
    assert meta[-1]["fault"] is True and meta[-1]["complete"] is False
    assert all(m["complete"] and not m["fault"] for m in meta[:-1])
    assert no_active_files(summary)
