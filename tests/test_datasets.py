"""Offline dataset I/O: episode MCAP files, the paper's folder layout, the reference keypoint export."""

from __future__ import annotations

import importlib
import itertools
import json
import logging
import os
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchestrator.config import ColorOutputConfig
from orchestrator.recorder import EpisodeWriter
from orchestrator.recovery import recover_active
from tdcommon.transforms import invert_transform, matrix_to_pose7, pose7_to_matrix
from tdcommon.types import GroundTruth, RGBDFrame
from tdrecord import (
    DatasetError,
    FrameSource,
    nearest_index,
    paper,
    read_calibration,
    read_episodes,
    read_paper_layout,
    read_reference_npz,
    read_sequence,
    verify_sequence_files,
    write_paper_layout,
    write_reference_npz,
)
from tdrecord.sequence import iter_depth, read_ahead
from tests.conftest import make_frame

RAW_COLOR = ColorOutputConfig(codec="raw")

W, H = 64, 48


def _pose(xyz: tuple[float, float, float], rpy: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = xyz
    return T


T_CAM = _pose((0.1, -0.6, 0.8), (-2.0, 0.1, 0.3))
BASES = {"left": _pose((0.0, 0.35, 0.0), (0.0, 0.0, -0.2)), "right": _pose((0.0, -0.35, 0.0), (0.0, 0.0, 0.3))}


def _state(t: float) -> dict:
    """An arms/state message whose joints and TCP input encode its stamp."""
    u = np.concatenate([[t, 0.1, 0.2], [0.0, 0.0, t], [t, -0.1, 0.2], [0.0, t, 0.0]])
    return {
        "stamp": t,
        "left": {"stamp": t, "q": [t] * 7, "dq": [0.0] * 7, "gripper_width": 0.04, "grasped": t > 0.05},
        "right": {"stamp": t, "q": [-t] * 7, "dq": [0.0] * 7, "gripper_width": 0.08, "grasped": False},
        "u": u.tolist(),
    }


def _gt(n: int) -> GroundTruth:
    kp = np.array([[0.0, 0.0, n * 0.01], [0.1, 0.0, 0.0]])
    return GroundTruth(kp, np.array([[0, 1]]), kp, 0.008, np.array([0, 1]), "dlo")


def _frame(n: int, gt: bool = False) -> RGBDFrame:
    f = make_frame(n, W, H)
    if gt:
        from dataclasses import replace

        f = replace(f, ground_truth=_gt(n))
    return f


def _metadata() -> dict:
    K = make_frame(0, W, H).intrinsics.K
    return {"object": "rope", "calibration": {
        "width": W, "height": H, "K": K.tolist(), "T_world_cam": T_CAM.tolist(),
        "T_world_base": {k: v.tolist() for k, v in BASES.items()}, "depth_scale": 0.001}}


def _episode(path: Path, frames: range, states: bool = True, gt: bool = False, close: bool = True) -> EpisodeWriter:
    """Frames ``frames`` at 30 Hz with arm states every 7 ms in between."""
    w = EpisodeWriter(path, "cam0", color=RAW_COLOR)  # random colour: exact
    for n in frames:
        if states:
            for t in np.arange(n / 30 - 1 / 30, n / 30, 0.007):
                if t >= 0:
                    w.write_arm_state(_state(float(t)))
        w.write_frame(_frame(n, gt), T_CAM)
    if close:
        w.close(_metadata())
    return w


# ------------------------------------------------------------------------------------------ helpers
def test_nearest_index_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    src = rng.uniform(0, 10, 200)
    q = np.concatenate([rng.uniform(-1, 11, 500), src[:5]])
    expect = np.abs(q[:, None] - src[None, :]).argmin(axis=1)
    np.testing.assert_array_equal(np.abs(src[nearest_index(src, q)] - q), np.abs(src[expect] - q))
    assert (nearest_index(np.array([3.0]), np.array([0.0, 9.0])) == 0).all()


def test_pose7_round_trip_scalar_first() -> None:
    T = np.stack([_pose((1, 2, 3), (0.1, 0.2, 0.3)), _pose((0, 0, 0), (3.0, -0.5, 1.0))])
    p = matrix_to_pose7(T)
    assert p.shape == (2, 7) and (p[:, 3] >= 0).all()
    np.testing.assert_allclose(pose7_to_matrix(p), T, atol=1e-12)
    np.testing.assert_allclose(pose7_to_matrix(np.array([0, 0, 0, 0.0, 0, 0, 1.0]))[:3, :3], np.diag([-1, -1, 1]))
    np.testing.assert_allclose(invert_transform(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


# ------------------------------------------------------------------------------------------ episodes
def test_episode_round_trip_and_joint_alignment(tmp_path: Path) -> None:
    p = _episode(tmp_path / "episode_000000.mcap", range(6)).path
    seq = read_episodes(p)
    assert len(seq) == 6 and isinstance(seq.frames, FrameSource)
    frames = list(seq.frames)
    for n, f in enumerate(frames):
        ref = make_frame(n, W, H)
        np.testing.assert_array_equal(f.color, ref.color)
        np.testing.assert_array_equal(f.depth, ref.depth)
        assert f.frame_number == n and f.depth_scale == 0.001
        assert f.device_stamp == pytest.approx(ref.device_stamp) and f.host_stamp == pytest.approx(ref.host_stamp)
        assert f.intrinsics == ref.intrinsics and f.color.flags.writeable
    np.testing.assert_allclose(seq.K, make_frame(0, W, H).intrinsics.K)
    np.testing.assert_allclose(seq.T_world_cam, T_CAM)
    np.testing.assert_allclose(seq.T_world_base["right"], BASES["right"])
    assert seq.intrinsics == make_frame(0, W, H).intrinsics
    np.testing.assert_array_equal(seq.frame_numbers, np.arange(6))
    # nearest state to each frame's host stamp (n/30 + 0.01), by brute force
    src = np.array([t for n in range(6) for t in np.arange(n / 30 - 1 / 30, n / 30, 0.007) if t >= 0])
    nearest = src[np.abs(seq.stamps[:, None] - src[None, :]).argmin(axis=1)]
    np.testing.assert_allclose(seq.q_left, np.repeat(nearest[:, None], 7, axis=1))
    np.testing.assert_allclose(seq.q_right, -np.repeat(nearest[:, None], 7, axis=1))
    np.testing.assert_array_equal(seq.grasped_left, nearest > 0.05)
    assert seq.tcp_left.shape == (6, 4, 4)
    np.testing.assert_allclose(seq.tcp_left[:, 0, 3], nearest)
    np.testing.assert_allclose(seq.tcp_right[:, :3, :3], Rotation.from_rotvec(
        np.stack([np.zeros(6), nearest, np.zeros(6)], axis=1)).as_matrix(), atol=1e-12)
    assert seq.metadata["object"] == "rope" and seq.metadata["files"] == [str(p)]
    assert seq.metadata["max_state_offset_s"] == pytest.approx(np.abs(nearest - seq.stamps).max())
    assert seq.ground_truth is None


def test_folder_of_episodes_lazy_and_skips_unfinished(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    _episode(tmp_path / "episode_000001.mcap", range(4, 7), gt=True)
    _episode(tmp_path / "episode_000000.mcap", range(0, 4), gt=True)
    _episode(tmp_path / "episode_000002.mcap", range(7, 9), close=False).abort()
    with caplog.at_level(logging.WARNING):
        seq = read_sequence(tmp_path)
    assert "trackdeform recover" in caplog.text and "episode_000002.mcap.active" in caplog.text
    assert [Path(f).name for f in seq.metadata["files"]] == ["episode_000000.mcap", "episode_000001.mcap"]
    assert seq.metadata["frames_per_file"] == [4, 3] and len(seq.metadata["skipped_unfinished"]) == 1
    assert [f.frame_number for f in seq.frames] == list(range(7))
    tail = list(seq.frames.iter_from(3))
    assert [f.frame_number for f in tail] == [3, 4, 5, 6]
    np.testing.assert_array_equal(tail[2].color, make_frame(5, W, H).color)
    assert seq.q_left.shape == (7, 7) and len(seq.ground_truth) == 7
    np.testing.assert_allclose(seq.ground_truth[5].keypoints, _gt(5).keypoints)
    assert tail[2].ground_truth is not None and tail[2].ground_truth.category == "dlo"


def test_unfinished_file_names_recover(tmp_path: Path) -> None:
    w = EpisodeWriter(tmp_path / "episode_000000.mcap", "cam0")
    for n in range(6):  # 1.5 MB frames: the 4 MB chunks reach the disk before the "crash"
        w.write_frame(make_frame(n, 640, 480), T_CAM)
    w.abort()
    with pytest.raises(DatasetError, match=r"episode_000000\.mcap\.active.*trackdeform recover"):
        read_sequence(w.active_path)
    with pytest.raises(DatasetError, match="no episode .mcap files.*trackdeform recover"):
        read_episodes(tmp_path)
    # after recovery: no metadata record, calibration from the calibration channel and /tf
    assert recover_active(tmp_path)[0][1].startswith("recovered")
    seq = read_episodes(tmp_path / "episode_000000.mcap")
    assert 1 <= len(seq) <= 6 and seq.T_world_base is None and (seq.width, seq.height) == (640, 480)
    np.testing.assert_array_equal(seq.frame_numbers, np.arange(len(seq)))
    np.testing.assert_allclose(seq.T_world_cam, T_CAM, atol=1e-9)
    np.testing.assert_allclose(seq.K, make_frame(0, 640, 480).intrinsics.K)
    np.testing.assert_array_equal(next(iter(seq.frames)).depth, make_frame(0, 640, 480).depth)


def test_missing_channel_and_missing_file_are_named(tmp_path: Path) -> None:
    from mcap.writer import Writer

    p = tmp_path / "bad.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        w.register_channel("/cam/cam0/color", "json", sid)
        w.finish()
    with pytest.raises(DatasetError, match=r"bad\.mcap: no '/cam/cam0/depth' channel"):
        read_episodes(p)
    with pytest.raises(FileNotFoundError, match="nope.mcap"):
        read_sequence(tmp_path / "nope.mcap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="neither episode .mcap files nor a rgbd.npz"):
        read_sequence(tmp_path / "empty")


def test_episode_without_states(tmp_path: Path) -> None:
    seq = read_episodes(_episode(tmp_path / "e.mcap", range(2), states=False).path)
    assert seq.q_left is None and seq.tcp_right is None and len(list(seq.frames)) == 2


# ------------------------------------------------------------------------------------------ paper layout
def _paper(tmp_path: Path, T: int = 5, compress: bool = False) -> tuple[Path, list[RGBDFrame], dict]:
    frames = [make_frame(n, W, H) for n in range(T)]
    t = np.linspace(0, 1, T)
    tcp_l = np.stack([_pose((0.4 + 0.1 * s, 0.2, 0.3), (np.pi, 0.0, s)) for s in t])
    tcp_r = np.stack([_pose((0.4, -0.2 - 0.1 * s, 0.3), (np.pi, s, 0.0)) for s in t])
    q = np.arange(T * 7, dtype=float).reshape(T, 7) / 100
    kw = dict(T_world_cam=T_CAM, T_world_base=BASES, tcp_left=tcp_l, tcp_right=tcp_r, q_left=q, q_right=-q)
    write_paper_layout(tmp_path / "chunk", frames, compress=compress, **kw)
    return tmp_path / "chunk", frames, kw


@pytest.mark.parametrize("compress", [False, True])
def test_paper_layout_round_trip(tmp_path: Path, compress: bool) -> None:
    folder, frames, kw = _paper(tmp_path, compress=compress)
    with np.load(folder / "rgbd.npz") as z:  # stored as the paper's code expects: BGR, uint16 mm
        assert z["color"].shape == (5, H, W, 3) and z["depth"].dtype == np.uint16
        np.testing.assert_array_equal(z["color"][2], frames[2].color[..., ::-1])
    with np.load(folder / "left_arm_poses.npz") as z:
        assert sorted(z.files, key=lambda k: int(k[4:])) == [f"arr_{i}" for i in range(5)]
    seq = read_sequence(folder)
    got = list(seq.frames)
    assert len(seq) == 5 and [f.frame_number for f in got] == list(range(5))
    for f, ref in zip(got, frames, strict=True):
        np.testing.assert_array_equal(f.color, ref.color)  # BGR -> RGB on reading
        np.testing.assert_array_equal(f.depth, ref.depth)
        assert f.intrinsics == ref.intrinsics and f.device_stamp == pytest.approx(ref.frame_number / 30)
    # the world is the left base: every pose is the original one seen from the left base
    inv_l = invert_transform(BASES["left"])
    np.testing.assert_allclose(seq.T_world_cam, inv_l @ T_CAM, atol=1e-9)
    np.testing.assert_allclose(seq.T_world_base["left"], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(seq.T_world_base["right"], inv_l @ BASES["right"], atol=1e-9)
    np.testing.assert_allclose(seq.tcp_left, inv_l @ kw["tcp_left"], atol=1e-9)
    np.testing.assert_allclose(seq.tcp_right, inv_l @ kw["tcp_right"], atol=1e-9)
    np.testing.assert_allclose(seq.q_right, -kw["q_left"])
    assert list(seq.frames.iter_from(4))[0].frame_number == 4


@pytest.mark.parametrize("compress", [False, True])
def test_paper_layout_depth_only_stream_matches_frames(tmp_path: Path, compress: bool) -> None:
    folder, frames, _ = _paper(tmp_path, compress=compress)
    seq = read_sequence(folder)
    got = list(seq.frames.iter_depth())  # depth and colour arrays, decoded by a reader thread
    assert [d.frame_number for d in got] == list(range(5))
    for d, ref in zip(got, frames, strict=True):
        assert d.depth.dtype == np.uint16 and d.depth_scale == ref.depth_scale
        np.testing.assert_array_equal(d.depth_m(), ref.depth_m())
        assert d.color is not None
        np.testing.assert_array_equal(d.color, ref.color)  # RGB, as the whole frames
    assert [d.frame_number for d in seq.frames.iter_depth(3)] == [3, 4]
    depth_only = list(iter_depth(seq.frames, colour=False))  # a cloth's tracking: the colour is not decoded
    assert [d.color for d in depth_only] == [None] * 5
    for d, ref in zip(depth_only, frames, strict=True):
        np.testing.assert_array_equal(d.depth_m(), ref.depth_m())
    assert [d.frame_number for d in iter_depth(frames)] == list(range(5))  # a list: the frames themselves


def test_paper_layout_depth_stream_checks_its_crc(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(paper._Member, "_BLOCK", 1 << 12)  # blocks smaller than this test's small array
    folder, frames, _ = _paper(tmp_path)  # stored: a flipped byte decodes, only the CRC notices
    rgbd = folder / "rgbd.npz"
    data = bytearray(rgbd.read_bytes())
    at = bytes(data).index(frames[2].depth.astype("<u2").tobytes())
    data[at + 7] ^= 0xFF
    rgbd.write_bytes(bytes(data))
    seq = read_sequence(folder)
    stream = seq.frames.iter_depth()
    assert [d.frame_number for d in itertools.islice(stream, 4)] == [0, 1, 2, 3]  # frames come as they decode
    with pytest.raises(DatasetError, match=r"rgbd\.npz: corrupt \.npz: member 'depth\.npy'.*CRC"):
        next(stream)  # ... and the end of the member checks them
    verify_sequence_files(folder, except_streamed=True)  # what the stream checks is left to it
    with pytest.raises(DatasetError, match="'depth.npy' fails its CRC check"):
        verify_sequence_files(folder)


def test_read_ahead_forwards_errors_and_stops_its_reader() -> None:
    made: list[int] = []

    def items() -> Iterator[int]:
        for i in range(1000):
            made.append(i)
            if i == 3 and fail:
                raise ValueError("bad row 3")
            yield i

    before = threading.active_count()
    fail = True
    stream = read_ahead(items, depth=2)
    assert [next(stream) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(ValueError, match="bad row 3"):
        next(stream)
    fail = False
    made.clear()
    stream = read_ahead(items, depth=2)
    assert next(stream) == 0
    stream.close()  # the reader stops: at most depth + 2 items were made
    n = len(made)
    assert n <= 4 and threading.active_count() == before
    assert [t.name for t in threading.enumerate()].count("read-ahead") == 0


def test_paper_layout_convention_matches_published_code(tmp_path: Path) -> None:
    """(T_left_base2cam @ T_base_tcp)[:3, 3] is the TCP in the camera: equal to inv(T_world_cam) @ tcp."""
    folder, _, _ = _paper(tmp_path)
    with np.load(folder / "calibration/transform_ee_cam_world.npz") as z:
        T_l2c, T_r2c = z["T_left_base2cam"], z["T_right_base2cam"]
    with np.load(folder / "right_arm_poses.npz") as z:
        right3 = pose7_to_matrix(z["arr_3"])
    seq = read_paper_layout(folder)
    cam_from_world = invert_transform(seq.T_world_cam)
    np.testing.assert_allclose((cam_from_world @ seq.tcp_right[3])[:3, 3], (T_r2c @ right3)[:3, 3], atol=1e-9)
    np.testing.assert_allclose(seq.T_world_cam, invert_transform(T_l2c), atol=1e-12)
    cam_world = read_paper_layout(folder, world="camera")
    np.testing.assert_allclose(cam_world.tcp_right[3], T_r2c @ right3, atol=1e-9)
    np.testing.assert_allclose(read_calibration(folder).T_world_cam, seq.T_world_cam)


def test_paper_layout_errors_name_file_and_key(tmp_path: Path) -> None:
    folder, _, _ = _paper(tmp_path)
    # pose counts differ: strict names the file; align="end" keeps the last common frames
    with np.load(folder / "left_arm_poses.npz") as z:
        poses = [z[f"arr_{i}"] for i in range(5)]
    np.savez(folder / "left_arm_poses.npz", *poses[1:])
    with pytest.raises(DatasetError, match=r"left_arm_poses\.npz: 4 rows but rgbd\.npz has 5 frames"):
        read_paper_layout(folder)
    seq = read_paper_layout(folder, align="end", world="camera")
    assert len(seq) == 4 and seq.q_left.shape == (4, 7)
    first = next(iter(seq.frames))
    np.testing.assert_array_equal(first.color, make_frame(1, W, H).color)
    # a gap in arr_i
    np.savez(folder / "left_arm_poses.npz", **{f"arr_{i}": p for i, p in enumerate(poses) if i != 2})
    with pytest.raises(DatasetError, match=r"left_arm_poses\.npz: expected arrays arr_0 \.\.\. arr_3; missing arr_2"):
        read_paper_layout(folder)
    np.savez(folder / "left_arm_poses.npz", *[p[:6] for p in poses])
    with pytest.raises(DatasetError, match=r"arr_0 has shape \(6,\), expected \(7,\)"):
        read_paper_layout(folder)
    np.savez(folder / "left_arm_poses.npz", *poses)
    # calibration key missing, then not rigid
    cal = folder / "calibration/transform_ee_cam_world.npz"
    with np.load(cal) as z:
        c = dict(z)
    np.savez(cal, K=c["K"], T_left_base2cam=c["T_left_base2cam"])
    with pytest.raises(DatasetError, match=r"transform_ee_cam_world\.npz: no array 'T_right_base2cam'"):
        read_paper_layout(folder)
    np.savez(cal, K=c["K"], T_left_base2cam=c["T_left_base2cam"] * 2, T_right_base2cam=c["T_right_base2cam"])
    with pytest.raises(DatasetError, match="T_left_base2cam: not a rigid transform"):
        read_paper_layout(folder)
    np.savez(cal, K=c["K"][:2], T_left_base2cam=c["T_left_base2cam"], T_right_base2cam=c["T_right_base2cam"])
    with pytest.raises(DatasetError, match=r"'K' has shape \(2, 3\), expected \(3, 3\)"):
        read_paper_layout(folder)
    # rgbd.npz without depth, then missing altogether
    np.savez(folder / "rgbd.npz", color=np.zeros((5, H, W, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"rgbd\.npz: no array 'depth'"):
        read_sequence(folder / "rgbd.npz")
    (folder / "rgbd.npz").unlink()
    (folder / "left_arm_poses.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"chunk/rgbd\.npz: missing"):
        read_paper_layout(folder)


def test_paper_layout_missing_pose_file(tmp_path: Path) -> None:
    folder, _, _ = _paper(tmp_path, T=2)
    (folder / "right_arm_poses.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"right_arm_poses\.npz: missing"):
        read_paper_layout(folder)


def test_episode_to_paper_layout_export(tmp_path: Path) -> None:
    seq = read_episodes(_episode(tmp_path / "e.mcap", range(3)).path)
    write_paper_layout(tmp_path / "out", seq.frames, T_world_cam=seq.T_world_cam, T_world_base=seq.T_world_base,
                       tcp_left=seq.tcp_left, tcp_right=seq.tcp_right, q_left=seq.q_left, q_right=seq.q_right)
    back = read_paper_layout(tmp_path / "out")
    inv_l = invert_transform(BASES["left"])
    np.testing.assert_allclose(back.tcp_left, inv_l @ seq.tcp_left, atol=1e-9)
    np.testing.assert_array_equal(next(iter(back.frames)).color, make_frame(0, W, H).color)


# ------------------------------------------------------------------------------------------ reference export
def test_reference_npz_round_trip_in_mm(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    X = rng.normal(size=(4, 6, 3)) * 0.2
    X[1, 2] = np.nan
    edges = np.array([[i, i + 1] for i in range(5)])
    rest = np.full(5, 0.025)
    out = write_reference_npz(tmp_path, X, edges, rest)
    assert out == tmp_path / "3d_keypoints.npz"
    with np.load(out) as z:
        np.testing.assert_allclose(z["full"], X * 1000.0)
        np.testing.assert_allclose(z["reference_lengths"], 25.0)
        assert z["edge_connection"].dtype.kind == "i" and z["edge_connection"].shape == (5, 2)
    ref = read_reference_npz(out)
    np.testing.assert_allclose(ref.keypoints, X, equal_nan=True)
    np.testing.assert_array_equal(ref.edges, edges)
    np.testing.assert_allclose(ref.rest_lengths, rest)
    assert write_reference_npz(tmp_path / "named", X, edges, rest).name == "named"  # no .npz appended
    with pytest.raises(ValueError, match="5 edges but 4 rest lengths"):
        write_reference_npz(tmp_path / "x.npz", X, edges, rest[:4])
    np.savez(tmp_path / "bad.npz", full=X, edge_connection=edges)
    with pytest.raises(DatasetError, match=r"bad\.npz: no array 'reference_lengths'"):
        read_reference_npz(tmp_path / "bad.npz")


def test_episode_metadata_is_json(tmp_path: Path) -> None:
    """The Sequence metadata stays JSON-serialisable (for summaries and exports)."""
    seq = read_episodes(_episode(tmp_path / "e.mcap", range(2)).path)
    json.dumps(seq.metadata)


def test_read_ahead_on_one_core_makes_items_inline(monkeypatch: pytest.MonkeyPatch) -> None:
    import tdrecord.sequence as seqmod

    monkeypatch.setattr(seqmod, "usable_cores", lambda: 1)
    names: list[str] = []

    def items() -> Iterator[int]:
        for i in range(3):
            names.append(threading.current_thread().name)
            yield i

    assert list(read_ahead(items)) == [0, 1, 2] and set(names) == {threading.current_thread().name}


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="per-thread nice values are a Linux feature")
def test_background_threads_lower_only_their_own_priority() -> None:
    from tdrecord.sequence import lower_thread_priority

    def nice() -> int:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    main_before, seen = nice(), []

    def job() -> None:
        before = nice()
        lower_thread_priority(3)
        seen.append(nice() - before)

    t = threading.Thread(target=job)
    t.start()
    t.join()
    assert seen in ([3], [19 - main_before]) and nice() == main_before


@pytest.mark.parametrize("inflater", ["isal", "zlib_ng", "zlib"])
@pytest.mark.parametrize("compressed", [True, False])
def test_npz_member_stream_gives_zipfiles_bytes_and_checks_the_crc(
    tmp_path: Path, compressed: bool, inflater: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = {"isal": "isal.isal_zlib", "zlib_ng": "zlib_ng.zlib_ng", "zlib": "zlib"}[inflater]
    monkeypatch.setattr(paper, "INFLATE", importlib.import_module(module))  # the fallbacks read the same
    monkeypatch.setattr(paper._Member, "_BLOCK", 1 << 10)  # many blocks, rows across their borders
    rng = np.random.default_rng(0)
    arrays = {"depth": rng.integers(0, 900, (7, 33, 41)).astype(np.uint16), "color": rng.random((3, 5, 6)),
              "flat": np.zeros((40, 100), np.uint16)}  # one compressed block inflates to many
    path = tmp_path / "a.npz"
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    with zipfile.ZipFile(path) as zf:
        for name in zf.namelist():
            with zf.open(name) as ref, paper._open_member(zf, path, name) as ours:
                assert ours.read(100) + ours.read(5000) + ours.read() == ref.read()
            with paper._open_member(zf, path, name) as ours:
                sizes = []
                while ours._more():
                    sizes.append(len(ours._chunk))
                assert max(sizes) <= paper._Member._BLOCK and sum(sizes) == zf.getinfo(name).file_size
            if compressed:  # a deflate stream that stops short of its end marker, the zip's sizes consistent
                info = zf.getinfo(name)
                info.compress_size //= 2
                with paper._open_member(zf, path, name) as ours, pytest.raises(EOFError, match="end-of-stream"):
                    ours.drain()
    paper.verify_npz(path)
    rows = list(paper._iter_npz_rows(path, "depth", start=2))
    assert np.array_equal(np.stack(rows), arrays["depth"][2:])
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("depth.npy")
    data[info.header_offset + 30 + len("depth.npy") + 200] ^= 0x55  # inside the depth member's data
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"a\.npz: corrupt \.npz: member 'depth\.npy'"):
        list(paper._iter_npz_rows(path, "depth"))
    with pytest.raises(DatasetError, match="'depth.npy' fails its CRC check"):
        paper.verify_npz(path)
    path.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(DatasetError):
        list(paper._iter_npz_rows(path, "depth"))
