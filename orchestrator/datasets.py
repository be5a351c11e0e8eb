"""Offline dataset I/O: episode MCAP files and the paper's published folder layout, read into one ``Sequence``.

Readers:

- :func:`read_episodes`: one episode ``.mcap`` or a folder of them (this daemon's output).
- :func:`read_paper_layout`: a folder as the paper's published code reads it (``rgbd.npz``, per-arm
  pose files, ``calibration/transform_ee_cam_world.npz``).
- :func:`read_sequence`: either, chosen from what the path is.

Frames are decoded lazily: ``Sequence.frames`` is a :class:`FrameSource` that reads them from disk
again at every iteration (one frame in memory at a time), since 1280×720 sequences are gigabytes.
Everything else (calibration, joint states, TCP poses, ground truth) is read eagerly. Units inside
are SI (m, s, rad); millimetres appear only in the files of the paper's layout and in
``3d_keypoints.npz`` (:func:`write_reference_npz`), as the paper's code expects them.
"""

from __future__ import annotations

import inspect
import json
import logging
import math
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.types import CameraIntrinsics, GroundTruth, RGBDFrame
from orchestrator.recorder import ACTIVE_SUFFIX
from tdrecord.channels import edges_from_json, points_from_json
from tdrecord.codecs import SCHEMA_RAW, SCHEMA_VIDEO, CodecError, ImageDecoder

log = logging.getLogger(__name__)

DEPTH_SCALE_MM = 0.001  # m per depth unit of every format read here
RGBD_FILE = "rgbd.npz"
POSE_FILES = {"left": "left_arm_poses.npz", "right": "right_arm_poses.npz"}
CALIBRATION_FILE = "calibration/transform_ee_cam_world.npz"
JOINT_FILE = "joint_states.npz"
REFERENCE_FILE = "3d_keypoints.npz"


class DatasetError(ValueError):
    """A dataset file is missing a channel/key, has the wrong shape, or is unfinished; the message names the file."""


# ---------------------------------------------------------------------------------------------- containers
class FrameSource:
    """A re-iterable, lazily decoded run of frames: every ``iter()`` reads them from disk again."""

    def __init__(self, factory: Callable[[int], Iterator[RGBDFrame]], length: int) -> None:
        self._factory = factory
        self._length = int(length)

    def __iter__(self) -> Iterator[RGBDFrame]:
        return self._factory(0)

    def __len__(self) -> int:
        return self._length

    def iter_from(self, start: int) -> Iterator[RGBDFrame]:
        """Frames ``start, start + 1, ...`` (earlier ones are skipped without being decoded where possible)."""
        return self._factory(max(0, int(start)))

    def load(self) -> list[RGBDFrame]:
        """All frames in memory (mind the size: ~4.6 MB a 1280×720 frame)."""
        return list(self)


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
        return _intrinsics(self.K, self.width, self.height)


class Calibration(NamedTuple):
    """What a dataset says about its camera: K (3, 3), image size px, T_world_cam (4, 4), bases (4, 4) or None."""

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray
    T_world_base: dict[str, np.ndarray] | None


class ReferenceKeypoints(NamedTuple):
    """Keypoints (T, N, 3) m, edges (E, 2) int64 and rest lengths (E,) m, as read from ``3d_keypoints.npz``."""

    keypoints: np.ndarray
    edges: np.ndarray
    rest_lengths: np.ndarray


# ---------------------------------------------------------------------------------------------- geometry
def _intrinsics(K: np.ndarray, width: int, height: int) -> CameraIntrinsics:
    K = np.asarray(K, dtype=np.float64)
    return CameraIntrinsics(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def pose7_to_matrix(pose: np.ndarray) -> np.ndarray:
    """(..., 7) [x, y, z, qw, qx, qy, qz] (m, unit quaternion scalar first) -> (..., 4, 4)."""
    p = np.asarray(pose, dtype=np.float64)
    flat = p.reshape(-1, 7)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    if len(flat):
        T[:, :3, :3] = Rotation.from_quat(flat[:, [4, 5, 6, 3]]).as_matrix()
        T[:, :3, 3] = flat[:, :3]
    return T.reshape(*p.shape[:-1], 4, 4)


def matrix_to_pose7(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 7) [x, y, z, qw, qx, qy, qz] with qw >= 0."""
    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    out = np.zeros((len(flat), 7))
    if len(flat):
        q = Rotation.from_matrix(flat[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        q *= np.where(q[:, :1] < 0, -1.0, 1.0)
        out[:, :3] = flat[:, :3, 3]
        out[:, 3:] = q
    return out.reshape(*T.shape[:-2], 7)


def input_to_matrix(u: np.ndarray) -> np.ndarray:
    """(..., 6) [x, y, z (m), rotation vector (rad)] -> (..., 4, 4); NaN rows give NaN matrices."""
    u = np.asarray(u, dtype=np.float64)
    flat = u.reshape(-1, 6)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        T[ok, :3, :3] = Rotation.from_rotvec(flat[ok, 3:]).as_matrix()
        T[ok, :3, 3] = flat[ok, :3]
    T[~ok] = np.nan
    return T.reshape(*u.shape[:-1], 4, 4)


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


def _check_rigid(T: np.ndarray, where: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatasetError(f"{where}: expected shape (4, 4), got {T.shape}")
    R = T[:3, :3]
    if not (np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) and np.allclose(R @ R.T, np.eye(3), atol=1e-3)):
        raise DatasetError(f"{where}: not a rigid transform (rotation not orthonormal or last row not [0 0 0 1])")
    return T


# ---------------------------------------------------------------------------------------------- episodes (MCAP)
@dataclass
class _EpisodeIndex:
    """What one eager pass over an episode file learns (everything but the images)."""

    path: Path
    topics: tuple[str, str]  # colour, depth
    times: np.ndarray  # (T,) int64 ns log times of frames with both colour and depth
    frame_numbers: np.ndarray
    device_stamps: np.ndarray
    host_stamps: np.ndarray
    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray
    T_world_base: dict[str, np.ndarray] | None
    metadata: dict[str, Any]
    state_stamps: np.ndarray  # (S,)
    q: dict[str, np.ndarray]  # arm -> (S, 7)
    u: np.ndarray  # (S, 12)
    grasped: dict[str, np.ndarray]  # arm -> (S,) bool
    gripper_width: dict[str, np.ndarray]  # arm -> (S,) m
    ground_truth: list[GroundTruth | None]
    incomplete_frames: int
    keyframes: np.ndarray | None = None  # (T,) bool: the colour image decodes without earlier ones


def _unfinished_message(path: Path) -> str:
    return (
        f"{path}: unfinished episode ({ACTIVE_SUFFIX}: still being written, or left by a crash); "
        f"run `trackdeform recover {path.parent}` to turn it into a readable .mcap"
    )


def _camera_ids(topics: Iterable[str]) -> list[str]:
    parts = (t.split("/") for t in topics)
    return sorted(p[2] for p in parts if len(p) == 4 and p[1] == "cam" and p[3] == "color")


def _gt_from_json(d: dict[str, Any]) -> GroundTruth:
    kp = points_from_json(d.get("keypoints", []))
    return GroundTruth(
        keypoints=kp,
        edges=edges_from_json(d.get("edges", [])),
        # episodes store a subsampled centreline (older files none): empty unless the message carries one
        centreline=points_from_json(d.get("centreline")),
        radius=float(d.get("radius", 0.0)),
        anchors=np.asarray(d.get("anchors", []), dtype=np.int64),
        category=str(d.get("category", "")),
    )


def _index_episode(path: Path, camera_id: str | None) -> _EpisodeIndex:
    """Eager pass over every topic but the image payloads (those are only located, not decoded)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    if path.name.endswith(ACTIVE_SUFFIX):
        raise DatasetError(_unfinished_message(path))
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such episode file")
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            summary = reader.get_summary()
            if summary is None:
                raise DatasetError(f"{path}: no summary section (not a finished episode file)")
            topics = {c.topic for c in summary.channels.values()}
            cams = _camera_ids(topics)
            if camera_id is None:
                if len(cams) != 1:
                    raise DatasetError(
                        f"{path}: " + (f"several cameras {cams}: pass camera_id" if cams else
                                       f"no '/cam/<id>/color' channel (channels: {sorted(topics)})")
                    )
                camera_id = cams[0]
            cam = f"/cam/{camera_id}"
            for t in (f"{cam}/color", f"{cam}/depth"):
                if t not in topics:
                    raise DatasetError(f"{path}: no '{t}' channel (channels: {sorted(topics)})")
            metadata: dict[str, Any] = {}
            for m in reader.iter_metadata():
                if m.name == "episode":
                    metadata = {k: json.loads(v) for k, v in m.metadata.items()}
            color_t: dict[int, int] = {}
            depth_t: set[int] = set()
            info: dict[int, dict[str, Any]] = {}
            states: list[dict[str, Any]] = []
            gts: dict[int, dict[str, Any]] = {}
            calib_msg: Any = None
            tf_cam: np.ndarray | None = None
            factory = DecoderFactory()
            decoders: dict[int, Callable[[bytes], Any]] = {}
            wanted = [f"{cam}/color", f"{cam}/depth", f"{cam}/frame_info", f"{cam}/calibration", "/arms/state",
                      "/ground_truth/keypoints", "/tf"]
            for schema, channel, msg in reader.iter_messages(topics=[t for t in wanted if t in topics]):
                topic = channel.topic
                if topic == f"{cam}/color":
                    color_t[msg.log_time] = msg.publish_time
                elif topic == f"{cam}/depth":
                    depth_t.add(msg.log_time)
                elif topic == f"{cam}/frame_info":
                    info[msg.log_time] = json.loads(msg.data)
                elif topic == "/arms/state":
                    states.append(json.loads(msg.data))
                elif topic == "/ground_truth/keypoints":
                    d = json.loads(msg.data)
                    gts[int(d.get("frame_number", -1))] = d
                elif topic in (f"{cam}/calibration", "/tf") and schema is not None:
                    if calib_msg is not None and tf_cam is not None:
                        continue
                    dec = decoders.get(schema.id)
                    if dec is None:
                        dec = decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
                    obj = dec(msg.data)
                    if topic == "/tf":
                        for tr in obj.transforms:
                            if tr.child_frame_id == "cam" and tf_cam is None:
                                q, p = tr.rotation, tr.translation
                                tf_cam = np.eye(4)
                                tf_cam[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                                tf_cam[:3, 3] = [p.x, p.y, p.z]
                    elif calib_msg is None:
                        calib_msg = obj
    except McapError as e:
        raise DatasetError(f"{path}: unreadable MCAP file ({type(e).__name__}: {e})") from e

    times = np.array(sorted(set(color_t) & depth_t), dtype=np.int64)
    incomplete = len(set(color_t) ^ depth_t)
    if incomplete:
        log.warning("%s: %d colour/depth messages without their pair were skipped", path, incomplete)
    T = len(times)
    frame_numbers = np.empty(T, dtype=np.int64)
    device = np.empty(T)
    keyframes = np.zeros(T, dtype=bool)
    host = np.empty(T)
    prev = -1
    for i, t in enumerate(times.tolist()):
        d = info.get(t)
        if d is None:  # frame_info lost with its chunk (recovered file): best effort
            frame_numbers[i], device[i], host[i] = prev + 1, t * 1e-9, color_t[t] * 1e-9
        else:
            frame_numbers[i], device[i], host[i] = d["frame_number"], d["device_stamp"], d["host_stamp"]
            keyframes[i] = bool(d.get("color_keyframe", True))  # files before H.264: every image stands alone
        prev = int(frame_numbers[i])

    cal = metadata.get("calibration") or {}
    if "K" in cal:
        K = np.asarray(cal["K"], dtype=np.float64).reshape(3, 3)
        width, height = int(cal.get("width", 0)), int(cal.get("height", 0))
    elif calib_msg is not None:
        K = np.asarray(calib_msg.K, dtype=np.float64).reshape(3, 3)
        width, height = int(calib_msg.width), int(calib_msg.height)
    else:
        raise DatasetError(f"{path}: no camera calibration (no 'calibration' metadata and no '{cam}/calibration')")
    if "T_world_cam" in cal:
        T_world_cam = np.asarray(cal["T_world_cam"], dtype=np.float64).reshape(4, 4)
    elif tf_cam is not None:
        T_world_cam = tf_cam
    else:
        raise DatasetError(f"{path}: no camera pose (no 'calibration' metadata and no '/tf' world -> cam)")
    bases = cal.get("T_world_base")
    T_world_base = {k: np.asarray(v, dtype=np.float64).reshape(4, 4) for k, v in bases.items()} if bases else None

    S = len(states)
    state_stamps = np.array([s.get("stamp", np.nan) for s in states], dtype=np.float64)
    nan7 = [np.nan] * 7
    q = {a: np.array([s.get(a, {}).get("q") or nan7 for s in states], dtype=np.float64).reshape(S, 7)
         for a in ("left", "right")}
    grasped = {a: np.array([bool(s.get(a, {}).get("grasped", False)) for s in states], dtype=bool)
               for a in ("left", "right")}
    gripper_width = {a: np.array([float(s.get(a, {}).get("gripper_width", np.nan)) for s in states], dtype=np.float64)
                     for a in ("left", "right")}
    u = np.array([s.get("u") or [np.nan] * 12 for s in states], dtype=np.float64).reshape(S, 12)
    gt_list = [(_gt_from_json(gts[int(n)]) if int(n) in gts else None) for n in frame_numbers]
    return _EpisodeIndex(
        path=path, topics=(f"{cam}/color", f"{cam}/depth"), times=times, frame_numbers=frame_numbers,
        device_stamps=device, host_stamps=host, K=K, width=width, height=height, T_world_cam=T_world_cam,
        T_world_base=T_world_base, metadata=metadata, state_stamps=state_stamps, q=q, u=u, grasped=grasped,
        gripper_width=gripper_width, ground_truth=gt_list, incomplete_frames=incomplete, keyframes=keyframes,
    )


def _decode_image(
    msg: Any, where: str, schema: str = SCHEMA_RAW, decoder: ImageDecoder | None = None
) -> tuple[np.ndarray, float]:
    """An image message (foxglove.RawImage, CompressedImage png/jpeg, CompressedVideo h264 through the
    stream's ``decoder``) -> (H, W, 3) uint8 RGB or (H, W) uint16 depth, and the depth scale (m per unit)."""
    try:
        img = (decoder or ImageDecoder(where)).decode(schema, msg)
    except CodecError as e:
        raise DatasetError(f"{where}: {e}" if not str(e).startswith(where) else str(e)) from e
    return img, (1.0 if img.ndim == 3 else DEPTH_SCALE_MM)


def _iter_episode_frames(ep: _EpisodeIndex, start: int = 0) -> Iterator[RGBDFrame]:
    """Decode the colour + depth pairs of one episode from index ``start`` on, in log-time order."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    if start >= len(ep.times):
        return
    # H.264 colour decodes only from a keyframe on: start there and decode (not yield) up to ``start``
    keys = np.flatnonzero(ep.keyframes[: start + 1]) if ep.keyframes is not None else np.array([start])
    first = int(keys[-1]) if len(keys) else 0
    index = {int(t): i for i, t in enumerate(ep.times.tolist()) if i >= first}
    factory = DecoderFactory()
    decoders: dict[int, Callable[[bytes], Any]] = {}
    color_topic, depth_topic = ep.topics
    images = {t: ImageDecoder(f"{ep.path} {t}") for t in (color_topic, depth_topic)}
    pending: dict[int, dict[str, Any]] = {}
    t_from = int(ep.times[first])
    with open(ep.path, "rb") as f:
        reader = make_reader(f, decoder_factories=[factory])
        # mcap >= 1.3 names the inclusive lower bound starting_at (start_time is deprecated)
        since = "starting_at" if "starting_at" in inspect.signature(reader.iter_messages).parameters else "start_time"
        for schema, channel, msg in reader.iter_messages(topics=[color_topic, depth_topic], **{since: t_from}):
            i = index.get(msg.log_time)
            if schema is None or (i is None and schema.name != SCHEMA_VIDEO):
                continue  # a video message without its pair is still decoded: later frames depend on it
            dec = decoders.get(schema.id)
            if dec is None:
                dec = decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
            where = f"{ep.path} frame {int(ep.frame_numbers[i]) if i is not None else '?'}"
            if schema.name == SCHEMA_VIDEO or (i is not None and i >= start):
                image = _decode_image(dec(msg.data), where, schema.name, images[channel.topic])
            else:
                image = None  # before ``start`` and not needed to decode later frames
            if i is None:
                continue
            slot = pending.setdefault(i, {})
            slot[channel.topic] = image
            if len(slot) < 2:
                continue
            del pending[i]
            if i < start:
                continue
            (color, _), (depth, scale) = slot[color_topic], slot[depth_topic]
            if color.ndim != 3 or depth.ndim != 2 or color.shape[:2] != depth.shape:
                raise DatasetError(f"{where}: colour {color.shape} and depth {depth.shape} do not match")
            h, w = depth.shape
            yield RGBDFrame(
                color=color, depth=depth, depth_scale=scale, intrinsics=_intrinsics(ep.K, w, h),
                device_stamp=float(ep.device_stamps[i]), host_stamp=float(ep.host_stamps[i]),
                frame_number=int(ep.frame_numbers[i]), ground_truth=ep.ground_truth[i],
            )


def _episode_files(path: Path) -> tuple[list[Path], list[Path]]:
    """(finished episode files, unfinished .active files) for a file or folder."""
    if path.is_dir():
        return sorted(path.glob("*.mcap")), sorted(path.glob(f"*{ACTIVE_SUFFIX}"))
    if path.name.endswith(ACTIVE_SUFFIX):
        return [], [path]
    return [path], []


def read_episodes(path: str | Path, camera_id: str | None = None) -> Sequence:
    """An episode ``.mcap`` or a folder of them (sorted by name) as one Sequence, frames decoded lazily.

    Joint states, grasp flags and TCP poses (from ``u``, world frame) are those of the ``/arms/state``
    sample nearest each frame's host stamp (both on the host clock), within the same file; files without
    arm states give NaN rows (None when no file has any). Calibration comes from the ``episode``
    metadata (else the calibration channel and ``/tf``); every file must agree on it. Unfinished
    ``.active`` files are an error when named, skipped with a warning inside a folder.
    """
    path = Path(path)
    files, active = _episode_files(path)
    if path.is_file() and active:
        raise DatasetError(_unfinished_message(path))
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such episode file or folder")
    if not files:
        hint = f"; {len(active)} unfinished file(s): run `trackdeform recover {path}`" if active else ""
        raise DatasetError(f"{path}: no episode .mcap files{hint}")
    for a in active:
        log.warning("%s", _unfinished_message(a) + " (skipped)")
    episodes = [_index_episode(f, camera_id) for f in files]
    first = episodes[0]
    for ep in episodes[1:]:
        if not (np.allclose(ep.K, first.K) and np.allclose(ep.T_world_cam, first.T_world_cam, atol=1e-9)):
            raise DatasetError(
                f"{ep.path}: calibration (K or T_world_cam) differs from {first.path}; read it separately"
            )
    lengths = [len(ep.times) for ep in episodes]
    offsets = np.concatenate([[0], np.cumsum(lengths)])

    def frames(start: int) -> Iterator[RGBDFrame]:
        for k, ep in enumerate(episodes):
            if start < offsets[k + 1]:
                yield from _iter_episode_frames(ep, max(0, start - int(offsets[k])))

    def per_frame(ep: _EpisodeIndex, values: np.ndarray, fill: float | bool) -> np.ndarray:
        T = len(ep.times)
        ok = np.isfinite(ep.state_stamps)
        if not ok.any():
            return np.full((T, *values.shape[1:]), fill, dtype=values.dtype)
        idx = nearest_index(ep.state_stamps[ok], ep.host_stamps)
        return values[ok][idx]

    has_states = any(np.isfinite(ep.state_stamps).any() for ep in episodes)
    out: dict[str, Any] = {}
    state_offset = 0.0  # worst |frame host stamp - aligned state stamp|, s
    if has_states:
        for ep in episodes:
            if np.isfinite(ep.state_stamps).any():
                aligned = per_frame(ep, ep.state_stamps[:, None], np.nan)[:, 0]
                state_offset = max(state_offset, float(np.max(np.abs(aligned - ep.host_stamps), initial=0.0)))
        for arm in ("left", "right"):
            out[f"q_{arm}"] = np.concatenate([per_frame(ep, ep.q[arm], np.nan) for ep in episodes])
            out[f"grasped_{arm}"] = np.concatenate([per_frame(ep, ep.grasped[arm], False) for ep in episodes])
            out[f"gripper_width_{arm}"] = np.concatenate(
                [per_frame(ep, ep.gripper_width[arm], np.nan) for ep in episodes]
            )
        u = np.concatenate([per_frame(ep, ep.u, np.nan) for ep in episodes])
        out["tcp_left"], out["tcp_right"] = input_to_matrix(u[:, :6]), input_to_matrix(u[:, 6:])
    gt = [g for ep in episodes for g in ep.ground_truth]
    width, height = first.width, first.height
    if not (width and height) and offsets[-1]:  # calibration without a size: take it from the first image
        height, width = next(_iter_episode_frames(first)).depth.shape
    meta = dict(first.metadata)
    meta.update(
        layout="episodes",
        files=[str(ep.path) for ep in episodes],
        frames_per_file=lengths,
        episodes=[ep.metadata for ep in episodes],
        skipped_unfinished=[str(a) for a in active],
        incomplete_frames=sum(ep.incomplete_frames for ep in episodes),
        max_state_offset_s=state_offset if has_states else None,
        world_frame="the station's world frame (see calibration)",
    )
    return Sequence(
        frames=FrameSource(frames, int(offsets[-1])),
        T_world_cam=first.T_world_cam,
        K=first.K,
        width=width,
        height=height,
        T_world_base=first.T_world_base,
        ground_truth=gt if any(g is not None for g in gt) else None,
        metadata=meta,
        source=path,
        stamps=np.concatenate([ep.host_stamps for ep in episodes]),
        frame_numbers=np.concatenate([ep.frame_numbers for ep in episodes]),
        **out,
    )


# ---------------------------------------------------------------------------------------------- paper layout
def _read_npy_header(fp: IO[bytes], where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fp)
        if version == (1, 0):
            return fmt.read_array_header_1_0(fp)
        return fmt.read_array_header_2_0(fp)
    except ValueError as e:
        raise DatasetError(f"{where}: not a .npy array ({e})") from e


def _npz_member_header(path: Path, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of array ``key`` in an .npz, read from its header only."""
    with zipfile.ZipFile(path) as zf:
        names = [n.removesuffix(".npy") for n in zf.namelist()]
        if key not in names:
            raise DatasetError(f"{path}: no array '{key}' (has: {sorted(names)})")
        with zf.open(f"{key}.npy") as fp:
            shape, _, dtype = _read_npy_header(fp, f"{path}:{key}")
    return shape, dtype


def _iter_npz_rows(path: Path, key: str, start: int = 0) -> Iterator[np.ndarray]:
    """The rows ``arr[start], arr[start + 1], ...`` of array ``key`` in an .npz, streamed (one row in memory)."""
    with zipfile.ZipFile(path) as zf, zf.open(f"{key}.npy") as fp:
        shape, fortran, dtype = _read_npy_header(fp, f"{path}:{key}")
        if fortran:  # rare: no row streaming possible
            with np.load(path) as z:
                arr = z[key]
            yield from (np.array(r) for r in arr[start:])
            return
        n = math.prod(shape[1:]) * dtype.itemsize
        for i in range(shape[0]):
            buf = fp.read(n)
            if len(buf) != n:
                raise DatasetError(f"{path}: array '{key}' is truncated at row {i} of {shape[0]}")
            if i >= start:
                yield np.frombuffer(buf, dtype=dtype).reshape(shape[1:])


def _require_file(folder: Path, name: str) -> Path:
    p = folder / name
    if not p.is_file():
        raise FileNotFoundError(f"{p}: missing (the paper's layout needs {name} in {folder})")
    return p


def _read_npz_array(path: Path, key: str, shape: tuple[int | None, ...]) -> np.ndarray:
    with np.load(path) as z:
        if key not in z.files:
            raise DatasetError(f"{path}: no array '{key}' (has: {sorted(z.files)})")
        a = np.asarray(z[key])
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        raise DatasetError(f"{path}: array '{key}' has shape {a.shape}, expected {want}")
    return a


def _read_pose_file(path: Path) -> np.ndarray:
    """(T, 7) [x, y, z, qw, qx, qy, qz] from ``arr_0 ... arr_{T-1}``."""
    with np.load(path) as z:
        files = set(z.files)
        n = len(files)
        missing = [f"arr_{i}" for i in range(n) if f"arr_{i}" not in files]
        if missing:
            extra = sorted(files - {f"arr_{i}" for i in range(n)})
            raise DatasetError(
                f"{path}: expected arrays arr_0 ... arr_{n - 1}; missing {missing[0]} (unexpected: {extra})"
            )
        rows = [np.asarray(z[f"arr_{i}"], dtype=np.float64) for i in range(n)]
    bad = next((i for i, r in enumerate(rows) if r.shape != (7,)), None)
    if bad is not None:
        raise DatasetError(f"{path}: arr_{bad} has shape {rows[bad].shape}, expected (7,) [x, y, z, qw, qx, qy, qz]")
    return np.stack(rows) if rows else np.zeros((0, 7))


def _paper_calibration(folder: Path, world: str) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(K, T_world_cam, T_world_base) from ``calibration/transform_ee_cam_world.npz``."""
    cal = _require_file(folder, CALIBRATION_FILE)
    K = _read_npz_array(cal, "K", (3, 3)).astype(np.float64)
    T_cam_base = {a: _check_rigid(_read_npz_array(cal, f"T_{a}_base2cam", (4, 4)), f"{cal}: T_{a}_base2cam")
                  for a in ("left", "right")}
    if world == "camera":
        T_world_cam = np.eye(4)
    elif world in T_cam_base:
        T_world_cam = invert_transform(T_cam_base[world])
    else:
        raise ValueError(f"world must be 'left', 'right' or 'camera', not {world!r}")
    return K, T_world_cam, {a: T_world_cam @ T for a, T in T_cam_base.items()}


def read_paper_layout(
    folder: str | Path,
    *,
    world: Literal["left", "right", "camera"] = "left",
    fps: float = 30.0,
    align: Literal["strict", "end"] = "strict",
) -> Sequence:
    """A folder in the layout of the paper's published code as a Sequence (frames streamed lazily).

    Files: ``rgbd.npz`` (``color`` (T, H, W, 3) uint8 BGR, ``depth`` (T, H, W) uint16 mm);
    ``left_arm_poses.npz`` / ``right_arm_poses.npz`` (``arr_0 ... arr_{T-1}``: [x, y, z, qw, qx, qy, qz],
    m, TCP in that robot's base frame); ``calibration/transform_ee_cam_world.npz`` (``T_left_base2cam``,
    ``T_right_base2cam`` (4, 4), ``K`` (3, 3)); optional ``joint_states.npz`` (``left``, ``right`` (T, 7) rad).

    Frame convention: the paper's code computes TCP positions in the camera as
    ``(T_left_base2cam @ T_base_tcp)[:3, 3]``, so ``T_<arm>_base2cam`` maps base coordinates to camera
    coordinates (it is the base pose in the camera frame, ``T_cam_base``). The world frame is the left
    robot's base (``world="left"``, default): ``T_world_cam = inv(T_left_base2cam)``,
    ``T_world_base["right"] = inv(T_left_base2cam) @ T_right_base2cam``, and TCP poses are
    ``T_world_base[arm] @ pose``. ``world="right"`` / ``"camera"`` use the right base / camera instead.
    The files carry no stamps: frame k is stamped ``k / fps`` s. Frame counts must agree
    (``align="end"`` keeps the last common frames instead, as the published scripts do).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    rgbd = _require_file(folder, RGBD_FILE)
    cshape, cdtype = _npz_member_header(rgbd, "color")
    dshape, ddtype = _npz_member_header(rgbd, "depth")
    if len(cshape) != 4 or cshape[3] != 3 or cdtype != np.uint8:
        raise DatasetError(f"{rgbd}: array 'color' is {cdtype} {cshape}, expected uint8 (T, H, W, 3) BGR")
    if len(dshape) != 3 or dshape != cshape[:3] or ddtype.kind != "u" or ddtype.itemsize != 2:
        raise DatasetError(f"{rgbd}: array 'depth' is {ddtype} {dshape}, expected uint16 {cshape[:3]} (mm)")
    T_rgb, H, W = cshape[:3]
    K, T_world_cam, T_world_base = _paper_calibration(folder, world)
    poses = {a: _read_pose_file(_require_file(folder, f)) for a, f in POSE_FILES.items()}
    joints: dict[str, np.ndarray] = {}
    if (folder / JOINT_FILE).is_file():
        joints = {a: _read_npz_array(folder / JOINT_FILE, a, (None, 7)).astype(np.float64) for a in ("left", "right")}
    counts = {RGBD_FILE: T_rgb, **{POSE_FILES[a]: len(p) for a, p in poses.items()},
              **{f"{JOINT_FILE}:{a}": len(q) for a, q in joints.items()}}
    T = min(counts.values())
    if align == "strict":
        bad = {k: v for k, v in counts.items() if v != T_rgb}
        if bad:
            name, n = next(iter(bad.items()))
            raise DatasetError(
                f"{folder / name.split(':')[0]}: {n} rows but {RGBD_FILE} has {T_rgb} frames "
                f"(counts: {counts}); pass align='end' to keep the last {T} of each"
            )
    skip = T_rgb - T

    def tail(a: np.ndarray) -> np.ndarray:
        return a[len(a) - T:]

    tcp = {a: T_world_base[a] @ pose7_to_matrix(tail(p)) for a, p in poses.items()}
    intr = _intrinsics(K, W, H)

    def frames(start: int) -> Iterator[RGBDFrame]:
        rows = zip(_iter_npz_rows(rgbd, "color", skip + start), _iter_npz_rows(rgbd, "depth", skip + start),
                   strict=True)
        for k, (bgr, depth) in enumerate(rows, start=start):
            t = k / fps
            yield RGBDFrame(
                color=np.ascontiguousarray(bgr[..., ::-1]), depth=depth.astype(np.uint16),
                depth_scale=DEPTH_SCALE_MM, intrinsics=intr, device_stamp=t, host_stamp=t, frame_number=k,
            )

    return Sequence(
        frames=FrameSource(frames, T),
        T_world_cam=T_world_cam,
        K=K,
        width=W,
        height=H,
        q_left=tail(joints["left"]) if joints else None,
        q_right=tail(joints["right"]) if joints else None,
        tcp_left=tcp["left"],
        tcp_right=tcp["right"],
        T_world_base=T_world_base,
        metadata={"layout": "paper", "fps": fps, "world_frame": f"{world} robot base" if world != "camera"
                  else "camera", "frame_counts": counts, "skipped_leading_frames": skip},
        source=folder,
        stamps=np.arange(T) / fps,
        frame_numbers=np.arange(T, dtype=np.int64),
    )


def _npy_header_dict(shape: tuple[int, ...], dtype: np.dtype) -> dict[str, Any]:
    return {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": shape}


def write_paper_layout(
    folder: str | Path,
    frames: Iterable[RGBDFrame],
    *,
    T_world_cam: np.ndarray,
    T_world_base: dict[str, np.ndarray],
    tcp_left: np.ndarray,
    tcp_right: np.ndarray,
    q_left: np.ndarray | None = None,
    q_right: np.ndarray | None = None,
    K: np.ndarray | None = None,
    compress: bool = False,
) -> Path:
    """Write ``folder`` in the paper's layout (see :func:`read_paper_layout`); returns the folder.

    frames: re-iterable (a list or a FrameSource; read twice, one frame in memory at a time), RGB colour.
    tcp_left / tcp_right: (T, 4, 4) world frame; T_world_base: {"left", "right"} -> (4, 4); q: (T, 7) rad.
    K defaults to the first frame's intrinsics. Reading it back expresses everything in the left base frame.
    """
    folder = Path(folder)
    try:
        T = len(frames)  # type: ignore[arg-type]
    except TypeError:
        frames = list(frames)
        T = len(frames)
    if T == 0:
        raise ValueError("write_paper_layout: no frames")
    tcp = {"left": np.asarray(tcp_left, dtype=np.float64), "right": np.asarray(tcp_right, dtype=np.float64)}
    for a, arr in tcp.items():
        if arr.shape != (T, 4, 4):
            raise ValueError(f"write_paper_layout: tcp_{a} has shape {arr.shape}, expected ({T}, 4, 4)")
    (folder / CALIBRATION_FILE).parent.mkdir(parents=True, exist_ok=True)
    first = next(iter(frames))
    H, W = first.depth.shape
    K = first.intrinsics.K if K is None else np.asarray(K, dtype=np.float64)
    members = {
        "color": ((T, H, W, 3), np.uint8, lambda f: np.ascontiguousarray(f.color[..., ::-1], dtype=np.uint8)),
        "depth": ((T, H, W), np.dtype("<u2"), _depth_mm),
    }
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    tmp = folder / (RGBD_FILE + ".part")
    with zipfile.ZipFile(tmp, "w", compression=mode, allowZip64=True) as zf:
        for key, (shape, dtype, convert) in members.items():
            n = 0
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fp:
                np.lib.format.write_array_header_1_0(fp, _npy_header_dict(shape, dtype))
                for f in frames:
                    if f.depth.shape != (H, W):
                        raise ValueError(f"write_paper_layout: frame {f.frame_number} is {f.depth.shape}, not {(H, W)}")
                    fp.write(np.ascontiguousarray(convert(f), dtype=dtype).tobytes())
                    n += 1
            if n != T:
                raise ValueError(f"write_paper_layout: frames yielded {n} frames, len() said {T}")
    tmp.replace(folder / RGBD_FILE)
    T_cam_world = invert_transform(T_world_cam)
    bases = {a: np.asarray(T_world_base[a], dtype=np.float64) for a in ("left", "right")}
    for a, name in POSE_FILES.items():
        pose = matrix_to_pose7(invert_transform(bases[a]) @ tcp[a])
        np.savez(folder / name, *pose)
    np.savez(folder / CALIBRATION_FILE, K=K, T_left_base2cam=T_cam_world @ bases["left"],
             T_right_base2cam=T_cam_world @ bases["right"])
    if q_left is not None and q_right is not None:
        np.savez(folder / JOINT_FILE, left=np.asarray(q_left, dtype=np.float64),
                 right=np.asarray(q_right, dtype=np.float64))
    return folder


def _depth_mm(f: RGBDFrame) -> np.ndarray:
    """(H, W) uint16 depth in millimetres."""
    if abs(f.depth_scale - DEPTH_SCALE_MM) < 1e-12:
        return f.depth.astype("<u2", copy=False)
    return np.clip(np.round(f.depth.astype(np.float64) * f.depth_scale * 1000.0), 0, 65535).astype("<u2")


# ---------------------------------------------------------------------------------------------- dispatch
def read_sequence(path: str | Path, **options: Any) -> Sequence:
    """Read an episode ``.mcap``, a folder of episodes, or a folder (or its ``rgbd.npz``) in the paper's layout.

    ``options`` go to the chosen reader (``camera_id`` for episodes; ``world``, ``fps``, ``align`` for the
    paper layout).
    """
    path = Path(path)
    if path.is_file() and path.name == RGBD_FILE:
        return read_paper_layout(path.parent, **options)
    if path.is_dir() and (path / RGBD_FILE).is_file():
        return read_paper_layout(path, **options)
    if path.name.endswith(ACTIVE_SUFFIX) or path.suffix == ".mcap":
        return read_episodes(path, **options)
    if path.is_dir():
        files, active = _episode_files(path)
        if files or active:
            return read_episodes(path, **options)
        raise DatasetError(f"{path}: neither episode .mcap files nor a {RGBD_FILE} (the paper's layout)")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    raise DatasetError(f"{path}: not an episode .mcap, a folder of them, or a folder with {RGBD_FILE}")


def read_calibration(path: str | Path) -> Calibration:
    """A dataset's camera calibration without reading its frames (cheap: metadata / calibration file only)."""
    path = Path(path)
    folder = path.parent if path.name == RGBD_FILE else path
    if folder.is_dir() and (folder / RGBD_FILE).is_file():
        K, T_world_cam, bases = _paper_calibration(folder, "left")
        shape, _ = _npz_member_header(folder / RGBD_FILE, "color")
        return Calibration(K, int(shape[2]), int(shape[1]), T_world_cam, bases)
    files, active = _episode_files(path) if path.exists() else ([], [])
    if path.is_file() and active:
        raise DatasetError(_unfinished_message(path))
    if files:
        from orchestrator.recorder import read_episode_metadata

        try:
            cal = read_episode_metadata(files[0]).get("calibration") or {}
        except ValueError:
            cal = {}
        if {"K", "T_world_cam", "width", "height"} <= set(cal):
            bases = cal.get("T_world_base")
            return Calibration(
                np.asarray(cal["K"], dtype=np.float64).reshape(3, 3), int(cal["width"]), int(cal["height"]),
                np.asarray(cal["T_world_cam"], dtype=np.float64).reshape(4, 4),
                {k: np.asarray(v, dtype=np.float64).reshape(4, 4) for k, v in bases.items()} if bases else None,
            )
    seq = read_sequence(path)
    return Calibration(seq.K, seq.width, seq.height, seq.T_world_cam, seq.T_world_base)


# ---------------------------------------------------------------------------------------------- reference export
def _reference_path(path: str | Path) -> Path:
    path = Path(path)
    return path / REFERENCE_FILE if path.is_dir() else path


def write_reference_npz(path: str | Path, keypoints: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> Path:
    """Write ``3d_keypoints.npz`` as the paper's code does: ``full`` (T, N, 3) mm, ``edge_connection`` (E, 2),
    ``reference_lengths`` (E,) mm. keypoints: (T, N, 3) m (NaN allowed); rest_lengths: (E,) m.
    A folder ``path`` gets ``3d_keypoints.npz`` inside; returns the file written.
    """
    X = np.asarray(keypoints, dtype=np.float64)
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    d = np.asarray(rest_lengths, dtype=np.float64).reshape(-1)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"write_reference_npz: keypoints have shape {X.shape}, expected (T, N, 3)")
    if len(d) != len(E):
        raise ValueError(f"write_reference_npz: {len(E)} edges but {len(d)} rest lengths")
    if len(E) and (E.min() < 0 or E.max() >= X.shape[1]):
        raise ValueError(f"write_reference_npz: edge index out of range for {X.shape[1]} keypoints")
    out = _reference_path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as f:  # a file object: numpy must not append .npz to the name
        np.savez(f, full=X * 1000.0, edge_connection=E, reference_lengths=d * 1000.0)
    return out


def read_reference_npz(path: str | Path) -> ReferenceKeypoints:
    """Read ``3d_keypoints.npz`` (or a folder holding it) back in metres: (T, N, 3), (E, 2), (E,)."""
    p = _reference_path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: missing")
    with np.load(p) as z:
        missing = [k for k in ("full", "edge_connection", "reference_lengths") if k not in z.files]
        if missing:
            raise DatasetError(f"{p}: no array '{missing[0]}' (has: {sorted(z.files)})")
        X = np.asarray(z["full"], dtype=np.float64)
        E = np.asarray(z["edge_connection"]).astype(np.int64)
        d = np.asarray(z["reference_lengths"], dtype=np.float64).reshape(-1)
    if X.ndim == 2:
        X = X[None]
    if X.ndim != 3 or X.shape[2] != 3:
        raise DatasetError(f"{p}: 'full' has shape {X.shape}, expected (T, N, 3)")
    if E.size == 0:
        E = E.reshape(0, 2)
    if E.ndim != 2 or E.shape[1] != 2 or len(E) != len(d):
        raise DatasetError(
            f"{p}: 'edge_connection' {E.shape} and 'reference_lengths' {d.shape} do not match (E, 2) / (E,)"
        )
    return ReferenceKeypoints(X / 1000.0, E, d / 1000.0)
