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
- ``keypoints``: JSON, see :func:`encode_keypoints`; its JSON Schema is :data:`KEYPOINTS_JSON_SCHEMA`
  (also ``schemas/keypoints.schema.json`` and, from a live session, a get on ``schema/keypoints``).
- ``session/run``: JSON :func:`run_announcement`, the run the session records now (the tracker
  switches tracks on it alone: a new ``track_id``, else a new ``run_id``). ``phase`` is ``record``, or
  ``init`` for the live initialisation's frames (published, never recorded; each frame header's
  ``init_step`` says p0, move, p1, back or rest).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from itertools import chain
from operator import itemgetter
from typing import Any

import numpy as np

from tdcommon.types import CameraIntrinsics, GroundTruth, RGBDFrame

FRAME_MAGIC = b"TDF1"
KEYPOINTS_SCHEMA = "trackdeform.Keypoints/2"
KEYPOINTS_STATUS = ("reference", "waiting", "init", "tracking", "degraded", "lost")

_POINT = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_PAIR = {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 2, "maxItems": 2}
_MM = {"type": ["number", "null"], "minimum": 0}
KEYPOINTS_JSON_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://trackdeform3d.invalid/schemas/keypoints.schema.json",
    "title": KEYPOINTS_SCHEMA,
    "description": "Live TrackDeform3D keypoints of one camera frame, published as UTF-8 JSON on "
                   "<prefix>/<station>/keypoints. Units: metres, seconds; world frame (z up).",
    "type": "object",
    "required": ["schema", "session_id", "run_id", "frame_number", "stamp", "keypoints", "edges",
                 "grasp_indices", "object", "category", "status", "abs_mm", "cd_mm", "anchors"],
    "properties": {
        "schema": {"const": KEYPOINTS_SCHEMA},
        "session_id": {"type": "string", "minLength": 1, "description": "the recording session (its announcement)"},
        "run_id": {"type": "string", "minLength": 1, "description": "the program run (session/run announcement)"},
        "frame_number": {"type": "integer", "minimum": 0, "description": "the camera frame the keypoints are of"},
        "stamp": {"type": "number", "description": "the frame's device stamp, s"},
        "keypoints": {"type": "array", "items": _POINT, "description": "(N, 3) m, world frame; [] when lost"},
        "edges": {"type": "array", "items": _PAIR, "description": "(E, 2) indices into keypoints"},
        "grasp_indices": {
            "type": "object", "required": ["left", "right"],
            "properties": {s: {"type": "integer", "minimum": -1} for s in ("left", "right")},
            "description": "the keypoint each gripper holds, -1 for none",
        },
        "object": {"type": "string"},
        "category": {"enum": ["dlo", "bdlo", "cloth", ""]},
        "status": {"enum": list(KEYPOINTS_STATUS)},
        "abs_mm": {**_MM, "description": "the paper's Abs: edge-length RMSE against the rest lengths, mm"},
        "cd_mm": {**_MM, "description": "the paper's CD: keypoint-to-cloud distance, mm"},
        "anchors": {"type": "array", "items": {"type": "integer", "minimum": 0}},
        "smoothed": {"type": "array", "items": _POINT, "description": "(N, 3) m, causal moving average"},
        "rest_lengths": {"type": "array", "items": {"type": "number", "minimum": 0}, "description": "(E,) m"},
        "n_points": {"type": "integer", "minimum": 0, "description": "object cloud points used"},
        "processing_ms": {"type": "number", "minimum": 0},
        "note": {"type": "string"},
        "run_index": {"type": ["integer", "null"], "description": "the run's index in the plan"},
    },
}


@dataclass(frozen=True)
class FrameMessage:
    """A decoded frame message: the frame plus the camera pose it was captured with."""

    frame: RGBDFrame
    T_world_cam: np.ndarray  # (4, 4)
    camera_id: str
    run: dict[str, Any]  # what is being recorded: object, category, program, speed, run_index
    joint_state: dict[str, Any] | None = None  # the arms at the frame's capture time, when the sender paired them


def points_to_json(points: Any, decimals: int = 6) -> list[dict[str, float]]:
    """(N, 3) points -> [{"x", "y", "z"}, ...] rounded to ``decimals``."""
    p = np.round(np.asarray(points, dtype=np.float64).reshape(-1, 3), decimals)
    return [{"x": x, "y": y, "z": z} for x, y, z in p.tolist()]


def edges_to_json(edges: Any) -> list[dict[str, int]]:
    """(E, 2) index pairs -> [{"i", "j"}, ...]."""
    return [{"i": i, "j": j} for i, j in np.asarray(edges, dtype=np.int64).reshape(-1, 2).tolist()]


_XYZ = itemgetter("x", "y", "z")


def points_from_json(value: Any) -> np.ndarray:
    """[{"x", "y", "z"}, ...], [[x, y, z], ...] or an (N, 3) array -> (N, 3) float64."""
    if isinstance(value, np.ndarray):
        return np.asarray(value, dtype=np.float64).reshape(-1, 3)
    if value and isinstance(value[0], dict):  # a C-level walk: ground truth has hundreds of points a frame
        return np.fromiter(chain.from_iterable(map(_XYZ, value)), np.float64, count=3 * len(value)).reshape(-1, 3)
    return np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1, 3)


def edges_from_json(value: Any) -> np.ndarray:
    """[{"i", "j"}, ...] or [[i, j], ...] -> (E, 2) int64."""
    if value and isinstance(value[0], dict):
        return np.array([[e["i"], e["j"]] for e in value], dtype=np.int64).reshape(-1, 2)
    return np.asarray(value if value is not None else [], dtype=np.int64).reshape(-1, 2)


_last_ground_truth: tuple[GroundTruth, int, dict[str, Any]] | None = None  # (gt, max_centreline, its JSON)


def ground_truth_to_json(gt: GroundTruth, max_centreline: int = 400) -> dict[str, Any]:
    """Ground truth as JSON (keypoints to 1 µm, points as ``{x, y, z}``, edges as ``{i, j}``: the layout
    Foxglove's JSON parser takes); the dense centreline / mid-surface is thinned to at most
    ``max_centreline`` evenly picked samples, rounded to 0.1 mm, so a cloth frame's message stays small.

    The result for the last object asked is kept and given again (do not modify it): a frame's ground truth
    goes both to the bus and to the episode file, and its hundreds of points cost the daemon's threads."""
    global _last_ground_truth
    last = _last_ground_truth
    if last is not None and last[0] is gt and last[1] == max_centreline:
        return last[2]
    c = np.asarray(gt.centreline)
    idx = np.unique(np.linspace(0, len(c) - 1, min(max_centreline, len(c))).round().astype(int)) if len(c) else []
    out = {
        "keypoints": points_to_json(gt.keypoints, 6),
        "edges": edges_to_json(gt.edges),
        "anchors": gt.anchors.tolist(),
        "radius": gt.radius,
        "category": gt.category,
        "centreline": points_to_json(c[idx] if len(c) else np.zeros((0, 3)), 4),
    }
    _last_ground_truth = (gt, max_centreline, out)
    return out


def ground_truth_from_json(d: dict[str, Any]) -> GroundTruth:
    """Inverse of :func:`ground_truth_to_json` (also plain nested lists); a missing field reads as empty."""
    return GroundTruth(
        keypoints=points_from_json(d.get("keypoints", [])),
        edges=edges_from_json(d.get("edges", [])),
        centreline=points_from_json(d.get("centreline")),
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
    session_id: str = "",
    run_id: str = "",
) -> bytes:
    """Live keypoints as JSON (:data:`KEYPOINTS_JSON_SCHEMA`).

    ``{"schema": "trackdeform.Keypoints/2", "session_id", "run_id", "frame_number", "stamp" (s, the frame's
    device stamp), "keypoints": [[x, y, z], ...] (m, world), "edges": [[i, j], ...], "grasp_indices":
    {"left": i or -1, "right": ...}, "object", "category" ("dlo"|"bdlo"|"cloth"), "status"
    (:data:`KEYPOINTS_STATUS`), "abs_mm", "cd_mm", "anchors": [i, ...]}``.
    """
    msg = {
        "schema": KEYPOINTS_SCHEMA,
        "session_id": session_id,
        "run_id": run_id,
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


def check_keypoints(msg: Any) -> tuple[str, str] | None:
    """Why a decoded keypoint message cannot be recorded, as (kind, detail); None when it can.

    Checks what a JSON Schema cannot: keypoints (N, 3) finite, edges and anchors indices < N,
    grasp indices in [-1, N). ``kind`` is one of: not_object, schema, missing, ids, frame_number,
    keypoints, not_finite, edges, anchors, grasp, status.
    """
    if not isinstance(msg, dict):
        return "not_object", f"expected a JSON object, got {type(msg).__name__}"
    if msg.get("schema") != KEYPOINTS_SCHEMA:
        return "schema", f"schema {msg.get('schema')!r}, expected {KEYPOINTS_SCHEMA!r}"
    missing = [k for k in KEYPOINTS_JSON_SCHEMA["required"] if k not in msg]
    if missing:
        return "missing", f"missing fields {missing}"
    if not all(isinstance(msg[k], str) and msg[k] for k in ("session_id", "run_id")):
        return "ids", "session_id and run_id must be non-empty strings"
    fn = msg["frame_number"]
    if isinstance(fn, bool) or not isinstance(fn, int) or fn < 0:
        return "frame_number", f"frame_number {fn!r} is not an integer >= 0"
    if msg["status"] not in KEYPOINTS_STATUS:
        return "status", f"status {msg['status']!r} is not one of {KEYPOINTS_STATUS}"
    try:
        kp = np.asarray(msg["keypoints"], dtype=np.float64)
    except (TypeError, ValueError):
        return "keypoints", "keypoints are not a numeric (N, 3) array"
    if kp.size == 0:
        kp = kp.reshape(0, 3)
    if kp.ndim != 2 or kp.shape[1] != 3:
        return "keypoints", f"keypoints have shape {kp.shape}, expected (N, 3)"
    if not np.isfinite(kp).all():
        return "not_finite", "keypoints hold NaN or infinite values"
    n = len(kp)
    for field in ("edges", "anchors"):
        try:
            a = np.asarray(msg[field], dtype=np.float64)
        except (TypeError, ValueError):
            return field, f"{field} are not numeric"
        if field == "edges" and a.size == 0:
            a = a.reshape(0, 2)
        if (field == "edges" and (a.ndim != 2 or a.shape[1] != 2)) or (field == "anchors" and a.ndim != 1):
            return field, f"{field} have shape {a.shape}"
        if a.size and (not np.isfinite(a).all() or (a != np.round(a)).any() or a.min() < 0 or a.max() >= n):
            return field, f"{field} hold indices outside [0, {n}) or non-integers"
    g = msg["grasp_indices"]
    if not isinstance(g, dict) or any(not isinstance(g.get(s), int) or not -1 <= g[s] < max(n, 0)
                                      for s in ("left", "right") if s in g) or not {"left", "right"} <= set(g):
        return "grasp", f"grasp_indices {g!r} must map left and right to -1 or a keypoint index < {n}"
    return None


def run_announcement(*, session_id: str, run_id: str, run: dict[str, Any], stamp: float) -> dict[str, Any]:
    """The ``session/run`` message: which run the session records now (object, category, program, speed,
    run_index, n_keypoints, phase, track_id in ``run``); ``run_id`` "" between runs. ``stamp``: host time, s."""
    return {"schema": "trackdeform.Run/1", "session_id": session_id, "run_id": run_id, "stamp": stamp, **run}
