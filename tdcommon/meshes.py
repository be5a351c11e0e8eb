"""Triangle meshes as plain arrays: boxes, tubes around polylines, sheets over grids, and their union.

A mesh is ``(vertices (V, 3) float64 m, triangles (F, 3) int32)``. The simulated station renders these,
the arm mask in tracking and the synthetic test scenes build them, and the Panda model places its links.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) float64 m, triangles (F, 3) int32

_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_BOX_TRIANGLES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
    dtype=np.int32,
)


def box_mesh(centre: Sequence[float], half: Sequence[float], yaw: float = 0.0) -> Mesh:
    """A box with half extents ``half`` (3,) m rotated by ``yaw`` (rad) about z, centred at ``centre`` (3,) m."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    v = (_BOX_CORNERS * np.asarray(half, dtype=np.float64)) @ R.T + np.asarray(centre, dtype=np.float64)
    return v, _BOX_TRIANGLES.copy()


def tube_mesh(points: np.ndarray, radius: float, sides: int = 10) -> Mesh:
    """A closed tube of ``radius`` m around the polyline ``points`` (n, 3) m, with end caps."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    t = np.gradient(points, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    ref = np.where(np.abs(t[:, 2:3]) > 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    a = np.cross(t, ref)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = np.cross(t, a)
    ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = radius * (np.cos(ang)[None, :, None] * a[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :])
    verts = (points[:, None, :] + ring).reshape(-1, 3)
    k, s = np.meshgrid(np.arange(n - 1), np.arange(sides), indexing="ij")
    v00, v01 = k * sides + s, k * sides + (s + 1) % sides
    v10, v11 = v00 + sides, v01 + sides
    side = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    c0, c1 = n * sides, n * sides + 1
    s1 = np.arange(sides)
    caps = np.concatenate(
        [
            np.stack([np.full(sides, c0), (s1 + 1) % sides, s1], -1),
            np.stack([np.full(sides, c1), (n - 1) * sides + s1, (n - 1) * sides + (s1 + 1) % sides], -1),
        ]
    )
    verts = np.concatenate([verts, points[[0, -1]]])
    return verts, np.concatenate([side, caps]).astype(np.int32)


def sheet_mesh(grid: np.ndarray, half_thickness: float = 0.0) -> Mesh:
    """A sheet over the mid-surface ``grid`` (rows, cols, 3) m: closed, 2 * ``half_thickness`` m thick, or the
    bare surface (two triangles a cell) when ``half_thickness`` is 0."""
    grid = np.asarray(grid, dtype=np.float64)
    rows, cols, _ = grid.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    face_top = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    if half_thickness == 0.0:
        return grid.reshape(-1, 3).copy(), face_top.astype(np.int32)
    du = np.gradient(grid, axis=1)
    dv = np.gradient(grid, axis=0)
    nrm = np.cross(du, dv)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-12)
    top = (grid + half_thickness * nrm).reshape(-1, 3)
    bottom = (grid - half_thickness * nrm).reshape(-1, 3)
    m = rows * cols
    face_bottom = face_top[:, ::-1] + m
    loop = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
    nxt = np.roll(loop, -1)
    rim = np.concatenate([np.stack([loop, nxt, nxt + m], -1), np.stack([loop, nxt + m, loop + m], -1)])
    return np.concatenate([top, bottom]), np.concatenate([face_top, face_bottom, rim]).astype(np.int32)


def merge_meshes(meshes: Sequence[Mesh]) -> Mesh:
    """One triangle soup from several meshes: vertices (V, 3) float64, triangles (F, 3) int32."""
    if not meshes:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    return (
        np.concatenate([np.asarray(v, dtype=np.float64) for v, _ in meshes]),
        np.concatenate([np.asarray(f, dtype=np.int32) + o for (_, f), o in zip(meshes, offsets, strict=True)]),
    )


def mesh_sources(meshes: Sequence[Mesh]) -> np.ndarray:
    """(F,) int32: for each triangle of ``merge_meshes(meshes)``, the index of the mesh it came from."""
    return np.concatenate([np.full(len(f), k, dtype=np.int32) for k, (_, f) in enumerate(meshes)] or
                          [np.zeros(0, np.int32)])


def closed_outward(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(F,) bool: the triangles on closed, consistently and outward oriented components of a mesh.

    vertices: (V, 3) m (coincident vertices are merged first: a triangle soup is fine);
    triangles: (F, 3). On such a (non self-intersecting) component a back face is always
    hidden behind a front face of the same component, so a renderer may skip it.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    _, key = np.unique(np.round(np.asarray(vertices, dtype=np.float64), 9), axis=0, return_inverse=True)
    f = key.reshape(-1)[np.asarray(triangles, dtype=np.int64)]
    n_v = int(key.max()) + 1 if len(key) else 0
    a, b = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)  # directed edges, three per triangle
    code, reverse = a * n_v + b, b * n_v + a
    order = np.sort(code)
    unique_edges = len(np.unique(code)) == len(code)
    pos = np.clip(np.searchsorted(order, reverse), 0, len(order) - 1)
    proper = (a != b).reshape(-1, 3).all(axis=1)  # no degenerate edge
    has_reverse = (order[pos] == reverse).reshape(-1, 3).all(axis=1) & proper
    graph = sp.csr_matrix((np.ones(len(a)), (a, b)), shape=(n_v, n_v))
    _, comp = connected_components(graph, directed=False)
    tri_comp = comp[f[:, 0]]
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    volume = np.bincount(tri_comp, np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)
    comp_ok = np.bincount(tri_comp, ~has_reverse) == 0
    return unique_edges & comp_ok[tri_comp] & (volume[tri_comp] > 0)


class OutwardCache:
    """``closed_outward`` of a mesh, computed once per triangle list: a rigidly moving mesh (an arm's links at
    any joints) keeps its vertex count, triangles and orientation. Call it with a mesh (vertices, triangles)."""

    def __init__(self) -> None:
        self._known: dict[tuple[int, int, int], np.ndarray] = {}

    def __call__(self, mesh: Mesh) -> np.ndarray:
        """(F,) bool: the triangles of ``mesh`` a renderer may skip when they face away from the camera."""
        v, f = mesh
        f = np.ascontiguousarray(f)
        key = (len(v), len(f), zlib.crc32(f.tobytes()))
        if key not in self._known:
            self._known[key] = closed_outward(v, f)
        return self._known[key]
