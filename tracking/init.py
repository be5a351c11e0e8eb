"""Keypoint initialisation (paper section III-D): classify, anchors, warm start, topology, solve."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from tracking.anchors import (
    boundary_indices,
    contour_3d,
    lift_grid,
    skeleton_3d,
)
from tracking.classify import ObjectClass, classify_object
from tracking.geometry import farthest_point_sampling
from tracking.params import TrackingParams
from tracking.skeleton import LEAF
from tracking.solver import edge_colouring, solve_keypoints


class InitialisationError(RuntimeError):
    """The segmented cloud does not support an initialisation (too small, no skeleton, no contour)."""


@dataclass(frozen=True)
class Topology:
    """Fixed object topology.

    kind: "1d" or "2d". edges: (E, 2) int64 keypoint pairs; rest: (E,) float64 target lengths, m.
    anchor_idx: (A,) int64 anchor keypoints; anchor_kind: (A,) int64 LEAF/JUNCTION/BOUNDARY/CORNER.
    chains: 1D: keypoint index arrays, one per branch, node to node; 2D: the grid rows.
    grid_shape: (rows, cols) for 2D, else None. colours: edge colour classes for the solver.
    """

    kind: str
    edges: np.ndarray
    rest: np.ndarray
    anchor_idx: np.ndarray
    anchor_kind: np.ndarray
    chains: list[np.ndarray]
    grid_shape: tuple[int, int] | None = None
    colours: list[np.ndarray] = field(default_factory=list, compare=False)

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


def _polyline_arc(poly: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])


def _dfs_branch_order(n_nodes: int, branches: list[tuple[int, int, np.ndarray]], root: int) -> list[tuple[int, bool]]:
    """Branches in depth-first order from root: (branch id, reversed?) so each starts at a visited node."""
    adj: list[list[int]] = [[] for _ in range(n_nodes)]
    for k, (a, b, _) in enumerate(branches):
        adj[a].append(k)
        adj[b].append(k)
    seen_node = np.zeros(n_nodes, bool)
    seen_br = np.zeros(len(branches), bool)
    order: list[tuple[int, bool]] = []
    stack = [root]
    seen_node[root] = True
    while stack:
        u = stack.pop()
        for k in sorted(adj[u], reverse=True):
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


def initialise_1d(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, obj: ObjectClass
) -> Initialisation:
    """Initialise a 1D object (rope, branched rope) from its segmented cloud (N, 3) float64 m world.

    Anchors = skeleton leaves and junctions; warm start = FPS on the cloud seeded from the anchors,
    each sample assigned to the nearest skeleton branch and ordered along it; edges chain each
    branch node to node; rest length of a branch = its 3D arc length / its edge count.
    """
    sk = skeleton_3d(cloud, K, T_world_cam, params, all_components=False)
    if len(sk.branches) == 0:
        raise InitialisationError("no skeleton branch in the segmented cloud")
    nodes, kinds = sk.nodes, sk.kinds
    Nn = len(nodes)
    n_free = max(0, params.n_keypoints_1d - Nn)
    polys = [p for _, _, p in sk.branches]
    lengths = np.array([_polyline_arc(p)[-1] for p in polys])
    # warm start: FPS from the anchors, assigned to branches by nearest skeleton sample
    fps = cloud[farthest_point_sampling(cloud, n_free, seeds=nodes)]
    samples = np.concatenate(polys)
    owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(polys)])
    arc = np.concatenate([_polyline_arc(p) for p in polys])
    _, nn = cKDTree(samples).query(fps) if len(fps) else (None, np.zeros(0, np.int64))
    f_branch, f_arc = owner[nn], arc[nn]
    leaves = np.nonzero(kinds == LEAF)[0]
    root = int(leaves[np.argmin(nodes[leaves, 0])]) if len(leaves) else 0
    X: list[np.ndarray] = [nodes[root]]
    node_kp = np.full(Nn, -1)
    node_kp[root] = 0
    edges: list[tuple[int, int]] = []
    rest: list[float] = []
    chains: list[np.ndarray] = []
    for k, rev in _dfs_branch_order(Nn, sk.branches, root):
        a, b, _ = sk.branches[k]
        start, end = (b, a) if rev else (a, b)
        sel = np.nonzero(f_branch == k)[0]
        sel = sel[np.argsort(f_arc[sel])]
        if rev:
            sel = sel[::-1]
        chain = [int(node_kp[start])]
        for i in sel:
            X.append(fps[i])
            chain.append(len(X) - 1)
        if node_kp[end] < 0:
            X.append(nodes[end])
            node_kp[end] = len(X) - 1
        chain.append(int(node_kp[end]))
        d = lengths[k] / (len(chain) - 1)
        edges += list(zip(chain[:-1], chain[1:], strict=True))
        rest += [d] * (len(chain) - 1)
        chains.append(np.array(chain, np.int64))
    Xa = np.array(X)
    E = np.array(edges, np.int64)
    anchor_idx = node_kp[node_kp >= 0]
    anchor_kind = kinds[node_kp >= 0]
    topo = Topology("1d", E, np.array(rest), anchor_idx, anchor_kind, chains, None, edge_colouring(E, len(Xa)))
    Xs = solve_keypoints(
        Xa, E, topo.rest, anchor_idx, Xa[anchor_idx], cloud, params.init_iterations, params, topo.colours
    )
    return Initialisation(Xs, topo, obj)


def grid_topology(rows: int, cols: int, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """4-neighbour grid edges (E, 2) row-major and rest lengths (E,) m: dx along rows, dy along columns."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    h = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1)
    v = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1)
    return np.concatenate([h, v]), np.concatenate([np.full(len(h), dx), np.full(len(v), dy)])


def initialise_2d(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, obj: ObjectClass
) -> Initialisation:
    """Initialise a rectangular 2D object (cloth) from its segmented cloud (N, 3) float64 m world.

    Contour -> four corners -> sides; a rows x cols Coons (bilinear) grid bounded by the sides,
    lifted by the nearest cloud point; boundary nodes are anchors; rest lengths from the measured
    side lengths (mean of opposite sides / edge count).
    """
    ct = contour_3d(cloud, K, T_world_cam, params)
    if ct is None:
        raise InitialisationError("no contour in the segmented cloud")
    R, C = params.grid_rows, params.grid_cols
    X0 = lift_grid(ct, cloud, R, C)
    dx = 0.5 * (ct.lengths[0] + ct.lengths[2]) / (C - 1)
    dy = 0.5 * (ct.lengths[1] + ct.lengths[3]) / (R - 1)
    E, rest = grid_topology(R, C, dx, dy)
    bi, bk = boundary_indices(R, C)
    chains = [np.arange(r * C, (r + 1) * C) for r in range(R)]
    topo = Topology("2d", E, rest, bi, bk, chains, (R, C), edge_colouring(E, R * C))
    Xs = solve_keypoints(X0, E, rest, bi, X0[bi], cloud, params.init_iterations, params, topo.colours)
    return Initialisation(Xs, topo, obj)


def initialise(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, kind: str | None = None
) -> Initialisation:
    """Classify (unless ``kind`` "1d"/"2d" is given) and initialise keypoints on a segmented cloud (N, 3) m.

    Raises InitialisationError when the cloud is too small or has no usable skeleton / contour.
    """
    if len(cloud) < params.min_object_points:
        raise InitialisationError(f"only {len(cloud)} object points (< {params.min_object_points})")
    obj = classify_object(cloud, params)
    if kind is not None:
        obj = ObjectClass(kind, obj.line_ratio, obj.plane_ratio)
    if obj.kind == "1d":
        return initialise_1d(cloud, K, T_world_cam, params, obj)
    return initialise_2d(cloud, K, T_world_cam, params, obj)
