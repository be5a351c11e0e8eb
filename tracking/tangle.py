"""A cloth grid's tangles: detection (cells folded over themselves) and repair (a grid re-lifted from the
frame's contour in the track's own correspondence).

A tracked grid tangles when the solver folds a cell over itself, a corner pulled across the opposite edge (a
bow-tie): plain in a picture, hidden in the mean edge error. A real cloth's 6x6 grid seldom has one (the
test bed's true surface sampled 6x6: in 4 of 180 frames of a crumpled cloth, none in four other clips; the
project's simulator: in 6 of 180 frames, as its fold closes). Two neighbouring cells facing apart are not a
tangle: those of a real fold face up to ~165 degrees apart.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from tracking.anchors import contour_3d, lift_grid
from tracking.init import Topology
from tracking.metrics import edge_lengths
from tracking.params import TrackingParams


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


__all__ = ["cell_corner_normals", "grid_symmetries", "relift_grid", "tangled_cells"]
