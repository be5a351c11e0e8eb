"""Image-space skeleton graph of a 1D object: skeletonise, MST, leaves, junctions, spur pruning, branches."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra, minimum_spanning_tree
from skimage.morphology import skeletonize

LEAF = 0
JUNCTION = 1

_OFFSETS = np.array([[0, 1], [1, -1], [1, 0], [1, 1]])


@dataclass(frozen=True)
class SkeletonGraph:
    """Tree of a skeleton in mask pixels.

    node_rc: (K, 2) float64 node pixel (row, col); node_kind: (K,) int64 LEAF / JUNCTION;
    branches: list of (node_a, node_b, pixels (M, 2) float64 ordered from a to b, ends included);
    component: (K,) int64 connected component of each node (0 = the largest).
    """

    node_rc: np.ndarray
    node_kind: np.ndarray
    branches: list[tuple[int, int, np.ndarray]]
    component: np.ndarray


def pixel_graph(skel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-neighbour graph of skeleton pixels (H, W) bool -> (rc (P, 2) int, edges (Q, 2) int, weights (Q,) px)."""
    rc = np.argwhere(skel)
    H, W = skel.shape
    index = np.full((H + 2, W + 2), -1, np.int64)
    index[rc[:, 0] + 1, rc[:, 1] + 1] = np.arange(len(rc))
    es, ws = [], []
    for dr, dc in _OFFSETS:
        nb = index[rc[:, 0] + 1 + dr, rc[:, 1] + 1 + dc]
        ok = nb >= 0
        es.append(np.stack([np.nonzero(ok)[0], nb[ok]], axis=1))
        ws.append(np.full(int(ok.sum()), np.hypot(dr, dc)))
    return rc, np.concatenate(es).astype(np.int64), np.concatenate(ws)


def spanning_forest(n: int, edges: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Minimum spanning forest (scipy) of an n-vertex graph -> its edges (Q', 2) int64."""
    if len(edges) == 0:
        return np.zeros((0, 2), np.int64)
    g = coo_matrix((weights, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    t = minimum_spanning_tree(g).tocoo()
    return np.stack([t.row, t.col], axis=1).astype(np.int64)


def _csr(n: int, edges: np.ndarray, weights: np.ndarray | None = None) -> coo_matrix:
    w = np.ones(len(edges)) if weights is None else weights
    return coo_matrix((w, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()


def _branches(
    rc: np.ndarray, alive: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """Decompose a forest (edges among alive pixels) into branches between non-degree-2 pixels.

    Returns degree (P,) and branches (a, b, pixel indices ordered a -> b, ends included).
    """
    n = len(rc)
    deg = np.bincount(edges.ravel(), minlength=n)
    node = alive & (deg != 2)
    inner = alive & (deg == 2)
    both_inner = inner[edges[:, 0]] & inner[edges[:, 1]]
    _, lab = connected_components(_csr(n, edges[both_inner]), directed=False)
    # distance from one root per component orders the pixels along every branch
    _, comp = connected_components(_csr(n, edges), directed=False)
    first = np.full(comp.max() + 1, -1)
    cand = np.nonzero(node)[0]
    first[comp[cand[::-1]]] = cand[::-1]
    roots = first[first >= 0]
    lengths = np.hypot(*(rc[edges[:, 0]] - rc[edges[:, 1]]).T)
    dist = dijkstra(_csr(n, edges, lengths), directed=False, indices=roots, min_only=True)
    out: list[tuple[int, int, np.ndarray]] = []
    nn = node[edges[:, 0]] & node[edges[:, 1]]
    for a, b in edges[nn]:
        a, b = (a, b) if dist[a] <= dist[b] else (b, a)
        out.append((int(a), int(b), np.array([a, b])))
    mixed = node[edges[:, 0]] != node[edges[:, 1]]
    me = edges[mixed]
    nd = np.where(node[me[:, 0]], me[:, 0], me[:, 1])
    it = np.where(node[me[:, 0]], me[:, 1], me[:, 0])
    inner_idx = np.nonzero(inner)[0]
    order = inner_idx[np.lexsort((dist[inner_idx], lab[inner_idx]))]
    labs = lab[order]
    starts = np.searchsorted(labs, np.unique(labs))
    ends = np.append(starts[1:], len(order)) if len(starts) else starts  # no inner pixel: no such branch
    for s, e in zip(starts, ends, strict=True):
        pix = order[s:e]
        ends_nodes = nd[lab[it] == lab[pix[0]]]
        if len(ends_nodes) < 2:
            continue
        a, b = ends_nodes[np.argsort(dist[ends_nodes])][[0, -1]]
        out.append((int(a), int(b), np.concatenate([[a], pix, [b]])))
    return deg, out


def _path_length(rc: np.ndarray, pix: np.ndarray) -> float:
    p = rc[pix].astype(np.float64)
    return float(np.hypot(*np.diff(p, axis=0).T).sum())


def skeleton_graph(mask: np.ndarray, spur_px: float, merge_px: float, min_component_px: float) -> SkeletonGraph:
    """Skeleton tree of a binary mask (H, W) bool.

    Skeletonise, minimum spanning forest over 8-neighbour pixels, drop components shorter than
    ``min_component_px``, prune leaf branches shorter than ``spur_px`` (repeatedly), merge junctions
    joined by a branch shorter than ``merge_px``.
    """
    skel = skeletonize(mask)
    rc, edges, w = pixel_graph(skel)
    n = len(rc)
    empty = SkeletonGraph(np.zeros((0, 2)), np.zeros(0, np.int64), [], np.zeros(0, np.int64))
    if n < 2:
        return empty
    edges = spanning_forest(n, edges, w)
    ncomp, comp = connected_components(_csr(n, edges), directed=False)
    sizes = np.bincount(comp, minlength=ncomp)
    alive = sizes[comp] >= max(2, min_component_px)
    edges = edges[alive[edges[:, 0]] & alive[edges[:, 1]]]
    for _ in range(6):
        deg, br = _branches(rc, alive, edges)
        drop = np.zeros(n, bool)
        for a, b, pix in br:
            leaf_a, leaf_b = deg[a] == 1, deg[b] == 1
            if leaf_a != leaf_b and _path_length(rc, pix) < spur_px:
                drop[pix[1:-1]] = True
                drop[a if leaf_a else b] = True
        if not drop.any():
            break
        alive &= ~drop
        edges = edges[alive[edges[:, 0]] & alive[edges[:, 1]]]
    else:  # pruned six times: the branches of what is left (after a break they are those of the last pass)
        deg, br = _branches(rc, alive, edges)
    node_pix = np.nonzero(alive & (deg != 2) & (deg > 0))[0]
    if len(node_pix) == 0:
        return empty
    # merge junctions joined by short branches
    pos = {int(p): k for k, p in enumerate(node_pix)}
    short = [(pos[a], pos[b]) for a, b, pix in br if deg[a] >= 3 and deg[b] >= 3 and _path_length(rc, pix) < merge_px]
    K0 = len(node_pix)
    se = np.array(short, np.int64).reshape(-1, 2)
    _, group = connected_components(_csr(K0, se), directed=False)
    G = group.max() + 1
    cnt = np.bincount(group, minlength=G)
    mean_rc = np.stack([np.bincount(group, rc[node_pix, i], minlength=G) for i in range(2)], 1) / cnt[:, None]
    dev = np.linalg.norm(rc[node_pix] - mean_rc[group], axis=1)
    rep = np.full(G, -1)
    order = np.lexsort((dev, group))
    rep[group[order[::-1]]] = node_pix[order[::-1]]
    kind = np.where(deg[rep] >= 3, JUNCTION, LEAF).astype(np.int64)
    branches: list[tuple[int, int, np.ndarray]] = []
    for a, b, pix in br:
        ga, gb = group[pos[a]], group[pos[b]]
        if ga == gb:
            continue
        p = rc[pix].astype(np.float64)
        p[0], p[-1] = rc[rep[ga]], rc[rep[gb]]
        branches.append((int(ga), int(gb), p))
    _, comp = connected_components(_csr(n, edges), directed=False)
    csize = np.bincount(comp[rep], minlength=comp.max() + 1)
    rank = np.argsort(-csize, kind="stable")
    relabel = np.empty_like(rank)
    relabel[rank] = np.arange(len(rank))
    return SkeletonGraph(rc[rep].astype(np.float64), kind, branches, relabel[comp[rep]])
