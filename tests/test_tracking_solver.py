"""Algorithm 1: edge colouring and the Gauss-Seidel projections."""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from tracking.init import grid_topology
from tracking.metrics import edge_rmse_mm
from tracking.params import TrackingParams
from tracking.solver import edge_colouring, solve_keypoints

P = TrackingParams()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 14), st.integers(0, 14)), min_size=1, max_size=60))
def test_edge_colouring_has_no_shared_vertex_in_a_class(pairs):
    edges = np.array([(a, b) for a, b in pairs if a != b] or [(0, 1)])
    classes = edge_colouring(edges, 15)
    assert sorted(np.concatenate(classes).tolist()) == list(range(len(edges)))
    max_deg = np.bincount(edges.ravel()).max()
    assert len(classes) <= 2 * max_deg - 1
    for cls in classes:
        v = edges[cls].ravel()
        assert len(np.unique(v)) == len(v)


def _curve_cloud(rng, n=4000):
    s = rng.uniform(0, 1, n)
    c = np.stack([0.6 * s, 0.1 * np.sin(4 * s), np.full(n, 0.01)], axis=1)
    return c + rng.normal(0, 0.001, c.shape)


def test_solver_keeps_edge_lengths_and_stays_on_cloud():
    rng = np.random.default_rng(0)
    cloud = _curve_cloud(rng)
    line = np.stack([0.6 * np.linspace(0, 1, 500), 0.1 * np.sin(4 * np.linspace(0, 1, 500)), np.full(500, 0.01)], 1)
    length = np.linalg.norm(np.diff(line, axis=0), axis=1).sum()
    N = 20
    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    rest = np.full(N - 1, length / (N - 1))
    # an unordered warm start can fold the chain (a local minimum); start from an uneven but ordered one
    idx = np.clip(np.linspace(0, 499, N).astype(int) + rng.integers(-8, 9, N), 0, 499)
    X0 = line[np.sort(idx)] + rng.normal(0, 0.003, (N, 3))
    anchors = np.array([0, N - 1])
    X = solve_keypoints(X0, edges, rest, anchors, line[[0, -1]], cloud, 100, P)
    assert np.allclose(X[anchors], line[[0, -1]])
    assert edge_rmse_mm(X, edges, rest) < 1.5
    assert cKDTree(cloud).query(X)[0].max() < 0.004
    # the paper's exact nearest-point projection puts non-anchors on cloud points
    Xn = solve_keypoints(X0, edges, rest, anchors, line[[0, -1]], cloud, 100, dataclasses.replace(P, surface_k=1))
    assert cKDTree(cloud).query(Xn[1:-1])[0].max() < 1e-12
    assert edge_rmse_mm(Xn, edges, rest) < 4.0


def test_grid_edge_projection_alone_converges():
    E, rest = grid_topology(4, 5, 0.05, 0.04)
    rng = np.random.default_rng(1)
    X0 = np.stack(np.meshgrid(np.arange(5) * 0.05, np.arange(4) * 0.04), -1).reshape(-1, 2)
    X0 = np.column_stack([X0, np.zeros(len(X0))]) + rng.normal(0, 0.005, (20, 3))
    p = dataclasses.replace(P, use_cloud_projection=False, use_anchors=False)
    X = solve_keypoints(X0, E, rest, np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), 200, p)
    assert edge_rmse_mm(X, E, rest) < 0.05


def test_ablation_switches():
    rng = np.random.default_rng(2)
    cloud = _curve_cloud(rng)
    N = 10
    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    rest = np.full(N - 1, 0.05)
    X0 = rng.uniform(0, 0.3, (N, 3))
    a_pos = np.array([[0.0, 0.0, 0.5]])
    off = dataclasses.replace(P, use_anchors=False, use_edge_projection=False, use_cloud_projection=False)
    assert np.array_equal(solve_keypoints(X0, edges, rest, [0], a_pos, cloud, 10, off), X0)
    no_anchor = dataclasses.replace(P, use_anchors=False)
    assert not np.allclose(solve_keypoints(X0, edges, rest, [0], a_pos, cloud, 10, no_anchor)[0], a_pos[0])
    anchor = solve_keypoints(X0, edges, rest, [0], a_pos, cloud, 10, P)
    assert np.allclose(anchor[0], a_pos[0])


def test_centre_on_ridge_moves_points_across_a_tube_to_the_side_facing_the_camera():
    from tracking.segmentation import voxel_downsample
    from tracking.solver import centre_on_ridge

    rng = np.random.default_rng(0)
    r = 0.008  # a tube along x at the origin, seen from +z: the ridge is the line y = 0, z = r
    x = rng.uniform(-0.1, 0.1, 4000)
    phi = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, 4000)  # the visible half
    cloud = np.stack([x, r * np.sin(phi), r * np.cos(phi)], axis=1) + rng.normal(0, 0.001, (4000, 3))
    cloud = voxel_downsample(cloud, P.voxel_m)
    X = np.stack([np.linspace(-0.05, 0.05, 7), np.full(7, 0.005), np.full(7, r * np.cos(np.arcsin(5 / 8)))], axis=1)
    out = centre_on_ridge(X, np.tile([1.0, 0, 0], (7, 1)), cKDTree(cloud), np.array([0.0, 0, 1.0]), 0.012)
    assert np.abs(out[:, 1]).max() < 0.0025  # across: centred (was 5 mm off; 4 mm voxels, 1 mm noise)
    assert np.abs(out[:, 2] - r).max() < 0.0015  # on the skin at the ridge, not inside the tube
    assert np.abs(out[:, 0] - X[:, 0]).max() < 1e-9  # along the tube: untouched


def test_soft_anchor_pulls_part_way_and_keeps_edge_lengths_better() -> None:
    """A chain held at one end (hard) with a noisy anchor 3 cm beyond its other end: hard, the edges stretch
    by the whole 3 cm; soft (weight 0.2), the end keypoint stops between the chain's length and the anchor."""
    X0 = np.stack([np.linspace(0.0, 0.4, 5), np.zeros(5), np.zeros(5)], axis=1)
    edges = np.stack([np.arange(4), np.arange(1, 5)], axis=1)
    rest = np.full(4, 0.1)
    idx, pos = np.array([0, 4]), np.array([[0.0, 0.0, 0.0], [0.43, 0.0, 0.0]])
    params = TrackingParams(use_cloud_projection=False)
    hard = solve_keypoints(X0, edges, rest, idx, pos, np.zeros((0, 3)), 50, params)
    soft = solve_keypoints(X0, edges, rest, idx, pos, np.zeros((0, 3)), 50, params, anchor_weight=np.array([1.0, 0.2]))
    assert np.allclose(hard[[0, 4]], pos) and np.allclose(soft[0], pos[0])
    assert 0.4 < soft[4, 0] < 0.43
    assert edge_rmse_mm(soft, edges, rest) < 0.5 * edge_rmse_mm(hard, edges, rest)


def test_hidden_keypoint_is_projected_onto_the_cloud_only_beside_it() -> None:
    # a chain held at x = 0 whose first keypoints are hidden: the cloud is the seen part of the rope, x >= 0.1 m
    N = 11
    rest = np.full(N - 1, 0.02)
    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    X0 = np.stack([0.02 * np.arange(N), np.zeros(N), np.zeros(N)], axis=1)
    xs = np.linspace(0.1, 0.2, 200)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    hidden = X0[:, 0] < 0.1
    anchors = np.array([0, N - 1])
    free = solve_keypoints(X0, edges, rest, anchors, X0[anchors], cloud, 30, P)
    kept = solve_keypoints(X0, edges, rest, anchors, X0[anchors], cloud, 30, P, hidden=hidden)
    # without the flag the hidden keypoints are pulled onto the seen rope and the edge to the held end stretches
    assert free[1, 0] > 0.05 and edge_rmse_mm(free, edges, rest) > 10.0
    # with it they stay where the edges put them (the nearest cloud point is 2 cm or more away: beyond reach)
    assert 0.1 - X0[4, 0] > P.hidden_reach * 0.02
    assert np.allclose(kept, X0, atol=1e-9)
    # a hidden keypoint beside the cloud (4 mm above the seen rope: within reach) is projected onto it
    Xb = X0.copy()
    Xb[5:, 2] = 0.004
    moved = solve_keypoints(Xb, edges, rest, anchors, X0[anchors], cloud, 1, P, hidden=np.ones(N, bool))
    assert abs(moved[5, 2]) < 1e-9 and np.allclose(moved[1:4], Xb[1:4], atol=5e-4)


def test_chain_neighbours_two_each_side_and_none_at_a_junction() -> None:
    from tracking.solver import chain_neighbours

    nb = chain_neighbours([np.array([0, 1, 2, 3]), np.array([1, 4, 5])], 6)
    assert nb[2].tolist() == [0, 1, 3, -1]
    assert nb[0].tolist() == [-1, -1, 1, 2]
    assert nb[4].tolist() == [-1, 1, 5, -1]
    assert nb[1].tolist() == [-1, -1, -1, -1]  # on two chains: no one curve runs through it


def test_hidden_stretch_is_drawn_smooth_not_kinked() -> None:
    from tracking.solver import chain_neighbours

    # keypoints 0-3 seen on a straight rope along x, 4-7 hidden behind a hand, 8 held at the TCP further along x
    N = 9
    rest = np.full(N - 1, 0.02)
    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    X0 = np.stack([0.02 * np.arange(N), np.zeros(N), np.zeros(N)], axis=1)
    X0[8, 0] = 0.15  # slack: the hidden stretch must bend somewhere
    X0[[5, 7], 1] = 0.012  # warm start kinked
    xs = np.linspace(0.0, 0.06, 100)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    hidden = np.arange(N) >= 4
    anchors = np.array([0, 8])
    nb = chain_neighbours([np.arange(N)], N)

    def kink(X: np.ndarray) -> float:
        return float(np.abs(np.diff(X[3:], n=2, axis=0)).sum())

    plain = solve_keypoints(X0, edges, rest, anchors, X0[anchors], cloud, 30, P, hidden=hidden)
    smooth = solve_keypoints(X0, edges, rest, anchors, X0[anchors], cloud, 30, P, hidden=hidden, bend=nb)
    assert kink(smooth) < 0.5 * kink(plain)
    assert edge_rmse_mm(smooth, edges, rest) < 2.0
    assert np.abs(smooth[:4, 1:]).max() < 1e-9  # the seen part stays on the cloud


def test_hidden_keypoint_is_not_pulled_beyond_its_edge_from_a_held_neighbour() -> None:
    # keypoint 0 held at the TCP, keypoint 1 hidden by the hand; the seen rope starts 2.8 cm from the TCP, 8 mm
    # from keypoint 1 (within hidden_reach) but beyond its 2 cm edge (plus hidden_stretch) from the held end
    N = 6
    rest = np.full(N - 1, 0.02)
    edges = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    X0 = np.stack([0.02 * np.arange(N), np.zeros(N), np.zeros(N)], axis=1)
    X0[1, 1] = 0.004  # off the line: a projection would move it
    xs = np.linspace(0.028, 0.1, 200)
    cloud = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    hidden = np.zeros(N, bool)
    hidden[1] = True
    held = np.array([0])
    kept = solve_keypoints(X0, edges, rest, held, X0[held], cloud, 1, P, hidden=hidden)
    assert np.linalg.norm(kept[1] - kept[0]) < 0.0205 and kept[1, 1] > 0.001  # not projected
    loose = dataclasses.replace(P, hidden_stretch=1.0)  # a 4 cm reach: the seen rope's start is within it
    pulled = solve_keypoints(X0, edges, rest, held, X0[held], cloud, 1, loose, hidden=hidden)
    assert abs(pulled[1, 1]) < 1e-9


def test_relax_hidden_restores_hidden_edges_and_moves_nothing_else() -> None:
    from tracking.solver import relax_hidden

    # a 4 x 4 grid of 5 cm edges whose last column is pressed 3 cm towards the third (hidden, cloud-less)
    R = C = 4
    a, b = np.meshgrid(np.linspace(0.0, 0.15, C), np.linspace(0.0, 0.15, R))
    X = np.stack([a, b, np.zeros_like(a)], axis=-1).reshape(-1, 3)
    edges, rest = grid_topology(R, C, 0.05, 0.05)
    hidden = np.zeros(R * C, bool)
    hidden[C - 1 :: C] = True
    X[hidden, 0] -= 0.03
    before = edge_rmse_mm(X, edges, rest)
    out = relax_hidden(X, edges, rest, hidden, 10, P)
    assert np.array_equal(out[~hidden], X[~hidden])  # the seen keypoints stay put
    assert before > 10.0 and edge_rmse_mm(out, edges, rest) < 1.0
    assert np.allclose(out[hidden, 0], 0.15, atol=2e-3)  # the hidden column back at its rest distance
    assert relax_hidden(X, edges, rest, hidden, 0, P) is X  # off
    assert relax_hidden(X, edges, rest, np.zeros(R * C, bool), 10, P) is X  # nothing hidden
