"""The in-memory form of a recorded sequence, for offline tracking, replay and exports.

A :class:`Sequence` holds per-frame arrays in the world frame (SI units) and a lazily decoded
:class:`FrameSource` of frames; :mod:`tdrecord.episodes` and :mod:`tdrecord.paper` fill it.
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from tdcommon.types import CameraIntrinsics, GroundTruth, RGBDFrame

DEPTH_SCALE_MM = 0.001  # m per depth unit of every format read here


class DatasetError(ValueError):
    """A dataset file is missing a channel/key, has the wrong shape, or is unfinished; the message names the file."""


@dataclass(frozen=True)
class DepthImage:
    """One frame's depth for tracking: depth (H, W) uint16, ``depth * depth_scale`` metres, 0 = no data;
    frame_number: the frame's index in its sequence; ground_truth as in RGBDFrame; color (H, W, 3) uint8 RGB where
    the reader has it without decoding a video (None: a depth-only reader)."""

    depth: np.ndarray
    depth_scale: float
    frame_number: int
    ground_truth: GroundTruth | None = None
    color: np.ndarray | None = None

    def depth_m(self) -> np.ndarray:
        """(H, W) float32 depth in metres, 0 where missing (as ``RGBDFrame.depth_m``)."""
        return self.depth.astype(np.float32) * np.float32(self.depth_scale)


class FrameSource:
    """A re-iterable, lazily decoded run of frames: every ``iter()`` reads them from disk again.

    depth_factory(start, colour), when given, yields the frames' depth (``DepthImage``), with their colour where
    colour is true and without decoding it where it is false (a cloth's tracking reads none); without it
    ``iter_depth`` reads whole frames.
    """

    def __init__(self, factory: Callable[[int], Iterator[RGBDFrame]], length: int,
                 depth_factory: Callable[[int, bool], Iterator[DepthImage]] | None = None) -> None:
        self._factory = factory
        self._length = int(length)
        self._depth_factory = depth_factory

    def __iter__(self) -> Iterator[RGBDFrame]:
        return self._factory(0)

    def __len__(self) -> int:
        return self._length

    def iter_from(self, start: int) -> Iterator[RGBDFrame]:
        """Frames ``start, start + 1, ...`` (earlier ones are skipped without being decoded where possible)."""
        return self._factory(max(0, int(start)))

    def iter_depth(self, start: int = 0, colour: bool = True) -> Iterator[DepthImage | RGBDFrame]:
        """The depth of frames ``start, start + 1, ...``: ``DepthImage`` from the depth reader (with its colour
        where ``colour``), else whole frames (both have ``depth``, ``depth_scale``, ``ground_truth``, ``color``
        and ``depth_m()``)."""
        if self._depth_factory is not None:
            return self._depth_factory(max(0, int(start)), colour)
        return self.iter_from(start)


def iter_depth(frames: Iterable[RGBDFrame], colour: bool = True) -> Iterator[DepthImage | RGBDFrame]:
    """The depth of every frame of ``frames`` (a FrameSource: its depth reader where it has one, with the colour where
    ``colour``; a list: the frames themselves)."""
    return frames.iter_depth(colour=colour) if isinstance(frames, FrameSource) else iter(frames)


_Item = TypeVar("_Item")


def lower_thread_priority(steps: int = 5) -> None:
    """Make the calling thread yield to the others of its process when the cores are busy (Linux: a thread's
    nice value is its own; raising it needs no privilege); elsewhere a no-op."""
    if not hasattr(os, "setpriority"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + steps))
    except OSError:
        pass


def usable_cores() -> int:
    """The number of CPU cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def read_ahead(make: Callable[[], Iterator[_Item]], depth: int = 4) -> Iterator[_Item]:
    """The items of ``make()``, produced by a reader thread up to ``depth`` items ahead of the consumer.

    Decompression (zlib) and file reads release the GIL, so a clip is decoded while the consumer computes;
    at most ``depth + 1`` items are held. An exception in the reader is raised to the consumer at the point
    of the stream where it happened; closing the returned generator stops the reader. A process allowed
    only one core gets the items made inline instead: a thread would only interleave with the consumer
    there (and its decoding would land inside the consumer's timed steps).
    """
    if usable_cores() <= 1:
        return make()
    q: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()

    def put(entry: tuple[str, Any]) -> bool:
        while not stop.is_set():
            try:
                q.put(entry, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        it = make()
        try:
            for item in it:
                if not put(("item", item)):
                    return
            put(("end", None))
        except BaseException as e:  # noqa: BLE001 - handed to the consumer, which re-raises it
            put(("error", e))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    def consume() -> Iterator[_Item]:
        t = threading.Thread(target=run, name="read-ahead", daemon=True)
        t.start()
        try:
            while True:
                kind, value = q.get()
                if kind == "end":
                    return
                if kind == "error":
                    raise value
                yield value
        finally:
            stop.set()
            t.join()

    return consume()


@dataclass
class Sequence:
    """One recorded sequence for offline tracking; per-frame arrays have T rows, all in the world frame (m, rad).

    frames: T RGBDFrame (colour RGB uint8, depth uint16 × depth_scale m), lazily decoded (FrameSource) or a list.
    T_world_cam: (4, 4) camera optical frame in the world. K: (3, 3) intrinsics of the (aligned) colour image.
    q_left / q_right: (T, 7) rad, joint states nearest in time to each frame, or None.
    tcp_left / tcp_right: (T, 4, 4) TCP poses in the world, or None.
    T_world_base: {"left", "right"} -> (4, 4) robot base poses in the world, or None.
    ground_truth: T GroundTruth (or None per frame) in mock-mode episodes, else None.
    stamps: (T,) s host stamps; frame_numbers: (T,) int64; grasped_left / grasped_right: (T,) bool or None;
    gripper_width_left / gripper_width_right: (T,) m finger opening or None.
    """

    frames: Iterable[RGBDFrame]
    T_world_cam: np.ndarray
    K: np.ndarray
    width: int = 0
    height: int = 0
    q_left: np.ndarray | None = None
    q_right: np.ndarray | None = None
    tcp_left: np.ndarray | None = None
    tcp_right: np.ndarray | None = None
    T_world_base: dict[str, np.ndarray] | None = None
    ground_truth: list[GroundTruth | None] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    source: Path = field(default_factory=Path)
    stamps: np.ndarray | None = None
    frame_numbers: np.ndarray | None = None
    grasped_left: np.ndarray | None = None
    grasped_right: np.ndarray | None = None
    gripper_width_left: np.ndarray | None = None
    gripper_width_right: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frames)  # type: ignore[arg-type]

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the colour image (from K and the image size)."""
        return CameraIntrinsics.from_K(self.K, self.width, self.height)


def nearest_index(source: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(T,) index into ``source`` (S,) stamps of the stamp nearest each ``query`` (T,) stamp (ties: earlier)."""
    source = np.asarray(source, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    if len(source) == 0:
        raise ValueError("nearest_index: no source stamps")
    order = np.argsort(source, kind="stable")
    s = source[order]
    if len(s) == 1:
        return np.zeros(len(query), dtype=np.int64)
    i = np.clip(np.searchsorted(s, query), 1, len(s) - 1)
    take_left = (query - s[i - 1]) <= (s[i] - query)
    return order[np.where(take_left, i - 1, i)]


def check_rigid(T: np.ndarray, where: str) -> np.ndarray:
    """T as a (4, 4) float64 rigid transform, or a DatasetError naming ``where``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatasetError(f"{where}: expected shape (4, 4), got {T.shape}")
    R = T[:3, :3]
    if not (np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) and np.allclose(R @ R.T, np.eye(3), atol=1e-3)):
        raise DatasetError(f"{where}: not a rigid transform (rotation not orthonormal or last row not [0 0 0 1])")
    return T
