"""A fake ``pyrealsense2`` module: pipeline/config/align with synthetic frames, stalls and restarts.

Follows pyrealsense2's API: ``rs.config().enable_stream(stream, w, h, format, fps)``,
``rs.pipeline().start(cfg) -> profile``, ``profile.get_device().first_depth_sensor()
.get_depth_scale()``, ``profile.get_stream(rs.stream.color).as_video_stream_profile()
.get_intrinsics()`` (fx, fy, ppx, ppy, width, height), ``pipeline.wait_for_frames(timeout_ms)``
raising ``RuntimeError("Frame didn't arrive within N")``, ``rs.align(rs.stream.color).process``.
"""

from __future__ import annotations

import types
from typing import Any

import numpy as np

stream = types.SimpleNamespace(depth="depth", color="color")
format = types.SimpleNamespace(z16="z16", rgb8="rgb8", bgr8="bgr8")  # noqa: A001 - pyrealsense2's name
option = types.SimpleNamespace(laser_power="laser_power")
camera_info = types.SimpleNamespace(serial_number="serial_number")
frame_metadata_value = types.SimpleNamespace(frame_timestamp="frame_timestamp")

# Names a double offers that the real pyrealsense2 does not: state and fault injection.
DOUBLE_ONLY = {"State", "STATE", "make_module", "DOUBLE_ONLY", "LASER_RANGE", "Intrinsics"}
LASER_RANGE = (0.0, 360.0, 30.0, 150.0)  # D4xx laser_power option: min, max, step, default (mW)


class _OptionRange:
    def __init__(self, lo: float, hi: float, step: float, default: float) -> None:
        self.min, self.max, self.step, self.default = lo, hi, step, default


class State:
    """Shared device state and fault injection for one test."""

    def __init__(self) -> None:
        self.serial = "123456789012"
        self.stall = 0  # next N wait_for_frames time out
        self.start_failures = 0  # next N pipeline.start calls fail
        self.starts = 0
        self.stops = 0
        self.resets = 0
        self.frame_number = 0
        self.metadata = True
        self.stamp_offset_us = 0  # added to the 32-bit frame_timestamp counter (to place a wrap)
        self.options: dict[str, float] = {}
        self.aligned = 0
        self.enabled: list[tuple[Any, ...]] = []
        self.timeouts: list[int] = []


STATE = State()


class Intrinsics:
    def __init__(self, w: int, h: int) -> None:
        self.width, self.height = w, h
        self.fx = self.fy = 0.9 * w
        self.ppx, self.ppy = w / 2 - 0.3, h / 2 + 0.7


class config:  # noqa: N801 - pyrealsense2's name
    DOUBLE_ONLY = {"streams", "device"}

    def __init__(self) -> None:
        self.streams: dict[str, tuple[int, int, str, int]] = {}
        self.device: str | None = None

    def enable_device(self, serial: str) -> None:
        self.device = serial

    def enable_stream(self, s: str, w: int, h: int, f: str, fps: int) -> None:
        assert isinstance(fps, int) and isinstance(w, int)
        STATE.enabled.append((s, w, h, f, fps))
        self.streams[s] = (w, h, f, fps)


class _Sensor:
    def get_depth_scale(self) -> float:
        return 0.001

    def supports(self, opt: str) -> bool:
        return opt == option.laser_power

    def is_option_read_only(self, opt: str) -> bool:
        return False

    def get_option_range(self, opt: str) -> _OptionRange:
        return _OptionRange(*LASER_RANGE)

    def set_option(self, opt: str, value: float) -> None:
        lo, hi, step, _ = LASER_RANGE
        if not lo <= value <= hi or abs((value - lo) / step - round((value - lo) / step)) > 1e-6:
            raise RuntimeError(f"hwmon command 0x80 ( 5 0 0 0 ) failed (response -7= HW not ready): {value}")
        STATE.options[opt] = value


class _Device:
    def first_depth_sensor(self) -> _Sensor:
        return _Sensor()

    def get_info(self, what: str) -> str:
        return STATE.serial

    def hardware_reset(self) -> None:
        STATE.resets += 1


class _VideoProfile:
    DOUBLE_ONLY = {"w", "h"}

    def __init__(self, w: int, h: int) -> None:
        self.w, self.h = w, h

    def as_video_stream_profile(self) -> _VideoProfile:
        return self

    def get_intrinsics(self) -> Intrinsics:
        return Intrinsics(self.w, self.h)


class _Profile:
    DOUBLE_ONLY = {"cfg"}

    def __init__(self, cfg: config) -> None:
        self.cfg = cfg

    def get_device(self) -> _Device:
        return _Device()

    def get_stream(self, s: str) -> _VideoProfile:
        w, h, _, _ = self.cfg.streams[s]
        return _VideoProfile(w, h)


class _Frame:
    DOUBLE_ONLY = {"data", "number", "stamp_ms"}

    def __init__(self, data: np.ndarray, number: int, stamp_ms: float) -> None:
        self.data, self.number, self.stamp_ms = data, number, stamp_ms

    def __bool__(self) -> bool:
        return True

    def get_data(self) -> np.ndarray:
        return self.data

    def get_frame_number(self) -> int:
        return self.number

    def get_timestamp(self) -> float:
        return self.stamp_ms

    def supports_frame_metadata(self, m: str) -> bool:
        return STATE.metadata and m == frame_metadata_value.frame_timestamp

    def get_frame_metadata(self, m: str) -> int:
        return (int(round(self.stamp_ms * 1000)) + STATE.stamp_offset_us) % (1 << 32)  # a 32-bit µs counter


class _Frameset:
    DOUBLE_ONLY = {"color", "depth", "aligned"}

    def __init__(self, color: _Frame, depth: _Frame, aligned: bool = False) -> None:
        self.color, self.depth, self.aligned = color, depth, aligned

    def get_color_frame(self) -> _Frame:
        return self.color

    def get_depth_frame(self) -> _Frame:
        assert self.aligned, "the driver must align depth to colour"
        return self.depth


class align:  # noqa: N801
    def __init__(self, to: str) -> None:
        assert to == stream.color

    def process(self, frames: _Frameset) -> _Frameset:
        STATE.aligned += 1
        return _Frameset(frames.color, frames.depth, aligned=True)


class pipeline:  # noqa: N801
    def __init__(self) -> None:
        self.cfg: config | None = None

    def start(self, cfg: config) -> _Profile:
        STATE.starts += 1
        if STATE.start_failures:
            STATE.start_failures -= 1
            raise RuntimeError("No device connected")
        self.cfg = cfg
        return _Profile(cfg)

    def stop(self) -> None:
        STATE.stops += 1

    def wait_for_frames(self, timeout_ms: int = 5000) -> _Frameset:
        STATE.timeouts.append(timeout_ms)
        if STATE.stall:
            STATE.stall -= 1
            raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
        w, h, _, fps = self.cfg.streams[stream.color]
        STATE.frame_number += 1
        n = STATE.frame_number
        color = np.full((h, w, 3), n % 256, dtype=np.uint8)
        depth = np.full((h, w), 1000 + n, dtype=np.uint16)
        stamp = 1000.0 + n * 1000.0 / fps  # ms since the device started
        return _Frameset(_Frame(color, n, stamp), _Frame(depth, n, stamp))


class context:  # noqa: N801
    def query_devices(self) -> list[_Device]:
        return [_Device()]


def make_module() -> types.ModuleType:
    """A fresh fake ``pyrealsense2`` module (state reset)."""
    global STATE
    STATE = State()
    mod = types.ModuleType("pyrealsense2")
    for name in ("stream", "format", "option", "camera_info", "frame_metadata_value", "config", "pipeline",
                 "align", "context"):
        setattr(mod, name, globals()[name])
    mod.STATE = STATE
    return mod
