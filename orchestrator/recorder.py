"""Episode files: one MCAP per episode, written as ``*.mcap.active``, fsynced, renamed on close.

Channels (Foxglove schemas where one fits, so a file opens in Foxglove):

- ``/cam/<id>/color``  foxglove.CompressedVideo h264 (default), CompressedImage jpeg or RawImage rgb8
- ``/cam/<id>/depth``  foxglove.CompressedImage 16-bit png (default), trackdeform.CompressedDepth planes or
  RawImage 16UC1, mm, lossless
  (codecs and settings: tdrecord.codecs, ``output.color`` / ``output.depth`` of the config)
- ``/cam/<id>/calibration``  foxglove.CameraCalibration (frame ``cam``)
- ``/cam/<id>/frame_info``  JSON {frame_number, device_stamp, host_stamp, color_keyframe}
  (every JSON channel has a JSON Schema with its properties: tdrecord.channels)
- ``/arms/state``  JSON (see tdcommon.wire);  ``/arms/state_at_frame``  JSON: both arms' joints interpolated
  at each frame's capture time and u_t from them (orchestrator.timesync), with ``frame_number``
- ``/tf``  foxglove.FrameTransforms (world -> cam, TCPs)
- ``/keypoints``  JSON (trackdeform.Keypoints: the live message, points as {x, y, z})
- ``/keypoints/scene``  foxglove.SceneUpdate
- ``/ground_truth/keypoints``  JSON (mock mode)

and metadata records whose values are JSON strings: ``episode_open`` (what was known when the episode
opened: object, program, speed, index, calibration...), written and flushed first so a file cut by a
crash still has it, and ``episode`` (everything, with ``complete`` / ``fault`` and the frame counts),
written on close. Readers merge the two (``episode`` wins). Leftover ``.active`` files (after a crash or
SIGKILL) are rewritten from their readable records by :func:`recover_active`, which keeps
``episode_open`` and adds ``complete: false``.

An I/O error (a full disk: ENOSPC) stops the :class:`Recorder` for good: it keeps what it wrote,
opens nothing more and reports the failure in ``Recorder.failed``; a close that failed stays failed.

One module (~600 lines) on purpose: the episode writer and the recorder thread share one lifecycle per
file (open, write, grace period, close or failure); recovery after a crash is orchestrator.recovery.
"""

from __future__ import annotations

import json
import logging
import os
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np
import orjson
from mcap.writer import CompressionType, Writer

from orchestrator.config import ColorOutputConfig, DepthOutputConfig
from orchestrator.episode_stats import message_gt_errors_mm
from orchestrator.fsutil import fsync_dir
from tdcommon.types import RGBDFrame
from tdcommon.wire import ground_truth_to_json
from tdrecord.channels import SCHEMAS, keypoints_record
from tdrecord.codecs import (
    SCHEMA_COMPRESSED,
    SCHEMA_DEPTH,
    SCHEMA_RAW,
    SCHEMA_VIDEO,
    ColorEncoder,
    DepthEncoder,
    EncodedImage,
)
from tdrecord.digest import DigestWriter, digest_path
from tdrecord.episodes import ACTIVE_SUFFIX, CLOSE_METADATA, OPEN_METADATA

log = logging.getLogger(__name__)

TF_RATE = 30.0  # Hz: TCP frames on /tf
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def _ns(t: float) -> int:
    return max(0, int(round(t * 1e9)))


class RecordingFailed(RuntimeError):
    """The recorder hit an I/O error (e.g. a full disk) and records nothing more; the message says where."""


def _json_values(meta: dict[str, Any]) -> dict[str, str]:
    return {k: json.dumps(v) for k, v in meta.items()}


def _quats_xyzw(R: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions x, y, z, w of rotation matrices (n, 3, 3), in one call."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def _rename_message(fds: Any, full_name: str, new_full_name: str) -> None:
    """Give message ``full_name`` of a FileDescriptorSet the name ``new_full_name`` (package.Message) in its own
    file: the same fields under a name of ours (``trackdeform.CompressedDepth`` is foxglove.CompressedImage's)."""
    package, _, message = full_name.rpartition(".")
    new_package, _, new_message = new_full_name.rpartition(".")
    for f in fds.file:
        if f.package == package and any(m.name == message for m in f.message_type):
            f.package, f.name = new_package, f"{new_package.replace('.', '/')}/{new_message}.proto"
            for m in f.message_type:
                if m.name == message:
                    m.name = new_message
            return
    raise ValueError(f"no message {full_name} in the descriptor set")


class EpisodeWriter:
    """Writes one episode file; call ``close()`` to finish it (``abort()`` leaves ``.active``).

    Colour and depth are encoded as ``color`` / ``depth`` say (defaults: H.264 and 16-bit PNG); with an
    ``executor`` depth is encoded on it while colour is encoded on the calling thread.
    ``metadata`` (the open-time facts) is written as the ``episode_open`` record and flushed before
    any frame, so recovery of a file cut short keeps it.
    """

    def __init__(self, path: Path, camera_id: str, compression: str = "zstd",
                 color: ColorOutputConfig | None = None, depth: DepthOutputConfig | None = None,
                 executor: Executor | None = None, fps: float = 30.0, *,
                 metadata: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.active_path = self.path.with_name(self.path.name.removesuffix(".mcap") + ACTIVE_SUFFIX)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists already; refusing to overwrite a finished episode")
        digest_path(self.path).unlink(missing_ok=True)  # a stale digest of a deleted episode of this name
        self._file = open(self.active_path, "wb")  # noqa: SIM115 - closed in close()/abort()
        self.closed = False
        self.failed: str | None = None  # why close() failed; a failed writer never reports its path as finished
        self.color_config = color or ColorOutputConfig()
        self.depth_config = depth or DepthOutputConfig()
        self._executor = executor
        try:
            self._start(camera_id, compression, metadata, fps)
        except BaseException:
            self._file.close()
            self.closed = True
            self.active_path.unlink(missing_ok=True)  # nothing readable in it yet
            raise

    def _start(self, camera_id: str, compression: str, metadata: dict[str, Any] | None, fps: float) -> None:
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
        from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
        from mcap_protobuf.schema import build_file_descriptor_set

        self._w = Writer(self._file, compression=_COMPRESSION[compression], chunk_size=4 << 20)
        self._w.start(profile="", library="trackdeform3d")
        if metadata is not None:
            self._w.add_metadata(OPEN_METADATA, _json_values(metadata))
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        # the small JSON channels (ground truth as errors), written beside the file once it is final
        self._digest = DigestWriter(message_gt_errors_mm)
        self.camera_id = camera_id
        self.n_frames = 0
        self._last_tf = -np.inf
        self.first_frame: int | None = None
        self.last_frame: int | None = None
        c = self.color_config
        self._color_enc = ColorEncoder(c.codec, crf=c.crf, preset=c.preset, gop=c.gop, jpeg_quality=c.jpeg_quality,
                                       fps=fps)
        self._depth_enc = DepthEncoder(self.depth_config.codec)
        self._image_cls = {SCHEMA_RAW: RawImage, SCHEMA_COMPRESSED: CompressedImage, SCHEMA_VIDEO: CompressedVideo,
                           SCHEMA_DEPTH: CompressedImage}  # planes depth: CompressedImage's fields, its own name
        color_cls = {"h264": CompressedVideo, "jpeg": CompressedImage, "raw": RawImage}[c.codec]
        depth_cls, depth_name = {"png": (CompressedImage, None), "planes": (CompressedImage, SCHEMA_DEPTH),
                                 "raw": (RawImage, None)}[self.depth_config.codec]

        def proto(cls: Any, name: str | None = None) -> int:
            fds = build_file_descriptor_set(cls)
            if name is not None:
                _rename_message(fds, cls.DESCRIPTOR.full_name, name)
            return self._w.register_schema(name or cls.DESCRIPTOR.full_name, "protobuf", fds.SerializeToString())

        def js(name: str, schema: dict[str, Any]) -> int:
            return self._w.register_schema(name, "jsonschema", json.dumps(schema).encode())

        calib, tf, scene = proto(CameraCalibration), proto(FrameTransforms), proto(SceneUpdate)
        color_sid = proto(color_cls)
        depth_sid = color_sid if depth_cls is color_cls and depth_name is None else proto(depth_cls, depth_name)
        cam = f"/cam/{camera_id}"
        for topic, sid, enc in [
            (f"{cam}/color", color_sid, "protobuf"),
            (f"{cam}/depth", depth_sid, "protobuf"),
            (f"{cam}/calibration", calib, "protobuf"),
            (f"{cam}/frame_info", js("trackdeform.FrameInfo", SCHEMAS["trackdeform.FrameInfo"]), "json"),
            ("/arms/state", js("trackdeform.ArmState", SCHEMAS["trackdeform.ArmState"]), "json"),
            ("/arms/state_at_frame", js("trackdeform.ArmStateAtFrame", SCHEMAS["trackdeform.ArmStateAtFrame"]),
             "json"),
            ("/tf", tf, "protobuf"),
            ("/keypoints", js("trackdeform.Keypoints", SCHEMAS["trackdeform.Keypoints"]), "json"),
            ("/keypoints/scene", scene, "protobuf"),
            ("/ground_truth/keypoints", js("trackdeform.GroundTruth", SCHEMAS["trackdeform.GroundTruth"]), "json"),
        ]:
            self._channels[topic] = self._w.register_channel(topic, enc, sid)
            self._seq[topic] = 0
        self._RawImage, self._Calib, self._TF, self._Scene = RawImage, CameraCalibration, FrameTransforms, SceneUpdate
        self._file.flush()  # the header and episode_open reach the disk before any frame

    # ------------------------------------------------------------------ writing
    def _add(self, topic: str, data: bytes, t: float, publish: float | None = None) -> None:
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        self._w.add_message(self._channels[topic], _ns(t), data, _ns(t if publish is None else publish), seq)

    def _add_json(self, topic: str, obj: dict[str, Any], t: float) -> None:
        data = _json_bytes(obj)
        self._add(topic, data, t)
        self._digest.add(topic, _ns(t), data.decode(), obj)

    def _image_message(self, img: EncodedImage, ts: Any) -> bytes:
        cls = self._image_cls[img.schema]
        if img.schema == SCHEMA_RAW:
            msg = cls(timestamp=ts, frame_id="cam", width=img.width, height=img.height, encoding=img.fmt,
                      step=img.step, data=img.data)
        else:
            msg = cls(timestamp=ts, frame_id="cam", format=img.fmt, data=img.data)
        return msg.SerializeToString()

    def write_frame(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        """Colour, depth, frame info (+ calibration and camera pose on the first frame, ground truth if any)."""
        from google.protobuf.timestamp_pb2 import Timestamp

        t = frame.device_stamp
        ts = Timestamp()
        ts.FromNanoseconds(_ns(t))
        cam = f"/cam/{self.camera_id}"
        if self.n_frames == 0:
            self.write_calibration(frame, T_world_cam)
        depth_mm = np.asarray(frame.depth_mm(), dtype=np.uint16)
        pending = self._executor.submit(self._depth_enc.encode, depth_mm) if self._executor is not None else None
        try:
            color = self._color_enc.encode(frame.color)
        finally:
            depth = pending.result() if pending is not None else self._depth_enc.encode(depth_mm)
        self._add(f"{cam}/color", self._image_message(color, ts), t, frame.host_stamp)
        self._add(f"{cam}/depth", self._image_message(depth, ts), t, frame.host_stamp)
        self._add_json(
            f"{cam}/frame_info",
            {"frame_number": frame.frame_number, "device_stamp": frame.device_stamp, "host_stamp": frame.host_stamp,
             "color_keyframe": color.keyframe},
            t,
        )
        if frame.ground_truth is not None:
            gt = frame.ground_truth
            self._add_json(
                "/ground_truth/keypoints",
                {"frame_number": frame.frame_number, **ground_truth_to_json(gt)},
                t,
            )
        self.n_frames += 1
        if self.first_frame is None:
            self.first_frame = frame.frame_number
        self.last_frame = frame.frame_number

    def write_calibration(self, frame: RGBDFrame, T_world_cam: np.ndarray) -> None:
        """Camera intrinsics (foxglove.CameraCalibration) and the world -> cam transform."""
        from google.protobuf.timestamp_pb2 import Timestamp

        ts = Timestamp()
        ts.FromNanoseconds(_ns(frame.device_stamp))
        k = frame.intrinsics
        K = k.K
        P = np.hstack([K, np.zeros((3, 1))])
        msg = self._Calib(
            timestamp=ts, frame_id="cam", width=k.width, height=k.height, distortion_model="plumb_bob",
            D=[0.0] * 5, K=K.ravel().tolist(), R=np.eye(3).ravel().tolist(), P=P.ravel().tolist(),
        )
        self._add(f"/cam/{self.camera_id}/calibration", msg.SerializeToString(), frame.device_stamp)
        self.write_transforms(frame.device_stamp, {"cam": T_world_cam})

    def write_transforms(self, t: float, poses: dict[str, np.ndarray]) -> None:
        """foxglove.FrameTransforms world -> each named frame."""
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
        from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
        from google.protobuf.timestamp_pb2 import Timestamp

        ts = Timestamp()
        ts.FromNanoseconds(_ns(t))
        msg = self._TF()
        quats = _quats_xyzw(np.stack([T[:3, :3] for T in poses.values()]))
        for (child, T), (x, y, z, w) in zip(poses.items(), quats.tolist(), strict=True):
            msg.transforms.append(
                FrameTransform(
                    timestamp=ts, parent_frame_id="world", child_frame_id=child,
                    translation=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                    rotation=Quaternion(x=x, y=y, z=z, w=w),
                )
            )
        self._add("/tf", msg.SerializeToString(), t)

    def write_arm_state(self, state: dict[str, Any], tcp_poses: dict[str, np.ndarray] | None = None) -> None:
        """One sample of both arms (the ``arms/state`` JSON, every sample) and their TCP frames.

        The TCP frames go to ``/tf`` at most at ``TF_RATE`` (for viewing; the exact arm input is in
        ``u`` of every state), which keeps the files and the writer's CPU small.
        """
        t = float(state["stamp"])
        self._add_json("/arms/state", state, t)
        if tcp_poses and t - self._last_tf >= 1.0 / TF_RATE - 1e-9:
            self._last_tf = t
            self.write_transforms(t, tcp_poses)

    def write_frame_state(self, paired: dict[str, Any], t: float) -> None:
        """The arms' state at a frame's capture time (``t``: the frame's log time, s)."""
        self._add_json("/arms/state_at_frame", paired, t)

    def write_keypoints(self, msg: dict[str, Any], t: float) -> None:
        """Tracked keypoints (JSON, points as {x, y, z}) and a SceneUpdate with spheres and edge lines."""
        self._add_json("/keypoints", keypoints_record(msg), t)
        self._add("/keypoints/scene", _scene_update(self._Scene, msg, t).SerializeToString(), t)

    # ------------------------------------------------------------------ closing
    def close(self, metadata: dict[str, Any]) -> Path:
        """Write metadata, finish, fsync and rename to the final name; returns it.

        Raises RecordingFailed when the file could not be finished (now or in an earlier call): it then
        stays ``.active`` for :func:`recover_active`, and is never reported as finished.
        """
        if self.failed is not None:
            raise RecordingFailed(self.failed)
        if self.closed:
            return self.path
        self._color_enc.close()
        meta = dict(metadata)
        meta.update(n_frames=self.n_frames, first_frame=self.first_frame, last_frame=self.last_frame,
                    image_encoding={"color": self.color_config.model_dump(), "depth": self.depth_config.model_dump()})
        try:
            self._w.add_metadata(CLOSE_METADATA, _json_values(meta))
            self._w.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.active_path, self.path)
            fsync_dir(self.path.parent)
        except Exception as e:
            self.failed = f"{self.path.name}: could not be finished ({type(e).__name__}: {e}); left as .active"
            self.abort()
            raise RecordingFailed(self.failed) from e
        try:  # the digest only speeds up readers (the report): an episode never fails for it
            self._digest.write(self.path, self.n_frames)
        except OSError as e:
            log.warning("%s: could not write its digest (%s); readers will read the episode file", self.path, e)
        self.closed = True
        return self.path

    def abort(self) -> None:
        """Stop writing without finishing; the ``.active`` file stays for :func:`recover_active`.

        Never raises: a flush that fails (a full disk) loses only the unflushed tail.
        """
        if self.closed:
            return
        self.closed = True
        self._color_enc.close()
        try:
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as e:
            log.warning("%s: unflushed data lost (%s)", self.active_path.name, e)
        finally:
            try:
                self._file.close()
            except OSError:
                pass


def _json_bytes(obj: Any) -> bytes:  # noqa: ANN401 - any JSON value
    """Compact JSON of ``obj``, non-finite floats as null (not JSON: Foxglove's JSON.parse refuses them).

    orjson (a few times json's speed on the 250 Hz arm states the recorder thread writes beside the frames);
    json for what orjson does not take (ints beyond 64 bits).
    """
    try:
        return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY)
    except TypeError:
        pass
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:
        return json.dumps(_finite_or_null(obj), separators=(",", ":"), allow_nan=False).encode()


def _finite_or_null(obj: Any) -> Any:  # noqa: ANN401 - any JSON value
    """``obj`` with every non-finite float replaced by None (JSON null)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_null(v) for v in obj]
    return obj


def _scene_update(SceneUpdate: Any, msg: dict[str, Any], t: float) -> Any:
    """Keypoints as spheres and edges as a line list, in the world frame."""
    from foxglove_schemas_protobuf.Color_pb2 import Color
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
    from foxglove_schemas_protobuf.Point3_pb2 import Point3
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
    from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp

    ts = Timestamp()
    ts.FromNanoseconds(_ns(t))
    kp = msg.get("keypoints", [])
    if not kp:  # nothing tracked (lost): clear the previous keypoints instead of an empty entity
        from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion

        return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletion.MATCHING_ID,
                                                          id="keypoints")])
    ent = SceneEntity(timestamp=ts, frame_id="world", id="keypoints")
    for p in kp:
        ent.spheres.append(
            SpherePrimitive(size=Vector3(x=0.012, y=0.012, z=0.012), color=Color(r=1.0, g=0.8, b=0.1, a=1.0))
        )
        ent.spheres[-1].pose.position.x, ent.spheres[-1].pose.position.y, ent.spheres[-1].pose.position.z = p
        ent.spheres[-1].pose.orientation.w = 1.0
    line = LinePrimitive(type=LinePrimitive.LINE_LIST, thickness=3.0, scale_invariant=True,
                         color=Color(r=0.1, g=0.9, b=1.0, a=1.0))
    line.pose.orientation.w = 1.0
    for i, j in msg.get("edges", []):
        line.points.append(Point3(x=kp[i][0], y=kp[i][1], z=kp[i][2]))
        line.points.append(Point3(x=kp[j][0], y=kp[j][1], z=kp[j][2]))
    if line.points:  # Foxglove warns about a line without points
        ent.lines.append(line)
    return SceneUpdate(entities=[ent])


class Recorder:
    """Writes episodes on its own thread so capture never waits on the disk.

    The queue is bounded and ``put`` blocks when it is full: frames are never dropped here.
    A closed episode stays open for ``close_grace`` more frames so late keypoints of its last
    frames (the tracker runs behind the camera) still land in it. Images are encoded here, off the
    capture thread: colour on this thread, depth on one helper thread at the same time.
    ``cpu_seconds`` is the CPU time these two threads have used (encoding and writing).

    frames (the tracker runs behind the camera) still land in it.

    The first I/O error (OSError: a full disk, a vanished mount) sets ``failed`` and the recorder
    stops for good: the open episode is left ``.active`` with what reached the disk, episodes in
    their grace period are still finished if the disk allows, and every later open / frame / state
    / keypoint is dropped. Only files whose close succeeded are in ``finished``.
    """

    def __init__(self, camera_id: str, compression: str = "zstd", maxsize: int = 60, close_grace: int = 15,
                 color: ColorOutputConfig | None = None, depth: DepthOutputConfig | None = None) -> None:
        import queue
        import threading
        from concurrent.futures import ThreadPoolExecutor

        self.camera_id = camera_id
        self.compression = compression
        self.color = color or ColorOutputConfig()
        self.depth = depth or DepthOutputConfig()
        self.cpu_seconds = 0.0
        self.frames_written = 0
        self._cpu_lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="recorder-depth")
        self._executor = _CpuTimedExecutor(self._pool, self._add_cpu)
        self.close_grace = close_grace
        self.finished: list[Path] = []
        self.errors: list[str] = []
        self.failed: str | None = None  # the I/O error that stopped the recorder
        self.keypoints_written = 0
        self.keypoints_unmatched = 0
        self.dropped_after_failure = 0
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._current: EpisodeWriter | None = None
        self._closing: list[tuple[EpisodeWriter, dict[str, Any], int]] = []
        self._current_meta: dict[str, Any] = {}
        self._logged: set[tuple[str, str]] = set()
        self._thread.start()

    # ------------------------------------------------------------ producer side (any thread)
    def open_episode(self, path: Path, metadata: dict[str, Any]) -> None:
        """Start a new episode file (the previous one must have been closed); ``metadata`` is written at once."""
        self._q.put(("open", path, metadata))

    def frame(self, frame: RGBDFrame, T_world_cam: np.ndarray, paired: dict[str, Any] | None = None) -> None:
        """Record a frame in the current episode, with the arms' state at its capture time if paired."""
        self._q.put(("frame", frame, T_world_cam, paired))

    def arm_state(self, state: dict[str, Any], tcp_poses: dict[str, np.ndarray] | None = None) -> None:
        """Record one joint-state sample of both arms."""
        self._q.put(("arm", state, tcp_poses))

    def keypoints(self, msg: dict[str, Any]) -> None:
        """Record a keypoint message in the episode that holds its frame."""
        self._q.put(("kp", msg))

    def close_episode(self, metadata: dict[str, Any]) -> None:
        """Finish the current episode with ``metadata`` merged into what open_episode gave."""
        self._q.put(("close", metadata))

    def stop(self, timeout: float = 60.0) -> None:
        """Flush everything, close open episodes and join the thread."""
        self._q.put(("stop",))
        self._thread.join(timeout)
        if self._thread.is_alive():
            self.errors.append(f"recorder did not finish within {timeout} s")
        else:
            self._pool.shutdown(wait=True)

    def _add_cpu(self, seconds: float) -> None:
        with self._cpu_lock:
            self.cpu_seconds += seconds

    # ------------------------------------------------------------ writer thread
    def _fail(self, message: str) -> None:
        """Stop recording for good after an I/O error (the first one is the reason)."""
        if self.failed is None:
            self.failed = message
            log.info("recording stopped: %s", message)  # the session reports it in one line
        self.errors.append(message)
        if self._current is not None:
            self._current.abort()
            self._current = None

    def _finish(self, writer: EpisodeWriter, meta: dict[str, Any]) -> None:
        """Close ``writer``; a file only counts as finished when its close succeeded."""
        try:
            path = writer.close(meta)
        except RecordingFailed as e:
            cause = e.__cause__
            if isinstance(cause, OSError) or cause is None:
                self._fail(str(e))
            else:
                self.errors.append(str(e))
                self._log_once("close", type(cause).__name__, str(e))
            return
        self.finished.append(path)

    def _tick_closing(self) -> None:
        due = [(w, m) for w, m, left in self._closing if left <= 1]
        self._closing = [(w, m, left - 1) for w, m, left in self._closing if left > 1]
        for writer, meta in due:
            self._finish(writer, meta)

    def _route_keypoints(self, msg: dict[str, Any]) -> None:
        fn = msg.get("frame_number", -1)
        t = float(msg.get("stamp", 0.0))
        for writer in [w for w, _, _ in self._closing] + ([self._current] if self._current else []):
            if writer.first_frame is not None and writer.first_frame <= fn <= (writer.last_frame or -1):
                writer.write_keypoints(msg, t)
                self.keypoints_written += 1
                return
        self.keypoints_unmatched += 1

    def _log_once(self, op: str, kind: str, message: str) -> None:
        """Log a failure once per (operation, exception type): a bad input repeated every frame is no log flood."""
        if (op, kind) not in self._logged:
            self._logged.add((op, kind))
            log.error("recorder: %s (further %s errors of this kind are counted, not logged)", message, op)

    def _stop_all(self) -> None:
        closing, self._closing = self._closing, []
        for writer, meta, _ in closing:
            self._finish(writer, meta)
        if self._current is not None:
            current, self._current = self._current, None
            self._finish(current, {**self._current_meta, "complete": False})

    def _run(self) -> None:
        import time

        while True:
            item = self._q.get()
            op = item[0]
            if op == "stop":
                self._stop_all()
                return
            if self.failed is not None:
                self.dropped_after_failure += 1
                continue
            c0 = time.thread_time()
            try:
                self._handle(op, item)
            except OSError as e:
                where = self._current.active_path.name if self._current is not None else str(item[1])
                self._fail(f"{where}: {op}: {type(e).__name__}: {e}")
            except Exception as e:  # keep the thread alive; the session reads .errors
                if len(self.errors) < 100:
                    self.errors.append(f"recorder: {op}: {type(e).__name__}: {e}")
                self._log_once(op, type(e).__name__, f"{op}: {type(e).__name__}: {e}")
            finally:
                self._add_cpu(time.thread_time() - c0)

    def _handle(self, op: str, item: tuple[Any, ...]) -> None:
        if op == "open":
            if self._current is not None:  # defensive: never lose the previous one
                current, self._current = self._current, None
                self._finish(current, {**self._current_meta, "complete": False})
            self._current_meta = dict(item[2])
            self._current = EpisodeWriter(item[1], self.camera_id, self.compression, self.color, self.depth,
                                          self._executor, metadata=self._current_meta)
        elif op == "frame":
            if self._current is not None:
                self._current.write_frame(item[1], item[2])
                self.frames_written += 1
                if len(item) > 3 and item[3] is not None:
                    self._current.write_frame_state(item[3], item[1].device_stamp)
            self._tick_closing()
        elif op == "arm":
            if self._current is not None:
                self._current.write_arm_state(item[1], item[2])
        elif op == "kp":
            self._route_keypoints(item[1])
        elif op == "close":
            if self._current is not None:
                current, self._current = self._current, None
                meta = {**self._current_meta, **item[1]}
                if self.close_grace > 0:
                    self._closing.append((current, meta, self.close_grace))
                else:
                    self._finish(current, meta)


class _CpuTimedExecutor(Executor):
    """Submits to ``inner`` and reports each task's CPU time (its thread's) to ``report``."""

    def __init__(self, inner: Executor, report: Any) -> None:
        self._inner, self._report = inner, report

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Any:  # noqa: ANN401 - Executor's signature
        """Run ``fn(*args, **kwargs)`` on the inner executor, timing its thread's CPU."""
        import time

        def timed() -> Any:  # noqa: ANN401
            c0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self._report(time.thread_time() - c0)

        return self._inner.submit(timed)
