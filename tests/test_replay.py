"""Replay camera: recorded frames played back on the clock, as a live camera would deliver them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.base import DeviceError, RGBDCamera, create_camera
from drivers.clock import SimClock
from drivers.config import ReplayCameraConfig
from drivers.replay import ReplayCamera
from orchestrator.config import ColorOutputConfig
from orchestrator.recorder import EpisodeWriter
from tdrecord import write_paper_layout
from tests.conftest import make_frame

W, H = 64, 48


def _episode(path: Path, frames: range) -> Path:
    w = EpisodeWriter(path, "cam0", color=ColorOutputConfig(codec="raw"))  # random colour compared exactly
    for n in frames:
        w.write_frame(make_frame(n, W, H), np.eye(4))
    K = make_frame(0, W, H).intrinsics.K
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.0]
    return w.close({"calibration": {"width": W, "height": H, "K": K.tolist(), "T_world_cam": T.tolist()}})


def _camera(path: Path, clock: SimClock, **kw: object) -> ReplayCamera:
    cfg = ReplayCameraConfig(path=str(path), width=W, height=H, **kw)
    cam = create_camera(cfg, clock=clock, station=None, name="x")  # unknown context is ignored
    assert isinstance(cam, ReplayCamera) and isinstance(cam, RGBDCamera)
    return cam


def test_paced_on_the_clock_with_recorded_numbers(tmp_path: Path) -> None:
    p = _episode(tmp_path / "episode_000000.mcap", range(100, 105))
    clock = SimClock(10.0)
    cam = _camera(p, clock, fps=15.0)
    assert cam.intrinsics == make_frame(0, W, H).intrinsics  # from the file, before connect
    with pytest.raises(DeviceError, match="not connected"):
        cam.read()
    cam.connect()
    assert cam.T_world_cam is not None and cam.T_world_cam[2, 3] == 1.0
    for k, n in enumerate(range(100, 105)):
        f = cam.read()
        assert clock.now() == pytest.approx(10.0 + k / 15.0)
        assert f.frame_number == n and f.host_stamp == clock.now()
        assert f.device_stamp == pytest.approx(n / 30.0)
        np.testing.assert_array_equal(f.color, make_frame(n, W, H).color)
        np.testing.assert_array_equal(f.depth, make_frame(n, W, H).depth)
    with pytest.raises(DeviceError, match="replay finished") as e:
        cam.read()
    assert e.value.recoverable is False
    with pytest.raises(DeviceError, match="replay finished"):  # and stays finished
        cam.read()
    cam.close()
    cam.close()


def test_loop_keeps_numbers_and_stamps_increasing(tmp_path: Path) -> None:
    p = _episode(tmp_path / "e.mcap", range(3))
    cam = _camera(p, SimClock(), loop=True)
    cam.connect()
    frames = [cam.read() for _ in range(8)]
    assert [f.frame_number for f in frames] == list(range(8))
    assert np.all(np.diff([f.device_stamp for f in frames]) > 0)
    np.testing.assert_array_equal(frames[4].color, make_frame(1, W, H).color)
    assert cam.loops == 2 and cam.frames_delivered == 8


def test_timeout_keeps_the_frame_and_late_reader_gets_it_at_once(tmp_path: Path) -> None:
    p = _episode(tmp_path / "e.mcap", range(4))
    clock = SimClock()
    cam = _camera(p, clock, fps=1.0)
    cam.connect()
    assert cam.read().frame_number == 0
    with pytest.raises(DeviceError, match="no frame within 0.25 s") as e:
        cam.read(timeout=0.25)
    assert e.value.recoverable and clock.now() == pytest.approx(0.25)
    assert cam.read().frame_number == 1 and clock.now() == pytest.approx(1.0)
    clock.sleep_until(5.0)  # a slow consumer: no burst to catch up, no frame lost
    assert cam.read().frame_number == 2 and clock.now() == pytest.approx(5.0)
    assert cam.read().frame_number == 3 and clock.now() == pytest.approx(6.0)


def test_reconnect_continues_where_it_stopped(tmp_path: Path) -> None:
    p = _episode(tmp_path / "e.mcap", range(5))
    cam = _camera(p, SimClock())
    cam.connect()
    assert [cam.read().frame_number for _ in range(2)] == [0, 1]
    cam.close()
    cam.connect()
    f = cam.read()
    assert f.frame_number == 2
    np.testing.assert_array_equal(f.color, make_frame(2, W, H).color)


def test_missing_source_is_not_recoverable(tmp_path: Path) -> None:
    cam = _camera(tmp_path / "nothing.mcap", SimClock())
    assert (cam.intrinsics.width, cam.intrinsics.height) == (W, H)  # nominal until the file is readable
    with pytest.raises(DeviceError, match="nothing.mcap") as e:
        cam.connect()
    assert e.value.recoverable is False


def test_replays_the_paper_layout(tmp_path: Path) -> None:
    frames = [make_frame(n, W, H) for n in range(3)]
    tcp = np.broadcast_to(np.eye(4), (3, 4, 4))
    write_paper_layout(tmp_path / "chunk", frames, T_world_cam=np.eye(4), T_world_base={"left": np.eye(4),
                       "right": np.eye(4)}, tcp_left=tcp, tcp_right=tcp)
    clock = SimClock()
    cam = _camera(tmp_path / "chunk", clock)
    assert cam.intrinsics == frames[0].intrinsics
    cam.connect()
    got = [cam.read() for _ in range(3)]
    np.testing.assert_array_equal(got[2].color, frames[2].color)
    assert clock.now() == pytest.approx(2 / 30)
    with pytest.raises(DeviceError, match="replay finished"):
        cam.read()
