"""A cloth grid's tangles: detection on folded and twisted grids, repair by a re-lifted grid in the track's order."""

from __future__ import annotations

import numpy as np
import pytest

from tdcommon.meshes import sheet_mesh
from tracking import synthetic as S
from tracking.init import Topology, initialise
from tracking.offline import gaps
from tracking.params import TrackingParams
from tracking.segmentation import background_from_depths, segment_against_background
from tracking.tangle import (
    captured,
    chain_reversals,
    clip_tangles,
    grid_symmetries,
    relift_chains,
    relift_grid,
    tangled_cells,
    unfold_chains,
)
from tracking.tracker import Tracker

W, H = 640, 480
P = TrackingParams()
R = C = 6


def _grid(fold: float = 0.0) -> np.ndarray:
    """A 0.3 m square grid (R*C, 3) m, the rows past the third bent by ``fold`` rad about the third row's line."""
    u, v = np.meshgrid(np.linspace(0.0, 0.3, C), np.linspace(0.0, 0.3, R))
    X = np.stack([u, v, np.zeros_like(u)], axis=-1)
    m = v > 0.121
    d = v[m] - 0.12
    X[m, 1] = 0.12 + d * np.cos(fold)
    X[m, 2] = d * np.sin(fold)
    return X.reshape(-1, 3)


def test_a_flat_bent_or_folded_grid_is_not_tangled() -> None:
    # flat, bent 45 degrees, folded 110 degrees, folded back onto itself (170 degrees) along a grid line: a real
    # fold's neighbouring cells face apart, none of them is folded over itself
    for fold in (0.0, 0.8, 1.9, np.pi - 0.2):
        assert not tangled_cells(_grid(fold), R, C).any()


def test_a_corner_pulled_across_its_cell_is_tangled() -> None:
    X = _grid()
    X[7] = X[14] + [0.01, 0.01, 0.0]  # node (1, 1) pulled past node (2, 2): its cells turn into bow-ties
    bad = tangled_cells(X, R, C)
    assert bad[:2, :2].any() and not bad[3:, 3:].any()


def test_grid_symmetries_are_permutations_that_keep_neighbours() -> None:
    X = _grid(0.5)
    E = np.array([[i, i + 1] for i in range(R * C) if (i + 1) % C] + [[i, i + C] for i in range(R * C - C)])
    L = np.linalg.norm(X[E[:, 0]] - X[E[:, 1]], axis=1)
    syms = grid_symmetries(R, C)
    assert len(syms) == 8 and len({p.tobytes() for p in syms}) == 8
    for p in syms:
        assert sorted(p.tolist()) == list(range(R * C))
        Y = X[p]
        assert np.isclose(np.sort(np.linalg.norm(Y[E[:, 0]] - Y[E[:, 1]], axis=1)), np.sort(L)).all()
    assert len(grid_symmetries(4, 6)) == 4


@pytest.fixture(scope="module")
def cloth_scene():
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(0)
    bg = background_from_depths(np.stack([S.render_depth([S.table_mesh()], K, T, (H, W), rng=rng) for _ in range(3)]))
    cs = S.cloth_surface()
    d = S.render_depth([S.table_mesh(), sheet_mesh(cs)], K, T, (H, W), rng=rng)
    return K, T, segment_against_background(d, bg, K, T, P).points


def test_relifted_grid_keeps_the_tracks_keypoint_order(cloth_scene) -> None:
    K, T, cloud = cloth_scene
    ini = initialise(cloud, K, T, P, "2d")
    for p in grid_symmetries(R, C):  # however the track's grid lies, the fresh one is laid the same way
        prev = ini.keypoints[p]
        topo = ini.topology
        X = relift_grid(prev, topo, cloud, K, T, P)
        assert X is not None
        assert np.linalg.norm(X - prev, axis=1).max() < 0.015
    # a contour showing part of the cloth (the rest folded under or hidden): no grid is spread over that part
    half = cloud[cloud[:, 0] < np.median(cloud[:, 0])]
    assert relift_grid(ini.keypoints, ini.topology, half, K, T, P) is None


def test_tracker_repairs_a_tangled_grid_and_reports_it(cloth_scene) -> None:
    K, T, cloud = cloth_scene
    tr = Tracker(P, K, T)
    tr.initialise(cloud, kind="2d")
    assert tr.keypoints is not None
    ok = tr.step(cloud)
    assert ok.tangled == 0 and not ok.repaired
    G = tr.keypoints.copy().reshape(R, C, 3)
    G[4:] = G[4:, ::-1]  # the last two rows laid the other way round: a half twist the solver folds into bow-ties
    tr.keypoints = G.reshape(-1, 3)
    res = tr.step(cloud)
    assert res.repaired and res.tangled == 0
    assert not tangled_cells(res.keypoints, R, C).any()
    assert np.linalg.norm(res.keypoints - ok.keypoints, axis=1).max() < 0.02


def _chain(n: int = 10, spacing: float = 0.04) -> tuple[np.ndarray, Topology]:
    """A straight rope chain (n, 3) m along x and its topology (one chain, end to end)."""
    X = np.stack([np.arange(n) * spacing, np.zeros(n), np.zeros(n)], axis=1)
    E = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    topo = Topology("1d", E, np.full(n - 1, spacing), np.array([0, n - 1]), np.zeros(2, np.int64), [np.arange(n)])
    return X, topo


def test_a_bent_chain_does_not_turn_back_and_a_z_fold_does() -> None:
    X, topo = _chain()
    t = np.linspace(0.0, np.pi, len(X))  # bent into a half circle: 20 degrees a keypoint
    bent = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1) * 0.12
    assert len(chain_reversals(X, topo.chains, P.fold_cos)) == 0
    assert len(chain_reversals(bent, topo.chains, P.fold_cos)) == 0
    Z = X.copy()
    Z[[3, 4]] = X[[4, 3]]  # keypoints 3 and 4 in the wrong order along the rope: the chain runs 2 -> 4 -> 3 -> 5
    assert sorted(chain_reversals(Z, topo.chains, P.fold_cos).tolist()) == [3, 4]


def test_a_clips_tangled_frames_are_counted_frame_by_frame() -> None:
    X, topo = _chain()
    Z = X.copy()
    Z[[3, 4]] = X[[4, 3]]
    gap = np.full_like(X, np.nan)  # a frame without keypoints is not counted
    assert clip_tangles(np.stack([X, Z, Z, gap, X, Z]), topo, P.fold_cos).tolist() == [0, 2, 2, 0, 0, 2]
    runs = [[a, b - 1] for a, b in gaps(np.array([0, 2, 2, 0, 0, 2]) == 0)]  # as trackdeform track reports them
    assert runs == [[1, 2], [5, 5]]
    assert gaps(np.ones(4, bool)) == []
    E = np.array([[i, i + 1] for i in range(R * C) if (i + 1) % C] + [[i, i + C] for i in range(R * C - C)])
    grid = Topology("2d", E, np.full(len(E), 0.06), np.zeros(0, np.int64), np.zeros(0, np.int64), [], (R, C))
    bad = _grid()
    bad[7] = bad[14] + [0.01, 0.01, 0.0]
    assert clip_tangles(np.stack([_grid(), bad]), grid, P.fold_cos).tolist() == [0, int(tangled_cells(bad, R, C).sum())]
    assert tangled_cells(bad, R, C).sum() > 0


def test_unfold_lays_a_folded_chain_out_in_order_along_itself() -> None:
    X, topo = _chain()
    Z = X.copy()
    Z[[3, 4]] = X[[4, 3]]
    Z[5:] -= [0.02, 0.0, 0.0]  # the fold took up length: the keypoints past it sit closer to the start
    U = unfold_chains(Z, topo, P.fold_cos, P.fold_span_min)
    assert U is not None
    assert np.array_equal(U[[0, -1]], Z[[0, -1]])  # the ends stay
    assert (np.diff(U[:, 0]) > 0).all() and len(chain_reversals(U, topo.chains, P.fold_cos)) == 0
    assert np.allclose(np.diff(U[:, 0]), (Z[-1, 0] - Z[0, 0]) / (len(X) - 1))  # even spacing, as the rest lengths
    assert unfold_chains(X, topo, P.fold_cos, P.fold_span_min) is None  # nothing folded, nothing to do
    S = X * [0.5, 1.0, 1.0]  # a chain seen over half its length (the rest out of sight), folded at its end
    S[[7, 8]] = S[[8, 7]]
    assert unfold_chains(S, topo, P.fold_cos, P.fold_span_min) is None


def _y(spacing: float = 0.04) -> tuple[np.ndarray, Topology]:
    """A Y-shaped branched rope (10, 3) m: main rope 0..6 along x with its junction at 3, branch 3 -> 7, 8, 9
    along y; chains end to end (the junction on each)."""
    main = np.stack([np.arange(7) * spacing, np.zeros(7), np.zeros(7)], axis=1)
    branch = main[3] + np.stack([np.zeros(3), np.arange(1, 4) * spacing, np.zeros(3)], axis=1)
    chains = [np.array([0, 1, 2, 3]), np.array([3, 4, 5, 6]), np.array([3, 7, 8, 9])]
    E = np.array([[a, b] for c in chains for a, b in zip(c[:-1], c[1:], strict=True)])
    topo = Topology("1d", E, np.full(len(E), spacing), np.array([0, 6, 9, 3]), np.array([0, 0, 0, 1]), chains)
    return np.concatenate([main, branch]), topo


def test_a_keypoint_taken_by_another_part_of_the_rope_is_laid_out_again_whatever_the_span() -> None:
    X, topo = _y()
    reach = P.fold_capture * 0.04
    # the branch's first keypoint lies on the main rope beside keypoint 4 and the rest of the branch is seen
    # short (partly hidden): the chain 3 -> 7 -> 8 turns back at 7, and what is left spans under fold_span_min
    Z = X.copy()
    Z[7] = X[4] + [0.003, 0.0, 0.0]
    Z[8], Z[9] = X[3] + [0.0, 0.03, 0.0], X[3] + [0.0, 0.06, 0.0]
    assert chain_reversals(Z, topo.chains, P.fold_cos).tolist() == [7]
    assert captured(Z, topo.chains, np.array([7]), reach).tolist() == [True]
    assert unfold_chains(Z, topo, P.fold_cos, P.fold_span_min) is None  # not captured: the short span holds
    U = unfold_chains(Z, topo, P.fold_cos, P.fold_span_min, reach)
    assert U is not None and len(chain_reversals(U, topo.chains, P.fold_cos)) == 0
    assert np.array_equal(U[:7], Z[:7]) and abs(U[7, 0] - X[3, 0]) < 1e-9  # back on the branch, the main kept
    # a branch collapsed onto its own junction has not been taken by another part: the junction is on its chain
    C = X.copy()
    C[8] = X[3] + [0.0, 0.002, 0.0]
    assert captured(C, topo.chains, np.array([8]), reach).tolist() == [False]


def test_tracker_unfolds_a_folded_rope_and_reports_it() -> None:
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(3)
    bg = background_from_depths(np.stack([S.rope_scene(0, K, T, (H, W), rng, with_object=False).depth] * 2))
    fr = S.rope_scene(0, K, T, (H, W), rng)
    cloud = segment_against_background(fr.depth, bg, K, T, P).points
    tr = Tracker(P, K, T)
    tr.initialise(cloud, kind="1d")
    assert tr.keypoints is not None and tr.topology is not None
    ok = tr.step(cloud)
    assert ok.tangled == 0 and not ok.repaired
    # the fold seen on a test-bed rope: keypoints 2 and 3 the wrong way round along it, the chain past them
    # stretched to make up the length the fold takes (positions in keypoint spacings along the tracked rope)
    n = len(ok.keypoints)
    at = np.concatenate([[0.0, 1.1, 2.1, 1.45], np.linspace(2.4, n - 1, n - 4)])
    tr.keypoints = np.stack([np.interp(at, np.arange(n), ok.keypoints[:, i]) for i in range(3)], axis=1)
    res = tr.step(cloud)
    assert res.repaired and res.tangled == 0
    assert len(chain_reversals(res.keypoints, tr.topology.chains, P.fold_cos)) == 0
    assert np.linalg.norm(res.keypoints - ok.keypoints, axis=1).max() < 0.01


def test_relifted_chains_keep_a_branched_ropes_keypoint_order() -> None:
    # a Y-shaped rope on the table, tracked; then one branch's keypoints folded back onto the junction (a branch
    # lost behind the rest of the rope and seen again): laid out again along the skeleton, each keypoint where it
    # was, and the tracker takes that repair
    from tdcommon.meshes import tube_mesh

    K, T = S.default_camera(W, H)
    br = S.y_rope_branches()
    depth = S.render_depth([S.table_mesh()] + [tube_mesh(b, 0.006) for b in br], K, T, (H, W))
    bg = S.render_depth([S.table_mesh()], K, T, (H, W))
    cloud = segment_against_background(depth, bg, K, T, P).points
    tr = Tracker(P, K, T)
    tr.initialise(cloud, kind="1d")
    ok = tr.step(cloud)
    topo = tr.topology
    assert topo is not None and len(topo.chains) == 3
    chain = max(topo.chains, key=len)
    j, free = int(chain[0]), chain[1:]  # a chain from the junction (or a leaf) on
    folded = ok.keypoints.copy()
    back = ok.keypoints[free[::-1]]  # the chain's keypoints in reverse order, squeezed towards its start
    folded[free] = ok.keypoints[j] + 0.4 * (back - ok.keypoints[j])
    X = relift_chains(folded, topo, cloud, K, T, P)
    assert X is not None
    assert np.linalg.norm(X - ok.keypoints, axis=1).max() < 0.02
    # a straight rope's skeleton has one branch, not the Y's three: no re-lift
    rope = S.render_depth([S.table_mesh(), tube_mesh(br[0], 0.006)], K, T, (H, W))
    assert relift_chains(folded, topo, segment_against_background(rope, bg, K, T, P).points, K, T, P) is None
    tr.keypoints = folded
    res = tr.step(cloud)
    assert res.repaired
    assert np.linalg.norm(res.keypoints - ok.keypoints, axis=1).max() < 0.02


def _hanging_sheet(n: int = 6, side: float = 0.25) -> tuple[np.ndarray, Topology, np.ndarray]:
    """A flat n x n grid (row-major) hanging in the x-z plane from its top row at z = 0.6 m, its topology, and a
    dense cloud on it (M, 3) m, 5 mm apart."""
    from tracking.init import cloth_topology

    s = np.linspace(0.0, side, n)
    X = np.stack([np.tile(s, n), np.zeros(n * n), np.repeat(0.6 - s, n)], axis=1)
    d = np.arange(0.0, side + 1e-9, 0.005)
    cloud = np.stack([np.tile(d, len(d)), np.zeros(len(d) ** 2), np.repeat(0.6 - d, len(d))], axis=1)
    return X, cloth_topology(X, n, n), cloud


def test_uncovered_share_is_the_part_of_the_cloud_beyond_the_grids_surface() -> None:
    from tracking.tangle import uncovered_share

    X, topo, cloud = _hanging_sheet()
    gap = 0.35 * float(np.median(topo.rest))
    assert uncovered_share(X, (6, 6), cloud, gap) == 0.0
    folded = X.copy()
    folded[18:] = np.tile(X[12:18], (3, 1))  # the lower three rows bunched up on the third
    share = uncovered_share(folded, (6, 6), cloud, gap)
    assert 0.3 < share < 0.6  # the lower half of the sheet, less the strip within the gap of the bunched rows
    assert uncovered_share(X, (6, 6), np.zeros((0, 3)), gap) == 0.0


def test_cover_cloud_unfolds_a_grid_folded_onto_half_the_sheet_at_its_rest_lengths() -> None:
    from tracking.metrics import edge_rmse_mm
    from tracking.tangle import cover_cloud, hung_sheet, uncovered_share

    X, topo, cloud = _hanging_sheet()
    r = float(np.median(topo.rest))
    folded = X.copy()  # the lower half folded like an accordion under the upper half, its edges at rest length
    for k, row in enumerate(range(3, 6), 1):
        folded[6 * row:6 * row + 6] = X[12:18] + [0.0, 0.047 * (k % 2), -0.015 * k]
    assert edge_rmse_mm(folded, topo.edges, topo.rest) < 4.0
    assert uncovered_share(folded, (6, 6), cloud, 0.35 * r) > 0.3
    held = np.array([0, 5])
    Y = cover_cloud(folded, topo, cloud, held, X[held], P)
    assert uncovered_share(Y, (6, 6), cloud, 0.35 * r) < 0.05
    assert edge_rmse_mm(Y, topo.edges, topo.rest) < 2.0
    np.testing.assert_allclose(Y[held], X[held])
    assert np.abs(Y[30:] - X[30:]).max() < 0.3 * r  # the bottom row back at the bottom, in its order
    H = hung_sheet(topo, held, X[held], cloud)  # the start that knows nothing of the last frame: the sheet itself
    assert H is not None and np.abs(H - X).max() < 1e-9
    assert hung_sheet(topo, np.array([0, 35]), X[[0, 35]], cloud) is None  # two opposite corners: no side held


def test_tracker_covers_a_sheet_its_grid_left_folded_and_goes_on_from_there() -> None:
    from tracking.tangle import uncovered_share

    X, topo, cloud = _hanging_sheet()
    folded = X.copy()
    for k, row in enumerate(range(3, 6), 1):
        folded[6 * row:6 * row + 6] = X[12:18] + [0.0, 0.047 * (k % 2), -0.015 * k]
    T = np.eye(4)
    T[:3, 3] = [0.125, -1.0, 0.45]  # a camera 1 m in front of the sheet, looking along +y
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    tracker = Tracker(P, np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]]), T)
    tracker.resume(topo, folded, np.array([0, 5]))
    res = tracker.step(cloud, tcp=X[[0, 5]])
    gap = P.cover_gap * float(np.median(topo.rest))
    assert res.repaired
    assert uncovered_share(res.keypoints, (6, 6), cloud, gap) < 0.05
    assert tracker.keypoints is not None and uncovered_share(tracker.keypoints, (6, 6), cloud, gap) < 0.05
