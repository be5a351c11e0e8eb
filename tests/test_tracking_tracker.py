"""Algorithm 2 on a moving synthetic rope: accuracy, grasp indices, smoothing, loss of track."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tracking import synthetic as S
from tracking.init import Topology
from tracking.metrics import anchor_error_mm, edge_rmse_mm, surface_error_mm
from tracking.params import TrackingParams
from tracking.segmentation import background_from_depths, render_arm_mask, segment_against_background
from tracking.tracker import (
    Tracker,
    TrackStatus,
    assign_grasp_indices,
    final_keypoints,
    match_anchors,
    smooth_causal,
    smooth_symmetric,
    update_grasp_indices,
)

W, H = 640, 480
P = TrackingParams()


@pytest.fixture(scope="module")
def sequence():
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(0)
    bg = background_from_depths(np.stack([S.rope_scene(0, K, T, (H, W), rng, with_object=False).depth] * 2))
    frames = [S.rope_scene(0.15 * k, K, T, (H, W), rng) for k in range(16)]
    return K, T, bg, frames


def _segment(K, T, bg, f, prev):
    am = render_arm_mask(f.arm_vertices, f.arm_triangles, K, T, (H, W), P.arm_margin_px, f.depth, P.arm_margin_m)
    return segment_against_background(f.depth, bg, K, T, P, am, prev).points


def test_tracks_moving_rope(sequence):
    K, T, bg, frames = sequence
    tr = Tracker(P, K, T)
    errs, aerrs, raw = [], [], []
    for k, f in enumerate(frames):
        pts = _segment(K, T, bg, f, tr.keypoints)
        r = tr.initialise(pts)[1] if k == 0 else tr.step(pts)
        assert r.status == TrackStatus.OK
        assert r.edge_rmse_mm < 5.0 and r.chamfer_mm < 3.0
        errs.append(surface_error_mm(r.keypoints, f.centreline, f.radius, polyline=True))
        aerrs.append(anchor_error_mm(r.keypoints[tr.topology.anchor_idx], f.anchors))
        raw.append(r.keypoints)
        assert r.smoothed.shape == r.keypoints.shape
    assert max(errs) < 3.0  # mm, to the rope's skin
    assert max(aerrs) < 12.0  # mm, ends (on the skin tip vs the centreline end)
    # the keypoints really moved with the rope (not stuck at the start)
    assert np.linalg.norm(raw[-1] - raw[0], axis=1).max() > 0.05


def test_loss_of_track_is_reported(sequence):
    K, T, bg, frames = sequence
    tr = Tracker(P, K, T)
    tr.initialise(_segment(K, T, bg, frames[0], None))
    statuses = [tr.step(np.zeros((0, 3))).status for _ in range(P.lost_after_frames)]
    assert statuses[:-1] == [TrackStatus.DEGRADED] * (P.lost_after_frames - 1)
    assert statuses[-1] == TrackStatus.LOST and not tr.initialised
    assert tr.step(_segment(K, T, bg, frames[1], None)).status == TrackStatus.UNINITIALISED
    # a cloud that is not the object (a far-away blob) is bad too
    tr.initialise(_segment(K, T, bg, frames[0], None))
    blob = np.random.default_rng(0).normal([0.0, 0.0, 0.5], 0.01, (500, 3))
    assert tr.step(blob).status == TrackStatus.DEGRADED


def test_grasped_keypoint_follows_the_gripper(sequence):
    K, T, bg, frames = sequence
    tr = Tracker(P, K, T)
    f0 = frames[0]
    tcp = f0.centreline[[0]] + [0.0, 0.0, 0.005]
    _, r = tr.initialise(_segment(K, T, bg, f0, None), tcp=tcp)
    assert r.grasp_idx[0] in (0, P.n_keypoints_1d - 1)
    f1 = frames[1]
    tcp1 = f1.centreline[[0]] + [0.0, 0.0, 0.005]
    r = tr.step(_segment(K, T, bg, f1, tr.keypoints), tcp=tcp1, gripper_closed=np.array([True]))
    assert np.allclose(r.keypoints[r.grasp_idx[0]], tcp1[0])
    r = tr.step(_segment(K, T, bg, f1, tr.keypoints), tcp=tcp1, gripper_closed=np.array([False]))
    assert r.grasp_idx[0] == -1


def test_grasp_index_functions():
    X = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])
    assert assign_grasp_indices(X, np.array([[0.19, 0, 0], [1.0, 0, 0]]), 0.05).tolist() == [2, -1]
    g = update_grasp_indices(np.array([2, -1]), X, np.array([[0.5, 0, 0], [0.11, 0, 0]]), np.array([True, True]), 0.05)
    assert g.tolist() == [2, 1]  # held stays held; newly closed grasps the nearest
    g = update_grasp_indices(g, X, np.zeros((2, 3)), np.array([False, True]), 0.05)
    assert g.tolist() == [-1, 1]


def test_anchor_matching_gates_and_kinds():
    prev = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    kinds = np.array([0, 1])
    det = np.array([[1.01, 0, 0], [0.02, 0, 0], [5.0, 0, 0]])
    assert match_anchors(prev, kinds, det, np.array([1, 0, 0]), 0.05, True).tolist() == [1, 0]
    assert match_anchors(prev, kinds, det, np.array([0, 1, 0]), 0.05, True).tolist() == [-1, -1]
    far = np.array([[0.1, 0, 0]])
    assert match_anchors(prev[:1], kinds[:1], far, np.array([0]), 0.05, True).tolist() == [-1]
    assert match_anchors(prev[:1], kinds[:1], far, np.array([0]), 0.05, True, regate_m=0.15).tolist() == [0]
    # an anchor re-detected and kept last frame is not recaptured by a detection 10 cm off (a spur, the end of a
    # part seen short); one that was not is
    no, yes = np.array([False]), np.array([True])
    assert match_anchors(prev[:1], kinds[:1], far, np.array([0]), 0.05, True, 0.15, no).tolist() == [-1]
    assert match_anchors(prev[:1], kinds[:1], far, np.array([0]), 0.05, True, 0.15, yes).tolist() == [0]


def test_smoothing():
    traj = np.arange(6, dtype=float)[:, None, None] * np.ones((6, 2, 3))
    assert np.allclose(smooth_causal(traj, 3)[:, 0, 0], [0, 0.5, 1, 2, 3, 4])
    # a steady motion is kept exactly, the clip's ends included (a window cut on one side would lag there)
    assert np.allclose(smooth_symmetric(traj, 3), traj) and np.allclose(smooth_symmetric(traj, 5), traj)
    assert np.allclose(smooth_symmetric(traj, 1), traj)
    bump = np.zeros((6, 1, 1))
    bump[2] = 6.0
    assert np.allclose(smooth_symmetric(bump, 5)[:, 0, 0], [0, 2, 1.2, 1.2, 0, 0])  # windows 1, 3, 5, 5, 3, 1
    # with a gate, a steady motion of any speed is still kept exactly; a jump is not averaged across
    fast = 10.0 * traj
    assert np.allclose(smooth_symmetric(fast, 5, gate_m=0.1), fast)
    jump = np.zeros((8, 2, 3))
    jump[4:, 0] = 1.0  # keypoint 0 jumps between frames 3 and 4; keypoint 1 stays
    out = smooth_symmetric(jump, 5, gate_m=0.25)
    np.testing.assert_allclose(out[:, 0, 0], [0, 0, 0, 0, 1, 1, 1, 1])  # ungated: 0.2, 0.4, 0.6, 0.8 at 2-5
    np.testing.assert_allclose(out[:, 1], 0.0)
    np.testing.assert_allclose(smooth_symmetric(jump, 5)[2:6, 0, 0], [0.2, 0.4, 0.6, 0.8])
    # a clip's final keypoints: frames never tracked stay NaN; the gate is params.smooth_gate median rest lengths
    raw = np.concatenate([np.full((1, 2, 3), np.nan), jump])
    def pair(rest: float) -> Topology:
        return Topology("1d", np.array([[0, 1]]), np.array([rest]), np.array([0, 1]), np.zeros(2, np.int64),
                        [np.arange(2)])

    final = final_keypoints(raw, pair(0.1), replace(P, symmetric_window=5, smooth_gate=2.0))
    assert np.isnan(final[0]).all()
    np.testing.assert_allclose(final[1:, 0, 0], [0, 0, 0, 0, 1, 1, 1, 1])  # the jump: 10 rest lengths
    final = final_keypoints(raw, pair(1.0), replace(P, symmetric_window=5, smooth_gate=2.0))
    np.testing.assert_allclose(final[3:7, 0, 0], [0.2, 0.4, 0.6, 0.8])  # one rest length: a motion


def test_final_keypoints_keep_a_grids_raw_frame_where_the_average_would_break_its_edges():
    from tracking.tracker import final_keypoints

    # a 2x2 grid of 1 m edges folds its far row over the near one between frames 3 and 4 (a re-lifted grid)
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    up = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 1]], np.float64)
    raw = np.stack([flat] * 4 + [up] * 4)
    edges = np.array([[0, 1], [2, 3], [0, 2], [1, 3]])
    grid = Topology("2d", edges, np.ones(4), np.arange(4), np.zeros(4, np.int64), [np.arange(2), np.arange(2, 4)],
                    grid_shape=(2, 2))
    blended = final_keypoints(raw, grid, replace(P, symmetric_window=5, smooth_gate=2.0, smooth_edge_slack_mm=1e9))
    assert not np.allclose(blended[2:6], raw[2:6])  # the average of flat and folded: edges 0.7 m long
    np.testing.assert_allclose(final_keypoints(raw, grid, replace(P, symmetric_window=5, smooth_gate=2.0)), raw)
    moving = raw[:1] + np.linspace(0.0, 0.07, 8)[:, None, None] * np.array([1.0, 0.0, 0.0])  # a steady motion
    moving[3] += [0.0, 0.0, 0.01]  # with 1 cm of noise in one frame, which the average takes out
    out = final_keypoints(moving, grid, replace(P, symmetric_window=5, smooth_gate=2.0))
    assert abs(out[3, 0, 2]) < 0.005


def test_respace_chains_spaces_keypoints_along_their_curve_as_their_rest_lengths():
    from tracking.tangle import respace_chains

    def chain(rest: np.ndarray) -> Topology:
        n = len(rest) + 1
        E = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
        return Topology("1d", E, rest, np.array([0, n - 1]), np.zeros(2, np.int64), [np.arange(n)])

    # a straight chain 0-1-2-3-4 with rest lengths 1, 1, 2, 2 (m), its keypoints bunched towards one end
    rest = np.array([1.0, 1.0, 2.0, 2.0])
    x = np.array([0.0, 0.5, 1.0, 1.5, 6.0])
    X = np.zeros((2, 5, 3))
    X[:, :, 0] = x
    X[1, :, 1] = 1.0  # a second frame, moved sideways: each frame is spaced on its own
    out = out_all = respace_chains(X, chain(rest), cap_m=10.0)
    np.testing.assert_allclose(out[:, :, 0], [[0, 1, 2, 4, 6]] * 2)  # arcs in proportion 1 : 1 : 2 : 2
    np.testing.assert_allclose(out[:, :, 1:], X[:, :, 1:])
    # each keypoint moves at most cap_m towards its place; the chain's ends (a tip, a junction) never move
    capped = respace_chains(X, chain(rest), cap_m=1.0)
    np.testing.assert_allclose(capped[0, :, 0], [0, 1, 2, 2.5, 6])
    # a chain whose edges are off their rest lengths by at most min_error_m (RMS) in a frame is left so there
    kept = respace_chains(X, chain(rest), cap_m=10.0, min_error_m=1.6)  # RMS 1.5 m
    np.testing.assert_allclose(kept, X)
    np.testing.assert_allclose(respace_chains(X, chain(rest), cap_m=10.0, min_error_m=1.4), out_all)
    # a chain bent at a right angle: the keypoints stay on its polyline
    B = np.array([[[0.0, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0]]])
    out = respace_chains(B, chain(np.ones(3)), cap_m=10.0)
    np.testing.assert_allclose(out[0], [[0, 0, 0], [2 / 3, 0, 0], [1, 1 / 3, 0], [1, 1, 0]], atol=1e-12)
    # a fixed inner keypoint (a held one) stays, and the chain is spaced on either side of it
    fixed = np.zeros(5, bool)
    fixed[3] = True
    held = respace_chains(X, chain(rest), cap_m=10.0, fixed=fixed)
    np.testing.assert_allclose(held[:, :, 0], [[0, 0.375, 0.75, 1.5, 6]] * 2)  # 0-1-2-3: arcs 1 : 1 : 2 of 1.5 m


def test_final_keypoints_respace_a_rope_not_a_grid():
    from tracking.init import cloth_topology

    E = np.array([[0, 1], [1, 2]])
    rope = Topology("1d", E, np.array([0.1, 0.1]), np.array([0, 2]), np.zeros(2, np.int64), [np.arange(3)])
    raw = np.zeros((3, 3, 3))
    raw[:, :, 0] = [0.0, 0.05, 0.2]
    final = final_keypoints(raw, rope, P)
    np.testing.assert_allclose(final[:, :, 0], [[0.0, 0.1, 0.2]] * 3)
    np.testing.assert_allclose(final_keypoints(raw, rope, replace(P, respace_cap=0.0)), raw)
    G = np.stack(np.meshgrid(np.arange(3.0), np.arange(3.0)), -1).reshape(-1, 2) * 0.1
    grid = cloth_topology(np.concatenate([G, np.zeros((9, 1))], 1), 3, 3)
    uneven = np.repeat(np.concatenate([G, np.zeros((9, 1))], 1)[None], 2, axis=0)
    uneven[:, 4, :2] += 0.03  # the middle keypoint off the grid's centre: a cloth keeps what the solve gave
    np.testing.assert_allclose(final_keypoints(uneven, grid, P), uneven)


def test_consistent_anchors_leave_a_torn_edge_free():
    from tracking.init import Topology
    from tracking.tracker import consistent_anchors

    E = np.array([[0, 1], [1, 2], [2, 3]])
    topo = Topology("1d", E, np.full(3, 0.1), np.array([0, 1, 2, 3]), np.zeros(4, np.int64), [np.arange(4)])
    pos = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.45, 0, 0]])  # the last edge 2.5x its rest
    ok = consistent_anchors(topo, np.arange(4), pos, 4, 0.15)
    assert ok.tolist() == [True, True, False, False]
    assert consistent_anchors(topo, np.array([0, 3]), pos[[0, 3]], 4, 0.15).all()  # no edge between them


def test_consistent_anchors_check_a_lone_anchor_against_its_neighbours_prediction():
    """A free end matched to a spur 6 cm off is left free: its neighbour is predicted a rest length away."""
    from tracking.init import Topology
    from tracking.tracker import consistent_anchors

    E = np.array([[0, 1], [1, 2], [2, 3]])
    topo = Topology("1d", E, np.full(3, 0.04), np.array([0, 3]), np.zeros(2, np.int64), [np.arange(4)])
    X_pred = np.array([[0.0, 0, 0], [0.04, 0, 0], [0.08, 0, 0], [0.12, 0, 0]])
    good = np.array([[0.0, 0.005, 0], [0.125, 0.0, 0]])  # a few mm from the prediction
    spur = np.array([[0.0, 0.005, 0], [0.12, 0.06, 0]])  # the end's detection is a spur
    assert consistent_anchors(topo, np.array([0, 3]), good, 4, 0.15, X_pred, 0.02).all()
    assert consistent_anchors(topo, np.array([0, 3]), spur, 4, 0.15, X_pred, 0.02).tolist() == [True, False]
    assert consistent_anchors(topo, np.array([0, 3]), spur, 4, 0.15).all()  # without the prediction: unseen


def test_without_anchors_the_grasped_keypoint_stays_at_the_tcp_and_detections_are_ignored(sequence):
    """The ``use_anchors=False`` ablation leaves out re-detected anchors only: a grasped keypoint is the robot's
    input and stays at its TCP; the initialisation is the full method's."""
    import dataclasses

    K, T, bg, frames = sequence
    off = dataclasses.replace(P, use_anchors=False)
    full_tr, off_tr = Tracker(P, K, T), Tracker(off, K, T)
    f0, f1 = frames[0], frames[1]
    tcp = f0.centreline[[0]] + [0.0, 0.0, 0.005]
    cloud0 = _segment(K, T, bg, f0, None)
    _, r_full = full_tr.initialise(cloud0, tcp=tcp)
    _, r_off = off_tr.initialise(cloud0, tcp=tcp)
    np.testing.assert_array_equal(r_full.keypoints, r_off.keypoints)  # the same initialisation
    tcp1 = f1.centreline[[0]] + [0.0, 0.0, 0.005]
    cloud1 = _segment(K, T, bg, f1, off_tr.keypoints)
    r = off_tr.step(cloud1, tcp=tcp1, gripper_closed=np.array([True]))
    assert np.allclose(r.keypoints[r.grasp_idx[0]], tcp1[0])
    free_end = P.n_keypoints_1d - 1 if r.grasp_idx[0] == 0 else 0
    r_full = full_tr.step(cloud1, tcp=tcp1, gripper_closed=np.array([True]))
    # the free end is a re-detected (fixed) tip in the full method and moves freely without anchors
    assert not np.allclose(r.keypoints[free_end], r_full.keypoints[free_end])


def _straight_rope(N: int = 11, spacing: float = 0.02) -> tuple[Topology, np.ndarray]:
    """A rope of N keypoints along x from the origin, spacing m apart, both ends anchors: (Topology, X (N, 3) m)."""
    from tracking.skeleton import LEAF
    from tracking.solver import edge_colouring

    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    topo = Topology("1d", edges, np.full(N - 1, spacing), np.array([0, N - 1]), np.array([LEAF, LEAF]),
                    [np.arange(N)], colours=edge_colouring(edges, N))
    return topo, np.stack([spacing * np.arange(N), np.zeros(N), np.zeros(N)], axis=1)


def test_hidden_keypoints_move_with_the_hand_and_do_not_fail_the_frame() -> None:
    K, T = S.default_camera(W, H)
    topo, X0 = _straight_rope()
    xs = np.linspace(0.1, 0.2, 300)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)  # the rope seen beyond the hand
    hidden = X0[:, 0] < 0.1  # keypoint 0 held at the TCP, 1-4 behind the hand
    tr = Tracker(P, K, T)
    tr.resume(topo, X0, np.array([0]))
    first = tr.step(cloud, tcp=X0[:1], hidden=hidden)
    lift = np.array([[0.0, 0.0, 0.01]])
    second = tr.step(cloud, tcp=X0[:1] + lift, hidden=hidden)
    for res in (first, second):
        # the paper's CD over all keypoints is large (they are 2-10 cm from the cloud), but they have none of their own
        assert res.chamfer_mm > 1e3 * P.max_chamfer_m
        assert res.status == TrackStatus.OK
    X = second.keypoints
    assert np.allclose(X[0], X0[0] + lift[0])  # held at the TCP
    assert np.all(X[1:4, 2] > 0.008)  # the hidden keypoints followed the hand up (by the edges alone: < 3 mm)
    assert np.abs(X[6:, 2]).max() < 1e-6  # the seen ones stay on the cloud



def test_a_rope_keypoint_left_without_cloud_goes_where_behind_arm_puts_it() -> None:
    """After the solve, the 1D keypoints (not held) with no cloud within ``hidden_reach`` of the median rest length
    are handed to behind_arm, which moves the ones the camera would see (``geometry.behind_nearest_occluder``).
    The solve's keypoints are the ones reported here (no tube mean: that report is tested on its own)."""
    K, T = S.default_camera(W, H)
    topo, X0 = _straight_rope()
    p = replace(P, tube_mean_half=0.0)
    xs = np.linspace(0.1, 0.2, 300)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)  # keypoints 1-4 have no cloud
    asked: list[np.ndarray] = []

    def behind_arm(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        asked.append(points.copy())
        moved = points[:, 0] > 0.05  # say the camera sees those there
        return points + moved[:, None] * np.array([0.0, 0.05, 0.0]), moved

    tr = Tracker(p, K, T)
    tr.resume(topo, X0, np.array([0]))
    plain = Tracker(p, K, T)
    plain.resume(topo, X0, np.array([0]))
    X = tr.step(cloud, tcp=X0[:1], behind_arm=behind_arm).keypoints
    Xp = plain.step(cloud, tcp=X0[:1]).keypoints
    off = np.flatnonzero(np.linalg.norm(Xp[:, None] - cloud[None], axis=-1).min(axis=1) > P.hidden_reach * 0.02)
    off = off[off != 0]  # not the held one
    assert len(off) >= 3 and len(asked) == 1
    np.testing.assert_array_equal(asked[0], Xp[off])
    moved = off[Xp[off, 0] > 0.05]
    assert len(moved) >= 1
    np.testing.assert_allclose(X[moved, 1] - Xp[moved, 1], 0.05)
    np.testing.assert_array_equal(np.delete(X, moved, axis=0), np.delete(Xp, moved, axis=0))
    np.testing.assert_array_equal(tr.keypoints, X)  # the next frame starts there


def test_a_rope_gone_from_sight_is_carried_by_the_hands() -> None:
    """A frame with too little cloud to track (the rope behind an arm) moves the keypoints with the hands that hold
    it, as a bad frame: held ends at their TCPs, the rest with them, at its rest lengths (frozen, the ends would
    be left behind the moving grippers for as long as the rope stays hidden)."""
    K, T = S.default_camera(W, H)
    topo, X0 = _straight_rope()
    xs = np.linspace(0.0, 0.2, 300)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    ends = X0[[0, -1]]
    tr = Tracker(P, K, T)
    tr.resume(topo, X0, np.array([0, len(X0) - 1]))
    assert tr.step(cloud, tcp=ends).status == TrackStatus.OK
    move = np.array([0.0, 0.03, 0.01])
    for k in range(1, 3):
        res = tr.step(np.zeros((0, 3)), tcp=ends + k * move)
        assert res.status == TrackStatus.DEGRADED
        assert np.allclose(res.keypoints[[0, -1]], ends + k * move)
        assert np.allclose(res.keypoints, X0 + k * move, atol=1e-6)
    assert np.allclose(tr.keypoints, X0 + 2 * move, atol=1e-6)  # the next tracked frame starts there

def test_hidden_keypoints_beside_a_held_end_leave_the_hand_the_way_they_were_seen() -> None:
    from tracking.solver import hop_neighbours

    K, T = S.default_camera(W, H)
    topo, X0 = _straight_rope()
    N, edges = len(X0), topo.edges
    assert hop_neighbours(edges, N, 0, 2).tolist() == [1, 2]
    assert sorted(hop_neighbours(edges, N, 5, 1).tolist()) == [4, 6]
    xs = np.linspace(0.0, 0.2, 600)
    seen = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    beyond = seen[xs >= 0.1]  # the hand hides the rope next to it
    tcp = X0[:1]
    turned = np.array([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])  # the hand turned 90 deg about z
    hidden = X0[:, 0] < 0.09
    ends = {}
    for rot in (None, np.eye(3)[None]):
        tr = Tracker(P, K, T)
        tr.resume(topo, X0, np.array([0]))
        tr.step(seen, tcp=tcp, hidden=np.zeros(N, bool), tcp_rot=rot)  # all in sight: learnt
        for _ in range(5):
            res = tr.step(beyond, tcp=tcp, hidden=hidden, tcp_rot=None if rot is None else turned)
            assert res.status == TrackStatus.OK
        ends[rot is None] = res.keypoints
    assert np.abs(ends[True][1:3, 1]).max() < 1e-3  # positions alone: nothing turns the hidden stretch
    # with the hand's orientation, the keypoints beside the fingers turn with it (towards (0, 0.02) and (0, 0.04))
    assert ends[False][1, 1] > 0.005 and ends[False][2, 1] > 0.005
    assert np.allclose(ends[False][0], tcp[0])


def test_a_cloths_keypoints_behind_its_near_layer_stay_off_it() -> None:
    """A cloth folded over itself, or turned edge-on: the keypoints under the near layer have no cloud of their own
    (the depth shows the near layer in front of them); projected onto it they would leave the far layer and fold the
    grid onto the strip that is seen. LivePipeline marks them hidden for a 2D object, so only the edges move them."""
    from tdcommon.meshes import sheet_mesh
    from tracking.init import cloth_topology
    from tracking.pipeline import LivePipeline

    def sheet(x: tuple[float, float], y: tuple[float, float], z: float, rows: int, cols: int) -> np.ndarray:
        """(rows, cols, 3) m: a flat sheet at height z over x, y (m)."""
        a, b = np.meshgrid(np.linspace(*x, cols), np.linspace(*y, rows))
        return np.stack([a, b, np.full_like(a, z)], axis=-1)

    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(0)
    R = C = 6
    X0 = sheet((-0.15, 0.15), (-0.15, 0.15), 0.12, R, C).reshape(-1, 3)  # keypoints on the far layer
    topo = cloth_topology(X0, R, C)
    far = sheet((-0.15, 0.15), (-0.15, 0.15), 0.12, 41, 41)
    near = sheet((-0.2, 0.2), (0.04, 0.2), 0.17, 17, 41)  # 5 cm above the far half
    bg = S.render_depth([S.table_mesh()], K, T, (H, W), rng=rng)
    depth = S.render_depth([S.table_mesh(), sheet_mesh(far), sheet_mesh(near)], K, T, (H, W), rng=rng)
    pipe = LivePipeline(P, K, T, "2d")
    pipe.resume(topo, X0, np.full(2, -1, np.int64), pipe.decimate(bg))
    out = pipe.process(depth)
    assert out.status in ("tracking", "degraded") and len(out.keypoints) == R * C
    under = X0[:, 1] > 0.06  # well under the near layer (from this camera, in front of and above the cloth)
    assert under.sum() >= 6
    assert np.abs(out.keypoints[under, 2] - 0.12).max() < 0.015  # not pulled up onto the near layer 5 cm above
    assert np.abs(out.keypoints[~under & (X0[:, 1] < -0.02), 2] - 0.12).max() < 0.005  # the seen ones stay on it


def test_a_held_corners_hidden_neighbours_keep_their_place_in_the_grippers_frame() -> None:
    """A cloth's held corner is clamped like a rope's end: its grid neighbours (one edge away), hidden behind the
    hand, are drawn to where they were last seen in the gripper's frame; the rest of the grid is left to the cloud."""
    from tracking.init import cloth_topology

    K, T = S.default_camera(W, H)
    R = C = 6
    a, b = np.meshgrid(np.linspace(0.0, 0.25, C), np.linspace(0.0, 0.25, R))
    X0 = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    topo = cloth_topology(X0, R, C)  # 5 cm edges
    u, v = np.meshgrid(np.linspace(0.0, 0.25, 101), np.linspace(0.0, 0.25, 101))
    sheet = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    beyond = sheet[np.hypot(sheet[:, 0], sheet[:, 1]) > 0.065]  # the hand hides the cloth around the held corner
    tcp = X0[:1]
    tilted = np.array([[[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]])  # the hand turned 90 deg about x
    hidden = np.hypot(X0[:, 0], X0[:, 1]) < 0.065
    assert sorted(np.flatnonzero(hidden).tolist()) == [0, 1, 6]
    tr = Tracker(P, K, T)
    tr.resume(topo, X0, np.array([0]))
    tr.step(sheet, tcp=tcp, hidden=np.zeros(R * C, bool), tcp_rot=np.eye(3)[None])  # all in sight: learnt
    assert sorted(j for _, _, j in tr._exits(None, tcp, np.eye(3)[None])[0]) == [1, 6]  # one edge away only
    for _ in range(5):
        res = tr.step(beyond, tcp=tcp, hidden=hidden, tcp_rot=tilted)
    X = res.keypoints
    assert X[6, 2] > 0.01  # the neighbour along y turned up with the hand (towards (0, 0, 0.05))
    assert np.allclose(X[0], tcp[0]) and np.abs(X[~hidden, 2]).max() < 0.005  # the rest stays on the cloud


def test_without_gripper_states_the_grippers_the_track_holds_hold_the_corners(monkeypatch) -> None:
    """A clip with arm poses only (no gripper states): each frame's held corners are the TCPs of the grippers the
    track holds a keypoint at (as initialisation took them), not none at all; with gripper states, the closed ones."""
    import tracking.tracker as TR
    from tracking.init import cloth_topology

    K, T = S.default_camera(W, H)
    a, b = np.meshgrid(np.linspace(0.0, 0.25, 6), np.linspace(0.0, 0.25, 6))
    X0 = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    tcp = np.stack([X0[0], X0[5] + [0.0, 0.0, 0.3]])  # the second gripper is nowhere near the cloth
    tr = Tracker(P, K, T)
    tr.resume(cloth_topology(X0, 6, 6), X0, np.array([0, -1]))
    seen: list[np.ndarray | None] = []
    real = TR.detect_anchors

    def spy(kind, cloud, K_, T_, params, held=None):
        seen.append(None if held is None else np.array(held))
        return real(kind, cloud, K_, T_, params, held)

    monkeypatch.setattr(TR, "detect_anchors", spy)
    u, v = np.meshgrid(np.linspace(0.0, 0.25, 60), np.linspace(0.0, 0.25, 60))
    sheet = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    tr.step(sheet, tcp=tcp)
    assert seen[-1] is not None and np.allclose(seen[-1], tcp[:1])
    tr.step(sheet, tcp=tcp, gripper_closed=np.array([True, True]))
    assert np.allclose(seen[-1], tcp)
    tr.step(sheet)
    assert seen[-1] is None


@pytest.mark.parametrize("sweeps", [0, 10])
def test_a_cloths_hidden_part_keeps_its_edge_lengths(sweeps: int) -> None:
    """A cloth whose last two columns are out of sight, pulled towards the seen part by a soft anchor (a corner
    detected on the visible contour, where the sheet turns away): the frame's solve leaves their edges short; the
    relaxation after it (``hidden_relax_sweeps``) gives them their lengths back, the seen keypoints and the held
    corner staying where the solve put them."""
    from dataclasses import replace

    from tracking.init import cloth_topology
    from tracking.metrics import edge_rmse_mm
    from tracking.tracker import track_frame

    R = C = 6
    a, b = np.meshgrid(np.linspace(0.0, 0.25, C), np.linspace(0.0, 0.25, R))
    X0 = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    topo = cloth_topology(X0, R, C)  # 5 cm edges
    u, v = np.meshgrid(np.linspace(0.0, 0.15, 61), np.linspace(0.0, 0.25, 101))
    seen = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)  # columns 0-3
    hidden = X0[:, 0] > 0.16
    corner = R * C - 1  # the free bottom right corner, hidden, drawn towards the seen edge
    soft = (np.array([corner]), np.array([[0.17, 0.25, 0.0]]), np.array([0.2]))
    params = replace(P, hidden_relax_sweeps=sweeps)
    no_det = (np.zeros((0, 3)), np.zeros(0, np.int64))
    X = track_frame(X0, topo, seen, *no_det, params, X0[[C - 1]], np.array([C - 1]), hidden=hidden, soft=soft).X
    assert np.allclose(X[C - 1], X0[C - 1])  # held
    inside = hidden[topo.edges].all(axis=1)  # the edges between hidden keypoints
    err = edge_rmse_mm(X, topo.edges[inside], topo.rest[inside])
    if sweeps:
        ref = track_frame(X0, topo, seen, *no_det, replace(P, hidden_relax_sweeps=0), X0[[C - 1]],
                          np.array([C - 1]), hidden=hidden, soft=soft).X
        assert np.array_equal(X[~hidden], ref[~hidden])  # only the hidden keypoints moved
        assert err < 1.2
        assert edge_rmse_mm(X, topo.edges, topo.rest) < edge_rmse_mm(ref, topo.edges, topo.rest)
    else:
        assert err > 2.0


def test_a_hidden_cloth_keypoint_is_never_relaxed_into_open_space() -> None:
    """The relaxation after the solve leaves a hidden keypoint where the solve put it when its relaxed place is
    where the camera sees through (``open_space``: something there would be seen); the others keep theirs."""
    from dataclasses import replace

    from tracking.init import cloth_topology
    from tracking.tracker import track_frame

    R = C = 6
    a, b = np.meshgrid(np.linspace(0.0, 0.25, C), np.linspace(0.0, 0.25, R))
    X0 = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    topo = cloth_topology(X0, R, C)
    u, v = np.meshgrid(np.linspace(0.0, 0.15, 61), np.linspace(0.0, 0.25, 101))
    seen = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    hidden = X0[:, 0] > 0.16
    soft = (np.array([R * C - 1]), np.array([[0.17, 0.25, 0.0]]), np.array([0.2]))
    args = (X0, topo, seen, np.zeros((0, 3)), np.zeros(0, np.int64), P, X0[[C - 1]], np.array([C - 1]))
    solved = track_frame(*args[:5], replace(P, hidden_relax_sweeps=0), *args[6:], hidden=hidden, soft=soft).X
    relaxed = track_frame(*args, hidden=hidden, soft=soft).X

    step = np.linalg.norm(relaxed - solved, axis=1)
    # the camera sees through the place the relaxation gives keypoint k (a ball no solved keypoint is in)
    clear = np.linalg.norm(relaxed[:, None] - solved[None], axis=2).min(axis=1)
    k = int(np.argmax(np.where(hidden, np.minimum(step, clear), 0.0)))

    def open_space(pts: np.ndarray) -> np.ndarray:
        return np.linalg.norm(pts - relaxed[k], axis=1) < 0.5 * clear[k]

    X = track_frame(*args, hidden=hidden, soft=soft, open_space=open_space).X
    into = hidden & open_space(relaxed)
    assert clear[k] > 0.002 and into[k] and (hidden & ~into).any()
    assert not open_space(solved[hidden]).any()
    np.testing.assert_array_equal(X[into], solved[into])
    np.testing.assert_array_equal(X[~into], relaxed[~into])


def test_a_tip_seen_short_pulls_its_keypoint_instead_of_fixing_it() -> None:
    """A rope's end detected 1.2 cm inside the rope (end-on: its extreme point lies inside the object) is a soft
    anchor: the tip keypoint does not jump there, and the rope is less compressed than with the tip fixed."""
    from dataclasses import replace

    from tracking.skeleton import JUNCTION, LEAF
    from tracking.tracker import short_tips, track_frame

    topo, X0 = _straight_rope()
    N = len(X0)
    xs = np.linspace(0.0, 0.2, 400)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    det = np.array([[0.012, 0.0, 0.0], [0.2, 0.0, 0.0]])  # tip 0 seen 12 mm in: its edge would be 8 mm of 20
    kinds = np.array([LEAF, LEAF])

    assert short_tips(topo, np.array([0, N - 1]), det, kinds, X0, P).tolist() == [True, False]
    assert not short_tips(topo, np.array([0, N - 1]), det, np.array([JUNCTION, LEAF]), X0, P).any()
    far = det + np.array([[-0.006, 0.06, 0.0], [0.0, 0.0, 0.0]])  # beyond anchor_gate_m of the prediction
    assert not short_tips(topo, np.array([0, N - 1]), far, kinds, X0, P).any()
    fixed_params = replace(P, tip_short_tol=0.0)
    assert not short_tips(topo, np.array([0, N - 1]), det, kinds, X0, fixed_params).any()

    fixed = track_frame(X0, topo, cloud, det, kinds, fixed_params).X
    soft = track_frame(X0, topo, cloud, det, kinds, P).X
    assert np.allclose(fixed[0], det[0])  # the paper's hard tip: at the detection
    assert np.linalg.norm(soft[0] - det[0]) > 0.002  # pulled part of the way only (to 8 mm of 12)
    def length(X: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(X, axis=0), axis=1).sum())

    assert abs(soft[0, 0]) < abs(fixed[0, 0])  # nearer the true end (x = 0)
    assert abs(length(soft) - 0.2) < abs(length(fixed) - 0.2)  # the rope less compressed
    assert np.allclose(soft[N - 1], det[1])  # the tip seen at its full length stays fixed


def test_a_free_tip_seen_beyond_its_chain_lengthens_the_chain() -> None:
    """A rope measured 0.20 m long (held at keypoint 0) whose free end is seen 0.26 m from the held end frame after
    frame (a part hanging end-on at initialisation) is lengthened to that after grow_frames frames; a rope seen
    as long as it was measured keeps its rest lengths."""
    from dataclasses import replace

    K, T = S.default_camera(W, H)
    xs = np.linspace(0.0, 0.26, 600)
    long_cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    for cloud, params, grown in ((long_cloud, P, True), (long_cloud, replace(P, grow_frames=0), False),
                                 (long_cloud[xs <= 0.2], P, False)):
        topo, X0 = _straight_rope()
        tr = Tracker(params, K, T)
        tr.resume(topo, X0, np.array([0]))
        for _ in range(P.grow_frames):
            tr.step(cloud, tcp=X0[:1], gripper_closed=np.array([True]))
        total = float(tr.topology.rest.sum())  # type: ignore[union-attr]
        if grown:
            assert total == pytest.approx(0.26, abs=0.01)
        else:
            assert total == pytest.approx(0.2)


def test_track_frame_reports_the_anchors_it_kept() -> None:
    """``used`` says which anchors were re-detected and kept (``Tracker.step`` lets only the others be recaptured
    within the wider gate next frame): a tip detected where it is, yes; a tip with no detection, no."""
    from tracking.skeleton import LEAF
    from tracking.tracker import track_frame

    topo, X0 = _straight_rope()
    xs = np.linspace(0.0, 0.2, 400)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    used = track_frame(X0, topo, cloud, X0[[0]], np.array([LEAF]), P).used
    assert used.tolist() == (topo.anchor_idx == 0).tolist()
    assert used.sum() == 1


def test_a_tip_is_not_recaptured_by_a_detection_on_the_rope() -> None:
    """A 1D tip is matched within the wider gate only by a detection off the rest of the rope (a tip whipping ahead
    of its prediction), not by one lying on it (a spur of the skeleton, a part seen short), between its keypoints
    as well as beside one."""
    from tracking.tracker import regate_on_object

    topo, X0 = _straight_rope()  # 11 keypoints 2 cm apart along x, anchors 0 and 10
    det = np.array([[0.10, 0.003, 0.0], [-0.08, 0.0, 0.0], [0.01, 0.0, 0.0], [0.11, 0.008, 0.0]])
    on_rope = regate_on_object(topo, X0, det, np.array([0, -1]), P)  # 10 cm off, beside keypoint 5
    between = regate_on_object(topo, X0, det, np.array([3, -1]), P)  # 13 mm from keypoints 5 and 6, 8 from the rope
    beyond = regate_on_object(topo, X0, det, np.array([1, -1]), P)  # 8 cm beyond the tip
    near = regate_on_object(topo, X0, det, np.array([2, -1]), P)  # within the gate: a plain match
    assert np.linalg.norm(det[3] - X0, axis=1).min() > P.anchor_regate_clear * 0.02  # no keypoint is that near
    assert on_rope.tolist() == [True, False] and between.tolist() == [True, False]
    assert not beyond.any() and not near.any()


def test_cloudless_keypoints_are_those_whose_nearest_cloud_is_another_part() -> None:
    """A 1D keypoint whose nearest cloud point lies beyond the reach and belongs to a keypoint that is not its
    neighbour has no cloud of its own; one beside its neighbour's cloud, or on its own, has."""
    from tracking.tracker import cloudless

    topo, X0 = _straight_rope()  # 11 keypoints 2 cm apart along x
    xs = np.linspace(0.0, 0.1, 200)  # only keypoints 0-5 are seen
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    assert np.flatnonzero(cloudless(topo, X0, cloud, 0.01)).tolist() == [7, 8, 9, 10]
    assert not cloudless(topo, X0, cloud, 0.2).any()  # all within the reach
    assert not cloudless(topo, X0, np.zeros((0, 3)), 0.01).any()


def test_a_rope_part_without_cloud_is_not_folded_onto_another_part() -> None:
    """A U-shaped rope whose right leg has no cloud (hidden where no arm mask says so): the leg stays a leg (its
    lowest keypoint, beside the bottom's cloud, is projected onto it) instead of folding onto the left leg."""
    from tracking.tracker import track_frame

    s = 0.02
    left = [(0.0, y) for y in (0.08, 0.06, 0.04, 0.02, 0.0)]
    X0 = np.array([(x, y, 0.0) for x, y in [*left, (0.02, 0.0), (0.04, 0.0), (0.04, 0.02), (0.04, 0.04),
                                             (0.04, 0.06), (0.04, 0.08)]])
    topo, _ = _straight_rope(len(X0), s)
    t = np.linspace(0.0, 1.0, 200)
    cloud = np.concatenate([np.stack([0 * t, 0.08 * t, 0 * t], 1), np.stack([0.04 * t, 0 * t, 0 * t], 1)])
    no_det = (np.zeros((0, 3)), np.zeros(0, np.int64))
    X = track_frame(X0, topo, cloud, *no_det, P).X
    assert np.abs(X[7:, 0] - 0.04).max() < 0.002  # the unseen leg stays the right leg, in order up it
    assert (np.diff(X[7:, 1]) > 0.9 * s).all()
    assert np.abs(np.linalg.norm(np.diff(X[:7], axis=0), axis=1) - s).max() < 0.002


def _noisy_tube(rng: np.random.Generator, eye: np.ndarray, radius: float, sigma: float) -> np.ndarray:
    """The visible skin of a straight tube along x (y = 0, z = radius above the table), seen from eye (3,) m,
    with depth noise sigma (m) along each point's line of sight: (M, 3) m, a point every 2 mm along, 1 mm across."""
    x, a = np.meshgrid(np.arange(-0.05, 0.25, 0.002), np.linspace(-np.pi / 2, np.pi / 2, 2 * int(radius * 1e3) + 1))
    view = np.array([0.0, eye[1], eye[2] - radius])
    view /= np.linalg.norm(view)  # towards the camera, across the tube
    side = np.cross([1.0, 0.0, 0.0], view)
    skin = np.stack([x, np.zeros_like(x), np.full_like(x, radius)], -1)
    skin = skin + radius * (np.cos(a)[..., None] * view + np.sin(a)[..., None] * side)
    skin = skin.reshape(-1, 3)
    ray = skin - eye
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return skin + rng.normal(0.0, sigma, (len(skin), 1)) * ray


def test_a_rope_is_reported_in_the_middle_of_its_tube_and_solved_on_from_where_the_solve_left_it() -> None:
    """A noisy tube's solved keypoints sit on single cloud points; the reported ones (``Tracker._reported``) are
    moved across the tube to the mean of their slice, nearer its axis, spaced along the rope as its rest lengths
    are, the held one where it was; the solve's own keypoints stay the next frame's warm start."""
    from tracking.solver import tube_mean

    K, T = S.default_camera(W, H)
    eye = T[:3, 3]
    rng = np.random.default_rng(3)
    radius = 0.006
    cloud = _noisy_tube(rng, eye, radius, 0.003)
    topo, X0 = _straight_rope()
    X0[:, 2] = 2 * radius  # the rope's top
    axis_dist = lambda X: np.hypot(X[:, 1], X[:, 2] - radius)  # noqa: E731
    tr = Tracker(P, K, T)
    tr.resume(topo, X0, np.array([0]))
    res = tr.step(cloud, tcp=X0[:1])
    solved, reported = tr.keypoints, res.keypoints
    inner = np.arange(1, len(X0))
    assert np.sqrt(np.mean(axis_dist(reported[inner]) ** 2)) < 0.8 * np.sqrt(np.mean(axis_dist(solved[inner]) ** 2))
    np.testing.assert_array_equal(reported[0], solved[0])  # the held end stays at its TCP
    assert not np.array_equal(reported, solved)
    off = replace(P, tube_mean_half=0.0)
    plain = Tracker(off, K, T)
    plain.resume(topo, X0, np.array([0]))
    np.testing.assert_array_equal(plain.step(cloud, tcp=X0[:1]).keypoints, solved)  # the warm start is the solve's
    # tube_mean on its own: across the tube only, unflagged points and points with under three in reach unmoved
    tan = np.tile([1.0, 0.0, 0.0], (len(X0), 1))
    use = np.ones(len(X0), bool)
    use[5] = False
    far = solved.copy()
    far[7] += [0.0, 0.0, 0.2]  # nothing within reach of it
    moved = tube_mean(far, tan, cKDTree(cloud), 0.005, 0.01, use)
    np.testing.assert_array_equal(moved[[5, 7]], far[[5, 7]])
    np.testing.assert_allclose(moved[:, 0], far[:, 0])


def test_a_ropes_reference_lengths_are_those_of_its_keypoints_as_reported() -> None:
    """Initialisation on a noisy tube measures rest lengths on the skin's points the solve holds keypoints to; the
    reference lengths written out are the reported (centred) chain's, nearer the tube's true 0.30 m, and the Abs
    reported is against them. A cloth has none of its own (reference_lengths is its rest)."""
    from tracking.metrics import edge_rmse_mm

    K, T = S.default_camera(W, H)
    cloud = _noisy_tube(np.random.default_rng(0), T[:3, 3], 0.006, 0.003)
    tr = Tracker(P, K, T)
    ini, res = tr.initialise(cloud, kind="1d")
    topo = ini.topology
    assert tr.topology is topo and topo.reference is not None
    assert abs(topo.reference_lengths.sum() - 0.30) < abs(topo.rest.sum() - 0.30)
    assert res.edge_rmse_mm == pytest.approx(edge_rmse_mm(res.keypoints, topo.edges, topo.reference_lengths))
    assert res.edge_rmse_mm < edge_rmse_mm(res.keypoints, topo.edges, topo.rest)
    off = Tracker(replace(P, tube_mean_half=0.0), K, T)
    assert off.initialise(cloud, kind="1d")[0].topology.reference is None


def test_shorten_stretched_shortens_only_the_stretched_edges_and_keeps_the_fixed_keypoints() -> None:
    """A chain of three with one edge 50 % too long and one 50 % too short: sweeps bring the long one to its rest
    length and leave the short one shorter than its rest length; an unmovable keypoint does not move."""
    from tracking.solver import shorten_stretched

    X = np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0], [0.2, 0.0, 0.0]])
    edges = np.array([[0, 1], [1, 2]])
    rest = np.array([0.1, 0.1])
    Y = shorten_stretched(X, edges, rest, np.array([False, True, True]), 30)
    L = np.linalg.norm(Y[edges[:, 1]] - Y[edges[:, 0]], axis=1)
    np.testing.assert_allclose(Y[0], X[0])
    assert abs(L[0] - 0.1) < 1e-6 and L[1] <= 0.1
    np.testing.assert_allclose(shorten_stretched(X, edges, np.array([0.2, 0.1]), np.ones(3, bool), 5), X)


def test_onto_local_plane_moves_points_along_the_surface_normal_only() -> None:
    """Points 5 mm above a tilted plane of cloud points end on it, each along the plane's normal; the ones not
    asked for do not move."""
    from tracking.solver import onto_local_plane

    u, v = np.meshgrid(np.linspace(-0.1, 0.1, 41), np.linspace(-0.1, 0.1, 41))
    normal = np.array([0.0, -np.sin(0.4), np.cos(0.4)])
    e1, e2 = np.array([1.0, 0.0, 0.0]), np.cross(normal, [1.0, 0.0, 0.0])
    cloud = u.reshape(-1, 1) * e1 + v.reshape(-1, 1) * e2
    on = np.array([[0.02, 0.03], [-0.05, 0.01], [0.0, 0.0]]) @ np.stack([e1, e2])
    X = on + 0.005 * normal
    Y = onto_local_plane(X, cKDTree(cloud), np.array([True, True, False]))
    np.testing.assert_allclose(Y[:2], on[:2], atol=1e-9)
    np.testing.assert_allclose(Y[2], X[2])


def test_a_cloths_stretched_keypoints_are_reported_unstretched_a_folded_one_as_solved() -> None:
    """A grid keypoint pulled 3 cm off its place in the sheet (its four edges stretched) is reported back towards it,
    its held corner kept, the solve's keypoints untouched; a grid whose edges are only shorter (a fold) is reported
    as solved, as is one whose edge error is under ``stretch_abs_mm``."""
    from tracking.init import cloth_topology

    K, T = S.default_camera(W, H)
    a, b = np.meshgrid(np.linspace(0.0, 0.25, 6), np.linspace(0.0, 0.25, 6))
    X0 = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    tr = Tracker(P, K, T)
    tr.resume(cloth_topology(X0, 6, 6), X0, np.array([0, -1]))
    u, v = np.meshgrid(np.linspace(0.0, 0.25, 60), np.linspace(0.0, 0.25, 60))
    sheet = cKDTree(np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1))
    X = X0.copy()
    X[14] += [0.03, 0.0, 0.0]
    out = tr._reported(X, sheet, None)
    assert out is not X and np.linalg.norm(out[14] - X0[14]) < 0.7 * np.linalg.norm(X[14] - X0[14])
    topo = tr.topology
    assert edge_rmse_mm(out, topo.edges, topo.rest) < 0.7 * edge_rmse_mm(X, topo.edges, topo.rest)
    np.testing.assert_allclose(out[0], X0[0])
    assert abs(out[:, 2]).max() < 1e-9  # on the sheet
    np.testing.assert_allclose(X[14], X0[14] + [0.03, 0.0, 0.0])  # the solve's keypoints are not changed
    folded = X0 * [1.0, 0.8, 1.0]  # every column edge 20 % short
    assert tr._reported(folded, sheet, None) is folded
    small = X0.copy()
    small[14] += [0.003, 0.0, 0.0]
    assert tr._reported(small, sheet, None) is small
