"""Camera–arm time sync: the clock offset estimated online, frames paired with the joints at their capture time."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from drivers.clock import SimClock
from orchestrator.config import Config
from orchestrator.session import Session
from orchestrator.timesync import ClockOffsetEstimator, StateHistory, TimeSync
from tdcommon.wire import decode_frame, encode_frame
from tdrecord import read_episode_metadata, read_episodes
from tests.conftest import make_frame
from tests.test_journal import make_config

OFFSET, DRIFT_PPM, LATENCY, JITTER = 1000.0, 200.0, 0.04, 0.01


def test_the_offset_estimate_follows_offset_and_drift_under_jitter() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(0, 60, 1 / 30)  # capture times, host clock
    device = OFFSET + t * (1 + DRIFT_PPM * 1e-6)
    host = t + LATENCY + JITTER * rng.random(len(t))
    est = ClockOffsetEstimator(window_s=30.0)
    errors = []
    for d, h, tc in zip(device, host, t, strict=True):
        est.add(d, h)
        errors.append(d + est.envelope(d) - LATENCY - tc)  # estimated minus true capture time
    errors = np.abs(errors)
    assert errors[:5].max() < JITTER  # from the first frame on, never worse than the jitter
    assert errors[300:].max() < 1.5e-3  # after 10 s: within 1.5 ms though arrivals jitter by up to 10 ms
    assert abs(est.drift_ppm - DRIFT_PPM) < 60


def test_a_device_clock_reset_restarts_the_estimate() -> None:
    est = ClockOffsetEstimator()
    for i in range(100):
        est.add(500.0 + i / 30, i / 30 + 0.02)
    for i in range(100, 130):
        est.add(i / 30 - 3.3, i / 30 + 0.02)  # a reconnected camera counts from 0 again
    assert est.resets == 1
    assert abs(est.envelope(129 / 30 - 3.3) - 3.32) < 1e-9


def test_state_history_interpolates_joints_and_holds_the_grasp_flag() -> None:
    h = StateHistory(capacity=8)
    for k in range(12):  # wraps the ring
        q = np.full(7, float(k))
        h.add({"stamp": k * 0.004, "left": {"q": q, "gripper_width": 0.08, "grasped": k >= 6},
               "right": {"q": -q, "gripper_width": 0.04, "grasped": False}})
    row, err = h.at(6.25 * 0.004)
    np.testing.assert_allclose(row[:7], 6.25)
    np.testing.assert_allclose(row[7:14], -6.25)
    assert row[16] == 1.0 and abs(err - 0.25 * 0.004) < 1e-12
    row, err = h.at(20 * 0.004)  # beyond the newest: held, the error says how far
    np.testing.assert_allclose(row[:7], 11.0)
    assert abs(err - 9 * 0.004) < 1e-12


def test_the_joint_state_travels_in_the_frame_header() -> None:
    js = {"stamp": 1.5, "left": {"q": [0.1] * 7, "gripper_width": 0.08, "grasped": False},
          "right": {"q": [0.2] * 7, "gripper_width": 0.08, "grasped": True}, "u": [0.0] * 12, "pairing_error_s": 0.001}
    msg = decode_frame(encode_frame(make_frame(3), np.eye(4), "cam0", {"run_index": 0}, joint_state=js))
    assert msg.joint_state == js
    assert decode_frame(encode_frame(make_frame(3), np.eye(4), "cam0")).joint_state is None


def _offset_camera_config() -> Config:
    cfg = make_config()
    data = cfg.model_dump()
    data["station"]["camera"].update(clock_offset=OFFSET, clock_drift_ppm=DRIFT_PPM, latency=LATENCY,
                                     latency_jitter=JITTER)
    data["sync"] = {"camera_latency_s": LATENCY}
    return Config.model_validate(data)


def _true_q(states: list[dict[str, Any]], t: np.ndarray, arm: str) -> np.ndarray:
    """(T, 7) joints at times t, from the recorded 250 Hz samples (linear between them)."""
    stamps = np.array([s["stamp"] for s in states])
    q = np.array([s[arm]["q"] for s in states])
    return np.stack([np.interp(t, stamps, q[:, j]) for j in range(7)], axis=1)


def test_frames_of_an_offset_drifting_late_camera_get_the_joints_at_capture_time(tmp_path: Path) -> None:
    cfg = _offset_camera_config()
    fps = cfg.station.camera.fps
    Session(cfg, tmp_path, SimClock()).run()
    files = sorted(tmp_path.glob("episode_*.mcap"))
    assert len(files) >= 3
    states: list[dict[str, Any]] = []
    for f in files:
        with open(f, "rb") as fh:
            states += [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=["/arms/state"])]
    seq = read_episodes(tmp_path)
    assert seq.metadata["frames_paired_at_capture"] == len(seq)
    capture = seq.frame_numbers / fps  # the fake camera captures frame k at host time k / fps
    true_left = _true_q(states, capture, "left")
    moving = np.linalg.norm(_true_q(states, capture + LATENCY, "left") - true_left, axis=1) > 1e-3
    assert moving.sum() > 10  # the arms move: pairing by arrival time would be wrong by 40 ms of motion
    paired_err = np.linalg.norm(seq.q_left - true_left, axis=1)
    naive = _true_q(states, seq.stamps, "left")  # the joints at the frames' host (arrival) stamps
    naive_err = np.linalg.norm(naive - true_left, axis=1)
    assert paired_err[moving].max() < 0.15 * naive_err[moving].max()
    assert np.median(paired_err[moving]) < 0.1 * np.median(naive_err[moving])
    stamps = np.array([s["stamp"] for s in states])  # u_t (TCP poses) follows the paired joints too
    u = np.array([s["u"][:3] for s in states])
    tcp_true = np.stack([np.interp(capture, stamps, u[:, j]) for j in range(3)], axis=1)
    tcp_naive = np.stack([np.interp(seq.stamps, stamps, u[:, j]) for j in range(3)], axis=1)
    tcp_err = np.linalg.norm(seq.tcp_left[:, :3, 3] - tcp_true, axis=1)
    assert tcp_err[moving].max() < 0.15 * np.linalg.norm(tcp_naive - tcp_true, axis=1)[moving].max()
    print(f"joint error max {paired_err[moving].max():.2e} rad (by arrival {naive_err[moving].max():.2e}), "
          f"TCP error max {tcp_err[moving].max() * 1e3:.3f} mm")

    for k, f in enumerate(files):
        ts = read_episode_metadata(f)["time_sync"]
        assert ts["latency_s"] == LATENCY and ts["frames_unpaired"] == 0 and ts["frames_paired"] > 0
        # at most half a joint-state period; the very first frame's capture time is off by its own jitter
        assert ts["pairing_error_s"]["max"] <= (1 / 250 / 2 if k else JITTER + 1 / 250) + 1e-9
        drift_s = DRIFT_PPM * 1e-6 * read_episode_metadata(f)["first_frame"] / fps
        assert abs(ts["device_minus_host_s"] - (OFFSET + drift_s)) < JITTER
        assert LATENCY - 1e-3 <= ts["arrival_delay_s"]["mean"] <= LATENCY + JITTER + 1e-3


def test_a_frame_without_a_joint_state_near_its_capture_time_is_unpaired() -> None:
    sync = TimeSync(0.0, lambda arm, q: np.zeros(6), max_gap_s=0.01)
    assert sync.pair(0, 10.0, 0.02) is None  # no joint state at all yet
    sync.states.add({"stamp": 0.0, "left": {"q": [0.0] * 7, "gripper_width": 0.08, "grasped": False},
                     "right": {"q": [0.0] * 7, "gripper_width": 0.08, "grasped": False}})
    assert sync.pair(1, 10.1, 0.12) is None  # 0.1 s after the only sample
    paired = sync.pair(2, 9.98, 0.0)  # captured when the sample was taken
    assert paired is not None and paired["pairing_error_s"] == 0.0 and paired["stamp"] == 0.0
    rep = sync.episode_report(9.98)
    assert rep["frames_unpaired"] == 2 and rep["frames_paired"] == 1
    assert abs(rep["device_minus_host_s"] - 9.98) < 1e-9
