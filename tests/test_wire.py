"""Bus encodings round-trip exactly and reject malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from tdcommon.wire import decode_frame, decode_json, encode_frame, encode_keypoints
from tests.conftest import make_frame


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
        abs_mm=1.5, cd_mm=2.0,
    ))
    assert msg["schema"] == "trackdeform.Keypoints/1"
    np.testing.assert_allclose(msg["keypoints"], kp)
    assert msg["grasp_indices"] == {"left": 0, "right": 3} and msg["edges"][2] == [2, 3]
