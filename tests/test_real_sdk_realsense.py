"""RealSenseCamera against the real pyrealsense2: a .db3 recorded here from ``rs.software_device``.

The recording holds depth (Z16) and colour (RGB8) with ``frame_timestamp`` metadata that wraps
past 2**32 µs, one dropped frame number, and ends (the "disconnect": no more frames). The
driver plays it through the real pipeline, align and metadata code paths.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from drivers.base import DeviceError
from drivers.clock import SimClock
from drivers.config import RealSenseCameraConfig
from drivers.realsense import RealSenseCamera, set_laser_power

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install '.[realsense]')")
pytestmark = pytest.mark.real_sdk

W, H, FPS = 64, 48, 30
SERIAL = "123456789012"
PERIOD_US = 33_333
FRAME_NUMBERS = [1, 2, 3, 4, 6, 7, 8, 9]  # 5 is dropped
WRAP_BEFORE = 3  # the 32-bit µs counter wraps between frames 3 and 4


def stamp_us(n: int) -> int:
    """frame_timestamp metadata of frame ``n``: a 32-bit counter that wraps after frame WRAP_BEFORE."""
    return ((1 << 32) - (WRAP_BEFORE + 1) * PERIOD_US + n * PERIOD_US + PERIOD_US // 2) % (1 << 32)


def _stream(kind: object, fmt: object, bpp: int, uid: int) -> object:
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = W, H, 50.0, 51.0, 31.5, 23.5
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = kind, 0, uid, W, H, FPS, bpp, fmt
    vs.intrinsics = intr
    return vs


def laser_range() -> object:
    """The D4xx laser_power range, 0-360 mW in 30 mW steps, default 150.

    Set by attribute: this pyrealsense2's 4-argument option_range constructor stores its
    third and fourth arguments as default and step, not step and default as documented.
    """
    r = rs.option_range()
    r.min, r.max, r.step, r.default = 0.0, 360.0, 30.0, 150.0
    return r


def _inject(sensor: object, profile: object, n: int, pixels: np.ndarray, bpp: int) -> None:
    f = rs.software_video_frame()
    f.pixels, f.stride, f.bpp = pixels, W * bpp, bpp
    f.timestamp = stamp_us(n) / 1000.0
    f.domain = rs.timestamp_domain.hardware_clock
    f.frame_number = n
    f.profile = profile.as_video_stream_profile()
    if bpp == 2:
        f.depth_units = 0.001
    sensor.set_metadata(rs.frame_metadata_value.frame_timestamp, stamp_us(n))
    sensor.on_video_frame(f)


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """Record the software device's frames to a .db3 file with rs.recorder."""
    path = tmp_path / "d455.db3"
    dev = rs.software_device()
    dev.register_info(rs.camera_info.serial_number, SERIAL)
    dev.register_info(rs.camera_info.name, "Intel RealSense D455 (software)")
    depth_sensor, color_sensor = dev.add_sensor("Stereo Module"), dev.add_sensor("RGB Camera")
    dprof = depth_sensor.add_video_stream(_stream(rs.stream.depth, rs.format.z16, 2, 0), True)
    cprof = color_sensor.add_video_stream(_stream(rs.stream.color, rs.format.rgb8, 3, 1), True)
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    depth_sensor.add_option(rs.option.laser_power, laser_range(), True)
    dev.create_matcher(rs.matchers.dlr_c)
    recorder = rs.recorder(str(path), dev)
    depth_sensor.open(dprof)
    color_sensor.open(cprof)
    syncer = rs.syncer()
    depth_sensor.start(syncer)
    color_sensor.start(syncer)
    for n in FRAME_NUMBERS:
        _inject(depth_sensor, dprof, n, np.full((H, W), 1000 + n, np.uint16), 2)
        _inject(color_sensor, cprof, n, np.full((H, W, 3), n, np.uint8), 3)
        time.sleep(1.0 / FPS)
        syncer.poll_for_frames()
    for s in (depth_sensor, color_sensor):
        s.stop()
        s.close()
    del recorder  # flushes and closes the file
    assert path.stat().st_size > 0
    return path


@pytest.fixture
def playback(recording: Path, monkeypatch):
    """The real rs.config pointed at the recording, and a real pipeline that plays it frame by frame.

    Playback at recorded pace would skip frames while the driver connects; not real time, it
    hands out every recorded frame in order. Everything else the driver builds is untouched.
    """
    real_config, real_pipeline = rs.config, rs.pipeline

    def config_from_file() -> object:
        cfg = real_config()
        cfg.enable_device_from_file(str(recording), False)
        return cfg

    class FramePacedPipeline(real_pipeline):
        def start(self, cfg: object) -> object:
            profile = super().start(cfg)
            profile.get_device().as_playback().set_real_time(False)
            return profile

    monkeypatch.setattr(rs, "config", config_from_file)
    monkeypatch.setattr(rs, "pipeline", FramePacedPipeline)
    return recording


def cam(**kw) -> RealSenseCamera:
    cfg = RealSenseCameraConfig(id="d455", serial=SERIAL, width=W, height=H, fps=FPS, start_timeout=2.0, **kw)
    return RealSenseCamera(cfg, clock=SimClock(1.0))


def test_driver_plays_a_recording_with_a_stamp_wrap_a_drop_and_the_end_of_stream(playback: Path):
    c = cam(laser_power=160.0)
    c.connect()
    assert c.serial == SERIAL and c.depth_scale == pytest.approx(0.001)
    assert c.laser_power is None  # a played-back sensor's laser_power is read-only: left alone
    k = c.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (W, H, pytest.approx(50.0), pytest.approx(51.0),
                                                            pytest.approx(31.5), pytest.approx(23.5))
    frames = []
    with pytest.raises(DeviceError, match="no frame within") as end:
        for _ in range(20):
            frames.append(c.read(timeout=0.5))
    assert end.value.recoverable
    numbers = [f.frame_number for f in frames]
    assert numbers[-1] == FRAME_NUMBERS[-1] and {WRAP_BEFORE, WRAP_BEFORE + 1} <= set(numbers)
    f = frames[-1]
    assert f.color.shape == (H, W, 3) and f.depth.shape == (H, W) and f.depth.dtype == np.uint16
    assert f.color[0, 0].tolist() == [f.frame_number] * 3
    stamps = np.array([x.device_stamp for x in frames])
    assert np.all(np.diff(stamps) >= 0), "device_stamp went back (the 32-bit counter wrap was not unwrapped)"
    assert stamps[-1] == pytest.approx(((1 << 32) + (FRAME_NUMBERS[-1] - WRAP_BEFORE - 1) * PERIOD_US
                                        + PERIOD_US // 2) * 1e-6)
    assert c._unwrap.wraps == 1
    assert c.dropped == 1  # frame number 5 never came
    c.close()


def test_recover_after_the_device_is_gone_says_no_device_was_reset(playback: Path):
    c = cam()
    c.connect()
    playback.unlink()  # the "cable pulled": the device behind the config is gone
    with pytest.raises(DeviceError) as info:
        c.recover()
    assert f"no RealSense device with serial {SERIAL}" in str(info.value)
    assert "reset;" not in str(info.value)
    c.close()


def test_laser_power_is_set_on_the_options_step_of_a_real_sensor():
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    sensor.add_option(rs.option.laser_power, laser_range(), True)
    with pytest.raises(RuntimeError):
        sensor.set_option(rs.option.laser_power, 160.0)  # librealsense rejects an off-step value
    assert set_laser_power(rs, sensor, 160.0) == 150.0
    assert sensor.get_option(rs.option.laser_power) == 150.0
    assert set_laser_power(rs, sensor, 1000.0) == 360.0
    ro = dev.add_sensor("RGB Camera")
    ro.add_read_only_option(rs.option.laser_power, 90.0)
    assert set_laser_power(rs, ro, 150.0) is None
