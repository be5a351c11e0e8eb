"""A cloth grid's tangles: detection (cells folded over themselves) and repair (a grid re-lifted from the
frame's contour in the track's own correspondence); a 1D chain's folds: detection (the chain turns back on
itself at a keypoint) and repair (the chain laid out again along itself without the fold).

A tracked grid tangles when the solver folds a cell over itself, a corner pulled across the opposite edge (a
bow-tie): plain in a picture, hidden in the mean edge error. A real cloth's 6x6 grid seldom has one (the
test bed's true surface sampled 6x6: in 4 of 180 frames of a crumpled cloth, none in four other clips; the
project's simulator: in 6 of 180 frames, as its fold closes). Two neighbouring cells facing apart are not a
tangle: those of a real fold face up to ~165 degrees apart.

A rope's keypoint chain folds when a fast move or a part hidden under a hand puts two keypoints the wrong way
round along the rope: each still lies on it, so the solver keeps the zig-zag, and the rest of the chain is
stretched to make up the length the fold takes. A true centreline sampled at the keypoint spacing turns by at
most ~57 degrees at a keypoint over the test bed's rope clips; a folded chain turns back by ~180.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tracking.anchors import contour_3d, lift_grid, skeleton_3d
from tracking.geometry import cell_samples
from tracking.init import Topology, polyline_arc
from tracking.metrics import edge_lengths
from tracking.params import TrackingParams
from tracking.solver import relax_hidden


def cell_corner_normals(X: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Unit normals (rows-1, cols-1, 4, 3) of each cell's four corner triangles; X (rows*cols, 3) m row-major.

    Corner k's triangle is the corner and its two neighbours in the cell, all taken the same way round, so a
    flat or gently curved cell has four nearly equal normals and a bow-tie has opposed ones."""
    G = X.reshape(rows, cols, 3)
    a, b, c, d = G[:-1, :-1], G[:-1, 1:], G[1:, :-1], G[1:, 1:]
    n = np.stack([np.cross(b - a, c - a), np.cross(d - b, a - b), np.cross(c - d, b - d), np.cross(a - c, d - c)], 2)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def tangled_cells(X: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Cells (rows-1, cols-1) bool folded over themselves: a corner triangle facing against its cell's mean
    normal (a bow-tie). X: (rows*cols, 3) m."""
    u = cell_corner_normals(X, rows, cols)
    m = u.sum(axis=2)
    m /= np.maximum(np.linalg.norm(m, axis=-1, keepdims=True), 1e-12)
    return (np.einsum("ijkc,ijc->ijk", u, m) < 0).any(axis=2)


def grid_symmetries(rows: int, cols: int) -> list[np.ndarray]:
    """Index permutations (rows*cols,) of a row-major grid onto itself: the identity, flips and half turn, and
    for a square grid the quarter turns and transposes too (the ways a re-detected grid can be laid)."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    out = [idx, idx[::-1], idx[:, ::-1], idx[::-1, ::-1]]
    if rows == cols:
        out += [idx.T, idx.T[::-1], idx.T[:, ::-1], idx.T[::-1, ::-1]]
    return [p.ravel() for p in out]


def relift_grid(
    X_prev: np.ndarray,
    topology: Topology,
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    held: np.ndarray | None = None,
) -> np.ndarray | None:
    """A fresh grid (N, 3) m on the cloud (M, 3) m, laid like the track's grid X_prev (N, 3) m.

    The frame's contour gives four corners, sides and a lifted Coons grid (as at initialisation; held (H, 3) m:
    the closed grippers' TCPs pick the held corners); of the grid's symmetries, the one nearest X_prev keeps
    every keypoint's identity. None when the cloud has no usable contour, or when the fresh grid's edges add up
    to more than ``params.relift_span_tol`` away from the rest lengths: the contour does not outline the cloth
    (a fold or an arm hides part of it, or it takes in more than the cloth) and a grid spread over it would
    flatten a fold or stretch the cloth."""
    assert topology.grid_shape is not None
    rows, cols = topology.grid_shape
    ct = contour_3d(cloud, K, T_world_cam, params, held)
    if ct is None:
        return None
    X0 = lift_grid(ct, cloud, rows, cols)
    span = edge_lengths(X0, topology.edges).sum() / topology.rest.sum()
    if abs(span - 1.0) > params.relift_span_tol:
        return None
    syms = grid_symmetries(rows, cols)
    costs = [float(np.linalg.norm(X0[p] - X_prev, axis=1).sum()) for p in syms]
    X = X0[syms[int(np.argmin(costs))]]
    if held is not None and len(held):  # a held corner is at its gripper
        corners = np.array([0, cols - 1, (rows - 1) * cols, rows * cols - 1])
        hp = np.asarray(held, np.float64).reshape(-1, 3)
        C = np.linalg.norm(hp[:, None, :] - X[corners][None, :, :], axis=2)
        r, k = linear_sum_assignment(C)
        ok = C[r, k] <= params.grasp_gate_m
        X[corners[k[ok]]] = hp[r[ok]]
    return X


def uncovered_share(X: np.ndarray, shape: tuple[int, int], cloud: np.ndarray, gap_m: float, max_points: int = 1500
                    ) -> float:
    """The share of the cloud (M, 3) m (up to max_points of it, evenly taken) farther than gap_m from the surface of
    the grid X (N, 3) m of shape (rows, cols), sampled four times a cell each way: the part of the sheet in sight
    that the grid leaves out (a grid folded onto one part of it; a right grid leaves under 0.05)."""
    pts = np.asarray(cloud, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(np.int64)]
    I, W = cell_samples(shape, 4)
    S = np.einsum("kj,kjc->kc", W, np.asarray(X, np.float64)[I])
    return float((cKDTree(S).query(pts)[0] > gap_m).mean())


def cover_cloud(
    X0: np.ndarray, topology: Topology, cloud: np.ndarray, fixed_idx: np.ndarray, fixed_pos: np.ndarray,
    params: TrackingParams, open_space: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """A grid X0 (N, 3) m registered to cover its frame's cloud (M, 3) m at its rest lengths, the keypoints
    fixed_idx (F,) int64 fixed at fixed_pos (F, 3) m (the held corners). Each of ``params.cover_iterations``
    iterations: a cloud point farther than ``params.cover_pull_gap`` median rest lengths from the grid's surface
    pulls the surface's nearest point ``params.cover_step`` of the way to it (shared among that point's four
    corners by their bilinear weights); each keypoint goes ``params.cover_keypoint_step`` of the way to its nearest
    cloud point (all of it where ``open_space`` says the camera sees through it); then ``params.cover_sweeps``
    edge sweeps. The solve projects keypoints onto the cloud and so keeps a grid folded onto the part of the sheet
    it covers; pulling from the uncovered cloud unfolds it. Returns (N, 3) float64 m."""
    assert topology.grid_shape is not None
    pts = np.asarray(cloud, np.float64).reshape(-1, 3)
    if len(pts) > params.cover_points:
        pts = pts[np.linspace(0, len(pts) - 1, params.cover_points).astype(np.int64)]
    X = np.array(X0, np.float64)
    if len(pts) == 0:
        return X
    tree = cKDTree(pts)
    fixed_idx = np.asarray(fixed_idx, np.int64)
    X[fixed_idx] = fixed_pos
    movable = np.ones(len(X), bool)
    movable[fixed_idx] = False
    I, W = cell_samples(topology.grid_shape, 4)
    gap = params.cover_pull_gap * float(np.median(topology.rest))
    for _ in range(params.cover_iterations):
        S = np.einsum("kj,kjc->kc", W, X[I])  # (K, 3) the grid's surface
        d, nn = cKDTree(S).query(pts)
        far = d > gap
        if far.any():
            f = pts[far] - S[nn[far]]  # (F, 3)
            wi, ii = W[nn[far]], I[nn[far]]  # (F, 4)
            pull = np.zeros_like(X)
            total = np.zeros(len(X))
            for j in range(4):
                np.add.at(pull, ii[:, j], wi[:, j, None] * f)
                np.add.at(total, ii[:, j], wi[:, j])
            m = (total > 1e-9) & movable
            X[m] += params.cover_step * pull[m] / total[m, None]
        step = np.full(len(X), params.cover_keypoint_step)
        if open_space is not None:
            step[open_space(X)] = 1.0
        nk = tree.query(X)[1]
        X[movable] += step[movable, None] * (pts[nk[movable]] - X[movable])
        X = relax_hidden(X, topology.edges, topology.rest, movable, params.cover_sweeps, params, topology.colours)
    return X


def hung_sheet(topology: Topology, fixed_idx: np.ndarray, fixed_pos: np.ndarray, cloud: np.ndarray
               ) -> np.ndarray | None:
    """A flat grid (N, 3) m hung from its two held keypoints, fixed_idx (2,) int64 at fixed_pos (2, 3) m, of one row
    or column (a cloth held by the two corners of one side): the other rows (columns) at their rest spacing in the
    direction, across the held side, in which the cloud (M, 3) m spreads most. A start for ``cover_cloud`` that
    knows nothing of the track's last frame; None unless the two held keypoints share a row or a column."""
    assert topology.grid_shape is not None
    rows, cols = topology.grid_shape
    if len(fixed_idx) != 2 or len(cloud) == 0:
        return None
    (ra, ca), (rb, cb) = (divmod(int(k), cols) for k in fixed_idx)
    if (ra == rb) == (ca == cb):  # not two corners of one side
        return None
    A, B = np.asarray(fixed_pos, np.float64).reshape(2, 3)
    e = topology.edges
    along_row = np.abs(e[:, 0] - e[:, 1]) == 1
    rest_col, rest_row = float(np.mean(topology.rest[along_row])), float(np.mean(topology.rest[~along_row]))
    u = (B - A) / max(float(np.linalg.norm(B - A)), 1e-9)
    pts = np.asarray(cloud, np.float64).reshape(-1, 3)
    q = pts - A
    q -= np.outer(q @ u, u)  # across the held side
    v = np.linalg.eigh(q.T @ q)[1][:, -1]
    if v @ q.mean(axis=0) < 0:
        v = -v
    r, c = np.divmod(np.arange(rows * cols), cols)
    if ra == rb:  # held along a row: the other rows hang below it
        s, off = (c - ca) / (cb - ca), np.abs(r - ra) * rest_row
    else:
        s, off = (r - ra) / (rb - ra), np.abs(c - ca) * rest_col
    return A + s[:, None] * (B - A) + off[:, None] * v


def chain_reversals(X: np.ndarray, chains: list[np.ndarray], cos_max: float) -> np.ndarray:
    """Interior keypoints (K,) int64 of the chains where a chain turns back on itself: the cosine between the
    edge in and the edge out is below cos_max. X: (N, 3) m; chains: keypoint index arrays, end to end."""
    out = []
    for c in chains:
        if len(c) < 3:
            continue
        d = np.diff(X[c], axis=0)
        n = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        cos = np.einsum("ij,ij->i", d[:-1], d[1:]) / (n[:-1] * n[1:])
        out.append(c[1:-1][cos < cos_max])
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def clip_tangles(X: np.ndarray, topology: Topology, cos_max: float) -> np.ndarray:
    """(T,) int64: how tangled each frame of keypoints X (T, N, 3) m is, as the tracker checks a frame: a grid's
    tangled cells (``tangled_cells``), a 1D object's keypoints where a chain turns back by more than cos_max allows
    (``chain_reversals``); 0 for a frame with a missing (NaN) keypoint. The offline output flags such frames
    (``trackdeform track``, an episode's final keypoints) instead of passing them on as good ones."""
    X = np.asarray(X, np.float64)
    out = np.zeros(len(X), np.int64)
    for t in np.flatnonzero(np.isfinite(X).all(axis=(1, 2))):
        if topology.grid_shape is not None:
            out[t] = int(tangled_cells(X[t], *topology.grid_shape).sum())
        else:
            out[t] = len(chain_reversals(X[t], topology.chains, cos_max))
    return out


def captured(X: np.ndarray, chains: list[np.ndarray], idx: np.ndarray, reach: float) -> np.ndarray:
    """Which keypoints idx (K,) int64 lie within reach (m) of a keypoint of a chain they are not on (K,) bool:
    taken by another part of the object (a branch's first keypoint lying on the main rope beside the junction).
    X: (N, 3) m; chains: keypoint index arrays, end to end (a junction is on each chain it ends)."""
    idx = np.asarray(idx, np.int64)
    out = np.zeros(len(idx), bool)
    for i, k in enumerate(idx.tolist()):
        own = [c for c in chains if k in c]
        others = [c for c in chains if k not in c]
        if not others:
            continue
        o = np.setdiff1d(np.concatenate(others), np.concatenate([*own, [k]]))  # a junction is on its own chain
        out[i] = len(o) > 0 and float(np.linalg.norm(X[o] - X[k], axis=1).min()) < reach
    return out


def chain_edges(topology: Topology) -> list[np.ndarray]:
    """Each chain's edges (len(chain) - 1,) int64, indices into topology.edges, edge by edge along it."""
    row = {(int(min(e)), int(max(e))): k for k, e in enumerate(np.asarray(topology.edges).tolist())}
    return [np.array([row[int(min(a, b)), int(max(a, b))] for a, b in zip(c[:-1], c[1:], strict=True)], np.int64)
            for c in topology.chains]


def chain_rests(topology: Topology) -> list[np.ndarray]:
    """Each chain's rest lengths (len(chain) - 1,) m, edge by edge along it."""
    return [np.asarray(topology.rest, np.float64)[e] for e in chain_edges(topology)]


def spaced_along(poly: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Points (len(r) + 1, 3) m along a polyline (M, 3) m from its start to its end, spaced in proportion to the
    rest lengths r (E,) m."""
    s = polyline_arc(poly)
    f = np.concatenate([[0.0], np.cumsum(r)]) / max(r.sum(), 1e-12)
    return np.stack([np.interp(f * s[-1], s, poly[:, i]) for i in range(3)], axis=1)


def respace_chains(
    X: np.ndarray, topology: Topology, cap_m: float, min_error_m: float = 0.0, fixed: np.ndarray | None = None,
) -> np.ndarray:
    """Keypoints (T, N, 3) m with each chain's inner keypoints moved along the chain's polyline to where
    ``spaced_along`` puts them (arcs in proportion to their rest lengths: the same curve, its edges evenly
    strained). A chain's end keypoints (tips, junctions) stay, and so do those flagged in fixed (N,) bool (a held
    keypoint: the chain is spaced on either side of it); each keypoint moves at most cap_m; a chain is left as it
    is in the frames where the RMS of its edges' length errors is at most min_error_m."""
    out = np.array(X, np.float64)
    for c, r in zip(topology.chains, chain_rests(topology), strict=True):
        if len(c) < 3:
            continue
        cut = [0, len(c) - 1] if fixed is None else [0, *np.flatnonzero(fixed[c[1:-1]]) + 1, len(c) - 1]
        for t in range(len(out)):
            P = out[t, c]  # (n, 3) this frame's chain
            if np.sqrt(np.mean((np.linalg.norm(np.diff(P, axis=0), axis=1) - r) ** 2)) <= min_error_m:
                continue  # evenly enough strained already
            move = np.zeros_like(P)
            for a, b in zip(cut[:-1], cut[1:], strict=True):
                if b - a >= 2:
                    move[a:b + 1] = spaced_along(P[a:b + 1], r[a:b]) - P[a:b + 1]
            move[cut] = 0.0
            norm = np.linalg.norm(move, axis=1, keepdims=True)
            out[t, c] = P + move * np.minimum(1.0, cap_m / np.maximum(norm, 1e-12))
    return out


def unfold_chains(
    X: np.ndarray, topology: Topology, cos_max: float, min_span: float, capture_m: float = 0.0,
) -> np.ndarray | None:
    """Keypoints X (N, 3) m with every chain that turns back on itself (``chain_reversals``) laid out again
    along itself with the fold taken out: the turned-back keypoints dropped from the chain's polyline (until it
    has none), the chain's keypoints spaced on what is left in proportion to their rest lengths, its ends kept.
    A warm start for the solver, which a fold holds in a local minimum: its keypoints lie on the object, in the
    wrong order, and the rest of the chain is stretched to make up the length the fold takes. A chain whose
    polyline without the fold spans less than min_span of its rest length is left as it is, unless a dropped
    keypoint was ``captured`` (within capture_m of another chain's keypoint). None: no fold."""
    out, changed = X.copy(), False
    for c, r in zip(topology.chains, chain_rests(topology), strict=True):
        if len(c) < 3:
            continue
        keep = np.ones(len(c), bool)
        while True:
            k = np.flatnonzero(keep)
            bad = chain_reversals(X, [c[k]], cos_max)
            if len(bad) == 0:
                break
            keep[np.isin(c, bad)] = False
        if keep.all():
            continue
        P = X[c[keep]]
        if polyline_arc(P)[-1] < min_span * r.sum() and not captured(X, topology.chains, c[~keep], capture_m).any():
            continue
        changed = True
        out[c] = spaced_along(P, r)
    return out if changed else None


def relift_chains(
    X_prev: np.ndarray,
    topology: Topology,
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    held: dict[int, np.ndarray] | None = None,
) -> np.ndarray | None:
    """Fresh chains (N, 3) m on the cloud (M, 3) m, laid like the track's X_prev (N, 3) m: a 1D object's
    skeleton (as at initialisation) whose leaves and junctions match the track's anchors one to one, each
    skeleton branch joining the two nodes a chain of the track joins.

    Of the node assignments that keep the kinds and the branches, the one nearest the track (a held keypoint's
    anchor: its gripper's TCP, held {keypoint: (3,) m}) keeps every keypoint's identity; each chain's keypoints
    are spaced along its branch in proportion to their rest lengths, a held end's branch continued to its TCP
    (the hand hides the last centimetres). None when the skeleton has other nodes or branches than the track,
    or when a branch's length is more than ``params.relift_span_tol`` away from its chain's rest length."""
    held = held or {}
    ai, ak = topology.anchor_idx, topology.anchor_kind
    sk = skeleton_3d(cloud, K, T_world_cam, params, all_components=False)
    if len(sk.nodes) != len(ai) or sorted(sk.kinds.tolist()) != sorted(ak.tolist()):
        return None
    links = {}
    for a, b, poly in sk.branches:
        key = (min(a, b), max(a, b))
        if key in links or a == b:
            return None  # two branches between two nodes (a loop): not the track's tree
        links[key] = poly if a < b else poly[::-1]
    pos = {int(k): held.get(int(k), X_prev[k]) for k in ai}
    slot = {int(k): i for i, k in enumerate(ai)}
    ends = [(int(c[0]), int(c[-1])) for c in topology.chains]
    best, best_cost = None, np.inf
    kinds = sorted(set(ak.tolist()))
    slots_of = [np.flatnonzero(ak == k) for k in kinds]  # the track's anchors of each kind
    nodes_of = [np.flatnonzero(sk.kinds == k) for k in kinds]  # the skeleton's nodes of that kind
    for choice in itertools.product(*(itertools.permutations(n.tolist()) for n in nodes_of)):
        perm = np.empty(len(ai), np.int64)
        for sl, nodes in zip(slots_of, choice, strict=True):
            perm[sl] = nodes
        if any((min(perm[slot[a]], perm[slot[b]]), max(perm[slot[a]], perm[slot[b]])) not in links for a, b in ends):
            continue
        cost = sum(float(np.linalg.norm(sk.nodes[perm[slot[k]]] - pos[k])) for k in pos)
        if cost < best_cost:
            best, best_cost = perm, cost
    if best is None or len(links) != len(ends):
        return None
    out = X_prev.copy()
    for c, r, (a, b) in zip(topology.chains, chain_rests(topology), ends, strict=True):
        na, nb = best[slot[a]], best[slot[b]]
        poly = links[(min(na, nb), max(na, nb))]
        poly = poly if na < nb else poly[::-1]
        if a in held:
            poly = np.concatenate([held[a][None], poly])
        if b in held:
            poly = np.concatenate([poly, held[b][None]])
        if abs(polyline_arc(poly)[-1] / r.sum() - 1.0) > params.relift_span_tol:
            return None
        out[c] = spaced_along(poly, r)
    return out


__all__ = [
    "captured", "cell_corner_normals", "chain_reversals", "grid_symmetries", "relift_chains", "relift_grid",
    "tangled_cells", "unfold_chains",
]
