"""Algorithm 1: Gauss-Seidel iterative projection (edge lengths, point cloud, anchors).

Edges are greedily coloured so that no two edges of a colour class share a vertex, and swept class by
class; the iterations run compiled (``tracking.kernels.solve_iterations``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from tracking.kernels import solve_iterations
from tracking.params import TrackingParams


def edge_colouring(edges: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Greedy edge colouring of edges (E, 2) int -> list of index arrays into edges, one per colour.

    No two edges in a class share a vertex (at most 2 * max_degree - 1 classes).
    """
    used: list[set[int]] = [set() for _ in range(n_vertices)]
    colour = np.empty(len(edges), np.int64)
    for e, (i, j) in enumerate(np.asarray(edges, np.int64)):
        taken = used[i] | used[j]
        c = 0
        while c in taken:
            c += 1
        colour[e] = c
        used[i].add(c)
        used[j].add(c)
    if len(edges) == 0:
        return []
    return [np.nonzero(colour == c)[0] for c in range(int(colour.max()) + 1)]


def solve_keypoints(
    X0: np.ndarray,
    edges: np.ndarray,
    rest: np.ndarray,
    anchor_idx: np.ndarray,
    anchor_pos: np.ndarray,
    cloud: np.ndarray | cKDTree,
    iterations: int,
    params: TrackingParams,
    classes: list[np.ndarray] | None = None,
    anchor_weight: np.ndarray | None = None,
    hidden: np.ndarray | None = None,
    bend: np.ndarray | None = None,
    symmetric_last: bool = False,
) -> np.ndarray:
    """Solve problem (1) by Algorithm 1 from the warm start X0 (N, 3) m.

    edges (E, 2) int, rest (E,) m; anchor_idx (A,) int fixed at anchor_pos (A, 3) m; cloud (M, 3) m
    segmented points or a prebuilt cKDTree of them. anchor_weight (A,) in (0, 1]: 1 (default) fixes an
    anchor; below 1 the anchor's keypoint stays free in the edge and cloud projections and is moved
    that fraction of the way to its anchor after each iteration (a measured anchor with noise, which a
    hard constraint passes on to its edges). The ablation switches of ``params`` turn the anchor, edge
    and cloud projections off. hidden (N,) bool: keypoints out of sight, projected onto the cloud only
    within ``params.hidden_reach`` of the median rest length of it and, with their chain neighbours bend (N, 4)
    int64 (``chain_neighbours``), drawn ``params.hidden_bend`` of the way towards a smooth curve each sweep (a rope
    is not kinked where nobody sees it), and never onto a point beyond ``1 + params.hidden_stretch`` times its edge
    from a fixed neighbour (the hand that holds the end next to it). symmetric_last: the last iteration sweeps the
    edge classes in order and in reverse order from the same start and averages the two (a 1D object's chain:
    one order alone leaves the residual on every other edge, twice the error of the others on the test bed's
    ropes; on a cloth's grid it measured no better). Returns X (N, 3) float64, metres, world frame.
    """
    X = np.array(X0, np.float64, copy=True)
    N = len(X)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    rest = np.asarray(rest, np.float64)
    anchor_idx = np.asarray(anchor_idx, np.int64).reshape(-1)
    anchor_pos = np.asarray(anchor_pos, np.float64).reshape(-1, 3)
    use_anchors = params.use_anchors and len(anchor_idx) > 0
    w = np.ones(len(anchor_idx)) if anchor_weight is None else np.asarray(anchor_weight, np.float64).reshape(-1)
    hard = w >= 1.0
    hard_idx, hard_pos = anchor_idx[hard], anchor_pos[hard]
    soft_idx, soft_pos, soft_w = anchor_idx[~hard], anchor_pos[~hard], w[~hard]
    inv_mass = np.ones(N)
    if use_anchors:
        inv_mass[hard_idx] = 0.0
        X[anchor_idx] = anchor_pos
    if classes is None:
        classes = edge_colouring(edges, N)
    order = np.concatenate(classes) if params.use_edge_projection and len(classes) else np.zeros(0, np.int64)
    first, second = edges[order, 0], edges[order, 1]
    pts = np.zeros((0, 3))
    if params.use_cloud_projection:
        pts = cloud.data if isinstance(cloud, cKDTree) else np.asarray(cloud, np.float64).reshape(-1, 3)
    if not use_anchors:
        soft_idx, hard_idx = soft_idx[:0], hard_idx[:0]
    solve_iterations(
        X, first, second, inv_mass[first], inv_mass[second], rest[order], np.ascontiguousarray(pts, np.float64),
        int(params.surface_k), float(params.surface_slide_m),
        soft_idx, np.ascontiguousarray(soft_pos), soft_w, hard_idx, np.ascontiguousarray(hard_pos), int(iterations),
        np.zeros(N, np.bool_) if hidden is None else np.ascontiguousarray(hidden, np.bool_),
        params.hidden_reach * float(np.median(rest)) if len(rest) else 0.0,
        np.full((0, 4), -1, np.int64) if bend is None else np.ascontiguousarray(bend, np.int64),
        float(params.hidden_bend),
        *(fixed_neighbours(edges, rest, hard_idx, N, 1.0 + params.hidden_stretch) if hidden is not None
          else (np.zeros(0, np.int64), np.zeros(0))),  # read for hidden keypoints only
        bool(symmetric_last),
    )
    return X


def relax_hidden(
    X: np.ndarray, edges: np.ndarray, rest: np.ndarray, movable: np.ndarray, sweeps: int, params: TrackingParams,
    classes: list[np.ndarray] | None = None,
) -> np.ndarray:
    """Keypoints X (N, 3) m after ``sweeps`` Gauss-Seidel sweeps of the edge projections (edges (E, 2), rest (E,) m)
    that move only the movable (N,) bool ones: the others are fixed where they are, no cloud, no anchors.
    Returns (N, 3) float64 m (X itself when nothing can move)."""
    movable = np.asarray(movable, bool)
    if sweeps <= 0 or not movable.any():
        return X
    fixed = np.flatnonzero(~movable)
    only_edges = replace(params, use_anchors=True, use_cloud_projection=False)
    return solve_keypoints(X, edges, rest, fixed, X[fixed], np.zeros((0, 3)), sweeps, only_edges, classes)


def fixed_neighbours(
    edges: np.ndarray, rest: np.ndarray, fixed: np.ndarray, n: int, stretch: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each of n keypoints' fixed neighbour along edges (E, 2), as its place in fixed ((F,) int64 keypoints), (n,)
    int64 (-1: none), and how far from it the keypoint may be, m (n,): that edge's rest (E,) m times stretch."""
    tether, reach = np.full(n, -1, np.int64), np.zeros(n)
    slot = np.full(n, -1, np.int64)
    slot[fixed] = np.arange(len(fixed))
    for a, b in ((0, 1), (1, 0)):
        sel = (slot[edges[:, b]] >= 0) & (slot[edges[:, a]] < 0)
        tether[edges[sel, a]] = slot[edges[sel, b]]
        reach[edges[sel, a]] = stretch * rest[sel]
    return tether, reach


def chain_neighbours(chains: list[np.ndarray], n_keypoints: int) -> np.ndarray:
    """(N, 4) int64: each keypoint's neighbours two and one back and one and two on along its chain (chains:
    keypoint index arrays, node to node), -1 where there is none; a keypoint on several chains (a junction) has
    none at all (no one smooth curve runs through it)."""
    out = np.full((n_keypoints, 4), -1, np.int64)
    seen = np.zeros(n_keypoints, np.int64)
    for ch in chains:
        ch = np.asarray(ch, np.int64)
        seen[ch] += 1
        pad = np.concatenate([[-1, -1], ch, [-1, -1]])
        out[ch] = np.stack([pad[:-4], pad[1:-3], pad[3:-1], pad[4:]], axis=1)
    out[seen > 1] = -1
    return out


def chain_tangents(X: np.ndarray, chains: list[np.ndarray]) -> np.ndarray:
    """Unit tangents (N, 3) of keypoints X (N, 3) m along their chains (index arrays, node to node):
    central differences inside a chain, one-sided at its ends (a keypoint on several chains, e.g. a
    junction, keeps the last one's)."""
    T = np.zeros_like(X)
    for ch in chains:
        if len(ch) >= 2:
            T[ch] = np.gradient(X[ch], axis=0)
    return T / np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)


def centre_on_ridge(
    X: np.ndarray,
    tangents: np.ndarray,
    tree: cKDTree,
    eye: np.ndarray,
    radius_m: float,
    k: int = 96,
    band_m: float = 0.003,
) -> np.ndarray:
    """Move points X (n, 3) m on a tube's visible skin to its ridge (the line nearest the camera).

    tangents: (n, 3) unit tube directions; tree: cKDTree of the cloud (m); eye: (3,) camera centre, m.
    The cloud within ``radius_m`` across and ``radius_m / 2`` along the tube (up to k points) is its
    cross-section there: across the tube (perpendicular to the tangent and the line of sight) a
    point goes to the middle of that section (between its 10th and 90th percentiles), along the
    line of sight to the median of the section's points within ``band_m`` of that middle. A
    keypoint's place across the tube is otherwise undetermined (edge lengths along the tube do not
    fix it) and the noise of the one point it was projected on decides it. Returns (n, 3) float64 m.
    """
    X = np.array(X, np.float64)
    n = len(X)
    if n == 0 or tree.n == 0:
        return X
    k = min(k, tree.n)
    d, nn = tree.query(X, k=k, distance_upper_bound=float(np.hypot(radius_m, 0.5 * radius_m)))
    d, nn = d.reshape(n, k), nn.reshape(n, k)
    rel = tree.data[np.minimum(nn, tree.n - 1)] - X[:, None, :]  # (n, k, 3)
    view = X - eye
    lat = np.cross(tangents, view)
    lat /= np.maximum(np.linalg.norm(lat, axis=1, keepdims=True), 1e-12)
    dep = view - np.einsum("nk,nk->n", view, tangents)[:, None] * tangents
    dep /= np.maximum(np.linalg.norm(dep, axis=1, keepdims=True), 1e-12)
    a = np.einsum("nki,ni->nk", rel, lat)  # across, m
    sec = np.isfinite(d) & (np.abs(np.einsum("nki,ni->nk", rel, tangents)) <= 0.5 * radius_m)
    sec &= np.abs(a) <= radius_m
    has = sec.sum(axis=1) >= 3
    across = np.zeros(n)
    if has.any():
        q = np.nanpercentile(np.where(sec[has], a[has], np.nan), [10.0, 90.0], axis=1)
        across[has] = 0.5 * (q[0] + q[1])
    band = sec & (np.abs(a - across[:, None]) <= band_m)
    z = np.where(band, np.einsum("nki,ni->nk", rel, dep), np.nan)
    on = has & band.any(axis=1)
    along_view = np.zeros(n)
    if on.any():
        along_view[on] = np.nanmedian(z[on], axis=1)
    return X + across[:, None] * lat + along_view[:, None] * dep


def tube_mean(
    X: np.ndarray, tangents: np.ndarray, tree: cKDTree, half_m: float, reach_m: float, use: np.ndarray,
) -> np.ndarray:
    """Points X (N, 3) m on a tube's visible skin, those flagged in use (N,) bool, moved across the tube to the
    mean of its slice there: the cloud's points (``tree``, m) within half_m of the point along its unit tangent
    (tangents (N, 3)) and reach_m across it, at least three. Only the part of the move perpendicular to the
    tangent is taken: a keypoint keeps its place along the tube. The solve leaves a keypoint on one cloud point,
    with that point's depth noise and wherever across the tube its edges pulled it; the slice's mean is the
    middle of the seen skin with that noise averaged over the slice. Returns (N, 3) float64 m."""
    X = np.array(X, np.float64)
    idx = np.flatnonzero(np.asarray(use, bool))
    if len(idx) == 0 or tree.n < 3:
        return X
    near = tree.query_ball_point(X[idx], float(np.hypot(half_m, reach_m)))
    counts = np.array([len(n) for n in near])
    owner = np.repeat(np.arange(len(idx)), counts)  # (M,) which keypoint each candidate point is near
    rel = tree.data[np.concatenate(near).astype(np.int64)] - X[idx][owner]  # (M, 3)
    t = tangents[idx][owner]
    along = np.einsum("mj,mj->m", rel, t)
    across = rel - along[:, None] * t
    take = (np.abs(along) <= half_m) & (np.linalg.norm(across, axis=1) <= reach_m)
    n = np.bincount(owner[take], minlength=len(idx))
    total = np.stack([np.bincount(owner[take], across[take, i], minlength=len(idx)) for i in range(3)], axis=1)
    ok = n >= 3
    X[idx[ok]] += total[ok] / n[ok, None]
    return X


def shorten_stretched(
    X: np.ndarray, edges: np.ndarray, rest: np.ndarray, movable: np.ndarray, sweeps: int
) -> np.ndarray:
    """Keypoints X (N, 3) m after ``sweeps`` Jacobi sweeps that shorten each edge (edges (E, 2)) longer than its
    rest length (rest (E,) m) back to it, moving only the movable (N,) bool keypoints (each by the mean of its
    edges' corrections); a shorter edge is left as it is. A cloth does not stretch but folds: between two
    keypoints a chord longer than the cloth is wrong, a shorter one a fold the grid cannot show.
    Returns (N, 3) float64 m."""
    Y = np.array(X, np.float64)
    w = np.asarray(movable, np.float64)
    i, j = np.asarray(edges, np.int64).T
    for _ in range(sweeps):
        d = Y[j] - Y[i]
        L = np.linalg.norm(d, axis=1)
        over = np.maximum(L - rest, 0.0) / np.maximum(L, 1e-12)  # (E,) the fraction of each edge to take off
        wsum = w[i] + w[j]
        f = (over / np.where(wsum > 0, wsum, 1.0))[:, None] * d  # (E, 3)
        move = np.zeros_like(Y)
        count = np.zeros(len(Y))
        np.add.at(move, i, w[i, None] * f)
        np.add.at(move, j, -w[j, None] * f)
        np.add.at(count, i, (over > 0) * w[i])
        np.add.at(count, j, (over > 0) * w[j])
        Y += move / np.maximum(count, 1.0)[:, None]
    return Y


def onto_local_plane(X: np.ndarray, tree: cKDTree, use: np.ndarray, k: int = 8) -> np.ndarray:
    """Points X (N, 3) m, those flagged in use (N,) bool, moved along the normal of the plane through their k
    nearest cloud points (``tree``, m; the least-variance direction) onto that plane: back onto the seen surface,
    wherever along it they are. Returns (N, 3) float64 m."""
    X = np.array(X, np.float64)
    idx = np.flatnonzero(np.asarray(use, bool))
    if len(idx) == 0 or tree.n < k:
        return X
    _, nn = tree.query(X[idx], k=k)
    nb = tree.data[nn]  # (S, k, 3)
    c = nb.mean(axis=1)
    d = nb - c[:, None, :]
    normal = np.linalg.eigh(np.einsum("ski,skj->sij", d, d))[1][:, :, 0]  # (S, 3) unit, smallest eigenvalue's
    X[idx] -= np.einsum("si,si->s", X[idx] - c, normal)[:, None] * normal
    return X


def adjacency(edges: np.ndarray, n_keypoints: int, self_loops: bool = False) -> np.ndarray:
    """(N, N) bool: which keypoints edges (E, 2) join; with self_loops each keypoint is its own neighbour too."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    adj = np.eye(n_keypoints, dtype=bool) if self_loops else np.zeros((n_keypoints, n_keypoints), bool)
    adj[edges[:, 0], edges[:, 1]] = adj[edges[:, 1], edges[:, 0]] = True
    return adj


def hop_neighbours(edges: np.ndarray, n_keypoints: int, start: int, hops: int) -> np.ndarray:
    """The keypoints (K,) int64 within ``hops`` edges (E, 2) of keypoint ``start``, itself excluded, nearest
    first (breadth-first over the graph)."""
    adj = adjacency(edges, n_keypoints)
    seen = np.zeros(n_keypoints, bool)
    seen[start] = True
    front, out = np.array([start]), []
    for _ in range(hops):
        front = np.flatnonzero(adj[front].any(axis=0) & ~seen)
        seen[front] = True
        out.append(front)
    return np.concatenate(out) if out else np.zeros(0, np.int64)
