"""The zenoh message encodings: plain bytes and JSON, readable from any language.

Keys (``<prefix>/<station>/...``):

- ``cam/<id>/frame``: one message per colour + depth pair::

      b"TDF1" | uint32 little-endian n | n bytes of UTF-8 JSON header | colour bytes | depth bytes

  The header holds ``frame_number``, ``device_stamp``, ``host_stamp`` (s), ``width``, ``height``,
  ``color_encoding`` ("rgb8", row-major H×W×3), ``depth_encoding`` ("16UC1", row-major H×W,
  little-endian), ``depth_scale`` (m per unit), ``K`` (9 floats, row-major), ``T_world_cam``
  (16 floats, row-major, metres), ``camera_id``, ``run`` (object, category, program, speed,
  run_index of the program run being recorded), optionally ``joint_state`` (both arms' joints at the
  frame's capture time: ``{"stamp", "left": {"q", "gripper_width", "grasped"}, "right": {...}, "u",
  "pairing_error_s"}``, see orchestrator.timesync; use it rather than the latest ``arms/state``)
  and, in mock mode, ``ground_truth``.
- ``arms/state``: JSON ``{"stamp": s, "left": {"q": [7], "dq": [7], "gripper_width": m,
  "grasped": bool}, "right": {...}, "u": [12]}`` — u is the paper's arm input (per arm: TCP
  position m + rotation vector rad, world frame; left then right).
- ``keypoints``: JSON, see :func:`encode_keypoints`.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from tdcommon.types import CameraIntrinsics, GroundTruth, RGBDFrame

FRAME_MAGIC = b"TDF1"
KEYPOINTS_SCHEMA = "trackdeform.Keypoints/1"


@dataclass(frozen=True)
class FrameMessage:
    """A decoded frame message: the frame plus the camera pose it was captured with."""

    frame: RGBDFrame
    T_world_cam: np.ndarray  # (4, 4)
    camera_id: str
    run: dict[str, Any]  # what is being recorded: object, category, program, speed, run_index
    joint_state: dict[str, Any] | None = None  # the arms at the frame's capture time, when the sender paired them


def ground_truth_to_json(gt: GroundTruth, max_centreline: int = 400) -> dict[str, Any]:
    """Ground truth as JSON (keypoints to 1 µm); the dense centreline / mid-surface is thinned to at most
    ``max_centreline`` evenly picked samples, rounded to 0.1 mm, so a cloth frame's message stays small."""
    c = np.asarray(gt.centreline)
    idx = np.unique(np.linspace(0, len(c) - 1, min(max_centreline, len(c))).round().astype(int)) if len(c) else []
    return {
        "keypoints": np.round(gt.keypoints, 6).tolist(),
        "edges": gt.edges.tolist(),
        "anchors": gt.anchors.tolist(),
        "radius": gt.radius,
        "category": gt.category,
        "centreline": np.round(c[idx], 4).tolist(),
    }


def ground_truth_from_json(d: dict[str, Any]) -> GroundTruth:
    """Inverse of :func:`ground_truth_to_json`; a missing field reads as empty (older episodes lack some)."""
    return GroundTruth(
        keypoints=np.asarray(d.get("keypoints", []), dtype=np.float64).reshape(-1, 3),
        edges=np.asarray(d.get("edges", []), dtype=np.int64).reshape(-1, 2),
        centreline=np.asarray(d.get("centreline") or [], dtype=np.float64).reshape(-1, 3),
        radius=float(d.get("radius", 0.0)),
        anchors=np.asarray(d.get("anchors", []), dtype=np.int64),
        category=str(d.get("category", "")),
    )


def encode_frame(frame: RGBDFrame, T_world_cam: np.ndarray, camera_id: str, run: dict[str, Any] | None = None,
                 joint_state: dict[str, Any] | None = None) -> bytes:
    """Serialise a frame for the bus (see module docstring for the layout); ``run`` says what is recorded,
    ``joint_state`` the arms at the frame's capture time."""
    color = np.ascontiguousarray(frame.color, dtype=np.uint8)
    depth = np.ascontiguousarray(frame.depth, dtype="<u2")
    k = frame.intrinsics
    header = {
        "frame_number": int(frame.frame_number),
        "device_stamp": float(frame.device_stamp),
        "host_stamp": float(frame.host_stamp),
        "width": k.width,
        "height": k.height,
        "color_encoding": "rgb8",
        "depth_encoding": "16UC1",
        "depth_scale": float(frame.depth_scale),
        "K": k.K.ravel().tolist(),
        "T_world_cam": np.asarray(T_world_cam, dtype=np.float64).ravel().tolist(),
        "camera_id": camera_id,
        "color_size": color.nbytes,
        "depth_size": depth.nbytes,
        "run": run or {},
    }
    if joint_state is not None:
        header["joint_state"] = joint_state
    if frame.ground_truth is not None:
        header["ground_truth"] = ground_truth_to_json(frame.ground_truth)
    hb = json.dumps(header, separators=(",", ":")).encode()
    return b"".join([FRAME_MAGIC, struct.pack("<I", len(hb)), hb, color.tobytes(), depth.tobytes()])


def decode_frame(payload: bytes | memoryview) -> FrameMessage:
    """Inverse of :func:`encode_frame`; raises ValueError on a malformed message."""
    buf = memoryview(payload)
    if bytes(buf[:4]) != FRAME_MAGIC:
        raise ValueError(f"not a frame message (magic {bytes(buf[:4])!r}, expected {FRAME_MAGIC!r})")
    (n,) = struct.unpack("<I", buf[4:8])
    h = json.loads(bytes(buf[8 : 8 + n]))
    w, hgt = int(h["width"]), int(h["height"])
    off = 8 + n
    if len(buf) != off + h["color_size"] + h["depth_size"] or h["color_size"] != w * hgt * 3:
        raise ValueError("frame message size does not match its header")
    color = np.frombuffer(buf[off : off + h["color_size"]], dtype=np.uint8).reshape(hgt, w, 3)
    depth = np.frombuffer(buf[off + h["color_size"] :], dtype="<u2").reshape(hgt, w)
    K = np.asarray(h["K"]).reshape(3, 3)
    intr = CameraIntrinsics.from_K(K, w, hgt)
    gt = ground_truth_from_json(h["ground_truth"]) if "ground_truth" in h else None
    frame = RGBDFrame(
        color, depth.astype(np.uint16, copy=False), float(h["depth_scale"]), intr,
        float(h["device_stamp"]), float(h["host_stamp"]), int(h["frame_number"]), gt,
    )
    js = h.get("joint_state")
    return FrameMessage(frame, np.asarray(h["T_world_cam"]).reshape(4, 4), str(h["camera_id"]), h.get("run", {}),
                        js if isinstance(js, dict) else None)


def encode_json(obj: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON."""
    return json.dumps(obj, separators=(",", ":")).encode()


def decode_json(payload: bytes | memoryview) -> dict[str, Any]:
    """Parse a JSON message."""
    return json.loads(bytes(payload))


def encode_keypoints(
    *,
    frame_number: int,
    stamp: float,
    keypoints: np.ndarray,
    edges: np.ndarray,
    grasp_indices: dict[str, int],
    object_name: str,
    category: str,
    status: str,
    abs_mm: float | None,
    cd_mm: float | None,
    anchors: np.ndarray | None = None,
    extra: dict[str, Any] | None = None,
) -> bytes:
    """Live keypoints as JSON.

    ``{"schema": "trackdeform.Keypoints/1", "frame_number", "stamp" (s, the frame's device stamp),
    "keypoints": [[x, y, z], ...] (m, world), "edges": [[i, j], ...], "grasp_indices":
    {"left": i or -1, "right": ...}, "object", "category" ("dlo"|"bdlo"|"cloth"), "status"
    ("init"|"tracking"|"lost"), "abs_mm", "cd_mm", "anchors": [i, ...]}``.
    """
    msg = {
        "schema": KEYPOINTS_SCHEMA,
        "frame_number": int(frame_number),
        "stamp": float(stamp),
        "keypoints": np.round(np.asarray(keypoints, dtype=np.float64), 6).tolist(),
        "edges": np.asarray(edges, dtype=np.int64).tolist(),
        "grasp_indices": {k: int(v) for k, v in grasp_indices.items()},
        "object": object_name,
        "category": category,
        "status": status,
        "abs_mm": None if abs_mm is None else float(abs_mm),
        "cd_mm": None if cd_mm is None else float(cd_mm),
        "anchors": [] if anchors is None else np.asarray(anchors, dtype=np.int64).tolist(),
    }
    if extra:
        msg.update(extra)
    return encode_json(msg)
