"""A cloth grid's tangles: detection (inverted cells, opposed neighbours) and repair (a grid re-lifted from the
frame's contour in the track's own correspondence).

A tracked grid tangles when the solver folds a cell over itself (a corner pulled across the opposite edge: a
bow-tie) or turns a cell face-down against its neighbour; both are plain in a picture and hidden in the mean
edge error. A real cloth's 6x6 grid, even twisted, folded or crumpled on the table, has neither: its cells are
small patches of a surface.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from tracking.anchors import contour_3d, lift_grid
from tracking.init import Topology
from tracking.params import TrackingParams

OPPOSED_COS = -0.5  # two neighbouring cells whose normals are more than 120 degrees apart are folded onto each other


def cell_corner_normals(X: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Unit normals (rows-1, cols-1, 4, 3) of each cell's four corner triangles; X (rows*cols, 3) m row-major.

    Corner k's triangle is the corner and its two neighbours in the cell, all taken the same way round, so a
    flat or gently curved cell has four nearly equal normals and a bow-tie has opposed ones."""
    G = X.reshape(rows, cols, 3)
    a, b, c, d = G[:-1, :-1], G[:-1, 1:], G[1:, :-1], G[1:, 1:]
    n = np.stack([np.cross(b - a, c - a), np.cross(d - b, a - b), np.cross(c - d, b - d), np.cross(a - c, d - c)], 2)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def tangled_cells(X: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Cells (rows-1, cols-1) bool that are tangled: a corner triangle facing against its cell's mean normal
    (the cell is folded over itself), or a neighbouring cell facing more than 120 degrees away (two cells
    folded onto each other along their shared edge). X: (rows*cols, 3) m."""
    u = cell_corner_normals(X, rows, cols)
    m = u.sum(axis=2)
    m /= np.maximum(np.linalg.norm(m, axis=-1, keepdims=True), 1e-12)
    bad = (np.einsum("ijkc,ijc->ijk", u, m) < 0).any(axis=2)
    down = np.einsum("ijc,ijc->ij", m[1:], m[:-1]) < OPPOSED_COS
    right = np.einsum("ijc,ijc->ij", m[:, 1:], m[:, :-1]) < OPPOSED_COS
    bad[1:] |= down
    bad[:-1] |= down
    bad[:, 1:] |= right
    bad[:, :-1] |= right
    return bad


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
    every keypoint's identity. None when the cloud has no usable contour."""
    assert topology.grid_shape is not None
    rows, cols = topology.grid_shape
    ct = contour_3d(cloud, K, T_world_cam, params, held)
    if ct is None:
        return None
    X0 = lift_grid(ct, cloud, rows, cols)
    costs = [float(np.linalg.norm(X0[p] - X_prev, axis=1).sum()) for p in grid_symmetries(rows, cols)]
    best = grid_symmetries(rows, cols)[int(np.argmin(costs))]
    X = X0[best]
    if held is not None and len(held):  # a held corner is at its gripper
        corners = np.array([0, cols - 1, (rows - 1) * cols, rows * cols - 1])
        hp = np.asarray(held, np.float64).reshape(-1, 3)
        C = np.linalg.norm(hp[:, None, :] - X[corners][None, :, :], axis=2)
        r, k = linear_sum_assignment(C)
        ok = C[r, k] <= params.grasp_gate_m
        X[corners[k[ok]]] = hp[r[ok]]
    return X


__all__ = ["cell_corner_normals", "grid_symmetries", "relift_grid", "tangled_cells"]
