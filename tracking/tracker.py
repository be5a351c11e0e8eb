"""Algorithm 2: per-frame tracking, anchor matching, grasp indices, smoothing and loss-of-track detection.

The stages are pure functions; ``Tracker`` only holds the state between frames.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tracking.anchors import detect_anchors_1d, detect_anchors_2d
from tracking.geometry import cloud_tree
from tracking.init import Initialisation, Topology, initialise
from tracking.kernels import nearest, warm_up
from tracking.metrics import chamfer_mm, edge_rmse_mm, segment_distances
from tracking.params import TrackingParams
from tracking.skeleton import LEAF
from tracking.solver import (
    adjacency,
    chain_neighbours,
    chain_tangents,
    hop_neighbours,
    onto_local_plane,
    relax_hidden,
    shorten_stretched,
    solve_keypoints,
    tube_mean,
)
from tracking.tangle import (
    captured,
    chain_edges,
    chain_reversals,
    cover_cloud,
    hung_sheet,
    relift_chains,
    relift_grid,
    respace_chains,
    tangled_cells,
    uncovered_share,
    unfold_chains,
)


class TrackStatus(str, Enum):
    """Quality of one tracked frame: OK, DEGRADED (bad, not yet lost), LOST (re-initialise), UNINITIALISED."""

    OK = "ok"
    DEGRADED = "degraded"
    LOST = "lost"
    UNINITIALISED = "uninitialised"


@dataclass(frozen=True)
class FrameResult:
    """One frame's output.

    keypoints: (N, 3) float64 m world, the frame's solution as reported (a 1D object's in the middle of its tube:
    ``Tracker._reported``), before any smoothing; smoothed: (N, 3) causal moving average;
    status: TrackStatus (keypoints are only trustworthy when OK); edge_rmse_mm, chamfer_mm: Abs and CD;
    n_points: segmented points; anchors_matched / anchors_total: re-detected anchors used;
    grasp_idx: (G,) int64 keypoint held by each gripper, -1 = none.
    tangled: a grid's tangled cells, or a 1D object's keypoints where a chain turns back on itself (a fold),
    left in this solution (``tracking.tangle``; such a frame is bad);
    repaired: the grid had tangled and was re-lifted from the frame's contour, or a fold was laid out again.
    """

    keypoints: np.ndarray
    smoothed: np.ndarray
    status: TrackStatus
    edge_rmse_mm: float
    chamfer_mm: float
    n_points: int
    anchors_matched: int
    anchors_total: int
    grasp_idx: np.ndarray
    tangled: int = 0
    repaired: bool = False


@dataclass(frozen=True)
class FrameSolve:
    """One solve of Algorithm 2 (``track_frame``).

    X: (N, 3) float64 m keypoints; matched: anchors matched to a detection; match: (A,) int64 each anchor's
    detection (index into the detections, -1: none) before the consistency check (``Tracker._grow`` reads the
    tips' from it); used: (A,) bool which anchors were re-detected and kept (consistent).
    """

    X: np.ndarray
    matched: int
    match: np.ndarray
    used: np.ndarray


def _hungarian(C: np.ndarray, bad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min-cost assignment of cost (A, D) avoiding ``bad`` pairs -> matched (rows, cols)."""
    r, c = linear_sum_assignment(np.where(bad, 1e6, C))
    ok = ~bad[r, c]
    return r[ok], c[ok]


def match_anchors(
    prev: np.ndarray,
    prev_kinds: np.ndarray,
    det: np.ndarray,
    det_kinds: np.ndarray,
    gate_m: float,
    by_kind: bool,
    regate_m: float = 0.0,
    recapture: np.ndarray | None = None,
) -> np.ndarray:
    """Hungarian match of predicted anchors (A, 3) m to detections (D, 3) m -> (A,) index into det or -1.

    Pairs farther than gate_m (or of different kinds when ``by_kind``) are not matched; anchors and
    detections left over are then matched among themselves within the wider ``regate_m`` (an anchor
    that drifted while it was not detected is recaptured): those of recapture (A,) bool only, when given
    (an anchor re-detected and kept the frame before is where it is predicted; a detection farther is more
    likely something else: a spur, the end of a part seen short).
    """
    out = np.full(len(prev), -1, np.int64)
    if len(prev) == 0 or len(det) == 0:
        return out
    C = np.linalg.norm(prev[:, None, :] - det[None, :, :], axis=2)
    kind_bad = (prev_kinds[:, None] != det_kinds[None, :]) if by_kind else np.zeros(C.shape, bool)
    r, c = _hungarian(C, kind_bad | (C > gate_m))
    out[r] = c
    if regate_m > gate_m:
        ra = np.nonzero((out < 0) if recapture is None else (out < 0) & np.asarray(recapture, bool))[0]
        cd = np.setdiff1d(np.arange(len(det)), c)
        if len(ra) and len(cd):
            sub = np.ix_(ra, cd)
            r2, c2 = _hungarian(C[sub], kind_bad[sub] | (C[sub] > regate_m))
            out[ra[r2]] = cd[c2]
    return out


def assign_grasp_indices(keypoints: np.ndarray, tcp: np.ndarray, gate_m: float) -> np.ndarray:
    """Nearest keypoint (G,) int64 to each TCP (G, 3) m among keypoints (N, 3) m; -1 beyond gate_m."""
    tcp = np.asarray(tcp, np.float64).reshape(-1, 3)
    if len(tcp) == 0:
        return np.zeros(0, np.int64)
    d, i = cKDTree(keypoints).query(tcp)
    return np.where(d <= gate_m, i, -1).astype(np.int64)


def update_grasp_indices(
    prev_idx: np.ndarray, keypoints: np.ndarray, tcp: np.ndarray, closed: np.ndarray, gate_m: float
) -> np.ndarray:
    """Grasp indices (G,) after a frame: open grippers hold nothing, a newly closed one grasps the nearest.

    prev_idx: (G,) int64 (-1 none); keypoints (N, 3) m; tcp (G, 3) m; closed (G,) bool.
    """
    closed = np.asarray(closed, bool)
    out = np.where(closed, prev_idx, -1).astype(np.int64)
    regrasp = closed & (out < 0)
    if regrasp.any():
        out[regrasp] = assign_grasp_indices(keypoints, np.asarray(tcp)[regrasp], gate_m)
    return out


def consistent_anchors(
    topology: Topology,
    idx: np.ndarray,
    pos: np.ndarray,
    n_keypoints: int,
    tol: float,
    X_pred: np.ndarray | None = None,
    slack_m: float = 0.0,
) -> np.ndarray:
    """Which re-detected anchors (A,) bool agree with the topology: anchors of keypoints idx (A,) at
    pos (A, 3) m; an edge of the topology joining two of them whose length differs from its rest
    length by more than ``tol`` times that rest length condemns both ends (a contour side shortened
    by a fold, a detection matched to the wrong anchor). With the predicted keypoints X_pred (N, 3) m,
    an edge from a re-detected anchor to a keypoint that is not one condemns the anchor when the
    anchor's distance to that keypoint's prediction is off by more than ``tol`` of the rest length
    plus ``slack_m`` (a free end matched to a spur: no other anchor is its neighbour). The others are kept."""
    at = np.full((n_keypoints, 3), np.nan)
    at[idx] = pos
    e = topology.edges
    L = np.linalg.norm(at[e[:, 0]] - at[e[:, 1]], axis=1)
    bad = np.abs(L - topology.rest) > tol * topology.rest  # nan (an end not detected) compares False
    condemned = np.zeros(n_keypoints, bool)
    condemned[e[bad].ravel()] = True
    if X_pred is not None:
        det = np.isfinite(at[:, 0])
        one = det[e[:, 0]] != det[e[:, 1]]
        k = np.where(det[e[:, 0]], e[:, 0], e[:, 1])[one]
        j = np.where(det[e[:, 0]], e[:, 1], e[:, 0])[one]
        rest = topology.rest[one]
        Lp = np.linalg.norm(at[k] - X_pred[j], axis=1)
        condemned[k[np.abs(Lp - rest) > tol * rest + slack_m]] = True
    return ~condemned[idx]


def regate_on_object(
    topology: Topology, X_pred: np.ndarray, det: np.ndarray, m: np.ndarray, params: TrackingParams,
) -> np.ndarray:
    """(A,) bool: which anchors were matched (m (A,) into det (D, 3) m) beyond ``anchor_gate_m`` of their
    prediction (X_pred (N, 3) m) to a detection within ``anchor_regate_clear`` median rest lengths of an edge of
    the predicted object that neither the anchor nor a neighbour of it ends: on the object (a spur of its skeleton,
    the end of a part seen short, where a branch hanging to the table seems to end when its lying part is lost in
    the table's noise), so not that anchor. A detection beyond the anchor's own edge (a tip whipping ahead of its
    prediction, a tip seen short before) is left matched."""
    out = np.zeros(len(m), bool)
    ai = topology.anchor_idx
    far = m >= 0
    if not far.any() or len(X_pred) < 2:
        return out
    far[far] = np.linalg.norm(det[m[far]] - X_pred[ai[far]], axis=1) > params.anchor_gate_m
    a = np.flatnonzero(far)
    if not len(a):
        return out
    e = np.asarray(topology.edges, np.int64)
    mine = adjacency(e, len(X_pred), self_loops=True)[ai[a]]  # (F, N) the anchor and its neighbours
    d = segment_distances(det[m[a]], X_pred[e[:, 0]], X_pred[e[:, 1]])  # (F, E)
    d[mine[:, e[:, 0]] | mine[:, e[:, 1]]] = np.inf
    out[a] = d.min(axis=1) < params.anchor_regate_clear * float(np.median(topology.rest))
    return out


def free_tips(X: np.ndarray, edges: np.ndarray, grasp_idx: np.ndarray | None) -> np.ndarray:
    """(T, 6) float64: the free tips of a 1D object's keypoints X (N, 3) m (leaves of edges (E, 2) that no gripper
    holds, grasp_idx (G,) int64, -1 none): each one's position (3,) m and the unit direction (3,) its last edge
    points outwards (``segmentation.tip_continuations``)."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    deg = np.bincount(edges.ravel(), minlength=len(X))
    held = np.zeros(len(X), bool)
    if grasp_idx is not None:
        g = np.asarray(grasp_idx, np.int64).reshape(-1)
        held[g[(g >= 0) & (g < len(X))]] = True
    e = np.concatenate([edges, edges[:, ::-1]])  # (tip, its neighbour) both ways
    e = e[(deg[e[:, 0]] == 1) & ~held[e[:, 0]]]
    d = X[e[:, 0]] - X[e[:, 1]]
    n = np.linalg.norm(d, axis=1)
    ok = n > 1e-9
    return np.hstack([X[e[ok, 0]], d[ok] / n[ok, None]]).astype(np.float64).reshape(-1, 6)


def held_seeds(X: np.ndarray, topology: Topology, grasp_idx: np.ndarray | None) -> np.ndarray | None:
    """(H, 4) float64: a grid's held keypoints of X (N, 3) m, each one's position (3,) m and the sheet's reach from
    it (m), its longest row plus its longest column over the rest lengths (``segmentation.chained_to``: a side
    hanging edge-on from the hand lifts to points too sparse for DBSCAN); None for other objects or none held."""
    if topology.grid_shape is None or grasp_idx is None:
        return None
    g = np.asarray(grasp_idx, np.int64).reshape(-1)
    g = g[(g >= 0) & (g < len(X))]
    if not len(g):
        return None
    rows, cols = topology.grid_shape
    e = np.asarray(topology.edges, np.int64).reshape(-1, 2)
    rest = np.asarray(topology.rest, np.float64)
    along = (e[:, 0] // cols) == (e[:, 1] // cols)  # an edge within a row, else within a column
    row = np.bincount(e[along, 0] // cols, rest[along], minlength=rows).max(initial=0.0)
    col = np.bincount(e[~along, 0] % cols, rest[~along], minlength=cols).max(initial=0.0)
    return np.hstack([X[g], np.full((len(g), 1), row + col)])


def cloudless(topology: Topology, X: np.ndarray, cloud: np.ndarray | cKDTree, reach_m: float) -> np.ndarray:
    """(N,) bool: the keypoints X (N, 3) m whose nearest point of the cloud ((M, 3) m or its cKDTree) lies
    farther than reach_m and nearer another keypoint than them, one that is not their neighbour (topology's
    edges): that cloud is another part of the object, and projecting onto it folds the chain. Their own part is
    out of sight where no arm mask says so (a rope under a hand seen from above, a stretch behind the arm that
    the prediction put beside it)."""
    pts = cloud.data if isinstance(cloud, cKDTree) else np.ascontiguousarray(cloud, np.float64).reshape(-1, 3)
    N = len(X)
    if len(pts) == 0 or N < 3:
        return np.zeros(N, bool)
    d, nn = nearest(np.ascontiguousarray(X, np.float64), pts)  # the solver's slab search: no tree to build
    owner = np.argmin(np.linalg.norm(pts[nn][:, None, :] - X[None], axis=-1), axis=1)
    return (d > reach_m) & ~adjacency(topology.edges, N, self_loops=True)[np.arange(N), owner]


def short_tips(
    topology: Topology, idx: np.ndarray, pos: np.ndarray, kinds: np.ndarray, X_pred: np.ndarray,
    params: TrackingParams,
) -> np.ndarray:
    """Which re-detected 1D tips are seen short: nearer their one neighbour's prediction than the edge's rest
    length allows by more than ``params.tip_short_tol`` of it, yet within ``anchor_gate_m`` of their own.

    idx: (A,) int64 keypoints of matched anchors; pos: (A, 3) m their detections; kinds: (A,) anchor kinds;
    X_pred: (N, 3) m predicted keypoints. Returns (A,) bool. Such a tip (end-on, bent away or partly hidden)
    marks a point inside the object, so fixing its keypoint there would compress the tip's edge.
    """
    out = np.zeros(len(idx), bool)
    if params.tip_short_tol <= 0 or not len(idx):
        return out
    e = np.asarray(topology.edges, np.int64)
    degree = np.bincount(e.ravel(), minlength=len(X_pred))
    tip = (kinds == LEAF) & (degree[idx] == 1)
    if not tip.any():
        return out
    # the one edge of each tip: row of e holding it
    row = np.full(len(X_pred), -1, np.int64)
    row[e[:, 0]] = np.arange(len(e))
    row[e[:, 1]] = np.arange(len(e))
    r_edge = row[idx[tip]]
    nb = np.where(e[r_edge, 0] == idx[tip], e[r_edge, 1], e[r_edge, 0])
    rest = np.asarray(topology.rest, np.float64)[r_edge]
    short = rest - np.linalg.norm(pos[tip] - X_pred[nb], axis=1) > params.tip_short_tol * rest
    near = np.linalg.norm(pos[tip] - X_pred[idx[tip]], axis=1) <= params.anchor_gate_m
    out[np.flatnonzero(tip)[short & near]] = True
    return out


def track_frame(
    X_prev: np.ndarray,
    topology: Topology,
    cloud: np.ndarray | cKDTree,
    det_pos: np.ndarray,
    det_kinds: np.ndarray,
    params: TrackingParams,
    tcp: np.ndarray | None = None,
    grasp_idx: np.ndarray | None = None,
    X_pred: np.ndarray | None = None,
    hidden: np.ndarray | None = None,
    soft: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    open_space: Callable[[np.ndarray], np.ndarray] | None = None,
    recapture: np.ndarray | None = None,
) -> FrameSolve:
    """One step of Algorithm 2: match anchors, add grasped TCP anchors, solve warm-started from X_prev.

    X_prev: (N, 3) m; cloud: (M, 3) m segmented (or its cKDTree);
    det_pos/det_kinds: re-detected anchors (D, 3) m / (D,).
    X_pred: (N, 3) m predicted keypoints (e.g. constant velocity) used to match anchors, default X_prev.
    An anchor not re-detected is left free this frame (warm-started at its previous position).
    Keypoints held by a gripper (grasp_idx >= 0) are fixed at that gripper's TCP (G, 3) m, also in the
    ``use_anchors=False`` ablation, which leaves out the re-detected anchors only: the TCPs are the robot's
    inputs, not detections (the paper's ablation, where a rope held at both ends tracks as the full method).
    hidden: (N,) bool keypoints out of sight (``solve_keypoints``; ``Tracker.step``); a 1D object's keypoints
    whose nearest cloud is another part of it (``cloudless``) are solved as hidden ones too.
    soft: more anchors, (K,) int64 keypoints, (K, 3) m positions, (K,) weights in (0, 1), in place of any
    re-detected anchor of those keypoints (``Tracker.step``: where a held end or corner leaves the fingers).
    open_space: points (K, 3) m -> (K,) bool, where the frame's depth sees through (``geometry.in_open_space``); a
    cloth's hidden keypoint that the relaxation after the solve would put there stays where the solve put it.
    recapture: (A,) bool the anchors not re-detected and kept the frame before: a cloth's others are not matched
    within ``anchor_regate_m`` (``match_anchors``); a 1D object's anchors are matched there only by a detection off
    the rest of the object (``regate_on_object``).
    Returns the keypoints, the anchors matched and kept (``FrameSolve``).
    """
    ai = topology.anchor_idx
    Xm = X_prev if X_pred is None else X_pred
    m = match_anchors(
        Xm[ai],
        topology.anchor_kind,
        det_pos,
        det_kinds,
        params.anchor_gate_m,
        topology.kind == "1d",
        params.anchor_regate_m,
        recapture if topology.kind == "2d" else None,
    )
    if topology.kind == "1d":
        m[regate_on_object(topology, Xm, det_pos, m, params)] = -1
    idx = [ai[m >= 0]]
    pos = [det_pos[m[m >= 0]]]
    kinds = topology.anchor_kind[m >= 0]
    if params.anchor_edge_tol > 0:
        ok = consistent_anchors(
            topology, idx[0], pos[0], len(X_prev), params.anchor_edge_tol, Xm, params.anchor_neighbour_slack_m
        )
        idx, pos, kinds = [idx[0][ok]], [pos[0][ok]], kinds[ok]
    used = np.isin(ai, idx[0])
    # a 1D object's tips are sharp in the cloud and stay fixed; its junctions and a cloth's boundary, found
    # less sharply, pull their keypoints part of the way (anchor_stiffness)
    weight = np.full(len(kinds), params.anchor_stiffness)
    if topology.kind == "1d":
        weight[kinds == LEAF] = 1.0
        weight[short_tips(topology, idx[0], pos[0], kinds, Xm, params)] = params.anchor_stiffness
    if tcp is not None and grasp_idx is not None:
        g = np.asarray(grasp_idx, np.int64)
        held = g >= 0
        keep = ~np.isin(idx[0], g[held])
        idx, pos = [idx[0][keep], g[held]], [pos[0][keep], np.asarray(tcp, np.float64).reshape(-1, 3)[held]]
        weight = np.concatenate([weight[keep], np.ones(int(held.sum()))])  # grasped: fixed at the TCP
    if not params.use_anchors:  # the grasped keypoints only (appended last)
        n_grasped = len(idx[1]) if len(idx) > 1 else 0
        idx, pos, weight = idx[1:], pos[1:], weight[len(weight) - n_grasped:]
        params = replace(params, use_anchors=True)
    aidx = np.concatenate(idx) if idx else np.zeros(0, np.int64)
    apos = np.concatenate(pos) if pos else np.zeros((0, 3))
    if soft is not None and len(soft[0]):  # in place of a re-detected anchor of the same keypoint
        keep = ~np.isin(aidx, soft[0])
        aidx, apos = np.concatenate([aidx[keep], soft[0]]), np.concatenate([apos[keep], soft[1]])
        weight = np.concatenate([weight[keep], soft[2]])
    solve_hidden = hidden  # a 1D object's keypoints without cloud of their own are solved as hidden ones too
    if topology.kind == "1d" and len(topology.rest):
        off = cloudless(topology, X_prev, cloud, params.hidden_reach * float(np.median(topology.rest)))
        if off.any():
            solve_hidden = off if hidden is None else np.asarray(hidden, bool) | off
    X = solve_keypoints(
        X_prev, topology.edges, topology.rest, aidx, apos, cloud, params.track_iterations, params, topology.colours,
        weight, solve_hidden,
        chain_neighbours(topology.chains, len(X_prev)) if solve_hidden is not None and topology.kind == "1d" else None,
        symmetric_last=topology.kind == "1d",
    )
    if topology.kind == "2d" and hidden is not None and params.use_edge_projection:
        movable = np.array(hidden, bool)
        movable[aidx[weight >= 1.0]] = False  # a held corner stays at its TCP
        relaxed = relax_hidden(X, topology.edges, topology.rest, movable, params.hidden_relax_sweeps, params,
                               topology.colours)
        if open_space is not None and movable.any():
            stay = movable & open_space(relaxed)
            relaxed[stay] = X[stay]
        X = relaxed
    return FrameSolve(X, int((m >= 0).sum()), m, used)


def detect_anchors(
    kind: str,
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    held: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Re-detect anchors of a "1d" or "2d" object in a segmented cloud (M, 3) m -> (positions (D, 3), kinds (D,)).

    held: (H, 3) m TCPs of closed grippers (2D: they mark held corners)."""
    if kind == "1d":
        return detect_anchors_1d(cloud, K, T_world_cam, params)
    return detect_anchors_2d(cloud, K, T_world_cam, params, held)


def smooth_causal(traj: np.ndarray, window: int) -> np.ndarray:
    """Causal moving average of a trajectory (T, N, 3): frame t averages frames max(0, t-w+1)..t."""
    T = len(traj)
    c = np.cumsum(np.concatenate([np.zeros((1,) + traj.shape[1:]), traj]), axis=0)
    t = np.arange(T)
    lo = np.maximum(0, t - window + 1)
    return (c[t + 1] - c[lo]) / (t + 1 - lo)[:, None, None]


def smooth_symmetric(traj: np.ndarray, window: int, gate_m: float = np.inf) -> np.ndarray:
    """Symmetric moving average of a trajectory (T, N, 3) with an odd window, frames. Near the ends the window
    shrinks on both sides (frame t averages t-h..t+h with h <= t and h <= T-1-t): a window cut on one side only
    lags a moving object by up to half a window at the clip's first and last frames. Frames t-k and t+k enter
    frame t's average (each keypoint's own) only while their midpoint lies within gate_m (m) of it, as do all
    nearer pairs: a steady motion of any speed is averaged, a jump (a correspondence lost and found again, a
    re-initialisation) is not averaged across, which would put the keypoints where the object never was."""
    traj = np.asarray(traj, np.float64)
    T = len(traj)
    acc = traj.copy()
    n = np.ones(traj.shape[:2])
    live = np.ones(traj.shape[:2], bool)
    for k in range(1, max(0, window // 2) + 1):
        pair = np.zeros_like(traj)
        ok = np.zeros(traj.shape[:2], bool)
        if T > 2 * k:
            pair[k:T - k] = traj[: T - 2 * k] + traj[2 * k:]
            ok[k:T - k] = np.linalg.norm(0.5 * pair[k:T - k] - traj[k:T - k], axis=-1) <= gate_m
        live &= ok
        acc += np.where(live[..., None], pair, 0.0)
        n += 2 * live
    return acc / n[..., None]


def final_keypoints(raw: np.ndarray, topology: Topology, params: TrackingParams) -> np.ndarray:
    """A clip's final keypoints (T, N, 3) m from its raw track (T, N, 3) m (rows of NaN: frames never tracked,
    kept so): the tracked frames smoothed by ``smooth_symmetric`` over ``params.symmetric_window`` frames, not
    across a jump of more than ``params.smooth_gate`` median rest lengths, a grid's frames whose smoothed edges are
    further off their rest lengths than their raw ones by more than ``params.smooth_edge_slack_mm`` (RMS) kept raw;
    a 1D object's chains whose edge lengths are off by more than ``params.respace_error`` median rest lengths (RMS)
    then spaced along their curves as their rest lengths are (``respace_chains``, moves of at most
    ``params.respace_cap`` median rest lengths)."""
    final = np.array(raw, np.float64)
    ok = ~np.isnan(final).any(axis=(1, 2))
    rest = topology.rest
    if ok.any():
        gate = params.smooth_gate * float(np.median(rest)) if len(rest) else np.inf
        smoothed = smooth_symmetric(final[ok], params.symmetric_window, gate)
        if topology.grid_shape is not None and len(rest):
            worse = np.array([edge_rmse_mm(a, topology.edges, rest) > edge_rmse_mm(b, topology.edges, rest)
                              + params.smooth_edge_slack_mm for a, b in zip(smoothed, final[ok], strict=True)])
            smoothed[worse] = final[ok][worse]
        final[ok] = smoothed
        if topology.kind == "1d" and params.respace_cap > 0 and len(rest):
            final[ok] = respace_chains(final[ok], topology, params.respace_cap * float(np.median(rest)),
                                       params.respace_error * float(np.median(rest)))
    return final


class Tracker:
    """Stateful wrapper: initialise on a segmented cloud, then ``step`` per frame (K, T_world_cam fixed)."""

    def __init__(self, params: TrackingParams, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        """params: TrackingParams; K: (3, 3) camera matrix; T_world_cam: (4, 4) camera pose in the world.
        Loads the compiled solver kernels here, not on the first frame (``tracking.kernels.warm_up``)."""
        warm_up()
        self.params = params
        self.K = np.asarray(K, np.float64)
        self.T = np.asarray(T_world_cam, np.float64)
        self.topology: Topology | None = None
        self.keypoints: np.ndarray | None = None
        self._velocity: np.ndarray | None = None
        self.grasp_idx = np.zeros(0, np.int64)
        self._history: deque[np.ndarray] = deque(maxlen=max(1, params.causal_window))
        self._bad = 0
        self.last_timings_ms: dict[str, float] = {}  # "anchors", "solve" of the last step, ms

    @property
    def initialised(self) -> bool:
        """True once initialised and not lost."""
        return self.topology is not None

    def reset(self) -> None:
        """Forget the track (the caller re-initialises)."""
        self.topology = None
        self.keypoints = None
        self._velocity = None
        self.grasp_idx = np.zeros(0, np.int64)
        self._history.clear()
        self._bad = 0
        self._tcp: np.ndarray | None = None  # the last tracked frame's TCPs (G, 3) m
        # where each keypoint beside a held one was last seen in its gripper's frame, m:
        # (gripper, held keypoint, keypoint) -> (3,)
        self._exit: dict[tuple[int, int, int], np.ndarray] = {}
        self._beyond: dict[int, int] = {}  # free 1D tip -> frames running it was re-detected beyond its chain
        # (A,) bool: which anchors were re-detected and kept last frame (None: not known; all may be recaptured
        # within the wider gate)
        self._kept: np.ndarray | None = None

    def initialise(
        self,
        cloud: np.ndarray,
        tcp: np.ndarray | None = None,
        kind: str | None = None,
        gripper_closed: np.ndarray | None = None,
        grasp_gate: np.ndarray | None = None,
    ) -> tuple[Initialisation, FrameResult]:
        """Initialise on a segmented cloud (M, 3) m; tcp (G, 3) m of the grippers gives grasp indices
        (and keypoint 0 at the first gripper's end); the ends (corners) held by the closed grippers
        (gripper_closed (G,) bool; None: every TCP within ``grasp_gate_m`` of an end or a corner) are placed
        at their TCPs. grasp_gate (G,) m: how far from each TCP an end or a corner held there may be seen
        (default ``grasp_gate_m``; farther where the hand hides more of it: ``LivePipeline.grasp_gates``).

        Raises tracking.init.InitialisationError when the cloud cannot be initialised.
        """
        self.reset()
        tcps = None if tcp is None else np.asarray(tcp, np.float64).reshape(-1, 3)
        hint = None if tcps is None or len(tcps) == 0 else tcps[0]
        held_gate = None
        if tcps is None:
            held = None
        else:
            # the closed grippers' TCPs; without gripper states every TCP: an end (a cloth's corner) within the gate
            # of one is held there (tracking pins it there: its grasp index), so the rest lengths span the part
            # hidden between the fingers
            sel = np.ones(len(tcps), bool) if gripper_closed is None else np.asarray(gripper_closed, bool)
            held = tcps[sel]
            if grasp_gate is not None:
                held_gate = np.asarray(grasp_gate, np.float64).reshape(-1)[sel]
        # the ablation switches are of the tracking step (the paper's Table II): every variant starts from the
        # full method's initialisation
        full = replace(self.params, use_anchors=True, use_edge_projection=True, use_cloud_projection=True)
        ini = initialise(cloud, self.K, self.T, full, kind, root_hint=hint, held=held, held_gate=held_gate)
        self.topology = ini.topology
        self.keypoints = ini.keypoints
        if tcp is not None:
            self.grasp_idx = assign_grasp_indices(ini.keypoints, tcp, self.params.grasp_gate_m)
        out = self._centred(ini.keypoints, cloud, None)
        if out is not ini.keypoints:  # the reference lengths are the centred chain's; then it is reported spaced
            self.topology = replace(ini.topology, reference=self._reference(out))
            ini = replace(ini, topology=self.topology)
            out = self._spaced(out)
        self._history.append(out)
        na = len(ini.topology.anchor_idx)
        return ini, self._result(ini.keypoints, cloud, na, na, out=out)

    def resume(self, topology: Topology, keypoints: np.ndarray, grasp_idx: np.ndarray) -> None:
        """Continue from a known solution instead of initialising: keypoints (N, 3) m world of
        ``topology``, grasp_idx (G,) int64 (no velocity yet: the next frame may run the other way in time)."""
        self.reset()
        self.topology = topology
        self.keypoints = np.array(keypoints, np.float64)
        self.grasp_idx = np.array(grasp_idx, np.int64)
        self._history.append(self.keypoints)

    def step(
        self, cloud: np.ndarray, tcp: np.ndarray | None = None, gripper_closed: np.ndarray | None = None,
        hidden: np.ndarray | None = None, tcp_rot: np.ndarray | None = None,
        open_space: Callable[[np.ndarray], np.ndarray] | None = None,
        behind_arm: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> FrameResult:
        """Track one frame's segmented cloud (M, 3) m; tcp (G, 3) m and gripper_closed (G,) bool are optional,
        as are the grippers' orientations tcp_rot (G, 3, 3) (TCP frame to world).

        hidden (N,) bool: the keypoints out of sight this frame (``tracking.geometry.hidden_behind``: behind the
        arm; a cloth's also behind its own near layer). They have no cloud of their own: they start from where
        their nearest TCP's motion since the last frame takes them (what a hand hides moves with it), are projected
        onto the cloud only beside it (``params.hidden_reach``), are drawn towards a smooth curve along their chain
        (a 1D object's, ``params.hidden_bend``) and are left out of the CD that judges the frame, as held
        keypoints are (the robot places those). With tcp_rot, a hidden keypoint within ``params.exit_keypoints``
        (a cloth's: ``exit_keypoints_2d``) edges of a held one is also drawn towards where it was last seen in that
        gripper's frame (``params.exit_stiffness``). open_space: the frame's test of where the camera sees through
        (``track_frame``), which a hidden keypoint is never moved into after the solve. behind_arm: the frame's
        ``geometry.behind_nearest_occluder`` (points (K, 3) m -> points, moved (K,) bool): a 1D keypoint the solve
        left with no cloud within ``params.hidden_reach`` and in open space goes behind the arm beside it.

        Grasp indices follow the grippers (regrasp on closing). After ``lost_after_frames`` bad frames
        the status is LOST and the tracker resets: the caller must initialise again.
        """
        early = self._begin_step(cloud, tcp, gripper_closed)
        if early is not None:
            return early
        assert self.topology is not None and self.keypoints is not None
        p = self.params
        na = len(self.topology.anchor_idx)
        t0 = time.perf_counter()
        held = self._held_tcps(tcp, gripper_closed)
        det, kinds = detect_anchors(self.topology.kind, cloud, self.K, self.T, p, held)
        t1 = time.perf_counter()
        pred = self.keypoints if self._velocity is None else self.keypoints + self._velocity
        cloud = np.ascontiguousarray(cloud, np.float64)
        tcp_now = None if tcp is None else np.asarray(tcp, np.float64).reshape(-1, 3)
        warm = self.keypoints
        move = self._hand_motion(tcp_now)
        if hidden is not None and hidden.any() and move is not None:
            h = np.flatnonzero(hidden)
            warm = self.keypoints.copy()
            warm[h] += move[h]
            pred = pred.copy()
            pred[h] = warm[h]
        self._tcp = tcp_now
        rot = None if tcp_rot is None else np.asarray(tcp_rot, np.float64).reshape(-1, 3, 3)
        exits, soft = self._exits(hidden, tcp_now, rot)
        if soft is not None:
            warm = warm.copy()
            warm[soft[0]] = soft[1]
        recapture = None if self._kept is None else ~self._kept
        solve = track_frame(warm, self.topology, cloud, det, kinds, p, tcp, self.grasp_idx, pred, hidden, soft,
                            open_space, recapture)
        X, matched = solve.X, solve.matched
        tangled, repaired = 0, False
        if self.topology.grid_shape is not None:
            X, matched, tangled, repaired = self._untangle(X, matched, cloud, det, kinds, tcp, held, open_space)
        elif self.topology.kind == "1d":
            X, matched, tangled, repaired = self._unfold(X, matched, cloud, det, kinds, tcp, hidden, soft, recapture)
        if behind_arm is not None and self.topology.kind == "1d" and len(cloud):
            X = self._behind_arm(X, cloud, behind_arm)
        if rot is not None and tcp_now is not None:
            for g, k, j in exits:  # learnt where seen
                if hidden is None or not hidden[j]:
                    self._exit[g, k, j] = rot[g].T @ (X[j] - tcp_now[g])
        if self.topology.kind == "1d" and p.grow_frames > 0:
            self._grow(X, det, solve.match)
        self._kept = solve.used
        res = self._result(X, cloud, matched, na, tangled=tangled, repaired=repaired, hidden=hidden,
                           out=self._reported(X, cloud, hidden))
        self.last_timings_ms = {"anchors": 1e3 * (t1 - t0), "solve": 1e3 * (time.perf_counter() - t1)}
        return res

    def _behind_arm(
        self, X: np.ndarray, cloud: np.ndarray, behind_arm: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    ) -> np.ndarray:
        """A 1D solution X (N, 3) m whose keypoints (not held) with no point of the cloud (M, 3) m within
        ``params.hidden_reach`` of the median edge rest length and where the camera sees through them are moved
        behind the arm beside them (behind_arm, ``Tracker.step``): the solve put them on a chord across the open
        space where the rope passes under a finger (rope_above_fast_s61), which the camera would have seen."""
        assert self.topology is not None
        d, _ = nearest(np.ascontiguousarray(X, np.float64), np.ascontiguousarray(cloud, np.float64))
        off = d > self.params.hidden_reach * float(np.median(self.topology.rest))
        off[self.grasp_idx[self.grasp_idx >= 0]] = False
        if not off.any():
            return X
        Xo, moved = behind_arm(X[off])
        if not moved.any():
            return X
        X = X.copy()
        X[np.flatnonzero(off)[moved]] = Xo[moved]
        return X

    def _grow(self, X: np.ndarray, det: np.ndarray, m: np.ndarray) -> None:
        """Lengthen a 1D chain whose free tip (not held) was re-detected farther from the chain's other node (in
        X (N, 3) m, this frame's solution) than (1 + ``grow_tol``) of the chain's rest length in
        ``grow_frames`` frames running: the chain's rest lengths are scaled (in place, the track's topology) to
        that distance. Initialisation measures what it sees; a branch hanging end-on to the camera, or lying
        partly hidden, is longer. m (A,) int64: each anchor's detection in det (D, 3) m, -1 none, as
        ``track_frame`` matched them (its ``match``)."""
        topo = self.topology
        assert topo is not None
        p = self.params
        ai = topo.anchor_idx
        held = set(self.grasp_idx[self.grasp_idx >= 0].tolist())
        for ch, e in zip(topo.chains, chain_edges(topo), strict=True):
            ch = np.asarray(ch, np.int64)
            if len(ch) < 2:
                continue
            for tip, node in ((int(ch[0]), int(ch[-1])), (int(ch[-1]), int(ch[0]))):
                a = np.flatnonzero(ai == tip)
                if not len(a) or topo.anchor_kind[a[0]] != LEAF or tip in held:
                    continue
                R = float(topo.rest[e].sum())
                reach = float(np.linalg.norm(det[m[a[0]]] - X[node])) if m[a[0]] >= 0 else 0.0
                self._beyond[tip] = self._beyond.get(tip, 0) + 1 if reach > (1.0 + p.grow_tol) * R else 0
                if self._beyond[tip] >= p.grow_frames:
                    topo.rest[e] *= reach / R
                    if topo.reference is not None:
                        topo.reference[e] *= reach / R
                    self._beyond[tip] = 0

    def _exits(
        self, hidden: np.ndarray | None, tcp: np.ndarray | None, rot: np.ndarray | None
    ) -> tuple[list[tuple[int, int, int]], tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """The (gripper, held keypoint, keypoint) triples of the keypoints within ``params.exit_keypoints``
        edges of a held one (a cloth's: ``exit_keypoints_2d``; not held themselves), and the soft anchors
        (keypoints, positions (K, 3) m, weights) of the hidden ones among them at their last seen place in their
        gripper's frame (tcp (G, 3) m, rot (G, 3, 3)): a held rope leaves the fingers the way it did, a held
        corner's cloth too. What was learnt for a gripper that let go or holds another keypoint now is forgotten."""
        assert self.topology is not None and self.keypoints is not None
        g_idx = self.grasp_idx
        self._exit = {key: v for key, v in self._exit.items() if key[0] < len(g_idx) and g_idx[key[0]] == key[1]}
        depth = self.params.exit_keypoints if self.topology.kind == "1d" else self.params.exit_keypoints_2d
        if rot is None or tcp is None or depth <= 0 or len(rot) != len(g_idx):
            return [], None
        held = set(g_idx[g_idx >= 0].tolist())
        exits = [(g, int(k), int(j)) for g, k in enumerate(g_idx) if k >= 0
                 for j in hop_neighbours(self.topology.edges, len(self.keypoints), int(k), depth)
                 if int(j) not in held]
        idx: list[int] = []
        pos: list[np.ndarray] = []
        for g, k, j in exits:
            local = self._exit.get((g, k, j))
            if hidden is not None and hidden[j] and local is not None and j not in idx:
                idx.append(j)
                pos.append(tcp[g] + rot[g] @ local)
        if not idx:
            return exits, None
        return exits, (np.array(idx, np.int64), np.array(pos), np.full(len(idx), self.params.exit_stiffness))

    def _untangle(
        self, X: np.ndarray, matched: int, cloud: np.ndarray, det: np.ndarray, kinds: np.ndarray,
        tcp: np.ndarray | None, held: np.ndarray | None,
        open_space: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> tuple[np.ndarray, int, int, bool]:
        """A grid solution X (N, 3) m checked for tangles and for the cloud (M, 3) m it leaves uncovered
        (``_cover``); a tangled one is solved again from a grid re-lifted from the frame's cloud in the track's
        correspondence (``relift_grid``), kept when it has fewer tangled cells. open_space: ``track_frame``'s.
        Returns (X, anchors matched, tangled cells left, repaired)."""
        assert self.topology is not None and self.topology.grid_shape is not None
        rows, cols = self.topology.grid_shape
        bad = int(tangled_cells(X, rows, cols).sum())
        covered = self._cover(X, cloud, tcp, held, bad, open_space)
        if covered is not None:
            return covered[0], matched, covered[1], True
        if bad == 0:
            return X, matched, 0, False
        X0 = relift_grid(X, self.topology, cloud, self.K, self.T, self.params, held)
        if X0 is None:
            return X, matched, bad, False
        again = track_frame(X0, self.topology, cloud, det, kinds, self.params, tcp, self.grasp_idx, X0)
        X2, m2 = again.X, again.matched
        bad2 = int(tangled_cells(X2, rows, cols).sum())
        if bad2 < bad:
            return X2, m2, bad2, True
        return X, matched, bad, False

    def _cover(
        self, X: np.ndarray, cloud: np.ndarray, tcp: np.ndarray | None, held: np.ndarray | None, bad: int,
        open_space: Callable[[np.ndarray], np.ndarray] | None,
    ) -> tuple[np.ndarray, int] | None:
        """A grid X (N, 3) m (bad: its tangled cells) that leaves more than ``params.cover_trigger`` of the cloud
        (M, 3) m uncovered (``uncovered_share``) registered to cover it (``cover_cloud``, the held keypoints at their
        TCPs) from itself, from the grid re-lifted from the frame's contour and from a flat sheet hung from the held
        corners (``hung_sheet``). Returns the registration that leaves the least uncovered of those that leave less
        than ``params.cover_gain`` of the share before, fewer tangled cells (none if there were none) and an edge
        error within ``params.cover_abs_slack_mm`` of X's, with its tangled cells; None if none does."""
        topo, p = self.topology, self.params
        assert topo is not None and topo.grid_shape is not None
        rows, cols = topo.grid_shape
        gap = p.cover_gap * float(np.median(topo.rest))
        share = uncovered_share(X, topo.grid_shape, cloud, gap)
        if len(cloud) < 10 or share < p.cover_trigger:
            return None
        fixed, at = np.zeros(0, np.int64), np.zeros((0, 3))
        if tcp is not None and self.grasp_idx is not None:
            g = np.flatnonzero(self.grasp_idx >= 0)
            fixed, at = self.grasp_idx[g].astype(np.int64), np.asarray(tcp, np.float64).reshape(-1, 3)[g]
        starts = [X, relift_grid(X, topo, cloud, self.K, self.T, p, held), hung_sheet(topo, fixed, at, cloud)]
        limit = edge_rmse_mm(X, topo.edges, topo.rest) + p.cover_abs_slack_mm
        best, least = None, p.cover_gain * share
        for start in starts:
            if start is None:
                continue
            Y = cover_cloud(start, topo, cloud, fixed, at, p, open_space)
            left = uncovered_share(Y, topo.grid_shape, cloud, gap)
            bad2 = int(tangled_cells(Y, rows, cols).sum())
            if left < least and (bad2 < bad or bad2 == bad == 0) and edge_rmse_mm(Y, topo.edges, topo.rest) <= limit:
                best, least = (Y, bad2), left
        return best

    def _unfold(
        self, X: np.ndarray, matched: int, cloud: np.ndarray, det: np.ndarray, kinds: np.ndarray,
        tcp: np.ndarray | None, hidden: np.ndarray | None = None,
        soft: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, recapture: np.ndarray | None = None,
    ) -> tuple[np.ndarray, int, int, bool]:
        """A 1D solution X (N, 3) m checked for chains folded onto themselves; a folded one is solved again from
        its chains laid out without the fold (``unfold_chains``) and from chains laid along the frame's skeleton
        (``relift_chains``: a branch lost behind the rest of the object and seen again), the one with the fewest
        keypoints turned back kept when there are fewer than before and its edge error is no larger (where a
        turned-back keypoint was ``captured`` by another part of the object: no larger than
        ``params.fold_capture_abs_mm`` either).
        Returns (X, anchors matched, keypoints turned back left, repaired)."""
        p, topo = self.params, self.topology
        assert topo is not None
        cos_max = p.fold_cos
        bad_idx = chain_reversals(X, topo.chains, cos_max)
        bad = len(bad_idx)
        if bad == 0:
            return X, matched, 0, False
        held = {}
        if tcp is not None:
            at = np.asarray(tcp, np.float64).reshape(-1, 3)
            held = {int(k): at[i] for i, k in enumerate(self.grasp_idx) if k >= 0 and i < len(at)}
        reach = p.fold_capture * float(np.median(topo.rest))
        slack = p.fold_capture_abs_mm if captured(X, topo.chains, bad_idx, reach).any() else 0.0
        starts = [unfold_chains(X, topo, cos_max, p.fold_span_min, reach),
                  relift_chains(X, topo, cloud, self.K, self.T, p, held)]
        edges, rest = topo.edges, topo.rest
        best = (X, matched, bad, False)
        abs_best = edge_rmse_mm(X, edges, rest)
        for X0 in starts:
            if X0 is None:
                continue
            again = track_frame(X0, topo, cloud, det, kinds, p, tcp, self.grasp_idx, X0, hidden, soft,
                                recapture=recapture)
            X2, m2 = again.X, again.matched
            bad2 = len(chain_reversals(X2, topo.chains, cos_max))
            abs2 = edge_rmse_mm(X2, edges, rest)
            if bad2 < best[2] and abs2 <= max(abs_best, slack):
                best, abs_best = (X2, m2, bad2, True), abs2
        return best

    def _held_tcps(self, tcp: np.ndarray | None, gripper_closed: np.ndarray | None) -> np.ndarray | None:
        """(H, 3) m: the TCPs of the grippers holding the object this frame (a cloth's held corners), or None
        without TCPs. The closed grippers' (gripper_closed (G,) bool); without gripper states (a recorded clip
        with arm poses only) those the track holds a keypoint at (its grasp indices): at initialisation every
        TCP near an end or a corner was taken as holding it, so the frames after it keep to the same grasp."""
        if tcp is None:
            return None
        tcp = np.asarray(tcp, np.float64).reshape(-1, 3)
        if gripper_closed is not None:
            return tcp[np.asarray(gripper_closed, bool)]
        if len(self.grasp_idx) != len(tcp):
            return None
        return tcp[self.grasp_idx >= 0]

    def _begin_step(
        self, cloud: np.ndarray, tcp: np.ndarray | None, gripper_closed: np.ndarray | None
    ) -> FrameResult | None:
        """What every per-frame update shares: no keypoints before initialisation, grasp indices follow the
        grippers, too small a cloud keeps the keypoints as a bad frame. None when the update is to run."""
        if self.topology is None or self.keypoints is None:
            empty = np.zeros((0, 3))
            return FrameResult(
                empty, empty, TrackStatus.UNINITIALISED, float("nan"), float("nan"), len(cloud), 0, 0, self.grasp_idx
            )
        p = self.params
        if tcp is not None and gripper_closed is not None:
            if len(self.grasp_idx) != len(tcp):
                self.grasp_idx = np.full(len(tcp), -1, np.int64)
            self.grasp_idx = update_grasp_indices(self.grasp_idx, self.keypoints, tcp, gripper_closed, p.grasp_gate_m)
        self.last_timings_ms = {}
        if len(cloud) < p.min_object_points:
            self._carry(tcp)
            return self._result(self.keypoints, cloud, 0, len(self.topology.anchor_idx), force_bad=True)
        return None

    def _hand_motion(self, tcp: np.ndarray | None) -> np.ndarray | None:
        """(N, 3) m: each keypoint's nearest gripper's motion from the last tracked frame's TCPs to tcp (G, 3) m
        (what a hand hides moves with it); None without TCPs in both frames, or when their count changed."""
        if tcp is None or self._tcp is None or not len(tcp) or self._tcp.shape != tcp.shape:
            return None
        assert self.keypoints is not None
        near = np.argmin(np.linalg.norm(self.keypoints[:, None, :] - self._tcp[None, :, :], axis=2), axis=1)
        return (tcp - self._tcp)[near]

    def _carry(self, tcp: np.ndarray | None) -> None:
        """Move the keypoints with the hands through a frame with too little cloud to track (the object behind an
        arm): each by its nearest gripper's motion since the last frame (TCPs tcp (G, 3) m), held ones to their
        TCPs, the others then relaxed to their rest lengths (``relax_hidden``). No velocity is kept: the next
        tracked frame starts from here."""
        assert self.topology is not None and self.keypoints is not None
        now = None if tcp is None else np.asarray(tcp, np.float64).reshape(-1, 3)
        move = self._hand_motion(now)
        if move is None or now is None:
            return
        X = self.keypoints + move
        held = (self.grasp_idx >= 0) & (self.grasp_idx < len(X))
        X[self.grasp_idx[held]] = now[: len(held)][held]
        movable = np.ones(len(X), bool)
        movable[self.grasp_idx[held]] = False
        if held.any():
            X = relax_hidden(X, self.topology.edges, self.topology.rest, movable, self.params.hidden_relax_sweeps,
                             self.params, self.topology.colours)
        self.keypoints, self._tcp, self._velocity = X, now, None

    def _reported(self, X: np.ndarray, cloud: np.ndarray | cKDTree, hidden: np.ndarray | None) -> np.ndarray:
        """The keypoints reported for a frame's solution X (N, 3) m: a 1D object's moved across the tube to the
        mean of their slice of the cloud (m; ``solver.tube_mean``, the ones in sight that are neither held nor a
        junction) and spaced along each chain as its rest lengths are (``tangle.respace_chains``, the held ones
        fixed); a cloth's are X, or, with an edge error above ``params.stretch_abs_mm``, X unstretched
        (``_unstretched``). hidden: (N,) bool or None."""
        if self.topology is not None and self.topology.kind == "2d":
            return self._unstretched(X, cloud, hidden)
        out = self._centred(X, cloud, hidden)
        return X if out is X else self._spaced(out)

    def _unstretched(self, X: np.ndarray, cloud: np.ndarray | cKDTree, hidden: np.ndarray | None) -> np.ndarray:
        """A cloth's keypoints X (N, 3) m with an edge error above ``params.stretch_abs_mm``: the edges longer
        than their rest lengths shortened (``solver.shorten_stretched``, the held keypoints fixed) and the
        keypoints in sight put back onto the plane of their nearest cloud points (``solver.onto_local_plane``);
        X itself when that does not lower the edge error, or below the threshold."""
        assert self.topology is not None
        p, topo = self.params, self.topology
        before = edge_rmse_mm(X, topo.edges, topo.rest)
        if p.stretch_sweeps <= 0 or before <= p.stretch_abs_mm:
            return X
        held = self._held(len(X))
        Y = shorten_stretched(X, topo.edges, topo.rest, ~held, p.stretch_sweeps)
        tree = cloud_tree(cloud)
        seen = ~held if hidden is None else ~held & ~np.asarray(hidden, bool)
        Y = onto_local_plane(Y, tree, seen)
        return Y if edge_rmse_mm(Y, topo.edges, topo.rest) < before else X

    def _spaced(self, X: np.ndarray) -> np.ndarray:
        """A 1D object's keypoints X (N, 3) m spaced along each chain as its rest lengths are, the held ones fixed
        (``tangle.respace_chains``, moves of at most ``params.respace_cap`` median rest lengths)."""
        assert self.topology is not None
        mr = float(np.median(self.topology.rest))
        return respace_chains(X[None], self.topology, self.params.respace_cap * mr, 0.0, fixed=self._held(len(X)))[0]

    def _held(self, n: int) -> np.ndarray:
        """(n,) bool: the keypoints a gripper holds."""
        held = np.zeros(n, bool)
        held[self.grasp_idx[(self.grasp_idx >= 0) & (self.grasp_idx < n)]] = True
        return held

    def _centred(self, X: np.ndarray, cloud: np.ndarray | cKDTree, hidden: np.ndarray | None) -> np.ndarray:
        """A 1D object's keypoints X (N, 3) m in sight, neither held nor a junction, moved across the tube to the
        mean of their slice of the cloud (m; ``solver.tube_mean``); X itself for a cloth or with the mean off."""
        assert self.topology is not None
        p = self.params
        topo = self.topology
        if topo.kind != "1d" or p.tube_mean_half <= 0 or not len(topo.rest):
            return X
        tree = cloud_tree(cloud)
        if tree.n < 3:
            return X
        seen = ~self._held(len(X)) & (np.bincount(topo.edges.ravel(), minlength=len(X)) <= 2)
        if hidden is not None:
            seen &= ~np.asarray(hidden, bool)
        mr = float(np.median(topo.rest))
        return tube_mean(X, chain_tangents(X, topo.chains), tree, p.tube_mean_half * mr, p.tube_mean_reach * mr, seen)

    def _reference(self, Y: np.ndarray) -> np.ndarray:
        """The reference lengths (E,) m of an initialisation's centred keypoints Y (N, 3) m (``_centred``): each
        chain's rest lengths scaled by its length through Y over their sum, so the reported chain, spaced as its
        rest lengths are, keeps them."""
        assert self.topology is not None
        topo = self.topology
        ref = np.array(topo.rest, np.float64)
        for ch, e in zip(topo.chains, chain_edges(topo), strict=True):
            if len(e):
                length = float(np.linalg.norm(np.diff(Y[np.asarray(ch, np.int64)], axis=0), axis=1).sum())
                ref[e] = topo.rest[e] * length / max(float(topo.rest[e].sum()), 1e-12)
        return ref

    def _result(
        self, X: np.ndarray, cloud: np.ndarray | cKDTree, matched: int, total: int, force_bad: bool = False,
        tangled: int = 0, repaired: bool = False, hidden: np.ndarray | None = None, out: np.ndarray | None = None,
    ) -> FrameResult:
        """Score a solution, update the state and the loss-of-track counter.

        A frame is bad without a cloud, when the keypoints jumped (solution discarded) or when Abs or
        CD exceed their thresholds (solution kept as the next warm start, flagged DEGRADED). A grid left
        tangled or a chain left folded (``tangled`` cells / keypoints) is kept as the warm start too and flagged
        DEGRADED, but does not count
        towards a loss: the next frame tries the repair again, in the track's own topology, which a
        re-initialisation would replace (new rest lengths, keypoints renumbered). The CD that judges the frame
        is over the keypoints neither hidden (hidden (N,) bool) nor held, which have no cloud of their own; the
        CD reported is the paper's, over all keypoints. out: the keypoints reported for X (``_reported``; default
        X), whose Abs and CD are the ones reported; X stays the next frame's warm start.
        """
        assert self.topology is not None
        p = self.params
        abs_mm = edge_rmse_mm(X, self.topology.edges, self.topology.rest)
        n_points = cloud.n if isinstance(cloud, cKDTree) else len(cloud)
        cd_mm = chamfer_mm(X, cloud) if n_points else float("inf")
        seen = np.ones(len(X), bool) if hidden is None else ~np.asarray(hidden, bool)
        seen[self.grasp_idx[(self.grasp_idx >= 0) & (self.grasp_idx < len(X))]] = False
        cd_seen = cd_mm if seen.all() or not seen.any() or not n_points else chamfer_mm(X[seen], cloud)
        jump = self.keypoints is not None and bool(np.median(np.linalg.norm(X - self.keypoints, axis=1)) > p.max_jump_m)
        jump &= not (repaired and self.topology.grid_shape is not None)  # a grid re-laid on purpose
        bad = force_bad or jump or abs_mm > 1e3 * p.max_edge_rmse_m or cd_seen > 1e3 * p.max_chamfer_m
        self._bad = self._bad + 1 if bad else 0
        if not (force_bad or jump):
            if self.keypoints is not None and self.keypoints is not X:
                self._velocity = X - self.keypoints
            self.keypoints = X
        if out is not None and out is not X:
            abs_mm = edge_rmse_mm(out, self.topology.edges, self.topology.reference_lengths)
            cd_mm = chamfer_mm(out, cloud) if n_points else float("inf")
        else:
            out = X
        if not bad and not tangled:
            self._history.append(out)
        smoothed = np.mean(np.stack(self._history), axis=0) if self._history else out
        status = TrackStatus.OK if not (bad or tangled) else TrackStatus.DEGRADED
        grasp = self.grasp_idx.copy()
        if self._bad >= p.lost_after_frames:
            status = TrackStatus.LOST
            self.reset()
        return FrameResult(out, smoothed, status, abs_mm, cd_mm, n_points, matched, total, grasp, tangled, repaired)
