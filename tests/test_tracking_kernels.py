"""The compiled solver iterations (tracking.kernels) against a plain numpy implementation of Algorithm 1."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tracking.init import grid_topology
from tracking.params import TrackingParams
from tracking.segmentation import dbscan_labels
from tracking.solver import edge_colouring, solve_keypoints

P = TrackingParams()


def _reference_solve(
    X0: np.ndarray, edges: np.ndarray, rest: np.ndarray, anchor_idx: np.ndarray, anchor_pos: np.ndarray,
    cloud: np.ndarray, iterations: int, params: TrackingParams, anchor_weight: np.ndarray,
    symmetric_last: bool = False,
) -> np.ndarray:
    """Algorithm 1 in numpy: per colour class a batched edge projection (symmetric_last: in the last iteration,
    the classes in order and in reverse order from the same start, averaged), every keypoint to its k nearest
    cloud points' local extent (a cKDTree), soft anchors pulled, hard anchors fixed."""
    X = np.array(X0, np.float64)
    hard = anchor_weight >= 1.0
    inv_mass = np.ones(len(X))
    inv_mass[anchor_idx[hard]] = 0.0
    X[anchor_idx] = anchor_pos
    tree = cKDTree(cloud)
    k = min(params.surface_k, tree.n)
    classes = edge_colouring(edges, len(X))

    def sweep(X: np.ndarray, order: list[np.ndarray]) -> np.ndarray:
        X = X.copy()
        for cls in order:
            i, j = edges[cls, 0], edges[cls, 1]
            d = X[j] - X[i]
            L = np.linalg.norm(d, axis=1)
            wsum = inv_mass[i] + inv_mass[j]
            ok = (wsum > 0) & (L > 1e-12)
            s = np.where(ok, (L - rest[cls]) / np.where(ok, L * wsum, 1.0), 0.0)[:, None] * d
            X[i] += inv_mass[i, None] * s
            X[j] -= inv_mass[j, None] * s
        return X

    for it in range(iterations):
        if it < iterations - 1 or not symmetric_last:
            X = sweep(X, classes)
        else:  # the last: both class orders from the same start, averaged
            X = 0.5 * (sweep(X, classes) + sweep(X, classes[::-1]))
        nn = tree.query(X, k=k)[1].reshape(len(X), k)
        nb = cloud[nn]
        c = nb - nb.mean(axis=1, keepdims=True)
        lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
        proj = np.einsum("nij,nj,nkj->nik", vec, lam >= 0.1 * lam[:, -1:], vec)
        p = cloud[nn[:, 0]]
        off = np.einsum("nj,nij->ni", X - p, proj)
        n = np.linalg.norm(off, axis=1, keepdims=True)
        X = p + off * (params.surface_slide_m / np.maximum(n, params.surface_slide_m))
        soft = anchor_idx[~hard]
        X[soft] += anchor_weight[~hard, None] * (anchor_pos[~hard] - X[soft])
        X[anchor_idx[hard]] = anchor_pos[hard]
    return X


def _cloth_problem(seed: int) -> tuple[np.ndarray, ...]:
    """A 6 x 6 grid over a bent, noisy 0.3 m sheet of points, warm-started off it."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.0, 0.3, (3000, 2))
    cloud = np.stack([uv[:, 0], uv[:, 1], 0.05 * np.sin(8 * uv[:, 0])], axis=1) + rng.normal(0, 0.001, (3000, 3))
    edges, rest = grid_topology(6, 6, 0.06, 0.06)
    g = np.linspace(0.0, 0.3, 6)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    X0 = np.stack([gx.ravel(), gy.ravel(), 0.05 * np.sin(8 * gx.ravel())], axis=1) + rng.normal(0, 0.01, (36, 3))
    return X0, edges, rest, cloud


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_iterations_equal_numpy_reference(seed):
    X0, edges, rest, cloud = _cloth_problem(seed)
    idx = np.array([0, 5, 30])
    pos = X0[idx] + 0.01
    weight = np.array([1.0, 1.0, 0.3])  # two hard anchors, one soft
    want = _reference_solve(X0, edges, rest, idx, pos, cloud, 30, P, weight)
    got = solve_keypoints(X0, edges, rest, idx, pos, cloud, 30, P, anchor_weight=weight)
    assert np.abs(got - want).max() < 1e-12
    # a prebuilt tree gives the same, and the warm start is not modified
    X0_copy = X0.copy()
    assert np.array_equal(solve_keypoints(X0, edges, rest, idx, pos, cKDTree(cloud), 30, P, anchor_weight=weight), got)
    assert np.array_equal(X0, X0_copy)


@pytest.mark.parametrize("seed", [0, 1])
def test_symmetric_last_sweep_equals_reference_and_spreads_a_chains_residual(seed):
    """With symmetric_last the compiled solve still equals the numpy reference; on a rope pulled onto a cloud
    shorter than its rest lengths, one sweep order leaves the compression on every other edge, the averaged
    last sweep shares it between neighbouring edges."""
    X0, edges, rest, cloud = _cloth_problem(seed)
    idx, pos, weight = np.array([0, 5]), X0[[0, 5]] + 0.01, np.ones(2)
    want = _reference_solve(X0, edges, rest, idx, pos, cloud, 30, P, weight, symmetric_last=True)
    got = solve_keypoints(X0, edges, rest, idx, pos, cloud, 30, P, anchor_weight=weight, symmetric_last=True)
    assert np.abs(got - want).max() < 1e-12

    rng = np.random.default_rng(seed)
    N = 20
    chain = np.stack([np.arange(N - 1), np.arange(1, N)], axis=1)
    crest = np.full(N - 1, 0.05)  # 0.95 m of rest lengths
    xs = rng.uniform(0.0, 0.9, 3000)  # a rope 0.9 m long, held at both ends
    rope = np.stack([xs, 0.004 * np.cos(40 * xs), np.zeros_like(xs)], axis=1)
    X = np.stack([np.linspace(0.0, 0.9, N), np.zeros(N), np.zeros(N)], axis=1)
    ends, at = np.array([0, N - 1]), X[[0, N - 1]]

    def residual(symmetric: bool) -> np.ndarray:
        Y = solve_keypoints(X, chain, crest, ends, at, rope, 30, P, symmetric_last=symmetric)
        return np.linalg.norm(Y[chain[:, 1]] - Y[chain[:, 0]], axis=1) - crest

    plain, even = residual(False), residual(True)
    rms = lambda r: float(np.sqrt(np.mean(r**2)))  # noqa: E731
    assert max(rms(plain[::2]), rms(plain[1::2])) > 1.5 * min(rms(plain[::2]), rms(plain[1::2]))  # one class bears it
    assert rms(even) < rms(plain)
    assert max(rms(even[::2]), rms(even[1::2])) < 1.5 * min(rms(even[::2]), rms(even[1::2]))


def test_compiled_nearest_point_projection_and_far_moves():
    """k = 1 puts keypoints on cloud points; a warm start far from where it ends (the candidate points gathered
    again as keypoints travel) still finds the exact nearest points."""
    X0, edges, rest, cloud = _cloth_problem(3)
    X0 = X0 + np.array([0.0, 0.0, 0.2])  # 20 cm above the sheet
    none, nowhere = np.zeros(0, int), np.zeros((0, 3))
    got = solve_keypoints(X0, edges, rest, none, nowhere, cloud, 40, dataclasses.replace(P, surface_k=1))
    d, _ = cKDTree(cloud).query(got)
    assert d.max() < 1e-15
    far = solve_keypoints(X0, edges, rest, none, nowhere, cloud, 40, P)
    ref = _reference_solve(X0, edges, rest, none, nowhere, cloud, 40, P, np.zeros(0))
    assert np.abs(far - ref).max() < 1e-12


def test_compiled_iterations_without_cloud_or_edges():
    X0, edges, rest, cloud = _cloth_problem(4)
    no_cloud = solve_keypoints(X0, edges, rest, [0], X0[:1], np.zeros((0, 3)), 50, P)
    assert np.abs(np.linalg.norm(no_cloud[edges[:, 0]] - no_cloud[edges[:, 1]], axis=1) - rest).max() < 1e-3
    no_edges = solve_keypoints(X0, np.zeros((0, 2), int), np.zeros(0), [0], X0[:1], cloud, 5, P)
    assert cKDTree(cloud).query(no_edges[1:])[0].max() < P.surface_slide_m + 1e-9
    one_point = solve_keypoints(X0, edges, rest, [], np.zeros((0, 3)), cloud[:1], 3, P)
    assert np.isfinite(one_point).all()


def _reference_dbscan(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """DBSCAN from a KD-tree pair query and scipy's connected components; a border point takes its nearest core
    point's cluster; clusters numbered by their first core point."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(points)
    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    core = np.bincount(pairs.ravel(), minlength=n) + 1 >= min_points
    cc = pairs[core[pairs[:, 0]] & core[pairs[:, 1]]]
    _, comp = connected_components(coo_matrix((np.ones(len(cc)), (cc[:, 0], cc[:, 1])), shape=(n, n)), directed=False)
    lab = np.full(n, -1)
    first = {}
    for i in np.flatnonzero(core):
        lab[i] = first.setdefault(comp[i], len(first))
    tree = cKDTree(points[core])
    for i in np.flatnonzero(~core):
        d, j = tree.query(points[i])
        if d <= eps:
            lab[i] = lab[np.flatnonzero(core)[j]]
    return lab


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_compiled_dbscan_equals_reference(seed):
    """Blobs, lines and noise at several scales (negative coordinates, one flat axis, points on cell borders)."""
    rng = np.random.default_rng(seed)
    parts = [rng.normal(c, 0.01, (300, 3)) for c in rng.uniform(-0.3, 0.3, (4, 3))]
    parts.append(np.stack([np.linspace(-0.2, 0.2, 60), np.zeros(60), np.zeros(60)], axis=1))  # 6.8 mm apart
    parts.append(rng.uniform(-0.5, 0.5, (400, 3)))
    parts.append(0.015 * rng.integers(-20, 20, (200, 3)).astype(float))  # on the eps grid's cell borders
    pts = np.concatenate(parts)
    for eps, mp in ((0.015, 3), (0.008, 5), (0.03, 1)):
        got = dbscan_labels(pts, eps, mp)
        np.testing.assert_array_equal(got, _reference_dbscan(pts, eps, mp))
    assert dbscan_labels(np.zeros((0, 3)), 0.015, 3).shape == (0,)
    assert dbscan_labels(np.zeros((1, 3)), 0.015, 1).tolist() == [0]


def test_compiled_searches_equal_kd_tree_queries():
    """near_any and nearest against cKDTree's distance_upper_bound (strict) and nearest-neighbour queries, with
    points far outside the references' extent and a single reference."""
    from tracking.kernels import near_any, nearest

    rng = np.random.default_rng(5)
    for n, m, r in ((4000, 300, 0.02), (3000, 3000, 0.015), (500, 1, 0.5)):
        P = np.concatenate([rng.normal(size=(n, 3)) * 0.2, rng.normal(size=(20, 3)) + 5.0])
        R = rng.normal(size=(m, 3)) * 0.2
        d, i = cKDTree(R).query(P)
        np.testing.assert_array_equal(near_any(P, R, r), d < r)
        got_d, got_i = nearest(P, R)
        np.testing.assert_array_equal(got_d, d)
        np.testing.assert_array_equal(got_i, i)
    on_border = np.array([[0.0, 0.0, 0.0]])
    assert not near_any(on_border, np.array([[0.5, 0.0, 0.0]]), 0.5)[0]  # exactly r away: not closer than r


def test_compiled_voxel_centroids_equal_numpy():
    from tracking.segmentation import voxel_groups

    rng = np.random.default_rng(6)
    for n in (1, 7, 5000):
        P = rng.normal(size=(n, 3)) * 0.1 - 0.3
        keys = np.floor(P / 0.009).astype(np.int64)
        _, inv = np.unique([tuple(k) for k in keys], axis=0, return_inverse=True)
        inv = inv.ravel()
        cnt = np.bincount(inv)
        cen = np.stack([np.bincount(inv, P[:, k]) for k in range(3)], axis=1) / cnt[:, None]
        got_cen, got_inv = voxel_groups(P, 0.009)
        np.testing.assert_array_equal(got_inv, inv)
        np.testing.assert_array_equal(got_cen, cen)
