"""Bus encodings round-trip exactly and reject malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from tdcommon.wire import (
    KEYPOINTS_JSON_SCHEMA,
    check_keypoints,
    decode_frame,
    decode_json,
    encode_frame,
    encode_keypoints,
)
from tests.conftest import REPO, make_frame


def test_frame_round_trip() -> None:
    f = make_frame(7)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    msg = decode_frame(encode_frame(f, T, "cam0"))
    assert msg.camera_id == "cam0"
    np.testing.assert_array_equal(msg.frame.color, f.color)
    np.testing.assert_array_equal(msg.frame.depth, f.depth)
    np.testing.assert_allclose(msg.T_world_cam, T)
    assert msg.frame.frame_number == 7 and msg.frame.intrinsics == f.intrinsics


def test_malformed_frames_are_rejected() -> None:
    data = encode_frame(make_frame(1), np.eye(4), "cam0")
    with pytest.raises(ValueError, match="not a frame message"):
        decode_frame(b"BAD!" + data[4:])
    with pytest.raises(ValueError, match="size does not match"):
        decode_frame(data[:-10])


def test_keypoints_json() -> None:
    kp = np.arange(12, dtype=float).reshape(4, 3) / 10
    msg = decode_json(encode_keypoints(
        frame_number=3, stamp=0.1, keypoints=kp, edges=np.array([[0, 1], [1, 2], [2, 3]]),
        grasp_indices={"left": 0, "right": 3}, object_name="rope", category="dlo", status="tracking",
        abs_mm=1.5, cd_mm=2.0, session_id="s1", run_id="r1",
    ))
    assert msg["schema"] == "trackdeform.Keypoints/2" and msg["session_id"] == "s1" and msg["run_id"] == "r1"
    np.testing.assert_allclose(msg["keypoints"], kp)
    assert msg["grasp_indices"] == {"left": 0, "right": 3} and msg["edges"][2] == [2, 3]


def _good(n: int = 4) -> dict:
    return decode_json(encode_keypoints(
        frame_number=3, stamp=0.1, keypoints=np.zeros((n, 3)), edges=np.array([[i, i + 1] for i in range(n - 1)]),
        grasp_indices={"left": 0, "right": n - 1}, object_name="rope", category="dlo", status="tracking",
        abs_mm=1.5, cd_mm=None, anchors=np.array([0, n - 1]), session_id="s", run_id="r",
        extra={"processing_ms": 12.5, "note": "", "run_index": 0},
    ))


def test_shipped_schema_is_the_python_definition() -> None:
    import json

    shipped = json.loads((REPO / "schemas" / "keypoints.schema.json").read_text())
    assert shipped == json.loads(json.dumps(KEYPOINTS_JSON_SCHEMA)), "regenerate: trackdeform schema --out ..."


@pytest.mark.parametrize("mutate, kind", [
    (lambda m: m.update(keypoints=[[0.0, 0.0]] * 4), "keypoints"),
    (lambda m: m.update(keypoints=[[0.0, float("nan"), 0.0]] * 4), "not_finite"),
    (lambda m: m.update(edges=[[0, 4]]), "edges"),
    (lambda m: m.update(edges=[[0, 1.5]]), "edges"),
    (lambda m: m.update(anchors=[7]), "anchors"),
    (lambda m: m.update(grasp_indices={"left": 9, "right": 0}), "grasp"),
    (lambda m: m.update(frame_number=-1), "frame_number"),
    (lambda m: m.update(frame_number="3"), "frame_number"),
    (lambda m: m.pop("run_id"), "missing"),
    (lambda m: m.update(session_id=""), "ids"),
    (lambda m: m.update(schema="trackdeform.Keypoints/1"), "schema"),
    (lambda m: m.update(status="great"), "status"),
])
def test_malformed_keypoints_are_named(mutate, kind) -> None:
    import jsonschema

    msg = _good()
    assert check_keypoints(msg) is None
    jsonschema.validate(msg, KEYPOINTS_JSON_SCHEMA)  # the worker's message is what the schema says
    mutate(msg)
    problem = check_keypoints(msg)
    assert problem is not None and problem[0] == kind, problem


def test_lost_frame_is_valid() -> None:
    msg = _good()
    msg.update(keypoints=[], edges=[], anchors=[], grasp_indices={"left": -1, "right": -1}, status="lost")
    assert check_keypoints(msg) is None
