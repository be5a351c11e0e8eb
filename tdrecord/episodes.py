"""Episode MCAP files as this daemon writes them: read into a :class:`tdrecord.sequence.Sequence`.

Finished files are ``episode_NNNNNN.mcap``; ``*.mcap.active`` are still being written (or were left by
a crash) and are refused until ``trackdeform recover`` has turned them into finished files. Frames are
decoded lazily (one frame in memory at a time): 1280×720 sequences are gigabytes.
"""

from __future__ import annotations

import inspect
import json
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from tdcommon.transforms import input_to_matrix
from tdcommon.types import CameraIntrinsics, GroundTruth, RGBDFrame
from tdcommon.wire import ground_truth_from_json
from tdrecord.codecs import SCHEMA_VIDEO, CodecError, ImageDecoder
from tdrecord.sequence import DEPTH_SCALE_MM, DatasetError, FrameSource, Sequence, nearest_index

log = logging.getLogger(__name__)

ACTIVE_SUFFIX = ".mcap.active"


OPEN_METADATA = "episode_open"  # written when the episode opens (kept by recovery)
CLOSE_METADATA = "episode"  # written when it closes, or by recovery (complete: false)


def merge_metadata(records: Iterable[Any]) -> dict[str, Any] | None:
    """The episode metadata of an MCAP file's metadata records: ``episode_open`` updated by ``episode``,
    values decoded from JSON; None when the file has neither."""
    opened: dict[str, Any] | None = None
    closed: dict[str, Any] | None = None
    for m in records:
        if m.name in (OPEN_METADATA, CLOSE_METADATA):
            values = {k: json.loads(v) for k, v in m.metadata.items()}
            if m.name == OPEN_METADATA:
                opened = {**(opened or {}), **values}
            else:
                closed = {**(closed or {}), **values}
    if opened is None and closed is None:
        return None
    return {**(opened or {}), **(closed or {})}


def read_episode_metadata(path: Path) -> dict[str, Any]:
    """The episode metadata of a finished file (``episode_open`` merged with ``episode``), values decoded."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        meta = merge_metadata(make_reader(f).iter_metadata())
    if meta is None:
        raise ValueError(f"{path}: no 'episode' metadata record")
    return meta


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
    paired: list[dict[str, Any] | None]  # per frame: the arms at its capture time (/arms/state_at_frame), if any
    keyframes: np.ndarray | None = None  # (T,) bool: the colour image decodes without earlier ones


def unfinished_message(path: Path) -> str:
    return (
        f"{path}: unfinished episode ({ACTIVE_SUFFIX}: still being written, or left by a crash); "
        f"run `trackdeform recover {path.parent}` to turn it into a readable .mcap"
    )


def _camera_ids(topics: Iterable[str]) -> list[str]:
    parts = (t.split("/") for t in topics)
    return sorted(p[2] for p in parts if len(p) == 4 and p[1] == "cam" and p[3] == "color")


def _index_episode(path: Path, camera_id: str | None) -> _EpisodeIndex:
    """Eager pass over every topic but the image payloads (those are only located, not decoded)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    if path.name.endswith(ACTIVE_SUFFIX):
        raise DatasetError(unfinished_message(path))
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
            metadata: dict[str, Any] = merge_metadata(reader.iter_metadata()) or {}
            color_t: dict[int, int] = {}
            depth_t: set[int] = set()
            info: dict[int, dict[str, Any]] = {}
            states: list[dict[str, Any]] = []
            gts: dict[int, dict[str, Any]] = {}
            at_frame: dict[int, dict[str, Any]] = {}
            calib_msg: Any = None
            tf_cam: np.ndarray | None = None
            factory = DecoderFactory()
            decoders: dict[int, Callable[[bytes], Any]] = {}
            wanted = [f"{cam}/color", f"{cam}/depth", f"{cam}/frame_info", f"{cam}/calibration", "/arms/state",
                      "/arms/state_at_frame", "/ground_truth/keypoints", "/tf"]
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
                elif topic == "/arms/state_at_frame":
                    d = json.loads(msg.data)
                    at_frame[int(d.get("frame_number", -1))] = d
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
    gt_list = [(ground_truth_from_json(gts[int(n)]) if int(n) in gts else None) for n in frame_numbers]
    return _EpisodeIndex(
        path=path, topics=(f"{cam}/color", f"{cam}/depth"), times=times, frame_numbers=frame_numbers,
        device_stamps=device, host_stamps=host, K=K, width=width, height=height, T_world_cam=T_world_cam,
        T_world_base=T_world_base, metadata=metadata, state_stamps=state_stamps, q=q, u=u, grasped=grasped,
        gripper_width=gripper_width, ground_truth=gt_list, incomplete_frames=incomplete, keyframes=keyframes,
        paired=[at_frame.get(int(n)) for n in frame_numbers],
    )


def _decode_image(msg: Any, where: str, schema: str, decoder: ImageDecoder) -> tuple[np.ndarray, float]:
    """An image message (foxglove.RawImage, CompressedImage png/jpeg, CompressedVideo h264 through the
    stream's ``decoder``) -> (H, W, 3) uint8 RGB or (H, W) uint16 depth, and the depth scale (m per unit)."""
    try:
        img = decoder.decode(schema, msg)
    except CodecError as e:
        raise DatasetError(f"{where}: {e}" if not str(e).startswith(where) else str(e)) from e
    return img, (1.0 if img.ndim == 3 else DEPTH_SCALE_MM)


def _iter_episode_frames(ep: _EpisodeIndex, start: int = 0) -> Iterator[RGBDFrame]:
    """Decode the colour + depth pairs of one episode from index ``start`` on, in log-time order.

    H.264 colour decodes only from a keyframe on: decoding starts at the last keyframe at or before
    ``start`` and the frames before ``start`` are decoded, not yielded.
    """
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    if start >= len(ep.times):
        return
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
                color=color, depth=depth, depth_scale=scale, intrinsics=CameraIntrinsics.from_K(ep.K, w, h),
                device_stamp=float(ep.device_stamps[i]), host_stamp=float(ep.host_stamps[i]),
                frame_number=int(ep.frame_numbers[i]), ground_truth=ep.ground_truth[i],
            )


def episode_files(path: Path) -> tuple[list[Path], list[Path]]:
    """(finished episode files, unfinished .active files) for a file or folder."""
    if path.is_dir():
        return sorted(path.glob("*.mcap")), sorted(path.glob(f"*{ACTIVE_SUFFIX}"))
    if path.name.endswith(ACTIVE_SUFFIX):
        return [], [path]
    return [path], []


def read_episodes(path: str | Path | list[Path], camera_id: str | None = None) -> Sequence:
    """An episode ``.mcap``, a folder of them (sorted by name) or a list of files (in that order) as one
    Sequence, frames decoded lazily.

    Joint states, grasp flags and TCP poses (from ``u``, world frame) of a frame are those recorded at its
    capture time (``/arms/state_at_frame``: interpolated by the recorder's camera–arm time sync), else
    those of the ``/arms/state`` sample nearest its host stamp (both on the host clock), within the same
    file; files without arm states give NaN rows (None when no file has any). Calibration comes from the ``episode``
    metadata (else the calibration channel and ``/tf``); every file must agree on it. Unfinished
    ``.active`` files are an error when named, skipped with a warning inside a folder.
    """
    if isinstance(path, (list, tuple)):  # one program run's episodes
        files, active = [Path(p) for p in path], []
        path = files[0].parent if files else Path(".")
    else:
        path = Path(path)
        files, active = episode_files(path)
    if path.is_file() and active:
        raise DatasetError(unfinished_message(path))
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such episode file or folder")
    if not files:
        hint = f"; {len(active)} unfinished file(s): run `trackdeform recover {path}`" if active else ""
        raise DatasetError(f"{path}: no episode .mcap files{hint}")
    for a in active:
        log.warning("%s", unfinished_message(a) + " (skipped)")
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

    def per_frame(ep: _EpisodeIndex, values: np.ndarray, fill: float | bool,
                  paired: Callable[[dict[str, Any]], Any] | None = None) -> np.ndarray:
        T = len(ep.times)
        ok = np.isfinite(ep.state_stamps)
        if not ok.any():
            rows = np.full((T, *values.shape[1:]), fill, dtype=values.dtype)
        else:
            rows = values[ok][nearest_index(ep.state_stamps[ok], ep.host_stamps)]
        if paired is not None:
            at = [i for i, p in enumerate(ep.paired) if p is not None]
            if at:
                rows[at] = np.asarray([paired(ep.paired[i]) for i in at], dtype=values.dtype).reshape(
                    len(at), *values.shape[1:]
                )
        return rows

    has_states = any(np.isfinite(ep.state_stamps).any() or any(ep.paired) for ep in episodes)
    out: dict[str, Any] = {}
    state_offset = 0.0  # worst |frame host stamp - aligned state stamp|, s (frames aligned by host stamp)
    if has_states:
        for ep in episodes:
            if np.isfinite(ep.state_stamps).any():
                aligned = per_frame(ep, ep.state_stamps[:, None], np.nan)[:, 0]
                nearest = np.array([p is None for p in ep.paired], dtype=bool)
                state_offset = max(state_offset, float(np.max(np.abs(aligned - ep.host_stamps)[nearest], initial=0.0)))
        for arm in ("left", "right"):
            out[f"q_{arm}"] = np.concatenate([per_frame(ep, ep.q[arm], np.nan, lambda p, a=arm: p[a]["q"])
                                              for ep in episodes])
            out[f"grasped_{arm}"] = np.concatenate(
                [per_frame(ep, ep.grasped[arm], False, lambda p, a=arm: p[a]["grasped"]) for ep in episodes]
            )
            out[f"gripper_width_{arm}"] = np.concatenate(
                [per_frame(ep, ep.gripper_width[arm], np.nan, lambda p, a=arm: p[a]["gripper_width"])
                 for ep in episodes]
            )
        u = np.concatenate([per_frame(ep, ep.u, np.nan, lambda p: p["u"]) for ep in episodes])
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
        frames_paired_at_capture=sum(sum(p is not None for p in ep.paired) for ep in episodes),
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


@dataclass
class RecordedRun:
    """The episode files of one program run (one attempt), in recording order, with each file's metadata."""

    key: tuple
    episodes: list[Path]
    metadata: list[dict[str, Any]]

    @property
    def first(self) -> dict[str, Any]:
        """The first episode's metadata: what the run is (object, program, speed, repeat, attempt)."""
        return self.metadata[0]


def run_key(meta: dict[str, Any]) -> tuple:
    """What tells one program run (one attempt) from another in the ``episode`` metadata."""
    return (meta.get("session_started"), meta.get("plan_pass", 0), meta.get("run_index"), meta.get("object"),
            meta.get("program"), meta.get("speed"), meta.get("repeat", 0), meta.get("attempt", 1))


def recorded_runs(files: Iterable[Path]) -> list[RecordedRun]:
    """Episode files grouped into program runs by their ``episode`` metadata, in file order.

    A file whose metadata cannot be read is its own run, with ``unreadable`` in its metadata.
    """
    runs: dict[tuple, RecordedRun] = {}
    for f in files:
        try:
            meta = read_episode_metadata(f)
        except Exception as e:  # reported by the caller, never fatal here
            meta = {"object": "?", "program": "?", "speed": "?", "unreadable": f"{type(e).__name__}: {e}"}
        key = run_key(meta) if "unreadable" not in meta else ("unreadable", str(f))
        run = runs.setdefault(key, RecordedRun(key, [], []))
        run.episodes.append(Path(f))
        run.metadata.append(meta)
    return list(runs.values())
