"""Keypoint initialisation (paper section III-D): classify, anchors, warm start, topology, solve."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tracking.anchors import (
    boundary_indices,
    contour_3d,
    lift_grid,
    skeleton_3d,
)
from tracking.classify import ObjectClass, classify_object
from tracking.geometry import project_points
from tracking.metrics import edge_lengths
from tracking.params import TrackingParams
from tracking.skeleton import LEAF
from tracking.solver import centre_on_ridge, chain_tangents, edge_colouring, solve_keypoints


class InitialisationError(RuntimeError):
    """The segmented cloud does not support an initialisation (too small, no skeleton, no contour)."""


@dataclass(frozen=True)
class Topology:
    """Fixed object topology.

    kind: "1d" or "2d". edges: (E, 2) int64 keypoint pairs; rest: (E,) float64 target lengths, m.
    anchor_idx: (A,) int64 anchor keypoints; anchor_kind: (A,) int64 LEAF/JUNCTION/BOUNDARY/CORNER.
    chains: 1D: keypoint index arrays, one per branch, node to node; 2D: the grid rows.
    grid_shape: (rows, cols) for 2D, else None. colours: edge colour classes for the solver.
    reference: (E,) float64 m, the edge lengths of the keypoints as reported where they differ from rest (a 1D
    object's, reported in the middle of its tube, ``Tracker._reported``: rest is measured on the skin's points the
    solve holds its keypoints to), or None: rest. Written as the reference lengths (``reference_lengths``).
    """

    kind: str
    edges: np.ndarray
    rest: np.ndarray
    anchor_idx: np.ndarray
    anchor_kind: np.ndarray
    chains: list[np.ndarray]
    grid_shape: tuple[int, int] | None = None
    colours: list[np.ndarray] = field(default_factory=list, compare=False)
    reference: np.ndarray | None = field(default=None, compare=False)

    @property
    def reference_lengths(self) -> np.ndarray:
        """(E,) float64 m: the edge lengths the reported keypoints are held to (``reference``, else rest)."""
        return self.rest if self.reference is None else self.reference

    @property
    def n_keypoints(self) -> int:
        """Number of keypoints N."""
        return int(self.edges.max()) + 1 if len(self.edges) else len(self.anchor_idx)


@dataclass(frozen=True)
class Initialisation:
    """Initial keypoints (N, 3) float64 m world, their topology and the object classification."""

    keypoints: np.ndarray
    topology: Topology
    object_class: ObjectClass


def polyline_arc(poly: np.ndarray) -> np.ndarray:
    """Arc length (M,) m from the first point to each point of a polyline (M, 3) m."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])


def _dfs_branch_order(
    n_nodes: int, branches: list[tuple[int, int, np.ndarray]], root: int, node_key: np.ndarray | None = None
) -> list[tuple[int, bool]]:
    """Branches in depth-first order from root: (branch id, reversed?) so each starts at a visited node.

    node_key: (n_nodes,) float; at a node, its branches are taken in increasing key of their far
    node (e.g. the image column), so the order follows the geometry, not the skeleton's pixel order.
    """
    adj: list[list[int]] = [[] for _ in range(n_nodes)]
    for k, (a, b, _) in enumerate(branches):
        adj[a].append(k)
        adj[b].append(k)
    seen_node = np.zeros(n_nodes, bool)
    seen_br = np.zeros(len(branches), bool)
    order: list[tuple[int, bool]] = []
    stack = [root]
    seen_node[root] = True

    def far_key(k: int, u: int) -> tuple[float, int]:
        a, b, _ = branches[k]
        v = a if b == u else b
        return (float(node_key[v]) if node_key is not None else 0.0, k)

    while stack:
        u = stack.pop()
        for k in sorted(adj[u], key=lambda k: far_key(k, u)):
            if seen_br[k]:
                continue
            seen_br[k] = True
            a, b, _ = branches[k]
            rev = b == u
            v = a if rev else b
            order.append((k, rev))
            if not seen_node[v]:
                seen_node[v] = True
                stack.append(v)
    return order


def root_leaf(
    nodes: np.ndarray, kinds: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, hint: np.ndarray | None, gate_m: float
) -> int:
    """Node index (into nodes (K, 3) m) of keypoint 0 of a 1D object, chosen so repeated
    initialisations number the keypoints the same way: the leaf nearest ``hint`` (3,) m (the first
    gripper's TCP) when one lies within ``gate_m``, else the leftmost leaf in the image."""
    leaves = np.nonzero(kinds == LEAF)[0]
    if len(leaves) == 0:
        return 0
    if hint is not None:
        d = np.linalg.norm(nodes[leaves] - np.asarray(hint, np.float64).reshape(3), axis=1)
        if d.min() <= gate_m:
            return int(leaves[np.argmin(d)])
    uv, _ = project_points(nodes[leaves], K, T_world_cam)
    return int(leaves[np.argmin(uv[:, 0])])


def allocate_keypoints(
    lengths: np.ndarray, n_free: int, order: np.ndarray | None = None, tie: float = 0.25
) -> np.ndarray:
    """Free keypoints (B,) int per branch of lengths (B,) m so all edges are about equally long.

    Branch k gets e_k = m_k + 1 edges with e_k proportional to its length (largest remainder,
    at least one edge each) and sum(m_k) = n_free. Remainders within the same ``tie`` bin count
    as equal and go by ``order`` (B,) (e.g. the branches' traversal order): two branches of about
    the same length then get the same counts whatever the sensor noise.
    """
    B = len(lengths)
    total = n_free + B
    order = np.arange(B) if order is None else np.asarray(order)
    share = total * np.asarray(lengths, np.float64) / max(float(np.sum(lengths)), 1e-12)
    e = np.maximum(1, np.floor(share).astype(np.int64))
    while e.sum() < total:
        e[np.lexsort((order, -np.floor((share - e) / tie)))[0]] += 1
    while e.sum() > total and (e > 1).any():
        cand = np.nonzero(e > 1)[0]
        e[cand[int(np.argmin((share - e)[cand]))]] -= 1
    return e - 1


def snap_held_leaves(
    nodes: np.ndarray, kinds: np.ndarray, branches: list[tuple[int, int, np.ndarray]], held: np.ndarray,
    gate_m: float | np.ndarray,
) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """Move each leaf held by a closed gripper to the gripper's TCP (the end is between the fingers).

    nodes (K, 3) m, kinds (K,), branches (a, b, polyline (M, 3) m a -> b); held: (H, 3) m TCPs of
    the closed grippers; gate_m: m, one or (H,) one per TCP. The leaf nearest a TCP within its gate
    becomes the TCP and its branch's polyline is extended to it (the skeleton stops at the visible
    tip, short of the hidden end; the rest lengths then span the whole object, as tracking pins held
    keypoints at the TCPs).
    Returns the new (nodes, branches).
    """
    leaves = np.nonzero(kinds == LEAF)[0]
    held = np.asarray(held, np.float64).reshape(-1, 3)
    if len(leaves) == 0 or len(held) == 0:
        return nodes, branches
    C = np.linalg.norm(held[:, None, :] - nodes[leaves][None, :, :], axis=2)
    r, c = linear_sum_assignment(C)
    ok = C[r, c] <= np.broadcast_to(np.asarray(gate_m, np.float64), (len(held),))[r]
    nodes = nodes.copy()
    moved = dict(zip(leaves[c[ok]].tolist(), held[r[ok]], strict=True))
    out = []
    for a, b, poly in branches:
        if a in moved:
            poly = np.concatenate([moved[a][None], poly])
        if b in moved:
            poly = np.concatenate([poly, moved[b][None]])
        out.append((a, b, poly))
    for k, x in moved.items():
        nodes[k] = x
    return nodes, out


def space_branch(poly: np.ndarray, m: int, gaps: tuple[bool, bool] = (False, False)) -> tuple[np.ndarray, np.ndarray]:
    """The m free keypoints (m, 3) m along a branch's polyline poly (P, 3) m, start to end, and the rest lengths
    (m + 1,) m of the edges from its start node through them to its end node: evenly by arc length. Where an end
    was held across a gap the hand hides (gaps: start, end; the polyline's first or last segment is then the
    straight way from the seen tip to the TCP), that segment is an edge of its own from the seen tip, its chord
    its rest length: keypoints spread evenly over it would lie off the rope, which arcs into the fingers."""
    s = int(gaps[0] and m >= 1 and len(poly) > 2)
    e = int(gaps[1] and m - s >= 1 and len(poly) - s > 2)
    core = poly[s : len(poly) - e]
    arc = polyline_arc(core)
    n = m - s - e
    t = arc[-1] * np.arange(1, n + 1) / (n + 1)
    free = [core[:s], np.stack([np.interp(t, arc, core[:, i]) for i in range(3)], axis=1), core[len(core) - e :]]
    rest = [np.linalg.norm(poly[1] - poly[0], keepdims=True)[:s], np.full(n + 1, arc[-1] / (n + 1)),
            np.linalg.norm(poly[-1] - poly[-2], keepdims=True)[:e]]
    return np.concatenate(free).reshape(-1, 3), np.concatenate(rest)


def initialise_1d(
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    obj: ObjectClass,
    root_hint: np.ndarray | None = None,
    held: np.ndarray | None = None,
    held_gate: np.ndarray | None = None,
) -> Initialisation:
    """Initialise a 1D object (rope, branched rope) from its segmented cloud (N, 3) float64 m world.

    Anchors = skeleton leaves and junctions; each branch gets keypoints in proportion to its
    length (``allocate_keypoints``) and the warm start places them evenly along its skeleton
    (the paper's FPS warm start gives seed-dependent per-branch counts and spacings, which
    Gauss-Seidel evens out only slowly along a chain: repeated initialisations then disagree);
    edges chain each branch node to node; rest length of a branch = its 3D arc length / its edge count (but a
    gap the hand hides between a seen tip and the TCP that holds it, when longer than that spacing or than
    ``grasp_gate_m``, is one edge: ``space_branch``; a keypoint placed in it would be pulled onto the seen rope).
    Keypoint 0
    is the leaf at ``root_hint`` (3,) m or the image's leftmost (``root_leaf``); branches are
    numbered depth-first, leftmost (image) first at junctions. held: (H, 3) m TCPs of closed
    grippers: the ends they hold are placed there (``snap_held_leaves``; held_gate (H,) m: how far from each
    TCP its end may be seen, default ``grasp_gate_m``). The solved free keypoints
    are finally moved to the ridge of the tube's visible skin (``snap_to_ridge``): where across the
    tube a keypoint ends is otherwise set by depth noise (3 mm spread over camera seeds, 1.5 after).
    """
    sk = skeleton_3d(cloud, K, T_world_cam, params, all_components=False)
    if len(sk.branches) == 0:
        raise InitialisationError("no skeleton branch in the segmented cloud")
    nodes, kinds, branches = sk.nodes, sk.kinds, sk.branches
    seen = nodes
    if held is not None:
        gate = params.grasp_gate_m if held_gate is None else held_gate
        nodes, branches = snap_held_leaves(nodes, kinds, branches, held, gate)
    gap = np.linalg.norm(nodes - seen, axis=1)  # m: how far a held end was moved from its seen tip to its TCP
    Nn = len(nodes)
    n_free = max(0, params.n_keypoints_1d - Nn)
    polys = [p for _, _, p in branches]
    lengths = np.array([polyline_arc(p)[-1] for p in polys])
    root = root_leaf(nodes, kinds, K, T_world_cam, root_hint, 2.0 * params.grasp_gate_m)
    node_u = project_points(nodes, K, T_world_cam)[0][:, 0]
    dfs = _dfs_branch_order(Nn, branches, root, node_u)
    rank = np.empty(len(branches), np.int64)
    rank[[k for k, _ in dfs]] = np.arange(len(dfs))
    counts = allocate_keypoints(lengths, n_free, rank)
    X: list[np.ndarray] = [nodes[root]]
    node_kp = np.full(Nn, -1)
    node_kp[root] = 0
    edges: list[tuple[int, int]] = []
    rest: list[float] = []
    chains: list[np.ndarray] = []
    for k, rev in dfs:
        a, b, _ = branches[k]
        start, end = (b, a) if rev else (a, b)
        chain = [int(node_kp[start])]
        poly = polys[k][::-1] if rev else polys[k]
        # held across a gap the hand hides: a gap longer than the branch's spacing would put keypoints in it
        far = gap > min(params.grasp_gate_m, lengths[k] / (int(counts[k]) + 1))
        free, d = space_branch(poly, int(counts[k]), (bool(far[start]), bool(far[end])))
        for x in free:
            X.append(x)
            chain.append(len(X) - 1)
        if node_kp[end] < 0:
            X.append(nodes[end])
            node_kp[end] = len(X) - 1
        chain.append(int(node_kp[end]))
        edges += list(zip(chain[:-1], chain[1:], strict=True))
        rest += d.tolist()
        chains.append(np.array(chain, np.int64))
    Xa = np.array(X)
    E = np.array(edges, np.int64)
    anchor_idx = node_kp[node_kp >= 0]
    anchor_kind = kinds[node_kp >= 0]
    topo = Topology("1d", E, np.array(rest), anchor_idx, anchor_kind, chains, None, edge_colouring(E, len(Xa)))
    tree = cKDTree(cloud)
    Xs = solve_keypoints(
        Xa, E, topo.rest, anchor_idx, Xa[anchor_idx], tree, params.init_iterations, params, topo.colours,
        symmetric_last=True,
    )
    Xs = snap_to_ridge(Xs, topo, anchor_idx, tree, T_world_cam, params)
    return Initialisation(Xs, topo, obj)


def snap_to_ridge(
    X: np.ndarray, topology: Topology, fixed: np.ndarray, tree: cKDTree, T_world_cam: np.ndarray,
    params: TrackingParams,
) -> np.ndarray:
    """A 1D object's keypoints X (N, 3) m, except ``fixed`` (F,) (anchors, held ends), moved to the
    ridge of the tube's visible skin (``centre_on_ridge`` within ``params.ridge_radius_m``; 0: off).
    tree: cKDTree of the segmented cloud, m. Returns (N, 3) float64 m."""
    if params.ridge_radius_m <= 0 or topology.kind != "1d":
        return X
    free = np.ones(len(X), bool)
    free[np.asarray(fixed, np.int64)] = False
    out = X.copy()
    T = chain_tangents(X, topology.chains)
    out[free] = centre_on_ridge(X[free], T[free], tree, T_world_cam[:3, 3], params.ridge_radius_m)
    return out


def grid_topology(rows: int, cols: int, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """4-neighbour grid edges (E, 2) row-major and rest lengths (E,) m: dx along rows, dy along columns."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    h = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1)
    v = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1)
    return np.concatenate([h, v]), np.concatenate([np.full(len(h), dx), np.full(len(v), dy)])


def initialise_2d(
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    obj: ObjectClass,
    held: np.ndarray | None = None,
    held_gate: np.ndarray | None = None,
) -> Initialisation:
    """Initialise a rectangular 2D object (cloth) from its segmented cloud (N, 3) float64 m world.

    Contour -> four corners -> sides; a rows x cols Coons (bilinear) grid bounded by the sides
    (each resampled evenly by 3D arc length), lifted by the nearest cloud point; boundary nodes are
    anchors. Rest length of each edge = its length in that lifted grid: a draped cloth is folded
    and wrinkled between its sides, so one spacing per direction from the side lengths cannot fit
    it (its edges then disagree by ~10 mm RMS from the start; measured across the cloud surface
    instead of as chords, the rest lengths exceed what chords between keypoints on a folded
    surface can reach). held: (H, 3) m TCPs of closed grippers: they pick the held corners of the
    contour, and a grid corner within held_gate (H,) m (default ``grasp_gate_m``) of one is placed at it.
    """
    ct = contour_3d(cloud, K, T_world_cam, params, held, robust=True)
    if ct is None:
        raise InitialisationError("no contour in the segmented cloud")
    R, C = params.grid_rows, params.grid_cols
    X0 = lift_grid(ct, cloud, R, C)
    if held is not None and len(held):
        corners = np.array([0, C - 1, (R - 1) * C, R * C - 1])
        hp = np.asarray(held, np.float64).reshape(-1, 3)
        cost = np.linalg.norm(hp[:, None, :] - X0[corners][None, :, :], axis=2)
        r, k = linear_sum_assignment(cost)
        gate = np.broadcast_to(np.asarray(params.grasp_gate_m if held_gate is None else held_gate, np.float64),
                               (len(hp),))
        ok = cost[r, k] <= gate[r]
        X0[corners[k[ok]]] = hp[r[ok]]
    topo = cloth_topology(X0, R, C)
    bi = topo.anchor_idx
    Xs = solve_keypoints(X0, topo.edges, topo.rest, bi, X0[bi], cloud, params.init_iterations, params, topo.colours)
    return Initialisation(Xs, topo, obj)


def cloth_topology(X: np.ndarray, rows: int, cols: int) -> Topology:
    """The 2D topology of a rows x cols grid of keypoints X (rows * cols, 3) m, row-major: 4-neighbour edges with
    their lengths in X as rest lengths, the boundary nodes as anchors (corners, sides), the rows as chains."""
    E, _ = grid_topology(rows, cols, 0.0, 0.0)
    bi, bk = boundary_indices(rows, cols)
    chains = [np.arange(r * cols, (r + 1) * cols) for r in range(rows)]
    return Topology("2d", E, edge_lengths(X, E), bi, bk, chains, (rows, cols), edge_colouring(E, rows * cols))


def initialise(
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    kind: str | None = None,
    root_hint: np.ndarray | None = None,
    held: np.ndarray | None = None,
    held_gate: np.ndarray | None = None,
) -> Initialisation:
    """Classify (unless ``kind`` "1d"/"2d" is given) and initialise keypoints on a segmented cloud (N, 3) m.

    root_hint: (3,) m, e.g. the first gripper's TCP: a 1D object's keypoint 0 is the end there.
    held: (H, 3) m TCPs of the closed grippers: the object is held there (1D ends and cloth corners are put there;
    held_gate (H,) m: how far from each TCP its end or corner may be seen, default ``grasp_gate_m``).
    Raises InitialisationError when the cloud is too small or has no usable skeleton / contour.
    """
    if len(cloud) < params.min_object_points:
        raise InitialisationError(f"only {len(cloud)} object points (< {params.min_object_points})")
    obj = classify_object(cloud, params)
    if kind is not None:
        obj = ObjectClass(kind, obj.line_ratio, obj.plane_ratio)
    if obj.kind == "1d":
        return initialise_1d(cloud, K, T_world_cam, params, obj, root_hint, held, held_gate)
    return initialise_2d(cloud, K, T_world_cam, params, obj, held, held_gate)
