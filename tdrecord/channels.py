"""JSON channels of episode files: their JSON Schemas (so Foxglove parses them) and the point layout.

Foxglove's JSON channel parser takes a schema of ``"type": "object"`` with ``properties``, each a plain
type; an array's items must be a scalar or an object (no nested arrays). So points are recorded as
objects ``{"x", "y", "z"}`` (m, world frame) and edges as ``{"i", "j"}`` (keypoint indices), which
Foxglove's plot and raw-message panels can also address (``/keypoints.keypoints[3].z``). Readers take
both these and the plain nested lists of the live (zenoh) messages: :func:`points_from_json`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tdcommon.wire import edges_from_json, edges_to_json, points_from_json, points_to_json

__all__ = ["SCHEMAS", "edges_from_json", "edges_to_json", "keypoints_record", "points_from_json", "points_to_json"]

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
POINT = {"type": "object", "description": "m, world frame", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
EDGE = {"type": "object", "description": "keypoint indices", "properties": {"i": _INT, "j": _INT}}


def _array(items: dict[str, Any], description: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {"type": "array", "items": items}
    if description:
        out["description"] = description
    return out


def _object(title: str, properties: dict[str, Any], required: list[str], description: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {"title": title, "type": "object", "properties": properties, "required": required}
    if description:
        out["description"] = description
    return out


_ARM = {
    "type": "object",
    "properties": {
        "stamp": {"type": "number", "description": "s, host clock"},
        "q": _array(_NUM, "joint positions, rad"),
        "dq": _array(_NUM, "joint velocities, rad/s"),
        "gripper_width": {"type": "number", "description": "finger opening, m"},
        "grasped": _BOOL,
    },
}

SCHEMAS: dict[str, dict[str, Any]] = {
    "trackdeform.FrameInfo": _object(
        "trackdeform.FrameInfo",
        {"frame_number": _INT, "device_stamp": {"type": "number", "description": "s, camera clock"},
         "host_stamp": {"type": "number", "description": "s, host clock"},
         "color_keyframe": {"type": "boolean", "description": "the colour image decodes without earlier ones"}},
        ["frame_number", "device_stamp", "host_stamp"],
    ),
    "trackdeform.ArmState": _object(
        "trackdeform.ArmState",
        {"stamp": {"type": "number", "description": "s, host clock"}, "left": _ARM, "right": _ARM,
         "u": _array(_NUM, "arm input: per arm TCP position (m) and rotation vector (rad), world, left then right")},
        ["stamp", "u"],
    ),
    "trackdeform.ArmStateAtFrame": _object(
        "trackdeform.ArmStateAtFrame",
        {"frame_number": _INT, "stamp": {"type": "number", "description": "s, the frame's capture time, host clock"},
         "left": _ARM, "right": _ARM,
         "u": _array(_NUM, "arm input from the interpolated joints, left then right"),
         "pairing_error_s": {"type": "number", "description": "distance to the nearest joint sample, s"},
         "device_minus_host_s": {"type": "number", "description": "estimated camera clock minus host clock, s"}},
        ["frame_number", "stamp"],
        "both arms' joints interpolated at the frame's capture time (camera-arm time sync)",
    ),
    "trackdeform.Keypoints": _object(
        "trackdeform.Keypoints",
        {"schema": _STR, "frame_number": _INT, "stamp": {"type": "number", "description": "s, the frame's stamp"},
         "keypoints": _array(POINT), "edges": _array(EDGE),
         "grasp_indices": {"type": "object", "description": "keypoint held by each gripper, -1 none",
                           "properties": {"left": _INT, "right": _INT}},
         "object": _STR, "category": {"type": "string", "description": "dlo, bdlo or cloth"},
         "status": {"type": "string", "description": "init, tracking or lost (live); final"},
         "tangled": {"type": "integer", "description": "final: tangled grid cells or keypoints where a chain turns "
                                                       "back on itself, 0 none"},
         "abs_mm": {"type": "number", "description": "mean keypoint-to-cloud distance, mm"},
         "cd_mm": {"type": "number", "description": "Chamfer distance, mm"},
         "anchors": _array(_INT, "keypoints anchored this frame"),
         "rest_lengths": _array(_NUM, "rest length of each edge, m")},
        ["frame_number", "keypoints", "edges"],
    ),
    "trackdeform.GroundTruth": _object(
        "trackdeform.GroundTruth",
        {"frame_number": _INT, "keypoints": _array(POINT), "edges": _array(EDGE), "anchors": _array(_INT),
         "radius": {"type": "number", "description": "m"}, "category": _STR,
         "centreline": _array(POINT, "subsampled centreline / mid-surface points, 0.1 mm")},
        ["frame_number", "keypoints", "edges"],
        "the simulator's true keypoints (mock mode)",
    ),
}


def keypoints_record(msg: dict[str, Any]) -> dict[str, Any]:
    """A live keypoint message as recorded: points and edges as objects, NaN as null, other fields as they are."""
    out = dict(msg)
    if "keypoints" in out:
        kp = np.asarray(out["keypoints"], dtype=np.float64).reshape(-1, 3)
        out["keypoints"] = [{k: (None if v != v else v) for k, v in p.items()} for p in points_to_json(kp)]
    if "edges" in out:
        out["edges"] = edges_to_json(out["edges"])
    return out
